//! Checkpoints: everything needed to evaluate or continue a run, in one safetensors file.
//!
//! Layout (all tensors little-endian `F32`, shapes as in the layers, so NumPy and PyTorch read them
//! with `safetensors.numpy.load_file` / `safetensors.torch.load_file`):
//!
//! | tensor | shape |
//! | --- | --- |
//! | `online.conv1.weight` | `[8, 8, C, 32]` (HWIO: height, width, in, out) |
//! | `online.conv1.bias` | `[32]` |
//! | `online.conv2.weight`, `.bias` | `[4, 4, 32, 64]`, `[64]` |
//! | `online.conv3.weight`, `.bias` | `[3, 3, 64, 64]`, `[64]` |
//! | `online.dense1.weight`, `.bias` | `[7040, 128]` (in, out; inputs in NHWC flatten order), `[128]` |
//! | `online.dense2.weight`, `.bias` | `[128, A]`, `[A]` |
//! | `target.*` | the target network, same names |
//! | `adam.m.*`, `adam.v.*` | Adam's first and second moments, same names as `online.*` |
//!
//! Metadata (strings): `format` (`invaders-checkpoint-1`), `config` (the run's resolved TOML),
//! `counters` (JSON: episodes, agent steps, emulator frames, train steps, Adam's step count, wall
//! seconds). Files are written atomically: to a temporary file in the same directory, flushed
//! to disk, then renamed over the old one, so a crash leaves either the old or the new checkpoint,
//! never half of one.

use super::{Config, Learner};
use crate::layers::Sequential;
use crate::tensor::Tensor;
use anyhow::{anyhow, bail, Context};
use safetensors::tensor::TensorView;
use safetensors::{Dtype, SafeTensors};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::io::Write;
use std::path::Path;

/// The format tag stored in every checkpoint.
pub const FORMAT: &str = "invaders-checkpoint-1";

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

/// A loaded checkpoint.
pub struct Checkpoint {
    /// The run's configuration.
    pub config: Config,
    /// Its counters.
    pub counters: Counters,
    /// The networks and optimizer.
    pub learner: Learner,
}

fn view(t: &Tensor<f32>) -> Result<TensorView<'_>, safetensors::SafeTensorError> {
    TensorView::new(
        Dtype::F32,
        t.shape().to_vec(),
        bytemuck::cast_slice(t.data()),
    )
}

/// Writes `bytes` to `path` atomically (temporary file, fsync, rename, fsync of the directory).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> anyhow::Result<()> {
    let dir = path
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let name = path
        .file_name()
        .ok_or_else(|| anyhow!("{} is not a file path", path.display()))?;
    let tmp = dir.join(format!(".{}.tmp", name.to_string_lossy()));
    let result = (|| -> std::io::Result<()> {
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(bytes)?;
        f.sync_all()?;
        drop(f);
        std::fs::rename(&tmp, path)?;
        if let Ok(d) = std::fs::File::open(dir) {
            let _ = d.sync_all();
        }
        Ok(())
    })();
    if let Err(e) = result {
        let _ = std::fs::remove_file(&tmp);
        return Err(e).with_context(|| format!("cannot write {}", path.display()));
    }
    Ok(())
}

/// Serialises the learner, config and counters to safetensors bytes.
pub fn to_bytes(
    config: &Config,
    counters: &Counters,
    learner: &Learner,
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
    let mut counters_json = serde_json::to_value(counters)?;
    counters_json["adam_steps"] = learner.adam.t.into();
    let meta = HashMap::from([
        ("format".to_string(), FORMAT.to_string()),
        ("config".to_string(), config.to_toml()),
        ("counters".to_string(), counters_json.to_string()),
    ]);
    Ok(safetensors::serialize(tensors, &Some(meta))?)
}

/// Saves a checkpoint atomically.
pub fn save(
    path: &Path,
    config: &Config,
    counters: &Counters,
    learner: &Learner,
) -> anyhow::Result<()> {
    write_atomic(path, &to_bytes(config, counters, learner)?)
}

