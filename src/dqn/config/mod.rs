//! Every hyperparameter of a run, named once, and the presets.
//!
//! A run's configuration is resolved in three layers: a preset (`article` by default), then the
//! keys of an optional TOML file, then command-line flags. Unknown keys and out-of-range values
//! are errors, and the resolved configuration is saved with the run as `config.toml`.

use super::Replay;
use crate::env::{Downsample, EnvConfig, EnvMode, Normalization, Pipeline};
use crate::layers::loss::LossKind;
use crate::ops::plan::Precision;
use crate::tensor::Padding;
use anyhow::{bail, Context};
use serde::{Deserialize, Serialize};

mod file;
mod validate;

pub use file::merge_toml;

/// The largest replay memory a configuration may ask for (about 70 GB of frames).
pub const MAX_REPLAY: usize = 10_000_000;
/// The largest minibatch a configuration may ask for.
pub const MAX_BATCH: usize = 4_096;
/// The most games a DQN run may play side by side ([`Config::games`]).
pub const MAX_GAMES: usize = 256;

/// The named configurations.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Preset {
    /// The article's hyperparameters with the notebook's defects fixed: `stack-max`
    /// composition, inputs in [-1, 1), actions from the online network.
    #[default]
    Article,
    /// The same with one frame per state: the article's baseline.
    ArticleVanilla,
    /// The notebook's behaviour on purpose: running-max composition, inputs in [-2, 0), actions
    /// picked by the lagged (target) network, a fake terminal transition stored per episode.
    ArticleAsWritten,
    /// The best player found for issue #43's budget (`docs/strong.md`): `strong-v1` learning
    /// once every 16 agent steps instead of 4, so the same compute plays 40 million frames
    /// (10 million agent steps, 625 000 updates) with a 1 M-transition memory, the target copied
    /// every 8 000 agent steps (500 updates) and the learning rate falling over the whole run.
    Strong,
    /// The first `strong` (until 2026-12), chosen by measurement to play well within an afternoon
    /// on a 2-core machine: the `v5` game, Double DQN with a dueling head, 3-step returns, life
    /// loss ending bootstrapping, clipped rewards, Huber loss, a 400 000-transition memory, a
    /// slower target, a faster ε schedule, a learning rate falling to a tenth, the faster of f32
    /// and bf16 products on the host (`auto`) and 13.5 million frames. Its published results
    /// (`docs/strong/three-seeds/`, the levers tried on it) reproduce under this name.
    StrongV1,
}

impl Preset {
    /// The preset's name as used on the command line and in config files.
    pub fn name(self) -> &'static str {
        match self {
            Preset::Article => "article",
            Preset::ArticleVanilla => "article-vanilla",
            Preset::ArticleAsWritten => "article-as-written",
            Preset::Strong => "strong",
            Preset::StrongV1 => "strong-v1",
        }
    }
}

/// Adam's ε unless a config says otherwise (TensorFlow 1's default).
pub const ADAM_EPSILON: f64 = 1e-8;

/// The `strong` preset's budget in emulator frames: 10 million agent steps, learning every 16,
/// about what `strong-v1`'s 3.65 million agent steps cost (issue #43's cap; docs/strong.md).
pub const STRONG_FRAMES: u64 = 40_000_000;

/// The `strong-v1` preset's budget in emulator frames: 3.375 million agent steps, about 2.3 hours
/// alone on two threads of a Zen 5 machine in bf16 (docs/strong.md).
pub const STRONG_V1_FRAMES: u64 = 13_500_000;

/// The bound of every knob counted in agent steps or episodes (`train_every`, `learning_starts`,
/// `target_update`, `epsilon_decay_steps`, `checkpoint_every`, `plot_every`): ten billion, beyond
/// any run this program could finish.
pub const MAX_STEPS_KNOB: u64 = 10_000_000_000;

