//! Checkpoints: everything needed to evaluate a network or continue a run exactly.
//!
//! A run directory holds `checkpoint.safetensors` and, unless the config sets
//! `checkpoint_replay = false`, one `replay-E.safetensors` (E: the episodes finished) that the
//! checkpoint names in its metadata.
//!
//! # `checkpoint.safetensors` (format `invaders-checkpoint-3`)
//!
//! Tensors (little-endian; shapes as in the layers, so NumPy and PyTorch read them with
//! `safetensors.numpy.load_file` / `safetensors.torch.load_file`):
//!
//! | tensor | dtype | shape |
//! | --- | --- | --- |
//! | `online.conv1.weight` | F32 | `[8, 8, C, 32]` (HWIO: height, width, in, out) |
//! | `online.conv1.bias` | F32 | `[32]` |
//! | `online.conv2.weight`, `.bias` | F32 | `[4, 4, 32, 64]`, `[64]` |
//! | `online.conv3.weight`, `.bias` | F32 | `[3, 3, 64, 64]`, `[64]` |
//! | `online.dense1.weight`, `.bias` | F32 | `[7040, 128]` (in, out; inputs in NHWC flatten order), `[128]` |
//! | `online.dense2.weight`, `.bias` | F32 | `[128, A]`, `[A]` |
//! | `online.iqn.weight`, `.bias` | F32 | an implicit quantile head's embedding, `[E, F]`, `[F]` (`F`: 128 after dense1, 7040 after the convolutions; only with `iqn_samples > 0`) |
//! | `online.dense_tau.weight`, `.bias` | F32 | the dense layer after an embedding that enters after dense1, `[128, 128]`, `[128]` |
//! | `target.*` | F32 | the target network, same names |
//! | `adam.m.*`, `adam.v.*` | F32 | Adam's first and second moments, same names as `online.*` (absent before the first step) |
//! | `observer.composite` | U8 | `[88, 80]`: the composer's latest composite frame |
//! | `observer.stack` | U8 | `[C, 88, 80]`: the frame stack, oldest first |
//! | `game.state` | U8 | `[n]`: the emulator's saved state (`SpaceInvaders::save_state`); absent for games that cannot be saved |
//! | `pqn.observer.composite`, `pqn.observer.stack` | U8 | PQN with `G > 1` games only: games 1 to `G − 1`'s, `[G − 1, 88, 80]` and `[G − 1, C, 88, 80]` (game 0's are the two above) |
//! | `pqn.game.state.g` | U8 | PQN only: game `g`'s saved state (`g` = 1 to `G − 1`), as `game.state` |
//!
//! Metadata (strings): `format` (`invaders-checkpoint-3`), `checksum` (below), `config` (the run's resolved TOML),
//! `counters` (JSON: episodes, agent steps, emulator frames, train steps, Adam's step count, wall
//! seconds), `rngs` (JSON: the agent's exploration and minibatch-sampling ChaCha8 generators as
//! `{seed, stream, word_pos}`; ε is derived from the agent-step counter), `replay` (the
//! replay file's name in the same directory, or empty), `replay_checksum` (that file's
//! `checksum`, or empty) and `kernels` (the kernels the products ran on,
//! [`crate::ops::plan::kernels`]: a run resumed where others run continues, but not bit for bit,
//! and `train --resume` says so; absent in older checkpoints, which load as before). A PQN
//! run's checkpoint (its config has a `[pqn]` table) also has `pqn` (JSON: every game's episode
//! in progress, and the finished episodes' rows not yet written to `metrics.csv`, a NaN mean as
//! `null`); its `sample` generator is the one that shuffles the rollouts. A PQN agent is saved
//! only between rollouts, so nothing of a rollout is held, and it has no replay memory to save.
//!
//! # `replay-E.safetensors` (format `invaders-replay-2`)
//!
//! The replay memory's `len = min(written, capacity)` held entries in *slot order*: row `s` holds
//! entry `g` with `g % capacity = s` (oldest first until the ring wraps), so the file is the
//! memory's own arrays, written without a copy (up to 7 KB per entry: 141 MB for 20 000) and
//! read back the same way, the frames streamed from the file into the memory ([`read_replay`]).
//!
//! | tensor | dtype | shape |
//! | --- | --- | --- |
//! | `replay.frames` | U8 | `[len, 88, 80]` |
//! | `replay.actions` | U8 | `[len]` |
//! | `replay.rewards` | F32 | `[len]` (after clipping, as stored) |
//! | `replay.flags` | U8 | `[len]`: bit 0 done, bit 1 episode start, bit 2 acted on |
//! | `replay.priorities` | F64 | `[len]`: each slot's priority (only if `prioritized`) |
//! | `replay.max_priority` | F64 | `[1]`: the largest priority ever set (only if `prioritized`) |
//!
//! Metadata: `format`, `checksum`, `written` (the entry counter), `capacity`, `frames_per_state`,
//! and the `episodes` and `agent_steps` of the checkpoint it belongs to (checked on loading).
//!
//! # Checksums
//!
//! Every file's `checksum` is the CRC-32 of its tensors, each name followed by its data bytes, in
//! name order ([`tensors_checksum`]), as 8 hex digits. The loaders recompute it, so a flipped byte
//! anywhere in the data is refused, and a checkpoint accepts only the replay file whose checksum
//! it names, so a replay file copied in from another run (even at the same counters) is refused.
//! Files of the previous formats (`invaders-checkpoint-2`, `invaders-replay-1`), written before
//! checksums, still load.
//!
//! # Crash safety
//!
//! Every file is written atomically: to a temporary file in the same directory, flushed to disk,
//! then renamed over the old one (then the directory is synced). [`save_run`] writes the new
//! replay file first, then the checkpoint that names it, and only then deletes older replay
//! files, so a crash at any moment leaves a checkpoint whose replay file exists. A failed write
//! (full disk, unwritable directory) returns an error and leaves the previous pair as it was.
//!
//! # Resuming without the replay memory
//!
//! With `checkpoint_replay = false` a resumed run starts with an empty replay memory, and that is
//! the only state it lacks. It then differs from an uninterrupted run in this: gradient steps
//! wait, as at the start of a run, until the memory holds `learning_starts` entries again (the
//! agent-step schedule of `train_every` is kept), the first minibatches are drawn from those
//! fresh transitions only, and from then on weights, rewards and ε-greedy choices drift apart
//! from the uninterrupted run's. Counters, ε, random generators, the
//! emulator and the networks are still restored exactly.
//!
//! # Snapshots: a run that outlives its machine
//!
//! A run directory's replay memory is gigabytes, so it stays on the machine that trained it. A
//! *snapshot* ([`snapshot_to_bytes`], [`save_snapshot`]) is the part of a checkpoint small
//! enough to keep elsewhere (about 4 MB for `strong`, a quarter of the checkpoint): a
//! checkpoint of the same format with the metadata `contents = "snapshot"`, the `online.*`,
//! `observer.*` and `game.state` tensors, the counters, the generators, and no `target.*`,
//! `adam.*` or replay file. `train --snapshot DIR` writes one after each checkpoint, and
//! `experiment --keep` keeps one for each run still training, so a run continues on another
//! machine (`train --resume` on a directory holding it) where its run directory is gone. What
//! it lacks is set as a run that never had it would: the replay memory starts empty (above),
//! the target network is a copy of the online one (as after ALGO 7's copy), and Adam starts
//! anew (step 0, zero moments). A run continued so is a run of its configuration, but not the
//! one an uninterrupted run would have been; `experiment` records where it happened.
//!
//! # A model file (format `invaders-model-1`)
//!
//! What `invaders export` writes for sharing a trained player: the `online.*` tensors only (a few
//! MB), with the metadata `format`, `checksum`, `config` and `counters` (with `adam_steps`).
//! [`load_model`] reads it, or the online network of a checkpoint, for `eval`; it has no target
//! network, optimizer state, random generators or game, so [`load`] refuses it for `--resume`.
//!
//! # Loading
//!
//! [`from_bytes`] checks everything before returning a network: the format tag, the config
//! (parsed and validated), the counters, every tensor's name, dtype and shape (derived from the
//! config's preset and pipeline and the saved action count), that no tensor is missing or extra,
//! and that every value is finite. Any damage (truncation, flipped bytes, a tensor renamed or
//! reshaped, another preset's network) is an error; nothing is ever partly loaded.
//!
//! # Where
//!
//! `format.rs` the checkpoint's bytes, `model.rs` the model file, `replay_file.rs` the replay
//! file, `run_dir.rs` the pair in a run directory, `atomic.rs` the atomic writes every file goes
//! through.

