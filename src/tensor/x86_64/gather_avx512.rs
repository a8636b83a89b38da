//! The AVX-512 kernel: an `MR × 16·NV` block of `C` lives in `MR·NV ≤ 24` zmm registers for
//! a block of 128 reduction steps (256 for conv1's forward: [`block_len`]); each step loads
//! `NV` vectors of the `b` row and broadcasts `MR` gathered `a` values, i.e. `MR + NV` loads
//! per `MR·NV` FMAs. Shapes: up to 32 columns (conv1's 32 channels) run 10 × 2 (12 × 2
//! spilled), 48 run 8 × 3, 64 (conv2, conv3) 6 × 4; wider `C` goes in panels of 64 columns
//! with the column tail under a mask, except a lone row (a GEMV) which takes 128-column
//! panels. Leftover rows get one tile of their height. A `C` of at most 8 columns (the IMPALA
//! encoder's first stage) runs 16 × 8 tiles in 256-bit registers instead ([`tile8`]).

use crate::tensor::gather::{row_start, rows_per_task, GatherGemm};
use rayon::prelude::*;
use std::arch::x86_64::*;

use super::sums::{self, End, Start};

use crate::tensor::cpu::avx512 as available;

/// Reduction steps per block: the block's `b` rows (128 × 64 floats, 32 KiB) stay in L1
/// while every row tile of a task runs over them.
const TB: usize = 128;

/// The longest block: see [`block_len`].
const TB_MAX: usize = 2 * TB;

/// Reduction steps per block of an `n`-column product over `steps` steps: [`TB`], or the
/// whole reduction up to [`TB_MAX`] steps when `C` is at most 32 columns wide. That is
/// conv1's forward pass (256 steps × 32 columns of `b`, 32 KiB, which fit L1 as well): each
/// row tile then keeps its sums in registers from start to end, and the task reads the
/// batch once instead of twice. Paired steps in one process (the switch flipped every step,
/// 3 × 60 pairs) measured the one-thread train step 0.3–0.7 ms faster, two threads level.
/// (A weight gradient's long reduction keeps 128-step blocks: 256-pixel blocks measured
/// slower.)
fn block_len(n: usize, steps: usize) -> usize {
    if n <= 32 && steps <= TB_MAX {
        TB_MAX
    } else {
        TB
    }
}

/// Values of `A` (256 KiB) a task's block must read before its rows count as streamed
/// from memory and get prefetched.
const STREAMED: usize = 1 << 16;

/// Splits a block of reduction offsets into runs of consecutive values, `(first, length)`,
/// so the tile walks each run with pointer increments instead of reading `q` per step.
fn runs(q: &[usize], out: &mut [(usize, usize); TB_MAX]) -> usize {
    let mut k = 0;
    for &v in q {
        if k > 0 && out[k - 1].0 + out[k - 1].1 == v {
            out[k - 1].1 += 1;
        } else {
            out[k] = (v, 1);
            k += 1;
        }
    }
    k
}

/// One block of reduction steps: the offset table, and the same offsets as runs of
/// consecutive values when the runs are long enough to pay (at least 4 steps on average).
#[derive(Clone, Copy)]
struct Steps<'a> {
    table: &'a [usize],
    runs: Option<&'a [(usize, usize)]>,
}

impl<'a> Steps<'a> {
    fn new(table: &'a [usize], buf: &'a mut [(usize, usize); TB_MAX]) -> Self {
        let n = runs(table, buf);
        let runs = (4 * n <= table.len()).then_some(&buf[..n]);
        Steps { table, runs }
    }
}

/// One vector of a `b` row: a plain load for a full panel (`FULL`), else under its lane mask.
/// A masked load with a mask known only at run time costs this core an extra uop on the
/// vector ports the FMAs use: a 6 × 4 tile over L1-resident data ran at 89–117 GFLOP/s with
/// masked loads against 136 with plain ones.
///
/// # Safety
/// AVX-512F; the masked lanes (all 16 if `FULL`) of `p` readable.
#[target_feature(enable = "avx512f")]
#[inline]
unsafe fn load_b<const FULL: bool>(mask: u16, p: *const f32) -> __m512 {
    if FULL {
        _mm512_loadu_ps(p)
    } else {
        _mm512_maskz_loadu_ps(mask, p)
    }
}

