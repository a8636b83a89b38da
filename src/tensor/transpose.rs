//! Matrix transpose: `dst[c, r] = src[r, c]` for a row-major `src` of `rows × cols`.
//!
//! dense1's input gradient is computed as `dXᵀ` (7040 × 48, so that its 3.6 MB of weights are
//! read in place) and turned into `dX` by this: a third of a million values per train step.
//! The portable loop goes in blocks of 64 source rows (64 × `cols` values, in L1 for dense1),
//! each destination row taking its 64 values from the block, one at a time; it took 0.6 ms of a
//! 1-thread train step. On AVX-512, 16 × 16 blocks are transposed in registers, 16 loads, 64
//! shuffles and 16 stores each. (Gathering each 16 values with `vgatherdps` measured slower than
//! the plain loop on this machine.)

use super::cpu::{took, Family};
use super::Float;

/// Writes `src` (`rows × cols`, row-major) transposed into `dst` (`cols × rows`).
///
/// # Panics
/// If the slices' lengths are not `rows · cols`.
pub fn transpose<T: Float>(src: &[T], rows: usize, cols: usize, dst: &mut [T]) {
    assert_eq!(src.len(), rows * cols, "transpose: source size");
    assert_eq!(dst.len(), rows * cols, "transpose: destination size");
    if rows == 0 || cols == 0 {
        return;
    }
    let fast = took(Family::Transpose, T::simd());
    #[cfg(target_arch = "x86_64")]
    if fast {
        // SAFETY: `simd` holds only where the CPU runs AVX-512F, and `T` is f32 there; every
        // load and store goes through a bounds-checked 16-value slice.
        return unsafe {
            avx512::transpose(
                bytemuck::cast_slice(src),
                rows,
                cols,
                bytemuck::cast_slice_mut(dst),
            )
        };
    }
    for (b, block) in src.chunks(64 * cols).enumerate() {
        let r0 = 64 * b;
        for (c, row) in dst.chunks_exact_mut(rows).enumerate() {
            let column = block.iter().skip(c).step_by(cols);
            for (v, &s) in row[r0..].iter_mut().zip(column) {
                *v = s;
            }
        }
    }
}

#[cfg(target_arch = "x86_64")]
use super::x86_64::transpose_avx512 as avx512;
