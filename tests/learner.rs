//! The DQN learner and agent against values worked out by hand: a Q-network with fixed, small
//! weights whose every Q-value is a line through the sum of the state's pixels, hand-built
//! batches, and a scripted game. Every number is a short binary fraction, so the library's
//! arithmetic is exact and the checks are equalities.

mod common;

use invaders::dqn::{
    greedy_atoms, Agent, Batch, Config, Head, Learner, TargetRule, FLAG_ACTED, FLAG_DONE,
};
use invaders::env::{Game, StepResult, FRAME_LEN};
use invaders::layers::loss::LossKind;
use invaders::layers::Sequential;
use invaders::optim::global_grad_norm;

/// A 4×4 single-frame input: conv1 (8×8, stride 4, SAME) sees the whole image in one window.
const INPUT: [usize; 3] = [4, 4, 1];
/// Actions.
const A: usize = 3;

/// Sets a network built by [`Learner::new`] for [`INPUT`] to compute
/// `Q(s, a) = b[a] + w[a]·relu(Σ s)`: each convolution adds up its input's first channel over
/// all taps into its first output channel (the other channels are zero, as is every bias),
/// dense1 passes that to its first unit, and dense2 reads the unit with weights `w` and biases
/// `b`. Every other weight is zero.
fn set_q(net: &mut Sequential<f32>, w: [f32; A], b: [f32; A]) {
    for p in net.params_mut() {
        let shape = p.value.shape().to_vec();
        let v = p.value.data_mut();
        v.fill(0.0);
        match p.name.as_str() {
            "conv1.weight" | "conv2.weight" | "conv3.weight" => {
                let (taps, cin, cout) = (shape[0] * shape[1], shape[2], shape[3]);
                for t in 0..taps {
                    v[t * cin * cout] = 1.0;
                }
            }
            "dense1.weight" => v[0] = 1.0,
            "dense2.weight" => v[..A].copy_from_slice(&w),
            "dense2.bias" => v.copy_from_slice(&b),
            _ => {}
        }
    }
}

/// The Q-values of [`set_q`]'s network for a state whose pixels sum to `sum`, by hand.
fn q(w: [f32; A], b: [f32; A], sum: f32) -> [f32; A] {
    std::array::from_fn(|a| b[a] + w[a] * sum.max(0.0))
}

/// One transition: the sums of `s` and `s'`, the action, the return `R`, done, and the steps
/// `m` from `s` to `s'`.
#[derive(Clone, Copy)]
struct T {
    s: f32,
    a: usize,
    r: f32,
    next: f32,
    done: bool,
    m: u32,
}

impl T {
    /// A one-step transition, not done, from a state of sum `s` by action `a` with return `r`
    /// to a state of sum `next`.
    fn new(s: f32, a: usize, r: f32, next: f32) -> T {
        T {
            s,
            a,
            r,
            next,
            done: false,
            m: 1,
        }
    }
}

/// A batch of [`INPUT`] states, each image's 16 pixels equal (`sum / 16`).
fn batch(ts: &[T]) -> Batch {
    let mut b = Batch::new(ts.len(), INPUT);
    for (i, t) in ts.iter().enumerate() {
        b.states.data_mut()[i * 16..][..16].fill(t.s / 16.0);
        b.next_states.data_mut()[i * 16..][..16].fill(t.next / 16.0);
        b.actions[i] = t.a;
        b.rewards[i] = t.r;
        b.dones[i] = t.done;
        b.steps[i] = t.m;
    }
    b
}

/// A learner with the online network `(w, b)` and the target network `(wt, bt)`.
fn learner(gamma: f32, online: ([f32; A], [f32; A]), target: ([f32; A], [f32; A])) -> Learner {
    let mut l = Learner::new(INPUT, A, 1e-3, gamma, &mut common::rng(1));
    set_q(&mut l.online, online.0, online.1);
    set_q(l.target_mut(), target.0, target.1);
    l
}

/// The gradient of dense2's bias after the last step: `∂L/∂Q(s, a)` summed over the batch.
fn bias_grad(l: &Learner) -> Vec<f32> {
    let p = l.online.params().find(|p| p.name == "dense2.bias").unwrap();
    p.grad.data().to_vec()
}