/// The longest return a configuration may ask for (`n_step`).
pub const MAX_N_STEP: u32 = 100;

fn one() -> u32 {
    1
}

fn yes() -> bool {
    true
}

/// The article's dense layer: 128 units.
pub const ARTICLE_HIDDEN: usize = 128;

/// Prioritized replay's `α`: sampling probability ∝ `(|δ| + ε)^α` (Dopamine's Rainbow: 0.5).
pub const PRIORITY_EXPONENT: f64 = 0.5;

/// Prioritized replay's `β`: loss weights `(N · P)^(−β)` (Dopamine's Rainbow: 0.5, fixed).
pub const IMPORTANCE_EXPONENT: f64 = 0.5;

/// The largest random shift of a sampled state (`random_shift`; DrQ's is 4 on 84x84).
pub const MAX_RANDOM_SHIFT: usize = 16;

/// The most resets a configuration may ask for (`reset_dense_at`).
pub const MAX_RESETS: usize = 1_000;

/// The most quantiles a quantile head may have (`quantiles`; QR-DQN used 200).
pub const MAX_QUANTILES: usize = 1024;

/// The widest dense layer a configuration may ask for (`hidden`).
pub const MAX_HIDDEN: usize = 4096;

/// The most fractions an implicit quantile head may take per state in one pass (`iqn_samples`,
/// `iqn_target_samples`, `iqn_policy_samples`; Dopamine: 64, 64, 32).
pub const MAX_IQN_SAMPLES: usize = 256;

/// The largest cosine embedding of an implicit quantile head (`iqn_embedding`).
pub const MAX_IQN_EMBEDDING: usize = 1024;

fn iqn_embedding_default() -> usize {
    64
}

fn impala_channels_default() -> [usize; 3] {
    super::IMPALA_CHANNELS
}

fn impala_blocks_default() -> usize {
    super::IMPALA_BLOCKS
}

/// The widest stage an IMPALA encoder may ask for (`impala_channels`).
pub const MAX_IMPALA_CHANNELS: usize = 256;

/// The most residual blocks per stage an IMPALA encoder may ask for (`impala_blocks`).
pub const MAX_IMPALA_BLOCKS: usize = 8;

fn iqn_samples_default() -> usize {
    32
}

fn munchausen_tau_default() -> f64 {
    0.03
}

fn munchausen_clip_default() -> f64 {
    -1.0
}

fn is_false(v: &bool) -> bool {
    !*v
}

fn is_zero(v: &usize) -> bool {
    *v == 0
}

fn one_f64() -> f64 {
    1.0
}

fn one_usize() -> usize {
    1
}

fn is_one(v: &usize) -> bool {
    *v == 1
}

fn article_hidden() -> usize {
    ARTICLE_HIDDEN
}

fn adam_epsilon_default() -> f64 {
    ADAM_EPSILON
}

/// `episodes` of a run bounded by frames only: as many as TOML's integers hold (they are i64,
/// so `u64::MAX` would not serialise into `config.toml`).
pub const NO_EPISODE_LIMIT: u64 = i64::MAX as u64;

