//! A hostile user against the files a run owns (split from `tests/hostile.rs` by concern): its
//! snapshot continued elsewhere while it writes, its `--keep` record, its sibling files named as
//! outputs, a torn `metrics.csv` row, a full disk. Each asserts a clear message, the exit code,
//! and that the run's files are as they were.

mod common;

use std::path::Path;

use common::cli::{bin, fails_with, invaders, ok, resume, resume_args, s, train_command, TINY};
use common::hostile::{
    files, keep_experiment, line_with, output_within, spawn_lines, tmp_run, train_strong, trained,
    two_configs, write_record,
};

fn inode(path: &Path) -> u64 {
    std::os::unix::fs::MetadataExt::ino(&std::fs::metadata(path).unwrap())
}

/// Row 1: a snapshot folder is written by one run only. While run A writes snapshots into S, a
/// second process that would continue S in place is refused (A holds S's lock), and where S is
/// replaced behind A's back all the same (a file system that locks do not reach), A notices
/// before its next write, says so, and writes nothing more there: S keeps what replaced it.
#[test]
fn a_snapshot_folder_is_written_by_its_own_run_only() {
    let (root, cfg, run) = tmp_run("snapshot-owner");
    let snap = root.join("snap");
    let mut cmd = train_command(&cfg, 1, 1_000_000, &run);
    cmd.arg("--snapshot").arg(&snap);
    let (mut a, mut lines) = spawn_lines(cmd);
    line_with(&mut lines, "ep 2 ");
    let mut second = bin();
    second.args(resume_args(&snap, 1_000_000));
    let err = fails_with(
        &output_within(second, 120),
        &["in use by another process", &format!("pid {}", a.id())],
    );
    assert!(!err.contains("training"), "{err}");
    // Replaced behind A's back: a new file (another inode) with a snapshot's bytes. A may be
    // writing its own at that very moment, so this is tried until A notices.
    let file = snap.join("checkpoint.safetensors");
    let mut noticed = None;
    'tries: for _ in 0..20 {
        let bytes = std::fs::read(&file).unwrap();
        let tmp = snap.join("elsewhere.tmp");
        std::fs::write(&tmp, &bytes).unwrap();
        std::fs::rename(&tmp, &file).unwrap();
        // The next two episodes' lines, or the warning among them.
        let mut episodes = 0;
        while episodes < 2 {
            let l = line_with(&mut lines, "");
            if l.contains("no longer holds") {
                noticed = Some(l);
                break 'tries;
            }
            episodes += usize::from(l.starts_with("ep "));
        }
    }
    let noticed = noticed.expect("the run notices that its snapshot was replaced");
    assert!(
        noticed.contains("writes no more snapshots there"),
        "{noticed}"
    );
    let (kept, ino) = (files(&snap), inode(&file));
    line_with(&mut lines, "ep ");
    line_with(&mut lines, "ep ");
    line_with(&mut lines, "ep ");
    assert_eq!(inode(&file), ino, "the run wrote no snapshot after");
    assert!(files(&snap) == kept, "the snapshot folder is left as it is");
    a.kill().unwrap();
    a.wait().unwrap();
    let _ = std::fs::remove_dir_all(&root);
}

/// Row 2: `experiment --keep` refuses a record of another configuration as `--out` refuses a run
/// directory of one, naming the keys, before anything trains; the record is left byte for byte.
#[test]
fn a_kept_record_is_replaced_only_by_its_own_configuration() {
    let (root, _, _) = tmp_run("keep-config");
    let (x, y) = two_configs(&root);
    let run = root.join("run");
    train_strong(&x, 400, &run);
    let keep = root.join("keep");
    let record = write_record(&keep, &run, TINY, ["10.0", "1.0", "5.0", "15.0"]);
    let before = files(&record);
    let out = root.join("exp");
    let args = keep_experiment(&y, &keep, &out);
    let err = fails_with(
        &invaders(&args),
        &["another configuration", "`gamma`", "strong-seed1"],
    );
    assert!(!err.contains("replaced when"), "{err}");
    assert!(files(&record) == before, "the record is left byte for byte");
    assert!(!out.join("strong-seed1.log").exists(), "nothing trained");
    let _ = std::fs::remove_dir_all(&root);
}

