//! The standard streams, written so that nothing that happens to them costs work or panics.
//!
//! Every line the program prints goes through [`say!`] (standard error: progress, warnings,
//! errors) or [`out!`] (standard output: results). `println!` and `eprintln!` panic when their
//! stream fails (a pipe whose reader left, `… | head`; a terminal that closed, EIO; `2>/dev/full`),
//! and a panic in `train` would lose every episode since the last checkpoint; the lints
//! `clippy::print_stdout` and `clippy::print_stderr` keep them out of the program.
//!
//! - **Standard error** is for people: a failed write is dropped, and the program goes on.
//!   `train` keeps training when its terminal or log pipe goes away (a closing terminal also
//!   sends SIGHUP, which `train` takes as a Ctrl-C: it finishes the episode, checkpoints and
//!   exits with 130).
//! - **Standard output** carries results. The first failed write stops every later one and is
//!   remembered; a command whose only product is its output (`eval` without `--gif`) checks
//!   [`stdout_lost`] and stops early. At the end, [`finish`] ends the program as a Unix tool
//!   does: a reader that left (EPIPE, `eval … | head -1`) ends it quietly, by SIGPIPE, after the
//!   files it was asked to write are written; any other failure (`>/dev/full`) is an error, exit
//!   code 1.

use std::fmt;
use std::io::Write;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Mutex;

/// Whether a write to standard output has failed (no later write is tried).
static STDOUT_LOST: AtomicBool = AtomicBool::new(false);
/// The first failure of standard output other than a reader that left, as text.
static STDOUT_ERROR: Mutex<Option<String>> = Mutex::new(None);

/// Writes one line to standard error, whatever becomes of it (see the module).
pub fn err_line(args: fmt::Arguments<'_>) {
    let mut e = std::io::stderr().lock();
    let _ = e.write_fmt(args).and_then(|()| e.write_all(b"\n"));
}

/// Writes one line to standard output, unless it has failed before (see the module).
pub fn out_line(args: fmt::Arguments<'_>) {
    if STDOUT_LOST.load(Ordering::SeqCst) {
        return;
    }
    let mut o = std::io::stdout().lock();
    let written = o
        .write_fmt(args)
        .and_then(|()| o.write_all(b"\n"))
        .and_then(|()| o.flush());
    if let Err(e) = written {
        lose_stdout(e);
    }
}

fn lose_stdout(e: std::io::Error) {
    STDOUT_LOST.store(true, Ordering::SeqCst);
    if e.kind() != std::io::ErrorKind::BrokenPipe {
        let mut slot = STDOUT_ERROR.lock().unwrap_or_else(|p| p.into_inner());
        slot.get_or_insert_with(|| e.to_string());
    }
}

/// Whether standard output has failed: what is printed from now on reaches nobody.
pub fn stdout_lost() -> bool {
    STDOUT_LOST.load(Ordering::SeqCst)
}

/// The end of a command that succeeded: `Ok` if standard output took everything; an error if it
/// failed otherwise than by its reader leaving; and if its reader left (EPIPE), the program ends
/// here, quietly, by SIGPIPE, as `cat` or `yes` would.
pub fn finish() -> anyhow::Result<()> {
    if !STDOUT_LOST.load(Ordering::SeqCst) {
        if let Err(e) = std::io::stdout().lock().flush() {
            lose_stdout(e);
        }
    }
    if !STDOUT_LOST.load(Ordering::SeqCst) {
        return Ok(());
    }
    let error = STDOUT_ERROR
        .lock()
        .unwrap_or_else(|p| p.into_inner())
        .clone();
    match error {
        Some(e) => anyhow::bail!("cannot write to standard output: {e}"),
        None => die_by_sigpipe(),
    }
}

/// Ends the process by SIGPIPE, its default action restored (Rust starts programs with it
/// ignored, so that writes fail with EPIPE instead).
fn die_by_sigpipe() -> ! {
    #[cfg(unix)]
    // SAFETY: restoring a signal's default disposition and raising it touch no memory of ours.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
        libc::raise(libc::SIGPIPE);
    }
    // Where SIGPIPE does not end a process: the shell's code for it.
    std::process::exit(128 + 13)
}
