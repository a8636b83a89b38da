//! The bf16 products (issue 19) against their references: the AVX512-BF16 dot product against
//! the same rounded operands summed in index order, and against the exact f64 dot product of the
//! f32 inputs, each to the bound derived in `invaders::tensor::bf16`.

mod common;

use common::{avx512_expected, on_path, rng};
use invaders::tensor::bf16::{dot_bf16, dot_bf16_reference, dot_error_bound, round_bf16};
use invaders::tensor::cpu::Family;
use proptest::prelude::*;
use rand::Rng;

/// Whether this host should run the AVX512-BF16 loop: AVX-512 as the other kernels, and
/// AVX512-BF16; says once why not.
fn bf16_expected() -> bool {
    #[cfg(target_arch = "x86_64")]
    let has = is_x86_feature_detected!("avx512bf16");
    #[cfg(not(target_arch = "x86_64"))]
    let has = false;
    let on = avx512_expected() && has;
    if !on && !has {
        static NOTE: std::sync::Once = std::sync::Once::new();
        NOTE.call_once(|| {
            eprintln!("note: this CPU lacks avx512bf16: the bf16 tests check the reference loop")
        });
    }
    assert_eq!(invaders::tensor::cpu::avx512_bf16(), on);
    on
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
