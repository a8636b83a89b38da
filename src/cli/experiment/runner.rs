//! Running an experiment's jobs: each training and evaluation is an `invaders` child process,
//! `--jobs` at a time, each run evaluated as soon as it has trained.

use super::*;

/// How long each run trains.
#[derive(Clone, Copy)]
pub(super) enum Budget {
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
pub(super) struct Job<'a> {
    pub(super) label: &'a str,
    pub(super) preset: Preset,
    pub(super) seed: u64,
    pub(super) cfg: PathBuf,
    pub(super) dir: PathBuf,
    /// Kernel threads of its training (`train --threads`).
    pub(super) threads: usize,
}

/// What an experiment asks of each finished run's final network.
#[derive(Clone, Copy)]
pub(super) struct Evals {
    /// Protocol episodes (`eval --protocol`).
    pub(super) protocol: u32,
    /// `preprocessing`: episodes in the run's own game with ε = 0.05, on seed 1000 + the run's
    /// seed.
    pub(super) own_game: Option<u32>,
}

/// A run trained to its budget and evaluated: its record (kept with `--keep` or not) and where
/// its per-episode `metrics.csv` is (in its run directory, or in its `--keep` record).
pub(super) struct Finished {
    pub(super) record: Record,
    pub(super) metrics: PathBuf,
}

