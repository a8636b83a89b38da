//! How much of the screen blinks (docs/environment.md): plays Space Invaders one emulator frame
//! per step (random actions held for 4 frames, no sticky actions, seed 7) and prints the rows of
//! the 88x80 frame lit more often on even than on odd frames, how much the lit count changes over
//! 1 to 4 frames (a period-2 flicker changes it more over odd gaps), and what an agent that sees
//! every 4th frame gets against the max of the 4th and the 3rd (DeepMind's max over the last two
//! frames): `cargo run --release --example flicker`.
use invaders::env::preprocess::Downsample;
use invaders::env::{EnvConfig, EnvMode, SpaceInvaders};
use rand::{Rng, SeedableRng};

fn main() {
    let mut cfg = EnvConfig::from_mode(EnvMode::V5);
    cfg.frame_skip_min = 1;
    cfg.frame_skip_max = 1;
    cfg.sticky_prob = 0.0;
    cfg.downsample = Downsample::Max;
    let mut env = SpaceInvaders::new(&cfg, 7).unwrap();
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
    env.reset();
    let (mut lit_last, mut lit_max, mut only_prev, mut n) = (0u64, 0u64, 0u64, 0u64);
    let mut prev = env.observation().to_vec();
    let mut action = 0;
    // Lit pixels of every frame, for the period of what changes.
    let mut counts: Vec<i64> = Vec::new();
    // Lit counts per row at even and odd frames.
    let mut rows = [[0u64; 88]; 2];
    for t in 1..=40_000u64 {
        if t % 4 == 1 {
            action = rng.random_range(0..env.n_actions());
        }
        let r = env.step(action);
        let obs = env.observation().to_vec();
        counts.push(obs[..80 * 80].iter().filter(|&&v| v > 0).count() as i64);
        for (y, row) in obs.chunks(80).enumerate() {
            rows[(t % 2) as usize][y] += row.iter().filter(|&&v| v > 0).count() as u64;
        }
        if t % 4 == 0 {
            // Rows 0..80 of 88: above the ground line.
            for i in 0..80 * 80 {
                let (a, b) = (prev[i] > 0, obs[i] > 0);
                lit_last += b as u64;
                lit_max += (a || b) as u64;
                only_prev += (a && !b) as u64;
            }
            n += 1;
        }
        prev = obs;
        if r.terminal || r.truncated || env.is_finished() {
            env.reset();
            prev = env.observation().to_vec();
            counts.push(-1);
        }
    }
    let lag = |k: usize| {
        let pairs: Vec<f64> = counts
            .windows(k + 1)
            .filter(|w| w.iter().all(|&c| c >= 0))
            .map(|w| (w[k] - w[0]).abs() as f64)
            .collect();
        pairs.iter().sum::<f64>() / pairs.len() as f64
    };
    for (y, (&e, &o)) in rows[0].iter().zip(&rows[1]).enumerate() {
        if e.abs_diff(o) * 20 > (e + o).max(1) {
            println!("row {y}: lit at even frames {e}, odd frames {o}");
        }
    }
    println!(
        "mean |lit(t) - lit(t - k)| for k = 1, 2, 3, 4: {:.2} {:.2} {:.2} {:.2}",
        lag(1),
        lag(2),
        lag(3),
        lag(4)
    );
    println!(
        "{n} observations: lit pixels per observation, last frame {:.1}, max of last two {:.1}; lit only in the frame before: {:.1}",
        lit_last as f64 / n as f64,
        lit_max as f64 / n as f64,
        only_prev as f64 / n as f64
    );
}
