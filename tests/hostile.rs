//! The program tried as a careless or hostile user would: one test per class of defect (data
//! lost or damaged, a configuration that says one thing and does another, panics, aborts and
//! hangs, interruptions). Each asserts a clear message, the exit code, and that nothing earlier
//! was harmed.

mod common;

use std::io::{BufRead, BufReader};
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};

use common::cli::{bin, fails_with, invaders, ok, tmp_dir};

fn tmp(name: &str) -> PathBuf {
    tmp_dir("invaders-hostile", name)
}

/// Short episodes (cut at 50 agent steps, so two seeds reach the same counters), learning early.
const FAST: &str = "learning_starts = 30\nreplay_capacity = 300\nbatch_size = 8\ncheckpoint_every = 1\nplot_every = 1000\n[env]\nmax_episode_steps = 50\n";

fn config(root: &Path, text: &str) -> String {
    let p = root.join("fast.toml");
    std::fs::write(&p, text).unwrap();
    p.to_str().unwrap().to_string()
}

fn train(cfg: &str, seed: u64, episodes: u64, out: &Path) -> Output {
    invaders(&[
        "train",
        "--config",
        cfg,
        "--seed",
        &seed.to_string(),
        "--threads",
        "1",
        "--episodes",
        &episodes.to_string(),
        "--out",
        out.to_str().unwrap(),
    ])
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// One episode of `run`'s checkpoint, recorded to `gif`.
fn eval_gif(run: &Path, gif: &Path, extra: &[&str]) -> Output {
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

#[test]
fn nothing_a_user_types_loses_or_damages_data() {
    let root = tmp("data");
    let cfg = config(&root, FAST);
    let (a, b) = (root.join("a"), root.join("b"));
    ok(&train(&cfg, 1, 1, &a));
    ok(&train(&cfg, 2, 1, &b));
    let ckpt = a.join("checkpoint.safetensors");
    let before = std::fs::read(&ckpt).unwrap();

    // An output path never replaces an input, nor an existing file without --force, and a
    // directory is refused before any episode is played, leaving no temporary file.
    fails_with(&eval_gif(&a, &ckpt, &[]), &["refusing to write over it"]);
    fails_with(
        &eval_gif(&a, &ckpt, &["--force"]),
        &["refusing to write over it"],
    );
    let metrics = a.join("metrics.csv");
    fails_with(&eval_gif(&a, &metrics, &[]), &["exists", "--force"]);
    let dir_out = invaders(&[
        "eval",
        "--checkpoint",
        s(&a),
        "--episodes",
        "50",
        "--gif",
        s(&root),
    ]);
    let err = fails_with(&dir_out, &["is a directory"]);
    assert!(!err.contains("episode"), "refused before playing: {err}");
    assert!(
        std::fs::read_dir(&root).unwrap().all(|e| !e
            .unwrap()
            .file_name()
            .to_string_lossy()
            .ends_with(".tmp")),
        "no temporary file left"
    );
    fails_with(
        &invaders(&["plot", s(&a), "--out", s(&metrics)]),
        &["refusing to write over it"],
    );
    assert_eq!(
        std::fs::read(&ckpt).unwrap(),
        before,
        "the checkpoint is untouched"
    );

    // A byte flipped inside tensor data is refused.
    let mut flipped = before.clone();
    let at = flipped.len() - 100;
    flipped[at] ^= 0x40;
    let bad = root.join("flipped");
    std::fs::create_dir_all(&bad).unwrap();
    std::fs::write(bad.join("checkpoint.safetensors"), &flipped).unwrap();
    fails_with(
        &invaders(&["eval", "--checkpoint", s(&bad), "--episodes", "1"]),
        &["damaged"],
    );

    // A replay file copied in from another run with the same counters is refused.
    let replay = "replay-1.safetensors";
    assert!(a.join(replay).is_file() && b.join(replay).is_file());
    let own = std::fs::read(a.join(replay)).unwrap();
    std::fs::copy(b.join(replay), a.join(replay)).unwrap();
    fails_with(
        &invaders(&[
            "train",
            "--resume",
            s(&a),
            "--episodes",
            "2",
            "--threads",
            "1",
        ]),
        &["not the replay memory saved with this checkpoint"],
    );
    std::fs::write(a.join(replay), own).unwrap();

    // Malformed metrics rows are named, not dropped; a deleted file is said to be lost.
    let good_metrics = std::fs::read_to_string(&metrics).unwrap();
    std::fs::write(&metrics, good_metrics.replace("\n1,", "\nx,")).unwrap();
    fails_with(
        &invaders(&[
            "train",
            "--resume",
            s(&a),
            "--episodes",
            "2",
            "--threads",
            "1",
        ]),
        &["line 2", "malformed"],
    );
    std::fs::remove_file(&metrics).unwrap();
    let out = ok(&invaders(&[
        "train",
        "--resume",
        s(&a),
        "--episodes",
        "2",
        "--threads",
        "1",
    ]));
    assert!(out.contains("metrics.csv is missing"), "{out}");

    // One process per run directory: a second one is refused while the first trains.
    let mut first = bin()
        .args([
            "train",
            "--resume",
            s(&a),
            "--episodes",
            "1000000",
            "--threads",
            "1",
        ])
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut lines = BufReader::new(first.stderr.take().unwrap()).lines();
    // Wait for the event (the first episode line), not for a number of seconds.
    let mut seen = Vec::new();
    let started = lines.by_ref().map_while(Result::ok).any(|l| {
        seen.push(l.clone());
        l.starts_with("ep ")
    });
    assert!(started, "the first process trains: {seen:?}");
    fails_with(
        &invaders(&[
            "train",
            "--resume",
            s(&a),
            "--episodes",
            "1000000",
            "--threads",
            "1",
        ]),
        &["in use by another process", &format!("pid {}", first.id())],
    );
    first.kill().unwrap();
    first.wait().unwrap();
    let _ = std::fs::remove_dir_all(&root);
}

#[test]
fn the_configuration_says_what_runs() {
    let root = tmp("config");
    // A mode sets its knobs; an explicit knob overrides them; 0 removes the episode cap.
    let cfg = config(&root, &format!("{FAST}mode = \"nature\"\nnoop_max = 5\n"));
    let run = root.join("nature");
    ok(&train(&cfg, 1, 1, &run));
    let saved = std::fs::read_to_string(run.join("config.toml")).unwrap();
    for line in [
        "mode = \"nature\"",
        "frame_skip_min = 4",
        "frame_skip_max = 4",
        "sticky_prob = 0.0",
        "max_pool_last_two = true",
        "noop_max = 5",
        "max_episode_steps = 50",
    ] {
        assert!(saved.contains(line), "`{line}` in\n{saved}");
    }
    let parsed =
        invaders::dqn::Config::resolve(None, Some("[env]\nmode = \"v5\"\nmax_episode_steps = 0\n"))
            .unwrap();
    assert_eq!(parsed.env.max_episode_steps, None);
    assert!(
        parsed.to_toml().contains("max_episode_steps = 0"),
        "no cap is written as 0"
    );

    // Extending a resumed run's budget rewrites config.toml; a budget already met is an error.
    ok(&invaders(&[
        "train",
        "--resume",
        s(&run),
        "--episodes",
        "2",
        "--threads",
        "1",
    ]));
    let saved = std::fs::read_to_string(run.join("config.toml")).unwrap();
    assert!(saved.contains("episodes = 2\n"), "{saved}");
    fails_with(
        &invaders(&[
            "train",
            "--resume",
            s(&run),
            "--episodes",
            "1",
            "--threads",
            "1",
        ]),
        &["has done 2 episodes", "larger"],
    );
    fails_with(
        &invaders(&[
            "train",
            "--config",
            &cfg,
            "--frames",
            "0",
            "--out",
            s(&root.join("f0")),
        ]),
        &["--frames must be at least 1"],
    );

    // Errors name the user's file line, not an internal document's.
    let bad = config(&root, "seed = 1\n\ngamma = \"high\"\n");
    fails_with(
        &invaders(&["train", "--config", &bad, "--out", s(&root.join("bad"))]),
        &["line 3", "gamma"],
    );
    let bad = config(&root, "[env]\nsticky_prob = \"x\"\n");
    fails_with(
        &invaders(&["train", "--config", &bad, "--out", s(&root.join("bad"))]),
        &["line 2", "env.sticky_prob"],
    );
    let _ = std::fs::remove_dir_all(&root);
}

#[test]
fn no_input_panics_aborts_or_hangs() {
    let root = tmp("bounds");
    // Numbers TOML cannot hold: a clear error and no run directory left behind.
    for flag in ["--seed", "--episodes", "--frames"] {
        let out_dir = root.join(format!("big{flag}"));
        fails_with(
            &invaders(&["train", flag, "9223372036854775808", "--out", s(&out_dir)]),
            &["at most 9223372036854775807"],
        );
        assert!(!out_dir.exists(), "{flag}: no run directory");
    }
    // A replay memory larger than the machine's memory, and knobs without a usable bound.
    for (text, needle) in [
        ("replay_capacity = 10000000\n", "needs about"),
        (
            "[env]\nframe_skip_max = 4000000000\n",
            "frame_skip_max must be at most",
        ),
        ("[env]\nnoop_max = 4000000000\n", "noop_max must be at most"),
        (
            "[env]\nmax_episode_steps = 4000000000\n",
            "max_episode_steps must be at most",
        ),
        (
            "learning_starts = 100000000000\n",
            "learning_starts must be at most",
        ),
        ("n_step = 1000\n", "n_step must be in"),
        (
            "learning_rate_end = -1e-4\nlearning_rate_decay = [0, 10]\n",
            "learning_rate_end must be >= 0",
        ),
        (
            "learning_rate_end = 1e-5\nlearning_rate_decay = [10, 10]\n",
            "learning_rate_decay must be [from, to]",
        ),
        (
            "learning_rate_decay = [0, 10]\n",
            "learning_rate_decay needs learning_rate_end",
        ),
    ] {
        let cfg = config(&root, text);
        let out_dir = root.join("bounded");
        fails_with(
            &invaders(&["train", "--config", &cfg, "--out", s(&out_dir)]),
            &[needle],
        );
        let _ = std::fs::remove_dir_all(&out_dir);
    }
    // ROMs that are not Space Invaders are refused before the emulator sees them.
    for (name, bytes) in [
        (
            "random.bin",
            (0..4096u32)
                .map(|i| (i.wrapping_mul(2654435761) >> 13) as u8)
                .collect::<Vec<_>>(),
        ),
        ("zeros.bin", vec![0u8; 4096]),
        ("text.bin", b"not a rom\n".repeat(50)),
        ("tiny.bin", vec![0x4c]),
    ] {
        let rom = root.join(name);
        std::fs::write(&rom, bytes).unwrap();
        fails_with(
            &invaders(&["eval", "--random", "--episodes", "1", "--rom", s(&rom)]),
            &["is not a Space Invaders ROM"],
        );
    }
    // Plotting terminates on non-finite rewards and says what it skipped.
    let run = root.join("nan");
    std::fs::create_dir_all(&run).unwrap();
    std::fs::write(
        run.join("metrics.csv"),
        "episode,agent_steps,emulator_frames,reward,length,epsilon,mean_loss,mean_max_q,wall_seconds\n1,10,40,5,10,1,NaN,NaN,0.1\n2,20,80,inf,10,1,NaN,NaN,0.2\n3,30,120,NaN,10,1,NaN,NaN,0.3\n4,40,160,15,10,1,NaN,NaN,0.4\n",
    )
    .unwrap();
    let out = ok(&invaders(&[
        "plot",
        s(&run),
        "--out",
        s(&root.join("nan.png")),
    ]));
    assert!(
        out.contains("skipped 2 row(s)") && out.contains("line 3, 4"),
        "{out}"
    );
    let _ = std::fs::remove_dir_all(&root);
}

/// Ctrl-C at a terminal signals the foreground process group. `experiment`'s runs are in groups
/// of their own, so it alone gets it and must pass it on once (twice would stop a run at once):
/// the running training stops with a checkpoint, no further run starts, and the experiment exits
/// with 130 after its runs have stopped.
#[test]
fn an_interrupted_experiment_stops_its_runs_and_starts_no_more() {
    let root = tmp("experiment-signals");
    std::fs::create_dir_all(&root).unwrap();
    // No periodic checkpoint: the one the test finds must be the stop's.
    let cfg = config(
        &root,
        &FAST.replace("checkpoint_every = 1", "checkpoint_every = 1000"),
    );
    let out = root.join("exp");
    let child = bin()
        .args([
            "experiment",
            "strong",
            "--seeds",
            "2",
            "--jobs",
            "1",
            "--threads",
            "1",
            "--frames",
            "100000000",
            "--config",
            &cfg,
            "--out",
            s(&out),
        ])
        .process_group(0) // a terminal's foreground group, with the experiment as its leader
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // Whatever happens below, no process outlives the test: the experiment is asked twice (it
    // passes both on, which stops its run at once), then the run itself, by its lock's pid.
    struct Reaper(std::process::Child, PathBuf);
    impl Drop for Reaper {
        fn drop(&mut self) {
            if self.0.try_wait().ok().flatten().is_some() {
                return;
            }
            let group = format!("-{}", self.0.id());
            for _ in 0..2 {
                let _ = Command::new("kill").args(["-TERM", "--", &group]).status();
                std::thread::sleep(std::time::Duration::from_millis(300));
            }
            // "pid N, started …", written by the run that holds it.
            let lock = std::fs::read_to_string(self.1.join("strong-seed1/.lock"));
            let pid = lock.as_deref().unwrap_or("").strip_prefix("pid ");
            if let Some(pid) = pid.and_then(|p| p.split(',').next()) {
                let _ = Command::new("kill").args(["-KILL", pid]).status();
            }
            let _ = self.0.kill();
            let _ = self.0.wait();
        }
    }
    let mut guard = Reaper(child, out.clone());
    let child = &mut guard.0;
    let log = out.join("strong-seed1.log");
    let started = std::time::Instant::now();
    while !std::fs::read_to_string(&log).is_ok_and(|t| t.contains("\nep 3 ")) {
        assert!(
            started.elapsed().as_secs() < 300,
            "the first run never reached episode 3"
        );
        std::thread::sleep(std::time::Duration::from_millis(100));
    }
    let sent = Command::new("kill")
        .args(["-INT", "--", &format!("-{}", child.id())])
        .status()
        .unwrap();
    assert!(sent.success());
    let waited = std::time::Instant::now();
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        assert!(
            waited.elapsed().as_secs() < 120,
            "the experiment did not stop within 120 s of a Ctrl-C"
        );
        std::thread::sleep(std::time::Duration::from_millis(100));
    };
    let mut stderr = String::new();
    std::io::Read::read_to_string(&mut child.stderr.take().unwrap(), &mut stderr).unwrap();
    assert_eq!(status.code(), Some(130), "{stderr}");
    assert!(stderr.contains("run the same command again"), "{stderr}");
    let text = std::fs::read_to_string(&log).unwrap();
    assert!(
        text.contains("stopped at episode"),
        "the run stopped by itself, with a checkpoint, before the experiment exited:\n{text}"
    );
    let ckpt =
        invaders::dqn::checkpoint::load(&out.join("strong-seed1/checkpoint.safetensors")).unwrap();
    assert!(ckpt.counters.episodes >= 3, "the episodes played are kept");
    assert!(
        !out.join("strong-seed2").exists() && !out.join("strong-seed2.log").exists(),
        "no run starts after a stop"
    );
    let _ = std::fs::remove_dir_all(&root);
}

#[test]
fn an_interrupted_run_keeps_its_work() {
    let root = tmp("signals");
    // No checkpoint until the end of the budget: SIGTERM must write one.
    let cfg = config(
        &root,
        &FAST.replace("checkpoint_every = 1", "checkpoint_every = 1000"),
    );
    let run = root.join("run");
    let mut child = bin()
        .args([
            "train",
            "--config",
            &cfg,
            "--seed",
            "4",
            "--threads",
            "1",
            "--episodes",
            "1000000",
            "--out",
            s(&run),
        ])
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut lines = BufReader::new(child.stderr.take().unwrap()).lines();
    let started = lines
        .by_ref()
        .map_while(Result::ok)
        .any(|l| l.starts_with("ep 2 "));
    assert!(started, "training runs");
    let killed = Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(killed.success());
    let rest: Vec<String> = lines.map_while(Result::ok).collect();
    let status = child.wait().unwrap();
    assert_eq!(
        status.code(),
        Some(130),
        "exit code after SIGTERM: {rest:?}"
    );
    assert!(rest.iter().any(|l| l.contains("--resume")), "{rest:?}");
    let ckpt = invaders::dqn::checkpoint::load(&run.join("checkpoint.safetensors")).unwrap();
    assert!(ckpt.counters.episodes >= 2, "the episodes played are kept");
    ok(&invaders(&[
        "train",
        "--resume",
        s(&run),
        "--episodes",
        &(ckpt.counters.episodes + 1).to_string(),
        "--threads",
        "1",
    ]));

    // A directory stopped before its first checkpoint can be resumed from its start, or reused.
    let early = root.join("early");
    std::fs::create_dir_all(&early).unwrap();
    std::fs::copy(&cfg, early.join("config.toml")).unwrap();
    std::fs::write(early.join("metrics.csv"), "episode\n").unwrap();
    let out = ok(&invaders(&[
        "train",
        "--resume",
        s(&early),
        "--episodes",
        "1",
        "--threads",
        "1",
    ]));
    assert!(out.contains("before its first checkpoint"), "{out}");
    assert!(early.join("checkpoint.safetensors").is_file());
    let reuse = root.join("reuse");
    std::fs::create_dir_all(&reuse).unwrap();
    std::fs::write(reuse.join("metrics.csv"), "episode\n").unwrap();
    let out = ok(&train(&cfg, 1, 1, &reuse));
    assert!(out.contains("starting anew"), "{out}");
    // But a directory with anything else in it is not taken.
    let other = root.join("other");
    std::fs::create_dir_all(&other).unwrap();
    std::fs::write(other.join("notes.txt"), "mine").unwrap();
    fails_with(&train(&cfg, 1, 1, &other), &["notes.txt"]);
    assert_eq!(
        std::fs::read_to_string(other.join("notes.txt")).unwrap(),
        "mine"
    );
    let _ = std::fs::remove_dir_all(&root);
}
