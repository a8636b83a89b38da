//! Running the `invaders` binary from a test, and asserting on what it says.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// The path as text.
pub fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// The experiments' tiny configuration: a small replay memory, learning from step 200.
#[allow(dead_code)]
pub const TINY: &str = "replay_capacity = 2000\nlearning_starts = 200\nbatch_size = 8\n";

/// The binary, without a backtrace setting inherited from the test's environment.
pub fn bin() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_invaders"));
    c.env_remove("RUST_BACKTRACE");
    c
}

/// Runs the binary to completion.
pub fn invaders(args: &[&str]) -> Output {
    bin().args(args).output().expect("the binary runs")
}

/// Standard output then standard error.
pub fn text(out: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    )
}

/// Asserts success; returns what it printed.
pub fn ok(out: &Output) -> String {
    assert!(out.status.success(), "command failed:\n{}", text(out));
    text(out)
}

/// Asserts a clear failure: exit code 1, every one of `needles` in the message, no panic.
pub fn fails_with(out: &Output, needles: &[&str]) -> String {
    let err = String::from_utf8_lossy(&out.stderr).into_owned();
    assert_eq!(out.status.code(), Some(1), "expected exit code 1:\n{err}");
    for n in needles {
        assert!(err.contains(n), "error should mention `{n}`:\n{err}");
    }
    assert!(
        !err.contains("panicked"),
        "a panic is not a clear error:\n{err}"
    );
    err
}

/// Asserts that the run in `dir` saved a `config.toml` holding each of `lines`.
#[allow(dead_code)]
pub fn assert_saved_config(dir: &Path, lines: &[&str]) {
    let saved = std::fs::read_to_string(dir.join("config.toml")).unwrap();
    for line in lines {
        assert!(saved.contains(line), "`{line}` in\n{saved}");
    }
}

/// A new empty directory under the system's temporary one, named after the test process.
pub fn tmp_dir(prefix: &str, name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("{prefix}-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Writes `text` to the file `file` in `dir`; returns its path.
#[allow(dead_code)]
pub fn write_file(dir: &Path, file: &str, text: &str) -> PathBuf {
    let path = dir.join(file);
    std::fs::write(&path, text).unwrap();
    path
}

/// A new temporary directory ([`tmp_dir`]) holding the file `file` with `text`; returns the
/// directory and the file's path.
#[allow(dead_code)]
pub fn tmp_with_file(prefix: &str, name: &str, file: &str, text: &str) -> (PathBuf, PathBuf) {
    let dir = tmp_dir(prefix, name);
    let path = write_file(&dir, file, text);
    (dir, path)
}

/// `invaders experiment kind flags… --config cfg --out out`, as arguments.
#[allow(dead_code)]
pub fn experiment_args<'a>(
    kind: &'a str, flags: &[&'a str], cfg: &'a str, out: &'a str,
) -> Vec<&'a str> {
    let mut args = vec!["experiment", kind];
    args.extend_from_slice(flags);
    args.extend(["--config", cfg, "--out", out]);
    args
}

/// The command `invaders train --config cfg --seed seed --threads 1 --episodes episodes --out
/// out`, not started.
#[allow(dead_code)]
pub fn train_command(cfg: &str, seed: u64, episodes: u64, out: &Path) -> Command {
    let mut c = bin();
    c.args(["train", "--config", cfg, "--seed", &seed.to_string()])
        .args(["--threads", "1", "--episodes", &episodes.to_string()])
        .args(["--out", out.to_str().unwrap()]);
    c
}

/// Runs [`train_command`] to completion.
#[allow(dead_code)]
pub fn train(cfg: &str, seed: u64, episodes: u64, out: &Path) -> Output {
    train_command(cfg, seed, episodes, out)
        .output()
        .expect("the binary runs")
}

/// `invaders train --resume dir --threads 1 --episodes episodes`, as arguments.
#[allow(dead_code)]
pub fn resume_args(dir: &Path, episodes: u64) -> Vec<String> {
    [
        "train",
        "--resume",
        dir.to_str().unwrap(),
        "--threads",
        "1",
        "--episodes",
        &episodes.to_string(),
    ]
    .map(String::from)
    .to_vec()
}

/// Runs `invaders train --resume dir --threads 1 --episodes episodes` to completion.
#[allow(dead_code)]
pub fn resume(dir: &Path, episodes: u64) -> Output {
    bin()
        .args(resume_args(dir, episodes))
        .output()
        .expect("the binary runs")
}