/// The one-step TD target `y = r + γ·(1 − done)·max_a Q_target(s', a)` against a hand
/// computation, the network's Q-values against the hand formula, the MSE loss and its gradient,
/// which reaches only the taken actions (`2(Q(s, a) − y)/B`), and the mean of `max_a Q(s, a)`.
#[test]
fn td_targets_match_a_hand_computation() {
    let (w, b) = ([1.0, 0.0, -0.5], [0.0, 0.5, 1.0]);
    let (wt, bt) = ([1.0, -1.0, 0.5], [0.25, 2.0, 0.0]);
    let mut l = learner(0.5, (w, b), (wt, bt));
    let ts = [
        T::new(2.0, 0, 1.0, 1.0),
        T::new(1.0, 2, -1.0, 4.0),
        T {
            done: true,
            ..T::new(0.5, 1, 0.5, 3.0)
        },
        T::new(3.0, 2, 2.0, 0.5),
    ];
    let batch = batch(&ts);
    // The construction: Q_target(s') is the hand formula's.
    let got = l.target_mut().forward(&batch.next_states).data().to_vec();
    let want: Vec<f32> = ts.iter().flat_map(|t| q(wt, bt, t.next)).collect();
    assert_eq!(got, want, "Q_target(s', ·)");
    // By hand: max Q_target(s') = 1.25, 4.25, (done), 1.5.
    let y = [1.0 + 0.5 * 1.25, -1.0 + 0.5 * 4.25, 0.5, 2.0 + 0.5 * 1.5];
    let stats = l.train_step(&batch);
    assert_eq!(l.targets(), y);
    // Q(s, a) = 2, 0.5, 0.5, −0.5; the loss and its gradient at the taken actions only.
    let qa = [2.0, 0.5, 0.5, -0.5];
    let loss = qa
        .iter()
        .zip(&y)
        .map(|(q, y)| (q - y) * (q - y))
        .sum::<f32>()
        / 4.0;
    assert_eq!(stats.loss, loss);
    let mut grad = [0.0f32; A];
    for (t, (q, y)) in ts.iter().zip(qa.iter().zip(&y)) {
        grad[t.a] += 2.0 * (q - y) / 4.0;
    }
    assert_eq!(bias_grad(&l), grad);
    // max_a Q(s, a): 2, 1, 0.75, 3.
    assert_eq!(stats.mean_max_q, (2.0 + 1.0 + 0.75 + 3.0) / 4.0);
}

/// Double DQN with online and target networks that disagree on `argmax Q(s', ·)`: the target
/// is `Q_target(s', argmax_a Q_online(s', a))`, not `max_a Q_target(s', a)`; without it, the
/// plain maximum. Two transitions whose online argmaxes differ (actions 0 and 2).
#[test]
fn double_dqn_evaluates_the_online_argmax_with_the_target() {
    let online = ([1.0, -1.0, 0.0], [0.0, 0.0, 0.5]);
    let target = ([-1.0, 1.0, 0.0], [0.0, 0.0, -3.0]);
    let ts = [
        // Σ s' = 2: Q_online = (2, −2, 0.5) → 0; Q_target = (−2, 2, −3).
        T::new(1.0, 1, 1.0, 2.0),
        // Σ s' = 0.25: Q_online = (0.25, −0.25, 0.5) → 2; Q_target = (−0.25, 0.25, −3).
        T::new(1.0, 0, 0.0, 0.25),
    ];
    for (double, y) in [
        (true, [1.0 + 0.5 * -2.0, 0.5 * -3.0]),
        (false, [1.0 + 0.5 * 2.0, 0.5 * 0.25]),
    ] {
        let mut l = learner(0.5, online, target);
        l.rule = rule(double);
        l.train_step(&batch(&ts));
        assert_eq!(l.targets(), y, "double_dqn = {double}");
    }
}

/// n-step targets `y = R + γ^m·(1 − done)·max_a Q_target(s', a)` with `Batch::steps`: the
/// same return and `s'` bootstrapped with `γ`, `γ²` and `γ³`, and not at all when done.
#[test]
fn n_step_targets_discount_by_the_steps_taken() {
    let mut l = learner(0.5, ([0.0; A], [0.0; A]), ([1.0, 0.0, 0.0], [0.0; A]));
    let t = |m, done| T {
        s: 1.0,
        a: 0,
        r: 1.5,
        next: 4.0,
        done,
        m,
    };
    l.train_step(&batch(&[t(1, false), t(2, false), t(3, false), t(3, true)]));
    assert_eq!(
        l.targets(),
        [1.5 + 0.5 * 4.0, 1.5 + 0.25 * 4.0, 1.5 + 0.125 * 4.0, 1.5]
    );
}

