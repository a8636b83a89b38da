//! Subcommands of the `invaders` binary. Add a subcommand by adding a variant to [`Command`]
//! with its own `Args` struct in a file of this folder, and a line in [`run`].

use anyhow::{bail, Context};
use clap::{Parser, Subcommand};

/// A line on standard error that never panics and never stops the program
/// ([`streams::err_line`]): every message goes through it.
macro_rules! say {
    ($($arg:tt)*) => {
        $crate::cli::streams::err_line(format_args!($($arg)*))
    };
}

/// A line on standard output that never panics ([`streams::out_line`]): every result goes
/// through it.
macro_rules! out {
    ($($arg:tt)*) => {
        $crate::cli::streams::out_line(format_args!($($arg)*))
    };
}

mod bench;
mod config_errors;
mod eval;
mod experiment;
mod export;
mod figures;
mod guard;
mod memory;
mod metrics_file;
mod plot;
mod returns;
mod rundir;
mod show;
mod snapshot;
pub mod streams;
mod train;

pub use config_errors::short_number;
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
    /// Print runs' training return at equal emulator frames, as a markdown table.
    Returns(returns::ReturnsArgs),
    /// Time the train step, acting, the emulator and end-to-end training.
    Bench(bench::BenchArgs),
    /// Draw what the network sees: a raw screen, its preprocessing, and each pipeline's stack.
    ShowPreprocessing(show::ShowArgs),
    /// Reproduce one of the article's experiments.
    #[command(subcommand)]
    Experiment(experiment::Experiment),
}

/// Runs a command's body on a rayon pool of its own with `threads` workers (default: one per
/// core); every kernel the body calls runs on that pool, not on rayon's global one.
///
/// The body runs *on* a worker, not beside the pool: a parallel loop called from outside would
/// hand its work over and sleep until it is done (two futex round trips per call, a tenth of a
/// batch-1 forward pass); from a worker it runs in place, helped by the others.
pub fn in_pool<R: Send>(
    threads: Option<usize>, body: impl FnOnce() -> anyhow::Result<R> + Send,
) -> anyhow::Result<R> {
    let mut builder = rayon::ThreadPoolBuilder::new().stack_size(8 << 20);
    if let Some(t) = threads {
        if !(1..=MAX_THREADS).contains(&t) {
            bail!("--threads must be in 1..={MAX_THREADS}, got {t}");
        }
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        if t > cores {
            say!(
                "warning: --threads {t} is more than the {cores} core(s) here: the threads take \
                 turns, and every product runs slower than on {cores} (a run is reproduced with \
                 its thread count, so this is allowed)"
            );
        }
        builder = builder.num_threads(t);
    }
    let pool = builder.build().context("cannot set up the thread pool")?;
    pool.install(body)
}

/// The most `--threads`: beyond any machine this program trains on (each thread's share of a
/// product must stay worth starting it).
pub const MAX_THREADS: usize = 256;

/// Says once, on stderr, when `precision` asks for bf16 on a CPU that cannot run it (its
/// products then run in f32: [`invaders::ops::plan::bf16_runs`]).
pub fn note_precision(precision: invaders::ops::plan::Precision) {
    use invaders::ops::plan::{bf16_runs, Precision};
    static NOTE: std::sync::Once = std::sync::Once::new();
    if precision == Precision::Bf16 && !bf16_runs(precision) {
        NOTE.call_once(|| {
            let why = invaders::tensor::cpu::why_no_bf16().unwrap_or_default();
            say!("note: bf16 asked for, but {why}: the products run in f32");
        });
    }
}

/// Runs the chosen subcommand.
pub fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Train(args) => train::run(&args),
        Command::Eval(args) => eval::run(&args),
        Command::Export(args) => export::run(&args),
        Command::Plot(args) => plot::run(&args),
        Command::Returns(args) => returns::run(&args),
        Command::Bench(args) => bench::run(&args),
        Command::ShowPreprocessing(args) => show::run(&args),
        Command::Experiment(e) => experiment::run(&e),
    }
}
