//! Acting's sparse products ([`Layer::infer`] at batch 1) against the reference convolution and
//! the layers' own dense forward pass, on inputs with exact zeros, in f32 (the AVX-512 kernels
//! where the CPU has them) and f64 (the portable loops).

mod common;

use common::{assert_close, rng, set_params, uniform};
use invaders::dqn::article_qnet;
use invaders::layers::init::VarianceScaling;
use invaders::layers::{Conv2d, Dense, Layer};
use invaders::tensor::{
    conv2d_reference, pad_input, Background, Border, ConvGeom, Float, Nonzeros, Padding, Tensor,
};
use proptest::prelude::*;
use rand::Rng;

/// Uniform values in [-1, 1) of which about `zeros` (a fraction) are exact zeros, some `-0.0`.
fn sparse<T: Float>(shape: &[usize], zeros: f64, r: &mut impl Rng) -> Tensor<T> {
    let mut t = uniform::<T>(shape, r);
    for v in t.data_mut() {
        if r.random_bool(zeros) {
            *v = if r.random_bool(0.5) {
                T::zero()
            } else {
                -T::zero()
            };
        }
    }
    t
}

/// Like a game frame: each pixel is the background `β` (a random colour, the first pixel's)
/// with probability `share`; otherwise it differs in every channel or, half the time, in one
/// (stacked frames often differ in one).
fn frame<T: Float>(shape: &[usize], share: f64, r: &mut impl Rng) -> Tensor<T> {
    let c = *shape.last().unwrap();
    let mut t = uniform::<T>(shape, r);
    let beta = t.data()[..c].to_vec();
    for px in t.data_mut().chunks_exact_mut(c) {
        if r.random_bool(share) {
            px.copy_from_slice(&beta);
        } else if r.random_bool(0.5) {
            let keep = px[r.random_range(0..c)];
            px.copy_from_slice(&beta);
            px[r.random_range(0..c)] = keep;
        }
    }
    t
}

/// A `k × k` convolution of stride `s`, SAME or VALID. SAME takes any size, kernels larger than
/// the input included; VALID gets the input grown to fit the kernel.
fn square_geom(
    k: usize,
    s: usize,
    h: usize,
    w: usize,
    cin: usize,
    cout: usize,
    same: bool,
) -> ConvGeom {
    let (pad, h, w) = if same {
        (Padding::Same, h, w)
    } else {
        (Padding::Valid, h.max(k), w.max(k))
    };
    ConvGeom::new(h, w, cin, cout, k, k, (s, s), pad).unwrap()
}

/// A convolution with sparse inference: `infer` at batch 1 gives the reference convolution's
/// output (ReLU, border) whether the input is sparse enough for the sparse product (up to a
/// fifth nonzero) or not, after a larger batch left values where the border now is. With
/// `background`, the input is a [`frame`] (`zeros` its background share) and the layer acts
/// by [`Conv2d::with_background_inference`] (up to an eighth of the pixels differing).
#[allow(clippy::too_many_arguments)]
fn conv_case<T: Float>(
    k: usize,
    s: usize,
    h: usize,
    w: usize,
    cin: usize,
    cout: usize,
    same: bool,
    relu: bool,
    border: usize,
    n: usize,
    zeros: f64,
    background: bool,
    seed: u64,
    tol: f64,
) -> Result<(), TestCaseError> {
    let g = square_geom(k, s, h, w, cin, cout, same);
    let (h, w) = (g.h, g.w);
    let b = Border {
        top: border,
        bottom: 1,
        left: border,
        right: 0,
    };
    let mut layer = Conv2d::<T>::new("c", g)
        .with_border(b)
        .with_sparse_inference(true)
        .with_background_inference(background);
    if relu {
        layer = layer.with_relu();
    }
    let mut r = rng(seed);
    let (wt, bt) = (
        uniform::<T>(&[k, k, cin, cout], &mut r),
        uniform::<T>(&[cout], &mut r),
    );
    set_params(&mut layer, &[&wt, &bt]);
    layer.forward(&uniform::<T>(&[n + 1, h, w, cin], &mut r));
    let x = if background {
        frame::<T>(&[n, h, w, cin], zeros, &mut r)
    } else {
        sparse::<T>(&[n, h, w, cin], zeros, &mut r)
    };
    // The same image inside its SAME padding, as a replay batch is laid out: read in place.
    let mut xpad = Vec::new();
    pad_input(&g, n, x.data(), &mut xpad);
    let (hp, wp) = g.padded();
    let xpad = Tensor::from_vec(&[n, hp, wp, cin], xpad);
    let mut z = vec![T::zero(); n * g.oh * g.ow * cout];
    conv2d_reference(&g, n, x.data(), wt.data(), bt.data(), &mut z);
    let (hb, wb) = b.around(g.oh, g.ow);
    let mut at = Vec::new();
    b.interior_offsets(n, g.oh, g.ow, cout, &mut at);
    let mut y = vec![T::zero(); n * hb * wb * cout];
    for (zrow, &o) in z.chunks_exact(cout).zip(&at) {
        for (yv, &zv) in y[o..o + cout].iter_mut().zip(zrow) {
            *yv = if relu { zv.max(T::zero()) } else { zv };
        }
    }
    layer.infer(&x);
    prop_assert_eq!(layer.output().shape(), &[n, hb, wb, cout][..]);
    assert_close("infer", layer.output().data(), &y, tol)?;
    if !g.reads_input_directly() {
        layer.infer(&xpad);
        assert_close("infer, padded input", layer.output().data(), &y, tol)?;
    }
    layer.forward(&x);
    assert_close("forward", layer.output().data(), &y, tol)
}

