//! Experiments as Slurm job arrays (`--slurm DIR`, `--submit`, `--task K`).
//!
//! `--slurm DIR` trains nothing: it writes `DIR/KIND.sbatch`, a job array of one task per run
//! (arm and seed), `DIR/README.md` with the command that submits it, a copy of this program
//! (`DIR/invaders`, so that every task runs the program the sweep was written with, as the local
//! runs do), and the list of tasks into the experiment's folder ([`TASKS_FILE`]). `--submit` also
//! runs `sbatch` on it.
//!
//! Task K (`--task K`, which the script passes as `$SLURM_ARRAY_TASK_ID`) is the K-th run in the
//! order the experiment lists its runs: arm by arm in the order of its table, and within an arm
//! its seeds upward (`strong`: seeds 1, 2, …; `ablation`: `strong` then the arms in the order of
//! `ablation::ABLATIONS`; `preprocessing`: `article-vanilla`, `article`, `article-as-written`,
//! then each `--pipeline`, each with seeds 0, 1, …). The task trains that run in its run folder
//! (continuing it from its checkpoint if it has one), evaluates it and writes its record
//! (`--keep DIR`, or `OUT/records` without one); a run already recorded is not trained again.
//!
//! The script runs the task as a child of its shell (the batch step), which traps SIGTERM:
//!
//! - **Slurm's warning** before the time limit (`--signal=B:TERM@S`) reaches the shell alone. It
//!   passes the first SIGTERM on to the experiment (and no later one), which passes it on once to
//!   its `train`, which finishes its episode, checkpoints and exits with 130, and so does the
//!   experiment (one warned while it evaluates ends the evaluation at once, to play it again).
//!   The shell waits for it (its `wait` returns as the trap runs: it waits again
//!   until the experiment has exited, with that status), and since the experiment stopped with
//!   130 after the trap ran, requeues its task (`scontrol requeue JOB_TASK`, which `--requeue`
//!   allows): Slurm starts it again, and it continues from that checkpoint exactly. The shell then
//!   exits with 130. A task that finishes (0), or fails otherwise, is not requeued.
//! - **`scancel --signal=TERM --full`** signals every process of the task at once: the shell
//!   (which passes it on to the experiment), the experiment and `train`. The experiment gets two
//!   SIGTERMs, Slurm's and the shell's, and `train` two or more (Slurm's and one passed on for
//!   each of the experiment's): `train` stops at once, keeping its last periodic checkpoint
//!   (`checkpoint_every`), and exits with 130, and so does the experiment, "stopping the runs at
//!   once". The shell requeues the task as above, and it replays from that checkpoint to the same
//!   end. (`scancel --signal=TERM --batch` reaches the shell alone, as the warning does.)
//! - Preemption with `--requeue` is Slurm's own requeue; run by hand
//!   (`SLURM_ARRAY_TASK_ID=K bash SCRIPT`, no `SLURM_ARRAY_JOB_ID`) the shell requeues nothing.
//!
//! Once the folder has its task list, the same command without `--task` trains nothing: it
//! gathers the records into the table and figure when every task has finished, and otherwise
//! names the unfinished tasks, says how to submit them again, and fails (exit code 1).

use super::*;

/// The file in the experiment's folder listing its tasks (`K LABEL-seedS`, one a line); while it
/// is there, the experiment's runs are Slurm tasks and the command without `--task` only gathers.
pub(super) const TASKS_FILE: &str = "slurm-tasks.txt";

/// Where the tasks keep their records when the experiment has no `--keep`.
const RECORDS_DIR: &str = "records";

/// What `--slurm` writes into its folder beside the script (`KIND.sbatch`): the README, the
/// program's copy and `logs/`. Any other file there is someone else's.
const OWN_FILES: &[&str] = &["README.md", "invaders", "logs"];

