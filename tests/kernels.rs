//! The fast kernels against the plain reference kernels, on random shapes, in f32.
//!
//! The reference kernels are the ones `tests/gradcheck.rs` checks in f64 against finite
//! differences; here each fast path (gather, scatter, phases, Winograd) meets them in f32, to a
//! tolerance derived from f32 rounding, and meets its portable twin bit for bit where the sums
//! run in the same order. Tests also assert which loop ran (`common::on_path`).

mod common;

use common::{
    assert_close, avx2_expected, avx512_expected, conv_and_dense_passes, dense_pass,
    forward_backward_into, gamma, on_path, padded_input, reference_dz, reference_forward,
    reference_grads, reference_output, rng, same_on_1_2_3_threads, set_params, uniform, Square,
};
use invaders::layers::{Conv2d, Layer};
use invaders::ops::plan::{self, Kernel, Precision, Product};
use invaders::tensor::cpu::Family;
use invaders::tensor::{
    fill_iota, gather_gemm_portable, gemm, gemm_matrixmultiply, gemm_reference, pad_input,
    scatter_gemm_portable, transpose, winograd_conv, winograd_filters, winograd_filters_s2d,
    winograd_filters_s2d_adjoint, winograd_wgrad, Border, ConvGeom, Float, GatherGemm, Init, Op,
    Padding, ScatterGemm, Tensor, WinogradKind, WinogradScratch, WinogradShape, SKIP_OUTPUT,
};
use proptest::prelude::*;

/// A plain `Conv2d` of `g` with weights drawn from `r`, forward on `n` images drawn from `r` and
/// backward with a `dY` drawn from `r`, against the direct convolution and its direct backward
/// pass: `y`, `dX`, `dW` and `db` within 1e-5.
fn conv_matches_reference(
    g: ConvGeom, n: usize, r: &mut impl rand::Rng,
) -> Result<(), TestCaseError> {
    let mut layer = Conv2d::<f32>::new("c", g);
    let wt = uniform::<f32>(&[g.kh, g.kw, g.cin, g.cout], r);
    let bt = uniform::<f32>(&[g.cout], r);
    set_params(&mut layer, &[&wt, &bt]);
    let x = uniform::<f32>(&[n, g.h, g.w, g.cin], r);
    let dy = uniform::<f32>(&[n, g.oh, g.ow, g.cout], r);
    layer.forward(&x);
    let y = reference_forward(&g, n, x.data(), wt.data(), bt.data(), false);
    assert_close("y", layer.output().data(), &y, 1e-5)?;
    layer.backward(&x, &dy, true);
    let grads = reference_grads(&g, n, x.data(), wt.data(), dy.data());
    assert_grads(&layer, grads, 1e-5)
}

/// Asserts that `layer`'s input, weight and bias gradients are `(dX, dW, db)` within `tol`.
fn assert_grads(
    layer: &Conv2d<f32>, (dx, dw, db): (Vec<f32>, Vec<f32>, Vec<f32>), tol: f64,
) -> Result<(), TestCaseError> {
    assert_close("dx", layer.input_grad().data(), &dx, tol)?;
    assert_close("dw", layer.params()[0].grad.data(), &dw, tol)?;
    assert_close("db", layer.params()[1].grad.data(), &db, tol)
}

/// Runs `layer` (of `g`, weights `wt`, output pixels starting at `at`, just run forward on
/// `xin`: `x`, or `x` inside its padding) backward with a `dY` of its output's shape drawn from
/// `r`; returns the reference gradients `(dX, dW, db)` for `x` and that `dY`, past the ReLU if
/// `relu` (its mask from the layer's own output: a fast kernel rounds differently from the
/// reference).
fn backward_ref(
    layer: &mut Conv2d<f32>, g: &ConvGeom, (x, xin): (&Tensor<f32>, &Tensor<f32>),
    wt: &Tensor<f32>, at: &[usize], relu: bool, r: &mut impl rand::Rng,
) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let dy = uniform::<f32>(layer.output().shape(), r);
    let dz = reference_dz(dy.data(), layer.output().data(), at, g.cout, relu);
    layer.backward(xin, &dy, true);
    reference_grads(g, x.shape()[0], x.data(), wt.data(), &dz)
}

