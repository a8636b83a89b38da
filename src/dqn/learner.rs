//! The learning half of DQN: one gradient step on a minibatch of transitions.

use super::qnet::midpoints;
use super::{qnet, Batch, Head, Iqn};
use crate::layers::init::VarianceScaling;
use crate::layers::loss::{quantile_huber, quantile_huber_at, LossKind};
use crate::layers::Sequential;
use crate::optim::{clip_grad_norm, Adam};
use crate::tensor::Tensor;
use rand::Rng;

/// What one train step measured.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StepStats {
    /// The loss before the update.
    pub loss: f32,
    /// Mean over the batch of `max_a Q(s, a)` (the online network's value estimate).
    pub mean_max_q: f32,
    /// Global gradient norm before any clipping.
    pub grad_norm: f32,
    /// Whether every online-network weight is finite after the update ([`Adam::step`] checks
    /// each as it writes it; [`Learner::non_finite_param`] finds which one is not).
    pub weights_finite: bool,
}

/// The online network, its lagged target copy and the optimizer, with every buffer a step needs.
pub struct Learner {
    /// The network being trained; it also picks the actions.
    pub online: Sequential<f32>,
    /// A copy of `online` refreshed every `target_update` steps; it gives the bootstrap values.
    pub target: Sequential<f32>,
    /// The optimizer and its moments.
    pub adam: Adam<f32>,
    /// Discount factor γ.
    pub gamma: f32,
    /// The regression loss.
    pub loss: LossKind,
    /// Double DQN: the online network picks `a' = argmax Q(s', ·)`, the target evaluates it.
    pub double: bool,
    /// Clip gradients to this global norm, if set.
    pub clip_norm: Option<f32>,
    /// Munchausen targets, if set ([`Munchausen`]).
    pub munchausen: Option<Munchausen>,
    /// The implicit quantile head, if the networks have one.
    iqn: Option<Iqn>,
    n_actions: usize,
    /// `[B]`: `Q(s, a)` of the taken actions, the TD targets `y`, and `∂L/∂Q(s, a)`.
    q_taken: Vec<f32>,
    y: Vec<f32>,
    dq_taken: Vec<f32>,
    /// `[B]`: the online network's greedy `a'` (Double DQN only).
    next_greedy: Vec<usize>,
    /// `[B]`: the TD errors `Q(s, a) − y` of the last step.
    td: Vec<f32>,
    /// Values per action: 1, or a quantile head's `N` (the buffers above then hold `[B, N]`).
    atoms: usize,
    /// `[B]`: each sample's quantile Huber loss (quantile heads only).
    per_sample: Vec<f32>,
    /// `[B, n_actions]`: the upstream gradient, non-zero only at the taken actions.
    dq: Tensor<f32>,
}

impl Learner {
    /// A learner of the article's network for inputs of shape `[H, W, C]`; the target starts as a
    /// copy of the online net.
    pub fn new(
        input: [usize; 3], n_actions: usize, lr: f32, gamma: f32, rng: &mut impl Rng,
    ) -> Self {
        Learner::with_head(input, n_actions, Head::ARTICLE, lr, gamma, rng)
    }

    /// [`Learner::new`] with another head ([`qnet`]): dense1's width, a dueling combine, and a
    /// quantile head's `N` values per action (QR-DQN: the loss is then the quantile Huber loss).
    pub fn with_head(
        input: [usize; 3], n_actions: usize, head: Head, lr: f32, gamma: f32, rng: &mut impl Rng,
    ) -> Self {
        let online = qnet(input, n_actions, head, &VarianceScaling::HE, rng);
        let mut target = qnet(input, n_actions, head, &VarianceScaling::HE, rng);
        target.copy_params_from(&online);
        Learner {
            online,
            target,
            adam: Adam::new(lr),
            gamma,
            loss: LossKind::Mse,
            double: false,
            clip_norm: None,
            munchausen: None,
            iqn: head.iqn,
            n_actions,
            q_taken: Vec::new(),
            y: Vec::new(),
            dq_taken: Vec::new(),
            next_greedy: Vec::new(),
            td: Vec::new(),
            atoms: head.atoms,
            per_sample: Vec::new(),
            dq: Tensor::empty(),
        }
    }