/// Huber inside the train step: a TD error of 10 gives the gradient `δ/B = 1/B`, clamped (MSE
/// would give `2·10/B`), a TD error of 0.25 its own value over `B`; the loss is
/// `mean(|d| − ½)` beyond δ and `mean(d²/2)` within.
#[test]
fn huber_clamps_the_gradient_of_a_large_td_error() {
    // Q(s, 0) = Σ s; the target network is all zeros, so y = r.
    let ts = [T::new(10.0, 0, 0.0, 1.0), T::new(1.0, 1, 1.25, 1.0)];
    let online = ([1.0, 1.0, 0.0], [0.0; A]);
    for (loss, grad, value) in [
        (LossKind::Huber, [0.5, -0.125, 0.0], (9.5 + 0.03125) / 2.0),
        (LossKind::Mse, [10.0, -0.25, 0.0], (100.0 + 0.0625) / 2.0),
    ] {
        let mut l = learner(0.5, online, ([0.0; A], [0.0; A]));
        l.loss = loss;
        let stats = l.train_step(&batch(&ts));
        assert_eq!(l.targets(), [0.0, 1.25]);
        assert_eq!(bias_grad(&l), grad, "{loss:?}");
        assert_eq!(stats.loss, value, "{loss:?}");
    }
}

/// Gradient clipping by global norm inside the learner: the step reports the norm before
/// clipping, and leaves gradients scaled by `max / norm` (global norm `max`, same direction)
/// when the norm exceeds `max`, untouched when it does not.
#[test]
fn the_learner_clips_gradients_by_global_norm() {
    let ts = [T::new(10.0, 0, 0.0, 1.0), T::new(2.0, 1, 3.0, 1.0)];
    let batch = batch(&ts);
    let run = |clip: Option<f32>| {
        let mut l = learner(0.5, ([1.0, 1.0, 0.0], [0.5; A]), ([0.0; A], [0.0; A]));
        l.clip_norm = clip;
        let stats = l.train_step(&batch);
        let grads: Vec<Vec<f32>> = l.online.params().map(|p| p.grad.data().to_vec()).collect();
        (stats.grad_norm, grads, global_grad_norm(&l.online))
    };
    let (norm, free, after) = run(None);
    assert!(
        norm > 2.0,
        "the unclipped norm {norm} is large enough to clip"
    );
    assert_eq!(after, norm);
    let (clipped_norm, clipped, after) = run(Some(2.0));
    assert_eq!(clipped_norm, norm, "the norm before clipping");
    assert!(
        (after - 2.0).abs() <= 1e-5,
        "global norm after clipping: {after}"
    );
    let scale = 2.0 / norm;
    for (c, f) in clipped.iter().flatten().zip(free.iter().flatten()) {
        assert!(
            (c - f * scale).abs() <= 1e-6 * f.abs(),
            "{c} vs {f}·{scale}"
        );
    }
    let (_, loose, _) = run(Some(norm * 2.0));
    assert!(loose == free, "under the limit nothing changes");
}

/// The configuration's switches reach the learner: Double DQN (or Munchausen, which replaces
/// it), the loss, the clipping norm (0 meaning none), γ and Adam's ε.
#[test]
fn the_learner_takes_its_switches_from_the_config() {
    let mut c = common::vanilla_config();
    for (double, loss, clip) in [(true, LossKind::Huber, 2.5), (false, LossKind::Mse, 0.0)] {
        c.double_dqn = double;
        c.loss = loss;
        c.clip_grad_norm = clip;
        c.gamma = 0.75;
        c.adam_epsilon = 1e-4;
        let l = Learner::from_config(&c, 4, &mut common::rng(2));
        assert_eq!(
            (l.rule, l.loss, l.clip_norm, l.gamma, l.adam.eps),
            (
                rule(double),
                loss,
                (clip > 0.0).then_some(clip as f32),
                0.75,
                1e-4
            )
        );
    }
    // Munchausen's soft target has no max for Double DQN to pick: it replaces both.
    c.double_dqn = true;
    c.munchausen_alpha = 0.9;
    let l = Learner::from_config(&c, 4, &mut common::rng(2));
    assert_eq!(l.rule, TargetRule::Munchausen(c.munchausen().unwrap()));
}