proptest! {
    #![proptest_config(ProptestConfig { cases: common::cases(64), ..ProptestConfig::default() })]

    /// The parallel GEMM for every transpose combination, with beta 0 (overwrite, even NaN) and 1
    /// (accumulate), at sizes that split into several row blocks.
    #[test]
    fn gemm_matches_reference(
        m in 1usize..300, n in 1usize..40, k in 1usize..70,
        ta in any::<bool>(), tb in any::<bool>(), accumulate in any::<bool>(), seed in any::<u64>(),
    ) {
        let mut r = rng(seed);
        let a = uniform::<f32>(&[m * k], &mut r);
        let b = uniform::<f32>(&[k * n], &mut r);
        let c0 = uniform::<f32>(&[m * n], &mut r);
        let (opa, opb) = (if ta { Op::T } else { Op::N }, if tb { Op::T } else { Op::N });
        let beta = if accumulate { 1.0 } else { 0.0 };
        let mut fast = c0.data().to_vec();
        if !accumulate { fast.fill(f32::NAN); }
        let mut slow = c0.data().to_vec();
        let mut other = fast.clone();
        gemm(opa, opb, m, n, k, 0.5, a.data(), b.data(), beta, &mut fast);
        gemm_matrixmultiply(opa, opb, m, n, k, 0.5, a.data(), b.data(), beta, &mut other);
        gemm_reference(opa, opb, m, n, k, 0.5, a.data(), b.data(), beta, &mut slow);
        assert_close("C (faer)", &fast, &slow, 1e-5)?;
        assert_close("C (matrixmultiply)", &other, &slow, 1e-5)?;
    }

    /// The gather GEMM (AVX-512 where the CPU has it) as a plain `A·B` and `Aᵀ·B` against the
    /// reference GEMM, for each start (zero over NaN, accumulate, bias), at widths that cover
    /// every panel width and masked tail and heights that leave row remainders (a lone row takes
    /// 128-column panels); and bit-for-bit
    /// against the portable loops, which sum in the same order. The AVX-512 kernel is the one
    /// that ran where the host has it (the portable one otherwise).
    #[test]
    fn gather_gemm_matches_reference(
        // Single rows (and 7 = one 6-row tile + 1) with wide C take the 128-column GEMV panels.
        m in prop_oneof![1usize..3, Just(7usize), 1usize..80],
        // Up to 8 columns take the AVX-512 kernel's 8-lane tiles of 16 rows.
        n in prop_oneof![1usize..=8, 1usize..150, 120usize..300],
        k in 0usize..300, trans in any::<bool>(),
        init in 0u8..3, seed in any::<u64>(),
        // Rows of C placed apart (`c_rows`, as for an output with a zero border), and a ReLU.
        gap in prop_oneof![Just(0usize), 1usize..20], relu in any::<bool>(),
    ) {
        let mut r = rng(seed);
        let a = uniform::<f32>(&[(m * k).max(1)], &mut r);
        let b = uniform::<f32>(&[(k * n).max(1)], &mut r);
        let bias = uniform::<f32>(&[n], &mut r);
        let c0 = uniform::<f32>(&[m * n], &mut r);
        let (mut p, mut q) = (Vec::new(), Vec::new());
        if trans {
            fill_iota(&mut p, m, 1);
            fill_iota(&mut q, k, m);
        } else {
            fill_iota(&mut p, m, k);
            fill_iota(&mut q, k, 1);
        }
        let mut slow = c0.data().to_vec();
        match init {
            0 => slow.fill(0.0),
            2 => for row in slow.chunks_exact_mut(n) { row.copy_from_slice(bias.data()) },
            _ => {}
        }
        let opa = if trans { Op::T } else { Op::N };
        gemm_reference(opa, Op::N, m, n, k, 1.0, a.data(), b.data(), 1.0, &mut slow);
        if relu {
            slow.iter_mut().for_each(|v| *v = v.max(0.0));
        }
        // With a gap, row r lives at 3 + r·(n + gap) of a buffer whose other places hold a
        // sentinel the kernel must not touch.
        let rows: Vec<usize> = (0..m).map(|r| 3 + r * (n + gap)).collect();
        let run = |portable: bool| {
            let mut cb = vec![7.5f32; 3 + m * (n + gap)];
            for (row, &at) in c0.data().chunks_exact(n).zip(&rows) {
                cb[at..at + n].copy_from_slice(if init == 0 { &[f32::NAN; 300][..n] } else { row });
            }
            let init = match init { 0 => Init::Zero, 1 => Init::Accumulate, _ => Init::Bias(bias.data()) };
            let (c_rows, c) = if gap == 0 { (None, &mut cb[3..]) } else { (Some(&rows[..]), &mut cb[..]) };
            let g = GatherGemm { a: a.data(), p: &p, q: &q, b: b.data(), ldb: n, n, c, ldc: n, c_rows, init, relu };
            if portable {
                gather_gemm_portable(g)
            } else {
                on_path(Family::Gather, avx512_expected(), "gather_gemm", || f32::gather_gemm(g))
            }
            let untouched = cb.iter().enumerate().all(|(i, &v)| {
                rows.iter().any(|&at| (at..at + n).contains(&i)) || v == 7.5
            });
            assert!(untouched, "a place between rows was written");
            rows.iter().flat_map(|&at| cb[at..at + n].to_vec()).collect::<Vec<f32>>()
        };
        let fast = run(false);
        assert_close("C", &fast, &slow, 1e-5)?;
        prop_assert_eq!(fast, run(true));
    }

    /// The `Dense` layer in f32 (the gather GEMM where the CPU has it), with and without its
    /// fused ReLU, against the plain products in f64: `y`, `dW`, `db` and `dX`, for batches
    /// whose input gradient runs on `W` in place and on `Wᵀ` ([`plan::dense_dx_on_wt`]).
    #[test]
    fn dense_matches_reference(
        ni in 1usize..150, no in 1usize..40, n in 1usize..70, relu in any::<bool>(),
        seed in any::<u64>(),
    ) {
        let (layer, [w, b, x, dy]) = dense_pass(ni, no, n, relu, Precision::F32, &mut rng(seed));
        let y = layer.output().data().to_vec();
        let f = |v: f32| f64::from(v);
        let (mut y_ref, mut dz) = (vec![0.0f64; n * no], vec![0.0f64; n * no]);
        for s in 0..n {
            for j in 0..no {
                let z = f(b.data()[j])
                    + (0..ni).map(|i| f(x.data()[s * ni + i]) * f(w.data()[i * no + j])).sum::<f64>();
                y_ref[s * no + j] = if relu { z.max(0.0) } else { z };
                // The mask as the layer stored it (a value within rounding of 0 may fall
                // either side).
                let on = !relu || y[s * no + j] > 0.0;
                dz[s * no + j] = if on { f(dy.data()[s * no + j]) } else { 0.0 };
            }
        }
        let dw_ref: Vec<f64> = (0..ni * no)
            .map(|k| (0..n).map(|s| f(x.data()[s * ni + k / no]) * dz[s * no + k % no]).sum())
            .collect();
        let db_ref: Vec<f64> = (0..no).map(|j| (0..n).map(|s| dz[s * no + j]).sum()).collect();
        let dx_ref: Vec<f64> = (0..n * ni)
            .map(|k| (0..no).map(|j| dz[k / ni * no + j] * f(w.data()[k % ni * no + j])).sum())
            .collect();
        let f64s = |v: &[f32]| v.iter().map(|&v| f64::from(v)).collect::<Vec<f64>>();
        assert_close("y", &f64s(&y), &y_ref, 1e-5)?;
        assert_close("dW", &f64s(layer.params()[0].grad.data()), &dw_ref, 1e-5)?;
        assert_close("db", &f64s(layer.params()[1].grad.data()), &db_ref, 1e-5)?;
        assert_close("dX", &f64s(layer.input_grad().data()), &dx_ref, 1e-5)?;
    }

    /// The `Conv2d` layer (im2col + GEMM, col2im) against the direct convolution and its direct
    /// backward pass.
    #[test]
    fn conv2d_matches_reference(
        kh in 1usize..=8, kw in 1usize..=8, sh in 1usize..=4, sw in 1usize..=4,
        h in 1usize..24, w in 1usize..24, cin in 1usize..6, cout in 1usize..9, n in 1usize..4,
        same in any::<bool>(), seed in any::<u64>(),
    ) {
        let pad = if same { Padding::Same } else { Padding::Valid };
        let Some(g) = ConvGeom::new(h, w, cin, cout, kh, kw, (sh, sw), pad) else {
            return Ok(()); // VALID with a kernel larger than the input
        };
        conv_matches_reference(g, n, &mut rng(seed))?;
    }

    /// `Conv2d` with a fused ReLU and a zero border around its output (on the fast path where
    /// the CPU has it, so the kernel's `c_rows` and ReLU store): the output is the reference
    /// convolution's, clamped and placed inside zeros (stale values from a larger batch must not
    /// survive in the border), and the gradients are the reference's for `dZ` = the interior of
    /// `dY` where the output is positive, whatever `dY` holds on the border.
    #[test]
    fn conv2d_relu_and_border_match_reference(
        k in 1usize..=4, s in 1usize..=3, h in 4usize..14, w in 4usize..14, cin in 1usize..6,
        cout in 1usize..40, n in 1usize..3, same in any::<bool>(), relu in any::<bool>(),
        top in 0usize..3, bottom in 0usize..3, left in 0usize..3, right in 0usize..3,
        in_border in any::<bool>(), winograd in any::<bool>(), seed in any::<u64>(),
    ) {
        // Winograd (batches of 8 or more): F(2×2, 3×3) for a 3×3 stride-1 filter (forward, and
        // the input gradient when the input is read in place), or F(2×2, 2×2) over s × s
        // blocks for a 2s × 2s filter of stride s (forward).
        let (k, s) = match (winograd, seed % 2) {
            (false, _) => (k, s),
            (true, 0) => (3, 1),
            (true, _) => (2 * s, s),
        };
        let (n, h, w) = if winograd { (n + 7, h.max(k), w.max(k)) } else { (n, h, w) };
        let pad = if same { Padding::Same } else { Padding::Valid };
        let g = ConvGeom::new(h, w, cin, cout, k, k, (s, s), pad).unwrap();
        let border = Border { top, bottom, left, right };
        let mut r = rng(seed);
        let mut layer = Conv2d::<f32>::new("c", g).with_border(border).with_winograd(winograd);
        // The input's outer ring declared a border: its gradient is left out (zeros).
        let ib = Border { top: 1, bottom: 1, left: 1, right: 1 };
        if in_border {
            layer = layer.with_input_border(ib);
        }
        if relu {
            layer = layer.with_relu();
        }
        let wt = uniform::<f32>(&[k, k, cin, cout], &mut r);
        let bt = uniform::<f32>(&[cout], &mut r);
        set_params(&mut layer, &[&wt, &bt]);
        // A larger batch first, forward and backward: the layer zeroes a border only in the
        // images it has not zeroed before, so what the first pass leaves must still hold.
        let (hb, wb) = border.around(g.oh, g.ow);
        let big = uniform::<f32>(&[n + 1, h, w, cin], &mut r);
        layer.forward(&big);
        layer.backward(&big, &uniform::<f32>(&[n + 1, hb, wb, cout], &mut r), true);
        for p in layer.params_mut() {
            p.grad.fill_zero();
        }
        let x = uniform::<f32>(&[n, h, w, cin], &mut r);
        layer.forward(&x);
        let (y, at) = reference_output(&g, n, x.data(), wt.data(), bt.data(), border, relu);
        prop_assert_eq!(layer.output().shape(), &[n, hb, wb, cout][..]);
        assert_close("y", layer.output().data(), &y, 1e-5)?;
        let (mut dx, dw, db) = backward_ref(&mut layer, &g, (&x, &x), &wt, &at, relu, &mut r);
        if in_border {
            ib.zero(&mut dx, n, h - 2, w - 2, cin);
        }
        assert_grads(&layer, (dx, dw, db), 1e-5)?;
    }
}

