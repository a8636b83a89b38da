//! A run's `metrics.csv` reopened on resume: kept up to its checkpoint's episode.

use std::path::Path;

use anyhow::{bail, Context};

use invaders::dqn::checkpoint::write_atomic;
use invaders::dqn::EpisodeRow;

/// Keeps the first `episodes` data rows of `metrics.csv` (rows written after the checkpoint being
/// resumed are replayed by the resumed run, and the message says so) and returns them as
/// `(episode, reward)`. A last line torn by an interrupted append (a full disk, a kill: no
/// newline, too few fields) is cut off with a note ([`torn_tail`]); any other malformed or
/// misnumbered row among those kept is refused, naming it; a missing file is said to be missing
/// and started anew.
pub(super) fn reopen_metrics(
    path: &Path, episodes: u64,
) -> anyhow::Result<(std::fs::File, Vec<(f64, f64)>)> {
    let mut kept = String::from(EpisodeRow::HEADER);
    kept.push('\n');
    let mut points = Vec::new();
    match std::fs::read_to_string(path) {
        Ok(mut text) => {
            if let Some(cut) = torn_tail(&text) {
                say!(
                    "note: {}: the last line (`{}`) was cut short by an interrupted write (a full disk, a kill): it is removed",
                    path.display(),
                    text[cut..].trim_end()
                );
                text.truncate(cut);
            }
            let mut lines = text.lines();
            if lines.next() != Some(EpisodeRow::HEADER) {
                bail!(
                    "{}: line 1 is not the header `{}`; put the header back by hand, or move the file away to resume without the curve so far (no other copy of it is kept)",
                    path.display(),
                    EpisodeRow::HEADER
                );
            }
            let (mut next, mut last_kept, mut dropped) = (None::<u64>, 0u64, 0u64);
            for (i, line) in lines.enumerate() {
                let mut f = line.split(',');
                let ep = f.next().and_then(|v| v.parse::<u64>().ok());
                let reward = f.nth(2).and_then(|v| v.parse::<f64>().ok());
                let (Some(ep), Some(r)) = (ep, reward.filter(|r| r.is_finite())) else {
                    bail!(
                        "{}: line {} is malformed (`{line}`); correct that line by hand, or move the file away to resume without the curve so far (no other copy of it is kept)",
                        path.display(),
                        i + 2
                    );
                };
                if next.is_some_and(|n| n != ep) || ep == 0 {
                    bail!(
                        "{}: line {} is episode {ep}'s row where episode {} was expected; correct the file by hand, or move it away to resume without the curve so far (no other copy of it is kept)",
                        path.display(),
                        i + 2,
                        next.unwrap_or(1)
                    );
                }
                next = Some(ep + 1);
                if ep <= episodes {
                    points.push((ep as f64, r));
                    kept.push_str(line);
                    kept.push('\n');
                    last_kept = ep;
                } else {
                    dropped += 1;
                }
            }
            if last_kept != episodes {
                bail!(
                    "{} ends at episode {last_kept} but the checkpoint is at episode {episodes}; move the file away to resume without the curve so far (the missing rows are kept nowhere else)",
                    path.display()
                );
            }
            if let Some(&(first, _)) = points.first().filter(|p| p.0 > 1.0) {
                say!(
                    "note: {} starts at episode {first}: the rows before it were lost earlier",
                    path.display()
                );
            }
            if dropped > 0 {
                say!(
                    "metrics.csv: dropping the {dropped} row(s) after episode {episodes}, the checkpoint's: those episodes are played again"
                );
            }
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            if episodes > 0 {
                say!(
                    "warning: {} is missing: the rows of episodes 1 to {episodes} are lost; it starts again at episode {}",
                    path.display(),
                    episodes + 1
                );
            }
        }
        Err(e) => return Err(e).with_context(|| format!("cannot read {}", path.display())),
    }
    write_atomic(path, kept.as_bytes())?;
    let file = std::fs::OpenOptions::new()
        .append(true)
        .open(path)
        .with_context(|| format!("cannot open {}", path.display()))?;
    Ok((file, points))
}

/// Where a torn last line starts, if the file ends in one: a line without its newline that has
/// fewer fields than the header, as only an append cut short leaves it (rows are written whole,
/// newline last).
pub(super) fn torn_tail(text: &str) -> Option<usize> {
    if text.is_empty() || text.ends_with('\n') {
        return None;
    }
    let start = text.rfind('\n')? + 1;
    let fields = EpisodeRow::HEADER.split(',').count();
    (text[start..].split(',').count() < fields).then_some(start)
}