    /// A learner with every setting taken from a run's configuration.
    pub fn from_config(config: &super::Config, n_actions: usize, rng: &mut impl Rng) -> Self {
        let mut l = Learner::with_head(
            config.input_shape(),
            n_actions,
            Head::of(config),
            config.learning_rate as f32,
            config.gamma as f32,
            rng,
        );
        l.adam.eps = config.adam_epsilon as f32;
        l.adam.rectified = config.radam;
        l.loss = config.loss;
        l.double = config.double_dqn;
        l.clip_norm = (config.clip_grad_norm > 0.0).then_some(config.clip_grad_norm as f32);
        l.munchausen = config.munchausen();
        l.set_precision(config.precision);
        l
    }

    /// Both networks' training arithmetic ([`crate::ops::plan::Precision`]).
    pub fn set_precision(&mut self, precision: crate::ops::plan::Precision) {
        self.online.set_precision(precision);
        self.target.set_precision(precision);
    }

    /// The number of actions.
    pub fn n_actions(&self) -> usize {
        self.n_actions
    }

    /// The TD targets `y` of the last [`Learner::train_step`], one per transition of its batch
    /// (empty before the first): what the online network's `Q(s, a)` was regressed towards.
    /// With a quantile head, `N` target samples per transition (`[B, N]`).
    pub fn targets(&self) -> &[f32] {
        &self.y
    }

    /// The first online-network parameter holding a NaN or an infinity, as `name[index]`.
    /// (The target network only ever copies the online one.)
    pub fn non_finite_param(&self) -> Option<String> {
        self.online.params().find_map(|p| {
            p.value
                .data()
                .iter()
                .position(|x| !x.is_finite())
                .map(|i| format!("{}[{i}]", p.name))
        })
    }

    /// The TD errors `Q(s_b, a_b) − y_b` of the last [`train_step`](Self::train_step), `[B]`: what
    /// prioritized replay sets its priorities from.
    pub fn td_errors(&self) -> &[f32] {
        &self.td
    }

    /// Copies the online network into the target network.
    pub fn update_target(&mut self) {
        self.target.copy_params_from(&self.online);
    }

    /// Draws the layers after the convolutions afresh (a reset against lost plasticity,
    /// `Config::reset_dense_at`): each of their parameters takes its value from `fresh`, a
    /// newly initialised network of the same architecture, and its Adam first moment `m` is
    /// zeroed, so no step of the old weights' momentum lands on the new ones. The second moments
    /// `v` stay: they hold the scale of these parameters' gradients, and zeroed under Adam's late
    /// bias correction (`α_t ≈ lr`) they would make the next steps several times the learning
    /// rate (`m/√v ≈ 0.1·g/√(0.001·g²) ≈ 3` after one step). The convolutions (`conv1` to
    /// `conv3`, and `ln1` to `ln3` with layer normalisation), the target network and Adam's step
    /// count are kept. Returns how many parameters (tensors) were reset.
    pub fn reset_dense(&mut self, fresh: &Sequential<f32>) -> usize {
        let trunk = |name: &str| {
            ["conv1.", "conv2.", "conv3.", "ln1.", "ln2.", "ln3."]
                .iter()
                .any(|p| name.starts_with(p))
        };
        let mut theirs = fresh.params();
        let mut reset = 0;
        for (i, mine) in self.online.params_mut().enumerate() {
            let p = theirs.next().expect("reset_dense: the same architecture");
            assert_eq!(mine.name, p.name, "reset_dense: architectures differ");
            if trunk(&mine.name) {
                continue;
            }
            mine.value.data_mut().copy_from_slice(p.value.data());
            if let Some(m) = self.adam.m.get_mut(i) {
                m.fill_zero();
            }
            reset += 1;
        }
        reset
    }

    /// One DQN update on `batch`: [`Learner::q_step`] for a Q-value or quantile head,
    /// [`Learner::iqn_step`] for an implicit quantile head.
    pub fn train_step(&mut self, batch: &Batch) -> StepStats {
        match self.iqn {
            None => self.q_step(batch),
            Some(iqn) => self.iqn_step(batch, iqn),
        }
    }

