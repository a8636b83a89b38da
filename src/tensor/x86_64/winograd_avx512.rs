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

/// [`crate::tensor::bf16::to_bf16`] of 16 lanes, in the top half of each 32-bit lane (the
/// bottom half is garbage): `bits + 0x7FFF + lsb`, or for a NaN its bits with the quiet bit set.
#[inline(always)]
unsafe fn rounded_high(v: __m512) -> __m512i {
    let bits = _mm512_castps_si512(v);
    let lsb = _mm512_and_si512(_mm512_srli_epi32::<16>(bits), _mm512_set1_epi32(1));
    let rounded = _mm512_add_epi32(bits, _mm512_add_epi32(lsb, _mm512_set1_epi32(0x7FFF)));
    let nan = _mm512_cmp_ps_mask::<_CMP_UNORD_Q>(v, v);
    let quiet = _mm512_or_si512(bits, _mm512_set1_epi32(0x0040_0000));
    _mm512_mask_mov_epi32(rounded, nan, quiet)
}

/// [`crate::tensor::bf16::to_bf16`] of 16 lanes, packed.
#[inline(always)]
unsafe fn to_bf16x16(v: __m512) -> __m256i {
    _mm512_cvtepi32_epi16(_mm512_srli_epi32::<16>(rounded_high(v)))
}

/// Stores 16 lanes rounded to bf16 as the `k`th halves of 16 pairs at `p` (`p[2j + k]`), the
/// other halves left as they are.
#[inline(always)]
unsafe fn store_pair_halves(p: *mut u16, v: __m512, k: usize) {
    let r = rounded_high(v);
    if k == 0 {
        _mm512_mask_storeu_epi16(p as *mut _, 0x5555_5555, _mm512_srli_epi32::<16>(r))
    } else {
        _mm512_mask_storeu_epi16(p as *mut _, 0xAAAA_AAAA, r)
    }
}

/// One tile's input transform into pairs of tiles, rounded to bf16 as it is stored: place
/// `ξ`, channel `c` goes to `dst[2·(ξ·stride + c) + k]`, `k` the tile's place in its pair
/// (the weight gradient's `V [ξ, pair, I, 2]`, `dst` starting at the tile's pair). The bits
/// of [`input_tile`] then `pack_pairs_into`.
///
/// # Safety
/// As [`input_tile`]; the CPU also runs AVX-512BW; `k < 2`.
#[target_feature(enable = "avx512f,avx512bw")]
pub(crate) unsafe fn input_tile_pairs(
    s: &WinogradShape, img: &[f32], zeros: &[f32], starts: &[Option<usize>], dst: &mut [u16],
    stride: usize, k: usize,
) {
    let (seg, blk, places) = (s.seg(), s.kind.block(), s.places());
    assert!(
        k < 2 && dst.len() >= 2 * ((places - 1) * stride + blk * seg),
        "input_tile_pairs"
    );
    let dp = dst.as_mut_ptr();
    // SAFETY (of each store): 32 halves from `2·at`, `at ≤ (P − 1)·stride + blk·seg − 16`,
    // inside `dst` (asserted).
    let store = |at: usize, val: __m512| store_pair_halves(dp.add(2 * at), val, k);
    simd::input_tile_with::<__m512>(s, img, zeros, starts, stride, store)
}

/// One tile's output adjoint into pairs of tiles, rounded to bf16 as it is stored: place
/// `ξ`, channel `c` to `dst[2·(ξ·stride + c) + k]` (the weight gradient's `dM [ξ, image,
/// pair, O, 2]`). The bits of [`adjoint_tile`] then `pack_pairs_into`.
///
/// # Safety
/// As [`adjoint_tile`]; the CPU also runs AVX-512BW; `k < 2`.
#[target_feature(enable = "avx512f,avx512bw")]
#[allow(clippy::too_many_arguments)]
pub(crate) unsafe fn adjoint_tile_pairs(
    img: &[f32], at: [Option<usize>; 4], dst: &mut [u16], stride: usize, co: usize, places: usize,
    k: usize,
) {
    assert!(
        k < 2 && dst.len() >= 2 * ((places - 1) * stride + co),
        "adjoint_tile_pairs"
    );
    let dp = dst.as_mut_ptr();
    // SAFETY (of each store): as in `input_tile_pairs`, below `(P − 1)·stride + co`.
    let store = |at: usize, val: __m512| store_pair_halves(dp.add(2 * at), val, k);
    simd::adjoint_tile_with::<__m512>(img, at, stride, co, places, store)
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
