//! The `invaders` binary end to end: a short Space Invaders training run, its run directory,
//! evaluation, resume, plotting, and every bad-input path giving a clear error and a non-zero
//! exit without touching earlier results.

mod common;

use common::cli::{
    assert_saved_config, bin, fails_saying as fails_with, invaders, ok, resume, row, s, tmp_dir,
    tmp_with_file, train, train_command, TINY,
};
use std::path::{Path, PathBuf};

fn tmp(name: &str) -> PathBuf {
    tmp_dir("invaders-cli", name)
}

/// A new temporary directory named `name` holding `file` with `text`; returns the directory and
/// the file's path.
fn tmp_with(name: &str, file: &str, text: &str) -> (PathBuf, PathBuf) {
    tmp_with_file("invaders-cli", name, file, text)
}

/// A new temporary directory named `name` holding `text` (a variant of [`QUICK`]) in
/// `quick.toml`: the directory, the file's path and that of a run in the directory.
fn quick_run(name: &str, text: &str) -> (PathBuf, PathBuf, PathBuf) {
    let (root, cfg) = tmp_with(name, "quick.toml", text);
    let run = root.join("run");
    (root, cfg, run)
}

/// A small but real configuration: short episodes (cut at 150 agent steps), learning from step 60.
const QUICK: &str = "learning_starts = 60\nreplay_capacity = 400\nbatch_size = 8\ncheckpoint_every = 1\nplot_every = 1\n[env]\nmax_episode_steps = 150\n";

/// The shipped player's model file.
const SHIPPED_MODEL: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/models/strong/model.safetensors"
);

fn metrics_rows(dir: &Path) -> Vec<Vec<String>> {
    let text = std::fs::read_to_string(dir.join("metrics.csv")).unwrap();
    let mut lines = text.lines();
    assert_eq!(
        lines.next().unwrap(),
        "episode,agent_steps,emulator_frames,reward,length,epsilon,mean_loss,mean_max_q,wall_seconds"
    );
    lines
        .map(|l| l.split(',').map(str::to_string).collect())
        .collect()
}

/// The f32 kernel family this host runs, as `bench --json` names it.
fn f32_family() -> &'static str {
    if invaders::tensor::cpu::avx512() {
        "avx512-f32"
    } else if invaders::tensor::cpu::avx2() {
        "avx2-f32"
    } else {
        "portable-f32"
    }
}

/// `bench --precision bf16 --json` says which kernel family ran: AVX512-BF16 where the CPU has
/// it, else the f32 kernels, with one note on stderr saying why. `INVADERS_NO_BF16=1` makes an
/// AVX512-BF16 host an AVX-512 one without it (Intel Skylake-SP to Ice Lake), so both kinds are
/// checked here.
#[test]
fn bench_in_bf16_says_which_kernels_ran() {
    use invaders::tensor::cpu;
    for no_bf16 in [false, true] {
        let mut cmd = bin();
        cmd.args(["bench", "--threads", "1", "--steps", "1", "--json"])
            .args(["--precision", "bf16"]);
        if no_bf16 {
            cmd.env("INVADERS_NO_BF16", "1");
        }
        let out = cmd.output().expect("the binary runs");
        let (stdout, stderr) = (
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr),
        );
        assert!(out.status.success(), "{stderr}");
        let json: serde_json::Value = serde_json::from_str(stdout.trim()).expect(&stdout);
        // The child inherits this process's environment, so this process's check applies to it.
        let runs = cpu::avx512_bf16() && !no_bf16;
        let family = match (runs, cpu::amx()) {
            (true, true) => "amx-bf16",
            (true, false) => "avx512-bf16",
            _ => f32_family(),
        };
        assert_eq!(json["kernel_family"], family, "{stdout}");
        assert_eq!(json["precision"], "bf16", "{stdout}");
        let conv = json["kernels"]["conv_forward"].as_str().unwrap_or_default();
        assert_eq!(conv.contains("Bf16"), runs, "{stdout}");
        assert_eq!(
            stderr.matches("bf16 asked for").count(),
            usize::from(!runs),
            "one note exactly when bf16 does not run: {stderr}"
        );
        if no_bf16 && cpu::avx512() {
            // The note names the switch where the CPU has AVX512-BF16, else the missing feature
            // (an AVX-512 CPU without it: Intel Skylake-SP to Ice Lake).
            let f = cpu::features();
            let why = if f.avx512_bf16 || f.bf16_switched_off {
                "INVADERS_NO_BF16 is set"
            } else {
                "this CPU lacks avx512bf16"
            };
            assert!(stderr.contains(why), "{stderr}");
        }
    }
}

