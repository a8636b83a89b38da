//! Winograd's transforms ([`crate::tensor::winograd`]) written once for both vector widths
//! ([`F32s`]: 8 channels per AVX2 register, 16 per AVX-512 one), the tile's values in
//! registers: the operations of the portable loops in their order (additions and subtractions
//! only, then the output's bias and ReLU), so their bits. One frame per tile kind, generic over
//! the 16 or 9 places, each given its transform. The entry points that run them, compiled for
//! their instruction set, are `winograd_avx2.rs` and `winograd_avx512.rs`; each body here is
//! `#[inline(always)]`, so it is compiled inside them.

use super::simd::F32s;
use super::{cast, cast_mut, row};
use crate::tensor::winograd::WinogradShape;
use crate::tensor::Float;

/// [`crate::tensor::winograd::input_tile_portable`] in `V`'s registers.
///
/// # Safety
/// `V`'s instruction set is available; `T` is `f32`; `seg` is a multiple of `V::LANES`; every
/// `Some` start is a block row of `seg` values inside `img`, `zeros` holds `seg` and `v`
/// reaches the tile's last place.
#[inline(always)]
pub(super) unsafe fn input_tile<V: F32s, T: Float>(
    s: &WinogradShape, img: &[T], zeros: &[T], starts: &[Option<usize>], v: &mut [T], stride: usize,
) {
    let (img, zeros, v) = (cast(img), cast(zeros), cast_mut(v));
    let (seg, blk, places) = (s.seg(), s.kind.block(), s.places());
    assert!(
        v.len() >= (places - 1) * stride + blk * seg,
        "input_tile: v"
    );
    let vp = v.as_mut_ptr();
    // SAFETY (of each store): `at` is below `(P − 1)·stride + blk·seg` (`input_tile_with`),
    // inside `v` (asserted).
    let store = |at: usize, val: V| V::store(vp.add(at), val);
    input_tile_with(s, img, zeros, starts, stride, store)
}

/// [`input_tile`]'s transform with each vector of `V::LANES` channels handed to
/// `store(at, value)`, `at` the place in a destination laid out as [`input_tile`]'s `v`
/// (`ξ·stride + dy·seg + c`, below `(P − 1)·stride + blk·seg`): a caller may round it
/// (`winograd_avx512::input_tile_bf16`) instead of storing it as it is.
///
/// # Safety
/// As [`input_tile`], `store` safe to call for every such place.
#[inline(always)]
pub(super) unsafe fn input_tile_with<V: F32s>(
    s: &WinogradShape, img: &[f32], zeros: &[f32], starts: &[Option<usize>], stride: usize,
    store: impl Fn(usize, V),
) {
    if s.places() == 16 {
        input_tile_v::<V, 16>(s, img, zeros, starts, stride, input_transform16::<V>, store)
    } else {
        input_tile_v::<V, 9>(s, img, zeros, starts, stride, input_transform9::<V>, store)
    }
}

/// [`crate::tensor::winograd::output_tile_portable`] in `V`'s registers.
///
/// # Safety
/// `V`'s instruction set is available; `T` is `f32`; `len` is a multiple of `V::LANES`; `mt`
/// holds `places·co` values, the bias `co`, each destination `len` inside the image.
#[inline(always)]
pub(super) unsafe fn output_tile<V: F32s, T: Float>(
    mt: &[T], len: usize, bias: Option<&[T]>, relu: bool, img: &mut [T], at: &[[Option<usize>; 4]],
    places: usize,
) {
    let (mt, bias, img) = (cast(mt), bias.map(cast), cast_mut(img));
    if places == 16 {
        output_tile_v::<V, 16>(mt, len, bias, relu, img, at, output_transform16::<V>)
    } else {
        output_tile_v::<V, 9>(mt, len, bias, relu, img, at, output_transform9::<V>)
    }
}

/// [`crate::tensor::winograd::adjoint_tile_portable`] in `V`'s registers.
///
/// # Safety
/// `V`'s instruction set is available; `T` is `f32`; `co` is a multiple of `V::LANES`; every
/// `Some` output holds `co` values inside `img` and `mt` reaches the tile's last place.
#[inline(always)]
pub(super) unsafe fn adjoint_tile<V: F32s, T: Float>(
    img: &[T], at: [Option<usize>; 4], mt: &mut [T], stride: usize, co: usize, places: usize,
) {
    let (img, mt) = (cast(img), cast_mut(mt));
    assert!(mt.len() >= (places - 1) * stride + co, "adjoint_tile: m");
    let mp = mt.as_mut_ptr();
    // SAFETY (of each store): `at` is below `(P − 1)·stride + co`, inside `mt` (asserted).
    let store = |at: usize, val: V| V::store(mp.add(at), val);
    adjoint_tile_with(img, at, stride, co, places, store)
}

