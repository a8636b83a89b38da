//! Winograd's minimal filtering with its products in bf16 (`Kernel::WinogradBf16`, issue 100)
//! against the exact convolution of the unrounded operands (f64), by two checks:
//!
//! - **The bound**, element by element. Winograd rounds the transformed input `V = Bᵀ·d·B` and
//!   filter `U = G·g·Gᵀ` to bf16, so each product `M_ξ = Σ_i V_ξ,i·U_ξ,i` is within
//!   `dot_error_bound` of `Σ_i |V_ξ,i·U_ξ,i|`, and the output `Y = Aᵀ·M·A` within the sum of
//!   those weighted by `|A|`. With the transforms taken over absolute values (`|Bᵀ|·|d|·|B|`,
//!   `|G|·|g|·|Gᵀ|`) the same sum also covers the transforms' own f32 roundings, counted among
//!   the bound's terms.
//! - **The size of the error**, which the bound (loose: the absolute transforms add up to
//!   dozens of terms per product) could not see grow from a wrong index: in norm, the error is
//!   at most 4 times the direct bf16 product's on the same operands. Measured 1.7–2.2 times
//!   on these uniform operands, 1.5 times for conv3's shape on a sparse non-negative input
//!   (`tools/winograd_bf16_error.py`); an operand read from a wrong place gives errors the
//!   size of the outputs, hundreds of times the direct product's.

mod common;

use common::{bf16_expected, f64s, reference_forward, reference_grads, rng, set_params};
use common::{uniform, Square};
use invaders::layers::{Conv2d, Layer};
use invaders::ops::plan::{self, Kernel, Precision, Product};
use invaders::tensor::bf16::{dot_error_bound, round_bf16};
use invaders::tensor::{ConvGeom, WinogradKind};
use rand::Rng;

/// A small matrix, by rows.
type Matrix = Vec<Vec<f64>>;

/// Winograd's matrices `(Bᵀ, G, Aᵀ)` for a filter of `k` taps and stride `s` (rows of the
/// 1-D transforms), and the side of its blocks: F(2×2, 3×3) on pixels, or F(2×2, 2×2) on
/// `s × s` blocks.
fn matrices(k: usize, s: usize) -> (Matrix, Matrix, Matrix, usize) {
    let v = |rows: &[&[f64]]| rows.iter().map(|r| r.to_vec()).collect::<Vec<_>>();
    if (k, s) == (3, 1) {
        let bt = v(&[
            &[1., 0., -1., 0.],
            &[0., 1., 1., 0.],
            &[0., -1., 1., 0.],
            &[0., 1., 0., -1.],
        ]);
        let g = v(&[
            &[1., 0., 0.],
            &[0.5, 0.5, 0.5],
            &[0.5, -0.5, 0.5],
            &[0., 0., 1.],
        ]);
        let at = v(&[&[1., 1., 1., 0.], &[0., 1., -1., -1.]]);
        (bt, g, at, 1)
    } else {
        assert_eq!(k, 2 * s, "a 2s × 2s filter of stride s");
        let bt = v(&[&[1., -1., 0.], &[0., 1., 0.], &[0., -1., 1.]]);
        let g = v(&[&[1., 0.], &[1., 1.], &[0., 1.]]);
        let at = v(&[&[1., 1., 0.], &[0., 1., 1.]]);
        (bt, g, at, s)
    }
}

/// The absolute transforms of the VALID convolution `g` (f64, NHWC input, `[k, k, Cin, Cout]`
/// filter) as Winograd runs it, `P × P` places per tile, `ch = b²·Cin` transformed channels.
struct Abs {
    bt: Matrix,
    gm: Matrix,
    at: Matrix,
    blk: usize,
    p: usize,
    ch: usize,
    tiles: (usize, usize),
}

impl Abs {
    fn new(g: &ConvGeom) -> Abs {
        let (bt, gm, at, blk) = matrices(g.kh, g.sh);
        let p = bt.len();
        let tiles = (g.oh.div_ceil(2), g.ow.div_ceil(2));
        Abs {
            bt,
            gm,
            at,
            blk,
            p,
            ch: blk * blk * g.cin,
            tiles,
        }
    }

