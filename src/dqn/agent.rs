//! The DQN loop: act ε-greedily, remember, learn, refresh the target network.
//!
//! Read top to bottom, one episode of [`Agent::play_episode`] is the whole algorithm (Mnih et al.
//! 2015, Algorithm 1) with the article's hyperparameters from [`Config`]:
//!
//! ```text
//! 1  reset the game; compose the first frame; fill the stack with it; store it
//!    repeat
//! 2      ε ← linear schedule(agent step)
//! 3      a ← random action with probability ε, else argmax_a Q_online(stack, a)
//! 4      play a (2–4 emulator frames); compose the step's frame; push it on the stack
//! 5      store (a, r, done, new frame) in the replay memory
//! 6      every `train_every` steps after `learning_starts`: one gradient step on a sampled batch
//! 7      every `target_update` steps: copy the online network into the target network
//! 8  until the game is over or the step limit is hit
//! ```
//!
//! The code marks these lines `ALGO 1` … `ALGO 8`. One switch beyond the algorithm, off in
//! every preset, sits beside ALGO 7: at the agent steps `reset_dense_at` lists, the layers after
//! the convolutions are drawn afresh ([`Learner::reset_dense`]). Another changes when ALGO 6
//! runs, not what it computes: with [`Config::act_while_learning`] each update runs on the
//! pool's other threads while this one plays the steps through the next update's (ALGO 2–5)
//! with the parameters from before it, samples the next update's batch and makes its target
//! pass, and ALGO 7 catches up on those steps once the update has landed.
//!
//! With [`Config::games`] above 1 the agent plays that many games side by side
//! ([`Agent::with_games`]): each pass of the loop plays one agent step of every game (ALGO 2–5
//! for all of them, their greedy actions from one forward pass and the emulators stepped in
//! parallel, each game storing into its own lane of the replay memory), then ALGO 6 and 7 for
//! each of those agent steps in turn; a game whose episode ends starts its next at once (ALGO 1).

use super::acting::greedy;
use super::{Batch, Config, Head, Learner, NextValues, Replay, StepStats};
use crate::env::{Game, Observer, StepResult, FRAME_LEN};
use crate::layers::init::VarianceScaling;
use crate::layers::Sequential;
use crate::tensor::Tensor;
use anyhow::{bail, Context};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use std::collections::VecDeque;
use std::time::Instant;

mod games;

const HE: VarianceScaling = VarianceScaling::HE;

/// Progress counters of a run.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Counters {
    /// Episodes finished.
    pub episodes: u64,
    /// Agent steps (actions chosen).
    pub agent_steps: u64,
    /// Emulator frames.
    pub frames: u64,
    /// Gradient steps.
    pub train_steps: u64,
    /// Training wall time so far, in seconds.
    pub wall_seconds: f64,
}

/// Where an agent's wall time went, in seconds, summed over its agent steps since it was built:
/// what `invaders bench` reports as each core's shares. Timing only; not saved in a checkpoint.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct LoopTimes {
    /// ε and the action (ALGO 2–3): the acting network's forward pass, on the playing thread.
    pub acting: f64,
    /// The emulator and the frame pipeline (ALGO 4), on the playing thread.
    pub emulator: f64,
    /// Storing the transition (ALGO 5), on the playing thread.
    pub storing: f64,
    /// Sampling each update's minibatch (ALGO 6's batch), on the playing thread.
    pub sampling: f64,
    /// With [`Config::act_while_learning`]: the next update's target pass (step 1 of ALGO 6's
    /// gradient step, [`super::NextValues`]), made by the playing thread beside the update
    /// before it.
    pub target_pass: f64,
    /// The updates (ALGO 6's gradient step), start to end: on every thread of the pool when
    /// they take turns with play; beside the play with [`Config::act_while_learning`].
    pub update: f64,
    /// With [`Config::act_while_learning`]: the playing thread's time from the end of its block
    /// to the update's end (waiting for it, or working on it with the pool).
    pub joining: f64,
}

impl LoopTimes {
    /// The time spent since `before` (an earlier reading of the same agent's).
    pub fn since(&self, before: &LoopTimes) -> LoopTimes {
        LoopTimes {
            acting: self.acting - before.acting,
            emulator: self.emulator - before.emulator,
            storing: self.storing - before.storing,
            sampling: self.sampling - before.sampling,
            target_pass: self.target_pass - before.target_pass,
            update: self.update - before.update,
            joining: self.joining - before.joining,
        }
    }
}

/// Seconds from `t` to now.
fn secs(t: Instant) -> f64 {
    t.elapsed().as_secs_f64()
}

