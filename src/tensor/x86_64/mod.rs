//! x86-64 code that is not AVX-512: the AVX2 and FMA family, for CPUs without AVX-512 (or with it
//! switched off by `INVADERS_NO_AVX512`). Each kernel is checked against its portable twin, with
//! which it agrees to the bit (`tests/kernels.rs`).

pub mod gather_avx2;