/// [`adjoint_tile`]'s transform with each vector of `V::LANES` channels handed to
/// `store(at, value)`, `at` the place in a destination laid out as [`adjoint_tile`]'s `mt`
/// (`ξ·stride + c`, below `(P − 1)·stride + co`).
///
/// # Safety
/// As [`adjoint_tile`], `store` safe to call for every such place.
#[inline(always)]
pub(super) unsafe fn adjoint_tile_with<V: F32s>(
    img: &[f32], at: [Option<usize>; 4], stride: usize, co: usize, places: usize,
    store: impl Fn(usize, V),
) {
    if places == 16 {
        adjoint_tile_v::<V, 16>(img, at, stride, co, adjoint_transform16::<V>, store)
    } else {
        adjoint_tile_v::<V, 9>(img, at, stride, co, adjoint_transform9::<V>, store)
    }
}

/// The input transform for a whole tile (all `blk` block rows of `seg` values, from `s`), f32,
/// `P` positions (16 for F(2×2, 3×3), 9 for F(2×2, 2×2)): for each block row `dy` and
/// `V::LANES` channels at a time, the positions' values `d` from the rows `starts[k·blk + dy]` (zeros
/// where `None`), transformed by `transform` (`Bᵀ·d·B`) and handed to `store` for place
/// `ξ·stride + dy·seg + c` of the destination.
///
/// # Safety
/// `V`'s instruction set must be available; every `Some` start must have `seg` values in `img`, `zeros`
/// hold `seg`, `stride ≥ blk·seg`, `store` take every place below `(P − 1)·stride + blk·seg`;
/// `seg` a multiple of `V::LANES`.
#[inline(always)]
unsafe fn input_tile_v<V: F32s, const P: usize>(
    s: &WinogradShape, img: &[f32], zeros: &[f32], starts: &[Option<usize>], stride: usize,
    transform: unsafe fn(&[V; P]) -> [V; P], store: impl Fn(usize, V),
) {
    let (seg, blk) = (s.seg(), s.kind.block());
    debug_assert!(seg.is_multiple_of(V::LANES) && zeros.len() >= seg && stride >= blk * seg);
    debug_assert!(starts.len() == P * blk);
    debug_assert!(starts.iter().flatten().all(|&o| o + seg <= img.len()));
    for dy in 0..blk {
        let px: [*const f32; P] = std::array::from_fn(|k| row(img, zeros, starts[k * blk + dy]));
        for c0 in (0..seg).step_by(V::LANES) {
            let mut d = [V::zero(); P];
            for k in 0..P {
                d[k] = V::load(px[k].add(c0));
            }
            for (xi, &val) in transform(&d).iter().enumerate() {
                store(xi * stride + dy * seg + c0, val);
            }
        }
    }
}

/// `Bᵀ·d·B` of F(2×2, 3×3), `V::LANES` channels: the portable `input_transform`'s operations.
///
/// # Safety
/// `V`'s instruction set must be available.
#[inline(always)]
unsafe fn input_transform16<V: F32s>(d: &[V; 16]) -> [V; 16] {
    let mut t = [V::zero(); 16];
    for c in 0..4 {
        t[c] = V::sub(d[c], d[8 + c]);
        t[4 + c] = V::add(d[4 + c], d[8 + c]);
        t[8 + c] = V::sub(d[8 + c], d[4 + c]);
        t[12 + c] = V::sub(d[4 + c], d[12 + c]);
    }
    let mut v = [V::zero(); 16];
    for r in 0..4 {
        let q = [t[4 * r], t[4 * r + 1], t[4 * r + 2], t[4 * r + 3]];
        v[4 * r] = V::sub(q[0], q[2]);
        v[4 * r + 1] = V::add(q[1], q[2]);
        v[4 * r + 2] = V::sub(q[2], q[1]);
        v[4 * r + 3] = V::sub(q[1], q[3]);
    }
    v
}

