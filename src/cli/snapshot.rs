//! `train --snapshot DIR`: the small copy of a run kept after each checkpoint (module
//! `checkpoint`'s "Snapshots").

use std::path::{Path, PathBuf};

use anyhow::{bail, Context};

use super::guard;
use super::rundir::{dir_names, CONTINUED_FILE};
use invaders::dqn::checkpoint::{self, write_atomic};
use invaders::dqn::{Config, Trainer};

/// The files a snapshot directory holds ([`write_snapshot`]).
const SNAPSHOT_FILES: [&str; 4] = [
    checkpoint::CHECKPOINT_FILE,
    "config.toml",
    "metrics.csv",
    CONTINUED_FILE,
];

/// Refuses a `--snapshot` path that can never be a snapshot directory (a file), before the run
/// makes or locks any folder.
pub(super) fn check_path(snap: &Path) -> anyhow::Result<()> {
    if snap.exists() && !snap.is_dir() {
        bail!(
            "--snapshot {} is a file, not a directory: give a directory for the snapshot",
            snap.display()
        );
    }
    Ok(())
}

/// The snapshot directory a run writes (`train --snapshot`), which it owns while it trains: it
/// holds the directory's lock, so that no other process (`train --resume DIR`, another run's
/// `--snapshot DIR`) continues or writes it meanwhile, and before each write it checks that the
/// directory still holds the checkpoint it wrote last (its device, inode, size and time): one
/// that has changed was continued or replaced by someone else (on a file system where locks do
/// not reach, say), so the run says so and writes no more snapshots there.
pub(super) struct Snapshot {
    dir: PathBuf,
    /// The checkpoint file as this run left it (none: there was none).
    mark: Option<Mark>,
    /// No more snapshots: the directory is not this run's any more.
    stopped: bool,
    _lock: guard::RunLock,
}

impl Drop for Snapshot {
    /// The lock file goes with the run that held it (a snapshot is meant to be committed, kept
    /// or copied: it holds only the snapshot's files); the lock itself is released after.
    fn drop(&mut self) {
        let _ = std::fs::remove_file(self.dir.join(guard::LOCK_FILE));
    }
}

/// What tells one write of a file from another: device, inode, size and modification time.
type Mark = (u64, u64, u64, i64, i64);

/// The [`Mark`] of `path`, if it exists.
fn mark(path: &Path) -> Option<Mark> {
    use std::os::unix::fs::MetadataExt;
    let m = std::fs::metadata(path).ok()?;
    Some((m.dev(), m.ino(), m.size(), m.mtime(), m.mtime_nsec()))
}

impl Snapshot {
    /// Writes the run's snapshot after a checkpoint at `episode` ([`write_snapshot`]), if the
    /// directory is still this run's; a failure is a warning, and the run goes on.
    pub(super) fn write(&mut self, run: &Path, agent: &dyn Trainer, episode: u64) {
        if self.stopped {
            return;
        }
        let file = self.dir.join(checkpoint::CHECKPOINT_FILE);
        if mark(&file) != self.mark {
            say!(
                "warning: {} no longer holds the snapshot this run wrote last: another process continued or replaced it, so this run writes no more snapshots there (the run and its checkpoint go on; episode {episode} is in {})",
                self.dir.display(),
                run.display()
            );
            self.stopped = true;
            return;
        }
        if let Err(e) = write_snapshot(&self.dir, run, agent) {
            say!(
                "warning: no snapshot of episode {episode} in {} (the run and its checkpoint go on): {e:#}",
                self.dir.display()
            );
        }
        self.mark = mark(&file);
    }
}

