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

use super::cpu::avx512_twin;
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

/// The operands of one gather GEMM (see the module documentation): `A` and `B` of `T`, `C` of
/// `O`. In f32 or f64 all three are of one type; in bf16 ([`super::GatherGemmBf16`]) `A` and `B`
/// hold bf16 bits in pairs of reduction steps and `C` is f32.
pub struct GatherGemm<'a, T, O = T> {
    /// The gathered operand.
    pub a: &'a [T],
    /// One offset into `a` per row of `C`.
    pub p: &'a [usize],
    /// One offset into `a` per reduction step (bf16: per pair of steps, the pair being
    /// `a[p[r] + q[u]]` and the value after it).
    pub q: &'a [usize],
    /// The right operand: row `t` is `b[t·ldb .. t·ldb + n]` (bf16: pair `u` of column `j` is
    /// `b[2·(u·ldb + j)..][..2]`).
    pub b: &'a [T],
    pub ldb: usize,
    /// Columns of `C`.
    pub n: usize,
    /// The result: row `r` is `c[r·ldc .. r·ldc + n]`, or `c[c_rows[r] ..][..n]` if given.
    pub c: &'a mut [O],
    pub ldc: usize,
    /// Where each row of `C` starts in `c`, strictly increasing by at least `n` (e.g. the
    /// interior pixels of an output with a zero border): `None` means `r·ldc`. Places of `c`
    /// between rows are not touched.
    pub c_rows: Option<&'a [usize]>,
    pub init: Init<'a, O>,
    /// Store `max(C, 0)` instead of `C` (a fused ReLU).
    pub relu: bool,
}

impl<'a, T, O> GatherGemm<'a, T, O> {
    /// `C = init + A[p, q]·B` in the common layout: `B` and `C` packed `n` wide (`ldb = ldc =
    /// n`), the rows of `C` one after another, no ReLU. Set `c_rows` or `relu` on the result
    /// for the others.
    pub fn new(
        a: &'a [T], p: &'a [usize], q: &'a [usize], b: &'a [T], n: usize, c: &'a mut [O],
        init: Init<'a, O>,
    ) -> Self {
        GatherGemm {
            a,
            p,
            q,
            b,
            ldb: n,
            n,
            c,
            ldc: n,
            c_rows: None,
            init,
            relu: false,
        }
    }
}

/// Whether `start + plus < limit`, with `start` `None` when computing it overflowed: no sum in
/// a bounds check may wrap around.
pub(crate) fn within(start: Option<usize>, plus: usize, limit: usize) -> bool {
    start
        .and_then(|s| s.checked_add(plus))
        .is_some_and(|end| end < limit)
}

avx512_twin! {
    /// The largest offset in a table (0 if empty).
    ///
    /// A branch-free fold, so that compiled for AVX-512 it runs 8 lanes wide: the checks scan
    /// every offset table of every product (over 20 000 rows for conv1), and as baseline SSE2,
    /// which has no 64-bit max, they took 1.5% of a train step.
    pub(crate) fn largest(v: &[usize]) -> usize {
        v.iter().fold(0, |m, &x| m.max(x))
    }
}

avx512_twin! {
    /// Whether each row start is at least `n` past the one before (rows increase, never
    /// overlap), written without a sum that could wrap.
    pub(crate) fn rows_apart(starts: &[usize], n: usize) -> bool {
        starts.windows(2).fold(true, |ok, w| {
            ok & (w[1] >= w[0]) & (w[1].wrapping_sub(w[0]) >= n)
        })
    }
}

/// Rows of `C` per rayon task for a gather GEMM of `rows` rows, `steps` reduction steps and `n`
/// columns, a multiple of the register tile's `mr` rows: tasks of about 2²² flops, a few per
/// thread (enough to balance two cores, one of which may be busy; few enough that each task's
/// row tiles share every block of `b` while it is in cache), but one per thread for a weight
/// gradient (few rows, a long reduction: each task streams all of `a` and `b`). Any split gives
/// the same bits.
pub(crate) fn rows_per_task(rows: usize, steps: usize, n: usize, mr: usize) -> usize {
    let flops = 2 * rows * steps.max(1) * n;
    let threads = rayon::current_num_threads();
    let most = if 8 * rows < steps {
        threads
    } else {
        4 * threads
    };
    let tasks = flops.div_ceil(1 << 22).clamp(1, most);
    rows.div_ceil(tasks).div_ceil(mr) * mr
}