/// One `MR × 16·NV` tile over the steps `q`.
///
/// # Safety
/// AVX-512F must be available; `a + p[r] + q[t]` for all `r < MR`, `t` must be readable, `b`
/// rows `t` readable up to their masked width, `c` rows `r` (stride `ldc`) readable and
/// writable up to the masked width, and a `Bias` pointer readable likewise.
#[target_feature(enable = "avx512f")]
#[inline]
#[allow(clippy::too_many_arguments)]
unsafe fn tile<const MR: usize, const NV: usize, const FULL: bool>(
    a: *const f32, p: &[usize], q: Steps<'_>, b: *const f32, ldb: usize, c: *mut f32,
    crow: &[usize], masks: [u16; NV], start: Start, end: End,
) {
    let mut acc = sums::start::<__m512, MR, NV>(c, crow, masks, start);
    let rows = sums::rows::<_, MR>(a, p);
    let mut brow = b;
    if let Some(runs) = q.runs {
        // Steps in runs of consecutive offsets (a convolution's patch rows, a plain `A·B`):
        // every row pointer advances by one, no table reads.
        for &(first, len) in runs {
            let mut ar = [a; MR];
            for r in 0..MR {
                ar[r] = rows[r].add(first);
            }
            for _ in 0..len {
                let mut bv = [_mm512_setzero_ps(); NV];
                for v in 0..NV {
                    bv[v] = load_b::<FULL>(masks[v], brow.add(16 * v));
                }
                for r in 0..MR {
                    let av = _mm512_set1_ps(*ar[r]);
                    ar[r] = ar[r].add(1);
                    for v in 0..NV {
                        acc[r][v] = _mm512_fmadd_ps(av, bv[v], acc[r][v]);
                    }
                }
                brow = brow.add(ldb);
            }
        }
    } else {
        for &qt in q.table {
            let mut bv = [_mm512_setzero_ps(); NV];
            for v in 0..NV {
                bv[v] = load_b::<FULL>(masks[v], brow.add(16 * v));
            }
            for r in 0..MR {
                let av = _mm512_set1_ps(*rows[r].add(qt));
                for v in 0..NV {
                    acc[r][v] = _mm512_fmadd_ps(av, bv[v], acc[r][v]);
                }
            }
            brow = brow.add(ldb);
        }
    }
    sums::end(&acc, c, crow, masks, end);
}

/// `$tile::<$mr, NV, FULL>(args…, masks, tail…)` for a panel `nv` vectors wide (1 to 4) with
/// lane masks `m`: the panel's width and whether all its lanes are used become constants of
/// the tile. Shared with the bf16 kernel.
macro_rules! by_panel {
    ($tile:ident::<$mr:ident>($($arg:expr),*; $nv:expr, $m:expr; $($tail:expr),*)) => {{
        let (nv, m): (usize, [u16; 4]) = ($nv, $m);
        let full = m[..nv].iter().all(|&x| x == u16::MAX);
        match (nv, full) {
            (1, true) => $tile::<$mr, 1, true>($($arg,)* [m[0]], $($tail),*),
            (1, false) => $tile::<$mr, 1, false>($($arg,)* [m[0]], $($tail),*),
            (2, true) => $tile::<$mr, 2, true>($($arg,)* [m[0], m[1]], $($tail),*),
            (2, false) => $tile::<$mr, 2, false>($($arg,)* [m[0], m[1]], $($tail),*),
            (3, true) => $tile::<$mr, 3, true>($($arg,)* [m[0], m[1], m[2]], $($tail),*),
            (3, false) => $tile::<$mr, 3, false>($($arg,)* [m[0], m[1], m[2]], $($tail),*),
            (_, true) => $tile::<$mr, 4, true>($($arg,)* m, $($tail),*),
            (_, false) => $tile::<$mr, 4, false>($($arg,)* m, $($tail),*),
        }
    }};
}
pub(crate) use by_panel;

