//! `invaders train`: a headless training run that writes a run directory.
//!
//! ```text
//! RUN_DIR/
//!   config.toml              the resolved configuration
//!   metrics.csv              one row per episode (see `EpisodeRow::HEADER`)
//!   checkpoint.safetensors   the latest checkpoint (replaced atomically)
//!   replay-E.safetensors     the replay memory saved with it (unless checkpoint_replay = false)
//!   rewards.png              reward per episode with a 100-episode moving average
//!   events.out.tfevents.*    TensorBoard's scalars (unless tensorboard = false)
//!   continued.csv            where the run continued from a snapshot (`--resume` of one), if ever
//!   .lock                    held by the process training in it (one at a time)
//! ```
//!
//! Ctrl-C or SIGTERM lets the current episode finish, writes a checkpoint and exits with 130; a
//! second one stops at once (the last checkpoint is kept).

use std::io::{IsTerminal, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::time::Instant;

use anyhow::{bail, Context};
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};

use super::in_pool;
use invaders::dqn::checkpoint::{self, write_atomic};

use super::figures::{plot_rewards, Curve};
use super::guard;
use super::memory::check_memory;
use super::metrics_file::reopen_metrics;
use super::rundir::{clear_run_files, prepare_new_dir, restart_unsaved};
use super::snapshot::{self, note_continued};
use invaders::dqn::{
    game_seed, Agent, Config, EpisodeRow, PqnAgent, Preset, Trainer, NO_EPISODE_LIMIT,
};
use invaders::env::SpaceInvaders;
use invaders::ops::plan::Precision;

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
    /// The training products' arithmetic (default: the preset's: auto for `strong`, f32 for the
    /// article's): bf16 rounds their operands to bfloat16 and keeps f32 sums, on CPUs with
    /// AVX512-BF16 (elsewhere f32); auto picks whichever of the two trains faster here, measured
    /// when the run starts and recorded in its config.toml.
    #[arg(long, value_enum, conflicts_with = "resume")]
    precision: Option<Precision>,
    /// Worker threads for the kernels (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// The run directory (default: runs/PRESET-seedS-TIME). Must be new or empty.
    #[arg(long, value_name = "DIR", conflicts_with = "resume")]
    out: Option<PathBuf>,
    /// Continue the run in DIR from its checkpoint (its configuration is kept; --episodes or
    /// --frames may extend the budget, and config.toml is rewritten to say so). The configuration
    /// comes from the checkpoint: edits to config.toml have no effect. A run stopped before its
    /// first checkpoint starts again from its config.toml.
    #[arg(long, value_name = "DIR")]
    resume: Option<PathBuf>,
    /// After each checkpoint, also keep a snapshot of the run in DIR: its `config.toml`,
    /// `metrics.csv` and a `checkpoint.safetensors` without the replay memory, the target network
    /// and Adam's moments (about 4 MB for `strong`), small enough to keep where the run
    /// directory is not (a repository), so the run can continue on another machine with
    /// `--resume DIR` (docs/runs.md). A failed snapshot is a warning; the run goes on.
    #[arg(long, value_name = "DIR")]
    snapshot: Option<PathBuf>,
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

/// A new directory `runs/PRESET-seedS-TIME` (with `-2`, `-3`, … where that name is taken: two
/// runs started in the same second get a directory each), created here so no other process can
/// take it.
fn new_default_dir(config: &Config) -> anyhow::Result<PathBuf> {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs())
        .unwrap_or(0);
    let runs = PathBuf::from("runs");
    std::fs::create_dir_all(&runs).with_context(|| format!("cannot create {}", runs.display()))?;
    let base = format!("{}-seed{}-{secs}", config.preset.name(), config.seed);
    for n in 1..10_000 {
        let name = if n == 1 {
            base.clone()
        } else {
            format!("{base}-{n}")
        };
        let dir = runs.join(name);
        match std::fs::create_dir(&dir) {
            Ok(()) => return Ok(dir),
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => continue,
            Err(e) => return Err(e).with_context(|| format!("cannot create {}", dir.display())),
        }
    }
    bail!(
        "no free run directory named {}/{base}-N; give --out",
        runs.display()
    )
}

pub fn run(args: &TrainArgs) -> anyhow::Result<()> {
    in_pool(args.threads, || train(args))
}

