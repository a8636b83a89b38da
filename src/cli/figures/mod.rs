//! Reward curves like the article's figures: each episode's score, faint, and its moving average.

use anyhow::anyhow;
use plotters::coord::types::RangedCoordf64;
use plotters::prelude::*;
use std::path::Path;
use std::sync::Once;

/// DejaVu Sans (`assets/fonts/`, with its licence), the font fontconfig gave plotters for
/// "sans-serif" before the font was embedded.
const SANS: &[u8] = include_bytes!("../../../assets/fonts/DejaVuSans.ttf");

/// plotters sizes text differently by backend: font-kit (the `ttf` feature, what plotters used
/// with fontconfig) takes a size of `s` pixels as an em of `s / 1.24` pixels, ab_glyph as a
/// height (ascender to descender) of `s` pixels, which for DejaVu Sans (2048 units per em,
/// ascender 1901, descender −483) is an em of `s / 1.164`. Sizes go through [`sans`], which scales
/// by the ratio so that text keeps the size it had.
const AB_GLYPH_SCALE: f64 = (1901.0 + 483.0) / (1.24 * 2048.0);

/// The embedded sans-serif font at the size that font-kit drew as `size` (see `AB_GLYPH_SCALE`).
pub fn sans(size: f64) -> FontDesc<'static> {
    register_fonts();
    FontDesc::new(
        FontFamily::SansSerif,
        size * AB_GLYPH_SCALE,
        FontStyle::Normal,
    )
}

/// Registers the embedded font as plotters' "sans-serif", once per process. Every function that
/// draws text calls it first: plotters is built without system font support (no fontconfig),
/// so a family that is not registered cannot be drawn.
pub fn register_fonts() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        plotters::style::register_font("sans-serif", FontStyle::Normal, SANS)
            .unwrap_or_else(|_| panic!("the embedded font is a valid TrueType file"));
    });
}

/// One run's curve: a label and `(episode, reward)` points.
pub struct Curve {
    /// Legend label.
    pub label: String,
    /// `(episode, reward)`, in episode order.
    pub points: Vec<(f64, f64)>,
}

/// The trailing moving average over `window` points (shorter at the start).
pub fn moving_average(ys: &[f64], window: usize) -> Vec<f64> {
    let mut out = Vec::with_capacity(ys.len());
    let mut sum = 0.0;
    for i in 0..ys.len() {
        sum += ys[i];
        if i >= window {
            sum -= ys[i - window];
        }
        out.push(sum / (i + 1).min(window) as f64);
    }
    out
}

/// Reads `(episode, reward)` from a run's `metrics.csv`. Rows whose episode or reward is not a
/// finite number (NaN, infinity) are skipped, with a warning naming their lines: a plot of them
/// would have no scale.
pub fn read_metrics(path: &Path) -> anyhow::Result<Vec<(f64, f64)>> {
    read_columns(path, "episode", "reward")
}

/// Reads `(emulator frames, reward)` from a run's `metrics.csv`, as [`read_metrics`] does.
pub fn read_frame_metrics(path: &Path) -> anyhow::Result<Vec<(f64, f64)>> {
    read_columns(path, "emulator_frames", "reward")
}

/// Reads the columns `x` and `y` of a `metrics.csv` as points (see [`read_metrics`]).
fn read_columns(path: &Path, x: &str, y: &str) -> anyhow::Result<Vec<(f64, f64)>> {
    let text = super::guard::read_text(path, "the metrics")?;
    let mut lines = text.lines();
    let header = lines
        .next()
        .ok_or_else(|| anyhow!("{} is empty", path.display()))?;
    let cols: Vec<&str> = header.split(',').collect();
    let col = |name: &str| {
        cols.iter()
            .position(|c| *c == name)
            .ok_or_else(|| anyhow!("{}: no `{name}` column", path.display()))
    };
    let (ie, ir) = (col(x)?, col(y)?);
    let mut points = Vec::new();
    let mut skipped = Vec::new();
    for (n, line) in lines.enumerate() {
        let f: Vec<&str> = line.split(',').collect();
        let parse = |i: usize| -> anyhow::Result<f64> {
            f.get(i)
                .and_then(|v| v.parse().ok())
                .ok_or_else(|| anyhow!("{}: line {} is malformed", path.display(), n + 2))
        };
        let (x, y) = (parse(ie)?, parse(ir)?);
        if x.is_finite() && y.is_finite() {
            points.push((x, y));
        } else {
            skipped.push((n + 2).to_string());
        }
    }
    if !skipped.is_empty() {
        say!(
            "warning: {}: skipped {} row(s) with a non-finite episode or reward (line {})",
            path.display(),
            skipped.len(),
            skipped.join(", ")
        );
    }
    Ok(points)
}

