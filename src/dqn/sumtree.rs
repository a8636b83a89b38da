//! A sum tree: sampling in proportion to priorities, for prioritized replay (Schaul et al. 2016).
//!
//! The leaves hold one non-negative priority `p_i` per replay slot; every inner node holds the
//! sum of its two children, so the root holds `Σ p_i`. Drawing `u` uniformly in `[0, Σ p_i)` and
//! walking down (left if `u` is below the left child's sum, else subtract it and go right) lands
//! on leaf `i` with probability `p_i / Σ p`. Setting a leaf recomputes the sums on its path to the
//! root. Both take `O(log n)`.
//!
//! Layout: `nodes[1]` is the root, node `k` has children `2k` and `2k + 1`, and leaf `i` is node
//! `leaves + i` with `leaves` the next power of two at or above `n`. Sums are `f64` and every
//! inner node is recomputed from its children (never updated by differences), so no rounding
//! drift builds up over millions of updates and the tree is a pure function of its leaves.

/// Priorities over `n` slots, sampled in proportion to their values.
#[derive(Clone, Debug)]
pub struct SumTree {
    n: usize,
    leaves: usize,
    nodes: Vec<f64>,
}

impl SumTree {
    /// `n` slots, all of priority 0.
    pub fn new(n: usize) -> Self {
        assert!(n >= 1, "a sum tree needs at least one slot");
        let leaves = n.next_power_of_two();
        SumTree {
            n,
            leaves,
            nodes: vec![0.0; 2 * leaves],
        }
    }

    /// The number of slots.
    pub fn len(&self) -> usize {
        self.n
    }

    /// Whether the tree has no slots (never: [`SumTree::new`] needs one).
    pub fn is_empty(&self) -> bool {
        self.n == 0
    }

    /// The priority of slot `i`.
    pub fn get(&self, i: usize) -> f64 {
        assert!(i < self.n, "slot {i} out of {}", self.n);
        self.nodes[self.leaves + i]
    }

    /// Sets the priority of slot `i` (finite and `>= 0`) and the sums above it.
    pub fn set(&mut self, i: usize, p: f64) {
        assert!(i < self.n, "slot {i} out of {}", self.n);
        assert!(
            p >= 0.0 && p.is_finite(),
            "priority must be finite and >= 0, got {p}"
        );
        let mut k = self.leaves + i;
        self.nodes[k] = p;
        while k > 1 {
            k /= 2;
            self.nodes[k] = self.nodes[2 * k] + self.nodes[2 * k + 1];
        }
    }

    /// `Σ p_i`.
    pub fn total(&self) -> f64 {
        self.nodes[1]
    }

    /// The slot where the prefix sum passes `u`: the `i` with `Σ_{j<i} p_j <= u < Σ_{j<=i} p_j`,
    /// for `u` in `[0, total)`. Rounding can leave `u` at or past the last positive leaf; the
    /// walk then ends on the rightmost slot whose priority is positive. `None` if all are 0.
    pub fn find(&self, mut u: f64) -> Option<usize> {
        if self.total() <= 0.0 {
            return None;
        }
        let mut k = 1;
        while k < self.leaves {
            let left = self.nodes[2 * k];
            if u < left || self.nodes[2 * k + 1] <= 0.0 {
                // Go left when `u` falls there, or when the right subtree is empty (rounding).
                if u >= left {
                    u = left; // clamp: only reachable through rounding
                }
                k *= 2;
            } else {
                u -= left;
                k = 2 * k + 1;
            }
        }
        let i = k - self.leaves;
        debug_assert!(self.nodes[k] > 0.0, "the walk ends on a positive leaf");
        Some(i)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn finds_the_slot_of_each_prefix_sum() {
        let mut t = SumTree::new(5); // 8 leaves, 3 of them padding
        for (i, p) in [1.0, 0.0, 2.0, 0.5, 0.0].into_iter().enumerate() {
            t.set(i, p);
        }
        assert_eq!(t.total(), 3.5);
        let cases = [
            (0.0, 0),
            (0.999, 0),
            (1.0, 2),
            (2.999, 2),
            (3.0, 3),
            (3.49, 3),
        ];
        for (u, want) in cases {
            assert_eq!(t.find(u), Some(want), "u = {u}");
        }
        // Past the total (rounding): the last positive slot, never a zero one.
        assert_eq!(t.find(3.5), Some(3));
        assert_eq!(t.find(10.0), Some(3));
        t.set(0, 0.0);
        t.set(2, 0.0);
        t.set(3, 0.0);
        assert_eq!(t.find(0.0), None);
    }
}
