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
//! component in [`ABLATIONS`], the preset with that one switched off, all with one seed at a
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
//! experiment of several days can go on across machines from a repository.
//!
//! A Ctrl-C (or SIGTERM, or SIGHUP from a closed terminal) before the end stops the whole
//! experiment and loses nothing: the runs stop after their episode with a checkpoint, no new run
//! or evaluation starts, and the command exits with 130 (see [`stop`]).

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
use invaders::dqn::checkpoint;
use invaders::dqn::{merge_toml, Config, Preset, STRONG_FRAMES};
use invaders::env::{Downsample, Pipeline};
use invaders::layers::loss::LossKind;

#[derive(Debug, Subcommand)]
pub enum Experiment {
    /// Vanilla against stacked and composed inputs (the article's figures).
    Preprocessing(PreprocessingArgs),
    /// The `strong` preset over several training seeds, each evaluated by the protocol.
    Strong(StrongArgs),
    /// The `strong` preset with each of its components switched off in turn.
    Ablation(AblationArgs),
}

/// One arm of the ablation: the `strong` preset with one component switched off.
pub struct Ablation {
    /// Its name (`--arms`, the run directory `NAME-seedS`).
    pub name: &'static str,
    /// What it switches off, and what takes its place.
    pub what: &'static str,
    /// The TOML keys that do it, over the preset and `--config`.
    pub keys: &'static str,
    /// Whether the arm's configuration really switches the component off against the preset's
    /// (`--config` may already have, or made it moot: the loss, say, under a quantile head).
    pub switches: fn(arm: &Config, preset: &Config) -> bool,
}

/// The ablation's arms; the first, with no keys, is the preset itself. The others are the
/// preset's on/off components and its replay size; its other settings (Adam's, the target
/// period, the batch, one update per 4 agent steps) are the published agents' and not ablated.
/// The falling learning rate is left out too: its schedule starts at agent step 250 000 (1 M
/// frames) and has barely moved by the ablation's budget, so it is measured at full budget
/// instead (docs/strong.md).
pub const ABLATIONS: &[Ablation] = &[
    Ablation {
        name: "strong",
        what: "nothing (the preset)",
        keys: "",
        switches: |_, _| true,
    },
    Ablation {
        name: "no-dueling",
        what: "the dueling head (a plain dense head instead)",
        keys: "dueling = false",
        switches: |a, p| p.dueling && !a.dueling,
    },
    Ablation {
        name: "n-step-1",
        what: "3-step returns (1-step instead)",
        keys: "n_step = 1",
        switches: |a, p| p.n_step > 1 && a.n_step == 1,
    },
    Ablation {
        name: "no-double",
        what: "Double DQN (the target network's own max instead)",
        keys: "double_dqn = false",
        switches: |a, p| p.double_dqn && !a.double_dqn,
    },
    Ablation {
        name: "no-life-loss",
        what: "a lost life ending bootstrapping (only the game's end does)",
        keys: "life_loss_terminal = false",
        switches: |a, p| p.life_loss_terminal && !a.life_loss_terminal,
    },
    Ablation {
        name: "no-reward-clip",
        what: "reward clipping to ±1 (the game's rewards instead)",
        keys: "clip_rewards = false",
        switches: |a, p| p.clip_rewards && !a.clip_rewards,
    },
    Ablation {
        name: "mse",
        what: "the Huber loss (squared error instead)",
        keys: "loss = \"mse\"",
        switches: |a, p| p.loss == LossKind::Huber && a.loss == LossKind::Mse && p.quantiles == 0,
    },
    Ablation {
        name: "no-grad-clip",
        what: "clipping the gradient's norm to 10 (no clipping)",
        keys: "clip_grad_norm = 0.0",
        switches: |a, p| p.clip_grad_norm > 0.0 && a.clip_grad_norm == 0.0,
    },
    Ablation {
        name: "small-replay",
        what: "the 400 000-transition replay (100 000 instead)",
        keys: "replay_capacity = 100000",
        switches: |a, p| a.replay_capacity < p.replay_capacity,
    },
    Ablation {
        name: "pick-pixels",
        what: "max-pooled downsampling (each 2x2 block's top-left pixel instead)",
        keys: "[env]\ndownsample = \"pick\"",
        switches: |a, p| {
            p.env.downsample == Downsample::Max && a.env.downsample == Downsample::Pick
        },
    },
];

#[derive(Debug, Args)]
pub struct AblationArgs {
    /// The training seed of every arm (not 1 000 000, the seed the protocol plays on).
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Emulator frames per run.
    #[arg(long, default_value_t = 1_500_000)]
    frames: u64,
    /// The arms to train, by name (default: all; `strong`, the preset, is always trained).
    #[arg(long, value_delimiter = ',',
          value_parser = PossibleValuesParser::new(ABLATIONS.iter().map(|a| a.name)))]
    arms: Vec<String>,
    /// Runs trained at once (default: the cores divided by `--threads`, at least one).
    #[arg(long, value_parser = parse_jobs)]
    jobs: Option<usize>,
    /// Kernel threads per run.
    #[arg(long, default_value_t = 1)]
    threads: usize,
    /// Protocol episodes per final network (at least 100).
    #[arg(long, default_value_t = 100)]
    eval_episodes: u32,
    /// A TOML file of overrides applied to every arm before its own switch.
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// Keep each finished run's record in DIR (`DIR/NAME-seedS/`: its scores and counters,
    /// `metrics.csv` and `config.toml`, small enough to commit), and take a run recorded there
    /// for the same configuration, budget and evaluation as finished, even where its run
    /// directory is gone (another machine).
    #[arg(long, value_name = "DIR")]
    keep: Option<PathBuf>,
    /// The experiment directory.
    #[arg(long, default_value = "runs/experiment-ablation")]
    out: PathBuf,
}

#[derive(Debug, Args)]
pub struct StrongArgs {
    /// Training seeds 1, 2, … (the protocol plays on seed 1 000 000).
    #[arg(long, default_value_t = 3)]
    seeds: u64,
    /// Emulator frames per run.
    #[arg(long, default_value_t = STRONG_FRAMES)]
    frames: u64,
    /// Runs trained at once (default: the cores divided by `--threads`, at least one).
    #[arg(long, value_parser = parse_jobs)]
    jobs: Option<usize>,
    /// Kernel threads per run: 2 for one run alone on a 2-core machine (the preset's 13.5 million
    /// frames took 2.25–2.32 hours so on an AVX512-BF16 host), 1 for runs side by side.
    #[arg(long, default_value_t = 2)]
    threads: usize,
    /// Protocol episodes per final network (at least 100).
    #[arg(long, default_value_t = 100)]
    eval_episodes: u32,
    /// A TOML file of overrides applied to every run (e.g. `precision = "bf16"`).
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// Published curves to draw beside the runs', from a CSV `agent,frames,score` (e.g.
    /// docs/strong/dopamine-spaceinvaders.csv).
    #[arg(long, value_name = "CSV")]
    reference: Option<PathBuf>,
    /// The reference agents to draw (default: all in the file).
    #[arg(long, value_delimiter = ',')]
    agents: Vec<String>,
    /// Keep each finished run's record in DIR (`DIR/NAME-seedS/`: its scores and counters,
    /// `metrics.csv` and `config.toml`, small enough to commit), and take a run recorded there
    /// for the same configuration, budget and evaluation as finished, even where its run
    /// directory is gone (another machine).
    #[arg(long, value_name = "DIR")]
    keep: Option<PathBuf>,
    /// The experiment directory.
    #[arg(long, default_value = "runs/experiment-strong")]
    out: PathBuf,
}