/// The flags of every experiment that run it on Slurm.
#[derive(Debug, Args)]
pub struct SlurmArgs {
    /// Train nothing here: write a Slurm job array into DIR (an sbatch script with one task per
    /// arm and seed, a README with the command that submits it), for a cluster. See "On a
    /// cluster" in docs/runs.md.
    #[arg(long, value_name = "DIR", conflicts_with = "task")]
    slurm: Option<PathBuf>,
    /// With --slurm: each task's time limit, as sbatch takes it (`MINUTES`, `H:MM:SS`,
    /// `D-HH:MM:SS`).
    #[arg(
        long,
        value_name = "TIME",
        default_value = "24:00:00",
        requires = "slurm"
    )]
    slurm_time: String,
    /// With --slurm: how many seconds before the limit Slurm sends the task SIGTERM
    /// (`--signal=B:TERM@S`; shorter than --slurm-time), for it to finish its episode, write its
    /// checkpoint and requeue itself.
    #[arg(long, value_name = "S", default_value_t = 600, requires = "slurm")]
    slurm_warning: u32,
    /// With --slurm: submit the script with `sbatch`.
    #[arg(long, requires = "slurm")]
    submit: bool,
    /// Run task K alone (0 for the first; the order is in the script and `slurm-tasks.txt`):
    /// train its one run in its folder, continuing it if it has a checkpoint, evaluate it and
    /// record it. The Slurm script passes `$SLURM_ARRAY_TASK_ID`.
    #[arg(long, value_name = "K")]
    task: Option<usize>,
}

/// The experiment's part in a sweep: what it is and where it keeps things.
pub(super) struct Sweep<'a> {
    /// `strong`, `ablation` or `preprocessing`.
    pub(super) kind: &'static str,
    pub(super) out: &'a Path,
    /// The folder the records go to ([`keep_dir`]).
    pub(super) keep: Option<&'a Path>,
    pub(super) budget: Budget,
    pub(super) evals: Evals,
}

impl SlurmArgs {
    /// Whether these flags, or the experiment's folder, make its runs Slurm tasks.
    fn sweep(&self, out: &Path) -> bool {
        self.slurm.is_some() || self.task.is_some() || out.join(TASKS_FILE).exists()
    }

    /// Refuses, before anything is written, a `--slurm` folder that is a file or holds other
    /// things than `--slurm` writes, and `--submit` where no `sbatch` is on the PATH.
    pub(super) fn check(&self) -> anyhow::Result<()> {
        if let Some(dir) = &self.slurm {
            let Some(limit) = time_seconds(&self.slurm_time) else {
                bail!(
                    "--slurm-time {} is not a time sbatch takes: give MINUTES, MINUTES:SECONDS, \
                     H:MM:SS, D-HH, D-HH:MM or D-HH:MM:SS; nothing was written",
                    self.slurm_time
                );
            };
            if limit.is_some_and(|l| u64::from(self.slurm_warning) >= l) {
                bail!(
                    "--slurm-warning {} is not shorter than --slurm-time {} ({} s): the warning \
                     would come before the task starts; give a shorter --slurm-warning or a \
                     longer --slurm-time; nothing was written",
                    self.slurm_warning,
                    self.slurm_time,
                    limit.unwrap_or_default()
                );
            }
            check_slurm_dir(dir)?;
            if self.submit && find_on_path("sbatch").is_none() {
                bail!(
                    "--submit runs `sbatch`, and there is none on the PATH here: run this where \
                     Slurm is installed, or leave out --submit and submit {} there with sbatch; \
                     nothing was written",
                    dir.join("<experiment>.sbatch").display()
                );
            }
        }
        Ok(())
    }
}

/// A time limit as sbatch's `--time` takes it, in seconds: `Some(None)` for no limit (`0`,
/// `UNLIMITED`, `INFINITE`), `None` for what sbatch does not take.
fn time_seconds(time: &str) -> Option<Option<u64>> {
    if ["UNLIMITED", "INFINITE"].contains(&time.to_ascii_uppercase().as_str()) {
        return Some(None);
    }
    let (days, rest) = match time.split_once('-') {
        Some((d, r)) => (Some(d), r),
        None => (None, time),
    };
    let number = |s: &str| -> Option<u64> {
        (!s.is_empty() && s.bytes().all(|b| b.is_ascii_digit()))
            .then(|| s.parse().ok())
            .flatten()
    };
    let parts: Vec<u64> = rest.split(':').map(number).collect::<Option<_>>()?;
    let seconds = match (days, parts.as_slice()) {
        (None, [m]) => m * 60,
        (None, [m, s]) => m * 60 + s,
        (None, [h, m, s]) | (Some(_), [h, m, s]) => h * 3600 + m * 60 + s,
        (Some(_), [h]) => h * 3600,
        (Some(_), [h, m]) => h * 3600 + m * 60,
        _ => return None,
    } + days.map_or(Some(0), number)? * 86_400;
    Some((seconds > 0).then_some(seconds))
}