/// A dense layer with sparse inference: `infer` at batch 1 gives `b + x·W`.
fn dense_case<T: Float>(
    n_in: usize,
    n_out: usize,
    n: usize,
    zeros: f64,
    seed: u64,
    tol: f64,
) -> Result<(), TestCaseError> {
    let mut layer = Dense::<T>::new("d", n_in, n_out).with_sparse_inference(true);
    let mut r = rng(seed);
    let (wt, bt) = (
        uniform::<T>(&[n_in, n_out], &mut r),
        uniform::<T>(&[n_out], &mut r),
    );
    set_params(&mut layer, &[&wt, &bt]);
    layer.forward(&uniform::<T>(&[n + 2, n_in], &mut r));
    let x = sparse::<T>(&[n, n_in], zeros, &mut r);
    let mut y = Vec::new();
    for sample in x.data().chunks_exact(n_in) {
        let mut row = bt.data().to_vec();
        for (i, &v) in sample.iter().enumerate() {
            for (j, yv) in row.iter_mut().enumerate() {
                *yv += v * wt.data()[i * n_out + j];
            }
        }
        y.extend(row);
    }
    layer.infer(&x);
    prop_assert_eq!(layer.output().shape(), &[n, n_out][..]);
    assert_close("infer", layer.output().data(), &y, tol)
}

