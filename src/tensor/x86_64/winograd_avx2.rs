//! Winograd's transforms for AVX2 and FMA, 8 channels per 256-bit register, the operations of
//! the portable loops of [`crate::tensor::winograd`] in their order (additions and subtractions
//! only, then the output's bias and ReLU), so their bits. Rows whose channel count is not a
//! multiple of 8 take the portable loops compiled for AVX2.

use super::{cast, cast_mut, row};
use crate::tensor::winograd::{
    adjoint_tile_portable, input_tile_portable, output_tile_portable, WinogradShape,
};
use crate::tensor::Float;
use std::arch::x86_64::*;

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
    if !s.seg().is_multiple_of(8) {
        return input_tile_portable(s, img, zeros, starts, v, stride);
    }
    let (img, zeros, v) = (cast(img), cast(zeros), cast_mut(v));
    if s.places() == 16 {
        input_tile_v::<16>(s, img, zeros, starts, v, stride, input_transform16)
    } else {
        input_tile_v::<9>(s, img, zeros, starts, v, stride, input_transform9)
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
        output_tile_v::<16>(mt, len, bias, relu, img, at, output_transform16)
    } else {
        output_tile_v::<9>(mt, len, bias, relu, img, at, output_transform9)
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
        adjoint_tile_v::<16>(img, at, mt, stride, co, adjoint_transform16)
    } else {
        adjoint_tile_v::<9>(img, at, mt, stride, co, adjoint_transform9)
    }
}

/// [`input_tile_portable`] for a whole tile (all `blk` block rows of `seg` values, from `s`),
/// f32, `P` positions (16 for F(2×2, 3×3), 9 for F(2×2, 2×2)): for each block row `dy` and 8
/// channels at a time, the positions' values `d` from the rows `starts[k·blk + dy]` (zeros
/// where `None`), transformed by `transform` (`Bᵀ·d·B`) and stored at
/// `v[ξ·stride + dy·seg + c]`.
///
/// # Safety
/// AVX2 and FMA must be available; every `Some` start must have `seg` values in `img`, `zeros`
/// hold `seg`, `stride ≥ blk·seg` and `v` `(P − 1)·stride + blk·seg` values; `seg` a multiple
/// of 8.
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn input_tile_v<const P: usize>(
    s: &WinogradShape, img: &[f32], zeros: &[f32], starts: &[Option<usize>], v: &mut [f32],
    stride: usize, transform: unsafe fn(&[__m256; P]) -> [__m256; P],
) {
    let (seg, blk) = (s.seg(), s.kind.block());
    debug_assert!(seg.is_multiple_of(8) && zeros.len() >= seg && stride >= blk * seg);
    debug_assert!(v.len() >= (P - 1) * stride + blk * seg);
    debug_assert!(starts.len() == P * blk);
    debug_assert!(starts.iter().flatten().all(|&o| o + seg <= img.len()));
    for dy in 0..blk {
        let px: [*const f32; P] = std::array::from_fn(|k| row(img, zeros, starts[k * blk + dy]));
        let vp = v.as_mut_ptr().add(dy * seg);
        for c0 in (0..seg).step_by(8) {
            let mut d = [_mm256_setzero_ps(); P];
            for k in 0..P {
                d[k] = _mm256_loadu_ps(px[k].add(c0));
            }
            for (xi, &val) in transform(&d).iter().enumerate() {
                _mm256_storeu_ps(vp.add(xi * stride + c0), val);
            }
        }
    }
}

/// `Bᵀ·d·B` of F(2×2, 3×3), 8 channels: the portable `input_transform`'s operations.
///
/// # Safety
/// AVX2 and FMA must be available.
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn input_transform16(d: &[__m256; 16]) -> [__m256; 16] {
    let mut t = [_mm256_setzero_ps(); 16];
    for c in 0..4 {
        t[c] = _mm256_sub_ps(d[c], d[8 + c]);
        t[4 + c] = _mm256_add_ps(d[4 + c], d[8 + c]);
        t[8 + c] = _mm256_sub_ps(d[8 + c], d[4 + c]);
        t[12 + c] = _mm256_sub_ps(d[4 + c], d[12 + c]);
    }
    let mut v = [_mm256_setzero_ps(); 16];
    for r in 0..4 {
        let q = [t[4 * r], t[4 * r + 1], t[4 * r + 2], t[4 * r + 3]];
        v[4 * r] = _mm256_sub_ps(q[0], q[2]);
        v[4 * r + 1] = _mm256_add_ps(q[1], q[2]);
        v[4 * r + 2] = _mm256_sub_ps(q[2], q[1]);
        v[4 * r + 3] = _mm256_sub_ps(q[1], q[3]);
    }
    v
}

/// `Bᵀ·d·B` of F(2×2, 2×2) (9 positions), 8 channels: the portable `input_transform9`'s
/// operations.
///
/// # Safety
/// AVX2 and FMA must be available.
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn input_transform9(d: &[__m256; 9]) -> [__m256; 9] {
    let mut t = [_mm256_setzero_ps(); 9];
    for c in 0..3 {
        t[c] = _mm256_sub_ps(d[c], d[3 + c]);
        t[3 + c] = d[3 + c];
        t[6 + c] = _mm256_sub_ps(d[6 + c], d[3 + c]);
    }
    let mut v = [_mm256_setzero_ps(); 9];
    for r in 0..3 {
        let q = [t[3 * r], t[3 * r + 1], t[3 * r + 2]];
        v[3 * r] = _mm256_sub_ps(q[0], q[1]);
        v[3 * r + 1] = q[1];
        v[3 * r + 2] = _mm256_sub_ps(q[2], q[1]);
    }
    v
}