/// What an agent needs, besides its learner, counters and replay memory, to continue exactly.
#[derive(Clone, Debug, PartialEq)]
pub struct AgentState {
    /// ε-greedy coin flips and random actions.
    pub explore_rng: ChaCha8Rng,
    /// Minibatch sampling.
    pub sample_rng: ChaCha8Rng,
    /// The composer's latest composite frame (88·80 bytes).
    pub composite: Vec<u8>,
    /// The frame stack, oldest first (`k`·88·80 bytes).
    pub stack: Vec<u8>,
    /// The game's saved state, if it can be saved.
    pub game: Option<Vec<u8>>,
    /// PQN's, or a DQN agent's with [`Config::games`] above 1 (else empty): the games after the
    /// first, each as the fields above hold the first ([`super::PqnAgent`]).
    pub other_games: Vec<GameSlot>,
    /// The same agents': every game's episode in progress.
    pub players: Vec<super::Player>,
    /// The same agents': finished episodes whose rows have not been handed out yet, oldest
    /// first.
    pub finished: Vec<EpisodeRow>,
}

/// One game's part of an [`AgentState`]: its observer and its saved state.
#[derive(Clone, Debug, PartialEq)]
pub struct GameSlot {
    /// The composer's latest composite frame (88·80 bytes).
    pub composite: Vec<u8>,
    /// The frame stack, oldest first (`k`·88·80 bytes).
    pub stack: Vec<u8>,
    /// The game's saved state, if it can be saved.
    pub game: Option<Vec<u8>>,
}

/// One row of a run's `metrics.csv`.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct EpisodeRow {
    /// Episode number, from 1.
    pub episode: u64,
    /// Agent steps since the start of the run, at the end of this episode.
    pub agent_steps: u64,
    /// Emulator frames since the start of the run.
    pub frames: u64,
    /// The episode's score (unclipped rewards).
    pub reward: f64,
    /// Agent steps in this episode.
    pub length: u64,
    /// ε at the end of the episode.
    pub epsilon: f32,
    /// Mean loss of this episode's gradient steps (NaN if none).
    pub mean_loss: f32,
    /// Mean of `max_a Q(s, a)` over this episode's gradient steps (NaN if none).
    pub mean_max_q: f32,
    /// Training wall time since the start of the run, in seconds.
    pub wall_seconds: f64,
}

impl EpisodeRow {
    /// The CSV header.
    pub const HEADER: &'static str =
        "episode,agent_steps,emulator_frames,reward,length,epsilon,mean_loss,mean_max_q,wall_seconds";

    /// The row as CSV.
    pub fn csv(&self) -> String {
        format!(
            "{},{},{},{},{},{:.6},{:.6},{:.6},{:.3}",
            self.episode,
            self.agent_steps,
            self.frames,
            self.reward,
            self.length,
            self.epsilon,
            self.mean_loss,
            self.mean_max_q,
            self.wall_seconds
        )
    }
}

/// The random streams of the resets of `reset_dense_at`, one per agent step `t`:
/// `RESET_STREAMS | t`, apart from the initialisation's (1) and the episodes' (2, 3, …).
const RESET_STREAMS: u64 = 1 << 63;

/// Random streams of a run, all derived from its seed.
pub(super) fn stream(seed: u64, id: u64) -> ChaCha8Rng {
    let mut r = ChaCha8Rng::seed_from_u64(seed);
    r.set_stream(id);
    r
}

/// The [`Player`] of an agent's fields: a macro, so that each field is borrowed on its own and
/// the learner, the batch and the acting network stay free for the update.
macro_rules! player {
    ($agent:expr, $metrics:expr) => {
        Player {
            config: &$agent.config,
            game: &mut $agent.game,
            observer: &mut $agent.observer,
            replay: &mut $agent.replay,
            counters: &mut $agent.counters,
            explore_rng: &mut $agent.explore_rng,
            table: &$agent.table,
            input: &mut $agent.input,
            metrics: $metrics,
            times: &mut $agent.times,
        }
    };
}

/// What one agent step touches besides the networks, borrowed from an [`Agent`].
struct Player<'a, G> {
    config: &'a Config,
    game: &'a mut G,
    observer: &'a mut Observer,
    replay: &'a mut Replay,
    counters: &'a mut Counters,
    explore_rng: &'a mut ChaCha8Rng,
    table: &'a [f32; 256],
    input: &'a mut Tensor<f32>,
    metrics: &'a mut EpisodeMetrics,
    times: &'a mut LoopTimes,
}

