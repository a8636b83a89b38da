//! The weight gradient of a Winograd convolution, through the transforms' adjoints.

use super::*;

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
    s: WinogradShape, x: &[T], dz: &[T], dw: &mut [T], scratch: &mut WinogradScratch<T>,
) {
    wgrad_with(s, x, dz, dw, scratch, false);
}

/// [`winograd_wgrad`] with the products `dU_ξ = V_ξᵀ·dM_ξ` in bf16 (f32 layers): `V` and `dM`
/// rounded to bf16 in pairs of consecutive tiles of an image (an odd count's last tile paired
/// with zeros), the sums and both adjoint transforms in f32. The batch's chunks are summed in
/// four groups, each in order, then the groups in order (`du_bf16`): another order than
/// [`winograd_wgrad`]'s, the same on any thread count. The error is bounded as
/// [`super::winograd_conv_bf16`]'s, over the absolute transforms (`tests/winograd_bf16.rs`).
pub fn winograd_wgrad_bf16<T: Float>(
    s: WinogradShape, x: &[T], dz: &[T], dw: &mut [T], scratch: &mut WinogradScratch<T>,
) {
    f32s(x);
    wgrad_with(s, x, dz, dw, scratch, true);
}

fn wgrad_with<T: Float>(
    s: WinogradShape, x: &[T], dz: &[T], dw: &mut [T], scratch: &mut WinogradScratch<T>, bf16: bool,
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
    input_offsets(&s, &mut scratch.pixels);
    if bf16 {
        du_bf16(s, x, dz, scratch);
    } else {
        du_f32(s, x, dz, scratch);
    }
    match s.kind {
        WinogradKind::F2x3 => filter_adjoint(&scratch.du, s.channels(), s.co, dw),
        WinogradKind::S2d(blk) => filter_adjoint_s2d(&scratch.du, blk, s.ci, s.co, dw),
    }
}

/// Images per chunk of the weight gradient: 96 tiles or more (4 images of conv3: 120 tiles,
/// `V` and `dM` 480 KiB each in f32, in L2).
fn images_per_chunk(s: &WinogradShape) -> usize {
    let (ty, tx) = s.tiles();
    96usize.div_ceil(ty * tx).min(s.n)
}

/// `dU [P, I, O]` into `scratch.du` in f32: chunk after chunk of images, each transformed image
/// by image in parallel and its `P` products run in parallel, every `dU` value summing its
/// chunks in order.
fn du_f32<T: Float>(s: WinogradShape, x: &[T], dz: &[T], scratch: &mut WinogradScratch<T>) {
    let (ty, tx) = s.tiles();
    // `ci` here is a transformed place's channel count (s²·I over blocks).
    let (places, ci, co, seg) = (s.places(), s.channels(), s.co, s.seg());
    let per_chunk = images_per_chunk(&s);
    let fast = Transforms::choose::<T>(&s, co);
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
            .for_each(|(v, x)| transform_image(&s, fast, pixels, zeros, x, v));
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
                let (a, b) = (
                    &v[xi * img_tiles * ci..],
                    &m[xi * tiles * co..][..tiles * co],
                );
                T::gather_gemm(GatherGemm::new(a, p, q, b, co, du, Init::Accumulate))
            });
    }
}

/// One image's `V [ξ, tile, I]` (the forward pass's input transform) into `v`.
fn transform_image<T: Float>(
    s: &WinogradShape, fast: Transforms, pixels: &[Option<usize>], zeros: &[T], x: &[T],
    v: &mut [T],
) {
    let job = Chunk {
        s: *s,
        fast,
        images: 1,
        x,
        u: Filters::Same(&[]),
        bias: None,
        relu: false,
        pixels,
        out_pixels: &[],
    };
    job.input_by_place(v, zeros);
}