/// The folder the runs' records go to: `--keep`, or for Slurm tasks without one `OUT/records`
/// (the gathering reads the records, not the run folders, so it plays nothing again).
pub(super) fn keep_dir(s: &SlurmArgs, keep: Option<&Path>, out: &Path) -> Option<PathBuf> {
    match keep {
        Some(k) => Some(k.to_path_buf()),
        None if s.sweep(out) => Some(out.join(RECORDS_DIR)),
        None => None,
    }
}

/// Runs the experiment's `jobs` as `s` asks: with `--slurm`, writes the job array (and submits
/// it); with `--task K`, trains, evaluates and records run K; in a folder of Slurm tasks, gathers
/// their records if all have finished; else runs them all here, `workers` at a time. Returns the
/// finished runs for the table, or `None` when there is no table to write.
pub(super) fn run_jobs(
    s: &SlurmArgs, sweep: &Sweep<'_>, jobs: &[Job<'_>], workers: Option<usize>,
) -> anyhow::Result<Option<Vec<Finished>>> {
    if !s.sweep(sweep.out) {
        let exe = exe_path()?;
        return run_all(&exe, jobs, workers, sweep.budget, sweep.evals, sweep.keep).map(Some);
    }
    let names: Vec<String> = jobs
        .iter()
        .map(|j| format!("{}-seed{}", j.label, j.seed))
        .collect();
    if let Some(dir) = &s.slurm {
        write_array(s, sweep, jobs, &names, dir)?;
        return Ok(None);
    }
    check_tasks_file(sweep.out, &names)?;
    if let Some(k) = s.task {
        let Some(job) = jobs.get(k) else {
            bail!(
                "--task {k} is out of range: this experiment has {} task(s), 0 to {} ({})",
                jobs.len(),
                jobs.len() - 1,
                sweep.out.join(TASKS_FILE).display()
            );
        };
        write_tasks_file(sweep.out, &names, None)?;
        say!("task {k}: {}", names[k]);
        let exe = exe_path()?;
        finish_one(&exe, job, sweep.budget, sweep.evals, sweep.keep)?;
        say!(
            "task {k}: {} finished; once every task has, the same command without --task \
             writes the table",
            names[k]
        );
        return Ok(None);
    }
    gather(sweep, jobs, &names).map(Some)
}

/// Every task's record, if every task has finished; else the unfinished ones, named with where
/// each stands, and an error: nothing is trained or played here.
fn gather(sweep: &Sweep<'_>, jobs: &[Job<'_>], names: &[String]) -> anyhow::Result<Vec<Finished>> {
    let mut finished = Vec::new();
    let mut missing = Vec::new();
    for (k, job) in jobs.iter().enumerate() {
        match kept_run(job, sweep.budget, sweep.evals, sweep.keep)? {
            Some(f) => finished.push(f),
            None => missing.push((k, where_it_stands(job))),
        }
    }
    if missing.is_empty() {
        say!(
            "all {} tasks have finished: gathering their records",
            jobs.len()
        );
        return Ok(finished);
    }
    let lines: Vec<String> = missing
        .iter()
        .map(|(k, why)| format!("  task {k} ({}): {why}", names[*k]))
        .collect();
    let list: Vec<String> = missing.iter().map(|(k, _)| k.to_string()).collect();
    let script = read_script_path(sweep.out)
        .unwrap_or_else(|| PathBuf::from(format!("<slurm dir>/{}.sbatch", sweep.kind)));
    bail!(
        "{} of {} tasks have not finished, so nothing is gathered (and nothing was started):\n{}\n\
         Submit them again with `sbatch --array={} {}` (or `scontrol requeue` a stopped one), or \
         run one here with --task K; to train them all here instead, delete {}",
        missing.len(),
        jobs.len(),
        lines.join("\n"),
        list.join(","),
        script.display(),
        sweep.out.join(TASKS_FILE).display()
    )
}

/// Where an unfinished task's run stands: not started, or trained so far.
fn where_it_stands(job: &Job<'_>) -> String {
    let ckpt = job.dir.join(checkpoint::CHECKPOINT_FILE);
    match checkpoint::load(&ckpt) {
        Ok(c) => format!(
            "checkpoint at episode {}, {} frames, not recorded yet",
            c.counters.episodes, c.counters.frames
        ),
        Err(_) if job.dir.exists() => "started, no checkpoint yet".into(),
        Err(_) => "not started".into(),
    }
}

