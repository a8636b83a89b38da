//! The `invaders` command line; each subcommand lives in `src/cli/`.

mod cli;

use clap::Parser;

fn main() -> anyhow::Result<()> {
    cli::run(cli::Cli::parse())
}
