//! Stopping an experiment. Its child processes run in process groups of their own, so a Ctrl-C
//! at the terminal reaches this process alone, and it passes each Ctrl-C, SIGTERM or SIGHUP on to
//! every running child exactly once, as SIGTERM. A training takes the first as `train` takes a
//! Ctrl-C (it stops after the current episode, with a checkpoint) and a second as "stop at once"
//! (its last checkpoint is kept); an evaluation ends at once and is played again next time. On
//! Linux a child also gets SIGTERM if this process dies without passing anything on (SIGKILL,
//! the OOM killer). Ctrl-Z suspends this process only: its runs go on training.
//!
//! A signal to the experiment's process group (`kill -- -PGID`) reaches the experiment alone,
//! which passes it on once. A signal to every process at once (a service manager stopping a
//! whole control group) reaches each run twice, directly and passed on: the run then stops at
//! once and keeps its last periodic checkpoint.

use std::process::{Command, Output, Stdio};
use std::sync::{Mutex, MutexGuard};

struct State {
    /// Signals received so far.
    signals: u32,
    /// The children running now (process ids).
    children: Vec<u32>,
    /// Whether the handler is in place (else children stay in this process's group, where
    /// a terminal's Ctrl-C reaches them directly).
    caught: bool,
    /// Whether any child has started: before that, a signal ends the experiment at once
    /// (it may be blocked reading its `--config` from a FIFO).
    started: bool,
}

/// One lock for all of it, so that a child is started only while no stop has been asked
/// for, and every child on the list gets each signal once.
static STATE: Mutex<State> = Mutex::new(State {
    signals: 0,
    children: Vec::new(),
    caught: false,
    started: false,
});

fn state() -> MutexGuard<'static, State> {
    STATE.lock().unwrap_or_else(|e| e.into_inner())
}

fn term(pid: u32) {
    // SAFETY: `kill` touches no memory of ours. `pid` is a child not reaped yet (`run` takes
    // it off the list before it reaps it, and `catch` makes sure the system does not reap
    // it first), so it names that child and no other process.
    unsafe {
        libc::kill(pid as libc::pid_t, libc::SIGTERM);
    }
}

/// Installs the handler (once, before any child starts).
pub fn catch() {
    // SAFETY: setting a signal's disposition to the default touches no memory of ours. With
    // SIGCHLD ignored (a disposition `exec` keeps), the system would reap children itself.
    unsafe {
        libc::signal(libc::SIGCHLD, libc::SIG_DFL);
    }
    let set = ctrlc::set_handler(|| {
        // ctrlc runs this on a thread of its own, not in the signal handler: a lock is fine.
        let first = {
            let mut s = state();
            if !s.started {
                say!("\nstopped before any run started: nothing has changed");
                std::process::exit(130);
            }
            s.signals += 1;
            s.children.iter().copied().for_each(term);
            s.signals == 1
        };
        if first {
            say!(
                "\nstopping: the runs stop after their episode with a checkpoint; the same \
                 command continues them (Ctrl-C again to stop them at once)"
            );
        } else {
            say!("\nstopping the runs at once: each keeps its last checkpoint");
        }
    });
    match set {
        Ok(()) => state().caught = true,
        Err(e) => {
            say!("warning: a Ctrl-C will not reach the runs through the experiment ({e})")
        }
    }
}

/// Whether a Ctrl-C, SIGTERM or SIGHUP has arrived.
pub fn requested() -> bool {
    state().signals > 0
}

/// The error an experiment stopped by a signal returns (the program exits with 130).
pub fn stopped() -> anyhow::Error {
    say!("experiment stopped; run the same command again to continue it");
    super::Interrupted.into()
}

/// Runs `cmd` to its end where a stop reaches it (see the module), with no input, and
/// returns its status and whatever output was piped; `None` if a stop came before it could
/// start.
pub fn run(cmd: &mut Command) -> std::io::Result<Option<Output>> {
    use std::io::Read;
    let mut child = {
        let mut s = state();
        if s.signals > 0 {
            return Ok(None);
        }
        if s.caught {
            std::os::unix::process::CommandExt::process_group(cmd, 0);
        }
        die_with_parent(cmd);
        let child = cmd.stdin(Stdio::null()).spawn()?;
        s.started = true;
        s.children.push(child.id());
        child
    };
    let pid = child.id();
    fn drain(pipe: Option<impl Read>) -> Vec<u8> {
        let mut bytes = Vec::new();
        if let Some(mut pipe) = pipe {
            let _ = pipe.read_to_end(&mut bytes);
        }
        bytes
    }
    let (stdout, stderr) = (child.stdout.take(), child.stderr.take());
    std::thread::scope(|s| {
        let stdout = s.spawn(|| drain(stdout));
        let stderr = s.spawn(|| drain(stderr));
        // Wait for the child to end without reaping it (`WNOWAIT`): until `wait` below, its
        // process id stays its own, so the handler never signals a stranger.
        loop {
            // SAFETY: a zeroed `siginfo_t` (plain integers) is a valid value, and `info` is
            // a valid place for `waitid` to write one to.
            let rc = unsafe {
                let mut info: libc::siginfo_t = std::mem::zeroed();
                libc::waitid(
                    libc::P_PID,
                    pid as libc::id_t,
                    &mut info,
                    libc::WEXITED | libc::WNOWAIT,
                )
            };
            if rc == 0 || std::io::Error::last_os_error().kind() != std::io::ErrorKind::Interrupted
            {
                break;
            }
        }
        state().children.retain(|&p| p != pid);
        let status = child.wait()?;
        Ok(Some(Output {
            status,
            stdout: stdout.join().unwrap_or_default(),
            stderr: stderr.join().unwrap_or_default(),
        }))
    })
}

/// On Linux, SIGTERM to the child when the thread that started it ends: `run` waits for the
/// child on that thread, so only this process's death ends it first.
fn die_with_parent(cmd: &mut Command) {
    #[cfg(target_os = "linux")]
    {
        use std::os::unix::process::CommandExt;
        let parent = std::process::id();
        // SAFETY: between fork and exec the closure calls only `prctl` and `getppid`, both
        // async-signal-safe, and allocates nothing.
        unsafe {
            cmd.pre_exec(move || {
                libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGTERM);
                // The parent may have died before the request was made.
                if libc::getppid() as u32 != parent {
                    return Err(std::io::Error::from_raw_os_error(libc::ESRCH));
                }
                Ok(())
            });
        }
    }
    #[cfg(not(target_os = "linux"))]
    let _ = cmd;
}
