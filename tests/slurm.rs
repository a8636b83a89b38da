//! Experiments as Slurm job arrays (`--slurm DIR`, `--task K`; issue #102). Always: what the
//! script holds, a task run by hand with `SLURM_ARRAY_TASK_ID` set, the gathering that starts
//! nothing while tasks are unfinished, and the bad inputs. Where `sbatch` answers (a cluster, or
//! `tools/slurm-single-node.sh up`): a tiny sweep submitted to Slurm runs to its table, and a
//! task stopped by `scancel --signal=TERM --full` requeues itself and ends with the `metrics.csv`
//! of an uninterrupted run; elsewhere that test prints why it is skipped. A task's shell sent
//! SIGTERM alone (as Slurm's warning is) requeues its task, tested always with a stand-in
//! `scontrol`.

mod common;

use common::cli::{bin, fails_saying, fails_with, invaders, metrics_but_wall_time, ok, s, tmp_dir};
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::time::{Duration, Instant};

/// [`common::cli::TINY`] with a checkpoint after every episode, so that a stopped task has one.
const TINY: &str =
    "replay_capacity = 2000\nlearning_starts = 200\nbatch_size = 8\ncheckpoint_every = 1\n";

/// A new temporary folder with `tiny.toml` ([`TINY`]): the folder and the file.
fn setup(name: &str) -> (PathBuf, PathBuf) {
    let root = tmp_dir("invaders-slurm", name);
    let cfg = root.join("tiny.toml");
    std::fs::write(&cfg, TINY).unwrap();
    (root, cfg)
}

/// `experiment preprocessing` with `seeds` seeds of `episodes` episodes (3 arms: one task per
/// arm and seed), one own-game evaluation episode, `tiny.toml`, into `out`, then `extra`.
fn preprocessing(cfg: &Path, out: &Path, seeds: u32, episodes: u32, extra: &[&str]) -> Vec<String> {
    let mut a: Vec<String> = ["experiment", "preprocessing", "--eval-episodes", "1"]
        .iter()
        .map(|x| x.to_string())
        .collect();
    a.extend(["--seeds".into(), seeds.to_string()]);
    a.extend(["--episodes".into(), episodes.to_string()]);
    a.extend([
        "--config".into(),
        s(cfg).into(),
        "--out".into(),
        s(out).into(),
    ]);
    a.extend(extra.iter().map(|x| x.to_string()));
    a
}

/// `experiment preprocessing --slurm` for one seed of `episodes` episodes: the experiment goes to
/// `root/NAME`, the script to `root/NAME-slurm`; returns those two folders.
fn one_seed_script(root: &Path, cfg: &Path, name: &str, episodes: u32) -> (PathBuf, PathBuf) {
    let (out, dir) = (root.join(name), root.join(format!("{name}-slurm")));
    ok(&run(&preprocessing(
        cfg,
        &out,
        1,
        episodes,
        &["--slurm", s(&dir)],
    )));
    (out, dir)
}

fn run(args: &[String]) -> Output {
    bin().args(args).output().expect("the binary runs")
}

/// The lines of `text` that start with `#SBATCH `.
fn directives(text: &str) -> Vec<&str> {
    text.lines().filter(|l| l.starts_with("#SBATCH ")).collect()
}

