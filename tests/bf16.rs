//! The bf16 products (issue 19) against their references: the AVX512-BF16 dot product against
//! the same rounded operands summed in index order, and against the exact f64 dot product of the
//! f32 inputs, each to the bound derived in `invaders::tensor::bf16`.

mod common;

use common::{
    abs64, bf16_expected, conv_and_dense_passes, dense_pass, f64s, on_exactly, on_path,
    padded_input, reference_forward, reference_grads, rng, same_on_1_2_3_threads, set_params,
    uniform, Square,
};
use invaders::layers::{Conv2d, Dense, Layer};
use invaders::ops::plan::{self, Kernel, Precision, Product};
use invaders::tensor::bf16::to_bf16;
use invaders::tensor::bf16::{dot_bf16, dot_bf16_reference, dot_error_bound, round_bf16};
use invaders::tensor::cpu::{Family, Path};
use invaders::tensor::gather_bf16::{pack_pairs, pack_shifted, pair_shifted, to_bf16_vec};
use invaders::tensor::{gather_gemm_bf16, gather_gemm_bf16_portable, GatherGemmBf16, Init};
use invaders::tensor::{ConvGeom, Padding, Tensor};
use proptest::prelude::*;
use rand::Rng;

/// Whether this host runs the bf16 gather GEMM on AMX tiles: only where the AVX512-BF16 loops
/// run ([`bf16_expected`]), the CPU has AMX-TILE and AMX-BF16 (CPUID leaf 7, EDX bits 24 and
/// 22) and `INVADERS_NO_AMX` is unset; there the library also needs the operating system's
/// consent (XCR0, Linux's `arch_prctl` permission), which an older kernel, a VM or a sandbox
/// may withhold, and then keeps `vdpbf16ps` (said once).
fn amx_expected() -> bool {
    #[cfg(target_arch = "x86_64")]
    let has = {
        let edx = std::arch::x86_64::__cpuid_count(7, 0).edx;
        edx & (1 << 24) != 0 && edx & (1 << 22) != 0
    };
    #[cfg(not(target_arch = "x86_64"))]
    let has = false;
    let could = bf16_expected() && has && std::env::var_os("INVADERS_NO_AMX").is_none();
    let on = invaders::tensor::cpu::amx();
    assert!(could || !on, "the library runs AMX tiles where it must not");
    if could && !on {
        static NOTE: std::sync::Once = std::sync::Once::new();
        NOTE.call_once(|| {
            eprintln!("note: the CPU has AMX but the OS withholds the tiles: vdpbf16ps is tested")
        });
    }
    on
}

/// The loop the bf16 gather GEMM runs here: AMX, AVX512-BF16 (recorded as the AVX-512 loop) or
/// the portable one.
fn gather_path() -> Path {
    if amx_expected() {
        Path::Amx
    } else if bf16_expected() {
        Path::Avx512
    } else {
        Path::Portable
    }
}

/// A value in (−2^6, 2^6) with its magnitude spread over twelve binades.
fn draw(r: &mut impl Rng) -> f32 {
    let mag = 2f32.powi(r.random_range(-6..6));
    r.random_range(-1.0f32..1.0) * mag
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(common::cases(96)))]

    /// `dot_bf16` on random lengths (tails of every size below 32) and values spread over twelve
    /// binades, with the path it ran asserted. Against the reference (the same products, summed
    /// in another order) it must agree to `k·2^−24·Σ|a_i·b_i|`, which a single misplaced term
    /// (a product of the order of `Σ/k`, far above that) breaks; against the exact f64 dot
    /// product of the unrounded inputs, to `dot_error_bound`.
    #[test]
    fn dot_matches_its_references(k in 1usize..700, seed in any::<u64>()) {
        let mut r = rng(seed);
        let a: Vec<f32> = (0..k).map(|_| draw(&mut r)).collect();
        let b: Vec<f32> = (0..k).map(|_| draw(&mut r)).collect();
        let fast = on_path(Family::Bf16, bf16_expected(), "dot_bf16", || dot_bf16(&a, &b));
        let slow = dot_bf16_reference(&a, &b);
        let abs_rounded: f64 = a
            .iter()
            .zip(&b)
            .map(|(&x, &y)| f64::from((round_bf16(x) * round_bf16(y)).abs()))
            .sum();
        let order = 2.0 * k as f64 * 2f64.powi(-24) * abs_rounded;
        prop_assert!(
            (f64::from(fast) - f64::from(slow)).abs() <= order,
            "k {}: {} vs reference {} (bound {})", k, fast, slow, order
        );
        let exact: f64 = a.iter().zip(&b).map(|(&x, &y)| f64::from(x) * f64::from(y)).sum();
        let abs: f64 = a.iter().zip(&b).map(|(&x, &y)| (f64::from(x) * f64::from(y)).abs()).sum();
        let bound = dot_error_bound(k, abs);
        prop_assert!(
            (f64::from(fast) - exact).abs() <= bound,
            "k {}: {} vs exact {} (bound {})", k, fast, exact, bound
        );
    }
}

