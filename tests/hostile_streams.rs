//! The program tried as a careless or hostile user would, on its streams and files: an output
//! file is replaced whole or written through (a FIFO, a device), never destroyed; a closed or
//! failing stream costs no work; an input without end does not hang. (Split from
//! `tests/hostile.rs`.)

mod common;

use std::os::unix::process::CommandExt;
use std::path::Path;
use std::process::Stdio;

use common::cli::{bin, fails_with, invaders, ok, s, train_command};
use common::hostile::{
    config, eval_gif, no_periodic_checkpoint, read_all, run_within, sigterm, spawn_train, tmp,
    tmp_config, trained, wait_at_most, wait_for_line, FAST,
};

fn mkfifo(path: &Path) {
    let c = std::ffi::CString::new(path.as_os_str().as_encoded_bytes()).unwrap();
    // SAFETY: `c` is a NUL-terminated path.
    assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0, "mkfifo");
}

/// A device node (`S_IFCHR` or `S_IFBLK`, major and minor numbers) in a temporary directory, if
/// this process may make one (root, or CAP_MKNOD).
fn mknod(path: &Path, kind: libc::mode_t, major: u32, minor: u32) -> bool {
    let c = std::ffi::CString::new(path.as_os_str().as_encoded_bytes()).unwrap();
    // SAFETY: `c` is a NUL-terminated path.
    unsafe { libc::mknod(c.as_ptr(), kind | 0o600, libc::makedev(major, minor)) == 0 }
}

fn inode(path: &Path) -> u64 {
    std::os::unix::fs::MetadataExt::ino(&std::fs::metadata(path).unwrap())
}

fn no_temporary_files(dir: &Path) {
    for e in std::fs::read_dir(dir).unwrap() {
        let name = e.unwrap().file_name().to_string_lossy().into_owned();
        assert!(
            !name.contains(".tmp"),
            "temporary file left in {}: {name}",
            dir.display()
        );
    }
}

/// Class 1: one mechanism for every output file. A regular file is replaced whole (a new file
/// renamed over it, never rewritten in place); a symbolic link keeps being a link to the new
/// file; a character device or a FIFO is written through, never replaced; a FIFO nobody reads, a
/// block device and a socket are refused. (`eval --gif` and `plot --out` stand for every output
/// flag: they share `OutputFile`.)
#[test]
fn an_output_file_is_replaced_whole_or_written_through_never_destroyed() {
    use std::os::unix::fs::FileTypeExt;
    let (root, _, run) = trained("outputs", 1);

    // A plot over an existing file: a new file takes its place (another inode), nothing left.
    let png = root.join("curve.png");
    ok(&invaders(&["plot", s(&run), "--out", s(&png)]));
    let before = inode(&png);
    ok(&invaders(&["plot", s(&run), "--out", s(&png), "--force"]));
    assert_ne!(
        inode(&png),
        before,
        "plot --force rewrote the old file in place"
    );
    no_temporary_files(&root);

    // A symbolic link: its target is replaced, the link stays.
    let target = root.join("target.gif");
    std::fs::write(&target, b"old").unwrap();
    let link = root.join("link.gif");
    std::os::unix::fs::symlink(&target, &link).unwrap();
    ok(&eval_gif(&run, &link, &["--force"]));
    assert!(std::fs::symlink_metadata(&link)
        .unwrap()
        .file_type()
        .is_symlink());
    assert!(std::fs::read(&target).unwrap().starts_with(b"GIF89a"));
    let dangling = root.join("dangling.gif");
    std::os::unix::fs::symlink(root.join("nothing"), &dangling).unwrap();
    fails_with(
        &eval_gif(&run, &dangling, &[]),
        &["symbolic link to nothing"],
    );

    // A FIFO with a reader gets the GIF; one with no reader is an error, not a hang.
    let fifo = root.join("pipe.gif");
    mkfifo(&fifo);
    let reader = {
        let fifo = fifo.clone();
        std::thread::spawn(move || std::fs::read(fifo).unwrap())
    };
    ok(&eval_gif(&run, &fifo, &[]));
    assert!(reader.join().unwrap().starts_with(b"GIF89a"));
    assert!(std::fs::metadata(&fifo).unwrap().file_type().is_fifo());
    let (status, err) = run_within(
        &[
            "eval",
            "--checkpoint",
            s(&run),
            "--episodes",
            "1",
            "--gif",
            s(&fifo),
        ],
        false,
        60,
    );
    assert_eq!(status.code(), Some(1), "{err}");
    assert!(err.contains("no process is reading"), "{err}");
    assert!(std::fs::metadata(&fifo).unwrap().file_type().is_fifo());

    // /dev/null is written through and stays a device.
    ok(&eval_gif(&run, Path::new("/dev/null"), &["--force"]));
    assert!(std::fs::metadata("/dev/null")
        .unwrap()
        .file_type()
        .is_char_device());

    // Device nodes made here (as root): a character device like /dev/null is written through
    // with or without --force, a block device refused (a loop device's numbers; never opened).
    let chr = root.join("null-like");
    if mknod(&chr, libc::S_IFCHR, 1, 3) {
        ok(&eval_gif(&run, &chr, &["--force"]));
        assert!(std::fs::metadata(&chr)
            .unwrap()
            .file_type()
            .is_char_device());
        let blk = root.join("block-like");
        assert!(mknod(&blk, libc::S_IFBLK, 7, 250));
        fails_with(&eval_gif(&run, &blk, &["--force"]), &["block device"]);
        assert!(std::fs::metadata(&blk)
            .unwrap()
            .file_type()
            .is_block_device());
    }
    let sock = root.join("socket");
    let _listener = std::os::unix::net::UnixListener::bind(&sock).unwrap();
    fails_with(
        &invaders(&["plot", s(&run), "--out", s(&sock), "--force"]),
        &["socket"],
    );
    no_temporary_files(&root);
    let _ = std::fs::remove_dir_all(&root);
}