/// PQN's settings (Gallici et al. 2024, "Simplifying Deep Temporal Difference Learning"; the
/// `[pqn]` table of a config file). Defaults: CleanRL's `pqn_atari_envpool.py`.
///
/// Each rollout plays `games` games side by side for `rollout` agent steps each, acting
/// ε-greedily on the online network (the only network); its `games · rollout` transitions get
/// Q(λ) returns ([`super::q_lambda_returns`]) bootstrapped from the acting network's own
/// `max_a Q`, and are learnt in `epochs` passes, each over a fresh shuffle cut into
/// `minibatches` minibatches; then the rollout is dropped. Under PQN the replay, target and
/// update-rate keys (`replay_capacity`, `batch_size`, `train_every`, `learning_starts`,
/// `target_update`, `double_dqn`, `n_step`) are not used; ε and the learning rate follow their
/// schedules over agent steps, each game's step counting one.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Pqn {
    /// Games played side by side (CleanRL: 8).
    #[serde(default = "pqn_games_default")]
    pub games: usize,
    /// Agent steps of each game per rollout (CleanRL: 128).
    #[serde(default = "pqn_rollout_default")]
    pub rollout: usize,
    /// Passes over each rollout (CleanRL: 4).
    #[serde(default = "pqn_epochs_default")]
    pub epochs: usize,
    /// Minibatches per pass (CleanRL: 4, so 256 transitions each); they must divide
    /// `games · rollout`.
    #[serde(default = "pqn_minibatches_default")]
    pub minibatches: usize,
    /// λ of the Q(λ) returns: 0 the one-step target, 1 the Monte-Carlo return (CleanRL: 0.65).
    #[serde(default = "pqn_lambda_default")]
    pub lambda: f64,
}

impl Default for Pqn {
    fn default() -> Self {
        Pqn {
            games: pqn_games_default(),
            rollout: pqn_rollout_default(),
            epochs: pqn_epochs_default(),
            minibatches: pqn_minibatches_default(),
            lambda: pqn_lambda_default(),
        }
    }
}

impl Pqn {
    /// Transitions per rollout, `games · rollout`.
    pub fn transitions(&self) -> usize {
        self.games * self.rollout
    }

    /// Transitions per minibatch.
    pub fn minibatch(&self) -> usize {
        self.transitions() / self.minibatches
    }
}

fn pqn_games_default() -> usize {
    8
}

fn pqn_rollout_default() -> usize {
    128
}

fn pqn_epochs_default() -> usize {
    4
}

fn pqn_minibatches_default() -> usize {
    4
}

fn pqn_lambda_default() -> f64 {
    0.65
}

/// The most games a PQN run may play side by side.
pub const MAX_PQN_GAMES: usize = 256;

