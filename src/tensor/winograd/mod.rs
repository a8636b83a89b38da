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

mod filters;
#[cfg(test)]
mod tests;
mod transforms;
mod wgrad;

pub use filters::{winograd_filters, winograd_filters_s2d, winograd_filters_s2d_adjoint};
pub use wgrad::{winograd_wgrad, winograd_wgrad_bf16};

use super::cpu::{self, took_path, Family, Path};
use super::gather_bf16::{
    f32s, f32s_mut, gather_gemm_bf16, pack_pairs_into, round_into, GatherGemmBf16,
};
use super::{fill_iota, Float, GatherGemm, Init};
use filters::*;
use transforms::*;

// The portable loops the AVX2 family compiles for rows that are not whole vectors.
use rayon::prelude::*;
#[cfg(target_arch = "x86_64")]
pub(in crate::tensor) use transforms::{input_tile_portable, output_tile_portable};
#[cfg(target_arch = "x86_64")]
pub(in crate::tensor) use wgrad::adjoint_tile_portable;

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
    pub fn block(self) -> usize {
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
    pub fn channels(&self) -> usize {
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
    /// In bf16, each group of chunks' own `dU` ([`winograd_wgrad_bf16`]), summed in order.
    partials: Vec<T>,
}

#[derive(Debug, Default)]
struct Part<T> {
    /// `s·I` zeros: the input pixels (block rows) of a tile that lie outside the image.
    zeros: Vec<T>,
    v: Vec<T>,
    m: Vec<T>,
    p: Vec<usize>,
    q: Vec<usize>,
    /// In bf16 ([`winograd_conv_bf16`]): `V` rounded, and the pair table `0, 2, 4, …`; the
    /// weight gradient's `dM` in pairs of tiles ([`winograd_wgrad_bf16`]).
    vb: Vec<u16>,
    bq: Vec<usize>,
    mb: Vec<u16>,
}

/// The transformed filters a Winograd convolution multiplies by: in the input's precision, or
/// in bf16 pairs ([`winograd_conv_bf16`]).
#[derive(Clone, Copy)]
enum Filters<'a, T> {
    Same(&'a [T]),
    Bf16(&'a [u16]),
}

/// The convolution of [`WinogradShape`] by its [`WinogradKind`]: `u` from [`winograd_filters`]
/// (F(2×2, 3×3)), [`winograd_filters_s2d`] (F(2×2, 2×2) over blocks) or
/// [`winograd_filters_s2d_adjoint`] (a strided filter's input gradient), `bias` (`O` values)
/// added if given, `max(·, 0)` stored if `relu`. Writes only the output pixels (the pieces not
/// at [`SKIP_OUTPUT`]).
#[allow(clippy::too_many_arguments)]
pub fn winograd_conv<T: Float>(
    s: WinogradShape, x: &[T], u: &[T], bias: Option<&[T]>, relu: bool, out: &mut [T],
    out_pixels: &[usize], scratch: &mut WinogradScratch<T>,
) {
    let u = Filters::Same(u);
    conv_with(s, x, u, bias, relu, out, out_pixels, scratch);
}

/// [`winograd_conv`] with the 16 (or 9) products in bf16 ([`crate::tensor::GatherGemmBf16`]):
/// each chunk's transformed input `V` is rounded to bf16, and `u` holds the transformed
/// filters rounded to bf16, in pairs of transformed channels as the bf16 product reads them
/// ([`winograd_filters_bf16`]); the products' sums, and both transforms, stay f32. For f32
/// layers with an even `s²I`.
///
/// Error: with `V` and `U` rounded, each product `M_ξ[tile, o]` is within
/// [`crate::tensor::bf16::dot_error_bound`] of `Σ_i |V_ξ[tile, i]·U_ξ[i, o]|` of the exact one;
/// the output transform adds at most `Σ_ξ |A_ξ|` of those. Taking the transforms over absolute
/// values (`|Bᵀ|·|d|·|B|`, `|G|·|g|·|Gᵀ|`) bounds it, the transforms' own f32 roundings
/// included (tested in `tests/bf16.rs`). For conv3's shape that is about 1.5 times the direct
/// bf16 product's error in norm (`tools/winograd_bf16_error.py`).
#[allow(clippy::too_many_arguments)]
pub fn winograd_conv_bf16<T: Float>(
    s: WinogradShape, x: &[T], u: &[u16], bias: Option<&[T]>, relu: bool, out: &mut [T],
    out_pixels: &[usize], scratch: &mut WinogradScratch<T>,
) {
    assert!(
        s.channels().is_multiple_of(2),
        "winograd_conv_bf16: an odd number of transformed channels ({})",
        s.channels()
    );
    f32s(x);
    let u = Filters::Bf16(u);
    conv_with(s, x, u, bias, relu, out, out_pixels, scratch);
}

/// The transformed filters `u` of [`winograd_filters`] (or its kin) for
/// [`winograd_conv_bf16`]: each place's `[s²I, O]` matrix rounded to bf16 with pairs of rows
/// (transformed channels `2c`, `2c + 1`) interleaved. `channels` is `s²I` (even).
pub fn winograd_filters_bf16(u: &[f32], channels: usize, co: usize, dst: &mut Vec<u16>) {
    assert!(
        channels.is_multiple_of(2) && u.len().is_multiple_of(channels * co.max(1)),
        "winograd_filters_bf16: {channels} channels"
    );
    // The pairs never straddle two places: each place has an even number of rows.
    super::gather_bf16::pack_pairs(u, u.len() / co.max(1), co, co, dst);
}

#[allow(clippy::too_many_arguments)]
fn conv_with<T: Float>(
    s: WinogradShape, x: &[T], u: Filters<'_, T>, bias: Option<&[T]>, relu: bool, out: &mut [T],
    out_pixels: &[usize], scratch: &mut WinogradScratch<T>,
) {
    assert_eq!(x.len(), s.n * s.h * s.w * s.ci, "winograd_conv: input");
    let u_len = match u {
        Filters::Same(u) => u.len(),
        Filters::Bf16(u) => u.len(),
    };
    assert_eq!(
        u_len,
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

/// A run of whole images through the three stages.
struct Chunk<'a, T> {
    s: WinogradShape,
    /// Which transforms run on AVX-512, chosen once for the whole call.
    fast: Transforms,
    images: usize,
    x: &'a [T],
    u: Filters<'a, T>,
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
        if let Filters::Bf16(_) = self.u {
            // Each tile transformed into the first tile's block of `v` (in L1), then rounded
            // into `vb`: `V` in f32 is never written out whole.
            if part.vb.len() < nv {
                part.vb.resize(nv, 0);
            }
            self.input_bf16(v, &mut part.vb[..nv], &part.zeros[..seg]);
        } else {
            self.input(v, &part.zeros[..seg]);
        }
        // M_ξ = V_ξ · U_ξ: rows are tiles (`v_stride` apart in V, `m_stride` in M), the
        // reduction runs over the transformed channels.
        fill_iota(&mut part.p, rows, vs);
        match self.u {
            Filters::Same(u) => {
                fill_iota(&mut part.q, ch, 1);
                for xi in 0..places {
                    let (b, c) = (&u[xi * ch * s.co..][..ch * s.co], &mut m[xi * s.co..]);
                    let g =
                        GatherGemm::new(&v[xi * ch..], &part.p, &part.q, b, s.co, c, Init::Zero);
                    T::gather_gemm(GatherGemm { ldc: ms, ..g });
                }
            }
            Filters::Bf16(u) => {
                // The same products by pairs of transformed channels: pair `k` of a row is
                // channels `2k`, `2k + 1` of `V` in bf16.
                let vb = &part.vb[..nv];
                fill_iota(&mut part.bq, ch / 2, 2);
                let m = f32s_mut(m);
                for xi in 0..places {
                    let (b, c) = (&u[xi * ch * s.co..][..ch * s.co], &mut m[xi * s.co..]);
                    let g =
                        GatherGemm::new(&vb[xi * ch..], &part.p, &part.bq, b, s.co, c, Init::Zero);
                    gather_gemm_bf16(GatherGemmBf16 { ldc: ms, ..g });
                }
            }
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

    /// [`Chunk::input`] rounded to bf16 into `vb` (the same layout): on AVX-512 as each value
    /// is stored, elsewhere each tile transformed in f32 into `v`'s first block and rounded
    /// from there ([`round_into`]), to nearest even either way.
    fn input_bf16(&self, v: &mut [T], vb: &mut [u16], zeros: &[T]) {
        let s = self.s;
        let (places, blk, ch) = (s.places(), s.kind.block(), s.channels());
        let vt = &mut v[..s.v_stride()];
        let mut tiles = vb.chunks_exact_mut(s.v_stride());
        for img in self.x.chunks_exact(s.h * s.w * s.ci) {
            for starts in self.pixels.chunks_exact(places * blk) {
                let vbt = tiles.next().expect("one V block per tile");
                #[cfg(target_arch = "x86_64")]
                if self.fast.input == Path::Avx512 {
                    // SAFETY: as `input_tile_any`'s AVX-512 call (`Transforms::choose` checked
                    // AVX-512F, f32 and `seg`; `vbt` holds a whole tile's block).
                    unsafe { avx512::input_tile_bf16(&s, f32s(img), f32s(zeros), starts, vbt, ch) };
                    continue;
                }
                input_tile_any(&s, img, zeros, starts, vt, ch, self.fast.input);
                round_into(f32s(&vt[..places * ch]), &mut vbt[..places * ch]);
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
                        // SAFETY: AVX-512F, T = f32 and `len` a multiple of 16 checked
                        // (`Transforms::choose`); `mt` holds places·co values, the bias `co`,
                        // each destination `len` inside the image (checked on entry).
                        Path::Avx512 => unsafe {
                            avx512::output_tile(mt, len, bias, relu, img, at, places)
                        },
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

#[cfg(target_arch = "x86_64")]
use super::x86_64::winograd_avx512 as avx512;
