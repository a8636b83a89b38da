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
//!
//! Metadata (strings): `format` (`invaders-checkpoint-3`), `checksum` (below), `config` (the run's resolved TOML),
//! `counters` (JSON: episodes, agent steps, emulator frames, train steps, Adam's step count, wall
//! seconds), `rngs` (JSON: the agent's exploration and minibatch-sampling ChaCha8 generators as
//! `{seed, stream, word_pos}`; ε is derived from the agent-step counter), `replay` (the
//! replay file's name in the same directory, or empty) and `replay_checksum` (that file's
//! `checksum`, or empty).
//!
//! # `replay-E.safetensors` (format `invaders-replay-2`)
//!
//! The replay memory's `len = min(written, capacity)` held entries in *slot order*: row `s` holds
//! entry `g` with `g % capacity = s` (oldest first until the ring wraps), so the file is the
//! memory's own arrays, written without a copy (up to 7 KB per entry: 141 MB for 20 000).
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
//! pause until the memory again holds `batch_size + C + 1` entries (the agent-step schedule of
//! `train_every` and `learning_starts` is kept), the first minibatches are drawn from those few
//! fresh transitions only, and from then on weights, rewards and ε-greedy choices drift apart
//! from the uninterrupted run's. Counters, ε, random generators, the emulator and the networks
//! are still restored exactly.
//!
//! # A model file (format `invaders-model-1`)
//!
//! What `invaders export` writes for sharing a trained player: the `online.*` tensors only (a few
//! MB), with the metadata `format`, `config` and `counters` (with `adam_steps`). [`load_model`]
//! reads it, or the online network of a checkpoint, for `eval`; it has no target network,
//! optimizer state, random generators or game, so [`load`] refuses it for `--resume`.
//!
//! # Loading
//!
//! [`from_bytes`] checks everything before returning a network: the format tag, the config
//! (parsed and validated), the counters, every tensor's name, dtype and shape (derived from the
//! config's preset and pipeline and the saved action count), that no tensor is missing or extra,
//! and that every value is finite. Any damage (truncation, flipped bytes, a tensor renamed or
//! reshaped, another preset's network) is an error; nothing is ever partly loaded.

use super::{Agent, Config, Learner, Preset, Replay};
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

/// Progress counters of a run.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
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
}

#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct Rngs {
    explore: ChaCha8Rng,
    sample: ChaCha8Rng,
}

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
}

impl Checkpoint {
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

fn view(t: &Tensor<f32>) -> Result<TensorView<'_>, safetensors::SafeTensorError> {
    TensorView::new(
        Dtype::F32,
        t.shape().to_vec(),
        bytemuck::cast_slice(t.data()),
    )
}

/// The temporary file an atomic write of `path` goes through: `.NAME.tmp` in the same directory
/// (the same filesystem, so the final rename is atomic).
pub fn tmp_path(path: &Path) -> anyhow::Result<std::path::PathBuf> {
    let dir = path
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let name = path
        .file_name()
        .ok_or_else(|| anyhow!("{} is not a file path", path.display()))?;
    Ok(dir.join(format!(".{}.tmp", name.to_string_lossy())))
}

/// Writes a file atomically: `write` fills a temporary file in the same directory, which is then
/// synced to disk and renamed over `path` (then the directory is synced). On any error the
/// temporary file is removed and `path` is left as it was.
pub fn write_atomic_with(
    path: &Path,
    write: impl FnOnce(&Path) -> anyhow::Result<()>,
) -> anyhow::Result<()> {
    let tmp = tmp_path(path)?;
    let dir = tmp
        .parent()
        .expect("a temporary path has a parent")
        .to_owned();
    let result = write(&tmp).and_then(|()| {
        let f = std::fs::File::open(&tmp)?;
        f.sync_all()?;
        drop(f);
        std::fs::rename(&tmp, path)?;
        if let Ok(d) = std::fs::File::open(&dir) {
            let _ = d.sync_all();
        }
        Ok(())
    });
    if let Err(e) = result {
        if tmp.is_file() {
            let _ = std::fs::remove_file(&tmp);
        }
        return Err(e).with_context(|| {
            format!(
                "cannot write {} (any previous version is kept)",
                path.display()
            )
        });
    }
    Ok(())
}

