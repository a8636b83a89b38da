//! The heads of the update: how a network's outputs give `Q(s, ·)` and the target samples, and
//! the loss that compares the online values with the targets ([`ValueHead`]), for DQN's Q-values,
//! QR-DQN's fixed quantiles and IQN's implicit quantiles. [`super::Learner::train_step`] reads
//! each head through this one trait, so its four steps are written once.

use super::learner::mean;
use super::qnet::midpoint;
use super::{Batch, Head, Iqn};
use crate::layers::loss::{quantile_huber, quantile_huber_at, LossKind};
use crate::layers::Sequential;

/// The head's part of the update ([`ValueHead`]) for `head`'s outputs.
pub(super) fn value_head(head: &Head, n_actions: usize) -> Box<dyn ValueHead> {
    match (head.iqn, head.atoms) {
        (Some(iqn), _) => Box::new(Implicit {
            iqn,
            actions: n_actions,
        }),
        (None, 1) => Box::new(QValues),
        (None, n) => Box::new(Quantiles(n)),
    }
}

/// Which pass of the update a network runs (an implicit quantile head takes different fractions
/// in each; a pass for `Q(s, ·)` alone takes [`ValueHead::policy_fractions`]).
#[derive(Clone, Copy, Debug)]
pub(super) enum Pass {
    /// The target network over `s'`: `Q(s', ·)` and the target samples.
    Next,
    /// The online network over `s`, the pass that is differentiated.
    Online,
}

/// What the update needs of a network's head: how its outputs give `Q(s, ·)` and the target
/// samples, and the loss that compares the online values with the targets.
pub(super) trait ValueHead: Send + Sync {
    /// Values per action in an output row (`[A, k]` per row): a quantile head's `N`, else 1.
    fn atoms(&self) -> usize {
        1
    }

    /// Sets `net`'s quantile fractions for `pass` (an implicit head's; the others have none);
    /// `taus` is scratch.
    fn fractions(
        &self, _net: &mut Sequential<f32>, _pass: Pass, _batch: &Batch, _taus: &mut Vec<f64>,
    ) {
    }

    /// Sets `net`'s quantile fractions for a pass that gives `Q(s, ·)` of `states` states and
    /// nothing else: acting, Double DQN's pick, Munchausen's bonus; `taus` is scratch.
    fn policy_fractions(&self, _net: &mut Sequential<f32>, _states: usize, _taus: &mut Vec<f64>) {}

    /// `Q(s, ·)` (`[A]`) from one state's output of a policy or online pass, into `q`.
    fn q_values(&self, out: &[f32], q: &mut Vec<f32>);

    /// One next state's output of the target pass: writes its target samples `Z_j(s', ·)` into
    /// `z` (`[M, A]`) and returns the part that gives `Q(s', ·)`.
    fn next<'a>(&self, out: &'a [f32], z: &mut Vec<f32>) -> &'a [f32];

    /// The loss of `θ` (`[B, N]`) against the targets `y` (`[B, M]`): `∂L/∂θ` into `d`, each
    /// sample's term `ℓ_b` into `per_sample` (`[B]`).
    fn loss(
        &self, theta: &[f32], y: &[f32], batch: &Batch, kind: LossKind, d: &mut [f32],
        per_sample: &mut [f32],
    ) -> f32;
}

/// DQN's head: one `Q(s, a)` per action, `[B, A]`; `M = N = 1`.
struct QValues;

impl ValueHead for QValues {
    fn q_values(&self, out: &[f32], q: &mut Vec<f32>) {
        q.clear();
        q.extend_from_slice(out);
    }

    fn next<'a>(&self, out: &'a [f32], z: &mut Vec<f32>) -> &'a [f32] {
        z.clear();
        z.extend_from_slice(out);
        out
    }

    /// `L = mean_b ℓ(Q(s_b, a_b) − y_b)`, MSE or Huber (`kind`).
    fn loss(
        &self, theta: &[f32], y: &[f32], _: &Batch, kind: LossKind, d: &mut [f32],
        per_sample: &mut [f32],
    ) -> f32 {
        let mut one = [0.0f32];
        for (i, term) in per_sample.iter_mut().enumerate() {
            *term = kind.eval(&theta[i..=i], &y[i..=i], &mut one);
        }
        kind.eval(theta, y, d)
    }
}

/// QR-DQN's head (Dabney et al. 2017): `N` outputs per action, `[B, A, N]`, the quantiles
/// `θ_1..N` of its return at the fixed fractions `τ_i = (2i − 1)/2N`; `Q(s, a)` is their mean,
/// and the target samples are the `N` quantiles of `a'`: `T_j = R + γ^m·(1 − done)·θ_j(s', a')`.
struct Quantiles(usize);

