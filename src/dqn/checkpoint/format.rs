//! `checkpoint.safetensors` (format `invaders-checkpoint-3`, see the module above): its bytes
//! written and read back, with every check of [`super::from_bytes`].

use super::*;

#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct Rngs {
    explore: ChaCha8Rng,
    sample: ChaCha8Rng,
}

/// A PQN checkpoint's `pqn` metadata: every game's episode in progress and the finished
/// episodes' rows not yet handed out.
#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct PqnMeta {
    players: Vec<crate::dqn::Player>,
    finished: Vec<RowWire>,
}

/// An [`EpisodeRow`] in JSON: a NaN mean (no gradient step in the episode) as `null`.
#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct RowWire {
    episode: u64,
    agent_steps: u64,
    frames: u64,
    reward: f64,
    length: u64,
    epsilon: f32,
    mean_loss: Option<f32>,
    mean_max_q: Option<f32>,
    wall_seconds: f64,
}

/// A `$row` of `r`'s fields, the two means through `mean`: the one list of the fields both
/// ways.
macro_rules! convert {
    ($row:ident, $r:expr, $mean:expr) => {{
        let (r, mean) = ($r, $mean);
        $row {
            episode: r.episode,
            agent_steps: r.agent_steps,
            frames: r.frames,
            reward: r.reward,
            length: r.length,
            epsilon: r.epsilon,
            mean_loss: mean(r.mean_loss),
            mean_max_q: mean(r.mean_max_q),
            wall_seconds: r.wall_seconds,
        }
    }};
}

impl From<&EpisodeRow> for RowWire {
    fn from(r: &EpisodeRow) -> Self {
        convert!(RowWire, r, |v: f32| (!v.is_nan()).then_some(v))
    }
}

impl From<RowWire> for EpisodeRow {
    fn from(r: RowWire) -> Self {
        convert!(EpisodeRow, r, |v: Option<f32>| v.unwrap_or(f32::NAN))
    }
}