/// An agent step played: its action, and whether the episode ended with it.
#[derive(Clone, Copy, Debug)]
struct Played {
    action: usize,
    ended: bool,
}

impl<G: Game> Player<'_, G> {
    /// ALGO 2–5: one agent step, acting with `net`; `lives` are the lives after the last step
    /// (none before the episode's first). Counts the step.
    fn step(&mut self, net: &mut Sequential<f32>, lives: &mut Option<i32>) -> Played {
        let t0 = Instant::now();
        // ALGO 2: ε from the linear schedule of the agent step.
        let eps = self.config.epsilon(self.counters.agent_steps);
        // ALGO 3: a random action with probability ε, else argmax_a Q(stack, a).
        let n_actions = self.game.n_actions();
        let action = if self.explore_rng.random::<f32>() < eps {
            self.explore_rng.random_range(0..n_actions)
        } else {
            let head = Head::of(self.config);
            greedy(net, &head, self.observer, self.table, self.input, n_actions)
        };
        let t1 = Instant::now();
        // ALGO 4: play it; compose the step's frame; push it on the stack.
        let r = self.game.step(action);
        let frame = self.observer.step(&*self.game);
        let t2 = Instant::now();
        // ALGO 5: store (a, r, done, new frame). Rewards scaled and clipped (to [-1, 1] in
        // the Nature DQN) if so configured, less `life_penalty` per life lost; done ends the
        // bootstrapping: the game is over, or (if so configured) a life was lost.
        let lives_lost = lives.map_or(0, |l| l - r.lives);
        let reward = self.config.learner_reward(r.reward, lives_lost);
        *lives = Some(r.lives);
        let done = r.terminal || (self.config.life_loss_terminal && lives_lost > 0);
        self.replay.push_step(action, reward, done, frame);
        self.count(&r);
        self.times.acting += (t1 - t0).as_secs_f64();
        self.times.emulator += (t2 - t1).as_secs_f64();
        self.times.storing += secs(t2);
        Played {
            action,
            ended: r.terminal || r.truncated,
        }
    }

    /// ALGO 2–5 for each agent step up to agent step `through`, acting with `net`, stopping
    /// early if the episode ends; returns the last step played, if any.
    fn play_through(
        &mut self, through: u64, net: &mut Sequential<f32>, lives: &mut Option<i32>,
    ) -> Option<Played> {
        let mut last = None;
        while self.counters.agent_steps < through {
            let step = self.step(net, lives);
            last = Some(step);
            if step.ended {
                break;
            }
        }
        last
    }

    /// Counts one agent step: its reward, length and emulator frames.
    fn count(&mut self, r: &StepResult) {
        self.metrics.score += r.reward as f64;
        self.metrics.length += 1;
        self.counters.agent_steps += 1;
        self.counters.frames += r.frames as u64;
    }
}

/// A DQN agent playing and learning one game.
pub struct Agent<G: Game> {
    /// The run's configuration.
    pub config: Config,
    /// The game.
    pub game: G,
    /// Frame composition and stacking for acting.
    pub observer: Observer,
    /// The replay memory.
    pub replay: Replay,
    /// Networks and optimizer.
    pub learner: Learner,
    /// Progress.
    pub counters: Counters,
    /// ε-greedy coin flips and random actions.
    explore_rng: ChaCha8Rng,
    /// Minibatch sampling.
    sample_rng: ChaCha8Rng,
    /// u8 pixel → network input.
    table: [f32; 256],
    /// `[1, 88, 80, k]`: the acting input.
    input: Tensor<f32>,
    /// The minibatch buffers.
    batch: Batch,
    /// With [`Config::act_while_learning`]: the network the agent acts with while an update
    /// runs, a copy of the online network from before it.
    acting: Option<Sequential<f32>>,
    /// With [`Config::act_while_learning`]: the next update's minibatch, sampled while the
    /// update before it runs.
    ahead: Option<Batch>,
    /// With [`Config::act_while_learning`]: a copy of the target network, with which the playing
    /// thread makes the next update's target pass over `ahead` beside the update before it.
    next: Option<NextValues>,
    /// That pass's outputs for `ahead` and for `batch` (empty where it was not made: the update
    /// then makes it).
    ahead_values: Vec<f32>,
    batch_values: Vec<f32>,
    /// With [`Config::games`] above 1: the games after the first (`game`), each with its
    /// observer, and every game's episode in progress (the first's first).
    others: Vec<(G, Observer)>,
    players: Vec<super::Player>,
    /// With [`Config::games`] above 1: finished episodes' rows not yet handed out, oldest first.
    finished: VecDeque<EpisodeRow>,
    /// With [`Config::games`] above 1: `[G, H, W, k]`, every game's stack for one acting pass,
    /// and the actions it gives.
    inputs: Tensor<f32>,
    actions: Vec<usize>,
    /// Where the wall time went.
    pub times: LoopTimes,
}