/// A run bounded by emulator frames instead of episodes starts, stops on its budget and saves
/// its configuration (it once panicked writing `config.toml`: the unbounded episode count did
/// not fit TOML's integers).
#[test]
fn train_by_frames() {
    let (root, cfg, run) = quick_run("frames", QUICK);
    let text = ok(&invaders(&[
        "train",
        "--config",
        s(&cfg),
        "--frames",
        "900",
        "--threads",
        "1",
        "--out",
        s(&run),
    ]));
    assert!(text.contains("frames"), "{text}");
    let saved = std::fs::read_to_string(run.join("config.toml")).unwrap();
    assert!(saved.contains("max_frames = 900"), "{saved}");
    assert!(run.join("checkpoint.safetensors").is_file());
    // `bench` prints its figures as one JSON object, acting also timed with this run's network.
    let text = ok(&invaders(&[
        "bench",
        "--threads",
        "1",
        "--steps",
        "2",
        "--json",
        "--checkpoint",
        s(&run),
    ]));
    let json: serde_json::Value = serde_json::from_str(text.trim()).expect(&text);
    for key in [
        "train_step_ms",
        "train_step_gflops",
        "act_ms",
        "act_checkpoint_ms",
        "env_frames_per_s",
        "agent_steps_per_s",
        "strong_agent_steps_per_s",
        "strong_4_games_agent_steps_per_s",
        "strong_v1_agent_steps_per_s",
    ] {
        let v = json[key].as_f64().unwrap_or(-1.0);
        assert!(v > 0.0 && v.is_finite(), "{key} in {text}");
    }
    // Both of `strong`'s loops at ε's floor, with each core's shares: on one thread the
    // player's shares are the whole wall time (the update among them when it takes turns;
    // beside the play, the update's time is the block's wait for it).
    for (key, beside) in [
        ("strong_final_epsilon", false),
        ("strong_acting_while_learning_final_epsilon", true),
        ("strong_4_games_final_epsilon", false),
        ("strong_4_games_acting_while_learning_final_epsilon", true),
    ] {
        let v = json[key]["agent_steps_per_s"].as_f64().unwrap_or(-1.0);
        assert!(v > 0.0 && v.is_finite(), "{key} in {text}");
        let p = &json[key]["core_shares"]["player"];
        let share = |k: &str| p[k].as_f64().unwrap_or(-1.0);
        let parts = [
            "acting",
            "emulator",
            "storing",
            "sampling",
            "target_pass",
            "update",
            "joining",
            "other",
        ];
        assert!(
            parts.iter().all(|&k| (0.0..=1.0).contains(&share(k))),
            "{key} in {text}"
        );
        let sum: f64 = parts.iter().map(|&k| share(k)).sum();
        assert!(
            (0.98..=1.02).contains(&sum),
            "{key}'s shares add to {sum}: {text}"
        );
        assert!(
            share("emulator") > 0.0 && share("acting") > 0.0,
            "{key} in {text}"
        );
        let (update, joining) = (share("update"), share("joining"));
        // Beside the play, the playing thread makes each next update's target pass.
        let target_pass = share("target_pass");
        assert!(
            if beside {
                update == 0.0 && joining > 0.0 && target_pass > 0.0
            } else {
                update > 0.0 && joining == 0.0 && target_pass == 0.0
            },
            "{key} in {text}"
        );
        let others = json[key]["core_shares"]["others_update"]
            .as_f64()
            .unwrap_or(-1.0);
        assert!(others > 0.0 && others <= 1.0, "{key} in {text}");
    }
    assert_eq!(json["threads"], 1, "{text}");
    assert_eq!(json["precision"], "f32", "{text}");
    assert_eq!(json["kernel_family"], f32_family(), "{text}");
    assert!(
        json["kernels"]["conv_forward"].is_string(),
        "each product's kernel: {text}"
    );
    // A weights-only model file times acting too (the shipped player's network); a config of
    // one's own is timed from the preset `--preset` names, which the report says (here 3 games
    // side by side, whose replay lanes must divide the benchmark's smaller memory too).
    let own = root.join("own.toml");
    let own_text = "precision = \"f32\"\ngames = 3\nreplay_capacity = 999999\n";
    std::fs::write(&own, own_text).unwrap();
    let text = ok(&invaders(&[
        "bench",
        "--threads",
        "1",
        "--steps",
        "1",
        "--json",
        "--checkpoint",
        SHIPPED_MODEL,
        "--config",
        s(&own),
        "--preset",
        "strong",
    ]));
    let json: serde_json::Value = serde_json::from_str(text.trim()).expect(&text);
    let v = json["act_checkpoint_ms"].as_f64().unwrap_or(-1.0);
    assert!(
        v > 0.0 && v.is_finite(),
        "act_checkpoint_ms with a model file: {text}"
    );
    assert_eq!(json["config_preset"], "strong", "{text}");
    assert_eq!(json["config_batch_size"], 32, "{text}");
    let v = json["config_train_step_ms"].as_f64().unwrap_or(-1.0);
    assert!(v > 0.0 && v.is_finite(), "config_train_step_ms: {text}");
    let v = json["config_agent_steps_per_s"].as_f64().unwrap_or(-1.0);
    assert!(v > 0.0 && v.is_finite(), "config_agent_steps_per_s: {text}");
    let _ = std::fs::remove_dir_all(&root);
}

