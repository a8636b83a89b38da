//! PQN: the Q(λ) returns against a hand computation and their limits, the configuration's
//! `[pqn]` table, and the agent learning a toy game, deterministically and resumably.

mod common;

use common::corridor::{Corridor, LEN};
use invaders::dqn::checkpoint::Counters;
use invaders::dqn::{checkpoint, q_lambda_returns, Config, Learner, Pqn, PqnAgent, Preset};
use invaders::env::{Observer, Pipeline};
use invaders::ops::plan::Precision;
use invaders::tensor::Tensor;
use proptest::prelude::*;

/// Two games, three steps, γ = 0.9, λ = 0.5, worked by hand. Game 0 ends bootstrapping after
/// its step 1 (rewards 1, 0, 2; `max Q` 10, 4, 6 and 8 at the end):
/// `G_2 = 2 + 0.9·(0.5·8 + 0.5·8) = 9.2`, `G_1 = 0` (done: nothing after it counts),
/// `G_0 = 1 + 0.9·(0.5·G_1 + 0.5·4) = 2.8`. Game 1 never ends (rewards 0; `max Q` 0, 1, 2, 3):
/// `G_2 = 0.9·3 = 2.7`, `G_1 = 0.9·(0.5·2.7 + 0.5·2) = 2.115`,
/// `G_0 = 0.9·(0.5·2.115 + 0.5·1) = 1.40175`.
#[test]
fn q_lambda_returns_match_a_hand_computation() {
    // [T, G]: row t holds the two games' step t.
    let rewards = [1.0, 0.0, 0.0, 0.0, 2.0, 0.0];
    let dones = [false, false, true, false, false, false];
    let max_q = [10.0, 0.0, 4.0, 1.0, 6.0, 2.0, 8.0, 3.0];
    let mut returns = [f32::NAN; 6];
    q_lambda_returns(&rewards, &dones, &max_q, 2, 0.9, 0.5, &mut returns);
    let want = [2.8, 1.40175, 0.0, 2.115, 9.2, 2.7];
    for (i, (&g, &w)) in returns.iter().zip(&want).enumerate() {
        assert!((g - w).abs() < 1e-5, "returns[{i}] = {g}, want {w}");
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(common::cases(64)))]

    /// λ = 0 is the one-step target `r_t + γ(1 − done_t) max Q(s_{t+1})`; λ = 1 the discounted
    /// return to the episode's end or, without one, to the rollout's end bootstrapped there.
    #[test]
    fn q_lambda_returns_reach_their_limits(
        games in 1usize..4,
        steps in 1usize..9,
        seed in any::<u64>(),
        gamma in 0.5f32..1.0,
    ) {
        let mut rng = common::rng(seed);
        use rand::Rng;
        let n = games * steps;
        let rewards: Vec<f32> = (0..n).map(|_| rng.random_range(-1.0..1.0)).collect();
        let dones: Vec<bool> = (0..n).map(|_| rng.random_bool(0.25)).collect();
        let max_q: Vec<f32> = (0..n + games).map(|_| rng.random_range(-5.0..5.0)).collect();
        let mut one_step = vec![0.0; n];
        q_lambda_returns(&rewards, &dones, &max_q, games, gamma, 0.0, &mut one_step);
        let mut monte_carlo = vec![0.0; n];
        q_lambda_returns(&rewards, &dones, &max_q, games, gamma, 1.0, &mut monte_carlo);
        for t in 0..steps {
            for g in 0..games {
                let i = t * games + g;
                let cont = if dones[i] { 0.0 } else { 1.0 };
                let want = rewards[i] + gamma * cont * max_q[i + games];
                prop_assert!((one_step[i] - want).abs() < 1e-4, "λ = 0 at {i}");
                // Forward from t: rewards until a done, else the bootstrap at T.
                let (mut ret, mut discount) = (0.0f32, 1.0f32);
                let mut ended = false;
                for u in t..steps {
                    let j = u * games + g;
                    ret += discount * rewards[j];
                    discount *= gamma;
                    if dones[j] {
                        ended = true;
                        break;
                    }
                }
                if !ended {
                    ret += discount * max_q[steps * games + g];
                }
                prop_assert!((monte_carlo[i] - ret).abs() < 1e-4, "λ = 1 at {i}");
            }
        }
    }
}