/// A convolution of `g` over `n` images for the Winograd checks: its weights, bias, input and
/// `dY`, drawn in that order from a generator of `seed`; the Winograd scratch space; the
/// tolerance of the comparisons with the reference.
struct WinogradCheck<T: Float> {
    g: ConvGeom,
    n: usize,
    wt: Tensor<T>,
    bt: Tensor<T>,
    x: Tensor<T>,
    dy: Tensor<T>,
    scratch: WinogradScratch<T>,
    tol: f64,
}

impl<T: Float> WinogradCheck<T> {
    fn new(g: ConvGeom, n: usize, seed: u64, tol: f64) -> Self {
        let mut r = rng(seed);
        let wt = uniform::<T>(&[g.kh, g.kw, g.cin, g.cout], &mut r);
        let bt = uniform::<T>(&[g.cout], &mut r);
        let x = uniform::<T>(&[n, g.h, g.w, g.cin], &mut r);
        let dy = uniform::<T>(&[n, g.oh, g.ow, g.cout], &mut r);
        let scratch = WinogradScratch::default();
        WinogradCheck {
            g,
            n,
            wt,
            bt,
            x,
            dy,
            scratch,
            tol,
        }
    }

    /// [`winograd_conv`] forward by `kind` (`u` the filters transformed for it), with the bias
    /// and the ReLU if `relu`, against the reference convolution; returns the shape it ran.
    fn forward(
        &mut self, kind: WinogradKind, u: &[T], relu: bool,
    ) -> Result<WinogradShape, TestCaseError> {
        let (g, n) = (&self.g, self.n);
        let mut pixels = Vec::new();
        fill_iota(&mut pixels, g.oh * g.ow, g.cout);
        let shape = WinogradShape {
            n,
            h: g.h,
            w: g.w,
            ci: g.cin,
            oh: g.oh,
            ow: g.ow,
            pad_top: g.pad_top,
            pad_left: g.pad_left,
            co: g.cout,
            out_image: g.oh * g.ow * g.cout,
            out_pieces: 1,
            kind,
        };
        let (x, wt, bt) = (self.x.data(), self.wt.data(), self.bt.data());
        let mut y = vec![T::of(f64::NAN); n * g.oh * g.ow * g.cout];
        winograd_conv(
            shape,
            x,
            u,
            Some(bt),
            relu,
            &mut y,
            &pixels,
            &mut self.scratch,
        );
        let want = reference_forward(g, n, x, wt, bt, relu);
        assert_close("y", &y, &want, self.tol)?;
        Ok(shape)
    }

