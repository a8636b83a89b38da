//! Winograd's transforms for AVX2 and FMA, 8 channels per 256-bit register: the entry points
//! that compile the width-generic frames of `winograd_simd.rs` for `__m256`. Rows whose channel
//! count is not a multiple of 8 take the portable loops compiled for AVX2.

use super::winograd_simd as simd;
use crate::tensor::winograd::{
    adjoint_tile_portable, input_tile_portable, output_tile_portable, WinogradShape,
};
use crate::tensor::Float;
use std::arch::x86_64::__m256;

/// [`input_tile_portable`] for AVX2 and FMA.
///
/// # Safety
/// The CPU runs AVX2 and FMA; `T` is `f32`; the arguments as [`input_tile_portable`] checks
/// them (every start a block row of `seg` values inside `img`, `zeros` of `seg`, `v` reaching
/// the tile's last place).
#[target_feature(enable = "avx2,fma")]
pub(crate) unsafe fn input_tile<T: Float>(
    s: &WinogradShape, img: &[T], zeros: &[T], starts: &[Option<usize>], v: &mut [T], stride: usize,
) {
    if s.seg().is_multiple_of(8) {
        simd::input_tile::<__m256, T>(s, img, zeros, starts, v, stride)
    } else {
        input_tile_portable(s, img, zeros, starts, v, stride)
    }
}

/// [`output_tile_portable`] for AVX2 and FMA.
///
/// # Safety
/// The CPU runs AVX2 and FMA; `T` is `f32`; `mt` holds `places·co` values, the bias `co`, each
/// destination `len` inside the image.
#[target_feature(enable = "avx2,fma")]
pub(crate) unsafe fn output_tile<T: Float>(
    mt: &[T], len: usize, bias: Option<&[T]>, relu: bool, img: &mut [T], at: &[[Option<usize>; 4]],
    places: usize,
) {
    if len.is_multiple_of(8) {
        simd::output_tile::<__m256, T>(mt, len, bias, relu, img, at, places)
    } else {
        output_tile_portable(mt, len, bias, relu, img, at, places)
    }
}

/// [`adjoint_tile_portable`] for AVX2 and FMA.
///
/// # Safety
/// The CPU runs AVX2 and FMA; `T` is `f32`; every `Some` output holds `co` values inside `img`
/// and `mt` reaches the tile's last place.
#[target_feature(enable = "avx2,fma")]
pub(crate) unsafe fn adjoint_tile<T: Float>(
    img: &[T], at: [Option<usize>; 4], mt: &mut [T], stride: usize, co: usize, places: usize,
) {
    if co.is_multiple_of(8) {
        simd::adjoint_tile::<__m256, T>(img, at, mt, stride, co, places)
    } else {
        adjoint_tile_portable(img, at, mt, stride, co, places)
    }
}
