use super::*;

/// The legend goes to the corner whose box covers the fewest drawn points, upper left when
/// corners tie. Boxes here are 45 % of the width and 20 % of the height of a 100x100 plot.
#[test]
fn the_legend_goes_where_it_hides_the_least() {
    let (max, size) = ((100.0, 100.0), (0.45, 0.2));
    let line = |xs: std::ops::RangeInclusive<i32>, y: f64| -> Vec<(f64, f64)> {
        xs.map(|x| (x as f64, y)).collect()
    };
    assert_eq!(
        legend_corner(&[], max, size),
        0,
        "nothing drawn: upper left"
    );
    let rising: Vec<(f64, f64)> = (0..=100).map(|x| (x as f64, x as f64)).collect();
    assert_eq!(legend_corner(&rising, max, size), 0, "a rising line: a tie");
    assert_eq!(
        legend_corner(&line(0..=40, 95.0), max, size),
        1,
        "upper right"
    );
    let top_and_low_left = [line(0..=100, 95.0), line(0..=40, 5.0)].concat();
    assert_eq!(
        legend_corner(&top_and_low_left, max, size),
        2,
        "lower right"
    );
    let top_and_low_right = [line(0..=100, 95.0), line(60..=100, 5.0)].concat();
    assert_eq!(
        legend_corner(&top_and_low_right, max, size),
        3,
        "lower left"
    );
    let everywhere = [line(0..=100, 95.0), line(0..=100, 5.0)].concat();
    assert_eq!(legend_corner(&everywhere, max, size), 0, "four ties");
    // The box's height counts: a line at 70 is clear of a 20 % box, not of a 40 % one.
    let high_and_low_left = [line(0..=100, 70.0), line(0..=40, 5.0)].concat();
    assert_eq!(legend_corner(&high_and_low_left, max, (0.45, 0.2)), 0);
    assert_eq!(legend_corner(&high_and_low_left, max, (0.45, 0.4)), 2);
    assert_eq!(
        legend_pixels(&["ab".into(), "abcd".into()]),
        (4.0 * 6.5 + 55.0, 55.0)
    );
}

/// Two seeds whose episodes end at different frames: the grid reads each seed's latest
/// average, and stops where the shorter seed stops.
#[test]
fn the_frames_band_reads_each_seed_on_one_grid() {
    let a = vec![(40.0, 10.0), (90.0, 30.0), (160.0, 50.0)];
    let b = vec![(45.0, 20.0), (120.0, 40.0)];
    let band = mean_band_frames(&[a, b], 1, 50.0);
    assert_eq!(
        band,
        vec![(50.0, 15.0, 10.0, 20.0), (100.0, 25.0, 20.0, 30.0)]
    );
}

fn write(name: &str, text: &str) -> std::path::PathBuf {
    let path = std::env::temp_dir().join(format!("invaders-plot-{}-{name}", std::process::id()));
    std::fs::write(&path, text).unwrap();
    path
}

const HEADER: &str = "pixel_col,episode_x_from,episode_x_to,first_episode_index,last_episode_index,reward_min,reward_max,reward_per_pixel\n";

/// Columns expand into one bound per episode, widened by a pixel (and never below 0); the
/// moving bounds are the moving averages of the two edges.
#[test]
fn a_digitised_plot_bounds_each_episode_and_its_moving_average() {
    let path = write(
        "ok.csv",
        &format!("{HEADER}48,-0.7,1.9,0,1,2.0,60.0,4.5\n49,1.9,4.5,2,4,100.0,130.0,4.5\n"),
    );
    let curve = read_digitized(&path, "nb").unwrap();
    assert_eq!(
        curve.points,
        vec![
            (1.0, 0.0, 64.5),
            (2.0, 0.0, 64.5),
            (3.0, 95.5, 134.5),
            (4.0, 95.5, 134.5),
            (5.0, 95.5, 134.5),
        ]
    );
    let m = moving_bounds(&curve, 2);
    assert_eq!(m[0], (1.0, 0.0, 64.5));
    assert_eq!(m[2], (3.0, 47.75, 99.5));
    assert_eq!(m[4], (5.0, 95.5, 134.5));
    let _ = std::fs::remove_file(path);
}

