//! PQN (Gallici et al. 2024, "Simplifying Deep Temporal Difference Learning"): Q-learning
//! without a replay memory or a target network, from short rollouts of several games played at
//! once, each rollout learnt from Q(λ) returns and then dropped.
//!
//! Read top to bottom, one call of [`PqnAgent::play_rollout`] is the whole algorithm (CleanRL's
//! `pqn_atari_envpool.py`), with the settings of [`Pqn`] and the run's [`Config`]:
//!
//! ```text
//! 1  start G games; compose each one's first frame; fill its stack with it
//!    repeat (one rollout)
//! 2      for t in 0 .. T:
//! 3          ε ← linear schedule(agent step); Q(s_t^g, ·) of all G games in one batch
//! 4          a^g ← random with probability ε, else argmax_a Q(s_t^g, a); keep max_a Q(s_t^g, a)
//! 5          play a^g in game g; store (s_t^g, a^g, r_t^g, done_t^g); a finished game starts again
//! 6      max_a Q(s_T^g, a): the values of the states the rollout ends in
//! 7      the Q(λ) returns G_t = r_t + γ(1 − done_t)·(λ·G_{t+1} + (1 − λ)·max_a Q(s_{t+1}, a)),
//!        G_T = max_a Q(s_T, a)
//! 8      E times: shuffle the G·T transitions; for each of M minibatches, regress Q(s, a)
//!        towards G (MSE or Huber) and take one optimizer step
//! ```
//!
//! The code marks these lines `ALGO 1` … `ALGO 8`. What makes it work without a target network
//! (the paper's argument): layer normalisation in the network (`layer_norm = true`) keeps the
//! bootstrapped values from running away, and the games played at once decorrelate a rollout
//! as a replay memory would. The values bootstrapped from are those the acting network gave
//! while it played (before this rollout's updates), so a rollout costs one forward pass per
//! transition to act and `E` forward and backward passes to learn, nothing more.
//!
//! The agent steps of the G games count one each; ε and the learning rate follow their
//! schedules over them. An episode's row goes out when its game ends ([`PqnAgent::play_episode`]
//! plays rollouts until one has), so a run's `metrics.csv` reads as a DQN run's.

use super::agent::{check_finite, stream, AgentState, Counters, EpisodeRow, GameSlot};
use super::config::Pqn;
use super::replay::write_state;
use super::{Batch, Config, Learner};
use crate::env::{Game, Observer, FRAME_LEN};
use crate::tensor::bf16::to_bf16;
use crate::tensor::Tensor;
use anyhow::{bail, Context};
use rand::seq::SliceRandom;
use rand::{Rng, RngCore};
use rand_chacha::ChaCha8Rng;
use std::collections::VecDeque;
use std::time::Instant;

/// The random streams of the games' emulator seeds: game `g` of a run with seed `s` plays with
/// the seed `stream(s, GAME_STREAMS | g).next_u64()`, game 0 with `s` itself (as a DQN run).
const GAME_STREAMS: u64 = 1 << 62;

/// The emulator seed of game `g` of a PQN run seeded `seed`.
pub fn game_seed(seed: u64, g: usize) -> u64 {
    if g == 0 {
        seed
    } else {
        stream(seed, GAME_STREAMS | g as u64).next_u64() >> 1
    }
}

/// The Q(λ) returns of a rollout of `T` steps of `G` games (Watkins's Q(λ) without trace
/// cutting, as PQN uses it), written into `returns` (`[T, G]`, row `t` the games' step `t`):
///
/// ```text
/// G_t = r_t + γ·(1 − done_t)·(λ·G_{t+1} + (1 − λ)·max_a Q(s_{t+1}, a)),   G_T = max_a Q(s_T, a)
/// ```
///
/// `rewards` and `dones` are `[T, G]`; `max_q` is `[T + 1, G]`: the acting network's
/// `max_a Q(s_t, a)` of every state of the rollout and of the states `s_T` it ends in. `λ = 0`
/// gives the one-step target `r_t + γ max_a Q(s_{t+1}, a)`, `λ = 1` the discounted return to the
/// rollout's end, bootstrapped there. `done_t` (the game over, or a lost life where those end
/// bootstrapping) cuts both the bootstrap and the return of the steps after it, which belong to
/// the next episode (or life).
///
/// # Panics
/// If the lengths disagree.
pub fn q_lambda_returns(
    rewards: &[f32], dones: &[bool], max_q: &[f32], games: usize, gamma: f32, lambda: f32,
    returns: &mut [f32],
) {
    let t_len = rewards.len() / games;
    assert!(
        rewards.len() == t_len * games
            && dones.len() == rewards.len()
            && returns.len() == rewards.len()
            && max_q.len() == (t_len + 1) * games,
        "q_lambda_returns: rewards, dones and returns [T, G], max_q [T + 1, G]"
    );
    for g in 0..games {
        let mut next_return = max_q[t_len * games + g];
        for t in (0..t_len).rev() {
            let i = t * games + g;
            let cont = if dones[i] { 0.0 } else { 1.0 };
            let next_q = max_q[i + games];
            next_return =
                rewards[i] + gamma * cont * (lambda * next_return + (1.0 - lambda) * next_q);
            returns[i] = next_return;
        }
    }
}

