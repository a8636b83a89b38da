//! The f32 register the kernels written once for both widths are generic over ([`F32s`]):
//! AVX2's `__m256` (8 lanes) and AVX-512's `__m512` (16 lanes). Each method is one intrinsic
//! marked `#[inline(always)]`: a generic body called from a `#[target_feature]` entry point (one
//! per instruction set, in the family's `*_avx2.rs` and `*_avx512.rs`) is inlined into it whole,
//! and the intrinsics with it, so the entry point compiles to the same instructions as a body
//! written for its width. A generic body calls the methods in plain loops, never inside a
//! closure (`array::from_fn`, `map_or`): a closure is not compiled for the entry point's
//! instruction set, and where it is not inlined its intrinsics become calls.

use std::arch::x86_64::*;

/// A register of f32 lanes: the operations the width-generic kernels use.
///
/// # Safety
/// Every method is an intrinsic of its instruction set: call them only where the CPU runs it
/// (from inside a `#[target_feature]` function enabling it, so that they inline).
pub(crate) trait F32s: Copy {
    /// Lanes per register.
    const LANES: usize;
    /// A lane mask (the gather kernels' panel tails): AVX2's `__m256i` of 0 or −1 lanes,
    /// AVX-512's `u16` of bits.
    type Mask: Copy;
    /// All lanes zero.
    unsafe fn zero() -> Self;
    /// `LANES` values from `p` (unaligned).
    unsafe fn load(p: *const f32) -> Self;
    /// The lanes to `p` (unaligned).
    unsafe fn store(p: *mut f32, v: Self);
    /// The lanes of mask `m` from `p`, zero elsewhere.
    unsafe fn load_masked(p: *const f32, m: Self::Mask) -> Self;
    /// The lanes of mask `m` of `v` to `p`, the others left.
    unsafe fn store_masked(p: *mut f32, m: Self::Mask, v: Self);
    /// `a + b`, lane by lane.
    unsafe fn add(a: Self, b: Self) -> Self;
    /// `a − b`, lane by lane.
    unsafe fn sub(a: Self, b: Self) -> Self;
    /// `max(a, b)`, lane by lane.
    unsafe fn max(a: Self, b: Self) -> Self;
    /// `x` in every lane.
    unsafe fn splat(x: f32) -> Self;
    /// `a·b + c`, lane by lane, rounded once.
    unsafe fn fmadd(a: Self, b: Self, c: Self) -> Self;
}

/// Stamps [`F32s`] for one register type from its intrinsics (`$ld_m`, `$st_m`: the masked
/// load and store, written out over the trait's arguments).
macro_rules! f32s {
    ($v:ty, $lanes:expr, $mask:ty, $zero:ident, $load:ident, $store:ident,
     |$lp:ident, $lm:ident| $ld_m:expr, |$sp:ident, $sm:ident, $sv:ident| $st_m:expr,
     $add:ident, $sub:ident, $max:ident, $splat:ident, $fmadd:ident) => {
        impl F32s for $v {
            const LANES: usize = $lanes;
            type Mask = $mask;
            #[inline(always)]
            unsafe fn zero() -> Self {
                $zero()
            }
            #[inline(always)]
            unsafe fn load(p: *const f32) -> Self {
                $load(p)
            }
            #[inline(always)]
            unsafe fn store(p: *mut f32, v: Self) {
                $store(p, v)
            }
            #[inline(always)]
            unsafe fn load_masked($lp: *const f32, $lm: $mask) -> Self {
                $ld_m
            }
            #[inline(always)]
            unsafe fn store_masked($sp: *mut f32, $sm: $mask, $sv: Self) {
                $st_m
            }
            #[inline(always)]
            unsafe fn add(a: Self, b: Self) -> Self {
                $add(a, b)
            }
            #[inline(always)]
            unsafe fn sub(a: Self, b: Self) -> Self {
                $sub(a, b)
            }
            #[inline(always)]
            unsafe fn max(a: Self, b: Self) -> Self {
                $max(a, b)
            }
            #[inline(always)]
            unsafe fn splat(x: f32) -> Self {
                $splat(x)
            }
            #[inline(always)]
            unsafe fn fmadd(a: Self, b: Self, c: Self) -> Self {
                $fmadd(a, b, c)
            }
        }
    };
}

f32s! { __m256, 8, __m256i, _mm256_setzero_ps, _mm256_loadu_ps, _mm256_storeu_ps,
|p, m| _mm256_maskload_ps(p, m), |p, m, v| _mm256_maskstore_ps(p, m, v),
_mm256_add_ps, _mm256_sub_ps, _mm256_max_ps, _mm256_set1_ps, _mm256_fmadd_ps }
f32s! { __m512, 16, u16, _mm512_setzero_ps, _mm512_loadu_ps, _mm512_storeu_ps,
|p, m| _mm512_maskz_loadu_ps(m, p), |p, m, v| _mm512_mask_storeu_ps(p, m, v),
_mm512_add_ps, _mm512_sub_ps, _mm512_max_ps, _mm512_set1_ps, _mm512_fmadd_ps }