/// Writes `bytes` to `path` atomically (temporary file, fsync, rename, fsync of the directory).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> anyhow::Result<()> {
    write_atomic_with(path, |tmp| {
        let mut f = std::fs::File::create(tmp)?;
        f.write_all(bytes)?;
        Ok(())
    })
}

/// The CRC-32 of tensors: each name, then its data bytes, in name order.
pub fn tensors_checksum<'a>(tensors: impl IntoIterator<Item = (&'a str, &'a [u8])>) -> u32 {
    let mut sorted: Vec<(&str, &[u8])> = tensors.into_iter().collect();
    sorted.sort_by_key(|t| t.0);
    let mut h = crc32fast::Hasher::new();
    for (name, data) in sorted {
        h.update(name.as_bytes());
        h.update(data);
    }
    h.finalize()
}

/// Checks a loaded file's `checksum` metadata against its tensors.
fn verify_checksum(st: &SafeTensors<'_>, meta: &HashMap<String, String>) -> anyhow::Result<u32> {
    let stored = parse_checksum(meta_get(meta, "checksum")?)?;
    let tensors = st.tensors();
    let actual = tensors_checksum(tensors.iter().map(|(n, v)| (n.as_str(), v.data())));
    if actual != stored {
        bail!(
            "its contents are damaged: checksum {actual:08x}, but the file was written with {stored:08x}"
        );
    }
    Ok(stored)
}

fn parse_checksum(text: &str) -> anyhow::Result<u32> {
    u32::from_str_radix(text, 16).map_err(|_| anyhow!("bad checksum `{text}`"))
}

/// Serialises a checkpoint to safetensors bytes; `replay` names the replay file saved with it,
/// and that file's checksum, if any.
pub fn to_bytes(
    config: &Config,
    counters: &Counters,
    learner: &Learner,
    agent: &AgentState,
    replay: Option<(&str, u32)>,
) -> anyhow::Result<Vec<u8>> {
    let mut tensors: Vec<(String, TensorView<'_>)> = Vec::new();
    for (prefix, net) in [("online", &learner.online), ("target", &learner.target)] {
        for p in net.params() {
            tensors.push((format!("{prefix}.{}", p.name), view(&p.value)?));
        }
    }
    for (i, p) in learner.online.params().enumerate() {
        if let (Some(m), Some(v)) = (learner.adam.m.get(i), learner.adam.v.get(i)) {
            tensors.push((format!("adam.m.{}", p.name), view(m)?));
            tensors.push((format!("adam.v.{}", p.name), view(v)?));
        }
    }
    let k = agent.stack.len() / FRAME_LEN;
    tensors.push((
        "observer.composite".into(),
        TensorView::new(Dtype::U8, vec![FRAME_HEIGHT, FRAME_WIDTH], &agent.composite)?,
    ));
    tensors.push((
        "observer.stack".into(),
        TensorView::new(Dtype::U8, vec![k, FRAME_HEIGHT, FRAME_WIDTH], &agent.stack)?,
    ));
    if let Some(g) = &agent.game {
        tensors.push((
            "game.state".into(),
            TensorView::new(Dtype::U8, vec![g.len()], g)?,
        ));
    }
    let mut counters_json = serde_json::to_value(counters)?;
    counters_json["adam_steps"] = learner.adam.t.into();
    let rngs = Rngs {
        explore: agent.explore_rng.clone(),
        sample: agent.sample_rng.clone(),
    };
    let checksum = tensors_checksum(tensors.iter().map(|(n, v)| (n.as_str(), v.data())));
    let meta = HashMap::from([
        ("format".to_string(), FORMAT.to_string()),
        ("checksum".to_string(), format!("{checksum:08x}")),
        ("config".to_string(), config.to_toml()),
        ("counters".to_string(), counters_json.to_string()),
        ("rngs".to_string(), serde_json::to_string(&rngs)?),
        (
            "replay".to_string(),
            replay.map(|r| r.0).unwrap_or_default().to_string(),
        ),
        (
            "replay_checksum".to_string(),
            replay.map(|r| format!("{:08x}", r.1)).unwrap_or_default(),
        ),
    ]);
    Ok(safetensors::serialize(tensors, &Some(meta))?)
}

/// Copies the named tensors into `net`'s parameters after checking every name, dtype and shape.
fn load_net(st: &SafeTensors<'_>, prefix: &str, net: &mut Sequential<f32>) -> anyhow::Result<()> {
    for p in net.params_mut() {
        let name = format!("{prefix}.{}", p.name);
        read_into(st, &name, &mut p.value)?;
    }
    Ok(())
}

/// The tensor `name` after checking its dtype and shape.
fn tensor<'a>(
    st: &'a SafeTensors<'_>,
    name: &str,
    dtype: Dtype,
    shape: &[usize],
) -> anyhow::Result<TensorView<'a>> {
    let v = st.tensor(name).map_err(|_| anyhow!("no tensor `{name}`"))?;
    if v.dtype() != dtype {
        bail!(
            "tensor `{name}` has dtype {:?}, expected {dtype:?}",
            v.dtype()
        );
    }
    if v.shape() != shape {
        bail!(
            "tensor `{name}` has shape {:?}, expected {shape:?}",
            v.shape()
        );
    }
    Ok(v)
}

