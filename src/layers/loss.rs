//! Regression losses on a vector of predictions, each returning the loss and its gradient.
//!
//! Both are means over the `n` elements, as Keras reduces them, so the gradient carries `1/n`.

use crate::tensor::Float;
use serde::{Deserialize, Serialize};

/// Which loss a DQN regresses its Q-values with.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LossKind {
    /// Mean squared error (the article's).
    Mse,
    /// Huber with δ = 1 (the Nature DQN's "error clipping").
    Huber,
}

impl LossKind {
    /// The loss of `pred` against `target`; writes `∂loss/∂pred` into `grad`.
    pub fn eval<T: Float>(self, pred: &[T], target: &[T], grad: &mut [T]) -> T {
        match self {
            LossKind::Mse => mse(pred, target, grad),
            LossKind::Huber => huber(pred, target, T::one(), grad),
        }
    }
}

/// `L = (1/n) Σ (p − t)²`; `∂L/∂p = 2(p − t)/n`.
pub fn mse<T: Float>(pred: &[T], target: &[T], grad: &mut [T]) -> T {
    assert!(
        pred.len() == target.len() && pred.len() == grad.len(),
        "mse: lengths differ"
    );
    let n = T::of(pred.len() as f64);
    let mut sum = T::zero();
    for ((g, &p), &t) in grad.iter_mut().zip(pred).zip(target) {
        let d = p - t;
        sum += d * d;
        *g = (d + d) / n;
    }
    sum / n
}

/// `L = (1/n) Σ h(p − t)` with `h(d) = d²/2` for `|d| ≤ δ` and `δ(|d| − δ/2)` beyond: quadratic
/// near the target, linear far from it, so a large error gives a gradient of at most `δ/n`.
/// `∂L/∂p = clamp(p − t, −δ, δ)/n`.
pub fn huber<T: Float>(pred: &[T], target: &[T], delta: T, grad: &mut [T]) -> T {
    assert!(
        pred.len() == target.len() && pred.len() == grad.len(),
        "huber: lengths differ"
    );
    let n = T::of(pred.len() as f64);
    let half = T::of(0.5);
    let mut sum = T::zero();
    for ((g, &p), &t) in grad.iter_mut().zip(pred).zip(target) {
        let d = p - t;
        if d.abs() <= delta {
            sum += half * d * d;
            *g = d / n;
        } else {
            sum += delta * (d.abs() - half * delta);
            *g = delta * d.signum() / n;
        }
    }
    sum / n
}
