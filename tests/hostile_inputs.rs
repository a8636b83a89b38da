//! A hostile user against what the program reads and what it says (split from
//! `tests/hostile.rs` by concern): memory limits, damaged `--keep` records, plot inputs and
//! reference curves, configuration values out of range, and messages that must be true.

mod common;

use std::os::unix::process::CommandExt;
use std::path::Path;

use common::cli::{bin, fails_with, invaders, ok, s, train_command, write_file, TINY};
use common::hostile::{
    keep_experiment, output_within, tmp_run, train_strong, trained, write_record,
};

/// `invaders ARGS` under an address-space limit of `kib` KiB (as `ulimit -v` sets it).
fn under_ulimit_v(args: &[&str], kib: u64) -> std::process::Output {
    let mut cmd = bin();
    cmd.args(args);
    // SAFETY: setrlimit is async-signal-safe and touches no memory of the parent.
    unsafe {
        cmd.pre_exec(move || {
            let lim = libc::rlimit {
                rlim_cur: kib * 1024,
                rlim_max: kib * 1024,
            };
            if libc::setrlimit(libc::RLIMIT_AS, &lim) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
    output_within(cmd, 300)
}

/// Row 5: a replay memory or a PQN rollout larger than what the process may use (here
/// `ulimit -v`) is refused with the need and the limit, exit 1 and no run folder, not an abort.
#[test]
fn memory_is_checked_against_what_the_process_may_use() {
    let (root, _, _) = tmp_run("memory");
    let dqn = write_file(&root, "dqn.toml", "replay_capacity = 1000000\n");
    let pqn = write_file(
        &root,
        "pqn.toml",
        "[pqn]\ngames = 256\nrollout = 1024\nminibatches = 64\n",
    );
    for (cfg, what) in [(&dqn, "replay_capacity = 1000000"), (&pqn, "PQN rollout")] {
        let out = root.join("run");
        let args = [
            "train",
            "--preset",
            "strong",
            "--config",
            s(cfg),
            "--episodes",
            "1",
            "--threads",
            "1",
            "--out",
            s(&out),
        ];
        let err = fails_with(
            &under_ulimit_v(&args, 3_000_000),
            &[what, "needs about", "ulimit -v", "nothing was written"],
        );
        assert!(!err.contains("memory allocation of"), "{err}");
        assert!(!out.exists(), "no run folder: {err}");
    }
    let _ = std::fs::remove_dir_all(&root);
}

/// Row 7: a `--keep` record whose scores no evaluation gives (NaN, a negative standard
/// deviation, a mean outside [min, max]) is an error naming the file, line and key, not a
/// table of NaN.
#[test]
fn a_damaged_record_is_refused_by_file_line_and_key() {
    let (root, _, _) = tmp_run("record-damaged");
    let cfg = s(&write_file(&root, "x.toml", TINY)).to_string();
    let run = root.join("run");
    train_strong(&cfg, 400, &run);
    let keep = root.join("keep");
    let out = root.join("exp");
    for (scores, key) in [
        (["nan", "1.0", "5.0", "15.0"], "mean"),
        (["10.0", "-1.0", "5.0", "15.0"], "std"),
        (["20.0", "1.0", "5.0", "15.0"], "mean"),
    ] {
        let record = write_record(&keep, &run, TINY, scores);
        let text = std::fs::read_to_string(record.join("result.toml")).unwrap();
        let at = text
            .lines()
            .position(|l| l.starts_with(&format!("{key} =")))
            .unwrap();
        let line = format!("line {}", at + 1);
        let key = format!("protocol.{key}");
        let (line, key) = (line.as_str(), key.as_str());
        let args = keep_experiment(&cfg, &keep, &out);
        let err = fails_with(&invaders(&args), &["result.toml", line, key, "damaged"]);
        assert!(!err.contains("NaN."), "{err}");
        assert!(record.join("result.toml").is_file(), "the record is kept");
    }
    let _ = std::fs::remove_dir_all(&root);
}

/// The `metrics.csv` of a run with `rows` (frames, reward) points, in a new folder `dir`.
fn metrics_run(dir: &Path, rows: &[(u64, f64)]) {
    std::fs::create_dir_all(dir).unwrap();
    let mut text = String::from(
        "episode,agent_steps,emulator_frames,reward,length,epsilon,mean_loss,mean_max_q,wall_seconds\n",
    );
    for (i, (frames, reward)) in rows.iter().enumerate() {
        text.push_str(&format!(
            "{},{},{frames},{reward},10,1,0,0,0.1\n",
            i + 1,
            frames / 4
        ));
    }
    std::fs::write(dir.join("metrics.csv"), text).unwrap();
}

/// Rows 6, 8, 9 and `plot --out` without `.png`: a group of short runs is drawn (a figure with
/// no curve is an error), `--reference` without `--group` is refused, and reference curves out
/// of range, not finite, unordered or empty are refused by file, line and value.
#[test]
fn plot_draws_what_it_is_given_or_says_why_not() {
    let (root, _, run) = trained("plot-short", 2);
    let png = root.join("p.png");
    let group = format!("short={}", s(&run));
    ok(&invaders(&["plot", "--group", &group, "--out", s(&png)]));
    assert!(png.is_file());
    // No episode: no curve, so no figure.
    let empty = root.join("empty");
    metrics_run(&empty, &[]);
    let none = format!("none={}", s(&empty));
    let p2 = root.join("p2.png");
    fails_with(
        &invaders(&["plot", "--group", &none, "--out", s(&p2)]),
        &["no finished episode", "nothing is drawn"],
    );
    fails_with(
        &invaders(&["plot", s(&empty), "--out", s(&p2)]),
        &["no finished episode"],
    );
    assert!(!p2.exists());

    // --reference without --group.
    let good = write_file(&root, "ref.csv", "agent,frames,score\nA,100,5\nA,200,7\n");
    fails_with(
        &invaders(&["plot", s(&run), "--reference", s(&good), "--out", s(&p2)]),
        &["--reference", "--group"],
    );
    ok(&invaders(&[
        "plot",
        "--group",
        &group,
        "--reference",
        s(&good),
        "--out",
        s(&p2),
    ]));

    // References out of range.
    for (body, needles) in [
        ("A,-5,10\n", vec!["line 2", "frames -5"]),
        ("A,100,1e30\n", vec!["line 2", "score 1e30"]),
        ("A,100,NaN\n", vec!["line 2", "score NaN"]),
        ("A,2e12,5\n", vec!["line 2", "frames 2000000000000"]),
        (
            "A,200,5\nA,100,6\n",
            vec!["line 3", "increasing frame order"],
        ),
        ("", vec!["no curve"]),
    ] {
        let bad = write_file(&root, "bad.csv", &format!("agent,frames,score\n{body}"));
        let mut all = vec!["bad.csv"];
        all.extend(needles);
        let p3 = root.join("p3.png");
        fails_with(
            &invaders(&[
                "plot",
                "--group",
                &group,
                "--reference",
                s(&bad),
                "--out",
                s(&p3),
            ]),
            &all,
        );
        assert!(!p3.exists());
    }

    // --out without .png says so, not the temporary file's name.
    let err = fails_with(
        &invaders(&["plot", s(&run), "--out", s(&root.join("figure"))]),
        &["give a file name ending in .png"],
    );
    assert!(!err.contains("PathExtension"), "{err}");
    let _ = std::fs::remove_dir_all(&root);
}

/// Messages that must be true: a range error names the key and the line of the user's file and
/// writes a huge number short, in `train`, the experiments and `bench` alike; the bf16 notes name `INVADERS_NO_BF16` when that is why, and
/// config.toml says so too.
#[test]
fn messages_name_key_line_and_the_real_cause() {
    let (root, cfg, run) = tmp_run("messages");
    let huge = "learning_starts = 30\ngamma = 1e300\n";
    let bad = write_file(&root, "huge.toml", huge);
    let err = fails_with(
        &output_within(train_command(s(&bad), 1, 1, &run), 120),
        &["huge.toml, line 2", "gamma must be in [0, 1]", "1e300"],
    );
    assert!(
        !err.contains("0000000000000"),
        "a huge number shortened: {err}"
    );
    assert!(!run.exists(), "no run folder");
    // Every command that takes --config says the same: the experiments and bench.
    let exp = root.join("exp");
    for kind in ["strong", "ablation", "preprocessing"] {
        let args = ["experiment", kind, "--config", s(&bad), "--out", s(&exp)];
        fails_with(&invaders(&args), &["huge.toml, line 2", "gamma", "1e300"]);
    }
    fails_with(
        &invaders(&["bench", "--config", s(&bad)]),
        &["huge.toml, line 2", "gamma", "1e300"],
    );
    assert!(!exp.exists(), "no experiment folder");

    // bf16 asked for where INVADERS_NO_BF16 switches it off.
    let cpu_runs_bf16 = invaders::tensor::cpu::why_no_bf16().is_none();
    let mut cmd = train_command(&cfg, 1, 1, &run);
    cmd.args(["--precision", "bf16"])
        .env("INVADERS_NO_BF16", "1");
    let said = ok(&output_within(cmd, 300));
    let saved = std::fs::read_to_string(run.join("config.toml")).unwrap();
    assert!(
        saved.contains("was asked for, but") && saved.contains("runs its products in f32"),
        "{saved}"
    );
    let mut cmd = train_command(&cfg, 1, 1, &root.join("auto"));
    cmd.args(["--precision", "auto"])
        .env("INVADERS_NO_BF16", "1");
    let auto = ok(&output_within(cmd, 300));
    if cpu_runs_bf16 {
        assert!(said.contains("INVADERS_NO_BF16 is set"), "{said}");
        assert!(saved.contains("INVADERS_NO_BF16 is set"), "{saved}");
        assert!(auto.contains("INVADERS_NO_BF16 is set"), "{auto}");
        assert!(!auto.contains("on this CPU"), "{auto}");
    }
    let _ = std::fs::remove_dir_all(&root);
}
