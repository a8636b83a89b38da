//! What an experiment keeps of a finished run (`--keep`), and the check that a run already in an
//! experiment's folder was trained with the configuration asked for.

use super::*;

/// The file of a `--keep` record (`KEEP/LABEL-seedS/`), beside a copy of the run's `metrics.csv`
/// and `config.toml`.
pub(super) use crate::cli::rundir::RECORD_FILE;

/// The folder of a `--keep` record (`KEEP/LABEL-seedS/snapshot/`) where the run's snapshot is
/// kept while it trains, and its final network after (`train --snapshot`; module `checkpoint`'s
/// "Snapshots"): where the run directory is gone, the run continues from it.
pub(super) const SNAPSHOT_DIR: &str = "snapshot";

/// A finished run as `--keep` keeps it: what the tables need of it, and the question it
/// answers (preset, seed, overrides, budget reached, evaluations), so that a record is taken
/// only for the same question. A few hundred kilobytes with its metrics, meant to be committed:
/// a run directory (its replay memory alone is gigabytes) does not outlive its machine.
#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct Record {
    pub(super) preset: String,
    pub(super) seed: u64,
    /// The TOML overrides the run trained with (`--config` and the arm's own keys).
    pub(super) overrides: String,
    pub(super) protocol_episodes: u32,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub(super) own_game_episodes: Option<u32>,
    pub(super) counters: checkpoint::Counters,
    pub(super) protocol: Scores,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub(super) own_game: Option<Scores>,
    /// The frames at which the run continued from its snapshot, without its replay memory
    /// (its machine was gone); empty for a run trained in one piece.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub(super) continued_from_snapshot: Vec<u64>,
}

/// Adds a finished run's evaluation scores to its TensorBoard events (where it writes them), at
/// its last agent step: `eval/protocol_*` and `eval/own_game_*` (mean, std, min, max). A failure
/// is said, not fatal: the scores are in the record and the tables.
pub(super) fn log_evaluations(
    dir: &Path, counters: &checkpoint::Counters, protocol: &Scores, own_game: Option<&Scores>,
) {
    if invaders::dqn::tensorboard::event_files(dir).map_or(true, |f| f.is_empty()) {
        return;
    }
    let mut values = Vec::new();
    for (name, s) in [("protocol", Some(protocol)), ("own_game", own_game)] {
        if let Some(s) = s {
            for (stat, v) in [
                ("mean", s.mean),
                ("std", s.std),
                ("min", s.min),
                ("max", s.max),
            ] {
                values.push((format!("eval/{name}_{stat}"), v));
            }
        }
    }
    let named: Vec<(&str, f64)> = values.iter().map(|(t, v)| (t.as_str(), *v)).collect();
    let written = invaders::dqn::tensorboard::EventWriter::append_only(dir).and_then(|mut w| {
        w.scalars(
            counters.agent_steps as i64,
            invaders::dqn::tensorboard::now(),
            &named,
        )
    });
    if let Err(e) = written {
        say!(
            "warning: the evaluation is not in {}'s TensorBoard events: {e:#}",
            dir.display()
        );
    }
}

/// The record in `dir`, if there is one; an error if it cannot be read.
pub(super) fn read_record(dir: &Path) -> anyhow::Result<Option<Record>> {
    let path = dir.join(RECORD_FILE);
    let text = match std::fs::read_to_string(&path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(e).with_context(|| format!("cannot read {}", path.display())),
    };
    let fail = || {
        format!(
            "{} is not a run's record; delete {} to train and evaluate that run again",
            path.display(),
            dir.display()
        )
    };
    let record: Record = toml::from_str(&text).with_context(fail)?;
    if !dir.join("metrics.csv").is_file() {
        return Err(anyhow!("its metrics.csv is missing")).with_context(fail);
    }
    for (table, scores) in [
        ("protocol", Some(&record.protocol)),
        ("own_game", record.own_game.as_ref()),
    ] {
        if let Some(s) = scores {
            check_scores(&text, table, s).map_err(|e| anyhow!("{}: {e}", path.display()))?;
        }
    }
    Ok(Some(record))
}

/// Refuses scores no evaluation gives (a value that is not finite, a negative standard
/// deviation, a mean outside `[min, max]`): a record damaged by hand or by a disk, whose tables
/// would report it. Says the line (of `text`, the record) and key.
fn check_scores(text: &str, table: &str, s: &Scores) -> anyhow::Result<()> {
    let line = |key: &str| {
        let mut inside = false;
        for (n, l) in text.lines().enumerate() {
            let l = l.trim();
            if l.starts_with('[') {
                inside = l == format!("[{table}]");
            } else if inside && l.split('=').next().is_some_and(|k| k.trim() == key) {
                return format!("line {}", n + 1);
            }
        }
        "no line".to_string()
    };
    let bad = |key: &str, v: f64, why: &str| {
        Err(anyhow!(
            "{}, `{table}.{key}` = {v} {why}: the record is damaged; delete its folder to train and evaluate that run again",
            line(key)
        ))
    };
    for (key, v) in [
        ("mean", s.mean),
        ("std", s.std),
        ("min", s.min),
        ("max", s.max),
    ] {
        if !v.is_finite() {
            return bad(key, v, "is not a finite number");
        }
    }
    if s.std < 0.0 {
        return bad("std", s.std, "is negative");
    }
    if s.min > s.max {
        return bad("min", s.min, &format!("is above max = {}", s.max));
    }
    if !(s.min..=s.max).contains(&s.mean) {
        return bad(
            "mean",
            s.mean,
            &format!("is outside [min, max] = [{}, {}]", s.min, s.max),
        );
    }
    Ok(())
}

