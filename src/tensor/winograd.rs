//! Winograd's minimal filtering F(2×2, 3×3): a stride-1 3×3 convolution in 16 multiplications
//! per 2×2 output tile and channel pair instead of 36.
//!
//! In one dimension, F(2, 3) gives two outputs of a 3-tap filter `g` over four inputs `d`,
//! `y₀ = d₀g₀ + d₁g₁ + d₂g₂`, `y₁ = d₁g₀ + d₂g₁ + d₃g₂`, as `y = Aᵀ[(G·g) ⊙ (Bᵀ·d)]` with
//!
//! ```text
//!      ⎡1  0 −1  0⎤        ⎡1   0   0⎤
//! Bᵀ = ⎢0  1  1  0⎥    G = ⎢½   ½   ½⎥    Aᵀ = ⎡1  1  1  0⎤
//!      ⎢0 −1  1  0⎥        ⎢½  −½   ½⎥         ⎣0  1 −1 −1⎦
//!      ⎣0  1  0 −1⎦        ⎣0   0   1⎦
//! ```
//!
//! (four multiplications for six). Nested, a 4×4 input tile `d` gives the 2×2 outputs
//! `Y = Aᵀ[U ⊙ V]A` with `U = G·g·Gᵀ` and `V = Bᵀ·d·B`. The sum over input channels commutes
//! with `Aᵀ[·]A`, so for each of the 16 transformed places `ξ` the convolution is a matrix product
//!
//! ```text
//! M_ξ[tile, o] = Σ_i V_ξ[tile, i] · U_ξ[i, o]          Y[tile] = Aᵀ · M[tile] · A (+ bias)
//! ```
//!
//! 16 GEMMs of `tiles × I × O` (4 multiply-adds per output where the direct convolution needs 9),
//! between an input transform and an output transform that only add. `Bᵀ` and `Aᵀ` hold ±1 and 0,
//! so the transforms round little; `G`'s halves are exact in binary.
//!
//! # Strided filters: F(2×2, 2×2) over a space-to-depth view
//!
//! A `2s × 2s` filter of stride `s` (conv1: 8×8 stride 4; conv2: 4×4 stride 2) is a 2×2 filter
//! of stride 1 over the input cut into `s × s` pixel blocks, each block one "pixel" of `s²·I`
//! channels (space-to-depth: channel `(dy·s + dx)·I + i` of block `(Y, X)` is channel `i` of
//! pixel `(s·Y + dy, s·X + dx)`). F(2, 2) gives two outputs of a 2-tap filter over three inputs:
//!
//! ```text
//!      ⎡1 −1  0⎤        ⎡1  0⎤
//! Bᵀ = ⎢0  1  0⎥    G = ⎢1  1⎥    Aᵀ = ⎡1  1  0⎤
//!      ⎣0 −1  1⎦        ⎣0  1⎦         ⎣0  1  1⎦
//! ```
//!
//! (three multiplications for four), so a 3×3 tile of blocks gives 2×2 outputs from 9 products
//! where the direct convolution needs 16: 9 GEMMs of `tiles × s²I × O`. The blocks are never
//! copied: a block's channels for one `dy` are `s·I` consecutive values of the NHWC input (conv1:
//! 4 pixels × 4 frames, one vector), read in place by the input transform.
//!
//! The same routine serves a convolution's forward pass and its input gradient (the adjoint
//! convolution: the filter rotated by 180° with its channel axes swapped, [`winograd_filters`]).
//! A strided filter's adjoint is a 2×2 stride-1 convolution over blocks, `O → s²I` channels:
//! F(2×2, 2×2) with blocks of one pixel, each output "pixel" stored as its block's `s²` pixels
//! ([`winograd_filters_s2d_adjoint`], [`WinogradShape::out_pieces`]).
//! [`winograd_wgrad`] computes the weight gradient through the transforms' adjoints. Work goes in
//! chunks of whole images, enough tiles for one GEMM to fill its register tiles, whose
//! transformed inputs and products (480 KiB for two images of conv3) stay in L2; each rayon task
//! takes a contiguous run of images with its own scratch. Every output is computed from its own
//! tile in a fixed order, so the results do not depend on the thread count.

use super::cpu::{self, took_path, Family, Path};
use super::{fill_iota, Float, GatherGemm, Init};
use rayon::prelude::*;

/// Channels handled together by the transforms (one AVX-512 vector of f32).
const L: usize = 16;

/// `L` channels of one value.
type Lanes<T> = [T; L];

#[inline(always)]
fn add<T: Float>(a: &Lanes<T>, b: &Lanes<T>) -> Lanes<T> {
    let mut c = *a;
    for (c, &b) in c.iter_mut().zip(b) {
        *c += b;
    }
    c
}

#[inline(always)]
fn sub<T: Float>(a: &Lanes<T>, b: &Lanes<T>) -> Lanes<T> {
    let mut c = *a;
    for (c, &b) in c.iter_mut().zip(b) {
        *c -= b;
    }
    c
}