/// `$tile::<H>(args…)` for a tile height `h` below 10 (the rows left over after the full
/// tiles). Shared with the bf16 kernel.
macro_rules! by_height {
    ($tile:ident($h:expr; $($arg:expr),*)) => {
        match $h {
            1 => $tile::<1>($($arg),*),
            2 => $tile::<2>($($arg),*),
            3 => $tile::<3>($($arg),*),
            4 => $tile::<4>($($arg),*),
            5 => $tile::<5>($($arg),*),
            6 => $tile::<6>($($arg),*),
            7 => $tile::<7>($($arg),*),
            8 => $tile::<8>($($arg),*),
            _ => $tile::<9>($($arg),*),
        }
    };
}
pub(crate) use by_height;

/// One row tile of height `h` whose full height is `mr` (10, 8 or 6): a full tile by
/// `$full::<MR>(args…)` (inlined), the rows left over by `$any(h, args…)`. Shared with the bf16
/// kernel.
macro_rules! by_rows {
    ($full:ident, $any:ident($h:expr, $mr:expr; $($arg:expr),*)) => {
        if $h == $mr {
            match $mr {
                10 => $full::<10>($($arg),*),
                8 => $full::<8>($($arg),*),
                _ => $full::<6>($($arg),*),
            }
        } else {
            $any($h, $($arg),*)
        }
    };
}
pub(crate) use by_rows;

/// Dispatches one tile on the panel width (in vectors) and whether it is full.
///
/// # Safety
/// As [`tile`], with `nv` in `1..=4` and `m[..nv]` the panel's lane masks.
#[target_feature(enable = "avx512f")]
#[inline]
#[allow(clippy::too_many_arguments)]
unsafe fn tile_nv<const MR: usize>(
    nv: usize, a: *const f32, p: &[usize], q: Steps<'_>, b: *const f32, ldb: usize, c: *mut f32,
    crow: &[usize], m: [u16; 4], start: Start, end: End,
) {
    by_panel!(tile::<MR>(a, p, q, b, ldb, c, crow; nv, m; start, end))
}

/// A tile of any height `h < 10`.
///
/// # Safety
/// As [`tile_nv`] for `h` rows.
#[target_feature(enable = "avx512f")]
#[allow(clippy::too_many_arguments)]
unsafe fn tile_any(
    h: usize, nv: usize, a: *const f32, p: &[usize], q: Steps<'_>, b: *const f32, ldb: usize,
    c: *mut f32, crow: &[usize], m: [u16; 4], start: Start, end: End,
) {
    by_height!(tile_nv(h; nv, a, p, q, b, ldb, c, crow, m, start, end))
}

/// Columns of the widest `C` that runs [`tile8`]'s 8-lane tiles.
const NARROW: usize = 8;

/// Rows of a full [`tile8`]: 16 accumulators of the 32 ymm registers AVX-512 gives.
const MR8: usize = 16;

/// Whether [`tile8`] may run: AVX-512VL and AVX2 beside AVX-512F, as on every AVX-512 core
/// but Xeon Phi's (which keep the 512-bit tiles). The standard library caches the answer.
fn narrow_tiles() -> bool {
    is_x86_feature_detected!("avx512vl") && is_x86_feature_detected!("avx2")
}