    fn places(&self) -> impl Iterator<Item = (usize, usize)> + use<> {
        let p = self.p;
        (0..p).flat_map(move |a| (0..p).map(move |b| (a, b)))
    }

    /// `|Bᵀ|·|d|·|B|`: `[image, tile, ξ, c]`, `c = (dy·b + dx)·Cin + i`.
    fn v(&self, g: &ConvGeom, n: usize, x: &[f64]) -> Vec<f64> {
        let (p, ch, ci, blk) = (self.p, self.ch, g.cin, self.blk);
        let (ty, tx) = self.tiles;
        let px = |img: usize, y: usize, xx: usize, i: usize| {
            if y < g.h && xx < g.w {
                x[((img * g.h + y) * g.w + xx) * ci + i].abs()
            } else {
                0.0
            }
        };
        let mut v = vec![0.0; n * ty * tx * p * p * ch];
        for img in 0..n {
            for (ta, tb) in (0..ty).flat_map(|a| (0..tx).map(move |b| (a, b))) {
                let t = (img * ty + ta) * tx + tb;
                for (xy, xx) in self.places() {
                    for c in 0..ch {
                        let (dy, dx, i) = (c / ci / blk, c / ci % blk, c % ci);
                        let mut sum = 0.0;
                        for (jy, jx) in self.places() {
                            let (y, xp) = (blk * (2 * ta + jy) + dy, blk * (2 * tb + jx) + dx);
                            sum +=
                                self.bt[xy][jy].abs() * self.bt[xx][jx].abs() * px(img, y, xp, i);
                        }
                        v[(t * p * p + xy * p + xx) * ch + c] = sum;
                    }
                }
            }
        }
        v
    }

    /// `|G|·|g|·|Gᵀ|`: `[ξ, c, o]`.
    fn u(&self, g: &ConvGeom, w: &[f64]) -> Vec<f64> {
        let (p, ch, ci, co, blk) = (self.p, self.ch, g.cin, g.cout, self.blk);
        let r = self.gm[0].len();
        let mut u = vec![0.0; p * p * ch * co];
        for (xy, xx) in self.places() {
            for c in 0..ch {
                let (dy, dx, i) = (c / ci / blk, c / ci % blk, c % ci);
                for o in 0..co {
                    let mut sum = 0.0;
                    for (my, mx) in (0..r).flat_map(|a| (0..r).map(move |b| (a, b))) {
                        let tap = ((blk * my + dy) * g.kw + blk * mx + dx) * ci + i;
                        sum +=
                            self.gm[xy][my].abs() * self.gm[xx][mx].abs() * w[tap * co + o].abs();
                    }
                    u[((xy * p + xx) * ch + c) * co + o] = sum;
                }
            }
        }
        u
    }

    /// `|A|·|dY|·|Aᵀ|`: `[image, tile, ξ, o]` (zero past the edge).
    fn dm(&self, g: &ConvGeom, n: usize, dy: &[f64]) -> Vec<f64> {
        let (p, co) = (self.p, g.cout);
        let (ty, tx) = self.tiles;
        let mut m = vec![0.0; n * ty * tx * p * p * co];
        for img in 0..n {
            for (ta, tb) in (0..ty).flat_map(|a| (0..tx).map(move |b| (a, b))) {
                let t = (img * ty + ta) * tx + tb;
                for (ky, kx) in [(0, 0), (0, 1), (1, 0), (1, 1)] {
                    let (oy, ox) = (2 * ta + ky, 2 * tb + kx);
                    if oy >= g.oh || ox >= g.ow {
                        continue;
                    }
                    let at = ((img * g.oh + oy) * g.ow + ox) * co;
                    for (xy, xx) in self.places() {
                        let a = self.at[ky][xy].abs() * self.at[kx][xx].abs();
                        for o in 0..co {
                            m[(t * p * p + xy * p + xx) * co + o] += a * dy[at + o].abs();
                        }
                    }
                }
            }
        }
        m
    }
}