#[test]
fn train_eval_resume_plot() {
    let (root, cfg, run) = quick_run("run", QUICK);
    ok(&train(s(&cfg), 5, 2, &run));
    for f in [
        "config.toml",
        "metrics.csv",
        "checkpoint.safetensors",
        "rewards.png",
    ] {
        assert!(run.join(f).is_file(), "{f} missing");
    }
    let rows = metrics_rows(&run);
    assert_eq!(rows.len(), 2);
    assert_eq!(rows[0][0], "1");
    assert_eq!(rows[1][0], "2");
    let steps: u64 = rows[1][1].parse().unwrap();
    assert!(steps > 150, "two episodes of up to 150 steps: {steps}");
    assert_ne!(rows[1][6], "NaN", "learning started in episode 2");
    let saved = std::fs::read_to_string(run.join("config.toml")).unwrap();
    assert!(
        saved.contains("seed = 5") && saved.contains("max_episode_steps = 150"),
        "{saved}"
    );

    // Evaluation of the checkpoint, with a GIF.
    let gif = root.join("play.gif");
    let text = ok(&invaders(&[
        "eval",
        "--checkpoint",
        s(&run),
        "--episodes",
        "2",
        "--gif",
        gif.to_str().unwrap(),
    ]));
    assert!(
        text.contains("mean")
            && text.contains("std")
            && text.contains("min")
            && text.contains("max"),
        "{text}"
    );
    // Each episode's line and the summary count the mothership's passes and the hits on it,
    // and say how each game ended (the last life, a landing or the step limit).
    assert!(
        text.contains("steps")
            && text
                .lines()
                .filter(|l| l.starts_with("episode") && l.contains(" mothership "))
                .count()
                == 2
            && text.contains(", mothership hit in "),
        "{text}"
    );
    let ended: Vec<&str> = text
        .lines()
        .filter(|l| l.starts_with("episode"))
        .filter_map(|l| l.rsplit(": ").next())
        .collect();
    assert!(
        ended.len() == 2
            && ended
                .iter()
                .all(|e| ["last life", "landing", "step limit"].contains(e)),
        "{text}"
    );
    let summary = text.lines().last().unwrap();
    let counted: u64 = ["by the last life ", "by a landing ", "by the step limit "]
        .iter()
        .map(|k| {
            let at = summary.find(k).unwrap_or_else(|| panic!("{k}: {summary}")) + k.len();
            let n: String = summary[at..]
                .chars()
                .take_while(char::is_ascii_digit)
                .collect();
            n.parse::<u64>().unwrap()
        })
        .sum();
    assert_eq!(counted, 2, "{summary}");
    let bytes = std::fs::read(&gif).unwrap();
    assert!(bytes.starts_with(b"GIF89a") && bytes.len() > 10_000);
    assert_eq!(u16::from_le_bytes([bytes[6], bytes[7]]), 160, "GIF width");
    assert_eq!(u16::from_le_bytes([bytes[8], bytes[9]]), 210, "GIF height");

    // Resume continues from the saved counters.
    ok(&resume(&run, 3));
    let rows = metrics_rows(&run);
    assert_eq!(rows.len(), 3);
    assert_eq!(rows[2][0], "3");
    let steps3: u64 = rows[2][1].parse().unwrap();
    assert!(
        steps3 > steps,
        "agent steps continue: {steps3} after {steps}"
    );

    // Plot of two runs on one figure.
    let png = root.join("cmp.png");
    ok(&invaders(&[
        "plot",
        s(&run),
        s(&run),
        "--out",
        png.to_str().unwrap(),
    ]));
    assert!(std::fs::read(&png).unwrap().starts_with(b"\x89PNG"));

    // A non-empty --out is refused and left as it was.
    let before = std::fs::read(run.join("checkpoint.safetensors")).unwrap();
    fails_with(
        &invaders(&[
            "train",
            "--config",
            s(&cfg),
            "--episodes",
            "1",
            "--out",
            s(&run),
        ]),
        "not empty",
    );
    assert_eq!(
        std::fs::read(run.join("checkpoint.safetensors")).unwrap(),
        before
    );
    assert_eq!(metrics_rows(&run).len(), 3);
    let _ = std::fs::remove_dir_all(&root);
}