/// `dU [P, I, O]` into `scratch.du` with the products in bf16. The chunks of images form
/// [`GROUPS`] groups of consecutive chunks, and one thread takes a group from the images to
/// its partial `dU_g`: for each chunk it transforms the images, rounding `V` and `dM` into
/// pairs of tiles (`V [image, ξ, pair, I, 2]`, `dM [ξ, image, pair, O, 2]`), and adds the `P`
/// products `V_ξᵀ·dM_ξ` to `dU_g`. Nothing a thread writes is read by another until the sum
/// `dU = dU_0 + dU_1 + …`, in group order, so the bits do not depend on the thread count, and
/// no cache line moves between cores mid-group. (Splitting the products by place instead, as
/// [`du_f32`] does, has each thread read the transforms the other wrote: on this Zen 4 guest
/// that made two threads barely faster than one.)
fn du_bf16<T: Float>(s: WinogradShape, x: &[T], dz: &[T], scratch: &mut WinogradScratch<T>) {
    let (places, ci, co) = (s.places(), s.channels(), s.co);
    let per_chunk = images_per_chunk(&s);
    let chunks = s.n.div_ceil(per_chunk);
    let fast = Transforms::choose::<T>(&s, co);
    let du_len = places * ci * co;
    scratch.du.clear();
    scratch.du.resize(du_len, T::zero());
    // Group g: chunks `g·chunks/G` up to `(g + 1)·chunks/G`, summed in order into its own
    // partial with its own scratch; the groups are rayon's to place (a thread whose core is
    // also playing the game takes fewer of them).
    let groups = chunks.min(GROUPS);
    let group = |g: usize| g * chunks / groups..(g + 1) * chunks / groups;
    let partials = &mut scratch.partials;
    partials.resize(groups * du_len, T::zero());
    if scratch.parts.len() < groups {
        scratch.parts.resize_with(groups, Part::default);
    }
    for part in &mut scratch.parts[..groups] {
        part.size_for_chunks(&s, per_chunk);
    }
    let job = ChunkGrad {
        s,
        fast,
        x,
        dz,
        pixels: &scratch.pixels,
        per_chunk,
    };
    scratch.parts[..groups]
        .par_iter_mut()
        .zip(partials.par_chunks_mut(du_len))
        .enumerate()
        .for_each(|(g, (part, du))| {
            for c in group(g) {
                let init = if c == group(g).start {
                    Init::Zero
                } else {
                    Init::Accumulate
                };
                job.run(c, part, f32s_mut(du), init);
            }
        });
    // dU = dU_0 + dU_1 + …, in group order, in blocks across the threads.
    let partials = &scratch.partials[..];
    const BLOCK: usize = 4096;
    scratch
        .du
        .par_chunks_mut(BLOCK)
        .enumerate()
        .for_each(|(b, du)| {
            for (c, part) in partials.chunks_exact(du_len).enumerate() {
                let part = &part[b * BLOCK..][..du.len()];
                if c == 0 {
                    du.copy_from_slice(part);
                } else {
                    du.iter_mut().zip(part).for_each(|(d, &p)| *d += p);
                }
            }
        });
}

impl<T: Float> Part<T> {
    /// Grows the buffers [`ChunkGrad::run`] uses for chunks of `per_chunk` images.
    fn size_for_chunks(&mut self, s: &WinogradShape, per_chunk: usize) {
        let (ty, tx) = s.tiles();
        let (places, ci, co, seg) = (s.places(), s.channels(), s.co, s.seg());
        let (img_tiles, pairs) = (ty * tx, (ty * tx).div_ceil(2));
        let grow = |v: &mut Vec<T>, n: usize| v.resize(v.len().max(n), T::zero());
        grow(&mut self.v, places * img_tiles * ci);
        grow(&mut self.m, places * img_tiles * co);
        grow(&mut self.zeros, seg);
        let (nvb, nmb) = (
            places * per_chunk * pairs * 2 * ci,
            places * per_chunk * pairs * 2 * co,
        );
        self.vb.resize(self.vb.len().max(nvb), 0);
        self.mb.resize(self.mb.len().max(nmb), 0);
    }
}

/// Chunk 0's `dU [P, I, O]` of [`winograd_wgrad_bf16`] (`x` and `dz` one chunk of images)
/// with the transforms `fast`: the tests compare the pairs rounded as stored with the pairs
/// packed after.
#[cfg(test)]
pub(super) fn chunk_du_bf16(s: WinogradShape, x: &[f32], dz: &[f32], fast: Transforms) -> Vec<f32> {
    let mut pixels = Vec::new();
    input_offsets(&s, &mut pixels);
    let mut part = Part::default();
    part.size_for_chunks(&s, s.n);
    // Stale pairs (bf16 ones) where a chunk before left them: nothing may read them.
    part.vb.fill(0x3F80);
    part.mb.fill(0x3F80);
    let job = ChunkGrad {
        s,
        fast,
        x,
        dz,
        pixels: &pixels,
        per_chunk: s.n,
    };
    let mut du = vec![f32::NAN; s.places() * s.channels() * s.co];
    job.run(0, &mut part, &mut du, Init::Zero);
    du
}

/// Groups of chunks in [`du_bf16`]: as many threads as it can keep busy. More groups would
/// split the batch finer and sum more partial `dU`s (and keep more scratch).
const GROUPS: usize = 4;