/// A game that plays episodes of scripted lengths with a fixed reward per step, shows the
/// step count as its frame, ends each episode as terminal, and records the actions it gets.
struct Scripted {
    lengths: Vec<u32>,
    episode: usize,
    step: u32,
    reward: f32,
    actions: Vec<usize>,
    frame: Vec<u8>,
}

impl Scripted {
    fn new(lengths: &[u32], reward: f32) -> Self {
        Scripted {
            lengths: lengths.to_vec(),
            episode: 0,
            step: 0,
            reward,
            actions: Vec::new(),
            frame: vec![0; FRAME_LEN],
        }
    }
}

impl Game for Scripted {
    fn n_actions(&self) -> usize {
        2
    }
    fn reset(&mut self) {
        self.step = 0;
        self.frame.fill(0);
    }
    fn step(&mut self, action: usize) -> StepResult {
        self.actions.push(action);
        self.step += 1;
        self.frame.fill((self.step as u8).wrapping_mul(20));
        let len = self.lengths[self.episode % self.lengths.len()];
        let terminal = self.step >= len;
        if terminal {
            self.episode += 1;
        }
        common::toy_step(self.reward, terminal, false)
    }
    fn observation(&self) -> &[u8] {
        &self.frame
    }
}

/// A small single-frame configuration that never trains and acts greedily.
fn agent_config() -> Config {
    let mut c = common::small_config(64, 2, 1_000_000, 1_000_000, 5);
    (c.epsilon_start, c.epsilon_end) = (0.0, 0.0);
    c
}

/// An agent of [`agent_config`] changed by `set`, playing [`Scripted`] episodes of `lengths`
/// with `reward` a step.
fn scripted_agent(lengths: &[u32], reward: f32, set: impl FnOnce(&mut Config)) -> Agent<Scripted> {
    let mut c = agent_config();
    set(&mut c);
    Agent::new(c, Scripted::new(lengths, reward))
}

/// Makes `net` prefer `action` whatever the state: every weight zero, dense2's bias one-hot.
fn prefer(net: &mut Sequential<f32>, action: usize) {
    for p in net.params_mut() {
        p.value.fill_zero();
        if p.name == "dense2.bias" {
            p.value.data_mut()[action] = 1.0;
        }
    }
}

/// Whether the online and target networks hold the same weights.
fn same_networks<G: Game>(agent: &Agent<G>) -> bool {
    agent
        .learner
        .online
        .params()
        .zip(agent.learner.target().params())
        .all(|(a, b)| a.value == b.value)
}

/// With `clip_rewards` a reward of 5 is stored (and so sampled) as 1, without it as 5; the
/// episode's score is the game's, unclipped, either way.
#[test]
fn clipped_rewards_are_stored_clipped() {
    for (clip, stored) in [(true, 1.0), (false, 5.0)] {
        let mut agent = scripted_agent(&[3], 5.0, |c| c.clip_rewards = clip);
        let row = agent.play_episode().unwrap();
        assert_eq!(row.reward, 15.0, "the score is unclipped");
        let (_, _, rewards, flags) = agent.replay.parts();
        let acted: Vec<f32> = (0..flags.len())
            .filter(|&i| flags[i] & FLAG_ACTED != 0)
            .map(|i| rewards[i])
            .collect();
        assert_eq!(acted, [stored; 3], "clip_rewards = {clip}");
    }
}

/// The target network is copied from the online one every `target_update` agent steps: equal
/// right after steps 10 and 20, different at steps 9 and 19 (the online network trained since).
/// Episodes of 9 and 1 steps end exactly there.
#[test]
fn the_target_network_is_refreshed_every_target_update_steps() {
    let mut agent = scripted_agent(&[9, 1], 0.5, |c| {
        c.learning_starts = 4;
        c.train_every = 1;
        c.target_update = 10;
    });
    assert!(same_networks(&agent), "the target starts as a copy");
    for (steps, equal) in [(9, false), (10, true), (19, false), (20, true)] {
        agent.play_episode().unwrap();
        assert_eq!(agent.counters.agent_steps, steps);
        assert_eq!(same_networks(&agent), equal, "after agent step {steps}");
    }
    assert!(agent.counters.train_steps >= 15, "{:?}", agent.counters);
}

