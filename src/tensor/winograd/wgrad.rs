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
/// with zeros), the sums and both adjoint transforms in f32. The error is bounded as
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
    // bf16: V `[image, ξ, pair of tiles, I, 2]`, dM in pairs `[ξ, image, pair of tiles, O, 2]`.
    let pairs = (ty * tx).div_ceil(2);
    if bf16 {
        let (nv, nm) = (
            places * per_chunk * pairs * 2 * ci,
            places * per_chunk * pairs * 2 * co,
        );
        part.vb.resize(part.vb.len().max(nv), 0);
        part.mb.resize(part.mb.len().max(nm), 0);
    }
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
        let transform = |v: &mut [T], x: &[T]| {
            let job = Chunk {
                s,
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
        };
        let (v_image, vb_image) = (places * img_tiles * ci, places * pairs * 2 * ci);
        if bf16 {
            // Image by image, in parallel: V's places in pairs of tiles, rounded as soon as
            // they are transformed, and dM `[image, ξ, tile, O]` (each image's own block, so
            // that the adjoint too runs on every thread).
            v.par_chunks_mut(v_image)
                .zip(xs.par_chunks(image))
                .zip(part.vb[..images * vb_image].par_chunks_mut(vb_image))
                .zip(m.par_chunks_mut(places * img_tiles * co))
                .zip(dzs.par_chunks(dz_image))
                .for_each(|((((v, x), vb), m), dz)| {
                    transform(v, x);
                    for (xi, out) in vb.chunks_exact_mut(pairs * 2 * ci).enumerate() {
                        let src = f32s(&v[xi * img_tiles * ci..][..img_tiles * ci]);
                        pack_pairs_into(src, img_tiles, ci, ci, out);
                    }
                    output_adjoint(&s, dz, m, fast.output);
                });
        } else {
            v.par_chunks_mut(v_image)
                .zip(xs.par_chunks(image))
                .for_each(|(v, x)| transform(v, x));
            output_adjoint(&s, dzs, m, fast.output);
        }
        // dU_ξ += V_ξᵀ · dM_ξ: rows are input channels, the reduction runs over the chunk's
        // tiles (gathered from V image by image; dM's rows in order).
        fill_iota(&mut part.p, ci, 1);
        part.q.clear();
        for img in 0..images {
            part.q
                .extend((0..img_tiles).map(|t| (img * places * img_tiles + t) * ci));
        }
        if bf16 {
            // The same products by pairs of tiles: row i of V_ξᵀ is `2i` into a pair's block,
            // pair u of image `img` is `(img·P + ξ)·pairs + u` blocks of `2I` into V.
            fill_iota(&mut part.p, ci, 2);
            part.q.clear();
            for img in 0..images {
                part.q
                    .extend((0..pairs).map(|u| (img * places * pairs + u) * 2 * ci));
            }
            let (p, q, vb, m) = (&part.p[..], &part.q[..], &part.vb[..], &*m);
            let mb = &mut part.mb[..places * images * pairs * 2 * co];
            scratch
                .du
                .par_chunks_mut(ci * co)
                .zip(mb.par_chunks_mut(images * pairs * 2 * co))
                .enumerate()
                .for_each(|(xi, (du, mb))| {
                    for (img, out) in mb.chunks_exact_mut(pairs * 2 * co).enumerate() {
                        let src = &m[(img * places + xi) * img_tiles * co..][..img_tiles * co];
                        pack_pairs_into(f32s(src), img_tiles, co, co, out);
                    }
                    let (a, du) = (&vb[xi * pairs * 2 * ci..], f32s_mut(du));
                    let g = GatherGemmBf16::new(a, p, q, mb, co, du, Init::Accumulate);
                    gather_gemm_bf16(g);
                });
            continue;
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