    /// The reference gradients `(dX, dW, db)` for `dY`.
    fn reference_grads(&self) -> (Vec<T>, Vec<T>, Vec<T>) {
        let (x, wt, dy) = (self.x.data(), self.wt.data(), self.dy.data());
        reference_grads(&self.g, self.n, x, wt, dy)
    }

    /// [`winograd_wgrad`] over the forward `shape` adds the reference weight gradient `dw` to
    /// what its output holds (ones, to start).
    fn wgrad(&mut self, shape: WinogradShape, mut dw: Vec<T>) -> Result<(), TestCaseError> {
        let mut dww = vec![T::one(); dw.len()];
        let (x, dy) = (self.x.data(), self.dy.data());
        winograd_wgrad(shape, x, dy, &mut dww, &mut self.scratch);
        dw.iter_mut().for_each(|v| *v += T::one());
        assert_close("dw", &dww, &dw, self.tol)
    }
}

/// [`winograd_conv`] against the direct reference convolution, forward (bias, ReLU, SAME or VALID)
/// and as the adjoint (the input gradient: the rotated, transposed filter over `dY`), and
/// [`winograd_wgrad`] against the reference weight gradient, in `T`.
/// With f32 and channel counts that are multiples of 16 this runs the AVX-512 transforms, and
/// otherwise the portable ones.
#[allow(clippy::too_many_arguments)]
fn winograd_case<T: Float>(
    h: usize, w: usize, ci: usize, co: usize, n: usize, same: bool, relu: bool, seed: u64, tol: f64,
) -> Result<(), TestCaseError> {
    let pad = if same { Padding::Same } else { Padding::Valid };
    let g = ConvGeom::new(h, w, ci, co, 3, 3, (1, 1), pad).unwrap();
    let mut c = WinogradCheck::<T>::new(g, n, seed, tol);
    let mut u = Vec::new();
    // Forward: y = relu(b + conv(x, w)), over x read as zero outside the image.
    winograd_filters(c.wt.data(), ci, co, false, &mut u);
    let forward = c.forward(WinogradKind::F2x3, &u, relu)?;
    // Adjoint: dX[iy, ix] = Σ dY[iy − ky + pad, ix − kx + pad]·wᵀ, dY read at padding 2 − pad.
    winograd_filters(c.wt.data(), ci, co, true, &mut u);
    let mut pixels = Vec::new();
    fill_iota(&mut pixels, h * w, ci);
    let shape = WinogradShape {
        n,
        h: g.oh,
        w: g.ow,
        ci: co,
        oh: h,
        ow: w,
        pad_top: 2 - g.pad_top,
        pad_left: 2 - g.pad_left,
        co: ci,
        out_image: h * w * ci,
        out_pieces: 1,
        kind: WinogradKind::F2x3,
    };
    let mut dx = vec![T::of(f64::NAN); n * h * w * ci];
    winograd_conv(
        shape,
        c.dy.data(),
        &u,
        None,
        false,
        &mut dx,
        &pixels,
        &mut c.scratch,
    );
    let (want, dw, _) = c.reference_grads();
    assert_close("dx", &dx, &want, tol)?;
    // Weight gradient (added to what `dw` holds: start from ones).
    c.wgrad(forward, dw)
}

/// [`winograd_conv`] and [`winograd_wgrad`] by F(2×2, 2×2) over `s × s` blocks (a `2s × 2s`
/// filter of stride `s`, VALID: the layer passes an input padded already) against the direct
/// reference, in `T`.
/// With f32, `s·ci` and `co` multiples of 16 (conv1's 4 × 4, conv2's 2 × 32) this runs the
/// AVX-512 transforms.
#[allow(clippy::too_many_arguments)]
fn winograd_s2d_case<T: Float>(
    s: usize, h: usize, w: usize, ci: usize, co: usize, n: usize, relu: bool, seed: u64, tol: f64,
) -> Result<(), TestCaseError> {
    let g = ConvGeom::new(h, w, ci, co, 2 * s, 2 * s, (s, s), Padding::Valid).unwrap();
    let mut c = WinogradCheck::<T>::new(g, n, seed, tol);
    let mut u = Vec::new();
    winograd_filters_s2d(c.wt.data(), s, ci, co, &mut u);
    let shape = c.forward(WinogradKind::S2d(s), &u, relu)?;
    // Weight gradient (added to what `dw` holds: start from ones) against the reference's.
    let (mut dx, dw, _) = c.reference_grads();
    c.wgrad(shape, dw)?;
    // Input gradient by the adjoint over blocks, F(2×2, 2×2) with blocks of one pixel: dY read
    // from one pixel above and to the left, into the blocks that tile s(OH+1) × s(OW+1), each
    // block's s² pixels a piece of `ci` channels. The first row and column are skipped (as a
    // border would be); they and the places past the blocks keep what they held.
    let (bh, bw) = (g.oh + 1, g.ow + 1);
    let mut wt2 = Vec::new();
    winograd_filters_s2d_adjoint(c.wt.data(), s, ci, co, &mut wt2, &mut u);
    let mut pieces = Vec::new();
    for by in 0..bh {
        for bx in 0..bw {
            for (dy, dx) in (0..s).flat_map(|dy| (0..s).map(move |dx| (dy, dx))) {
                let (iy, ix) = (s * by + dy, s * bx + dx);
                pieces.push(if iy == 0 || ix == 0 {
                    SKIP_OUTPUT
                } else {
                    (iy * w + ix) * ci
                });
            }
        }
    }
    let adjoint = WinogradShape {
        n,
        h: g.oh,
        w: g.ow,
        ci: co,
        oh: bh,
        ow: bw,
        pad_top: 1,
        pad_left: 1,
        co: s * s * ci,
        out_image: h * w * ci,
        out_pieces: s * s,
        kind: WinogradKind::S2d(1),
    };
    let held = T::of(7.0);
    let mut dxw = vec![held; c.x.len()];
    winograd_conv(
        adjoint,
        c.dy.data(),
        &u,
        None,
        false,
        &mut dxw,
        &pieces,
        &mut c.scratch,
    );
    for (p, v) in dx.chunks_exact_mut(ci).enumerate() {
        let (iy, ix) = (p / w % h, p % w);
        if iy == 0 || ix == 0 || iy >= s * bh || ix >= s * bw {
            v.fill(held);
        }
    }
    assert_close("dx", &dxw, &dx, tol)
}

