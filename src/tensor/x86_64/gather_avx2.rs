//! The gather GEMM ([`GatherGemm`]) on AVX2 and FMA: what CPUs without AVX-512 run (Intel's
//! client CPUs since Haswell, AMD Zen 1 to 3).
//!
//! The same kernel as the AVX-512 one, 8 lanes wide: an `MR × 8·NV` block of `C` lives in
//! registers for a block of [`TB`] reduction steps; each step loads the `NV` vectors of the `b`
//! row and broadcasts `MR` gathered `a` values, `NV + MR` loads per `MR·NV` FMAs. With 16 ymm
//! registers a tile is at most 12 accumulators beside its `b` vectors and a broadcast: panels of
//! 16 columns (`NV = 2`) and 6 rows; a panel's tail columns under a lane mask. Every element of
//! `C` is summed in the order `t = 0, 1, …` with one fused multiply-add per step, as the portable
//! loop ([`super::super::gather::gather_gemm_portable`]) sums it: the two give the same bits, for
//! any tiling and thread count.

use std::arch::x86_64::*;

use super::super::cpu;
use super::super::gather::{row_start, rows_per_task, GatherGemm};
use super::gather_avx512::{row_tiles, split_tasks, Dest, Operands};
use super::sums::{self, End, Start};

/// Reduction steps per block: the block's `b` rows of one panel (128 × 16 floats, 8 KiB) stay in
/// L1 while every row tile of a task runs over them.
const TB: usize = 128;

/// Rows of the tallest tile: 6 × 2 vectors = 12 accumulators.
const MR: usize = 6;

/// Columns per panel: the whole of a `C` up to 32 columns wide (conv1's forward pass: 2 × 4
/// tiles, the gathered values read once), else 16 (6 × 2 tiles, more rows sharing each `b`
/// load). Measured on conv1's forward pass (AMD Zen 3, one thread): 16-column panels ran at 48
/// GFLOP/s, 32-column panels of 3 rows (spilled) at 36, of 2 rows at 69; conv2's and conv3's
/// products were faster by 16-column panels of 6 rows.
fn panel_width(n: usize) -> usize {
    if n <= 32 {
        32
    } else {
        16
    }
}

/// Tile rows for a panel `nv` vectors wide: at most 12 accumulators beside the `b` vectors.
fn tile_rows(nv: usize) -> usize {
    match nv {
        1 | 2 => 6,
        3 => 4,
        _ => MR4,
    }
}

/// Tile rows of a full 4-vector panel.
const MR4: usize = 2;

/// The lane mask of `lanes` (0 to 8) leading lanes, for `maskload`/`maskstore`.
#[inline]
fn lane_mask(lanes: usize) -> [i32; 8] {
    std::array::from_fn(|i| if i < lanes { -1 } else { 0 })
}

