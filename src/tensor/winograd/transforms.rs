//! The transforms of Winograd's minimal filtering, a tile at a time, `L` channels at a time:
//! `V = Bᵀ·d·B` for an input tile and `Y = Aᵀ·m·A` for a tile of products, by the loop
//! [`Transforms`] chose (the portable one here, or an architecture's in `tensor/x86_64/`).

use super::*;

/// Channels handled together by the transforms (one AVX-512 vector of f32).
pub(super) const L: usize = 16;

/// `L` channels of one value.
pub(super) type Lanes<T> = [T; L];

#[inline(always)]
pub(super) fn add<T: Float>(a: &Lanes<T>, b: &Lanes<T>) -> Lanes<T> {
    let mut c = *a;
    for (c, &b) in c.iter_mut().zip(b) {
        *c += b;
    }
    c
}

#[inline(always)]
pub(super) fn sub<T: Float>(a: &Lanes<T>, b: &Lanes<T>) -> Lanes<T> {
    let mut c = *a;
    for (c, &b) in c.iter_mut().zip(b) {
        *c -= b;
    }
    c
}

/// `l ≤ L` values of `src` into lanes (the rest zero).
#[inline(always)]
pub(super) fn load<T: Float>(src: &[T], l: usize) -> Lanes<T> {
    if l == L {
        // A fixed-size copy: a vector load, not a call to memcpy.
        let full: &Lanes<T> = src[..L].try_into().expect("L values");
        *full
    } else {
        let mut lanes = [T::zero(); L];
        lanes[..l].copy_from_slice(&src[..l]);
        lanes
    }
}

/// The first `l ≤ L` lanes into `dst`.
#[inline(always)]
pub(super) fn store<T: Float>(dst: &mut [T], lanes: &Lanes<T>, l: usize) {
    if l == L {
        let full: &mut Lanes<T> = (&mut dst[..L]).try_into().expect("L values");
        *full = *lanes;
    } else {
        dst[..l].copy_from_slice(&lanes[..l]);
    }
}

/// `V = Bᵀ·d·B` for a 4×4 tile `d` (row-major), lane by lane.
#[inline(always)]
pub(super) fn input_transform<T: Float>(d: &[Lanes<T>; 16]) -> [Lanes<T>; 16] {
    // Bᵀ·d, column by column: rows d₀ − d₂, d₁ + d₂, d₂ − d₁, d₁ − d₃.
    let mut t = [[T::zero(); L]; 16];
    for c in 0..4 {
        t[c] = sub(&d[c], &d[8 + c]);
        t[4 + c] = add(&d[4 + c], &d[8 + c]);
        t[8 + c] = sub(&d[8 + c], &d[4 + c]);
        t[12 + c] = sub(&d[4 + c], &d[12 + c]);
    }
    // (Bᵀ·d)·B, row by row: the same combinations of the columns.
    let mut v = [[T::zero(); L]; 16];
    for r in 0..4 {
        let row = &t[4 * r..4 * r + 4];
        v[4 * r] = sub(&row[0], &row[2]);
        v[4 * r + 1] = add(&row[1], &row[2]);
        v[4 * r + 2] = sub(&row[2], &row[1]);
        v[4 * r + 3] = sub(&row[1], &row[3]);
    }
    v
}

/// `Y = Aᵀ·m·A` for a 4×4 tile of products `m`: the 2×2 outputs, row-major.
#[inline(always)]
pub(super) fn output_transform<T: Float>(m: &[Lanes<T>; 16]) -> [Lanes<T>; 4] {
    // Aᵀ·m: rows m₀ + m₁ + m₂ and m₁ − m₂ − m₃.
    let mut s = [[T::zero(); L]; 8];
    for c in 0..4 {
        s[c] = add(&add(&m[c], &m[4 + c]), &m[8 + c]);
        s[4 + c] = sub(&sub(&m[4 + c], &m[8 + c]), &m[12 + c]);
    }
    let mut y = [[T::zero(); L]; 4];
    for r in 0..2 {
        let row = &s[4 * r..4 * r + 4];
        y[2 * r] = add(&add(&row[0], &row[1]), &row[2]);
        y[2 * r + 1] = sub(&sub(&row[1], &row[2]), &row[3]);
    }
    y
}