proptest! {
    #![proptest_config(ProptestConfig { cases: common::cases(64), ..ProptestConfig::default() })]

    /// Winograd F(2×2, 2×2) over blocks, f32 (AVX-512 transforms where `s·ci` and `co` are
    /// multiples of 16) and f64 (portable), odd and even output sizes: forward, weight gradient
    /// and input gradient (in pieces of `ci` channels: AVX-512 output transforms for 16 and 32,
    /// a full and a short lane group per piece for 20).
    #[test]
    fn winograd_s2d_matches_reference(
        s in 1usize..=4, extra_h in 0usize..12, extra_w in 0usize..12,
        ci in prop_oneof![1usize..7, Just(4), Just(8), Just(16), Just(20), Just(32)],
        co in prop_oneof![1usize..20, Just(16), Just(32), Just(64)],
        n in 1usize..4, relu in any::<bool>(), seed in any::<u64>(),
    ) {
        let (h, w) = (2 * s + extra_h, 2 * s + extra_w);
        winograd_s2d_case::<f32>(s, h, w, ci, co, n, relu, seed, 2e-5)?;
        winograd_s2d_case::<f64>(s, h, w, ci, co, n, relu, seed, 1e-12)?;
    }

    /// Winograd F(2×2, 3×3) in f32 (AVX-512 transforms for 16, 32, 64 channels) and in f64
    /// (portable transforms, where only rounding can differ: 1e-12).
    #[test]
    fn winograd_matches_reference(
        h in 3usize..14, w in 3usize..14,
        ci in prop_oneof![1usize..20, Just(16), Just(32), Just(64)],
        co in prop_oneof![1usize..20, Just(16), Just(32), Just(64)],
        n in 1usize..4, same in any::<bool>(), relu in any::<bool>(), seed in any::<u64>(),
    ) {
        winograd_case::<f32>(h, w, ci, co, n, same, relu, seed, 2e-5)?;
        winograd_case::<f64>(h, w, ci, co, n, same, relu, seed, 1e-12)?;
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: common::cases(16), ..ProptestConfig::default() })]

    /// The article's conv1 (8×8 stride 4 over 4 frames) and conv2 (4×4 stride 2, 32 → 64
    /// channels) as `Conv2d` layers with Winograd on, at a batch of 8 (where it runs, on the
    /// AVX-512 transforms), SAME: the output matches the reference convolution, with the ReLU and
    /// the border the network writes, and the gradients are the reference's for that output.
    /// `bordered`: built as `article_qnet` builds conv2 (and conv3), a VALID convolution over an
    /// input that carries its SAME padding as a border whose gradient is left out; its input
    /// gradient is then the Winograd adjoint over blocks (pieces of 32 channels for conv2, on the
    /// AVX-512 output transform; of 4 for conv1, on the portable one), the plain input's
    /// gradient inside zeros.
    #[test]
    fn conv2d_winograd_blocks_match_reference(
        conv1 in any::<bool>(), h in 8usize..30, w in 8usize..30, bordered in any::<bool>(),
        seed in any::<u64>(),
    ) {
        let (cin, cout, k, s) = if conv1 { (4, 32, 8, 4) } else { (32, 64, 4, 2) };
        let g = ConvGeom::new(h, w, cin, cout, k, k, (s, s), Padding::Same).unwrap();
        let border = Border { top: 1, bottom: 1, left: 1, right: 1 };
        let (valid, padding) = g.as_valid();
        let built = if bordered {
            Conv2d::<f32>::new("c", valid).with_input_border(padding)
        } else {
            Conv2d::<f32>::new("c", g)
        };
        let mut layer = built.with_border(border).with_relu().with_winograd(true);
        let mut r = rng(seed);
        let n = 8;
        let wt = uniform::<f32>(&[k, k, cin, cout], &mut r);
        let bt = uniform::<f32>(&[cout], &mut r);
        set_params(&mut layer, &[&wt, &bt]);
        let x = uniform::<f32>(&[n, h, w, cin], &mut r);
        let xin = if bordered {
            padded_input(&g, n, &x)
        } else {
            x.clone()
        };
        layer.forward(&xin);
        let (y, at) = reference_output(&g, n, x.data(), wt.data(), bt.data(), border, true);
        let (hb, wb) = border.around(g.oh, g.ow);
        prop_assert_eq!(layer.output().shape(), &[n, hb, wb, cout][..]);
        assert_close("y", layer.output().data(), &y, 1e-5)?;
        let (mut dx, dw, db) = backward_ref(&mut layer, &g, (&x, &xin), &wt, &at, true, &mut r);
        if bordered {
            let mut dxp = Vec::new();
            pad_input(&g, n, &dx, &mut dxp);
            dx = dxp;
        }
        assert_grads(&layer, (dx, dw, db), 1e-5)?;
    }
}

