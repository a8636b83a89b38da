//! The `invaders` command line; each subcommand lives in `src/cli/`.

mod cli;

/// Cache-line-aligned buffers for the kernels (`invaders::CacheAligned`): the library leaves
/// the allocator to the program.
#[global_allocator]
static GLOBAL: invaders::CacheAligned = invaders::CacheAligned;

use clap::Parser;

fn main() -> std::process::ExitCode {
    match cli::run(cli::Cli::parse()) {
        Ok(()) => std::process::ExitCode::SUCCESS,
        Err(e) if e.is::<cli::Interrupted>() => std::process::ExitCode::from(130),
        Err(e) => {
            // `{:#}` prints the error with its causes on one line, and no backtrace.
            eprintln!("error: {e:#}");
            std::process::ExitCode::FAILURE
        }
    }
}
