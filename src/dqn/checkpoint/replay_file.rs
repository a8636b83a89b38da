//! `replay-E.safetensors` (format `invaders-replay-2`): the replay memory saved with a
//! checkpoint.

use super::*;
use safetensors::tensor::{Metadata, TensorInfo};
use std::io::{Read, Seek, SeekFrom};

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
    let mut meta = HashMap::from([
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
    if replay.lanes() > 1 {
        // Each lane's own counter, as `lane_written = "w0,w1,…"`.
        let each: Vec<String> = replay.lane_written().iter().map(u64::to_string).collect();
        meta.insert("lane_written".to_string(), each.join(","));
    }
    write_atomic_with(path, |tmp| {
        // The operating system's error as itself (a full disk says so), not as the library's
        // `IoError(Os { … })`.
        safetensors::serialize_to_file(tensors, &Some(meta), tmp).map_err(|e| match e {
            safetensors::SafeTensorError::IoError(io) => anyhow::Error::from(io),
            e => anyhow::anyhow!("{e}"),
        })
    })?;
    Ok(checksum)
}

/// Parses a replay file saved with the checkpoint `ckpt` (its bytes in memory), checking that
/// it belongs to it: [`read_replay`] over the bytes.
pub fn replay_from_bytes(bytes: &[u8], ckpt: &Checkpoint) -> anyhow::Result<Replay> {
    read_replay(std::io::Cursor::new(bytes), bytes.len() as u64, ckpt)
}

/// Bytes of frames read per call while streaming them into the memory.
const CHUNK: usize = 8 << 20;

/// The largest JSON header accepted (safetensors' own limit).
const MAX_HEADER: u64 = 100_000_000;

/// Reads a replay file of `file_len` bytes saved with the checkpoint `ckpt` from `source`,
/// checking that it belongs to it. The frames, nearly all of the file, are read in chunks
/// straight into the new memory's own buffer while their checksum is computed, so loading holds
/// the memory once, not the file and the memory (a million entries are 7 GB).
pub fn read_replay<R: Read + Seek>(
    mut source: R, file_len: u64, ckpt: &Checkpoint,
) -> anyhow::Result<Replay> {
    let not_st = |why: String| anyhow!("not a safetensors file: {why}");
    // The header: an 8-byte length, then that many bytes of JSON.
    let mut n = [0u8; 8];
    source
        .read_exact(&mut n)
        .map_err(|_| not_st("shorter than its 8-byte header length".into()))?;
    let n = u64::from_le_bytes(n);
    if n > MAX_HEADER || 8 + n > file_len {
        return Err(not_st(format!(
            "a header of {n} bytes in a file of {file_len}"
        )));
    }
    let mut header = vec![0u8; n as usize];
    source.read_exact(&mut header)?;
    let header: Metadata = std::str::from_utf8(&header)
        .ok()
        .and_then(|h| serde_json::from_str(h).ok())
        .ok_or_else(|| not_st("its header is not valid JSON metadata".into()))?;
    let data_start = 8 + n;
    // Every tensor's bytes, in file order, must tile the rest of the file.
    let mut infos: Vec<(String, &TensorInfo)> = header.tensors().into_iter().collect();
    infos.sort_by_key(|(_, i)| i.data_offsets);
    let mut end = 0u64;
    for (name, info) in &infos {
        let (a, b) = (info.data_offsets.0 as u64, info.data_offsets.1 as u64);
        let size = info
            .shape
            .iter()
            .try_fold(info.dtype.size() as u64, |s, &d| s.checked_mul(d as u64));
        if a != end || size.is_none() || b.checked_sub(a) != size {
            return Err(not_st(format!("tensor `{name}` has bad offsets")));
        }
        end = b;
    }
    if data_start.checked_add(end) != Some(file_len) {
        return Err(not_st(format!(
            "its tensors end {end} bytes past its {data_start}-byte header, the file at byte {file_len}"
        )));
    }
    let meta = header
        .metadata()
        .clone()
        .ok_or_else(|| anyhow!("no metadata"))?;
    let format = meta_get(&meta, "format")?;
    let stored = match (format, ckpt.replay_checksum) {
        (REPLAY_FORMAT, Some(_)) => Some(parse_checksum(meta_get(&meta, "checksum")?)?),
        (REPLAY_FORMAT_V1, None) => None, // both written before checksums
        (REPLAY_FORMAT | REPLAY_FORMAT_V1, _) => {
            bail!("it is not the replay memory saved with this checkpoint (their formats differ)")
        }
        _ => bail!("unknown replay format `{format}` (expected `{REPLAY_FORMAT}`)"),
    };
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
    let mut replay = config.new_replay();
    let lanes = replay.lanes();
    let lane_written: Vec<u64> = if lanes == 1 {
        vec![written]
    } else {
        meta_get(&meta, "lane_written")?
            .split(',')
            .map(|w| w.parse().ok())
            .collect::<Option<_>>()
            .ok_or_else(|| anyhow!("replay metadata `lane_written` is not a list of numbers"))?
    };
    if lane_written.len() != lanes || lane_written.iter().sum::<u64>() != written {
        bail!("the replay memory's lanes differ from the checkpoint's config ({lanes} games)");
    }
    let lane_capacity = (config.replay_capacity / lanes) as u64;
    let longest = lane_written.iter().map(|&w| w.min(lane_capacity)).max();
    let len = longest.unwrap_or(0) as usize * lanes;
    let mut expected = vec![
        (
            "replay.frames",
            Dtype::U8,
            vec![len, FRAME_HEIGHT, FRAME_WIDTH],
        ),
        ("replay.actions", Dtype::U8, vec![len]),
        ("replay.rewards", Dtype::F32, vec![len]),
        ("replay.flags", Dtype::U8, vec![len]),
    ];
    if config.prioritized {
        expected.push(("replay.priorities", Dtype::F64, vec![len]));
        expected.push(("replay.max_priority", Dtype::F64, vec![1]));
    }
    for (name, dtype, shape) in &expected {
        let info = header
            .info(name)
            .ok_or_else(|| anyhow!("no tensor `{name}`"))?;
        if info.dtype != *dtype {
            bail!(
                "tensor `{name}` has dtype {:?}, expected {dtype:?}",
                info.dtype
            );
        }
        if info.shape != *shape {
            bail!(
                "tensor `{name}` has shape {:?}, expected {shape:?}",
                info.shape
            );
        }
    }
    if infos.len() != expected.len() {
        bail!(
            "replay file has {} tensors, expected {}",
            infos.len(),
            expected.len()
        );
    }
    // The small arrays into memory; the frames are streamed below.
    let mut small: HashMap<&str, Vec<u8>> = HashMap::new();
    for (name, ..) in expected.iter().filter(|e| e.0 != "replay.frames") {
        let (a, b) = header.info(name).expect("checked").data_offsets;
        let mut bytes = vec![0u8; b - a];
        source.seek(SeekFrom::Start(data_start + a as u64))?;
        source.read_exact(&mut bytes)?;
        small.insert(name, bytes);
    }
    let actions = &small["replay.actions"];
    let n_actions = ckpt.learner.n_actions();
    if let Some(i) = actions.iter().position(|&a| a as usize >= n_actions) {
        bail!("replay action {} in row {i} is out of range", actions[i]);
    }
    let rewards: Vec<f32> = bytemuck::pod_collect_to_vec(&small["replay.rewards"]);
    // The checksum runs over the tensors in name order, the frames' chunks as they arrive.
    let mut names: Vec<&str> = expected.iter().map(|e| e.0).collect();
    names.sort();
    let mut crc = crc32fast::Hasher::new();
    replay
        .restore(
            &lane_written,
            actions,
            &rewards,
            &small["replay.flags"],
            |frames| -> Result<(), String> {
                let io = |e: std::io::Error| format!("cannot read its frames: {e}");
                for name in names {
                    crc.update(name.as_bytes());
                    if name != "replay.frames" {
                        crc.update(&small[name]);
                        continue;
                    }
                    let at = header.info(name).expect("checked").data_offsets.0 as u64;
                    source.seek(SeekFrom::Start(data_start + at)).map_err(io)?;
                    for chunk in frames.chunks_mut(CHUNK) {
                        source.read_exact(chunk).map_err(io)?;
                        crc.update(chunk);
                    }
                }
                Ok(())
            },
        )
        .map_err(|e| anyhow!("bad replay memory: {e}"))?;
    if let Some(stored) = stored {
        let actual = crc.finalize();
        if actual != stored {
            bail!(
                "its contents are damaged: checksum {actual:08x}, but the file was written with {stored:08x}"
            );
        }
        let named = ckpt.replay_checksum.expect("matched above");
        if actual != named {
            bail!(
                "it is not the replay memory saved with this checkpoint (checksum {actual:08x}, the checkpoint names {named:08x}): was it copied from another run?"
            );
        }
    }
    if config.prioritized {
        let values: Vec<f64> = bytemuck::pod_collect_to_vec(&small["replay.priorities"]);
        let max: f64 = bytemuck::pod_read_unaligned(&small["replay.max_priority"]);
        replay
            .restore_priorities(&values, max)
            .map_err(|e| anyhow!("bad replay priorities: {e}"))?;
    }
    Ok(replay)
}
