//! The learning half of DQN: one gradient step on a minibatch of transitions.
//!
//! [`Learner::train_step`] is the whole update, in CleanRL's four steps: the targets with no
//! gradient, the forward pass, the loss and its gradient, backward and the optimizer step. It
//! reads the same for every head; what differs between them is two short functions:
//!
//! - the head ([`ValueHead`]: one Q-value per action, QR-DQN's fixed quantiles, IQN's implicit
//!   ones) says how its outputs give `Q(s, ·)` and the target samples `Z_j(s', ·)`, and which
//!   loss compares them with the online network's values;
//! - the target rule ([`TargetRule`]: the max, Double DQN, Munchausen) says how the next state's
//!   value is bootstrapped from them.

use super::heads::{value_head, Pass, ValueHead};
use super::{qnet, Batch, Head};
use crate::layers::init::VarianceScaling;
use crate::layers::loss::LossKind;
use crate::layers::Sequential;
use crate::optim::{clip_grad_norm, Adam};
use crate::tensor::Tensor;
use rand::Rng;

/// The panic of a target network asked of a learner that has none.
const NO_TARGET: &str = "this learner has no target network (PQN's: Learner::without_target)";

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
///
/// Shapes, for a batch of `B` transitions and `A` actions: `N` values of `Q(s, a)` per
/// transition (1; a quantile head's `N` quantiles; an implicit head's `N` drawn fractions) and
/// `M` target samples (1; the `N` quantiles; the `N'` target fractions).
pub struct Learner {
    /// The network being trained; it also picks the actions.
    pub online: Sequential<f32>,
    /// A copy of `online` refreshed every `target_update` steps; it gives the bootstrap values
    /// ([`Learner::target`]). PQN's learner has none: its targets come from its rollouts.
    target: Option<Sequential<f32>>,
    /// The optimizer and its moments.
    pub adam: Adam<f32>,
    /// Discount factor γ.
    pub gamma: f32,
    /// The regression loss of a Q-value head (the quantile heads have their own).
    pub loss: LossKind,
    /// How the targets bootstrap the next state: the max, Double DQN or Munchausen.
    pub rule: TargetRule,
    /// Clip gradients to this global norm, if set.
    pub clip_norm: Option<f32>,
    /// The head: its targets and its loss.
    head: Box<dyn ValueHead>,
    n_actions: usize,
    /// `[B, M]`: the targets `y` (a quantile head's target samples `T_j`).
    y: Vec<f32>,
    /// `[B, N]`: `Q(s, a)` of the taken actions (`θ_i` with a quantile head), and `∂L/∂θ`.
    q_taken: Vec<f32>,
    dq_taken: Vec<f32>,
    /// `[B]`: each transition's term of the loss (what prioritized sampling weights).
    per_sample: Vec<f32>,
    /// `[B]`: the TD errors `Q(s, a) − y` of the last step.
    td: Vec<f32>,
    /// `[B·R, A·k]`: the upstream gradient, non-zero only at the taken actions (`R` rows per
    /// state, `k` values per action: [`ValueHead::atoms`]).
    dq: Tensor<f32>,
    /// The small buffers of steps 1 and 2, kept so that a step allocates none of them anew.
    scratch: Scratch,
}

/// Buffers a train step writes and reads back within the step.
#[derive(Default)]
struct Scratch {
    /// `[B, A]`: the rule's policy values ([`TargetRule::policy`]; empty for the max).
    policy: Vec<f32>,
    /// `[A]`: one next state's `Q(s', ·)`, then one state's `Q(s, ·)`.
    q: Vec<f32>,
    /// `[M, A]`: one next state's target samples.
    z: Vec<f32>,
    /// An implicit quantile head's fractions for a pass over several states.
    taus: Vec<f64>,
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
    /// quantile head's `N` values per action (QR-DQN: the loss is then the quantile Huber loss),
    /// or an implicit quantile head (IQN).
    pub fn with_head(
        input: [usize; 3], n_actions: usize, head: Head, lr: f32, gamma: f32, rng: &mut impl Rng,
    ) -> Self {
        let online = qnet(input, n_actions, head, &VarianceScaling::HE, rng);
        let mut target = qnet(input, n_actions, head, &VarianceScaling::HE, rng);
        target.copy_params_from(&online);
        let target = Some(target);
        let values = value_head(&head, n_actions);
        Learner {
            online,
            target,
            adam: Adam::new(lr),
            gamma,
            loss: LossKind::Mse,
            rule: TargetRule::Max,
            clip_norm: None,
            head: values,
            n_actions,
            y: Vec::new(),
            q_taken: Vec::new(),
            dq_taken: Vec::new(),
            per_sample: Vec::new(),
            td: Vec::new(),
            dq: Tensor::empty(),
            scratch: Scratch::default(),
        }
    }