fn read_into(st: &SafeTensors<'_>, name: &str, t: &mut Tensor<f32>) -> anyhow::Result<()> {
    let v = tensor(st, name, Dtype::F32, t.shape())?;
    let values: Vec<f32> = bytemuck::pod_collect_to_vec(v.data());
    if let Some(bad) = values.iter().position(|x| !x.is_finite()) {
        bail!("tensor `{name}` holds a non-finite value at index {bad}");
    }
    t.data_mut().copy_from_slice(&values);
    Ok(())
}

/// Parses a safetensors file with metadata; returns the tensors and a metadata getter.
fn parse(bytes: &[u8]) -> anyhow::Result<(SafeTensors<'_>, HashMap<String, String>)> {
    let (_, header) =
        SafeTensors::read_metadata(bytes).map_err(|e| anyhow!("not a safetensors file: {e}"))?;
    let st = SafeTensors::deserialize(bytes).map_err(|e| anyhow!("not a safetensors file: {e}"))?;
    let meta = header
        .metadata()
        .clone()
        .ok_or_else(|| anyhow!("no metadata"))?;
    Ok((st, meta))
}

fn meta_get<'a>(meta: &'a HashMap<String, String>, k: &str) -> anyhow::Result<&'a str> {
    meta.get(k)
        .map(String::as_str)
        .ok_or_else(|| anyhow!("metadata has no `{k}`"))
}

/// Whether `name` is a replay file name as [`save_run`] makes them (no directories).
fn is_replay_name(name: &str) -> bool {
    name.strip_prefix("replay-")
        .and_then(|r| r.strip_suffix(".safetensors"))
        .is_some_and(|n| !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()))
}

/// The configuration, counters, Adam's step count and action count recorded in a checkpoint's or
/// model file's metadata, checked.
fn header(
    st: &SafeTensors<'_>,
    meta: &HashMap<String, String>,
) -> anyhow::Result<(Config, Counters, u64, usize)> {
    let config: Config = toml::from_str(meta_get(meta, "config")?).context("checkpoint config")?;
    config.validate().context("checkpoint config")?;
    let mut json: serde_json::Value =
        serde_json::from_str(meta_get(meta, "counters")?).context("checkpoint counters")?;
    let adam_steps = json
        .get("adam_steps")
        .and_then(|v| v.as_u64())
        .ok_or_else(|| anyhow!("checkpoint counters lack adam_steps"))?;
    if let Some(o) = json.as_object_mut() {
        o.remove("adam_steps");
    }
    let counters: Counters = serde_json::from_value(json).context("checkpoint counters")?;
    // The action count is the last layer's bias length (over the values per action), less the
    // value row of a dueling head.
    let bias = st
        .tensor("online.dense2.bias")
        .map_err(|_| anyhow!("no tensor `online.dense2.bias`"))?
        .shape()
        .first()
        .copied()
        .unwrap_or(0);
    let n_actions = (bias / config.atoms()).saturating_sub(config.dueling as usize);
    if n_actions == 0 || n_actions > 18 {
        bail!("checkpoint has {n_actions} actions");
    }
    Ok((config, counters, adam_steps, n_actions))
}

