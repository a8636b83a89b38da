//! What a run directory holds, and what belongs to it: the files `train` writes there, how a
//! directory is made ready for a new run, and how a run stopped before its first checkpoint is
//! told from one whose checkpoint is lost.

use std::path::Path;

use anyhow::{bail, Context};

use super::guard;
use invaders::dqn::checkpoint;
use invaders::dqn::{Config, Preset};

/// The files a run writes into its directory: a directory holding nothing else, and no
/// checkpoint, can be reused by a new run.
pub const RUN_FILES: [&str; 5] = [
    "config.toml",
    "metrics.csv",
    "rewards.png",
    CONTINUED_FILE,
    guard::LOCK_FILE,
];

/// The file where a run notes each time it continued from a snapshot (module `checkpoint`'s
/// "Snapshots"): a header, then `episode,agent_steps,frames` of each continuation.
pub const CONTINUED_FILE: &str = "continued.csv";

/// Makes `dir` ready for a new run and locks it: it is created, or it is empty, or it holds only
/// what a run that never reached its first checkpoint wrote (then that is cleared). A directory
/// holding a run (its checkpoint, or the traces of one that was lost) or anything else is refused.
pub(super) fn prepare_new_dir(dir: &Path) -> anyhow::Result<guard::RunLock> {
    if dir.exists() && !dir.is_dir() {
        bail!("--out {} is a file, not a directory", dir.display());
    }
    let names = match std::fs::read_dir(dir) {
        Ok(_) => dir_names(dir)?,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Vec::new(),
        Err(e) => return Err(e).with_context(|| format!("cannot read {}", dir.display())),
    };
    if names.iter().any(|n| n == checkpoint::CHECKPOINT_FILE) {
        bail!(
            "run directory {} is not empty: it holds a run; choose another --out, or continue it with --resume {}",
            dir.display(),
            dir.display()
        );
    }
    let d = dir.display();
    refuse_foreign_or_lost(
        dir,
        &names,
        |other| {
            format!("run directory {d} is not empty (it holds `{other}`); choose another --out")
        },
        |lost| {
            format!("run directory {d} holds a run whose checkpoint is lost ({lost}); its files are left as they are: choose another --out")
        },
    )?;
    std::fs::create_dir_all(dir)
        .with_context(|| format!("cannot create run directory {}", dir.display()))?;
    let lock = guard::RunLock::acquire(dir)?;
    if names.iter().any(|n| n != guard::LOCK_FILE) {
        say!(
            "{} holds a run stopped before its first checkpoint: starting anew in it",
            dir.display()
        );
        clear_run_files(dir)?;
    }
    Ok(lock)
}

/// For `--resume DIR` where DIR has no checkpoint: the configuration to start the run again
/// with, from its `config.toml`, if DIR is a run stopped before its first checkpoint. Refused if
/// its checkpoint was written and is now lost (the run's history stays as it is), or if DIR holds
/// files a run does not write.
pub(super) fn restart_unsaved(dir: &Path, preset: Option<Preset>) -> anyhow::Result<Config> {
    let names = dir_names(dir)?;
    let saved = dir.join("config.toml");
    if !saved.is_file() {
        bail!(
            "{} holds no checkpoint and no config.toml: there is no run to resume",
            dir.display()
        );
    }
    // Starting again clears the run's files: only where the directory holds nothing else (a
    // model exported beside its config.toml, say, is not a stopped run).
    let (d, ckpt) = (dir.display(), checkpoint::CHECKPOINT_FILE);
    refuse_foreign_or_lost(
        dir,
        &names,
        |other| {
            format!("{d} holds no checkpoint, and {other}, which a run does not write: it is not a stopped run, so it is not resumed (a weights-only model plays with `eval --checkpoint`; train a new run with --out)")
        },
        |lost| {
            format!("{d} holds no {ckpt}, but its run had one ({lost}): the checkpoint is lost, so the run cannot continue; its files are left as they are (restore the checkpoint, or train a new run with --out)")
        },
    )?;
    let text = guard::read_text(&saved, "the run's configuration")?;
    Config::resolve(preset, Some(&text)).with_context(|| format!("{}", saved.display()))
}

/// Refuses `dir` (holding `names`, and no checkpoint) as a run's directory, with the message
/// `foreign` gives, if it holds a file a run does not write; with the message `lost` gives, if
/// its run's checkpoint was written and is gone ([`lost_checkpoint`]).
fn refuse_foreign_or_lost(
    dir: &Path, names: &[String], foreign: impl FnOnce(&str) -> String,
    lost: impl FnOnce(&str) -> String,
) -> anyhow::Result<()> {
    if let Some(other) = names.iter().find(|n| !is_run_file(n)) {
        bail!(foreign(other));
    }
    if let Some(why) = lost_checkpoint(dir, names)? {
        bail!(lost(&why));
    }
    Ok(())
}