    /// A learner with every setting taken from a run's configuration; with a `[pqn]` table,
    /// without a target network ([`Learner::without_target`]).
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
        l.rule = config.target_rule();
        l.clip_norm = (config.clip_grad_norm > 0.0).then_some(config.clip_grad_norm as f32);
        l.set_precision(config.precision);
        match config.pqn {
            Some(_) => l.without_target(),
            None => l,
        }
    }

    /// The learner without its target network, for an algorithm that bootstraps otherwise (PQN:
    /// [`Learner::regress_step`] with its rollouts' λ-returns). [`Learner::train_step`] then
    /// panics, and [`Learner::update_target`] does nothing.
    pub fn without_target(mut self) -> Self {
        self.target = None;
        self
    }

    /// The target network.
    ///
    /// # Panics
    /// If the learner has none ([`Learner::without_target`]).
    pub fn target(&self) -> &Sequential<f32> {
        self.target.as_ref().expect(NO_TARGET)
    }

    /// The target network, mutably.
    ///
    /// # Panics
    /// If the learner has none ([`Learner::without_target`]).
    pub fn target_mut(&mut self) -> &mut Sequential<f32> {
        self.target.as_mut().expect(NO_TARGET)
    }

    /// The target network, if the learner has one.
    pub fn target_if_any(&self) -> Option<&Sequential<f32>> {
        self.target.as_ref()
    }

    /// Both networks' training arithmetic ([`crate::ops::plan::Precision`]).
    pub fn set_precision(&mut self, precision: crate::ops::plan::Precision) {
        self.online.set_precision(precision);
        if let Some(target) = &mut self.target {
            target.set_precision(precision);
        }
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

    /// Copies the online network into the target network (none: nothing to do).
    pub fn update_target(&mut self) {
        if let Some(target) = &mut self.target {
            target.copy_params_from(&self.online);
        }
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
        // The convolutions: the article's, or the IMPALA encoder's stages.
        let trunk = |name: &str| {
            [
                "conv1.", "conv2.", "conv3.", "ln1.", "ln2.", "ln3.", "stage",
            ]
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

    /// One DQN update on `batch` (an implicit quantile head needs its fractions drawn,
    /// [`Batch::draw_fractions`]), as CleanRL's:
    ///
    /// 1. The targets, with no gradient (inference passes, which skip the ReLUs' zeros): the
    ///    TD target `y = R + γ^m·(1 − done)·max_a' Q_target(s', a')`, with `R` the return of the
    ///    `m` steps from `s` to `s'` (`m = 1`: the one-step target). The rule ([`TargetRule`])
    ///    picks `a'` or replaces the max; the head (`ValueHead`, below) gives `Q(s', ·)` and the
    ///    samples it bootstraps (one, or a quantile head's `M`).
    /// 2. The forward pass `Q_online(s, ·)`, keeping `Q(s, a)` of the taken actions (`θ`).
    /// 3. The loss `L = mean_b ℓ_b` of `θ` against `y` and `∂L/∂θ` (the head's loss); with
    ///    prioritized sampling each term is weighted, `L = mean_b w_b ℓ_b`, and so is its
    ///    gradient.
    /// 4. Backward from `dQ` (zero but at the taken actions), then one Adam step.
    ///
    /// The target network's pass over `s'` and the online one's over `s` are independent: they
    /// run side by side, each layer's work still split over the pool.
    pub fn train_step(&mut self, batch: &Batch) -> StepStats {
        self.train_step_with(batch, None)
    }

    /// [`Learner::train_step`], the target network's pass over the next states given where
    /// another thread made it ahead ([`NextValues`]): `next` is that pass's output for this
    /// `batch` by a copy of this learner's target network, the numbers the step would compute
    /// itself (`None`: the step makes the pass).
    pub fn train_step_with(&mut self, batch: &Batch, next: Option<&[f32]>) -> StepStats {
        let (head, na, rule, gamma) = (&*self.head, self.n_actions, self.rule, self.gamma);
        // 1. The targets y: the rule's own pass first (Double DQN: `Q_online(s', ·)`;
        //    Munchausen: `Q_target(s, ·)`), then the target network's over s', beside step 2.
        let target = self.target.as_mut().expect(NO_TARGET);
        let Scratch { policy, q, z, taus } = &mut self.scratch;
        rule.policy(head, &mut self.online, target, batch, q, taus, policy);
        let (online, y) = (&mut self.online, &mut self.y);
        let ((), out) = rayon::join(
            || {
                let out = match next {
                    Some(out) => {
                        assert!(
                            !out.is_empty() && out.len().is_multiple_of(batch.len()),
                            "train_step_with: {} target values for a batch of {}",
                            out.len(),
                            batch.len()
                        );
                        out
                    }
                    None => next_values(head, target, batch, taus),
                };
                targets(head, rule, out, batch, policy, gamma, y, [q, z]);
            },
            // 2. The forward pass; θ = Q(s, a) of the taken actions.
            || forward(head, online, batch),
        );
        let max_q_sum = taken(head, out.data(), batch, na, &mut self.q_taken, q);
        // 3. The loss and ∂L/∂θ, weighted under prioritized sampling.
        let loss = self.loss_and_gradient(batch);
        // 4. Backward from dQ (non-zero at the taken actions only), then one Adam step.
        self.backward_and_step(batch, loss, max_q_sum)
    }

    /// One regression of `Q(s, a)` towards given targets (PQN's update, whose targets come from
    /// its rollout: [`super::q_lambda_returns`]): steps 2 to 4 of [`Learner::train_step`] with
    /// `targets` (`[B]`) as `y`. Of the batch only `states` and `actions` are read.
    ///
    /// # Panics
    /// If `targets` is not one per transition, or the network has a quantile head (the loss's
    /// lengths then differ).
    pub fn regress_step(&mut self, batch: &Batch, targets: &[f32]) -> StepStats {
        assert_eq!(
            targets.len(),
            batch.len(),
            "regress_step: one target per transition"
        );
        self.y.clear();
        self.y.extend_from_slice(targets);
        let out = forward(&*self.head, &mut self.online, batch);
        let max_q_sum = taken(
            &*self.head,
            out.data(),
            batch,
            self.n_actions,
            &mut self.q_taken,
            &mut self.scratch.q,
        );
        let loss = self.loss_and_gradient(batch);
        self.backward_and_step(batch, loss, max_q_sum)
    }

    /// Step 3: the head's loss of `θ` (`q_taken`, `[B, N]`) against `y` (`[B, M]`), `∂L/∂θ`
    /// into `dq_taken` and the TD errors (of the means, with a quantile head) for prioritized
    /// replay; under prioritized sampling each term and its gradient are weighted by
    /// `batch.weights` ([`weight_terms`]).
    fn loss_and_gradient(&mut self, batch: &Batch) -> f32 {
        let b = batch.len();
        self.dq_taken.resize(self.q_taken.len(), 0.0);
        self.per_sample.resize(b, 0.0);
        let (theta, y) = (&self.q_taken, &self.y);
        let loss = (self.head).loss(
            theta,
            y,
            batch,
            self.loss,
            &mut self.dq_taken,
            &mut self.per_sample,
        );
        td_errors(theta, y, b, &mut self.td);
        if batch.weights.is_empty() {
            return loss;
        }
        weight_terms(
            &batch.weights,
            &self.per_sample,
            theta.len() / b,
            &mut self.dq_taken,
        )
    }

    /// Step 4: `dQ` (`self.dq`): `dq_taken` at each sample's taken action, zeros elsewhere;
    /// back-propagated through the online network's last forward pass (on `batch.states`), the
    /// gradient clipped if configured, one Adam step. Returns the step's statistics: `loss`, the
    /// mean of `max_q_sum` and the gradient's global norm before clipping.
    fn backward_and_step(&mut self, batch: &Batch, loss: f32, max_q_sum: f32) -> StepStats {
        let k = self.head.atoms();
        scatter_rows(&self.dq_taken, batch, self.n_actions * k, k, &mut self.dq);
        self.online.zero_grad();
        self.online.backward(&batch.states, &self.dq, false);
        let grad_norm = match self.clip_norm {
            Some(max) => clip_grad_norm(&mut self.online, max),
            None => crate::optim::global_grad_norm(&self.online),
        };
        let weights_finite = self.adam.step_net(&mut self.online);
        StepStats {
            loss,
            mean_max_q: max_q_sum / batch.len() as f32,
            grad_norm,
            weights_finite,
        }
    }
}

/// Step 1's target pass made ahead, on another thread than the update's: a copy of a learner's
/// target network, and its head. With [`super::Config::act_while_learning`] the playing thread
/// makes the pass over the next update's batch while the current update runs, and the next
/// update takes it ([`Learner::train_step_with`]) instead of making it on its own critical path.
/// The copy must hold the target network's parameters as that update will see them: whoever
/// holds it [`syncs`](NextValues::sync) it when the target network changes, and drops a pass
/// made before.
pub struct NextValues {
    /// The copy of the target network.
    net: Sequential<f32>,
    /// The learner's head (an implicit quantile head sets the copy's target fractions).
    head: Box<dyn ValueHead>,
    /// An implicit quantile head's fractions (scratch).
    taus: Vec<f64>,
}

impl NextValues {
    /// A copy of the target network of `learner`, built from `config` as
    /// [`Learner::from_config`] builds it.
    pub fn new(config: &super::Config, learner: &Learner) -> Self {
        let head = Head::of(config);
        // Its values are overwritten at once; the draw touches no run stream.
        let rng = &mut <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(0);
        let (input, n_actions) = (config.input_shape(), learner.n_actions);
        let mut net = qnet(input, n_actions, head, &VarianceScaling::HE, rng);
        net.set_precision(config.precision);
        net.copy_params_from(learner.target());
        NextValues {
            net,
            head: value_head(&head, n_actions),
            taus: Vec::new(),
        }
    }

    /// Copies the target network's parameters into the copy (after the target changed).
    pub fn sync(&mut self, learner: &Learner) {
        self.net.copy_params_from(learner.target());
    }

    /// The target network's outputs at `batch`'s next states (step 1's pass) into `out`.
    pub fn compute(&mut self, batch: &Batch, out: &mut Vec<f32>) {
        out.clear();
        out.extend_from_slice(next_values(
            &*self.head,
            &mut self.net,
            batch,
            &mut self.taus,
        ));
    }
}

/// Step 1's forward pass: the target network's (`net`, or a copy of it) outputs at the batch's
/// next states, one row per state (an implicit quantile head's `N'` rows, at the batch's target
/// fractions) of `A·k` values; `taus` is scratch.
fn next_values<'n>(
    head: &dyn ValueHead, net: &'n mut Sequential<f32>, batch: &Batch, taus: &mut Vec<f64>,
) -> &'n [f32] {
    head.fractions(net, Pass::Next, batch, taus);
    net.infer(&batch.next_states).data()
}