proptest! {
    #![proptest_config(ProptestConfig { cases: common::cases(64), ..ProptestConfig::default() })]

    #[test]
    fn nonzeros_lists_each_pixels_nonzero_channels(
        pixels in 1usize..6, c in prop_oneof![1usize..40, Just(16), Just(32), Just(64)],
        zeros in 0.0f64..1.0, seed in any::<u64>(),
    ) {
        let mut r = rng(seed);
        let mut x = sparse::<f32>(&[pixels, c], zeros, &mut r);
        if c > 2 {
            x.data_mut()[2] = f32::NAN; // not a zero: kept
        }
        let mut nz = Nonzeros::default();
        // Twice: the second call reuses the buffers of the first.
        nz.collect(sparse::<f32>(&[pixels + 1, c], 0.5, &mut r).data(), c);
        nz.collect(x.data(), c);
        let mut total = 0;
        for (p, px) in x.data().chunks_exact(c).enumerate() {
            let (index, value) = nz.pixel(p);
            let want: Vec<(u32, f32)> = px
                .iter()
                .enumerate()
                .filter(|(_, v)| **v != 0.0)
                .map(|(i, &v)| (i as u32, v))
                .collect();
            let got: Vec<(u32, f32)> = index.iter().copied().zip(value.iter().copied()).collect();
            prop_assert_eq!(got.len(), want.len());
            for ((gi, gv), (wi, wv)) in got.iter().zip(&want) {
                prop_assert_eq!(gi, wi);
                prop_assert!(gv.to_bits() == wv.to_bits(), "pixel {} channel {}", p, gi);
            }
            total += want.len();
        }
        prop_assert_eq!(nz.len(), total);
    }

    #[test]
    fn conv2d_sparse_inference_matches_reference(
        k in 1usize..=4, s in 1usize..=3, h in 3usize..12, w in 3usize..12,
        cin in prop_oneof![1usize..20, Just(16), Just(32)],
        cout in prop_oneof![1usize..20, Just(16), Just(64), Just(144)],
        same in any::<bool>(), relu in any::<bool>(), border in 0usize..3, n in 1usize..4,
        zeros in prop_oneof![Just(1.0), Just(0.95), Just(0.9), Just(0.8), Just(0.3)],
        seed in any::<u64>(),
    ) {
        conv_case::<f32>(k, s, h, w, cin, cout, same, relu, border, n, zeros, false, seed, 1e-5)?;
        conv_case::<f64>(k, s, h, w, cin, cout, same, relu, border, n, zeros, false, seed, 1e-12)?;
    }

    #[test]
    fn background_split_matches_reference(
        k in 1usize..=8, s in 1usize..=4, h in 1usize..24, w in 1usize..24,
        cin in prop_oneof![1usize..6, Just(4), Just(16), Just(20), Just(33)],
        cout in prop_oneof![1usize..20, Just(16), Just(32), Just(64), Just(144)],
        same in any::<bool>(), share in prop_oneof![Just(1.0), Just(0.9), Just(0.5), Just(0.0)],
        seed in any::<u64>(),
    ) {
        background_case::<f32>(k, s, h, w, cin, cout, same, share, seed, 1e-5)?;
        background_case::<f64>(k, s, h, w, cin, cout, same, share, seed, 1e-12)?;
    }

    #[test]
    fn conv2d_background_inference_matches_reference(
        k in 1usize..=8, s in 1usize..=4, h in 3usize..24, w in 3usize..24,
        cin in prop_oneof![1usize..6, Just(4), Just(16), Just(20), Just(33)],
        cout in prop_oneof![1usize..20, Just(16), Just(32), Just(64), Just(144)],
        same in any::<bool>(), relu in any::<bool>(), border in 0usize..3, n in 1usize..3,
        share in prop_oneof![Just(1.0), Just(0.95), Just(0.9), Just(0.5)],
        seed in any::<u64>(),
    ) {
        conv_case::<f32>(k, s, h, w, cin, cout, same, relu, border, n, share, true, seed, 1e-5)?;
        conv_case::<f64>(k, s, h, w, cin, cout, same, relu, border, n, share, true, seed, 1e-12)?;
    }

    #[test]
    fn dense_sparse_inference_matches_reference(
        n_in in prop_oneof![1usize..100, Just(7040)],
        n_out in prop_oneof![1usize..40, Just(16), Just(128), Just(144)], n in 1usize..4,
        zeros in prop_oneof![Just(1.0), Just(0.95), Just(0.5), Just(0.0)], seed in any::<u64>(),
    ) {
        dense_case::<f32>(n_in, n_out, n, zeros, seed, 1e-5)?;
        dense_case::<f64>(n_in, n_out, n, zeros, seed, 1e-12)?;
    }
}

/// [`Background`] on its own: the split lists every differing pixel (it must not give up, so the
/// sum below runs on the split path) and `b + conv(B) + conv(x − B)` is the reference
/// convolution, for either input layout; a limit under the count gives up.
#[allow(clippy::too_many_arguments)]
fn background_case<T: Float>(
    k: usize,
    s: usize,
    h: usize,
    w: usize,
    cin: usize,
    cout: usize,
    same: bool,
    share: f64,
    seed: u64,
    tol: f64,
) -> Result<(), TestCaseError> {
    let g = square_geom(k, s, h, w, cin, cout, same);
    let (h, w) = (g.h, g.w);
    let mut r = rng(seed);
    let (wt, bt) = (
        uniform::<T>(&[k, k, cin, cout], &mut r),
        uniform::<T>(&[cout], &mut r),
    );
    let x = frame::<T>(&[1, h, w, cin], share, &mut r);
    let mut want = vec![T::zero(); g.oh * g.ow * cout];
    conv2d_reference(&g, 1, x.data(), wt.data(), bt.data(), &mut want);
    let mut xpad = Vec::new();
    pad_input(&g, 1, x.data(), &mut xpad);
    let differing = x
        .data()
        .chunks_exact(cin)
        .filter(|px| px != &&x.data()[..cin])
        .count();
    let rows: Vec<usize> = (0..g.oh * g.ow).map(|r| r * cout).collect();
    let mut bg = Background::default();
    for (input, padded) in [(x.data(), false), (&xpad[..], true)] {
        if differing > 0 {
            prop_assert!(!bg.split(&g, input, padded, differing - 1));
        }
        prop_assert!(bg.split(&g, input, padded, differing));
        let mut got = vec![T::zero(); g.oh * g.ow * cout];
        bg.conv(&g, wt.data(), bt.data(), false, &mut got, &rows);
        assert_close("Background::conv", &got, &want, tol)?;
    }
    Ok(())
}

