//! Winograd's transforms on AVX-512 ([`crate::tensor::winograd`]), 16 channels per zmm
//! register: the entry points that compile the width-generic frames of `winograd_simd.rs` for
//! `__m512`. `Transforms::choose` sends here only rows whose channel count is a multiple of 16.

use super::winograd_simd as simd;
use crate::tensor::winograd::WinogradShape;
use crate::tensor::Float;
use std::arch::x86_64::*;

/// [`crate::tensor::winograd::input_tile_portable`] on AVX-512.
///
/// # Safety
/// The CPU runs AVX-512F; `T` is `f32`; `seg` is a multiple of 16; every `Some` start is a
/// block row of `seg` values inside `img`, `zeros` holds `seg` and `v` reaches the tile's last
/// place.
#[target_feature(enable = "avx512f")]
pub(crate) unsafe fn input_tile<T: Float>(
    s: &WinogradShape, img: &[T], zeros: &[T], starts: &[Option<usize>], v: &mut [T], stride: usize,
) {
    simd::input_tile::<__m512, T>(s, img, zeros, starts, v, stride)
}

/// [`input_tile`] with each value rounded to bf16 as it is stored, into `vb` laid out as
/// `input_tile`'s `v`: the bits of the f32 transform followed by
/// [`crate::tensor::bf16::to_bf16`] (to nearest even, NaNs quieted), without writing and
/// reading back the f32 values (a separate rounding pass was 10% of conv3's bf16 forward pass).
///
/// # Safety
/// As [`input_tile`], for `vb`.
#[target_feature(enable = "avx512f")]
pub(crate) unsafe fn input_tile_bf16(
    s: &WinogradShape, img: &[f32], zeros: &[f32], starts: &[Option<usize>], vb: &mut [u16],
    stride: usize,
) {
    let (seg, blk, places) = (s.seg(), s.kind.block(), s.places());
    assert!(
        vb.len() >= (places - 1) * stride + blk * seg,
        "input_tile_bf16: vb"
    );
    let vp = vb.as_mut_ptr();
    // SAFETY (of each store): 16 values at `at`, below `(P − 1)·stride + blk·seg − 15`, inside
    // `vb` (asserted; `seg` is a multiple of 16).
    let store =
        |at: usize, val: __m512| _mm256_storeu_si256(vp.add(at) as *mut __m256i, to_bf16x16(val));
    simd::input_tile_with::<__m512>(s, img, zeros, starts, stride, store)
}

/// [`crate::tensor::bf16::to_bf16`] of 16 lanes: `(bits + 0x7FFF + lsb) >> 16`, or for a NaN
/// its top half with the quiet bit set.
#[inline(always)]
unsafe fn to_bf16x16(v: __m512) -> __m256i {
    let bits = _mm512_castps_si512(v);
    let lsb = _mm512_and_si512(_mm512_srli_epi32::<16>(bits), _mm512_set1_epi32(1));
    let rounded = _mm512_add_epi32(bits, _mm512_add_epi32(lsb, _mm512_set1_epi32(0x7FFF)));
    let nan = _mm512_cmp_ps_mask::<_CMP_UNORD_Q>(v, v);
    let quiet = _mm512_or_si512(bits, _mm512_set1_epi32(0x0040_0000));
    let r = _mm512_mask_mov_epi32(rounded, nan, quiet);
    _mm512_cvtepi32_epi16(_mm512_srli_epi32::<16>(r))
}

/// [`crate::tensor::winograd::output_tile_portable`] on AVX-512.
///
/// # Safety
/// The CPU runs AVX-512F; `T` is `f32`; `len` is a multiple of 16; `mt` holds `places·co`
/// values, the bias `co`, each destination `len` inside the image.
#[target_feature(enable = "avx512f")]
pub(crate) unsafe fn output_tile<T: Float>(
    mt: &[T], len: usize, bias: Option<&[T]>, relu: bool, img: &mut [T], at: &[[Option<usize>; 4]],
    places: usize,
) {
    simd::output_tile::<__m512, T>(mt, len, bias, relu, img, at, places)
}

/// [`crate::tensor::winograd::adjoint_tile_portable`] on AVX-512.
///
/// # Safety
/// The CPU runs AVX-512F; `T` is `f32`; `co` is a multiple of 16; every `Some` output holds
/// `co` values inside `img` and `mt` reaches the tile's last place.
#[target_feature(enable = "avx512f")]
pub(crate) unsafe fn adjoint_tile<T: Float>(
    img: &[T], at: [Option<usize>; 4], mt: &mut [T], stride: usize, co: usize, places: usize,
) {
    simd::adjoint_tile::<__m512, T>(img, at, mt, stride, co, places)
}