/// One game's episode in progress.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Player {
    /// Lives after the last step (none before the episode's first step).
    pub lives: Option<i32>,
    /// The episode's score so far (the game's rewards, unclipped).
    pub score: f64,
    /// Its agent steps so far.
    pub length: u64,
    /// The sums of the losses and of the mean `max_a Q` of the gradient steps taken during the
    /// episode, and their number (the row's `mean_loss` and `mean_max_q`).
    pub loss_sum: f64,
    /// See `loss_sum`.
    pub q_sum: f64,
    /// See `loss_sum`.
    pub n_train: u64,
}

impl Player {
    /// Counts a gradient step taken during the episode: its loss and mean `max_a Q`.
    pub(super) fn add_train_step(&mut self, s: &super::StepStats) {
        self.loss_sum += s.loss as f64;
        self.q_sum += s.mean_max_q as f64;
        self.n_train += 1;
    }

    /// The row of this episode, which ended at the agent step `counters` have just counted:
    /// its `episode` number, ε there and the wall time since the run began.
    pub(super) fn row(
        &self, episode: u64, counters: &Counters, epsilon: f32, wall_seconds: f64,
    ) -> EpisodeRow {
        EpisodeRow {
            episode,
            agent_steps: counters.agent_steps,
            frames: counters.frames,
            reward: self.score,
            length: self.length,
            epsilon,
            mean_loss: self.mean(self.loss_sum),
            mean_max_q: self.mean(self.q_sum),
            wall_seconds,
        }
    }

    /// The mean of a sum over the episode's gradient steps (NaN without any).
    fn mean(&self, sum: f64) -> f32 {
        if self.n_train > 0 {
            (sum / self.n_train as f64) as f32
        } else {
            f32::NAN
        }
    }
}

/// One rollout's transitions, `[T, G]` each (row `t` the games' step `t`).
struct Rollout {
    /// The states `s_t`: each one's `k` frames, oldest first (`k·88·80` bytes).
    states: Vec<u8>,
    actions: Vec<usize>,
    /// The learner's rewards (scaled, clipped, less any life penalty).
    rewards: Vec<f32>,
    /// Whether bootstrapping stops after the step.
    dones: Vec<bool>,
    /// `[T + 1, G]`: the acting network's `max_a Q(s_t, a)`, and at `T` the states the rollout
    /// ends in.
    max_q: Vec<f32>,
    /// The Q(λ) returns ([`q_lambda_returns`]).
    returns: Vec<f32>,
    /// The learning passes' shuffled order of the transitions, and one minibatch's returns.
    order: Vec<usize>,
    targets: Vec<f32>,
}

impl Rollout {
    fn new(pqn: &Pqn, state_len: usize) -> Self {
        let n = pqn.transitions();
        Rollout {
            states: vec![0; n * state_len],
            actions: vec![0; n],
            rewards: vec![0.0; n],
            dones: vec![false; n],
            max_q: vec![0.0; n + pqn.games],
            returns: vec![0.0; n],
            order: (0..n).collect(),
            targets: vec![0.0; pqn.minibatch()],
        }
    }
}