/// A SAME convolution fed its input already padded (`[N, HP, WP, Cin]` inside a zero border, as
/// the agent's replay batches are for conv1) against the same layer fed the plain input: the
/// output and the weight and bias gradients are bit-identical (same products over the same
/// padded layout), and the input gradient is the VALID convolution's over the padded input
/// (its interior the plain input's gradient, its border the padding places' own gradient).
#[allow(clippy::too_many_arguments)]
fn prepadded_case<T: Float>(
    c: Square, n: usize, relu: bool, seed: u64, tol: f64,
) -> Result<(), TestCaseError> {
    let g = c.geom(true);
    let Square {
        k, h, w, cin, cout, ..
    } = c;
    let mut r = rng(seed);
    let make = || {
        let l = Conv2d::<T>::new("c", g);
        if relu {
            l.with_relu()
        } else {
            l
        }
    };
    let (mut plain, mut padded) = (make(), make());
    let wt = uniform::<T>(&[k, k, cin, cout], &mut r);
    let bt = uniform::<T>(&[cout], &mut r);
    set_params(&mut plain, &[&wt, &bt]);
    set_params(&mut padded, &[&wt, &bt]);
    let x = uniform::<T>(&[n, h, w, cin], &mut r);
    let xp = padded_input(&g, n, &x);
    let valid = g.as_valid().0;
    prop_assert_eq!(padded.input_geometry(&xp), valid);
    prop_assert_eq!(padded.input_geometry(&x), g);
    plain.forward(&x);
    padded.forward(&xp);
    prop_assert!(plain.output() == padded.output(), "y differs");
    let dy = uniform::<T>(plain.output().shape(), &mut r);
    plain.backward(&x, &dy, true);
    padded.backward(&xp, &dy, true);
    for i in 0..2 {
        prop_assert!(
            plain.params()[i].grad == padded.params()[i].grad,
            "gradient of parameter {} differs",
            i
        );
    }
    // dX of the padded input: the reference VALID convolution's over it, through the layer's
    // own ReLU mask (a reference pre-activation summed in another order can fall on the other
    // side of 0, which would move a whole window's dX).
    prop_assert_eq!(padded.output().len(), n * g.oh * g.ow * cout);
    let dz: Vec<T> = padded
        .output()
        .data()
        .iter()
        .zip(dy.data())
        .map(|(&yv, &d)| {
            if !relu || yv > T::zero() {
                d
            } else {
                T::zero()
            }
        })
        .collect();
    let (dx, _, _) = reference_grads(&valid, n, xp.data(), wt.data(), &dz);
    prop_assert_eq!(padded.input_grad().shape(), xp.shape());
    let scale = dx
        .iter()
        .fold(1.0, |m: f64, v| m.max(v.to_f64().unwrap().abs()));
    for (i, (a, b)) in padded.input_grad().data().iter().zip(&dx).enumerate() {
        prop_assert!(
            (a.to_f64().unwrap() - b.to_f64().unwrap()).abs() <= tol * scale,
            "dx[{}]: {:?} vs {:?}",
            i,
            a,
            b
        );
    }
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig { cases: common::cases(48), ..ProptestConfig::default() })]

    /// A pre-padded input, on the fast path (f32) and the portable one (f64).
    #[test]
    fn conv2d_reads_a_prepadded_input(
        k in 1usize..=8, s in 1usize..=4, h in 3usize..14, w in 3usize..14, cin in 1usize..6,
        cout in 1usize..40, n in 1usize..3, relu in any::<bool>(), seed in any::<u64>(),
    ) {
        prepadded_case::<f32>(Square { k, s, h, w, cin, cout }, n, relu, seed, 1e-5)?;
        prepadded_case::<f64>(Square { k, s, h, w, cin, cout }, n, relu, seed, 1e-12)?;
    }
}

/// The article's three convolutions at their exact shapes (batch 2), forward and backward, against
/// the direct reference.
#[test]
fn article_convolutions_match_reference() {
    for (i, (h, w, cin, cout, k, s)) in common::ARTICLE_CONVS.into_iter().enumerate() {
        let g = ConvGeom::new(h, w, cin, cout, k, k, (s, s), Padding::Same).unwrap();
        conv_matches_reference(g, 2, &mut rng(i as u64)).unwrap();
    }
}

/// TensorFlow's SAME rule, including the uneven case (the extra padding goes after).
#[test]
fn same_padding_follows_tensorflow() {
    // 88 rows, kernel 8, stride 4: 22 outputs, (21·4 + 8) − 88 = 4 rows of padding, 2 above.
    let g = ConvGeom::new(88, 80, 4, 32, 8, 8, (4, 4), Padding::Same).unwrap();
    assert_eq!((g.oh, g.ow, g.pad_top, g.pad_left), (22, 20, 2, 2));
    // 22x20, kernel 4, stride 2: 11x10, padding 2 in total, 1 before.
    let g = ConvGeom::new(22, 20, 32, 64, 4, 4, (2, 2), Padding::Same).unwrap();
    assert_eq!((g.oh, g.ow, g.pad_top, g.pad_left), (11, 10, 1, 1));
    // 9 rows, kernel 4, stride 3: 3 outputs, (2·3 + 4) − 9 = 1 row, 0 above, 1 below.
    let g = ConvGeom::new(9, 7, 3, 5, 4, 4, (3, 3), Padding::Same).unwrap();
    assert_eq!((g.oh, g.ow, g.pad_top, g.pad_left), (3, 3, 0, 1));
    // A kernel smaller than the stride needs no padding.
    let g = ConvGeom::new(8, 8, 1, 1, 1, 1, (4, 4), Padding::Same).unwrap();
    assert_eq!((g.oh, g.pad_top), (2, 0));
    let g = ConvGeom::new(10, 9, 2, 3, 3, 2, (2, 2), Padding::Valid).unwrap();
    assert_eq!((g.oh, g.ow), (4, 4));
    assert!(ConvGeom::new(2, 9, 2, 3, 3, 2, (2, 2), Padding::Valid).is_none());
    assert!(ConvGeom::new(2, 9, 2, 3, 3, 2, (0, 2), Padding::Same).is_none());
}

/// Changing the batch size reuses buffers and gives the same per-sample results.
#[test]
fn batch_size_changes_are_consistent() {
    let g = ConvGeom::new(12, 10, 3, 4, 3, 3, (2, 2), Padding::Same).unwrap();
    let mut layer = Conv2d::<f32>::new("c", g);
    let mut r = rng(3);
    let wt = uniform::<f32>(&[3, 3, 3, 4], &mut r);
    set_params(&mut layer, &[&wt]);
    let x = uniform::<f32>(&[5, 12, 10, 3], &mut r);
    layer.forward(&x);
    let big = layer.output().clone();
    let one = Tensor::from_vec(&[1, 12, 10, 3], x.data()[..360].to_vec());
    layer.forward(&one);
    assert_eq!(layer.output().data(), &big.data()[..g.out_pixels() * 4]);
}