/// One `MR × 8` tile of a `C` at most [`NARROW`] columns wide, in 256-bit registers: the
/// IMPALA encoder's first stage (8 channels). A 512-bit tile would leave half of each vector
/// masked off, and on AMD Zen 4 a masked 512-bit FMA costs two 256-bit ones; on cores with
/// two 512-bit FMA units a 256-bit FMA issues as often, so no host loses. Every element of `C`
/// is summed in the same order as [`tile`] sums it (one fused multiply-add per step), so the
/// two give the same bits.
///
/// # Safety
/// As [`tile`], AVX-512VL besides; `mask` the lanes of `C`'s columns (all 8 if `FULL`).
#[target_feature(enable = "avx512f,avx512vl,avx2,fma")]
#[inline]
#[allow(clippy::too_many_arguments)]
unsafe fn tile8<const MR: usize, const FULL: bool>(
    a: *const f32, p: &[usize], q: Steps<'_>, b: *const f32, ldb: usize, c: *mut f32,
    crow: &[usize], mask: __m256i, start: Start, end: End,
) {
    let mut acc = sums::start::<__m256, MR, 1>(c, crow, [mask], start);
    let rows = sums::rows::<_, MR>(a, p);
    let mut brow = b;
    // One step: the `b` row, then each row's gathered value `a_r` times it.
    macro_rules! step {
        ($a_r:expr) => {{
            let bv = if FULL {
                _mm256_loadu_ps(brow)
            } else {
                _mm256_maskload_ps(brow, mask)
            };
            for r in 0..MR {
                let av = _mm256_broadcast_ss(&*$a_r(r));
                acc[r][0] = _mm256_fmadd_ps(av, bv, acc[r][0]);
            }
            brow = brow.add(ldb);
        }};
    }
    if let Some(runs) = q.runs {
        for &(first, len) in runs {
            let mut ar = [a; MR];
            for r in 0..MR {
                ar[r] = rows[r].add(first);
            }
            for i in 0..len {
                step!(|r: usize| ar[r].add(i));
            }
        }
    } else {
        for &qt in q.table {
            step!(|r: usize| rows[r].add(qt));
        }
    }
    sums::end(&acc, c, crow, [mask], end);
}

/// A [`tile8`] of any height `h` up to [`MR8`] over `n ≤ 8` columns.
///
/// # Safety
/// As [`tile8`] for `h` rows.
#[target_feature(enable = "avx512f,avx512vl,avx2,fma")]
#[allow(clippy::too_many_arguments)]
unsafe fn tile8_any(
    h: usize, n: usize, a: *const f32, p: &[usize], q: Steps<'_>, b: *const f32, ldb: usize,
    c: *mut f32, crow: &[usize], start: Start, end: End,
) {
    let lanes: [i32; 8] = std::array::from_fn(|i| if i < n { -1 } else { 0 });
    let mask = _mm256_loadu_si256(lanes.as_ptr().cast());
    macro_rules! go {
        ($($h:literal)*) => {
            match (h, n == NARROW) {
                $(($h, true) => tile8::<$h, true>(a, p, q, b, ldb, c, crow, mask, start, end),
                ($h, false) => tile8::<$h, false>(a, p, q, b, ldb, c, crow, mask, start, end),)*
                _ => unreachable!("a narrow tile has 1 to {MR8} rows"),
            }
        };
    }
    go!(1 2 3 4 5 6 7 8 9 10 11 12 13 14 15 16)
}

/// Lane masks of the 64-column panel starting at `j0` of an `n`-column product, and its
/// width in vectors.
pub(crate) fn panel_masks(n: usize, j0: usize) -> ([u16; 4], usize) {
    let w = (n - j0).min(64);
    let nv = w.div_ceil(16);
    let mut m = [0u16; 4];
    for (v, mv) in m.iter_mut().enumerate().take(nv) {
        let lanes = (w - 16 * v).min(16);
        *mv = if lanes == 16 {
            0xffff
        } else {
            (1u16 << lanes) - 1
        };
    }
    (m, nv)
}

/// Where a task's rows go: row `r0 + i` of `C` starts at `dest(i)` of the task's part of `c`
/// (which begins at index `base` of the whole `c`).
#[derive(Clone, Copy)]
pub(crate) struct Dest<'a> {
    pub(crate) c_rows: Option<&'a [usize]>,
    pub(crate) ldc: usize,
    pub(crate) r0: usize,
    pub(crate) base: usize,
}

