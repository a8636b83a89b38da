//! `invaders eval`: play whole episodes and summarise their scores.

use std::path::PathBuf;

use anyhow::{bail, Context};
use clap::{Args, ValueEnum};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use invaders::env::{EnvConfig, EnvMode, SpaceInvaders};

#[derive(Debug, Args)]
pub struct EvalArgs {
    /// Play uniformly random actions (the baseline every agent must beat).
    #[arg(long)]
    random: bool,
    /// A trained agent to evaluate (not available yet).
    #[arg(long, value_name = "PATH")]
    checkpoint: Option<PathBuf>,
    /// Number of episodes.
    #[arg(long, default_value_t = 30)]
    episodes: u32,
    /// Seed of the environment (the agent's random choices use a stream derived from it).
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Environment mode.
    #[arg(long, value_enum, default_value_t = EnvMode::V0)]
    mode: EnvMode,
    /// Space Invaders ROM to use instead of the bundled one.
    #[arg(long, value_name = "PATH")]
    rom: Option<PathBuf>,
}

pub fn run(args: &EvalArgs) -> anyhow::Result<()> {
    if !args.random {
        if args.checkpoint.is_some() {
            bail!("evaluating a --checkpoint is not available yet; use --random for the baseline");
        }
        bail!("eval needs --checkpoint PATH (not available yet) or --random");
    }
    if args.episodes == 0 {
        bail!("--episodes must be at least 1");
    }
    let config = EnvConfig {
        rom: args.rom.clone(),
        ..EnvConfig::from_mode(args.mode)
    };
    let mut env = SpaceInvaders::new(&config, args.seed).context("cannot start Space Invaders")?;
    let mut agent = ChaCha8Rng::seed_from_u64(args.seed);
    agent.set_stream(1); // independent of the environment's stream 0
    let n = env.n_actions();
    let mut scores = Vec::with_capacity(args.episodes as usize);
    for episode in 0..args.episodes {
        if episode > 0 {
            env.reset();
        }
        let truncated = loop {
            let r = env.step(agent.random_range(0..n));
            if r.terminal || r.truncated {
                break r.truncated;
            }
        };
        let stats = env.episode();
        println!(
            "episode {:>3}: score {:>6} steps {:>5} frames {:>6}{}",
            episode + 1,
            stats.score,
            stats.steps,
            stats.frames,
            if truncated {
                " (cut by the step limit)"
            } else {
                ""
            }
        );
        scores.push(stats.score);
    }
    let s = Summary::of(&scores);
    println!(
        "random agent, mode {}, {} episodes, seed {}: mean {:.1} std {:.1} min {} max {}",
        args.mode
            .to_possible_value()
            .expect("modes are named")
            .get_name(),
        s.n,
        args.seed,
        s.mean,
        s.std,
        s.min,
        s.max
    );
    Ok(())
}

/// Mean, population standard deviation, min and max of episode scores.
struct Summary {
    n: usize,
    mean: f64,
    std: f64,
    min: f64,
    max: f64,
}

impl Summary {
    fn of(xs: &[f64]) -> Summary {
        let n = xs.len();
        let mean = xs.iter().sum::<f64>() / n as f64;
        let var = xs.iter().map(|x| (x - mean) * (x - mean)).sum::<f64>() / n as f64;
        Summary {
            n,
            mean,
            std: var.sqrt(),
            min: xs.iter().copied().fold(f64::INFINITY, f64::min),
            max: xs.iter().copied().fold(f64::NEG_INFINITY, f64::max),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::Summary;

    #[test]
    fn summary_uses_population_std() {
        let s = Summary::of(&[1.0, 3.0]);
        assert_eq!((s.mean, s.std, s.min, s.max), (2.0, 1.0, 1.0, 3.0));
    }
}
