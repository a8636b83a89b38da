//! The "gather GEMM": one register-blocked kernel for every product of the network's layers.
//!
//! ```text
//! C[r, j] (= init[r, j]) + Σ_t a[p[r] + q[t]] · b[t·ldb + j]      r < p.len(), t < q.len(), j < n
//! ```
//!
//! The left operand is read through two offset tables, one per accumulator row (`p`) and one per
//! reduction step (`q`), so the same kernel computes, without materialising anything:
//! - a convolution's forward product `cols·W` straight from the (padded) input: `p[m]` is where
//!   output pixel `m`'s receptive field starts, `q[k]` where patch element `k` sits relative to it
//!   (implicit GEMM: im2col's 16x larger matrix for conv1 is never written);
//! - its weight gradient `colsᵀ·dY` with the roles swapped (`p` = patch offsets, `q` = pixel
//!   starts): `dW` is the accumulator, the reduction runs over all `N·OH·OW` pixels, and each row
//!   of `dY` is one contiguous `b` row;
//! - a plain row-major `A·B` (`p[r] = r·lda`, `q[t] = t`) and `Aᵀ·B` (`p[r] = r`, `q[t] = t·lda`).
//!
//! Every element of `C` is summed in the order `t = 0, 1, …` (after its initial value), whatever
//! the tiling and the thread count, so results are bit-identical for any number of threads.

use super::Float;

/// What `C` starts from before the sum.
#[derive(Clone, Copy, Debug)]
pub enum Init<'a, T> {
    /// Zero: `C` is overwritten (whatever it held, NaN included).
    Zero,
    /// `C`'s current values: the product is added to it.
    Accumulate,
    /// The same row vector (`n` values) for every row, e.g. a layer's bias.
    Bias(&'a [T]),
}

/// The operands of one gather GEMM (see the module documentation).
pub struct GatherGemm<'a, T> {
    /// The gathered operand.
    pub a: &'a [T],
    /// One offset into `a` per row of `C`.
    pub p: &'a [usize],
    /// One offset into `a` per reduction step.
    pub q: &'a [usize],
    /// The right operand: row `t` is `b[t·ldb .. t·ldb + n]`.
    pub b: &'a [T],
    pub ldb: usize,
    /// Columns of `C`.
    pub n: usize,
    /// The result: row `r` is `c[r·ldc .. r·ldc + n]`.
    pub c: &'a mut [T],
    pub ldc: usize,
    pub init: Init<'a, T>,
}

impl<T: Float> GatherGemm<'_, T> {
    /// Panics unless every index the product reaches is inside its slice.
    pub fn check(&self) {
        let (rows, steps) = (self.p.len(), self.q.len());
        if rows == 0 || self.n == 0 {
            return;
        }
        assert!(self.n <= self.ldc, "gather_gemm: n > ldc");
        assert!(
            self.c.len() >= (rows - 1) * self.ldc + self.n,
            "gather_gemm: C too short"
        );
        if let Init::Bias(bias) = self.init {
            assert!(bias.len() >= self.n, "gather_gemm: bias too short");
        }
        if steps > 0 {
            assert!(self.n <= self.ldb, "gather_gemm: n > ldb");
            assert!(
                self.b.len() >= (steps - 1) * self.ldb + self.n,
                "gather_gemm: B too short"
            );
            let pmax = self.p.iter().copied().max().unwrap_or(0);
            let qmax = self.q.iter().copied().max().unwrap_or(0);
            assert!(
                pmax + qmax < self.a.len(),
                "gather_gemm: A index out of range"
            );
        }
    }
}

/// The portable kernel: plain loops in the same summation order as the fast one (the fallback
/// where AVX-512 is missing, and the oracle for it in the tests).
pub fn gather_gemm_portable<T: Float>(g: GatherGemm<'_, T>) {
    g.check();
    let GatherGemm {
        a,
        p,
        q,
        b,
        ldb,
        n,
        c,
        ldc,
        init,
    } = g;
    for (r, &pr) in p.iter().enumerate() {
        let row = &mut c[r * ldc..][..n];
        match init {
            Init::Zero => row.fill(T::zero()),
            Init::Accumulate => {}
            Init::Bias(bias) => row.copy_from_slice(&bias[..n]),
        }
        for (t, &qt) in q.iter().enumerate() {
            let av = a[pr + qt];
            for (cv, &bv) in row.iter_mut().zip(&b[t * ldb..][..n]) {
                *cv = av.mul_add(bv, *cv);
            }
        }
    }
}