impl Dest<'_> {
    #[inline]
    pub(crate) fn at(&self, i: usize) -> usize {
        row_start(self.c_rows, self.ldc, self.r0 + i) - self.base
    }

    /// Where the tile of rows `r .. r + h` starts (row `r`), and each of its rows from there
    /// (rows past `h`, never used, 0): a tile's `c` and `crow`.
    pub(crate) fn tile<const N: usize>(&self, r: usize, h: usize) -> (usize, [usize; N]) {
        let d0 = self.at(r);
        (
            d0,
            std::array::from_fn(|i| if i < h { self.at(r + i) - d0 } else { 0 }),
        )
    }
}

/// A task's `nr` rows in tiles of `mr` (the last one shorter): each tile's first row and
/// height.
pub(crate) fn row_tiles(nr: usize, mr: usize) -> impl Iterator<Item = (usize, usize)> {
    (0..nr).step_by(mr).map(move |r| (r, (nr - r).min(mr)))
}

/// The operands every task of a gather GEMM reads (all four kernels: `A` and `B` of `T`,
/// f32 or bf16 bits); a task's rows of `p` and part of `C` come beside them.
#[derive(Clone, Copy)]
pub(crate) struct Operands<'a, T> {
    pub(crate) a: &'a [T],
    pub(crate) q: &'a [usize],
    pub(crate) b: &'a [T],
    pub(crate) ldb: usize,
    pub(crate) n: usize,
    pub(crate) relu: bool,
}

impl<'a, T> Operands<'a, T> {
    /// The operands of `g`.
    pub(crate) fn of<O>(g: &GatherGemm<'a, T, O>) -> Self {
        Operands {
            a: g.a,
            q: g.q,
            b: g.b,
            ldb: g.ldb,
            n: g.n,
            relu: g.relu,
        }
    }
}

/// Rows `0..p.len()` of one task's part of `C` (`c` points at the start of its part).
///
/// # Safety
/// AVX-512F available; the bounds of [`GatherGemm::check`] hold for these rows.
#[target_feature(enable = "avx512f")]
unsafe fn task(
    mr: usize, op: Operands<'_, f32>, p: &[usize], c: *mut f32, dest: Dest<'_>, init: Start,
) {
    let (a, q, b, ldb, n, relu) = (op.a, op.q, op.b, op.ldb, op.n, op.relu);
    let nr = p.len();
    let steps = q.len();
    let tb = block_len(n, steps);
    let nblocks = steps.div_ceil(tb).max(1);
    let narrow = narrow_tiles();
    for blk in 0..nblocks {
        let t0 = blk * tb;
        let qb = &q[t0.min(steps)..(t0 + tb).min(steps)];
        let mut rbuf = [(0, 0); TB_MAX];
        let qr = Steps::new(qb, &mut rbuf);
        // A block that reads each row's values as one run, rows not overlapping (judged by
        // the task's first two rows), over more than L2 holds comfortably (a plain `A·B`
        // over a large `A`, e.g. dense1's weights in its input gradient): every tile reads
        // new memory, so the next tile's lines are requested while this one computes.
        // (Convolutions' rows overlap and come from cache, and Winograd's products read
        // what the transform just wrote: there the prefetches only cost instructions.)
        let streamed = match qr.runs {
            Some(&[(_, len)]) => {
                nr * len >= STREAMED && p.windows(2).take(1).all(|w| w[1] >= w[0] + len)
            }
            _ => false,
        };
        let bb = if qb.is_empty() {
            b.as_ptr()
        } else {
            b.as_ptr().add(t0 * ldb)
        };
        let (start, end) = (init.block(blk), End::last(relu, blk, nblocks));
        // Panels outer, row tiles inner: one panel's block of `b` (128 steps × 64 columns,
        // 32 KiB) stays in L1 across all the task's row tiles. (Both of dense1's panels,
        // 64 KiB, would not: each tile would read them again from L2.)
        if n <= NARROW && narrow {
            // A `C` of 8 columns or fewer: 8-lane tiles of 16 rows (`tile8`).
            for (r, h) in row_tiles(nr, MR8) {
                let (d0, crow) = dest.tile::<MR8>(r, h);
                let (cp, pr) = (c.add(d0), &p[r..r + h]);
                tile8_any(h, n, a.as_ptr(), pr, qr, bb, ldb, cp, &crow, start, end);
            }
            continue;
        }
        for j0 in (0..n).step_by(64) {
            let (m, nv) = panel_masks(n, j0);
            for (r, h) in row_tiles(nr, mr) {
                let pr = &p[r..r + h];
                let ap = a.as_ptr();
                if h == 1 && n - j0 / 128 * 128 >= 128 {
                    // A single row (dense1 at batch 1: a GEMV over 3.6 MB of weights, bound
                    // by memory): 128-column panels, so each row of `b` is read in one sweep.
                    if j0 % 128 == 0 {
                        let (cp, bp) = (c.add(dest.at(r) + j0), bb.add(j0));
                        let st = start.panel(j0);
                        tile::<1, 8, true>(ap, pr, qr, bp, ldb, cp, &[0], [!0; 8], st, end);
                    }
                    continue;
                }
                if streamed && j0 == 0 && r + mr < nr {
                    let next = &p[r + mr..(r + 2 * mr).min(nr)];
                    prefetch_rows(ap, next, qr);
                }
                let (d0, crow) = dest.tile::<10>(r, h);
                let (cp, bp, st) = (c.add(d0 + j0), bb.add(j0), start.panel(j0));
                by_rows!(tile_nv, tile_any(h, mr; nv, ap, pr, qr, bp, ldb, cp, &crow, m, st, end));
            }
        }
    }
}

