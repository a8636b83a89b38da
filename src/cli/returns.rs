//! `invaders returns`: runs' training return at equal emulator frames, as a markdown table.
//!
//! The training return at `f` frames is the mean reward of the last `window` episodes that ended
//! at or before frame `f` (the episodes' rewards in `metrics.csv`, played at the run's ε, 0.01
//! for `strong` from its 100 000th agent step). A run that has not trained to `f` frames, or has
//! fewer than `window` episodes by then, has no value there: its cell is empty. The `end` row is
//! the last `window` episodes of the whole run. A row whose frames or reward is not a finite
//! number is left out, with a warning ([`read_frame_metrics`]), so the window reaches one episode
//! further back. The tables of training return in docs/strong.md come from this command
//! (reformatted).

use std::path::PathBuf;

use anyhow::{anyhow, bail};
use clap::Args;

use super::figures::read_frame_metrics;
use super::plot::parse_group;

#[derive(Debug, Args)]
pub struct ReturnsArgs {
    /// Run directories (each with a metrics.csv), a column each.
    #[arg(value_name = "RUN_DIR", required_unless_present = "group")]
    runs: Vec<PathBuf>,
    /// Seeds of one configuration, `LABEL=DIR,DIR,...`: a column of their mean (min–max), before
    /// the runs' own columns (repeat for several configurations).
    #[arg(long, value_name = "LABEL=DIRS")]
    group: Vec<String>,
    /// Emulator frames at which to read every run, comma-separated: `500000`, or in millions,
    /// `0.5M`. Without it, only the runs' ends.
    #[arg(long, value_name = "FRAMES", value_delimiter = ',', value_parser = parse_frames)]
    at: Vec<u64>,
    /// Episodes in each mean.
    #[arg(long, default_value_t = 100)]
    window: usize,
}

/// `500000`, `0.5M` or `0.5m`: a positive whole number of frames.
fn parse_frames(text: &str) -> Result<u64, String> {
    let bad = || format!("`{text}` is not a number of frames (say 500000 or 0.5M)");
    let frames = match text.strip_suffix(['M', 'm']) {
        // Millions: read as `{n}e6`, so the decimal is rounded once (1.001M is 1 001 000, where
        // 1.001 × 1e6 in binary would fall just short of it).
        Some(n) if !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit() || b == b'.') => {
            let value = format!("{n}e6").parse::<f64>().map_err(|_| bad())?;
            if value.fract() != 0.0 || value > (1u64 << 53) as f64 {
                return Err(bad());
            }
            value as u64
        }
        Some(_) => return Err(bad()),
        None => text.parse::<u64>().map_err(|_| bad())?,
    };
    if frames == 0 {
        return Err(format!("`{text}`: the frames must be at least 1"));
    }
    Ok(frames)
}

/// One column: a run, or a group of runs summarised by mean (min–max).
struct Column {
    label: String,
    /// Each run's `(emulator frames, reward)` per episode, in the order they were played.
    runs: Vec<Vec<(f64, f64)>>,
}

/// The mean reward of the last `window` episodes ending at or before `frames` (all of them when
/// `None`); `None` where the run stops short of `frames` or has fewer episodes than `window`.
fn return_at(episodes: &[(f64, f64)], frames: Option<u64>, window: usize) -> Option<f64> {
    let last = episodes.last()?.0;
    let upto = match frames {
        Some(f) if last < f as f64 => return None,
        Some(f) => episodes.partition_point(|&(x, _)| x <= f as f64),
        None => episodes.len(),
    };
    let seen = upto.checked_sub(window)?;
    Some(episodes[seen..upto].iter().map(|&(_, r)| r).sum::<f64>() / window as f64)
}

/// A cell: one run's value, or a group's mean (min–max) with `[k of n]` when only k of its n
/// runs have one.
fn cell(values: &[Option<f64>], decimals: usize) -> String {
    let have: Vec<f64> = values.iter().flatten().copied().collect();
    let Some(first) = have.first() else {
        return String::new();
    };
    let f = |v: f64| format!("{v:.decimals$}");
    let mut text = if have.len() == 1 {
        f(*first)
    } else {
        let mean = have.iter().sum::<f64>() / have.len() as f64;
        let (lo, hi) = have
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &v| {
                (lo.min(v), hi.max(v))
            });
        format!("{} ({}–{})", f(mean), f(lo), f(hi))
    };
    if values.len() > 1 && have.len() < values.len() {
        text += &format!(" [{} of {}]", have.len(), values.len());
    }
    text
}

