//! `invaders bench`: the figures that matter for training speed, in one command.
//!
//! Times (medians over repeated runs) the article network's train step at batch 48, its batch-1
//! forward pass (acting, on game frames: [`Sequential::infer`], whose sparse products depend on
//! how many activations are zero, so `--checkpoint` also times a trained network's), the emulator's
//! frames per second with the `article` preset's pipeline, and end-to-end agent steps per second
//! of the `article` preset with learning on, and of the `strong` presets; `strong`'s loop, taking
//! turns and acting beside learning, also at ε's floor with where each core's time goes.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::Context;
use clap::Args;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

use invaders::dqn::{
    checkpoint, game_seed, random_play_inputs, Agent, Batch, Config, Learner, LoopTimes, PqnAgent,
    Preset,
};
use invaders::env::{Observer, SpaceInvaders};
use invaders::layers::Sequential;
use invaders::ops::plan::{self, Precision, Product};
use invaders::tensor::cpu::{self, Family};

#[derive(Debug, Args)]
pub struct BenchArgs {
    /// Worker threads for the kernels (default: all cores).
    #[arg(long)]
    threads: Option<usize>,
    /// Print one JSON object instead of text.
    #[arg(long)]
    json: bool,
    /// The products' arithmetic: f32, or bf16 operands with f32 sums (on CPUs with
    /// AVX512-BF16; elsewhere f32, and the report says so), or auto (what a run would resolve it
    /// to here: the report always says what auto gives for the strong preset, and the two train
    /// steps it timed).
    #[arg(long, value_enum, default_value_t = Precision::F32)]
    precision: Precision,
    /// Train steps to time.
    #[arg(long, default_value_t = 30)]
    steps: usize,
    /// Also time acting with a trained network (a run directory, its `checkpoint.safetensors`,
    /// a weights-only model file or a shipped model's folder such as models/strong), besides a newly
    /// initialised one. A trained network's activations are mostly zeros, which acting skips.
    #[arg(long, value_name = "PATH")]
    checkpoint: Option<PathBuf>,
    /// Also time a configuration of your own (a TOML file as `train --config` takes): its train
    /// step at its batch size and its end-to-end agent steps per second (`--precision` applies
    /// to it too); the report names the preset and batch it resolved to. For choosing settings
    /// by their cost (an implicit quantile head's fractions, `hidden`, …).
    #[arg(long, value_name = "FILE")]
    config: Option<PathBuf>,
    /// The preset `--config` starts from, as for `train`: this, else the file's `preset` key,
    /// else `article`.
    #[arg(long, value_enum, requires = "config")]
    preset: Option<Preset>,
}

/// A configuration as the end-to-end figures run it: in `precision`, learning from agent step
/// 500, a replay memory of 5 000 (or the multiple of `games` just below, a lane per game).
fn bench_config(c: Config, precision: Precision) -> Config {
    Config {
        precision,
        learning_starts: 500,
        replay_capacity: 5_000 / c.games * c.games,
        ..c
    }
}

/// Agent steps per second and each core's shares ([`CoreShares`]) of `N` DQN configurations
/// played as most of a run plays them, ε at its floor (nearly every action a forward pass; from
/// ε = 1 nearly every action is random): after 600 steps each to warm up, their episodes take
/// turns until each has played 6 000 more agent steps, each timed over its own episodes, so
/// that a neighbour who slows the host for a while slows all.
fn paired_at_floor<const N: usize>(
    configs: [Config; N], precision: Precision,
) -> anyhow::Result<[(f64, CoreShares); N]> {
    let mut agents = Vec::new();
    for c in configs {
        let c = Config {
            epsilon_start: c.epsilon_end,
            ..bench_config(c, precision)
        };
        let games = bench_games(&c, c.games)?;
        let mut agent = Agent::with_games(c, games)?;
        while agent.counters.agent_steps < 600 {
            agent.play_episode()?;
        }
        agents.push(agent);
    }
    let starts: Vec<_> = agents
        .iter()
        .map(|a| (a.counters.agent_steps, a.times))
        .collect();
    let mut walls = [0.0; N];
    while agents
        .iter()
        .zip(&starts)
        .any(|(a, (s0, _))| a.counters.agent_steps < s0 + 6_000)
    {
        for (agent, wall) in agents.iter_mut().zip(&mut walls) {
            let t = Instant::now();
            agent.play_episode()?;
            *wall += t.elapsed().as_secs_f64();
        }
    }
    Ok(std::array::from_fn(|i| {
        let (a, (s0, times0)) = (&agents[i], &starts[i]);
        let beside = a.config.act_while_learning;
        let shares = CoreShares::of(&a.times.since(times0), walls[i], beside);
        ((a.counters.agent_steps - s0) as f64 / walls[i], shares)
    }))
}