/// Draws reward curves (faint per-episode scores, bold moving averages over `window` episodes)
/// into a PNG.
pub fn plot_rewards(
    curves: &[Curve], title: &str, window: usize, out: &Path,
) -> anyhow::Result<()> {
    let max_x = curves
        .iter()
        .flat_map(|c| c.points.iter().map(|p| p.0))
        .fold(1.0, f64::max);
    let max_y = curves
        .iter()
        .flat_map(|c| c.points.iter().map(|p| p.1))
        .fold(10.0, f64::max);
    let averages: Vec<Vec<(f64, f64)>> = curves
        .iter()
        .map(|c| {
            let ys: Vec<f64> = c.points.iter().map(|p| p.1).collect();
            c.points
                .iter()
                .map(|p| p.0)
                .zip(moving_average(&ys, window))
                .collect()
        })
        .collect();
    let labels: Vec<String> = curves
        .iter()
        .map(|c| format!("{} ({window}-episode mean)", c.label))
        .collect();
    let ink = Ink {
        points: curves
            .iter()
            .flat_map(|c| c.points.iter().copied())
            .chain(averages.iter().flatten().copied())
            .collect(),
        labels: labels.clone(),
    };
    figure(
        out,
        title,
        "episode",
        "reward per episode",
        (max_x, max_y),
        ink,
        |chart| {
            for (i, ((c, avg), label)) in curves.iter().zip(averages).zip(labels).enumerate() {
                let color = Palette99::pick(i);
                chart.draw_series(LineSeries::new(c.points.iter().copied(), color.mix(0.25)))?;
                chart
                    .draw_series(LineSeries::new(avg, color.stroke_width(3)))?
                    .label(label)
                    .legend(move |(x, y)| {
                        PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(3))
                    });
            }
            Ok(())
        },
    )
}

type Chart<'a, 'b> =
    ChartContext<'a, BitMapBackend<'b>, Cartesian2d<RangedCoordf64, RangedCoordf64>>;
type DrawResult =
    Result<(), DrawingAreaErrorKind<<BitMapBackend<'static> as DrawingBackend>::ErrorType>>;

/// Where a figure's drawn lines are, and its legend's labels: the legend goes where it hides the
/// fewest of those points ([`legend_corner`]).
struct Ink {
    points: Vec<(f64, f64)>,
    labels: Vec<String>,
}

/// The legend's size in pixels at 12-pixel labels (plotters' layout: rows 15 pixels apart,
/// 10-pixel margins, a 20-pixel key beside each label), with about 6.5 pixels a character.
fn legend_pixels(labels: &[String]) -> (f64, f64) {
    let longest = labels.iter().map(|l| l.chars().count()).max().unwrap_or(0);
    (
        longest as f64 * 6.5 + 55.0,
        labels.len() as f64 * 15.0 + 25.0,
    )
}

/// The corner of the plot whose legend box (`size`, as fractions of the plot's width and
/// height) covers the fewest of `points`, in the order upper left, upper right, lower right,
/// lower left when several tie. `max` is the axes' extent.
fn legend_corner(points: &[(f64, f64)], max: (f64, f64), size: (f64, f64)) -> usize {
    let (w, h) = (size.0.min(1.0) * max.0, size.1.min(1.0) * max.1);
    let boxes = [
        (0.0, w, max.1 - h, max.1),           // upper left
        (max.0 - w, max.0, max.1 - h, max.1), // upper right
        (max.0 - w, max.0, 0.0, h),           // lower right
        (0.0, w, 0.0, h),                     // lower left
    ];
    let covered = |b: &(f64, f64, f64, f64)| {
        points
            .iter()
            .filter(|p| p.0 >= b.0 && p.0 <= b.1 && p.1 >= b.2 && p.1 <= b.3)
            .count()
    };
    (0..boxes.len())
        .min_by_key(|&i| (covered(&boxes[i]), i))
        .expect("four corners")
}