/// An infinite background is not split: `conv(B) + conv(x − B)` would be `∞ − ∞`.
#[test]
fn background_with_an_infinite_colour_is_not_split() {
    let g = ConvGeom::new(4, 4, 2, 16, 3, 3, (1, 1), Padding::Same).unwrap();
    let mut x = vec![0.5f32; 4 * 4 * 2];
    x[0] = f32::NEG_INFINITY;
    assert!(!Background::default().split(&g, &x, false, usize::MAX));
}

/// The article's network acts (`infer`, sparse products where the activations allow) as its
/// forward pass computes: with the convolutions' biases lowered so that conv2 and conv3 see
/// mostly zeros and take the sparse product, and as initialised, where they do not. On uniform
/// inputs conv1 takes the dense product and acting gives the forward pass's bits; on frames
/// (90% background) it splits off the background and agrees up to rounding.
#[test]
fn article_network_infers_as_it_forwards() {
    let mut r = rng(7);
    for shift in [0.0f32, -1.0] {
        let mut net = article_qnet::<f32>([88, 80, 4], 6, &VarianceScaling::HE, &mut r);
        for p in net.params_mut() {
            // conv1 needs the larger shift: its input (the frame) has no zeros.
            match p.name.as_str() {
                "conv1.bias" => p.value.data_mut().fill(shift),
                "conv2.bias" | "conv3.bias" => p.value.data_mut().fill(shift / 6.0),
                _ => {}
            }
        }
        for i in 0..4 {
            let frames = i >= 2;
            let x = if frames {
                frame::<f32>(&[1, 88, 80, 4], 0.9, &mut r)
            } else {
                uniform::<f32>(&[1, 88, 80, 4], &mut r)
            };
            let want = net.forward(&x).data().to_vec();
            let zeros: Vec<f64> = net.layers()[..3]
                .iter()
                .map(|l| {
                    let y = l.output().data();
                    y.iter().filter(|v| **v == 0.0).count() as f64 / y.len() as f64
                })
                .collect();
            if shift < 0.0 && !frames {
                // conv2 and conv3 read conv1's and conv2's outputs: under a fifth nonzero (and
                // something reaches dense1).
                assert!(
                    zeros[0] > 0.8 && zeros[1] > 0.8 && zeros[2] < 0.99,
                    "zeros {zeros:?}"
                );
            }
            let got = net.infer(&x).data().to_vec();
            if f32::simd() && !frames {
                // The same fused multiply-adds in the same order, the zero terms left out.
                assert_eq!(got, want);
            }
            let scale = 1.0 + want.iter().fold(0.0f32, |m, v| m.max(v.abs()));
            for (a, b) in got.iter().zip(&want) {
                assert!((a - b).abs() <= 1e-5 * scale, "{got:?} vs {want:?}");
            }
        }
    }
}

/// `infer` discards what a forward pass kept for backward: a backward pass after it is refused,
/// not computed from a mix of the two. `layer` (with a ReLU) runs forward on two images, then
/// `infer` on an image of zeros: all zeros for the sparse product, all background for the split.
fn backward_after_infer(layer: Conv2d<f32>) {
    let mut layer = layer.with_relu();
    let g = layer.geom;
    let mut r = rng(1);
    let (wt, bt) = (
        uniform::<f32>(&[g.kh, g.kw, g.cin, g.cout], &mut r),
        uniform::<f32>(&[g.cout], &mut r),
    );
    set_params(&mut layer, &[&wt, &bt]);
    let x = uniform::<f32>(&[2, g.h, g.w, g.cin], &mut r);
    layer.forward(&x);
    layer.infer(&Tensor::from_vec(
        &[1, g.h, g.w, g.cin],
        vec![0.0; g.h * g.w * g.cin],
    ));
    let dy = uniform::<f32>(&[2, g.oh, g.ow, g.cout], &mut r);
    layer.backward(&x, &dy, true);
}

/// After the sparse product.
#[test]
#[should_panic(expected = "backward without forward")]
fn backward_after_infer_is_refused() {
    let g = ConvGeom::new(6, 6, 16, 16, 3, 3, (1, 1), Padding::Same).unwrap();
    backward_after_infer(Conv2d::new("c", g).with_sparse_inference(true));
}

/// After conv1's background split.
#[test]
#[should_panic(expected = "backward without forward")]
fn backward_after_background_infer_is_refused() {
    let g = ConvGeom::new(8, 8, 4, 16, 4, 4, (2, 2), Padding::Same).unwrap();
    backward_after_infer(Conv2d::new("c", g).with_background_inference(true));
}