/// A PQN agent: `G` games, their observers, and one network that acts and learns.
pub struct PqnAgent<G: Game> {
    /// The run's configuration (with its `pqn` table).
    pub config: Config,
    /// PQN's settings (`config.pqn`).
    pub pqn: Pqn,
    /// The games, played side by side.
    pub games: Vec<G>,
    /// Frame composition and stacking, one per game.
    observers: Vec<Observer>,
    /// Each game's episode in progress.
    players: Vec<Player>,
    /// The network and the optimizer; no target network ([`Learner::without_target`]).
    pub learner: Learner,
    /// Progress: `episodes` counts the rows handed out.
    pub counters: Counters,
    /// ε-greedy coin flips and random actions.
    explore_rng: ChaCha8Rng,
    /// The shuffles of the rollouts' transitions.
    shuffle_rng: ChaCha8Rng,
    /// u8 pixel → network input, and its bf16 roundings (where the products run in bf16).
    table: [f32; 256],
    rounded: Option<[u16; 256]>,
    /// `[G, 88, 80, k]`: the acting input, every game's stack.
    input: Tensor<f32>,
    /// A minibatch (states inside conv1's padding, [`Batch::padded`]).
    batch: Batch,
    rollout: Rollout,
    /// Finished episodes' rows not yet handed out, oldest first.
    finished: VecDeque<EpisodeRow>,
}

impl<G: Game> PqnAgent<G> {
    /// A fresh agent: the network initialised from the config's seed (as a DQN agent's), every
    /// game started.
    ///
    /// # Errors
    /// If `config` has no `pqn` table, or `games` is not `pqn.games` games.
    pub fn new(config: Config, games: Vec<G>) -> anyhow::Result<Self> {
        let n_actions = games.first().map_or(0, |g| g.n_actions());
        let learner = Learner::from_config(&config, n_actions, &mut stream(config.seed, 1));
        let mut agent = Self::with_learner(config, games, learner, Counters::default())?;
        for (game, observer) in agent.games.iter_mut().zip(&mut agent.observers) {
            // ALGO 1: start each game; compose its first frame; fill its stack with it.
            game.reset();
            observer.reset(game);
        }
        Ok(agent)
    }

    /// An agent around a learner and counters; its games are not started.
    fn with_learner(
        config: Config, games: Vec<G>, learner: Learner, counters: Counters,
    ) -> anyhow::Result<Self> {
        let Some(pqn) = config.pqn else {
            bail!("a PQN agent needs the configuration's [pqn] table");
        };
        if games.len() != pqn.games {
            bail!(
                "PQN plays {} games side by side, and {} were given",
                pqn.games,
                games.len()
            );
        }
        if games.iter().any(|g| g.n_actions() != learner.n_actions()) {
            bail!(
                "every game must have the network's {} actions",
                learner.n_actions()
            );
        }
        let [h, w, k] = config.input_shape();
        let bf16 = crate::ops::plan::bf16_runs(config.precision);
        let table = config.normalization.table();
        Ok(PqnAgent {
            observers: (0..pqn.games)
                .map(|_| Observer::new(config.pipeline))
                .collect(),
            players: vec![Player::default(); pqn.games],
            rounded: bf16.then(|| std::array::from_fn(|v| to_bf16(table[v]))),
            table,
            input: Tensor::zeros(&[pqn.games, h, w, k]),
            batch: Batch {
                keep_bf16: bf16,
                ..Batch::with_border(
                    pqn.minibatch(),
                    [h, w, k],
                    super::Head::of(&config).input_border([h, w, k]),
                )
            },
            rollout: Rollout::new(&pqn, k * FRAME_LEN),
            finished: VecDeque::new(),
            explore_rng: stream(config.seed, 2),
            shuffle_rng: stream(config.seed, 3),
            learner,
            counters,
            games,
            pqn,
            config,
        })
    }

    /// Continues a run from a checkpoint: its learner and counters, the random generators, every
    /// game's observer, episode and saved state (`state`, as [`PqnAgent::state`] made it). The
    /// games must be built with the checkpoint's environment settings.
    pub fn resume(
        games: Vec<G>, config: Config, counters: Counters, learner: Learner, state: AgentState,
    ) -> anyhow::Result<Self> {
        let mut agent = Self::with_learner(config, games, learner, counters)?;
        let n = agent.pqn.games;
        if state.other_games.len() + 1 != n || state.players.len() != n {
            bail!("the saved state is not of the {n} games PQN plays");
        }
        let first = GameSlot {
            composite: state.composite,
            stack: state.stack,
            game: state.game,
        };
        let k = agent.config.pipeline.channels();
        for (g, slot) in std::iter::once(&first)
            .chain(&state.other_games)
            .enumerate()
        {
            match &slot.game {
                Some(saved) => agent.games[g]
                    .restore_state(saved)
                    .with_context(|| format!("cannot restore game {g}'s saved state"))?,
                None => agent.games[g].reset(),
            }
            if slot.composite.len() != FRAME_LEN || slot.stack.len() != k * FRAME_LEN {
                bail!("the saved observer of game {g} does not match the configuration");
            }
            let frames: Vec<&[u8]> = slot.stack.chunks_exact(FRAME_LEN).collect();
            agent.observers[g].restore(&slot.composite, &frames);
        }
        agent.players = state.players;
        agent.explore_rng = state.explore_rng;
        agent.shuffle_rng = state.sample_rng;
        agent.finished = state.finished.into();
        Ok(agent)
    }