/// Everything a training run depends on.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// The preset these values started from.
    pub preset: Preset,
    /// Seed of every random generator of the run (network init, exploration, replay sampling,
    /// the emulator).
    pub seed: u64,
    /// Stop after this many episodes (the article: 800); [`NO_EPISODE_LIMIT`] when a frame
    /// budget (`max_frames`) ends the run instead.
    pub episodes: u64,
    /// Or after this many emulator frames, whichever comes first (0: no frame limit).
    pub max_frames: u64,
    /// How frames become the network's input.
    pub pipeline: Pipeline,
    /// How u8 pixels map to network inputs.
    pub normalization: Normalization,
    /// Replay memory size in transitions (the article: 20 000).
    pub replay_capacity: usize,
    /// Minibatch size (the article: 48).
    pub batch_size: usize,
    /// Adam learning rate (the article: 1e-3).
    pub learning_rate: f64,
    /// If set, the learning rate falls linearly from `learning_rate` to this between agent steps
    /// `learning_rate_decay[0]` and `learning_rate_decay[1]`, and stays there (the article: a
    /// constant rate).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub learning_rate_end: Option<f64>,
    /// The agent steps `[from, to]` over which the learning rate falls to `learning_rate_end`.
    #[serde(default)]
    pub learning_rate_decay: [u64; 2],
    /// Discount factor γ (the article: 0.97).
    pub gamma: f64,
    /// Agent steps between gradient steps (the article: 4).
    pub train_every: u64,
    /// Agent steps before learning starts (the article: 2000).
    pub learning_starts: u64,
    /// Agent steps between copies of the online network into the target network (the
    /// article: 100).
    pub target_update: u64,
    /// Exploration rate at step 0.
    pub epsilon_start: f64,
    /// Exploration rate after the decay.
    pub epsilon_end: f64,
    /// Agent steps over which ε falls linearly (the article: 500 000).
    pub epsilon_decay_steps: u64,
    /// The regression loss (the article: MSE).
    pub loss: LossKind,
    /// Double DQN targets.
    pub double_dqn: bool,
    /// The convolutions' padding: `same` (the article's: conv1 to conv3 give 22 x 20, 11 x 10 and
    /// 11 x 10 pixels, 7 040 features) or `valid` (the Nature DQN's and Dopamine's: no padding,
    /// 21 x 19, 9 x 8 and 7 x 6 pixels, 2 688 features; 0.62 times the multiply-adds per sample)
    /// ([`super::qnet`]).
    #[serde(default)]
    pub padding: Padding,
    /// Units of the dense layer after the convolutions (the article: 128; the Nature DQN: 512).
    #[serde(default = "article_hidden")]
    pub hidden: usize,
    /// A quantile head (QR-DQN, Dabney et al. 2018) with this many quantiles per action, trained
    /// with the quantile Huber loss (then `loss` is not used); 0: one Q-value per action (the
    /// article).
    #[serde(default)]
    pub quantiles: usize,
    /// A dueling head: Q = V + A − mean A ([`crate::layers::Dueling`]).
    #[serde(default)]
    pub dueling: bool,
    /// Layer normalisation ([`crate::layers::LayerNorm`]) of each convolution's and dense1's
    /// pre-activations, before their ReLU (PQN's placement, Gallici et al. 2024); off in every
    /// preset.
    #[serde(default)]
    pub layer_norm: bool,
    /// The convolutions before the dense layers: `article` (conv1 to conv3) or `impala`
    /// (Dopamine's IMPALA encoder, [`super::impala_encoder`]: 4.3 times the article's
    /// multiply-adds per sample; SAME padding, no `layer_norm`); `article` in every preset.
    #[serde(default)]
    pub encoder: super::Encoder,
    /// With `encoder = "impala"`: each of its three stages' channels (Dopamine's `[16, 32, 32]`;
    /// fewer thin it, and its cost falls about as their square).
    #[serde(default = "impala_channels_default")]
    pub impala_channels: [usize; 3],
    /// With `encoder = "impala"`: residual blocks per stage (Dopamine's 2; 0 leaves the
    /// convolutions and poolings).
    #[serde(default = "impala_blocks_default")]
    pub impala_blocks: usize,
    /// An implicit quantile head (IQN, Dabney et al. 2018) trained at this many random fractions
    /// `τ` per state (`N`), with the quantile Huber loss (then `loss` is not used); 0: none.
    /// ([`super::Iqn`].)
    #[serde(default)]
    pub iqn_samples: usize,
    /// IQN: random fractions per next state for the target's samples (`N'`).
    #[serde(default = "iqn_samples_default")]
    pub iqn_target_samples: usize,
    /// IQN: midpoint fractions whose mean gives `Q(s, a)` for acting and for the bootstrapped
    /// action (`K`).
    #[serde(default = "iqn_samples_default")]
    pub iqn_policy_samples: usize,
    /// IQN: cosines in the embedding of a fraction (Dopamine: 64).
    #[serde(default = "iqn_embedding_default")]
    pub iqn_embedding: usize,
    /// IQN: where the embedding enters, `hidden` (after dense1; cheap) or `features` (after the
    /// convolutions, as Dopamine's).
    #[serde(default)]
    pub iqn_merge: super::IqnMerge,
    /// Munchausen targets (Vieillard et al. 2020) with this scale `α` of the log-policy bonus
    /// (their 0.9); 0: none. The target becomes soft: `y = R + α·max(τ log π(a|s), l0) +
    /// γ^m Σ_a' π(a'|s')·(q(s', a') − τ log π(a'|s'))` with `π = softmax(q_target/τ)`.
    #[serde(default)]
    pub munchausen_alpha: f64,
    /// Munchausen: the entropy temperature `τ` (their 0.03).
    #[serde(default = "munchausen_tau_default")]
    pub munchausen_tau: f64,
    /// Munchausen: the lower clip `l0` of the bonus `τ log π(a|s)` (their −1).
    #[serde(default = "munchausen_clip_default")]
    pub munchausen_clip: f64,
    /// Steps `n` of the returns the TD target bootstraps after:
    /// `y = r_t + γ r_{t+1} + … + γ^{n−1} r_{t+n−1} + γ^n max Q(s_{t+n})`, cut short at an episode's
    /// end (the article: 1).
    #[serde(default = "one")]
    pub n_step: u32,
    /// A lost life ends bootstrapping during training (the target sees it as terminal; the game
    /// goes on). The article: no.
    #[serde(default)]
    pub life_loss_terminal: bool,
    /// Each life a step loses costs the learner this much reward (after scaling and clipping;
    /// default 0). A bomb takes one life; the invaders landing end the game with every life left,
    /// so a landing with `L` lives costs `L` times as much. With `life_loss_terminal` the target
    /// stops at the lost life and sees nothing of the lives after it, so without a penalty a
    /// landing is no worse than a bomb ([`Config::learner_reward`]; docs/strong.md, "The plateau
    /// is a landing").
    #[serde(default)]
    pub life_penalty: f64,
    /// Prioritized replay: transitions drawn in proportion to `(|δ| + ε)^α`, losses weighted by
    /// `(N · P)^(−β)` ([`PRIORITY_EXPONENT`], [`IMPORTANCE_EXPONENT`]; `dqn::Replay`). The
    /// article: uniform.
    #[serde(default)]
    pub prioritized: bool,
    /// Random shifts (DrQ, Kostrikov et al. 2021): each sampled state and next state moved by
    /// up to this many pixels each way, its border repeated (`dqn::Replay::with_random_shift`);
    /// 0: none (every preset). Acting sees the frames unshifted.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub random_shift: usize,
    /// Resets against lost plasticity (Nikishin et al. 2022, "The primacy bias in deep
    /// reinforcement learning"): at each of these agent steps (increasing) every layer after the
    /// convolutions (dense1, dense2 and what lies between them) is drawn afresh as at a run's
    /// start, and its Adam first moments are zeroed; the convolutions, the target network and
    /// the replay memory are kept ([`super::Learner::reset_dense`]). Empty: never (every
    /// preset).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub reset_dense_at: Vec<u64>,
    /// Adam's ε (TensorFlow's default 1e-8; Rainbow and its data-efficient variants use 1.5e-4,
    /// which damps the steps of parameters with rare gradients).
    #[serde(default = "adam_epsilon_default")]
    pub adam_epsilon: f64,
    /// Rectified Adam (RAdam, Liu et al. 2020; PQN's optimizer) instead of Adam: the same
    /// moments, a step without the second moment while its estimate is too young to trust
    /// ([`crate::optim::Adam::rectified`]). Off in every preset.
    #[serde(default, skip_serializing_if = "is_false")]
    pub radam: bool,
    /// PQN (Gallici et al. 2024): Q-learning from rollouts of several games played at once, with
    /// Q(λ) targets and no replay memory or target network ([`Pqn`], `dqn::PqnAgent`); absent:
    /// the DQN loop (every preset).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pqn: Option<Pqn>,
    /// Clip gradients to this global norm (0: no clipping).
    pub clip_grad_norm: f64,
    /// The training products' arithmetic: `f32`, or `bf16` operands with f32 sums where the CPU
    /// has AVX512-BF16 (elsewhere f32; [`crate::ops::plan::Precision`]), or `auto`: whichever
    /// trains faster here, measured when the run starts and recorded in its `config.toml`
    /// ([`super::resolve_precision`]). Weights, gradients, Adam's state and checkpoints stay f32.
    #[serde(default)]
    pub precision: Precision,
    /// Clip rewards to [-`reward_clip`, `reward_clip`] (the Nature DQN: [-1, 1]; the article
    /// does not).
    pub clip_rewards: bool,
    /// The game's rewards are multiplied by this before any clipping (default 1). With
    /// `reward_scale = 1/32` and `reward_clip = 10` an invader (5 to 30 points) is worth 0.16 to
    /// 0.94 and the mothership (200) 6.25, where clipping to [-1, 1] makes both worth 1
    /// ([`Config::reward`]).
    #[serde(default = "one_f64")]
    pub reward_scale: f64,
    /// The bound of clipped rewards (default 1, the Nature DQN's).
    #[serde(default = "one_f64")]
    pub reward_clip: f64,
    /// The notebook's swap: pick actions with the lagged (target) network.
    pub act_with_target_network: bool,
    /// Acting beside learning (issue #101): each update runs on the pool's other threads while
    /// this thread plays the agent steps through the next update's (`train_every` of them), which
    /// act with a copy of the parameters from before the update (one update old), samples the
    /// next update's batch and makes its target pass (the same numbers as the update would).
    /// Results depend on the seed alone, not on the thread count; with one thread the block is
    /// played first, then the update. Default off: each update lands before the next action.
    #[serde(default, skip_serializing_if = "is_false")]
    pub act_while_learning: bool,
    /// Games played side by side (issue #101; default 1). Each agent step of the loop plays one
    /// step of every game: their actions from one forward pass over their `games` stacks, the
    /// emulators stepped in parallel on the pool's threads; each game writes its own lane of the
    /// replay memory (`replay_capacity / games` entries; `dqn::Replay::with_lanes`), and each of
    /// the agent steps counts towards ε, `train_every` and `target_update` as one game's would.
    /// An episode's row goes out when its game ends it. The seeds of the games after the first
    /// come from `dqn::game_seed`, as PQN's. With `act_while_learning` each update runs beside
    /// the passes through the next update's (then `train_every >= games`).
    #[serde(default = "one_usize", skip_serializing_if = "is_one")]
    pub games: usize,
    /// The notebook's extra transition at each episode end: the final state, the last action,
    /// reward 0, marked terminal, leading to itself.
    pub fake_terminal_transition: bool,
    /// Episodes between checkpoints (the last one is always written).
    pub checkpoint_every: u64,
    /// Save the replay memory with each checkpoint (`replay-*.safetensors` beside it, up to
    /// 7 KB per transition), so that a resumed run continues exactly as if never stopped. Without
    /// it a resumed run starts with an empty memory: see `dqn::checkpoint` for what then differs.
    pub checkpoint_replay: bool,
    /// Episodes between refreshes of the reward plot.
    pub plot_every: u64,
    /// Write TensorBoard event files into the run directory beside `metrics.csv` (scalars per
    /// episode; `tensorboard --logdir runs/`).
    #[serde(default = "yes")]
    pub tensorboard: bool,
    /// The environment.
    pub env: EnvConfig,
}

