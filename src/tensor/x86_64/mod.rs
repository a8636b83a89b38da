//! The x86-64 kernels, one file per family and instruction set: the AVX-512 families
//! (`*_avx512.rs`; AVX512-BF16 in `bf16_avx512.rs` and `gather_bf16_avx512.rs`, AMX tiles in
//! `gather_bf16_amx.rs`) and the AVX2
//! and FMA family (`*_avx2.rs`) for CPUs without AVX-512 (or with it switched off by
//! `INVADERS_NO_AVX512`). Where the two families differ only in the register's width the code
//! is written once, generic over the f32 vector (`simd.rs`: `__m256` and `__m512`), and each
//! family's file holds only its entry points compiled for its instruction set (Winograd's
//! transforms: `winograd_simd.rs`). `crate::tensor::cpu` says which runs (the family asks it
//! on each call); each kernel's portable twin is
//! in its family's module one level up (`gather.rs`, `winograd/`, …), and the tests check
//! each kernel against it (`tests/kernels.rs`, `tests/sparse.rs`, `tests/bf16.rs`, the Winograd
//! module's tests).

pub(crate) mod acting_avx2;
pub(crate) mod background_avx512;
pub(crate) mod bf16_avx512;
pub(crate) mod gather_avx2;
pub(crate) mod gather_avx512;
pub(crate) mod gather_bf16_amx;
pub(crate) mod gather_bf16_avx512;
pub(crate) mod scatter_avx2;
mod simd;
pub(crate) mod sparse_avx512;
mod sparse_simd;
mod sums;
pub(crate) mod transpose_avx512;
pub(crate) mod winograd_avx2;
pub(crate) mod winograd_avx512;
mod winograd_simd;

use crate::tensor::Float;

/// A slice of `T` known to be `f32` (the f32-only kernels take the generic slices of their
/// callers), as `f32`. `T` must be `f32`: a slice of `f64` would be read as twice as many
/// halves.
fn cast<T: Float>(s: &[T]) -> &[f32] {
    debug_assert!(size_of::<T>() == 4, "an f32 kernel given another type");
    bytemuck::cast_slice(s)
}

/// [`cast`] for a mutable slice.
fn cast_mut<T: Float>(s: &mut [T]) -> &mut [f32] {
    debug_assert!(size_of::<T>() == 4, "an f32 kernel given another type");
    bytemuck::cast_slice_mut(s)
}

/// Where a Winograd tile's input for position `k`, block row `dy`, starts: in the image, or
/// the zeros outside it (both Winograd families).
///
/// # Safety
/// Every `Some` offset must be inside `img`.
#[inline(always)]
unsafe fn row(img: &[f32], zeros: &[f32], at: Option<usize>) -> *const f32 {
    match at {
        Some(o) => img.as_ptr().add(o),
        None => zeros.as_ptr(),
    }
}