/// Class 2: one mechanism for every output stream. Standard error closed, full, or a terminal
/// that goes away costs `train` nothing (a closing terminal stops it as a Ctrl-C does); `eval`
/// and `plot` into a closed pipe end quietly, by SIGPIPE, after writing their files; a full
/// standard output is a clear error.
#[test]
fn a_closed_or_failing_stream_costs_no_work() {
    use std::os::unix::process::ExitStatusExt;
    let (root, cfg) = tmp_config("streams", FAST);

    // train with stderr a pipe nobody reads, and with stderr /dev/full.
    for (name, closed) in [("closed", true), ("full", false)] {
        let run = root.join(name);
        let mut cmd = train_command(&cfg, 1, 3, &run);
        cmd.stdout(Stdio::null());
        if closed {
            cmd.stderr(Stdio::piped());
        } else {
            cmd.stderr(std::fs::File::create("/dev/full").unwrap());
        }
        let mut child = cmd.spawn().unwrap();
        drop(child.stderr.take()); // the reader leaves at once
        let status = wait_at_most(&mut child, 120, name);
        assert_eq!(
            status.code(),
            Some(0),
            "train with stderr {name}: {status:?}"
        );
        let ckpt = invaders::dqn::checkpoint::load(&run.join("checkpoint.safetensors")).unwrap();
        assert_eq!(ckpt.counters.episodes, 3, "train with stderr {name}");
    }
    let run = root.join("closed");

    // eval and plot into a pipe whose reader left: quiet, SIGPIPE, files written.
    let gif = root.join("play.gif");
    let (status, err) = run_within(
        &[
            "eval",
            "--checkpoint",
            s(&run),
            "--episodes",
            "3",
            "--gif",
            s(&gif),
        ],
        true,
        120,
    );
    assert_eq!(status.signal(), Some(libc::SIGPIPE), "{status:?}: {err}");
    assert!(err.is_empty(), "quiet: {err}");
    assert!(std::fs::read(&gif).unwrap().starts_with(b"GIF89a"));
    let png = root.join("curve.png");
    let (status, err) = run_within(&["plot", s(&run), "--out", s(&png)], true, 60);
    assert_eq!(status.signal(), Some(libc::SIGPIPE), "{status:?}: {err}");
    assert!(err.is_empty(), "quiet: {err}");
    assert!(png.is_file());

    // A full standard output loses the results: a clear error.
    let out = bin()
        .args(["eval", "--checkpoint", s(&run), "--episodes", "1"])
        .stdout(std::fs::File::create("/dev/full").unwrap())
        .output()
        .unwrap();
    fails_with(&out, &["cannot write to standard output"]);

    // A terminal that closes under `train`: SIGHUP, then every write fails (EIO). The run stops
    // after its episode with a checkpoint and exits with 130, as for a Ctrl-C.
    let (mut master, mut slave) = (0, 0);
    // SAFETY: two valid places for the descriptors; no name, settings or size.
    let rc = unsafe {
        libc::openpty(
            &mut master,
            &mut slave,
            std::ptr::null_mut(),
            std::ptr::null(),
            std::ptr::null(),
        )
    };
    assert_eq!(rc, 0, "openpty");
    // Neither side may leak into a child: a child holding the master would keep the terminal up.
    for fd in [master, slave] {
        // SAFETY: `fd` is open; F_SETFD touches no memory.
        unsafe { libc::fcntl(fd, libc::F_SETFD, libc::FD_CLOEXEC) };
    }
    let tty = root.join("tty");
    let no_periodic = config(&root, &no_periodic_checkpoint());
    let mut cmd = train_command(&no_periodic, 2, 1_000_000, &tty);
    // SAFETY: `slave` is an open descriptor; dup gives each stream its own.
    unsafe {
        use std::os::fd::FromRawFd;
        cmd.stdin(Stdio::from_raw_fd(libc::dup(slave)))
            .stdout(Stdio::from_raw_fd(libc::dup(slave)))
            .stderr(Stdio::from_raw_fd(libc::dup(slave)));
        // A session of its own with the terminal as its controlling terminal, as a login shell's.
        cmd.pre_exec(|| {
            if libc::setsid() < 0 || libc::ioctl(0, libc::TIOCSCTTY, 0) < 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
        libc::close(slave);
    }
    let mut child = cmd.spawn().unwrap();
    // Drain the terminal (the progress bar) until the run has finished two episodes, then close
    // its master side: the terminal goes away (the kernel hangs up the session).
    let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let drain = {
        let stop = stop.clone();
        std::thread::spawn(move || {
            let mut buf = [0u8; 4096];
            while !stop.load(std::sync::atomic::Ordering::SeqCst) {
                let mut fds = libc::pollfd {
                    fd: master,
                    events: libc::POLLIN,
                    revents: 0,
                };
                // SAFETY: one valid pollfd; `master` is open until this thread closes it, and
                // `buf` is valid for writes of its length.
                unsafe {
                    if libc::poll(&mut fds, 1, 50) > 0
                        && libc::read(master, buf.as_mut_ptr().cast(), buf.len()) <= 0
                    {
                        break;
                    }
                }
            }
            // SAFETY: the descriptor is this thread's to close.
            unsafe { libc::close(master) };
        })
    };
    let metrics = tty.join("metrics.csv");
    let started = std::time::Instant::now();
    while std::fs::read_to_string(&metrics).map_or(0, |t| t.lines().count()) < 3 {
        assert!(started.elapsed().as_secs() < 120, "the run never trained");
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    stop.store(true, std::sync::atomic::Ordering::SeqCst);
    drain.join().unwrap();
    let status = wait_at_most(&mut child, 120, "train after its terminal closed");
    assert_eq!(status.code(), Some(130), "{status:?}");
    let ckpt = invaders::dqn::checkpoint::load(&tty.join("checkpoint.safetensors")).unwrap();
    let rows = std::fs::read_to_string(&metrics).unwrap().lines().count() as u64 - 1;
    assert!(ckpt.counters.episodes >= 2, "the episodes played are kept");
    assert_eq!(
        ckpt.counters.episodes, rows,
        "the checkpoint holds every episode recorded"
    );
    let _ = std::fs::remove_dir_all(&root);
}

/// Class 5: an input without end is an error (`/dev/zero`), or, where it may legitimately be a
/// stream (a FIFO), waits only until a signal: the first SIGTERM then stops the program at once,
/// saying nothing was changed. The second signal of a run says truly whether a checkpoint is kept.
#[test]
fn an_input_without_end_does_not_hang() {
    let root = tmp("endless");
    let zero = root.join("zero");
    let (status, err) = run_within(
        &["train", "--config", "/dev/zero", "--out", s(&zero)],
        false,
        30,
    );
    assert_eq!(status.code(), Some(1), "{err}");
    assert!(err.contains("larger than"), "{err}");

    let fifo = root.join("config.fifo");
    mkfifo(&fifo);
    // A writer that never closes: opened read-write so the open itself does not block.
    let _writer = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .open(&fifo)
        .unwrap();
    let mut child = bin()
        .args([
            "train",
            "--config",
            s(&fifo),
            "--out",
            s(&root.join("fifo")),
        ])
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    std::thread::sleep(std::time::Duration::from_millis(500));
    assert!(
        child.try_wait().unwrap().is_none(),
        "it waits for the writer"
    );
    sigterm(&child);
    let status = wait_at_most(&mut child, 10, "train on a FIFO config after SIGTERM");
    let err = read_all(child.stderr.take());
    assert_eq!(status.code(), Some(130), "{err}");
    assert!(err.contains("stopped before the first episode"), "{err}");

    // Two signals during a run that has no checkpoint yet: the message says so (or, if the
    // first signal's checkpoint came between them, names it).
    let cfg = config(&root, &no_periodic_checkpoint());
    let run = root.join("run");
    let (mut child, mut lines) = spawn_train(&cfg, 3, 1_000_000, &run);
    wait_for_line(&mut lines, "ep 1 ");
    for _ in 0..2 {
        sigterm(&child);
    }
    let rest: Vec<String> = lines.map_while(Result::ok).collect();
    let status = wait_at_most(&mut child, 30, "train after two SIGTERMs");
    assert_eq!(status.code(), Some(130), "{rest:?}");
    let said = rest.join("\n");
    if run.join("checkpoint.safetensors").exists() {
        assert!(
            said.contains("is kept") || said.contains("with a checkpoint"),
            "{said}"
        );
    } else {
        assert!(said.contains("no checkpoint was written yet"), "{said}");
        assert!(!said.contains("is kept"), "{said}");
    }
    let _ = std::fs::remove_dir_all(&root);

    // A run's replay file swapped for a FIFO is refused at once, not waited on; and a budget
    // already met is refused before the replay memory (gigabytes in a real run) is read.
    let (root, _, run) = trained("endless-replay", 1);
    let replay = run.join("replay-1.safetensors");
    std::fs::remove_file(&replay).unwrap();
    mkfifo(&replay);
    let (status, err) = run_within(
        &["train", "--resume", s(&run), "--episodes", "1"],
        false,
        30,
    );
    assert_eq!(status.code(), Some(1), "{err}");
    assert!(err.contains("has done 1 episodes"), "{err}");
    let (status, err) = run_within(
        &["train", "--resume", s(&run), "--episodes", "2"],
        false,
        30,
    );
    assert_eq!(status.code(), Some(1), "{err}");
    assert!(
        err.contains("replay-1.safetensors is not a regular file"),
        "{err}"
    );

    // A checkpoint or model that is a device, a FIFO or far larger than any checkpoint (a sparse
    // file: no disk used) is refused at once, not read without end or waited on.
    let fifo = root.join("model.fifo");
    mkfifo(&fifo);
    let huge = root.join("huge.safetensors");
    std::fs::File::create(&huge)
        .unwrap()
        .set_len(invaders::dqn::checkpoint::MAX_CHECKPOINT_BYTES + 1)
        .unwrap();
    for (path, needle) in [
        ("/dev/zero", "is not a regular file"),
        (s(&fifo), "is not a regular file"),
        (s(&huge), "is larger than 1024 MiB"),
    ] {
        for args in [
            vec!["eval", "--checkpoint", path, "--episodes", "1"],
            vec!["export", "--checkpoint", path, "--out", s(&root.join("m"))],
        ] {
            let (status, err) = run_within(&args, false, 30);
            assert_eq!(status.code(), Some(1), "{args:?}: {err}");
            assert!(err.contains(needle), "{args:?}: {err}");
        }
    }
    let _ = std::fs::remove_dir_all(&root);
}