/// Why `dir` (holding `names`, and no checkpoint) is a run whose checkpoint was written and is
/// gone, if it is: a replay file (written only with a checkpoint), or at least `checkpoint_every`
/// finished episodes in its `metrics.csv` (the first checkpoint comes with episode
/// `checkpoint_every`, or earlier when a run is stopped).
fn lost_checkpoint(dir: &Path, names: &[String]) -> anyhow::Result<Option<String>> {
    if let Some(replay) = names.iter().find(|n| is_replay_file(n)) {
        return Ok(Some(format!(
            "{replay}, the replay memory saved with a checkpoint, is there"
        )));
    }
    let metrics = dir.join("metrics.csv");
    if !metrics.is_file() {
        return Ok(None);
    }
    let episodes = guard::read_text(&metrics, "the metrics")?
        .lines()
        .skip(1)
        .filter(|l| !l.trim().is_empty())
        .count() as u64;
    // What `checkpoint_every` the run had; without a readable config.toml, the smallest there is.
    let every = std::fs::read_to_string(dir.join("config.toml"))
        .ok()
        .and_then(|t| Config::resolve(None, Some(&t)).ok())
        .map_or(1, |c| c.checkpoint_every);
    Ok((episodes >= every).then(|| {
        format!(
            "metrics.csv records {episodes} finished episodes, and it checkpoints every {every}"
        )
    }))
}

/// The names in `dir`.
pub(super) fn dir_names(dir: &Path) -> anyhow::Result<Vec<String>> {
    std::fs::read_dir(dir)
        .with_context(|| format!("cannot read {}", dir.display()))?
        .map(|e| e.map(|e| e.file_name().to_string_lossy().into_owned()))
        .collect::<Result<_, _>>()
        .with_context(|| format!("cannot read {}", dir.display()))
}

/// A file a run writes into its directory: one of [`RUN_FILES`], a replay memory, a replay
/// memory being written, or a TensorBoard event file.
pub(super) fn is_run_file(name: &str) -> bool {
    RUN_FILES.contains(&name)
        || is_replay_file(name)
        || is_replay_tmp(name)
        || name.starts_with(invaders::dqn::tensorboard::PREFIX)
}

/// A replay memory saved with a checkpoint: `replay-E.safetensors`.
fn is_replay_file(name: &str) -> bool {
    name.strip_prefix("replay-")
        .and_then(|r| r.strip_suffix(".safetensors"))
        .is_some_and(|e| !e.is_empty() && e.bytes().all(|b| b.is_ascii_digit()))
}

/// A replay file being written (`.replay-E.safetensors.tmp`), left by a run killed meanwhile.
fn is_replay_tmp(name: &str) -> bool {
    name.starts_with(".replay-") && name.ends_with(".tmp")
}

/// Removes what a run that never reached a checkpoint left (not the lock file: it may be held).
pub(super) fn clear_run_files(dir: &Path) -> anyhow::Result<()> {
    let events = invaders::dqn::tensorboard::event_files(dir)?;
    for path in RUN_FILES
        .iter()
        .filter(|n| **n != guard::LOCK_FILE)
        .map(|n| dir.join(n))
        .chain(events)
    {
        if path.exists() {
            std::fs::remove_file(&path)
                .with_context(|| format!("cannot remove {}", path.display()))?;
        }
    }
    Ok(())
}

/// A record's file (`experiment --keep`'s `result.toml`), beside its copy of the run's files.
pub const RECORD_FILE: &str = "result.toml";

/// Why no command may write `path` (whether it exists or not), if it is so: its name is one of
/// the files a run, a snapshot or a `--keep` record owns, in a folder that holds one of them
/// (a checkpoint, a `metrics.csv`, a record or a run's lock). Replacing it would cost the run its
/// curve, its replay memory or its configuration, and `--resume` would fail; `--force` does not
/// change that. Another name in the same folder is the user's to write.
pub fn owned_by_run(path: &Path) -> Option<String> {
    let name = path.file_name()?.to_str()?;
    let dir = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    let owned = is_run_file(name)
        || name == checkpoint::CHECKPOINT_FILE
        || name == RECORD_FILE
        || (name.starts_with('.') && name.ends_with(".tmp"));
    let markers = [
        checkpoint::CHECKPOINT_FILE,
        "metrics.csv",
        RECORD_FILE,
        guard::LOCK_FILE,
    ];
    let is_run = markers.iter().any(|m| dir.join(m).is_file());
    (owned && is_run).then(|| {
        format!(
            "{name} belongs to the run in {}: no command writes over a run's own files, --force or not; give another name",
            dir.display()
        )
    })
}