/// Trains every job to `budget` (each continued if it exists), `workers` at a time, and
/// evaluates each as soon as it has trained, while the others train; with `keep`, a job whose
/// record there answers the same question is taken as it is, and each newly finished job's
/// record is written there. Returns the jobs in their order; fails after all have stopped if
/// any failed, and returns [`Interrupted`] if a run or evaluation was stopped by a signal (then
/// nothing further starts).
pub(super) fn run_all(
    exe: &Path, jobs: &[Job<'_>], workers: Option<usize>, budget: Budget, evals: Evals,
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

/// The `--keep` record of `job` (`KEEP/LABEL-seedS`) if it answers the same question (preset,
/// seed, overrides, evaluations, and a budget reached), as a finished run; `None` otherwise.
pub(super) fn kept_run(
    job: &Job<'_>, budget: Budget, evals: Evals, keep: Option<&Path>,
) -> anyhow::Result<Option<Finished>> {
    let name = format!("{}-seed{}", job.label, job.seed);
    let Some(k) = keep.map(|k| k.join(&name)) else {
        return Ok(None);
    };
    let Some(r) = read_record(&k)? else {
        return Ok(None);
    };
    let overrides = std::fs::read_to_string(&job.cfg)
        .with_context(|| format!("cannot read {}", job.cfg.display()))?;
    let same = r.preset == job.preset.name()
        && r.seed == job.seed
        && r.overrides == overrides
        && r.protocol_episodes == evals.protocol
        && r.own_game_episodes == evals.own_game
        && budget.done(&r.counters);
    if !same {
        return Ok(None);
    }
    say!(
        "{name}: kept in {} ({} episodes, {} frames, evaluated)",
        k.display(),
        r.counters.episodes,
        r.counters.frames
    );
    Ok(Some(Finished {
        record: r,
        metrics: k.join("metrics.csv"),
    }))
}

/// One job of [`run_all`]: its `--keep` record if that answers the same question, else trained,
/// evaluated and (with `keep`) recorded.
pub(super) fn finish_one(
    exe: &Path, job: &Job<'_>, budget: Budget, evals: Evals, keep: Option<&Path>,
) -> anyhow::Result<Finished> {
    if let Some(f) = kept_run(job, budget, evals, keep)? {
        return Ok(f);
    }
    let name = format!("{}-seed{}", job.label, job.seed);
    let overrides = std::fs::read_to_string(&job.cfg)
        .with_context(|| format!("cannot read {}", job.cfg.display()))?;
    let kept = keep.map(|k| k.join(&name));
    if let Some(k) = &kept {
        if read_record(k)?.is_some() {
            check_record(k, job.preset, &overrides, job.seed)?;
            say!(
                "{name}: the record in {} is of this configuration but not of this question \
                 (another budget, evaluation or record); it is replaced when the run has \
                 trained and been evaluated",
                k.display()
            );
        }
    }
    let snapshot = kept.as_ref().map(|k| k.join(SNAPSHOT_DIR));
    if let Some(snap) = &snapshot {
        continue_from_snapshot(&name, job, &overrides, snap)?;
    }
    train_one(exe, job, budget, snapshot.as_deref())?;
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
        continued_from_snapshot: read_continued(&job.dir)?,
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

/// Where the run directory of `job` is gone (another machine) and its `--keep` record has a
/// snapshot of it (`snap`, written by `train --snapshot`) for the same configuration: a new run
/// directory holding the snapshot's `config.toml`, `metrics.csv`, `continued.csv` and
/// checkpoint, which `train --resume` continues (module `checkpoint`'s "Snapshots": without the
/// replay memory, the target network or Adam's moments). A run directory with files in it is
/// the run's own and is left as it is; a snapshot of another configuration is refused (nothing
/// is replaced).
fn continue_from_snapshot(
    name: &str, job: &Job<'_>, overrides: &str, snap: &Path,
) -> anyhow::Result<()> {
    let file = snap.join(checkpoint::CHECKPOINT_FILE);
    if !file.exists() || job.dir.join(checkpoint::CHECKPOINT_FILE).exists() {
        return Ok(());
    }
    let occupied = std::fs::read_dir(&job.dir).is_ok_and(|mut d| d.next().is_some());
    if occupied {
        say!(
            "{name}: its snapshot in {} is not used: {} holds the run's files (without a checkpoint)",
            snap.display(),
            job.dir.display()
        );
        return Ok(());
    }
    let ckpt = checkpoint::load(&file).with_context(|| {
        format!(
            "its snapshot cannot be used; delete {} to train that run from its start",
            snap.display()
        )
    })?;
    let mut asked = Config::resolve(Some(job.preset), Some(overrides))?;
    asked.seed = job.seed;
    let differ = config_differences(&ckpt.config, &asked);
    if !differ.is_empty() {
        bail!(
            "the snapshot in {} is of another configuration than this experiment asks for ({}): delete it to train this run from its start, or give another --keep",
            snap.display(),
            differ.join("; ")
        );
    }
    std::fs::create_dir_all(&job.dir)
        .with_context(|| format!("cannot create {}", job.dir.display()))?;
    // The checkpoint last: until it is there, the directory is not a run that continues.
    let files = [
        "config.toml",
        "metrics.csv",
        CONTINUED_FILE,
        checkpoint::CHECKPOINT_FILE,
    ];
    checkpoint::copy_files_atomic(snap, &job.dir, &files, &[CONTINUED_FILE])?;
    let c = &ckpt.counters;
    say!(
        "{name}: its run directory is gone; continued from its snapshot in {} (episode {}, {} frames), without its replay memory",
        snap.display(),
        c.episodes,
        c.frames
    );
    Ok(())
}

/// The frames at which the run in `dir` continued from a snapshot (its `continued.csv`), oldest
/// first; none if it never did.
fn read_continued(dir: &Path) -> anyhow::Result<Vec<u64>> {
    let path = dir.join(CONTINUED_FILE);
    let text = match std::fs::read_to_string(&path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(e).with_context(|| format!("cannot read {}", path.display())),
    };
    text.lines()
        .skip(1)
        .filter(|l| !l.trim().is_empty())
        .map(|l| {
            l.rsplit(',')
                .next()
                .and_then(|f| f.trim().parse::<u64>().ok())
                .ok_or_else(|| anyhow!("{}: bad line `{l}`", path.display()))
        })
        .collect()
}

/// Trains one run to `budget`, continuing it if it exists, with `train --snapshot` into
/// `snapshot` if given; [`Interrupted`] if a signal stopped it (or a stop came before it
/// started).
pub(super) fn train_one(
    exe: &Path, job: &Job<'_>, budget: Budget, snapshot: Option<&Path>,
) -> anyhow::Result<()> {
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
    if let Some(snap) = snapshot {
        cmd.arg("--snapshot").arg(snap);
    }
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
pub(super) fn evaluate(exe: &Path, dir: &Path, episodes: u32, seed: u64) -> anyhow::Result<Scores> {
    let (episodes, seed) = (episodes.to_string(), seed.to_string());
    let last = run_eval(exe, dir, &["--episodes", &episodes, "--seed", &seed])?;
    parse_scores(&last)
}

/// Runs `invaders eval` on a run's final checkpoint with `args` (one thread) and returns its
/// summary line (`… mean M std S min A max B`); [`Interrupted`] if a stop came first or ended
/// it.
pub(super) fn run_eval(exe: &Path, dir: &Path, args: &[&str]) -> anyhow::Result<String> {
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
pub(super) struct Scores {
    pub(super) mean: f64,
    pub(super) std: f64,
    pub(super) min: f64,
    pub(super) max: f64,
}

/// Evaluates a run's final network by the protocol (`eval --protocol`: `v5`, ε = 0.01, seed
/// 1 000 000) over `episodes` episodes. The summary is kept beside the run (`DIR.protocol`, with
/// the frames the network was trained for): evaluation is deterministic, so asking again for
/// the same network and episodes reads it back instead of playing them again.
pub(super) fn evaluate_protocol(exe: &Path, dir: &Path, episodes: u32) -> anyhow::Result<Scores> {
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
pub(super) fn parse_scores(last: &str) -> anyhow::Result<Scores> {
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

/// This program, which each run and evaluation runs again as a child process. On Linux that is
/// `/proc/self/exe`: the very file this process started from, even after a `cargo build` has
/// replaced it during an experiment of hours (its path would then name a new program, or for a
/// moment none), so every run of an experiment trains with the program it started with.
pub(super) fn exe_path() -> anyhow::Result<PathBuf> {
    let own = Path::new("/proc/self/exe");
    if cfg!(target_os = "linux") && own.exists() {
        return Ok(own.to_path_buf());
    }
    std::env::current_exe().context("cannot find the invaders executable")
}

/// A command running `exe` (from [`exe_path`]), which names itself `invaders` in its messages.
pub(super) fn invaders_command(exe: &Path) -> Command {
    let mut cmd = Command::new(exe);
    #[cfg(unix)]
    std::os::unix::process::CommandExt::arg0(&mut cmd, "invaders");
    cmd
}

/// This command as a shell would take it back: `invaders` and its arguments, each quoted where
/// the shell would otherwise split or expand it.
pub(super) fn command_line() -> String {
    std::iter::once("invaders".to_string())
        .chain(std::env::args().skip(1).map(|a| shell_quote(&a)))
        .collect::<Vec<_>>()
        .join(" ")
}

/// `a` as a shell takes it back: as it is where it holds nothing the shell would split or
/// expand, else in single quotes.
pub(super) fn shell_quote(a: &str) -> String {
    if !a.is_empty()
        && a.chars()
            .all(|c| c.is_ascii_alphanumeric() || "-_./,=:+".contains(c))
    {
        a.to_string()
    } else {
        format!("'{}'", a.replace('\'', "'\\''"))
    }
}

/// What a finished run reports beside its score.
pub(super) struct RunSummary {
    pub(super) frames: u64,
    pub(super) hours: f64,
    pub(super) steps_per_second: f64,
    /// The mean reward of its last 100 training episodes.
    pub(super) last100: f64,
    /// Its training curve: (frames, reward) per episode.
    pub(super) points: Vec<(f64, f64)>,
}

/// The summary of a finished run from its record and its `metrics.csv`, read up to the frames
/// it was evaluated at: a run directory may have trained on since (a longer budget asked of the
/// same run), and its later episodes are not the recorded network's.
pub(super) fn summarize(run: &Finished) -> anyhow::Result<RunSummary> {
    let c = run.record.counters;
    let mut points = read_frame_metrics(&run.metrics)?;
    points.retain(|p| p.0 <= c.frames as f64);
    let tail = &points[points.len().saturating_sub(100)..];
    Ok(RunSummary {
        frames: c.frames,
        hours: c.wall_seconds / 3600.0,
        steps_per_second: c.agent_steps as f64 / c.wall_seconds.max(1e-9),
        last100: tail.iter().map(|p| p.1).sum::<f64>() / tail.len().max(1) as f64,
        points,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A run continued past its record (here: episodes at 100, 200, 300 frames, recorded at
    /// 200) is summarised as it was recorded: its curve and last-100 mean stop at 200 frames.
    #[test]
    fn a_run_continued_past_its_record_is_summarised_as_recorded() {
        let dir = std::env::temp_dir().join(format!("invaders-summarize-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let metrics = dir.join("metrics.csv");
        std::fs::write(
            &metrics,
            "episode,emulator_frames,reward\n1,100,10\n2,200,30\n3,300,500\n",
        )
        .unwrap();
        let counters = checkpoint::Counters {
            episodes: 2,
            agent_steps: 50,
            frames: 200,
            wall_seconds: 10.0,
            ..Default::default()
        };
        let scores = Scores {
            mean: 1.0,
            std: 0.0,
            min: 1.0,
            max: 1.0,
        };
        let run = Finished {
            record: Record {
                preset: "strong".into(),
                seed: 1,
                overrides: String::new(),
                protocol_episodes: 1,
                own_game_episodes: None,
                counters,
                protocol: scores,
                own_game: None,
                continued_from_snapshot: Vec::new(),
            },
            metrics,
        };
        let s = summarize(&run).unwrap();
        assert_eq!(s.points, vec![(100.0, 10.0), (200.0, 30.0)]);
        assert_eq!(s.last100, 20.0);
        assert_eq!((s.frames, s.steps_per_second), (200, 5.0));
        let _ = std::fs::remove_dir_all(&dir);
    }
}
