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

/// The quantile Huber loss of QR-DQN (Dabney et al. 2018) with κ = 1, for `B` samples of `N`
/// predicted quantiles `θ` against `N` target samples `T` each (both `[B, N]`, row-major):
///
/// ```text
/// u_ij = T_j − θ_i                       (each target sample against each predicted quantile)
/// ρ_ij = |τ_i − 1{u_ij < 0}| · h(u_ij)   (h: Huber with δ = 1, as in `huber`)
/// L    = (1/B) Σ_b Σ_i (1/N) Σ_j ρ_ij
/// ∂L/∂θ_i = −(1/B)(1/N) Σ_j |τ_i − 1{u_ij < 0}| · clamp(u_ij, −1, 1)
/// ```
///
/// Minimising it over `θ_i` moves `θ_i` to the `τ_i`-quantile of the targets: below a target
/// sample the pull is weighted `τ_i`, above it `1 − τ_i`, with the midpoints
/// `τ_i = (2i + 1)/(2N)`, `i = 0..N`, the probability levels the head's outputs estimate. Writes
/// `∂L/∂θ` into `grad` and each sample's share of `L` (before the `1/B`) into `per_sample`.
pub fn quantile_huber<T: Float>(
    pred: &[T], target: &[T], n: usize, grad: &mut [T], per_sample: &mut [T],
) -> T {
    assert!(
        n > 0 && pred.len() == target.len() && pred.len() == grad.len(),
        "quantile_huber: lengths differ"
    );
    let mid = |_: usize, i: usize| T::of((2 * i + 1) as f64 / (2 * n) as f64);
    quantile_huber_by(pred, mid, target, n, grad, per_sample)
}

/// The quantile Huber loss at given fractions: `B` samples of `N` predictions `θ_i` at the
/// fractions `τ_i` (`pred` and `taus` both `[B, N]`; the fractions in f64, as they are drawn,
/// each rounded to `T` where it is used) against `N'` target samples each (`target`,
/// `[B, N']`); `n` is `N`. The same sums as [`quantile_huber`], whose midpoints it generalises:
/// an implicit quantile network (IQN) draws its `τ_i` at random, `N` for the online network and
/// `N'` for the target's samples, and Dopamine's IQN reduces as here (a sum over `i`, a mean over
/// `j` and over the batch):
///
/// ```text
/// L = (1/B) Σ_b Σ_i (1/N') Σ_j |τ_i − 1{u_ij < 0}| · h(u_ij),   u_ij = T_j − θ_i
/// ```
pub fn quantile_huber_at<T: Float>(
    pred: &[T], taus: &[f64], target: &[T], n: usize, grad: &mut [T], per_sample: &mut [T],
) -> T {
    assert_eq!(pred.len(), taus.len(), "quantile_huber: lengths differ");
    let tau = |b: usize, i: usize| T::of(taus[b * n + i]);
    quantile_huber_by(pred, tau, target, n, grad, per_sample)
}

/// The sums of [`quantile_huber_at`] with sample `b`'s fraction `i` given by `tau(b, i)`.
fn quantile_huber_by<T: Float>(
    pred: &[T], tau: impl Fn(usize, usize) -> T, target: &[T], n: usize, grad: &mut [T],
    per_sample: &mut [T],
) -> T {
    assert!(
        n > 0 && pred.len() == grad.len(),
        "quantile_huber: lengths differ"
    );
    let b = pred.len() / n;
    assert_eq!(b * n, pred.len(), "quantile_huber: not [B, N]");
    assert_eq!(per_sample.len(), b, "quantile_huber: one loss per sample");
    let n_target = target.len() / b.max(1);
    assert!(
        n_target > 0 && n_target * b == target.len(),
        "quantile_huber: targets not [B, N']"
    );
    let (one, half) = (T::one(), T::of(0.5));
    let scale = T::one() / (T::of(b as f64) * T::of(n_target as f64));
    let inv_n = T::one() / T::of(n_target as f64);
    let mut total = T::zero();
    for (s, (((theta, t), g), ps)) in pred
        .chunks_exact(n)
        .zip(target.chunks_exact(n_target))
        .zip(grad.chunks_exact_mut(n))
        .zip(per_sample.iter_mut())
        .enumerate()
    {
        let mut sample = T::zero();
        for i in 0..n {
            let (mut gi, tau_i) = (T::zero(), tau(s, i));
            for &tj in t {
                let u = tj - theta[i];
                let w = if u < T::zero() { one - tau_i } else { tau_i };
                let (h, dh) = if u.abs() <= one {
                    (half * u * u, u)
                } else {
                    (u.abs() - half, u.signum())
                };
                sample += w * h;
                gi -= w * dh;
            }
            g[i] = gi * scale;
        }
        *ps = sample * inv_n;
        total += *ps;
    }
    total / T::of(b as f64)
}