pub(super) fn view(t: &Tensor<f32>) -> Result<TensorView<'_>, safetensors::SafeTensorError> {
    TensorView::new(
        Dtype::F32,
        t.shape().to_vec(),
        bytemuck::cast_slice(t.data()),
    )
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
pub(super) fn verify_checksum(
    st: &SafeTensors<'_>, meta: &HashMap<String, String>,
) -> anyhow::Result<u32> {
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

pub(super) fn parse_checksum(text: &str) -> anyhow::Result<u32> {
    u32::from_str_radix(text, 16).map_err(|_| anyhow!("bad checksum `{text}`"))
}

/// Serialises a checkpoint to safetensors bytes; `replay` names the replay file saved with it,
/// and that file's checksum, if any.
pub fn to_bytes(
    config: &Config, counters: &Counters, learner: &Learner, agent: &AgentState,
    replay: Option<(&str, u32)>,
) -> anyhow::Result<Vec<u8>> {
    encode(config, counters, learner, agent, replay, false)
}

/// Serialises a snapshot (see the module's "Snapshots"): a checkpoint without the target
/// network, Adam's moments and the replay memory, a quarter of the size.
pub fn snapshot_to_bytes(
    config: &Config, counters: &Counters, learner: &Learner, agent: &AgentState,
) -> anyhow::Result<Vec<u8>> {
    encode(config, counters, learner, agent, None, true)
}

/// A checkpoint's bytes, or a snapshot's (`snapshot`: the online network only, Adam's step
/// count written as 0, and the metadata `contents = "snapshot"`).
fn encode(
    config: &Config, counters: &Counters, learner: &Learner, agent: &AgentState,
    replay: Option<(&str, u32)>, snapshot: bool,
) -> anyhow::Result<Vec<u8>> {
    // PQN's games after the first, as one array each (declared before the views of them).
    let others = &agent.other_games;
    let other_composites: Vec<u8> = others.iter().flat_map(|g| g.composite.clone()).collect();
    let other_stacks: Vec<u8> = others.iter().flat_map(|g| g.stack.clone()).collect();
    let mut tensors: Vec<(String, TensorView<'_>)> = Vec::new();
    let mut nets: Vec<(&str, &Sequential<f32>)> = vec![("online", &learner.online)];
    if let (false, Some(target)) = (snapshot, learner.target_if_any()) {
        nets.push(("target", target));
    }
    for (prefix, net) in nets {
        for p in net.params() {
            tensors.push((format!("{prefix}.{}", p.name), view(&p.value)?));
        }
    }
    for (i, p) in learner.online.params().enumerate() {
        if snapshot {
            break;
        }
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
    if !others.is_empty() {
        tensors.push((
            "pqn.observer.composite".into(),
            TensorView::new(
                Dtype::U8,
                vec![others.len(), FRAME_HEIGHT, FRAME_WIDTH],
                &other_composites,
            )?,
        ));
        tensors.push((
            "pqn.observer.stack".into(),
            TensorView::new(
                Dtype::U8,
                vec![others.len(), k, FRAME_HEIGHT, FRAME_WIDTH],
                &other_stacks,
            )?,
        ));
    }
    for (i, slot) in others.iter().enumerate() {
        if let Some(g) = &slot.game {
            tensors.push((
                format!("pqn.game.state.{}", i + 1),
                TensorView::new(Dtype::U8, vec![g.len()], g)?,
            ));
        }
    }
    let rngs = Rngs {
        explore: agent.explore_rng.clone(),
        sample: agent.sample_rng.clone(),
    };
    let adam_steps = if snapshot { 0 } else { learner.adam.t };
    let mut meta = make_header(FORMAT, &tensors, config, counters, adam_steps)?;
    if snapshot {
        meta.insert("contents".to_string(), SNAPSHOT_CONTENTS.to_string());
    }
    if config.pqn.is_some() || config.games > 1 {
        let pqn = PqnMeta {
            players: agent.players.clone(),
            finished: agent.finished.iter().map(RowWire::from).collect(),
        };
        meta.insert("pqn".to_string(), serde_json::to_string(&pqn)?);
    }
    meta.extend([
        ("rngs".to_string(), serde_json::to_string(&rngs)?),
        (
            "replay".to_string(),
            replay.map(|r| r.0).unwrap_or_default().to_string(),
        ),
        (
            "replay_checksum".to_string(),
            replay.map(|r| format!("{:08x}", r.1)).unwrap_or_default(),
        ),
        (
            "kernels".to_string(),
            crate::ops::plan::kernels(config.precision),
        ),
    ]);
    Ok(safetensors::serialize(tensors, &Some(meta))?)
}

/// The metadata a checkpoint and a model file start with (read back by [`header`]): the file's
/// `format`, the `checksum` of its tensors ([`tensors_checksum`], as hex), the `config` it
/// trained with (TOML) and its `counters` (JSON, with Adam's step count). A replay file has its
/// own.
pub(super) fn make_header(
    format: &str, tensors: &[(String, TensorView<'_>)], config: &Config, counters: &Counters,
    adam_steps: u64,
) -> anyhow::Result<HashMap<String, String>> {
    let mut counters_json = serde_json::to_value(counters)?;
    counters_json["adam_steps"] = adam_steps.into();
    let checksum = tensors_checksum(tensors.iter().map(|(n, v)| (n.as_str(), v.data())));
    Ok(HashMap::from([
        ("format".to_string(), format.to_string()),
        ("checksum".to_string(), format!("{checksum:08x}")),
        ("config".to_string(), config.to_toml()),
        ("counters".to_string(), counters_json.to_string()),
    ]))
}

/// Copies the named tensors into `net`'s parameters after checking every name, dtype and shape.
pub(super) fn load_net(
    st: &SafeTensors<'_>, prefix: &str, net: &mut Sequential<f32>,
) -> anyhow::Result<()> {
    for p in net.params_mut() {
        let name = format!("{prefix}.{}", p.name);
        read_into(st, &name, &mut p.value)?;
    }
    Ok(())
}

/// The tensor `name` after checking its dtype and shape.
pub(super) fn tensor<'a>(
    st: &'a SafeTensors<'_>, name: &str, dtype: Dtype, shape: &[usize],
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

pub(super) fn read_into(
    st: &SafeTensors<'_>, name: &str, t: &mut Tensor<f32>,
) -> anyhow::Result<()> {
    let v = tensor(st, name, Dtype::F32, t.shape())?;
    let values: Vec<f32> = bytemuck::pod_collect_to_vec(v.data());
    if let Some(bad) = values.iter().position(|x| !x.is_finite()) {
        bail!("tensor `{name}` holds a non-finite value at index {bad}");
    }
    t.data_mut().copy_from_slice(&values);
    Ok(())
}

/// Parses a safetensors file with metadata; returns the tensors and a metadata getter.
pub(super) fn parse(bytes: &[u8]) -> anyhow::Result<(SafeTensors<'_>, HashMap<String, String>)> {
    let (_, header) =
        SafeTensors::read_metadata(bytes).map_err(|e| anyhow!("not a safetensors file: {e}"))?;
    let st = SafeTensors::deserialize(bytes).map_err(|e| anyhow!("not a safetensors file: {e}"))?;
    let meta = header
        .metadata()
        .clone()
        .ok_or_else(|| anyhow!("no metadata"))?;
    Ok((st, meta))
}

pub(super) fn meta_get<'a>(meta: &'a HashMap<String, String>, k: &str) -> anyhow::Result<&'a str> {
    meta.get(k)
        .map(String::as_str)
        .ok_or_else(|| anyhow!("metadata has no `{k}`"))
}

/// The configuration, counters, Adam's step count and action count recorded in a checkpoint's or
/// model file's metadata, checked.
pub(super) fn header(
    st: &SafeTensors<'_>, meta: &HashMap<String, String>,
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
    let snapshot = match meta.get("contents").map(String::as_str) {
        None => false,
        Some(SNAPSHOT_CONTENTS) => true,
        Some(other) => {
            bail!("unknown checkpoint contents `{other}` (expected `{SNAPSHOT_CONTENTS}` or none)")
        }
    };
    if snapshot && adam_steps != 0 {
        bail!("a snapshot holds no optimizer state, yet its counters give Adam {adam_steps} steps");
    }
    let rngs: Rngs =
        serde_json::from_str(meta_get(&meta, "rngs")?).context("checkpoint random generators")?;
    let replay_file = match meta_get(&meta, "replay")? {
        "" => None,
        name if is_replay_name(name) => Some(name.to_string()),
        name => bail!("checkpoint names a bad replay file `{name}`"),
    };
    let kernels = meta.get("kernels").cloned();
    let replay_checksum = match (format == FORMAT, &replay_file) {
        (true, Some(_)) => Some(parse_checksum(meta_get(&meta, "replay_checksum")?)?),
        _ => None,
    };
    // The initial weights are overwritten below; any generator will do.
    let mut rng = <ChaCha8Rng as rand::SeedableRng>::seed_from_u64(0);
    let mut learner = Learner::from_config(&config, n_actions, &mut rng);
    load_net(&st, "online", &mut learner.online)?;
    let has_target = learner.target_if_any().is_some();
    if snapshot {
        // The target network starts as the online one (as after a copy, ALGO 7).
        learner.update_target();
    } else if has_target {
        load_net(&st, "target", learner.target_mut())?;
    }
    // A PQN learner has no target network; a PQN checkpoint written before it lost its own
    // holds one, which is read past.
    let old_target = match has_target {
        true => 0,
        false => st
            .names()
            .iter()
            .filter(|n| n.starts_with("target."))
            .count(),
    };
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
    let (other_games, players, finished) = read_pqn(&st, &meta, &config)?;
    let pqn_tensors = other_games.iter().filter(|g| g.game.is_some()).count()
        + if other_games.is_empty() { 0 } else { 2 };
    // A snapshot holds the online network only; a checkpoint also the target network (where the
    // learner has one) and, once Adam stepped, its two moments.
    let copies = match snapshot {
        true => 1,
        false => 1 + usize::from(has_target) + 2 * usize::from(adam_steps > 0),
    };
    let nets = copies * learner.online.params().count() + old_target;
    let expected = nets + 2 + game.is_some() as usize + pqn_tensors;
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
            other_games,
            players,
            finished,
        },
        replay_file,
        replay_checksum,
        kernels,
        snapshot,
    })
}

