//! The program tried as a careless or hostile user would: one test per class of defect (data
//! lost or damaged, a configuration that says one thing and does another, panics, aborts and
//! hangs, interruptions). Each asserts a clear message, the exit code, and that nothing earlier
//! was harmed.

mod common;

use std::io::{BufRead, BufReader};
use std::os::unix::process::CommandExt;
use std::path::PathBuf;
use std::process::{Command, Stdio};

use common::cli::{
    assert_saved_config, bin, experiment_args, fails_with, invaders, ok, resume, resume_args, s,
    train, write_file, TINY,
};
use common::hostile::{
    config, eval_gif, no_periodic_checkpoint, read_all, sigterm, spawn_train, tmp, tmp_config,
    trained, wait_at_most, wait_for_line, FAST,
};

/// [`tmp_config`], and the path of a run in the directory: the directory, the configuration's
/// path and the run's.
fn tmp_run(name: &str, text: &str) -> (PathBuf, String, PathBuf) {
    let (root, cfg) = tmp_config(name, text);
    let run = root.join("run");
    (root, cfg, run)
}

#[test]
fn nothing_a_user_types_loses_or_damages_data() {
    let (root, cfg) = tmp_config("data", FAST);
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
    fails_with(&eval_gif(&a, &metrics, &[]), &["belongs to the run"]);
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
        &resume(&a, 2),
        &["not the replay memory saved with this checkpoint"],
    );
    std::fs::write(a.join(replay), own).unwrap();

    // Malformed metrics rows are named, not dropped; a deleted file is said to be lost.
    let good_metrics = std::fs::read_to_string(&metrics).unwrap();
    std::fs::write(&metrics, good_metrics.replace("\n1,", "\nx,")).unwrap();
    fails_with(&resume(&a, 2), &["line 2", "malformed"]);
    std::fs::remove_file(&metrics).unwrap();
    let out = ok(&resume(&a, 2));
    assert!(out.contains("metrics.csv is missing"), "{out}");

    // One process per run directory: a second one is refused while the first trains.
    let mut first = bin()
        .args(resume_args(&a, 1_000_000))
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
        &resume(&a, 1_000_000),
        &["in use by another process", &format!("pid {}", first.id())],
    );
    first.kill().unwrap();
    first.wait().unwrap();
    let _ = std::fs::remove_dir_all(&root);
}

