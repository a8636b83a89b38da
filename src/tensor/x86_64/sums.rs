//! A gather tile's sums in registers, for all three gather kernels (AVX2's `gather_avx2.rs`,
//! AVX-512's `gather_avx512.rs` and AVX512-BF16's `gather_bf16_avx512.rs`): how an `MR × NV`
//! block of accumulators starts ([`Start`], [`start`]) and how it leaves its sums in `C`
//! ([`End`], [`end`]), written once over the register ([`F32s`]); each kernel's own loop of
//! products runs between the two.

use super::simd::F32s;
use crate::tensor::gather::Init;

/// How a tile starts its sums.
#[derive(Clone, Copy)]
pub(super) enum Start {
    /// From zero.
    Zero,
    /// From what `C` holds (a block after the first, or a product added to `C`).
    Load,
    /// From the bias row at this pointer (the panel's columns).
    Bias(*const f32),
}

impl Start {
    /// How a product's first block starts, from its [`Init`].
    pub(super) fn of(init: &Init<'_, f32>) -> Start {
        match init {
            Init::Zero => Start::Zero,
            Init::Accumulate => Start::Load,
            Init::Bias(bias) => Start::Bias(bias.as_ptr()),
        }
    }

    /// How block `blk` of the reduction starts: as the product (`self`) for the first, from
    /// `C` for the others.
    pub(super) fn block(self, blk: usize) -> Start {
        if blk == 0 {
            self
        } else {
            Start::Load
        }
    }

    /// This start for the panel whose first column is `j0` (a bias moves with the columns).
    ///
    /// # Safety
    /// A bias must hold column `j0`.
    pub(super) unsafe fn panel(self, j0: usize) -> Start {
        match self {
            Start::Bias(bias) => Start::Bias(bias.add(j0)),
            s => s,
        }
    }
}

/// How a tile leaves its sums in `C`.
#[derive(Clone, Copy)]
pub(super) enum End {
    Store,
    /// `max(sum, 0)`: the last block of a GEMM with a fused ReLU.
    Relu,
    /// Added to what is there (a scatter).
    Add,
}

impl End {
    /// [`End::Relu`] where `relu`, else [`End::Store`].
    pub(super) fn relu(relu: bool) -> End {
        if relu {
            End::Relu
        } else {
            End::Store
        }
    }

    /// How block `blk` of `blocks` leaves `C` in a GEMM with a fused ReLU where `relu`: the
    /// last block takes the ReLU, the others store the partial sums.
    pub(super) fn last(relu: bool, blk: usize, blocks: usize) -> End {
        End::relu(relu && blk + 1 == blocks)
    }
}

/// The `MR × NV` accumulators of a tile whose rows of `C` are `c + crow[r]`, `NV` registers
/// a row under the lane masks `masks`, as `start` says.
///
/// # Safety
/// `V`'s instruction set available; for `Load`, the masked lanes of each row readable; for
/// `Bias`, the masked lanes of the bias readable.
#[inline(always)]
pub(super) unsafe fn start<V: F32s, const MR: usize, const NV: usize>(
    c: *const f32, crow: &[usize], masks: [V::Mask; NV], start: Start,
) -> [[V; NV]; MR] {
    let mut acc = [[V::zero(); NV]; MR];
    for r in 0..MR {
        for v in 0..NV {
            acc[r][v] = match start {
                Start::Zero => V::zero(),
                Start::Load => V::load_masked(c.add(crow[r] + V::LANES * v), masks[v]),
                Start::Bias(bias) => V::load_masked(bias.add(V::LANES * v), masks[v]),
            };
        }
    }
    acc
}

/// Where each of a tile's `MR` rows of `A` starts: `a + p[r]`.
///
/// # Safety
/// Every `a + p[r]` inside `A`.
#[inline(always)]
pub(super) unsafe fn rows<T, const MR: usize>(a: *const T, p: &[usize]) -> [*const T; MR] {
    let mut rows = [a; MR];
    for (row, &pr) in rows.iter_mut().zip(p) {
        *row = a.add(pr);
    }
    rows
}

/// Leaves the sums `acc` in the rows `c + crow[r]` of `C` as `end` says, under the lane
/// masks. With `Add`, row by row (load, add, store), so rows whose destinations overlap (a
/// scatter onto overlapping windows) each see the previous row's sum.
///
/// # Safety
/// `V`'s instruction set available; the masked lanes of each row readable and writable.
#[inline(always)]
pub(super) unsafe fn end<V: F32s, const MR: usize, const NV: usize>(
    acc: &[[V; NV]; MR], c: *mut f32, crow: &[usize], masks: [V::Mask; NV], end: End,
) {
    for r in 0..MR {
        for v in 0..NV {
            let dst = c.add(crow[r] + V::LANES * v);
            let val = match end {
                End::Store => acc[r][v],
                End::Relu => V::max(acc[r][v], V::zero()),
                End::Add => V::add(V::load_masked(dst, masks[v]), acc[r][v]),
            };
            V::store_masked(dst, masks[v], val);
        }
    }
}