/// For every output of the VALID convolution `g` of `n` images `x` by `w` (f64, NHWC and
/// `[k, k, Cin, Cout]`), `|bias| + Σ_ξ |A_ξ|·Σ_c (|Bᵀ|·|d|·|B|)_ξ,c·(|G|·|g|·|Gᵀ|)_ξ,c`: the
/// sum of absolute terms the bf16 Winograd convolution's error is bounded by.
fn winograd_abs(g: &ConvGeom, n: usize, x: &[f64], w: &[f64], bias: &[f64]) -> Vec<f64> {
    let abs = Abs::new(g);
    let (p, ch, co) = (abs.p, abs.ch, g.cout);
    let (ty, tx) = abs.tiles;
    let (v, u) = (abs.v(g, n, x), abs.u(g, w));
    let mut out = vec![0.0; n * g.oh * g.ow * co];
    for img in 0..n {
        for (ta, tb) in (0..ty).flat_map(|a| (0..tx).map(move |b| (a, b))) {
            let t = (img * ty + ta) * tx + tb;
            for (ky, kx) in [(0, 0), (0, 1), (1, 0), (1, 1)] {
                let (oy, ox) = (2 * ta + ky, 2 * tb + kx);
                if oy >= g.oh || ox >= g.ow {
                    continue;
                }
                for o in 0..co {
                    let mut sum = bias[o].abs();
                    for (xy, xx) in abs.places() {
                        let a = abs.at[ky][xy].abs() * abs.at[kx][xx].abs();
                        let place = xy * p + xx;
                        let dot: f64 = (0..ch)
                            .map(|c| v[(t * p * p + place) * ch + c] * u[(place * ch + c) * co + o])
                            .sum();
                        sum += a * dot;
                    }
                    out[((img * g.oh + oy) * g.ow + ox) * co + o] = sum;
                }
            }
        }
    }
    out
}

/// For every weight of the same convolution, the weight gradient's sum of absolute terms:
/// `Σ_ξ |Gᵀ|_ξ·Σ_tiles (|Bᵀ|·|d|·|B|)_ξ,c·(|A|·|dY|·|Aᵀ|)_ξ,o` at the weight's tap.
fn winograd_wgrad_abs(g: &ConvGeom, n: usize, x: &[f64], dy: &[f64]) -> Vec<f64> {
    let abs = Abs::new(g);
    let (p, ch, ci, co, blk) = (abs.p, abs.ch, g.cin, g.cout, abs.blk);
    let tiles = n * abs.tiles.0 * abs.tiles.1;
    let (v, m) = (abs.v(g, n, x), abs.dm(g, n, dy));
    // |dU| [ξ, c, o]
    let mut du = vec![0.0; p * p * ch * co];
    for t in 0..tiles {
        for place in 0..p * p {
            for c in 0..ch {
                let vv = v[(t * p * p + place) * ch + c];
                for o in 0..co {
                    du[(place * ch + c) * co + o] += vv * m[(t * p * p + place) * co + o];
                }
            }
        }
    }
    let r = abs.gm[0].len();
    let mut dw = vec![0.0; g.kh * g.kw * ci * co];
    for (my, mx) in (0..r).flat_map(|a| (0..r).map(move |b| (a, b))) {
        for c in 0..ch {
            let (dy, dx, i) = (c / ci / blk, c / ci % blk, c % ci);
            let tap = ((blk * my + dy) * g.kw + blk * mx + dx) * ci + i;
            for o in 0..co {
                dw[tap * co + o] = abs
                    .places()
                    .map(|(xy, xx)| {
                        abs.gm[xy][my].abs()
                            * abs.gm[xx][mx].abs()
                            * du[((xy * p + xx) * ch + c) * co + o]
                    })
                    .sum();
            }
        }
    }
    dw
}