/// One `H × 8·NV` tile over a block of the reduction ([`Steps`]); `FULL`: every lane of the
/// panel is used, so `b` is read by plain loads.
///
/// # Safety
/// AVX2 and FMA available; `a + p[r] + q[t]` readable for all `r < H`, `t`; `b` rows `t`
/// readable up to their masked width; `c` rows `crow[r]` readable and writable up to the masked
/// width; a `Bias` pointer readable likewise.
#[target_feature(enable = "avx2,fma")]
#[inline]
#[allow(clippy::too_many_arguments)]
unsafe fn tile<const H: usize, const NV: usize, const FULL: bool>(
    a: *const f32, p: &[usize], q: Steps<'_>, b: *const f32, ldb: usize, c: *mut f32,
    crow: &[usize], masks: [__m256i; NV], start: Start, end: End,
) {
    let mut acc = sums::start::<__m256, H, NV>(c, crow, masks, start);
    let rows = sums::rows::<_, H>(a, p);
    let mut brow = b;
    // One step: the `b` vectors, then each row's broadcast value `a_r` into its accumulators.
    macro_rules! step {
        ($a_r:expr) => {{
            let mut bv = [_mm256_setzero_ps(); NV];
            for v in 0..NV {
                bv[v] = if FULL {
                    _mm256_loadu_ps(brow.add(8 * v))
                } else {
                    _mm256_maskload_ps(brow.add(8 * v), masks[v])
                };
            }
            for r in 0..H {
                let av = _mm256_broadcast_ss(&*$a_r(r));
                for v in 0..NV {
                    acc[r][v] = _mm256_fmadd_ps(av, bv[v], acc[r][v]);
                }
            }
            brow = brow.add(ldb);
        }};
    }
    match q {
        // Runs of consecutive offsets (a convolution's patch rows, a plain `A·B`): within a run
        // one index addresses every row.
        Steps::Runs(runs) => {
            for &(first, len) in runs {
                let mut ar = [a; H];
                for r in 0..H {
                    ar[r] = rows[r].add(first);
                }
                for i in 0..len {
                    step!(|r: usize| ar[r].add(i));
                }
            }
        }
        // Scattered offsets (a weight gradient's pixel starts): the table, step by step.
        Steps::Table(table) => {
            for &qt in table {
                step!(|r: usize| rows[r].add(qt));
            }
        }
    }
    sums::end(&acc, c, crow, masks, end);
}