impl<G: Game> Agent<G> {
    /// A fresh agent: networks initialised from the config's seed, empty replay memory.
    ///
    /// # Panics
    /// If the config plays several games side by side ([`Agent::with_games`] starts those).
    pub fn new(config: Config, game: G) -> Self {
        assert_eq!(config.games, 1, "Agent::with_games starts several games");
        let learner = Learner::from_config(&config, game.n_actions(), &mut stream(config.seed, 1));
        Self::with_learner(config, game, learner, Counters::default())
    }

    /// A fresh agent playing `games` side by side ([`Config::games`] of them; with one, as
    /// [`Agent::new`]): networks initialised from the config's seed, empty replay memory, and
    /// with more than one game every game started (ALGO 1).
    ///
    /// # Errors
    /// If `games` is not `config.games` games, or their action counts differ.
    pub fn with_games(config: Config, games: Vec<G>) -> anyhow::Result<Self> {
        check_games(&config, &games)?;
        let n_actions = games[0].n_actions();
        let learner = Learner::from_config(&config, n_actions, &mut stream(config.seed, 1));
        let mut agent = Self::with_learner_games(config, games, learner, Counters::default());
        for g in 0..agent.players.len() {
            agent.start(g);
        }
        Ok(agent)
    }

    /// An agent that continues from a learner and counters (a checkpoint).
    pub fn with_learner(config: Config, game: G, learner: Learner, counters: Counters) -> Self {
        Self::with_learner_games(config, vec![game], learner, counters)
    }

    /// [`Agent::with_learner`] for `games` (checked by the caller); the games are not started.
    fn with_learner_games(
        config: Config, games: Vec<G>, learner: Learner, counters: Counters,
    ) -> Self {
        let input = config.input_shape();
        let n = games.len();
        let mut games = games.into_iter();
        let game = games.next().expect("at least one game");
        let others: Vec<(G, Observer)> =
            games.map(|g| (g, Observer::new(config.pipeline))).collect();
        let batch = || Batch {
            keep_bf16: crate::ops::plan::bf16_runs(config.precision),
            ..Batch::with_border(
                config.batch_size,
                input,
                Head::of(&config).input_border(input),
            )
        };
        Agent {
            observer: Observer::new(config.pipeline),
            replay: config.new_replay(),
            table: config.normalization.table(),
            input: Tensor::zeros(&[1, input[0], input[1], input[2]]),
            batch: batch(),
            ahead: config.act_while_learning.then(batch),
            next: config
                .act_while_learning
                .then(|| NextValues::new(&config, &learner)),
            ahead_values: Vec::new(),
            batch_values: Vec::new(),
            others,
            players: if n > 1 {
                vec![super::Player::default(); n]
            } else {
                Vec::new()
            },
            finished: VecDeque::new(),
            inputs: Tensor::zeros(&[n, input[0], input[1], input[2]]),
            actions: Vec::new(),
            acting: config.act_while_learning.then(|| {
                // Its values are overwritten before each use; the draw touches no run stream.
                let rng = &mut ChaCha8Rng::seed_from_u64(0);
                let mut net = super::qnet(input, game.n_actions(), Head::of(&config), &HE, rng);
                net.set_precision(config.precision);
                net
            }),
            explore_rng: stream(config.seed, 2 + 2 * counters.episodes),
            sample_rng: stream(config.seed, 3 + 2 * counters.episodes),
            learner,
            counters,
            game,
            config,
            times: LoopTimes::default(),
        }
    }

    /// Continues a run from a checkpoint: its learner and counters, every random generator, the
    /// observer, the game's state (if saved) and `replay` (if saved; else an empty memory).
    /// `game` must be built with the checkpoint's environment settings.
    pub fn resume(
        game: G, config: Config, counters: Counters, learner: Learner, state: AgentState,
        replay: Option<Replay>,
    ) -> anyhow::Result<Self> {
        Self::resume_games(vec![game], config, counters, learner, state, replay)
    }