fn train(args: &TrainArgs) -> anyhow::Result<()> {
    // First, so that a signal while the run loads (a replay memory takes seconds) stops it too.
    catch_signals();
    if args.frames == Some(0) {
        bail!("--frames must be at least 1 (without a frame budget, give --episodes)");
    }
    if let Some(s) = &args.snapshot {
        snapshot::check_path(s)?;
    }
    // The lock is taken before anything in the directory is read or written.
    let mut lock = None;
    // The user's configuration file and its text, for the line a range error names.
    let mut source: Option<(PathBuf, String)> = None;
    let (mut config, mut dir, mut resumed) = match &args.resume {
        Some(dir) => {
            if args.config.is_some() || args.seed.is_some() {
                bail!("--resume keeps the run's configuration: drop --config and --seed");
            }
            if dir.is_file() {
                let parent = dir
                    .parent()
                    .filter(|p| !p.as_os_str().is_empty())
                    .unwrap_or(Path::new("."));
                bail!(
                    "--resume takes a run directory, and {} is a file; its run directory is {} (--resume {})",
                    dir.display(),
                    parent.display(),
                    parent.display()
                );
            }
            if !dir.is_dir() {
                bail!(
                    "{} does not exist: there is no run, and no checkpoint, to resume",
                    dir.display()
                );
            }
            if dir.join(checkpoint::CHECKPOINT_FILE).exists() {
                lock = Some(guard::RunLock::acquire(dir)?);
                // The replay memory (gigabytes) once the checkpoint has been checked: below.
                let ckpt = checkpoint::load(&dir.join(checkpoint::CHECKPOINT_FILE))?;
                if let Some(p) = args.preset {
                    ckpt.expect_preset(p).with_context(|| {
                        format!("cannot resume {} with --preset", dir.display())
                    })?;
                }
                SAVED_EPISODE.store(ckpt.counters.episodes, Ordering::SeqCst);
                (ckpt.config.clone(), dir.clone(), Some((ckpt, None)))
            } else {
                let config = restart_unsaved(dir, args.preset)?;
                lock = Some(guard::RunLock::acquire(dir)?);
                say!(
                    "{} was stopped before its first checkpoint (episode {}): starting it again from episode 1 with its config.toml",
                    dir.display(),
                    config.checkpoint_every
                );
                clear_run_files(dir)?;
                (config, dir.clone(), None)
            }
        }
        None => {
            let text = match &args.config {
                Some(p) => Some(guard::read_text(p, "config file")?),
                None => None,
            };
            source = args.config.clone().zip(text);
            let mut config = Config::resolve(args.preset, source.as_ref().map(|s| s.1.as_str()))
                .map_err(|e| match &source {
                    Some((path, text)) => super::config_errors::locate(e, text, path),
                    None => e,
                })?;
            if let Some(s) = args.seed {
                config.seed = s;
            }
            if let Some(p) = args.precision {
                config.precision = p;
            }
            // The default directory is made once the configuration has passed its checks.
            (config, args.out.clone().unwrap_or_default(), None)
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
    config.validate().map_err(|e| match &source {
        Some((path, text)) => super::config_errors::locate(e, text, path),
        None => super::config_errors::locate(e, "", Path::new("")),
    })?;
    // Before any folder is made or written, and before the replay memory is loaded.
    check_memory(&config)?;
    if args.resume.is_none() && args.out.is_none() {
        dir = new_default_dir(&config)?;
    }
    if resumed.is_none() && config.precision == Precision::Auto {
        // Measured here, on this run's thread pool; config.toml records the answer.
        let r = invaders::dqn::resolve_precision(&config);
        say!("{}", r.why);
        config.precision = r.precision;
    }
    super::note_precision(config.precision);
    if let Some((ckpt, _)) = &resumed {
        let here = invaders::ops::plan::kernels(config.precision);
        if let Some(then) = ckpt.kernels.as_deref().filter(|&k| k != here.as_str()) {
            say!(
                "note: the checkpoint was written where the kernels `{then}` ran, and `{here}` run here: the run continues, but not bit for bit with one never stopped (docs/runs.md)"
            );
        }
        if ckpt.snapshot && config.pqn.is_some() {
            say!(
                "note: {} holds a snapshot, not a full checkpoint: the run continues from episode {} with Adam started anew (docs/runs.md)",
                dir.display(),
                ckpt.counters.episodes
            );
        } else if ckpt.snapshot {
            say!(
                "note: {} holds a snapshot, not a full checkpoint: the run continues from episode {} with an empty replay memory (learning waits until it holds {} entries again), the target network as a copy of the online one and Adam started anew (docs/runs.md)",
                dir.display(),
                ckpt.counters.episodes,
                config.learning_starts.min(config.replay_capacity as u64)
            );
        }
        let c = &ckpt.counters;
        if c.episodes >= config.episodes || (config.max_frames > 0 && c.frames >= config.max_frames)
        {
            bail!(
                "{} has done {} episodes ({} frames), which meets its budget ({}): give a larger --episodes or --frames to continue it",
                dir.display(),
                c.episodes,
                c.frames,
                budget(&config)
            );
        }
        if ckpt.snapshot {
            note_continued(&dir, c)?;
        }
    } else if lock.is_none() {
        lock = Some(prepare_new_dir(&dir)?);
    }
    if let Some((ckpt, replay)) = &mut resumed {
        *replay = checkpoint::load_run_replay(&dir, ckpt)?;
    }
    let snapshot = match &args.snapshot {
        Some(s) => {
            let at = match &resumed {
                Some((ckpt, _)) => ckpt.counters,
                None => checkpoint::Counters::default(),
            };
            Some(snapshot::prepare(s, &dir, &config, &at)?)
        }
        None => None,
    };
    // config.toml always says what runs, the budget included.
    write_atomic(&dir.join("config.toml"), config_text(&config).as_bytes())?;
    let _lock = lock;
    let mut agent: Box<dyn Trainer> = match (resumed, config.pqn) {
        (Some((mut ckpt, replay)), pqn) => {
            // A longer budget given on the command line is part of the resumed config.
            ckpt.config = config.clone();
            let resume = || format!("cannot resume {}", dir.display());
            match pqn {
                None => Box::new(
                    ckpt.into_agent_games(run_games(&config)?, replay)
                        .with_context(resume)?,
                ),
                Some(_) => Box::new(
                    ckpt.into_pqn_agent(run_games(&config)?)
                        .with_context(resume)?,
                ),
            }
        }
        (None, None) => Box::new(Agent::with_games(config.clone(), run_games(&config)?)?),
        (None, Some(_)) => Box::new(PqnAgent::new(config.clone(), run_games(&config)?)?),
    };
    train_loop(agent.as_mut(), &dir, snapshot, args.log_rss)
}

/// Game `g` of a run: Space Invaders with the run's environment
/// settings and the emulator seed [`game_seed`] gives it.
fn new_game(config: &Config, g: usize) -> anyhow::Result<SpaceInvaders> {
    SpaceInvaders::new(&config.env, game_seed(config.seed, g))
        .context("cannot start Space Invaders")
}

/// A run's games: PQN's `pqn.games`, or the DQN agent's `games` played side by side.
fn run_games(config: &Config) -> anyhow::Result<Vec<SpaceInvaders>> {
    let n = config.pqn.map_or(config.games, |p| p.games);
    (0..n).map(|g| new_game(config, g)).collect()
}

/// The budget as words.
fn budget(config: &Config) -> String {
    if config.max_frames > 0 {
        format!("{} frames", config.max_frames)
    } else {
        format!("{} episodes", config.episodes)
    }
}

/// Ctrl-C, SIGTERM and SIGHUP received so far.
static SIGNALS: AtomicU32 = AtomicU32::new(0);
/// Whether the first episode has begun: before it there is nothing to save, so a signal stops
/// the program at once (even one blocked reading a FIFO that never ends).
static TRAINING: AtomicBool = AtomicBool::new(false);
/// The episode of the run's latest checkpoint on disk ([`NO_CHECKPOINT`]: none yet), for what
/// the second signal says.
static SAVED_EPISODE: AtomicU64 = AtomicU64::new(NO_CHECKPOINT);
const NO_CHECKPOINT: u64 = u64::MAX;

/// The error a run stopped by Ctrl-C or SIGTERM returns, after its checkpoint is written; the
/// program then exits with 130.
#[derive(Debug)]
pub struct Interrupted;

impl std::fmt::Display for Interrupted {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "interrupted")
    }
}