/// A 1000x600 figure of reward against `x_desc` with axes up to `max` and a legend where `ink`
/// is thinnest; `draw` adds the series. Every figure of the project goes through here.
fn figure(
    out: &Path, title: &str, x_desc: &str, y_desc: &str, max: (f64, f64), ink: Ink,
    draw: impl FnOnce(&mut Chart<'_, '_>) -> DrawResult,
) -> anyhow::Result<()> {
    register_fonts();
    let e = |err: DrawingAreaErrorKind<_>| anyhow!("plot: {err}");
    if !(max.0.is_finite() && max.1.is_finite()) {
        anyhow::bail!("plot: the data are not finite numbers");
    }
    let root = BitMapBackend::new(out, (1000, 600)).into_drawing_area();
    root.fill(&WHITE).map_err(e)?;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, sans(24.0))
        .margin(15)
        .x_label_area_size(45)
        .y_label_area_size(60)
        .build_cartesian_2d(0.0..max.0, 0.0..max.1 * 1.05)
        .map_err(e)?;
    chart
        .configure_mesh()
        .x_desc(x_desc)
        .x_label_formatter(&|x| {
            if max.0 >= 1e6 {
                format!("{:.1}M", x / 1e6) // frames
            } else {
                format!("{x:.0}")
            }
        })
        .y_label_formatter(&|y| format!("{y:.0}"))
        .y_desc(y_desc)
        .label_style(sans(12.0)) // plotters' default size, as for the legend below
        .axis_desc_style(sans(12.0))
        .draw()
        .map_err(e)?;
    draw(&mut chart).map_err(e)?;
    let (width, height) = chart.plotting_area().dim_in_pixel();
    let (lw, lh) = legend_pixels(&ink.labels);
    let corner = legend_corner(
        &ink.points,
        (max.0, max.1 * 1.05),
        (lw / width as f64, lh / height as f64),
    );
    chart
        .configure_series_labels()
        .label_font(sans(12.0))
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .position(match corner {
            0 => SeriesLabelPosition::UpperLeft,
            1 => SeriesLabelPosition::UpperRight,
            2 => SeriesLabelPosition::LowerRight,
            _ => SeriesLabelPosition::LowerLeft,
        })
        .draw()
        .map_err(e)?;
    root.present()
        .map_err(|err| anyhow!("plot: cannot write {}: {err}", out.display()))?;
    Ok(())
}

/// Several seeds of one configuration: a label and each seed's `(episode, reward)` points.
pub struct Group {
    /// Legend label.
    pub label: String,
    /// One curve per seed.
    pub seeds: Vec<Vec<(f64, f64)>>,
}

/// The per-episode mean over seeds of each seed's `window`-episode moving average, with the
/// lowest and highest seed, over the episodes every seed reached: `(episode, mean, low, high)`.
pub fn mean_band(seeds: &[Vec<(f64, f64)>], window: usize) -> Vec<(f64, f64, f64, f64)> {
    let n = seeds.iter().map(Vec::len).min().unwrap_or(0);
    let avgs: Vec<Vec<f64>> = seeds
        .iter()
        .map(|s| moving_average(&s.iter().map(|p| p.1).collect::<Vec<_>>(), window))
        .collect();
    (0..n)
        .map(|i| {
            let vals: Vec<f64> = avgs.iter().map(|a| a[i]).collect();
            let mean = vals.iter().sum::<f64>() / vals.len() as f64;
            let lo = vals.iter().copied().fold(f64::INFINITY, f64::min);
            let hi = vals.iter().copied().fold(f64::NEG_INFINITY, f64::max);
            (seeds[0][i].0, mean, lo, hi)
        })
        .collect()
}

