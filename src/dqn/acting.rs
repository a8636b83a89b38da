//! Acting without learning: the greedy action of a network for the current frame stack, an
//! evaluation episode, and the inputs the acting benchmarks time.

use super::{Config, Head};
use crate::env::{Game, Observer};
use crate::layers::Sequential;
use crate::tensor::Tensor;
use anyhow::Context;
use rand::Rng;

/// `argmax_a Q(s, a)` over `n_actions` actions for the observer's current stack `s`, by `net`
/// built with `head`: writes the normalised stack into `input` (`[1, 88, 80, k]`) and runs a
/// batch-1 forward pass ([`Sequential::infer`]). A quantile head's `Q` is the mean of its
/// quantiles, an implicit quantile head's the mean over its policy fractions ([`Head::greedy`]).
pub fn greedy(
    net: &mut Sequential<f32>, head: &Head, observer: &Observer, table: &[f32; 256],
    input: &mut Tensor<f32>, n_actions: usize,
) -> usize {
    observer.write_input(table, input.data_mut());
    head.greedy(net, input, n_actions)
}

/// `n` inputs of `config`'s network (`[1, H, W, k]`, as the agent writes them), every `every`th
/// step of Space Invaders played with random actions drawn from `rng` (emulator seed 1), the
/// game reset when it ends: the acting benchmarks' workload.
pub fn random_play_inputs(
    config: &Config, n: usize, every: usize, rng: &mut impl Rng,
) -> anyhow::Result<Vec<Tensor<f32>>> {
    let mut env =
        crate::env::SpaceInvaders::new(&config.env, 1).context("cannot start Space Invaders")?;
    let mut observer = Observer::new(config.pipeline);
    let table = config.normalization.table();
    let [h, w, c] = config.input_shape();
    env.reset();
    observer.reset(&env);
    let mut inputs = Vec::with_capacity(n);
    for step in 0..n * every {
        let r = env.step(rng.random_range(0..env.n_actions()));
        observer.step(&env);
        if step % every == every - 1 {
            let mut x = Tensor::from_vec(&[1, h, w, c], vec![0.0; h * w * c]);
            observer.write_input(&table, x.data_mut());
            inputs.push(x);
        }
        if r.terminal || r.truncated {
            env.reset();
            observer.reset(&env);
        }
    }
    Ok(inputs)
}

/// Plays one episode with an ε-greedy policy and no learning (evaluation); `on_step` sees the
/// game after every step (to record it). Returns the score and the number of steps.
#[allow(clippy::too_many_arguments)]
pub fn play_evaluation_episode<G: Game>(
    game: &mut G, net: &mut Sequential<f32>, head: &Head, observer: &mut Observer,
    table: &[f32; 256], input: &mut Tensor<f32>, epsilon: f32, rng: &mut impl Rng,
    mut on_step: impl FnMut(&G),
) -> (f64, u64) {
    game.reset();
    observer.reset(game);
    on_step(game);
    let (mut score, mut steps) = (0.0, 0);
    loop {
        let action = if rng.random::<f32>() < epsilon {
            rng.random_range(0..game.n_actions())
        } else {
            greedy(net, head, observer, table, input, game.n_actions())
        };
        let r = game.step(action);
        observer.step(game);
        on_step(game);
        score += r.reward as f64;
        steps += 1;
        if r.terminal || r.truncated {
            return (score, steps);
        }
    }
}