/// The games after the first of a PQN checkpoint, or of a DQN run playing [`Config::games`] side
/// by side, every game's episode in progress and the rows not yet handed out (the `pqn.*`
/// tensors and the `pqn` metadata, named for PQN, which had them first); all empty for a
/// one-game DQN run, whose checkpoint must have none of them.
#[allow(clippy::type_complexity)]
fn read_pqn(
    st: &SafeTensors<'_>, meta: &HashMap<String, String>, config: &Config,
) -> anyhow::Result<(Vec<GameSlot>, Vec<crate::dqn::Player>, Vec<EpisodeRow>)> {
    let games = match config.pqn {
        Some(pqn) => pqn.games,
        None if config.games > 1 => config.games,
        None => {
            if meta.contains_key("pqn") {
                bail!("the checkpoint holds the state of several games (PQN's, or games side by side), and its config plays one");
            }
            return Ok((Vec::new(), Vec::new(), Vec::new()));
        }
    };
    let saved: PqnMeta =
        serde_json::from_str(meta_get(meta, "pqn")?).context("checkpoint's games' state")?;
    if saved.players.len() != games {
        bail!(
            "the checkpoint's state has {} games, its config {games}",
            saved.players.len(),
        );
    }
    let n = games - 1;
    let mut others = Vec::with_capacity(n);
    if n > 0 {
        let k = config.pipeline.channels();
        let composites = tensor(
            st,
            "pqn.observer.composite",
            Dtype::U8,
            &[n, FRAME_HEIGHT, FRAME_WIDTH],
        )?;
        let stacks = tensor(
            st,
            "pqn.observer.stack",
            Dtype::U8,
            &[n, k, FRAME_HEIGHT, FRAME_WIDTH],
        )?;
        for (g, (composite, stack)) in composites
            .data()
            .chunks_exact(FRAME_LEN)
            .zip(stacks.data().chunks_exact(k * FRAME_LEN))
            .enumerate()
        {
            let name = format!("pqn.game.state.{}", g + 1);
            let game = match st.tensor(&name) {
                Ok(v) if v.dtype() == Dtype::U8 && v.shape().len() == 1 => Some(v.data().to_vec()),
                Ok(v) => bail!(
                    "tensor `{name}` has dtype {:?} and shape {:?}, expected U8 [n]",
                    v.dtype(),
                    v.shape()
                ),
                Err(_) => None,
            };
            others.push(GameSlot {
                composite: composite.to_vec(),
                stack: stack.to_vec(),
                game,
            });
        }
    }
    let finished = saved.finished.into_iter().map(EpisodeRow::from).collect();
    Ok((others, saved.players, finished))
}