/// Fills `v` with `0, step, 2·step, …` (`len` values), reusing its buffer.
pub fn fill_iota(v: &mut Vec<usize>, len: usize, step: usize) {
    v.clear();
    v.extend((0..len).map(|i| i * step));
}

#[cfg(target_arch = "x86_64")]
pub(crate) mod avx512 {
    //! The AVX-512 kernel: an `MR × 16·NV` block of `C` lives in `MR·NV ≤ 24` zmm registers for
    //! a whole block of reduction steps; each step loads `NV` vectors of the `b` row and
    //! broadcasts `MR` gathered `a` values, i.e. `MR + NV` loads per `MR·NV` FMAs. Shapes: `n ≤ 32`
    //! (conv1's 32 channels) runs 12 × 2, `n = 64` (conv2, conv3) 6 × 4; wider `C` goes in panels
    //! of 64 columns, the column tail under a mask.
    use super::{GatherGemm, Init};
    use rayon::prelude::*;
    use std::arch::x86_64::*;

    /// Whether this CPU runs the kernel.
    pub fn available() -> bool {
        is_x86_feature_detected!("avx512f") && is_x86_feature_detected!("fma")
    }

    /// Reduction steps per block: the block's `b` rows (at most 256 × 64 floats, 64 KiB) stay in
    /// L1/L2 while every row tile of a task runs over them.
    const TB: usize = 256;

    #[derive(Clone, Copy)]
    enum Start {
        Zero,
        Load,
        Bias(*const f32),
    }

    /// One `MR × 16·NV` tile over the steps `q`.
    ///
    /// # Safety
    /// AVX-512F must be available; `a + p[r] + q[t]` for all `r < MR`, `t` must be readable, `b`
    /// rows `t` readable up to their masked width, `c` rows `r` (stride `ldc`) readable and
    /// writable up to the masked width, and a `Bias` pointer readable likewise.
    #[target_feature(enable = "avx512f")]
    #[inline]
    unsafe fn tile<const MR: usize, const NV: usize>(
        a: *const f32,
        p: &[usize],
        q: &[usize],
        b: *const f32,
        ldb: usize,
        c: *mut f32,
        ldc: usize,
        masks: [u16; NV],
        start: Start,
    ) {
        let mut acc = [[_mm512_setzero_ps(); NV]; MR];
        for r in 0..MR {
            for v in 0..NV {
                acc[r][v] = match start {
                    Start::Zero => _mm512_setzero_ps(),
                    Start::Load => _mm512_maskz_loadu_ps(masks[v], c.add(r * ldc + 16 * v)),
                    Start::Bias(bias) => _mm512_maskz_loadu_ps(masks[v], bias.add(16 * v)),
                };
            }
        }
        let mut rows = [a; MR];
        for r in 0..MR {
            rows[r] = a.add(p[r]);
        }
        let mut brow = b;
        for &qt in q {
            let mut bv = [_mm512_setzero_ps(); NV];
            for v in 0..NV {
                bv[v] = _mm512_maskz_loadu_ps(masks[v], brow.add(16 * v));
            }
            for r in 0..MR {
                let av = _mm512_set1_ps(*rows[r].add(qt));
                for v in 0..NV {
                    acc[r][v] = _mm512_fmadd_ps(av, bv[v], acc[r][v]);
                }
            }
            brow = brow.add(ldb);
        }
        for r in 0..MR {
            for v in 0..NV {
                _mm512_mask_storeu_ps(c.add(r * ldc + 16 * v), masks[v], acc[r][v]);
            }
        }
    }

    /// Dispatches one tile on the panel width (in vectors).
    ///
    /// # Safety
    /// As [`tile`], with `nv` in `1..=4` and `masks[..nv]` the panel's lane masks.
    #[target_feature(enable = "avx512f")]
    #[inline]
    #[allow(clippy::too_many_arguments)]
    unsafe fn tile_nv<const MR: usize>(
        nv: usize,
        a: *const f32,
        p: &[usize],
        q: &[usize],
        b: *const f32,
        ldb: usize,
        c: *mut f32,
        ldc: usize,
        m: [u16; 4],
        start: Start,
    ) {
        match nv {
            1 => tile::<MR, 1>(a, p, q, b, ldb, c, ldc, [m[0]], start),
            2 => tile::<MR, 2>(a, p, q, b, ldb, c, ldc, [m[0], m[1]], start),
            3 => tile::<MR, 3>(a, p, q, b, ldb, c, ldc, [m[0], m[1], m[2]], start),
            _ => tile::<MR, 4>(a, p, q, b, ldb, c, ldc, m, start),
        }
    }