/// A curve known only within bounds: each episode's reward lies in `[low, high]`. The article's
/// notebook's training curve, digitised from its saved plot, is one (see
/// `docs/experiment/notebook/README.md`).
pub struct Bounded {
    /// Legend label.
    pub label: String,
    /// `(episode, low, high)`, one per episode in episode order (episodes numbered from 1).
    pub points: Vec<(f64, f64, f64)>,
}

/// Reads a digitised plot (`tools/notebook/digitize_plot.py`): one row per pixel column with the
/// 0-based indices of the first and last episode it covers, the extent of the line there
/// (`reward_min`, `reward_max`) and one pixel in reward units. Every episode of a column lies in
/// its extent widened by a pixel each way (and rewards are never negative).
pub fn read_digitized(path: &Path, label: &str) -> anyhow::Result<Bounded> {
    const HEADER: &str = "pixel_col,episode_x_from,episode_x_to,first_episode_index,last_episode_index,reward_min,reward_max,reward_per_pixel";
    let text = super::guard::read_text(path, "the digitised curve")?;
    let mut lines = text.lines();
    if lines.next() != Some(HEADER) {
        anyhow::bail!("{}: the header must be `{HEADER}`", path.display());
    }
    let mut points: Vec<(f64, f64, f64)> = Vec::new();
    for (n, line) in lines.enumerate() {
        let at = || format!("{} line {}", path.display(), n + 2);
        let f: Vec<f64> = line
            .split(',')
            .map(|v| v.trim().parse::<f64>())
            .collect::<Result<_, _>>()
            .ok()
            .filter(|f: &Vec<f64>| f.len() == 8 && f.iter().all(|v| v.is_finite()))
            .ok_or_else(|| anyhow!("{}: 8 finite numbers expected", at()))?;
        let (first, last, min, max, px) = (f[3], f[4], f[5], f[6], f[7]);
        if first != points.len() as f64 {
            anyhow::bail!(
                "{}: the column starts at episode index {first}, not {} (columns cover the \
                 episodes in order, each once)",
                at(),
                points.len()
            );
        }
        // A plot of at most a million episodes: a bad last index must not fill the memory.
        if last.fract() != 0.0 || last < first || last >= 1e6 {
            anyhow::bail!(
                "{}: the last episode index ({last}) must be a whole number from {first} below a million",
                at()
            );
        }
        if min > max || px < 0.0 {
            anyhow::bail!(
                "{}: reward_min ({min}) above reward_max ({max}) or a negative pixel size ({px})",
                at()
            );
        }
        for _ in first as usize..=last as usize {
            let episode = points.len() as f64 + 1.0;
            points.push((episode, (min - px).max(0.0), max + px));
        }
    }
    if points.is_empty() {
        anyhow::bail!("{}: no columns", path.display());
    }
    Ok(Bounded {
        label: label.to_string(),
        points,
    })
}

/// Bounds on a bounded curve's `window`-episode moving average: the moving averages of its lower
/// and of its upper bounds, `(episode, low, high)`. The true average lies between them.
pub fn moving_bounds(curve: &Bounded, window: usize) -> Vec<(f64, f64, f64)> {
    let lows = moving_average(
        &curve.points.iter().map(|p| p.1).collect::<Vec<_>>(),
        window,
    );
    let highs = moving_average(
        &curve.points.iter().map(|p| p.2).collect::<Vec<_>>(),
        window,
    );
    curve
        .points
        .iter()
        .zip(lows.into_iter().zip(highs))
        .map(|(p, (lo, hi))| (p.0, lo, hi))
        .collect()
}