/// How long each run trains.
#[derive(Clone, Copy)]
enum Budget {
    Episodes(u64),
    Frames(u64),
}

impl Budget {
    /// Whether a run with these counters has trained its budget.
    fn done(self, c: &checkpoint::Counters) -> bool {
        match self {
            Budget::Episodes(e) => c.episodes >= e,
            Budget::Frames(f) => c.frames >= f,
        }
    }

    /// The `train` flag that sets it.
    fn flag(self) -> [String; 2] {
        match self {
            Budget::Episodes(e) => ["--episodes".into(), e.to_string()],
            Budget::Frames(f) => ["--frames".into(), f.to_string()],
        }
    }
}

/// One training run of an experiment.
struct Job<'a> {
    label: &'a str,
    preset: Preset,
    seed: u64,
    cfg: PathBuf,
    dir: PathBuf,
    /// Kernel threads of its training (`train --threads`).
    threads: usize,
}

#[derive(Debug, Args)]
pub struct PreprocessingArgs {
    /// Episodes per run (the article: 800).
    #[arg(long, default_value_t = 800)]
    episodes: u64,
    /// Seeds per configuration (0, 1, ...).
    #[arg(long, default_value_t = 1)]
    seeds: u64,
    /// Also train the `article` preset with these pipelines.
    #[arg(long = "pipeline", value_enum)]
    pipelines: Vec<Pipeline>,
    /// Runs trained at once (default: the number of cores).
    #[arg(long, value_parser = parse_jobs)]
    jobs: Option<usize>,
    /// Evaluation episodes per final checkpoint, with ε = 0.05 in the run's own game (each is
    /// also evaluated by the protocol: 100 episodes of `v5`).
    #[arg(long, default_value_t = 30)]
    eval_episodes: u32,
    /// A TOML file of overrides applied to every run (e.g. a shorter ε decay for a small budget).
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// The article's notebook's own curve, digitised from its plot
    /// (`docs/experiment/notebook/plot-digitized.csv`), drawn as the band its 100-episode mean
    /// lies in.
    #[arg(long, value_name = "CSV")]
    notebook: Option<PathBuf>,
    /// Keep each finished run's record in DIR (`DIR/NAME-seedS/`: its scores and counters,
    /// `metrics.csv` and `config.toml`, small enough to commit), and take a run recorded there
    /// for the same configuration, budget and evaluation as finished, even where its run
    /// directory is gone (another machine).
    #[arg(long, value_name = "DIR")]
    keep: Option<PathBuf>,
    /// The experiment directory.
    #[arg(long, default_value = "runs/experiment-preprocessing")]
    out: PathBuf,
}

/// One configuration of the comparison.
struct Arm {
    label: String,
    preset: Preset,
    pipeline: Option<Pipeline>,
}

fn arms(args: &PreprocessingArgs) -> Vec<Arm> {
    let mut arms: Vec<Arm> = [
        Preset::ArticleVanilla,
        Preset::Article,
        Preset::ArticleAsWritten,
    ]
    .into_iter()
    .map(|p| Arm {
        label: p.name().to_string(),
        preset: p,
        pipeline: None,
    })
    .collect();
    for &p in &args.pipelines {
        let name = p.to_possible_value().expect("named").get_name().to_string();
        arms.push(Arm {
            label: format!("article+{name}"),
            preset: Preset::Article,
            pipeline: Some(p),
        });
    }
    arms
}

pub fn run(e: &Experiment) -> anyhow::Result<()> {
    stop::catch();
    match e {
        Experiment::Preprocessing(args) => preprocessing(args),
        Experiment::Strong(args) => strong(args),
        Experiment::Ablation(args) => ablation(args),
    }
}

