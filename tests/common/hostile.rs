//! What the tests of a hostile user (`tests/hostile*.rs`) share: short runs, processes watched
//! line by line, and `--keep` records made by hand.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStderr, Command, Output, Stdio};

use super::cli::{bin, invaders, ok, s, tmp_dir, train, train_command, write_file};

/// Short episodes (cut at 50 agent steps), learning early, a checkpoint after every episode.
pub const FAST: &str = "learning_starts = 30\nreplay_capacity = 300\nbatch_size = 8\ncheckpoint_every = 1\nplot_every = 1000\n[env]\nmax_episode_steps = 50\n";

/// A new temporary directory named after the test, with [`FAST`] in its `fast.toml`: the
/// directory, the configuration's path and the path of a run in it (`run`, not made).
pub fn tmp_run(name: &str) -> (PathBuf, String, PathBuf) {
    let root = tmp_dir("invaders-hostile2", name);
    let cfg = s(&write_file(&root, "fast.toml", FAST)).to_string();
    let run = root.join("run");
    (root, cfg, run)
}

/// [`tmp_run`] with the run trained (seed 1) for `episodes`.
pub fn trained(name: &str, episodes: u64) -> (PathBuf, String, PathBuf) {
    let (root, cfg, run) = tmp_run(name);
    ok(&train(&cfg, 1, episodes, &run));
    (root, cfg, run)
}

/// Starts `cmd` with its standard error piped; returns the child and the lines it prints there.
pub fn spawn_lines(mut cmd: Command) -> (Child, std::io::Lines<BufReader<ChildStderr>>) {
    let mut child = cmd.stderr(Stdio::piped()).spawn().unwrap();
    let lines = BufReader::new(child.stderr.take().unwrap()).lines();
    (child, lines)
}

/// Reads `lines` until one contains `needle`; returns it (fails the test if the stream ends
/// first, saying what was read).
pub fn line_with(
    lines: &mut impl Iterator<Item = std::io::Result<String>>, needle: &str,
) -> String {
    let mut seen = Vec::new();
    for l in lines.map_while(Result::ok) {
        if l.contains(needle) {
            return l;
        }
        seen.push(l);
    }
    panic!("no line with `{needle}`: {seen:?}")
}

/// Runs `cmd` to completion, killing it (and failing the test) after `secs` seconds.
pub fn output_within(mut cmd: Command, secs: u64) -> Output {
    let child = cmd
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let id = child.id();
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let _ = tx.send(child.wait_with_output());
    });
    match rx.recv_timeout(std::time::Duration::from_secs(secs)) {
        Ok(out) => out.unwrap(),
        Err(_) => {
            let _ = Command::new("kill")
                .args(["-KILL", &id.to_string()])
                .status();
            panic!("still running after {secs} s");
        }
    }
}

/// Every file of `dir` with its bytes, by name (not recursive).
pub fn files(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let mut out: Vec<(String, Vec<u8>)> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.is_file())
        .map(|p| {
            (
                p.file_name().unwrap().to_string_lossy().into_owned(),
                std::fs::read(&p).unwrap(),
            )
        })
        .collect();
    out.sort();
    out
}

/// A `--keep` record of `experiment strong` for seed 1 in `keep/strong-seed1`, made by hand
/// from the run trained in `run` with the overrides `overrides` (the text of the experiment's
/// `--config`), evaluated by 100 protocol episodes with the scores `protocol` (mean, std, min,
/// max, as TOML values: `nan` is one). Returns the record's folder.
pub fn write_record(keep: &Path, run: &Path, overrides: &str, protocol: [&str; 4]) -> PathBuf {
    let dir = keep.join("strong-seed1");
    std::fs::create_dir_all(&dir).unwrap();
    for f in ["metrics.csv", "config.toml"] {
        std::fs::copy(run.join(f), dir.join(f)).unwrap();
    }
    let c = invaders::dqn::checkpoint::load(&run.join("checkpoint.safetensors"))
        .unwrap()
        .counters;
    let text = format!(
        "preset = \"strong\"\nseed = 1\noverrides = {}\nprotocol_episodes = 100\n\n[counters]\nepisodes = {}\nagent_steps = {}\nframes = {}\ntrain_steps = {}\nwall_seconds = 1.0\n\n[protocol]\nmean = {}\nstd = {}\nmin = {}\nmax = {}\n",
        toml::Value::String(overrides.to_string()),
        c.episodes,
        c.agent_steps,
        c.frames,
        c.train_steps,
        protocol[0],
        protocol[1],
        protocol[2],
        protocol[3]
    );
    std::fs::write(dir.join("result.toml"), text).unwrap();
    dir
}