    /// One DQN update on `batch`:
    ///
    /// 1. TD target `y = R + γ^m·(1 − done)·max_a' Q_target(s', a')`, with `R` the return of the
    ///    `m` steps from `s` to `s'` (`m = 1`, `R = r`: the one-step target) (Double DQN:
    ///    `Q_target(s', argmax_a' Q_online(s', a'))`; Munchausen: the soft target of
    ///    [`Munchausen`]); no gradient flows through `y`, so these passes are
    ///    [`Sequential::infer`] (sparse products where the activations allow).
    /// 2. Forward `Q_online(s, ·)`, keep `Q(s, a)` of the taken actions.
    /// 3. Loss `L = mean_b ℓ(Q(s_b, a_b) − y_b)` (MSE or Huber); `∂L/∂Q(s_b, a)` is non-zero only
    ///    at `a = a_b`, so the upstream gradient `dQ[B, A]` is zero except one entry per row.
    ///    With prioritized sampling each term is weighted: `L = mean_b w_b ℓ(…)`
    ///    (`batch.weights`), and so is its gradient.
    ///
    /// With a quantile head (QR-DQN, `atoms = N > 1`) each action has `N` outputs `θ_1..N`, the
    /// `τ_i = (2i − 1)/2N` quantiles of its return, and `Q` is their mean: `a'` maximises that
    /// mean, the target is the `N` samples `T_j = R + γ^m·(1 − done)·θ_j,target(s', a')`, and the
    /// loss is the quantile Huber loss of `θ(s, a)` against them ([`quantile_huber`]).
    /// 4. Backward through the online network (the first layer skips its input gradient), then
    ///    one Adam step.
    pub fn q_step(&mut self, batch: &Batch) -> StepStats {
        let (b, na, k) = (batch.len(), self.n_actions, self.atoms);
        for buf in [&mut self.q_taken, &mut self.y, &mut self.dq_taken] {
            buf.resize(b * k, 0.0);
        }
        // Double DQN: the online network picks a' (the soft target of Munchausen needs none).
        // The passes over s' are inference (no backward follows): `infer` skips the zeros the
        // ReLUs leave where they are most of the activations (a trained network).
        let double = self.double && self.munchausen.is_none();
        if double {
            let q_next = self.online.infer(&batch.next_states).data();
            greedy_actions(q_next, b, k, &mut self.next_greedy);
        }
        // The target network's pass over s' and the online network's over s are independent:
        // they run side by side, each layer's work still split over the pool.
        let (target, online) = (&mut self.target, &mut self.online);
        let (q_next, q) = rayon::join(
            || target.infer(&batch.next_states),
            || online.forward(&batch.states),
        );
        // 1. The TD targets y.
        match self.munchausen {
            None => {
                let picked = double.then_some(&self.next_greedy[..]);
                td_targets(batch, q_next.data(), picked, self.gamma, k, &mut self.y)
            }
            Some(m) => {
                let q_next = q_next.data().to_vec();
                let q_s = target.infer(&batch.states).data();
                m.targets(batch, &q_next, q_s, self.gamma, &mut self.y)
            }
        }
        // 2. Q(s, a) of the taken actions.
        let max_q_sum = taken_values(q.data(), batch, k, &mut self.q_taken);
        // 3. The loss and its gradient ∂L/∂Q(s, a), weighted under prioritized sampling.
        let loss = self.regression_loss(batch);
        // 4. Backward from dQ (non-zero at the taken actions only), then one Adam step.
        self.backward_and_step(batch, na * k, k, loss, max_q_sum)
    }

    /// One regression of `Q(s, a)` towards given targets (PQN's update, whose targets come from
    /// its rollout: [`super::q_lambda_returns`]): forward `Q_online(batch.states, ·)`, the loss
    /// `L = mean_b ℓ(Q(s_b, a_b) − y_b)` (MSE or Huber) against `targets` (`[B]`), backward from
    /// `dQ` (non-zero at the taken actions only), one optimizer step. Of the batch only
    /// `states` and `actions` are read.
    ///
    /// # Panics
    /// If the network has a quantile head, or `targets` is not one per transition.
    pub fn regress_step(&mut self, batch: &Batch, targets: &[f32]) -> StepStats {
        assert!(
            self.atoms == 1 && self.iqn.is_none(),
            "regress_step: a Q-value head"
        );
        let b = batch.len();
        assert_eq!(targets.len(), b, "regress_step: one target per transition");
        self.y.clear();
        self.y.extend_from_slice(targets);
        for buf in [&mut self.q_taken, &mut self.dq_taken] {
            buf.resize(b, 0.0);
        }
        let q = self.online.forward(&batch.states);
        let max_q_sum = taken_values(q.data(), batch, 1, &mut self.q_taken);
        let loss = self.loss.eval(&self.q_taken, &self.y, &mut self.dq_taken);
        td_errors(&self.q_taken, &self.y, b, &mut self.td);
        self.backward_and_step(batch, self.n_actions, 1, loss, max_q_sum)
    }