mod atomic;
mod format;
mod model;
mod replay_file;
mod run_dir;

pub use super::agent::{AgentState, Counters, EpisodeRow, GameSlot};
pub use atomic::{copy_files_atomic, tmp_path, write_atomic, write_atomic_with};
pub use format::{
    from_bytes, load, snapshot_to_bytes, tensors_checksum, to_bytes, MAX_CHECKPOINT_BYTES,
};
pub use model::{
    load_model, model_from_bytes, model_to_bytes, network_file, read_model_file, Model, MODEL_FILE,
};
pub use replay_file::{read_replay, replay_file_name, replay_from_bytes, save_replay};
pub use run_dir::{load_run, load_run_replay, save_run, save_snapshot};
// The files' helpers, for each other.
use format::*;
use replay_file::*;

use super::{Agent, Config, Learner, PqnAgent, Preset, Replay, Trainer};
use crate::env::{Game, FRAME_HEIGHT, FRAME_LEN, FRAME_WIDTH};
use crate::layers::Sequential;
use crate::tensor::Tensor;
use anyhow::{anyhow, bail, Context};
use rand_chacha::ChaCha8Rng;
use safetensors::tensor::TensorView;
use safetensors::{Dtype, SafeTensors};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::io::Write;
use std::path::Path;

/// The format tag stored in every checkpoint.
pub const FORMAT: &str = "invaders-checkpoint-3";
/// The checkpoint format before checksums, still read.
pub const FORMAT_V2: &str = "invaders-checkpoint-2";
/// The format tag stored in every replay file.
pub const REPLAY_FORMAT: &str = "invaders-replay-2";
/// The replay format before checksums, still read.
pub const REPLAY_FORMAT_V1: &str = "invaders-replay-1";
/// The format tag of a weights-only model file ([`model_to_bytes`]).
pub const MODEL_FORMAT: &str = "invaders-model-1";
/// The checkpoint's file name in a run directory.
pub const CHECKPOINT_FILE: &str = "checkpoint.safetensors";
/// The `contents` metadata of a snapshot ([`snapshot_to_bytes`]).
pub const SNAPSHOT_CONTENTS: &str = "snapshot";