/// The `[pqn]` table: CleanRL's defaults for what a file leaves out, its ranges, and the
/// switches PQN has no place for refused by name.
#[test]
fn the_pqn_table_has_defaults_ranges_and_refusals() {
    let c = Config::resolve(Some(Preset::Strong), Some("[pqn]\ngames = 4")).unwrap();
    assert_eq!(
        c.pqn,
        Some(Pqn {
            games: 4,
            ..Pqn::default()
        })
    );
    assert_eq!(Pqn::default().minibatch(), 256);
    assert_eq!(Config::preset(Preset::Strong).pqn, None);
    // A run's recorded configuration keeps it; one without it writes no table.
    let again = Config::resolve(None, Some(&c.to_toml())).unwrap();
    assert_eq!(again, c);
    assert!(!Config::preset(Preset::Strong).to_toml().contains("pqn"));
    let err = |text: &str| {
        format!(
            "{:#}",
            Config::resolve(Some(Preset::Strong), Some(text)).unwrap_err()
        )
    };
    assert!(err("[pqn]\ngames = 0").contains("pqn.games"));
    assert!(err("[pqn]\nminibatches = 3").contains("divide"));
    assert!(err("[pqn]\nlambda = 1.5").contains("pqn.lambda"));
    assert!(err("[pqn]\nepochs = 0").contains("pqn.epochs"));
    assert!(err("[pqn]\nbatch = 3").contains("batch"));
    assert!(err("prioritized = true\n[pqn]").contains("prioritized"));
    assert!(err("iqn_samples = 8\n[pqn]").contains("iqn_samples"));
    assert!(err("munchausen_alpha = 0.9\n[pqn]").contains("munchausen_alpha"));
}

/// A PQN configuration for the corridor: 4 games of 16 steps a rollout, 4 passes of 4
/// minibatches of 16, layer normalisation, RAdam, one frame per state.
fn toy_config() -> Config {
    let mut c = common::small_config(1_000, 16, 64, 25, 3);
    c.gamma = 0.9;
    c.epsilon_decay_steps = 1_000;
    c.epsilon_end = 0.05;
    c.learning_rate = 1e-3;
    c.layer_norm = true;
    c.radam = true;
    c.precision = Precision::F32;
    c.pqn = Some(Pqn {
        games: 4,
        rollout: 16,
        epochs: 4,
        minibatches: 4,
        lambda: 0.65,
    });
    c.validate().unwrap();
    c
}

fn corridors(n: usize) -> Vec<Corridor> {
    (0..n).map(|_| Corridor::new()).collect()
}

/// `max_a Q` and the greedy action of a corridor cell by `agent`'s network.
fn q_of(agent: &mut PqnAgent<Corridor>, cell: usize) -> Vec<f32> {
    let mut game = Corridor::new();
    game.pos = cell;
    game.draw();
    let mut observer = Observer::new(Pipeline::Vanilla);
    observer.reset(&game);
    let table = agent.config.normalization.table();
    let mut input = Tensor::zeros(&[1, 88, 80, 1]);
    observer.write_input(&table, input.data_mut());
    agent.learner.online.forward(&input).data().to_vec()
}

/// Rollouts, Q(λ) returns, minibatches and RAdam together: PQN learns the corridor's optimal
/// policy and values near `γ^k` without a replay memory or a target network.
#[test]
fn pqn_learns_a_toy_corridor() {
    let mut agent = PqnAgent::new(toy_config(), corridors(4)).unwrap();
    while agent.counters.agent_steps < 4_000 {
        agent.play_rollout().unwrap();
    }
    assert_eq!(agent.counters.agent_steps % 64, 0);
    assert_eq!(
        agent.counters.train_steps,
        agent.counters.agent_steps / 64 * 16
    );
    for cell in 0..LEN - 1 {
        common::corridor::assert_learned(cell, &q_of(&mut agent, cell));
    }
    // Late episodes walk straight to the goal (ε = 0.05 aside): the rows of the rollouts
    // played so far are handed out first, oldest first.
    let early = agent.pending();
    assert!(early > 300, "{early} episodes in 4 000 agent steps");
    for _ in 0..early {
        agent.play_episode().unwrap();
    }
    let mut lengths = Vec::new();
    while lengths.len() < 40 {
        let row = agent.play_episode().unwrap();
        assert!(row.episode as usize > lengths.len());
        lengths.push(row.length);
    }
    let straight = lengths.iter().filter(|&&l| l == LEN as u64 - 1).count();
    assert!(straight >= 30, "episode lengths {lengths:?}");
}

