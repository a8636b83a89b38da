//! Dormant units (Sokar et al. 2023, "The dormant neuron phenomenon in deep reinforcement
//! learning"): how many of a trained network's ReLU units have stopped taking part, layer by
//! layer, on one set of game states. A unit's score is its mean activation over the states (and,
//! for a convolution's channel, over the positions) divided by the mean of its layer's units;
//! it is dormant at `τ` if its score is at most `τ` (`τ = 0`: it never fires). A network that
//! has lost units this way has less capacity to fit new targets: the diagnosis that resets of
//! the dense layers (`reset_dense_at`) treat.
//!
//! `cargo run --release --example dormant -- FILE...`: the states are every 4th step of
//! episodes of `models/strong-v1/model.safetensors` playing at ε = 0.05 (emulator seed 7), 1 024 of
//! them; each FILE (a checkpoint or a model) is then run on them in f32.

use anyhow::Context;
use invaders::dqn::checkpoint::load_model;
use invaders::dqn::{greedy, midpoints, Head};
use invaders::env::{Observer, SpaceInvaders};
use invaders::ops::plan::Precision;
use invaders::tensor::Tensor;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::path::Path;

#[global_allocator]
static GLOBAL: invaders::CacheAligned = invaders::CacheAligned;

/// States collected, and the batch they are run in.
const STATES: usize = 1024;
const CHUNK: usize = 64;

fn main() -> anyhow::Result<()> {
    let files: Vec<String> = std::env::args().skip(1).collect();
    anyhow::ensure!(
        !files.is_empty(),
        "usage: dormant FILE... (checkpoints or models)"
    );
    let states = collect_states(Path::new("models/strong-v1/model.safetensors"))?;
    println!("| network | frames | conv1 | conv2 | conv3 | dense1 |");
    println!("| --- | --- | --- | --- | --- | --- |");
    for f in &files {
        let mut m = load_model(Path::new(f)).with_context(|| format!("cannot load {f}"))?;
        m.online.set_precision(Precision::F32);
        let iqn = m.config.iqn();
        let names = ["conv1", "conv2", "conv3", "relu4", "ln4"];
        // Per layer: each unit's summed activation.
        let mut sums: Vec<Vec<f64>> = vec![Vec::new(); names.len()];
        for chunk in states.chunks(CHUNK) {
            let [h, w, c] = m.config.input_shape();
            let mut x = Tensor::zeros(&[chunk.len(), h, w, c]);
            for (i, s) in chunk.iter().enumerate() {
                x.data_mut()[i * s.len()..][..s.len()].copy_from_slice(s);
            }
            if let Some(iqn) = iqn {
                m.online
                    .set_fractions(&midpoints(iqn.policy_samples, chunk.len()));
            }
            m.online.forward(&x);
            for layer in m.online.layers() {
                let Some(k) = names.iter().position(|n| *n == layer.name()) else {
                    continue;
                };
                let out = layer.output();
                let units = *out.shape().last().unwrap();
                let s = &mut sums[k];
                s.resize(units, 0.0);
                for row in out.data().chunks_exact(units) {
                    for (a, &v) in s.iter_mut().zip(row) {
                        *a += v.abs() as f64;
                    }
                }
            }
        }
        let cell = |s: &[f64]| {
            if s.is_empty() {
                return "-".to_string();
            }
            let mean = s.iter().sum::<f64>() / s.len() as f64;
            let at = |tau: f64| s.iter().filter(|&&v| v <= tau * mean).count();
            format!("{} / {} of {}", at(0.0), at(0.1), s.len())
        };
        let dense = if sums[3].is_empty() {
            &sums[4]
        } else {
            &sums[3]
        };
        println!(
            "| {f} | {:.2} M | {} | {} | {} | {} |",
            m.counters.frames as f64 / 1e6,
            cell(&sums[0]),
            cell(&sums[1]),
            cell(&sums[2]),
            cell(dense)
        );
    }
    println!("\n(each cell: units dormant at τ = 0 / at τ = 0.1, of the layer's units)");
    Ok(())
}

/// [`STATES`] network inputs from `model` playing at ε = 0.05: every 4th step, episodes
/// following each other on emulator seed 7.
fn collect_states(model: &Path) -> anyhow::Result<Vec<Vec<f32>>> {
    let mut m = load_model(model).with_context(|| format!("cannot load {}", model.display()))?;
    let head = Head::of(&m.config);
    let mut game = SpaceInvaders::new(&m.config.env, 7).context("cannot start the game")?;
    let mut observer = Observer::new(m.config.pipeline);
    let table = m.config.normalization.table();
    let [h, w, c] = m.config.input_shape();
    let mut input = Tensor::zeros(&[1, h, w, c]);
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    let mut states = Vec::with_capacity(STATES);
    game.reset();
    observer.reset(&game);
    for step in 0.. {
        let action = if rng.random::<f32>() < 0.05 {
            rng.random_range(0..game.n_actions())
        } else {
            let n = game.n_actions();
            greedy(&mut m.online, &head, &observer, &table, &mut input, n)
        };
        let r = game.step(action);
        observer.step(&game);
        if step % 4 == 3 {
            let mut s = vec![0.0; h * w * c];
            observer.write_input(&table, &mut s);
            states.push(s);
            if states.len() == STATES {
                break;
            }
        }
        if r.terminal || r.truncated {
            game.reset();
            observer.reset(&game);
        }
    }
    Ok(states)
}