/// A value of any kind the packing must round: normal over many binades, subnormal, zero and
/// infinity of either sign, quiet and signalling NaNs of either sign, and values halfway between
/// two bf16 values (ties to even).
fn any_f32(r: &mut impl Rng) -> f32 {
    let sign = |r: &mut dyn rand::RngCore| if r.random::<bool>() { 0x8000_0000 } else { 0 };
    match r.random_range(0..8) {
        0 => f32::from_bits(r.random_range(1..0x0080_0000) | sign(r)), // subnormal
        1 => [0.0, -0.0, f32::INFINITY, f32::NEG_INFINITY][r.random_range(0..4)],
        2 => f32::from_bits(0x7F80_0000 | r.random_range(1..0x0080_0000) | sign(r)), // NaN
        3 => f32::from_bits((r.random::<u32>() & 0xFFFF_0000) | 0x8000),             // a tie
        _ => draw(r),
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(common::cases(64)))]

    /// `pack_pairs`, `pack_shifted` and `pair_shifted` (written a pair word at a time so that they run wide)
    /// against their definitions, element by element with `to_bf16`: odd row counts, row strides
    /// above the width, shifts from 0 past the end, and every kind of value.
    #[test]
    fn packing_matches_its_definition(
        rows in 0usize..9,
        cols in 1usize..40,
        pad in 0usize..5,
        d in 0usize..300,
        seed in any::<u64>(),
    ) {
        let mut r = rng(seed);
        let ld = cols + pad;
        let src: Vec<f32> = (0..rows * ld).map(|_| any_f32(&mut r)).collect();
        let mut packed = Vec::new();
        let pairs = pack_pairs(&src, rows, cols, ld, &mut packed);
        prop_assert_eq!(pairs, rows.div_ceil(2));
        prop_assert_eq!(packed.len(), 2 * pairs * cols);
        for u in 0..pairs {
            for j in 0..cols {
                for k in 0..2 {
                    let row = 2 * u + k;
                    let want = if row < rows { to_bf16(src[row * ld + j]) } else { 0 };
                    prop_assert_eq!(packed[2 * (u * cols + j) + k], want, "pair {} col {}", u, j);
                }
            }
        }
        let mut shifted = vec![7u16; 3]; // a used buffer of another length
        pack_shifted(&src, d, &mut shifted);
        prop_assert_eq!(shifted.len(), 2 * src.len());
        for i in 0..src.len() {
            let partner = src.get(i + d).map_or(0, |&v| to_bf16(v));
            prop_assert_eq!(shifted[2 * i], to_bf16(src[i]), "value {}", i);
            prop_assert_eq!(shifted[2 * i + 1], partner, "partner of {}", i);
        }
        // Pairing the values once rounded gives the same bits.
        let rounded: Vec<u16> = src.iter().map(|&x| to_bf16(x)).collect();
        let mut paired = vec![7u16; 5];
        pair_shifted(&rounded, d, &mut paired);
        prop_assert_eq!(paired, shifted);
    }
}

/// Values that are already bf16 multiply exactly: a dot product of small integers is exact on
/// every path, whatever the order of the sums.
#[test]
fn exact_operands_give_exact_sums() {
    let a: Vec<f32> = (0..77).map(|i| (i % 13) as f32 - 6.0).collect();
    let b: Vec<f32> = (0..77).map(|i| (i % 7) as f32 - 3.0).collect();
    let want: f32 = a.iter().zip(&b).map(|(x, y)| x * y).sum();
    let got = on_path(Family::Bf16, bf16_expected(), "dot_bf16", || {
        dot_bf16(&a, &b)
    });
    assert_eq!(got, want);
    // Rounding reaches the operands: 1 + 2^-8 becomes 1, so the product is 1, not 1 + 2^-8.
    assert_eq!(dot_bf16(&[1.0 + 2f32.powi(-8)], &[1.0]), 1.0);
}