/// A loaded checkpoint.
pub struct Checkpoint {
    /// The run's configuration.
    pub config: Config,
    /// Its counters.
    pub counters: Counters,
    /// The networks and optimizer.
    pub learner: Learner,
    /// Random generators, observer and game.
    pub agent: AgentState,
    /// The name of the replay file saved with it (in the same directory), if any.
    pub replay_file: Option<String>,
    /// That replay file's checksum (none in checkpoints written before checksums).
    pub replay_checksum: Option<u32>,
    /// The kernels the run's products ran on when it was written
    /// ([`crate::ops::plan::kernels`]; none in older checkpoints). A run continues bit for bit
    /// only where the same ones run.
    pub kernels: Option<String>,
    /// Whether it is a snapshot (see the module's "Snapshots"): its target network was set to
    /// the online one and Adam starts anew.
    pub snapshot: bool,
}

impl Checkpoint {
    /// The agent that continues this run on `game` (built with the checkpoint's environment
    /// settings), with `replay` (the memory saved with it; else an empty one):
    /// [`Agent::resume`].
    pub fn into_agent<G: Game>(self, game: G, replay: Option<Replay>) -> anyhow::Result<Agent<G>> {
        Agent::resume(
            game,
            self.config,
            self.counters,
            self.learner,
            self.agent,
            replay,
        )
    }

    /// [`Checkpoint::into_agent`] for the [`Config::games`] games the run plays side by side,
    /// each built with the checkpoint's environment settings and seed
    /// ([`crate::dqn::game_seed`]): [`Agent::resume_games`].
    pub fn into_agent_games<G: Game>(
        self, games: Vec<G>, replay: Option<Replay>,
    ) -> anyhow::Result<Agent<G>> {
        Agent::resume_games(
            games,
            self.config,
            self.counters,
            self.learner,
            self.agent,
            replay,
        )
    }

    /// The PQN agent that continues this run on `games` (built with the checkpoint's
    /// environment settings, [`crate::dqn::game_seed`]): [`PqnAgent::resume`].
    pub fn into_pqn_agent<G: Game>(self, games: Vec<G>) -> anyhow::Result<PqnAgent<G>> {
        PqnAgent::resume(games, self.config, self.counters, self.learner, self.agent)
    }

    /// Refuses a checkpoint trained with another preset than `expected`.
    pub fn expect_preset(&self, expected: Preset) -> anyhow::Result<()> {
        if self.config.preset != expected {
            bail!(
                "the checkpoint was trained with preset `{}`, not `{}`",
                self.config.preset.name(),
                expected.name()
            );
        }
        Ok(())
    }
}
