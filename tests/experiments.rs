//! The experiments end to end at tiny budgets (`experiment strong`, `ablation`, `preprocessing`):
//! they train their runs, evaluate them, write tables and figures, keep records with `--keep`,
//! continue a run from its kept snapshot, and refuse bad input before training anything.
//! (Split from `tests/cli.rs`.)

mod common;

use common::cli::{
    experiment_args, fails_saying as fails_with, invaders, ok, row, run_owned, s, tmp_with_file,
    TINY,
};
use invaders::dqn::checkpoint;
use std::path::{Path, PathBuf};
use std::process::Command;

/// A new temporary directory named `name` holding `text` (a variant of [`TINY`]) in
/// `tiny.toml`: the directory, the file's path and that of an experiment in the directory.
fn tiny_experiment(name: &str, text: &str) -> (PathBuf, PathBuf, PathBuf) {
    let (root, cfg) = tmp_with_file("invaders-experiments", name, "tiny.toml", text);
    (root.clone(), cfg, root.join("exp"))
}

/// `experiment strong` end to end at a tiny budget: refuses a protocol below 100 episodes and a
/// bad reference file before training anything; trains the seeds, evaluates each by the
/// protocol and writes a table with each seed's frames, wall time, speed and score, the mean over
/// seeds, the command and the figure, also when its program's file is deleted while it runs; run
/// again, it trains and plays nothing and reports the same runs.
#[test]
fn experiment_strong_trains_evaluates_and_reports() {
    let (root, cfg, out) = tiny_experiment("experiment-strong", TINY);
    let flags = ["--seeds", "1", "--frames", "2000"];
    let base = experiment_args("strong", &flags, s(&cfg), s(&out));
    let with = |extra: &[&str]| -> Vec<String> {
        base.iter().chain(extra).map(|s| s.to_string()).collect()
    };
    fails_with(
        &run_owned(&with(&["--eval-episodes", "50"])),
        "at least 100 episodes",
    );
    fails_with(&run_owned(&with(&["--threads", "0"])), "--threads must be");
    let mut big = with(&[]);
    big[3] = "9223372036854775808".into(); // --seeds
    fails_with(&run_owned(&big), "at most 9223372036854775807");
    let bad = root.join("bad.csv");
    std::fs::write(&bad, "agent,frames\nx,1\n").unwrap();
    fails_with(
        &run_owned(&with(&["--reference", bad.to_str().unwrap()])),
        "agent,frames,score",
    );
    assert!(
        !out.join("strong-seed1").exists(),
        "nothing trained before the inputs are checked"
    );

    let reference = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/docs/strong/dopamine-spaceinvaders.csv"
    );
    // The defaults: two threads per run, as many runs at once as the cores hold. Started from a
    // copy of the program that is deleted as soon as it runs (as a `cargo build` replaces it
    // during an experiment of hours): its runs and evaluations still start.
    let args = with(&["--reference", reference, "--agents", "Dopamine DQN"]);
    let copy = root.join("invaders-copy");
    std::fs::copy(env!("CARGO_BIN_EXE_invaders"), &copy).unwrap();
    let child = Command::new(&copy)
        .args(&args)
        .env_remove("RUST_BACKTRACE")
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap(); // returns once the copy is executing
    std::fs::remove_file(&copy).unwrap();
    let first = ok(&child.wait_with_output().unwrap());
    let log = std::fs::read_to_string(out.join("strong-seed1.log")).unwrap();
    assert!(log.contains("on 2 thread(s)"), "{log}");
    let table = std::fs::read_to_string(out.join("results.md")).unwrap();
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let at_once = format!("2 thread(s) each, {} at a time", (cores / 2).max(1));
    assert!(table.contains(&at_once), "{table}");
    let row = row(&table, "1");
    let cells: Vec<&str> = row.split('|').map(str::trim).collect();
    let frames: u64 = cells[2].parse().unwrap();
    assert!((2000..2000 + 27_000 * 4).contains(&frames), "{row}");
    assert!(
        cells[4].parse::<f64>().unwrap() > 0.0,
        "agent steps/s: {row}"
    );
    assert!(
        cells[6].contains(" ± ") && cells[6].contains('–'),
        "protocol score: {row}"
    );
    assert!(
        table.contains("Mean protocol score over the seeds: "),
        "{table}"
    );
    assert!(
        table.contains("'Dopamine DQN'"),
        "the command, quoted as a shell takes it: {table}"
    );
    assert!(std::fs::metadata(out.join("rewards.png")).unwrap().len() > 1000);
    assert!(first.contains("strong-seed1: done"), "{first}");
    // Again: nothing to train or play (the evaluation is kept beside the run), the same report.
    assert!(out.join("strong-seed1.protocol").exists());
    let again = ok(&run_owned(&args));
    assert!(again.contains("strong-seed1: already trained"), "{again}");
    let table2 = std::fs::read_to_string(out.join("results.md")).unwrap();
    assert!(table2.contains(row), "{table2}");
    // A kept summary cut short is played again, not an error.
    let kept = out.join("strong-seed1.protocol");
    let text = std::fs::read_to_string(&kept).unwrap();
    std::fs::write(&kept, &text[..text.find('\n').unwrap() + 8]).unwrap();
    ok(&run_owned(&args));
    assert_eq!(std::fs::read_to_string(&kept).unwrap(), text);
    let _ = std::fs::remove_dir_all(&root);
}