    /// Everything besides the learner and counters that a checkpoint needs to continue this
    /// agent exactly, taken between rollouts (as [`PqnAgent::play_episode`] leaves it): game 0
    /// in the fields a DQN agent fills, the others in `other_games`, the shuffles' generator as
    /// `sample_rng`.
    pub fn state(&self) -> AgentState {
        let mut slots = self.games.iter().zip(&self.observers).map(|(game, o)| {
            let mut stack = vec![0; o.stack().len() * FRAME_LEN];
            copy_stack(o, &mut stack);
            GameSlot {
                composite: o.composer_frame().to_vec(),
                stack,
                game: game.save_state(),
            }
        });
        let first = slots.next().expect("at least one game");
        AgentState {
            explore_rng: self.explore_rng.clone(),
            sample_rng: self.shuffle_rng.clone(),
            composite: first.composite,
            stack: first.stack,
            game: first.game,
            other_games: slots.collect(),
            players: self.players.clone(),
            finished: self.finished.iter().copied().collect(),
        }
    }

    /// ε now.
    pub fn epsilon(&self) -> f32 {
        self.config.epsilon(self.counters.agent_steps)
    }

    /// Finished episodes whose rows have not been handed out.
    pub fn pending(&self) -> usize {
        self.finished.len()
    }

    /// The next finished episode's row, playing (and learning from) rollouts until a game ends
    /// one.
    ///
    /// # Errors
    /// If training diverges (as [`super::Agent::play_episode`]).
    pub fn play_episode(&mut self) -> anyhow::Result<EpisodeRow> {
        while self.finished.is_empty() {
            self.play_rollout()?;
        }
        let row = self.finished.pop_front().expect("a finished episode");
        self.counters.episodes += 1;
        Ok(row)
    }

    /// One rollout of every game, then learning from it. The lines marked `ALGO n` are the
    /// algorithm, numbered as in the module documentation.
    ///
    /// # Errors
    /// If training diverges: a gradient step gives a non-finite loss, gradient norm or weight.
    pub fn play_rollout(&mut self) -> anyhow::Result<()> {
        let start = Instant::now();
        let (n, t_len) = (self.pqn.games, self.pqn.rollout);
        let state_len = self.config.pipeline.channels() * FRAME_LEN;
        for t in 0..t_len {
            // ALGO 3: ε from the schedule; Q(s_t, ·) of every game in one batch.
            let eps = self.epsilon();
            self.act_values(t);
            for g in 0..n {
                let i = t * n + g;
                // ALGO 4: a random action with probability ε, else the greedy one (kept in
                // `actions` by `act_values`).
                if self.explore_rng.random::<f32>() < eps {
                    self.rollout.actions[i] = self.explore_rng.random_range(0..self.n_actions());
                }
                // ALGO 5: play it; store (s_t, a, r, done); a finished game starts again.
                let state = &mut self.rollout.states[i * state_len..(i + 1) * state_len];
                copy_stack(&self.observers[g], state);
                let r = self.games[g].step(self.rollout.actions[i]);
                self.observers[g].step(&self.games[g]);
                let player = &mut self.players[g];
                let lives_lost = player.lives.map_or(0, |l| l - r.lives);
                player.lives = Some(r.lives);
                player.score += r.reward as f64;
                player.length += 1;
                self.rollout.rewards[i] = self.config.learner_reward(r.reward, lives_lost);
                let over = r.terminal || r.truncated;
                // A truncated game ends bootstrapping too: the state after it is the next
                // game's first.
                self.rollout.dones[i] = over || (self.config.life_loss_terminal && lives_lost > 0);
                self.counters.agent_steps += 1;
                self.counters.frames += r.frames as u64;
                if over {
                    let wall = self.counters.wall_seconds + start.elapsed().as_secs_f64();
                    self.finish_episode(g, wall);
                }
            }
        }
        // ALGO 6: the values of the states the rollout ends in.
        self.act_values(t_len);
        // ALGO 7: the Q(λ) returns.
        let r = &mut self.rollout;
        q_lambda_returns(
            &r.rewards,
            &r.dones,
            &r.max_q,
            n,
            self.config.gamma as f32,
            self.pqn.lambda as f32,
            &mut r.returns,
        );
        // ALGO 8: E passes over the shuffled rollout, M minibatches each.
        self.learn()?;
        self.counters.wall_seconds += start.elapsed().as_secs_f64();
        Ok(())
    }