/// `--slurm` writes a script of one task per arm and seed with the resources asked for and the
/// command made absolute; task 0 run by hand through the script trains, evaluates and records
/// its run; the gathering then names the two unfinished tasks and starts nothing; task 0 again
/// trains nothing. Bad input: `--task` out of range, a task folder of another configuration, a
/// folder of other tasks; nothing recorded changes.
#[test]
fn the_script_holds_the_array_and_a_task_runs_by_hand() {
    let (root, cfg) = setup("by-hand");
    let (out, dir) = (root.join("exp"), root.join("slurm"));
    let slurm = [
        "--slurm",
        s(&dir),
        "--slurm-time",
        "0:30:00",
        "--slurm-warning",
        "120",
    ];
    let said = ok(&run(&preprocessing(&cfg, &out, 1, 2, &slurm)));
    let script_path = dir.join("preprocessing.sbatch");
    assert!(
        said.contains(&format!("sbatch {}", script_path.display())),
        "{said}"
    );
    let script = std::fs::read_to_string(&script_path).unwrap();
    let d = directives(&script);
    for want in [
        "#SBATCH --array=0-2",
        "#SBATCH --cpus-per-task=1",
        "#SBATCH --time=0:30:00",
        "#SBATCH --signal=B:TERM@120",
        "#SBATCH --requeue",
    ] {
        assert!(d.contains(&want), "{want} in\n{script}");
    }
    // 2 000 transitions, the networks' 512 MiB, a margin of 1 GiB.
    let mem = d
        .iter()
        .find_map(|l| l.strip_prefix("#SBATCH --mem="))
        .unwrap();
    assert_eq!(mem, "1550M", "{script}");
    // From `set -eu` on, the script is exactly this: the program as the shell's child, which
    // passes Slurm's warning on once, waits for it, and requeues a task it stopped.
    let program = dir.join("invaders");
    let tail = &script[script.find("set -eu\n").expect("set -eu")..];
    let (cd, tail) = tail
        .split_once("\ncd ")
        .and_then(|(head, rest)| Some((head, rest.split_once('\n')?)))
        .map(|(head, (cd, rest))| (format!("{head}\ncd {cd}\n"), rest))
        .unwrap();
    assert!(
        cd.starts_with(
            "set -eu\n: \"${SLURM_ARRAY_TASK_ID:?submit this with sbatch, or set \
             SLURM_ARRAY_TASK_ID=K to run task K here}\"\ncd "
        ),
        "{cd}"
    );
    let want = format!(
        "# The program runs as this shell's child. Slurm's warning reaches this shell alone
# (B:TERM), which passes its first SIGTERM on to the program; stopped by it with a
# checkpoint (exit 130), the task requeues itself, to continue from there. A task that
# finishes, or fails otherwise, ends with the program's exit status.
child=
traps=0
trap 'traps=$((traps + 1)); if [ \"$traps\" = 1 ]; then kill -TERM \"$child\" 2>/dev/null || true; fi' TERM
{} experiment preprocessing --eval-episodes 1 --seeds 1 --episodes 2 --config {} --out {} --task \"$SLURM_ARRAY_TASK_ID\" &
child=$!
# `wait` returns 143 as soon as the trap has run, the program still running: wait again.
while seen=$traps; status=0; wait \"$child\" || status=$?; [ \"$status\" = 143 ] && [ \"$traps\" != \"$seen\" ]; do :; done
if [ \"$status\" = 130 ] && [ \"$traps\" -gt 0 ] && [ -n \"${{SLURM_ARRAY_JOB_ID:-}}\" ]; then
  scontrol requeue \"${{SLURM_ARRAY_JOB_ID}}_${{SLURM_ARRAY_TASK_ID}}\" || true
fi
exit \"$status\"
",
        program.display(),
        cfg.display(),
        out.display()
    );
    assert_eq!(tail, want);
    for (k, name) in [
        "article-vanilla-seed0",
        "article-seed0",
        "article-as-written-seed0",
    ]
    .iter()
    .enumerate()
    {
        assert!(script.contains(&format!("#   {k} {name}\n")), "{script}");
    }
    assert!(program.is_file());
    let readme = std::fs::read_to_string(dir.join("README.md")).unwrap();
    assert!(
        readme.contains(&format!("sbatch {}", script_path.display())),
        "{readme}"
    );
    assert!(
        !out.join("article-vanilla-seed0").exists(),
        "--slurm trains nothing"
    );

    // Outside Slurm the script says what it needs; with the variable set, it runs task 0.
    let bare = Command::new("bash")
        .arg(&script_path)
        .env_remove("SLURM_ARRAY_TASK_ID")
        .output()
        .unwrap();
    fails_saying(&bare, "SLURM_ARRAY_TASK_ID");
    let task0 = Command::new("bash")
        .arg(&script_path)
        .env("SLURM_ARRAY_TASK_ID", "0")
        .output()
        .unwrap();
    let said = ok(&task0);
    assert!(
        said.contains("task 0: article-vanilla-seed0 finished"),
        "{said}"
    );
    let record = out.join("records/article-vanilla-seed0/result.toml");
    let recorded = std::fs::read(&record).unwrap();

    // The gathering names what is missing and starts nothing.
    let gather = fails_with(
        &run(&preprocessing(&cfg, &out, 1, 2, &[])),
        &[
            "2 of 3 tasks have not finished",
            "task 1 (article-seed0): not started",
            "task 2 (article-as-written-seed0): not started",
            &format!("sbatch --array=1,2 {}", script_path.display()),
        ],
    );
    assert!(!gather.contains("task 0 ("), "{gather}");
    assert!(!out.join("article-seed0").exists(), "nothing started");

    // Task 0 again: recorded, not trained or played again.
    let again = ok(&run(&preprocessing(&cfg, &out, 1, 2, &["--task", "0"])));
    assert!(again.contains("article-vanilla-seed0: kept in"), "{again}");
    assert!(!again.contains("training"), "{again}");

    // Bad input.
    fails_with(
        &run(&preprocessing(&cfg, &out, 1, 2, &["--task", "3"])),
        &["--task 3 is out of range: this experiment has 3 task(s), 0 to 2"],
    );
    let other = root.join("other.toml");
    std::fs::write(&other, TINY.replace("batch_size = 8", "batch_size = 16")).unwrap();
    fails_with(
        &run(&preprocessing(&other, &out, 1, 2, &["--task", "0"])),
        &["trained with another configuration", "batch_size"],
    );
    fails_with(
        &run(&preprocessing(&cfg, &out, 2, 2, &["--task", "0"])),
        &[
            "lists other tasks than this command's",
            "give another --out",
        ],
    );
    assert_eq!(
        std::fs::read(&record).unwrap(),
        recorded,
        "the record is left as it was"
    );
    let _ = std::fs::remove_dir_all(&root);
}

/// `strong` and `ablation` write their arrays too (two threads: two CPUs per task; the `strong`
/// preset's 7 GB replay memory in `--mem`); `--slurm` pointed at a file or at a folder of
/// something else, `--submit` where there is no `sbatch`, a `--slurm-warning` not shorter than
/// `--slurm-time` and a `--slurm-time` sbatch does not take are refused before anything is
/// written.
#[test]
fn every_experiment_writes_its_array_and_bad_folders_are_refused() {
    let (root, cfg) = setup("arrays");
    let dir = root.join("strong-slurm");
    let out = root.join("strong");
    let (d, c, o) = (s(&dir), s(&cfg), s(&out));
    let strong = [
        "experiment",
        "strong",
        "--seeds",
        "3",
        "--threads",
        "2",
        "--slurm",
        d,
        "--out",
        o,
    ];
    ok(&invaders(&strong));
    let script = std::fs::read_to_string(dir.join("strong.sbatch")).unwrap();
    let dirs = directives(&script);
    assert!(dirs.contains(&"#SBATCH --array=0-2"), "{script}");
    assert!(dirs.contains(&"#SBATCH --cpus-per-task=2"), "{script}");
    let mem: u64 = dirs
        .iter()
        .find_map(|l| l.strip_prefix("#SBATCH --mem="))
        .and_then(|m| m.strip_suffix('M'))
        .unwrap()
        .parse()
        .unwrap();
    assert!(mem > 7000, "{script}");
    let tasks = std::fs::read_to_string(out.join("slurm-tasks.txt")).unwrap();
    assert!(
        tasks.ends_with("0 strong-seed1\n1 strong-seed2\n2 strong-seed3\n"),
        "{tasks}"
    );
    // Written again into its own folder: fine.
    ok(&invaders(&strong));

    let adir = root.join("ablation-slurm");
    let aout = root.join("ablation");
    ok(&invaders(&[
        "experiment",
        "ablation",
        "--arms",
        "no-dueling",
        "--config",
        c,
        "--slurm",
        s(&adir),
        "--out",
        s(&aout),
    ]));
    let script = std::fs::read_to_string(adir.join("ablation.sbatch")).unwrap();
    assert!(
        directives(&script).contains(&"#SBATCH --array=0-1"),
        "{script}"
    );
    assert!(script.contains("#   1 no-dueling-seed1\n"), "{script}");

    // --slurm at a file, at a folder of something else; --submit without sbatch.
    let fresh = root.join("fresh");
    let (f, fo) = (s(&fresh), root.join("fresh-out"));
    let strong = |slurm: &str, extra: &[&str]| {
        let mut a = vec![
            "experiment",
            "strong",
            "--seeds",
            "2",
            "--slurm",
            slurm,
            "--out",
        ];
        a.push(s(&fo));
        a.extend_from_slice(extra);
        a.iter().map(|x| x.to_string()).collect::<Vec<_>>()
    };
    fails_with(&run(&strong(c, &[])), &["is a file"]);
    fails_with(
        &run(&strong(s(&root), &[])),
        &["which --slurm does not write"],
    );
    let empty = tmp_dir("invaders-slurm", "no-sbatch-path");
    let no_sbatch = bin()
        .args(strong(f, &["--submit"]))
        .env("PATH", &empty)
        .output()
        .unwrap();
    fails_with(
        &no_sbatch,
        &["--submit runs `sbatch`, and there is none on the PATH"],
    );
    // A warning that is not shorter than the time limit, and a time sbatch does not take.
    fails_with(
        &run(&strong(
            f,
            &["--slurm-time", "10", "--slurm-warning", "600"],
        )),
        &["--slurm-warning 600 is not shorter than --slurm-time 10 (600 s)"],
    );
    fails_with(
        &run(&strong(
            f,
            &["--slurm-time", "0:05:00", "--slurm-warning", "900"],
        )),
        &["--slurm-warning 900 is not shorter than --slurm-time 0:05:00 (300 s)"],
    );
    fails_with(
        &run(&strong(f, &["--slurm-time", "1h"])),
        &["--slurm-time 1h is not a time sbatch takes"],
    );
    assert!(!fresh.exists() && !fo.exists(), "nothing written");
    assert_eq!(std::fs::read_to_string(&cfg).unwrap(), TINY);
    let _ = std::fs::remove_dir_all(&root);
    let _ = std::fs::remove_dir_all(&empty);
}

/// The script run by hand as Slurm would run a task (`SLURM_ARRAY_JOB_ID`, `SLURM_ARRAY_TASK_ID`
/// set, an `scontrol` on the PATH that notes its arguments): SIGTERM to the shell alone, as
/// Slurm's warning (`B:TERM`) sends it, stops the program with a checkpoint, and the shell exits
/// with 130 after `scontrol requeue JOB_TASK`; run again, the task continues, finishes (0) and
/// requeues nothing.
#[test]
fn a_warned_task_requeues_itself() {
    let (root, cfg) = setup("warned");
    let (out, dir) = one_seed_script(&root, &cfg, "exp", 12);
    let bin_dir = root.join("bin");
    std::fs::create_dir_all(&bin_dir).unwrap();
    let noted = root.join("scontrol.args");
    let fake = bin_dir.join("scontrol");
    std::fs::write(
        &fake,
        format!("#!/bin/sh\necho \"$@\" >> {}\n", noted.display()),
    )
    .unwrap();
    std::fs::set_permissions(&fake, std::os::unix::fs::PermissionsExt::from_mode(0o755)).unwrap();
    let path = format!("{}:{}", bin_dir.display(), std::env::var("PATH").unwrap());
    let task = || {
        let mut c = Command::new("bash");
        c.arg(dir.join("preprocessing.sbatch"))
            .env("SLURM_ARRAY_TASK_ID", "0")
            .env("SLURM_ARRAY_JOB_ID", "77")
            .env("PATH", &path)
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::piped());
        c
    };
    let metrics = out.join("article-vanilla-seed0/metrics.csv");
    let rows =
        || std::fs::read_to_string(&metrics).map_or(0, |t| t.lines().count().saturating_sub(1));
    let shell = task().spawn().unwrap();
    wait_for("2 episodes of task 0", Duration::from_secs(300), || {
        rows() >= 2
    });
    let term = Command::new("kill")
        .args(["-TERM", &shell.id().to_string()])
        .status()
        .unwrap();
    assert!(term.success());
    let stopped = shell.wait_with_output().unwrap();
    let said = String::from_utf8_lossy(&stopped.stderr);
    assert_eq!(stopped.status.code(), Some(130), "{said}");
    assert!(said.contains("stopped with a checkpoint"), "{said}");
    assert_eq!(
        std::fs::read_to_string(&noted).unwrap(),
        "requeue 77_0\n",
        "the shell requeued its task"
    );
    let at = rows();
    assert!(at < 12, "stopped mid-run: {at} rows");
    // Requeued: it continues from its checkpoint to its end, and requeues nothing.
    let again = task().output().unwrap();
    let said = ok(&again);
    assert!(
        said.contains("task 0: article-vanilla-seed0 finished"),
        "{said}"
    );
    assert_eq!(rows(), 12);
    assert_eq!(std::fs::read_to_string(&noted).unwrap(), "requeue 77_0\n");
    let log = std::fs::read_to_string(out.join("article-vanilla-seed0.log")).unwrap();
    assert!(
        log.contains("resum"),
        "continued from its checkpoint:\n{log}"
    );
    let _ = std::fs::remove_dir_all(&root);
}