/// `experiment strong --keep` where a run's directory is gone (another machine) but its record
/// folder holds a snapshot (as `train --snapshot` writes while the run trains): a damaged
/// snapshot is refused, saying what to do; a good one continues the run, which then trains to
/// its budget, is evaluated and recorded with the frames where it continued, its curve whole,
/// and the snapshot now its final network.
#[test]
fn experiment_continues_a_run_from_its_kept_snapshot() {
    let (root, cfg, out) = tiny_experiment(
        "experiment-snapshot",
        &format!("{TINY}checkpoint_every = 1\n"),
    );
    let keep = root.join("keep");
    let snap = keep.join("strong-seed1/snapshot");
    // The run on the machine that was lost: 1000 frames, snapshots into the record folder.
    let lost = root.join("lost");
    ok(&invaders(&[
        "train",
        "--preset",
        "strong",
        "--seed",
        "1",
        "--config",
        s(&cfg),
        "--frames",
        "1000",
        "--threads",
        "1",
        "--out",
        s(&lost),
        "--snapshot",
        s(&snap),
    ]));
    let before = checkpoint::load(&snap.join(checkpoint::CHECKPOINT_FILE)).unwrap();
    assert!(before.snapshot);
    // One episode more than the lost run trained (its budget ended with its first episode).
    let budget = (before.counters.frames + 1).to_string();
    let flags = [
        "--seeds",
        "1",
        "--frames",
        &budget,
        "--threads",
        "1",
        "--keep",
        s(&keep),
    ];
    let args = experiment_args("strong", &flags, s(&cfg), s(&out));
    // A damaged snapshot: refused before anything trains.
    let file = snap.join(checkpoint::CHECKPOINT_FILE);
    let good = std::fs::read(&file).unwrap();
    let mut bad = good.clone();
    let last = bad.len() - 1;
    bad[last] ^= 1;
    std::fs::write(&file, &bad).unwrap();
    fails_with(&invaders(&args), "snapshot cannot be used; delete");
    assert!(!out.join("strong-seed1/checkpoint.safetensors").exists());
    std::fs::write(&file, &good).unwrap();
    // A snapshot of another configuration than the experiment asks for: refused, kept.
    let other_cfg = root.join("other.toml");
    std::fs::write(
        &other_cfg,
        format!("{TINY}checkpoint_every = 1\ngamma = 0.98\n"),
    )
    .unwrap();
    fails_with(
        &invaders(&experiment_args("strong", &flags, s(&other_cfg), s(&out))),
        "of another configuration than this experiment asks for (`gamma`",
    );
    assert_eq!(std::fs::read(&file).unwrap(), good);
    let said = ok(&invaders(&args));
    assert!(said.contains("continued from its snapshot"), "{said}");
    let log = std::fs::read_to_string(out.join("strong-seed1.log")).unwrap();
    assert!(log.contains("holds a snapshot"), "{log}");
    let record = std::fs::read_to_string(keep.join("strong-seed1/result.toml")).unwrap();
    let at = before.counters.frames;
    assert!(
        record.contains(&format!("continued_from_snapshot = [{at}]")),
        "{record}"
    );
    let rows = |p: &Path| -> Vec<String> {
        std::fs::read_to_string(p.join("metrics.csv"))
            .unwrap()
            .lines()
            .map(|l| l.rsplit_once(',').unwrap().0.to_string())
            .collect()
    };
    let (first, whole) = (rows(&lost), rows(&keep.join("strong-seed1")));
    assert!(whole.len() > first.len());
    assert_eq!(whole[..first.len()], first[..]);
    let after = checkpoint::load(&snap.join(checkpoint::CHECKPOINT_FILE)).unwrap();
    assert!(after.snapshot && after.counters.frames > before.counters.frames);
    let _ = std::fs::remove_dir_all(&root);
}