pub fn run(args: &ReturnsArgs) -> anyhow::Result<()> {
    if args.window == 0 {
        bail!("--window must be at least 1");
    }
    let read = |dir: &PathBuf| {
        let episodes = read_frame_metrics(&dir.join("metrics.csv"))?;
        // Rows are appended as episodes end, so frames only grow; a file edited by hand might not.
        if let Some(i) = episodes.windows(2).position(|w| w[1].0 < w[0].0) {
            return Err(anyhow!(
                "{}: emulator_frames falls after data row {}: not a run's metrics in the order \
                 played",
                dir.join("metrics.csv").display(),
                i + 1
            ));
        }
        Ok(episodes)
    };
    let mut columns = Vec::new();
    for spec in &args.group {
        let (label, dirs) = parse_group(spec)?;
        let runs = dirs.iter().map(read).collect::<anyhow::Result<_>>()?;
        columns.push(Column { label, runs });
    }
    for dir in &args.runs {
        columns.push(Column {
            label: dir.display().to_string(),
            runs: vec![read(dir)?],
        });
    }

    let row = |first: String, cells: Vec<String>| format!("| {first} | {} |", cells.join(" | "));
    // A `|` in a label would end its cell.
    let labels = columns
        .iter()
        .map(|c| c.label.replace('|', "\\|"))
        .collect();
    out!("{}", row("frames".into(), labels));
    out!("{}", row("---".into(), vec!["---".into(); columns.len()]));
    let at = |frames: Option<u64>, decimals: usize| -> Vec<String> {
        let values = |c: &Column| -> Vec<Option<f64>> {
            c.runs
                .iter()
                .map(|r| return_at(r, frames, args.window))
                .collect()
        };
        columns.iter().map(|c| cell(&values(c), decimals)).collect()
    };
    for &f in &args.at {
        out!("{}", row(format!("{} M", f as f64 / 1e6), at(Some(f), 0)));
    }
    out!(
        "{}",
        row(format!("end (last {})", args.window), at(None, 1))
    );
    let ends = columns
        .iter()
        .map(|c| {
            let frames: Vec<String> = c
                .runs
                .iter()
                .map(|r| r.last().map_or("none".into(), |p| format!("{}", p.0)))
                .collect();
            frames.join(", ")
        })
        .collect();
    out!("{}", row("frames at the end".into(), ends));
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_parse_in_units_and_millions() {
        assert_eq!(parse_frames("500000"), Ok(500_000));
        assert_eq!(parse_frames("0.5M"), Ok(500_000));
        assert_eq!(parse_frames("1.25m"), Ok(1_250_000));
        assert_eq!(parse_frames("1.001M"), Ok(1_001_000));
        assert_eq!(parse_frames("9007199254740993"), Ok(9_007_199_254_740_993));
        for bad in [
            "",
            "M",
            "-1",
            "0",
            "0M",
            "0.5",
            "0.0000001M",
            "1e3M",
            "1e400",
            "nan",
            "1.5x",
            "-1M",
        ] {
            assert!(parse_frames(bad).is_err(), "{bad} accepted");
        }
    }

    #[test]
    fn a_return_is_the_last_window_episodes_up_to_the_frames() {
        // Episode i ends at 1 000·i frames with reward i.
        let run: Vec<(f64, f64)> = (1..=10).map(|i| (1000.0 * i as f64, i as f64)).collect();
        assert_eq!(return_at(&run, Some(5000), 3), Some(4.0));
        assert_eq!(return_at(&run, Some(5999), 3), Some(4.0));
        assert_eq!(return_at(&run, Some(3000), 3), Some(2.0));
        assert_eq!(return_at(&run, Some(2000), 3), None, "two episodes only");
        assert_eq!(
            return_at(&run, Some(10_001), 3),
            None,
            "not trained that far"
        );
        assert_eq!(return_at(&run, Some(10_000), 3), Some(9.0));
        assert_eq!(return_at(&run, None, 4), Some(8.5));
        assert_eq!(return_at(&[], None, 1), None);
    }

    #[test]
    fn a_group_cell_gives_mean_min_max_and_what_is_missing() {
        assert_eq!(cell(&[Some(1.0), Some(2.0), Some(6.0)], 0), "3 (1–6)");
        assert_eq!(
            cell(&[Some(1.0), None, Some(2.0)], 1),
            "1.5 (1.0–2.0) [2 of 3]"
        );
        assert_eq!(cell(&[None, Some(2.0)], 0), "2 [1 of 2]");
        assert_eq!(cell(&[Some(2.26)], 1), "2.3");
        assert_eq!(cell(&[None, None], 0), "");
    }
}