/// `Bᵀ·d·B` of F(2×2, 2×2) (9 positions), `V::LANES` channels: the portable `input_transform9`'s
/// operations.
///
/// # Safety
/// `V`'s instruction set must be available.
#[inline(always)]
unsafe fn input_transform9<V: F32s>(d: &[V; 9]) -> [V; 9] {
    let mut t = [V::zero(); 9];
    for c in 0..3 {
        t[c] = V::sub(d[c], d[3 + c]);
        t[3 + c] = d[3 + c];
        t[6 + c] = V::sub(d[6 + c], d[3 + c]);
    }
    let mut v = [V::zero(); 9];
    for r in 0..3 {
        let q = [t[3 * r], t[3 * r + 1], t[3 * r + 2]];
        v[3 * r] = V::sub(q[0], q[1]);
        v[3 * r + 1] = q[1];
        v[3 * r + 2] = V::sub(q[2], q[1]);
    }
    v
}

/// The output adjoint for one tile, f32, `P` places (16 for F(2×2, 3×3), 9 for F(2×2, 2×2)),
/// `V::LANES` channels at a time: the tile's 2×2 outputs `y` from `img[at[k] + c]` (zeros for `None`),
/// spread by `transform` (`A·y·Aᵀ`) and handed to `store` for place `ξ·stride + c`.
///
/// # Safety
/// `V`'s instruction set must be available; every `Some` offset must have `co` values in `img`,
/// `store` take every place below `(P − 1)·stride + co`, and `co` be a multiple of `V::LANES`.
#[inline(always)]
unsafe fn adjoint_tile_v<V: F32s, const P: usize>(
    img: &[f32], at: [Option<usize>; 4], stride: usize, co: usize,
    transform: unsafe fn(&[V; 4]) -> [V; P], store: impl Fn(usize, V),
) {
    debug_assert!(co.is_multiple_of(V::LANES));
    debug_assert!(at.iter().flatten().all(|&o| o + co <= img.len()));
    let ip = img.as_ptr();
    for c0 in (0..co).step_by(V::LANES) {
        // A loop, not `array::from_fn`: a closure here would not be compiled for `V`'s
        // instruction set, and its loads would be calls.
        let mut y = [V::zero(); 4];
        for (y, &o) in y.iter_mut().zip(&at) {
            if let Some(o) = o {
                *y = V::load(ip.add(o + c0));
            }
        }
        for (xi, &val) in transform(&y).iter().enumerate() {
            store(xi * stride + c0, val);
        }
    }
}

/// `A·y·Aᵀ` of F(2×2, 3×3), `V::LANES` channels: `A` maps `(y₀, y₁)` to `(y₀, y₀ + y₁, y₀ − y₁, −y₁)`.
///
/// # Safety
/// `V`'s instruction set must be available.
#[inline(always)]
unsafe fn adjoint_transform16<V: F32s>(y: &[V; 4]) -> [V; 16] {
    let zero = V::zero();
    let mut t = [zero; 8];
    for c in 0..2 {
        t[c] = y[c];
        t[2 + c] = V::add(y[c], y[2 + c]);
        t[4 + c] = V::sub(y[c], y[2 + c]);
        t[6 + c] = V::sub(zero, y[2 + c]);
    }
    let mut m = [zero; 16];
    for r in 0..4 {
        let (t0, t1) = (t[2 * r], t[2 * r + 1]);
        m[4 * r] = t0;
        m[4 * r + 1] = V::add(t0, t1);
        m[4 * r + 2] = V::sub(t0, t1);
        m[4 * r + 3] = V::sub(zero, t1);
    }
    m
}

/// `A·y·Aᵀ` of F(2×2, 2×2) (9 places), `V::LANES` channels: `A` maps `(y₀, y₁)` to
/// `(y₀, y₀ + y₁, y₁)`.
///
/// # Safety
/// `V`'s instruction set must be available.
#[inline(always)]
unsafe fn adjoint_transform9<V: F32s>(y: &[V; 4]) -> [V; 9] {
    let mut t = [V::zero(); 6];
    for c in 0..2 {
        t[c] = y[c];
        t[2 + c] = V::add(y[c], y[2 + c]);
        t[4 + c] = y[2 + c];
    }
    let mut m = [V::zero(); 9];
    for r in 0..3 {
        let (t0, t1) = (t[2 * r], t[2 * r + 1]);
        m[3 * r] = t0;
        m[3 * r + 1] = V::add(t0, t1);
        m[3 * r + 2] = t1;
    }
    m
}