/// A random bf16 gather GEMM: a convolution-like gather (rows start at scattered offsets, pair
/// steps in runs) with a bordered `C` through `c_rows`, one of the three starts and the ReLU.
struct Case {
    a: Vec<f32>,
    p: Vec<usize>,
    q: Vec<usize>,
    w: Vec<f32>,
    pairs: usize,
    n: usize,
    bias: Vec<f32>,
    c0: Vec<f32>,
    c_rows: Vec<usize>,
    init: u8,
    relu: bool,
}

impl Case {
    fn draw(rows: usize, pairs: usize, n: usize, seed: u64) -> Case {
        let mut r = rng(seed);
        // Row offsets: scattered, or one pair apart (a weight gradient's rows: the patch's
        // elements, one pair word each, which AMX's kernel reads across the rows).
        let p: Vec<usize> = if r.random_range(0..2) == 1 {
            let first = r.random_range(0..4);
            (0..rows).map(|i| first + 2 * i).collect()
        } else {
            (0..rows).map(|i| i * 3 + r.random_range(0..4)).collect()
        };
        // Pair offsets: runs of consecutive pairs with gaps, as a convolution's patch rows (runs
        // of 16 and 32 as a pixel's channels in conv2 and conv3: whole rows of an AMX tile).
        let run = [5, 16, 32][r.random_range(0..3)];
        let q: Vec<usize> = (0..pairs).map(|u| 2 * u + 4 * (u / run)).collect();
        // Room for the farthest pair's second value, and a little more.
        let len = p.iter().max().unwrap() + q.iter().max().unwrap() + 2 + r.random_range(0..3);
        let a: Vec<f32> = (0..len).map(|_| draw(&mut r)).collect();
        let w: Vec<f32> = (0..2 * pairs * n).map(|_| draw(&mut r)).collect();
        let bias: Vec<f32> = (0..n).map(|_| draw(&mut r)).collect();
        // Rows of C with a gap of 3 between them (a border).
        let c_rows: Vec<usize> = (0..rows).map(|i| i * (n + 3) + 1).collect();
        let c0: Vec<f32> = (0..rows * (n + 3) + 2).map(|_| draw(&mut r)).collect();
        Case {
            a,
            p,
            q,
            w,
            pairs,
            n,
            bias,
            c0,
            c_rows,
            init: r.random_range(0..3),
            relu: r.random_range(0..2) == 1,
        }
    }

    /// Runs the product with `f` (the kernel under test or the portable loops).
    fn run(&self, f: impl FnOnce(GatherGemmBf16<'_>)) -> Vec<f32> {
        let mut a16 = Vec::new();
        to_bf16_vec(&self.a, &mut a16);
        let mut b16 = Vec::new();
        pack_pairs(&self.w, 2 * self.pairs, self.n, self.n, &mut b16);
        let mut c = self.c0.clone();
        f(GatherGemmBf16 {
            a: &a16,
            p: &self.p,
            q: &self.q,
            b: &b16,
            ldb: self.n,
            n: self.n,
            c: &mut c,
            ldc: 0,
            c_rows: Some(&self.c_rows),
            init: match self.init {
                0 => Init::Zero,
                1 => Init::Accumulate,
                _ => Init::Bias(&self.bias),
            },
            relu: self.relu,
        });
        c
    }

    /// The exact product of the unrounded operands (f64) and its bound per element, in the
    /// layout of `c`; places outside the rows keep `c0`.
    fn exact(&self) -> (Vec<f64>, Vec<f64>) {
        let mut want: Vec<f64> = self.c0.iter().map(|&v| f64::from(v)).collect();
        let mut bound = vec![0.0; want.len()];
        let k = 2 * self.pairs;
        for (r, &pr) in self.p.iter().enumerate() {
            for j in 0..self.n {
                let start = match self.init {
                    0 => 0.0,
                    1 => f64::from(self.c0[self.c_rows[r] + j]),
                    _ => f64::from(self.bias[j]),
                };
                let (mut s, mut abs) = (start, start.abs());
                for (u, &qu) in self.q.iter().enumerate() {
                    for e in 0..2 {
                        let t = f64::from(self.a[pr + qu + e])
                            * f64::from(self.w[(2 * u + e) * self.n + j]);
                        s += t;
                        abs += t.abs();
                    }
                }
                let at = self.c_rows[r] + j;
                want[at] = if self.relu { s.max(0.0) } else { s };
                bound[at] = dot_error_bound(k + 1, abs);
            }
        }
        (want, bound)
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(common::cases(64)))]