/// `returns` reads each run at equal frames (the last `--window` episodes up to them), a group
/// as mean (min–max), and leaves a cell empty where a run has not trained that far.
#[test]
fn returns_tabulates_runs_at_equal_frames() {
    let root = tmp("returns");
    let header = "episode,agent_steps,emulator_frames,reward,length,epsilon,mean_loss,mean_max_q,wall_seconds";
    // Run a: episode i ends at 1 000·i frames with reward i (10 episodes); run b: reward 10·i,
    // 6 episodes.
    for (name, episodes, scale) in [("a", 10, 1), ("b", 6, 10)] {
        let rows: String = (1..=episodes)
            .map(|i| {
                format!(
                    "{i},{},{},{},250,0.01,0.1,1.0,1.0\n",
                    250 * i,
                    1000 * i,
                    scale * i
                )
            })
            .collect();
        std::fs::create_dir_all(root.join(name)).unwrap();
        std::fs::write(
            root.join(name).join("metrics.csv"),
            format!("{header}\n{rows}"),
        )
        .unwrap();
    }
    let (a, b) = (root.join("a"), root.join("b"));
    let group = format!("both={},{}", s(&a), s(&b));
    let table = ok(&invaders(&[
        "returns",
        "--window",
        "3",
        "--at",
        "0.005M,9000",
        "--group",
        &group,
        s(&b),
    ]));
    assert_eq!(row(&table, "0.005 M"), "| 0.005 M | 22 (4–40) | 40 |");
    assert_eq!(row(&table, "0.009 M"), "| 0.009 M | 8 [1 of 2] |  |");
    assert_eq!(
        row(&table, "end (last 3)"),
        "| end (last 3) | 29.5 (9.0–50.0) | 50.0 |"
    );
    assert_eq!(
        row(&table, "frames at the end"),
        "| frames at the end | 10000, 6000 | 6000 |"
    );
    for (args, needle) in [
        (
            vec!["returns", s(&a), "--at", "half"],
            "`half` is not a number of frames",
        ),
        (vec!["returns", s(&a), "--window", "0"], "--window"),
        (vec!["returns", "--group", "nolabel"], "LABEL=DIR"),
        (vec!["returns", s(&root)], "metrics.csv"),
    ] {
        fails_with(&invaders(&args), needle);
    }
    let _ = std::fs::remove_dir_all(&root);
}

#[test]
fn bad_inputs_give_clear_errors() {
    let root = tmp("bad");
    let path = |n: &str| root.join(n).to_str().unwrap().to_string();
    std::fs::write(root.join("unknown.toml"), "gama = 0.5\n").unwrap();
    std::fs::write(root.join("range.toml"), "gamma = 1.5\n").unwrap();
    std::fs::write(root.join("precision.toml"), "precision = \"f16\"\n").unwrap();
    std::fs::write(
        root.join("corrupt.safetensors"),
        b"\x10\x00\x00\x00\x00\x00\x00\x00{\"a\":1}",
    )
    .unwrap();
    // Each command, in order, and what its error must mention.
    let (nothing, r5) = (path("nothing-here"), path("r5"));
    let cases: [(&[&str], &str); 18] = [
        (&["train", "--no-such-flag"], "--no-such-flag"),
        (&["train", "--preset", "nature"], "nature"),
        (
            &["train", "--config", &path("missing.toml")],
            "cannot read config file",
        ),
        (
            &[
                "train",
                "--config",
                &path("unknown.toml"),
                "--out",
                &path("r1"),
            ],
            "gama",
        ),
        (
            &[
                "train",
                "--config",
                &path("range.toml"),
                "--out",
                &path("r2"),
            ],
            "gamma",
        ),
        (
            &["train", "--threads", "0", "--out", &path("r3")],
            "--threads",
        ),
        (
            &["train", "--episodes", "0", "--out", &path("r4")],
            "episodes",
        ),
        (&["train", "--resume", &nothing], "checkpoint"),
        (&["train", "--precision", "fp16", "--out", &r5], "fp16"),
        (
            &["train", "--precision", "bf16", "--resume", &r5],
            "--resume",
        ),
        (
            &[
                "train",
                "--config",
                &path("precision.toml"),
                "--out",
                &path("r6"),
            ],
            "precision",
        ),
        (&["bench", "--precision", "f64"], "f64"),
        (&["bench", "--checkpoint", &nothing], "nothing-here"),
        (
            &["eval", "--checkpoint", &path("corrupt.safetensors")],
            "not a valid checkpoint",
        ),
        (&["eval"], "--checkpoint"),
        (&["eval", "--random", "--episodes", "0"], "--episodes"),
        (&["eval", "--random", "--rom", &path("no.bin")], "no.bin"),
        (&["plot", &nothing, "--out", &path("x.png")], "metrics.csv"),
    ];
    for (args, needle) in cases {
        fails_with(&invaders(args), needle);
    }
    for r in ["r1", "r2", "r3", "r4", "r5", "r6"] {
        assert!(
            !root.join(r).exists() || std::fs::read_dir(root.join(r)).unwrap().next().is_none(),
            "{r} written"
        );
    }
    let _ = std::fs::remove_dir_all(&root);
}