/// Checks, creates and locks `--snapshot`'s directory before anything trains, so that a
/// snapshot replaces nothing but an earlier snapshot of this very run (`config`, now at
/// `counters`): not the run directory itself, not a directory holding other files (another run,
/// say), not one another process holds, not the snapshot of another configuration or seed, and
/// not a later snapshot of this run.
pub(super) fn prepare(
    snap: &Path, run: &Path, config: &Config, counters: &checkpoint::Counters,
) -> anyhow::Result<Snapshot> {
    check_path(snap)?;
    std::fs::create_dir_all(snap)
        .with_context(|| format!("cannot create the snapshot directory {}", snap.display()))?;
    let same = match (snap.canonicalize(), run.canonicalize()) {
        (Ok(a), Ok(b)) => a == b,
        _ => false,
    };
    if same {
        bail!(
            "--snapshot {} is the run directory: a snapshot would replace its checkpoint; give another directory",
            snap.display()
        );
    }
    let is_tmp = |n: &str| SNAPSHOT_FILES.iter().any(|f| n == format!(".{f}.tmp"));
    if let Some(other) = dir_names(snap)?
        .into_iter()
        .find(|n| !SNAPSHOT_FILES.contains(&n.as_str()) && !is_tmp(n) && n != guard::LOCK_FILE)
    {
        bail!(
            "--snapshot {} holds {other}, which a snapshot does not: it is not a snapshot directory, so nothing is written there; give another directory",
            snap.display()
        );
    }
    let lock = guard::RunLock::acquire(snap).context("--snapshot")?;
    let file = snap.join(checkpoint::CHECKPOINT_FILE);
    if file.exists() {
        let had = checkpoint::load(&file).with_context(|| {
            format!(
                "--snapshot {} holds a checkpoint that cannot be read; move it away, or give another directory",
                snap.display()
            )
        })?;
        let budgetless = |c: &Config| {
            let mut c = c.clone();
            c.episodes = 0;
            c.max_frames = 0;
            c.to_toml()
        };
        if !had.snapshot {
            bail!(
                "--snapshot {} holds a run's full checkpoint, not a snapshot: give another directory",
                snap.display()
            );
        }
        if budgetless(&had.config) != budgetless(config) {
            bail!(
                "--snapshot {} holds the snapshot of another run (another configuration or seed): give another directory",
                snap.display()
            );
        }
        if had.counters.agent_steps > counters.agent_steps {
            bail!(
                "--snapshot {} holds a later snapshot of this run (episode {}) than the run is at (episode {}): continue from it with --resume {}, or give another directory",
                snap.display(),
                had.counters.episodes,
                counters.episodes,
                snap.display()
            );
        }
    }
    Ok(Snapshot {
        dir: snap.to_path_buf(),
        mark: mark(&file),
        stopped: false,
        _lock: lock,
    })
}

/// Appends a continuation from a snapshot at `counters` to the run's [`CONTINUED_FILE`].
pub(super) fn note_continued(dir: &Path, counters: &checkpoint::Counters) -> anyhow::Result<()> {
    let path = dir.join(CONTINUED_FILE);
    let mut text = match std::fs::read_to_string(&path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => "episode,agent_steps,frames\n".into(),
        Err(e) => return Err(e).with_context(|| format!("cannot read {}", path.display())),
    };
    let line = format!(
        "{},{},{}\n",
        counters.episodes, counters.agent_steps, counters.frames
    );
    // Resumed again from the same snapshot (a stop before its next checkpoint): noted once.
    if !text.ends_with(&line) {
        text.push_str(&line);
    }
    write_atomic(&path, text.as_bytes())
}

/// Writes the run's snapshot into `snap` after a checkpoint: `metrics.csv`, `config.toml` and
/// (if the run has one) [`CONTINUED_FILE`] first, then the snapshot's `checkpoint.safetensors`
/// (each atomically), so the snapshot there always has the rows it needs.
fn write_snapshot(snap: &Path, run: &Path, agent: &dyn Trainer) -> anyhow::Result<()> {
    checkpoint::copy_files_atomic(run, snap, &SNAPSHOT_FILES[1..], &[CONTINUED_FILE])?;
    checkpoint::save_snapshot(&snap.join(checkpoint::CHECKPOINT_FILE), agent)
}
