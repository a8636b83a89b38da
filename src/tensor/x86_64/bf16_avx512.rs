//! The bf16 dot product on AVX512-BF16 (`vcvtne2ps2bf16`, `vdpbf16ps`).

use std::arch::x86_64::*;

/// [`crate::tensor::bf16::dot_bf16`]'s AVX512-BF16 loop: 32 terms per step into 16 f32 lanes, the
/// tail (fewer than 32
/// terms) zero-padded through a masked load, then the 16 lanes summed.
///
/// # Safety
/// The CPU must support AVX-512F and AVX512-BF16.
#[target_feature(enable = "avx512f,avx512bf16")]
pub(crate) unsafe fn dot_bf16(a: &[f32], b: &[f32]) -> f32 {
    let k = a.len();
    let mut acc = _mm512_setzero_ps();
    let mut i = 0;
    // Loads 16 f32 at `p[j..]`, zero past `k` (a masked load reads nothing beyond the mask).
    let load = |p: &[f32], j: usize| -> __m512 {
        let n = k.saturating_sub(j).min(16);
        let mask: __mmask16 = if n == 16 { 0xFFFF } else { (1u16 << n) - 1 };
        // SAFETY: the mask covers only `p[j..j + n]`, inside the slice.
        unsafe { _mm512_maskz_loadu_ps(mask, p.as_ptr().add(j.min(k))) }
    };
    while i < k {
        // Rounds a[i..i + 32] into 16 bf16 pairs: the second argument fills the low half.
        let av = _mm512_cvtne2ps_pbh(load(a, i + 16), load(a, i));
        let bv = _mm512_cvtne2ps_pbh(load(b, i + 16), load(b, i));
        acc = _mm512_dpbf16_ps(acc, av, bv);
        i += 32;
    }
    _mm512_reduce_add_ps(acc)
}