/// The `strong` preset's switches (dueling head, 3-step returns, life loss ending bootstrapping)
/// train end to end; `export` writes a weights-only model that `eval` plays (bit-identically to
/// the checkpoint) and `--resume` refuses; `eval --protocol` holds to its rules.
#[test]
fn strong_preset_export_and_protocol() {
    let (root, cfg, run) = quick_run("strong", &format!("preset = \"strong\"\n{QUICK}"));
    ok(&train(s(&cfg), 3, 2, &run));
    assert_saved_config(
        &run,
        &["dueling = true", "n_step = 3", "life_loss_terminal = true"],
    );
    let model = root.join("model.safetensors");
    let model_s = model.to_str().unwrap();
    ok(&invaders(&[
        "export",
        "--checkpoint",
        s(&run),
        "--out",
        model_s,
    ]));
    let size = std::fs::metadata(&model).unwrap().len();
    let full = std::fs::metadata(run.join("checkpoint.safetensors"))
        .unwrap()
        .len();
    assert!(
        size < full / 2,
        "the model ({size} B) holds one network of the checkpoint's ({full} B)"
    );
    fails_with(
        &invaders(&["export", "--checkpoint", s(&run), "--out", model_s]),
        "exists",
    );
    // The same games from the model file and from the checkpoint.
    let play = |what: &str| {
        let text = ok(&invaders(&[
            "eval",
            "--checkpoint",
            what,
            "--episodes",
            "1",
            "--seed",
            "9",
            "--threads",
            "1",
        ]));
        text.lines()
            .find(|l| l.starts_with("episode"))
            .unwrap()
            .to_string()
    };
    assert_eq!(play(model_s), play(s(&run)));
    // A model file cannot continue a run.
    let resumed = root.join("resumed");
    std::fs::create_dir_all(&resumed).unwrap();
    std::fs::copy(&model, resumed.join("checkpoint.safetensors")).unwrap();
    fails_with(
        &invaders(&["train", "--resume", resumed.to_str().unwrap()]),
        "weights-only",
    );
    // The protocol: at least 100 episodes, never on the training seed, fixed ε and mode.
    fails_with(
        &invaders(&[
            "eval",
            "--checkpoint",
            model_s,
            "--protocol",
            "--episodes",
            "10",
        ]),
        "at least 100",
    );
    fails_with(
        &invaders(&["eval", "--checkpoint", model_s, "--protocol", "--seed", "3"]),
        "training seed",
    );
    let out = invaders(&[
        "eval",
        "--checkpoint",
        model_s,
        "--protocol",
        "--epsilon",
        "0.1",
    ]);
    assert!(!out.status.success(), "--protocol fixes epsilon");
    let _ = std::fs::remove_dir_all(&root);
}