impl std::error::Error for Interrupted {}

/// Before the first episode, a Ctrl-C, SIGTERM or SIGHUP stops the program at once (nothing is
/// lost: the run is as it was). After it, the first asks the run to stop after the current
/// episode, with a checkpoint; the second stops the program at once, keeping the last checkpoint.
/// A terminal that closes sends SIGHUP, so it stops a run as a Ctrl-C does.
fn catch_signals() {
    let set = ctrlc::set_handler(|| {
        let n = SIGNALS.fetch_add(1, Ordering::SeqCst) + 1;
        if !TRAINING.load(Ordering::SeqCst) {
            say!("\nstopped before the first episode: nothing of the run has changed");
            std::process::exit(130);
        }
        if n == 1 {
            say!("\nstopping after this episode, with a checkpoint (Ctrl-C again to stop at once)");
        } else {
            match SAVED_EPISODE.load(Ordering::SeqCst) {
                NO_CHECKPOINT => say!(
                    "\nstopped at once: no checkpoint was written yet, so the run starts again from episode 1"
                ),
                e => say!("\nstopped at once: the checkpoint of episode {e} is kept"),
            }
            std::process::exit(130);
        }
    });
    if let Err(e) = set {
        say!("warning: Ctrl-C will stop training at once ({e})");
    }
}

