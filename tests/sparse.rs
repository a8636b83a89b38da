//! Acting's sparse products ([`Layer::infer`] at batch 1) against the reference convolution and
//! the layers' own dense forward pass, on inputs with exact zeros, in f32 (the AVX-512 kernels
//! where the CPU has them) and f64 (the portable loops).

mod common;

use common::{
    abs64, assert_close, avx2_expected, avx512_expected, f64s, gamma, on_exactly, on_path,
    padded_input, random_params, reference_forward, reference_output, rng, set_params, uniform,
    Square,
};
use invaders::dqn::{qnet, Head};
use invaders::layers::init::VarianceScaling;
use invaders::layers::{Conv2d, Dense, Layer};
use invaders::ops::plan::{self, Kernel, Product};
use invaders::tensor::cpu::{self, Family};
use invaders::tensor::{pad_input, Background, Border, ConvGeom, Float, Nonzeros, Padding, Tensor};
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

/// A convolution with sparse inference: `infer` at batch 1 gives the reference convolution's
/// output (ReLU, border) whether the input is sparse enough for the sparse product (up to a
/// fifth nonzero) or not, after a larger batch left values where the border now is. With
/// `background`, the input is a [`frame`] (`zeros` its background share) and the layer acts
/// by [`Conv2d::with_background_inference`] (up to an eighth of the pixels differing).
#[allow(clippy::too_many_arguments)]
fn conv_case<T: Float>(
    c: Square, same: bool, relu: bool, border: usize, n: usize, zeros: f64, background: bool,
    seed: u64, tol: f64,
) -> Result<(), TestCaseError> {
    let g = c.geom(same);
    let Square { k, cin, cout, .. } = c;
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
    let xpad = padded_input(&g, n, &x);
    let (y, _) = reference_output(&g, n, x.data(), wt.data(), bt.data(), b, relu);
    let (hb, wb) = b.around(g.oh, g.ow);
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
    n_in: usize, n_out: usize, n: usize, zeros: f64, seed: u64, tol: f64,
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
        // Twice: the second call reuses the buffers of the first. AVX-512 (a compress per 16
        // channels) where the host has it and the pixels are whole vectors.
        nz.collect(sparse::<f32>(&[pixels + 1, c], 0.5, &mut r).data(), c);
        let avx = avx512_expected() && c % 16 == 0;
        on_path(Family::Nonzeros, avx, "Nonzeros::collect", || nz.collect(x.data(), c));
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
        conv_case::<f32>(Square { k, s, h, w, cin, cout }, same, relu, border, n, zeros, false, seed, 1e-5)?;
        conv_case::<f64>(Square { k, s, h, w, cin, cout }, same, relu, border, n, zeros, false, seed, 1e-12)?;
    }

    #[test]
    fn background_split_matches_reference(
        k in 1usize..=8, s in 1usize..=4, h in 1usize..24, w in 1usize..24,
        cin in prop_oneof![1usize..6, Just(4), Just(16), Just(20), Just(33)],
        cout in prop_oneof![1usize..20, Just(16), Just(32), Just(64), Just(144)],
        same in any::<bool>(), share in prop_oneof![Just(1.0), Just(0.9), Just(0.5), Just(0.0)],
        seed in any::<u64>(),
    ) {
        background_case::<f32>(Square { k, s, h, w, cin, cout }, same, share, seed, 1e-5)?;
        background_case::<f64>(Square { k, s, h, w, cin, cout }, same, share, seed, 1e-12)?;
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
        conv_case::<f32>(Square { k, s, h, w, cin, cout }, same, relu, border, n, share, true, seed, 1e-5)?;
        conv_case::<f64>(Square { k, s, h, w, cin, cout }, same, relu, border, n, share, true, seed, 1e-12)?;
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
    c: Square, same: bool, share: f64, seed: u64, tol: f64,
) -> Result<(), TestCaseError> {
    let g = c.geom(same);
    let Square { k, cin, cout, .. } = c;
    let (h, w) = (g.h, g.w);
    let mut r = rng(seed);
    let (wt, bt) = (
        uniform::<T>(&[k, k, cin, cout], &mut r),
        uniform::<T>(&[cout], &mut r),
    );
    let x = frame::<T>(&[1, h, w, cin], share, &mut r);
    let want = reference_forward(&g, 1, x.data(), wt.data(), bt.data(), false);
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
/// (90% background) it splits off the background and agrees up to rounding. The same with VALID
/// convolutions (`padding = "valid"`).
#[test]
fn article_network_infers_as_it_forwards() {
    let mut r = rng(7);
    let valid = Head {
        padding: Padding::Valid,
        ..Head::ARTICLE
    };
    for (head, shift) in [
        (Head::ARTICLE, 0.0f32),
        (Head::ARTICLE, -1.0),
        (valid, 0.0),
        (valid, -1.085),
    ] {
        let mut net = qnet::<f32>([88, 80, 4], 6, head, &VarianceScaling::HE, &mut r);
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
    random_params(&mut layer, &mut r);
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

/// The output channel counts the sparse and background products' AVX-512 kernels take (a
/// multiple of 16 up to 128, one register per 16: every arm of their dispatch), and two they
/// leave to the portable loops (the AVX2 kernels take both, in columns of 64, 40 and 16
/// channels); 20, which every host leaves to the portable loop.
const COUTS: [usize; 11] = [16, 32, 48, 64, 80, 96, 112, 128, 40, 144, 20];

/// The loop a sparse or background product of `cout` channels must run here: AVX-512 for a
/// multiple of 16 up to 128, AVX2 for a multiple of 8, else the portable one.
fn acting_path(cout: usize) -> cpu::Path {
    if avx512_expected() {
        if cout.is_multiple_of(16) && cout <= 128 {
            cpu::Path::Avx512
        } else {
            cpu::Path::Portable
        }
    } else if avx2_expected() && cout.is_multiple_of(8) {
        cpu::Path::Avx2
    } else {
        cpu::Path::Portable
    }
}

/// Asserts `|got − want| ≤ γ_n·bound` value by value.
fn within(what: &str, got: &[f32], want: &[f64], bound: &[f64], n: usize) {
    assert_eq!(got.len(), want.len(), "{what}: lengths");
    for (i, ((&g, &w), &b)) in got.iter().zip(want).zip(bound).enumerate() {
        assert!(
            (g as f64 - w).abs() <= gamma(n) * b,
            "{what}[{i}]: {g} vs {w} (bound {b})"
        );
    }
}

/// The f64 reference convolution `conv(x, W) + b` of one f32 image.
fn reference64(g: &ConvGeom, x: &Tensor<f32>, w: &Tensor<f32>, b: &Tensor<f32>) -> Vec<f64> {
    reference_forward(
        g,
        1,
        &f64s(x.data()),
        &f64s(w.data()),
        &f64s(b.data()),
        false,
    )
}

/// `layer.infer(x)`, asserting that it ran the sparse kernels' `path` loop and that the plan
/// recorded the sparse kernel for `product`; if `same_bits`, also that the forward pass gives
/// the same bits. Returns the inferred output.
fn sparse_infer(
    layer: &mut dyn Layer<f32>, x: &Tensor<f32>, path: cpu::Path, product: Product, what: &str,
    same_bits: bool,
) -> Vec<f32> {
    let got = on_exactly(Family::Sparse, path, what, || {
        layer.infer(x);
        layer.output().data().to_vec()
    });
    assert_eq!(plan::last(product), Some(Kernel::Sparse), "{what}");
    if same_bits {
        layer.forward(x);
        assert_eq!(
            got,
            layer.output().data(),
            "{what}: the forward pass's bits"
        );
    }
    got
}

/// The sparse product at every output channel count its dispatch knows (16 to 128 by 16: the
/// AVX-512 kernels of 3, 5, 6 and 7 registers included, which the network never reaches) and
/// at three it leaves to the portable loop (40, 144 and 20; AVX2 takes the first two), for a
/// convolution and a dense layer acting on one image: `infer` takes the sparse product (the
/// plan's record), by the host's SIMD kernel where it has one (the kernel's record), and gives
/// the forward pass's bits there (the same fused multiply-adds in the same order, zero terms
/// left out; a dense layer's forward pass on AVX2 is faer's GEMM, so there only the
/// convolution's). On every path it is
/// within the rounding bound of the f64 reference, `γ_{K+1}·(|b| + Σ|x||w|)` over its `K`
/// terms: the portable loop rounds each product, so it matches no other kernel's bits.
#[test]
fn sparse_products_at_every_channel_count() {
    let mut r = rng(21);
    for cout in COUTS {
        let path = acting_path(cout);
        // A 3×3 SAME convolution of 16 channels: 1024 padded values, about 58 nonzero.
        let g = ConvGeom::new(6, 6, 16, cout, 3, 3, (1, 1), Padding::Same).unwrap();
        let mut conv = Conv2d::<f32>::new("c", g).with_sparse_inference(true);
        let (w, b) = random_params(&mut conv, &mut r);
        let x = sparse::<f32>(&[1, 6, 6, 16], 0.9, &mut r);
        let what = format!("conv, {cout} channels");
        let same_bits = path != cpu::Path::Portable;
        let got = sparse_infer(&mut conv, &x, path, Product::ConvInfer, &what, same_bits);
        let want = reference64(&g, &x, &w, &b);
        let (xa, wa, ba) = (abs64(x.data()), abs64(w.data()), abs64(b.data()));
        let bound = reference_forward(&g, 1, &xa, &wa, &ba, false);
        within(&what, &got, &want, &bound, g.patch_len() + 1);

        // dense1's shape, small: 200 inputs, half of them zero.
        let mut dense = Dense::<f32>::new("d", 200, cout).with_sparse_inference(true);
        let (w, b) = random_params(&mut dense, &mut r);
        let x = sparse::<f32>(&[1, 200], 0.5, &mut r);
        let what = format!("dense, {cout} outputs");
        let same_bits = path == cpu::Path::Avx512;
        let got = sparse_infer(&mut dense, &x, path, Product::DenseInfer, &what, same_bits);
        let (want, bound): (Vec<f64>, Vec<f64>) = (0..cout)
            .map(|j| {
                (0..200).fold(
                    (b.data()[j] as f64, b.data()[j].abs() as f64),
                    |(s, a), i| {
                        let t = x.data()[i] as f64 * w.data()[i * cout + j] as f64;
                        (s + t, a + t.abs())
                    },
                )
            })
            .unzip();
        within(&what, &got, &want, &bound, 201);
    }
}

/// conv1's background split at every output channel count of [`COUTS`], on a frame with a
/// few differing pixels: `infer` takes the split (the plan's record), scans by the host's SIMD
/// loop where it has one and sums by its SIMD kernel for the counts its dispatch takes (the
/// kernels' records). The split groups the sum differently from the direct product
/// (`b + conv(B) + conv(x − B)`, with `x − β` rounded), so it is checked against the f64
/// reference within `γ_N·(|b| + Σ(|x| + 2|β|)|w|)`, `N = 2K + KH + KW + 2`: the
/// background's sums (`Cin`, then `KW` and `KH` terms), the differences' products (`Cin` each)
/// and one addition per tap.
#[test]
fn background_products_at_every_channel_count() {
    let mut r = rng(22);
    for cout in COUTS {
        let g = ConvGeom::new(16, 16, 4, cout, 8, 8, (4, 4), Padding::Same).unwrap();
        let mut conv = Conv2d::<f32>::new("c1", g).with_background_inference(true);
        let (w, b) = random_params(&mut conv, &mut r);
        let x = frame::<f32>(&[1, 16, 16, 4], 0.95, &mut r);
        let what = format!("background, {cout} channels");
        let got = on_path(Family::BackgroundSplit, avx512_expected(), &what, || {
            on_exactly(Family::Background, acting_path(cout), &what, || {
                conv.infer(&x);
                conv.output().data().to_vec()
            })
        });
        assert_eq!(
            plan::last(Product::ConvInfer),
            Some(Kernel::Background),
            "{what}"
        );
        let want = reference64(&g, &x, &w, &b);
        let beta = abs64(&x.data()[..4]);
        let xa: Vec<f64> = x
            .data()
            .iter()
            .enumerate()
            .map(|(i, v)| v.abs() as f64 + 2.0 * beta[i % 4])
            .collect();
        let bound = reference_forward(&g, 1, &xa, &abs64(w.data()), &abs64(b.data()), false);
        within(&what, &got, &want, &bound, 2 * g.patch_len() + 8 + 8 + 2);
    }
}

/// Places `count` nonzero values at distinct random places of `x` (zeros elsewhere), among
/// `places` (the values of each image that may be nonzero).
fn with_nonzeros(x: &mut [f32], places: &[usize], count: usize, r: &mut impl Rng) {
    x.fill(0.0);
    let mut free = places.to_vec();
    for _ in 0..count {
        let at = free.swap_remove(r.random_range(0..free.len()));
        x[at] = r.random_range(0.5..1.0);
    }
}

/// Acting's choice of algorithm at each side of each threshold, for inputs built with an
/// exact count of nonzero values or differing pixels: a convolution acts by the sparse
/// product up to `1/sparse_share(n)` of its padded input nonzero (a batch judged by its first
/// image, then as a whole) and by its forward pass one value above; conv1's split takes up to
/// `1/BACKGROUND_MAX_DIFFERING` of the pixels differing and one image only; a dense layer acts
/// sparse on any single sample and on a batch up to `1/dense_sparse_share(n)` nonzero. What
/// ran is the plan's record; a threshold that always fell back to the dense product, or one off
/// by one, fails here.
#[test]
fn infer_takes_each_algorithm_on_its_side_of_each_threshold() {
    // The dense products where no sparse one runs: the gather GEMM on AVX-512 (a convolution's
    // on AVX2 too; a dense layer's GEMM there is faer's).
    let avx = avx512_expected();
    let dense_kernel = if avx { Kernel::Gather } else { Kernel::Gemm };
    let conv_kernel = if avx || avx2_expected() {
        Kernel::Gather
    } else {
        Kernel::Im2col
    };
    let mut r = rng(23);

    // Sparse convolution: a 3×3 SAME layer over 6×6×16, padded to 8×8×16 = 1024 values.
    let g = ConvGeom::new(6, 6, 16, 16, 3, 3, (1, 1), Padding::Same).unwrap();
    let (hp, wp) = g.padded();
    let image = hp * wp * g.cin;
    let mut conv = Conv2d::<f32>::new("c", g).with_sparse_inference(true);
    let interior: Vec<usize> = (0..g.h * g.w * g.cin).collect();
    let mut infer_conv = |conv: &mut Conv2d<f32>, counts: &[usize]| {
        let mut x = Tensor::<f32>::zeros(&[counts.len(), 6, 6, 16]);
        for (img, &c) in x.data_mut().chunks_exact_mut(interior.len()).zip(counts) {
            with_nonzeros(img, &interior, c, &mut r);
        }
        conv.infer(&x);
        plan::last(Product::ConvInfer)
    };
    let one = image / plan::sparse_share(1);
    assert_eq!(plan::sparse_share(1), plan::SPARSE_MAX_NONZERO_ONE);
    assert_eq!(
        infer_conv(&mut conv, &[one]),
        Some(Kernel::Sparse),
        "{one} of {image}"
    );
    assert_eq!(
        infer_conv(&mut conv, &[one + 1]),
        Some(conv_kernel),
        "{}",
        one + 1
    );
    // A batch of 3: at most a tenth of the first image, then of the whole batch.
    let (first, all) = (
        image / plan::sparse_share(3),
        3 * image / plan::sparse_share(3),
    );
    assert_eq!(plan::sparse_share(3), plan::SPARSE_MAX_NONZERO_BATCH);
    let rest = all - first;
    for (counts, want) in [
        ([first, rest / 2, rest - rest / 2], Kernel::Sparse),
        ([first, rest / 2, rest - rest / 2 + 1], conv_kernel),
        ([first + 1, 0, 0], conv_kernel),
    ] {
        assert_eq!(
            infer_conv(&mut conv, &counts),
            Some(want),
            "batch {counts:?}"
        );
    }

    // conv1's split: 16×16 pixels, at most 32 differing.
    let g = ConvGeom::new(16, 16, 4, 32, 8, 8, (4, 4), Padding::Same).unwrap();
    let limit = g.h * g.w / plan::BACKGROUND_MAX_DIFFERING;
    for sparse_too in [false, true] {
        let mut conv1 = Conv2d::<f32>::new("c1", g)
            .with_background_inference(true)
            .with_sparse_inference(sparse_too);
        for (differing, n, want) in [
            (limit, 1, Kernel::Background),
            (limit + 1, 1, conv_kernel),
            (0, 2, conv_kernel),
        ] {
            // Background -1 (nonzero: the sparse product does not take it either); the
            // differing pixels differ in one channel.
            let mut x = Tensor::from_vec(&[n, 16, 16, 4], vec![-1.0f32; n * 16 * 16 * 4]);
            let mut pixels: Vec<usize> = (1..256).collect();
            for _ in 0..differing {
                let p = pixels.swap_remove(r.random_range(0..pixels.len()));
                x.data_mut()[p * 4 + r.random_range(0..4)] = r.random_range(0.0..1.0);
            }
            conv1.infer(&x);
            assert_eq!(
                plan::last(Product::ConvInfer),
                Some(want),
                "{differing} of 256 pixels differing, batch {n}, sparse inference {sparse_too}"
            );
        }
    }

    // Dense: 100 inputs; one sample acts sparse however dense, a batch of 3 up to a tenth.
    let mut dense = Dense::<f32>::new("d", 100, 16).with_sparse_inference(true);
    let places: Vec<usize> = (0..100).collect();
    let mut infer_dense = |counts: &[usize]| {
        let mut x = Tensor::<f32>::zeros(&[counts.len(), 100]);
        for (s, &c) in x.data_mut().chunks_exact_mut(100).zip(counts) {
            with_nonzeros(s, &places, c, &mut r);
        }
        dense.infer(&x);
        plan::last(Product::DenseInfer)
    };
    assert_eq!(plan::dense_sparse_share(1), 1);
    assert_eq!(
        infer_dense(&[100]),
        Some(Kernel::Sparse),
        "one dense sample"
    );
    let (first, all) = (
        100 / plan::dense_sparse_share(3),
        300 / plan::dense_sparse_share(3),
    );
    for (counts, want) in [
        ([first, all - first, 0], Kernel::Sparse),
        ([first, all - first, 1], dense_kernel),
        ([first + 1, 0, 0], dense_kernel),
    ] {
        assert_eq!(infer_dense(&counts), Some(want), "batch {counts:?}");
    }
}
