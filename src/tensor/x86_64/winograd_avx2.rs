//! Winograd's transforms for AVX2 and FMA: the portable loops of [`crate::tensor::winograd`]
//! compiled for AVX2, so that each group of 16 channels (`Lanes`) becomes two 256-bit vectors
//! instead of four 128-bit ones. The transforms are additions and subtractions only (and the
//! output's bias and ReLU), which the compiler does not fuse or reorder, so these give the
//! portable loops' bits (checked in the module's tests).

use crate::tensor::winograd::{
    adjoint_tile_portable, input_tile_portable, output_tile_portable, WinogradShape,
};
use crate::tensor::Float;

/// [`input_tile_portable`] for AVX2.
///
/// # Safety
/// The CPU runs AVX2 and FMA.
#[target_feature(enable = "avx2,fma")]
pub(crate) unsafe fn input_tile<T: Float>(
    s: &WinogradShape,
    img: &[T],
    zeros: &[T],
    starts: &[Option<usize>],
    v: &mut [T],
    stride: usize,
) {
    input_tile_portable(s, img, zeros, starts, v, stride)
}

/// [`output_tile_portable`] for AVX2.
///
/// # Safety
/// The CPU runs AVX2 and FMA.
#[target_feature(enable = "avx2,fma")]
pub(crate) unsafe fn output_tile<T: Float>(
    mt: &[T],
    len: usize,
    bias: Option<&[T]>,
    relu: bool,
    img: &mut [T],
    at: &[[Option<usize>; 4]],
    places: usize,
) {
    output_tile_portable(mt, len, bias, relu, img, at, places)
}

/// [`adjoint_tile_portable`] for AVX2.
///
/// # Safety
/// The CPU runs AVX2 and FMA.
#[target_feature(enable = "avx2,fma")]
pub(crate) unsafe fn adjoint_tile<T: Float>(
    img: &[T],
    at: [Option<usize>; 4],
    mt: &mut [T],
    stride: usize,
    co: usize,
    places: usize,
) {
    adjoint_tile_portable(img, at, mt, stride, co, places)
}