/// Requests into L1 the cache lines that rows `p` read over the steps `q` (one run).
///
/// # Safety
/// AVX-512F available (for the target feature); the addresses need not be valid (a
/// prefetch never faults), but they are: the rows are the next tile's.
#[target_feature(enable = "avx512f")]
unsafe fn prefetch_rows(a: *const f32, p: &[usize], q: Steps<'_>) {
    if let Some(&[(first, len)]) = q.runs {
        for &pr in p {
            let lo = a.wrapping_add(pr + first) as usize & !63;
            let hi = a.wrapping_add(pr + first + len) as usize;
            for line in (lo..hi).step_by(64) {
                _mm_prefetch::<_MM_HINT_T0>(line as *const i8);
            }
        }
    }
}

/// Register-tile height for an `n`-column product: `MR·NV ≤ 24` accumulators. (12 × 2 for
/// conv1's 32 columns spilled: LLVM hoists all 12 broadcasts, 38 live zmm.)
pub(crate) fn tile_rows(n: usize) -> usize {
    match n.min(64).div_ceil(16) {
        1 | 2 => 10,
        3 => 8,
        _ => 6,
    }
}

/// [`crate::tensor::gather::ScatterGemm`] on AVX-512, one rayon task per group. Call only if
/// [`available`].
pub fn scatter_gemm(g: crate::tensor::gather::ScatterGemm<'_, f32>) {
    assert!(available(), "scatter_gemm: AVX-512F and FMA needed");
    g.check();
    let crate::tensor::gather::ScatterGemm {
        a,
        p,
        q,
        b,
        ldb,
        n,
        out,
        out_rows,
        out_cols,
        groups,
    } = g;
    if p.is_empty() || n == 0 {
        return;
    }
    let (grows, glen) = (p.len() / groups, out.len() / groups);
    let mr = tile_rows(n);
    // Whether each 64-column panel lands on consecutive outputs (then tiles add straight
    // into `out`; otherwise through a buffer, element by element).
    let contiguous_at = |j0: usize| {
        let w = (n - j0).min(64);
        (0..w).all(|j| out_cols[j0 + j] == out_cols[j0] + j)
    };
    // Worked out once per call for the first 128 panels (checking 64 offsets per tile cost
    // about 5% of conv2's input gradient), on the fly beyond.
    let mut known = 0u128;
    for (i, j0) in (0..n).step_by(64).take(128).enumerate() {
        known |= u128::from(contiguous_at(j0)) << i;
    }
    let contiguous = |j0: usize| match j0 / 64 {
        i if i < 128 => known >> i & 1 == 1,
        _ => contiguous_at(j0),
    };
    out.par_chunks_mut(glen).enumerate().for_each(|(gi, o)| {
        let rows = &p[gi * grows..][..grows];
        let orows = &out_rows[gi * grows..][..grows];
        let base = gi * glen;
        // SAFETY: AVX-512F checked; `check` proved every `a` and `b` index in bounds and
        // every output index of this group's rows inside `o` (its `glen` values), which
        // no other task touches.
        unsafe {
            scatter_task(
                mr,
                a,
                rows,
                q,
                b,
                ldb,
                n,
                o,
                orows,
                base,
                out_cols,
                &contiguous,
            )
        }
    });
}