/// The task list's text: a comment, the script (once written), then `K NAME` per task.
fn tasks_text(names: &[String], script: Option<&Path>) -> String {
    let mut t = String::from(
        "# The Slurm array tasks of this experiment (`invaders experiment … --task K`): while this\n\
         # file is here, the command without --task trains nothing and gathers the tasks' records.\n",
    );
    if let Some(p) = script {
        t.push_str(&format!("# script: {}\n", p.display()));
    }
    for (k, n) in names.iter().enumerate() {
        t.push_str(&format!("{k} {n}\n"));
    }
    t
}

/// The tasks a task list holds (its `K NAME` lines).
fn listed_tasks(text: &str) -> Vec<String> {
    text.lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(str::to_string)
        .collect()
}

/// Refuses a folder whose task list names other tasks than this command's (other arms, seeds
/// or order): its runs and records are another sweep's.
fn check_tasks_file(out: &Path, names: &[String]) -> anyhow::Result<()> {
    let path = out.join(TASKS_FILE);
    let Ok(had) = std::fs::read_to_string(&path) else {
        return Ok(());
    };
    let want = listed_tasks(&tasks_text(names, None));
    let had = listed_tasks(&had);
    if had != want {
        bail!(
            "{} lists other tasks than this command's ({} there: {}; {} here: {}): it is another \
             sweep's folder; give another --out",
            path.display(),
            had.len(),
            had.join(", "),
            want.len(),
            want.join(", ")
        );
    }
    Ok(())
}

/// Writes the task list (atomically; a task list naming the script keeps naming it).
fn write_tasks_file(out: &Path, names: &[String], script: Option<&Path>) -> anyhow::Result<()> {
    let path = out.join(TASKS_FILE);
    let script = script
        .map(Path::to_path_buf)
        .or_else(|| read_script_path(out));
    let text = tasks_text(names, script.as_deref());
    if std::fs::read_to_string(&path).is_ok_and(|t| t == text) {
        return Ok(());
    }
    checkpoint::write_atomic(&path, text.as_bytes())
}

/// The script a task list names.
fn read_script_path(out: &Path) -> Option<PathBuf> {
    let text = std::fs::read_to_string(out.join(TASKS_FILE)).ok()?;
    text.lines()
        .find_map(|l| l.strip_prefix("# script: "))
        .map(PathBuf::from)
}

/// Refuses `--slurm` pointed at a file, or at a folder holding anything but what `--slurm`
/// writes (an earlier script of any experiment, its README, program and logs), before anything
/// is written.
fn check_slurm_dir(dir: &Path) -> anyhow::Result<()> {
    if dir.exists() && !dir.is_dir() {
        bail!(
            "--slurm {} is a file: give a folder (new, or one --slurm wrote)",
            dir.display()
        );
    }
    let Ok(entries) = std::fs::read_dir(dir) else {
        return Ok(());
    };
    for e in entries {
        let name = e?.file_name().to_string_lossy().into_owned();
        let ours = OWN_FILES.contains(&name.as_str())
            || ["strong", "ablation", "preprocessing"]
                .iter()
                .any(|k| name == format!("{k}.sbatch"))
            || name.starts_with(".invaders-")
            || (name.starts_with('.') && name.ends_with(".tmp"));
        if !ours {
            bail!(
                "--slurm {} holds `{name}`, which --slurm does not write: give a new folder, or \
                 one --slurm wrote; nothing was written",
                dir.display()
            );
        }
    }
    Ok(())
}