/// `experiment ablation` end to end at a tiny budget, with two arms: an unknown arm, a seed or
/// budget TOML cannot hold, the protocol's own seed and a `--config` that already switches the
/// arm's component off are refused before anything is written;
/// each arm's config file is the overrides plus its own switch, and its run trains with it; the
/// table sets each arm against the preset, which is always trained; run again, nothing trains.
#[test]
fn experiment_ablation_trains_each_arm_and_compares_it_with_the_preset() {
    let (root, cfg, out) = tiny_experiment("experiment-ablation", TINY);
    let flags = ["--frames", "2000", "--arms", "no-dueling"];
    let args = experiment_args("ablation", &flags, s(&cfg), s(&out));
    let mut unknown = args.clone();
    unknown[5] = "no-such-arm";
    fails_with(
        &invaders(&unknown),
        "[possible values: strong, no-dueling, n-step-1",
    );
    let already = root.join("already.toml");
    std::fs::write(&already, format!("{TINY}dueling = false\n")).unwrap();
    let mut same = args.clone();
    same[7] = already.to_str().unwrap();
    fails_with(
        &invaders(&same),
        "arm `no-dueling` would not switch off the dueling head",
    );
    for (flag, value, needle) in [
        (
            "--seed",
            "9223372036854775808",
            "at most 9223372036854775807",
        ),
        (
            "--frames",
            "9223372036854775808",
            "at most 9223372036854775807",
        ),
        ("--seed", "1000000", "the seed the protocol plays on"),
    ] {
        let mut bad = args.to_vec();
        match bad.iter().position(|&a| a == flag) {
            Some(i) => bad[i + 1] = value,
            None => bad.extend([flag, value]),
        }
        fails_with(&invaders(&bad), needle);
    }
    assert!(
        !out.exists(),
        "nothing written before the inputs are checked"
    );

    let first = ok(&invaders(&args));
    assert!(first.contains("2 runs of 2000 frames (seed 1)"), "{first}");
    let arm_cfg = std::fs::read_to_string(out.join("no-dueling.toml")).unwrap();
    assert!(
        arm_cfg.contains("dueling = false") && arm_cfg.contains("batch_size = 8"),
        "{arm_cfg}"
    );
    let trained =
        |arm: &str| std::fs::read_to_string(out.join(format!("{arm}-seed1/config.toml"))).unwrap();
    assert!(trained("no-dueling").contains("dueling = false"));
    assert!(trained("strong").contains("dueling = true"));
    let log = std::fs::read_to_string(out.join("no-dueling-seed1.log")).unwrap();
    assert!(log.contains("on 1 thread(s)"), "{log}");
    let table = std::fs::read_to_string(out.join("results.md")).unwrap();
    let cells_of = |arm: &str| -> Vec<String> {
        let line = row(&table, arm);
        line.split('|').map(|c| c.trim().to_string()).collect()
    };
    let (preset, arm) = (cells_of("strong"), cells_of("no-dueling"));
    assert_eq!(preset[2], "nothing (the preset)");
    assert!(arm[2].starts_with("the dueling head"), "{arm:?}");
    assert_eq!((preset[7].as_str(), preset[9].as_str()), ("+0.0", "+0.0"));
    // Each Δ is the arm's figure less the preset's.
    let num = |s: &str| s.split_whitespace().next().unwrap().parse::<f64>().unwrap();
    let delta = num(&arm[6]) - num(&preset[6]);
    assert!(
        (num(&arm[7]) - delta).abs() < 0.11,
        "{arm:?} against {preset:?}"
    );
    let delta = num(&arm[8]) - num(&preset[8]);
    assert!(
        (num(&arm[9]) - delta).abs() < 0.11,
        "{arm:?} against {preset:?}"
    );
    assert!(arm[8].contains(" ± ") && arm[8].contains('–'), "{arm:?}");
    assert!(std::fs::metadata(out.join("rewards.png")).unwrap().len() > 1000);
    // Again: nothing to train or play, the same table.
    let again = ok(&invaders(&args));
    assert!(
        again.contains("no-dueling-seed1: already trained"),
        "{again}"
    );
    assert_eq!(
        std::fs::read_to_string(out.join("results.md")).unwrap(),
        table
    );

    // --keep: each finished run's record. With the run directories gone (another machine),
    // nothing trains or plays and the arms' rows are the same.
    let keep = root.join("keep");
    let with_keep: Vec<&str> = args
        .iter()
        .copied()
        .chain(["--keep", keep.to_str().unwrap()])
        .collect();
    let recorded = ok(&invaders(&with_keep));
    assert!(
        recorded.contains("no-dueling-seed1: recorded in"),
        "{recorded}"
    );
    for arm in ["strong", "no-dueling"] {
        for file in ["result.toml", "metrics.csv", "config.toml"] {
            let path = keep.join(format!("{arm}-seed1")).join(file);
            assert!(path.is_file(), "{}", path.display());
        }
    }
    let rows = |t: &str| -> Vec<String> {
        t.lines()
            .filter(|l| l.starts_with("| strong |") || l.starts_with("| no-dueling |"))
            .map(String::from)
            .collect()
    };
    assert_eq!(rows(&table).len(), 2);
    std::fs::remove_dir_all(&out).unwrap();
    let kept = ok(&invaders(&with_keep));
    assert!(
        kept.contains("strong-seed1: kept in") && kept.contains("no-dueling-seed1: kept in"),
        "{kept}"
    );
    assert!(!kept.contains(": training (log"), "nothing trains: {kept}");
    assert!(!out.join("strong-seed1").exists());
    let results = || std::fs::read_to_string(out.join("results.md")).unwrap();
    assert_eq!(rows(&results()), rows(&table));
    // A record of another question (here another seed) is not taken: that run trains and is
    // evaluated again (the same run: training is deterministic), and its record replaced.
    let record = keep.join("strong-seed1/result.toml");
    let text = std::fs::read_to_string(&record).unwrap();
    assert!(text.contains("\nseed = 1\n"), "{text}");
    std::fs::write(&record, text.replace("\nseed = 1\n", "\nseed = 7\n")).unwrap();
    let other = ok(&invaders(&with_keep));
    assert!(
        other.contains("strong-seed1: the record in") && other.contains("strong-seed1: training"),
        "{other}"
    );
    assert!(other.contains("no-dueling-seed1: kept in"), "{other}");
    // All but the wall time (and the speed drawn from it) is the same.
    let timeless = |t: &str| -> Vec<String> {
        t.lines()
            .filter(|l| !l.starts_with("wall_seconds"))
            .map(String::from)
            .collect()
    };
    let record_text = std::fs::read_to_string(&record).unwrap();
    assert_eq!(timeless(&record_text), timeless(&text));
    let cells = |rows: Vec<String>| -> Vec<Vec<String>> {
        rows.iter()
            .map(|r| {
                let mut c: Vec<String> = r.split('|').map(|c| c.trim().to_string()).collect();
                c.drain(4..6); // wall hours, agent steps/s
                c
            })
            .collect()
    };
    assert_eq!(cells(rows(&results())), cells(rows(&table)));
    // A file that is not a record is refused, saying what to do.
    std::fs::write(&record, "protocol = 3\n").unwrap();
    fails_with(&invaders(&with_keep), "is not a run's record; delete");
    let _ = std::fs::remove_dir_all(&root);
}

