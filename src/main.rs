//! The `invaders` command line; each subcommand lives in `src/cli/`.

// Every line goes through `say!` and `out!` (src/cli/streams.rs), which never panic: a closed
// pipe or terminal must not cost a run its work.
#![deny(clippy::print_stdout, clippy::print_stderr)]

mod cli;

/// Cache-line-aligned buffers for the kernels (`invaders::CacheAligned`): the library leaves
/// the allocator to the program.
#[global_allocator]
static GLOBAL: invaders::CacheAligned = invaders::CacheAligned;

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