/// `V = Bᵀ·d·B` of F(2×2, 2×2) for a 3×3 tile of blocks `d` (row-major), lane by lane.
#[inline(always)]
pub(super) fn input_transform9<T: Float>(d: &[Lanes<T>; 9]) -> [Lanes<T>; 9] {
    // Bᵀ·d, column by column: rows d₀ − d₁, d₁, d₂ − d₁.
    let mut t = [[T::zero(); L]; 9];
    for c in 0..3 {
        t[c] = sub(&d[c], &d[3 + c]);
        t[3 + c] = d[3 + c];
        t[6 + c] = sub(&d[6 + c], &d[3 + c]);
    }
    // (Bᵀ·d)·B, row by row.
    let mut v = [[T::zero(); L]; 9];
    for r in 0..3 {
        let row = &t[3 * r..3 * r + 3];
        v[3 * r] = sub(&row[0], &row[1]);
        v[3 * r + 1] = row[1];
        v[3 * r + 2] = sub(&row[2], &row[1]);
    }
    v
}

/// `Y = Aᵀ·m·A` of F(2×2, 2×2) for a 3×3 tile of products `m`: the 2×2 outputs, row-major.
#[inline(always)]
pub(super) fn output_transform9<T: Float>(m: &[Lanes<T>; 9]) -> [Lanes<T>; 4] {
    let mut s = [[T::zero(); L]; 6];
    for c in 0..3 {
        s[c] = add(&m[c], &m[3 + c]);
        s[3 + c] = add(&m[3 + c], &m[6 + c]);
    }
    let mut y = [[T::zero(); L]; 4];
    for r in 0..2 {
        let row = &s[3 * r..3 * r + 3];
        y[2 * r] = add(&row[0], &row[1]);
        y[2 * r + 1] = add(&row[1], &row[2]);
    }
    y
}

/// One tile's output transform by the portable loop ([`output_tile`] with the transform of the
/// tile's `places`; also what the AVX2 family compiles for AVX2).
#[inline(always)]
pub(in crate::tensor) fn output_tile_portable<T: Float>(
    mt: &[T], len: usize, bias: Option<&[T]>, relu: bool, img: &mut [T], at: &[[Option<usize>; 4]],
    places: usize,
) {
    if places == 16 {
        output_tile(mt, len, bias, relu, img, at, output_transform);
    } else {
        output_tile(mt, len, bias, relu, img, at, output_transform9);
    }
}

/// One tile's input transform, all its block rows: `v[ξ·stride + dy·seg + c]` from the rows
/// `starts[k·blk + dy]` of `img` (`zeros` outside it), by the loop `path` chose
/// ([`Transforms::input`]). `stride` is `s²I` for the tile-major `V` of the forward pass, the
/// image's tiles times that for the place-major `V` of the weight gradient.
pub(super) fn input_tile_any<T: Float>(
    s: &WinogradShape, img: &[T], zeros: &[T], starts: &[Option<usize>], v: &mut [T],
    stride: usize, path: Path,
) {
    match path {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: `Transforms::choose` checked AVX-512F, that T is f32 and that `seg` is a
        // multiple of 16; every start is a block row of `seg` values inside the image (checked
        // where the table is built), `zeros` holds `seg`, `v` reaches place `places − 1` (the
        // callers' slices run to the end of their block).
        Path::Avx512 => unsafe { avx512::input_tile(s, img, zeros, starts, v, stride) },
        // SAFETY: `Transforms::choose` chose AVX2 only where the CPU runs AVX2 and FMA.
        #[cfg(target_arch = "x86_64")]
        Path::Avx2 => unsafe {
            crate::tensor::x86_64::winograd_avx2::input_tile(s, img, zeros, starts, v, stride)
        },
        _ => input_tile_portable(s, img, zeros, starts, v, stride),
    }
}

/// [`input_tile_any`]'s portable loop (also what the AVX2 family compiles for AVX2).
#[inline(always)]
pub(in crate::tensor) fn input_tile_portable<T: Float>(
    s: &WinogradShape, img: &[T], zeros: &[T], starts: &[Option<usize>], v: &mut [T], stride: usize,
) {
    let (places, seg, blk) = (s.places(), s.seg(), s.kind.block());
    // Block row dy of every position: `seg` values each, channels dy·seg.. of each place.
    for dy in 0..blk {
        let row = |k: usize| starts[k * blk + dy].map_or(zeros, |o| &img[o..o + seg]);
        let off = dy * seg;
        if places == 16 {
            let px: [&[T]; 16] = std::array::from_fn(row);
            input_tile(&px, v, stride, off, seg, input_transform);
        } else {
            let px: [&[T]; 9] = std::array::from_fn(row);
            input_tile(&px, v, stride, off, seg, input_transform9);
        }
    }
}