/// One chunk of [`du_bf16`]'s images, from the images to its products.
struct ChunkGrad<'a, T> {
    s: WinogradShape,
    fast: Transforms,
    x: &'a [T],
    dz: &'a [T],
    pixels: &'a [Option<usize>],
    per_chunk: usize,
}

impl<T: Float> ChunkGrad<'_, T> {
    /// Whether `V` and `dM` are rounded into their pairs as the transforms store them (on
    /// AVX-512 with BW, where [`Transforms`] chose AVX-512 for them), rather than transformed
    /// in f32 and packed after (`pack_pairs_into`): the same bits either way.
    fn pairs_as_stored(&self) -> (bool, bool) {
        #[cfg(target_arch = "x86_64")]
        let bw = std::arch::is_x86_feature_detected!("avx512bw");
        #[cfg(not(target_arch = "x86_64"))]
        let bw = false;
        (
            bw && self.fast.input == Path::Avx512,
            bw && self.fast.output == Path::Avx512,
        )
    }

    /// Chunk `c`'s `dU_ξ = V_ξᵀ·dM_ξ` for every place, into `du [P, I, O]` as `init` says:
    /// its images transformed one at a time into pairs of tiles rounded to bf16 (`V [image, ξ,
    /// pair, I, 2]`, `dM [ξ, image, pair, O, 2]`; rounded as stored where
    /// [`ChunkGrad::pairs_as_stored`], else `V [ξ, tile, I]` and `dM [ξ, tile, O]` in f32 first
    /// and packed after), then the `P` products over the chunk's pairs.
    fn run(&self, c: usize, part: &mut Part<T>, du: &mut [f32], init: Init<'_, f32>) {
        let s = self.s;
        let (ty, tx) = s.tiles();
        let (places, ci, co, seg) = (s.places(), s.channels(), s.co, s.seg());
        let (img_tiles, pairs) = (ty * tx, (ty * tx).div_ceil(2));
        let (image, dz_image) = (s.h * s.w * s.ci, s.oh * s.ow * co);
        let first = c * self.per_chunk;
        let images = self.per_chunk.min(s.n - first);
        let (vb_image, mb_image) = (pairs * 2 * ci, pairs * 2 * co);
        let (v, m) = (
            &mut part.v[..places * img_tiles * ci],
            &mut part.m[..places * img_tiles * co],
        );
        let (vb, mb) = (
            &mut part.vb[..places * images * vb_image],
            &mut part.mb[..places * images * mb_image],
        );
        let (v_pairs, m_pairs) = self.pairs_as_stored();
        for img in 0..images {
            let x = &self.x[(first + img) * image..][..image];
            let dz = &self.dz[(first + img) * dz_image..][..dz_image];
            let zeros = &part.zeros[..seg];
            // V's pairs: place ξ of pair u is `ξ·vb_image + 2u·I` into the image's block.
            let vb = &mut vb[img * places * vb_image..][..places * vb_image];
            if v_pairs {
                zero_odd_halves(vb, vb_image, ci, img_tiles);
                let blk = s.kind.block();
                for (t, starts) in self.pixels.chunks_exact(places * blk).enumerate() {
                    let (u, k) = (t / 2, t % 2);
                    let dst = &mut vb[2 * u * ci..];
                    let (x, zeros) = (f32s(x), f32s(zeros));
                    #[cfg(target_arch = "x86_64")]
                    // SAFETY: `pairs_as_stored` checked AVX-512F and BW, f32 and whole vectors
                    // (`Transforms::choose`); place ξ ≤ P − 1 of pair u ends inside `dst`.
                    unsafe {
                        avx512::input_tile_pairs(&s, x, zeros, starts, dst, pairs * ci, k)
                    };
                    #[cfg(not(target_arch = "x86_64"))]
                    unreachable!("{:?}{:?}{:?}{dst:?}{k}", x, zeros, starts);
                }
            } else {
                transform_image(&s, self.fast, self.pixels, zeros, x, v);
                for xi in 0..places {
                    let src = f32s(&v[xi * img_tiles * ci..][..img_tiles * ci]);
                    let out = &mut vb[xi * vb_image..][..vb_image];
                    pack_pairs_into(src, img_tiles, ci, ci, out);
                }
            }
            // dM's pairs: place ξ of pair u is `ξ·images·mb_image + img·mb_image + 2u·O`.
            let mb = &mut mb[img * mb_image..];
            if m_pairs {
                let stride = images * mb_image;
                zero_odd_halves(mb, stride, co, img_tiles);
                for (t, at) in tile_outputs(&s).enumerate() {
                    let (u, k) = (t / 2, t % 2);
                    let dst = &mut mb[2 * u * co..];
                    #[cfg(target_arch = "x86_64")]
                    // SAFETY: as for V; every `Some` output holds `O` values of `dz`; place
                    // ξ ≤ P − 1 of pair u ends inside `dst`.
                    unsafe {
                        avx512::adjoint_tile_pairs(f32s(dz), at, dst, stride / 2, co, places, k)
                    };
                    #[cfg(not(target_arch = "x86_64"))]
                    unreachable!("{at:?}{dst:?}{k}");
                }
            } else {
                output_adjoint(&s, dz, m, self.fast.output);
                for xi in 0..places {
                    let src = f32s(&m[xi * img_tiles * co..][..img_tiles * co]);
                    let out = &mut mb[xi * images * mb_image..][..mb_image];
                    pack_pairs_into(src, img_tiles, co, co, out);
                }
            }
        }
        // Row i of V_ξᵀ is `2i` into a pair's block; pair u of image `img` is
        // `(img·P + ξ)·pairs + u` blocks of `2I` into V, dM's pairs in order.
        fill_iota(&mut part.p, ci, 2);
        part.q.clear();
        for img in 0..images {
            part.q
                .extend((0..pairs).map(|u| (img * places * pairs + u) * 2 * ci));
        }
        let (p, q) = (&part.p[..], &part.q[..]);
        for (xi, du) in du.chunks_exact_mut(ci * co).enumerate() {
            let a = &vb[xi * vb_image..];
            let b = &mb[xi * images * mb_image..][..images * mb_image];
            gather_gemm_bf16(GatherGemmBf16::new(a, p, q, b, co, du, init));
        }
    }
}