/// The end of both output transforms: `+ bias`, `max(·, 0)`, each of the 2×2 outputs stored
/// at its destination (channels `c0 ..+ V::LANES`) if it is inside the output.
///
/// # Safety
/// `V`'s instruction set; `bias` (if any) readable for channels `c0 ..+ V::LANES` (of all `co`), and `ip + a`
/// writable for channels `c ..+ V::LANES` (of the destination's piece).
#[inline(always)]
unsafe fn finish<V: F32s>(
    mut y: [V; 4], bias: Option<&[f32]>, relu: bool, ip: *mut f32, at: [Option<usize>; 4],
    c0: usize, c: usize,
) {
    if let Some(b) = bias {
        let bv = V::load(b.as_ptr().add(c0));
        for yv in y.iter_mut() {
            *yv = V::add(*yv, bv);
        }
    }
    if relu {
        for yv in y.iter_mut() {
            *yv = V::max(*yv, V::zero());
        }
    }
    for k in 0..4 {
        if let Some(a) = at[k] {
            V::store(ip.add(a + c), y[k]);
        }
    }
}

/// The output transform for f32, `P` places (16 for F(2×2, 3×3), 9 for F(2×2, 2×2)),
/// `V::LANES` channels at a time: the places' products `m[ξ·co + c]`, transformed by `transform`
/// (`Aᵀ·m·A`, the 2×2 outputs) and [`finish`]ed at their destinations.
///
/// # Safety
/// `V`'s instruction set must be available; `m` must hold `P·co` values (`co = at.len()·len`), `bias`
/// (if any) `co`, and `img[a..a + len]` be in bounds for each destination `a`; `len` a
/// multiple of `V::LANES`.
#[inline(always)]
unsafe fn output_tile_v<V: F32s, const P: usize>(
    m: &[f32], len: usize, bias: Option<&[f32]>, relu: bool, img: &mut [f32],
    at: &[[Option<usize>; 4]], transform: unsafe fn(&[V; P]) -> [V; 4],
) {
    let co = at.len() * len;
    debug_assert!(len.is_multiple_of(V::LANES) && m.len() >= P * co);
    debug_assert!(at.iter().flatten().flatten().all(|&a| a + len <= img.len()));
    let (mp, ip) = (m.as_ptr(), img.as_mut_ptr());
    for c0 in (0..co).step_by(V::LANES) {
        let j = c0 / len;
        let mut mt = [V::zero(); P];
        for (xi, mt) in mt.iter_mut().enumerate() {
            *mt = V::load(mp.add(xi * co + c0));
        }
        finish(transform(&mt), bias, relu, ip, at[j], c0, c0 - j * len);
    }
}

/// `Aᵀ·m·A` of F(2×2, 3×3), `V::LANES` channels: the portable `output_transform`'s operations.
///
/// # Safety
/// `V`'s instruction set must be available.
#[inline(always)]
unsafe fn output_transform16<V: F32s>(mt: &[V; 16]) -> [V; 4] {
    let mut s = [V::zero(); 8];
    for c in 0..4 {
        s[c] = V::add(V::add(mt[c], mt[4 + c]), mt[8 + c]);
        s[4 + c] = V::sub(V::sub(mt[4 + c], mt[8 + c]), mt[12 + c]);
    }
    let mut y = [V::zero(); 4];
    for r in 0..2 {
        let q = [s[4 * r], s[4 * r + 1], s[4 * r + 2], s[4 * r + 3]];
        y[2 * r] = V::add(V::add(q[0], q[1]), q[2]);
        y[2 * r + 1] = V::sub(V::sub(q[1], q[2]), q[3]);
    }
    y
}

/// `Aᵀ·m·A` of F(2×2, 2×2) (9 places), `V::LANES` channels: the portable `output_transform9`'s
/// operations.
///
/// # Safety
/// `V`'s instruction set must be available.
#[inline(always)]
unsafe fn output_transform9<V: F32s>(mt: &[V; 9]) -> [V; 4] {
    let mut s = [V::zero(); 6];
    for c in 0..3 {
        s[c] = V::add(mt[c], mt[3 + c]);
        s[3 + c] = V::add(mt[3 + c], mt[6 + c]);
    }
    let mut y = [V::zero(); 4];
    for r in 0..2 {
        y[2 * r] = V::add(s[3 * r], s[3 * r + 1]);
        y[2 * r + 1] = V::add(s[3 * r + 1], s[3 * r + 2]);
    }
    y
}