/// Rows are numbered in the order the games end their episodes, each counting its own steps,
/// and are handed out one by one.
#[test]
fn pqn_rows_count_every_game_s_episodes() {
    let mut agent = PqnAgent::new(toy_config(), corridors(4)).unwrap();
    let mut rows = Vec::new();
    for _ in 0..50 {
        rows.push(agent.play_episode().unwrap());
    }
    assert_eq!(agent.counters.episodes, 50);
    for (i, row) in rows.iter().enumerate() {
        assert_eq!(row.episode, i as u64 + 1);
        assert!((LEN as u64 - 1..=12).contains(&row.length), "{row:?}");
        assert!(row.agent_steps <= agent.counters.agent_steps);
    }
    assert!(rows
        .windows(2)
        .all(|w| w[0].agent_steps <= w[1].agent_steps));
    // Every agent step is some game's: the finished episodes' and those in progress.
    let finished: u64 = rows.iter().map(|r| r.length).sum();
    assert!(finished <= agent.counters.agent_steps);
}

/// The same seed gives the same run; an agent resumed from another's state, learner and
/// counters between rollouts continues exactly as the original does.
#[test]
fn pqn_is_deterministic_and_resumes_exactly() {
    let mut a = PqnAgent::new(toy_config(), corridors(4)).unwrap();
    let mut b = PqnAgent::new(toy_config(), corridors(4)).unwrap();
    for _ in 0..5 {
        a.play_rollout().unwrap();
        b.play_rollout().unwrap();
    }
    let steady = |c: &invaders::dqn::checkpoint::Counters| {
        (c.episodes, c.agent_steps, c.frames, c.train_steps)
    };
    assert_eq!(steady(&a.counters), steady(&b.counters));
    // Everything but the rows' wall times (the states kept out of the message: frames are
    // big).
    let timeless = |mut s: invaders::dqn::AgentState| {
        for r in &mut s.finished {
            r.wall_seconds = 0.0;
            // NaN (no gradient step in the episode) is not equal to itself.
            for v in [&mut r.mean_loss, &mut r.mean_max_q] {
                if v.is_nan() {
                    *v = -1.0;
                }
            }
        }
        s
    };
    assert!(
        timeless(a.state()) == timeless(b.state()),
        "two runs of one seed differ"
    );
    // Resume c from a's state (a copy of its learner: weights and optimizer).
    let mut learner = Learner::from_config(&a.config, 2, &mut common::rng(99));
    learner.online.copy_params_from(&a.learner.online);
    learner.adam = a.learner.adam.clone();
    let mut c = PqnAgent::resume(
        corridors(4),
        a.config.clone(),
        a.counters,
        learner,
        a.state(),
    )
    .unwrap();
    let rows_a: Vec<_> = (0..30).map(|_| a.play_episode().unwrap()).collect();
    let rows_c: Vec<_> = (0..30).map(|_| c.play_episode().unwrap()).collect();
    // Wall times differ; everything else is the same.
    let strip = |rows: &[invaders::dqn::EpisodeRow]| {
        rows.iter()
            .map(|r| {
                (
                    r.episode,
                    r.agent_steps,
                    r.reward,
                    r.length,
                    r.mean_loss.to_bits(),
                )
            })
            .collect::<Vec<_>>()
    };
    assert_eq!(strip(&rows_a), strip(&rows_c));
    for (p, q) in a.learner.online.params().zip(c.learner.online.params()) {
        assert_eq!(p.value, q.value, "{}", p.name);
    }
    // A wrong number of games, or a configuration without the table, is refused.
    assert!(PqnAgent::new(toy_config(), corridors(3)).is_err());
    let mut dqn = toy_config();
    dqn.pqn = None;
    assert!(PqnAgent::new(dqn, corridors(4)).is_err());
}