/// Step 1 without the rule's own pass: the targets `y` (`[B, M]`) from the target network's
/// outputs at the next states (`out`, [`next_values`]), each state's split by the head into
/// `Q(s', ·)` (`[A]`) and the target samples `Z_j(s', ·)` (`[M, A]`), bootstrapped by `rule`
/// with `policy` (`[B, A]` or empty, [`TargetRule::policy`]); `q_next` and `z` are scratch.
#[allow(clippy::too_many_arguments)] // the step's inputs, then its scratch buffers
fn targets(
    head: &dyn ValueHead, rule: TargetRule, out: &[f32], batch: &Batch, policy: &[f32], gamma: f32,
    y: &mut Vec<f32>, [q_next, z]: [&mut Vec<f32>; 2],
) {
    y.clear();
    for (i, out) in out.chunks_exact(out.len() / batch.len()).enumerate() {
        head.q_values(head.next(out, z), q_next);
        let na = q_next.len();
        let t = Transition {
            r: batch.rewards[i],
            a: batch.actions[i],
            cont: if batch.dones[i] { 0.0 } else { 1.0 },
            discount: gamma.powi(batch.steps[i] as i32),
        };
        let policy = policy.get(i * na..(i + 1) * na).unwrap_or(&[]);
        rule.bootstrap(&t, q_next, policy, z, y);
    }
}