/// ε's linear schedule from 1 to 0.1 over 100 steps: 1 at step 0, 0.55 half-way, just above
/// 0.1 one step before the end, 0.1 at the end and after it; the agent reads it at its own
/// step count, and acts on it: with a network that prefers action 1, only that action at
/// ε = 0, both actions at ε = 1.
#[test]
fn epsilon_follows_its_schedule_and_the_agent_uses_it() {
    let mut c = agent_config();
    c.epsilon_start = 1.0;
    c.epsilon_end = 0.1;
    c.epsilon_decay_steps = 100;
    assert_eq!(c.epsilon(0), 1.0);
    assert!((c.epsilon(50) - 0.55).abs() < 1e-6, "{}", c.epsilon(50));
    assert!(
        c.epsilon(99) > 0.1 && c.epsilon(99) < 0.11,
        "{}",
        c.epsilon(99)
    );
    assert_eq!(c.epsilon(100), 0.1);
    assert_eq!(c.epsilon(10_000), 0.1);
    let mut agent = Agent::new(c.clone(), Scripted::new(&[20], 0.0));
    for t in [0, 50, 100, 150] {
        agent.counters.agent_steps = t;
        assert_eq!(agent.epsilon(), c.epsilon(t));
    }
    agent.counters.agent_steps = 0;
    let row = agent.play_episode().unwrap();
    assert_eq!(
        row.epsilon,
        c.epsilon(20),
        "the row's ε is at the episode's end"
    );
    for (eps, both) in [(0.0, false), (1.0, true)] {
        let mut agent = scripted_agent(&[40], 0.0, |c| {
            (c.epsilon_start, c.epsilon_end) = (eps, eps)
        });
        prefer(&mut agent.learner.online, 1);
        agent.play_episode().unwrap();
        let a = &agent.game.actions;
        let mixed = a.iter().any(|&x| x != 1);
        assert_eq!(mixed, both, "ε = {eps}: actions {a:?}");
    }
}

/// The learning rate's schedule: constant without `learning_rate_end`; with it, 1e-3 until
/// step 100, linear to 1e-4 at step 200 (5.5e-4 half-way), 1e-4 after; and the agent hands
/// Adam the rate of the step it trains at (the last train step of a 40-step episode that
/// trains every step from step 10 is at step 40).
#[test]
fn the_learning_rate_follows_its_schedule_and_adam_gets_it() {
    let mut c = agent_config();
    c.learning_rate = 1e-3;
    assert_eq!(c.learning_rate(123_456), 1e-3);
    c.learning_rate_end = Some(1e-4);
    c.learning_rate_decay = [100, 200];
    for (t, lr) in [
        (0, 1e-3),
        (100, 1e-3),
        (150, 5.5e-4),
        (199, 1.09e-4),
        (200, 1e-4),
        (10_000, 1e-4),
    ] {
        assert!(
            (c.learning_rate(t) - lr).abs() < 1e-12,
            "step {t}: {}",
            c.learning_rate(t)
        );
    }
    c.learning_rate_decay = [0, 80];
    c.train_every = 1;
    c.learning_starts = 10;
    let mut agent = Agent::new(c.clone(), Scripted::new(&[40], 0.0));
    agent.play_episode().unwrap();
    assert_eq!(agent.counters.agent_steps, 40);
    assert_eq!(agent.learner.adam.lr, c.learning_rate(40) as f32);
    assert!(
        (agent.learner.adam.lr - 5.5e-4).abs() < 1e-9,
        "{}",
        agent.learner.adam.lr
    );
}

/// `act_with_target_network` (the notebook's swap) picks actions with the target network:
/// online and target networks that prefer different actions (biases only), ε = 0, no training
/// and no copy, so every action shows which network chose it.
#[test]
fn acting_with_the_target_network_uses_the_target() {
    for (switch, action) in [(false, 0), (true, 1)] {
        let mut agent = scripted_agent(&[5], 0.0, |c| c.act_with_target_network = switch);
        prefer(&mut agent.learner.online, 0);
        prefer(agent.learner.target_mut(), 1);
        agent.play_episode().unwrap();
        assert_eq!(
            agent.game.actions, [action; 5],
            "act_with_target_network = {switch}"
        );
    }
}

