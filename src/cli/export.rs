//! `invaders export`: a run's trained player as a small weights-only model file.

use std::path::PathBuf;

use anyhow::Context;
use clap::Args;

use invaders::dqn::checkpoint;

#[derive(Debug, Args)]
pub struct ExportArgs {
    /// The run to export (`RUN_DIR/checkpoint.safetensors`, or the run directory), or a model
    /// (a model file, or a shipped model's folder such as models/strong).
    #[arg(long, value_name = "PATH")]
    checkpoint: PathBuf,
    /// The model file to write (format `invaders-model-1`: the online network, the run's
    /// configuration and counters). An existing file is refused unless --force, and replaced
    /// atomically; a symbolic link's target is written, a character device or FIFO written
    /// through (docs/runs.md, "Output files").
    #[arg(long, value_name = "FILE")]
    out: PathBuf,
    /// Replace an existing --out file.
    #[arg(long)]
    force: bool,
}

pub fn run(args: &ExportArgs) -> anyhow::Result<()> {
    let file = checkpoint::network_file(&args.checkpoint)?;
    let out = super::guard::OutputFile::check(&args.out, args.force, &[&file], "--out")?;
    // A model file (a shipped model's folder) is already what export writes: checked, then
    // written as it is.
    let (bytes, counters) = match checkpoint::read_model_file(&file)? {
        Some((raw, model)) => (raw, model.counters),
        None => {
            let ckpt = checkpoint::load(&file)?;
            let bytes = checkpoint::model_to_bytes(&ckpt.config, &ckpt.counters, &ckpt.learner)?;
            (bytes, ckpt.counters)
        }
    };
    out.write(&bytes)
        .with_context(|| format!("cannot export to {}", args.out.display()))?;
    out!(
        "wrote {} ({} bytes): the online network of {} after {} episodes, {} frames",
        args.out.display(),
        bytes.len(),
        file.display(),
        counters.episodes,
        counters.frames
    );
    Ok(())
}