/// Step 2: the online network's forward pass over the states (at the batch's fractions, with
/// an implicit quantile head), `[B·R, A·k]`.
fn forward<'n>(
    head: &dyn ValueHead, online: &'n mut Sequential<f32>, batch: &Batch,
) -> &'n Tensor<f32> {
    head.fractions(online, Pass::Online, batch, &mut Vec::new());
    online.forward(&batch.states)
}

/// `θ`: the values of the taken actions from the online outputs `out` (each state's `R` rows of
/// `A·k` values: `k` per action), into `theta` (`[B, R·k]`); returns the sum over the batch of
/// `max_a Q(s, a)`; `q` is scratch.
fn taken(
    head: &dyn ValueHead, out: &[f32], batch: &Batch, na: usize, theta: &mut Vec<f32>,
    q: &mut Vec<f32>,
) -> f32 {
    let k = head.atoms();
    let mut max_q_sum = 0.0;
    theta.clear();
    for (i, out) in out.chunks_exact(out.len() / batch.len()).enumerate() {
        let a = batch.actions[i];
        for row in out.chunks_exact(na * k) {
            theta.extend_from_slice(&row[a * k..(a + 1) * k]);
        }
        head.q_values(out, q);
        max_q_sum += q[argmax(q)];
    }
    max_q_sum
}