impl Config {
    /// The complete configuration of a preset.
    pub fn preset(p: Preset) -> Config {
        let article = Config {
            preset: p,
            seed: 0,
            episodes: 800,
            max_frames: 0,
            pipeline: Pipeline::StackMax,
            normalization: Normalization::Symmetric,
            replay_capacity: 20_000,
            batch_size: 48,
            learning_rate: 1e-3,
            learning_rate_end: None,
            learning_rate_decay: [0, 0],
            gamma: 0.97,
            train_every: 4,
            learning_starts: 2_000,
            target_update: 100,
            epsilon_start: 1.0,
            epsilon_end: 0.05,
            epsilon_decay_steps: 500_000,
            loss: LossKind::Mse,
            double_dqn: false,
            padding: Padding::Same,
            hidden: ARTICLE_HIDDEN,
            quantiles: 0,
            dueling: false,
            layer_norm: false,
            encoder: super::Encoder::Article,
            impala_channels: super::IMPALA_CHANNELS,
            impala_blocks: super::IMPALA_BLOCKS,
            iqn_samples: 0,
            iqn_target_samples: iqn_samples_default(),
            iqn_policy_samples: iqn_samples_default(),
            iqn_embedding: iqn_embedding_default(),
            iqn_merge: super::IqnMerge::Hidden,
            munchausen_alpha: 0.0,
            munchausen_tau: munchausen_tau_default(),
            munchausen_clip: munchausen_clip_default(),
            n_step: 1,
            life_loss_terminal: false,
            life_penalty: 0.0,
            prioritized: false,
            random_shift: 0,
            reset_dense_at: Vec::new(),
            adam_epsilon: ADAM_EPSILON,
            radam: false,
            pqn: None,
            precision: Precision::F32,
            clip_grad_norm: 0.0,
            clip_rewards: false,
            reward_scale: 1.0,
            reward_clip: 1.0,
            act_with_target_network: false,
            act_while_learning: false,
            games: 1,
            fake_terminal_transition: false,
            checkpoint_every: 25,
            checkpoint_replay: true,
            plot_every: 5,
            tensorboard: true,
            env: EnvConfig::from_mode(EnvMode::V0),
        };
        match p {
            Preset::Article => article,
            Preset::ArticleVanilla => Config {
                pipeline: Pipeline::Vanilla,
                ..article
            },
            Preset::ArticleAsWritten => Config {
                pipeline: Pipeline::StackRunningMax,
                normalization: Normalization::ArticleCode,
                act_with_target_network: true,
                fake_terminal_transition: true,
                ..article
            },
            Preset::Strong => Config {
                preset: p,
                max_frames: STRONG_FRAMES,
                replay_capacity: 1_000_000,
                train_every: 16,
                target_update: 8_000,
                learning_rate_decay: [940_000, 10_000_000],
                ..Config::preset(Preset::StrongV1)
            },
            Preset::StrongV1 => Config {
                episodes: NO_EPISODE_LIMIT,
                max_frames: STRONG_V1_FRAMES,
                replay_capacity: 400_000,
                batch_size: 32,
                learning_rate: 1e-4,
                learning_rate_end: Some(1e-5),
                learning_rate_decay: [250_000, 2_000_000],
                adam_epsilon: 1.5e-4,
                gamma: 0.99,
                train_every: 4,
                learning_starts: 20_000,
                target_update: 2_000,
                epsilon_start: 1.0,
                epsilon_end: 0.01,
                epsilon_decay_steps: 100_000,
                loss: LossKind::Huber,
                double_dqn: true,
                dueling: true,
                n_step: 3,
                life_loss_terminal: true,
                clip_grad_norm: 10.0,
                clip_rewards: true,
                precision: Precision::Auto,
                checkpoint_every: 50,
                plot_every: 25,
                env: EnvConfig {
                    downsample: Downsample::Max,
                    ..EnvConfig::from_mode(EnvMode::V5)
                },
                ..article
            },
        }
    }

