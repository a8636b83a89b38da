//! Environment throughput: raw emulation, and agent steps through each pipeline up to the
//! normalised `f32` network input. The goal: preprocessing + stacking under 10% of emulation.
//!
//! Throughput is reported in emulator frames per second (`elem/s`); the `processing_only`
//! group times the per-step work done outside the emulator on its own.

use std::time::Duration;

use clap::ValueEnum;
use criterion::{black_box, criterion_group, criterion_main, Criterion, Throughput};
use invaders::env::ale::{Ale, AleSettings, SCREEN_RGB_LEN};
use invaders::env::{
    preprocess_rgb, Composer, Crop, Downsample, EnvConfig, EnvMode, FrameStack, Normalization,
    Observer, Pipeline, SpaceInvaders, FRAME_LEN,
};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Cache-line-aligned buffers for the kernels (`invaders::CacheAligned`): the library leaves
/// the allocator to the program.
#[global_allocator]
static GLOBAL: invaders::CacheAligned = invaders::CacheAligned;

const FRAMES: u64 = 1000;

/// A fixed action sequence, so every benchmark emulates exactly the same game.
fn actions(n: u64) -> Vec<usize> {
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    (0..n).map(|_| rng.random_range(0..6)).collect()
}

fn emulation(c: &mut Criterion) {
    let mut g = c.benchmark_group("emulation");
    g.throughput(Throughput::Elements(FRAMES));
    let settings = AleSettings {
        random_seed: 0,
        repeat_action_probability: 0.0,
        verbose: false,
    };
    let mut ale = Ale::new(&settings, None).unwrap();
    let ids = ale.minimal_action_set().to_vec();
    ale.reset_game();
    let start = ale.save_state();
    let acts = actions(FRAMES);
    let mut rgb = vec![0u8; SCREEN_RGB_LEN];
    for with_screen in [false, true] {
        let name = if with_screen {
            "raw_frames_with_rgb_screen"
        } else {
            "raw_frames"
        };
        g.bench_function(name, |b| {
            b.iter(|| {
                ale.restore_state(&start).unwrap();
                for &a in &acts {
                    black_box(ale.act(ids[a]));
                    if with_screen {
                        ale.screen_rgb(&mut rgb);
                    }
                    if ale.game_over() {
                        ale.reset_game();
                    }
                }
            })
        });
    }
    g.finish();
}

/// Agent steps of 4 frames (nature mode without no-op starts, so every step is 4 frames), the
/// same game as above, through each pipeline including the normalised network input.
fn agent_steps(c: &mut Criterion) {
    let mut g = c.benchmark_group("agent_steps");
    g.throughput(Throughput::Elements(FRAMES));
    let cfg = EnvConfig {
        noop_max: 0,
        ..EnvConfig::from_mode(EnvMode::Nature)
    };
    let table = Normalization::Symmetric.table();
    let mut env = SpaceInvaders::new(&cfg, 0).unwrap();
    let start = env.save_state();
    let acts = actions(FRAMES / 4);
    g.bench_function("env_only", |b| {
        b.iter(|| {
            env.restore_state(&start).unwrap();
            for &a in &acts {
                let r = env.step(a);
                if r.terminal || r.truncated {
                    env.reset();
                }
                black_box(env.observation());
            }
        })
    });
    for pipeline in [
        Pipeline::Vanilla,
        Pipeline::Stack,
        Pipeline::StackMax,
        Pipeline::StackRunningMax,
    ] {
        let mut obs = Observer::new(pipeline);
        let mut input = vec![0.0f32; obs.input_len()];
        g.bench_function(name(pipeline), |b| {
            b.iter(|| {
                env.restore_state(&start).unwrap();
                obs.reset(&env);
                for &a in &acts {
                    let r = env.step(a);
                    if r.terminal || r.truncated {
                        env.reset();
                        obs.reset(&env);
                    } else {
                        obs.step(&env);
                    }
                    obs.write_input(&table, &mut input);
                    black_box(&input);
                }
            })
        });
    }
    g.finish();
}

/// What an agent step costs outside the emulator: preprocess its two frames, compose, stack and
/// write the input. Throughput is again per emulator frame (4 per step) to compare directly.
fn processing_only(c: &mut Criterion) {
    let mut g = c.benchmark_group("processing_only");
    g.throughput(Throughput::Elements(FRAMES));
    let mut env = SpaceInvaders::new(&EnvConfig::from_mode(EnvMode::Nature), 0).unwrap();
    for _ in 0..300 {
        env.step(1);
    }
    let rgb = env.screen_rgb().to_vec();
    let table = Normalization::Symmetric.table();
    let (mut a, mut b_) = (vec![0u8; FRAME_LEN], vec![0u8; FRAME_LEN]);
    for pipeline in [
        Pipeline::Vanilla,
        Pipeline::StackMax,
        Pipeline::StackRunningMax,
    ] {
        let mut composer = Composer::new(pipeline);
        let mut stack = FrameStack::new(pipeline.channels());
        stack.reset(&a);
        let mut input = vec![0.0f32; FRAME_LEN * pipeline.channels()];
        g.bench_function(name(pipeline), |bch| {
            bch.iter(|| {
                for _ in 0..FRAMES / 4 {
                    preprocess_rgb(
                        black_box(&rgb),
                        None,
                        Crop::Article,
                        Downsample::Pick,
                        &mut a,
                    );
                    preprocess_rgb(
                        black_box(&rgb),
                        None,
                        Crop::Article,
                        Downsample::Pick,
                        &mut b_,
                    );
                    let f = composer.step(&a, &b_, &b_);
                    stack.push(f);
                    stack.write_input(&table, &mut input);
                    black_box(&input);
                }
            })
        });
    }
    g.finish();
}

fn name(p: Pipeline) -> String {
    p.to_possible_value().expect("named").get_name().to_string()
}

criterion_group! {
    name = benches;
    config = Criterion::default()
        .sample_size(10)
        .warm_up_time(Duration::from_secs(1))
        .measurement_time(Duration::from_secs(3));
    targets = emulation, agent_steps, processing_only
}
criterion_main!(benches);
