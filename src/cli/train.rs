//! `invaders train`: a headless training run that writes a run directory.
//!
//! ```text
//! RUN_DIR/
//!   config.toml              the resolved configuration
//!   metrics.csv              one row per episode (see `EpisodeRow::HEADER`)
//!   checkpoint.safetensors   the latest checkpoint (replaced atomically)
//!   replay-E.safetensors     the replay memory saved with it (unless checkpoint_replay = false)
//!   rewards.png              reward per episode with a 100-episode moving average
//! ```

use std::io::{IsTerminal, Write};
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};

use super::in_pool;
use invaders::dqn::checkpoint::{self, write_atomic};
use invaders::dqn::{Agent, Config, EpisodeRow, Preset, NO_EPISODE_LIMIT};
use invaders::env::SpaceInvaders;
use invaders::plot::{plot_rewards, Curve};

#[derive(Debug, Args)]
pub struct TrainArgs {
    /// The configuration to start from (with --resume: the preset the run must have been
    /// trained with, checked).
    #[arg(long, value_enum)]
    preset: Option<Preset>,
    /// A TOML file overriding any configuration key (see `config.toml` in a run directory).
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// Episodes to train for (the article: 800).
    #[arg(long, conflicts_with = "frames")]
    episodes: Option<u64>,
    /// Train until this many emulator frames instead.
    #[arg(long)]
    frames: Option<u64>,
    /// Seed of every random generator.
    #[arg(long)]
    seed: Option<u64>,
    /// Worker threads for the kernels (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// The run directory (default: runs/PRESET-seedS-TIME). Must be new or empty.
    #[arg(long, value_name = "DIR", conflicts_with = "resume")]
    out: Option<PathBuf>,
    /// Continue the run in DIR from its checkpoint (its configuration is kept; --episodes or
    /// --frames may extend the budget).
    #[arg(long, value_name = "DIR")]
    resume: Option<PathBuf>,
    /// Print the resident memory (VmRSS) every N episodes, to check it stays flat.
    #[arg(long, value_name = "N")]
    log_rss: Option<u64>,
}

/// The process's resident memory in KiB (`VmRSS` of /proc/self/status; Linux only).
fn rss_kib() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmRSS:"))?;
    line.split_whitespace().nth(1)?.parse().ok()
}

fn default_out(config: &Config) -> PathBuf {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0);
    PathBuf::from("runs").join(format!(
        "{}-seed{}-{secs}",
        config.preset.name(),
        config.seed
    ))
}

pub fn run(args: &TrainArgs) -> anyhow::Result<()> {
    in_pool(args.threads, || train(args))
}

fn train(args: &TrainArgs) -> anyhow::Result<()> {
    let (mut config, dir, resumed) = match &args.resume {
        Some(dir) => {
            if args.config.is_some() || args.seed.is_some() {
                bail!("--resume keeps the run's configuration: drop --config and --seed");
            }
            let (ckpt, replay) = checkpoint::load_run(dir)?;
            if let Some(p) = args.preset {
                ckpt.expect_preset(p)
                    .with_context(|| format!("cannot resume {} with --preset", dir.display()))?;
            }
            (ckpt.config.clone(), dir.clone(), Some((ckpt, replay)))
        }
        None => {
            let text = match &args.config {
                Some(p) => Some(
                    std::fs::read_to_string(p)
                        .with_context(|| format!("cannot read config file {}", p.display()))?,
                ),
                None => None,
            };
            let mut config = Config::resolve(args.preset, text.as_deref())?;
            if let Some(s) = args.seed {
                config.seed = s;
            }
            let dir = args.out.clone().unwrap_or_else(|| default_out(&config));
            (config, dir, None)
        }
    };
    if let Some(e) = args.episodes {
        config.episodes = e;
        config.max_frames = 0;
    }
    if let Some(f) = args.frames {
        config.max_frames = f;
        config.episodes = NO_EPISODE_LIMIT;
    }
    config.validate()?;
    if resumed.is_none() {
        prepare_new_dir(&dir)?;
        write_atomic(&dir.join("config.toml"), config.to_toml().as_bytes())?;
    }
    let env =
        SpaceInvaders::new(&config.env, config.seed).context("cannot start Space Invaders")?;
    let mut agent = match resumed {
        Some((mut ckpt, replay)) => {
            // A longer budget given on the command line is part of the resumed config.
            ckpt.config = config.clone();
            Agent::resume(env, ckpt, replay)
                .with_context(|| format!("cannot resume {}", dir.display()))?
        }
        None => Agent::new(config.clone(), env),
    };
    train_loop(&mut agent, &dir, args.log_rss)
}

fn prepare_new_dir(dir: &Path) -> anyhow::Result<()> {
    if dir.exists() {
        let mut entries =
            std::fs::read_dir(dir).with_context(|| format!("cannot read {}", dir.display()))?;
        if entries.next().is_some() {
            bail!(
                "run directory {} is not empty; choose another --out, or continue it with --resume {}",
                dir.display(),
                dir.display()
            );
        }
    }
    std::fs::create_dir_all(dir)
        .with_context(|| format!("cannot create run directory {}", dir.display()))
}