/// Trains `config` (a TOML file) with `seed` on one thread twice in `root`: `straight` to
/// `total` episodes, and `split` to `stop` episodes then resumed to `total`. Returns both
/// directories, for a test that the two end alike.
#[allow(dead_code)]
pub fn straight_and_resumed(
    root: &std::path::Path, config: &std::path::Path, seed: u64, stop: u64, total: u64,
) -> (PathBuf, PathBuf) {
    let config = config.to_str().unwrap();
    let run = |out: &std::path::Path, episodes: u64| ok(&train(config, seed, episodes, out));
    let (straight, split) = (root.join("straight"), root.join("split"));
    run(&straight, total);
    run(&split, stop);
    ok(&resume(&split, total));
    (straight, split)
}

/// A run's checkpoint and replay memory.
#[allow(dead_code)]
pub type RunState = (invaders::dqn::checkpoint::Checkpoint, invaders::dqn::Replay);

/// Two runs of the TOML `config` (written to `config.toml` in a new temporary directory of
/// `prefix`) with seed 4 on one thread: 4 episodes straight, and 2 then resumed to 4
/// ([`straight_and_resumed`]). Asserts that learning ran (over 20 train steps) and that both end
/// with the same replay memory, online weights and metrics rows. Returns the directory, the
/// straight run's, and both runs' checkpoints and replay memories (the straight run's first).
#[allow(dead_code)]
pub fn resumed_like_straight(prefix: &str, config: &str) -> (PathBuf, PathBuf, [RunState; 2]) {
    let (root, cfg) = tmp_with_file(prefix, "resume", "config.toml", config);
    let (straight, split) = straight_and_resumed(&root, &cfg, 4, 2, 4);
    let load = |dir: &Path| {
        let (c, replay) = invaders::dqn::checkpoint::load_run(dir).unwrap();
        (c, replay.expect("replay saved"))
    };
    let ((ca, ra), (cb, rb)) = (load(&straight), load(&split));
    assert!(ca.counters.train_steps > 20, "learning ran");
    assert!(ra.parts() == rb.parts(), "replay memories");
    assert_eq!(online_weights(&ca), online_weights(&cb), "online weights");
    assert_eq!(
        metrics_but_wall_time(&straight),
        metrics_but_wall_time(&split)
    );
    (root, straight, [(ca, ra), (cb, rb)])
}

/// Runs `invaders eval --checkpoint path --episodes episodes --threads 1` to success; returns
/// what it printed.
#[allow(dead_code)]
pub fn eval(path: &Path, episodes: &str) -> String {
    ok(&invaders(&[
        "eval",
        "--checkpoint",
        s(path),
        "--episodes",
        episodes,
        "--threads",
        "1",
    ]))
}

/// A checkpoint's online weights, tensor by tensor.
#[allow(dead_code)]
pub fn online_weights(c: &invaders::dqn::checkpoint::Checkpoint) -> Vec<Vec<f32>> {
    c.learner
        .online
        .params()
        .map(|p| p.value.data().to_vec())
        .collect()
}

/// A run's `metrics.csv` rows without their last column (the wall seconds, which differ between
/// two runs of the same episodes).
#[allow(dead_code)]
pub fn metrics_but_wall_time(dir: &std::path::Path) -> Vec<String> {
    std::fs::read_to_string(dir.join("metrics.csv"))
        .unwrap()
        .lines()
        .map(|l| l.rsplit_once(',').unwrap().0.to_string())
        .collect()
}

/// Asserts a failure (any non-zero exit) whose message contains `needle`, without a panic.
#[allow(dead_code)]
pub fn fails_saying(out: &Output, needle: &str) {
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success(),
        "expected a failure, got success: {err}"
    );
    assert!(
        err.contains(needle),
        "error should mention `{needle}`:\n{err}"
    );
    assert!(
        !err.contains("panicked"),
        "a panic is not a clear error:\n{err}"
    );
}

/// The line of a results table whose first cell is `first`; fails the test if there is none.
#[allow(dead_code)]
pub fn row<'a>(table: &'a str, first: &str) -> &'a str {
    table
        .lines()
        .find(|l| l.starts_with(&format!("| {first} | ")))
        .unwrap_or_else(|| panic!("no row for {first}:\n{table}"))
}

/// `args` run to completion (the binary's arguments as owned strings).
#[allow(dead_code)]
pub fn run_owned(args: &[String]) -> Output {
    invaders(&args.iter().map(String::as_str).collect::<Vec<_>>())
}