#[test]
fn the_configuration_says_what_runs() {
    // A mode sets its knobs; an explicit knob overrides them; 0 removes the episode cap.
    let (root, cfg) = tmp_config(
        "config",
        &format!("{FAST}mode = \"nature\"\nnoop_max = 5\n"),
    );
    let run = root.join("nature");
    ok(&train(&cfg, 1, 1, &run));
    assert_saved_config(
        &run,
        &[
            "mode = \"nature\"",
            "frame_skip_min = 4",
            "frame_skip_max = 4",
            "sticky_prob = 0.0",
            "max_pool_last_two = true",
            "noop_max = 5",
            "max_episode_steps = 50",
        ],
    );
    let parsed =
        invaders::dqn::Config::resolve(None, Some("[env]\nmode = \"v5\"\nmax_episode_steps = 0\n"))
            .unwrap();
    assert_eq!(parsed.env.max_episode_steps, None);
    assert!(
        parsed.to_toml().contains("max_episode_steps = 0"),
        "no cap is written as 0"
    );

    // Extending a resumed run's budget rewrites config.toml; a budget already met is an error.
    ok(&resume(&run, 2));
    let saved = std::fs::read_to_string(run.join("config.toml")).unwrap();
    assert!(saved.contains("episodes = 2\n"), "{saved}");
    fails_with(&resume(&run, 1), &["has done 2 episodes", "larger"]);
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
    // No periodic checkpoint: the one the test finds must be the stop's.
    let (root, cfg) = tmp_config("experiment-signals", &no_periodic_checkpoint());
    let out = root.join("exp");
    let flags = [
        "--seeds",
        "2",
        "--jobs",
        "1",
        "--threads",
        "1",
        "--frames",
        "100000000",
    ];
    let child = bin()
        .args(experiment_args("strong", &flags, &cfg, s(&out)))
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
    // No checkpoint until the end of the budget: SIGTERM must write one.
    let (root, cfg, run) = tmp_run("signals", &no_periodic_checkpoint());
    let (mut child, mut lines) = spawn_train(&cfg, 4, 1_000_000, &run);
    wait_for_line(&mut lines, "ep 2 ");
    sigterm(&child);
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
    ok(&resume(&run, ckpt.counters.episodes + 1));

    // A directory stopped before its first checkpoint can be resumed from its start, or reused.
    let early = root.join("early");
    std::fs::create_dir_all(&early).unwrap();
    std::fs::copy(&cfg, early.join("config.toml")).unwrap();
    std::fs::write(early.join("metrics.csv"), "episode\n").unwrap();
    let out = ok(&resume(&early, 1));
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

/// Class 3: a run already in an experiment's folder is taken only if it was trained with the
/// configuration the command asks for; otherwise the command refuses, naming the keys, before
/// it writes or trains anything (the arm's TOML is not rewritten).
#[test]
fn a_reused_experiment_folder_is_refused_under_another_configuration() {
    let (root, a) = tmp_config("reuse", TINY);
    let b_path = write_file(
        &root,
        "b.toml",
        "replay_capacity = 2000\nlearning_starts = 200\nbatch_size = 16\ngamma = 0.9\n",
    );
    let exp = root.join("exp");
    let flags = ["--seeds", "1", "--frames", "400", "--threads", "1"];
    let strong = |cfg: &str| invaders(&experiment_args("strong", &flags, cfg, s(&exp)));
    // Seed 1's run, trained under A (as a first `experiment strong --config A` leaves it).
    let run = exp.join("strong-seed1");
    ok(&invaders(&[
        "train",
        "--preset",
        "strong",
        "--config",
        &a,
        "--seed",
        "1",
        "--frames",
        "400",
        "--threads",
        "1",
        "--out",
        s(&run),
    ]));
    std::fs::write(exp.join("strong.toml"), std::fs::read(&a).unwrap()).unwrap();
    let err = fails_with(
        &strong(s(&b_path)),
        &["another configuration", "`batch_size`", "`gamma`"],
    );
    assert!(
        !err.contains("replay_capacity"),
        "only the keys that differ: {err}"
    );
    assert_eq!(
        std::fs::read(exp.join("strong.toml")).unwrap(),
        std::fs::read(&a).unwrap(),
        "the folder's configuration is left as it was"
    );
    assert!(!exp.join("strong-seed1.log").exists(), "nothing trained");

    // The preprocessing experiment checks its runs the same way.
    let pre = root.join("pre");
    ok(&invaders(&[
        "train",
        "--preset",
        "article-vanilla",
        "--config",
        &a,
        "--seed",
        "0",
        "--episodes",
        "1",
        "--threads",
        "1",
        "--out",
        s(&pre.join("article-vanilla-seed0")),
    ]));
    fails_with(
        &invaders(&experiment_args(
            "preprocessing",
            &["--episodes", "1", "--seeds", "1"],
            s(&b_path),
            s(&pre),
        )),
        &["article-vanilla-seed0", "`batch_size`"],
    );
    assert!(
        !pre.join("article-vanilla.toml").exists(),
        "nothing written"
    );
    let _ = std::fs::remove_dir_all(&root);
}

/// Class 4: a run whose checkpoint is gone is never started again over its own history, by
/// `--resume` or by a new `train --out` (or an experiment) in its directory; the message says
/// what is lost.
#[test]
fn a_run_whose_checkpoint_is_lost_is_not_restarted_over_its_history() {
    let (root, cfg, run) = trained("lost", 3);
    std::fs::remove_file(run.join("checkpoint.safetensors")).unwrap();
    let metrics = std::fs::read(run.join("metrics.csv")).unwrap();
    let resume = || resume(&run, 5);
    // The replay file is still there: it is the run's, and says a checkpoint was written.
    let err = fails_with(&resume(), &["checkpoint is lost", "replay-3.safetensors"]);
    assert!(!err.contains("does not write"), "{err}");
    std::fs::remove_file(run.join("replay-3.safetensors")).unwrap();
    let err = fails_with(&resume(), &["checkpoint is lost", "3 finished episodes"]);
    assert!(!err.contains("before its first checkpoint"), "{err}");
    fails_with(&train(&cfg, 1, 3, &run), &["checkpoint is lost"]);
    assert_eq!(
        std::fs::read(run.join("metrics.csv")).unwrap(),
        metrics,
        "history kept"
    );
    let _ = std::fs::remove_dir_all(&root);
}

/// Class 6: messages say what is so.
#[test]
fn messages_say_what_is_so() {
    let (root, cfg, run) = trained("messages", 1);

    // `export` over an existing file suggests --force, and --force works.
    let model = root.join("model.safetensors");
    let export = |extra: &[&str]| {
        let args = ["export", "--checkpoint", s(&run), "--out", s(&model)];
        invaders(&[&args, extra].concat())
    };
    ok(&export(&[]));
    fails_with(&export(&[]), &["--force"]);
    ok(&export(&["--force"]));

    // Inconsistent frame skips are reported with the values written.
    for (text, needle) in [
        (
            "[env]\nframe_skip_min = 5\nframe_skip_max = 2\n",
            "(5) is larger than frame_skip_max (2)",
        ),
        (
            "[env]\nframe_skip_min = 0\nframe_skip_max = 0\n",
            "frame_skip_min must be at least 1",
        ),
    ] {
        let err = fails_with(
            &invaders(&[
                "train",
                "--config",
                &config(&root, text),
                "--out",
                s(&root.join("x")),
            ]),
            &[needle],
        );
        assert!(
            !err.contains("(4)") && !err.contains("(2) is larger"),
            "{err}"
        );
    }

    // No temporary directory: the path is named, the OS error said once.
    let out = bin()
        .args(["eval", "--random", "--episodes", "1"])
        .env("TMPDIR", root.join("missing"))
        .output()
        .unwrap();
    let err = fails_with(&out, &["missing", "TMPDIR"]);
    assert_eq!(err.matches("os error").count(), 1, "{err}");

    // `--resume` given the checkpoint file names its run directory.
    fails_with(
        &invaders(&[
            "train",
            "--resume",
            s(&run.join("checkpoint.safetensors")),
            "--episodes",
            "2",
        ]),
        &["is a file", &format!("--resume {}", run.display())],
    );

    // A stop during the budget's last episode: the run is complete, not "continue with --resume".
    let long = config(
        &root,
        &FAST.replace("max_episode_steps = 50", "max_episode_steps = 3000"),
    );
    let last = root.join("last");
    let (mut child, mut lines) = spawn_train(&long, 1, 1, &last);
    wait_for_line(&mut lines, "training preset");
    std::thread::sleep(std::time::Duration::from_millis(300));
    sigterm(&child);
    let rest = lines.map_while(Result::ok).collect::<Vec<_>>().join("\n");
    let status = wait_at_most(&mut child, 120, "train stopped in its last episode");
    assert_eq!(status.code(), Some(0), "{rest}");
    assert!(
        rest.contains("complete") && !rest.contains("--resume"),
        "{rest}"
    );

    // Two runs of one preset and seed started together with the default --out: a directory each.
    let cwd = root.join("cwd");
    std::fs::create_dir_all(&cwd).unwrap();
    let start = || {
        bin()
            .current_dir(&cwd)
            .args([
                "train",
                "--config",
                &cfg,
                "--seed",
                "7",
                "--threads",
                "1",
                "--episodes",
                "1",
            ])
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap()
    };
    let (mut one, mut two) = (start(), start());
    for child in [&mut one, &mut two] {
        let status = wait_at_most(child, 120, "train with the default --out");
        let err = read_all(child.stderr.take());
        assert!(status.success(), "{err}");
    }
    let dirs = std::fs::read_dir(cwd.join("runs")).unwrap().count();
    assert_eq!(dirs, 2, "each run its own directory");
    let _ = std::fs::remove_dir_all(&root);
}

/// Class 7: every knob has a bound.
#[test]
fn every_knob_has_a_bound() {
    let root = tmp("knobs");
    fails_with(
        &invaders(&["train", "--threads", "1000", "--out", s(&root.join("t"))]),
        &["--threads must be in 1..="],
    );
    assert!(!root.join("t").exists());
    fails_with(
        &invaders(&[
            "show-preprocessing",
            "--steps",
            "100000000",
            "--out",
            s(&root.join("p.png")),
        ]),
        &["--steps must be at most"],
    );
    let out = invaders(&[
        "experiment",
        "strong",
        "--jobs",
        "0",
        "--out",
        s(&root.join("e")),
    ]);
    assert_eq!(out.status.code(), Some(2), "a usage error");
    assert!(String::from_utf8_lossy(&out.stderr).contains("--jobs"));
    assert!(!root.join("e").exists());
    let _ = std::fs::remove_dir_all(&root);
}

/// `experiment strong` and `experiment ablation` start from a strong preset only: another
/// `--preset` is refused by name before anything is written.
#[test]
fn experiments_take_only_the_strong_presets() {
    let root = tmp("strong-presets");
    for experiment in ["strong", "ablation"] {
        let out = root.join(experiment);
        let got = invaders(&[
            "experiment",
            experiment,
            "--preset",
            "article",
            "--out",
            s(&out),
        ]);
        let err = String::from_utf8_lossy(&got.stderr);
        assert_eq!(got.status.code(), Some(2), "a usage error: {err}");
        assert!(err.contains("`strong` or `strong-v1`"), "{err}");
        assert!(!out.exists(), "{experiment}: {} written", out.display());
    }
    let out = root.join("v1");
    fails_with(
        &invaders(&[
            "experiment",
            "strong",
            "--preset",
            "strong-v1",
            "--frames",
            "0",
            "--out",
            s(&out),
        ]),
        &["--frames"],
    );
    assert!(!out.exists());
    let _ = std::fs::remove_dir_all(&root);
}
