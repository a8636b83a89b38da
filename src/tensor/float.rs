//! The scalar type the library is generic over.
//!
//! Everything numeric is written once for any [`Float`]; training uses `f32`, and the gradient
//! checks run the very same code in `f64`, where central finite differences are accurate to
//! about 1e-9, so a tolerance can be tight enough to catch a single wrong index.

use super::cpu::{took, Family};
use super::gather::{gather_gemm_portable, scatter_gemm_portable, GatherGemm, ScatterGemm};
use std::fmt::{Debug, Display};
use std::iter::Sum;
use std::ops::{AddAssign, MulAssign, SubAssign};

/// A floating-point scalar with a GEMM kernel.
pub trait Float:
    num_traits::Float
    + Default
    + Debug
    + Display
    + Sum
    + AddAssign
    + SubAssign
    + MulAssign
    + Send
    + Sync
    + bytemuck::Pod
    + 'static
{
    /// The safetensors dtype name (`"F32"` or `"F64"`).
    const DTYPE: &'static str;

    /// Converts from `f64` (exact for `f64`, rounded for `f32`).
    fn of(x: f64) -> Self;

    /// Whether the AVX-512 kernels run for this type on this CPU (f32 with AVX-512F and FMA,
    /// [`crate::tensor::cpu::avx512`]). The dense layers take the gather GEMM, and the bf16
    /// products may run, only then.
    fn simd() -> bool {
        false
    }

    /// Whether [`Float::gather_gemm`] runs a SIMD kernel for this type on this CPU: f32 with
    /// AVX-512 ([`Float::simd`]) or with AVX2 and FMA ([`crate::tensor::cpu::avx2`]). The
    /// convolutions take their fast kernels (gather, Winograd, phases, scatter) only then, and
    /// otherwise keep im2col + faer, the generic path the f64 gradient checks exercise.
    fn gather_simd() -> bool {
        false
    }

    /// The gather GEMM of [`crate::tensor::GatherGemm`]: the SIMD kernel where
    /// [`Float::gather_simd`], else the portable loops.
    fn gather_gemm(g: GatherGemm<'_, Self>) {
        took(Family::Gather, false);
        gather_gemm_portable(g)
    }

    /// The scatter GEMM of [`crate::tensor::ScatterGemm`]: the SIMD kernel where
    /// [`Float::gather_simd`] (AVX-512 or AVX2), else the portable loops.
    fn scatter_gemm(g: ScatterGemm<'_, Self>) {
        took(Family::Scatter, false);
        scatter_gemm_portable(g)
    }

    /// `C = alpha·op(A)·op(B) + (accumulate ? C : 0)` by faer, on row-major slices.
    #[allow(clippy::too_many_arguments)]
    fn gemm_faer(
        ta: bool, tb: bool, m: usize, n: usize, k: usize, alpha: Self, a: &[Self], b: &[Self],
        accumulate: bool, c: &mut [Self],
    );

    /// `C = alpha·A·B + beta·C` by matrixmultiply on strided matrices: A is `m x k` with row
    /// stride `rsa` and column stride `csa`, B is `k x n`, C is `m x n`.
    ///
    /// # Safety
    /// Every index `i·rs + j·cs` reached for the given sizes must lie inside the allocation
    /// behind each pointer, and C must not alias A or B. [`crate::tensor::gemm_matrixmultiply`]
    /// checks this.
    #[allow(clippy::too_many_arguments)]
    unsafe fn gemm_raw(
        m: usize, k: usize, n: usize, alpha: Self, a: *const Self, rsa: isize, csa: isize,
        b: *const Self, rsb: isize, csb: isize, beta: Self, c: *mut Self, rsc: isize, csc: isize,
    );
}

/// `C = alpha·op(A)·op(B) + beta·C` by faer on row-major slices (see [`crate::tensor::gemm_faer`]).
macro_rules! faer_gemm_impl {
    ($t:ty) => {
        fn gemm_faer(
            ta: bool, tb: bool, m: usize, n: usize, k: usize, alpha: $t, a: &[$t], b: &[$t],
            accumulate: bool, c: &mut [$t],
        ) {
            use faer::{Accum, MatMut, MatRef, Par};
            let a = if ta {
                MatRef::from_row_major_slice(&a[..m * k], k, m).transpose()
            } else {
                MatRef::from_row_major_slice(&a[..m * k], m, k)
            };
            let b = if tb {
                MatRef::from_row_major_slice(&b[..k * n], n, k).transpose()
            } else {
                MatRef::from_row_major_slice(&b[..k * n], k, n)
            };
            let c = MatMut::from_row_major_slice_mut(&mut c[..m * n], m, n);
            let beta = if accumulate {
                Accum::Add
            } else {
                Accum::Replace
            };
            let par = match rayon::current_num_threads() {
                1 => Par::Seq,
                t => Par::rayon(t),
            };
            faer::linalg::matmul::matmul(c, beta, a, b, alpha, par);
        }
    };
}

impl Float for f32 {
    faer_gemm_impl!(f32);
    const DTYPE: &'static str = "F32";
    fn of(x: f64) -> Self {
        x as f32
    }
    #[cfg(target_arch = "x86_64")]
    fn simd() -> bool {
        super::cpu::avx512()
    }
    #[cfg(target_arch = "x86_64")]
    fn gather_simd() -> bool {
        super::cpu::avx512() || super::cpu::avx2()
    }
    #[cfg(target_arch = "x86_64")]
    fn gather_gemm(g: GatherGemm<'_, f32>) {
        use super::cpu::{path, took_path, Path};
        match took_path(Family::Gather, path()) {
            Path::Avx512 => super::x86_64::gather_avx512::gather_gemm(g),
            Path::Avx2 => super::x86_64::gather_avx2::gather_gemm(g),
            Path::Portable => gather_gemm_portable(g),
            Path::Amx => unreachable!("cpu::path never picks AMX"),
        }
    }
    #[cfg(target_arch = "x86_64")]
    fn scatter_gemm(g: ScatterGemm<'_, f32>) {
        use super::cpu::{path, took_path, Path};
        match took_path(Family::Scatter, path()) {
            Path::Avx512 => super::x86_64::gather_avx512::scatter_gemm(g),
            // SAFETY: `cpu::path` chose AVX2 only where the CPU runs AVX2 and FMA.
            Path::Avx2 => unsafe { super::x86_64::scatter_avx2::scatter_gemm(g) },
            Path::Portable => scatter_gemm_portable(g),
            Path::Amx => unreachable!("cpu::path never picks AMX"),
        }
    }
    unsafe fn gemm_raw(
        m: usize, k: usize, n: usize, alpha: f32, a: *const f32, rsa: isize, csa: isize,
        b: *const f32, rsb: isize, csb: isize, beta: f32, c: *mut f32, rsc: isize, csc: isize,
    ) {
        matrixmultiply::sgemm(m, k, n, alpha, a, rsa, csa, b, rsb, csb, beta, c, rsc, csc)
    }
}

impl Float for f64 {
    faer_gemm_impl!(f64);
    const DTYPE: &'static str = "F64";
    fn of(x: f64) -> Self {
        x
    }
    unsafe fn gemm_raw(
        m: usize, k: usize, n: usize, alpha: f64, a: *const f64, rsa: isize, csa: isize,
        b: *const f64, rsb: isize, csb: isize, beta: f64, c: *mut f64, rsc: isize, csc: isize,
    ) {
        matrixmultiply::dgemm(m, k, n, alpha, a, rsa, csa, b, rsb, csb, beta, c, rsc, csc)
    }
}
