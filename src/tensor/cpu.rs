//! What this CPU runs, checked once: the one feature test every kernel family honours, and the
//! one wrapper that compiles a loop for AVX-512.
//!
//! The hand-written kernels (the gather and scatter GEMMs, the Winograd transforms, the sparse
//! and background products, the transposes) need AVX-512F and FMA. [`avx512`] says whether they
//! may run: this CPU has both, and `INVADERS_NO_SIMD` is unset. That variable is the switch back
//! to the portable code on an AVX-512 host (im2col + faer in the layers, the portable loops in
//! the kernels), for A/B timing in one session and for testing the portable path there. It is
//! read once, at the first call, so a process runs one way throughout.
//!
//! The kernels are selected by [`crate::tensor::plan`]; nothing else asks the CPU.

use std::sync::OnceLock;

/// The CPU features the kernels use, as detected once per process.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Features {
    /// AVX-512F and FMA, and `INVADERS_NO_SIMD` unset: the AVX-512 kernels run.
    pub avx512: bool,
}

/// The features of this CPU (detected on the first call, then cached).
pub fn features() -> Features {
    static FEATURES: OnceLock<Features> = OnceLock::new();
    *FEATURES.get_or_init(|| Features {
        avx512: detect_avx512() && std::env::var_os("INVADERS_NO_SIMD").is_none(),
    })
}

#[cfg(target_arch = "x86_64")]
fn detect_avx512() -> bool {
    is_x86_feature_detected!("avx512f") && is_x86_feature_detected!("fma")
}

#[cfg(not(target_arch = "x86_64"))]
fn detect_avx512() -> bool {
    false
}

/// Whether the AVX-512 kernels run (see the module documentation).
#[inline]
pub fn avx512() -> bool {
    features().avx512
}

/// Defines a function whose body is compiled for AVX-512 where [`avx512`] holds, else as built:
/// [`vectorized`] for a loop that must be a function of its own (a closure handed to
/// `vectorized` is not always inlined into it, and then runs 4 lanes wide).
///
/// ```ignore
/// avx512_twin! {
///     /// The largest offset.
///     fn largest(v: &[usize]) -> usize { v.iter().fold(0, |m, &x| m.max(x)) }
/// }
/// ```
macro_rules! avx512_twin {
    (
        $(#[$meta:meta])*
        $vis:vis fn $name:ident $(<$t:ident: $bound:path>)? ($($arg:ident: $ty:ty),* $(,)?)
            $(-> $ret:ty)? $body:block
    ) => {
        $(#[$meta])*
        $vis fn $name $(<$t: $bound>)? ($($arg: $ty),*) $(-> $ret)? {
            #[inline(always)]
            fn body $(<$t: $bound>)? ($($arg: $ty),*) $(-> $ret)? $body
            #[cfg(target_arch = "x86_64")]
            {
                #[target_feature(enable = "avx512f")]
                unsafe fn wide $(<$t: $bound>)? ($($arg: $ty),*) $(-> $ret)? {
                    body($($arg),*)
                }
                if $crate::tensor::cpu::avx512() {
                    // SAFETY: `avx512` checked that this CPU runs AVX-512F.
                    return unsafe { wide($($arg),*) };
                }
            }
            body($($arg),*)
        }
    };
}
pub(crate) use avx512_twin;

/// Runs `f` compiled for AVX-512 where [`avx512`] holds, else as built (baseline x86-64: 4-wide
/// SSE). The one place that enters AVX-512 code from portable code for a plain loop.
///
/// For the element-wise loops between the products (Adam, the ReLU masks, the gradient norm,
/// the offset-table checks): they are written as plain loops, and inlined here LLVM vectorises
/// them 16 lanes wide. Each element gets the same operations in the same order either way (no
/// reassociation, no fused multiply-add), so the result is bit-identical with or without it.
#[inline(always)]
pub fn vectorized<R>(f: impl FnOnce() -> R) -> R {
    #[cfg(target_arch = "x86_64")]
    {
        #[target_feature(enable = "avx512f")]
        unsafe fn wide<R>(f: impl FnOnce() -> R) -> R {
            f()
        }
        if avx512() {
            // SAFETY: `avx512` checked that this CPU runs AVX-512F.
            return unsafe { wide(f) };
        }
    }
    f()
}