/// `fake_terminal_transition` (the notebook's extra transition) appends the final state again
/// after each episode, acted on with the last action, reward 0, marked done; without it the
/// memory holds the episode's own entries only.
#[test]
fn the_fake_terminal_transition_repeats_the_last_state() {
    for fake in [false, true] {
        let mut agent = scripted_agent(&[3], 2.0, |c| c.fake_terminal_transition = fake);
        agent.play_episode().unwrap();
        // Entries: the first frame, the three steps' frames, and with the switch the repeat.
        assert_eq!(agent.replay.written(), 4 + fake as u64);
        let (frames, actions, rewards, flags) = agent.replay.parts();
        let frame = |i: usize| &frames[i * FRAME_LEN..][..FRAME_LEN];
        assert_eq!(
            flags[2] & FLAG_DONE,
            FLAG_DONE,
            "the game's own last step is done"
        );
        if fake {
            assert_eq!(flags[3] & (FLAG_ACTED | FLAG_DONE), FLAG_ACTED | FLAG_DONE);
            assert_eq!((actions[3], rewards[3]), (agent.game.actions[2] as u8, 0.0));
            assert_eq!(frame(4), frame(3), "the final state again");
        } else {
            assert_eq!(flags[3] & FLAG_ACTED, 0, "the last frame is not acted on");
        }
    }
}

/// Double DQN's rule if `double`, else the max.
fn rule(double: bool) -> TargetRule {
    if double {
        TargetRule::Double
    } else {
        TargetRule::Max
    }
}

/// A learner built with `head` whose outputs are constants (dense2's biases; every weight zero):
/// `online` and `target` are dense2's biases of the two networks.
fn constant_learner(head: Head, double: bool, online: &[f32], target: &[f32]) -> Learner {
    let mut l = Learner::with_head(INPUT, A, head, 1e-3, 0.5, &mut common::rng(1));
    l.rule = rule(double);
    for (which, b) in [(0, online), (1, target)] {
        let net = match which {
            0 => &mut l.online,
            _ => l.target_mut(),
        };
        for p in net.params_mut() {
            p.value.data_mut().fill(0.0);
            if p.name == "dense2.bias" {
                p.value.data_mut().copy_from_slice(b);
            }
        }
    }
    l
}

/// A learner with a quantile head of 2 quantiles per action whose outputs are constants:
/// `online` and `target` are `[A, 2]` quantiles, action by action.
fn quantile_learner(double: bool, online: [f32; 6], target: [f32; 6]) -> Learner {
    let head = Head {
        hidden: 8,
        dueling: false,
        atoms: 2,
        iqn: None,
        layer_norm: false,
        ..Head::ARTICLE
    };
    constant_learner(head, double, &online, &target)
}

/// QR-DQN by hand. Online quantiles (τ = 1/4, 3/4) per action: [0, 2], [1, 1], [−1, 5] (means
/// 1, 1, 2); the target's: [4, 8], [0, 0], [1, 3] (means 6, 0, 2). Transition: action 0, R = 1,
/// γ = 0.5, one step. Double DQN bootstraps the online network's best mean (action 2) with the
/// target's quantiles: T = 1 + 0.5·[1, 3] = [1.5, 2.5]; without it, the target's best mean
/// (action 0): T = [3, 5]; a terminal transition: T = [1, 1]. The loss of θ = [0, 2] against
/// T = [1.5, 2.5]: θ_0 is below both samples (weight τ_0 = 1/4; Huber 1 and 2), θ_1 is above
/// 1.5 (weight 1/4, Huber 1/8) and below 2.5 (weight 3/4, Huber 1/8): L = (1/2)(0.75 + 0.125)
/// = 0.4375. The TD error (for priorities) is mean θ − mean T = 1 − 2. Acting picks the best
/// mean, action 2.
#[test]
fn quantile_targets_and_loss_match_a_hand_computation() {
    let online = [0.0, 2.0, 1.0, 1.0, -1.0, 5.0];
    let target = [4.0, 8.0, 0.0, 0.0, 1.0, 3.0];
    let t = T::new(1.0, 0, 1.0, 2.0);
    let mut l = quantile_learner(true, online, target);
    let stats = l.train_step(&batch(&[t]));
    assert_eq!(l.targets(), [1.5, 2.5]);
    assert_eq!(stats.loss, 0.4375);
    assert_eq!(stats.mean_max_q, 2.0);
    assert_eq!(l.td_errors(), [-1.0]);
    let mut l = quantile_learner(false, online, target);
    l.train_step(&batch(&[t]));
    assert_eq!(l.targets(), [3.0, 5.0]);
    let mut l = quantile_learner(true, online, target);
    l.train_step(&batch(&[T { done: true, ..t }]));
    assert_eq!(l.targets(), [1.0, 1.0]);
    assert_eq!(greedy_atoms(&online, 2), 2);
    assert_eq!(greedy_atoms(&target, 2), 0);
}