/// `invaders train --preset strong --config cfg --seed 1 --frames frames --threads 1 --out
/// out`, to success.
pub fn train_strong(cfg: &str, frames: u64, out: &Path) {
    ok(&super::cli::invaders(&[
        "train",
        "--preset",
        "strong",
        "--config",
        cfg,
        "--seed",
        "1",
        "--frames",
        &frames.to_string(),
        "--threads",
        "1",
        "--out",
        s(out),
    ]));
}

pub fn tmp(name: &str) -> PathBuf {
    tmp_dir("invaders-hostile", name)
}

/// Writes `text` to `root/fast.toml`; returns its path.
pub fn config(root: &Path, text: &str) -> String {
    s(&write_file(root, "fast.toml", text)).to_string()
}

/// A new temporary directory ([`tmp`]) with `text` in its `fast.toml` ([`config`]): the
/// directory and the configuration's path.
pub fn tmp_config(name: &str, text: &str) -> (PathBuf, String) {
    let root = tmp(name);
    let cfg = config(&root, text);
    (root, cfg)
}

/// [`FAST`] without periodic checkpoints: only the end of the budget or a stop writes one.
pub fn no_periodic_checkpoint() -> String {
    FAST.replace("checkpoint_every = 1", "checkpoint_every = 1000")
}

/// One episode of `run`'s checkpoint, recorded to `gif`.
pub fn eval_gif(run: &Path, gif: &Path, extra: &[&str]) -> Output {
    let mut args = vec![
        "eval",
        "--checkpoint",
        s(run),
        "--episodes",
        "1",
        "--gif",
        s(gif),
    ];
    args.extend_from_slice(extra);
    invaders(&args)
}

/// `train` of `cfg` on one thread with its standard error piped, and the lines it prints there.
pub fn spawn_train(
    cfg: &str, seed: u64, episodes: u64, out: &Path,
) -> (
    std::process::Child,
    std::io::Lines<BufReader<std::process::ChildStderr>>,
) {
    let mut child = train_command(cfg, seed, episodes, out)
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let lines = BufReader::new(child.stderr.take().unwrap()).lines();
    (child, lines)
}

/// Reads `lines` until one starts with `prefix`.
pub fn wait_for_line(lines: &mut impl Iterator<Item = std::io::Result<String>>, prefix: &str) {
    assert!(
        lines.map_while(Result::ok).any(|l| l.starts_with(prefix)),
        "no line `{prefix}…`"
    );
}

pub fn sigterm(child: &std::process::Child) {
    let sent = Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(sent.success());
}

/// Runs the program with `args`, its standard output closed at once (a reader that left) if
/// `close_stdout`, else discarded; fails the test if it runs over `secs` seconds. Returns its
/// status and what it said on standard error.
pub fn run_within(
    args: &[&str], close_stdout: bool, secs: u64,
) -> (std::process::ExitStatus, String) {
    let mut child = bin()
        .args(args)
        .stdout(if close_stdout {
            Stdio::piped()
        } else {
            Stdio::null()
        })
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    drop(child.stdout.take());
    let status = wait_at_most(&mut child, secs, &args.join(" "));
    (status, read_all(child.stderr.take()))
}

/// Waits for `child` at most `secs` seconds; kills it and fails the test if it is still running.
pub fn wait_at_most(
    child: &mut std::process::Child, secs: u64, what: &str,
) -> std::process::ExitStatus {
    let started = std::time::Instant::now();
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            return status;
        }
        if started.elapsed().as_secs() >= secs {
            let _ = child.kill();
            let _ = child.wait();
            panic!("{what}: still running after {secs} s");
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
}

pub fn read_all(pipe: Option<impl std::io::Read>) -> String {
    let mut text = String::new();
    if let Some(mut p) = pipe {
        let _ = p.read_to_string(&mut text);
    }
    text
}

/// `experiment strong` for one seed to 400 frames on one thread, with `cfg` and `--keep keep`,
/// into `out`: the arguments of a tiny experiment that keeps its record.
pub fn keep_experiment<'a>(cfg: &'a str, keep: &'a Path, out: &'a Path) -> Vec<&'a str> {
    let flags = [
        "--seeds",
        "1",
        "--frames",
        "400",
        "--threads",
        "1",
        "--keep",
        s(keep),
    ];
    super::cli::experiment_args("strong", &flags, cfg, s(out))
}

/// Two configurations in `root` that differ in one key: `x.toml` ([`super::cli::TINY`]) and
/// `y.toml` (the same with `gamma = 0.9`); their paths.
pub fn two_configs(root: &Path) -> (String, String) {
    let tiny = super::cli::TINY;
    let x = s(&write_file(root, "x.toml", tiny)).to_string();
    let y = s(&write_file(root, "y.toml", &format!("{tiny}gamma = 0.9\n"))).to_string();
    (x, y)
}