/// `‖got − want‖₂`.
fn error_norm(got: &[f32], want: &[f64]) -> f64 {
    got.iter()
        .zip(want)
        .map(|(&g, &w)| (f64::from(g) - w).powi(2))
        .sum::<f64>()
        .sqrt()
}

/// What a layer computed: its output, input gradient and weight gradient, and the kernels
/// that ran the three products.
struct Ran {
    y: Vec<f32>,
    dx: Vec<f32>,
    dw: Vec<f32>,
    kernels: [Option<Kernel>; 3],
}

/// A layer of `g` in bf16 with Winograd allowed or not, its parameters set, after a forward
/// and a backward pass.
fn run(
    g: ConvGeom, winograd: bool, params: [&invaders::tensor::Tensor<f32>; 2],
    x: &invaders::tensor::Tensor<f32>, dy: &invaders::tensor::Tensor<f32>,
) -> Ran {
    let mut layer = Conv2d::<f32>::new("c", g).with_winograd(winograd);
    layer.set_precision(Precision::Bf16);
    set_params(&mut layer, &params);
    layer.forward(x);
    layer.backward(x, dy, true);
    let products = [
        Product::ConvForward,
        Product::ConvInputGrad,
        Product::ConvWeightGrad,
    ];
    Ran {
        y: layer.output().data().to_vec(),
        dx: layer.input_grad().data().to_vec(),
        dw: layer.params()[0].grad.data().to_vec(),
        kernels: products.map(plan::last),
    }
}