/// Writes the job array into `dir` and the task list into the experiment's folder; submits it
/// with `--submit`.
fn write_array(
    s: &SlurmArgs, sweep: &Sweep<'_>, jobs: &[Job<'_>], names: &[String], dir: &Path,
) -> anyhow::Result<()> {
    check_tasks_file(sweep.out, names)?;
    std::fs::create_dir_all(dir.join("logs"))
        .with_context(|| format!("cannot create {}", dir.display()))?;
    let dir = std::path::absolute(dir)?;
    // This program, copied under a temporary name and renamed: tasks already running keep the
    // file they started from.
    let exe = dir.join("invaders");
    let tmp = dir.join(".invaders-copy");
    std::fs::copy(exe_path()?, &tmp)
        .with_context(|| format!("cannot copy the program to {}", tmp.display()))?;
    std::fs::rename(&tmp, &exe)?;
    let script = dir.join(format!("{}.sbatch", sweep.kind));
    let text = script_text(s, sweep, jobs, names, &exe, &dir)?;
    checkpoint::write_atomic(&script, text.as_bytes())?;
    std::fs::set_permissions(&script, std::os::unix::fs::PermissionsExt::from_mode(0o755))?;
    let submit = format!("sbatch {}", script.display());
    let readme = format!(
        "# invaders experiment {} as a Slurm job array\n\nWritten by `{}`: {} task(s), one per run \
         (`{}`). Submit it with\n\n    {submit}\n\nand once every task has finished, gather the \
         table and figure with the same command without --slurm. See \"On a cluster\" in \
         docs/runs.md of invaders.\n",
        sweep.kind,
        command_line(),
        jobs.len(),
        sweep.out.join(TASKS_FILE).display(),
    );
    checkpoint::write_atomic(&dir.join("README.md"), readme.as_bytes())?;
    write_tasks_file(sweep.out, names, Some(&script))?;
    say!(
        "wrote {} ({} task(s)); submit it with `{submit}`",
        script.display(),
        jobs.len()
    );
    if s.submit {
        let out = Command::new("sbatch")
            .arg(&script)
            .output()
            .context("cannot run sbatch")?;
        if !out.status.success() {
            bail!(
                "sbatch refused {} ({}): {}",
                script.display(),
                out.status,
                String::from_utf8_lossy(&out.stderr).trim()
            );
        }
        out!("{}", String::from_utf8_lossy(&out.stdout).trim());
    }
    Ok(())
}

/// The memory a task asks for, in MiB: the largest run's replay memory and networks (the
/// estimate `train` checks before it starts) and a margin of a quarter of that, at least 1 GiB,
/// for the emulator, the evaluation, the program and the checkpoint's writing.
fn task_mem_mib(jobs: &[Job<'_>]) -> anyhow::Result<u64> {
    let mut need = 0;
    for job in jobs {
        let text = std::fs::read_to_string(&job.cfg)
            .with_context(|| format!("cannot read {}", job.cfg.display()))?;
        let config = Config::resolve(Some(job.preset), Some(&text))?;
        need = need.max(config.replay_bytes() + crate::cli::memory::NETWORKS_BYTES);
    }
    let with_margin = need + (need / 4).max(1 << 30);
    Ok(with_margin.div_ceil(1 << 20))
}

/// The sbatch script: the array's resources, then this experiment's command with `--task
/// $SLURM_ARRAY_TASK_ID` (the same flags, paths made absolute, the program `exe`) as a child of
/// the shell, which passes Slurm's warning on and requeues the task it stopped.
fn script_text(
    s: &SlurmArgs, sweep: &Sweep<'_>, jobs: &[Job<'_>], names: &[String], exe: &Path, dir: &Path,
) -> anyhow::Result<String> {
    let threads = jobs.iter().map(|j| j.threads).max().unwrap_or(1);
    let mem = task_mem_mib(jobs)?;
    let cwd = std::env::current_dir().context("cannot read the working directory")?;
    let mut command = vec![shell_quote(&exe.display().to_string())];
    command.extend(task_args(sweep.out)?.iter().map(|a| shell_quote(a)));
    let list: String = names
        .iter()
        .enumerate()
        .map(|(k, n)| format!("#   {k} {n}\n"))
        .collect();
    Ok(format!(
        "#!/bin/bash\n\
         # invaders experiment {kind} as a Slurm job array, written by\n\
         #   {cmd}\n\
         # Task K trains, evaluates and records the K-th run below in its folder under\n\
         # {out}, continuing it from its checkpoint if it has one.\n\
         {list}\
         #SBATCH --job-name=invaders-{kind}\n\
         #SBATCH --array=0-{last}\n\
         #SBATCH --ntasks=1\n\
         #SBATCH --cpus-per-task={threads}\n\
         # The largest run's replay memory and networks, and a margin of a quarter (at least 1 GiB).\n\
         #SBATCH --mem={mem}M\n\
         #SBATCH --time={time}\n\
         # SIGTERM to the task {warn} s before its limit: it finishes its episode, checkpoints and\n\
         # requeues itself (below).\n\
         #SBATCH --signal=B:TERM@{warn}\n\
         #SBATCH --requeue\n\
         #SBATCH --open-mode=append\n\
         #SBATCH --output={logs}/%x-%A_%a.out\n\
         set -eu\n\
         : \"${{SLURM_ARRAY_TASK_ID:?submit this with sbatch, or set SLURM_ARRAY_TASK_ID=K to run task K here}}\"\n\
         cd {cwd}\n\
         # The program runs as this shell's child. Slurm's warning reaches this shell alone\n\
         # (B:TERM), which passes its first SIGTERM on to the program; stopped by it with a\n\
         # checkpoint (exit 130), the task requeues itself, to continue from there. A task that\n\
         # finishes, or fails otherwise, ends with the program's exit status.\n\
         child=\n\
         traps=0\n\
         trap 'traps=$((traps + 1)); if [ \"$traps\" = 1 ]; then kill -TERM \"$child\" 2>/dev/null || true; fi' TERM\n\
         {command} --task \"$SLURM_ARRAY_TASK_ID\" &\n\
         child=$!\n\
         # `wait` returns 143 as soon as the trap has run, the program still running: wait again.\n\
         while seen=$traps; status=0; wait \"$child\" || status=$?; [ \"$status\" = 143 ] && [ \"$traps\" != \"$seen\" ]; do :; done\n\
         if [ \"$status\" = 130 ] && [ \"$traps\" -gt 0 ] && [ -n \"${{SLURM_ARRAY_JOB_ID:-}}\" ]; then\n\
         \x20 scontrol requeue \"${{SLURM_ARRAY_JOB_ID}}_${{SLURM_ARRAY_TASK_ID}}\" || true\n\
         fi\n\
         exit \"$status\"\n",
        kind = sweep.kind,
        cmd = command_line(),
        out = sweep.out.display(),
        last = jobs.len() - 1,
        time = s.slurm_time,
        warn = s.slurm_warning,
        logs = dir.join("logs").display(),
        cwd = shell_quote(&cwd.display().to_string()),
        command = command.join(" "),
    ))
}