    /// The acting network's values of every game's current state: `max_a Q(s, a)` into row `t`
    /// of the rollout's `max_q` and, for `t < T`, the greedy actions into row `t` of its
    /// actions.
    fn act_values(&mut self, t: usize) {
        let (n, na) = (self.pqn.games, self.n_actions());
        let per = self.input.len() / n;
        for (observer, x) in self
            .observers
            .iter()
            .zip(self.input.data_mut().chunks_exact_mut(per))
        {
            observer.write_input(&self.table, x);
        }
        let q = self.learner.online.infer(&self.input).data();
        for (g, row) in q.chunks_exact(na).enumerate() {
            let best = super::argmax(row);
            self.rollout.max_q[t * n + g] = row[best];
            if t < self.pqn.rollout {
                self.rollout.actions[t * n + g] = best;
            }
        }
    }

    /// Learns from the rollout: `epochs` passes, each over a fresh shuffle of its transitions
    /// cut into `minibatches` minibatches, one regression step towards the Q(λ) returns each
    /// ([`Learner::regress_step`]).
    fn learn(&mut self) -> anyhow::Result<()> {
        let t = self.counters.agent_steps;
        self.learner.adam.lr = self.config.learning_rate(t) as f32;
        let mb = self.pqn.minibatch();
        let k = self.config.pipeline.channels();
        assert!(k <= 4, "states of at most 4 frames");
        let tables = (&self.table, self.rounded.as_ref());
        let r = &mut self.rollout;
        // Each rollout's shuffles start from the transitions in order.
        for (j, o) in r.order.iter_mut().enumerate() {
            *o = j;
        }
        for _ in 0..self.pqn.epochs {
            r.order.shuffle(&mut self.shuffle_rng);
            for picks in r.order.chunks_exact(mb) {
                for (b, &i) in picks.iter().enumerate() {
                    let state = &r.states[i * k * FRAME_LEN..(i + 1) * k * FRAME_LEN];
                    let mut frames: [&[u8]; 4] = [&[]; 4];
                    for (f, c) in frames.iter_mut().zip(state.chunks_exact(FRAME_LEN)) {
                        *f = c;
                    }
                    let border = self.batch.border;
                    write_state(&frames[..k], tables, border, b, &mut self.batch.states);
                    self.batch.actions[b] = r.actions[i];
                    r.targets[b] = r.returns[i];
                }
                let stats = self.learner.regress_step(&self.batch, &r.targets);
                self.counters.train_steps += 1;
                let episode = self.counters.episodes + self.finished.len() as u64 + 1;
                check_finite(&self.learner, &stats, t, self.counters.train_steps, episode)?;
                for p in &mut self.players {
                    p.add_train_step(&stats);
                }
            }
        }
        Ok(())
    }

    /// Ends game `g`'s episode: its row joins the finished ones, the game starts again.
    fn finish_episode(&mut self, g: usize, wall_seconds: f64) {
        let p = std::mem::take(&mut self.players[g]);
        let episode = self.counters.episodes + self.finished.len() as u64 + 1;
        let row = p.row(episode, &self.counters, self.epsilon(), wall_seconds);
        self.finished.push_back(row);
        self.games[g].reset();
        self.observers[g].reset(&self.games[g]);
    }

    fn n_actions(&self) -> usize {
        self.learner.n_actions()
    }
}

/// Copies an observer's frame stack into `out` (`k·88·80` bytes), oldest frame first.
pub(super) fn copy_stack(observer: &Observer, out: &mut [u8]) {
    let stack = observer.stack();
    for (i, to) in out.chunks_exact_mut(FRAME_LEN).enumerate() {
        to.copy_from_slice(stack.get(i));
    }
}
