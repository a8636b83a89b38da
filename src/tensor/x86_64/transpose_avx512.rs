//! [`crate::tensor::transpose`] on AVX-512: 16 × 16 blocks transposed in registers.

use std::arch::x86_64::*;

/// A 16 × 16 block transposed in registers: `out[j]` lane `i` is `r[i]` lane `j`.
///
/// Three rounds of shuffles, each pairing what the last one built: `unpacklo/hi` interleave
/// row pairs, `shuffle_ps` makes each 128-bit lane one column's 4 rows, and two rounds of
/// `shuffle_f32x4` gather a column's four 4-row pieces.
#[target_feature(enable = "avx512f")]
#[inline]
pub(crate) fn block(r: [__m512; 16]) -> [__m512; 16] {
    let z = _mm512_setzero_ps();
    // t[2i], t[2i + 1]: rows 2i and 2i + 1 interleaved (low and high pairs of each lane).
    let mut t = [z; 16];
    for i in 0..8 {
        t[2 * i] = _mm512_unpacklo_ps(r[2 * i], r[2 * i + 1]);
        t[2 * i + 1] = _mm512_unpackhi_ps(r[2 * i], r[2 * i + 1]);
    }
    // u[4g + j], lane L: column 4L + j of rows 4g..4g + 4.
    let mut u = [z; 16];
    for g in 0..4 {
        let (a, b, c, d) = (t[4 * g], t[4 * g + 1], t[4 * g + 2], t[4 * g + 3]);
        u[4 * g] = _mm512_shuffle_ps::<0x44>(a, c);
        u[4 * g + 1] = _mm512_shuffle_ps::<0xee>(a, c);
        u[4 * g + 2] = _mm512_shuffle_ps::<0x44>(b, d);
        u[4 * g + 3] = _mm512_shuffle_ps::<0xee>(b, d);
    }
    // v[j]: columns j and j + 8 of rows 0..8 (lanes: j of 0..4, j + 8 of 0..4, j of 4..8,
    // j + 8 of 4..8), v[4 + j] the same for columns j + 4 and j + 12; v[8..] rows 8..16.
    let mut v = [z; 16];
    for j in 0..4 {
        v[j] = _mm512_shuffle_f32x4::<0x88>(u[j], u[4 + j]);
        v[4 + j] = _mm512_shuffle_f32x4::<0xdd>(u[j], u[4 + j]);
        v[8 + j] = _mm512_shuffle_f32x4::<0x88>(u[8 + j], u[12 + j]);
        v[12 + j] = _mm512_shuffle_f32x4::<0xdd>(u[8 + j], u[12 + j]);
    }
    let mut out = [z; 16];
    for j in 0..8 {
        out[j] = _mm512_shuffle_f32x4::<0x88>(v[j], v[8 + j]);
        out[8 + j] = _mm512_shuffle_f32x4::<0xdd>(v[j], v[8 + j]);
    }
    out
}

/// [`crate::tensor::transpose::transpose`] in 16 × 16 blocks, the edges value by value.
///
/// # Safety
/// AVX-512F; `src` and `dst` of `rows · cols` values.
#[target_feature(enable = "avx512f")]
pub unsafe fn transpose(src: &[f32], rows: usize, cols: usize, dst: &mut [f32]) {
    let (rf, cf) = (rows / 16 * 16, cols / 16 * 16);
    for r0 in (0..rf).step_by(16) {
        for c0 in (0..cf).step_by(16) {
            let r: [__m512; 16] = std::array::from_fn(|i| {
                let row = &src[(r0 + i) * cols + c0..][..16];
                _mm512_loadu_ps(row.as_ptr())
            });
            for (j, v) in block(r).into_iter().enumerate() {
                let out = &mut dst[(c0 + j) * rows + r0..][..16];
                _mm512_storeu_ps(out.as_mut_ptr(), v);
            }
        }
    }
    for r in 0..rows {
        let first = if r < rf { cf } else { 0 };
        for c in first..cols {
            dst[c * rows + r] = src[r * cols + c];
        }
    }
}