    /// The bf16 gather GEMM on random shapes (1 to 40 rows, so full and partial row tiles; 1 to
    /// 150 columns, so one to three 64-column panels with masked tails; 1 to 600 pairs, so
    /// one to three 256-pair blocks), with the path asserted:
    /// - against the exact f64 product of the unrounded operands, to the derived bound
    ///   (`dot_error_bound` with the start counted as one more term);
    /// - against the portable loops: bit for bit where AVX512-BF16 ran (the same additions in
    ///   the same order, `vdpbf16ps`'s). On AMX tiles (`tdpbf16ps` adds sixteen pairs in the
    ///   hardware's own order) the bound alone holds; `.ci/run` runs these tests again with
    ///   `INVADERS_NO_AMX=1`, so an AMX host checks the AVX512-BF16 kernel's bits too.
    #[test]
    fn gather_gemm_bf16_matches_its_references(
        rows in 1usize..40, pairs in 1usize..600, n in 1usize..150, seed in any::<u64>()
    ) {
        let case = Case::draw(rows, pairs, n, seed);
        let fast = case.run(|g| {
            on_exactly(Family::Bf16, gather_path(), "gather_gemm_bf16", || gather_gemm_bf16(g))
        });
        let (want, bound) = case.exact();
        for (i, ((&f, &w), &b)) in fast.iter().zip(&want).zip(&bound).enumerate() {
            prop_assert!((f64::from(f) - w).abs() <= b, "at {}: {} vs exact {} (bound {})", i, f, w, b);
        }
        let slow = case.run(gather_gemm_bf16_portable);
        if gather_path() == Path::Avx512 {
            let same = fast.iter().zip(&slow).all(|(x, y)| x.to_bits() == y.to_bits());
            prop_assert!(same, "AVX512-BF16 and the portable loops differ in bits");
        }
    }
}

/// The same bits on 1, 2 and 3 threads (each element summed in pair order, whatever the split),
/// for rows scattered and rows one pair apart (the AMX kernel reads those two ways).
#[test]
fn gather_gemm_bf16_is_the_same_on_any_thread_count() {
    for seed in 5..9 {
        let case = Case::draw(301, 600, 70, seed);
        same_on_1_2_3_threads(|| case.run(gather_gemm_bf16));
    }
}

/// `|got − want| ≤ bound` element by element, naming the first that fails.
fn within_bounds(
    what: &str, got: &[f32], want: &[f64], bound: &[f64],
) -> Result<(), TestCaseError> {
    prop_assert_eq!(got.len(), want.len(), "{}: lengths", what);
    for (i, ((&g, &w), &b)) in got.iter().zip(want).zip(bound).enumerate() {
        prop_assert!(
            (f64::from(g) - w).abs() <= b,
            "{}[{}]: {} vs exact {} (bound {})",
            what,
            i,
            g,
            w,
            b
        );
    }
    Ok(())
}