/// Row 3: no command writes over a file a run owns, `--force` or not, whether it exists or not;
/// another name in the run's folder is the user's.
#[test]
fn no_output_lands_on_a_file_of_a_run() {
    let (root, _, run) = trained("owned", 1);
    let events = std::fs::read_dir(&run)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .find(|n| n.starts_with("events.out.tfevents"))
        .expect("an event file");
    let before = files(&run);
    let owned = [
        "metrics.csv",
        "config.toml",
        "checkpoint.safetensors",
        "replay-1.safetensors",
        "replay-7.safetensors",
        "rewards.png",
        "continued.csv",
        "result.toml",
        ".lock",
        &events,
    ];
    for name in owned {
        let target = run.join(name);
        let t = s(&target);
        let checkpoint = s(&run);
        let cases: [Vec<&str>; 3] = [
            vec!["export", "--checkpoint", checkpoint, "--out", t, "--force"],
            vec![
                "eval",
                "--checkpoint",
                checkpoint,
                "--episodes",
                "1",
                "--gif",
                t,
                "--force",
            ],
            vec!["plot", checkpoint, "--out", t, "--force"],
        ];
        for args in cases {
            // The command's own input is refused as that; any other file of the run as the
            // run's.
            let err = fails_with(&invaders(&args), &[]);
            assert!(
                err.contains("belongs to the run") || err.contains("is the input"),
                "{args:?}: {err}"
            );
            assert!(!err.contains("episode 1"), "refused before any work: {err}");
        }
    }
    assert!(files(&run) == before, "the run's files are as they were");
    // Another name in the folder is fine.
    let model = run.join("model.safetensors");
    ok(&invaders(&[
        "export",
        "--checkpoint",
        s(&run),
        "--out",
        s(&model),
    ]));
    std::fs::remove_file(&model).unwrap();
    ok(&resume(&run, 2));
    let _ = std::fs::remove_dir_all(&root);
}

/// Row 4: a `metrics.csv` whose last line was cut short by an interrupted append (no newline,
/// too few fields) is cut back on resume with a note; other damage is refused with advice that
/// is true (no copy of the file exists to restore).
#[test]
fn a_torn_metrics_row_is_cut_back_on_resume() {
    let (root, _, run) = trained("torn", 2);
    let metrics = run.join("metrics.csv");
    let good = std::fs::read_to_string(&metrics).unwrap();
    std::fs::write(&metrics, format!("{good}3,84,840,")).unwrap();
    let said = ok(&resume(&run, 3));
    assert!(said.contains("cut short"), "{said}");
    let now = std::fs::read_to_string(&metrics).unwrap();
    assert!(now.starts_with(&good), "the whole rows are kept");
    assert_eq!(now.lines().count(), 4, "header and three episodes: {now}");
    assert!(now.ends_with('\n'));

    // A malformed row that is not a torn tail is refused by line, with advice that is true.
    let rows = std::fs::read_to_string(&metrics).unwrap();
    std::fs::write(&metrics, rows.replacen("\n1,", "\nx,", 1)).unwrap();
    let err = fails_with(
        &resume(&run, 4),
        &["line 2", "malformed", "move the file away"],
    );
    assert!(!err.contains("restore"), "no copy exists to restore: {err}");
    let _ = std::fs::remove_dir_all(&root);
}