/// Copies the named tensors into `net`'s parameters after checking every name, dtype and shape.
fn load_net(st: &SafeTensors<'_>, prefix: &str, net: &mut Sequential<f32>) -> anyhow::Result<()> {
    for p in net.params_mut() {
        let name = format!("{prefix}.{}", p.name);
        read_into(st, &name, &mut p.value)?;
    }
    Ok(())
}

fn read_into(st: &SafeTensors<'_>, name: &str, t: &mut Tensor<f32>) -> anyhow::Result<()> {
    let v = st
        .tensor(name)
        .map_err(|_| anyhow!("checkpoint has no tensor `{name}`"))?;
    if v.dtype() != Dtype::F32 {
        bail!("tensor `{name}` has dtype {:?}, expected F32", v.dtype());
    }
    if v.shape() != t.shape() {
        bail!(
            "tensor `{name}` has shape {:?}, expected {:?}",
            v.shape(),
            t.shape()
        );
    }
    let values: Vec<f32> = bytemuck::pod_collect_to_vec(v.data());
    if let Some(bad) = values.iter().position(|x| !x.is_finite()) {
        bail!("tensor `{name}` holds a non-finite value at index {bad}");
    }
    t.data_mut().copy_from_slice(&values);
    Ok(())
}

/// Parses checkpoint bytes into a fresh learner; nothing is modified unless every check passes.
pub fn from_bytes(bytes: &[u8]) -> anyhow::Result<Checkpoint> {
    let (_, header) =
        SafeTensors::read_metadata(bytes).map_err(|e| anyhow!("not a safetensors file: {e}"))?;
    let st = SafeTensors::deserialize(bytes).map_err(|e| anyhow!("not a safetensors file: {e}"))?;
    let meta = header
        .metadata()
        .as_ref()
        .ok_or_else(|| anyhow!("checkpoint has no metadata"))?;
    let get = |k: &str| {
        meta.get(k)
            .ok_or_else(|| anyhow!("checkpoint metadata has no `{k}`"))
    };
    let format = get("format")?;
    if format != FORMAT {
        bail!("unknown checkpoint format `{format}` (expected `{FORMAT}`)");
    }
    let config: Config = toml::from_str(get("config")?).context("checkpoint config")?;
    config.validate().context("checkpoint config")?;
    let json: serde_json::Value =
        serde_json::from_str(get("counters")?).context("checkpoint counters")?;
    let adam_steps = json
        .get("adam_steps")
        .and_then(|v| v.as_u64())
        .ok_or_else(|| anyhow!("checkpoint counters lack adam_steps"))?;
    let mut json = json;
    json.as_object_mut().map(|o| o.remove("adam_steps"));
    let counters: Counters = serde_json::from_value(json).context("checkpoint counters")?;
    let n_actions = st
        .tensor("online.dense2.bias")
        .map_err(|_| anyhow!("checkpoint has no tensor `online.dense2.bias`"))?
        .shape()
        .first()
        .copied()
        .unwrap_or(0);
    if n_actions == 0 || n_actions > 18 {
        bail!("checkpoint has {n_actions} actions");
    }
    // The initial weights are overwritten below; any generator will do.
    let mut rng = <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(0);
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
    let expected = 2 * learner.online.params().count() * if adam_steps > 0 { 2 } else { 1 };
    if st.len() != expected {
        bail!("checkpoint has {} tensors, expected {expected}", st.len());
    }
    Ok(Checkpoint {
        config,
        counters,
        learner,
    })
}

/// Loads a checkpoint file.
pub fn load(path: &Path) -> anyhow::Result<Checkpoint> {
    let bytes = std::fs::read(path)
        .with_context(|| format!("cannot read checkpoint {}", path.display()))?;
    from_bytes(&bytes).with_context(|| format!("{} is not a valid checkpoint", path.display()))
}