    /// [`Agent::resume`] for the [`Config::games`] games played side by side, each built with the
    /// checkpoint's environment settings (and seeds, [`super::game_seed`]): each game's
    /// observer, saved state and episode in progress, and the finished episodes' rows not yet
    /// handed out.
    pub fn resume_games(
        games: Vec<G>, config: Config, counters: Counters, learner: Learner, state: AgentState,
        replay: Option<Replay>,
    ) -> anyhow::Result<Self> {
        check_games(&config, &games)?;
        if learner.n_actions() != games[0].n_actions() {
            bail!(
                "the checkpoint's network has {} actions, the game {}",
                learner.n_actions(),
                games[0].n_actions()
            );
        }
        let n = games.len();
        let players = if n > 1 { n } else { 0 };
        if state.other_games.len() + 1 != n || state.players.len() != players {
            bail!("the saved state is not that of a DQN agent playing {n} games");
        }
        if n == 1 && !state.finished.is_empty() {
            bail!("the saved state holds episodes a one-game agent cannot have pending");
        }
        let mut agent = Self::with_learner_games(config, games, learner, counters);
        if let Some(r) = replay {
            if r.capacity() != agent.replay.capacity()
                || r.frames_per_state() != agent.replay.frames_per_state()
                || r.lanes() != agent.replay.lanes()
            {
                bail!("the saved replay memory does not match the configuration");
            }
            agent.replay = r;
        }
        if let Some(g) = &state.game {
            agent
                .game
                .restore_state(g)
                .context("cannot restore the game's saved state")?;
        }
        let k = agent.config.pipeline.channels();
        if state.composite.len() != FRAME_LEN || state.stack.len() != k * FRAME_LEN {
            bail!("the saved observer does not match the configuration");
        }
        let frames: Vec<&[u8]> = state.stack.chunks_exact(FRAME_LEN).collect();
        agent.observer.restore(&state.composite, &frames);
        for (g, (slot, (game, observer))) in
            state.other_games.iter().zip(&mut agent.others).enumerate()
        {
            let g = g + 1;
            match &slot.game {
                Some(saved) => game
                    .restore_state(saved)
                    .with_context(|| format!("cannot restore game {g}'s saved state"))?,
                // A game that cannot be saved starts afresh (as PQN's; the run is then not exact).
                None => game.reset(),
            }
            if slot.composite.len() != FRAME_LEN || slot.stack.len() != k * FRAME_LEN {
                bail!("the saved observer of game {g} does not match the configuration");
            }
            let frames: Vec<&[u8]> = slot.stack.chunks_exact(FRAME_LEN).collect();
            observer.restore(&slot.composite, &frames);
        }
        agent.players = state.players;
        agent.finished = state.finished.into();
        agent.explore_rng = state.explore_rng;
        agent.sample_rng = state.sample_rng;
        Ok(agent)
    }

    /// Everything besides the learner, counters and replay that a checkpoint needs to continue
    /// this agent exactly.
    pub fn state(&self) -> AgentState {
        let stack = self.observer.stack();
        let slot = |game: &G, o: &Observer| {
            let mut stack = vec![0; o.stack().len() * FRAME_LEN];
            super::pqn::copy_stack(o, &mut stack);
            GameSlot {
                composite: o.composer_frame().to_vec(),
                stack,
                game: game.save_state(),
            }
        };
        AgentState {
            explore_rng: self.explore_rng.clone(),
            sample_rng: self.sample_rng.clone(),
            composite: self.observer.composer_frame().to_vec(),
            stack: (0..stack.len())
                .flat_map(|i| stack.get(i).to_vec())
                .collect(),
            game: self.game.save_state(),
            other_games: self.others.iter().map(|(g, o)| slot(g, o)).collect(),
            players: self.players.clone(),
            finished: self.finished.iter().copied().collect(),
        }
    }

    /// Finished episodes whose rows have not been handed out (only with several games).
    pub fn pending(&self) -> usize {
        self.finished.len()
    }

    /// ε now.
    pub fn epsilon(&self) -> f32 {
        self.config.epsilon(self.counters.agent_steps)
    }

    /// `argmax_a Q(current stack, a)` with the acting network (the online one, or the lagged
    /// target network if the config reproduces the notebook's swap).
    pub fn greedy_action(&mut self) -> usize {
        let net = if self.config.act_with_target_network {
            self.learner.target_mut()
        } else {
            &mut self.learner.online
        };
        greedy(
            net,
            &Head::of(&self.config),
            &self.observer,
            &self.table,
            &mut self.input,
            self.game.n_actions(),
        )
    }

