//! The sparse product's AVX-512 kernels ([`crate::tensor::Nonzeros::collect`] by compress,
//! [`crate::tensor::SparseConv`] with its accumulators in zmm registers), f32.

use crate::tensor::sparse::{Nonzeros, SparseConv};
use crate::tensor::Float;
use std::arch::x86_64::*;

/// [`Nonzeros::collect`] 16 channels at a time: the nonzero lanes are compressed to the
/// front of a register, which is stored whole (the spare places take the rest) before the
/// place moves on by their count.
///
/// # Safety
/// The CPU must run AVX-512F, `T` must be `f32`, `c` a multiple of 16, and the buffers
/// sized by [`Nonzeros::collect`].
#[target_feature(enable = "avx512f")]
pub unsafe fn collect<T: Float>(nz: &mut Nonzeros<T>, x: &[T], c: usize) {
    let x = cast::<T>(x);
    let value: &mut [f32] = bytemuck::cast_slice_mut(&mut nz.value);
    let index = &mut nz.index;
    let lanes = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
    let mut k = 0;
    for (p, px) in x.chunks_exact(c).enumerate() {
        nz.start[p] = k;
        for (j, v16) in px.chunks_exact(16).enumerate() {
            let v = _mm512_loadu_ps(v16.as_ptr());
            let m = _mm512_cmp_ps_mask::<_CMP_NEQ_UQ>(v, _mm512_setzero_ps());
            let ci = _mm512_add_epi32(lanes, _mm512_set1_epi32(16 * j as i32));
            let (vs, is) = (&mut value[k..k + 16], &mut index[k..k + 16]);
            _mm512_storeu_ps(vs.as_mut_ptr(), _mm512_maskz_compress_ps(m, v));
            let ci = _mm512_maskz_compress_epi32(m, ci);
            _mm512_storeu_si512(is.as_mut_ptr().cast(), ci);
            k += m.count_ones() as usize;
        }
    }
    nz.start[x.len() / c] = k;
}

/// [`SparseConv::run`] with the `Cout / 16` accumulators in registers.
///
/// # Safety
/// The CPU must run AVX-512F, `T` must be `f32`, and `cout` a multiple of 16 from 16 to 128.
pub unsafe fn run<T: Float>(g: SparseConv<'_, T>, cin: usize, cout: usize) {
    match cout / 16 {
        1 => rows::<T, 1>(g, cin),
        2 => rows::<T, 2>(g, cin),
        3 => rows::<T, 3>(g, cin),
        4 => rows::<T, 4>(g, cin),
        5 => rows::<T, 5>(g, cin),
        6 => rows::<T, 6>(g, cin),
        7 => rows::<T, 7>(g, cin),
        8 => rows::<T, 8>(g, cin),
        _ => unreachable!("SparseConv: {cout} output channels on the AVX-512 path"),
    }
}

fn cast<T: Float>(s: &[T]) -> &[f32] {
    bytemuck::cast_slice(s)
}

/// Every row of [`run`], all `16·NV` output channels in registers (`sparse_simd.rs`).
#[target_feature(enable = "avx512f")]
unsafe fn rows<T: Float, const NV: usize>(mut g: SparseConv<'_, T>, cin: usize) {
    super::sparse_simd::columns::<__m512, T, NV>(&mut g, cin, 16 * NV, 0)
}