/// The fast convolution and dense layers give bit-identical results on 1, 2 and 3 threads: every
/// output element is summed in a fixed order whatever the split into rayon tasks.
#[test]
fn results_do_not_depend_on_thread_count() {
    same_on_1_2_3_threads(|| {
        let mut r = rng(11);
        let g = ConvGeom::new(22, 20, 32, 64, 4, 4, (2, 2), Padding::Same).unwrap();
        let conv = Conv2d::<f32>::new("c", g);
        let mut out = conv_and_dense_passes(conv, 6, Precision::F32, &mut r);
        // Winograd, F(2×2, 3×3) (forward and input gradient) and F(2×2, 2×2) over 2×2
        // blocks (forward; the input gradient by phases for 13 rows, which the blocks do
        // not tile, by the adjoint over blocks for 12), over a batch of 9 (Winograd runs
        // from 8), which splits unevenly.
        for (cin, k, s, h) in [(32, 3, 1, 13), (32, 4, 2, 13), (32, 4, 2, 12)] {
            let g = ConvGeom::new(h, 12, cin, 48, k, k, (s, s), Padding::Valid).unwrap();
            let mut conv = Conv2d::<f32>::new("w", g).with_winograd(true).with_relu();
            let (x, dy) = ([9, h, 12, cin], [9, g.oh, g.ow, 48]);
            forward_backward_into(&mut conv, &x, &dy, &mut r, &mut out);
        }
        out
    });
}

/// The checks in front of the unsafe gather kernel refuse what would read or write out of
/// bounds: an `A` offset past the end (the largest row start plus the largest step), and rows
/// of `C` that overlap or go backwards.
#[test]
fn gather_gemm_refuses_out_of_range_tables() {
    let (a, b) = (vec![1.0f32; 40], vec![1.0f32; 4 * 8]);
    let (mut p, mut q) = (Vec::new(), Vec::new());
    fill_iota(&mut p, 5, 4);
    fill_iota(&mut q, 4, 1);
    let run = |p: &[usize], rows: Option<&[usize]>| {
        let (p, q, a, b) = (p.to_vec(), q.clone(), a.clone(), b.clone());
        let rows = rows.map(<[usize]>::to_vec);
        std::panic::catch_unwind(move || {
            let mut c = vec![0.0f32; 100];
            f32::gather_gemm(GatherGemm {
                a: &a,
                p: &p,
                q: &q,
                b: &b,
                ldb: 8,
                n: 8,
                c: &mut c,
                ldc: 8,
                c_rows: rows.as_deref(),
                init: Init::Zero,
                relu: false,
            })
        })
        .map_err(|e| {
            // A literal message comes as `&str`, a formatted one as `String`.
            e.downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| e.downcast_ref::<String>().cloned())
                .unwrap_or_default()
        })
    };
    assert!(run(&p, None).is_ok());
    // The largest offset is the last row's start plus the last step: 16 + 3 < 40; one row
    // starting at 37 would read a[40].
    let mut far = p.clone();
    far[2] = 37;
    assert!(run(&far, None)
        .unwrap_err()
        .contains("A index out of range"));
    far[2] = 36;
    assert!(run(&far, None).is_ok());
    // A start near usize::MAX must not wrap around the check.
    far[2] = usize::MAX - 1;
    assert!(run(&far, None)
        .unwrap_err()
        .contains("A index out of range"));
    let apart = [0, 8, 16, 30, 40];
    assert!(run(&p, Some(&apart)).is_ok());
    for bad in [
        [0, 8, 15, 30, 40],
        [0, 8, 16, 40, 30],
        [0, 8, usize::MAX - 4, 30, 40],
    ] {
        let err = run(&p, Some(&bad)).unwrap_err();
        assert!(err.contains("c_rows overlap or decrease"), "{err}");
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: common::cases(64), ..ProptestConfig::default() })]

    /// `transpose` (16 × 16 register blocks and value-by-value edges on AVX-512, blocks of 64
    /// rows otherwise) moves every value exactly, f32 and f64, for any shape.
    #[test]
    fn transpose_moves_every_value(
        rows in prop_oneof![0usize..40, Just(48), Just(7040)],
        cols in prop_oneof![1usize..40, Just(48), Just(128)],
        seed in any::<u64>(),
    ) {
        fn case<T: Float>(rows: usize, cols: usize, seed: u64) -> Result<(), TestCaseError> {
            let src = uniform::<T>(&[rows * cols], &mut rng(seed));
            let mut dst = vec![T::nan(); rows * cols];
            // f32 on AVX-512 runs the register blocks; f64 (and f32 elsewhere) the plain loop.
            let avx = T::DTYPE == "F32" && avx512_expected();
            if rows > 0 {
                on_path(Family::Transpose, avx, "transpose", || {
                    transpose(src.data(), rows, cols, &mut dst)
                });
            }
            for r in 0..rows {
                for c in 0..cols {
                    let (a, b) = (dst[c * rows + r], src.data()[r * cols + c]);
                    prop_assert!(a == b, "[{}, {}]: {} vs {}", r, c, a, b);
                }
            }
            Ok(())
        }
        case::<f32>(rows, cols, seed)?;
        case::<f64>(rows, cols, seed)?;
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: common::cases(64), ..ProptestConfig::default() })]

    /// `scatter_gemm` (AVX-512 where the host has it, asserted) against
    /// `scatter_gemm_portable`, on tables like a convolution's input gradient: rows added onto
    /// overlapping places of their group's part of the output, through columns that are
    /// consecutive (added in place) or scattered (added through a buffer). With one panel of
    /// columns (n ≤ 64) and one block of steps (≤ 128) both sum each row from zero by fused
    /// multiply-adds in step order and add the rows into the output in row order: bit for bit.
    /// Wider, the AVX-512 kernel adds panel by panel; longer, block by block; those sums are
    /// grouped differently, so there the two agree within twice either one's rounding bound,
    /// `2·γ_N·Σ|terms|` with `N` the additions into one value.
    #[test]
    fn scatter_gemm_matches_its_portable_twin(
        groups in 1usize..4, grows in 1usize..30,
        steps in prop_oneof![0usize..20, Just(128usize), 120usize..140, 250usize..260],
        n in prop_oneof![1usize..=64, 60usize..140], ld_extra in 0usize..3,
        contiguous in any::<bool>(), seed in any::<u64>(),
    ) {
        use rand::Rng;
        let mut r = rng(seed);
        let rows = groups * grows;
        let (ldb, lda) = (n + ld_extra, steps + ld_extra);
        let a = uniform::<f32>(&[(rows * lda).max(1)], &mut r);
        let b = uniform::<f32>(&[(steps * ldb).max(1)], &mut r);
        let mut p = Vec::new();
        fill_iota(&mut p, rows, lda);
        let q: Vec<usize> = (0..steps).collect();
        // The columns' places: consecutive from an offset, or apart by gaps of 1 to 3.
        let out_cols: Vec<usize> = if contiguous {
            let off = r.random_range(0..3);
            (off..off + n).collect()
        } else {
            (0..n).scan(0, |at, _| { *at += r.random_range(1..4); Some(*at) }).collect()
        };
        let span = out_cols[n - 1] + 1;
        let glen = span + 2 * grows;
        let out_rows: Vec<usize> = (0..rows)
            .map(|row| row / grows * glen + r.random_range(0..=glen - span))
            .collect();
        let out0 = uniform::<f32>(&[groups * glen], &mut r);
        let run = |fast: bool| {
            let mut out = out0.data().to_vec();
            let g = ScatterGemm {
                a: a.data(), p: &p, q: &q, b: b.data(), ldb, n, out: &mut out,
                out_rows: &out_rows, out_cols: &out_cols, groups,
            };
            if fast {
                on_path(Family::Scatter, avx512_expected(), "scatter_gemm", || f32::scatter_gemm(g));
            } else {
                scatter_gemm_portable(g);
            }
            out
        };
        let (fast, slow) = (run(true), run(false));
        if n <= 64 && steps <= 128 {
            let same = fast.iter().zip(&slow).all(|(x, y)| x.to_bits() == y.to_bits());
            prop_assert!(same, "one panel, one block: bit for bit");
        }
        // Σ|terms| per output value: the same scatter in f64 on absolute values.
        let abs = |v: &[f32]| v.iter().map(|x| x.abs() as f64).collect::<Vec<f64>>();
        let (aa, ba) = (abs(a.data()), abs(b.data()));
        let mut bound = abs(out0.data());
        scatter_gemm_portable(ScatterGemm {
            a: &aa, p: &p, q: &q, b: &ba, ldb, n, out: &mut bound,
            out_rows: &out_rows, out_cols: &out_cols, groups,
        });
        let mut hits = vec![0usize; groups * glen];
        for &o in &out_rows {
            for &c in &out_cols {
                hits[o + c] += 1;
            }
        }
        let adds = steps + steps.div_ceil(128) + hits.iter().max().unwrap() + 1;
        for (i, ((&x, &y), &s)) in fast.iter().zip(&slow).zip(&bound).enumerate() {
            let d = (x as f64 - y as f64).abs();
            prop_assert!(d <= 2.0 * gamma(adds) * s, "out[{}]: {} vs {} (bound {})", i, x, y, s);
        }
    }
}

