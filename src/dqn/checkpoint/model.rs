//! A weights-only model file (format `invaders-model-1`): what `invaders export` writes and
//! `eval` reads.

use super::*;

/// The network file of a shipped model's folder (`models/strong/model.safetensors`).
pub const MODEL_FILE: &str = "model.safetensors";

/// The network file that `path` names for `eval`, `export` and `bench --checkpoint`: `path`
/// itself when it is a file; in a folder, a run's checkpoint ([`CHECKPOINT_FILE`]) or else a
/// shipped model's network ([`MODEL_FILE`]). A folder holding neither is an error naming both.
pub fn network_file(path: &Path) -> anyhow::Result<std::path::PathBuf> {
    if !path.is_dir() {
        return Ok(path.to_path_buf());
    }
    let run = path.join(CHECKPOINT_FILE);
    let model = path.join(MODEL_FILE);
    if run.exists() || !model.exists() {
        if !run.exists() {
            bail!(
                "{} holds no network: neither a run's {CHECKPOINT_FILE} nor a model's {MODEL_FILE}",
                path.display()
            );
        }
        return Ok(run);
    }
    Ok(model)
}

/// The bytes of `path` if it is a weights-only model file (format [`MODEL_FORMAT`]), checked
/// whole; `None` if it is a checkpoint (or anything else, which [`load`] then refuses). Read as
/// [`load`] reads: a regular file of bounded size only, so `/dev/zero` is refused, not read.
pub fn read_model_file(path: &Path) -> anyhow::Result<Option<(Vec<u8>, Model)>> {
    let bytes = read_checkpoint_file(path, "model")?;
    let is_model = parse(&bytes)
        .is_ok_and(|(_, meta)| meta_get(&meta, "format").is_ok_and(|f| f == MODEL_FORMAT));
    if !is_model {
        return Ok(None);
    }
    let model = model_from_bytes(&bytes)
        .with_context(|| format!("{} is not a valid model", path.display()))?;
    Ok(Some((bytes, model)))
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
    config: &Config, counters: &Counters, learner: &Learner,
) -> anyhow::Result<Vec<u8>> {
    let mut tensors: Vec<(String, TensorView<'_>)> = Vec::new();
    for p in learner.online.params() {
        tensors.push((format!("online.{}", p.name), view(&p.value)?));
    }
    let meta = make_header(MODEL_FORMAT, &tensors, config, counters, learner.adam.t)?;
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
    let mut online = crate::dqn::qnet(
        config.input_shape(),
        n_actions,
        crate::dqn::Head::of(&config),
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
    let bytes = read_checkpoint_file(path, "model")?;
    model_from_bytes(&bytes)
        .with_context(|| format!("{} is not a valid checkpoint or model", path.display()))
}
