//! The dueling head (Wang et al. 2016): Q-values from a state value and action advantages.

use super::Layer;
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
pub struct Dueling<T> {
    name: String,
    actions: usize,
    y: Tensor<T>,
    dx: Tensor<T>,
}

impl<T: Float> Dueling<T> {
    /// A head for `actions` actions; its input has `1 + actions` columns.
    pub fn new(name: &str, actions: usize) -> Self {
        assert!(actions > 0, "a dueling head needs at least one action");
        Dueling {
            name: name.to_string(),
            actions,
            y: Tensor::empty(),
            dx: Tensor::empty(),
        }
    }
}

impl<T: Float> Layer<T> for Dueling<T> {
    fn name(&self) -> &str {
        &self.name
    }

    fn output_shape(&self) -> Vec<usize> {
        vec![self.actions]
    }

    /// `Q_a = V + A_a − mean_b A_b`, row by row.
    fn forward(&mut self, x: &Tensor<T>) {
        let a = self.actions;
        let n = x.len() / (a + 1);
        assert_eq!(
            x.len(),
            n * (a + 1),
            "dueling head: input is not [N, 1 + A]"
        );
        self.y.set_shape(&[n, a]);
        let inv = T::one() / T::of(a as f64);
        for (y, x) in self
            .y
            .data_mut()
            .chunks_exact_mut(a)
            .zip(x.data().chunks_exact(a + 1))
        {
            let (v, adv) = (x[0], &x[1..]);
            let mean = adv.iter().fold(T::zero(), |s, &v| s + v) * inv;
            for (y, &adv) in y.iter_mut().zip(adv) {
                *y = v + adv - mean;
            }
        }
    }

    fn output(&self) -> &Tensor<T> {
        &self.y
    }

    /// `dV = Σ_a dY_a`, `dA_b = dY_b − (1/A)·Σ_a dY_a`.
    fn backward(&mut self, _x: &Tensor<T>, dy: &Tensor<T>, need_dx: bool) {
        if !need_dx {
            return;
        }
        let a = self.actions;
        let n = dy.len() / a;
        self.dx.set_shape(&[n, a + 1]);
        let inv = T::one() / T::of(a as f64);
        for (dx, dy) in self
            .dx
            .data_mut()
            .chunks_exact_mut(a + 1)
            .zip(dy.data().chunks_exact(a))
        {
            let sum = dy.iter().fold(T::zero(), |s, &v| s + v);
            dx[0] = sum;
            for (dx, &dy) in dx[1..].iter_mut().zip(dy) {
                *dx = dy - sum * inv;
            }
        }
    }

    fn input_grad(&self) -> &Tensor<T> {
        &self.dx
    }
}
