//! The scatter GEMM for AVX2 and FMA: the portable loop ([`scatter_gemm_portable`]) compiled
//! for AVX2 and FMA. Its inner loop, `row[j] = fma(a, b[j], row[j])`, then becomes 256-bit
//! fused multiply-adds instead of a call to `fmaf` per value (about 560 ms to 17 ms for a 3×3
//! layer's input gradient over a padded copy, 48 images of 11×10×64, on Zen 3). A fused
//! multiply-add rounds once either way, so the bits are the portable loop's.

use crate::tensor::gather::{scatter_gemm_portable, ScatterGemm};

/// [`scatter_gemm_portable`] for AVX2 and FMA.
///
/// # Safety
/// The CPU runs AVX2 and FMA.
#[target_feature(enable = "avx2,fma")]
pub(crate) unsafe fn scatter_gemm(g: ScatterGemm<'_, f32>) {
    scatter_gemm_portable(g)
}