fn train_loop(
    agent: &mut dyn Trainer, dir: &Path, mut snapshot: Option<snapshot::Snapshot>,
    log_rss: Option<u64>,
) -> anyhow::Result<()> {
    let config = agent.config().clone();
    let ckpt_path = dir.join(checkpoint::CHECKPOINT_FILE);
    let mut saved_episode = agent.counters().episodes;
    let (mut metrics, mut points) =
        reopen_metrics(&dir.join("metrics.csv"), agent.counters().episodes)?;
    // From here a signal stops the run after its episode, with a checkpoint.
    TRAINING.store(true, Ordering::SeqCst);
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
    say!(
        "training preset {} (seed {}) into {} for {} {unit} on {} thread(s)",
        config.preset.name(),
        config.seed,
        dir.display(),
        if total == u64::MAX {
            "unlimited".to_string()
        } else {
            total.to_string()
        },
        rayon::current_num_threads(),
    );
    // TensorBoard's event file of this process: its first point is the next agent step.
    let mut events = if config.tensorboard {
        match invaders::dqn::tensorboard::EventWriter::create(
            dir,
            agent.counters().agent_steps as i64 + 1,
        ) {
            Ok(w) => Some(w),
            Err(e) => {
                say!("warning: no TensorBoard events for this run: {e:#}");
                None
            }
        }
    } else {
        None
    };
    let started = Instant::now();
    let steps_at_start = agent.counters().agent_steps;
    while !agent.finished() {
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
        writeln!(metrics, "{}", row.csv()).map_err(|e| {
            let e = anyhow::Error::from(e);
            if guard::disk_full(&e) {
                disk_full_stop(
                    dir,
                    &format!("episode {}'s row of metrics.csv", row.episode),
                )
            } else {
                e.context("cannot append to metrics.csv")
            }
        })?;
        points.push((row.episode as f64, row.reward));
        let last100 = &points[points.len().saturating_sub(100)..];
        let mean100 = last100.iter().map(|p| p.1).sum::<f64>() / last100.len() as f64;
        let sps = (agent.counters().agent_steps - steps_at_start) as f64
            / started.elapsed().as_secs_f64();
        if let Some(w) = &mut events {
            let lr = config.learning_rate(row.agent_steps);
            if let Err(e) = w.scalars(
                row.agent_steps as i64,
                invaders::dqn::tensorboard::now(),
                &episode_scalars(&row, lr, sps),
            ) {
                say!("warning: TensorBoard events stop here (metrics.csv goes on): {e:#}");
                events = None;
            }
        }
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
            say!("{msg}");
        }
        let interrupted = SIGNALS.load(Ordering::SeqCst) > 0;
        let finished = agent.finished() || interrupted;
        if finished || row.episode.is_multiple_of(config.checkpoint_every) {
            checkpoint::save_run(dir, agent).map_err(|e| {
                if guard::disk_full(&e) {
                    disk_full_stop(dir, &format!("the checkpoint of episode {}", row.episode))
                } else {
                    e.context(format!(
                        "cannot save the checkpoint of episode {}",
                        row.episode
                    ))
                }
            })?;
            saved_episode = row.episode;
            SAVED_EPISODE.store(row.episode, Ordering::SeqCst);
            if let Some(snap) = &mut snapshot {
                snap.write(dir, agent, row.episode);
            }
        }
        if let Some(n) = log_rss.filter(|&n| n > 0) {
            if row.episode.is_multiple_of(n) {
                match rss_kib() {
                    Some(kib) => say!(
                        "rss: episode {} agent_steps {} VmRSS {kib} kB",
                        row.episode,
                        row.agent_steps
                    ),
                    None => say!("rss: unavailable (no /proc/self/status)"),
                }
            }
        }
        if finished || row.episode.is_multiple_of(config.plot_every) {
            write_plot(dir, &config, &points);
        }
        if interrupted && !agent.finished() {
            bar.finish();
            say!(
                "stopped at episode {} with a checkpoint; continue with --resume {}",
                row.episode,
                dir.display()
            );
            return Err(Interrupted.into());
        }
    }
    bar.finish();
    if SIGNALS.load(Ordering::SeqCst) > 0 {
        say!("the stop came during the budget's last episode: the run is complete, with its checkpoint");
    }
    let last100 = &points[points.len().saturating_sub(100)..];
    say!(
        "done: {} episodes, {} agent steps, {} frames, {:.0} s; mean reward of the last {} episodes {:.1}",
        agent.counters().episodes,
        agent.counters().agent_steps,
        agent.counters().frames,
        agent.counters().wall_seconds,
        last100.len(),
        last100.iter().map(|p| p.1).sum::<f64>() / last100.len().max(1) as f64
    );
    Ok(())
}

