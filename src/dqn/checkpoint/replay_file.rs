//! `replay-E.safetensors` (format `invaders-replay-2`): the replay memory saved with a
//! checkpoint.

use super::*;

/// Whether `name` is a replay file name as [`save_run`] makes them (no directories).
pub(super) fn is_replay_name(name: &str) -> bool {
    name.strip_prefix("replay-")
        .and_then(|r| r.strip_suffix(".safetensors"))
        .is_some_and(|n| !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()))
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
