//! Acting's kernels for AVX2 and FMA (batch 1, [`crate::layers::Layer::infer`]): the sparse
//! product ([`SparseConv`]) and the background split's product ([`Background::conv`]) with
//! their sums in 256-bit registers, columns of up to 64 output channels at a time (8
//! accumulators of the 16 registers), each output channel's terms by fused multiply-adds in the
//! order of the AVX-512 kernels, whose bits they give; the list of nonzeros and the background
//! scan are the portable loops compiled for AVX2.

use crate::tensor::sparse::{Nonzeros, SparseConv};
use crate::tensor::{Background, ConvGeom, Float};
use std::arch::x86_64::*;

/// Output channels summed at a time: 8 registers of 8.
const COLUMNS: usize = 64;

fn cast<T: Float>(s: &[T]) -> &[f32] {
    bytemuck::cast_slice(s)
}

/// [`Nonzeros::collect`]'s portable loop for AVX2.
///
/// # Safety
/// The CPU runs AVX2 and FMA; the buffers are sized by [`Nonzeros::collect`].
#[target_feature(enable = "avx2,fma")]
pub(crate) unsafe fn collect<T: Float>(nz: &mut Nonzeros<T>, x: &[T], c: usize) {
    nz.collect_portable(x, c)
}

/// [`Background::split`]'s scan with the portable comparison, for AVX2.
///
/// # Safety
/// The CPU runs AVX2 and FMA.
#[target_feature(enable = "avx2,fma")]
pub(crate) unsafe fn split<'x, T: Float>(
    bg: &mut Background<T>, g: &ConvGeom, rows: impl Iterator<Item = &'x [T]>, limit: usize,
) -> bool {
    bg.split_portable(g, rows, limit)
}

/// [`SparseConv::run`]: every output row from the bias, `y_r = b + Σ x·w` over the nonzero
/// inputs of its window, tap by tap and channel by channel.
///
/// # Safety
/// The CPU runs AVX2 and FMA, `T` is `f32` and `cout` a multiple of 8.
#[target_feature(enable = "avx2,fma")]
pub(crate) unsafe fn sparse_run<T: Float>(mut g: SparseConv<'_, T>, cin: usize, cout: usize) {
    debug_assert!(std::mem::size_of::<T>() == 4 && cout.is_multiple_of(8));
    for c0 in (0..cout).step_by(COLUMNS) {
        match (cout - c0).min(COLUMNS) / 8 {
            1 => sparse_columns::<T, 1>(&mut g, cin, cout, c0),
            2 => sparse_columns::<T, 2>(&mut g, cin, cout, c0),
            3 => sparse_columns::<T, 3>(&mut g, cin, cout, c0),
            4 => sparse_columns::<T, 4>(&mut g, cin, cout, c0),
            5 => sparse_columns::<T, 5>(&mut g, cin, cout, c0),
            6 => sparse_columns::<T, 6>(&mut g, cin, cout, c0),
            7 => sparse_columns::<T, 7>(&mut g, cin, cout, c0),
            _ => sparse_columns::<T, 8>(&mut g, cin, cout, c0),
        }
    }
}

/// Output channels `c0 ..+ 8·NV` of every row of [`sparse_run`] (`sparse_simd.rs`).
#[target_feature(enable = "avx2,fma")]
unsafe fn sparse_columns<T: Float, const NV: usize>(
    g: &mut SparseConv<'_, T>, cin: usize, cout: usize, c0: usize,
) {
    super::sparse_simd::columns::<__m256, T, NV>(g, cin, cout, c0)
}

/// [`Background::conv`] with its per-pixel product `a += Σ_ci d_ci·W[ci, :]` in registers: the
/// sum from zero by fused multiply-adds over `ci`, then added to `a`.
///
/// # Safety
/// The CPU runs AVX2 and FMA, `T` is `f32` and `Cout` a multiple of 8.
#[target_feature(enable = "avx2,fma")]
pub(crate) unsafe fn background_conv<T: Float>(
    bg: &mut Background<T>, g: &ConvGeom, w: &[T], bias: &[T], relu: bool, y: &mut [T],
    rows: &[usize],
) {
    debug_assert!(std::mem::size_of::<T>() == 4 && g.cout.is_multiple_of(8));
    bg.run(g, w, bias, relu, y, rows, |a, d, w| {
        let a: &mut [f32] = bytemuck::cast_slice_mut(a);
        let (d, w) = (cast(d), cast(w));
        let cout = a.len();
        for c0 in (0..cout).step_by(COLUMNS) {
            match (cout - c0).min(COLUMNS) / 8 {
                1 => add_columns::<1>(a, d, w, c0),
                2 => add_columns::<2>(a, d, w, c0),
                3 => add_columns::<3>(a, d, w, c0),
                4 => add_columns::<4>(a, d, w, c0),
                5 => add_columns::<5>(a, d, w, c0),
                6 => add_columns::<6>(a, d, w, c0),
                7 => add_columns::<7>(a, d, w, c0),
                _ => add_columns::<8>(a, d, w, c0),
            }
        }
    });
}

/// Channels `c0 ..+ 8·NV` of [`background_conv`]'s per-pixel product.
#[inline(always)]
fn add_columns<const NV: usize>(a: &mut [f32], d: &[f32], w: &[f32], c0: usize) {
    let cout = a.len();
    // SAFETY: called only from `background_conv`, which runs where AVX2 and FMA do; every load
    // and store is of 8 values inside `a` or a row of `w` (`c0 + 8·NV ≤ cout`).
    unsafe {
        let mut p = [_mm256_setzero_ps(); NV];
        for (&dv, wrow) in d.iter().zip(w.chunks_exact(cout)) {
            let dv = _mm256_set1_ps(dv);
            for (j, p) in p.iter_mut().enumerate() {
                let wv = _mm256_loadu_ps(wrow[c0 + 8 * j..][..8].as_ptr());
                *p = _mm256_fmadd_ps(dv, wv, *p);
            }
        }
        for (j, &p) in p.iter().enumerate() {
            let at = &mut a[c0 + 8 * j..][..8];
            let sum = _mm256_add_ps(_mm256_loadu_ps(at.as_ptr()), p);
            _mm256_storeu_ps(at.as_mut_ptr(), sum);
        }
    }
}