/// A learner with an implicit quantile head (embedding after dense1) whose outputs are
/// constants at every fraction: `Z_τ(s, a) = online[a]` for the online network and `target[a]`
/// for the target, whatever `τ`.
fn iqn_learner(double: bool, online: [f32; 3], target: [f32; 3]) -> Learner {
    let head = Head {
        hidden: 8,
        dueling: false,
        atoms: 1,
        iqn: Some(invaders::dqn::Iqn {
            embedding: 4,
            merge: invaders::dqn::IqnMerge::Hidden,
            samples: 2,
            target_samples: 3,
            policy_samples: 2,
        }),
        layer_norm: false,
        ..Head::ARTICLE
    };
    constant_learner(head, double, &online, &target)
}

/// IQN by hand. Online `Z` per action [1, 2, 0], the target's [4, 0, 1], at any fraction.
/// Transition: action 0, R = 1, γ = 0.5, one step; fractions τ = [0.1, 0.6] (N = 2) and three
/// target fractions (N' = 3). Without Double DQN the target's best mean (action 0) is
/// bootstrapped: every T_j = 1 + 0.5·4 = 3; with it the online network's best (action 1):
/// T_j = 1 + 0.5·0 = 1; terminal: T_j = 1. The loss of θ_i = 1 against T_j = 3: u = 2 > 1, so
/// h = 1.5 with weight τ_i (u ≥ 0): L = Σ_i (1/3)·Σ_j τ_i·1.5 = 1.5·(0.1 + 0.6) = 1.05, and
/// ∂L/∂θ_i = −τ_i (the Huber slope 1, over 3 samples thrice). With Munchausen (α = 0.9,
/// τ = 1, l0 = −1): π = softmax of the target's values; the bonus 0.9·max(log π(0|s), −1)
/// and the soft value Σ π·(q − log π) of s' (the same values, s' = s here).
#[test]
fn iqn_targets_and_loss_match_a_hand_computation() {
    let t = T::new(1.0, 0, 1.0, 2.0);
    let with_taus = |ts: &[T]| {
        let mut b = batch(ts);
        b.taus = vec![0.1, 0.6];
        b.target_taus = vec![0.2, 0.5, 0.9];
        b
    };
    let (online, target) = ([1.0, 2.0, 0.0], [4.0, 0.0, 1.0]);
    let mut l = iqn_learner(false, online, target);
    let stats = l.train_step(&with_taus(&[t]));
    assert_eq!(l.targets(), [3.0, 3.0, 3.0]);
    assert!((stats.loss - 1.05).abs() < 1e-6, "{}", stats.loss);
    assert_eq!(stats.mean_max_q, 2.0);
    assert_eq!(l.td_errors(), [1.0 - 3.0]);
    let mut l = iqn_learner(true, online, target);
    l.train_step(&with_taus(&[t]));
    assert_eq!(l.targets(), [1.0, 1.0, 1.0]);
    l.train_step(&with_taus(&[T { done: true, ..t }]));
    assert_eq!(l.targets(), [1.0, 1.0, 1.0]);

    let mut l = iqn_learner(true, online, target);
    l.rule = TargetRule::Munchausen(invaders::dqn::Munchausen {
        alpha: 0.9,
        tau: 1.0,
        clip: -1.0,
    });
    l.train_step(&with_taus(&[t]));
    let q = [4.0f64, 0.0, 1.0];
    let lse = q.iter().map(|v| v.exp()).sum::<f64>().ln();
    let log_pi: Vec<f64> = q.iter().map(|v| v - lse).collect();
    let soft: f64 = log_pi.iter().zip(&q).map(|(l, v)| l.exp() * (v - l)).sum();
    let expected = 1.0 + 0.9 * log_pi[0].max(-1.0) + 0.5 * soft;
    for &y in l.targets() {
        assert!((y as f64 - expected).abs() < 1e-5, "{y} vs {expected}");
    }
}