/// Draws each group's mean moving average over seeds as a line, with a shaded band from the
/// lowest to the highest seed; each bounded curve's moving average as a grey band between its
/// bounds ([`moving_bounds`]).
pub fn plot_groups(
    groups: &[Group], bounded: &[Bounded], title: &str, window: usize, out: &Path,
) -> anyhow::Result<()> {
    let bands: Vec<Vec<(f64, f64, f64, f64)>> =
        groups.iter().map(|g| mean_band(&g.seeds, window)).collect();
    let limits: Vec<Vec<(f64, f64, f64)>> =
        bounded.iter().map(|b| moving_bounds(b, window)).collect();
    let max_x = bands
        .iter()
        .flat_map(|b| b.iter().map(|p| p.0))
        .chain(limits.iter().flat_map(|b| b.iter().map(|p| p.0)))
        .fold(1.0, f64::max);
    let max_y = bands
        .iter()
        .flat_map(|b| b.iter().map(|p| p.3))
        .chain(limits.iter().flat_map(|b| b.iter().map(|p| p.2)))
        .fold(10.0, f64::max);
    let y_desc = format!("reward per episode ({window}-episode moving average)");
    let group_labels: Vec<String> = groups
        .iter()
        .map(|g| format!("{} (mean of {} seeds)", g.label, g.seeds.len()))
        .collect();
    let ink = Ink {
        points: bands
            .iter()
            .flatten()
            .flat_map(|p| [(p.0, p.1), (p.0, p.2), (p.0, p.3)])
            .chain(
                limits
                    .iter()
                    .flatten()
                    .flat_map(|p| [(p.0, p.1), (p.0, p.2)]),
            )
            .collect(),
        labels: bounded
            .iter()
            .map(|b| b.label.clone())
            .chain(group_labels.iter().cloned())
            .collect(),
    };
    figure(
        out,
        title,
        "episode",
        &y_desc,
        (max_x, max_y),
        ink,
        |chart| {
            for (b, limit) in bounded.iter().zip(&limits) {
                let grey = RGBColor(110, 110, 110);
                let mut outline: Vec<(f64, f64)> = limit.iter().map(|p| (p.0, p.2)).collect();
                outline.extend(limit.iter().rev().map(|p| (p.0, p.1)));
                chart.draw_series(std::iter::once(Polygon::new(outline, grey.mix(0.18))))?;
                for edge in [1, 2] {
                    let line = limit
                        .iter()
                        .map(|p| (p.0, if edge == 1 { p.1 } else { p.2 }));
                    let series = chart.draw_series(LineSeries::new(line, grey.stroke_width(1)))?;
                    if edge == 1 {
                        series.label(b.label.clone()).legend(move |(x, y)| {
                            Rectangle::new([(x, y - 5), (x + 20, y + 5)], grey.mix(0.35).filled())
                        });
                    }
                }
            }
            for (i, (band, label)) in bands.iter().zip(group_labels).enumerate() {
                draw_band(chart, band, Palette99::pick(i), label)?;
            }
            Ok(())
        },
    )
}

/// Draws one group's `(x, mean, low, high)` points: the mean as a bold line with `label` in the
/// legend, over a shaded band from the lowest to the highest seed.
fn draw_band(
    chart: &mut Chart<'_, '_>, band: &[(f64, f64, f64, f64)], color: PaletteColor<Palette99>,
    label: String,
) -> DrawResult {
    let mut outline: Vec<(f64, f64)> = band.iter().map(|p| (p.0, p.3)).collect();
    outline.extend(band.iter().rev().map(|p| (p.0, p.2)));
    chart.draw_series(std::iter::once(Polygon::new(outline, color.mix(0.15))))?;
    chart
        .draw_series(LineSeries::new(
            band.iter().map(|p| (p.0, p.1)),
            color.stroke_width(3),
        ))?
        .label(label)
        .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(3)));
    Ok(())
}

