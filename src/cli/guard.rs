//! What keeps a user's mistake from costing data: every output file the user names checked before
//! any work and written in one piece ([`OutputFile`]), and one process at a time per run directory.

use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context};

/// A file a command writes because the user named it (`eval --gif`, `plot --out`, `export --out`,
/// `show-preprocessing --out`): checked before any work by [`OutputFile::check`], written in one
/// piece at the end by [`OutputFile::write_with`] (or [`OutputFile::pending`] for a file written
/// bit by bit). What each kind of path gets, as a careful Unix tool does:
///
/// - **a new name, or an existing regular file with `--force`**: the file is written beside it
///   under a temporary name (`.NAME.tmp.EXT`), synced to disk and renamed over it, so a failure
///   (a full disk, a Ctrl-C, an error) leaves the old file as it was and no temporary file.
///   Without `--force` an existing file is refused.
/// - **a symbolic link**: what it points to, by these same rules; the link stays a link. A link
///   to nothing is refused.
/// - **a character device or a FIFO** (`/dev/null`, `/dev/stdout`, a named pipe): written
///   through, as `cp` and `tee` do, with no `--force` (nothing is replaced), once the whole file
///   is ready (in the temporary directory). A FIFO that no process reads is refused rather than
///   waited for.
/// - **a directory, a block device, a socket**: refused. So is any of the command's inputs,
///   whatever the path's spelling, even with `--force`, and any file a run owns in a run folder,
///   a snapshot or a `--keep` record ([`super::rundir::owned_by_run`]), whether it exists or not.
#[derive(Debug)]
pub struct OutputFile {
    /// The path as the user gave it, for messages.
    shown: PathBuf,
    /// Where the file goes: the path, or what its symbolic link points to.
    target: PathBuf,
    /// Written through instead of replaced (a character device or a FIFO).
    stream: bool,
    /// The flag that named it, for messages.
    flag: String,
}

impl OutputFile {
    /// Checks that `out` may be written (see [`OutputFile`]); writes nothing.
    pub fn check(
        out: &Path, force: bool, inputs: &[&Path], flag: &str,
    ) -> anyhow::Result<OutputFile> {
        let shown = out.display();
        let target = match std::fs::symlink_metadata(out) {
            Ok(m) if m.file_type().is_symlink() => match out.canonicalize() {
                Ok(t) => t,
                Err(_) => bail!("{flag} {shown} is a symbolic link to nothing; give a file name"),
            },
            _ => out.to_path_buf(),
        };
        let owned = super::rundir::owned_by_run(&target);
        let meta = match std::fs::metadata(&target) {
            Ok(m) => Some(m),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => None,
            Err(e) => return Err(e).with_context(|| format!("{flag} {shown}")),
        };
        let mut stream = false;
        if let Some(m) = &meta {
            use std::os::unix::fs::FileTypeExt;
            let t = m.file_type();
            if t.is_dir() {
                bail!("{flag} {shown} is a directory; give a file name");
            }
            let same = |a: &Path| match (a.canonicalize(), target.canonicalize()) {
                (Ok(a), Ok(b)) => a == b,
                _ => false,
            };
            if let Some(input) = inputs.iter().find(|i| same(i)) {
                bail!(
                    "{flag} {shown} is the input {}: refusing to write over it",
                    input.display()
                );
            }
            if let Some(why) = &owned {
                bail!("{flag} {shown}: {why}");
            }
            if t.is_block_device() || t.is_socket() {
                bail!(
                    "{flag} {shown} is a {}: refusing to write a file onto it",
                    if t.is_socket() {
                        "socket"
                    } else {
                        "block device"
                    }
                );
            }
            stream = t.is_char_device() || t.is_fifo();
            if !stream && !force {
                bail!("{flag} {shown} exists; choose another name, or pass --force to replace it");
            }
        }
        if let Some(why) = owned.filter(|_| meta.is_none()) {
            bail!("{flag} {shown}: {why}");
        }
        if !stream {
            let parent = match target.parent() {
                Some(p) if !p.as_os_str().is_empty() => p,
                _ => Path::new("."),
            };
            if !parent.is_dir() {
                bail!(
                    "{flag} {shown}: the directory {} does not exist",
                    parent.display()
                );
            }
        }
        Ok(OutputFile {
            shown: out.to_path_buf(),
            target,
            stream,
            flag: flag.to_string(),
        })
    }

    /// Starts writing: a temporary file for the content, which [`Pending::commit`] puts in place
    /// and a [`Pending`] dropped uncommitted removes.
    pub fn pending(&self) -> anyhow::Result<Pending<'_>> {
        let name = self
            .target
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_else(|| "output".into());
        // The extension stays last: the plotting library picks the image format by it.
        let ext = Path::new(&name)
            .extension()
            .map(|e| format!(".{}", e.to_string_lossy()))
            .unwrap_or_default();
        let tmp = if self.stream {
            let dir = std::env::temp_dir();
            if !dir.is_dir() {
                bail!(
                    "{} {}: the temporary directory {} does not exist (set TMPDIR to one that does)",
                    self.flag,
                    self.shown.display(),
                    dir.display()
                );
            }
            dir.join(format!("invaders-{}-{name}.tmp{ext}", std::process::id()))
        } else {
            let dir = match self.target.parent() {
                Some(p) if !p.as_os_str().is_empty() => p,
                _ => Path::new("."),
            };
            dir.join(format!(".{name}.tmp{ext}"))
        };
        Ok(Pending {
            file: self,
            tmp,
            done: false,
        })
    }

    /// Writes the file in one piece: `write` fills the temporary path it is given, which then
    /// takes the file's place ([`Pending::commit`]).
    pub fn write_with(
        &self, write: impl FnOnce(&Path) -> anyhow::Result<()>,
    ) -> anyhow::Result<()> {
        let pending = self.pending()?;
        match write(pending.path()) {
            Err(e) if disk_full(&e) => Err(self.full()),
            r => r,
        }?;
        pending.commit()
    }

    /// The error of a full disk while this file was written.
    fn full(&self) -> anyhow::Error {
        anyhow!(
            "cannot write {} {}: the disk is full (any earlier file of that name is kept as it was); free some space and try again",
            self.flag,
            self.shown.display()
        )
    }

    /// Writes `bytes` as the file ([`OutputFile::write_with`]).
    pub fn write(&self, bytes: &[u8]) -> anyhow::Result<()> {
        self.write_with(|tmp| {
            std::fs::write(tmp, bytes).with_context(|| format!("cannot write {}", tmp.display()))
        })
    }
}