/// Zeros the second halves of an image's last pair of tiles when its tile count is odd (the
/// pair has no second tile): `width` values in each of the `P` places, `stride` apart.
fn zero_odd_halves(pairs: &mut [u16], stride: usize, width: usize, tiles: usize) {
    if tiles.is_multiple_of(2) {
        return;
    }
    let last = (tiles / 2) * 2 * width;
    for place in pairs.chunks_mut(stride) {
        if let Some(pair) = place.get_mut(last..last + 2 * width) {
            pair.iter_mut().skip(1).step_by(2).for_each(|h| *h = 0);
        }
    }
}

/// Where each tile's 2×2 outputs start in an image of `dz` (`None` past the edge), tile by
/// tile in row-major order.
fn tile_outputs(s: &WinogradShape) -> impl Iterator<Item = [Option<usize>; 4]> + '_ {
    let (ty, tx) = s.tiles();
    (0..ty * tx).map(move |t| {
        let (a, b) = (t / tx, t % tx);
        std::array::from_fn(|k| {
            let (oy, ox) = (2 * a + k / 2, 2 * b + k % 2);
            (oy < s.oh && ox < s.ow).then_some((oy * s.ow + ox) * s.co)
        })
    })
}

/// `dM = A·dY·Aᵀ` for every tile of a chunk of images: `dz` `[images, OH, OW, O]` into `m`
/// `[ξ, tiles, O]`, zeros for outputs past the edge. In one dimension `A` maps `(y₀, y₁)` to
/// `(y₀, y₀ + y₁, y₀ − y₁, −y₁)`: the transpose of `Aᵀ`'s rows `m₀ + m₁ + m₂` and
/// `m₁ − m₂ − m₃`. (A few adds per value: one thread does the whole chunk.)
///
/// `path`: the loop [`Transforms::output`] chose.
pub(super) fn output_adjoint<T: Float>(s: &WinogradShape, dz: &[T], m: &mut [T], path: Path) {
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
                    // SAFETY: AVX-512F, T = f32 and `co` a multiple of 16 checked
                    // (`Transforms::choose`); every `Some` output holds `co` values inside the
                    // image; `mt` reaches the last place of this tile (`t` is below the chunk's
                    // tile count, `stride / co`).
                    Path::Avx512 => unsafe {
                        avx512::adjoint_tile(img, at, mt, stride, co, places)
                    },
                    // SAFETY: chosen only where the CPU runs AVX2 and FMA.
                    #[cfg(target_arch = "x86_64")]
                    Path::Avx2 => unsafe {
                        crate::tensor::x86_64::winograd_avx2::adjoint_tile(
                            img, at, mt, stride, co, places,
                        )
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
pub(in crate::tensor) fn adjoint_tile_portable<T: Float>(
    img: &[T], at: [Option<usize>; 4], mt: &mut [T], stride: usize, co: usize, places: usize,
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
