//! x86-64 code that is not AVX-512: the AVX2 and FMA family, for CPUs without AVX-512 (or with it
//! switched off by `INVADERS_NO_AVX512`). Each kernel is checked against its portable twin, with
//! which it agrees to the bit (`tests/kernels.rs`, and the Winograd module's tests).

pub(crate) mod acting_avx2;
pub mod gather_avx2;
pub(crate) mod scatter_avx2;
pub(crate) mod winograd_avx2;