/// `Q(s, ·)` of every state of `states` by `net` into `all` (`[B, A]`): a pass at the head's
/// policy fractions, each state's output reduced by [`ValueHead::q_values`] (`q` and `taus` are
/// scratch).
fn q_values(
    head: &dyn ValueHead, net: &mut Sequential<f32>, batch: &Batch, states: &Tensor<f32>,
    (q, taus): (&mut Vec<f32>, &mut Vec<f64>), all: &mut Vec<f32>,
) {
    head.policy_fractions(net, batch.len(), taus);
    let out = net.infer(states).data();
    all.clear();
    for out in out.chunks_exact(out.len() / batch.len()) {
        head.q_values(out, q);
        all.extend_from_slice(q);
    }
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

/// One transition as the target sees it: `R`, `a`, `1 − done` and `γ^m`.
struct Transition {
    r: f32,
    a: usize,
    cont: f32,
    discount: f32,
}

/// How the targets bootstrap the next state's value (step 1 of [`Learner::train_step`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum TargetRule {
    /// DQN's: `y_j = R + γ^m·(1 − done)·Z_j(s', a')` with `a' = argmax_a Q_target(s', a)`: the
    /// target network picks the action and evaluates it.
    Max,
    /// Double DQN (van Hasselt et al. 2016): `a' = argmax_a Q_online(s', a)`, evaluated by the
    /// target network, which curbs the max's overestimation.
    Double,
    /// Munchausen RL's soft target ([`Munchausen`]), which replaces the max.
    Munchausen(Munchausen),
}

impl TargetRule {
    /// The values the rule needs besides the target network's at `s'`, `[B, A]` (empty for the
    /// max), into `policy`: Double DQN's `Q_online(s', ·)`, whose greedy action the target
    /// evaluates; Munchausen's `Q_target(s, ·)`, whose policy gives the bonus (`q` and `taus`
    /// are scratch).
    #[allow(clippy::too_many_arguments)] // the rule's inputs, then its scratch and its output
    fn policy(
        self, head: &dyn ValueHead, online: &mut Sequential<f32>, target: &mut Sequential<f32>,
        batch: &Batch, q: &mut Vec<f32>, taus: &mut Vec<f64>, policy: &mut Vec<f32>,
    ) {
        let scratch = (q, taus);
        match self {
            TargetRule::Max => policy.clear(),
            TargetRule::Double => {
                q_values(head, online, batch, &batch.next_states, scratch, policy)
            }
            TargetRule::Munchausen(_) => {
                q_values(head, target, batch, &batch.states, scratch, policy)
            }
        }
    }

    /// One transition's targets, appended to `y`: `y_j` for each target sample `z_j`
    /// (`z`: `[M, A]`), from the target's `Q(s', ·)` (`q_next`) and the rule's `policy` row.
    fn bootstrap(
        self, t: &Transition, q_next: &[f32], policy: &[f32], z: &[f32], y: &mut Vec<f32>,
    ) {
        let na = q_next.len();
        let samples = z.chunks_exact(na);
        let at = |a_next: usize| {
            samples
                .clone()
                .map(move |z_j| t.r + t.discount * t.cont * z_j[a_next])
        };
        match self {
            TargetRule::Max => y.extend(at(argmax(q_next))),
            TargetRule::Double => y.extend(at(argmax(policy))),
            TargetRule::Munchausen(m) => {
                let r = t.r + m.bonus(policy, t.a);
                y.extend(samples.map(|z_j| r + t.discount * t.cont * m.soft_value(q_next, z_j)));
            }
        }
    }
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
    /// `(max q, τ·log Σ_a exp((q_a − max q)/τ))`, the two terms `τ·log π(a|s) = q_a − max q −
    /// τ·log Σ …` subtracts, for one state's values `q` (`[A]`).
    fn log_normaliser(&self, q: &[f32]) -> (f32, f32) {
        let max = q.iter().copied().fold(f32::NEG_INFINITY, f32::max);
        let sum: f32 = q.iter().map(|&v| ((v - max) / self.tau).exp()).sum();
        (max, self.tau * sum.ln())
    }