/// One tile's input transform for `len` channels: `V[ξ, off + c] = transform(d)[ξ][c]` (rows of
/// `V` `stride` apart) from its `P` input pixels or block rows, `L` channels at a time.
#[inline(always)]
pub(super) fn input_tile<T: Float, const P: usize>(
    px: &[&[T]; P], v: &mut [T], stride: usize, off: usize, len: usize,
    transform: fn(&[Lanes<T>; P]) -> [Lanes<T>; P],
) {
    for c0 in (0..len).step_by(L) {
        let l = (len - c0).min(L);
        let mut d = [[T::zero(); L]; P];
        for (d, px) in d.iter_mut().zip(px) {
            *d = load(&px[c0..], l);
        }
        for (xi, val) in transform(&d).iter().enumerate() {
            store(&mut v[xi * stride + off + c0..], val, l);
        }
    }
}

/// One tile's output transform from `M[ξ, o]` (`P × co`, `co = at.len()·len`): the 2×2 outputs
/// (+ bias, ReLU), channels `j·len ..+ len` of output `k` stored at `at[j][k]` in `img` if it is
/// `Some` (inside the output, and not skipped).
#[inline(always)]
pub(super) fn output_tile<T: Float, const P: usize>(
    m: &[T], len: usize, bias: Option<&[T]>, relu: bool, img: &mut [T], at: &[[Option<usize>; 4]],
    transform: fn(&[Lanes<T>; P]) -> [Lanes<T>; 4],
) {
    let co = at.len() * len;
    // Within each piece, `L` channels at a time (a short last group per piece).
    for (j, c0) in
        (0..at.len()).flat_map(|j| (j * len..(j + 1) * len).step_by(L).map(move |c| (j, c)))
    {
        let l = ((j + 1) * len - c0).min(L);
        let mut mt = [[T::zero(); L]; P];
        for (xi, mt) in mt.iter_mut().enumerate() {
            *mt = load(&m[xi * co + c0..], l);
        }
        let mut y = transform(&mt);
        if let Some(bias) = bias {
            let bl = load(&bias[c0..], l);
            for yv in y.iter_mut() {
                *yv = add(yv, &bl);
            }
        }
        if relu {
            for yv in y.iter_mut().flatten() {
                *yv = yv.max(T::zero());
            }
        }
        for (yv, at) in y.iter().zip(at[j]) {
            if let Some(at) = at {
                store(&mut img[at + c0 - j * len..], yv, l);
            }
        }
    }
}

/// Which loops a call's transforms run: chosen once per [`winograd_conv`] or
/// [`winograd_wgrad`], on the calling thread, where it is recorded ([`took_path`]); every task
/// of the call follows it. For f32 on AVX-512 the intrinsics of [`avx512`], for whole vectors
/// only; for f32 on AVX2 those of [`crate::tensor::x86_64::winograd_avx2`] (8 channels a
/// register; the portable loops compiled for AVX2 and FMA where a row is not whole vectors);
/// otherwise the portable loops. All three do the same
/// operations in the same order. The unsafe calls rely on these paths, so they are set only by
/// [`Transforms::choose`].
#[derive(Clone, Copy, Debug)]
pub(super) struct Transforms {
    /// The input transform: AVX-512 needs block rows of whole vectors (`s·I` a multiple of 16).
    pub(super) input: Path,
    /// The output transform, or its adjoint: AVX-512 needs whole vectors per output piece.
    pub(super) output: Path,
}

impl Transforms {
    /// The transforms for shape `s` whose outputs come in pieces of `len` channels.
    pub(super) fn choose<T: Float>(s: &WinogradShape, len: usize) -> Self {
        let f32 = cfg!(target_arch = "x86_64")
            && std::any::TypeId::of::<T>() == std::any::TypeId::of::<f32>();
        // `cpu::path` honours INVADERS_NO_SIMD and INVADERS_NO_AVX512 like every family.
        let path = if f32 { cpu::path() } else { Path::Portable };
        let whole = |n: usize| match path {
            Path::Avx512 if !n.is_multiple_of(L) => Path::Portable,
            p => p,
        };
        Transforms {
            input: took_path(Family::WinogradInput, whole(s.seg())),
            output: took_path(Family::WinogradOutput, whole(len)),
        }
    }

    /// The portable transforms, whatever the CPU (the SIMD ones' oracle in the tests).
    #[cfg(test)]
    pub(super) fn portable() -> Self {
        Transforms {
            input: Path::Portable,
            output: Path::Portable,
        }
    }
}
