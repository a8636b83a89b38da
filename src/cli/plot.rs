//! `invaders plot`: several runs' reward curves on one figure (the article's comparison).

use std::path::PathBuf;

use anyhow::{bail, Context};
use clap::Args;

use super::figures::{
    grid_step, mean_band_frames, plot_groups_frames, plot_rewards, read_frame_metrics,
    read_metrics, read_references, Curve, Group,
};

#[derive(Debug, Args)]
pub struct PlotArgs {
    /// Run directories (each with a metrics.csv), one curve each against episodes.
    #[arg(
        value_name = "RUN_DIR",
        required_unless_present = "group",
        conflicts_with = "group"
    )]
    runs: Vec<PathBuf>,
    /// Instead: seeds of one configuration, `LABEL=DIR,DIR,...`, drawn against emulator frames
    /// as their mean with a min-max band (repeat for several configurations).
    #[arg(long, value_name = "LABEL=DIRS")]
    group: Vec<String>,
    /// With --group: published curves to draw too, a CSV with the header `agent,frames,score`
    /// (docs/strong/dopamine-spaceinvaders.csv).
    #[arg(long, value_name = "FILE.csv", requires = "group")]
    reference: Option<PathBuf>,
    /// With --reference: the agents to draw, comma-separated [default: all].
    #[arg(
        long,
        value_name = "NAMES",
        requires = "reference",
        value_delimiter = ','
    )]
    agents: Vec<String>,
    /// The PNG to write: an existing file is refused unless --force, and replaced atomically; a
    /// symbolic link's target is written, a character device or FIFO written through
    /// (docs/runs.md, "Output files").
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
    if !args.group.is_empty() {
        return plot_frames(args);
    }
    if args.reference.is_some() {
        bail!(
            "--reference draws published curves against emulator frames, which only --group plots: give the runs as --group LABEL=DIR,DIR,… (one LABEL=DIR per run will do)"
        );
    }
    let inputs: Vec<PathBuf> = args.runs.iter().map(|d| d.join("metrics.csv")).collect();
    let inputs: Vec<&std::path::Path> = inputs.iter().map(PathBuf::as_path).collect();
    let out = super::guard::OutputFile::check(&args.out, args.force, &inputs, "--out")?;
    check_png(&args.out)?;
    let mut curves = Vec::new();
    for dir in &args.runs {
        let csv = dir.join("metrics.csv");
        let points = nonempty(read_metrics(&csv)?, &csv, "its curve")?;
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
    out.write_with(|tmp| plot_rewards(&curves, &args.title, args.window, tmp))
        .with_context(|| format!("cannot draw {}", args.out.display()))?;
    out!("wrote {}", args.out.display());
    Ok(())
}

/// `points` of `csv`, refused when empty: `curve` (what they would draw) would be empty.
fn nonempty<P>(points: Vec<P>, csv: &std::path::Path, curve: &str) -> anyhow::Result<Vec<P>> {
    if points.is_empty() {
        bail!(
            "{} holds no finished episode: {curve} would be empty, so nothing is drawn",
            csv.display()
        );
    }
    Ok(points)
}

/// `--group`: seeds against emulator frames, with published references.
fn plot_frames(args: &PlotArgs) -> anyhow::Result<()> {
    let mut groups = Vec::new();
    let mut inputs = Vec::new();
    for spec in &args.group {
        let (label, dirs) = parse_group(spec)?;
        let mut seeds = Vec::new();
        for d in &dirs {
            let csv = d.join("metrics.csv");
            let points = nonempty(
                read_frame_metrics(&csv)?,
                &csv,
                &format!("group {label}'s curve"),
            )?;
            seeds.push(points);
            inputs.push(csv);
        }
        groups.push(Group { label, seeds });
    }
    // A figure without a curve is an error, not an image of axes.
    let step = grid_step(&groups);
    for g in &groups {
        if mean_band_frames(&g.seeds, args.window, step).is_empty() {
            bail!(
                "group {}: on a grid of {step} frames there is no point where each of its runs has finished an episode (a run of one episode gives none): its curve would be empty, so nothing is drawn",
                g.label
            );
        }
    }
    if let Some(r) = &args.reference {
        inputs.push(r.clone());
    }
    let paths: Vec<&std::path::Path> = inputs.iter().map(PathBuf::as_path).collect();
    let out = super::guard::OutputFile::check(&args.out, args.force, &paths, "--out")?;
    check_png(&args.out)?;
    let references = match &args.reference {
        Some(r) => read_references(r, &args.agents)?,
        None => Vec::new(),
    };
    out.write_with(|tmp| plot_groups_frames(&groups, &references, &args.title, args.window, tmp))
        .with_context(|| format!("cannot draw {}", args.out.display()))?;
    out!("wrote {}", args.out.display());
    Ok(())
}

/// `--group LABEL=DIR,DIR,...`: the label and the run directories.
pub(super) fn parse_group(spec: &str) -> anyhow::Result<(String, Vec<PathBuf>)> {
    let bad = || anyhow::anyhow!("--group takes LABEL=DIR,DIR,...; got `{spec}`");
    let (label, dirs) = spec.split_once('=').ok_or_else(bad)?;
    let dirs: Vec<PathBuf> = dirs
        .split(',')
        .filter(|d| !d.is_empty())
        .map(PathBuf::from)
        .collect();
    if label.is_empty() || dirs.is_empty() {
        return Err(bad());
    }
    Ok((label.to_string(), dirs))
}

/// Refuses an `--out` whose name does not end in `.png` (unless it is a character device or a
/// FIFO, written through): the figure is a PNG, and the image library picks the format by the
/// name.
fn check_png(out: &std::path::Path) -> anyhow::Result<()> {
    use std::os::unix::fs::FileTypeExt;
    let png = out
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("png"));
    let stream = std::fs::metadata(out).is_ok_and(|m| {
        let t = m.file_type();
        t.is_char_device() || t.is_fifo()
    });
    if !png && !stream {
        bail!(
            "--out {}: a plot is a PNG image; give a file name ending in .png",
            out.display()
        );
    }
    Ok(())
}