    /// Plays one episode, learning as it goes, and returns its metrics row. The lines marked
    /// `ALGO n` are the algorithm, numbered as in the module documentation; everything else is
    /// bookkeeping (counters, metrics, the divergence guard), in functions of its own.
    ///
    /// With [`Config::act_while_learning`], ALGO 6's update runs beside the agent steps that
    /// follow it through the next update's (`Agent::learn_while_acting`), and ALGO 7 then
    /// catches up on each of them.
    ///
    /// # Errors
    /// If training diverges: a gradient step gives a non-finite loss, gradient norm or weight.
    /// The error names the agent step and the train step; the agent is then unusable (its
    /// weights are not finite), and nothing has been saved.
    pub fn play_episode(&mut self) -> anyhow::Result<EpisodeRow> {
        if !self.players.is_empty() {
            return self.play_games();
        }
        let start = Instant::now();
        let mut metrics = EpisodeMetrics::default();
        // ALGO 1: reset the game; compose the first frame; fill the stack with it; store it.
        self.game.reset();
        let first = self.observer.reset(&self.game);
        self.replay.push_start(first);
        let mut lives: Option<i32> = None;
        let last_action = loop {
            // ALGO 2-5: ε, an action, play it, store it ([`Player::step`]).
            let net = if self.config.act_with_target_network {
                self.learner.target_mut()
            } else {
                &mut self.learner.online
            };
            let t = self.counters.agent_steps + 1;
            let mut last = player!(self, &mut metrics).step(net, &mut lives);
            // ALGO 6: every `train_every` steps after `learning_starts`, one gradient step on a
            // sampled batch. (With `act_while_learning`, beside the agent steps that follow:
            // `Agent::learn_while_acting`, which says where ALGO 7 has caught up to.)
            let mut caught_up = t;
            if self.train_due(t) && self.config.act_while_learning && !last.ended {
                (last, caught_up) = self.learn_while_acting(t, &mut lives, &mut metrics)?;
            } else if self.train_due(t) {
                self.sample_batch();
                let stats = self.train_step(t);
                self.landed(&stats, t, &mut metrics)?;
            }
            // ALGO 7: every `target_update` steps, copy the online network into the target
            // ([`Agent::refresh_target`], for each step played since).
            self.refresh_target(caught_up..=self.counters.agent_steps);
            // ALGO 8: until the game is over or the step limit is hit.
            if last.ended {
                break last.action;
            }
        };
        if self.config.fake_terminal_transition {
            self.push_fake_terminal(last_action);
        }
        Ok(self.finish_episode(start, &metrics))
    }

    /// ALGO 6's batch: sampled from the replay memory (with an implicit quantile head, its
    /// fractions drawn too).
    fn sample_batch(&mut self) {
        let start = Instant::now();
        let (config, table) = (&self.config, &self.table);
        sample(
            config,
            &mut self.replay,
            &mut self.sample_rng,
            table,
            &mut self.batch,
        );
        // A new batch: the update makes its target pass.
        self.batch_values.clear();
        self.times.sampling += secs(start);
    }

    /// ALGO 6's gradient step on the sampled batch, at the learning rate of agent step `t`.
    fn train_step(&mut self, t: u64) -> StepStats {
        let start = Instant::now();
        self.learner.adam.lr = self.config.learning_rate(t) as f32;
        let values = (!self.batch_values.is_empty()).then_some(&self.batch_values[..]);
        let stats = self.learner.train_step_with(&self.batch, values);
        self.times.update += secs(start);
        stats
    }

    /// After an update at agent step `t` has landed: the sampled transitions' new priorities,
    /// the count, the divergence guard and the episode's loss statistics.
    fn landed(
        &mut self, stats: &StepStats, t: u64, metrics: &mut EpisodeMetrics,
    ) -> anyhow::Result<()> {
        self.replay
            .update_priorities(&self.batch.entries, self.learner.td_errors());
        self.counters.train_steps += 1;
        self.check_finite(stats, t)?;
        metrics.add_train_step(stats);
        for p in &mut self.players {
            p.add_train_step(stats);
        }
        Ok(())
    }

    /// ALGO 7 (and beside it the resets of `reset_dense_at`) for each agent step in `steps`.
    /// Returns whether the target network changed.
    fn refresh_target(&mut self, steps: std::ops::RangeInclusive<u64>) -> bool {
        let mut copied = false;
        for t in steps {
            // ALGO 7: every `target_update` steps, copy the online network into the target.
            if t.is_multiple_of(self.config.target_update) {
                self.learner.update_target();
                copied = true;
            }
            // Not the algorithm: a reset of the dense layers, if `reset_dense_at` lists `t`.
            if self.config.reset_dense_at.binary_search(&t).is_ok() {
                self.reset_dense(t);
            }
        }
        copied
    }