/// The flags that take a path: made absolute in the script, which may run elsewhere.
const PATH_FLAGS: &[&str] = &["--config", "--out", "--keep", "--reference", "--notebook"];

/// The flags (with a value) of `--slurm` itself and of the local runs, which a task does not take.
const DROPPED_FLAGS: &[&str] = &["--slurm", "--slurm-time", "--slurm-warning", "--jobs"];

/// This command's arguments after `invaders` as one task takes them: without [`DROPPED_FLAGS`]
/// and `--submit`, each path of [`PATH_FLAGS`] absolute, and `--out` given.
fn task_args(out: &Path) -> anyhow::Result<Vec<String>> {
    let mut args = Vec::new();
    let mut given = std::env::args().skip(1);
    while let Some(a) = given.next() {
        let (flag, inline) = match a.split_once('=') {
            Some((f, v)) if f.starts_with("--") => (f.to_string(), Some(v.to_string())),
            _ => (a.clone(), None),
        };
        if flag == "--submit" {
            continue;
        }
        let takes_value =
            DROPPED_FLAGS.contains(&flag.as_str()) || PATH_FLAGS.contains(&flag.as_str());
        if !takes_value {
            args.push(a);
            continue;
        }
        let value = match inline {
            Some(v) => v,
            None => given.next().unwrap_or_default(),
        };
        if flag == "--out" || DROPPED_FLAGS.contains(&flag.as_str()) {
            continue;
        }
        args.push(flag);
        args.push(std::path::absolute(&value)?.display().to_string());
    }
    args.push("--out".into());
    args.push(std::path::absolute(out)?.display().to_string());
    Ok(args)
}

/// The path of `program` on `PATH`, if there is one.
fn find_on_path(program: &str) -> Option<PathBuf> {
    let path = std::env::var_os("PATH")?;
    std::env::split_paths(&path)
        .map(|d| d.join(program))
        .find(|p| p.is_file())
}

#[cfg(test)]
mod tests {
    use super::time_seconds;

    #[test]
    fn sbatch_times_in_seconds() {
        for (time, want) in [
            ("30", Some(Some(1800))),
            ("30:15", Some(Some(1815))),
            ("0:30:00", Some(Some(1800))),
            ("24:00:00", Some(Some(86_400))),
            ("1-2", Some(Some(93_600))),
            ("1-2:30", Some(Some(95_400))),
            ("1-02:30:05", Some(Some(95_405))),
            ("0", Some(None)),
            ("unlimited", Some(None)),
            ("INFINITE", Some(None)),
            ("", None),
            ("1:2:3:4", None),
            ("1-", None),
            ("-5", None),
            ("1h", None),
            ("+5", None),
        ] {
            assert_eq!(time_seconds(time), want, "{time:?}");
        }
    }
}
