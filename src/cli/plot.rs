//! `invaders plot`: several runs' reward curves on one figure (the article's comparison).

use std::path::PathBuf;

use anyhow::{bail, Context};
use clap::Args;

use invaders::plot::{plot_rewards, read_metrics, Curve};

#[derive(Debug, Args)]
pub struct PlotArgs {
    /// Run directories (each with a metrics.csv).
    #[arg(required = true, value_name = "RUN_DIR")]
    runs: Vec<PathBuf>,
    /// The PNG to write (an existing file is refused unless --force).
    #[arg(long, value_name = "FILE.png")]
    out: PathBuf,
    /// Replace an existing --out file.
    #[arg(long)]
    force: bool,
    /// Episodes in the moving average.
    #[arg(long, default_value_t = 100)]
    window: usize,
    /// The figure's title.
    #[arg(long, default_value = "Space Invaders: reward per episode")]
    title: String,
}

pub fn run(args: &PlotArgs) -> anyhow::Result<()> {
    if args.window == 0 {
        bail!("--window must be at least 1");
    }
    let inputs: Vec<PathBuf> = args.runs.iter().map(|d| d.join("metrics.csv")).collect();
    let inputs: Vec<&std::path::Path> = inputs.iter().map(PathBuf::as_path).collect();
    super::guard::check_output(&args.out, args.force, &inputs, "--out")?;
    let mut curves = Vec::new();
    for dir in &args.runs {
        let points = read_metrics(&dir.join("metrics.csv"))?;
        // Label a run by its preset (from config.toml) and directory name.
        let preset = std::fs::read_to_string(dir.join("config.toml"))
            .ok()
            .and_then(|t| t.parse::<toml::Table>().ok())
            .and_then(|t| t.get("preset").and_then(|v| v.as_str()).map(str::to_string));
        let name = dir
            .file_name()
            .map(|n| n.to_string_lossy().to_string())
            .unwrap_or_default();
        let label = match preset {
            Some(p) if !name.contains(&p) => format!("{p} ({name})"),
            _ => name,
        };
        curves.push(Curve { label, points });
    }
    plot_rewards(&curves, &args.title, args.window, &args.out)
        .with_context(|| format!("cannot draw {}", args.out.display()))?;
    println!("wrote {}", args.out.display());
    Ok(())
}