/// A convolution in bf16 on an input that arrives padded (read in place, as conv2 and conv3
/// read theirs): forward, weight gradient and input gradient against the exact products of the
/// unrounded operands (f64), each element to `dot_error_bound` of its own `Σ|terms|` (the same
/// products of absolute values), with the kernels asserted.
#[allow(clippy::too_many_arguments)]
fn conv_case(c: Square, n: usize, seed: u64) -> Result<(), TestCaseError> {
    let g = c.geom(true);
    let Square {
        k, h, w, cin, cout, ..
    } = c;
    let mut r = rng(seed);
    let mut layer = Conv2d::<f32>::new("c", g);
    layer.set_precision(Precision::Bf16);
    let wt = uniform::<f32>(&[k, k, cin, cout], &mut r);
    let bt = uniform::<f32>(&[cout], &mut r);
    set_params(&mut layer, &[&wt, &bt]);
    let x = uniform::<f32>(&[n, h, w, cin], &mut r);
    let xp = padded_input(&g, n, &x);
    let valid = g.as_valid().0;
    let dy = uniform::<f32>(&[n, g.oh, g.ow, cout], &mut r);
    let bf16 = bf16_expected();
    layer.forward(&xp);
    layer.backward(&xp, &dy, true);
    let expect = |p: Product, k: Kernel| {
        if bf16 {
            prop_assert_eq!(plan::last(p), Some(k), "{:?}", p);
        } else {
            prop_assert_ne!(plan::last(p), Some(k), "{:?} without AVX512-BF16", p);
        }
        Ok(())
    };
    if (k * cin).is_multiple_of(2) {
        expect(Product::ConvForward, Kernel::GatherBf16)?;
    }
    if g.ow.is_multiple_of(2) {
        expect(Product::ConvWeightGrad, Kernel::GatherBf16)?;
    }
    if cout.is_multiple_of(2) {
        expect(Product::ConvInputGrad, Kernel::PhasesBf16)?;
    }
    // The exact products, and the same over absolute values (the bounds' Σ|terms|).
    let (x64, w64, b64, dy64) = (
        f64s(xp.data()),
        f64s(wt.data()),
        f64s(bt.data()),
        f64s(dy.data()),
    );
    let (xa, wa, ba, dya) = (
        abs64(xp.data()),
        abs64(wt.data()),
        abs64(bt.data()),
        abs64(dy.data()),
    );
    let y = reference_forward(&valid, n, &x64, &w64, &b64, false);
    let ya = reference_forward(&valid, n, &xa, &wa, &ba, false);
    let terms = (k * k * cin).max(n * g.oh * g.ow).max(k * k * cout) + 1;
    let bound = |abs: &[f64]| {
        abs.iter()
            .map(|&a| dot_error_bound(terms, a))
            .collect::<Vec<_>>()
    };
    within_bounds("y", layer.output().data(), &y, &bound(&ya))?;
    let (dx, dw, _) = reference_grads(&valid, n, &x64, &w64, &dy64);
    let (dxa, dwa, _) = reference_grads(&valid, n, &xa, &wa, &dya);
    within_bounds("dw", layer.params()[0].grad.data(), &dw, &bound(&dwa))?;
    within_bounds("dx", layer.input_grad().data(), &dx, &bound(&dxa))?;
    // The same convolution on the unpadded input: the layer pads a copy, whose bf16 rounding
    // the weight gradient pairs. After a pass at another batch size, so that every buffer is
    // reused at a new size without being cleared.
    let x1 = uniform::<f32>(&[n + 1, h, w, cin], &mut r);
    let dy1 = uniform::<f32>(&[n + 1, g.oh, g.ow, cout], &mut r);
    layer.forward(&x1);
    layer.backward(&x1, &dy1, true);
    layer.params_mut()[0].grad.fill_zero();
    layer.forward(&x);
    layer.backward(&x, &dy, true);
    within_bounds(
        "y, padded by the layer",
        layer.output().data(),
        &y,
        &bound(&ya),
    )?;
    within_bounds(
        "dw, padded by the layer",
        layer.params()[0].grad.data(),
        &dw,
        &bound(&dwa),
    )?;
    Ok(())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(common::cases(24)))]

    /// Random convolutions in bf16 (filters 1–4, strides 1–2, odd and even channel counts and
    /// widths, so that each product takes bf16 where its pairs exist and f32 where not).
    #[test]
    fn conv_in_bf16_matches_the_exact_products(
        k in 1usize..5, s in 1usize..3, h in 3usize..12, w in 3usize..12,
        cin in 1usize..9, cout in 1usize..40, n in 1usize..4, seed in any::<u64>()
    ) {
        conv_case(Square { k, s, h, w, cin, cout }, n, seed)?;
    }
}