    /// ALGO 6 beside ALGO 2–5, from the update at agent step `t` on. Each update is spawned
    /// into the pool ([`rayon::in_place_scope`]) while this thread plays the block of agent steps
    /// through the next update's (`train_every` of them, fewer if the episode ends), acting with
    /// a copy of the online network made before the update, samples the next update's batch
    /// and makes that update's target pass with a copy of the target network
    /// ([`NextValues`]); then it joins the update. ALGO 7 catches up on the steps before the
    /// next update, which then starts the same way, until a block ends the episode (an update
    /// due at its last step then runs alone). Returns the last step played and the first step
    /// ALGO 7 has not reached.
    ///
    /// The schedule depends on `train_every` alone, and every kernel's result on its inputs
    /// alone, so a run's results do not depend on the thread count; with one thread each
    /// block is played first, then its update.
    fn learn_while_acting(
        &mut self, mut t: u64, lives: &mut Option<i32>, metrics: &mut EpisodeMetrics,
    ) -> anyhow::Result<(Played, u64)> {
        self.sample_batch();
        // The copy of the target network as this chain's first update finds it.
        let next_net = self.next.as_mut().expect("built for act_while_learning");
        next_net.sync(&self.learner);
        loop {
            self.learner.adam.lr = self.config.learning_rate(t) as f32;
            let acting = self.acting.as_mut().expect("built for act_while_learning");
            acting.copy_params_from(&self.learner.online);
            let through = t + self.config.train_every;
            let (learner, batch) = (&mut self.learner, &self.batch);
            let values = (!self.batch_values.is_empty()).then_some(&self.batch_values[..]);
            let ahead = self.ahead.as_mut().expect("built for act_while_learning");
            let next_net = self.next.as_mut().expect("built for act_while_learning");
            let ahead_values = &mut self.ahead_values;
            let sample_rng = &mut self.sample_rng;
            let mut player = player!(self, metrics);
            let (mut stats, mut update_secs, mut play_secs) = (None, 0.0, 0.0);
            let mut update = || {
                let start = Instant::now();
                stats = Some(learner.train_step_with(batch, values));
                update_secs = secs(start);
            };
            let start = Instant::now();
            let (played, next) = rayon::in_place_scope(|scope| {
                scope.spawn(move |_| update());
                let played = player.play_through(through, acting, lives);
                // The next update's batch, if the block reached its step and it is due.
                let p = &mut player;
                let reached = p.counters.agent_steps == through;
                let next = if reached && train_due(p.config, p.replay, ahead.len(), through) {
                    let start = Instant::now();
                    sample(p.config, p.replay, sample_rng, p.table, ahead);
                    p.times.sampling += secs(start);
                    // And its target pass, off the update's critical path.
                    let start = Instant::now();
                    next_net.compute(ahead, ahead_values);
                    p.times.target_pass += secs(start);
                    Some(through)
                } else {
                    None
                };
                play_secs = secs(start);
                (played.expect("a block plays at least one step"), next)
            });
            self.times.update += update_secs;
            self.times.joining += secs(start) - play_secs;
            self.landed(&stats.expect("the update ran in the scope"), t, metrics)?;
            let Some(next) = next else {
                return Ok((played, t));
            };
            if self.refresh_target(t..=next - 1) {
                // The pass was made with the target network before it changed: the next
                // update makes it anew, and the copy follows the target.
                self.ahead_values.clear();
                self.next.as_mut().expect("built").sync(&self.learner);
            }
            std::mem::swap(&mut self.batch, self.ahead.as_mut().expect("built"));
            std::mem::swap(&mut self.batch_values, &mut self.ahead_values);
            t = next;
            if played.ended {
                // The episode's last update, with nothing left to play beside it.
                let stats = self.train_step(t);
                self.landed(&stats, t, metrics)?;
                return Ok((played, t));
            }
        }
    }

    /// Draws the layers after the convolutions afresh at agent step `t`
    /// ([`Learner::reset_dense`]), from a network initialised as a run's first is, on a random
    /// stream of its own for each `t` (so a resumed run resets as one never stopped would).
    fn reset_dense(&mut self, t: u64) {
        let fresh = super::qnet(
            self.config.input_shape(),
            self.game.n_actions(),
            Head::of(&self.config),
            &crate::layers::init::VarianceScaling::HE,
            &mut stream(self.config.seed, RESET_STREAMS | t),
        );
        self.learner.reset_dense(&fresh);
    }

    /// Whether agent step `t` takes a gradient step (the function `train_due`).
    fn train_due(&self, t: u64) -> bool {
        train_due(&self.config, &self.replay, self.batch.len(), t)
    }