/// A PQN checkpoint holds every game (observers, saved states, episodes in progress) and the
/// rows not yet handed out: the agent it loads into continues exactly as the saved one. A
/// checkpoint missing that state, or a DQN configuration's checkpoint given it, is refused.
/// PQN's learner has no target network, so its checkpoint holds none; one written while it
/// still had one (a copy of the online network) loads the same.
#[test]
fn pqn_checkpoints_round_trip() {
    let mut a = PqnAgent::new(toy_config(), corridors(4)).unwrap();
    for _ in 0..3 {
        a.play_rollout().unwrap();
    }
    assert!(a.learner.target_if_any().is_none(), "PQN has no target");
    // Rows pending, and a NaN mean among them (episodes before the first gradient step).
    assert!(a.pending() > 0);
    let state = a.state();
    assert!(state.finished.iter().any(|r| r.mean_loss.is_nan()));
    assert_eq!(state.other_games.len(), 3);
    let bytes = checkpoint::to_bytes(&a.config, &a.counters, &a.learner, &state, None).unwrap();
    let names = safetensors::SafeTensors::deserialize(&bytes)
        .unwrap()
        .names()
        .len();
    let mut old = a.config.clone();
    old.pqn = None;
    let mut with_target = Learner::from_config(&old, a.learner.n_actions(), &mut common::rng(0));
    with_target.online.copy_params_from(&a.learner.online);
    with_target.update_target();
    with_target.adam = a.learner.adam.clone();
    let older = checkpoint::to_bytes(&a.config, &a.counters, &with_target, &state, None).unwrap();
    let older_names = safetensors::SafeTensors::deserialize(&older)
        .unwrap()
        .names()
        .len();
    assert_eq!(older_names, names + a.learner.online.params().count());
    let from_older = checkpoint::from_bytes(&older).unwrap();
    assert!(from_older.learner.target_if_any().is_none());
    for (p, q) in from_older
        .learner
        .online
        .params()
        .zip(a.learner.online.params())
    {
        assert_eq!(p.value, q.value, "{}", p.name);
    }
    let back = checkpoint::from_bytes(&bytes).unwrap();
    assert_eq!(back.counters, a.counters);
    assert_eq!(back.agent.players, state.players);
    assert_eq!(back.agent.other_games, state.other_games);
    assert_eq!(back.agent.finished.len(), state.finished.len());
    let mut c = back.into_pqn_agent(corridors(4)).unwrap();
    for _ in 0..40 {
        let (ra, rc) = (a.play_episode().unwrap(), c.play_episode().unwrap());
        assert_eq!(
            (
                ra.episode,
                ra.agent_steps,
                ra.reward,
                ra.length,
                ra.wall_seconds > 0.0
            ),
            (rc.episode, rc.agent_steps, rc.reward, rc.length, true)
        );
        assert_eq!(ra.mean_loss.to_bits(), rc.mean_loss.to_bits());
    }
    for (p, q) in a.learner.online.params().zip(c.learner.online.params()) {
        assert_eq!(p.value, q.value, "{}", p.name);
    }
    // The state is checked against the configuration both ways.
    let mut dqn = a.config.clone();
    dqn.pqn = None;
    let wrong = checkpoint::to_bytes(&dqn, &a.counters, &a.learner, &a.state(), None).unwrap();
    assert!(
        checkpoint::from_bytes(&wrong).is_err(),
        "PQN tensors in a DQN checkpoint"
    );
    let mut fewer = a.config.clone();
    fewer.pqn = Some(Pqn {
        games: 2,
        ..fewer.pqn.unwrap()
    });
    let wrong = checkpoint::to_bytes(&fewer, &a.counters, &a.learner, &a.state(), None).unwrap();
    let err = format!("{:#}", checkpoint::from_bytes(&wrong).err().unwrap());
    assert!(err.contains("games"), "{err}");
}

/// A PQN run of Space Invaders from the command line: two games, rollouts of 32 steps.
const PQN_RUN: &str = "preset = \"strong\"
precision = \"f32\"
layer_norm = true
radam = true
checkpoint_every = 1
[pqn]
games = 2
rollout = 32
epochs = 1
minibatches = 2
";

/// `train` runs PQN from a config's `[pqn]` table: stopped after 2 episodes and resumed to 4 it
/// ends as the run never stopped (metrics rows, weights), with no replay file, and `eval` plays
/// its checkpoint.
#[test]
fn a_pqn_run_resumes_exactly_from_the_command_line() {
    use common::cli::{metrics_but_wall_time, online_weights};
    let (root, cfg) = common::cli::tmp_with_file("invaders-pqn", "resume", "config.toml", PQN_RUN);
    let (straight, split) = common::cli::straight_and_resumed(&root, &cfg, 4, 2, 4);
    assert_eq!(
        metrics_but_wall_time(&straight),
        metrics_but_wall_time(&split)
    );
    let load =
        |dir: &std::path::Path| checkpoint::load(&dir.join("checkpoint.safetensors")).unwrap();
    let (a, b) = (load(&straight), load(&split));
    assert!(a.counters.train_steps > 20, "learning ran");
    assert_eq!(
        a.counters,
        Counters {
            wall_seconds: a.counters.wall_seconds,
            ..b.counters
        }
    );
    assert_eq!(online_weights(&a), online_weights(&b));
    assert!(a.replay_file.is_none());
    let names: Vec<String> = std::fs::read_dir(&straight)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert!(!names.iter().any(|n| n.starts_with("replay")), "{names:?}");
    let out = common::cli::eval(&straight.join("checkpoint.safetensors"), "1");
    assert!(out.contains("mean"), "{out}");
    let _ = std::fs::remove_dir_all(&root);
}