/// [`adjoint_tile_portable`] for one tile, f32, `P` places (16 for F(2×2, 3×3), 9 for
/// F(2×2, 2×2)), 8 channels at a time: the tile's 2×2 outputs `y` from `img[at[k] + c]` (zeros
/// for `None`), spread by `transform` (`A·y·Aᵀ`) to `m[ξ·stride + c]`.
///
/// # Safety
/// AVX2 and FMA must be available; every `Some` offset must have `co` values in `img`, `m` hold
/// `(P − 1)·stride + co` values, and `co` be a multiple of 8.
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn adjoint_tile_v<const P: usize>(
    img: &[f32], at: [Option<usize>; 4], m: &mut [f32], stride: usize, co: usize,
    transform: unsafe fn(&[__m256; 4]) -> [__m256; P],
) {
    debug_assert!(co.is_multiple_of(8) && m.len() >= (P - 1) * stride + co);
    debug_assert!(at.iter().flatten().all(|&o| o + co <= img.len()));
    let (ip, mp) = (img.as_ptr(), m.as_mut_ptr());
    for c0 in (0..co).step_by(8) {
        let y: [__m256; 4] = std::array::from_fn(|k| {
            at[k].map_or(_mm256_setzero_ps(), |o| _mm256_loadu_ps(ip.add(o + c0)))
        });
        for (xi, &val) in transform(&y).iter().enumerate() {
            _mm256_storeu_ps(mp.add(xi * stride + c0), val);
        }
    }
}

/// `A·y·Aᵀ` of F(2×2, 3×3), 8 channels: `A` maps `(y₀, y₁)` to `(y₀, y₀ + y₁, y₀ − y₁, −y₁)`.
///
/// # Safety
/// AVX2 and FMA must be available.
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn adjoint_transform16(y: &[__m256; 4]) -> [__m256; 16] {
    let zero = _mm256_setzero_ps();
    let mut t = [zero; 8];
    for c in 0..2 {
        t[c] = y[c];
        t[2 + c] = _mm256_add_ps(y[c], y[2 + c]);
        t[4 + c] = _mm256_sub_ps(y[c], y[2 + c]);
        t[6 + c] = _mm256_sub_ps(zero, y[2 + c]);
    }
    let mut m = [zero; 16];
    for r in 0..4 {
        let (t0, t1) = (t[2 * r], t[2 * r + 1]);
        m[4 * r] = t0;
        m[4 * r + 1] = _mm256_add_ps(t0, t1);
        m[4 * r + 2] = _mm256_sub_ps(t0, t1);
        m[4 * r + 3] = _mm256_sub_ps(zero, t1);
    }
    m
}

/// `A·y·Aᵀ` of F(2×2, 2×2) (9 places), 8 channels: `A` maps `(y₀, y₁)` to `(y₀, y₀ + y₁, y₁)`.
///
/// # Safety
/// AVX2 and FMA must be available.
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn adjoint_transform9(y: &[__m256; 4]) -> [__m256; 9] {
    let mut t = [_mm256_setzero_ps(); 6];
    for c in 0..2 {
        t[c] = y[c];
        t[2 + c] = _mm256_add_ps(y[c], y[2 + c]);
        t[4 + c] = y[2 + c];
    }
    let mut m = [_mm256_setzero_ps(); 9];
    for r in 0..3 {
        let (t0, t1) = (t[2 * r], t[2 * r + 1]);
        m[3 * r] = t0;
        m[3 * r + 1] = _mm256_add_ps(t0, t1);
        m[3 * r + 2] = t1;
    }
    m
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

/// [`output_tile_portable`] for f32, `P` places (16 for F(2×2, 3×3), 9 for F(2×2, 2×2)), 8
/// channels at a time: the places' products `m[ξ·co + c]`, transformed by `transform`
/// (`Aᵀ·m·A`, the 2×2 outputs) and [`finish`]ed at their destinations.
///
/// # Safety
/// AVX2 and FMA must be available; `m` must hold `P·co` values (`co = at.len()·len`), `bias`
/// (if any) `co`, and `img[a..a + len]` be in bounds for each destination `a`; `len` a
/// multiple of 8.
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn output_tile_v<const P: usize>(
    m: &[f32], len: usize, bias: Option<&[f32]>, relu: bool, img: &mut [f32],
    at: &[[Option<usize>; 4]], transform: unsafe fn(&[__m256; P]) -> [__m256; 4],
) {
    let co = at.len() * len;
    debug_assert!(len.is_multiple_of(8) && m.len() >= P * co);
    debug_assert!(at.iter().flatten().flatten().all(|&a| a + len <= img.len()));
    let (mp, ip) = (m.as_ptr(), img.as_mut_ptr());
    for c0 in (0..co).step_by(8) {
        let j = c0 / len;
        let mut mt = [_mm256_setzero_ps(); P];
        for (xi, mt) in mt.iter_mut().enumerate() {
            *mt = _mm256_loadu_ps(mp.add(xi * co + c0));
        }
        finish(transform(&mt), bias, relu, ip, at[j], c0, c0 - j * len);
    }
}

/// `Aᵀ·m·A` of F(2×2, 3×3), 8 channels: the portable `output_transform`'s operations.
///
/// # Safety
/// AVX2 and FMA must be available.
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn output_transform16(mt: &[__m256; 16]) -> [__m256; 4] {
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
    y
}

/// `Aᵀ·m·A` of F(2×2, 2×2) (9 places), 8 channels: the portable `output_transform9`'s
/// operations.
///
/// # Safety
/// AVX2 and FMA must be available.
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn output_transform9(mt: &[__m256; 9]) -> [__m256; 4] {
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
    y
}