    /// The loss of `q_taken` against `y` (MSE or Huber; with a quantile head the quantile Huber
    /// loss), writing `∂L/∂Q` into `dq_taken` and the TD errors (of the means, with a quantile
    /// head) for prioritized replay; under prioritized sampling each term and its gradient are
    /// weighted by `batch.weights` ([`weight_terms`]).
    fn regression_loss(&mut self, batch: &Batch) -> f32 {
        let (b, k) = (batch.len(), self.atoms);
        let loss = if k == 1 {
            self.loss.eval(&self.q_taken, &self.y, &mut self.dq_taken)
        } else {
            self.per_sample.resize(b, 0.0);
            quantile_huber(
                &self.q_taken,
                &self.y,
                k,
                &mut self.dq_taken,
                &mut self.per_sample,
            )
        };
        td_errors(&self.q_taken, &self.y, b, &mut self.td);
        if batch.weights.is_empty() {
            return loss;
        }
        // One-term losses recomputed from the same function.
        let mut one = [0.0f32];
        let terms: Vec<f32> = (0..b)
            .map(|i| {
                if k == 1 {
                    self.loss
                        .eval(&self.q_taken[i..=i], &self.y[i..=i], &mut one)
                } else {
                    self.per_sample[i]
                }
            })
            .collect();
        weight_terms(&batch.weights, &terms, k, &mut self.dq_taken)
    }