/// A gap or an overlap between columns, a wrong header, a short row: each a clear error.
#[test]
fn a_malformed_digitised_plot_is_refused() {
    for (name, text, says) in [
        (
            "gap",
            format!("{HEADER}1,0,1,0,1,1,2,4\n2,1,2,3,4,1,2,4\n"),
            "not 2",
        ),
        (
            "overlap",
            format!("{HEADER}1,0,1,0,1,1,2,4\n2,1,2,1,4,1,2,4\n"),
            "not 2",
        ),
        ("header", "episode,reward\n1,2\n".to_string(), "header"),
        (
            "short",
            format!("{HEADER}1,0,1,0,1,1,2\n"),
            "8 finite numbers",
        ),
        (
            "nan",
            format!("{HEADER}1,0,1,0,1,1,NaN,4\n"),
            "8 finite numbers",
        ),
        (
            "reversed",
            format!("{HEADER}1,0,1,0,1,5,2,4\n"),
            "above reward_max",
        ),
        (
            "fraction",
            format!("{HEADER}1,0,1,0,1.5,1,2,4\n"),
            "whole number",
        ),
        (
            "huge",
            format!("{HEADER}1,0,1,0,1e12,1,2,4\n"),
            "below a million",
        ),
        ("empty", HEADER.to_string(), "no columns"),
    ] {
        let path = write(name, &text);
        let err = read_digitized(&path, "nb").err().map(|e| format!("{e:#}"));
        assert!(
            err.as_deref().is_some_and(|e| e.contains(says)),
            "{name}: {err:?}"
        );
        let _ = std::fs::remove_file(path);
    }
}

/// The bounded curve is drawn: the same groups with and without it make different images.
#[test]
fn a_bounded_curve_changes_the_figure() {
    let groups = [Group {
        label: "a".to_string(),
        seeds: vec![(1..=50).map(|e| (e as f64, 100.0)).collect()],
    }];
    let bounded = [Bounded {
        label: "nb".to_string(),
        points: (1..=50).map(|e| (e as f64, 20.0, 60.0)).collect(),
    }];
    let (with, without) = (
        std::env::temp_dir().join(format!("invaders-plot-{}-with.png", std::process::id())),
        std::env::temp_dir().join(format!("invaders-plot-{}-without.png", std::process::id())),
    );
    plot_groups(&groups, &bounded, "t", 10, &with).unwrap();
    plot_groups(&groups, &[], "t", 10, &without).unwrap();
    assert_ne!(
        std::fs::read(&with).unwrap(),
        std::fs::read(&without).unwrap()
    );
    let _ = (std::fs::remove_file(with), std::fs::remove_file(without));
}

/// The committed digitisation of the notebook's plot reads whole: about 800 episodes.
#[test]
fn the_notebooks_digitised_plot_reads() {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/docs/experiment/notebook/plot-digitized.csv"
    );
    let curve = read_digitized(Path::new(path), "nb").unwrap();
    assert_eq!(curve.points.len(), 799);
}

/// `plot --group` of runs shorter than the 50 000-frame grid: the grid shrinks to a hundredth
/// of the shortest run, so their curves have points (a grid of 50 000 frames gave none).
#[test]
fn short_runs_get_a_grid_of_their_own() {
    let seed = |n: u64| -> Vec<(f64, f64)> { (1..=n).map(|e| (e as f64 * 200.0, 1.0)).collect() };
    let groups = [Group {
        label: "short".into(),
        seeds: vec![seed(10), seed(12)],
    }];
    let step = grid_step(&groups);
    assert_eq!(step, 20.0);
    assert!(mean_band_frames(&groups[0].seeds, 5, step).len() >= 90);
    let long = [Group {
        label: "long".into(),
        seeds: vec![seed(100_000)],
    }];
    assert_eq!(
        grid_step(&long),
        50_000.0,
        "long runs keep the article's grid"
    );
}
