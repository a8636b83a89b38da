//! bfloat16: f32's sign and 8-bit exponent with a 7-bit fraction (8 significant bits), the
//! operand format of mixed-precision products (issue 19: AVX512-BF16's `vdpbf16ps`, AMX's
//! `tdpbf16ps`), whose sums stay in f32.
//!
//! A bf16 value is the top half of an f32's bits, so converting back is a shift. Converting to it
//! rounds to nearest, ties to even, as the hardware's `vcvtne2ps2bf16` does: add `0x7FFF` plus
//! the lowest kept bit to the f32's bits, then truncate. That carries into the exponent when the
//! fraction rounds up past its top, which is exactly right (the next binade's first value), and
//! turns the largest finite values into infinity, as rounding must. NaNs stay NaN (quieted).
//!
//! Accuracy: a rounded operand is within a relative `u = 2^−8` of the f32 value (half a unit in
//! the 8th significant bit), so a product of two is within about `2u = 2^−7`; the product itself
//! of two bf16 values is exact in f32 (8 + 8 significant bits ≤ 24). A dot product of `K` terms
//! summed in f32 is then within `(2u + u² + K·2^−24)·Σ|a_i·b_i|` of the exact one
//! ([`dot_error_bound`]): the tolerance the bf16 kernels are checked to.

use super::cpu::{took, Family};

/// The bf16 bits of `x`, rounded to nearest, ties to even.
#[inline]
pub fn to_bf16(x: f32) -> u16 {
    let bits = x.to_bits();
    if x.is_nan() {
        // Keep the sign and the top of the payload; force a quiet NaN.
        return ((bits >> 16) as u16) | 0x0040;
    }
    let lsb = (bits >> 16) & 1;
    (bits.wrapping_add(0x7FFF + lsb) >> 16) as u16
}

/// The f32 value of bf16 bits (exact).
#[inline]
pub fn from_bf16(b: u16) -> f32 {
    f32::from_bits(u32::from(b) << 16)
}

/// `x` rounded to the nearest bf16 value, as f32.
#[inline]
pub fn round_bf16(x: f32) -> f32 {
    from_bf16(to_bf16(x))
}

/// `Σ a_i·b_i` with both operands rounded to bf16 and the exact products summed in f32, in index
/// order: the reference the bf16 kernels are compared with (their sums run in another order, so
/// they agree to `K·2^−24·Σ|a_i·b_i|`, not bit for bit).
pub fn dot_bf16_reference(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len(), "dot: lengths differ");
    a.iter()
        .zip(b)
        .fold(0.0f32, |s, (&x, &y)| s + round_bf16(x) * round_bf16(y))
}

/// `Σ a_i·b_i` with both operands rounded to bf16 (to nearest, ties to even) and the products
/// summed in f32: by AVX512-BF16 where the CPU has it (`vcvtne2ps2bf16` to round 32 values at a
/// time into 16 pairs, `vdpbf16ps` to add each pair's two products into one of 16 f32 sums),
/// else by [`dot_bf16_reference`]. Recorded as [`Family::Bf16`].
pub fn dot_bf16(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len(), "dot: lengths differ");
    #[cfg(target_arch = "x86_64")]
    if took(Family::Bf16, super::cpu::avx512_bf16()) {
        // SAFETY: the CPU has AVX-512F and AVX512-BF16 (checked just above).
        return unsafe { super::x86_64::bf16_avx512::dot_bf16(a, b) };
    }
    #[cfg(not(target_arch = "x86_64"))]
    took(Family::Bf16, false);
    dot_bf16_reference(a, b)
}

/// The bound on `|dot_bf16 − Σ a_i·b_i|` for `k` terms whose products sum to `abs_sum` in
/// absolute value (module documentation): `(2u + u² + k·2^−24)·abs_sum` with `u = 2^−8`.
pub fn dot_error_bound(k: usize, abs_sum: f64) -> f64 {
    let u = 2f64.powi(-8);
    (2.0 * u + u * u + k as f64 * 2f64.powi(-24)) * abs_sum
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rounding_is_to_nearest_even() {
        // 1 + 2^-8 lies halfway between 1 and 1 + 2^-7: ties go to the even one, 1.
        assert_eq!(round_bf16(1.0 + 2f32.powi(-8)), 1.0);
        // 1 + 3·2^-8 lies halfway between 1 + 2^-7 (odd) and 1 + 2^-6 (even): up.
        assert_eq!(round_bf16(1.0 + 3.0 * 2f32.powi(-8)), 1.0 + 2f32.powi(-6));
        // Just above a tie rounds up; just below rounds down.
        assert_eq!(
            round_bf16(1.0 + 2f32.powi(-8) + 2f32.powi(-20)),
            1.0 + 2f32.powi(-7)
        );
        assert_eq!(round_bf16(1.0 + 2f32.powi(-8) - 2f32.powi(-20)), 1.0);
        // A carry into the exponent: the largest value below 2 rounds to 2.
        assert_eq!(round_bf16(2.0 - 2f32.powi(-23)), 2.0);
        // Overflow to infinity, signs, zeros, infinities and NaN.
        assert_eq!(round_bf16(f32::MAX), f32::INFINITY);
        assert_eq!(round_bf16(-3.0), -3.0);
        assert_eq!(to_bf16(-0.0), 0x8000);
        assert_eq!(round_bf16(f32::NEG_INFINITY), f32::NEG_INFINITY);
        assert!(round_bf16(f32::NAN).is_nan());
        // Every bf16 value converts to itself.
        for b in (0..=u16::MAX).step_by(7) {
            let x = from_bf16(b);
            if !x.is_nan() {
                assert_eq!(to_bf16(x), b, "{b:#06x}");
            }
        }
    }

    /// The relative error of one rounding is at most 2^-8 over many binades.
    #[test]
    fn rounding_error_is_half_a_unit_in_the_eighth_bit() {
        let mut x = 1.0e-30f32;
        while x < 1.0e30 {
            for f in [1.0f32, 1.2345, 1.5, 1.999_9] {
                let v = x * f;
                let err = ((round_bf16(v) - v) / v).abs();
                assert!(err <= 2f32.powi(-8), "{v}: {err}");
            }
            x *= 3.7;
        }
    }
}