/// Munchausen's pieces by hand, at τ = 0.5: `τ log π = q − max q − τ log Σ exp((q − max q)/τ)`,
/// the bonus clipped to [l0, 0], and the soft value; a tiny τ makes the soft value the max.
#[test]
fn munchausen_pieces_match_a_hand_computation() {
    let m = invaders::dqn::Munchausen {
        alpha: 0.9,
        tau: 0.5,
        clip: -1.0,
    };
    let q = [1.0f32, 3.0, 2.0];
    let mut out = [0.0f32; 3];
    m.scaled_log_policy(&q, &mut out);
    let z: f64 = [1.0f64, 3.0, 2.0]
        .iter()
        .map(|v| ((v - 3.0) / 0.5).exp())
        .sum();
    for (o, v) in out.iter().zip([1.0f64, 3.0, 2.0]) {
        assert!((*o as f64 - (v - 3.0 - 0.5 * z.ln())).abs() < 1e-6);
    }
    // τ log π(0) ≈ −2.06: clipped to −1.
    assert!((m.bonus(&q, 0) + 0.9).abs() < 1e-6, "α·l0");
    assert!((m.bonus(&q, 1) - 0.9 * out[1]).abs() < 1e-6);
    let pi: Vec<f32> = out.iter().map(|l| (l / 0.5).exp()).collect();
    let soft: f32 = pi
        .iter()
        .zip(&q)
        .zip(&out)
        .map(|((p, v), l)| p * (v - l))
        .sum();
    assert!((m.soft_value(&q, &q) - soft).abs() < 1e-5);
    let cold = invaders::dqn::Munchausen { tau: 1e-4, ..m };
    assert!((cold.soft_value(&q, &q) - 3.0).abs() < 1e-3);
}

/// M-DQN by hand: the soft target `y = r + α·clamp(τ log π(a|s), l0, 0) + γ^m (1 − done)
/// Σ_a' π(a'|s')(q'(s', a') − τ log π(a'|s'))`, with `π` the softmax of the target network's
/// values over τ, of `s` for the bonus and of `s'` for the soft value (no Double DQN: the soft
/// target replaces the max).
#[test]
fn munchausen_dqn_targets_match_a_hand_computation() {
    let (w, b) = ([1.0, 0.0, -0.5], [0.0, 0.5, 1.0]);
    let (wt, bt) = ([1.0, -1.0, 0.5], [0.25, 2.0, 0.0]);
    let mut l = learner(0.5, (w, b), (wt, bt));
    let m = invaders::dqn::Munchausen {
        alpha: 0.9,
        tau: 0.5,
        clip: -1.0,
    };
    l.rule = TargetRule::Munchausen(m);
    let ts = [
        T::new(2.0, 0, 1.0, 1.0),
        T {
            m: 2,
            ..T::new(1.0, 2, -1.0, 4.0)
        },
        T {
            done: true,
            ..T::new(0.5, 1, 0.5, 3.0)
        },
    ];
    l.train_step(&batch(&ts));
    let log_pi = |q: [f32; A]| -> Vec<f64> {
        let max = q.iter().fold(f64::NEG_INFINITY, |m, &v| m.max(v as f64));
        let z: f64 = q.iter().map(|&v| ((v as f64 - max) / 0.5).exp()).sum();
        q.iter().map(|&v| v as f64 - max - 0.5 * z.ln()).collect()
    };
    for (t, &y) in ts.iter().zip(l.targets()) {
        let now = log_pi(q(wt, bt, t.s));
        let qn = q(wt, bt, t.next);
        let next = log_pi(qn);
        let soft: f64 = next
            .iter()
            .zip(qn)
            .map(|(l, v)| (l / 0.5).exp() * (v as f64 - l))
            .sum();
        let cont = if t.done { 0.0 } else { 1.0 };
        let expected =
            t.r as f64 + 0.9 * now[t.a].clamp(-1.0, 0.0) + 0.5f64.powi(t.m as i32) * cont * soft;
        assert!((y as f64 - expected).abs() < 1e-5, "{y} vs {expected}");
    }
}