/// The article's three convolutions at their shapes, in bf16.
#[test]
fn article_convolutions_in_bf16_match_the_exact_products() {
    for (i, (h, w, cin, cout, k, s)) in common::ARTICLE_CONVS.into_iter().enumerate() {
        conv_case(
            Square {
                k,
                s,
                h,
                w,
                cin,
                cout,
            },
            3,
            i as u64,
        )
        .unwrap();
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(common::cases(32)))]

    /// A dense layer in bf16 (even and odd widths and batches; with and without its fused
    /// ReLU; batches whose input gradient runs on `W` in place and on `Wᵀ`): `y`, `dW` and `dX`
    /// against the exact products, to the derived bound.
    #[test]
    fn dense_in_bf16_matches_the_exact_products(
        ni in 1usize..200, no in 1usize..80, n in 1usize..40, relu in any::<bool>(),
        seed in any::<u64>()
    ) {
        let (layer, [wt, bt, x, dy]) = dense_pass(ni, no, n, relu, Precision::Bf16, &mut rng(seed));
        let y_layer = layer.output().data().to_vec();
        // With a ReLU, `dY` where the layer's output is positive (the mask it applied).
        let dy = if relu {
            let masked = dy.data().iter().zip(&y_layer).map(|(&g, &y)| if y > 0.0 { g } else { 0.0 });
            Tensor::from_vec(&[n, no], masked.collect())
        } else {
            dy
        };
        let even = ni.is_multiple_of(2) && no.is_multiple_of(2);
        let want = if bf16_expected() && even { Some(Kernel::GatherBf16) } else { plan::last(Product::DenseForward).filter(|&k| k != Kernel::GatherBf16) };
        prop_assert_eq!(plan::last(Product::DenseForward), want);
        prop_assert_eq!(plan::last(Product::DenseBackward), want);
        let (xs, ws, dys) = (x.data(), wt.data(), dy.data());
        let terms = ni.max(no).max(n) + 1;
        let (mut y, mut ya) = (vec![0.0; n * no], vec![0.0; n * no]);
        let (mut dw, mut dwa) = (vec![0.0; ni * no], vec![0.0; ni * no]);
        let (mut dx, mut dxa) = (vec![0.0; n * ni], vec![0.0; n * ni]);
        for s in 0..n {
            for j in 0..no {
                let (mut t, mut ta) = (f64::from(bt.data()[j]), f64::from(bt.data()[j]).abs());
                for i in 0..ni {
                    let v = f64::from(xs[s * ni + i]) * f64::from(ws[i * no + j]);
                    t += v;
                    ta += v.abs();
                    let g = f64::from(xs[s * ni + i]) * f64::from(dys[s * no + j]);
                    dw[i * no + j] += g;
                    dwa[i * no + j] += g.abs();
                    let d = f64::from(dys[s * no + j]) * f64::from(ws[i * no + j]);
                    dx[s * ni + i] += d;
                    dxa[s * ni + i] += d.abs();
                }
                // A ReLU moves a value no farther from the exact one's ReLU.
                y[s * no + j] = if relu { t.max(0.0) } else { t };
                ya[s * no + j] = ta;
            }
        }
        let bound = |abs: &[f64]| abs.iter().map(|&a| dot_error_bound(terms, a)).collect::<Vec<_>>();
        within_bounds("y", layer.output().data(), &y, &bound(&ya))?;
        within_bounds("dw", layer.params()[0].grad.data(), &dw, &bound(&dwa))?;
        within_bounds("dx", layer.input_grad().data(), &dx, &bound(&dxa))?;
    }
}

/// A tensor keeps its values' bf16 roundings from `write_with_bf16` (or `keep_bf16`), a write
/// starting from the roundings of the values as they are, until any other mutable access drops
/// them; a clone keeps them too.
#[test]
fn a_tensor_keeps_its_bf16_roundings_until_it_changes() {
    let mut r = rng(5);
    let rounded = |t: &Tensor<f32>| t.data().iter().map(|&v| to_bf16(v)).collect::<Vec<u16>>();
    let mut t = uniform::<f32>(&[3, 7], &mut r);
    assert!(t.bf16().is_none(), "none at first");
    t.keep_bf16();
    assert_eq!(t.bf16(), Some(&rounded(&t)[..]));
    t.write_with_bf16(|x, x16| {
        x[4] = 2.5;
        x16[4] = to_bf16(2.5);
    });
    assert_eq!(
        t.bf16(),
        Some(&rounded(&t)[..]),
        "one value written both ways"
    );
    assert_eq!(t.clone().bf16(), Some(&rounded(&t)[..]), "a clone");
    type Change = fn(&mut Tensor<f32>);
    let drops: [(&str, Change); 5] = [
        ("data_mut", |t| t.data_mut()[0] = 1.0),
        ("view_mut", |t| t.view_mut()[[0, 1]] = 1.0),
        ("fill_zero", |t| t.fill_zero()),
        ("set_shape", |t| t.set_shape(&[7, 3])),
        ("copy_from", |t| t.copy_from(&Tensor::zeros(&[3, 7]))),
    ];
    for (name, change) in drops {
        t.keep_bf16();
        change(&mut t);
        assert!(t.bf16().is_none(), "{name} drops them");
    }
    // A write to a tensor that kept none starts from its values' roundings.
    t.data_mut()
        .copy_from_slice(uniform::<f32>(&[3, 7], &mut r).data());
    let before = rounded(&t);
    t.write_with_bf16(|_, x16| assert_eq!(x16, &before[..]));
    assert_eq!(t.bf16(), Some(&before[..]));
}