/// `n` games of Space Invaders with `config`'s environment, seeded as a run seeded 0 seeds them
/// ([`game_seed`]).
fn bench_games(config: &Config, n: usize) -> anyhow::Result<Vec<SpaceInvaders>> {
    (0..n)
        .map(|g| SpaceInvaders::new(&config.env, game_seed(0, g)))
        .collect::<Result<Vec<_>, _>>()
        .context("cannot start Space Invaders")
}

/// Where each core's wall time went in an end-to-end loop ([`LoopTimes`] over the wall time):
/// the thread that plays, and each other thread of the pool, which works only on updates.
#[derive(Clone, Copy, Debug, serde::Serialize)]
struct CoreShares {
    /// The playing thread.
    player: PlayerShares,
    /// Each other thread: the share of the wall time an update ran (it works at most then).
    others_update: f64,
}

/// The playing thread's shares of the wall time.
#[derive(Clone, Copy, Debug, serde::Serialize)]
struct PlayerShares {
    acting: f64,
    emulator: f64,
    storing: f64,
    sampling: f64,
    /// Beside the updates: the next update's target pass, made ahead.
    target_pass: f64,
    /// The updates it took its turn in (none when it plays beside them).
    update: f64,
    /// Beside the updates: from the end of its block to the update's end.
    joining: f64,
    /// The rest: target copies, priorities, episode resets and metrics.
    other: f64,
}

impl CoreShares {
    /// The shares of `t` over `wall` seconds; `beside`: the updates ran beside the play.
    fn of(t: &LoopTimes, wall: f64, beside: bool) -> Self {
        let update = if beside { 0.0 } else { t.update };
        let played =
            t.acting + t.emulator + t.storing + t.sampling + t.target_pass + update + t.joining;
        CoreShares {
            player: PlayerShares {
                acting: t.acting / wall,
                emulator: t.emulator / wall,
                storing: t.storing / wall,
                sampling: t.sampling / wall,
                target_pass: t.target_pass / wall,
                update: update / wall,
                joining: t.joining / wall,
                other: (wall - played).max(0.0) / wall,
            },
            others_update: t.update / wall,
        }
    }

    /// One line: the playing thread's shares, then the other threads'.
    fn words(&self) -> String {
        let p = &self.player;
        let pc = |x: f64| format!("{:.0}%", 100.0 * x);
        format!(
            "player: acting {}, emulator {}, storing {}, sampling {}, target pass {}, update {}, joining {}, other {}; each other thread: update {}",
            pc(p.acting),
            pc(p.emulator),
            pc(p.storing),
            pc(p.sampling),
            pc(p.target_pass),
            pc(p.update),
            pc(p.joining),
            pc(p.other),
            pc(self.others_update)
        )
    }
}

fn median(mut xs: Vec<f64>) -> f64 {
    xs.sort_by(f64::total_cmp);
    xs[xs.len() / 2]
}

pub fn run(args: &BenchArgs) -> anyhow::Result<()> {
    super::in_pool(args.threads, || bench(args))
}