impl ValueHead for Quantiles {
    fn atoms(&self) -> usize {
        self.0
    }

    fn q_values(&self, out: &[f32], q: &mut Vec<f32>) {
        q.clear();
        q.extend(out.chunks_exact(self.0).map(mean));
    }

    /// `[A, N]` turned into the samples' rows `[N, A]`.
    fn next<'a>(&self, out: &'a [f32], z: &mut Vec<f32>) -> &'a [f32] {
        let n = self.0;
        z.clear();
        let na = out.len() / n;
        z.extend((0..n).flat_map(|j| (0..na).map(move |a| out[a * n + j])));
        out
    }

    /// The quantile Huber loss ([`quantile_huber`]): for each `θ_i` and target sample `T_j`,
    /// with `u = T_j − θ_i`, the Huber loss `h(u)` weighted by `|τ_i − 1{u < 0}|`; summed over
    /// `i`, averaged over `j` and the batch.
    fn loss(
        &self, theta: &[f32], y: &[f32], _: &Batch, _: LossKind, d: &mut [f32],
        per_sample: &mut [f32],
    ) -> f32 {
        quantile_huber(theta, y, self.0, d, per_sample)
    }
}

/// IQN's head (Dabney et al. 2018): the network evaluates each state at fractions `τ`, one row
/// `Z_τ(s, ·)` (`[A]`) per fraction. `Q(s, a)` is the mean of `Z_τ(s, a)` over the `K`
/// midpoints; the online network's `θ_i = Z_{τ_i}(s, a)` at the `N` drawn `τ_i`, and the target
/// samples are `Z^target_{τ'_j}(s', a')` at the `N'` drawn `τ'_j`. The target network takes the
/// `K` midpoints and the `N'` fractions in one pass: its trunk runs once per state.
struct Implicit {
    iqn: Iqn,
    actions: usize,
}

impl ValueHead for Implicit {
    fn fractions(&self, net: &mut Sequential<f32>, pass: Pass, batch: &Batch, taus: &mut Vec<f64>) {
        let Iqn {
            samples: n,
            target_samples: n2,
            policy_samples: k,
            ..
        } = self.iqn;
        let b = batch.len();
        assert!(
            batch.taus.len() == b * n && batch.target_taus.len() == b * n2,
            "an implicit quantile head: draw the batch's fractions first"
        );
        match pass {
            Pass::Online => net.set_fractions(&batch.taus),
            // Per next state: the K midpoints, then its N' drawn fractions.
            Pass::Next => {
                taus.clear();
                for drawn in batch.target_taus.chunks_exact(n2) {
                    taus.extend((0..k).map(|i| midpoint(i, k)));
                    taus.extend_from_slice(drawn);
                }
                net.set_fractions(taus);
            }
        }
    }

    /// The `K` midpoints `(2i + 1)/2K` for each state.
    fn policy_fractions(&self, net: &mut Sequential<f32>, states: usize, taus: &mut Vec<f64>) {
        let k = self.iqn.policy_samples;
        taus.clear();
        taus.extend((0..states).flat_map(|_| (0..k).map(move |i| midpoint(i, k))));
        net.set_fractions(taus);
    }

    /// The mean over the state's rows (its fractions).
    fn q_values(&self, out: &[f32], q: &mut Vec<f32>) {
        q.resize(self.actions, 0.0);
        mean_rows(out, self.actions, q);
    }

    fn next<'a>(&self, out: &'a [f32], z: &mut Vec<f32>) -> &'a [f32] {
        let (k, n2) = (self.iqn.policy_samples, self.iqn.target_samples);
        let (policy, samples) = out.split_at(out.len() / (k + n2) * k);
        z.clear();
        z.extend_from_slice(samples);
        policy
    }

    /// The quantile Huber loss at the drawn fractions ([`quantile_huber_at`]).
    fn loss(
        &self, theta: &[f32], y: &[f32], batch: &Batch, _: LossKind, d: &mut [f32],
        per_sample: &mut [f32],
    ) -> f32 {
        quantile_huber_at(theta, &batch.taus, y, self.iqn.samples, d, per_sample)
    }
}

/// The mean of `rows` (`[R, A]`, row-major) over its rows, into `out` (`[A]`): an implicit
/// quantile head's `Q(s, a)` from its values at `R` fractions.
fn mean_rows(rows: &[f32], n_actions: usize, out: &mut [f32]) {
    out.fill(0.0);
    let r = rows.len() / n_actions;
    for row in rows.chunks_exact(n_actions) {
        for (o, &v) in out.iter_mut().zip(row) {
            *o += v;
        }
    }
    for o in out.iter_mut() {
        *o /= r as f32;
    }
}