/// A dense layer in bf16 packs its weights into pairs once and reuses them until they change:
/// every change made through `params_mut` (a whole new set, one weight edited in place) is seen
/// by the next forward pass, which gives the bits of a fresh layer holding the new weights.
/// (Where the CPU runs no bf16 the f32 kernel runs, which packs nothing, and this holds too.)
#[test]
fn a_dense_layers_packed_weights_follow_its_weights() {
    let (ni, no, n) = (64, 32, 5);
    let mut r = rng(23);
    let x = uniform::<f32>(&[n, ni], &mut r);
    let fresh = |w: &Tensor<f32>, b: &Tensor<f32>| {
        let mut layer = Dense::<f32>::new("d", ni, no);
        layer.set_precision(Precision::Bf16);
        set_params(&mut layer, &[w, b]);
        layer.forward(&x);
        layer.output().data().to_vec()
    };
    let mut layer = Dense::<f32>::new("d", ni, no);
    layer.set_precision(Precision::Bf16);
    let (w1, b) = (
        uniform::<f32>(&[ni, no], &mut r),
        uniform::<f32>(&[no], &mut r),
    );
    set_params(&mut layer, &[&w1, &b]);
    layer.forward(&x);
    let y1 = layer.output().data().to_vec();
    assert_eq!(y1, fresh(&w1, &b), "the first pass");
    layer.forward(&x);
    assert_eq!(layer.output().data(), &y1[..], "the same weights again");
    if bf16_expected() {
        assert_eq!(plan::last(Product::DenseForward), Some(Kernel::GatherBf16));
    }

    // New weights, all of them.
    let w2 = uniform::<f32>(&[ni, no], &mut r);
    set_params(&mut layer, &[&w2, &b]);
    layer.forward(&x);
    let y2 = layer.output().data().to_vec();
    assert_ne!(y2, y1, "new weights, new outputs");
    assert_eq!(y2, fresh(&w2, &b), "a new set of weights");

    // One weight edited in place: row 7, column 3 (only output column 3 changes).
    let mut w3 = w2.clone();
    w3.data_mut()[7 * no + 3] += 4.0;
    layer.params_mut()[0].value.data_mut()[7 * no + 3] += 4.0;
    layer.forward(&x);
    let y3 = layer.output().data().to_vec();
    assert_eq!(y3, fresh(&w3, &b), "one weight edited");
    for (i, (a, b)) in y3.iter().zip(&y2).enumerate() {
        assert_eq!(a != b, i % no == 3, "output {i}: only column 3 changes");
    }
}

/// The layers in bf16 give the same bits on 1, 2 and 3 threads: a convolution reading its input
/// in place (so all three products run in bf16, the input gradient by phases) and a dense layer
/// with an odd batch.
#[test]
fn bf16_layers_are_the_same_on_any_thread_count() {
    same_on_1_2_3_threads(|| {
        let g = ConvGeom::new(24, 22, 32, 64, 4, 4, (2, 2), Padding::Valid).unwrap();
        let conv = Conv2d::<f32>::new("c", g).with_relu();
        let out = conv_and_dense_passes(conv, 7, Precision::Bf16, &mut rng(11));
        let ran = [
            Product::ConvForward,
            Product::ConvWeightGrad,
            Product::ConvInputGrad,
            Product::DenseForward,
            Product::DenseBackward,
        ]
        .map(plan::last);
        if bf16_expected() {
            let k = |k| Some(k);
            let want = [Kernel::GatherBf16, Kernel::GatherBf16, Kernel::PhasesBf16]
                .map(k)
                .into_iter()
                .chain([k(Kernel::GatherBf16); 2])
                .collect::<Vec<_>>();
            assert_eq!(ran.to_vec(), want);
        }
        out
    });
}