/// An episode's TensorBoard scalars, at its last agent step: every column of its `metrics.csv`
/// row (the step itself aside), the learning rate `lr` and this process's agent steps per second
/// `sps`.
pub fn episode_scalars(row: &EpisodeRow, lr: f64, sps: f64) -> [(&'static str, f64); 10] {
    [
        ("episode/reward", row.reward),
        ("episode/length", row.length as f64),
        ("episode/number", row.episode as f64),
        ("episode/emulator_frames", row.frames as f64),
        ("episode/epsilon", row.epsilon as f64),
        ("train/mean_loss", row.mean_loss as f64),
        ("train/mean_max_q", row.mean_max_q as f64),
        ("train/learning_rate", lr),
        ("time/wall_seconds", row.wall_seconds),
        ("time/agent_steps_per_s", sps),
    ]
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
        say!("warning: reward plot not written: {e:#}");
    }
}

/// A run's `config.toml`: the configuration, and where bf16 was asked for but its products run
/// in f32 here (`INVADERS_NO_BF16`, a CPU without AVX512-BF16), a comment saying so: the key
/// keeps `bf16` (a resumed run keeps its configuration), the comment says what ran.
fn config_text(config: &Config) -> String {
    use invaders::ops::plan::bf16_runs;
    let mut text = config.to_toml();
    if config.precision == Precision::Bf16 && !bf16_runs(config.precision) {
        let why = invaders::tensor::cpu::why_no_bf16().unwrap_or_default();
        text.push_str(&format!(
            "\n# precision = \"bf16\" was asked for, but {why}: this process runs its products in f32\n"
        ));
    }
    text
}

/// The error that stops a run whose disk is full while it writes `what`: what is kept (the last
/// checkpoint on disk and the rows up to it; a row cut short is repaired on resume) and how to
/// go on.
fn disk_full_stop(dir: &Path, what: &str) -> anyhow::Error {
    let kept = match SAVED_EPISODE.load(Ordering::SeqCst) {
        NO_CHECKPOINT => "no checkpoint was written yet, so the run starts again from episode 1".to_string(),
        e => format!(
            "the checkpoint of episode {e} and metrics.csv up to it are kept (a row cut short is removed when the run resumes)"
        ),
    };
    anyhow::anyhow!(
        "the disk holding {} is full: {what} was not written, and the run stops; {kept}. Free some space, then continue with --resume {}",
        dir.display(),
        dir.display()
    )
}
