//! TensorBoard event files beside `metrics.csv`: every scalar read back from the files equals the
//! record, for a fresh run and for one killed (SIGKILL) after a checkpoint and resumed, whose
//! replayed episodes must show once (TensorBoard's restart mark purges the orphans).

mod common;

use std::path::Path;
use std::process::Stdio;

use common::cli::{invaders, ok, resume, tmp_with_file, train, train_command};
use invaders::dqn::tensorboard::{event_files, read_scalars};

const FAST: &str = "learning_starts = 30\nreplay_capacity = 300\nbatch_size = 8\ncheckpoint_every = 2\nplot_every = 1000\n[env]\nmax_episode_steps = 50\n";

/// metrics.csv's rows as numbers, by column name.
fn metrics(dir: &Path) -> Vec<std::collections::HashMap<String, f64>> {
    let text = std::fs::read_to_string(dir.join("metrics.csv")).unwrap();
    let mut lines = text.lines();
    let header: Vec<String> = lines.next().unwrap().split(',').map(String::from).collect();
    lines
        .map(|l| {
            header
                .iter()
                .cloned()
                .zip(l.split(',').map(|v| v.parse::<f64>().unwrap()))
                .collect()
        })
        .collect()
}

/// Every tag that mirrors a column holds one point per row, at the row's agent step, equal to
/// the column (as f32; NaN where the row has NaN), in order.
fn events_match_metrics(dir: &Path) {
    let rows = metrics(dir);
    let tags = read_scalars(dir).unwrap();
    for (tag, column) in [
        ("episode/reward", "reward"),
        ("episode/length", "length"),
        ("episode/number", "episode"),
        ("episode/emulator_frames", "emulator_frames"),
        ("episode/epsilon", "epsilon"),
        ("train/mean_loss", "mean_loss"),
        ("train/mean_max_q", "mean_max_q"),
        ("time/wall_seconds", "wall_seconds"),
    ] {
        let points = tags.get(tag).unwrap_or_else(|| panic!("no tag {tag}"));
        assert_eq!(points.len(), rows.len(), "{tag}: one point per episode");
        for (p, row) in points.iter().zip(&rows) {
            assert_eq!(
                p.0 as f64, row["agent_steps"],
                "{tag}: the step is the agent step"
            );
            let want = row[column];
            let got = p.2 as f64;
            // metrics.csv prints ε, the loss and max-Q to 6 decimals, wall seconds to 3.
            let tol =
                1e-6 * want.abs().max(1.0) + if column == "wall_seconds" { 1e-3 } else { 1e-6 };
            assert!(
                (want.is_nan() && got.is_nan()) || (got - want).abs() <= tol,
                "{tag} at step {}: {got} vs {want}",
                p.0
            );
        }
    }
    for tag in ["train/learning_rate", "time/agent_steps_per_s"] {
        assert_eq!(tags[tag].len(), rows.len(), "{tag}");
    }
}

#[test]
fn event_files_agree_with_metrics_after_a_kill_and_a_resume() {
    let (root, cfg) = tmp_with_file("invaders-tb", "events", "fast.toml", FAST);
    let cfg = cfg.to_str().unwrap();
    // A fresh run.
    let fresh = root.join("fresh");
    ok(&train(cfg, 3, 5, &fresh));
    assert_eq!(event_files(&fresh).unwrap().len(), 1);
    events_match_metrics(&fresh);

    // Killed after its checkpoint of episode 2 while it plays on, then resumed to 6 episodes.
    let killed = root.join("killed");
    let mut child = train_command(cfg, 3, 1000, &killed)
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let started = std::time::Instant::now();
    // Episode 5 done: checkpoints at 2 and 4, and episode 5 played after the last.
    while std::fs::read_to_string(killed.join("metrics.csv")).map_or(0, |t| t.lines().count()) < 6 {
        assert!(started.elapsed().as_secs() < 120, "the run never trained");
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    child.kill().unwrap();
    child.wait().unwrap();
    let before = read_scalars(&killed).unwrap();
    ok(&resume(&killed, 6));
    assert_eq!(
        event_files(&killed).unwrap().len(),
        2,
        "one file per process"
    );
    events_match_metrics(&killed);
    // The same episodes as the fresh run's (the same seed), each once.
    let tags = read_scalars(&killed).unwrap();
    let steps: Vec<i64> = tags["episode/reward"].iter().map(|p| p.0).collect();
    assert!(
        steps.windows(2).all(|w| w[0] < w[1]),
        "each episode once: {steps:?}"
    );
    assert!(
        before["episode/reward"].len() > 4,
        "the killed process had logged past its checkpoint"
    );
    // Switched off: no event files.
    let off = root.join("off");
    let cfg_off = root.join("off.toml");
    std::fs::write(&cfg_off, format!("tensorboard = false\n{FAST}")).unwrap();
    ok(&invaders(&[
        "train",
        "--config",
        cfg_off.to_str().unwrap(),
        "--episodes",
        "1",
        "--threads",
        "1",
        "--out",
        off.to_str().unwrap(),
    ]));
    assert!(event_files(&off).unwrap().is_empty());
    let _ = std::fs::remove_dir_all(&root);
}