    /// The reward the learner sees for the game's reward `r`: `r · reward_scale`, clamped to
    /// ±`reward_clip` if `clip_rewards`. Returns and scores always count the game's `r`.
    pub fn reward(&self, r: f32) -> f32 {
        let r = r * self.reward_scale as f32;
        if self.clip_rewards {
            let c = self.reward_clip as f32;
            r.clamp(-c, c)
        } else {
            r
        }
    }

    /// The reward the learner stores for a step that scored `r` and lost `lives_lost` lives:
    /// [`Config::reward`]`(r) − life_penalty · lives_lost`.
    pub fn learner_reward(&self, r: f32, lives_lost: i32) -> f32 {
        self.reward(r) - self.life_penalty as f32 * lives_lost.max(0) as f32
    }

    /// Values per action of the network's output: 1, or the quantile head's `quantiles`.
    pub fn atoms(&self) -> usize {
        self.quantiles.max(1)
    }

    /// The implicit quantile head, if `iqn_samples` asks for one.
    pub fn iqn(&self) -> Option<super::Iqn> {
        (self.iqn_samples > 0).then_some(super::Iqn {
            embedding: self.iqn_embedding,
            merge: self.iqn_merge,
            samples: self.iqn_samples,
            target_samples: self.iqn_target_samples,
            policy_samples: self.iqn_policy_samples,
        })
    }

