//! `invaders experiment`: several training runs, their evaluations, a figure and a table.
//!
//! `preprocessing`, the article's comparison: trains `article-vanilla`, `article` and
//! `article-as-written` (and the `article` preset with any other pipeline named with
//! `--pipeline`) with the same seeds and budget, then evaluates every final checkpoint over 30
//! episodes as the article's game is played (`v0`, ε = 0.05) and by the evaluation protocol.
//!
//! `strong`, the `strong` preset's yardstick: trains it with seeds 1, 2, …, evaluates every final
//! network by the evaluation protocol and reports each run's frames, wall time and agent steps
//! per second beside its score.
//!
//! `ablation`, what each of the `strong` preset's components is worth: the preset and, for each
//! component in [`ablation::ABLATIONS`], the preset with that one switched off, all with one seed at a
//! reduced budget, each evaluated by the protocol and set against the preset.
//!
//! Runs are separate `invaders train` processes (`preprocessing` and `ablation`: one per core
//! side by side, one kernel thread each; `strong`: two kernel threads each, as many at a time as
//! the cores hold, so one at a time on a 2-core machine, as its budget needs).
//! Each run is evaluated as soon as it has trained, while the others go on training. Each
//! experiment writes `rewards.png` (mean over seeds with a min–max band) and `results.md` (the
//! table, with the command and budget) into `--out`. Re-running the same command continues
//! unfinished runs and skips finished ones.
//!
//! A run directory does not outlive its machine (its replay memory alone is gigabytes), so
//! `--keep DIR` keeps each finished run's record there (see [`Record`]: its scores, counters,
//! `metrics.csv` and `config.toml`, small enough to commit), and a run recorded there for the
//! same preset, seed, overrides, budget and evaluation is not trained or played again: an
//! experiment of several days can go on across machines from a repository. Each run also keeps
//! a snapshot of itself there while it trains (`DIR/LABEL-seedS/snapshot/`, about 4 MB for
//! `strong`: `train --snapshot`), and its final network once trained; a run whose directory is
//! gone continues from it, without its replay memory, and its record says at which frames.
//!
//! A Ctrl-C (or SIGTERM, or SIGHUP from a closed terminal) before the end stops the whole
//! experiment and loses nothing: the runs stop after their episode with a checkpoint, no new run
//! or evaluation starts, and the command exits with 130 (see [`stop`]).
//!
//! On a cluster, `--slurm DIR` writes the runs as a Slurm job array instead, each task one run
//! (`--task K`), and the same command then gathers their records (see [`slurm`]).
//!
//! One file a job: `preprocessing.rs`, `strong.rs` and `ablation.rs` the three experiments;
//! `runner.rs` runs their jobs (training and evaluating each as a child process); `records.rs`
//! the records `--keep` keeps and the check of a reused run's configuration; `stop.rs` passes a
//! stop on to the runs; `slurm.rs` the job arrays.

mod ablation;
mod preprocessing;
mod records;
mod runner;
mod slurm;
mod stop;
mod strong;

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Mutex;

use anyhow::{anyhow, bail, Context};
use clap::builder::PossibleValuesParser;
use clap::{Args, Subcommand, ValueEnum};
use serde::{Deserialize, Serialize};

use super::eval::{PROTOCOL_EPISODES, PROTOCOL_EPSILON, PROTOCOL_SEED};
use super::figures::{
    plot_groups, plot_groups_frames, read_digitized, read_frame_metrics, read_metrics,
    read_references, Group,
};
use super::Interrupted;
use crate::cli::rundir::CONTINUED_FILE;
use ablation::{ablation, AblationArgs};
use invaders::dqn::checkpoint;
use invaders::dqn::{merge_toml, Config, Preset};
use invaders::env::{Downsample, Pipeline};
use invaders::layers::loss::LossKind;
use preprocessing::{preprocessing, PreprocessingArgs};
use records::*;
use runner::*;
use slurm::{SlurmArgs, Sweep};
use strong::{strong, StrongArgs};

