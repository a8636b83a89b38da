//! Sums over long slices in one fixed order that vectorises.
//!
//! One running sum `s += x_i` is a chain of dependent additions, and reassociating it would make
//! the bits depend on the vector width. Here lane `l` of [`LANES`] running sums takes elements
//! `l, l + LANES, l + 2·LANES, …`, and [`Lanes::total`] adds the lanes pairwise (`LANES/2` sums
//! of pairs, then `LANES/4`, … down to one): the same order on every machine and thread count,
//! and sixteen independent chains a compiler maps onto vector registers.

use crate::tensor::Float;

/// Running sums per lane.
pub const LANES: usize = 16;

/// [`LANES`] running sums; see the module documentation.
#[derive(Clone, Copy, Debug)]
pub struct Lanes<T>([T; LANES]);

impl<T: Float> Default for Lanes<T> {
    fn default() -> Self {
        Lanes([T::zero(); LANES])
    }
}

impl<T: Float> Lanes<T> {
    /// Adds `v_i` to lane `i mod LANES`, for each `i`.
    #[inline(always)]
    pub fn add(&mut self, v: &[T]) {
        let mut rows = v.chunks_exact(LANES);
        for row in &mut rows {
            for (s, &x) in self.0.iter_mut().zip(row) {
                *s += x;
            }
        }
        for (s, &x) in self.0.iter_mut().zip(rows.remainder()) {
            *s += x;
        }
    }

    /// Adds `a_i·b_i` to lane `i mod LANES`, for each `i` (`a` and `b` of one length).
    #[inline(always)]
    pub fn add_products(&mut self, a: &[T], b: &[T]) {
        debug_assert_eq!(a.len(), b.len());
        let (mut ra, mut rb) = (a.chunks_exact(LANES), b.chunks_exact(LANES));
        for (ra, rb) in (&mut ra).zip(&mut rb) {
            for ((s, &x), &y) in self.0.iter_mut().zip(ra).zip(rb) {
                *s += x * y;
            }
        }
        for ((s, &x), &y) in self.0.iter_mut().zip(ra.remainder()).zip(rb.remainder()) {
            *s += x * y;
        }
    }

    /// The lanes added pairwise.
    #[inline(always)]
    pub fn total(self) -> T {
        let mut lanes = self.0;
        let mut width = LANES;
        while width > 1 {
            width /= 2;
            for i in 0..width {
                let upper = lanes[i + width];
                lanes[i] += upper;
            }
        }
        lanes[0]
    }
}

/// `Σ_i v_i` in lanes.
#[inline(always)]
pub fn sum<T: Float>(v: &[T]) -> T {
    let mut l = Lanes::default();
    l.add(v);
    l.total()
}

/// `Σ_i a_i·b_i` in lanes.
#[inline(always)]
pub fn dot<T: Float>(a: &[T], b: &[T]) -> T {
    let mut l = Lanes::default();
    l.add_products(a, b);
    l.total()
}
