//! The AVX512-BF16 kernel: an `MR × 16·NV` block of `C` in `MR·NV ≤ 24` zmm accumulators,
//! as the f32 kernel's tiles ([`crate::tensor::gather`]). Each pair step loads `NV` vectors
//! of `b` (16 columns × 2 bf16 each), broadcasts each row's pair (one 32-bit load), and
//! issues `MR·NV` `vdpbf16ps`: `MR + NV` loads per `2·16·MR·NV` multiply-adds.

use crate::tensor::cpu;
use crate::tensor::gather_bf16::GatherGemmBf16;
use crate::tensor::x86_64::gather_avx512::{
    by_height, by_panel, by_rows, panel_masks, row_tiles, split_rows, tile_rows, Dest, Operands,
};
use crate::tensor::x86_64::sums::{self, End, Start};
use std::arch::x86_64::*;

/// Pairs per block: the task's row tiles run over one block of `b` (256 pairs × 64 columns ×
/// 4 bytes, 64 KiB, in L2) before the next, and `C`'s tiles are stored and loaded again
/// between blocks. 64-pair blocks (16 KiB, in L1) made the article's train step 4% slower on
/// Zen 5 (docs/performance-history.md): the weight gradients' long reductions (conv1's,
/// 10 560 pairs of output pixels at batch 48) went back to `C` every 64 pairs. 128 and 512
/// measured level with 256.
const TP: usize = 256;

/// One `MR × 16·NV` tile over the pairs `q` of one block.
///
/// # Safety
/// AVX-512F and AVX512-BF16; every `a` pair `p[r] + q[u]` (two u16) readable, `b` pair rows
/// `u` readable over the masked columns, `c` rows `crow[r]` readable and writable likewise,
/// a `Bias` pointer readable likewise.
#[target_feature(enable = "avx512f,avx512bf16")]
#[inline]
#[allow(clippy::too_many_arguments)]
unsafe fn tile<const MR: usize, const NV: usize, const FULL: bool>(
    a: *const u16, p: &[usize], q: &[usize], b: *const u16, ldb: usize, c: *mut f32,
    crow: &[usize], masks: [u16; NV], start: Start, end: End,
) {
    let mut acc = sums::start::<__m512, MR, NV>(c, crow, masks, start);
    let rows = sums::rows::<_, MR>(a, p);
    let mut brow = b;
    for &qu in q {
        let mut bv = [_mm512_setzero_si512(); NV];
        for v in 0..NV {
            // Column j's pair is one 32-bit lane: the column mask is the lane mask.
            let at = brow.add(32 * v) as *const i32;
            bv[v] = if FULL {
                _mm512_loadu_si512(at as *const __m512i)
            } else {
                _mm512_maskz_loadu_epi32(masks[v], at)
            };
        }
        for r in 0..MR {
            let pair = (rows[r].add(qu) as *const i32).read_unaligned();
            let av: __m512bh = std::mem::transmute(_mm512_set1_epi32(pair));
            for v in 0..NV {
                let bh: __m512bh = std::mem::transmute(bv[v]);
                acc[r][v] = _mm512_dpbf16_ps(acc[r][v], av, bh);
            }
        }
        brow = brow.add(2 * ldb);
    }
    sums::end(&acc, c, crow, masks, end);
}

/// Dispatches one tile on the panel width (in vectors) and whether it is full.
///
/// # Safety
/// As [`tile`], with `nv` in `1..=4` and `m[..nv]` the panel's lane masks.
#[target_feature(enable = "avx512f,avx512bf16")]
#[inline]
#[allow(clippy::too_many_arguments)]
unsafe fn tile_nv<const MR: usize>(
    nv: usize, a: *const u16, p: &[usize], q: &[usize], b: *const u16, ldb: usize, c: *mut f32,
    crow: &[usize], m: [u16; 4], start: Start, end: End,
) {
    by_panel!(tile::<MR>(a, p, q, b, ldb, c, crow; nv, m; start, end))
}

/// A tile of any height `h < 10` (the rows left over after the full tiles).
///
/// # Safety
/// As [`tile_nv`] for `h` rows.
#[target_feature(enable = "avx512f,avx512bf16")]
#[allow(clippy::too_many_arguments)]
unsafe fn tile_any(
    h: usize, nv: usize, a: *const u16, p: &[usize], q: &[usize], b: *const u16, ldb: usize,
    c: *mut f32, crow: &[usize], m: [u16; 4], start: Start, end: End,
) {
    by_height!(tile_nv(h; nv, a, p, q, b, ldb, c, crow, m, start, end))
}

/// Rows `0..p.len()` of one task's part of `C` (`c` points at the start of its part):
/// blocks of [`TP`] pairs outer, 64-column panels, then row tiles.
///
/// # Safety
/// AVX-512F and AVX512-BF16; the bounds of [`GatherGemmBf16::check`] hold for these rows.
#[target_feature(enable = "avx512f,avx512bf16")]
#[allow(clippy::too_many_arguments)]
unsafe fn task(
    mr: usize, op: Operands<'_, u16>, p: &[usize], c: *mut f32, dest: Dest<'_>, init: Start,
) {
    let (a, q, b, ldb, n, relu) = (op.a, op.q, op.b, op.ldb, op.n, op.relu);
    let (nr, pairs) = (p.len(), q.len());
    let nblocks = pairs.div_ceil(TP).max(1);
    for blk in 0..nblocks {
        let u0 = blk * TP;
        let qb = &q[u0.min(pairs)..(u0 + TP).min(pairs)];
        let bb = if qb.is_empty() {
            b.as_ptr()
        } else {
            b.as_ptr().add(2 * u0 * ldb)
        };
        let (start, end) = (init.block(blk), End::last(relu, blk, nblocks));
        for j0 in (0..n).step_by(64) {
            let (m, nv) = panel_masks(n, j0);
            for (r, h) in row_tiles(nr, mr) {
                let pr = &p[r..r + h];
                let (d0, crow) = dest.tile::<10>(r, h);
                let (ap, cp, bp) = (a.as_ptr(), c.add(d0 + j0), bb.add(2 * j0));
                let st = start.panel(j0);
                by_rows!(tile_nv, tile_any(h, mr; nv, ap, pr, qb, bp, ldb, cp, &crow, m, st, end));
            }
        }
    }
}

/// The product by AVX512-BF16, split over rayon by blocks of rows whose size depends only
/// on the shape (the same split as the f32 kernel). Call only if the CPU has it.
pub fn gather_gemm_bf16(g: GatherGemmBf16<'_>) {
    assert!(cpu::avx512_bf16(), "gather_gemm_bf16: AVX512-BF16 needed");
    g.check();
    if g.is_empty() {
        return;
    }
    let mr = tile_rows(g.n);
    let op = Operands::of(&g);
    let init = g.init;
    let leaf = |pr: &[usize], cc: &mut [f32], dest: Dest<'_>| {
        let st = Start::of(&init);
        // SAFETY: AVX512-BF16 checked above; `check` proved every `a`, `b` and bias index
        // in bounds, and this task's rows of C lie inside `cc` (rows increase and the next
        // task's part starts where its first row does), which no other task touches.
        unsafe { task(mr, op, pr, cc.as_mut_ptr(), dest, st) }
    };
    // `q` counts pairs: two reduction steps each.
    let steps = 2 * g.q.len();
    split_rows(g.c, g.p, g.c_rows, g.ldc, g.n, steps, mr, &leaf);
}