/// Why Slurm cannot be used here, if it cannot: `sbatch` must answer and `sinfo` show a node up.
fn no_slurm() -> Option<String> {
    let answers = |cmd: &str, args: &[&str]| {
        Command::new(cmd)
            .args(args)
            .output()
            .ok()
            .filter(|o| o.status.success())
            .map(|o| String::from_utf8_lossy(&o.stdout).into_owned())
    };
    if answers("sbatch", &["--version"]).is_none() {
        return Some(
            "no `sbatch` answers here (bash tools/slurm-single-node.sh up makes one)".into(),
        );
    }
    let states = answers("sinfo", &["-h", "-N", "-o", "%T"]).unwrap_or_default();
    if !states
        .lines()
        .any(|l| ["idle", "mixed", "allocated"].contains(&l.trim()))
    {
        return Some(format!(
            "sbatch answers, but sinfo shows no node up: {states:?}"
        ));
    }
    None
}

/// `scontrol show job ID`'s `JobState`, or `None` once Slurm has forgotten the job.
fn job_state(id: &str) -> Option<String> {
    job_field(id, "JobState")
}

/// `scontrol show job ID`'s field `name` (`JobState`, `Restarts`), or `None` once Slurm has
/// forgotten the job.
fn job_field(id: &str, name: &str) -> Option<String> {
    let o = Command::new("scontrol")
        .args(["show", "job", id])
        .output()
        .ok()?;
    let text = String::from_utf8_lossy(&o.stdout);
    let key = format!("{name}=");
    text.split_whitespace()
        .find_map(|w| w.strip_prefix(key.as_str()))
        .map(String::from)
}