/// One group's rows of a scatter GEMM.
///
/// # Safety
/// AVX-512F available; the bounds of [`crate::tensor::gather::ScatterGemm::check`] hold, with `o`
/// the group's
/// output slice starting at index `base` of the whole output.
#[target_feature(enable = "avx512f")]
#[allow(clippy::too_many_arguments)]
unsafe fn scatter_task(
    mr: usize, a: &[f32], p: &[usize], q: &[usize], b: &[f32], ldb: usize, n: usize, o: &mut [f32],
    orows: &[usize], base: usize, ocols: &[usize], contiguous: &dyn Fn(usize) -> bool,
) {
    let nr = p.len();
    let steps = q.len();
    let ap = a.as_ptr();
    let op = o.as_mut_ptr();
    let mut buf = [0f32; 10 * 64];
    // Panels outer, row tiles inner: one panel of `b` (64 steps × 64 columns, 16 KiB for a
    // convolution's `Wᵀ`) stays in L1 across all the group's row tiles.
    for j0 in (0..n).step_by(64) {
        for (r, h) in row_tiles(nr, mr) {
            let (m, nv) = panel_masks(n, j0);
            let w = (n - j0).min(64);
            let direct = contiguous(j0);
            for blk in 0..steps.div_ceil(TB).max(1) {
                let t0 = blk * TB;
                let qb = &q[t0.min(steps)..(t0 + TB).min(steps)];
                // The steps are `0..Cout` here; the table walk measured faster than runs.
                let qr = Steps {
                    table: qb,
                    runs: None,
                };
                let bp = if qb.is_empty() {
                    b.as_ptr()
                } else {
                    b.as_ptr().add(t0 * ldb + j0)
                };
                let (cp, crow, end): (*mut f32, [usize; 10], End) = if direct {
                    let crow = std::array::from_fn(|i| {
                        orows.get(r + i).map_or(0, |&o| o + ocols[j0] - base)
                    });
                    (op, crow, End::Add)
                } else {
                    let crow = std::array::from_fn(|i| i * 64);
                    let end = if blk > 0 { End::Add } else { End::Store };
                    (buf.as_mut_ptr(), crow, end)
                };
                let start = Start::Zero;
                if h == mr {
                    let pr = &p[r..r + mr];
                    match mr {
                        10 => tile_nv::<10>(nv, ap, pr, qr, bp, ldb, cp, &crow, m, start, end),
                        8 => tile_nv::<8>(nv, ap, pr, qr, bp, ldb, cp, &crow, m, start, end),
                        _ => tile_nv::<6>(nv, ap, pr, qr, bp, ldb, cp, &crow, m, start, end),
                    }
                } else {
                    let pr = &p[r..r + h];
                    tile_any(h, nv, ap, pr, qr, bp, ldb, cp, &crow, m, start, end);
                }
            }
            if !direct {
                for i in 0..h {
                    for j in 0..w {
                        *op.add(orows[r + i] + ocols[j0 + j] - base) += buf[i * 64 + j];
                    }
                }
            }
        }
    }
}

