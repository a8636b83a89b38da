//! The background split's AVX-512 kernels ([`crate::tensor::Background`], f32): the block
//! comparison and the per-pixel product in 16 lanes.

use crate::tensor::background::Background;
use crate::tensor::{ConvGeom, Float};
use std::arch::x86_64::*;

fn cast<T: Float>(s: &[T]) -> &[f32] {
    bytemuck::cast_slice(s)
}

/// [`Background::differing`], each block compared with `β`'s tiling in one instruction.
///
/// # Safety
/// The CPU must run AVX-512F and `T` must be `f32`.
#[target_feature(enable = "avx512f")]
pub unsafe fn split<'x, T: Float>(
    bg: &mut Background<T>, g: &ConvGeom, rows: impl Iterator<Item = &'x [T]>, limit: usize,
) -> bool {
    debug_assert_eq!(std::mem::size_of::<T>(), 4, "Background: f32 on AVX-512");
    bg.differing(g, rows, limit, |block, tiled| {
        let (block, tiled) = (cast(block), cast(tiled));
        // A short block (a row's last) loads only its values.
        let m = if block.len() == 16 {
            u16::MAX
        } else {
            (1u16 << block.len()) - 1
        };
        let v = _mm512_maskz_loadu_ps(m, block.as_ptr());
        let t = _mm512_maskz_loadu_ps(m, tiled.as_ptr());
        _mm512_mask_cmp_ps_mask::<_CMP_NEQ_UQ>(m, v, t) != 0
    })
}

/// [`Background::conv`] with [`crate::tensor::background::add_products`] in `Cout / 16` registers,
/// each
/// pixel's sum by fused multiply-adds.
///
/// # Safety
/// The CPU must run AVX-512F, `T` must be `f32`, and `Cout` a multiple of 16 up to 128.
pub unsafe fn conv<T: Float>(
    bg: &mut Background<T>, g: &ConvGeom, w: &[T], bias: &[T], relu: bool, y: &mut [T],
    rows: &[usize],
) {
    debug_assert_eq!(std::mem::size_of::<T>(), 4, "Background: f32 on AVX-512");
    let run = match g.cout / 16 {
        1 => conv_nv::<T, 1>,
        2 => conv_nv::<T, 2>,
        3 => conv_nv::<T, 3>,
        4 => conv_nv::<T, 4>,
        5 => conv_nv::<T, 5>,
        6 => conv_nv::<T, 6>,
        7 => conv_nv::<T, 7>,
        8 => conv_nv::<T, 8>,
        _ => unreachable!("Background: {} output channels on the AVX-512 path", g.cout),
    };
    run(bg, g, w, bias, relu, y, rows)
}

#[target_feature(enable = "avx512f")]
unsafe fn conv_nv<T: Float, const NV: usize>(
    bg: &mut Background<T>, g: &ConvGeom, w: &[T], bias: &[T], relu: bool, y: &mut [T],
    rows: &[usize],
) {
    bg.run(g, w, bias, relu, y, rows, |a, d, w| {
        let a: &mut [f32] = bytemuck::cast_slice_mut(a);
        let (d, w) = (cast(d), cast(w));
        let mut p = [_mm512_setzero_ps(); NV];
        for (&dv, wrow) in d.iter().zip(w.chunks_exact(16 * NV)) {
            let dv = _mm512_set1_ps(dv);
            for (j, p) in p.iter_mut().enumerate() {
                *p = _mm512_fmadd_ps(dv, _mm512_loadu_ps(wrow[16 * j..].as_ptr()), *p);
            }
        }
        for (a, &p) in a.chunks_exact_mut(16).zip(&p) {
            let sum = _mm512_add_ps(_mm512_loadu_ps(a.as_ptr()), p);
            _mm512_storeu_ps(a.as_mut_ptr(), sum);
        }
    });
}
