//! The `invaders` command line; each subcommand lives in `src/cli/`.

// Every line goes through `say!` and `out!` (src/cli/streams.rs), which never panic: a closed
// pipe or terminal must not cost a run its work.
#![deny(clippy::print_stdout, clippy::print_stderr)]

mod cli;

/// Cache-line-aligned buffers for the kernels (`invaders::CacheAligned`): the library leaves
/// the allocator to the program.
#[global_allocator]
static GLOBAL: OrExit = OrExit;

/// `invaders::CacheAligned`, where an allocation that fails ends the program with a message
/// and exit code 1 instead of Rust's abort (a backtrace and 134). Runs check their big
/// allocations against the memory they may use before they start (`src/cli/memory.rs`); this
/// is for whatever still fails (another process took the memory meanwhile, say). Nothing is
/// lost: a run's files are as its last checkpoint left them.
struct OrExit;

// SAFETY: every call forwards to `CacheAligned` with the same arguments; a null result ends
// the process instead of being returned.
unsafe impl std::alloc::GlobalAlloc for OrExit {
    unsafe fn alloc(&self, layout: std::alloc::Layout) -> *mut u8 {
        or_exit(invaders::CacheAligned.alloc(layout), layout.size())
    }

    unsafe fn alloc_zeroed(&self, layout: std::alloc::Layout) -> *mut u8 {
        or_exit(invaders::CacheAligned.alloc_zeroed(layout), layout.size())
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: std::alloc::Layout) {
        invaders::CacheAligned.dealloc(ptr, layout)
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: std::alloc::Layout, new: usize) -> *mut u8 {
        or_exit(invaders::CacheAligned.realloc(ptr, layout, new), new)
    }
}

/// `ptr`, unless it is null: then says that `size` bytes could not be allocated and exits with
/// 1, allocating nothing (the message is put together on the stack).
fn or_exit(ptr: *mut u8, size: usize) -> *mut u8 {
    if !ptr.is_null() {
        return ptr;
    }
    let mut buf = [0u8; 400];
    let mut len = 0;
    let mut put = |bytes: &[u8]| {
        let n = bytes.len().min(buf.len() - len);
        buf[len..len + n].copy_from_slice(&bytes[..n]);
        len += n;
    };
    put(b"error: out of memory: ");
    let mut digits = [0u8; 20];
    let (mut at, mut v) = (digits.len(), size);
    loop {
        at -= 1;
        digits[at] = b'0' + (v % 10) as u8;
        v /= 10;
        if v == 0 {
            break;
        }
    }
    put(&digits[at..]);
    put(
        b" bytes could not be allocated (a memory limit: ulimit -v, a cgroup, or the machine's \
          memory); a run's files are as its last checkpoint left them. Lower replay_capacity \
          (or PQN's games or rollout), or free memory\n",
    );
    // SAFETY: `buf[..len]` is initialised; write(2) and _exit(2) allocate nothing.
    unsafe {
        libc::write(2, buf.as_ptr().cast(), len);
        libc::_exit(1)
    }
}

use clap::Parser;

fn main() -> std::process::ExitCode {
    match cli::run(cli::Cli::parse()).and_then(|()| cli::streams::finish()) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) if e.is::<cli::Interrupted>() => std::process::ExitCode::from(130),
        Err(e) => {
            // `{:#}` prints the error with its causes on one line, and no backtrace.
            cli::streams::err_line(format_args!("error: {e:#}"));
            std::process::ExitCode::FAILURE
        }
    }
}