/// The shipped players (`models/strong/`, `models/strong-v1/`, `models/every-8-cap/`, README
/// "Trained players") load and play on a fresh clone, by the file's own configuration; they hold
/// no training state, so `--resume` refuses them.
#[test]
fn the_shipped_model_plays() {
    let every_8_cap = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/models/every-8-cap/model.safetensors"
    );
    let strong_v1 = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/models/strong-v1/model.safetensors"
    );
    for model in [SHIPPED_MODEL, strong_v1, every_8_cap] {
        let text = ok(&invaders(&[
            "eval",
            "--checkpoint",
            model,
            "--episodes",
            "1",
            "--epsilon",
            "0.01",
            "--threads",
            "1",
        ]));
        assert!(text.contains("preset strong"), "{model}: {text}");
    }
    // The directory holds the model beside its config.toml: not a run stopped before its first
    // checkpoint, so not started again (which would clear its metrics.csv).
    let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/models/strong");
    let files = |d: &str| {
        let mut v: Vec<_> = std::fs::read_dir(d)
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        v.sort();
        v
    };
    let before = files(dir);
    let metrics = std::fs::read(format!("{dir}/metrics.csv")).unwrap();
    fails_with(
        &invaders(&["train", "--resume", dir]),
        "model.safetensors, which a run does not write",
    );
    assert_eq!(files(dir), before, "nothing written into {dir}");
    assert_eq!(
        std::fs::read(format!("{dir}/metrics.csv")).unwrap(),
        metrics
    );
}

/// A checkpoint records the kernels its run's products ran on; a run resumed where other
/// kernels run says that it continues, but not bit for bit, and one resumed where the same run
/// says nothing.
#[test]
fn a_resume_on_other_kernels_says_so() {
    let (root, cfg) = tmp_with("kernels", "tiny.toml", TINY);
    let run = root.join("run");
    ok(&train_command(cfg.to_str().unwrap(), 1, 2, &run)
        .env("INVADERS_NO_SIMD", "1")
        .output()
        .unwrap());
    let recorded = |run: &Path| {
        invaders::dqn::checkpoint::load(&run.join("checkpoint.safetensors"))
            .unwrap()
            .kernels
            .expect("a checkpoint records its kernels")
    };
    let then = recorded(&run);
    assert!(then.starts_with("portable"), "{then}");
    let here = invaders::ops::plan::kernels(invaders::ops::plan::Precision::F32);
    let note = "not bit for bit";
    let text = ok(&resume(&run, 3));
    if then == here {
        assert!(!text.contains(note), "{text}");
    } else {
        let said = format!("the kernels `{then}` ran, and `{here}` run here");
        assert!(text.contains(note) && text.contains(&said), "{text}");
    }
    assert_eq!(recorded(&run), here);
    let text = ok(&resume(&run, 4));
    assert!(!text.contains(note), "{text}");
    let _ = std::fs::remove_dir_all(&root);
}

/// `precision = "auto"` (the strong preset's) is resolved when a run starts, said, and recorded
/// in its config.toml: f32 or bf16, never `auto`, and f32 where bf16 products do not run
/// (`INVADERS_NO_BF16`); a resume keeps it.
#[test]
fn auto_precision_is_resolved_and_recorded() {
    let (root, cfg) = tmp_with(
        "auto-precision",
        "tiny.toml",
        "replay_capacity = 2000\nlearning_starts = 100\nbatch_size = 8\n[env]\nmax_episode_steps = 60\n",
    );
    for no_bf16 in [false, true] {
        let run = root.join(format!("run-{no_bf16}"));
        let mut cmd = bin();
        if no_bf16 {
            cmd.env("INVADERS_NO_BF16", "1");
        }
        let out = cmd
            .args([
                "train",
                "--preset",
                "strong",
                "--config",
                cfg.to_str().unwrap(),
            ])
            .args([
                "--episodes",
                "2",
                "--threads",
                "1",
                "--out",
                run.to_str().unwrap(),
            ])
            .output()
            .unwrap();
        let text = ok(&out);
        assert!(text.contains("precision auto: "), "{text}");
        let saved = std::fs::read_to_string(run.join("config.toml")).unwrap();
        let recorded = saved
            .lines()
            .find(|l| l.starts_with("precision = "))
            .unwrap()
            .to_string();
        assert!(
            recorded == "precision = \"f32\"" || recorded == "precision = \"bf16\"",
            "{recorded}"
        );
        if no_bf16 || !invaders::tensor::cpu::avx512_bf16() {
            assert_eq!(recorded, "precision = \"f32\"", "{text}");
        }
        ok(&resume(&run, 3));
        let again = std::fs::read_to_string(run.join("config.toml")).unwrap();
        assert!(
            again.contains(&recorded),
            "a resume keeps the resolved precision"
        );
    }
    let _ = std::fs::remove_dir_all(&root);
}