/// `l ≤ L` values of `src` into lanes (the rest zero).
#[inline(always)]
fn load<T: Float>(src: &[T], l: usize) -> Lanes<T> {
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
fn store<T: Float>(dst: &mut [T], lanes: &Lanes<T>, l: usize) {
    if l == L {
        let full: &mut Lanes<T> = (&mut dst[..L]).try_into().expect("L values");
        *full = *lanes;
    } else {
        dst[..l].copy_from_slice(&lanes[..l]);
    }
}

/// `V = Bᵀ·d·B` for a 4×4 tile `d` (row-major), lane by lane.
#[inline(always)]
fn input_transform<T: Float>(d: &[Lanes<T>; 16]) -> [Lanes<T>; 16] {
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
fn output_transform<T: Float>(m: &[Lanes<T>; 16]) -> [Lanes<T>; 4] {
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
fn input_transform9<T: Float>(d: &[Lanes<T>; 9]) -> [Lanes<T>; 9] {
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
fn output_transform9<T: Float>(m: &[Lanes<T>; 9]) -> [Lanes<T>; 4] {
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

/// The transformed filters `U_ξ = G·g·Gᵀ`, `[16, I, O]` (each `U_ξ` a row-major `I × O` matrix,
/// the right operand of the ξ-th GEMM), from HWIO weights `w: [3, 3, Cin, Cout]`.
///
/// Without `adjoint`, the filter of the convolution itself: `I = Cin`, `O = Cout`. With it, the
/// filter of its input gradient: `g'[ky, kx, co, ci] = w[2 − ky, 2 − kx, ci, co]` (`I = Cout`,
/// `O = Cin`), since `dX[iy, ix] = Σ dZ[iy − ky, ix − kx] · w[ky, kx]ᵀ` is a correlation of `dZ`
/// with the rotated filter.
pub fn winograd_filters<T: Float>(w: &[T], cin: usize, cout: usize, adjoint: bool, u: &mut Vec<T>) {
    assert_eq!(w.len(), 9 * cin * cout, "winograd_filters: weights");
    let (ni, no) = if adjoint { (cout, cin) } else { (cin, cout) };
    u.clear();
    u.resize(16 * ni * no, T::zero());
    let half = T::of(0.5);
    // One input channel `i` and `L` output channels at a time, in lanes on the stack (so the
    // loops vectorise and nothing is allocated): the 9 taps, G·g, then (G·g)·Gᵀ into U's rows.
    for i in 0..ni {
        for o0 in (0..no).step_by(L) {
            let l = (no - o0).min(L);
            let mut g = [[T::zero(); L]; 9];
            for (k, g) in g.iter_mut().enumerate() {
                if adjoint {
                    let (ky, kx) = (2 - k / 3, 2 - k % 3);
                    for (j, v) in g[..l].iter_mut().enumerate() {
                        *v = w[((ky * 3 + kx) * cin + o0 + j) * cout + i];
                    }
                } else {
                    *g = load(&w[(k * cin + i) * cout + o0..], l);
                }
            }
            // G·g (4×3): rows g₀, ½(g₀+g₁+g₂), ½(g₀−g₁+g₂), g₂ of each column.
            let mut gg = [[T::zero(); L]; 12];
            for c in 0..3 {
                let (g0, g1, g2) = (&g[c], &g[3 + c], &g[6 + c]);
                gg[c] = *g0;
                gg[3 + c] = std::array::from_fn(|j| half * (g0[j] + g1[j] + g2[j]));
                gg[6 + c] = std::array::from_fn(|j| half * (g0[j] - g1[j] + g2[j]));
                gg[9 + c] = *g2;
            }
            // (G·g)·Gᵀ (4×4): the same combinations of each row.
            for r in 0..4 {
                let (a, b, e) = (&gg[3 * r], &gg[3 * r + 1], &gg[3 * r + 2]);
                let row: [Lanes<T>; 4] = [
                    *a,
                    std::array::from_fn(|j| half * (a[j] + b[j] + e[j])),
                    std::array::from_fn(|j| half * (a[j] - b[j] + e[j])),
                    *e,
                ];
                for (c, val) in row.iter().enumerate() {
                    store(&mut u[((4 * r + c) * ni + i) * no + o0..], val, l);
                }
            }
        }
    }
}

/// The transformed filters of F(2×2, 2×2) over `s × s` blocks, `[9, s²·Cin, Cout]`, from HWIO
/// weights `w: [2s, 2s, Cin, Cout]`.
///
/// The block filter is `g[by, bx, (dy·s + dx)·Cin + c, o] = w[s·by + dy, s·bx + dx, c, o]`
/// (`by, bx < 2`), and `U = G·g·Gᵀ` with `G`'s rows `(1, 0)`, `(1, 1)`, `(0, 1)`: place
/// `(r, c)` is the sum of the taps `by ∈ rows[r]`, `bx ∈ rows[c]`. Sums of weights only, exact
/// up to one rounding per addition.
pub fn winograd_filters_s2d<T: Float>(w: &[T], s: usize, cin: usize, cout: usize, u: &mut Vec<T>) {
    let k = 2 * s;
    assert_eq!(w.len(), k * k * cin * cout, "winograd_filters_s2d: weights");
    let ni = s * s * cin;
    u.clear();
    u.resize(9 * ni * cout, T::zero());
    const ROWS: [&[usize]; 3] = [&[0], &[0, 1], &[1]];
    for dy in 0..s {
        for dx in 0..s {
            for c in 0..cin {
                let i = (dy * s + dx) * cin + c;
                for (r, rows) in ROWS.iter().enumerate() {
                    for (cc, cols) in ROWS.iter().enumerate() {
                        let dst = ((3 * r + cc) * ni + i) * cout;
                        for &by in *rows {
                            for &bx in *cols {
                                let src = (((s * by + dy) * k + s * bx + dx) * cin + c) * cout;
                                for o in 0..cout {
                                    u[dst + o] += w[src + o];
                                }
                            }
                        }
                    }
                }
            }
        }
    }
}

/// The transformed filters of a strided convolution's input gradient over `s × s` blocks,
/// `[9, Cout, s²·Cin]`, from HWIO weights `w: [2s, 2s, Cin, Cout]` (`wt` is scratch).
///
/// The gradient of block `(Y, X)` of the (padded) input, channel `c = (dy·s + dx)·Cin + i`
/// (pixel `(s·Y + dy, s·X + dx)`, channel `i`), collects every output the block feeds:
///
/// ```text
/// dXb[Y, X, c] = Σ_{by, bx < 2} Σ_o dZ[Y − by, X − bx, o] · w[s·by + dy, s·bx + dx, i, o]
/// ```
///
/// with `dZ` zero outside its image: a 2×2 stride-1 convolution of `dZ` padded by one pixel above
/// and to the left, with the filter `g'[ky, kx, o, c] = w[s·(1 − ky) + dy, s·(1 − kx) + dx, i, o]`
/// (rotated by 180° over blocks, channel axes swapped). That is F(2×2, 2×2) over blocks of one
/// pixel, [`WinogradKind::S2d`]`(1)`, whose `s²·Cin`-channel output "pixels" are stored as `s²`
/// pixels of `Cin` channels ([`WinogradShape::out_pieces`]).
pub fn winograd_filters_s2d_adjoint<T: Float>(
    w: &[T],
    s: usize,
    cin: usize,
    cout: usize,
    wt: &mut Vec<T>,
    u: &mut Vec<T>,
) {
    let k = 2 * s;
    assert_eq!(w.len(), k * k * cin * cout, "winograd_filters_s2d_adjoint");
    let ni = s * s * cin;
    wt.clear();
    wt.resize(4 * cout * ni, T::zero());
    for ky in 0..2 {
        for kx in 0..2 {
            for dy in 0..s {
                for dx in 0..s {
                    for i in 0..cin {
                        let src = (((s * (1 - ky) + dy) * k + s * (1 - kx) + dx) * cin + i) * cout;
                        let dst = (ky * 2 + kx) * cout * ni + (dy * s + dx) * cin + i;
                        for (o, &v) in w[src..src + cout].iter().enumerate() {
                            wt[dst + o * ni] = v;
                        }
                    }
                }
            }
        }
    }
    winograd_filters_s2d(wt, 1, cout, ni, u);
}

/// An output offset of [`winograd_conv`] that is not stored.
pub const SKIP_OUTPUT: usize = usize::MAX;

/// The most pieces an output pixel may be stored in ([`WinogradShape::out_pieces`]): `s²` for
/// blocks of up to 4 × 4 pixels.
pub const MAX_PIECES: usize = 16;

/// Which minimal filtering a [`WinogradShape`] runs (see the module documentation).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum WinogradKind {
    /// F(2×2, 3×3): a 3×3 filter of stride 1, 4×4 input tiles, 16 products.
    F2x3,
    /// F(2×2, 2×2) over `s × s` pixel blocks: a `2s × 2s` filter of stride `s`, 3×3 tiles of
    /// blocks, 9 products.
    S2d(usize),
}

impl WinogradKind {
    /// Tile positions per side (4 or 3); their square is the number of products.
    fn side(self) -> usize {
        match self {
            WinogradKind::F2x3 => 4,
            WinogradKind::S2d(_) => 3,
        }
    }

    /// The side of a block in pixels (1 for F(2×2, 3×3)).
    pub(super) fn block(self) -> usize {
        match self {
            WinogradKind::F2x3 => 1,
            WinogradKind::S2d(s) => s,
        }
    }
}

/// The sizes of one Winograd convolution (everything but the data):
///
/// ```text
/// out[n, oy, ox, o] = bias[o] + Σ_{ky,kx<3, i} x[n, oy + ky − pad_top, ox + kx − pad_left, i] · g[ky, kx, i, o]
/// ```
///
/// for [`WinogradKind::F2x3`], and with `s·oy`, `s·ox` and `ky, kx < 2s` for
/// [`WinogradKind::S2d`]`(s)`, with `x: [N, H, W, I]` read as zero outside the image, and output
/// pixel `(oy, ox)` of image `n` written at `out[n·out_image + out_pixels[oy·OW + ox] ..][..O]`,
/// or, in `out_pieces` pieces of `O / out_pieces` channels, piece `j` at
/// `out[n·out_image + out_pixels[(oy·OW + ox)·out_pieces + j] ..]`: an input gradient over
/// `s × s` blocks is `s²` pixels per output "pixel" (see [`winograd_filters_s2d_adjoint`]).
/// Pieces at [`SKIP_OUTPUT`] are not stored (a border whose gradient is left out).
#[derive(Clone, Copy, Debug)]
pub struct WinogradShape {
    pub n: usize,
    pub h: usize,
    pub w: usize,
    /// Input channels `I`.
    pub ci: usize,
    pub oh: usize,
    pub ow: usize,
    pub pad_top: usize,
    pub pad_left: usize,
    /// Output channels `O`.
    pub co: usize,
    /// Values per output image.
    pub out_image: usize,
    /// Pieces each output pixel's `O` channels are stored in (1: together).
    pub out_pieces: usize,
    pub kind: WinogradKind,
}

impl WinogradShape {
    fn tiles(&self) -> (usize, usize) {
        (self.oh.div_ceil(2), self.ow.div_ceil(2))
    }

    /// Products per tile: 16 or 9.
    pub(super) fn places(&self) -> usize {
        self.kind.side() * self.kind.side()
    }

    /// Values one input block contributes per `dy` (a row of `s` pixels).
    pub(super) fn seg(&self) -> usize {
        self.kind.block() * self.ci
    }

    /// Channels of a transformed place: `s²·I`.
    fn channels(&self) -> usize {
        self.kind.block() * self.seg()
    }

    /// Values from one tile's block of `V` to the next: its `P·s²I` values and `L` unused, so
    /// the same place of consecutive tiles is not a multiple of 4 KiB apart (for conv3,
    /// 16 × 64 values are exactly 4 KiB): a GEMM walking down the tiles would otherwise find
    /// every row in the same L1 set.
    fn v_stride(&self) -> usize {
        self.places() * self.channels() + L
    }

    /// Likewise for `M` (and `dM`): `P·O` values and `L` unused per tile.
    fn m_stride(&self) -> usize {
        self.places() * self.co + L
    }
}

/// The scratch of [`winograd_conv`]: per task, the transformed inputs `V [tiles, P, s²I]`, the
/// products `M [tiles, P, O]` (each tile's `P` = 16 or 9 transformed places together, so the transforms
/// read and write one contiguous block per tile) and the GEMM's offset tables. Kept between calls, so a train step
/// allocates nothing.
#[derive(Debug, Default)]
pub struct WinogradScratch<T> {
    parts: Vec<Part<T>>,
    /// Where each tile position's input pixels (block rows: `[tile, position, dy]`) start in an
    /// image (`None` outside it): the same for every image, so worked out once per call.
    pixels: Vec<Option<usize>>,
    /// The weight gradient's `dU [16, I, O]` ([`winograd_wgrad`]).
    du: Vec<T>,
}

#[derive(Debug, Default)]
struct Part<T> {
    /// `s·I` zeros: the input pixels (block rows) of a tile that lie outside the image.
    zeros: Vec<T>,
    v: Vec<T>,
    m: Vec<T>,
    p: Vec<usize>,
    q: Vec<usize>,
}

/// The convolution of [`WinogradShape`] by its [`WinogradKind`]: `u` from [`winograd_filters`]
/// (F(2×2, 3×3)), [`winograd_filters_s2d`] (F(2×2, 2×2) over blocks) or
/// [`winograd_filters_s2d_adjoint`] (a strided filter's input gradient), `bias` (`O` values)
/// added if given, `max(·, 0)` stored if `relu`. Writes only the output pixels (the pieces not
/// at [`SKIP_OUTPUT`]).
#[allow(clippy::too_many_arguments)]
pub fn winograd_conv<T: Float>(
    s: WinogradShape,
    x: &[T],
    u: &[T],
    bias: Option<&[T]>,
    relu: bool,
    out: &mut [T],
    out_pixels: &[usize],
    scratch: &mut WinogradScratch<T>,
) {
    assert_eq!(x.len(), s.n * s.h * s.w * s.ci, "winograd_conv: input");
    assert_eq!(
        u.len(),
        s.places() * s.channels() * s.co,
        "winograd_conv: filters"
    );
    let pieces = s.out_pieces;
    assert!(
        (1..=MAX_PIECES).contains(&pieces) && s.co.is_multiple_of(pieces),
        "winograd_conv: {} channels in {pieces} pieces",
        s.co
    );
    assert_eq!(
        out_pixels.len(),
        s.oh * s.ow * pieces,
        "winograd_conv: output pixels"
    );
    assert!(
        out_pixels.iter().all(|&o| o == SKIP_OUTPUT
            || o.checked_add(s.co / pieces)
                .is_some_and(|e| e <= s.out_image)),
        "winograd_conv: output pixel outside its image"
    );
    assert!(out.len() >= s.n * s.out_image, "winograd_conv: output");
    if let Some(b) = bias {
        assert_eq!(b.len(), s.co, "winograd_conv: bias");
    }
    if let WinogradKind::S2d(blk) = s.kind {
        // A block row is read whole or not at all, so every output's blocks must lie inside
        // the image across (rows are checked one by one: any top padding is fine). An input
        // padded already, a VALID convolution over it, as `Conv2d` passes it, satisfies this;
        // so does any input with blocks of one pixel.
        assert!(
            blk == 1 || (blk > 0 && s.pad_left == 0 && blk * (s.ow + 1) <= s.w),
            "winograd_conv: blocks of {blk} need no left padding and an input wide enough"
        );
    }
    if s.n == 0 || s.oh == 0 || s.ow == 0 {
        return;
    }
    let (ty, tx) = s.tiles();
    // Images per chunk: at least 48 GEMM rows (tiles) where the batch allows. For conv3 that is
    // 2 images, 60 tiles: V and M (60 × 16 × 64 values each, 480 KiB together) stay in L2
    // between the transforms and the products. (At least 128 tiles, 5 images and 1.2 MiB,
    // measured 3% slower on the train step; one image, 30 tiles, 1% slower.)
    let per_chunk = 48usize.div_ceil(ty * tx).min(s.n);
    let fast = Transforms::choose::<T>(&s, s.co / pieces);
    input_offsets(&s, &mut scratch.pixels);
    let pixels = &scratch.pixels[..];
    // A contiguous run of images per thread, each with its own scratch.
    let per_part = s.n.div_ceil(rayon::current_num_threads().max(1));
    let parts = s.n.div_ceil(per_part);
    if scratch.parts.len() < parts {
        scratch.parts.resize_with(parts, Part::default);
    }
    out[..s.n * s.out_image]
        .par_chunks_mut(per_part * s.out_image)
        .zip(scratch.parts.par_iter_mut())
        .enumerate()
        .for_each(|(pi, (out, part))| {
            for (ci, chunk) in out.chunks_mut(per_chunk * s.out_image).enumerate() {
                let first = pi * per_part + ci * per_chunk;
                let images = chunk.len() / s.out_image;
                let xs = &x[first * s.h * s.w * s.ci..][..images * s.h * s.w * s.ci];
                let job = Chunk {
                    s,
                    fast,
                    images,
                    x: xs,
                    u,
                    bias,
                    relu,
                    pixels,
                    out_pixels,
                };
                job.run(chunk, part);
            }
        });
}

/// Fills `pixels` (`[tile, position, dy]`) with where each tile position's block rows start in
/// an image (`None` outside it).
///
/// Position k of tile (a, b) is block (2a + k / side, 2b + k % side); its row dy starts at pixel
/// (blk·(2a + k / side) + dy, blk·(2b + k % side)), counted only if all `blk` pixels of the row
/// are inside (a row cut by the edge feeds only dropped outputs).
fn input_offsets(s: &WinogradShape, pixels: &mut Vec<Option<usize>>) {
    let (ty, tx) = s.tiles();
    let (places, blk, side) = (s.places(), s.kind.block(), s.kind.side());
    pixels.clear();
    for a in 0..ty {
        for b in 0..tx {
            for k in 0..places {
                pixels.extend((0..blk).map(|dy| {
                    let iy = (blk * (2 * a + k / side) + dy).checked_sub(s.pad_top)?;
                    let ix = (blk * (2 * b + k % side)).checked_sub(s.pad_left)?;
                    (iy < s.h && ix + blk <= s.w).then_some((iy * s.w + ix) * s.ci)
                }));
            }
        }
    }
}

/// The weight gradient of a Winograd convolution (no bias, no ReLU: `dz` is the gradient of the
/// plain sum, `[N, OH, OW, O]`), added to `dw` (`[3, 3, I, O]`, or `[2s, 2s, I, O]` for
/// [`WinogradKind::S2d`]`(s)`).
///
/// The forward pass is `Y = Aᵀ[Σ_i U_i ⊙ V_i]A` per tile with `U = G·g·Gᵀ`, so by the chain
/// rule, adjoint by adjoint:
///
/// ```text
/// dM = A·dY·Aᵀ                                (2×2 → 4×4: the output transform's adjoint)
/// dU_ξ[i, o] = Σ_tiles V_ξ[tile, i] · dM_ξ[tile, o]     (16 GEMMs reducing over the tiles)
/// dg = Gᵀ·dU·G                                (4×4 → 3×3: the filter transform's adjoint)
/// ```
///
/// (9 places, 3×3 and 2×2 for F(2×2, 2×2) over blocks, whose `dg` is then put back from the
/// block filter into the `2s × 2s` one.) `dM` is zero for the outputs a tile has past an odd
/// edge (dropped in the forward pass). The GEMMs do 4 multiply-adds per input pixel and filter
/// pair where the direct weight gradient does 9 (9 where it does 16 over blocks), and reduce
/// over all tiles of the batch. Chunks of images go one after another and
/// every `dU` value sums its chunks in order, so the result does not depend on the thread
/// count; within a chunk, images are transformed in parallel and the 16 GEMMs run in parallel.
pub fn winograd_wgrad<T: Float>(
    s: WinogradShape,
    x: &[T],
    dz: &[T],
    dw: &mut [T],
    scratch: &mut WinogradScratch<T>,
) {
    let k = match s.kind {
        WinogradKind::F2x3 => 3,
        WinogradKind::S2d(blk) => 2 * blk,
    };
    assert_eq!(x.len(), s.n * s.h * s.w * s.ci, "winograd_wgrad: input");
    assert_eq!(dz.len(), s.n * s.oh * s.ow * s.co, "winograd_wgrad: dz");
    assert_eq!(dw.len(), k * k * s.ci * s.co, "winograd_wgrad: dw");
    if let WinogradKind::S2d(blk) = s.kind {
        assert!(
            blk > 0 && s.pad_left == 0 && blk * (s.ow + 1) <= s.w,
            "winograd_wgrad: blocks of {blk} need no left padding and an input wide enough"
        );
    }
    if s.n == 0 || s.oh == 0 || s.ow == 0 {
        return;
    }
    let (ty, tx) = s.tiles();
    // `ci` here is a transformed place's channel count (s²·I over blocks).
    let (places, ci, co, seg) = (s.places(), s.channels(), s.co, s.seg());
    // 4 images of conv3 per chunk: 120 tiles, V and dM 480 KiB each, in L2.
    let per_chunk = 96usize.div_ceil(ty * tx).min(s.n);
    let fast = Transforms::choose::<T>(&s, co);
    input_offsets(&s, &mut scratch.pixels);
    if scratch.parts.is_empty() {
        scratch.parts.push(Part::default());
    }
    let part = &mut scratch.parts[0];
    let img_tiles = ty * tx;
    let rows = per_chunk * img_tiles;
    part.v
        .resize(part.v.len().max(places * rows * ci), T::zero());
    part.m
        .resize(part.m.len().max(places * rows * co), T::zero());
    part.zeros.resize(part.zeros.len().max(seg), T::zero());
    scratch.du.clear();
    scratch.du.resize(places * ci * co, T::zero());
    let (image, dz_image) = (s.h * s.w * s.ci, s.oh * s.ow * co);
    // The products reduce over tiles, so each place's values for consecutive tiles lie next
    // to each other (`I` or `O` apart), not a whole tile's block apart: a 4 KiB stride per step
    // (conv3's 16 × 64 values) would touch a new page, and a new TLB entry, at every step.
    for first in (0..s.n).step_by(per_chunk) {
        let images = per_chunk.min(s.n - first);
        let tiles = images * img_tiles;
        let (v, m) = (
            &mut part.v[..places * tiles * ci],
            &mut part.m[..places * tiles * co],
        );
        let (zeros, pixels) = (&part.zeros[..seg], &scratch.pixels[..]);
        // V `[image, ξ, tile, I]` (the forward pass's input transform), image by image in
        // parallel; dM `[ξ, chunk tile, O]`.
        let xs = &x[first * image..][..images * image];
        let dzs = &dz[first * dz_image..][..images * dz_image];
        v.par_chunks_mut(places * img_tiles * ci)
            .zip(xs.par_chunks(image))
            .for_each(|(v, x)| {
                let job = Chunk {
                    s,
                    fast,
                    images: 1,
                    x,
                    u: &[],
                    bias: None,
                    relu: false,
                    pixels,
                    out_pixels: &[],
                };
                job.input_by_place(v, zeros);
            });
        output_adjoint(&s, dzs, m, fast.output);
        // dU_ξ += V_ξᵀ · dM_ξ: rows are input channels, the reduction runs over the chunk's
        // tiles (gathered from V image by image; dM's rows in order).
        fill_iota(&mut part.p, ci, 1);
        part.q.clear();
        for img in 0..images {
            part.q
                .extend((0..img_tiles).map(|t| (img * places * img_tiles + t) * ci));
        }
        let (p, q, v, m) = (&part.p[..], &part.q[..], &*v, &*m);
        scratch
            .du
            .par_chunks_mut(ci * co)
            .enumerate()
            .for_each(|(xi, du)| {
                T::gather_gemm(GatherGemm {
                    a: &v[xi * img_tiles * ci..],
                    p,
                    q,
                    b: &m[xi * tiles * co..][..tiles * co],
                    ldb: co,
                    n: co,
                    c: du,
                    ldc: co,
                    c_rows: None,
                    init: Init::Accumulate,
                    relu: false,
                })
            });
    }
    match s.kind {
        WinogradKind::F2x3 => filter_adjoint(&scratch.du, ci, co, dw),
        WinogradKind::S2d(blk) => filter_adjoint_s2d(&scratch.du, blk, s.ci, co, dw),
    }
}

/// `dM = A·dY·Aᵀ` for every tile of a chunk of images: `dz` `[images, OH, OW, O]` into `m`
/// `[ξ, tiles, O]`, zeros for outputs past the edge. In one dimension `A` maps `(y₀, y₁)` to
/// `(y₀, y₀ + y₁, y₀ − y₁, −y₁)`: the transpose of `Aᵀ`'s rows `m₀ + m₁ + m₂` and
/// `m₁ − m₂ − m₃`. (A few adds per value: one thread does the whole chunk.)
///
/// `path`: the loop [`Transforms::output`] chose.
fn output_adjoint<T: Float>(s: &WinogradShape, dz: &[T], m: &mut [T], path: Path) {
    let (ty, tx) = s.tiles();
    let co = s.co;
    let places = s.places();
    let stride = m.len() / places;
    let mut t = 0;
    for img in dz.chunks_exact(s.oh * s.ow * co) {
        for a in 0..ty {
            for b in 0..tx {
                // Where each of the tile's outputs starts in `img` (None past the edge).
                let at: [Option<usize>; 4] = std::array::from_fn(|k| {
                    let (oy, ox) = (2 * a + k / 2, 2 * b + k % 2);
                    (oy < s.oh && ox < s.ow).then_some((oy * s.ow + ox) * co)
                });
                let mt = &mut m[t * co..];
                t += 1;
                match path {
                    #[cfg(target_arch = "x86_64")]
                    Path::Avx512 => {
                        let (img32, mt32) = (
                            bytemuck::cast_slice::<T, f32>(img),
                            bytemuck::cast_slice_mut::<T, f32>(mt),
                        );
                        // SAFETY: AVX-512F, T = f32 and `co` a multiple of 16 checked
                        // (`Transforms::choose`); every `Some` output holds `co` values inside
                        // the image; `mt` reaches the last place of this tile (`t` is below
                        // the chunk's tile count, `stride / co`).
                        unsafe {
                            if places == 16 {
                                avx512::adjoint_tile(img32, at, mt32, stride, co)
                            } else {
                                avx512::adjoint_tile9(img32, at, mt32, stride, co)
                            }
                        }
                    }
                    // SAFETY: chosen only where the CPU runs AVX2 and FMA.
                    #[cfg(target_arch = "x86_64")]
                    Path::Avx2 => unsafe {
                        super::x86_64::winograd_avx2::adjoint_tile(img, at, mt, stride, co, places)
                    },
                    _ => adjoint_tile_portable(img, at, mt, stride, co, places),
                }
            }
        }
    }
}

/// One tile of [`output_adjoint`] by the portable loop (also what the AVX2 family compiles for
/// AVX2): the outputs `at` of `img` (zeros where `None`) into `mt`, places `stride` apart.
#[inline(always)]
pub(super) fn adjoint_tile_portable<T: Float>(
    img: &[T],
    at: [Option<usize>; 4],
    mt: &mut [T],
    stride: usize,
    co: usize,
    places: usize,
) {
    let zeros = [T::zero(); L];
    // A·dY, column by column, then ·Aᵀ, row by row: with F(2×2, 3×3)'s `A`,
    // (y₀, y₁) ↦ (y₀, y₀ + y₁, y₀ − y₁, −y₁); with F(2×2, 2×2)'s, (y₀, y₀ + y₁, y₁).
    let side = if places == 16 { 4 } else { 3 };
    let a1 = |y0: &Lanes<T>, y1: &Lanes<T>| -> [Lanes<T>; 4] {
        if side == 4 {
            [*y0, add(y0, y1), sub(y0, y1), sub(&zeros, y1)]
        } else {
            [*y0, add(y0, y1), *y1, zeros]
        }
    };
    for c0 in (0..co).step_by(L) {
        let l = (co - c0).min(L);
        let y: [Lanes<T>; 4] =
            std::array::from_fn(|k| at[k].map_or(zeros, |o| load(&img[o + c0..], l)));
        let cols = [a1(&y[0], &y[2]), a1(&y[1], &y[3])];
        for r in 0..side {
            let row = a1(&cols[0][r], &cols[1][r]);
            for (c, val) in row[..side].iter().enumerate() {
                store(&mut mt[(side * r + c) * stride + c0..], val, l);
            }
        }
    }
}

/// `dw[ky, kx, i, o] += (Gᵀ·dU_{·}[i, o]·G)[ky, kx]`: the adjoint of [`winograd_filters`]. In one
/// dimension `Gᵀ` maps `(u₀, u₁, u₂, u₃)` to `(u₀ + ½u₁ + ½u₂, ½u₁ − ½u₂, ½u₁ + ½u₂ + u₃)`.
fn filter_adjoint<T: Float>(du: &[T], ci: usize, co: usize, dw: &mut [T]) {
    let half = T::of(0.5);
    let gt = |u: [T; 4]| -> [T; 3] {
        [
            u[0] + half * u[1] + half * u[2],
            half * u[1] - half * u[2],
            half * u[1] + half * u[2] + u[3],
        ]
    };
    for i in 0..ci {
        for o in 0..co {
            let u: [T; 16] = std::array::from_fn(|xi| du[(xi * ci + i) * co + o]);
            // Gᵀ on the left (each column), then G on the right (each row).
            let cols: [[T; 3]; 4] =
                std::array::from_fn(|c| gt([u[c], u[4 + c], u[8 + c], u[12 + c]]));
            for ky in 0..3 {
                let row = gt([cols[0][ky], cols[1][ky], cols[2][ky], cols[3][ky]]);
                for (kx, &val) in row.iter().enumerate() {
                    dw[((ky * 3 + kx) * ci + i) * co + o] += val;
                }
            }
        }
    }
}

/// The adjoint of [`winograd_filters_s2d`]: `dU [9, s²·Cin, Cout]` to the block filter's
/// gradient `dg = Gᵀ·dU·G` (in one dimension `(u₀, u₁, u₂) ↦ (u₀ + u₁, u₁ + u₂)`), added into
/// `dw [2s, 2s, Cin, Cout]` at `dw[s·by + dy, s·bx + dx, c] += dg[by, bx, (dy·s + dx)·Cin + c]`.
fn filter_adjoint_s2d<T: Float>(du: &[T], s: usize, cin: usize, cout: usize, dw: &mut [T]) {
    let k = 2 * s;
    let ni = s * s * cin;
    let gt = |u: [T; 3]| -> [T; 2] { [u[0] + u[1], u[1] + u[2]] };
    for dy in 0..s {
        for dx in 0..s {
            for c in 0..cin {
                let i = (dy * s + dx) * cin + c;
                for o in 0..cout {
                    let u: [T; 9] = std::array::from_fn(|xi| du[(xi * ni + i) * cout + o]);
                    // Gᵀ on the left (each column), then G on the right (each row).
                    let cols: [[T; 2]; 3] =
                        std::array::from_fn(|cc| gt([u[cc], u[3 + cc], u[6 + cc]]));
                    for by in 0..2 {
                        let row = gt([cols[0][by], cols[1][by], cols[2][by]]);
                        for (bx, &val) in row.iter().enumerate() {
                            dw[(((s * by + dy) * k + s * bx + dx) * cin + c) * cout + o] += val;
                        }
                    }
                }
            }
        }
    }
}

/// A run of whole images through the three stages.
struct Chunk<'a, T> {
    s: WinogradShape,
    /// Which transforms run on AVX-512, chosen once for the whole call.
    fast: Transforms,
    images: usize,
    x: &'a [T],
    u: &'a [T],
    bias: Option<&'a [T]>,
    relu: bool,
    /// The input offsets of [`WinogradScratch::pixels`].
    pixels: &'a [Option<usize>],
    out_pixels: &'a [usize],
}

impl<T: Float> Chunk<'_, T> {
    fn run(&self, out: &mut [T], part: &mut Part<T>) {
        let s = self.s;
        let (ty, tx) = s.tiles();
        let rows = self.images * ty * tx;
        let (places, ch, seg) = (s.places(), s.channels(), s.seg());
        // Grown, never shrunk: a short last chunk leaves the buffers' tails alone.
        let (vs, ms) = (s.v_stride(), s.m_stride());
        let (nv, nm) = (rows * vs, rows * ms);
        if part.v.len() < nv {
            part.v.resize(nv, T::zero());
        }
        if part.m.len() < nm {
            part.m.resize(nm, T::zero());
        }
        if part.zeros.len() < seg {
            part.zeros.resize(seg, T::zero());
        }
        let (v, m) = (&mut part.v[..nv], &mut part.m[..nm]);
        self.input(v, &part.zeros[..seg]);
        // M_ξ = V_ξ · U_ξ: rows are tiles (`v_stride` apart in V, `m_stride` in M), the
        // reduction runs over the transformed channels.
        fill_iota(&mut part.p, rows, vs);
        fill_iota(&mut part.q, ch, 1);
        for xi in 0..places {
            T::gather_gemm(GatherGemm {
                a: &v[xi * ch..],
                p: &part.p,
                q: &part.q,
                b: &self.u[xi * ch * s.co..][..ch * s.co],
                ldb: s.co,
                n: s.co,
                c: &mut m[xi * s.co..],
                ldc: ms,
                c_rows: None,
                init: Init::Zero,
                relu: false,
            });
        }
        self.output(m, out);
    }

    /// `V[tile, ξ, c]` for every tile of the chunk: tile `(ty, tx)` covers the blocks (pixels
    /// for F(2×2, 3×3)) `2·ty ..+ side` and `2·tx ..+ side`, less the padding (zeros outside
    /// the image). `pixels`: where each tile position's block rows start in an image.
    fn input(&self, v: &mut [T], zeros: &[T]) {
        let s = self.s;
        let (places, blk) = (s.places(), s.kind.block());
        let mut tiles = v.chunks_exact_mut(s.v_stride());
        for img in self.x.chunks_exact(s.h * s.w * s.ci) {
            for starts in self.pixels.chunks_exact(places * blk) {
                let vt = tiles.next().expect("one V block per tile");
                input_tile_any(&s, img, zeros, starts, vt, s.channels(), self.fast.input);
            }
        }
    }

    /// [`Chunk::input`] for one image into `V [ξ, tile, s²I]` (each place's tiles together, for
    /// a product that reduces over the tiles) instead of `[tile, ξ, s²I]`.
    fn input_by_place(&self, v: &mut [T], zeros: &[T]) {
        let s = self.s;
        let (places, ch, blk) = (s.places(), s.channels(), s.kind.block());
        let (ty, tx) = s.tiles();
        let stride = ty * tx * ch;
        assert!(self.images == 1 && v.len() >= places * stride);
        for (t, starts) in self.pixels.chunks_exact(places * blk).enumerate() {
            let vt = &mut v[t * ch..];
            input_tile_any(&s, self.x, zeros, starts, vt, stride, self.fast.input);
        }
    }

    /// `Y = Aᵀ·M·A` (+ bias, ReLU) for every tile, stored where the output pixels go (the
    /// second row or column of a tile past an odd output edge is dropped).
    fn output(&self, m: &[T], out: &mut [T]) {
        let s = self.s;
        let (ty, tx) = s.tiles();
        let (pieces, places) = (s.out_pieces, s.places());
        let len = s.co / pieces;
        let path = self.fast.output;
        let mut tiles = m.chunks_exact(s.m_stride());
        // Where piece `j` of each of a tile's 2×2 outputs goes (channels `j·len ..+ len`).
        let mut at = [[None; 4]; MAX_PIECES];
        let at = &mut at[..pieces];
        for img in out.chunks_exact_mut(s.out_image) {
            for a in 0..ty {
                for b in 0..tx {
                    let mt = tiles.next().expect("one M block per tile");
                    for (k, (oy, ox)) in [(0, 0), (0, 1), (1, 0), (1, 1)].into_iter().enumerate() {
                        let (oy, ox) = (2 * a + oy, 2 * b + ox);
                        let first = (oy * s.ow + ox) * pieces;
                        for (j, at) in at.iter_mut().enumerate() {
                            at[k] = if oy < s.oh && ox < s.ow {
                                Some(self.out_pixels[first + j]).filter(|&o| o != SKIP_OUTPUT)
                            } else {
                                None
                            };
                        }
                    }
                    let (at, bias, relu) = (&at[..], self.bias, self.relu);
                    match path {
                        #[cfg(target_arch = "x86_64")]
                        Path::Avx512 => {
                            let bias = bias.map(bytemuck::cast_slice::<T, f32>);
                            let (mt32, img32) = (
                                bytemuck::cast_slice::<T, f32>(mt),
                                bytemuck::cast_slice_mut::<T, f32>(img),
                            );
                            // SAFETY: AVX-512F, T = f32 and `len` a multiple of 16 checked
                            // (`Transforms::choose`); `mt` holds places·co values, the bias
                            // `co`, each destination `len` inside the image (checked on entry).
                            unsafe {
                                if places == 16 {
                                    avx512::output_tile(mt32, len, bias, relu, img32, at)
                                } else {
                                    avx512::output_tile9(mt32, len, bias, relu, img32, at)
                                }
                            }
                        }
                        // SAFETY: chosen only where the CPU runs AVX2 and FMA.
                        #[cfg(target_arch = "x86_64")]
                        Path::Avx2 => unsafe {
                            super::x86_64::winograd_avx2::output_tile(
                                mt, len, bias, relu, img, at, places,
                            )
                        },
                        _ => output_tile_portable(mt, len, bias, relu, img, at, places),
                    }
                }
            }
        }
    }
}

/// One tile's output transform by the portable loop ([`output_tile`] with the transform of the
/// tile's `places`; also what the AVX2 family compiles for AVX2).
#[inline(always)]
pub(super) fn output_tile_portable<T: Float>(
    mt: &[T],
    len: usize,
    bias: Option<&[T]>,
    relu: bool,
    img: &mut [T],
    at: &[[Option<usize>; 4]],
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
fn input_tile_any<T: Float>(
    s: &WinogradShape,
    img: &[T],
    zeros: &[T],
    starts: &[Option<usize>],
    v: &mut [T],
    stride: usize,
    path: Path,
) {
    match path {
        #[cfg(target_arch = "x86_64")]
        Path::Avx512 => {
            let (places, seg, blk) = (s.places(), s.seg(), s.kind.block());
            let img32 = bytemuck::cast_slice::<T, f32>(img);
            let z32 = bytemuck::cast_slice::<T, f32>(zeros);
            let v32 = bytemuck::cast_slice_mut::<T, f32>(v);
            // SAFETY: `Transforms::choose` checked AVX-512F, that T is f32 and that `seg` is a
            // multiple of 16; every start is a block row of `seg` values inside the image
            // (checked where the table is built), `zeros` holds `seg`, `v` reaches place
            // `places − 1` (the callers' slices run to the end of their block).
            unsafe {
                if places == 16 {
                    avx512::input_tile(img32, z32, starts, v32, stride, blk, seg)
                } else {
                    avx512::input_tile9(img32, z32, starts, v32, stride, blk, seg)
                }
            }
        }
        // SAFETY: `Transforms::choose` chose AVX2 only where the CPU runs AVX2 and FMA.
        #[cfg(target_arch = "x86_64")]
        Path::Avx2 => unsafe {
            super::x86_64::winograd_avx2::input_tile(s, img, zeros, starts, v, stride)
        },
        _ => input_tile_portable(s, img, zeros, starts, v, stride),
    }
}

/// [`input_tile_any`]'s portable loop (also what the AVX2 family compiles for AVX2).
#[inline(always)]
pub(super) fn input_tile_portable<T: Float>(
    s: &WinogradShape,
    img: &[T],
    zeros: &[T],
    starts: &[Option<usize>],
    v: &mut [T],
    stride: usize,
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
fn input_tile<T: Float, const P: usize>(
    px: &[&[T]; P],
    v: &mut [T],
    stride: usize,
    off: usize,
    len: usize,
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
fn output_tile<T: Float, const P: usize>(
    m: &[T],
    len: usize,
    bias: Option<&[T]>,
    relu: bool,
    img: &mut [T],
    at: &[[Option<usize>; 4]],
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
/// only; for f32 on AVX2 the portable loops compiled for AVX2 and FMA
/// ([`super::x86_64::winograd_avx2`]); otherwise the portable loops. All three do the same
/// operations in the same order. The unsafe calls rely on these paths, so they are set only by
/// [`Transforms::choose`].
#[derive(Clone, Copy, Debug)]
struct Transforms {
    /// The input transform: AVX-512 needs block rows of whole vectors (`s·I` a multiple of 16).
    input: Path,
    /// The output transform, or its adjoint: AVX-512 needs whole vectors per output piece.
    output: Path,
}

impl Transforms {
    /// The transforms for shape `s` whose outputs come in pieces of `len` channels.
    fn choose<T: Float>(s: &WinogradShape, len: usize) -> Self {
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
    fn portable() -> Self {
        Transforms {
            input: Path::Portable,
            output: Path::Portable,
        }
    }
}

#[cfg(target_arch = "x86_64")]
use super::x86_64::winograd_avx512 as avx512;

#[cfg(test)]
mod tests {
    //! The AVX-512 and AVX2 transforms against their portable twins, bit for bit: each is the
    //! same additions and subtractions in the same order, lane by lane (no multiplication, no
    //! fused operation), so any difference is a wrong index or a wrong sign.
    use super::*;
    use crate::tensor::cpu;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// The loop this host must run the transforms on, judged without the library's check:
    /// AVX-512 on x86-64 with AVX-512F and FMA, AVX2 with AVX2 and FMA, unless
    /// `INVADERS_NO_SIMD` (both) or `INVADERS_NO_AVX512` (the first) is set. Says once where
    /// the SIMD loops are not checked.
    fn host_path() -> Path {
        #[cfg(target_arch = "x86_64")]
        let (avx512, avx2) = (
            is_x86_feature_detected!("avx512f") && is_x86_feature_detected!("fma"),
            is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma"),
        );
        #[cfg(not(target_arch = "x86_64"))]
        let (avx512, avx2) = (false, false);
        let simd = std::env::var_os("INVADERS_NO_SIMD").is_none();
        let path = if avx512 && simd && std::env::var_os("INVADERS_NO_AVX512").is_none() {
            Path::Avx512
        } else if avx2 && simd {
            Path::Avx2
        } else {
            Path::Portable
        };
        if path != Path::Avx512 {
            static NOTE: std::sync::Once = std::sync::Once::new();
            #[allow(clippy::print_stderr)] // a test's note
            NOTE.call_once(|| {
                eprintln!(
                    "skip: the AVX-512 Winograd transforms are not checked here ({}); the \
                     {path:?} ones are compared with the portable loops",
                    cpu::why_portable().unwrap_or_default()
                )
            });
        }
        assert_eq!(cpu::path(), path, "the library's CPU check disagrees");
        path
    }

    /// One recorded call of `path`.
    fn once(path: Path) -> cpu::Paths {
        cpu::Paths {
            avx512: u64::from(path == Path::Avx512),
            portable: u64::from(path == Path::Portable),
            avx2: u64::from(path == Path::Avx2),
        }
    }

    fn values(n: usize, rng: &mut ChaCha8Rng) -> Vec<f32> {
        (0..n).map(|_| rng.random_range(-1.0f32..1.0)).collect()
    }

    fn same_bits(what: &str, a: &[f32], b: &[f32]) {
        assert_eq!(a.len(), b.len(), "{what}: lengths");
        for (i, (x, y)) in a.iter().zip(b).enumerate() {
            assert!(x.to_bits() == y.to_bits(), "{what}[{i}]: {x} vs {y}");
        }
    }

    /// The shapes the layers run, small, and one of odd channel counts: F(2×2, 3×3) with odd
    /// output edges (a tile's second row and column dropped) and padding; F(2×2, 2×2) over
    /// 2×2 blocks (conv2) and 4×4 blocks of 4 channels (conv1's, 16 values per block row);
    /// over blocks of one pixel with the output in 4 pieces (conv2's input gradient).
    fn shapes() -> Vec<WinogradShape> {
        let shape = |h, w, ci, oh, ow, pad, co, pieces, kind| WinogradShape {
            n: 3,
            h,
            w,
            ci,
            oh,
            ow,
            pad_top: pad,
            pad_left: pad,
            co,
            out_image: oh * ow * co,
            out_pieces: pieces,
            kind,
        };
        vec![
            shape(9, 7, 16, 9, 7, 1, 32, 1, WinogradKind::F2x3),
            shape(6, 6, 64, 4, 4, 0, 64, 1, WinogradKind::F2x3),
            shape(12, 12, 32, 5, 5, 0, 64, 1, WinogradKind::S2d(2)),
            shape(16, 16, 4, 3, 3, 0, 32, 1, WinogradKind::S2d(4)),
            shape(5, 5, 64, 6, 6, 1, 128, 4, WinogradKind::S2d(1)),
            // Rows of 12 input and 20 output channels: no whole vectors for any SIMD loop.
            shape(5, 5, 12, 5, 5, 1, 20, 1, WinogradKind::F2x3),
        ]
    }

    /// Each shape's transforms as chosen for f32 (recorded on this thread) and as the portable
    /// loops, with the path asserted: the host's SIMD family where it runs one, else portable.
    fn twins(s: &WinogradShape, len: usize) -> (Transforms, Transforms) {
        let before = (
            cpu::paths(Family::WinogradInput),
            cpu::paths(Family::WinogradOutput),
        );
        let fast = Transforms::choose::<f32>(s, len);
        let path = host_path();
        assert_eq!((fast.input, fast.output), (path, path), "{s:?}");
        let ran = (
            cpu::paths(Family::WinogradInput).since(before.0),
            cpu::paths(Family::WinogradOutput).since(before.1),
        );
        assert_eq!(ran, (once(path), once(path)), "recorded paths");
        let f64s = Transforms::choose::<f64>(s, len);
        assert_eq!(
            (f64s.input, f64s.output),
            (Path::Portable, Path::Portable),
            "f64 runs the portable loops"
        );
        (fast, Transforms::portable())
    }

    /// The transforms take their AVX-512 loops only for whole vectors: block rows of 8 input
    /// values and pieces of 24 output channels stay portable on an AVX-512 host. The AVX2
    /// loops (the portable ones compiled for AVX2) take any length.
    #[test]
    fn transforms_need_whole_vectors() {
        let path = host_path();
        let shape = |ci, co| WinogradShape {
            n: 1,
            h: 4,
            w: 4,
            ci,
            oh: 2,
            ow: 2,
            pad_top: 0,
            pad_left: 0,
            co,
            out_image: 4 * co,
            out_pieces: 1,
            kind: WinogradKind::F2x3,
        };
        let on = |whole: bool| match path {
            Path::Avx512 if !whole => Path::Portable,
            p => p,
        };
        for (ci, co, input, output) in [
            (8, 24, on(false), on(false)),
            (16, 24, on(true), on(false)),
            (8, 48, on(false), on(true)),
            (48, 48, on(true), on(true)),
        ] {
            let before = cpu::paths(Family::WinogradInput);
            let t = Transforms::choose::<f32>(&shape(ci, co), co);
            assert_eq!((t.input, t.output), (input, output), "{ci} → {co} channels");
            let ran = cpu::paths(Family::WinogradInput).since(before);
            assert_eq!(ran, once(input));
        }
    }

    /// The input transform, tile-major (the forward pass) and place-major (the weight
    /// gradient), over images whose tiles reach past their edges (zeros read there).
    #[test]
    fn input_transforms_match_their_portable_twins() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        for s in shapes() {
            let (fast, portable) = twins(&s, s.co / s.out_pieces);
            let x = values(s.n * s.h * s.w * s.ci, &mut rng);
            let mut pixels = Vec::new();
            input_offsets(&s, &mut pixels);
            let zeros = vec![0.0f32; s.seg()];
            let (ty, tx) = s.tiles();
            let run = |t: Transforms, by_place: bool| {
                let chunk = Chunk {
                    s,
                    fast: t,
                    images: if by_place { 1 } else { s.n },
                    x: if by_place { &x[..s.h * s.w * s.ci] } else { &x },
                    u: &[],
                    bias: None,
                    relu: false,
                    pixels: &pixels,
                    out_pixels: &[],
                };
                // NaN where nothing is written: the same places must stay untouched.
                let mut v = vec![f32::NAN; s.n * ty * tx * s.v_stride()];
                if by_place {
                    chunk.input_by_place(&mut v, &zeros);
                } else {
                    chunk.input(&mut v, &zeros);
                }
                v.iter().map(|x| x.to_bits()).collect::<Vec<u32>>()
            };
            for by_place in [false, true] {
                assert!(
                    run(fast, by_place) == run(portable, by_place),
                    "{s:?}, place-major {by_place}"
                );
            }
        }
    }

    /// The output transform with and without bias and ReLU, into pieces, some skipped.
    #[test]
    fn output_transforms_match_their_portable_twins() {
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        for s in shapes() {
            let len = s.co / s.out_pieces;
            let (fast, portable) = twins(&s, len);
            let (ty, tx) = s.tiles();
            let m = values(s.n * ty * tx * s.m_stride(), &mut rng);
            let bias = values(s.co, &mut rng);
            let out_pixels: Vec<usize> = (0..s.oh * s.ow * s.out_pieces)
                .map(|i| {
                    if i % 7 == 3 {
                        SKIP_OUTPUT
                    } else {
                        (i / s.out_pieces) * s.co + (i % s.out_pieces) * len
                    }
                })
                .collect();
            for (with_bias, relu) in [(false, false), (true, false), (true, true)] {
                let run = |t: Transforms| {
                    let chunk = Chunk {
                        s,
                        fast: t,
                        images: s.n,
                        x: &[],
                        u: &[],
                        bias: with_bias.then_some(&bias[..]),
                        relu,
                        pixels: &[],
                        out_pixels: &out_pixels,
                    };
                    let mut out = vec![f32::NAN; s.n * s.out_image];
                    chunk.output(&m, &mut out);
                    out
                };
                same_bits(
                    &format!("{s:?} bias {with_bias} relu {relu}"),
                    &run(fast),
                    &run(portable),
                );
            }
        }
    }

    /// The output transform's adjoint (the weight gradient's `dM = A·dY·Aᵀ`), zeros past the
    /// odd edges.
    #[test]
    fn output_adjoints_match_their_portable_twins() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for s in shapes().into_iter().filter(|s| s.out_pieces == 1) {
            let (fast, portable) = twins(&s, s.co);
            let (ty, tx) = s.tiles();
            let dz = values(s.n * s.oh * s.ow * s.co, &mut rng);
            let run = |t: Transforms| {
                let mut m = vec![f32::NAN; s.places() * s.n * ty * tx * s.co];
                output_adjoint(&s, &dz, &mut m, t.output);
                m
            };
            same_bits(&format!("{s:?}"), &run(fast), &run(portable));
        }
    }
}
