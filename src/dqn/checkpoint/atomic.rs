//! Writing a file atomically: a temporary file in the same directory, synced, renamed over the
//! old one, then the directory synced. Checkpoints and every file the program writes use it.

use super::*;

/// The temporary file an atomic write of `path` goes through: `.NAME.tmp` in the same directory
/// (the same filesystem, so the final rename is atomic).
pub fn tmp_path(path: &Path) -> anyhow::Result<std::path::PathBuf> {
    let dir = path
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let name = path
        .file_name()
        .ok_or_else(|| anyhow!("{} is not a file path", path.display()))?;
    Ok(dir.join(format!(".{}.tmp", name.to_string_lossy())))
}

/// Writes a file atomically: `write` fills a temporary file in the same directory, which is then
/// synced to disk and renamed over `path` (then the directory is synced). On any error the
/// temporary file is removed and `path` is left as it was.
pub fn write_atomic_with(
    path: &Path, write: impl FnOnce(&Path) -> anyhow::Result<()>,
) -> anyhow::Result<()> {
    let tmp = tmp_path(path)?;
    let dir = tmp
        .parent()
        .expect("a temporary path has a parent")
        .to_owned();
    let result = write(&tmp).and_then(|()| {
        let f = std::fs::File::open(&tmp)?;
        f.sync_all()?;
        drop(f);
        std::fs::rename(&tmp, path)?;
        if let Ok(d) = std::fs::File::open(&dir) {
            let _ = d.sync_all();
        }
        Ok(())
    });
    if let Err(e) = result {
        if tmp.is_file() {
            let _ = std::fs::remove_file(&tmp);
        }
        return Err(e).with_context(|| {
            format!(
                "cannot write {} (any previous version is kept)",
                path.display()
            )
        });
    }
    Ok(())
}

/// Writes `bytes` to `path` atomically (temporary file, fsync, rename, fsync of the directory).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> anyhow::Result<()> {
    write_atomic_with(path, |tmp| {
        let mut f = std::fs::File::create(tmp)?;
        f.write_all(bytes)?;
        Ok(())
    })
}

/// Copies the files `names` from the directory `from` into `to`, each atomically
/// ([`write_atomic`]) and in the order given (so a file that must come last, a checkpoint naming
/// the others, can); a name in `optional` that `from` lacks is skipped.
pub fn copy_files_atomic(
    from: &Path, to: &Path, names: &[&str], optional: &[&str],
) -> anyhow::Result<()> {
    for name in names {
        let src = from.join(name);
        if optional.contains(name) && !src.exists() {
            continue;
        }
        let bytes =
            std::fs::read(&src).with_context(|| format!("cannot read {}", src.display()))?;
        write_atomic(&to.join(name), &bytes)?;
    }
    Ok(())
}