    /// Munchausen targets, if `munchausen_alpha` asks for them.
    pub fn munchausen(&self) -> Option<super::Munchausen> {
        (self.munchausen_alpha > 0.0).then_some(super::Munchausen {
            alpha: self.munchausen_alpha as f32,
            tau: self.munchausen_tau as f32,
            clip: self.munchausen_clip as f32,
        })
    }

    /// How the targets bootstrap: Munchausen's soft target if `munchausen_alpha` asks for it
    /// (`double_dqn` is then unused: the soft target has no max to pick), else Double DQN's if
    /// `double_dqn`, else the max.
    pub fn target_rule(&self) -> super::TargetRule {
        match (self.munchausen(), self.double_dqn) {
            (Some(m), _) => super::TargetRule::Munchausen(m),
            (None, true) => super::TargetRule::Double,
            (None, false) => super::TargetRule::Max,
        }
    }

    /// An empty replay memory as this configuration asks for: its capacity, a lane for each of
    /// its `games`, frames per state, `n_step` returns, its `random_shift` and, if `prioritized`, prioritized sampling.
    pub fn new_replay(&self) -> Replay {
        let replay = Replay::new(self.replay_capacity, self.pipeline.channels())
            .with_lanes(self.games)
            .with_returns(self.n_step as usize, self.gamma as f32)
            .with_random_shift(self.random_shift);
        if self.prioritized {
            replay.with_priorities(PRIORITY_EXPONENT, IMPORTANCE_EXPONENT)
        } else {
            replay
        }
    }

