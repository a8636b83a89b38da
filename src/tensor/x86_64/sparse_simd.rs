//! The sparse product's rows ([`SparseConv::run`]) written once for both register widths
//! ([`F32s`]): each output row from the bias, `y_r = b + Σ x·w` over the nonzero inputs of its
//! window, tap by tap and channel by channel, `NV` registers of output channels in
//! accumulators, by fused multiply-adds. Compiled inside AVX-512's `sparse_avx512.rs` (all of
//! `Cout` at once) and AVX2's `acting_avx2.rs` (columns of up to 64 channels).

use super::cast;
use super::simd::F32s;
use crate::tensor::sparse::SparseConv;
use crate::tensor::Float;

/// Output channels `c0 ..+ V::LANES·NV` of every row of the product.
///
/// # Safety
/// `V`'s instruction set (with FMA) available; `T` is `f32`; `c0 + V::LANES·NV ≤ cout`, and
/// `g`'s weights, bias and output hold `cout` channels.
#[inline(always)]
pub(super) unsafe fn columns<V: F32s, T: Float, const NV: usize>(
    g: &mut SparseConv<'_, T>, cin: usize, cout: usize, c0: usize,
) {
    let (w, bias) = (cast::<T>(g.w), cast::<T>(g.bias));
    let y: &mut [f32] = bytemuck::cast_slice_mut(&mut *g.y);
    let lanes = V::LANES;
    for (&p, &r) in g.windows.iter().zip(g.rows) {
        let mut acc = [V::zero(); NV];
        for (j, a) in acc.iter_mut().enumerate() {
            *a = V::load(bias[c0 + lanes * j..][..lanes].as_ptr());
        }
        for (t, &o) in g.taps.iter().enumerate() {
            let wt = &w[t * cin * cout..][..cin * cout];
            let (index, value) = g.x.pixel(p + o);
            for (&ci, &v) in index.iter().zip(cast::<T>(value)) {
                let row = &wt[ci as usize * cout + c0..][..lanes * NV];
                let xv = V::splat(v);
                for (j, a) in acc.iter_mut().enumerate() {
                    *a = V::fmadd(xv, V::load(row[lanes * j..].as_ptr()), *a);
                }
            }
        }
        let out = &mut y[r + c0..][..lanes * NV];
        for (j, &a) in acc.iter().enumerate() {
            let a = if g.relu { V::max(a, V::zero()) } else { a };
            V::store(out[lanes * j..].as_mut_ptr(), a);
        }
    }
}