    /// One update of an implicit quantile network (IQN, Dabney et al. 2018) on `batch`, whose
    /// fractions were drawn by [`Batch::draw_fractions`]:
    ///
    /// 1. `Q(s', a) = mean_k Z_{τ_k}(s', a)` over the `K` midpoint fractions picks
    ///    `a' = argmax_a Q(s', a)` (by the online network with Double DQN, else the target).
    /// 2. Target samples at the drawn `τ'_j`, `j = 1..N'`:
    ///    `T_j = R + γ^m·(1 − done)·Z^target_{τ'_j}(s', a')` (Munchausen: the soft target of
    ///    [`Munchausen`], with `Z_{τ'_j}(s', ·)` as the next state's values).
    /// 3. Online quantiles at the drawn `τ_i`, `i = 1..N`: `θ_i = Z_{τ_i}(s, a)`; the quantile
    ///    Huber loss of `θ` against `T` ([`quantile_huber_at`]), weighted as in
    ///    [`Learner::q_step`] under prioritized sampling (by the TD error of the means).
    /// 4. Backward (`dZ` non-zero at `(b·N + i, a_b)` only), then one Adam step.
    ///
    /// The target network evaluates `s'` once, at the `K` midpoints and the `N'` fractions
    /// together: its trunk runs once per state.
    pub fn iqn_step(&mut self, batch: &Batch, iqn: Iqn) -> StepStats {
        let (b, na) = (batch.len(), self.n_actions);
        let (n, n2, k) = (iqn.samples, iqn.target_samples, iqn.policy_samples);
        assert!(
            batch.taus.len() == b * n && batch.target_taus.len() == b * n2,
            "iqn_step: draw the batch's fractions first"
        );
        // 1. The next states' fractions: K midpoints, then the N' drawn ones, per state.
        let mids = midpoints(k, 1);
        let next_taus: Vec<f64> = batch
            .target_taus
            .chunks_exact(n2)
            .flat_map(|drawn| mids.iter().chain(drawn).copied())
            .collect();
        self.next_greedy.resize(b, 0);
        if self.double && self.munchausen.is_none() {
            self.online.set_fractions(&midpoints(k, b));
            let q_next = self.online.infer(&batch.next_states).data();
            self.next_greedy.clear();
            self.next_greedy.extend(
                q_next
                    .chunks_exact(k * na)
                    .map(|rows| greedy_rows(rows, na)),
            );
        }
        self.target.set_fractions(&next_taus);
        self.online.set_fractions(&batch.taus);
        let (target, online) = (&mut self.target, &mut self.online);
        let (z_next, z) = rayon::join(
            || target.infer(&batch.next_states),
            || online.forward(&batch.states),
        );
        // 2. The target samples, `[B, N']`.
        self.y.resize(b * n2, 0.0);
        let z_next = z_next.data().to_vec();
        let q_s = match self.munchausen {
            Some(_) => {
                target.set_fractions(&midpoints(k, b));
                target.infer(&batch.states).data().to_vec()
            }
            None => Vec::new(),
        };
        let mut q_next = vec![0.0f32; na];
        let mut q_now = vec![0.0f32; na];
        for (i, rows) in z_next.chunks_exact((k + n2) * na).enumerate() {
            let (policy_rows, sample_rows) = rows.split_at(k * na);
            mean_rows(policy_rows, na, &mut q_next);
            let cont = if batch.dones[i] { 0.0 } else { 1.0 };
            let discount = self.gamma.powi(batch.steps[i] as i32);
            let y = &mut self.y[i * n2..(i + 1) * n2];
            match self.munchausen {
                Some(m) => {
                    mean_rows(&q_s[i * k * na..(i + 1) * k * na], na, &mut q_now);
                    let r = batch.rewards[i] + m.bonus(&q_now, batch.actions[i]);
                    for (y, z_j) in y.iter_mut().zip(sample_rows.chunks_exact(na)) {
                        *y = r + discount * cont * m.soft_value(&q_next, z_j);
                    }
                }
                None => {
                    let a_next = if self.double {
                        self.next_greedy[i]
                    } else {
                        argmax(&q_next)
                    };
                    for (y, z_j) in y.iter_mut().zip(sample_rows.chunks_exact(na)) {
                        *y = batch.rewards[i] + discount * cont * z_j[a_next];
                    }
                }
            }
        }
        // 3. The online quantiles of the taken actions, `[B, N]`, and the loss.
        self.q_taken.resize(b * n, 0.0);
        self.dq_taken.resize(b * n, 0.0);
        let mut max_q_sum = 0.0;
        for (i, rows) in z.data().chunks_exact(n * na).enumerate() {
            let a = batch.actions[i];
            for (t, row) in self.q_taken[i * n..(i + 1) * n]
                .iter_mut()
                .zip(rows.chunks_exact(na))
            {
                *t = row[a];
            }
            mean_rows(rows, na, &mut q_now);
            max_q_sum += q_now[argmax(&q_now)];
        }
        let taus: Vec<f32> = batch.taus.iter().map(|&t| t as f32).collect();
        self.per_sample.resize(b, 0.0);
        let mut loss = quantile_huber_at(
            &self.q_taken,
            &taus,
            &self.y,
            n,
            &mut self.dq_taken,
            &mut self.per_sample,
        );
        td_errors(&self.q_taken, &self.y, b, &mut self.td);
        if !batch.weights.is_empty() {
            loss = weight_terms(&batch.weights, &self.per_sample, n, &mut self.dq_taken);
        }
        // 4. `dZ`: each row's gradient at its sample's action only.
        self.backward_and_step(batch, na, 1, loss, max_q_sum)
    }

    /// `dQ` (`self.dq`): `dq_taken` at each sample's taken action (rows of `width` values, `k`
    /// per action), zeros elsewhere; back-propagated through the online network's last forward
    /// pass (on `batch.states`), the gradient clipped if configured, one Adam step. Returns the
    /// step's statistics: `loss`, the mean of `max_q_sum` and the gradient's global norm before
    /// clipping.
    fn backward_and_step(
        &mut self, batch: &Batch, width: usize, k: usize, loss: f32, max_q_sum: f32,
    ) -> StepStats {
        scatter_rows(&self.dq_taken, batch, width, k, &mut self.dq);
        self.online.zero_grad();
        self.online.backward(&batch.states, &self.dq, false);
        let grad_norm = match self.clip_norm {
            Some(max) => clip_grad_norm(&mut self.online, max),
            None => crate::optim::global_grad_norm(self.online.params()),
        };
        let weights_finite = self.adam.step(self.online.params_mut());
        StepStats {
            loss,
            mean_max_q: max_q_sum / batch.len() as f32,
            grad_norm,
            weights_finite,
        }
    }
}