/// The article's experiment (issue 23's command) end to end at a toy budget: the three presets
/// and an extra pipeline trained, each evaluated both ways, the table and the figure (with the
/// notebook's digitised curve) written; a bad notebook file fails before anything trains, and
/// the command run again trains nothing.
#[test]
fn experiment_preprocessing_trains_evaluates_and_reports() {
    let (root, cfg, out) = tiny_experiment(
        "experiment-preprocessing",
        &format!("{TINY}[env]\nmax_episode_steps = 300\n"),
    );
    let notebook = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/docs/experiment/notebook/plot-digitized.csv"
    );
    let args = |nb: &str| -> Vec<String> {
        [
            "experiment",
            "preprocessing",
            "--episodes",
            "1",
            "--seeds",
            "1",
            "--eval-episodes",
            "1",
            "--pipeline",
            "stack-running-max",
            "--jobs",
            "2",
            "--config",
            s(&cfg),
            "--notebook",
            nb,
            "--out",
            s(&out),
        ]
        .iter()
        .map(|s| s.to_string())
        .collect()
    };
    let bad = root.join("bad.csv");
    std::fs::write(&bad, "episode,reward\n1,2\n").unwrap();
    fails_with(
        &run_owned(&args(bad.to_str().unwrap())),
        "the header must be",
    );
    assert!(!out.exists(), "nothing made before the inputs are checked");

    let first = ok(&run_owned(&args(notebook)));
    let table = std::fs::read_to_string(out.join("results.md")).unwrap();
    for arm in [
        "article-vanilla",
        "article",
        "article-as-written",
        "article+stack-running-max",
    ] {
        let row = row(&table, arm);
        let cells: Vec<&str> = row.split('|').map(str::trim).collect();
        assert_eq!(cells[2], "1", "seeds: {row}");
        for (i, what) in [(3, "training"), (4, "evaluation"), (5, "protocol")] {
            assert!(
                cells[i].parse::<f64>().is_ok_and(|v| v >= 0.0),
                "{what} score of {arm}: {row}"
            );
        }
        assert!(out.join(format!("{arm}-seed0.protocol")).exists(), "{arm}");
        // The other two tables, found after the first row: the stretch of episodes 1–1 (its
        // one episode's reward, the training column), then the run's own row.
        let rows: Vec<Vec<&str>> = table
            .lines()
            .filter(|l| l.starts_with(&format!("| {arm} | ")) && *l != row)
            .map(|l| l.split('|').map(str::trim).collect())
            .collect();
        assert_eq!(rows.len(), 2, "{arm}:\n{table}");
        assert_eq!(rows[0][2], cells[3], "stretch 1–1 of {arm}:\n{table}");
        let run: &[&str] = &rows[1];
        assert_eq!(run[2], "0", "seed of {arm}: {run:?}");
        assert!(run[3].parse::<u64>().is_ok_and(|s| s > 0), "{run:?}");
        assert_eq!(run[6], cells[3], "{run:?}");
        assert!(run[7].starts_with(&format!("{} ± ", cells[4])), "{run:?}");
        assert!(run[8].starts_with(&format!("{} ± ", cells[5])), "{run:?}");
    }
    assert!(
        table.contains("| configuration | 1–1 |\n| --- | --- |\n"),
        "{table}"
    );
    assert!(std::fs::metadata(out.join("rewards.png")).unwrap().len() > 1000);
    assert!(first.contains("article-seed0: done"), "{first}");
    let again = ok(&run_owned(&args(notebook)));
    assert!(again.contains("article-seed0: already trained"), "{again}");
    assert!(
        !again.contains(": training (log"),
        "nothing trains again: {again}"
    );
    assert_eq!(
        std::fs::read_to_string(out.join("results.md")).unwrap(),
        table
    );
    let _ = std::fs::remove_dir_all(&root);
}