fn bench(args: &BenchArgs) -> anyhow::Result<()> {
    // A bad checkpoint fails before anything is timed.
    let mut trained = match &args.checkpoint {
        None => None,
        Some(path) => {
            let file = checkpoint::network_file(path)?;
            Some(checkpoint::load_model(&file)?)
        }
    };
    let own = match &args.config {
        Some(p) => Some(super::config_errors::resolve_file(
            args.preset,
            &super::guard::read_text(p, "config file")?,
            Some(p),
        )?),
        None => None,
    };
    let threads = rayon::current_num_threads();
    let config = Config::preset(Preset::Article);
    let mut rng = ChaCha8Rng::seed_from_u64(0);

    // The train step on a random batch.
    // `auto`, as a run resolves it: here for the strong preset's network and batch.
    let auto = invaders::dqn::resolve_precision(&Config {
        precision: Precision::Auto,
        ..Config::preset(Preset::Strong)
    });
    let precision = match args.precision {
        Precision::Auto => auto.precision,
        p => p,
    };
    super::note_precision(precision);
    let mut learner = Learner::from_config(&config, 6, &mut rng);
    learner.set_precision(precision);
    // Laid out as the agent's batches are: inside conv1's padding, a zero border.
    let batch = Batch::random(&config, &mut rng);
    let bf16_before = cpu::paths(Family::Bf16);
    for _ in 0..3 {
        learner.train_step(&batch);
    }
    // What ran: the kernel family, and the kernel of each product (the last layer's to run it).
    let bf16_calls = cpu::paths(Family::Bf16).since(bf16_before);
    let family = if bf16_calls.amx > 0 {
        "amx-bf16"
    } else if bf16_calls.avx512 > 0 {
        "avx512-bf16"
    } else if cpu::avx512() {
        "avx512-f32"
    } else if cpu::avx2() {
        "avx2-f32"
    } else {
        "portable-f32"
    };
    let kernels: Vec<(&str, String)> = [
        ("conv_forward", Product::ConvForward),
        ("conv_weight_grad", Product::ConvWeightGrad),
        ("conv_input_grad", Product::ConvInputGrad),
        ("dense_forward", Product::DenseForward),
        ("dense_backward", Product::DenseBackward),
    ]
    .into_iter()
    .map(|(name, p)| (name, format!("{:?}", plan::last(p))))
    .collect();
    let step_ms = median(
        (0..args.steps.max(1))
            .map(|_| {
                let t = Instant::now();
                learner.train_step(&batch);
                t.elapsed().as_secs_f64() * 1e3
            })
            .collect(),
    );
    let macs = learner.online.macs() as f64;
    let first = learner.online.layers()[0].macs() as f64;
    let flops = 2.0 * config.batch_size as f64 * (3.0 * macs + (macs - first));
    let gflops = flops / (step_ms * 1e-3) / 1e9;

    // Acting: a batch-1 forward pass on game frames, as the agent acts.
    let act_ms = time_acting(&mut learner.online, &config, &mut rng)?;
    let act_trained_ms = match &mut trained {
        None => None,
        // The trained online network, as `eval` plays it.
        Some(model) => Some(time_acting(&mut model.online, &model.config, &mut rng)?),
    };

    // The emulator with the article's pipeline and input normalisation, random actions.
    let mut env = SpaceInvaders::new(&config.env, 0).context("cannot start Space Invaders")?;
    let mut observer = Observer::new(config.pipeline);
    let table = config.normalization.table();
    let mut buf = vec![0.0f32; observer.input_len()];
    env.reset();
    observer.reset(&env);
    let (mut frames, mut steps) = (0u64, 0u64);
    let t = Instant::now();
    while steps < 5_000 {
        let r = env.step(rng.random_range(0..env.n_actions()));
        observer.step(&env);
        observer.write_input(&table, &mut buf);
        frames += r.frames as u64;
        steps += 1;
        if r.terminal || r.truncated {
            env.reset();
            observer.reset(&env);
        }
    }
    let env_secs = t.elapsed().as_secs_f64();
    let env_fps = frames as f64 / env_secs;
    let env_steps_per_s = steps as f64 / env_secs;

    // End to end: the article and strong presets with learning on from step 500.
    let end_to_end = |e2e: Config| -> anyhow::Result<f64> {
        let e2e = bench_config(e2e, precision);
        if let Some(pqn) = e2e.pqn {
            // PQN: whole rollouts (one to warm up), at least 2 000 agent steps timed.
            let games = bench_games(&e2e, pqn.games)?;
            let mut agent = PqnAgent::new(e2e, games)?;
            agent.play_rollout()?;
            let (s0, t0) = (agent.counters.agent_steps, Instant::now());
            while agent.counters.agent_steps < s0 + 2_000 {
                agent.play_rollout()?;
            }
            return Ok((agent.counters.agent_steps - s0) as f64 / t0.elapsed().as_secs_f64());
        }
        let games = bench_games(&e2e, e2e.games)?;
        let mut agent = Agent::with_games(e2e, games)?;
        while agent.counters.agent_steps < 600 {
            agent.play_episode()?;
        }
        let (s0, t0) = (agent.counters.agent_steps, Instant::now());
        while agent.counters.agent_steps < s0 + 2_000 {
            agent.play_episode()?;
        }
        Ok((agent.counters.agent_steps - s0) as f64 / t0.elapsed().as_secs_f64())
    };
    let agent_steps_per_s = end_to_end(Config::preset(Preset::Article))?;
    let strong_steps_per_s = end_to_end(Config::preset(Preset::Strong))?;
    // The same, each update beside the agent steps up to the next (issue #101).
    let beside = Config {
        act_while_learning: true,
        ..Config::preset(Preset::Strong)
    };
    let strong_beside_steps_per_s = end_to_end(beside.clone())?;
    // Four games side by side, taking turns with the updates (issue #101).
    let games = Config {
        games: 4,
        ..Config::preset(Preset::Strong)
    };
    let strong_4_games_steps_per_s = end_to_end(games.clone())?;
    // Both loops as most of a run plays them, ε at its floor, episodes taking turns, with where
    // each core's time goes.
    // And the 4 games with each update beside the play.
    let games_beside = Config {
        act_while_learning: true,
        ..games.clone()
    };
    let [strong_floor, beside_floor, games_floor, games_beside_floor] = paired_at_floor(
        [Config::preset(Preset::Strong), beside, games, games_beside],
        precision,
    )?;
    let loop_json = |(sps, shares): (f64, CoreShares)| serde_json::json!({"agent_steps_per_s": sps, "core_shares": shares});
    // The first `strong`: issue #43's compute cap is counted in its agent steps.
    let strong_v1_steps_per_s = end_to_end(Config::preset(Preset::StrongV1))?;
    // The user's configuration: its train step on a random batch, then end to end.
    let own_figures = match &own {
        None => None,
        Some(c) => {
            let mut l = Learner::from_config(c, 6, &mut rng);
            l.set_precision(precision);
            // PQN's step is a regression on one of its minibatches.
            let mut shaped = c.clone();
            if let Some(p) = c.pqn {
                shaped.batch_size = p.minibatch();
            }
            let mut b = Batch::random(&shaped, &mut rng);
            let targets = b.rewards.clone();
            let times: Vec<f64> = (0..args.steps.max(1) + 3)
                .map(|_| {
                    if let Some(iqn) = c.iqn() {
                        b.draw_fractions(&mut rng, iqn.samples, iqn.target_samples);
                    }
                    let t = Instant::now();
                    if c.pqn.is_some() {
                        l.regress_step(&b, &targets);
                    } else {
                        l.train_step(&b);
                    }
                    t.elapsed().as_secs_f64() * 1e3
                })
                .collect();
            Some((median(times[3..].to_vec()), end_to_end(c.clone())?))
        }
    };
    let env_share = agent_steps_per_s / env_steps_per_s;

    if args.json {
        out!(
            "{}",
            serde_json::json!({
                "threads": threads,
                "precision": precision,
                "auto_precision": auto.precision,
                "auto_train_step_ms": auto.times_ms.map(|t| serde_json::json!({"f32": t.0, "bf16": t.1})),
                "kernel_family": family,
                "kernels": kernels.iter().cloned().collect::<std::collections::BTreeMap<_, _>>(),
                "train_step_ms": step_ms,
                "train_step_gflops": gflops,
                "act_ms": act_ms,
                "act_checkpoint": args.checkpoint,
                "act_checkpoint_ms": act_trained_ms,
                "env_frames_per_s": env_fps,
                "agent_steps_per_s": agent_steps_per_s,
                "strong_agent_steps_per_s": strong_steps_per_s,
                "strong_acting_while_learning_agent_steps_per_s": strong_beside_steps_per_s,
                "strong_4_games_agent_steps_per_s": strong_4_games_steps_per_s,
                "strong_v1_agent_steps_per_s": strong_v1_steps_per_s,
                "strong_final_epsilon": loop_json(strong_floor),
                "strong_acting_while_learning_final_epsilon": loop_json(beside_floor),
                "strong_4_games_final_epsilon": loop_json(games_floor),
                "strong_4_games_acting_while_learning_final_epsilon": loop_json(games_beside_floor),
                "config": args.config,
                "config_preset": own.as_ref().map(|c| c.preset.name()),
                "config_batch_size": own.as_ref().map(|c| c.batch_size),
                "config_train_step_ms": own_figures.map(|f| f.0),
                "config_agent_steps_per_s": own_figures.map(|f| f.1),
                "env_share_of_training": env_share,
            })
        );
    } else {
        out!("threads                 {threads}");
        out!("precision               {precision:?} ({family})");
        out!("  auto here             {}", auto.why);
        for (name, k) in &kernels {
            out!("  {name:<21} {k}");
        }
        out!("train step (batch 48)   {step_ms:.2} ms  ({gflops:.1} GFLOP/s)");
        out!("act (batch-1 forward)   {act_ms:.3} ms  (an initial network, game frames)");
        if let (Some(ms), Some(p)) = (act_trained_ms, &args.checkpoint) {
            out!("act, trained network    {ms:.3} ms  ({})", p.display());
        }
        out!("emulator                {env_fps:.0} frames/s ({env_steps_per_s:.0} agent steps/s with the pipeline)");
        out!("training, end to end    {agent_steps_per_s:.1} agent steps/s (emulator and preprocessing: {:.1}% of the time)", 100.0 * env_share);
        out!("  the strong preset     {strong_steps_per_s:.1} agent steps/s");
        out!("  acting while learning {strong_beside_steps_per_s:.1} agent steps/s (strong with act_while_learning)");
        out!("  4 games side by side {strong_4_games_steps_per_s:.1} agent steps/s (strong with games = 4)");
        for (words, (sps, shares)) in [
            ("strong", strong_floor),
            ("acting while learning", beside_floor),
            ("4 games side by side", games_floor),
            ("4 games beside learning", games_beside_floor),
        ] {
            out!("  {words}, final ε: {sps:.1} agent steps/s");
            out!("    {}", shares.words());
        }
        out!("  strong-v1             {strong_v1_steps_per_s:.1} agent steps/s");
        if let (Some((ms, sps)), Some(p), Some(c)) = (own_figures, &args.config, &own) {
            out!(
                "{} (preset {}, {}): train step {ms:.2} ms, {sps:.1} agent steps/s",
                p.display(),
                c.preset.name(),
                batch_words(c)
            );
        }
    }
    Ok(())
}