/// The TD targets `y` (`[B, k]`) from the target network's outputs for the next states
/// (`q_next`, `[B, A·k]`): `y = R + γ^m·(1 − done)·Q_target(s', a')` with `a'` the greedy action of
/// `q_next`, or `picked` (Double DQN: the online network's). With a quantile head, one target
/// sample per quantile of `a'`: `T_j = R + γ^m·(1 − done)·θ_j(s', a')`.
fn td_targets(
    batch: &Batch, q_next: &[f32], picked: Option<&[usize]>, gamma: f32, k: usize, y: &mut [f32],
) {
    let per = q_next.len() / batch.len();
    for (i, row) in q_next.chunks_exact(per).enumerate() {
        let a_next = match picked {
            Some(p) => p[i],
            None => greedy_atoms(row, k),
        };
        let cont = if batch.dones[i] { 0.0 } else { 1.0 };
        let discount = gamma.powi(batch.steps[i] as i32);
        for (y, &future) in y[i * k..(i + 1) * k]
            .iter_mut()
            .zip(&row[a_next * k..(a_next + 1) * k])
        {
            *y = batch.rewards[i] + discount * cont * future;
        }
    }
}

/// The greedy action of each of `b` samples' outputs (`q`: `[B, A·k]`, [`greedy_atoms`]), into
/// `out`.
fn greedy_actions(q: &[f32], b: usize, k: usize, out: &mut Vec<usize>) {
    out.clear();
    out.extend(q.chunks_exact(q.len() / b).map(|row| greedy_atoms(row, k)));
}

/// Copies the outputs of the taken actions (`k` values each) from `q` (`[B, A·k]`) into `taken`
/// (`[B, k]`); returns the sum over the batch of `max_a Q(s, a)` (a quantile head's best mean).
fn taken_values(q: &[f32], batch: &Batch, k: usize, taken: &mut [f32]) -> f32 {
    let mut max_q_sum = 0.0;
    let per = q.len() / batch.len();
    for (i, row) in q.chunks_exact(per).enumerate() {
        let a = batch.actions[i];
        taken[i * k..(i + 1) * k].copy_from_slice(&row[a * k..(a + 1) * k]);
        max_q_sum += if k == 1 {
            row[argmax(row)]
        } else {
            let best = greedy_atoms(row, k);
            mean(&row[best * k..(best + 1) * k])
        };
    }
    max_q_sum
}

/// The upstream gradient `dQ` (`[R, width]`), zero but at the taken actions: `d_taken` holds `k`
/// values per row (the atoms of one action), which go at the action of the row's sample; a
/// sample has `R/B` rows, one after another (an implicit quantile head's fractions; else one).
fn scatter_rows(d_taken: &[f32], batch: &Batch, width: usize, k: usize, dq: &mut Tensor<f32>) {
    let rows = d_taken.len() / k;
    let per_sample = rows / batch.len();
    dq.set_shape(&[rows, width]);
    dq.fill_zero();
    for (r, row) in dq.data_mut().chunks_exact_mut(width).enumerate() {
        let a = batch.actions[r / per_sample];
        row[a * k..(a + 1) * k].copy_from_slice(&d_taken[r * k..(r + 1) * k]);
    }
}

/// Prioritized replay's weighted mean loss `(1/B) Σ_b w_b·ℓ_b` from each sample's term `ℓ_b`,
/// with each sample's `per` gradient entries in `d` scaled by its weight `w_b`.
fn weight_terms(weights: &[f32], terms: &[f32], per: usize, d: &mut [f32]) -> f32 {
    let b = weights.len();
    let mut loss = 0.0;
    for (i, (&w, &l)) in weights.iter().zip(terms).enumerate() {
        loss += w * l / b as f32;
        for d in &mut d[i * per..(i + 1) * per] {
            *d *= w;
        }
    }
    loss
}

/// Munchausen RL's targets (Vieillard et al. 2020): a soft Q-learning target, `π = softmax(q/τ)`
/// of the target network's values, plus the scaled log-policy of the action taken as a bonus
///
/// ```text
/// y = R + α·clamp(τ·log π(a|s), l0, 0) + γ^m·(1 − done)·Σ_a' π(a'|s')·(q(s', a') − τ·log π(a'|s'))
/// ```
///
/// (their M-DQN with α = 0.9, τ = 0.03, l0 = −1; M-IQN the same with `q(s', a')` each target
/// sample's value). `τ·log π` is computed as `q − max q − τ·log Σ exp((q − max q)/τ)`, stable for
/// any `τ`. With n-step returns `R` is the n-step return and the bonus that of the first action.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Munchausen {
    /// `α`, the bonus's scale.
    pub alpha: f32,
    /// `τ`, the entropy temperature.
    pub tau: f32,
    /// `l0`, the bonus's lower clip.
    pub clip: f32,
}