/// Each seed's `window`-episode moving average against emulator frames, read on a grid of
/// `step` frames (at each grid point, the average as of the last episode ended by then), then
/// the mean, lowest and highest seed at each grid point that every seed reached:
/// `(frames, mean, low, high)`. `seeds` hold `(frames, reward)` points in episode order.
pub fn mean_band_frames(
    seeds: &[Vec<(f64, f64)>], window: usize, step: f64,
) -> Vec<(f64, f64, f64, f64)> {
    assert!(step > 0.0, "a positive grid step");
    let averaged: Vec<Vec<(f64, f64)>> = seeds
        .iter()
        .map(|s| {
            let avg = moving_average(&s.iter().map(|p| p.1).collect::<Vec<_>>(), window);
            s.iter().map(|p| p.0).zip(avg).collect()
        })
        .collect();
    let reach = averaged
        .iter()
        .map(|s| s.last().map_or(0.0, |p| p.0))
        .fold(f64::INFINITY, f64::min);
    let mut out = Vec::new();
    let mut x = step;
    while x <= reach {
        let vals: Vec<f64> = averaged
            .iter()
            .filter_map(|s| s.iter().take_while(|p| p.0 <= x).last().map(|p| p.1))
            .collect();
        if vals.len() == averaged.len() {
            let mean = vals.iter().sum::<f64>() / vals.len() as f64;
            let lo = vals.iter().copied().fold(f64::INFINITY, f64::min);
            let hi = vals.iter().copied().fold(f64::NEG_INFINITY, f64::max);
            out.push((x, mean, lo, hi));
        }
        x += step;
    }
    out
}

/// The grid of [`plot_groups_frames`]: every 50 000 frames, or for runs shorter than 5 million
/// frames a hundredth of the shortest one (at least 1 frame), so that a short run is drawn too.
pub fn grid_step(groups: &[Group]) -> f64 {
    const STEP: f64 = 50_000.0;
    let shortest = groups
        .iter()
        .flat_map(|g| &g.seeds)
        .map(|s| s.last().map_or(0.0, |p| p.0))
        .fold(f64::INFINITY, f64::min);
    if shortest.is_finite() {
        (shortest / 100.0).floor().clamp(1.0, STEP)
    } else {
        STEP
    }
}

/// The largest frame count a reference curve may give: far beyond any published run (the
/// longest are 200 million frames).
pub const MAX_REFERENCE_FRAMES: f64 = 1e12;

/// The largest score a reference curve may give, in absolute value: far beyond any Space
/// Invaders score (the game's counter wraps at 9 999 per player).
pub const MAX_REFERENCE_SCORE: f64 = 1e7;

/// A published learning curve to compare with: a label and `(emulator frames, score)` points.
pub struct Reference {
    /// Legend label.
    pub label: String,
    /// `(frames, score)`.
    pub points: Vec<(f64, f64)>,
}

/// Reads reference curves from a CSV with the header `agent,frames,score` (one row per point,
/// rows of one agent in frame order), keeping the agents named in `agents` (all if empty).
pub fn read_references(path: &Path, agents: &[String]) -> anyhow::Result<Vec<Reference>> {
    let text = super::guard::read_text(path, "the reference curves")?;
    let mut lines = text.lines();
    if lines.next() != Some("agent,frames,score") {
        anyhow::bail!(
            "{}: the header must be `agent,frames,score`",
            path.display()
        );
    }
    let mut refs: Vec<Reference> = Vec::new();
    for (n, line) in lines.enumerate() {
        let bad = || anyhow!("{}: line {} is malformed", path.display(), n + 2);
        let mut f = line.split(',');
        let (agent, x, y) = (f.next(), f.next(), f.next());
        let (Some(agent), Some(x), Some(y), None) = (agent, x, y, f.next()) else {
            return Err(bad());
        };
        let (x, y): (f64, f64) = (x.parse().map_err(|_| bad())?, y.parse().map_err(|_| bad())?);
        let out_of_range = |what: &str, v: f64, range: &str| {
            anyhow!(
                "{}: line {}: {what} {} is {range}",
                path.display(),
                n + 2,
                super::short_number(v)
            )
        };
        if !(x.is_finite() && (0.0..=MAX_REFERENCE_FRAMES).contains(&x)) {
            return Err(out_of_range("frames", x, "outside 0..=1e12"));
        }
        if !(y.is_finite() && y.abs() <= MAX_REFERENCE_SCORE) {
            return Err(out_of_range("score", y, "outside -1e7..=1e7"));
        }
        let last = refs
            .iter()
            .find(|r| r.label == agent)
            .and_then(|r| r.points.last());
        if let Some(&(px, _)) = last.filter(|p| p.0 >= x) {
            anyhow::bail!(
                "{}: line {}: frames {} of agent `{agent}` come after {}: each agent's points must be in increasing frame order",
                path.display(),
                n + 2,
                super::short_number(x),
                super::short_number(px)
            );
        }
        if !agents.is_empty() && !agents.iter().any(|a| a == agent) {
            continue;
        }
        match refs.iter_mut().find(|r| r.label == agent) {
            Some(r) => r.points.push((x, y)),
            None => refs.push(Reference {
                label: agent.to_string(),
                points: vec![(x, y)],
            }),
        }
    }
    for a in agents {
        if !refs.iter().any(|r| &r.label == a) {
            anyhow::bail!("{}: no agent `{a}`", path.display());
        }
    }
    if refs.is_empty() {
        anyhow::bail!(
            "{}: no curve (the file holds a header and no point)",
            path.display()
        );
    }
    Ok(refs)
}