fn preprocessing(args: &PreprocessingArgs) -> anyhow::Result<()> {
    if args.episodes == 0 || args.seeds == 0 || args.eval_episodes == 0 {
        bail!("--episodes, --seeds and --eval-episodes must be at least 1");
    }
    let overrides = read_overrides(args.config.as_deref())?;
    // Read before hours of training, so a bad file fails now.
    let notebook = match &args.notebook {
        Some(p) => vec![read_digitized(
            p,
            "the article's notebook (stacked, running max), digitised: its mean lies in the band",
        )?],
        None => Vec::new(),
    };
    make_keep(args.keep.as_deref())?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    let exe = exe_path()?;
    let arms = arms(args);
    // Every run's configuration, checked before anything is written or starts (and each run
    // already in --out against it).
    let mut jobs = Vec::new();
    let mut arm_texts = Vec::new();
    for arm in &arms {
        let mut table: toml::Table = overrides.parse().context("--config is not valid TOML")?;
        if let Some(p) = arm.pipeline {
            table.insert("pipeline".into(), toml::Value::try_from(p)?);
        }
        let text = toml::to_string(&table)?;
        Config::resolve(Some(arm.preset), Some(&text))
            .with_context(|| format!("configuration of {}", arm.label))?;
        for seed in 0..args.seeds {
            let dir = args.out.join(format!("{}-seed{seed}", arm.label));
            check_reuse(&dir, arm.preset, &text, seed)?;
        }
        arm_texts.push(text);
    }
    for (arm, text) in arms.iter().zip(arm_texts) {
        let cfg_path = args.out.join(format!("{}.toml", arm.label));
        std::fs::write(&cfg_path, &text)
            .with_context(|| format!("cannot write {}", cfg_path.display()))?;
        for seed in 0..args.seeds {
            jobs.push(Job {
                label: &arm.label,
                preset: arm.preset,
                seed,
                cfg: cfg_path.clone(),
                dir: args.out.join(format!("{}-seed{seed}", arm.label)),
                threads: 1,
            });
        }
    }
    say!(
        "{} runs of {} episodes, into {}",
        jobs.len(),
        args.episodes,
        args.out.display()
    );
    // Every final checkpoint is evaluated both ways as soon as it has trained.
    let evals = Evals {
        protocol: PROTOCOL_EPISODES,
        own_game: Some(args.eval_episodes),
    };
    let finished = run_all(
        &exe,
        &jobs,
        args.jobs,
        Budget::Episodes(args.episodes),
        evals,
        args.keep.as_deref(),
    )?;
    let mut finished = finished.into_iter();
    let (mut rows, mut run_rows, mut stretch_rows) = (Vec::new(), Vec::new(), Vec::new());
    let mut groups = Vec::new();
    let stretches = (args.episodes as usize).div_ceil(STRETCH);
    for arm in &arms {
        let (mut last100, mut evals, mut seeds) = (Vec::new(), Vec::new(), Vec::new());
        let mut protocol = Vec::new();
        for seed in 0..args.seeds {
            let run = finished.next().expect("a run per seed, in the jobs' order");
            let points = read_metrics(&run.metrics)?;
            let tail = &points[points.len().saturating_sub(100)..];
            last100.push(tail.iter().map(|p| p.1).sum::<f64>() / tail.len().max(1) as f64);
            let own = run.record.own_game.expect("evaluated in its own game");
            evals.push(own.mean);
            protocol.push(run.record.protocol.mean);
            let c = run.record.counters;
            run_rows.push(format!(
                "| {} | {seed} | {} | {} | {:.2} | {:.1} | {} | {} |",
                arm.label,
                c.agent_steps,
                c.frames,
                c.wall_seconds / 3600.0,
                last100[last100.len() - 1],
                scores_cell(&own),
                scores_cell(&run.record.protocol)
            ));
            seeds.push(points);
        }
        rows.push(format!(
            "| {} | {} | {} | {} | {} |",
            arm.label,
            args.seeds,
            mean_std(&last100),
            mean_std(&evals),
            mean_std(&protocol)
        ));
        // Each stretch's mean reward per seed, then its mean and range over the seeds.
        let cells: Vec<String> = (0..stretches)
            .map(|k| {
                let per_seed: Vec<f64> = seeds
                    .iter()
                    .filter_map(|pts| {
                        let s = pts.get(k * STRETCH..pts.len().min((k + 1) * STRETCH))?;
                        (!s.is_empty()).then(|| s.iter().map(|p| p.1).sum::<f64>() / s.len() as f64)
                    })
                    .collect();
                range_cell(&per_seed)
            })
            .collect();
        stretch_rows.push(format!("| {} | {} |", arm.label, cells.join(" | ")));
        groups.push(Group {
            label: arm.label.clone(),
            seeds,
        });
    }
    let stretch_head: Vec<String> = (0..stretches)
        .map(|k| {
            let last = ((k + 1) * STRETCH).min(args.episodes as usize);
            format!("{}–{last}", k * STRETCH + 1)
        })
        .collect();
    let png = args.out.join("rewards.png");
    let title = format!(
        "Space Invaders: {} episodes, {} seed(s) per configuration",
        args.episodes, args.seeds
    );
    plot_groups(&groups, &notebook, &title, 100, &png)?;
    let table = format!(
        "# Preprocessing experiment\n\nCommand: `{}`\n\nBudget: {} episodes per run, {} seed(s) per configuration; evaluation over {} episodes with ε = 0.05 in the run's own game (the article's: `v0`), and by the evaluation protocol ({PROTOCOL_EPISODES} episodes of `v5`, ε = {PROTOCOL_EPSILON}, seed {PROTOCOL_SEED}).\n\n| configuration | seeds | mean reward, last 100 episodes | evaluation score | protocol score |\n| --- | --- | --- | --- | --- |\n{}\n\nMeans over seeds ± their standard deviation (population). Figure: `rewards.png`.\n\nTraining reward by stretch of {STRETCH} episodes: the mean over seeds of each run's mean episode reward in the stretch (lowest–highest seed).\n\n| configuration | {} |\n| --- |{}\n{}\n\nEvery run: its final network's evaluation in its own game (seed 1000 + the run's seed) and by the protocol, each `mean ± std (min–max)` over its episodes.\n\n| configuration | seed | agent steps | frames | wall hours | mean reward, last 100 episodes | evaluation | protocol |\n| --- | --- | --- | --- | --- | --- | --- | --- |\n{}\n",
        command_line(),
        args.episodes,
        args.seeds,
        args.eval_episodes,
        rows.join("\n"),
        stretch_head.join(" | "),
        " --- |".repeat(stretches),
        stretch_rows.join("\n"),
        run_rows.join("\n")
    );
    std::fs::write(args.out.join("results.md"), &table).context("cannot write results.md")?;
    out!("{table}");
    Ok(())
}

/// Episodes per stretch in the preprocessing table of training reward by stretch.
const STRETCH: usize = 100;

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

/// What an experiment asks of each finished run's final network.
#[derive(Clone, Copy)]
struct Evals {
    /// Protocol episodes (`eval --protocol`).
    protocol: u32,
    /// `preprocessing`: episodes in the run's own game with ε = 0.05, on seed 1000 + the run's
    /// seed.
    own_game: Option<u32>,
}

/// A run trained to its budget and evaluated: its record (kept with `--keep` or not) and where
/// its per-episode `metrics.csv` is (in its run directory, or in its `--keep` record).
struct Finished {
    record: Record,
    metrics: PathBuf,
}

/// The file of a `--keep` record (`KEEP/LABEL-seedS/`), beside a copy of the run's `metrics.csv`
/// and `config.toml`.
const RECORD_FILE: &str = "result.toml";

/// A finished run as `--keep` keeps it: what the tables need of it, and the question it
/// answers (preset, seed, overrides, budget reached, evaluations), so that a record is taken
/// only for the same question. A few hundred kilobytes with its metrics, meant to be committed:
/// a run directory (its replay memory alone is gigabytes) does not outlive its machine.
#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct Record {
    preset: String,
    seed: u64,
    /// The TOML overrides the run trained with (`--config` and the arm's own keys).
    overrides: String,
    protocol_episodes: u32,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    own_game_episodes: Option<u32>,
    counters: checkpoint::Counters,
    protocol: Scores,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    own_game: Option<Scores>,
}