/// `--snapshot FILE` where FILE is a file is refused before any folder is made or locked.
#[test]
fn a_snapshot_path_that_is_a_file_leaves_nothing() {
    let (root, cfg, run) = tmp_run("snapshot-file");
    let file = common::cli::write_file(&root, "notes.txt", "mine");
    let mut cmd = train_command(&cfg, 1, 1, &run);
    cmd.arg("--snapshot").arg(&file);
    fails_with(&output_within(cmd, 120), &["--snapshot", "is a file"]);
    assert!(!run.exists(), "no run folder is left");
    assert_eq!(std::fs::read_to_string(&file).unwrap(), "mine");
    let _ = std::fs::remove_dir_all(&root);
}

/// A full disk stops a run with a message that says so and what is kept, not the operating
/// system's error as a Rust value; the run then resumes. Needs a small tmpfs (root); skipped
/// where it cannot be mounted.
#[test]
fn a_full_disk_says_so_and_what_is_kept() {
    let (root, cfg, probe) = trained("full-disk", 1);
    let size = |n: &str| std::fs::metadata(probe.join(n)).unwrap().len();
    // Room for the first checkpoint and its replay file, not for the second replay file (twice
    // as long: two episodes of 50 steps).
    let room = size("checkpoint.safetensors") + size("replay-1.safetensors") + (160 << 10);
    let mnt = root.join("mnt");
    std::fs::create_dir_all(&mnt).unwrap();
    let mounted = std::process::Command::new("mount")
        .args(["-t", "tmpfs", "-o", &format!("size={}k", room >> 10)])
        .args(["tmpfs", s(&mnt)])
        .output()
        .is_ok_and(|o| o.status.success());
    if !mounted {
        eprintln!("skipped: cannot mount a tmpfs here");
        let _ = std::fs::remove_dir_all(&root);
        return;
    }
    let _unmount = Unmount(mnt.clone());
    let run = mnt.join("run");
    let cmd = train_command(&cfg, 1, 5, &run);
    let err = fails_with(
        &output_within(cmd, 300),
        &["the disk holding", "is full", "the checkpoint of episode 1"],
    );
    assert!(
        !err.contains("IoError") && !err.contains("os error"),
        "{err}"
    );
    let ckpt = invaders::dqn::checkpoint::load(&run.join("checkpoint.safetensors")).unwrap();
    assert_eq!(
        ckpt.counters.episodes, 1,
        "the last good checkpoint is kept"
    );
    drop(_unmount);
    let _ = std::fs::remove_dir_all(&root);
}

/// Unmounts on drop, so that a failing assertion leaves no mount behind.
struct Unmount(std::path::PathBuf);

impl Drop for Unmount {
    fn drop(&mut self) {
        let _ = std::process::Command::new("umount").arg(&self.0).status();
    }
}

/// An experiment's failing run is named once: "strong-seed1: the snapshot in …", not
/// "strong-seed1: strong-seed1: …".
#[test]
fn a_failing_run_is_named_once() {
    let (root, _, _) = tmp_run("name-once");
    let (x, y) = two_configs(&root);
    let keep = root.join("keep");
    let snap = keep.join("strong-seed1/snapshot");
    let mut cmd = bin();
    cmd.args(["train", "--preset", "strong", "--config", &x, "--seed", "1"])
        .args(["--frames", "400", "--threads", "1", "--out"])
        .arg(root.join("lost"))
        .arg("--snapshot")
        .arg(&snap);
    ok(&output_within(cmd, 300));
    let out = root.join("exp");
    let args = [
        "experiment",
        "strong",
        "--seeds",
        "1",
        "--frames",
        "800",
        "--threads",
        "1",
        "--config",
        &y,
        "--keep",
        s(&keep),
        "--out",
        s(&out),
    ];
    let err = fails_with(&invaders(&args), &["of another configuration", "`gamma`"]);
    assert_eq!(err.matches("strong-seed1: ").count(), 1, "{err}");
    assert!(
        !snap.join(".lock").exists(),
        "the snapshot's lock went with its run"
    );
    let _ = std::fs::remove_dir_all(&root);
}
