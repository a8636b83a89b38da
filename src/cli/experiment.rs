//! `invaders experiment preprocessing`: the article's comparison, reproduced.
//!
//! Trains `article-vanilla`, `article` and `article-as-written` (and the `article` preset with
//! any other pipeline named with `--pipeline`) with the same seeds and budget, as separate
//! `invaders train` processes running side by side (one per core, one kernel thread each), then
//! evaluates every final checkpoint over 30 episodes and writes `rewards.png` (mean over seeds
//! with a min–max band) and `results.md` (the table, with the command and budget) into `--out`.
//! Re-running the same command continues unfinished runs and skips finished ones.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Mutex;

use anyhow::{anyhow, bail, Context};
use clap::{Args, Subcommand, ValueEnum};

use invaders::dqn::checkpoint;
use invaders::dqn::{Config, Preset};
use invaders::env::Pipeline;
use invaders::plot::{plot_groups, read_metrics, Group};

#[derive(Debug, Subcommand)]
pub enum Experiment {
    /// Vanilla against stacked and composed inputs (the article's figures).
    Preprocessing(PreprocessingArgs),
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
    #[arg(long)]
    jobs: Option<usize>,
    /// Evaluation episodes per final checkpoint.
    #[arg(long, default_value_t = 30)]
    eval_episodes: u32,
    /// A TOML file of overrides applied to every run (e.g. a shorter ε decay for a small budget).
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
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
    let Experiment::Preprocessing(args) = e;
    if args.episodes == 0 || args.seeds == 0 || args.eval_episodes == 0 {
        bail!("--episodes, --seeds and --eval-episodes must be at least 1");
    }
    let overrides = match &args.config {
        Some(p) => {
            std::fs::read_to_string(p).with_context(|| format!("cannot read {}", p.display()))?
        }
        None => String::new(),
    };
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    let exe = std::env::current_exe().context("cannot find the invaders executable")?;
    let arms = arms(args);
    // Every run's config file, checked before anything starts.
    let mut jobs = Vec::new();
    for arm in &arms {
        let mut table: toml::Table = overrides.parse().context("--config is not valid TOML")?;
        if let Some(p) = arm.pipeline {
            table.insert("pipeline".into(), toml::Value::try_from(p)?);
        }
        let text = toml::to_string(&table)?;
        Config::resolve(Some(arm.preset), Some(&text))
            .with_context(|| format!("configuration of {}", arm.label))?;
        let cfg_path = args.out.join(format!("{}.toml", arm.label));
        std::fs::write(&cfg_path, &text)
            .with_context(|| format!("cannot write {}", cfg_path.display()))?;
        for seed in 0..args.seeds {
            jobs.push((
                arm,
                seed,
                cfg_path.clone(),
                args.out.join(format!("{}-seed{seed}", arm.label)),
            ));
        }
    }
    let workers = args
        .jobs
        .unwrap_or_else(|| {
            std::thread::available_parallelism()
                .map(|n| n.get())
                .unwrap_or(1)
        })
        .max(1);
    eprintln!(
        "{} runs of {} episodes, {workers} at a time, into {}",
        jobs.len(),
        args.episodes,
        args.out.display()
    );
    let queue = Mutex::new(jobs.iter());
    let failures = Mutex::new(Vec::new());
    std::thread::scope(|s| {
        for _ in 0..workers {
            s.spawn(|| loop {
                let Some((arm, seed, cfg, dir)) = queue.lock().expect("queue").next() else {
                    break;
                };
                if let Err(err) = train_one(&exe, arm, *seed, cfg, dir, args.episodes) {
                    failures
                        .lock()
                        .expect("failures")
                        .push(format!("{}-seed{seed}: {err:#}", arm.label));
                }
            });
        }
    });
    let failures = failures.into_inner().expect("failures");
    if !failures.is_empty() {
        bail!("some runs failed:\n{}", failures.join("\n"));
    }
    // Evaluate every final checkpoint, then the figure and the table.
    let mut rows = Vec::new();
    let mut groups = Vec::new();
    for arm in &arms {
        let (mut last100, mut evals, mut seeds) = (Vec::new(), Vec::new(), Vec::new());
        for seed in 0..args.seeds {
            let dir = args.out.join(format!("{}-seed{seed}", arm.label));
            let points = read_metrics(&dir.join("metrics.csv"))?;
            let tail = &points[points.len().saturating_sub(100)..];
            last100.push(tail.iter().map(|p| p.1).sum::<f64>() / tail.len().max(1) as f64);
            evals.push(evaluate(&exe, &dir, args.eval_episodes, 1000 + seed)?);
            seeds.push(points);
        }
        rows.push(format!(
            "| {} | {} | {} | {} |",
            arm.label,
            args.seeds,
            mean_std(&last100),
            mean_std(&evals)
        ));
        groups.push(Group {
            label: arm.label.clone(),
            seeds,
        });
    }
    let png = args.out.join("rewards.png");
    let title = format!(
        "Space Invaders: {} episodes, {} seed(s) per configuration",
        args.episodes, args.seeds
    );
    plot_groups(&groups, &title, 100, &png)?;
    let command: Vec<String> = std::env::args().collect();
    let table = format!(
        "# Preprocessing experiment\n\nCommand: `{}`\n\nBudget: {} episodes per run, {} seed(s) per configuration; evaluation over {} episodes with ε = 0.05.\n\n| configuration | seeds | mean reward, last 100 episodes | evaluation score |\n| --- | --- | --- | --- |\n{}\n\nMeans over seeds ± their standard deviation (population). Figure: `rewards.png`.\n",
        command.join(" "),
        args.episodes,
        args.seeds,
        args.eval_episodes,
        rows.join("\n")
    );
    std::fs::write(args.out.join("results.md"), &table).context("cannot write results.md")?;
    println!("{table}");
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

/// Trains one run to `episodes`, continuing it if it exists.
fn train_one(
    exe: &Path,
    arm: &Arm,
    seed: u64,
    cfg: &Path,
    dir: &Path,
    episodes: u64,
) -> anyhow::Result<()> {
    let ckpt = dir.join(checkpoint::CHECKPOINT_FILE);
    let mut cmd = Command::new(exe);
    if ckpt.exists() {
        let done = checkpoint::load(&ckpt)?.counters.episodes;
        if done >= episodes {
            eprintln!(
                "{}-seed{seed}: already trained ({done} episodes)",
                arm.label
            );
            return Ok(());
        }
        cmd.args(["train", "--resume"]).arg(dir);
    } else {
        if dir.exists() {
            std::fs::remove_dir_all(dir)
                .with_context(|| format!("cannot clear unfinished {}", dir.display()))?;
        }
        cmd.args([
            "train",
            "--preset",
            arm.preset.name(),
            "--seed",
            &seed.to_string(),
            "--config",
        ])
        .arg(cfg)
        .arg("--out")
        .arg(dir);
    }
    cmd.args(["--episodes", &episodes.to_string(), "--threads", "1"]);
    std::fs::create_dir_all(dir.parent().unwrap_or(Path::new(".")))?;
    let log_path = dir.with_extension("log");
    let log = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(&log_path)?;
    eprintln!(
        "{}-seed{seed}: training (log: {})",
        arm.label,
        log_path.display()
    );
    let status = cmd
        .stdout(log.try_clone()?)
        .stderr(log)
        .status()
        .context("cannot start invaders train")?;
    if !status.success() {
        return Err(anyhow!(
            "invaders train failed ({status}); see {}",
            log_path.display()
        ));
    }
    eprintln!("{}-seed{seed}: done", arm.label);
    Ok(())
}

/// The mean evaluation score of a run's final checkpoint.
fn evaluate(exe: &Path, dir: &Path, episodes: u32, seed: u64) -> anyhow::Result<f64> {
    let out = Command::new(exe)
        .args([
            "eval",
            "--threads",
            "1",
            "--episodes",
            &episodes.to_string(),
            "--seed",
            &seed.to_string(),
            "--checkpoint",
        ])
        .arg(dir)
        .output()
        .context("cannot start invaders eval")?;
    let text = String::from_utf8_lossy(&out.stdout);
    if !out.status.success() {
        bail!(
            "eval of {} failed: {}",
            dir.display(),
            String::from_utf8_lossy(&out.stderr)
        );
    }
    let last = text.lines().last().unwrap_or_default();
    last.split(" mean ")
        .nth(1)
        .and_then(|s| s.split_whitespace().next())
        .and_then(|v| v.parse().ok())
        .ok_or_else(|| anyhow!("cannot read the eval score from `{last}`"))
}