/// One VALID convolution `c` over `n` images (read in place, as conv2 and conv3 read theirs):
/// the forward pass by bf16 Winograd, and for F(2×2, 3×3) the input gradient too, held to
/// the bound and to the error's size.
fn case(c: Square, n: usize, seed: u64) {
    let g = c.geom(false);
    let mut r = rng(seed);
    let w = uniform::<f32>(&[c.k, c.k, c.cin, c.cout], &mut r);
    let b = uniform::<f32>(&[c.cout], &mut r);
    let x = uniform::<f32>(&[n, g.h, g.w, c.cin], &mut r);
    let dy = uniform::<f32>(&[n, g.oh, g.ow, c.cout], &mut r);
    let wino_run = run(g, true, [&w, &b], &x, &dy);
    let (y, dx, ran) = (&wino_run.y, &wino_run.dx, wino_run.kernels);
    let kind = if c.k == 3 {
        WinogradKind::F2x3
    } else {
        WinogradKind::S2d(c.s)
    };
    let wino = Some(Kernel::WinogradBf16(kind));
    // The input gradient by Winograd pairs dZ's channels; conv2's kind keeps phases.
    let dx_by_winograd = kind == WinogradKind::F2x3 && c.cout.is_multiple_of(2);
    if bf16_expected() {
        assert_eq!(ran[0], wino, "{c:?}: forward");
        assert_eq!(ran[2], wino, "{c:?}: weight gradient");
        if dx_by_winograd {
            assert_eq!(ran[1], wino, "{c:?}: input gradient");
        } else {
            let phases = if c.cout.is_multiple_of(2) {
                Kernel::PhasesBf16
            } else {
                Kernel::Phases
            };
            assert_eq!(ran[1], Some(phases), "{c:?}: input gradient");
        }
    } else {
        assert!(
            ran.iter().all(|&k| k != wino),
            "{c:?}: no bf16 without AVX512-BF16"
        );
    }

    let (x64, w64, b64, dy64) = (
        f64s(x.data()),
        f64s(w.data()),
        f64s(b.data()),
        f64s(dy.data()),
    );
    let exact = reference_forward(&g, n, &x64, &w64, &b64, false);
    let (exact_dx, exact_dw, _) = reference_grads(&g, n, &x64, &w64, &dy64);
    // The direct products of the operands rounded to bf16, exactly: the direct bf16 kernels'
    // error, less their f32 sums' (whichever kernel this shape's direct product would take).
    let r = |t: &invaders::tensor::Tensor<f32>| -> Vec<f64> {
        t.data().iter().map(|&v| f64::from(round_bf16(v))).collect()
    };
    let (xr, wr, dyr) = (r(&x), r(&w), r(&dy));
    let y_direct = reference_forward(&g, n, &xr, &wr, &b64, false);
    let (dx_direct, dw_direct, _) = reference_grads(&g, n, &xr, &wr, &dyr);
    let ref_error = |a: &[f64], b: &[f64]| {
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).powi(2))
            .sum::<f64>()
            .sqrt()
    };
    let ch = if c.k == 3 { c.cin } else { c.s * c.s * c.cin };
    let terms = 16 * ch + 32;
    let abs = winograd_abs(&g, n, &x64, &w64, &b64);
    for (i, ((&got, &want), &a)) in y.iter().zip(&exact).zip(&abs).enumerate() {
        let bound = dot_error_bound(terms, a);
        assert!(
            (f64::from(got) - want).abs() <= bound,
            "{c:?}: y[{i}] = {got}, exact {want}, bound {bound}"
        );
    }
    let (e, e_direct) = (error_norm(y, &exact), ref_error(&y_direct, &exact));
    assert!(
        e <= 4.0 * e_direct + 1e-30,
        "{c:?}: forward error {e:e} against the direct product's {e_direct:e}"
    );
    if bf16_expected() {
        // Rounded operands leave some error (the check above is not vacuous).
        assert!(e > 0.0 && e_direct > 0.0, "{c:?}: no rounding seen");
    }

    // The weight gradient: a sum over every tile of the batch.
    let abs = winograd_wgrad_abs(&g, n, &x64, &dy64);
    let (ty, tx) = (g.oh.div_ceil(2), g.ow.div_ceil(2));
    let terms = n * ty * tx + 64;
    for (i, ((&got, &want), &a)) in wino_run.dw.iter().zip(&exact_dw).zip(&abs).enumerate() {
        let bound = dot_error_bound(terms, a);
        assert!(
            (f64::from(got) - want).abs() <= bound,
            "{c:?}: dw[{i}] = {got}, exact {want}, bound {bound}"
        );
    }
    let (e, e_direct) = (
        error_norm(&wino_run.dw, &exact_dw),
        ref_error(&dw_direct, &exact_dw),
    );
    assert!(
        e <= 4.0 * e_direct + 1e-30,
        "{c:?}: weight gradient error {e:e} against the direct product's {e_direct:e}"
    );

    // The input gradient: the adjoint convolution of dZ padded by 2, filters rotated by 180°
    // with their channel axes swapped, by F(2×2, 3×3).
    let e = error_norm(dx, &exact_dx);
    let e_direct = ref_error(&dx_direct, &exact_dx);
    assert!(
        e <= 4.0 * e_direct + 1e-30,
        "{c:?}: input gradient error {e:e} against the direct product's {e_direct:e}"
    );
    if dx_by_winograd {
        let adj = ConvGeom::new(
            g.oh + 4,
            g.ow + 4,
            c.cout,
            c.cin,
            3,
            3,
            (1, 1),
            invaders::tensor::Padding::Valid,
        )
        .unwrap();
        let mut dzp = vec![0.0; n * adj.h * adj.w * c.cout];
        for img in 0..n {
            for (oy, ox) in (0..g.oh).flat_map(|a| (0..g.ow).map(move |b| (a, b))) {
                let from = ((img * g.oh + oy) * g.ow + ox) * c.cout;
                let to = ((img * adj.h + oy + 2) * adj.w + ox + 2) * c.cout;
                dzp[to..to + c.cout].copy_from_slice(&dy64[from..from + c.cout]);
            }
        }
        let mut wadj = vec![0.0; 9 * c.cin * c.cout];
        for (ky, kx, i, o) in (0..3).flat_map(|ky| {
            (0..3).flat_map(move |kx| {
                (0..c.cin).flat_map(move |i| (0..c.cout).map(move |o| (ky, kx, i, o)))
            })
        }) {
            wadj[((ky * 3 + kx) * c.cout + o) * c.cin + i] =
                w64[(((2 - ky) * 3 + 2 - kx) * c.cin + i) * c.cout + o];
        }
        let abs = winograd_abs(&adj, n, &dzp, &wadj, &vec![0.0; c.cin]);
        let terms = 16 * c.cout + 32;
        for (i, ((&got, &want), &a)) in dx.iter().zip(&exact_dx).zip(&abs).enumerate() {
            let bound = dot_error_bound(terms, a);
            assert!(
                (f64::from(got) - want).abs() <= bound,
                "{c:?}: dx[{i}] = {got}, exact {want}, bound {bound}"
            );
        }
    }
}