/// Draws each group's mean over seeds against emulator frames ([`mean_band_frames`]) with a
/// band from the lowest to the highest seed, and each reference as a dashed line with points,
/// up to the frames the groups reached (references beyond are cut there).
pub fn plot_groups_frames(
    groups: &[Group], references: &[Reference], title: &str, window: usize, out: &Path,
) -> anyhow::Result<()> {
    let step = grid_step(groups);
    let bands: Vec<Vec<(f64, f64, f64, f64)>> = groups
        .iter()
        .map(|g| mean_band_frames(&g.seeds, window, step))
        .collect();
    let max_x = bands
        .iter()
        .flat_map(|b| b.iter().map(|p| p.0))
        .fold(step, f64::max);
    let refs: Vec<Vec<(f64, f64)>> = references
        .iter()
        .map(|r| r.points.iter().copied().filter(|p| p.0 <= max_x).collect())
        .collect();
    let max_y = bands
        .iter()
        .flat_map(|b| b.iter().map(|p| p.3))
        .chain(refs.iter().flatten().map(|p| p.1))
        .fold(10.0, f64::max);
    let y_desc = format!("reward per episode ({window}-episode moving average)");
    let group_labels: Vec<String> = groups
        .iter()
        .map(|g| match g.seeds.len() {
            1 => g.label.clone(),
            n => format!("{} (mean of {n} seeds, min-max band)", g.label),
        })
        .collect();
    // The references' dashed lines, as points every twentieth of each segment.
    let dashes = refs.iter().flat_map(|r| {
        r.windows(2).flat_map(|w| {
            (0..20).map(move |k| {
                let t = k as f64 / 20.0;
                (
                    w[0].0 + t * (w[1].0 - w[0].0),
                    w[0].1 + t * (w[1].1 - w[0].1),
                )
            })
        })
    });
    let ink = Ink {
        points: bands
            .iter()
            .flatten()
            .flat_map(|p| [(p.0, p.1), (p.0, p.2), (p.0, p.3)])
            .chain(refs.iter().flatten().copied())
            .chain(dashes)
            .collect(),
        labels: group_labels
            .iter()
            .cloned()
            .chain(references.iter().map(|r| r.label.clone()))
            .collect(),
    };
    figure(
        out,
        title,
        "emulator frames",
        &y_desc,
        (max_x, max_y),
        ink,
        |chart| {
            for (i, (band, label)) in bands.iter().zip(group_labels).enumerate() {
                draw_band(chart, band, Palette99::pick(i), label)?;
            }
            for (i, (r, pts)) in references.iter().zip(&refs).enumerate() {
                let color = Palette99::pick(groups.len() + i);
                chart.draw_series(DashedLineSeries::new(
                    pts.iter().copied(),
                    8,
                    5,
                    color.stroke_width(2),
                ))?;
                chart
                    .draw_series(pts.iter().map(|&p| Circle::new(p, 4, color.filled())))?
                    .label(r.label.clone())
                    .legend(move |(x, y)| Circle::new((x + 10, y), 4, color.filled()));
            }
            Ok(())
        },
    )
}

#[cfg(test)]
mod tests;