/// The median time of `net`'s batch-1 forward pass ([`Sequential::infer`], as the agent acts) on
/// 64 observations from a game played with random actions through `config`'s pipeline, each
/// timed 5 times (after one pass to warm up).
fn time_acting(
    net: &mut Sequential<f32>, config: &Config, rng: &mut ChaCha8Rng,
) -> anyhow::Result<f64> {
    let frames = random_play_inputs(config, 64, 10, rng)?;
    // As the agent acts: argmax of the head's Q-values (an implicit quantile head's at its
    // policy fractions).
    let head = invaders::dqn::Head::of(config);
    for x in &frames {
        head.greedy(net, x, 6);
    }
    let mut times = Vec::with_capacity(5 * frames.len());
    for _ in 0..5 {
        for x in &frames {
            let t = Instant::now();
            head.greedy(net, x, 6);
            times.push(t.elapsed().as_secs_f64() * 1e3);
        }
    }
    Ok(median(times))
}

/// The batch a configuration trains on, in words: a PQN run's minibatch (games × rollout /
/// minibatches; its `batch_size` is unused), else `batch_size`.
pub(super) fn batch_words(c: &Config) -> String {
    match c.pqn {
        Some(p) => format!("PQN minibatch {}", p.minibatch()),
        None => format!("batch {}", c.batch_size),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `bench --config` with a PQN file names its minibatch (games × rollout / minibatches), not
    /// the `batch_size` a PQN run does not use.
    #[test]
    fn a_pqn_config_is_reported_with_its_minibatch() {
        let pqn = "[pqn]\ngames = 8\nrollout = 16\nminibatches = 4\n";
        let c = Config::resolve(Some(Preset::Strong), Some(pqn)).unwrap();
        assert_eq!(batch_words(&c), "PQN minibatch 32");
        let dqn = Config::resolve(Some(Preset::Strong), None).unwrap();
        assert_eq!(batch_words(&dqn), format!("batch {}", dqn.batch_size));
    }
}