/// A block of reduction offsets as a tile walks them.
#[derive(Clone, Copy)]
enum Steps<'a> {
    /// Runs `(first, length)` of consecutive offsets, where they are long enough to pay (at
    /// least 4 steps on average).
    Runs(&'a [(usize, usize)]),
    /// The offsets one by one.
    Table(&'a [usize]),
}

/// Splits a block of reduction offsets into runs of consecutive values, `(first, length)`.
fn runs(q: &[usize], out: &mut Vec<(usize, usize)>) {
    out.clear();
    for &v in q {
        match out.last_mut() {
            Some((first, len)) if *first + *len == v => *len += 1,
            _ => out.push((v, 1)),
        }
    }
}

/// A tile of height `h` (1 to [`MR`]) and width `nv` vectors (1 or 2), `full` if every lane is
/// used.
///
/// # Safety
/// As [`tile`].
#[target_feature(enable = "avx2,fma")]
#[allow(clippy::too_many_arguments)]
unsafe fn tile_any(
    h: usize, nv: usize, full: bool, a: *const f32, p: &[usize], q: Steps<'_>, b: *const f32,
    ldb: usize, c: *mut f32, crow: &[usize], m: [__m256i; 4], start: Start, end: End,
) {
    macro_rules! go {
        ($h:literal) => {
            match (nv, full) {
                (1, true) => tile::<$h, 1, true>(a, p, q, b, ldb, c, crow, [m[0]], start, end),
                (1, false) => tile::<$h, 1, false>(a, p, q, b, ldb, c, crow, [m[0]], start, end),
                (2, true) => {
                    tile::<$h, 2, true>(a, p, q, b, ldb, c, crow, [m[0], m[1]], start, end)
                }
                (2, false) => {
                    tile::<$h, 2, false>(a, p, q, b, ldb, c, crow, [m[0], m[1]], start, end)
                }
                (3, true) => {
                    tile::<$h, 3, true>(a, p, q, b, ldb, c, crow, [m[0], m[1], m[2]], start, end)
                }
                (3, false) => {
                    tile::<$h, 3, false>(a, p, q, b, ldb, c, crow, [m[0], m[1], m[2]], start, end)
                }
                (_, true) => tile::<$h, 4, true>(a, p, q, b, ldb, c, crow, m, start, end),
                (_, false) => tile::<$h, 4, false>(a, p, q, b, ldb, c, crow, m, start, end),
            }
        };
    }
    match h {
        1 => go!(1),
        2 => go!(2),
        3 => go!(3),
        4 => go!(4),
        5 => go!(5),
        _ => go!(6),
    }
}

/// Rows `0..p.len()` of one task's part of `C` (`c` points at the start of its part).
///
/// # Safety
/// AVX2 and FMA available; the bounds of [`GatherGemm::check`] hold for these rows.
#[target_feature(enable = "avx2,fma")]
unsafe fn task(op: Operands<'_, f32>, p: &[usize], c: *mut f32, dest: Dest<'_>, init: Start) {
    let (a, q, b, ldb, n, relu) = (op.a, op.q, op.b, op.ldb, op.n, op.relu);
    let (nr, steps) = (p.len(), q.len());
    // The whole reduction in one block where it is short and `C` narrow (conv1's forward: 256
    // steps, 32 columns), as the AVX-512 kernel does: sums stay in registers start to end.
    let tb = if n <= 32 && steps <= 2 * TB {
        2 * TB
    } else {
        TB
    };
    let nblocks = steps.div_ceil(tb).max(1);
    let mut run_buf = Vec::with_capacity(tb);
    // Panels outer, then blocks of steps, then row tiles: one panel's block of `b` stays in L1
    // across the task's row tiles.
    let panel = panel_width(n);
    for j0 in (0..n).step_by(panel) {
        let w = (n - j0).min(panel);
        let nv = w.div_ceil(8);
        let mr = tile_rows(nv);
        let m: [__m256i; 4] = std::array::from_fn(|v| {
            _mm256_loadu_si256(lane_mask(w.saturating_sub(8 * v).min(8)).as_ptr().cast())
        });
        for blk in 0..nblocks {
            let t0 = blk * tb;
            let qb = &q[t0.min(steps)..(t0 + tb).min(steps)];
            runs(qb, &mut run_buf);
            let steps_of = if 4 * run_buf.len() <= qb.len() {
                Steps::Runs(&run_buf)
            } else {
                Steps::Table(qb)
            };
            let bb = if qb.is_empty() {
                b.as_ptr()
            } else {
                b.as_ptr().add(t0 * ldb + j0)
            };
            let start = init.block(blk).panel(j0);
            let end = End::last(relu, blk, nblocks);
            for (r, h) in row_tiles(nr, mr) {
                let (d0, crow) = dest.tile::<MR>(r, h);
                tile_any(
                    h,
                    nv,
                    w.is_multiple_of(8),
                    a.as_ptr(),
                    &p[r..r + h],
                    steps_of,
                    bb,
                    ldb,
                    c.add(d0 + j0),
                    &crow,
                    m,
                    start,
                    end,
                );
            }
        }
    }
}

/// The product on AVX2 and FMA, split over rayon by blocks of rows of `C` whose size depends only
/// on the shape. Call only where [`super::super::cpu::avx2`] holds.
pub fn gather_gemm(g: GatherGemm<'_, f32>) {
    assert!(cpu::avx2(), "gather_gemm: AVX2 and FMA needed");
    g.check();
    if g.is_empty() {
        return;
    }
    let rows = g.p.len();
    let rpt = rows_per_task(rows, g.q.len(), g.n, MR);
    let tasks = rows.div_ceil(rpt);
    let end = g.row_start(rows - 1) + g.n;
    let (c_rows, ldc) = (g.c_rows, g.ldc);
    let start = move |t: usize| row_start(c_rows, ldc, t * rpt);
    let op = Operands::of(&g);
    let run = |t: usize, cc: &mut [f32], base: usize| {
        let r0 = t * rpt;
        let pr = &g.p[r0..(r0 + rpt).min(rows)];
        let init = Start::of(&g.init);
        let dest = Dest {
            c_rows,
            ldc,
            r0,
            base,
        };
        // SAFETY: AVX2 and FMA checked above; `check` proved every `a`, `b` and bias index in
        // bounds, and this task's rows of C lie inside `cc` (rows increase and the next task's
        // part starts where its first row does), which no other task touches.
        unsafe { task(op, pr, cc.as_mut_ptr(), dest, init) }
    };
    split_tasks(&mut g.c[..end], 0, 0, tasks, &start, &run);
}
