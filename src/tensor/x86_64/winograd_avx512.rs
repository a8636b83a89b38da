//! Winograd's transforms on AVX-512 ([`crate::tensor::winograd`]), 16 channels per zmm
//! register: the entry points that compile the width-generic frames of `winograd_simd.rs` for
//! `__m512`. `Transforms::choose` sends here only rows whose channel count is a multiple of 16.

use super::winograd_simd as simd;
use crate::tensor::winograd::WinogradShape;
use crate::tensor::Float;
use std::arch::x86_64::__m512;

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