/// Keeps the first `episodes` data rows of `metrics.csv` (rows written after the checkpoint being
/// resumed are replayed by the resumed run) and returns them as `(episode, reward)`.
fn reopen_metrics(path: &Path, episodes: u64) -> anyhow::Result<(std::fs::File, Vec<(f64, f64)>)> {
    let mut kept = String::from(EpisodeRow::HEADER);
    kept.push('\n');
    let mut points = Vec::new();
    if let Ok(text) = std::fs::read_to_string(path) {
        for line in text.lines().skip(1).take(episodes as usize) {
            let mut f = line.split(',');
            let ep = f.next().and_then(|v| v.parse().ok());
            let reward = f.nth(2).and_then(|v| v.parse().ok());
            if let (Some(ep), Some(r)) = (ep, reward) {
                points.push((ep, r));
                kept.push_str(line);
                kept.push('\n');
            }
        }
    }
    write_atomic(path, kept.as_bytes())?;
    let file = std::fs::OpenOptions::new()
        .append(true)
        .open(path)
        .with_context(|| format!("cannot open {}", path.display()))?;
    Ok((file, points))
}

fn train_loop(
    agent: &mut Agent<SpaceInvaders>,
    dir: &Path,
    log_rss: Option<u64>,
) -> anyhow::Result<()> {
    let config = agent.config.clone();
    let ckpt_path = dir.join(checkpoint::CHECKPOINT_FILE);
    let mut saved_episode = agent.counters.episodes;
    let (mut metrics, mut points) =
        reopen_metrics(&dir.join("metrics.csv"), agent.counters.episodes)?;
    let tty = std::io::stderr().is_terminal();
    let total = if config.max_frames > 0 {
        config.max_frames
    } else {
        config.episodes
    };
    let bar = if tty {
        ProgressBar::new(total)
    } else {
        ProgressBar::hidden()
    };
    bar.set_style(
        ProgressStyle::with_template("{elapsed_precise} [{bar:30}] {pos}/{len} {msg}")
            .expect("valid template")
            .progress_chars("=> "),
    );
    let unit = if config.max_frames > 0 {
        "frames"
    } else {
        "episodes"
    };
    eprintln!(
        "training preset {} (seed {}) into {} for {} {unit}",
        config.preset.name(),
        config.seed,
        dir.display(),
        if total == u64::MAX {
            "unlimited".to_string()
        } else {
            total.to_string()
        },
    );
    let started = Instant::now();
    let steps_at_start = agent.counters.agent_steps;
    let done = |a: &Agent<SpaceInvaders>| {
        a.counters.episodes >= config.episodes
            || (config.max_frames > 0 && a.counters.frames >= config.max_frames)
    };
    while !done(agent) {
        let row = agent.play_episode().with_context(|| {
            if ckpt_path.exists() {
                format!(
                    "run stopped; the last good checkpoint {} (episode {saved_episode}) is left as it was",
                    ckpt_path.display()
                )
            } else {
                "run stopped before its first checkpoint".to_string()
            }
        })?;
        writeln!(metrics, "{}", row.csv()).context("cannot append to metrics.csv")?;
        points.push((row.episode as f64, row.reward));
        let last100 = &points[points.len().saturating_sub(100)..];
        let mean100 = last100.iter().map(|p| p.1).sum::<f64>() / last100.len() as f64;
        let sps =
            (agent.counters.agent_steps - steps_at_start) as f64 / started.elapsed().as_secs_f64();
        let msg = format!(
            "ep {} steps {} ({sps:.0}/s) eps {:.3} reward {} mean100 {mean100:.1} loss {:.3}",
            row.episode, row.agent_steps, row.epsilon, row.reward, row.mean_loss
        );
        if tty {
            bar.set_position(if config.max_frames > 0 {
                row.frames
            } else {
                row.episode
            });
            bar.set_message(msg);
        } else {
            eprintln!("{msg}");
        }
        let finished = done(agent);
        if finished || row.episode.is_multiple_of(config.checkpoint_every) {
            checkpoint::save_run(dir, agent).with_context(|| {
                format!("cannot save the checkpoint of episode {}", row.episode)
            })?;
            saved_episode = row.episode;
        }
        if let Some(n) = log_rss.filter(|&n| n > 0) {
            if row.episode.is_multiple_of(n) {
                match rss_kib() {
                    Some(kib) => eprintln!(
                        "rss: episode {} agent_steps {} VmRSS {kib} kB",
                        row.episode, row.agent_steps
                    ),
                    None => eprintln!("rss: unavailable (no /proc/self/status)"),
                }
            }
        }
        if finished || row.episode.is_multiple_of(config.plot_every) {
            write_plot(dir, &config, &points);
        }
    }
    bar.finish();
    let last100 = &points[points.len().saturating_sub(100)..];
    eprintln!(
        "done: {} episodes, {} agent steps, {} frames, {:.0} s; mean reward of the last {} episodes {:.1}",
        agent.counters.episodes,
        agent.counters.agent_steps,
        agent.counters.frames,
        agent.counters.wall_seconds,
        last100.len(),
        last100.iter().map(|p| p.1).sum::<f64>() / last100.len().max(1) as f64
    );
    Ok(())
}

/// Redraws `rewards.png`; a plotting failure (no fonts, say) is reported but does not stop the
/// run.
fn write_plot(dir: &Path, config: &Config, points: &[(f64, f64)]) {
    let tmp = dir.join(".rewards.png.tmp.png");
    let curve = Curve {
        label: config.preset.name().to_string(),
        points: points.to_vec(),
    };
    let title = format!(
        "Space Invaders, preset {} (seed {})",
        config.preset.name(),
        config.seed
    );
    let result = plot_rewards(&[curve], &title, 100, &tmp).and_then(|_| {
        std::fs::rename(&tmp, dir.join("rewards.png")).context("cannot replace rewards.png")
    });
    if let Err(e) = result {
        eprintln!("warning: reward plot not written: {e:#}");
    }
}
