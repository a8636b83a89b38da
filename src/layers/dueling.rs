//! The dueling head (Wang et al. 2016): Q-values from a state value and action advantages.

use super::{Core, Layer};
use crate::tensor::{Float, Tensor};

/// Combines a state value `V(s)` and advantages `A(s, a)` into Q-values, mean-subtracted:
///
/// ```text
/// x  [N, 1 + A]   column 0 is V(s), columns 1..=A are A(s, a)  (the last dense layer's two streams)
/// y  [N, A]       Q(s, a) = V(s) + A(s, a) − (1/A)·Σ_b A(s, b)
/// ```
///
/// The streams are the rows of the dense layer before it (one row for the value, `A` for the
/// advantages), which share the hidden layer below: Wang et al.'s two fully connected streams, split
/// at the last linear layer. Subtracting the mean makes the split identifiable (adding a constant to
/// every advantage and removing it from the value would otherwise give the same Q), and it lets the
/// value learn from every action's update: each sample's TD error moves `V(s)` whichever action it
/// was taken with.
///
/// Backward: `∂Q_a/∂V = 1` and `∂Q_a/∂A_b = δ_ab − 1/A`, so with `S = Σ_a dY_a`
/// ```text
/// dV   = S
/// dA_b = dY_b − S/A
/// ```
/// No parameters.
///
/// With `K` atoms per action ([`Dueling::with_atoms`]: a quantile head's `K` quantiles) the same
/// is done atom by atom: `x [N, (1 + A)·K]` holds the value's `K` atoms, then each action's,
/// and `y [N, A·K]` holds `Q_{a,k} = V_k + A_{a,k} − (1/A)·Σ_b A_{b,k}`.
pub struct Dueling<T> {
    /// The name, output `y` and input gradient `dX` ([`Core`]).
    core: Core<T>,
    actions: usize,
    atoms: usize,
}

impl<T: Float> Dueling<T> {
    /// A head for `actions` actions; its input has `1 + actions` columns.
    pub fn new(name: &str, actions: usize) -> Self {
        Dueling::with_atoms(name, actions, 1)
    }

    /// A head for `actions` actions of `atoms` values each; its input has
    /// `(1 + actions)·atoms` columns.
    pub fn with_atoms(name: &str, actions: usize, atoms: usize) -> Self {
        assert!(actions > 0, "a dueling head needs at least one action");
        assert!(atoms > 0, "a dueling head needs at least one atom");
        Dueling {
            core: Core::new(name),
            actions,
            atoms,
        }
    }
}

impl<T: Float> Layer<T> for Dueling<T> {
    fn core(&self) -> &Core<T> {
        &self.core
    }

    fn output_shape(&self) -> Vec<usize> {
        vec![self.actions * self.atoms]
    }

    /// `Q_{a,k} = V_k + A_{a,k} − mean_b A_{b,k}`, row by row.
    fn forward(&mut self, x: &Tensor<T>) {
        let (a, k) = (self.actions, self.atoms);
        let n = x.len() / ((a + 1) * k);
        assert_eq!(
            x.len(),
            n * (a + 1) * k,
            "dueling head: input is not [N, (1 + A)·K]"
        );
        self.core.y.set_shape(&[n, a * k]);
        let inv = T::one() / T::of(a as f64);
        for (y, x) in self
            .core
            .y
            .data_mut()
            .chunks_exact_mut(a * k)
            .zip(x.data().chunks_exact((a + 1) * k))
        {
            let (v, adv) = x.split_at(k);
            for j in 0..k {
                let mean = (0..a).fold(T::zero(), |s, b| s + adv[b * k + j]) * inv;
                for b in 0..a {
                    y[b * k + j] = v[j] + adv[b * k + j] - mean;
                }
            }
        }
    }

    /// `dV_k = Σ_a dY_{a,k}`, `dA_{b,k} = dY_{b,k} − (1/A)·Σ_a dY_{a,k}`.
    fn backward(&mut self, _x: &Tensor<T>, dy: &Tensor<T>, need_dx: bool) {
        if !need_dx {
            return;
        }
        let (a, k) = (self.actions, self.atoms);
        let n = dy.len() / (a * k);
        self.core.dx.set_shape(&[n, (a + 1) * k]);
        let inv = T::one() / T::of(a as f64);
        for (dx, dy) in self
            .core
            .dx
            .data_mut()
            .chunks_exact_mut((a + 1) * k)
            .zip(dy.data().chunks_exact(a * k))
        {
            let (dv, da) = dx.split_at_mut(k);
            for j in 0..k {
                let sum = (0..a).fold(T::zero(), |s, b| s + dy[b * k + j]);
                dv[j] = sum;
                for b in 0..a {
                    da[b * k + j] = dy[b * k + j] - sum * inv;
                }
            }
        }
    }
}
