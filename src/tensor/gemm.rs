//! Matrix multiplication on faer's GEMM: the plain product of the plan's `Kernel::Gemm` and
//! `Kernel::Im2col` (a dense layer off AVX-512, im2col's products on the portable path) and of
//! the small products beside the layers (the quantile embedding). The layers' fast products
//! run this crate's own kernels instead (the gather GEMM, Winograd, the sparse products).
//!
//! All matrices are dense and row-major. `op(A)` is `A` or its transpose, so the three products of
//! a layer's forward and backward passes (`X·W`, `Xᵀ·dY`, `dY·Wᵀ`) are all one call without
//! copying a transpose. The work is split over rayon by disjoint blocks of rows of `C`; the block
//! size depends only on the shape, never on the thread count, and each element of `C` is summed in
//! the same order whatever the split, so the result is bit-identical for any number of threads.
//!
//! The per-shape measurements that choose between kernels live in `benches/layers.rs`.

use super::Float;
use rayon::prelude::*;

/// Whether an operand is used as stored or transposed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Op {
    /// Use the matrix as stored.
    N,
    /// Use its transpose.
    T,
}

/// Rows of `C` per rayon task: about 64 KFLOP of work each, but at least 16 rows.
fn rows_per_task(m: usize, k: usize, n: usize) -> usize {
    let per_row = (k * n).max(1);
    (65_536 / per_row).clamp(16, m.max(16))
}

/// `C[m×n] = alpha · op(A)[m×k] · op(B)[k×n] + beta · C`, all row-major: the plain product
/// (see the module documentation for who calls it). It runs faer's kernels, which measured about twice as fast as matrixmultiply on
/// every GEMM of the article's network (`cargo bench --bench layers -- gemm`), e.g. 70 against
/// 35 GFLOP/s for conv1's forward product on one core.
///
/// With `Op::N`, `a` holds `m×k`; with `Op::T` it holds `k×m` (likewise `b`: `k×n` or `n×k`).
/// `beta` must be 0 (overwrite `C`, whatever it held, NaN included) or 1 (accumulate into it).
#[allow(clippy::too_many_arguments)]
pub fn gemm<T: Float>(
    opa: Op, opb: Op, m: usize, n: usize, k: usize, alpha: T, a: &[T], b: &[T], beta: T,
    c: &mut [T],
) {
    gemm_faer(opa, opb, m, n, k, alpha, a, b, beta, c)
}

/// The same product by matrixmultiply, split over rayon by blocks of rows of `C`.
///
/// With `Op::N`, `a` holds `m×k`; with `Op::T` it holds `k×m` (likewise `b`: `k×n` or `n×k`).
/// `beta = 0` overwrites `C` (whatever it held, NaN included); `beta = 1` accumulates into it.
///
/// # Panics
/// If a slice is shorter than its shape needs.
#[allow(clippy::too_many_arguments)]
pub fn gemm_matrixmultiply<T: Float>(
    opa: Op, opb: Op, m: usize, n: usize, k: usize, alpha: T, a: &[T], b: &[T], beta: T,
    c: &mut [T],
) {
    assert!(a.len() >= m * k, "gemm: A has {} < {}x{}", a.len(), m, k);
    assert!(b.len() >= k * n, "gemm: B has {} < {}x{}", b.len(), k, n);
    assert!(c.len() >= m * n, "gemm: C has {} < {}x{}", c.len(), m, n);
    if m == 0 || n == 0 {
        return;
    }
    // Strides of op(A) (m×k) and op(B) (k×n) as stored.
    let (rsa, csa) = match opa {
        Op::N => (k as isize, 1),
        Op::T => (1, m as isize),
    };
    let (rsb, csb) = match opb {
        Op::N => (n as isize, 1),
        Op::T => (1, k as isize),
    };
    let rows = rows_per_task(m, k, n);
    let c = &mut c[..m * n];
    c.par_chunks_mut(rows * n)
        .enumerate()
        .for_each(|(task, c_block)| {
            let i0 = task * rows;
            let mb = c_block.len() / n;
            // First element of row i0 of op(A).
            let a_off = i0 as isize * rsa;
            // SAFETY: op(A) rows i0..i0+mb and all k columns lie inside `a` (checked above: the
            // largest index reached is (m-1)·rsa + (k-1)·csa < m·k); B is read whole; `c_block` is
            // exactly mb×n and is not shared with any other task.
            unsafe {
                T::gemm_raw(
                    mb,
                    k,
                    n,
                    alpha,
                    a.as_ptr().offset(a_off),
                    rsa,
                    csa,
                    b.as_ptr(),
                    rsb,
                    csb,
                    beta,
                    c_block.as_mut_ptr(),
                    n as isize,
                    1,
                )
            }
        });
}

/// The reference product: three plain loops, the oracle for [`gemm`] and every faster kernel.
#[allow(clippy::too_many_arguments)]
pub fn gemm_reference<T: Float>(
    opa: Op, opb: Op, m: usize, n: usize, k: usize, alpha: T, a: &[T], b: &[T], beta: T,
    c: &mut [T],
) {
    for i in 0..m {
        for j in 0..n {
            let mut s = T::zero();
            for p in 0..k {
                let av = match opa {
                    Op::N => a[i * k + p],
                    Op::T => a[p * m + i],
                };
                let bv = match opb {
                    Op::N => b[p * n + j],
                    Op::T => b[j * k + p],
                };
                s += av * bv;
            }
            let old = if beta == T::zero() {
                T::zero()
            } else {
                beta * c[i * n + j]
            };
            c[i * n + j] = alpha * s + old;
        }
    }
}

/// The same product by faer (its own packed, AVX-512-capable kernels, parallel over rayon's
/// threads). `beta` must be 0 or 1.
#[allow(clippy::too_many_arguments)]
pub fn gemm_faer<T: Float>(
    opa: Op, opb: Op, m: usize, n: usize, k: usize, alpha: T, a: &[T], b: &[T], beta: T,
    c: &mut [T],
) {
    assert!(
        beta == T::zero() || beta == T::one(),
        "gemm_faer: beta must be 0 or 1"
    );
    assert!(
        a.len() >= m * k && b.len() >= k * n && c.len() >= m * n,
        "gemm_faer: sizes"
    );
    T::gemm_faer(
        opa == Op::T,
        opb == Op::T,
        m,
        n,
        k,
        alpha,
        a,
        b,
        beta == T::one(),
        c,
    );
}
