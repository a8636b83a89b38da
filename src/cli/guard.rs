//! What keeps a user's mistake from costing data: output paths checked before any work, and one
//! process at a time per run directory.

use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context};

/// Checks, before any work, that `out` may be written: its directory exists, it is not a
/// directory, it is none of `inputs` (whatever the path's spelling), and it does not exist
/// unless `force`. Nothing is written here.
pub fn check_output(out: &Path, force: bool, inputs: &[&Path], flag: &str) -> anyhow::Result<()> {
    if out.is_dir() {
        bail!("{flag} {} is a directory; give a file name", out.display());
    }
    let parent = match out.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    if !parent.is_dir() {
        bail!(
            "{flag} {}: the directory {} does not exist",
            out.display(),
            parent.display()
        );
    }
    if out.exists() {
        let same = |a: &Path| match (a.canonicalize(), out.canonicalize()) {
            (Ok(a), Ok(b)) => a == b,
            _ => false,
        };
        if let Some(input) = inputs.iter().find(|i| same(i)) {
            bail!(
                "{flag} {} is the input {}: refusing to write over it",
                out.display(),
                input.display()
            );
        }
        if !force {
            bail!(
                "{flag} {} exists; choose another name, or pass --force to replace it",
                out.display()
            );
        }
    }
    Ok(())
}

/// An advisory lock on a run directory (`RUN_DIR/.lock`), held until dropped: a second process
/// that tries to train in the same directory gets an error naming the holder. The lock is the
/// operating system's (`flock`), so a killed process never leaves a stale one behind.
pub struct RunLock {
    _file: File,
}

/// The lock file's name in a run directory.
pub const LOCK_FILE: &str = ".lock";

impl RunLock {
    /// Takes the lock of `dir` (which must exist), or says who holds it.
    pub fn acquire(dir: &Path) -> anyhow::Result<RunLock> {
        let path: PathBuf = dir.join(LOCK_FILE);
        let mut file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .create(true)
            .truncate(false)
            .open(&path)
            .with_context(|| format!("cannot open the run's lock file {}", path.display()))?;
        match file.try_lock() {
            Ok(()) => {}
            Err(std::fs::TryLockError::WouldBlock) => {
                let holder = std::fs::read_to_string(&path).unwrap_or_default();
                bail!(
                    "run directory {} is in use by another process ({}); wait for it to finish or stop it first",
                    dir.display(),
                    holder.trim()
                );
            }
            Err(std::fs::TryLockError::Error(e)) => {
                return Err(e).with_context(|| format!("cannot lock {}", path.display()))
            }
        }
        // Who holds it, for the message another process will print.
        file.set_len(0)?;
        write!(
            file,
            "pid {}, started {} s after the Unix epoch",
            std::process::id(),
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map(|d| d.as_secs())
                .unwrap_or(0)
        )?;
        file.flush()?;
        Ok(RunLock { _file: file })
    }
}