/// conv3 (3×3, 64 → 64 over its padded 13 × 12 input) and conv2 (4×4 stride 2, 32 → 64 over
/// its padded 24 × 22 input) at a batch of 8, the least that takes Winograd, and of 20: 5
/// chunks of 4 images for the weight gradient, 2 of them summed in one group.
#[test]
fn the_article_convolutions_by_bf16_winograd_match_the_exact_products() {
    case(
        Square {
            k: 3,
            s: 1,
            h: 13,
            w: 12,
            cin: 64,
            cout: 64,
        },
        8,
        1,
    );
    for k in [3, 4] {
        let (s, h, w, cin) = if k == 3 {
            (1, 13, 12, 64)
        } else {
            (2, 24, 22, 32)
        };
        let cout = 64;
        case(
            Square {
                k,
                s,
                h,
                w,
                cin,
                cout,
            },
            20,
            3,
        );
    }
    case(
        Square {
            k: 4,
            s: 2,
            h: 24,
            w: 22,
            cin: 32,
            cout: 64,
        },
        8,
        2,
    );
}

/// Random shapes: odd and even sizes (tiles cut by the edge), few and many channels (even:
/// the pairs of transformed channels), strides 1 (3×3) and 2 and 3 (2s × 2s).
#[test]
fn random_convolutions_by_bf16_winograd_match_the_exact_products() {
    let mut r = rng(100);
    for seed in 0..common::cases(12) as u64 {
        let (k, s) = [(3, 1), (4, 2), (6, 3)][r.random_range(0..3)];
        let c = Square {
            k,
            s,
            h: r.random_range(k..k + 9),
            w: r.random_range(k..k + 9),
            cin: 2 * r.random_range(1..12),
            cout: r.random_range(1..24),
        };
        case(c, 8 + r.random_range(0..3), seed);
    }
}

/// conv3 and conv2 as the network runs them (read in place, fused ReLU) by bf16 Winograd give
/// the same bits on 1, 2 and 3 threads: each output is summed from its own tile, each product
/// in a fixed order, whatever the split of images and places among threads.
#[test]
fn bf16_winograd_is_the_same_on_any_thread_count() {
    for (h, w, cin, cout, k, s) in [(13, 12, 64, 64, 3, 1), (24, 22, 32, 64, 4, 2)] {
        common::same_on_1_2_3_threads(|| {
            let g = ConvGeom::new(
                h,
                w,
                cin,
                cout,
                k,
                k,
                (s, s),
                invaders::tensor::Padding::Valid,
            )
            .unwrap();
            let conv = Conv2d::<f32>::new("c", g).with_relu().with_winograd(true);
            // 18 images: 5 weight-gradient chunks in 4 groups of 1, 1, 1 and 2 chunks.
            let out = common::conv_and_dense_passes(conv, 18, Precision::Bf16, &mut rng(7));
            if bf16_expected() {
                let kind = if k == 3 {
                    WinogradKind::F2x3
                } else {
                    WinogradKind::S2d(s)
                };
                let wino = Some(Kernel::WinogradBf16(kind));
                assert_eq!(plan::last(Product::ConvForward), wino);
                assert_eq!(plan::last(Product::ConvWeightGrad), wino);
            }
            out
        });
    }
}
