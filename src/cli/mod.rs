//! Subcommands of the `invaders` binary. Add a subcommand by adding a variant to [`Command`]
//! with its own `Args` struct in a file of this folder, and a line in [`run`].

use clap::{Parser, Subcommand};

mod bench;
mod eval;
mod experiment;
mod export;
mod guard;
mod plot;
mod show;
mod train;

pub use train::Interrupted;

/// A from-scratch DQN that learns Atari Space Invaders.
#[derive(Debug, Parser)]
#[command(name = "invaders", version, about)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

/// What to do.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Train a DQN headlessly, writing a run directory.
    Train(train::TrainArgs),
    /// Play episodes and print score statistics (mean, std, min, max).
    Eval(eval::EvalArgs),
    /// Write a run's trained network as a small weights-only model file, for `eval`.
    Export(export::ExportArgs),
    /// Draw the reward curves of one or more runs on one figure.
    Plot(plot::PlotArgs),
    /// Time the train step, acting, the emulator and end-to-end training.
    Bench(bench::BenchArgs),
    /// Draw what the network sees: a raw screen, its preprocessing, and each pipeline's stack.
    ShowPreprocessing(show::ShowArgs),
    /// Reproduce one of the article's experiments.
    #[command(subcommand)]
    Experiment(experiment::Experiment),
}

/// Runs the chosen subcommand.
pub fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Train(args) => train::run(&args),
        Command::Eval(args) => eval::run(&args),
        Command::Export(args) => export::run(&args),
        Command::Plot(args) => plot::run(&args),
        Command::Bench(args) => bench::run(&args),
        Command::ShowPreprocessing(args) => show::run(&args),
        Command::Experiment(e) => experiment::run(&e),
    }
}