    /// `τ·log π(·|s)` for one state's values `q` (`[A]`), into `out`.
    pub fn scaled_log_policy(&self, q: &[f32], out: &mut [f32]) {
        let (max, log_sum) = self.log_normaliser(q);
        for (o, &v) in out.iter_mut().zip(q) {
            *o = v - max - log_sum;
        }
    }

    /// The bonus `α·clamp(τ·log π(a|s), l0, 0)` for the values `q` of `s` and the action `a`.
    pub fn bonus(&self, q: &[f32], a: usize) -> f32 {
        let (max, log_sum) = self.log_normaliser(q);
        self.alpha * (q[a] - max - log_sum).clamp(self.clip, 0.0)
    }

    /// The soft value `Σ_a π(a|s)·(v_a − τ·log π(a|s))` of a state whose policy comes from the
    /// values `q` and whose bootstrapped values are `v` (both `[A]`; `v = q` for M-DQN, a target
    /// sample's `Z_τ'` for M-IQN).
    pub fn soft_value(&self, q: &[f32], v: &[f32]) -> f32 {
        let (max, log_sum) = self.log_normaliser(q);
        q.iter()
            .zip(v)
            .map(|(&q, &v)| {
                let l = q - max - log_sum;
                (l / self.tau).exp() * (v - l)
            })
            .sum()
    }
}

/// `argmax_a Q(x, a)` for one state `x` (`[1, H, W, C]`) by `net`, built with `head`: a
/// batch-1 [`Sequential::infer`] at the head's policy fractions, its output reduced to `Q(x, ·)`
/// by the head's [`ValueHead::q_values`] as in the update (the first action on ties).
pub fn greedy(head: &Head, net: &mut Sequential<f32>, x: &Tensor<f32>, n_actions: usize) -> usize {
    let values = value_head(head, n_actions);
    values.policy_fractions(net, 1, &mut Vec::new());
    let mut q = Vec::with_capacity(n_actions);
    values.q_values(net.infer(x).data(), &mut q);
    argmax(&q)
}

/// `argmax_a Q(x_g, a)` for each of the `G` states of `x` (`[G, H, W, C]`: games played side by
/// side) by `net`, built with `head`, into `actions`: one batch-`G` [`Sequential::infer`], each
/// state's output reduced as [`greedy`] reduces its one (the first action on ties).
pub fn greedy_each(
    head: &Head, net: &mut Sequential<f32>, x: &Tensor<f32>, n_actions: usize,
    actions: &mut Vec<usize>,
) {
    let states = x.shape()[0];
    let values = value_head(head, n_actions);
    values.policy_fractions(net, states, &mut Vec::new());
    let out = net.infer(x).data();
    let mut q = Vec::with_capacity(n_actions);
    actions.clear();
    for row in out.chunks_exact(out.len() / states) {
        values.q_values(row, &mut q);
        actions.push(argmax(&q));
    }
}

/// The TD errors for prioritized replay, `b` samples: the mean of each sample's predictions
/// minus the mean of its targets (with one of each, `Q(s, a) − y`).
fn td_errors(q: &[f32], y: &[f32], b: usize, td: &mut Vec<f32>) {
    let (n, n_target) = (q.len() / b, y.len() / b);
    let pairs = q.chunks_exact(n).zip(y.chunks_exact(n_target));
    td.clear();
    td.extend(pairs.map(|(q, y)| mean(q) - mean(y)));
}

/// The mean of a slice (of one value, the value itself: the sum starts at −0).
pub(super) fn mean(x: &[f32]) -> f32 {
    x.iter().sum::<f32>() / x.len() as f32
}

/// The greedy action of one sample's outputs `[A, K]`: the largest Q-value (`K = 1`), or with a
/// quantile head the largest mean of its `K` quantiles (the expected return).
pub fn greedy_atoms(row: &[f32], k: usize) -> usize {
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