/// Parses checkpoint bytes into a fresh learner; nothing is returned unless every check passes.
pub fn from_bytes(bytes: &[u8]) -> anyhow::Result<Checkpoint> {
    let (st, meta) = parse(bytes)?;
    let format = meta_get(&meta, "format")?;
    if format == MODEL_FORMAT {
        bail!(
            "this is a weights-only model file (`invaders export`): it holds the online network \
             for `eval`, but no target network, optimizer state or random generators, so a run \
             cannot be resumed from it"
        );
    }
    if format == FORMAT {
        verify_checksum(&st, &meta)?;
    } else if format != FORMAT_V2 {
        bail!("unknown checkpoint format `{format}` (expected `{FORMAT}`)");
    }
    let (config, counters, adam_steps, n_actions) = header(&st, &meta)?;
    let rngs: Rngs =
        serde_json::from_str(meta_get(&meta, "rngs")?).context("checkpoint random generators")?;
    let replay_file = match meta_get(&meta, "replay")? {
        "" => None,
        name if is_replay_name(name) => Some(name.to_string()),
        name => bail!("checkpoint names a bad replay file `{name}`"),
    };
    let replay_checksum = match (format == FORMAT, &replay_file) {
        (true, Some(_)) => Some(parse_checksum(meta_get(&meta, "replay_checksum")?)?),
        _ => None,
    };
    // The initial weights are overwritten below; any generator will do.
    let mut rng = <ChaCha8Rng as rand::SeedableRng>::seed_from_u64(0);
    let mut learner = Learner::from_config(&config, n_actions, &mut rng);
    load_net(&st, "online", &mut learner.online)?;
    load_net(&st, "target", &mut learner.target)?;
    if adam_steps > 0 {
        for p in learner.online.params() {
            let mut m = Tensor::zeros(p.value.shape());
            let mut v = Tensor::zeros(p.value.shape());
            read_into(&st, &format!("adam.m.{}", p.name), &mut m)?;
            read_into(&st, &format!("adam.v.{}", p.name), &mut v)?;
            learner.adam.m.push(m);
            learner.adam.v.push(v);
        }
    }
    learner.adam.t = adam_steps;
    let k = config.pipeline.channels();
    let composite = tensor(
        &st,
        "observer.composite",
        Dtype::U8,
        &[FRAME_HEIGHT, FRAME_WIDTH],
    )?
    .data()
    .to_vec();
    let stack = tensor(
        &st,
        "observer.stack",
        Dtype::U8,
        &[k, FRAME_HEIGHT, FRAME_WIDTH],
    )?
    .data()
    .to_vec();
    let game = match st.tensor("game.state") {
        Ok(v) => {
            if v.dtype() != Dtype::U8 || v.shape().len() != 1 {
                bail!(
                    "tensor `game.state` has dtype {:?} and shape {:?}, expected U8 [n]",
                    v.dtype(),
                    v.shape()
                );
            }
            Some(v.data().to_vec())
        }
        Err(_) => None,
    };
    let nets = 2 * learner.online.params().count() * if adam_steps > 0 { 2 } else { 1 };
    let expected = nets + 2 + game.is_some() as usize;
    if st.len() != expected {
        let mut names = st.names();
        names.sort();
        bail!(
            "checkpoint has {} tensors, expected {expected} (found: {})",
            st.len(),
            names
                .iter()
                .map(|s| s.as_str())
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
    Ok(Checkpoint {
        config,
        counters,
        learner,
        agent: AgentState {
            explore_rng: rngs.explore,
            sample_rng: rngs.sample,
            composite,
            stack,
            game,
        },
        replay_file,
        replay_checksum,
    })
}

/// Loads a checkpoint file (not its replay memory: see [`load_run`]).
pub fn load(path: &Path) -> anyhow::Result<Checkpoint> {
    let bytes = std::fs::read(path)
        .with_context(|| format!("cannot read checkpoint {}", path.display()))?;
    from_bytes(&bytes).with_context(|| format!("{} is not a valid checkpoint", path.display()))
}

/// A trained network for playing: from a checkpoint or a weights-only model file.
pub struct Model {
    /// The configuration it was trained with (input pipeline, normalisation, game).
    pub config: Config,
    /// The training progress it was saved at.
    pub counters: Counters,
    /// The online network.
    pub online: Sequential<f32>,
    /// The number of actions.
    pub n_actions: usize,
}

/// Serialises the online network of a learner with its configuration and counters: a
/// weights-only model file (format [`MODEL_FORMAT`]).
pub fn model_to_bytes(
    config: &Config,
    counters: &Counters,
    learner: &Learner,
) -> anyhow::Result<Vec<u8>> {
    let mut tensors: Vec<(String, TensorView<'_>)> = Vec::new();
    for p in learner.online.params() {
        tensors.push((format!("online.{}", p.name), view(&p.value)?));
    }
    let mut counters_json = serde_json::to_value(counters)?;
    counters_json["adam_steps"] = learner.adam.t.into();
    let checksum = tensors_checksum(tensors.iter().map(|(n, v)| (n.as_str(), v.data())));
    let meta = HashMap::from([
        ("format".to_string(), MODEL_FORMAT.to_string()),
        ("checksum".to_string(), format!("{checksum:08x}")),
        ("config".to_string(), config.to_toml()),
        ("counters".to_string(), counters_json.to_string()),
    ]);
    Ok(safetensors::serialize(tensors, &Some(meta))?)
}

/// Parses a model file, or takes the online network of a checkpoint, checking everything.
pub fn model_from_bytes(bytes: &[u8]) -> anyhow::Result<Model> {
    let (st, meta) = parse(bytes)?;
    if meta_get(&meta, "format")? != MODEL_FORMAT {
        let c = from_bytes(bytes)?;
        let n_actions = c.learner.n_actions();
        return Ok(Model {
            config: c.config,
            counters: c.counters,
            online: c.learner.online,
            n_actions,
        });
    }
    verify_checksum(&st, &meta)?;
    let (config, counters, _, n_actions) = header(&st, &meta)?;
    let mut rng = <ChaCha8Rng as rand::SeedableRng>::seed_from_u64(0);
    let mut online = super::qnet(
        config.input_shape(),
        n_actions,
        super::Head::of(&config),
        &crate::layers::init::VarianceScaling::HE,
        &mut rng,
    );
    load_net(&st, "online", &mut online)?;
    let expected = online.params().count();
    if st.len() != expected {
        bail!("model file has {} tensors, expected {expected}", st.len());
    }
    Ok(Model {
        config,
        counters,
        online,
        n_actions,
    })
}

/// Loads a network to play with: a model file or a checkpoint.
pub fn load_model(path: &Path) -> anyhow::Result<Model> {
    let bytes =
        std::fs::read(path).with_context(|| format!("cannot read model {}", path.display()))?;
    model_from_bytes(&bytes)
        .with_context(|| format!("{} is not a valid checkpoint or model", path.display()))
}

/// The replay file name for a checkpoint at `counters`.
pub fn replay_file_name(counters: &Counters) -> String {
    format!("replay-{}.safetensors", counters.episodes)
}

/// Writes `replay` atomically to `path`, tagged with the checkpoint's counters, and returns its
/// checksum. The frames are streamed from the memory itself (no copy).
pub fn save_replay(path: &Path, replay: &Replay, counters: &Counters) -> anyhow::Result<u32> {
    let (frames, actions, rewards, flags) = replay.parts();
    let len = actions.len();
    let priorities = replay.priorities();
    let max_priority = priorities.as_ref().map(|p| [p.1]);
    let mut tensors = vec![
        (
            "replay.frames",
            TensorView::new(Dtype::U8, vec![len, FRAME_HEIGHT, FRAME_WIDTH], frames)?,
        ),
        (
            "replay.actions",
            TensorView::new(Dtype::U8, vec![len], actions)?,
        ),
        (
            "replay.rewards",
            TensorView::new(Dtype::F32, vec![len], bytemuck::cast_slice(rewards))?,
        ),
        (
            "replay.flags",
            TensorView::new(Dtype::U8, vec![len], &flags)?,
        ),
    ];
    if let (Some((values, _)), Some(max)) = (&priorities, &max_priority) {
        tensors.push((
            "replay.priorities",
            TensorView::new(Dtype::F64, vec![len], bytemuck::cast_slice(values))?,
        ));
        tensors.push((
            "replay.max_priority",
            TensorView::new(Dtype::F64, vec![1], bytemuck::cast_slice(max))?,
        ));
    }
    let checksum = tensors_checksum(tensors.iter().map(|(n, v)| (*n, v.data())));
    let meta = HashMap::from([
        ("format".to_string(), REPLAY_FORMAT.to_string()),
        ("checksum".to_string(), format!("{checksum:08x}")),
        ("written".to_string(), replay.written().to_string()),
        ("capacity".to_string(), replay.capacity().to_string()),
        (
            "frames_per_state".to_string(),
            replay.frames_per_state().to_string(),
        ),
        ("episodes".to_string(), counters.episodes.to_string()),
        ("agent_steps".to_string(), counters.agent_steps.to_string()),
    ]);
    write_atomic_with(path, |tmp| {
        safetensors::serialize_to_file(tensors, &Some(meta), tmp)?;
        Ok(())
    })?;
    Ok(checksum)
}

/// Parses a replay file saved with the checkpoint `ckpt`, checking that it belongs to it.
pub fn replay_from_bytes(bytes: &[u8], ckpt: &Checkpoint) -> anyhow::Result<Replay> {
    let (st, meta) = parse(bytes)?;
    let format = meta_get(&meta, "format")?;
    match (format, ckpt.replay_checksum) {
        (REPLAY_FORMAT, Some(named)) => {
            let actual = verify_checksum(&st, &meta)?;
            if actual != named {
                bail!(
                    "it is not the replay memory saved with this checkpoint (checksum {actual:08x}, the checkpoint names {named:08x}): was it copied from another run?"
                );
            }
        }
        (REPLAY_FORMAT_V1, None) => {} // both written before checksums
        (REPLAY_FORMAT | REPLAY_FORMAT_V1, _) => {
            bail!("it is not the replay memory saved with this checkpoint (their formats differ)")
        }
        _ => bail!("unknown replay format `{format}` (expected `{REPLAY_FORMAT}`)"),
    }
    let num = |k: &str| -> anyhow::Result<u64> {
        meta_get(&meta, k)?
            .parse()
            .map_err(|_| anyhow!("replay metadata `{k}` is not a number"))
    };
    let config = &ckpt.config;
    let k = config.pipeline.channels();
    if num("capacity")? != config.replay_capacity as u64 || num("frames_per_state")? != k as u64 {
        bail!("the replay memory's capacity or state size differs from the checkpoint's config");
    }
    let (episodes, steps) = (num("episodes")?, num("agent_steps")?);
    if (episodes, steps) != (ckpt.counters.episodes, ckpt.counters.agent_steps) {
        bail!(
            "the replay memory was saved at episode {episodes}, agent step {steps}, the checkpoint at episode {}, agent step {}",
            ckpt.counters.episodes,
            ckpt.counters.agent_steps
        );
    }
    let written = num("written")?;
    let len = written.min(config.replay_capacity as u64) as usize;
    let frames = tensor(
        &st,
        "replay.frames",
        Dtype::U8,
        &[len, FRAME_HEIGHT, FRAME_WIDTH],
    )?;
    let actions = tensor(&st, "replay.actions", Dtype::U8, &[len])?;
    let rewards = tensor(&st, "replay.rewards", Dtype::F32, &[len])?;
    let flags = tensor(&st, "replay.flags", Dtype::U8, &[len])?;
    let expected = if config.prioritized { 6 } else { 4 };
    if st.len() != expected {
        bail!("replay file has {} tensors, expected {expected}", st.len());
    }
    let n_actions = ckpt.learner.n_actions();
    if let Some(i) = actions.data().iter().position(|&a| a as usize >= n_actions) {
        bail!(
            "replay action {} in row {i} is out of range",
            actions.data()[i]
        );
    }
    let rewards: Vec<f32> = bytemuck::pod_collect_to_vec(rewards.data());
    let mut replay = config.new_replay();
    replay
        .restore(
            written,
            frames.data(),
            actions.data(),
            &rewards,
            flags.data(),
        )
        .map_err(|e| anyhow!("bad replay memory: {e}"))?;
    if config.prioritized {
        let values = tensor(&st, "replay.priorities", Dtype::F64, &[len])?;
        let values: Vec<f64> = bytemuck::pod_collect_to_vec(values.data());
        let max = tensor(&st, "replay.max_priority", Dtype::F64, &[1])?;
        let max: f64 = bytemuck::pod_read_unaligned(max.data());
        replay
            .restore_priorities(&values, max)
            .map_err(|e| anyhow!("bad replay priorities: {e}"))?;
    }
    Ok(replay)
}

/// Writes the agent's checkpoint into `dir`: the replay file first (if the config asks for it),
/// then `checkpoint.safetensors` naming it, then deletes replay files no longer named. A crash at
/// any point leaves a consistent pair; an error leaves the previous pair intact.
pub fn save_run<G: Game>(dir: &Path, agent: &Agent<G>) -> anyhow::Result<()> {
    let replay_name = agent
        .config
        .checkpoint_replay
        .then(|| replay_file_name(&agent.counters));
    let replay = match &replay_name {
        Some(name) => Some((
            name.as_str(),
            save_replay(&dir.join(name), &agent.replay, &agent.counters)?,
        )),
        None => None,
    };
    let bytes = to_bytes(
        &agent.config,
        &agent.counters,
        &agent.learner,
        &agent.state(),
        replay,
    )?;
    if let Err(e) = write_atomic(&dir.join(CHECKPOINT_FILE), &bytes) {
        if let Some(name) = &replay_name {
            let _ = std::fs::remove_file(dir.join(name));
        }
        return Err(e);
    }
    // Stale replay files (and temporaries of interrupted writes) are no longer referenced.
    if let Ok(entries) = std::fs::read_dir(dir) {
        for e in entries.flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            let stale_tmp = name.starts_with(".replay-") && name.ends_with(".tmp");
            if (is_replay_name(&name) && Some(&name) != replay_name.as_ref()) || stale_tmp {
                let _ = std::fs::remove_file(e.path());
            }
        }
    }
    Ok(())
}

/// Loads a run directory's checkpoint and the replay memory saved with it (if any).
pub fn load_run(dir: &Path) -> anyhow::Result<(Checkpoint, Option<Replay>)> {
    let ckpt = load(&dir.join(CHECKPOINT_FILE))?;
    let replay = match &ckpt.replay_file {
        None => None,
        Some(name) => {
            let path = dir.join(name);
            let bytes = std::fs::read(&path)
                .with_context(|| format!("cannot read replay memory {}", path.display()))?;
            Some(
                replay_from_bytes(&bytes, &ckpt)
                    .with_context(|| format!("{} is not a valid replay file", path.display()))?,
            )
        }
    };
    Ok((ckpt, replay))
}