/// Trains every job to `budget` (each continued if it exists), `workers` at a time, and
/// evaluates each as soon as it has trained, while the others train; with `keep`, a job whose
/// record there answers the same question is taken as it is, and each newly finished job's
/// record is written there. Returns the jobs in their order; fails after all have stopped if
/// any failed, and returns [`Interrupted`] if a run or evaluation was stopped by a signal (then
/// nothing further starts).
fn run_all(
    exe: &Path,
    jobs: &[Job<'_>],
    workers: Option<usize>,
    budget: Budget,
    evals: Evals,
    keep: Option<&Path>,
) -> anyhow::Result<Vec<Finished>> {
    let workers = worker_count(workers);
    let next = Mutex::new(0..jobs.len());
    let results: Vec<Mutex<Option<anyhow::Result<Finished>>>> =
        jobs.iter().map(|_| Mutex::new(None)).collect();
    // A run stopped by a signal (ours, passed on, or one sent to it alone) stops the experiment:
    // no further run starts.
    let stopped = AtomicBool::new(false);
    std::thread::scope(|s| {
        for _ in 0..workers {
            s.spawn(|| loop {
                if stopped.load(Ordering::SeqCst) || stop::requested() {
                    break;
                }
                let Some(i) = next.lock().expect("queue").next() else {
                    break;
                };
                let r = finish_one(exe, &jobs[i], budget, evals, keep);
                if matches!(&r, Err(e) if e.is::<Interrupted>()) {
                    stopped.store(true, Ordering::SeqCst);
                }
                *results[i].lock().expect("result") = Some(r);
            });
        }
    });
    let mut failures = Vec::new();
    let mut finished = Vec::new();
    for (job, r) in jobs.iter().zip(results) {
        match r.into_inner().expect("result") {
            Some(Ok(f)) => finished.push(f),
            Some(Err(err)) if err.is::<Interrupted>() => {}
            Some(Err(err)) => failures.push(format!("{}-seed{}: {err:#}", job.label, job.seed)),
            None => {}
        }
    }
    if !failures.is_empty() {
        bail!("some runs failed:\n{}", failures.join("\n"));
    }
    if stopped.into_inner() || stop::requested() || finished.len() < jobs.len() {
        return Err(stop::stopped());
    }
    Ok(finished)
}

/// One job of [`run_all`]: its `--keep` record if that answers the same question, else trained,
/// evaluated and (with `keep`) recorded.
fn finish_one(
    exe: &Path,
    job: &Job<'_>,
    budget: Budget,
    evals: Evals,
    keep: Option<&Path>,
) -> anyhow::Result<Finished> {
    let name = format!("{}-seed{}", job.label, job.seed);
    let overrides = std::fs::read_to_string(&job.cfg)
        .with_context(|| format!("cannot read {}", job.cfg.display()))?;
    let kept = keep.map(|k| k.join(&name));
    if let Some(k) = &kept {
        if let Some(r) = read_record(k)? {
            if r.preset == job.preset.name()
                && r.seed == job.seed
                && r.overrides == overrides
                && r.protocol_episodes == evals.protocol
                && r.own_game_episodes == evals.own_game
                && budget.done(&r.counters)
            {
                say!(
                    "{name}: kept in {} ({} episodes, {} frames, evaluated)",
                    k.display(),
                    r.counters.episodes,
                    r.counters.frames
                );
                return Ok(Finished {
                    record: r,
                    metrics: k.join("metrics.csv"),
                });
            }
            say!(
                "{name}: the record in {} is of another configuration, budget or evaluation; \
                 it is replaced when the run has trained and been evaluated",
                k.display()
            );
        }
    }
    train_one(exe, job, budget)?;
    let counters = checkpoint::load(&job.dir.join(checkpoint::CHECKPOINT_FILE))?.counters;
    let own_game = match evals.own_game {
        Some(episodes) => Some(evaluate(exe, &job.dir, episodes, 1000 + job.seed)?),
        None => None,
    };
    let protocol = evaluate_protocol(exe, &job.dir, evals.protocol)?;
    log_evaluations(&job.dir, &counters, &protocol, own_game.as_ref());
    let record = Record {
        preset: job.preset.name().to_string(),
        seed: job.seed,
        overrides,
        protocol_episodes: evals.protocol,
        own_game_episodes: evals.own_game,
        counters,
        protocol,
        own_game,
    };
    if let Some(k) = &kept {
        write_record(k, &job.dir, &record)?;
        say!("{name}: recorded in {}", k.display());
    }
    Ok(Finished {
        record,
        metrics: job.dir.join("metrics.csv"),
    })
}

/// Adds a finished run's evaluation scores to its TensorBoard events (where it writes them), at
/// its last agent step: `eval/protocol_*` and `eval/own_game_*` (mean, std, min, max). A failure
/// is said, not fatal: the scores are in the record and the tables.
fn log_evaluations(
    dir: &Path,
    counters: &checkpoint::Counters,
    protocol: &Scores,
    own_game: Option<&Scores>,
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
fn read_record(dir: &Path) -> anyhow::Result<Option<Record>> {
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
    Ok(Some(record))
}

/// Writes a run's record into `dir`: its `metrics.csv` and `config.toml` first, the record last,
/// each atomically, so a record is there only with its metrics.
fn write_record(dir: &Path, run: &Path, record: &Record) -> anyhow::Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    for file in ["metrics.csv", "config.toml"] {
        let from = run.join(file);
        let bytes =
            std::fs::read(&from).with_context(|| format!("cannot read {}", from.display()))?;
        checkpoint::write_atomic(&dir.join(file), &bytes)?;
    }
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
fn check_reuse(dir: &Path, preset: Preset, overrides: &str, seed: u64) -> anyhow::Result<()> {
    let ckpt = dir.join(checkpoint::CHECKPOINT_FILE);
    let saved = dir.join("config.toml");
    let had = if ckpt.exists() {
        checkpoint::load(&ckpt)
            .with_context(|| format!("cannot read the run in {}", dir.display()))?
            .config
    } else if saved.is_file() {
        let text = super::guard::read_text(&saved, "the run's configuration")?;
        Config::resolve(None, Some(&text))
            .with_context(|| format!("cannot read the run in {}", dir.display()))?
    } else {
        return Ok(());
    };
    let mut asked = Config::resolve(Some(preset), Some(overrides))?;
    asked.seed = seed;
    let differ = config_differences(&had, &asked);
    if !differ.is_empty() {
        bail!(
            "{} holds a run trained with another configuration than this experiment asks for \
             ({}): it is not taken as this experiment's run. Give another --out, or move that \
             run away",
            dir.display(),
            differ.join("; ")
        );
    }
    Ok(())
}

/// The keys whose values differ between two configurations, as `key: A, not B` (`[env]`'s keys as
/// `env.KEY`), leaving out the budget (`episodes`, `max_frames`), and the precision where `asked`
/// says `auto`.
fn config_differences(had: &Config, asked: &Config) -> Vec<String> {
    let flat = |c: &Config| -> std::collections::BTreeMap<String, toml::Value> {
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
        out.remove("episodes");
        out.remove("max_frames");
        // `auto` asks for whichever precision the run measured faster: either answers it.
        if asked.precision == invaders::tensor::plan::Precision::Auto {
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

/// `--keep`'s directory, made before anything trains so a bad path fails now.
fn make_keep(keep: Option<&Path>) -> anyhow::Result<()> {
    if let Some(k) = keep {
        std::fs::create_dir_all(k).with_context(|| format!("cannot create {}", k.display()))?;
    }
    Ok(())
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

/// `--jobs`, or one per core.
fn worker_count(jobs: Option<usize>) -> usize {
    jobs.unwrap_or_else(|| {
        std::thread::available_parallelism()
            .map(|n| n.get())
            .unwrap_or(1)
    })
    .max(1)
}

/// Trains one run to `budget`, continuing it if it exists; [`Interrupted`] if a signal stopped it
/// (or a stop came before it started).
fn train_one(exe: &Path, job: &Job<'_>, budget: Budget) -> anyhow::Result<()> {
    let (label, seed, dir) = (job.label, job.seed, &job.dir);
    let ckpt = dir.join(checkpoint::CHECKPOINT_FILE);
    let mut cmd = invaders_command(exe);
    if ckpt.exists() {
        let counters = checkpoint::load(&ckpt)?.counters;
        if budget.done(&counters) {
            say!(
                "{label}-seed{seed}: already trained ({} episodes, {} frames)",
                counters.episodes,
                counters.frames
            );
            return Ok(());
        }
        cmd.args(["train", "--resume"]).arg(dir);
    } else {
        // `train --out` starts a run stopped before its first checkpoint again, and refuses a
        // directory whose checkpoint was lost (its history is kept).
        cmd.args([
            "train",
            "--preset",
            job.preset.name(),
            "--seed",
            &seed.to_string(),
            "--config",
        ])
        .arg(&job.cfg)
        .arg("--out")
        .arg(dir);
    }
    cmd.args(budget.flag())
        .args(["--threads", &job.threads.to_string()]);
    std::fs::create_dir_all(dir.parent().unwrap_or(Path::new(".")))?;
    let log_path = dir.with_extension("log");
    let log = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(&log_path)?;
    say!("{label}-seed{seed}: training (log: {})", log_path.display());
    let Some(out) =
        stop::run(cmd.stdout(log.try_clone()?).stderr(log)).context("cannot run invaders train")?
    else {
        return Err(Interrupted.into());
    };
    let status = out.status;
    if status.code() == Some(130) {
        say!("{label}-seed{seed}: stopped with a checkpoint");
        return Err(Interrupted.into());
    }
    // Killed by the stop before it could catch it (while it loaded its replay memory, say):
    // nothing of it was lost, and this is a stop, not a failure.
    if stop::requested() && std::os::unix::process::ExitStatusExt::signal(&status).is_some() {
        say!("{label}-seed{seed}: stopped before it trained");
        return Err(Interrupted.into());
    }
    if !status.success() {
        return Err(anyhow!(
            "invaders train failed ({status}); see {}",
            log_path.display()
        ));
    }
    say!("{label}-seed{seed}: done");
    Ok(())
}

/// The evaluation of a run's final checkpoint in its own game (its own `env` settings, ε = 0.05).
fn evaluate(exe: &Path, dir: &Path, episodes: u32, seed: u64) -> anyhow::Result<Scores> {
    let (episodes, seed) = (episodes.to_string(), seed.to_string());
    let last = run_eval(exe, dir, &["--episodes", &episodes, "--seed", &seed])?;
    parse_scores(&last)
}

/// Runs `invaders eval` on a run's final checkpoint with `args` (one thread) and returns its
/// summary line (`… mean M std S min A max B`); [`Interrupted`] if a stop came first or ended
/// it.
fn run_eval(exe: &Path, dir: &Path, args: &[&str]) -> anyhow::Result<String> {
    let mut cmd = invaders_command(exe);
    cmd.args(["eval", "--threads", "1"])
        .args(args)
        .arg("--checkpoint")
        .arg(dir)
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped());
    let out = stop::run(&mut cmd).context("cannot run invaders eval")?;
    let Some(out) = out.filter(|_| !stop::requested()) else {
        return Err(Interrupted.into());
    };
    if !out.status.success() {
        bail!(
            "eval of {} failed: {}",
            dir.display(),
            String::from_utf8_lossy(&out.stderr)
        );
    }
    let text = String::from_utf8_lossy(&out.stdout);
    Ok(text.lines().last().unwrap_or_default().to_string())
}

/// An evaluation's summary.
#[derive(Clone, Copy, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct Scores {
    mean: f64,
    std: f64,
    min: f64,
    max: f64,
}

/// Evaluates a run's final network by the protocol (`eval --protocol`: `v5`, ε = 0.01, seed
/// 1 000 000) over `episodes` episodes. The summary is kept beside the run (`DIR.protocol`, with
/// the frames the network was trained for): evaluation is deterministic, so asking again for
/// the same network and episodes reads it back instead of playing them again.
fn evaluate_protocol(exe: &Path, dir: &Path, episodes: u32) -> anyhow::Result<Scores> {
    let frames = checkpoint::load(&dir.join(checkpoint::CHECKPOINT_FILE))?
        .counters
        .frames;
    let key = format!("frames {frames} episodes {episodes}");
    let cache = dir.with_extension("protocol");
    // A summary kept for this network and these episodes; anything else (another network, a
    // file cut short) is played again.
    let kept = std::fs::read_to_string(&cache).ok().and_then(|text| {
        let (k, line) = text.split_once('\n')?;
        (k == key).then(|| parse_scores(line.trim_end()).ok())?
    });
    if let Some(scores) = kept {
        return Ok(scores);
    }
    let last = run_eval(
        exe,
        dir,
        &["--protocol", "--episodes", &episodes.to_string()],
    )?;
    let scores = parse_scores(&last)?;
    std::fs::write(&cache, format!("{key}\n{last}\n"))
        .with_context(|| format!("cannot write {}", cache.display()))?;
    Ok(scores)
}

/// The scores of an `eval` summary line (`… mean M std S min A max B`).
fn parse_scores(last: &str) -> anyhow::Result<Scores> {
    let field = |name: &str| {
        last.split(&format!(" {name} "))
            .nth(1)
            .and_then(|s| s.split_whitespace().next())
            .and_then(|v| v.parse::<f64>().ok())
            .ok_or_else(|| anyhow!("cannot read `{name}` from the eval summary `{last}`"))
    };
    Ok(Scores {
        mean: field("mean")?,
        std: field("std")?,
        min: field("min")?,
        max: field("max")?,
    })
}

/// The `--config` file's text (empty without one).
fn read_overrides(path: Option<&Path>) -> anyhow::Result<String> {
    match path {
        Some(p) => super::guard::read_text(p, "config file"),
        None => Ok(String::new()),
    }
}

/// What a finished run reports beside its score.
struct RunSummary {
    frames: u64,
    hours: f64,
    steps_per_second: f64,
    /// The mean reward of its last 100 training episodes.
    last100: f64,
    /// Its training curve: (frames, reward) per episode.
    points: Vec<(f64, f64)>,
}

fn summarize(run: &Finished) -> anyhow::Result<RunSummary> {
    let c = run.record.counters;
    let points = read_frame_metrics(&run.metrics)?;
    let tail = &points[points.len().saturating_sub(100)..];
    Ok(RunSummary {
        frames: c.frames,
        hours: c.wall_seconds / 3600.0,
        steps_per_second: c.agent_steps as f64 / c.wall_seconds.max(1e-9),
        last100: tail.iter().map(|p| p.1).sum::<f64>() / tail.len().max(1) as f64,
        points,
    })
}

/// An evaluation's score as the tables print it: `mean ± std (min–max)` over its episodes.
fn scores_cell(s: &Scores) -> String {
    format!("{:.1} ± {:.1} ({:.0}–{:.0})", s.mean, s.std, s.min, s.max)
}

/// `experiment strong`: the preset with seeds 1..=N, each evaluated by the protocol.
fn strong(args: &StrongArgs) -> anyhow::Result<()> {
    if args.seeds == 0 || args.frames == 0 || args.threads == 0 {
        bail!("--seeds, --frames and --threads must be at least 1");
    }
    if args.eval_episodes < PROTOCOL_EPISODES {
        bail!(
            "the evaluation protocol plays at least {PROTOCOL_EPISODES} episodes (--eval-episodes)"
        );
    }
    let text = read_overrides(args.config.as_deref())?;
    let config =
        Config::resolve(Some(Preset::Strong), Some(&text)).context("configuration of the runs")?;
    Config {
        seed: args.seeds,
        max_frames: args.frames,
        ..config
    }
    .validate()
    .context("--seeds or --frames")?;
    // The references are read before hours of training, so a bad file fails now.
    let references = match &args.reference {
        Some(r) => read_references(r, &args.agents)?,
        None => Vec::new(),
    };
    make_keep(args.keep.as_deref())?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    for seed in 1..=args.seeds {
        check_reuse(
            &args.out.join(format!("strong-seed{seed}")),
            Preset::Strong,
            &text,
            seed,
        )?;
    }
    let cfg = args.out.join("strong.toml");
    std::fs::write(&cfg, &text).with_context(|| format!("cannot write {}", cfg.display()))?;
    let exe = exe_path()?;
    let jobs: Vec<Job<'_>> = (1..=args.seeds)
        .map(|seed| Job {
            label: "strong",
            preset: Preset::Strong,
            seed,
            cfg: cfg.clone(),
            dir: args.out.join(format!("strong-seed{seed}")),
            threads: args.threads,
        })
        .collect();
    say!(
        "{} runs of {} frames, into {}",
        jobs.len(),
        args.frames,
        args.out.display()
    );
    // Runs at once: as many as the cores hold at `--threads` each, unless `--jobs` says.
    let workers = args
        .jobs
        .unwrap_or_else(|| worker_count(None) / args.threads)
        .max(1);
    let evals = Evals {
        protocol: args.eval_episodes,
        own_game: None,
    };
    let finished = run_all(
        &exe,
        &jobs,
        Some(workers),
        Budget::Frames(args.frames),
        evals,
        args.keep.as_deref(),
    )?;
    let (mut rows, mut means, mut seeds) = (Vec::new(), Vec::new(), Vec::new());
    for (job, run) in jobs.iter().zip(&finished) {
        let (r, s) = (summarize(run)?, run.record.protocol);
        rows.push(format!(
            "| {} | {} | {:.2} | {:.0} | {:.1} | {} |",
            job.seed,
            r.frames,
            r.hours,
            r.steps_per_second,
            r.last100,
            scores_cell(&s)
        ));
        means.push(s.mean);
        seeds.push(r.points);
    }
    let groups = [Group {
        label: "strong".to_string(),
        seeds,
    }];
    let title = format!("Space Invaders, strong preset: {} seed(s)", args.seeds);
    plot_groups_frames(
        &groups,
        &references,
        &title,
        100,
        &args.out.join("rewards.png"),
    )?;
    let table = format!(
        "# The strong preset over {} seeds\n\nCommand: `{}`\n\nBudget: {} frames per run, {} thread(s) each, {} at a time. Evaluation: the protocol, {} episodes of `v5` with ε = {PROTOCOL_EPSILON} on seed {PROTOCOL_SEED}.\n\n| seed | frames | wall hours | agent steps/s | training return, last 100 episodes | protocol score: mean ± std (min–max) |\n| --- | --- | --- | --- | --- | --- |\n{}\n\nMean protocol score over the seeds: {}. Figure: `rewards.png`.\n",
        args.seeds,
        command_line(),
        args.frames,
        args.threads,
        workers,
        args.eval_episodes,
        rows.join("\n"),
        mean_std(&means)
    );
    std::fs::write(args.out.join("results.md"), &table).context("cannot write results.md")?;
    out!("{table}");
    Ok(())
}

/// `experiment ablation`: the preset and the arms of [`ABLATIONS`] that `--arms` names (all by
/// default), with one seed and budget, each evaluated by the protocol and set against the
/// preset.
fn ablation(args: &AblationArgs) -> anyhow::Result<()> {
    if args.frames == 0 || args.threads == 0 {
        bail!("--frames and --threads must be at least 1");
    }
    if args.eval_episodes < PROTOCOL_EPISODES {
        bail!(
            "the evaluation protocol plays at least {PROTOCOL_EPISODES} episodes (--eval-episodes)"
        );
    }
    if args.seed == PROTOCOL_SEED {
        bail!("--seed {PROTOCOL_SEED} is the seed the protocol plays on; train with another");
    }
    let arms: Vec<&Ablation> = ABLATIONS
        .iter()
        .filter(|a| a.keys.is_empty() || args.arms.is_empty() || args.arms.contains(&a.name.into()))
        .collect();
    let text = read_overrides(args.config.as_deref())?;
    let overrides: toml::Table = text.parse().context("--config is not valid TOML")?;
    let preset =
        Config::resolve(Some(Preset::Strong), Some(&text)).context("configuration of the runs")?;
    Config {
        seed: args.seed,
        max_frames: args.frames,
        ..preset.clone()
    }
    .validate()
    .context("--seed or --frames")?;
    // Every arm's configuration, checked before anything is written or trained: each must
    // switch its component off against the preset (`--config` may already have).
    let mut texts = Vec::new();
    for arm in &arms {
        let mut table = overrides.clone();
        merge_toml(
            &mut table,
            arm.keys.parse().expect("ABLATIONS' keys are TOML"),
        );
        let arm_text = toml::to_string(&table)?;
        let config = Config::resolve(Some(Preset::Strong), Some(&arm_text))
            .with_context(|| format!("configuration of {}", arm.name))?;
        if !(arm.switches)(&config, &preset) {
            bail!(
                "arm `{}` would not switch off {} against the preset with --config's keys",
                arm.name,
                arm.what
            );
        }
        check_reuse(
            &args.out.join(format!("{}-seed{}", arm.name, args.seed)),
            Preset::Strong,
            &arm_text,
            args.seed,
        )?;
        texts.push(arm_text);
    }
    make_keep(args.keep.as_deref())?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    let mut jobs = Vec::new();
    for (arm, arm_text) in arms.iter().zip(texts) {
        let cfg = args.out.join(format!("{}.toml", arm.name));
        std::fs::write(&cfg, &arm_text)
            .with_context(|| format!("cannot write {}", cfg.display()))?;
        jobs.push(Job {
            label: arm.name,
            preset: Preset::Strong,
            seed: args.seed,
            cfg,
            dir: args.out.join(format!("{}-seed{}", arm.name, args.seed)),
            threads: args.threads,
        });
    }
    let workers = args
        .jobs
        .unwrap_or_else(|| worker_count(None) / args.threads)
        .max(1);
    say!(
        "{} runs of {} frames (seed {}), {} at a time, into {}",
        jobs.len(),
        args.frames,
        args.seed,
        workers,
        args.out.display()
    );
    let exe = exe_path()?;
    let evals = Evals {
        protocol: args.eval_episodes,
        own_game: None,
    };
    let finished = run_all(
        &exe,
        &jobs,
        Some(workers),
        Budget::Frames(args.frames),
        evals,
        args.keep.as_deref(),
    )?;
    let scores: Vec<Scores> = finished.iter().map(|f| f.record.protocol).collect();
    let summaries = finished
        .iter()
        .map(summarize)
        .collect::<anyhow::Result<Vec<_>>>()?;
    // The preset is the first arm.
    let (base_return, base_score) = (summaries[0].last100, scores[0].mean);
    let mut rows = Vec::new();
    let mut groups = Vec::new();
    for (((job, arm), r), s) in jobs.iter().zip(&arms).zip(summaries).zip(&scores) {
        rows.push(format!(
            "| {} | {} | {} | {:.2} | {:.0} | {:.1} | {:+.1} | {} | {:+.1} |",
            job.label,
            arm.what,
            r.frames,
            r.hours,
            r.steps_per_second,
            r.last100,
            r.last100 - base_return,
            scores_cell(s),
            s.mean - base_score
        ));
        groups.push(Group {
            label: job.label.to_string(),
            seeds: vec![r.points],
        });
    }
    let title = format!(
        "Space Invaders, strong preset ablation: seed {}, {} frames",
        args.seed, args.frames
    );
    plot_groups_frames(&groups, &[], &title, 100, &args.out.join("rewards.png"))?;
    let table = format!(
        "# The strong preset, each component switched off in turn\n\nCommand: `{}`\n\nBudget: {} frames per run, seed {}, {} thread(s) each, {} at a time. Evaluation: the protocol, {} episodes of `v5` with ε = {PROTOCOL_EPSILON} on seed {PROTOCOL_SEED}. Δ: against the preset (`strong`).\n\n| arm | switched off | frames | wall hours | agent steps/s | training return, last 100 episodes | Δ | protocol score: mean ± std (min–max) | Δ |\n| --- | --- | --- | --- | --- | --- | --- | --- | --- |\n{}\n\nOne seed per arm: one network's protocol score moves by about ±50 from one checkpoint to the next, and seeds of one configuration differed by up to about 90 in training return at 1.5 M frames (docs/strong.md), so only larger differences say something. Figure: `rewards.png`.\n",
        command_line(),
        args.frames,
        args.seed,
        args.threads,
        workers,
        args.eval_episodes,
        rows.join("\n"),
    );
    std::fs::write(args.out.join("results.md"), &table).context("cannot write results.md")?;
    out!("{table}");
    Ok(())
}

/// This program, which each run and evaluation runs again as a child process. On Linux that is
/// `/proc/self/exe`: the very file this process started from, even after a `cargo build` has
/// replaced it during an experiment of hours (its path would then name a new program, or for a
/// moment none), so every run of an experiment trains with the program it started with.
fn exe_path() -> anyhow::Result<PathBuf> {
    let own = Path::new("/proc/self/exe");
    if cfg!(target_os = "linux") && own.exists() {
        return Ok(own.to_path_buf());
    }
    std::env::current_exe().context("cannot find the invaders executable")
}

/// A command running `exe` (from [`exe_path`]), which names itself `invaders` in its messages.
fn invaders_command(exe: &Path) -> Command {
    let mut cmd = Command::new(exe);
    #[cfg(unix)]
    std::os::unix::process::CommandExt::arg0(&mut cmd, "invaders");
    cmd
}

/// This command as a shell would take it back: `invaders` and its arguments, each quoted where
/// the shell would otherwise split or expand it.
fn command_line() -> String {
    let quote = |a: String| {
        if !a.is_empty()
            && a.chars()
                .all(|c| c.is_ascii_alphanumeric() || "-_./,=:+".contains(c))
        {
            a
        } else {
            format!("'{}'", a.replace('\'', "'\\''"))
        }
    };
    std::iter::once("invaders".to_string())
        .chain(std::env::args().skip(1).map(quote))
        .collect::<Vec<_>>()
        .join(" ")
}

/// Stopping an experiment. Its child processes run in process groups of their own, so a Ctrl-C
/// at the terminal reaches this process alone, and it passes each Ctrl-C, SIGTERM or SIGHUP on to
/// every running child exactly once, as SIGTERM. A training takes the first as `train` takes a
/// Ctrl-C (it stops after the current episode, with a checkpoint) and a second as "stop at once"
/// (its last checkpoint is kept); an evaluation ends at once and is played again next time. On
/// Linux a child also gets SIGTERM if this process dies without passing anything on (SIGKILL,
/// the OOM killer). Ctrl-Z suspends this process only: its runs go on training.
///
/// A signal to the experiment's process group (`kill -- -PGID`) reaches the experiment alone,
/// which passes it on once. A signal to every process at once (a service manager stopping a
/// whole control group) reaches each run twice, directly and passed on: the run then stops at
/// once and keeps its last periodic checkpoint.
mod stop {
    use std::process::{Command, Output, Stdio};
    use std::sync::{Mutex, MutexGuard};

    struct State {
        /// Signals received so far.
        signals: u32,
        /// The children running now (process ids).
        children: Vec<u32>,
        /// Whether the handler is in place (else children stay in this process's group, where
        /// a terminal's Ctrl-C reaches them directly).
        caught: bool,
        /// Whether any child has started: before that, a signal ends the experiment at once
        /// (it may be blocked reading its `--config` from a FIFO).
        started: bool,
    }

    /// One lock for all of it, so that a child is started only while no stop has been asked
    /// for, and every child on the list gets each signal once.
    static STATE: Mutex<State> = Mutex::new(State {
        signals: 0,
        children: Vec::new(),
        caught: false,
        started: false,
    });

    fn state() -> MutexGuard<'static, State> {
        STATE.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn term(pid: u32) {
        // SAFETY: `kill` touches no memory of ours. `pid` is a child not reaped yet (`run` takes
        // it off the list before it reaps it, and `catch` makes sure the system does not reap
        // it first), so it names that child and no other process.
        unsafe {
            libc::kill(pid as libc::pid_t, libc::SIGTERM);
        }
    }

    /// Installs the handler (once, before any child starts).
    pub fn catch() {
        // SAFETY: setting a signal's disposition to the default touches no memory of ours. With
        // SIGCHLD ignored (a disposition `exec` keeps), the system would reap children itself.
        unsafe {
            libc::signal(libc::SIGCHLD, libc::SIG_DFL);
        }
        let set = ctrlc::set_handler(|| {
            // ctrlc runs this on a thread of its own, not in the signal handler: a lock is fine.
            let first = {
                let mut s = state();
                if !s.started {
                    say!("\nstopped before any run started: nothing has changed");
                    std::process::exit(130);
                }
                s.signals += 1;
                s.children.iter().copied().for_each(term);
                s.signals == 1
            };
            if first {
                say!(
                    "\nstopping: the runs stop after their episode with a checkpoint; the same \
                     command continues them (Ctrl-C again to stop them at once)"
                );
            } else {
                say!("\nstopping the runs at once: each keeps its last checkpoint");
            }
        });
        match set {
            Ok(()) => state().caught = true,
            Err(e) => {
                say!("warning: a Ctrl-C will not reach the runs through the experiment ({e})")
            }
        }
    }

    /// Whether a Ctrl-C, SIGTERM or SIGHUP has arrived.
    pub fn requested() -> bool {
        state().signals > 0
    }

    /// The error an experiment stopped by a signal returns (the program exits with 130).
    pub fn stopped() -> anyhow::Error {
        say!("experiment stopped; run the same command again to continue it");
        super::Interrupted.into()
    }

    /// Runs `cmd` to its end where a stop reaches it (see the module), with no input, and
    /// returns its status and whatever output was piped; `None` if a stop came before it could
    /// start.
    pub fn run(cmd: &mut Command) -> std::io::Result<Option<Output>> {
        use std::io::Read;
        let mut child = {
            let mut s = state();
            if s.signals > 0 {
                return Ok(None);
            }
            if s.caught {
                std::os::unix::process::CommandExt::process_group(cmd, 0);
            }
            die_with_parent(cmd);
            let child = cmd.stdin(Stdio::null()).spawn()?;
            s.started = true;
            s.children.push(child.id());
            child
        };
        let pid = child.id();
        fn drain(pipe: Option<impl Read>) -> Vec<u8> {
            let mut bytes = Vec::new();
            if let Some(mut pipe) = pipe {
                let _ = pipe.read_to_end(&mut bytes);
            }
            bytes
        }
        let (stdout, stderr) = (child.stdout.take(), child.stderr.take());
        std::thread::scope(|s| {
            let stdout = s.spawn(|| drain(stdout));
            let stderr = s.spawn(|| drain(stderr));
            // Wait for the child to end without reaping it (`WNOWAIT`): until `wait` below, its
            // process id stays its own, so the handler never signals a stranger.
            loop {
                // SAFETY: a zeroed `siginfo_t` (plain integers) is a valid value, and `info` is
                // a valid place for `waitid` to write one to.
                let rc = unsafe {
                    let mut info: libc::siginfo_t = std::mem::zeroed();
                    libc::waitid(
                        libc::P_PID,
                        pid as libc::id_t,
                        &mut info,
                        libc::WEXITED | libc::WNOWAIT,
                    )
                };
                if rc == 0
                    || std::io::Error::last_os_error().kind() != std::io::ErrorKind::Interrupted
                {
                    break;
                }
            }
            state().children.retain(|&p| p != pid);
            let status = child.wait()?;
            Ok(Some(Output {
                status,
                stdout: stdout.join().unwrap_or_default(),
                stderr: stderr.join().unwrap_or_default(),
            }))
        })
    }

    /// On Linux, SIGTERM to the child when the thread that started it ends: `run` waits for the
    /// child on that thread, so only this process's death ends it first.
    fn die_with_parent(cmd: &mut Command) {
        #[cfg(target_os = "linux")]
        {
            use std::os::unix::process::CommandExt;
            let parent = std::process::id();
            // SAFETY: between fork and exec the closure calls only `prctl` and `getppid`, both
            // async-signal-safe, and allocates nothing.
            unsafe {
                cmd.pre_exec(move || {
                    libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM);
                    // The parent may have died before the request was made.
                    if libc::getppid() as u32 != parent {
                        return Err(std::io::Error::from_raw_os_error(libc::ESRCH));
                    }
                    Ok(())
                });
            }
        }
        #[cfg(not(target_os = "linux"))]
        let _ = cmd;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The `(key, value)` leaves of a configuration, `[env]`'s keys as `env.KEY`.
    fn leaves(c: &Config) -> Vec<(String, toml::Value)> {
        let mut out = Vec::new();
        for (k, v) in toml::Table::try_from(c).expect("a config serialises") {
            match v {
                toml::Value::Table(t) => {
                    out.extend(t.into_iter().map(|(k2, v2)| (format!("{k}.{k2}"), v2)))
                }
                v => out.push((k, v)),
            }
        }
        out
    }

    /// Each arm over the bare preset changes exactly the one setting its keys name, and its
    /// check says it switches that off; over an arm's own keys the check refuses it.
    #[test]
    fn every_arm_switches_off_one_setting_of_the_preset() {
        let preset = Config::preset(Preset::Strong);
        assert!(ABLATIONS[0].keys.is_empty() && ABLATIONS[0].name == "strong");
        for arm in &ABLATIONS[1..] {
            let config = Config::resolve(Some(Preset::Strong), Some(arm.keys)).unwrap();
            let changed: Vec<String> = leaves(&config)
                .into_iter()
                .zip(leaves(&preset))
                .filter(|(a, p)| a != p)
                .map(|(a, _)| a.0)
                .collect();
            let key = arm
                .keys
                .rsplit('\n')
                .next()
                .unwrap()
                .split(" = ")
                .next()
                .unwrap();
            assert_eq!(changed.len(), 1, "{}: {changed:?}", arm.name);
            assert!(changed[0].ends_with(key), "{}: {changed:?}", arm.name);
            assert!((arm.switches)(&config, &preset), "{}", arm.name);
            assert!(
                !(arm.switches)(&config, &config),
                "{}: already off",
                arm.name
            );
        }
        let names: Vec<&str> = ABLATIONS.iter().map(|a| a.name).collect();
        let mut unique = names.clone();
        unique.sort_unstable();
        unique.dedup();
        assert_eq!(unique.len(), names.len(), "{names:?}");
    }
}