/// Waits until `done` holds, polling; fails the test after `limit`.
fn wait_for(what: &str, limit: Duration, mut done: impl FnMut() -> bool) {
    let start = Instant::now();
    while !done() {
        assert!(
            start.elapsed() < limit,
            "timed out after {limit:?} waiting for {what}"
        );
        std::thread::sleep(Duration::from_millis(200));
    }
}

fn slurm(cmd: &str, args: &[&str]) -> String {
    let o = Command::new(cmd).args(args).output().unwrap();
    assert!(
        o.status.success(),
        "{cmd} {args:?}: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    String::from_utf8_lossy(&o.stdout).trim().to_string()
}

/// Where Slurm answers: `--submit` sends a tiny sweep (3 arms × 2 seeds) whose tasks run to the
/// gathered table; and a task of 30 episodes sent SIGTERM mid-run by `scancel --signal=TERM
/// --full` requeues itself (its shell runs `scontrol requeue`, no one else) and ends with the
/// same `metrics.csv` (but wall time) as an uninterrupted run of its seed on its one thread.
/// Elsewhere it prints why it is skipped.
#[test]
fn a_sweep_runs_on_a_live_slurm() {
    if let Some(why) = no_slurm() {
        println!("skipped: {why}");
        return;
    }
    let (root, cfg) = setup("live");
    let (out, dir) = (root.join("sweep"), root.join("sweep-slurm"));
    let started = Instant::now();
    let said = ok(&run(&preprocessing(
        &cfg,
        &out,
        2,
        2,
        &["--slurm", s(&dir), "--submit"],
    )));
    let job = said
        .lines()
        .find_map(|l| l.strip_prefix("Submitted batch job "))
        .unwrap_or_else(|| panic!("no job id in {said}"))
        .trim()
        .to_string();
    println!("sweep: job array {job}, 6 tasks");
    wait_for("the sweep's tasks", Duration::from_secs(900), || {
        slurm("squeue", &["-h", "-j", &job]).is_empty()
    });
    let gathered = ok(&run(&preprocessing(&cfg, &out, 2, 2, &[])));
    assert!(gathered.contains("all 6 tasks have finished"), "{gathered}");
    let table = std::fs::read_to_string(out.join("results.md")).unwrap();
    for arm in ["article-vanilla", "article", "article-as-written"] {
        let row = common::cli::row(&table, arm);
        assert!(row.contains("| 2 |"), "two seeds: {row}");
        println!("{row}");
    }
    assert!(std::fs::metadata(out.join("rewards.png")).unwrap().len() > 1000);
    println!("sweep gathered in {:.0} s", started.elapsed().as_secs_f64());

    // A task stopped mid-run and requeued.
    let (out, dir) = one_seed_script(&root, &cfg, "stopped", 30);
    let script = dir.join("preprocessing.sbatch");
    let array = slurm("sbatch", &["--parsable", "--array=0", s(&script)]);
    let task = format!("{array}_0");
    let metrics = out.join("article-vanilla-seed0/metrics.csv");
    let rows =
        || std::fs::read_to_string(&metrics).map_or(0, |t| t.lines().count().saturating_sub(1));
    wait_for("5 episodes of task 0", Duration::from_secs(300), || {
        rows() >= 5
    });
    slurm("scancel", &["--signal=TERM", "--full", &task]);
    // No `scontrol requeue` here: the task's shell requeues it once the program has stopped.
    wait_for("task 0 to requeue itself", Duration::from_secs(120), || {
        job_field(&task, "Restarts").is_some_and(|r| r != "0")
    });
    let stopped_at = rows();
    println!(
        "task {task} stopped by SIGTERM with {stopped_at} of 30 episodes in metrics.csv and \
         requeued itself: {:?}, Restarts={:?}",
        job_state(&task),
        job_field(&task, "Restarts")
    );
    assert!(stopped_at < 30, "stopped mid-run");
    // It starts again once its killed credential has expired (`AuthInfo=cred_expire`).
    wait_for("the requeued task", Duration::from_secs(600), || {
        job_state(&task).is_none_or(|s| s == "COMPLETED" || s == "FAILED")
    });
    assert_eq!(
        job_state(&task).as_deref().unwrap_or("COMPLETED"),
        "COMPLETED"
    );
    assert_eq!(job_field(&task, "Restarts").as_deref(), Some("1"));
    let slurm_log = std::fs::read_dir(dir.join("logs"))
        .unwrap()
        .map(|e| std::fs::read_to_string(e.unwrap().path()).unwrap())
        .collect::<String>();
    for line in slurm_log
        .lines()
        .filter(|l| l.contains("stop") || l.contains("task 0"))
    {
        println!("  log: {line}");
    }
    let log = std::fs::read_to_string(out.join("article-vanilla-seed0.log")).unwrap();
    assert!(
        log.contains("resum"),
        "continued from its checkpoint:\n{log}"
    );
    // The same run uninterrupted: `train` as the task runs it, on one thread.
    let straight = root.join("straight");
    ok(&invaders(&[
        "train",
        "--preset",
        "article-vanilla",
        "--seed",
        "0",
        "--config",
        s(&out.join("article-vanilla.toml")),
        "--out",
        s(&straight),
        "--episodes",
        "30",
        "--threads",
        "1",
    ]));
    let (a, b) = (
        metrics_but_wall_time(&straight),
        metrics_but_wall_time(&out.join("article-vanilla-seed0")),
    );
    assert_eq!(a.len(), 31);
    assert_eq!(
        a, b,
        "the stopped and requeued task ends as the uninterrupted run"
    );
    println!("requeued task {task}: metrics.csv equal to the uninterrupted run's (30 episodes, all columns but wall_seconds)");
    let _ = std::fs::remove_dir_all(&root);
}