/// The product on AVX-512, split over rayon by blocks of rows of `C` whose size depends only
/// on the shape. Call only if [`available`].
pub fn gather_gemm(g: GatherGemm<'_, f32>) {
    assert!(available(), "gather_gemm: AVX-512F and FMA needed");
    g.check();
    if g.is_empty() {
        return;
    }
    // Register tile: MR rows × up to 4 vectors, MR·NV ≤ 24 accumulators.
    let mr = tile_rows(g.n);
    let op = Operands::of(&g);
    let leaf = |pr: &[usize], cc: &mut [f32], dest: Dest<'_>| {
        let init = Start::of(&g.init);
        // SAFETY: AVX-512F checked above; `check` proved every `a`, `b` and bias index in
        // bounds, and this task's rows of C lie inside `cc` (rows increase and the next
        // task's part starts where its first row does), which no other task touches.
        unsafe { task(mr, op, pr, cc.as_mut_ptr(), dest, init) }
    };
    let (steps, n) = (g.q.len(), g.n);
    split_rows(g.c, g.p, g.c_rows, g.ldc, n, steps, mr, &leaf);
}

/// What [`split_rows`] runs for each task: its rows of `p`, its part of `C`, where they go.
pub(crate) type Leaf<'a> = dyn Fn(&[usize], &mut [f32], Dest<'_>) + Sync + 'a;

/// Splits the rows of a gather GEMM's `C` (row `r` at [`row_start`]`(c_rows, ldc, r)`, `n`
/// wide) into rayon tasks of [`rows_per_task`]`(p.len(), steps, n, mr)` rows, a size that depends
/// only on the shape, and runs `leaf(rows, part, dest)` for each: `rows` the task's slice of
/// `p`, `part` its rows' span of `c` (no other task's rows in it), `dest` where each of its rows
/// starts in `part`. The AVX-512 gather kernels (f32, AVX512-BF16, AMX) split their work so
/// (`p` not empty, `n` > 0).
#[allow(clippy::too_many_arguments)]
pub(crate) fn split_rows(
    c: &mut [f32], p: &[usize], c_rows: Option<&[usize]>, ldc: usize, n: usize, steps: usize,
    mr: usize, leaf: &Leaf<'_>,
) {
    let rows = p.len();
    let rpt = rows_per_task(rows, steps, n, mr);
    let tasks = rows.div_ceil(rpt);
    let end = row_start(c_rows, ldc, rows - 1) + n;
    let start = move |t: usize| row_start(c_rows, ldc, t * rpt);
    let run = |t: usize, cc: &mut [f32], base: usize| {
        let r0 = t * rpt;
        let dest = Dest {
            c_rows,
            ldc,
            r0,
            base,
        };
        leaf(&p[r0..(r0 + rpt).min(rows)], cc, dest)
    };
    split_tasks(&mut c[..end], 0, 0, tasks, &start, &run);
}

/// Runs tasks `t0..t1` on their disjoint parts of `c` (which starts at index `base` of the
/// whole `C`; task `t`'s part starts at `start(t)`), halving the range with `rayon::join`.
pub(crate) fn split_tasks(
    c: &mut [f32], base: usize, t0: usize, t1: usize, start: &(dyn Fn(usize) -> usize + Sync),
    run: &(dyn Fn(usize, &mut [f32], usize) + Sync),
) {
    if t1 - t0 == 1 {
        return run(t0, c, base);
    }
    let mid = (t0 + t1) / 2;
    let at = start(mid);
    let (lo, hi) = c.split_at_mut(at - base);
    rayon::join(
        || split_tasks(lo, base, t0, mid, start, run),
        || split_tasks(hi, at, mid, t1, start, run),
    );
}