/// The most bytes a checkpoint or model file may have: far above any real one (a `strong`
/// checkpoint, with its target network and Adam's moments, is 16 MB), so that a replay memory
/// named by mistake, or `/dev/zero`, is an error and not gigabytes read for nothing.
pub const MAX_CHECKPOINT_BYTES: u64 = 1 << 30;

/// Opens a file that must be a regular one (`what` names it in messages), checked on the path
/// before opening (opening a FIFO would block until a writer came) and again on the open file
/// (the path may have been swapped since); returns it with its length.
pub(crate) fn open_regular_file(path: &Path, what: &str) -> anyhow::Result<(std::fs::File, u64)> {
    let cannot = || format!("cannot read {what} {}", path.display());
    let not_regular = || anyhow!("{what} {} is not a regular file", path.display());
    if !std::fs::metadata(path).with_context(cannot)?.is_file() {
        return Err(not_regular());
    }
    let file = std::fs::File::open(path).with_context(cannot)?;
    let meta = file.metadata().with_context(cannot)?;
    if !meta.is_file() {
        return Err(not_regular());
    }
    Ok((file, meta.len()))
}

/// Reads a checkpoint or model file whole (`what` names it in messages): a regular file only
/// ([`open_regular_file`]; a device such as `/dev/zero` has no end) of at most
/// [`MAX_CHECKPOINT_BYTES`].
pub(crate) fn read_checkpoint_file(path: &Path, what: &str) -> anyhow::Result<Vec<u8>> {
    use std::io::Read;
    let (file, len) = open_regular_file(path, what)?;
    let mut bytes = Vec::new();
    if len <= MAX_CHECKPOINT_BYTES {
        bytes.reserve_exact(len as usize);
        // At most one byte more than the limit, should the file have grown since.
        file.take(MAX_CHECKPOINT_BYTES + 1)
            .read_to_end(&mut bytes)
            .with_context(|| format!("cannot read {what} {}", path.display()))?;
    }
    if len > MAX_CHECKPOINT_BYTES || bytes.len() as u64 > MAX_CHECKPOINT_BYTES {
        bail!(
            "{what} {} is larger than {} MiB: not a checkpoint or model this program wrote",
            path.display(),
            MAX_CHECKPOINT_BYTES >> 20
        );
    }
    Ok(bytes)
}

/// Loads a checkpoint file (not its replay memory: see [`load_run`]).
pub fn load(path: &Path) -> anyhow::Result<Checkpoint> {
    let bytes = read_checkpoint_file(path, "checkpoint")?;
    from_bytes(&bytes).with_context(|| format!("{} is not a valid checkpoint", path.display()))
}