/// An [`OutputFile`] being written: its content goes to [`Pending::path`].
pub struct Pending<'a> {
    file: &'a OutputFile,
    tmp: PathBuf,
    done: bool,
}

impl Pending<'_> {
    /// Where the content is written until [`Pending::commit`].
    pub fn path(&self) -> &Path {
        &self.tmp
    }

    /// Puts the content in place: renamed over the file (after a sync), or for a character
    /// device or a FIFO copied into it. On an error the file is as it was before.
    pub fn commit(mut self) -> anyhow::Result<()> {
        self.done = true;
        let f = self.file;
        let result = if f.stream {
            write_through(&self.tmp, &f.target)
        } else {
            sync_rename(&self.tmp, &f.target)
        };
        let _ = std::fs::remove_file(&self.tmp);
        match result {
            Err(e) if disk_full(&e) => Err(f.full()),
            r => r.with_context(|| format!("cannot write {} {}", f.flag, f.shown.display())),
        }
    }
}

impl Drop for Pending<'_> {
    fn drop(&mut self) {
        if !self.done {
            let _ = std::fs::remove_file(&self.tmp);
        }
    }
}

/// Syncs `tmp` to disk and renames it over `target`, then syncs the directory.
fn sync_rename(tmp: &Path, target: &Path) -> anyhow::Result<()> {
    File::open(tmp)?.sync_all()?;
    std::fs::rename(tmp, target)?;
    if let Some(dir) = target.parent().filter(|p| !p.as_os_str().is_empty()) {
        if let Ok(d) = File::open(dir) {
            let _ = d.sync_all();
        }
    }
    Ok(())
}

/// Copies `tmp` into the character device or FIFO `target`. A FIFO is opened without waiting: if
/// no process reads it, that is an error, not a hang.
fn write_through(tmp: &Path, target: &Path) -> anyhow::Result<()> {
    use std::os::unix::fs::OpenOptionsExt;
    let mut out = match std::fs::OpenOptions::new()
        .write(true)
        .custom_flags(libc::O_NONBLOCK)
        .open(target)
    {
        Ok(f) => f,
        Err(e) if e.raw_os_error() == Some(libc::ENXIO) => {
            bail!("it is a FIFO that no process is reading")
        }
        Err(e) => return Err(e.into()),
    };
    {
        use std::os::fd::AsRawFd;
        // Blocking writes from here on: the reader takes the file at its own pace.
        let fd = out.as_raw_fd();
        // SAFETY: `fd` is the open file's descriptor; F_GETFL and F_SETFL touch no memory.
        unsafe {
            let flags = libc::fcntl(fd, libc::F_GETFL);
            libc::fcntl(fd, libc::F_SETFL, flags & !libc::O_NONBLOCK);
        }
    }
    let mut from = File::open(tmp)?;
    std::io::copy(&mut from, &mut out).map_err(|e| {
        if e.kind() == std::io::ErrorKind::BrokenPipe {
            anyhow!("its reader went away before the whole file was written")
        } else {
            e.into()
        }
    })?;
    out.flush()?;
    Ok(())
}

/// Whether `e` (or one of its causes) is a file system that is full: no space left, or the
/// user's disk quota reached.
pub fn disk_full(e: &anyhow::Error) -> bool {
    e.chain()
        .filter_map(|c| c.downcast_ref::<std::io::Error>())
        .any(|io| {
            io.kind() == std::io::ErrorKind::StorageFull
                || matches!(io.raw_os_error(), Some(libc::ENOSPC) | Some(libc::EDQUOT))
        })
}

/// The most bytes an input text file (a `--config`, a run's `config.toml`) may have: far above
/// any real one (a config of every key is 2 KB), so that `/dev/zero` is an error, not a memory
/// that grows without end.
pub const MAX_TEXT_INPUT: u64 = 16 << 20;

/// Reads a text file the user named (`what` says which, for messages), of at most
/// [`MAX_TEXT_INPUT`] bytes. A FIFO is read as the file it stands for (`--config <(…)`); one whose
/// writer never closes waits, and a Ctrl-C then stops the program.
pub fn read_text(path: &Path, what: &str) -> anyhow::Result<String> {
    use std::io::Read;
    let file =
        File::open(path).with_context(|| format!("cannot read {what} {}", path.display()))?;
    if file.metadata().is_ok_and(|m| m.is_dir()) {
        bail!("{what} {} is a directory", path.display());
    }
    let mut bytes = Vec::new();
    file.take(MAX_TEXT_INPUT + 1)
        .read_to_end(&mut bytes)
        .with_context(|| format!("cannot read {what} {}", path.display()))?;
    if bytes.len() as u64 > MAX_TEXT_INPUT {
        bail!(
            "{what} {} is larger than {} MiB: not a file this program wrote or reads",
            path.display(),
            MAX_TEXT_INPUT >> 20
        );
    }
    String::from_utf8(bytes).map_err(|_| anyhow!("{what} {} is not UTF-8 text", path.display()))
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
