//! A run directory's checkpoint pair: the replay file, then the checkpoint that names it.

use super::*;

/// Writes the agent's checkpoint into `dir`: the replay file first (if the agent has a replay
/// memory and the config asks for it), then `checkpoint.safetensors` naming it, then deletes
/// replay files no longer named. A crash at any point leaves a consistent pair; an error leaves
/// the previous pair intact.
pub fn save_run<T: Trainer + ?Sized>(dir: &Path, agent: &T) -> anyhow::Result<()> {
    let (config, counters) = (agent.config(), agent.counters());
    let memory = agent.replay().filter(|_| config.checkpoint_replay);
    let replay_name = memory.map(|_| replay_file_name(counters));
    let replay = match (&replay_name, memory) {
        (Some(name), Some(memory)) => Some((
            name.as_str(),
            save_replay(&dir.join(name), memory, counters)?,
        )),
        _ => None,
    };
    let bytes = to_bytes(config, counters, agent.learner(), &agent.state(), replay)?;
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
    let replay = load_run_replay(dir, &ckpt)?;
    Ok((ckpt, replay))
}

/// Loads the replay memory that `ckpt`, the checkpoint of the run directory `dir`, names (if
/// any): what [`load_run`] does after loading the checkpoint, for a caller that checks the
/// checkpoint before reading a file that may be gigabytes.
pub fn load_run_replay(dir: &Path, ckpt: &Checkpoint) -> anyhow::Result<Option<Replay>> {
    let Some(name) = &ckpt.replay_file else {
        return Ok(None);
    };
    let path = dir.join(name);
    // Streamed from the file into the memory: the file is as large as the memory.
    let (file, len) = open_regular_file(&path, "replay memory")?;
    let replay = read_replay(file, len, ckpt)
        .with_context(|| format!("{} is not a valid replay file", path.display()))?;
    Ok(Some(replay))
}

/// Writes the agent's snapshot ([`snapshot_to_bytes`]) to `path`, atomically: a file to keep
/// where the run directory is not (the module's "Snapshots").
pub fn save_snapshot<T: Trainer + ?Sized>(path: &Path, agent: &T) -> anyhow::Result<()> {
    let bytes = snapshot_to_bytes(
        agent.config(),
        agent.counters(),
        agent.learner(),
        &agent.state(),
    )?;
    write_atomic(path, &bytes)
}