    /// The divergence guard: an error naming the agent step `t` and the train step if the last
    /// gradient step gave a non-finite loss, gradient norm or weight.
    fn check_finite(&self, s: &StepStats, t: u64) -> anyhow::Result<()> {
        check_finite(
            &self.learner,
            s,
            t,
            self.counters.train_steps,
            self.counters.episodes + 1,
        )
    }

    /// The notebook's extra transition at the end of an episode: the final state again, marked
    /// terminal ([`Config::fake_terminal_transition`]).
    fn push_fake_terminal(&mut self, last_action: usize) {
        let last = self
            .observer
            .stack()
            .get(self.observer.stack().len() - 1)
            .to_vec();
        self.replay.push_step(last_action, 0.0, true, &last);
    }

    /// Counts the episode and its wall time, and makes its metrics row.
    fn finish_episode(&mut self, start: Instant, m: &EpisodeMetrics) -> EpisodeRow {
        self.counters.episodes += 1;
        self.counters.wall_seconds += start.elapsed().as_secs_f64();
        EpisodeRow {
            episode: self.counters.episodes,
            agent_steps: self.counters.agent_steps,
            frames: self.counters.frames,
            reward: m.score,
            length: m.length,
            epsilon: self.epsilon(),
            mean_loss: m.mean(m.loss_sum),
            mean_max_q: m.mean(m.q_sum),
            wall_seconds: self.counters.wall_seconds,
        }
    }
}

/// Refuses `games` that are not the `config.games` an agent plays, or whose action counts
/// differ.
fn check_games<G: Game>(config: &Config, games: &[G]) -> anyhow::Result<()> {
    if games.len() != config.games {
        bail!(
            "the configuration plays {} games side by side, and {} were given",
            config.games,
            games.len()
        );
    }
    if games.iter().any(|g| g.n_actions() != games[0].n_actions()) {
        bail!("every game must have the same actions");
    }
    Ok(())
}

/// Whether agent step `t` takes a gradient step: past `learning_starts`, every `train_every`
/// steps, once the replay memory holds `learning_starts` entries (always so in a run that kept
/// its memory; a run resumed without it refills it first) and a batch of `batch_len`.
fn train_due(config: &Config, replay: &Replay, batch_len: usize, t: u64) -> bool {
    let refilled = config.learning_starts.min(replay.capacity() as u64);
    t > config.learning_starts
        && t.is_multiple_of(config.train_every)
        && replay.len() as u64 >= refilled
        && replay.can_sample(batch_len)
}

/// ALGO 6's batch: `batch` sampled from the replay memory (with an implicit quantile head, its
/// fractions drawn too).
fn sample(
    config: &Config, replay: &mut Replay, rng: &mut ChaCha8Rng, table: &[f32; 256],
    batch: &mut Batch,
) {
    replay.sample(rng, table, batch);
    if let Some(iqn) = config.iqn() {
        batch.draw_fractions(rng, iqn.samples, iqn.target_samples);
    }
}

/// The divergence guard: an error naming the agent step `t`, the train step `train_step` and
/// the `episode` under way if a gradient step of `learner` gave the non-finite loss, gradient
/// norm or weight that `s` reports.
pub(super) fn check_finite(
    learner: &Learner, s: &StepStats, t: u64, train_step: u64, episode: u64,
) -> anyhow::Result<()> {
    let what = if !s.loss.is_finite() {
        Some(format!("the loss is {}", s.loss))
    } else if !s.grad_norm.is_finite() {
        Some(format!("the gradient norm is {}", s.grad_norm))
    } else if !s.weights_finite {
        // Adam saw a non-finite weight as it wrote it: find which, for the message.
        let p = learner.non_finite_param();
        Some(format!(
            "weight {} is not finite",
            p.as_deref().unwrap_or("?")
        ))
    } else {
        None
    };
    if let Some(what) = what {
        bail!(
            "training diverged at agent step {t}, train step {} (episode {}): {what}",
            train_step,
            episode
        );
    }
    Ok(())
}

/// What one episode sums for its metrics row.
#[derive(Default)]
struct EpisodeMetrics {
    /// The unclipped game score.
    score: f64,
    length: u64,
    loss_sum: f64,
    q_sum: f64,
    n_train: u32,
}

impl EpisodeMetrics {
    fn add_train_step(&mut self, s: &StepStats) {
        self.loss_sum += s.loss as f64;
        self.q_sum += s.mean_max_q as f64;
        self.n_train += 1;
    }

    /// The mean of a sum over the episode's train steps (NaN without any).
    fn mean(&self, sum: f64) -> f32 {
        if self.n_train > 0 {
            (sum / self.n_train as f64) as f32
        } else {
            f32::NAN
        }
    }
}