/// The plan's Winograd thresholds, on each side: a 3×3 layer (F(2×2, 3×3)) and a 4×4 stride-2
/// one (F(2×2, 2×2) over 2×2 blocks), built as the network builds them
/// (`with_winograd(plan::winograd_pays(g))`), run Winograd at `WINOGRAD_MIN_BATCH` images with
/// `WINOGRAD_MIN_INPUT_CHANNELS` input channels, on the transforms of the host's family
/// (forward, weight and input gradients), and the gather GEMM one image or one channel under
/// either: f32 on an AVX-512 or AVX2 host. Elsewhere every case takes im2col and no transform
/// runs. The products at
/// either side of the batch threshold agree to rounding. A threshold that always fell back to
/// the direct product, or one off by one, fails here.
#[test]
fn winograd_thresholds_choose_the_kernel() {
    let avx = avx512_expected();
    let (batch, chans) = (plan::WINOGRAD_MIN_BATCH, plan::WINOGRAD_MIN_INPUT_CHANNELS);
    let mut r = rng(5);
    for (k, s, kind) in [(3, 1, WinogradKind::F2x3), (4, 2, WinogradKind::S2d(2))] {
        for cin in [chans - 1, chans] {
            let g = ConvGeom::new(8, 8, cin, 16, k, k, (s, s), Padding::Valid).unwrap();
            assert_eq!(plan::winograd_pays(&g), cin >= chans, "{cin} channels");
            let mut layer = Conv2d::<f32>::new("w", g).with_winograd(plan::winograd_pays(&g));
            for p in layer.params_mut() {
                let t = uniform::<f32>(p.value.shape(), &mut r);
                p.value.data_mut().copy_from_slice(t.data());
            }
            let x = uniform::<f32>(&[batch, 8, 8, cin], &mut r);
            let fewer = Tensor::from_vec(
                &[batch - 1, 8, 8, cin],
                x.data()[..(batch - 1) * 64 * cin].to_vec(),
            );
            let mut outputs = Vec::new();
            for x in [&fewer, &x] {
                let n = x.batch();
                let fast = avx || avx2_expected();
                let wino = fast && cin >= chans && n >= batch;
                let want = match (fast, wino) {
                    (false, _) => Kernel::Im2col,
                    (true, true) => Kernel::Winograd(kind),
                    (true, false) => Kernel::Gather,
                };
                let what = format!("{k}×{k}/{s}, {cin} channels, batch {n}");
                let dy = uniform::<f32>(&[n, g.oh, g.ow, 16], &mut r);
                let run = |layer: &mut Conv2d<f32>| {
                    layer.forward(x);
                    let y = layer.output().data().to_vec();
                    layer.backward(x, &dy, true);
                    y
                };
                let y = if wino {
                    on_path(Family::WinogradOutput, avx, &what, || {
                        on_path(Family::WinogradInput, avx, &what, || run(&mut layer))
                    })
                } else {
                    let before = invaders::tensor::cpu::paths(Family::WinogradInput);
                    let y = run(&mut layer);
                    let after = invaders::tensor::cpu::paths(Family::WinogradInput);
                    assert_eq!(after, before, "{what}: no Winograd transform");
                    y
                };
                assert_eq!(plan::last(Product::ConvForward), Some(want), "{what}");
                assert_eq!(plan::last(Product::ConvWeightGrad), Some(want), "{what}");
                outputs.push(y);
            }
            let (few, all) = (&outputs[0], &outputs[1]);
            let scale = 1.0 + all.iter().fold(0.0f32, |m, v| m.max(v.abs()));
            for (i, (a, b)) in few.iter().zip(all).enumerate() {
                assert!((a - b).abs() <= 1e-5 * scale, "[{i}]: {a} vs {b}");
            }
        }
    }
}