/// Writes a run's record into `dir`: its `metrics.csv` and `config.toml` first, the record last,
/// each atomically, so a record is there only with its metrics.
pub(super) fn write_record(dir: &Path, run: &Path, record: &Record) -> anyhow::Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    checkpoint::copy_files_atomic(run, dir, &["metrics.csv", "config.toml"], &[])?;
    let text = format!(
        "# A finished run of `invaders experiment` (see --keep): what it was asked and its scores.\n{}",
        toml::to_string(record)?
    );
    checkpoint::write_atomic(&dir.join(RECORD_FILE), text.as_bytes())
}

/// Refuses to take the run in `dir` as the run this experiment asks for (`preset`, the TOML
/// `overrides`, `seed`) if it was trained with another configuration, naming the keys that
/// differ: a folder reused under other settings must not report the old runs as the new ones.
/// The budget (`episodes`, `max_frames`) may differ: the experiment extends it. Nothing is
/// written; a directory with no run in it passes.
/// With `keep`, the `--keep` record of the same name (`KEEP/NAME`) is checked too
/// ([`check_record`]).
pub(super) fn check_reuse(
    dir: &Path, keep: Option<&Path>, preset: Preset, overrides: &str, seed: u64,
) -> anyhow::Result<()> {
    if let (Some(k), Some(name)) = (keep, dir.file_name()) {
        let record = k.join(name);
        if record.join(RECORD_FILE).exists() {
            check_record(&record, preset, overrides, seed)?;
        }
    }
    let ckpt = dir.join(checkpoint::CHECKPOINT_FILE);
    let saved = dir.join("config.toml");
    let had = if ckpt.exists() {
        checkpoint::load(&ckpt)
            .with_context(|| format!("cannot read the run in {}", dir.display()))?
            .config
    } else if saved.is_file() {
        let text = crate::cli::guard::read_text(&saved, "the run's configuration")?;
        Config::resolve(None, Some(&text))
            .with_context(|| format!("cannot read the run in {}", dir.display()))?
    } else {
        return Ok(());
    };
    refuse_other(&had, preset, overrides, seed, |differ| {
        format!(
            "{} holds a run trained with another configuration than this experiment asks for \
             ({differ}): it is not taken as this experiment's run. Give another --out, or move \
             that run away",
            dir.display()
        )
    })
}

/// Refuses to replace the `--keep` record in `dir` by a run of `preset`, `overrides` and `seed`
/// if the record is of another configuration (its `config.toml`, the run's), naming the keys
/// that differ, as a run directory of another configuration is refused ([`check_reuse`]): a
/// record holds a finished run, and only the same configuration (with a longer budget, or other
/// evaluations) may replace it. Nothing is written.
pub(super) fn check_record(
    dir: &Path, preset: Preset, overrides: &str, seed: u64,
) -> anyhow::Result<()> {
    let saved = dir.join("config.toml");
    let text = crate::cli::guard::read_text(&saved, "the record's configuration")?;
    let had = Config::resolve(None, Some(&text))
        .with_context(|| format!("cannot read the record in {}", dir.display()))?;
    refuse_other(&had, preset, overrides, seed, |differ| {
        format!(
            "{} holds the record of a run trained with another configuration than this \
             experiment asks for ({differ}): it is not replaced. Give another --keep, or move \
             that record away",
            dir.display()
        )
    })
}

/// Refuses `had` with the message `refusal` gives for the keys that differ (`key: A, not B`,
/// joined by `; `), if it is not the configuration of `preset`, `overrides` and `seed`
/// ([`config_differences`]).
fn refuse_other(
    had: &Config, preset: Preset, overrides: &str, seed: u64, refusal: impl FnOnce(&str) -> String,
) -> anyhow::Result<()> {
    let mut asked = Config::resolve(Some(preset), Some(overrides))?;
    asked.seed = seed;
    let differ = config_differences(had, &asked);
    if !differ.is_empty() {
        bail!(refusal(&differ.join("; ")));
    }
    Ok(())
}

/// The keys whose values differ between two configurations, as `key: A, not B` (`[env]`'s keys as
/// `env.KEY`), leaving out the budget (`episodes`, `max_frames`), the preset's name, and the
/// precision where `asked` says `auto`.
pub(super) fn config_differences(had: &Config, asked: &Config) -> Vec<String> {
    let flat = |c: &Config| {
        let mut out = config_leaves(c);
        out.remove("episodes");
        out.remove("max_frames");
        // A name, not a setting: every knob is compared. (`strong-v1` ran as `strong` until
        // 2026-12; its snapshots keep that name.)
        out.remove("preset");
        // `auto` asks for whichever precision the run measured faster: either answers it.
        if asked.precision == invaders::ops::plan::Precision::Auto {
            out.remove("precision");
        }
        out
    };
    let (a, b) = (flat(had), flat(asked));
    let keys: std::collections::BTreeSet<&String> = a.keys().chain(b.keys()).collect();
    let show = |v: Option<&toml::Value>| v.map_or("unset".to_string(), |v| v.to_string());
    keys.into_iter()
        .filter(|k| a.get(*k) != b.get(*k))
        .map(|k| format!("`{k}` is {} there, {} here", show(a.get(k)), show(b.get(k))))
        .collect()
}

/// The `(key, value)` leaves of a configuration, `[env]`'s keys as `env.KEY`, by key.
pub(super) fn config_leaves(c: &Config) -> std::collections::BTreeMap<String, toml::Value> {
    let mut out = std::collections::BTreeMap::new();
    for (k, v) in toml::Table::try_from(c).expect("a config serialises") {
        match v {
            toml::Value::Table(t) => {
                out.extend(t.into_iter().map(|(k2, v2)| (format!("{k}.{k2}"), v2)))
            }
            v => {
                out.insert(k, v);
            }
        }
    }
    out
}