    /// ε at agent step `t`: linear from `epsilon_start` to `epsilon_end` over
    /// `epsilon_decay_steps`, constant after.
    pub fn epsilon(&self, t: u64) -> f32 {
        if t >= self.epsilon_decay_steps {
            return self.epsilon_end as f32;
        }
        let frac = t as f64 / self.epsilon_decay_steps as f64;
        (self.epsilon_start + frac * (self.epsilon_end - self.epsilon_start)) as f32
    }

    /// The learning rate at agent step `t`: `learning_rate`, or with `learning_rate_end` linear
    /// from it to that between the steps of `learning_rate_decay`, constant outside them.
    pub fn learning_rate(&self, t: u64) -> f64 {
        let Some(end) = self.learning_rate_end else {
            return self.learning_rate;
        };
        let [from, to] = self.learning_rate_decay;
        let frac = (t.saturating_sub(from) as f64 / (to - from) as f64).min(1.0);
        self.learning_rate + frac * (end - self.learning_rate)
    }

    /// Bytes the replay memory takes when full: one 88x80 frame and 8 bytes of transition data
    /// per entry. Under PQN, which has none, its rollout's: every transition's `k` frames.
    pub fn replay_bytes(&self) -> u64 {
        match self.pqn {
            Some(p) => (p.transitions() * self.pipeline.channels() * crate::env::FRAME_LEN) as u64,
            None => self.replay_capacity as u64 * (crate::env::FRAME_LEN as u64 + 8),
        }
    }

    /// The network input shape `[88, 80, k]`.
    pub fn input_shape(&self) -> [usize; 3] {
        [
            crate::env::FRAME_HEIGHT,
            crate::env::FRAME_WIDTH,
            self.pipeline.channels(),
        ]
    }

    /// The configuration as TOML text.
    pub fn to_toml(&self) -> String {
        toml::to_string_pretty(self).expect("a config serialises")
    }
}