impl Munchausen {
    /// M-DQN's targets `y` (`[B]`) from the target network's values of the next states
    /// (`q_next`) and of the states (`q_s`), both `[B, A]`.
    pub fn targets(&self, batch: &Batch, q_next: &[f32], q_s: &[f32], gamma: f32, y: &mut [f32]) {
        let na = q_s.len() / batch.len();
        for (i, y) in y.iter_mut().enumerate() {
            let (now, next) = (&q_s[i * na..(i + 1) * na], &q_next[i * na..(i + 1) * na]);
            let cont = if batch.dones[i] { 0.0 } else { 1.0 };
            let discount = gamma.powi(batch.steps[i] as i32);
            *y = batch.rewards[i]
                + self.bonus(now, batch.actions[i])
                + discount * cont * self.soft_value(next, next);
        }
    }

    /// `τ·log π(·|s)` for one state's values `q` (`[A]`), into `out`.
    pub fn scaled_log_policy(&self, q: &[f32], out: &mut [f32]) {
        let max = q.iter().copied().fold(f32::NEG_INFINITY, f32::max);
        let sum: f32 = q.iter().map(|&v| ((v - max) / self.tau).exp()).sum();
        let log_sum = self.tau * sum.ln();
        for (o, &v) in out.iter_mut().zip(q) {
            *o = v - max - log_sum;
        }
    }

    /// The bonus `α·clamp(τ·log π(a|s), l0, 0)` for the values `q` of `s` and the action `a`.
    pub fn bonus(&self, q: &[f32], a: usize) -> f32 {
        let mut log_pi = vec![0.0; q.len()];
        self.scaled_log_policy(q, &mut log_pi);
        self.alpha * log_pi[a].clamp(self.clip, 0.0)
    }

    /// The soft value `Σ_a π(a|s)·(v_a − τ·log π(a|s))` of a state whose policy comes from the
    /// values `q` and whose bootstrapped values are `v` (both `[A]`; `v = q` for M-DQN, a target
    /// sample's `Z_τ'` for M-IQN).
    pub fn soft_value(&self, q: &[f32], v: &[f32]) -> f32 {
        let mut log_pi = vec![0.0; q.len()];
        self.scaled_log_policy(q, &mut log_pi);
        log_pi
            .iter()
            .zip(v)
            .map(|(&l, &v)| (l / self.tau).exp() * (v - l))
            .sum()
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

/// The greedy action of an implicit quantile head's output for one state, `[K, A]` (its values at
/// `K` fractions): the largest mean over the rows (the first on ties).
pub fn greedy_rows(rows: &[f32], n_actions: usize) -> usize {
    let mut q = vec![0.0f32; n_actions];
    mean_rows(rows, n_actions, &mut q);
    argmax(&q)
}

/// The mean of a slice.
/// The TD errors for prioritized replay, `b` samples: each sample's prediction minus its target,
/// or with a quantile head the mean of its predictions minus the mean of its target samples.
fn td_errors(q: &[f32], y: &[f32], b: usize, td: &mut Vec<f32>) {
    let (n, n_target) = (q.len() / b, y.len() / b);
    let pairs = q.chunks_exact(n).zip(y.chunks_exact(n_target));
    td.clear();
    td.extend(pairs.map(|(q, y)| {
        if n == 1 && n_target == 1 {
            q[0] - y[0]
        } else {
            mean(q) - mean(y)
        }
    }));
}

fn mean(x: &[f32]) -> f32 {
    x.iter().sum::<f32>() / x.len() as f32
}

/// The greedy action of one sample's outputs `[A, K]`: the largest Q-value (`K = 1`), or with a
/// quantile head the largest mean of its `K` quantiles (the expected return).
pub fn greedy_atoms(row: &[f32], k: usize) -> usize {
    if k == 1 {
        return argmax(row);
    }
    // As `argmax` over the means (the first on ties), without collecting them.
    let mut best = (0, f32::NEG_INFINITY);
    for (a, quantiles) in row.chunks_exact(k).enumerate() {
        let m = mean(quantiles);
        if a == 0 || m > best.1 {
            best = (a, m);
        }
    }
    best.0
}

/// Index of the largest value (the first one on ties).
pub fn argmax(row: &[f32]) -> usize {
    let mut best = 0;
    for (i, &v) in row.iter().enumerate() {
        if v > row[best] {
            best = i;
        }
    }
    best
}