/// Where row `r` of `C` starts in `c`: `c_rows[r]`, or `r·ldc` without a table.
#[inline]
pub(crate) fn row_start(c_rows: Option<&[usize]>, ldc: usize, r: usize) -> usize {
    c_rows.map_or(r * ldc, |cr| cr[r])
}

/// The checks on `C` shared by the gather kernels (`kernel` names the caller in the message): `rows`
/// rows of `n` columns at `ldc` apart or at `c_rows` (increasing, not overlapping), inside
/// `c_len` values; a bias covers the `n` columns.
pub(crate) fn check_c<T>(
    kernel: &str, rows: usize, n: usize, ldc: usize, c_rows: Option<&[usize]>, c_len: usize,
    init: &Init<'_, T>,
) {
    match c_rows {
        None => assert!(n <= ldc, "{kernel}: n > ldc"),
        Some(cr) => {
            assert_eq!(cr.len(), rows, "{kernel}: c_rows length");
            assert!(rows_apart(cr, n), "{kernel}: c_rows overlap or decrease");
        }
    }
    // Sums in checked arithmetic: a table entry near `usize::MAX` must not wrap past a check.
    let last = match c_rows {
        Some(cr) => Some(cr[rows - 1]),
        None => (rows - 1).checked_mul(ldc),
    };
    assert!(within(last, n, c_len + 1), "{kernel}: C too short");
    if let Init::Bias(bias) = init {
        assert!(bias.len() >= n, "{kernel}: bias too short");
    }
}

impl<T: Float> GatherGemm<'_, T> {
    /// Where row `r` of `C` starts in `c`.
    #[inline]
    pub fn row_start(&self, r: usize) -> usize {
        row_start(self.c_rows, self.ldc, r)
    }

    /// Panics unless every index the product reaches is inside its slice.
    pub fn check(&self) {
        self.check_steps("gather_gemm", 1);
    }
}

impl<T, O> GatherGemm<'_, T, O> {
    /// Whether the product has no element (no row or no column): a kernel, once it has
    /// checked the operands, returns at once.
    pub(crate) fn is_empty(&self) -> bool {
        self.p.is_empty() || self.n == 0
    }

    /// Panics (naming `what`) unless every index the product reaches is inside its slice, each
    /// reduction step reading `w` consecutive values of `A` and of `B` (1, or 2 for bf16 pairs).
    pub(crate) fn check_steps(&self, what: &str, w: usize) {
        let rows = self.p.len();
        if rows == 0 || self.n == 0 {
            return;
        }
        let c_len = self.c.len();
        check_c(what, rows, self.n, self.ldc, self.c_rows, c_len, &self.init);
        let (a, b) = (self.a.len(), self.b.len());
        check_ab(what, a, self.p, self.q, b, self.ldb, self.n, w);
    }
}

/// Panics (naming `what`) unless a gather GEMM's `A` (`a` values) and `B` (`b` values, rows
/// `ldb` apart, `n` wide) hold every value its offsets `p` and `q` reach, each reduction step
/// reading `w` consecutive values of both (1, or 2 for bf16 pairs).
#[allow(clippy::too_many_arguments)]
fn check_ab(
    what: &str, a: usize, p: &[usize], q: &[usize], b: usize, ldb: usize, n: usize, w: usize,
) {
    if q.is_empty() {
        return;
    }
    assert!(n <= ldb, "{what}: n > ldb");
    // The last step of the last row of `b` ends at w·((steps − 1)·ldb + n).
    let b_end = (q.len() - 1)
        .checked_mul(ldb)
        .and_then(|x| x.checked_add(n))
        .and_then(|x| x.checked_mul(w));
    assert!(within(b_end, 0, b + 1), "{what}: B too short");
    // The last value of the farthest step: p + q + w − 1 < a.len().
    let far = largest(p).checked_add(w - 1);
    assert!(within(far, largest(q), a), "{what}: A index out of range");
}