    /// Rows `0..p.len()` of one task's block of `C` (`c` points at its first row).
    ///
    /// # Safety
    /// AVX-512F available; the bounds of [`GatherGemm::check`] hold for these rows.
    #[target_feature(enable = "avx512f")]
    #[allow(clippy::too_many_arguments)]
    unsafe fn task(
        mr: usize,
        a: &[f32],
        p: &[usize],
        q: &[usize],
        b: &[f32],
        ldb: usize,
        n: usize,
        c: *mut f32,
        ldc: usize,
        init: Start,
    ) {
        let nr = p.len();
        let steps = q.len();
        let nblocks = steps.div_ceil(TB).max(1);
        for blk in 0..nblocks {
            let t0 = blk * TB;
            let qb = &q[t0.min(steps)..(t0 + TB).min(steps)];
            let bb = if qb.is_empty() {
                b.as_ptr()
            } else {
                b.as_ptr().add(t0 * ldb)
            };
            let start = if blk == 0 { init } else { Start::Load };
            let mut r = 0;
            while r < nr {
                let full = nr - r >= mr;
                for j0 in (0..n).step_by(64) {
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
                    let st = match start {
                        Start::Bias(bias) => Start::Bias(bias.add(j0)),
                        s => s,
                    };
                    let cp = c.add(r * ldc + j0);
                    let bp = bb.add(j0);
                    let ap = a.as_ptr();
                    if full {
                        let pr = &p[r..r + mr];
                        match mr {
                            12 => tile_nv::<12>(nv, ap, pr, qb, bp, ldb, cp, ldc, m, st),
                            8 => tile_nv::<8>(nv, ap, pr, qb, bp, ldb, cp, ldc, m, st),
                            _ => tile_nv::<6>(nv, ap, pr, qb, bp, ldb, cp, ldc, m, st),
                        }
                    } else {
                        for rr in r..nr {
                            let pr = &p[rr..rr + 1];
                            let cp = c.add(rr * ldc + j0);
                            tile_nv::<1>(nv, ap, pr, qb, bp, ldb, cp, ldc, m, st);
                        }
                    }
                }
                r += mr;
            }
        }
    }

    /// The product on AVX-512, split over rayon by blocks of rows of `C` whose size depends only
    /// on the shape. Call only if [`available`].
    pub fn gather_gemm(g: GatherGemm<'_, f32>) {
        assert!(available(), "gather_gemm: AVX-512F and FMA needed");
        g.check();
        let GatherGemm {
            a,
            p,
            q,
            b,
            ldb,
            n,
            c,
            ldc,
            init,
        } = g;
        let rows = p.len();
        if rows == 0 || n == 0 {
            return;
        }
        // Register tile: MR rows × up to 4 vectors, MR·NV ≤ 24 accumulators.
        let mr = match n.min(64).div_ceil(16) {
            1 | 2 => 8,
            3 => 8,
            _ => 6,
        };
        // A few tasks per thread: enough to balance two cores (one of which may be busy), few
        // enough that each task's row tiles share every block of `b` rows (and, for a weight
        // gradient, of gathered input) while it is in cache. Any split gives the same bits.
        let flops = 2 * rows * q.len().max(1) * n;
        let tasks = flops
            .div_ceil(1 << 22)
            .clamp(1, 4 * rayon::current_num_threads());
        let rpt = rows.div_ceil(tasks).div_ceil(mr) * mr;
        c[..(rows - 1) * ldc + n]
            .par_chunks_mut(rpt * ldc)
            .enumerate()
            .for_each(|(i, cc)| {
                let r0 = i * rpt;
                let pr = &p[r0..(r0 + rpt).min(rows)];
                let start = match init {
                    Init::Zero => Start::Zero,
                    Init::Accumulate => Start::Load,
                    Init::Bias(bias) => Start::Bias(bias.as_ptr()),
                };
                // SAFETY: AVX-512F checked above; `check` proved every `a`, `b` and bias index
                // in bounds, and this task's rows r0.. of C are exactly `cc` (row r's n columns
                // end at (r−r0)·ldc + n ≤ cc.len()), which no other task touches.
                unsafe { task(mr, a, pr, q, b, ldb, n, cc.as_mut_ptr(), ldc, start) }
            });
    }
}
