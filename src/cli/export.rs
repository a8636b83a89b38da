//! `invaders export`: a run's trained player as a small weights-only model file.

use std::path::PathBuf;

use anyhow::Context;
use clap::Args;

use invaders::dqn::checkpoint;

#[derive(Debug, Args)]
pub struct ExportArgs {
    /// The run to export (`RUN_DIR/checkpoint.safetensors`, or the run directory).
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
    let file = if args.checkpoint.is_dir() {
        args.checkpoint.join(checkpoint::CHECKPOINT_FILE)
    } else {
        args.checkpoint.clone()
    };
    let out = super::guard::OutputFile::check(&args.out, args.force, &[&file], "--out")?;
    let ckpt = checkpoint::load(&file)?;
    let bytes = checkpoint::model_to_bytes(&ckpt.config, &ckpt.counters, &ckpt.learner)?;
    out.write(&bytes)
        .with_context(|| format!("cannot export to {}", args.out.display()))?;
    out!(
        "wrote {} ({} bytes): the online network of {} after {} episodes, {} frames",
        args.out.display(),
        bytes.len(),
        file.display(),
        ckpt.counters.episodes,
        ckpt.counters.frames
    );
    Ok(())
}