#[derive(Debug, Subcommand)]
pub enum Experiment {
    /// Vanilla against stacked and composed inputs (the article's figures).
    Preprocessing(PreprocessingArgs),
    /// The `strong` preset (or `strong-v1`) over several training seeds, each evaluated by the
    /// protocol.
    Strong(StrongArgs),
    /// The `strong` preset (or `strong-v1`) with each of its components switched off in turn.
    Ablation(AblationArgs),
}

pub fn run(e: &Experiment) -> anyhow::Result<()> {
    stop::catch();
    match e {
        Experiment::Preprocessing(args) => preprocessing(args),
        Experiment::Strong(args) => strong(args),
        Experiment::Ablation(args) => ablation(args),
    }
}

/// The `--config` file's text (empty without one).
fn read_overrides(path: Option<&Path>) -> anyhow::Result<String> {
    match path {
        Some(p) => super::guard::read_text(p, "config file"),
        None => Ok(String::new()),
    }
}

/// The most runs an experiment trains at once (`--jobs`).
const MAX_JOBS: usize = 64;

/// `--jobs`: 1 to [`MAX_JOBS`].
fn parse_jobs(s: &str) -> Result<usize, String> {
    let n: usize = s.parse().map_err(|e| format!("{e}"))?;
    if !(1..=MAX_JOBS).contains(&n) {
        return Err(format!("must be in 1..={MAX_JOBS}"));
    }
    Ok(n)
}

/// `--preset` of the experiments on the strong presets: `strong` or `strong-v1`.
fn parse_strong_preset(s: &str) -> Result<Preset, String> {
    match s {
        "strong" => Ok(Preset::Strong),
        "strong-v1" => Ok(Preset::StrongV1),
        _ => Err(
            "must be `strong` or `strong-v1` (the article's presets: experiment \
                  preprocessing)"
                .into(),
        ),
    }
}

/// `--jobs`, or one per core.
fn worker_count(jobs: Option<usize>) -> usize {
    jobs.unwrap_or_else(|| {
        std::thread::available_parallelism()
            .map(|n| n.get())
            .unwrap_or(1)
    })
    .max(1)
}

/// Writes a run's configuration file (`OUT/LABEL.toml`) unless it already holds `text`, and then
/// atomically: the tasks of a Slurm sweep start at once, each writing every such file while the
/// others' runs may be reading them.
fn write_config(path: &Path, text: &str) -> anyhow::Result<()> {
    if std::fs::read_to_string(path).is_ok_and(|t| t == text) {
        return Ok(());
    }
    checkpoint::write_atomic(path, text.as_bytes())
        .with_context(|| format!("cannot write {}", path.display()))
}

/// `--keep`'s directory, made before anything trains so a bad path fails now.
fn make_keep(keep: Option<&Path>) -> anyhow::Result<()> {
    if let Some(k) = keep {
        std::fs::create_dir_all(k).with_context(|| format!("cannot create {}", k.display()))?;
    }
    Ok(())
}

fn mean_std(xs: &[f64]) -> String {
    let n = xs.len() as f64;
    let mean = xs.iter().sum::<f64>() / n;
    let std = (xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n).sqrt();
    if xs.len() > 1 {
        format!("{mean:.1} ± {std:.1}")
    } else {
        format!("{mean:.1}")
    }
}

/// A mean over seeds with the lowest and highest seed: `mean (min–max)`, or the one value.
fn range_cell(xs: &[f64]) -> String {
    let mean = xs.iter().sum::<f64>() / xs.len().max(1) as f64;
    let (lo, hi) = xs
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &x| {
            (l.min(x), h.max(x))
        });
    if xs.len() > 1 {
        format!("{mean:.1} ({lo:.0}–{hi:.0})")
    } else {
        format!("{mean:.1}")
    }
}

/// An evaluation's score as the tables print it: `mean ± std (min–max)` over its episodes.
fn scores_cell(s: &Scores) -> String {
    format!("{:.1} ± {:.1} ({:.0}–{:.0})", s.mean, s.std, s.min, s.max)
}
