//! `invaders show-preprocessing`: what the network sees, drawn from one real game moment.
//!
//! The picture shows the raw 210x160 colour screen, the article's 88x80 grey preprocessing of it
//! (and the `strong` preset's, which max-pools each 2x2 block), and, for each pipeline, the frames stacked into the network's input (oldest on the left). The
//! running max of `stack-running-max` shows as trails behind everything that moved since reset.

use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context};
use clap::Args;
use plotters::prelude::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use invaders::env::{
    preprocess_rgb, Crop, Downsample, EnvConfig, EnvMode, Observer, Pipeline, SpaceInvaders,
    FRAME_HEIGHT, FRAME_LEN, FRAME_WIDTH,
};

#[derive(Debug, Args)]
pub struct ShowArgs {
    /// The PNG to write: an existing file is refused unless --force, and replaced atomically; a
    /// symbolic link's target is written, a character device or FIFO written through
    /// (docs/runs.md, "Output files").
    #[arg(long, value_name = "FILE.png")]
    out: PathBuf,
    /// Replace an existing --out file.
    #[arg(long)]
    force: bool,
    /// Agent steps of random play before the picture is taken (at most 100 000).
    #[arg(long, default_value_t = 150)]
    steps: u32,
    /// Seed of the game and of the random play.
    #[arg(long, default_value_t = 0)]
    seed: u64,
}

/// The most `--steps`: about a minute of emulation.
const MAX_STEPS: u32 = 100_000;

const PIPELINES: [Pipeline; 4] = [
    Pipeline::Vanilla,
    Pipeline::Stack,
    Pipeline::StackMax,
    Pipeline::StackRunningMax,
];

pub fn run(args: &ShowArgs) -> anyhow::Result<()> {
    if args.steps > MAX_STEPS {
        bail!(
            "--steps must be at most {MAX_STEPS} (about a minute of play), got {}",
            args.steps
        );
    }
    let out = super::guard::OutputFile::check(&args.out, args.force, &[], "--out")?;
    let mut env = SpaceInvaders::new(&EnvConfig::from_mode(EnvMode::V0), args.seed)
        .context("cannot start Space Invaders")?;
    let mut observers: Vec<Observer> = PIPELINES.iter().map(|&p| Observer::new(p)).collect();
    let mut rng = ChaCha8Rng::seed_from_u64(args.seed);
    env.reset();
    for o in &mut observers {
        o.reset(&env);
    }
    for _ in 0..args.steps {
        // Random play that fires often, so there are shots in the air.
        let a = if rng.random_bool(0.5) {
            1
        } else {
            rng.random_range(0..env.n_actions())
        };
        let r = env.step(a);
        for o in &mut observers {
            o.step(&env);
        }
        if r.terminal || r.truncated {
            env.reset();
            for o in &mut observers {
                o.reset(&env);
            }
        }
    }
    out.write_with(|tmp| draw(tmp, &env, &observers))
        .with_context(|| format!("cannot draw {}", args.out.display()))?;
    out!("wrote {}", args.out.display());
    Ok(())
}

fn draw(path: &Path, env: &SpaceInvaders, observers: &[Observer]) -> anyhow::Result<()> {
    let e = |err: DrawingAreaErrorKind<_>| anyhow!("{err}");
    let (w, h) = (760u32, 1400u32);
    let root = BitMapBackend::new(path, (w, h)).into_drawing_area();
    root.fill(&WHITE).map_err(e)?;
    let font = super::figures::sans(20.0);
    let text = |s: &str, x: i32, y: i32| root.draw(&Text::new(s.to_string(), (x, y), font.clone()));
    // Raw screen, 2x.
    text("raw screen (210x160 RGB)", 20, 10).map_err(e)?;
    let rgb = env.screen_rgb();
    for y in 0..210 {
        for x in 0..160 {
            let p = &rgb[(y * 160 + x) * 3..][..3];
            let c = RGBColor(p[0], p[1], p[2]);
            for (dy, dx) in [(0, 0), (0, 1), (1, 0), (1, 1)] {
                root.draw_pixel((20 + 2 * x as i32 + dx, 40 + 2 * y as i32 + dy), &c)
                    .map_err(e)?;
            }
        }
    }
    // The last frame preprocessed both ways, 2x: a 2x2 block's top-left pixel (the article's),
    // and its max (the `strong` preset's), which keeps the one-pixel-wide shots.
    text("88x80 grey: pick", 400, 10).map_err(e)?;
    grey(&root, env.observation(), 400, 40, 2)?;
    text("2x2 max (strong)", 580, 10).map_err(e)?;
    let mut max = vec![0u8; FRAME_LEN];
    preprocess_rgb(
        env.screen_rgb(),
        None,
        Crop::Article,
        Downsample::Max,
        &mut max,
    );
    grey(&root, &max, 580, 40, 2)?;
    // The crop that also keeps the mothership's band (screen rows 12 to 19) in the top 4 rows.
    text("max, mothership crop", 400, 250).map_err(e)?;
    preprocess_rgb(
        env.screen_rgb(),
        None,
        Crop::Mothership,
        Downsample::Max,
        &mut max,
    );
    grey(&root, &max, 400, 280, 2)?;
    // Each pipeline's stack, 2x, oldest on the left.
    let mut y0 = 480;
    for (o, p) in observers.iter().zip(PIPELINES) {
        let name = match p {
            Pipeline::Vanilla => "vanilla: 1 frame",
            Pipeline::Stack => "stack: last 4 frames",
            Pipeline::StackMax => "stack-max: 4 frames, each max of a step's last two raw frames",
            Pipeline::StackRunningMax => {
                "stack-running-max (the notebook's): running max since reset"
            }
        };
        text(name, 20, y0).map_err(e)?;
        for i in 0..o.stack().len() {
            grey(
                &root,
                o.stack().get(i),
                20 + i as i32 * (2 * FRAME_WIDTH as i32 + 20),
                y0 + 25,
                2,
            )?;
        }
        y0 += 2 * FRAME_HEIGHT as i32 + 50;
    }
    root.present().map_err(e)?;
    Ok(())
}

fn grey<DB: DrawingBackend>(
    area: &DrawingArea<DB, plotters::coord::Shift>, frame: &[u8], x0: i32, y0: i32, scale: i32,
) -> anyhow::Result<()> {
    for y in 0..FRAME_HEIGHT as i32 {
        for x in 0..FRAME_WIDTH as i32 {
            let v = frame[(y * FRAME_WIDTH as i32 + x) as usize];
            let c = RGBColor(v, v, v);
            for dy in 0..scale {
                for dx in 0..scale {
                    area.draw_pixel((x0 + scale * x + dx, y0 + scale * y + dy), &c)
                        .map_err(|err| anyhow!("{err:?}"))?;
                }
            }
        }
    }
    Ok(())
}