/// A gather GEMM whose rows are added onto scattered, possibly overlapping places of `out`:
///
/// ```text
/// out[out_rows[r] + out_cols[j]] += Σ_t a[p[r] + q[t]] · b[t·ldb + j]      r < p.len(), j < n
/// ```
///
/// A convolution's input gradient with col2im fused in: `a = dY`, `b = Wᵀ`, `out` the padded
/// input gradient, `out_rows`/`out_cols` the pixel and patch offsets of the forward gather, so
/// the `[N·OH·OW, K]` matrix `dcols` is never stored. Rows come in `groups` equal groups (images)
/// that each write only to their own `1/groups` of `out`, one task per group, rows added in order.
pub struct ScatterGemm<'a, T> {
    pub a: &'a [T],
    pub p: &'a [usize],
    pub q: &'a [usize],
    pub b: &'a [T],
    pub ldb: usize,
    pub n: usize,
    pub out: &'a mut [T],
    pub out_rows: &'a [usize],
    pub out_cols: &'a [usize],
    pub groups: usize,
}

impl<T: Float> ScatterGemm<'_, T> {
    /// Panics unless every index is inside its slice and each group's rows stay in its part.
    pub fn check(&self) {
        let rows = self.p.len();
        if rows == 0 || self.n == 0 {
            return;
        }
        assert!(
            self.groups > 0
                && rows.is_multiple_of(self.groups)
                && self.out.len().is_multiple_of(self.groups),
            "scatter_gemm: groups"
        );
        assert_eq!(self.out_rows.len(), rows, "scatter_gemm: out_rows");
        assert!(self.out_cols.len() >= self.n, "scatter_gemm: out_cols");
        let (grows, glen) = (rows / self.groups, self.out.len() / self.groups);
        let cmax = self.out_cols[..self.n].iter().copied().max().unwrap_or(0);
        for (r, &o) in self.out_rows.iter().enumerate() {
            let g = r / grows;
            assert!(
                o >= g * glen && within(Some(o), cmax, (g + 1) * glen),
                "scatter_gemm: row {r} leaves its group"
            );
        }
        let (a, b) = (self.a.len(), self.b.len());
        check_ab("scatter_gemm", a, self.p, self.q, b, self.ldb, self.n, 1);
    }
}

/// The portable scatter GEMM (fallback and test oracle): each row's sums, then added in row order.
#[inline(always)]
pub fn scatter_gemm_portable<T: Float>(g: ScatterGemm<'_, T>) {
    g.check();
    let mut row = vec![T::zero(); g.n];
    for (r, &pr) in g.p.iter().enumerate() {
        row.fill(T::zero());
        for (t, &qt) in g.q.iter().enumerate() {
            let av = g.a[pr + qt];
            for (cv, &bv) in row.iter_mut().zip(&g.b[t * g.ldb..][..g.n]) {
                *cv = av.mul_add(bv, *cv);
            }
        }
        for (j, &v) in row.iter().enumerate() {
            g.out[g.out_rows[r] + g.out_cols[j]] += v;
        }
    }
}

/// The portable kernel: plain loops in the same summation order as the fast one (the fallback
/// where AVX-512 is missing, and the oracle for it in the tests).
pub fn gather_gemm_portable<T: Float>(g: GatherGemm<'_, T>) {
    g.check();
    let (a, q, b, ldb, n) = (g.a, g.q, g.b, g.ldb, g.n);
    portable_rows(g, |row, pr| {
        for (t, &qt) in q.iter().enumerate() {
            let av = a[pr + qt];
            for (cv, &bv) in row.iter_mut().zip(&b[t * ldb..][..n]) {
                *cv = av.mul_add(bv, *cv);
            }
        }
    });
}

/// The frame of the portable gather kernels (f32 and f64 here, bf16 in
/// [`super::gather_bf16`]), row by row of `C`: start the row as `init` says, add the product
/// of `A`'s row at `p[r]` (`add(row, p[r])`, in the kernel's own summation order), then store
/// `max(·, 0)` if `relu`.
pub(crate) fn portable_rows<T, O: Float>(
    g: GatherGemm<'_, T, O>, mut add: impl FnMut(&mut [O], usize),
) {
    for (r, &pr) in g.p.iter().enumerate() {
        let row = &mut g.c[row_start(g.c_rows, g.ldc, r)..][..g.n];
        match g.init {
            Init::Zero => row.fill(O::zero()),
            Init::Accumulate => {}
            Init::Bias(bias) => row.copy_from_slice(&bias[..g.n]),
        }
        add(row, pr);
        if g.relu {
            for v in row.iter_mut() {
                *v = v.max(O::zero());
            }
        }
    }
}

/// Fills `v` with `0, step, 2·step, …` (`len` values), reusing its buffer.
pub fn fill_iota(v: &mut Vec<usize>, len: usize, step: usize) {
    v.clear();
    v.extend((0..len).map(|i| i * step));
}
