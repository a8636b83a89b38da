//! Winograd's transforms for AVX2 and FMA, 8 channels per 256-bit register, the operations of
//! the portable loops of [`crate::tensor::winograd`] in their order (additions and subtractions
//! only, then the output's bias and ReLU), so their bits. Rows whose channel count is not a
//! multiple of 8 take the portable loops compiled for AVX2.

use crate::tensor::winograd::{
    adjoint_tile_portable, input_tile_portable, output_tile_portable, WinogradShape,
};
use crate::tensor::Float;
use std::arch::x86_64::*;

fn cast<T: Float>(s: &[T]) -> &[f32] {
    bytemuck::cast_slice(s)
}

fn cast_mut<T: Float>(s: &mut [T]) -> &mut [f32] {
    bytemuck::cast_slice_mut(s)
}

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
    let (places, seg, blk) = (s.places(), s.seg(), s.kind.block());
    if !seg.is_multiple_of(8) {
        return input_tile_portable(s, img, zeros, starts, v, stride);
    }
    let (img, zeros, v) = (cast(img), cast(zeros), cast_mut(v));
    if places == 16 {
        input_tile_v(img, zeros, starts, v, stride, blk, seg)
    } else {
        input_tile9_v(img, zeros, starts, v, stride, blk, seg)
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
    if !len.is_multiple_of(8) {
        return output_tile_portable(mt, len, bias, relu, img, at, places);
    }
    let (mt, bias, img) = (cast(mt), bias.map(cast), cast_mut(img));
    if places == 16 {
        output_tile_v(mt, len, bias, relu, img, at)
    } else {
        output_tile9_v(mt, len, bias, relu, img, at)
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
    if !co.is_multiple_of(8) {
        return adjoint_tile_portable(img, at, mt, stride, co, places);
    }
    let (img, mt) = (cast(img), cast_mut(mt));
    if places == 16 {
        adjoint_tile_v(img, at, mt, stride, co)
    } else {
        adjoint_tile9_v(img, at, mt, stride, co)
    }
}

/// Where a tile's input for position `k`, block row `dy`, starts: in the image, or the
/// zeros outside it.
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

/// [`input_tile_portable`] with F(2×2, 3×3)'s transform for a whole tile (all `blk` block
/// rows), for f32: `v[ξ·stride + dy·seg + c]` from the rows `starts[k·blk + dy]`.
///
/// # Safety
/// AVX2 and FMA must be available; every `Some` start must have `seg` values in `img`, `zeros`
/// hold `seg`, `stride ≥ blk·seg` and `v` `15·stride + blk·seg` values; `seg` a multiple
/// of 8.
#[target_feature(enable = "avx2,fma")]
unsafe fn input_tile_v(
    img: &[f32], zeros: &[f32], starts: &[Option<usize>], v: &mut [f32], stride: usize, blk: usize,
    seg: usize,
) {
    debug_assert!(seg.is_multiple_of(8) && zeros.len() >= seg && stride >= blk * seg);
    debug_assert!(v.len() >= 15 * stride + blk * seg);
    debug_assert!(starts.len() == 16 * blk);
    debug_assert!(starts.iter().flatten().all(|&o| o + seg <= img.len()));
    for dy in 0..blk {
        let px: [*const f32; 16] = std::array::from_fn(|k| row(img, zeros, starts[k * blk + dy]));
        let vp = v.as_mut_ptr().add(dy * seg);
        for c0 in (0..seg).step_by(8) {
            let mut d = [_mm256_setzero_ps(); 16];
            for k in 0..16 {
                d[k] = _mm256_loadu_ps(px[k].add(c0));
            }
            let mut t = [_mm256_setzero_ps(); 16];
            for c in 0..4 {
                t[c] = _mm256_sub_ps(d[c], d[8 + c]);
                t[4 + c] = _mm256_add_ps(d[4 + c], d[8 + c]);
                t[8 + c] = _mm256_sub_ps(d[8 + c], d[4 + c]);
                t[12 + c] = _mm256_sub_ps(d[4 + c], d[12 + c]);
            }
            for r in 0..4 {
                let q = [t[4 * r], t[4 * r + 1], t[4 * r + 2], t[4 * r + 3]];
                let at = |xi: usize| vp.add(xi * stride + c0);
                _mm256_storeu_ps(at(4 * r), _mm256_sub_ps(q[0], q[2]));
                _mm256_storeu_ps(at(4 * r + 1), _mm256_add_ps(q[1], q[2]));
                _mm256_storeu_ps(at(4 * r + 2), _mm256_sub_ps(q[2], q[1]));
                _mm256_storeu_ps(at(4 * r + 3), _mm256_sub_ps(q[1], q[3]));
            }
        }
    }
}

/// [`input_tile_v`] with F(2×2, 2×2)'s transform (9 positions) (9 positions).
///
/// # Safety
/// As [`input_tile_v`], with `starts` of `9·blk` and `v` of `8·stride + blk·seg` values.
#[target_feature(enable = "avx2,fma")]
unsafe fn input_tile9_v(
    img: &[f32], zeros: &[f32], starts: &[Option<usize>], v: &mut [f32], stride: usize, blk: usize,
    seg: usize,
) {
    debug_assert!(seg.is_multiple_of(8) && zeros.len() >= seg && stride >= blk * seg);
    debug_assert!(v.len() >= 8 * stride + blk * seg);
    debug_assert!(starts.len() == 9 * blk);
    debug_assert!(starts.iter().flatten().all(|&o| o + seg <= img.len()));
    for dy in 0..blk {
        let px: [*const f32; 9] = std::array::from_fn(|k| row(img, zeros, starts[k * blk + dy]));
        let vp = v.as_mut_ptr().add(dy * seg);
        for c0 in (0..seg).step_by(8) {
            let mut d = [_mm256_setzero_ps(); 9];
            for k in 0..9 {
                d[k] = _mm256_loadu_ps(px[k].add(c0));
            }
            let mut t = [_mm256_setzero_ps(); 9];
            for c in 0..3 {
                t[c] = _mm256_sub_ps(d[c], d[3 + c]);
                t[3 + c] = d[3 + c];
                t[6 + c] = _mm256_sub_ps(d[6 + c], d[3 + c]);
            }
            for r in 0..3 {
                let q = [t[3 * r], t[3 * r + 1], t[3 * r + 2]];
                let at = |xi: usize| vp.add(xi * stride + c0);
                _mm256_storeu_ps(at(3 * r), _mm256_sub_ps(q[0], q[1]));
                _mm256_storeu_ps(at(3 * r + 1), q[1]);
                _mm256_storeu_ps(at(3 * r + 2), _mm256_sub_ps(q[2], q[1]));
            }
        }
    }
}

/// [`adjoint_tile_portable`] for one tile, f32: `m[ξ·stride + c]` from the tile's 2×2
/// outputs at `img[at[k] + c]` (zeros for `None`).
///
/// # Safety
/// AVX2 and FMA must be available; every `Some` offset must have `co` values in `img`, `m` hold
/// `15·stride + co` values, and `co` be a multiple of 8.
#[target_feature(enable = "avx2,fma")]
unsafe fn adjoint_tile_v(
    img: &[f32], at: [Option<usize>; 4], m: &mut [f32], stride: usize, co: usize,
) {
    debug_assert!(co.is_multiple_of(8) && m.len() >= 15 * stride + co);
    debug_assert!(at.iter().flatten().all(|&o| o + co <= img.len()));
    let (ip, mp) = (img.as_ptr(), m.as_mut_ptr());
    let zero = _mm256_setzero_ps();
    for c0 in (0..co).step_by(8) {
        let y: [__m256; 4] =
            std::array::from_fn(|k| at[k].map_or(zero, |o| _mm256_loadu_ps(ip.add(o + c0))));
        let mut t = [zero; 8];
        for c in 0..2 {
            t[c] = y[c];
            t[2 + c] = _mm256_add_ps(y[c], y[2 + c]);
            t[4 + c] = _mm256_sub_ps(y[c], y[2 + c]);
            t[6 + c] = _mm256_sub_ps(zero, y[2 + c]);
        }
        for r in 0..4 {
            let (t0, t1) = (t[2 * r], t[2 * r + 1]);
            let row = [
                t0,
                _mm256_add_ps(t0, t1),
                _mm256_sub_ps(t0, t1),
                _mm256_sub_ps(zero, t1),
            ];
            for (c, &val) in row.iter().enumerate() {
                _mm256_storeu_ps(mp.add((4 * r + c) * stride + c0), val);
            }
        }
    }
}

/// [`adjoint_tile_portable`] of F(2×2, 2×2) for one tile, f32: `m[ξ·stride + c]` (9 places)
/// from the tile's 2×2 outputs, `A` mapping `(y₀, y₁)` to `(y₀, y₀ + y₁, y₁)`.
///
/// # Safety
/// As [`adjoint_tile_v`], with `m` holding `8·stride + co` values.
#[target_feature(enable = "avx2,fma")]
unsafe fn adjoint_tile9_v(
    img: &[f32], at: [Option<usize>; 4], m: &mut [f32], stride: usize, co: usize,
) {
    debug_assert!(co.is_multiple_of(8) && m.len() >= 8 * stride + co);
    debug_assert!(at.iter().flatten().all(|&o| o + co <= img.len()));
    let (ip, mp) = (img.as_ptr(), m.as_mut_ptr());
    let zero = _mm256_setzero_ps();
    for c0 in (0..co).step_by(8) {
        let y: [__m256; 4] =
            std::array::from_fn(|k| at[k].map_or(zero, |o| _mm256_loadu_ps(ip.add(o + c0))));
        let mut t = [zero; 6];
        for c in 0..2 {
            t[c] = y[c];
            t[2 + c] = _mm256_add_ps(y[c], y[2 + c]);
            t[4 + c] = y[2 + c];
        }
        for r in 0..3 {
            let (t0, t1) = (t[2 * r], t[2 * r + 1]);
            let row = [t0, _mm256_add_ps(t0, t1), t1];
            for (c, &val) in row.iter().enumerate() {
                _mm256_storeu_ps(mp.add((3 * r + c) * stride + c0), val);
            }
        }
    }
}

/// The end of both output transforms: `+ bias`, `max(·, 0)`, each of the 2×2 outputs stored
/// at its destination (channels `c0 ..+ 8`) if it is inside the output.
///
/// # Safety
/// AVX2 and FMA; `bias` (if any) readable for channels `c0 ..+ 8` (of all `co`), and `ip + a`
/// writable for channels `c ..+ 8` (of the destination's piece).
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn finish(
    mut y: [__m256; 4], bias: Option<&[f32]>, relu: bool, ip: *mut f32, at: [Option<usize>; 4],
    c0: usize, c: usize,
) {
    if let Some(b) = bias {
        let bv = _mm256_loadu_ps(b.as_ptr().add(c0));
        for yv in y.iter_mut() {
            *yv = _mm256_add_ps(*yv, bv);
        }
    }
    if relu {
        for yv in y.iter_mut() {
            *yv = _mm256_max_ps(*yv, _mm256_setzero_ps());
        }
    }
    for k in 0..4 {
        if let Some(a) = at[k] {
            _mm256_storeu_ps(ip.add(a + c), y[k]);
        }
    }
}

/// [`output_tile_portable`] with F(2×2, 3×3)'s transform, for f32.
///
/// # Safety
/// AVX2 and FMA must be available; `m` must hold `16·co` values (`co = at.len()·len`), `bias`
/// (if any) `co`, and `img[a..a + len]` be in bounds for each destination `a`; `len` a
/// multiple of 8.
#[target_feature(enable = "avx2,fma")]
unsafe fn output_tile_v(
    m: &[f32], len: usize, bias: Option<&[f32]>, relu: bool, img: &mut [f32],
    at: &[[Option<usize>; 4]],
) {
    let co = at.len() * len;
    debug_assert!(len.is_multiple_of(8) && m.len() >= 16 * co);
    debug_assert!(at.iter().flatten().flatten().all(|&a| a + len <= img.len()));
    let (mp, ip) = (m.as_ptr(), img.as_mut_ptr());
    for c0 in (0..co).step_by(8) {
        let j = c0 / len;
        let mut mt = [_mm256_setzero_ps(); 16];
        for (xi, mt) in mt.iter_mut().enumerate() {
            *mt = _mm256_loadu_ps(mp.add(xi * co + c0));
        }
        let mut s = [_mm256_setzero_ps(); 8];
        for c in 0..4 {
            s[c] = _mm256_add_ps(_mm256_add_ps(mt[c], mt[4 + c]), mt[8 + c]);
            s[4 + c] = _mm256_sub_ps(_mm256_sub_ps(mt[4 + c], mt[8 + c]), mt[12 + c]);
        }
        let mut y = [_mm256_setzero_ps(); 4];
        for r in 0..2 {
            let q = [s[4 * r], s[4 * r + 1], s[4 * r + 2], s[4 * r + 3]];
            y[2 * r] = _mm256_add_ps(_mm256_add_ps(q[0], q[1]), q[2]);
            y[2 * r + 1] = _mm256_sub_ps(_mm256_sub_ps(q[1], q[2]), q[3]);
        }
        finish(y, bias, relu, ip, at[j], c0, c0 - j * len);
    }
}

/// [`output_tile_portable`] with F(2×2, 2×2)'s transform, for f32.
///
/// # Safety
/// As [`output_tile_v`], with `m` holding `9·co` values.
#[target_feature(enable = "avx2,fma")]
unsafe fn output_tile9_v(
    m: &[f32], len: usize, bias: Option<&[f32]>, relu: bool, img: &mut [f32],
    at: &[[Option<usize>; 4]],
) {
    let co = at.len() * len;
    debug_assert!(len.is_multiple_of(8) && m.len() >= 9 * co);
    debug_assert!(at.iter().flatten().flatten().all(|&a| a + len <= img.len()));
    let (mp, ip) = (m.as_ptr(), img.as_mut_ptr());
    for c0 in (0..co).step_by(8) {
        let j = c0 / len;
        let mut mt = [_mm256_setzero_ps(); 9];
        for (xi, mt) in mt.iter_mut().enumerate() {
            *mt = _mm256_loadu_ps(mp.add(xi * co + c0));
        }
        let mut s = [_mm256_setzero_ps(); 6];
        for c in 0..3 {
            s[c] = _mm256_add_ps(mt[c], mt[3 + c]);
            s[3 + c] = _mm256_add_ps(mt[3 + c], mt[6 + c]);
        }
        let mut y = [_mm256_setzero_ps(); 4];
        for r in 0..2 {
            y[2 * r] = _mm256_add_ps(s[3 * r], s[3 * r + 1]);
            y[2 * r + 1] = _mm256_add_ps(s[3 * r + 1], s[3 * r + 2]);
        }
        finish(y, bias, relu, ip, at[j], c0, c0 - j * len);
    }
}
