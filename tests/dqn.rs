//! The DQN machinery: learning a toy game end to end, the replay memory's stacks, the
//! configuration, and checkpoints.

mod common;

use common::corridor::{Corridor, LEN};
use invaders::dqn::checkpoint;
use invaders::dqn::{greedy, input_border, Agent, Batch, Config, Learner, Preset, Replay};
use invaders::env::{Game, Observer, Pipeline, StepResult, FRAME_LEN};
use invaders::ops::plan::Precision;
use invaders::tensor::bf16::to_bf16;
use invaders::tensor::{Padding, Tensor};
use proptest::prelude::*;
use rand::Rng;

fn toy_config() -> Config {
    Config {
        gamma: 0.9,
        train_every: 1,
        epsilon_decay_steps: 600,
        epsilon_end: 0.1,
        ..common::small_config(1_000, 16, 64, 25, 3)
    }
}

/// Replay, target network, loss and optimizer together: the agent learns the optimal policy of
/// the corridor and Q-values near γ^k.
#[test]
fn dqn_learns_a_toy_corridor() {
    learns(|c| c.precision = Precision::F32);
}

/// The same in bf16 (issue 19: learning parity), with the bf16 kernels asserted where the CPU
/// has AVX512-BF16 (`vdpbf16ps`, or AMX tiles where it has those too; elsewhere the products
/// run in f32 and this is the test above again).
#[test]
fn dqn_learns_a_toy_corridor_in_bf16() {
    let before = invaders::tensor::cpu::paths(invaders::tensor::cpu::Family::Bf16);
    learns(|c| c.precision = Precision::Bf16);
    let ran = invaders::tensor::cpu::paths(invaders::tensor::cpu::Family::Bf16).since(before);
    assert_eq!(
        ran.avx512 + ran.amx > 0,
        invaders::tensor::cpu::avx512_bf16(),
        "bf16 kernels ran: {ran:?}"
    );
    assert_eq!(
        ran.amx > 0,
        invaders::tensor::cpu::amx(),
        "AMX tiles ran: {ran:?}"
    );
}

/// An implicit quantile head (8 fractions in the loss and for the target, 8 midpoints for Q)
/// with Munchausen targets learns the corridor too: its `Q` (the mean over the midpoints) near
/// γ^k. (Munchausen's entropy term lowers the values by at most `τ log 2` per step: 0.02 here.)
#[test]
fn iqn_with_munchausen_learns_a_toy_corridor() {
    learns(|c| {
        c.iqn_samples = 8;
        c.iqn_target_samples = 8;
        c.iqn_policy_samples = 8;
        c.munchausen_alpha = 0.9;
    });
}

/// Acting beside learning (`act_while_learning`, one update every 2 steps, so that the step
/// after each update acts with the parameters from before it) the agent learns the corridor too.
#[test]
fn acting_while_learning_learns_a_toy_corridor() {
    learns(|c| {
        c.act_while_learning = true;
        c.train_every = 2;
    });
}

/// Playing 4 corridors side by side (`games = 4`: one acting pass for the 4, each game in its
/// own lane of the replay memory) the agent learns the corridor too.
#[test]
fn games_side_by_side_learn_a_toy_corridor() {
    learns(|c| c.games = 4);
}

/// And 2 games with each update beside the play (`act_while_learning`, one update every 2
/// steps, as `acting_while_learning_learns_a_toy_corridor`).
#[test]
fn games_beside_the_update_learn_a_toy_corridor() {
    learns(|c| {
        c.games = 2;
        c.act_while_learning = true;
        c.train_every = 2;
    });
}

/// With layer normalisation before each ReLU (`layer_norm`) the agent learns the corridor too.
#[test]
fn layer_norm_learns_a_toy_corridor() {
    learns(|c| {
        c.precision = Precision::F32;
        c.layer_norm = true;
    });
}

/// With VALID convolutions (`padding = "valid"`, no zero border around the batches) the agent
/// learns the corridor too.
#[test]
fn valid_convolutions_learn_a_toy_corridor() {
    learns(|c| {
        c.precision = Precision::F32;
        c.padding = Padding::Valid;
    });
}

/// `strong` is `strong-v1` with every-16-cap's keys (issue #43's best), its precision left to
/// the host (`auto`): that lever file over `strong` resolves to the configuration its kept
/// records hold, so they and a run of it still count as that arm; over `strong-v1` it is the
/// arm as it was run. Nothing else of `strong-v1` moved.
#[test]
fn strong_is_strong_v1_learning_every_16_steps_to_40m_frames() {
    let file = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/docs/strong/levers/every-16-cap.toml"
    );
    let lever = std::fs::read_to_string(file).unwrap();
    let strong = Config::preset(Preset::Strong);
    let (v1, on_strong, on_v1) = (
        Config::preset(Preset::StrongV1),
        Config::resolve(Some(Preset::Strong), Some(&lever)).unwrap(),
        Config::resolve(Some(Preset::StrongV1), Some(&lever)).unwrap(),
    );
    assert_eq!(
        (strong.preset, v1.preset),
        (Preset::Strong, Preset::StrongV1)
    );
    assert_eq!((strong.max_frames, v1.max_frames), (40_000_000, 13_500_000));
    assert_eq!((strong.train_every, v1.train_every), (16, 4));
    assert_eq!(
        (strong.precision, on_strong.precision),
        (Precision::Auto, Precision::Bf16)
    );
    let record = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/docs/strong/levers/every-16-cap/strong-seed1/config.toml"
    );
    let record = Config::resolve(None, Some(&std::fs::read_to_string(record).unwrap())).unwrap();
    let same = |c: &Config| Config {
        seed: record.seed,
        max_frames: record.max_frames,
        preset: record.preset,
        ..c.clone()
    };
    assert_eq!(same(&on_strong).to_toml(), record.to_toml());
    assert_eq!(same(&on_v1).to_toml(), record.to_toml());
    let as_run = Config {
        precision: Precision::Bf16,
        ..strong.clone()
    };
    assert_eq!(same(&as_run).to_toml(), record.to_toml());
}

/// `padding` is `same` unless a file says `valid`; anything else is refused, naming the key.
#[test]
fn padding_is_same_unless_asked() {
    assert_eq!(Config::preset(Preset::Strong).padding, Padding::Same);
    let c = Config::resolve(Some(Preset::Strong), Some("padding = \"valid\"")).unwrap();
    assert_eq!(c.padding, Padding::Valid);
    // A run's recorded configuration keeps it.
    let again = Config::resolve(None, Some(&toml::to_string(&c).unwrap())).unwrap();
    assert_eq!(again.padding, Padding::Valid);
    let err = format!(
        "{:#}",
        Config::resolve(None, Some("padding = \"full\"")).unwrap_err()
    );
    assert!(err.contains("padding") && err.contains("valid"), "{err}");
}

/// An agent of [`toy_config`] changed by `set` learns the corridor.
fn learns(set: impl FnOnce(&mut Config)) {
    let mut config = toy_config();
    set(&mut config);
    let games = (0..config.games).map(|_| Corridor::new()).collect();
    let mut agent = Agent::with_games(config, games).unwrap();
    for _ in 0..120 {
        agent.play_episode().unwrap();
    }
    // Greedy play from the start walks straight to the goal.
    let mut game = Corridor::new();
    let mut observer = Observer::new(Pipeline::Vanilla);
    let table = agent.config.normalization.table();
    let mut input = Tensor::zeros(&[1, 88, 80, 1]);
    game.reset();
    observer.reset(&game);
    let (mut ret, mut steps) = (0.0, 0);
    loop {
        let a = greedy(
            &mut agent.learner.online,
            &invaders::dqn::Head::of(&agent.config),
            &observer,
            &table,
            &mut input,
            2,
        );
        let r = game.step(a);
        observer.step(&game);
        ret += r.reward;
        steps += 1;
        if r.terminal || r.truncated {
            break;
        }
    }
    assert_eq!((ret, steps), (1.0, LEN - 1), "greedy return and length");
    // And its value estimates are close to the true ones, γ^(LEN-2-i) for moving right.
    for cell in 0..LEN - 1 {
        game.pos = cell;
        game.draw();
        observer.reset(&game);
        observer.write_input(&table, input.data_mut());
        let q = match agent.config.iqn() {
            None => agent.learner.online.forward(&input).data().to_vec(),
            Some(iqn) => {
                let k = iqn.policy_samples;
                agent
                    .learner
                    .online
                    .set_fractions(&invaders::dqn::midpoints(k, 1));
                let rows = agent.learner.online.forward(&input).data().to_vec();
                (0..2)
                    .map(|a| (0..k).map(|r| rows[r * 2 + a]).sum::<f32>() / k as f32)
                    .collect()
            }
        };
        common::corridor::assert_learned(cell, &q);
    }
}

/// A game of scripted lives: step `k` (from 1) shows `lives[k − 1]` and scores 1, and the last
/// step ends the game.
struct Scripted {
    lives: &'static [i32],
    steps: usize,
    frame: Vec<u8>,
}

impl Scripted {
    /// Six steps, three lives: one lost on step 2, one on step 4, the game over on step 6.
    fn three_lives() -> Scripted {
        Scripted::new(&[3, 2, 2, 1, 1, 0])
    }

    /// Four steps: a bomb takes one of three lives on step 3, and on step 4 the invaders land,
    /// ending the game with the two lives left.
    fn landing() -> Scripted {
        Scripted::new(&[3, 3, 2, 0])
    }

    fn new(lives: &'static [i32]) -> Scripted {
        Scripted {
            lives,
            steps: 0,
            frame: vec![0; FRAME_LEN],
        }
    }
}

impl Game for Scripted {
    fn n_actions(&self) -> usize {
        2
    }
    fn reset(&mut self) {
        self.steps = 0;
    }
    fn step(&mut self, _action: usize) -> StepResult {
        self.steps += 1;
        StepResult {
            lives: self.lives[self.steps - 1],
            ..common::toy_step(1.0, self.steps == self.lives.len(), false)
        }
    }
    fn observation(&self) -> &[u8] {
        &self.frame
    }
}

/// `life_loss_terminal` marks the steps that lose a life as terminal in the replay memory (the
/// TD target stops there) while the episode plays on; without it only the game over is.
#[test]
fn a_lost_life_ends_bootstrapping_only_when_asked() {
    for (switch, expect_done) in [(false, vec![5]), (true, vec![1, 3, 5])] {
        let mut c = toy_config();
        c.life_loss_terminal = switch;
        let mut agent = Agent::new(c, Scripted::three_lives());
        let row = agent.play_episode().unwrap();
        assert_eq!(row.length, 6, "the episode goes on after a lost life");
        let (_, _, _, flags) = agent.replay.parts();
        let done: Vec<usize> = (0..flags.len())
            .filter(|&i| flags[i] & invaders::dqn::FLAG_DONE != 0)
            .collect();
        assert_eq!(done, expect_done, "life_loss_terminal = {switch}");
    }
}

/// `life_penalty` takes its value from the learner's reward once per life lost: once for the
/// bomb, twice for the landing that takes two lives; the game's score is left alone.
#[test]
fn each_lost_life_costs_the_life_penalty() {
    for (penalty, expect) in [(0.0, [1.0, 1.0, 1.0, 1.0]), (0.25, [1.0, 1.0, 0.75, 0.5])] {
        let mut c = toy_config();
        c.life_loss_terminal = true;
        c.life_penalty = penalty;
        let mut agent = Agent::new(c, Scripted::landing());
        let row = agent.play_episode().unwrap();
        assert_eq!(row.reward, 4.0, "the score counts the game's rewards");
        let (_, _, rewards, flags) = agent.replay.parts();
        // Entry `k` holds the frame before step `k + 1` with that step's action, reward and end.
        assert_eq!(&rewards[..4], &expect, "life_penalty = {penalty}");
        let done: Vec<usize> = (0..flags.len())
            .filter(|&i| flags[i] & invaders::dqn::FLAG_DONE != 0)
            .collect();
        assert_eq!(done, vec![2, 3]);
    }
}

fn frame(v: u8) -> Vec<u8> {
    vec![v; FRAME_LEN]
}

/// The first pixel of each of the 4 frames of state `b` in a batch of [`frame`]-built stacks.
fn px(t: &Tensor<f32>, b: usize) -> Vec<f32> {
    t.data()[b * FRAME_LEN * 4..][..4].to_vec()
}

/// The stack of 4 frames ending at frame `newest` of an episode that began at frame `first`
/// (whose first frame is repeated at its start), as [`px`] reads it.
fn stack(newest: u8, first: u8) -> Vec<f32> {
    (0..4)
        .map(|i| newest.saturating_sub(3 - i).max(first) as f32)
        .collect()
}

/// Draws `rounds` batches of 8 four-frame states from `replay` (with a generator of `seed`) and
/// calls `check` with each batch and each index in it.
fn for_each_sampled(
    replay: &mut Replay, seed: u64, rounds: usize, mut check: impl FnMut(&Batch, usize),
) {
    let table = common::identity_table();
    let mut batch = Batch::new(8, [88, 80, 4]);
    let mut rng = common::rng(seed);
    for _ in 0..rounds {
        replay.sample(&mut rng, &table, &mut batch);
        for b in 0..8 {
            check(&batch, b);
        }
    }
}

/// States are rebuilt from single frames: the last 4 of the same episode, the first frame
/// repeated at an episode's start, never a frame of the previous episode; `s'` is the state one
/// entry later; terminal and time-limit flags go where they belong.
#[test]
fn replay_rebuilds_stacks_within_episodes() {
    let mut replay = Replay::new(64, 4);
    // Episode A: frames 10, 11, 12 (terminal). Episode B: frames 20..=29.
    replay.push_start(&frame(10));
    replay.push_step(1, 1.0, false, &frame(11));
    replay.push_step(2, 2.0, true, &frame(12));
    replay.push_start(&frame(20));
    for i in 1..10u8 {
        replay.push_step(i as usize % 6, i as f32, false, &frame(20 + i));
    }
    for_each_sampled(&mut replay, 1, 80, |batch, b| {
        let (s, s2) = (px(&batch.states, b), px(&batch.next_states, b));
        let newest = s[3] as u8;
        let first = if newest >= 20 { 20 } else { 10 };
        assert_eq!(s, stack(newest, first), "state ending at {newest}");
        assert_eq!(s2, stack(newest + 1, first), "next state after {newest}");
        assert!(
            newest != 12 && newest != 29,
            "entries without a successor are never sampled"
        );
        match newest {
            10 => assert_eq!(
                (batch.actions[b], batch.rewards[b], batch.dones[b]),
                (1, 1.0, false)
            ),
            11 => assert_eq!(
                (batch.actions[b], batch.rewards[b], batch.dones[b]),
                (2, 2.0, true)
            ),
            n => {
                let i = n - 20 + 1;
                assert_eq!(
                    (batch.actions[b], batch.rewards[b], batch.dones[b]),
                    (i as usize % 6, i as f32, false)
                );
            }
        }
    });
}

/// What `replay_sums_n_step_returns_within_episodes` expects of the state ending at frame `f` of
/// its episodes A (10 → 14), B (20 → 24) and C (30 → 32), n = 3, γ = 0.5: `(R, m, done, newest
/// frame of s', first frame of the episode)`.
fn three_episodes_expected(f: u8) -> (f32, u32, bool, u8, u8) {
    match f {
        10 => (1.0 + 0.5 * 2.0 + 0.25 * 4.0, 3, false, 13, 10),
        11 => (2.0 + 0.5 * 4.0 + 0.25 * 8.0, 3, true, 14, 10),
        12 => (4.0 + 0.5 * 8.0, 2, true, 14, 10),
        13 => (8.0, 1, true, 14, 10),
        20 => (1.0 + 0.5 + 0.25, 3, true, 23, 20),
        21 => (1.0 + 0.5, 2, true, 23, 20),
        22 => (1.0, 1, true, 23, 20),
        23 => (1.0, 1, false, 24, 20),
        30 => (2.0 + 0.5 * 2.0, 2, false, 32, 30),
        31 => (2.0, 1, false, 32, 30),
        f => panic!("entry {f} has no successor and must not be sampled"),
    }
}

/// n-step returns (n = 3, γ = 0.5, so every sum is exact) against sums worked out by hand: they
/// stop at a terminal step (a game over, or a lost life marked done while the episode goes on),
/// at an episode cut by its time limit, and at the newest step; `s'` is the state `m` entries on,
/// its stack running across a lost life but never into another episode.
#[test]
fn replay_sums_n_step_returns_within_episodes() {
    let mut replay = Replay::new(64, 4).with_returns(3, 0.5);
    // Episode A: 10 → 14, rewards 1, 2, 4, 8, game over on the last step.
    replay.push_start(&frame(10));
    for (i, r) in [1.0, 2.0, 4.0, 8.0].into_iter().enumerate() {
        replay.push_step(i, r, i == 3, &frame(11 + i as u8));
    }
    // Episode B: 20 → 24, reward 1 each step, a life lost (done) on the step to 23, cut at 24.
    replay.push_start(&frame(20));
    for i in 0..4u8 {
        replay.push_step(i as usize, 1.0, i == 2, &frame(21 + i));
    }
    // Episode C, still running: 30 → 32, reward 2 each step.
    replay.push_start(&frame(30));
    replay.push_step(4, 2.0, false, &frame(31));
    replay.push_step(5, 2.0, false, &frame(32));
    let mut seen = std::collections::BTreeSet::new();
    for_each_sampled(&mut replay, 2, 100, |batch, b| {
        let f = px(&batch.states, b)[3] as u8;
        let (ret, m, done, next, first) = three_episodes_expected(f);
        assert_eq!(px(&batch.states, b), stack(f, first), "state ending at {f}");
        assert_eq!(
            (batch.rewards[b], batch.steps[b], batch.dones[b]),
            (ret, m, done),
            "return from {f}"
        );
        assert_eq!(
            px(&batch.next_states, b),
            stack(next, first),
            "s' of the return from {f}"
        );
        seen.insert(f);
    });
    assert_eq!(seen.len(), 10, "every sampleable entry drawn: {seen:?}");
}

/// Three games written side by side into the lanes of one memory (`Replay::with_lanes`, as
/// `games = 3` does), their pushes interleaved, give each game's transitions as a memory of its
/// own would: the episodes of `replay_sums_n_step_returns_within_episodes`, one per lane, give
/// the same states, n-step returns and next states, and never a frame of another lane. Then
/// the lanes survive a checkpoint's round trip (`parts`, `restore`): the same draws follow.
#[test]
fn replay_lanes_keep_each_games_transitions_apart() {
    let mut replay = Replay::new(63, 4).with_lanes(3).with_returns(3, 0.5);
    // Lane 0: episode A, 10 → 14. Lane 1: episode B, 20 → 24. Lane 2: episode C, 30 → 32.
    let a = [(1.0, false), (2.0, false), (4.0, false), (8.0, true)];
    let b = [(1.0, false), (1.0, false), (1.0, true), (1.0, false)];
    let c = [(2.0, false), (2.0, false)];
    for (lane, first) in [(0, 10), (1, 20), (2, 30)] {
        replay.push_start_in(lane, &frame(first));
    }
    for i in 0..4 {
        for (lane, steps, first) in [(2, &c[..], 30), (0, &a[..], 10), (1, &b[..], 20)] {
            if let Some(&(r, done)) = steps.get(i) {
                replay.push_step_in(lane, i, r, done, &frame(first + 1 + i as u8));
            }
        }
    }
    assert_eq!(replay.len(), 13);
    assert_eq!(replay.lane_written(), &[5, 5, 3]);
    let table = common::identity_table();
    let draws = |replay: &mut Replay| {
        let mut batch = Batch::new(2, [88, 80, 4]);
        let mut rng = common::rng(5);
        let mut seen = Vec::new();
        for _ in 0..200 {
            replay.sample(&mut rng, &table, &mut batch);
            for i in 0..2 {
                let f = px(&batch.states, i)[3] as u8;
                let (ret, m, done, next, first) = three_episodes_expected(f);
                assert_eq!(px(&batch.states, i), stack(f, first), "state ending at {f}");
                assert_eq!(
                    (
                        batch.rewards[i],
                        batch.steps[i],
                        batch.dones[i],
                        batch.actions[i]
                    ),
                    (ret, m, done, (f - first) as usize),
                    "return from {f}"
                );
                assert_eq!(px(&batch.next_states, i), stack(next, first), "s' of {f}");
                seen.push(f);
            }
        }
        seen
    };
    let seen = draws(&mut replay);
    let distinct: std::collections::BTreeSet<_> = seen.iter().collect();
    assert_eq!(
        distinct.len(),
        10,
        "every sampleable entry drawn: {distinct:?}"
    );
    // The round trip: a lane behind the others leaves rows of its own unwritten.
    let (frames, actions, rewards, flags) = replay.parts();
    assert_eq!(actions.len(), 15, "5 rows of 3 lanes");
    let mut back = Replay::new(63, 4).with_lanes(3).with_returns(3, 0.5);
    back.restore(replay.lane_written(), actions, rewards, &flags, |to| {
        to.copy_from_slice(frames);
        Ok(())
    })
    .unwrap();
    assert!(back.parts() == replay.parts());
    assert_eq!(
        draws(&mut back),
        seen,
        "the same draws after the round trip"
    );
    let err = Replay::new(63, 4)
        .with_lanes(3)
        .restore(&[13], actions, rewards, &flags, |_| Ok(()))
        .unwrap_err();
    assert!(err.contains("3"), "{err}");
}

/// Prioritized sampling over lanes: each lane's entries get their priorities, and a lane's
/// overwritten entries (the ring wrapped within it) are never drawn.
#[test]
fn prioritized_lanes_draw_only_held_entries() {
    let mut replay = Replay::new(40, 4).with_lanes(2).with_priorities(0.5, 0.5);
    // Lane 0 writes 3 episodes of 10 entries (it wraps: 20 slots), lane 1 one of 6.
    for ep in 0..3u8 {
        replay.push_start_in(0, &frame(100 + 10 * ep));
        for i in 1..10u8 {
            replay.push_step_in(0, 0, 1.0, i == 9, &frame(100 + 10 * ep + i));
        }
    }
    replay.push_start_in(1, &frame(50));
    for i in 1..6u8 {
        replay.push_step_in(1, 1, 0.0, false, &frame(50 + i));
    }
    let table = common::identity_table();
    let mut batch = Batch::new(4, [88, 80, 4]);
    let mut rng = common::rng(9);
    let mut seen = std::collections::BTreeSet::new();
    for _ in 0..300 {
        replay.sample(&mut rng, &table, &mut batch);
        let td: Vec<f32> = batch.entries.iter().map(|&g| (g % 7) as f32).collect();
        let entries = batch.entries.clone();
        replay.update_priorities(&entries, &td);
        for i in 0..4 {
            let f = px(&batch.states, i)[3] as u8;
            let (lane0, lane1) = ((110..=128).contains(&f), (50..=54).contains(&f));
            assert!(lane0 || lane1, "frame {f} is held and has a successor");
            assert_eq!(batch.actions[i], lane1 as usize, "frame {f}'s action");
            seen.insert(f);
        }
    }
    assert!(seen.len() > 15, "draws spread over both lanes: {seen:?}");
}

/// A replay memory of 40 patterned frames (a terminal every 13 steps) and a table that maps
/// bytes into [−0.5, 0.5]: batches to sample for the batch-layout tests below.
fn patterned_replay() -> (Replay, [f32; 256]) {
    let mut replay = Replay::new(64, 4);
    replay.push_start(&frame(0));
    for i in 1..40u8 {
        let f: Vec<u8> = (0..FRAME_LEN).map(|p| (p as u8).wrapping_mul(i)).collect();
        replay.push_step(i as usize % 6, i as f32, i % 13 == 0, &f);
    }
    (replay, std::array::from_fn(|i| i as f32 / 255.0 - 0.5))
}

/// The agent's batches are written inside conv1's padding (a zero border), which conv1 reads in
/// place: the states are the plain batch's inside zeros, and a train step on them is
/// bit-identical to one on the plain batch.
#[test]
fn padded_batches_train_exactly_like_plain_ones() {
    let (mut replay, table) = patterned_replay();
    let border = input_border([88, 80, 4], Padding::Same);
    assert_eq!(
        (border.top, border.bottom, border.left, border.right),
        (2, 2, 2, 2)
    );
    // VALID convolutions (`padding = "valid"`) need no border: their batches are plain ones.
    assert!(input_border([88, 80, 4], Padding::Valid).is_none());
    let (mut plain, mut padded) = (
        Batch::new(8, [88, 80, 4]),
        Batch::padded(8, [88, 80, 4], Padding::Same),
    );
    replay.sample(&mut common::rng(3), &table, &mut plain);
    replay.sample(&mut common::rng(3), &table, &mut padded);
    assert_eq!(padded.states.shape(), &[8, 92, 84, 4]);
    for (p, q) in [
        (&plain.states, &padded.states),
        (&plain.next_states, &padded.next_states),
    ] {
        for b in 0..8 {
            for y in 0..92 {
                for x in 0..84 {
                    let got = &q.data()[((b * 92 + y) * 84 + x) * 4..][..4];
                    if border.contains(92, 84, y, x) {
                        assert_eq!(got, [0.0; 4], "border place ({y}, {x})");
                    } else {
                        let want = &p.data()[((b * 88 + y - 2) * 80 + x - 2) * 4..][..4];
                        assert_eq!(got, want, "pixel ({y}, {x}) of state {b}");
                    }
                }
            }
        }
    }
    train_alike(&plain, &padded, Precision::F32);
}

/// Two train steps of two learners of one seed, one on `a` and one on `b`, give the same losses
/// and the same weights, bit for bit.
fn train_alike(a: &Batch, b: &Batch, precision: Precision) {
    let (mut one, mut two) = (
        Learner::new([88, 80, 4], 6, 1e-3, 0.97, &mut common::rng(4)),
        Learner::new([88, 80, 4], 6, 1e-3, 0.97, &mut common::rng(4)),
    );
    one.set_precision(precision);
    two.set_precision(precision);
    for _ in 0..2 {
        assert_eq!(one.train_step(a), two.train_step(b));
    }
    for (p, q) in one.online.params().zip(two.online.params()) {
        assert!(p.value == q.value, "{} differs", p.name);
    }
}

/// A batch that keeps its states' bf16 roundings (its `keep_bf16`, as an agent in bf16 asks)
/// gets the same values from the replay memory, and beside them, border included, exactly their
/// roundings; in bf16 a train step on it gives the bits of one on a batch that keeps none (conv1
/// reads the kept roundings instead of rounding the states itself).
#[test]
fn batches_keep_their_states_rounded_to_bf16_when_asked() {
    let (mut replay, table) = patterned_replay();
    let (mut plain, mut kept) = (
        Batch::padded(8, [88, 80, 4], Padding::Same),
        Batch::padded(8, [88, 80, 4], Padding::Same),
    );
    kept.keep_bf16 = true;
    // Twice: the second batch is written over the first one's values and roundings.
    for seed in [3, 5] {
        replay.sample(&mut common::rng(seed), &table, &mut plain);
        replay.sample(&mut common::rng(seed), &table, &mut kept);
        for (p, q) in [
            (&plain.states, &kept.states),
            (&plain.next_states, &kept.next_states),
        ] {
            assert!(p.bf16().is_none(), "a plain batch keeps no roundings");
            assert_eq!(p.data(), q.data(), "the same values");
            let want: Vec<u16> = q.data().iter().map(|&v| to_bf16(v)).collect();
            assert!(
                q.bf16() == Some(&want[..]),
                "their roundings, border included"
            );
        }
    }
    train_alike(&plain, &kept, Precision::Bf16);
}

/// When the ring wraps, overwritten frames are never used, even through a state's history.
#[test]
fn replay_ring_never_uses_overwritten_frames() {
    let mut replay = Replay::new(16, 4);
    replay.push_start(&frame(0));
    for i in 1..100u32 {
        replay.push_step(0, i as f32, false, &frame((i % 250) as u8));
    }
    assert_eq!(replay.len(), 16);
    for_each_sampled(&mut replay, 2, 50, |batch, b| {
        let s = &batch.states.data()[b * FRAME_LEN * 4..][..4];
        // The oldest frame held is 84 (entries 84..=99); a state's 4 frames are consecutive.
        assert!(s[0] >= 84.0, "state {s:?} uses an overwritten frame");
        assert_eq!([s[1] - s[0], s[2] - s[1], s[3] - s[2]], [1.0, 1.0, 1.0]);
        assert_eq!(
            batch.rewards[b],
            s[3] + 1.0,
            "the reward of the step from the newest frame"
        );
    });
}

#[test]
fn presets_differ_as_documented() {
    let a = Config::preset(Preset::Article);
    assert_eq!(
        (a.replay_capacity, a.batch_size, a.learning_rate, a.gamma),
        (20_000, 48, 1e-3, 0.97)
    );
    assert_eq!(
        (a.train_every, a.learning_starts, a.target_update),
        (4, 2000, 100)
    );
    assert_eq!(
        (
            a.epsilon_start,
            a.epsilon_end,
            a.epsilon_decay_steps,
            a.episodes
        ),
        (1.0, 0.05, 500_000, 800)
    );
    assert_eq!(a.pipeline, Pipeline::StackMax);
    assert!(!a.act_with_target_network && !a.fake_terminal_transition);
    let v = Config::preset(Preset::ArticleVanilla);
    assert_eq!(v.pipeline, Pipeline::Vanilla);
    assert_eq!(v.input_shape(), [88, 80, 1]);
    let w = Config::preset(Preset::ArticleAsWritten);
    assert_eq!(w.pipeline, Pipeline::StackRunningMax);
    assert!(w.act_with_target_network && w.fake_terminal_transition);
    assert_eq!(w.normalization.apply(0), -2.0);
    assert!((a.epsilon(250_000) - 0.525).abs() < 1e-6 && a.epsilon(10_000_000) == 0.05);
}

#[test]
fn config_files_override_and_reject_bad_keys() {
    let c = Config::resolve(
        None,
        Some("preset = \"article-vanilla\"\ngamma = 0.5\n[env]\nsticky_prob = 0.0\n"),
    )
    .unwrap();
    assert_eq!(
        (c.preset, c.gamma, c.env.sticky_prob),
        (Preset::ArticleVanilla, 0.5, 0.0)
    );
    assert_eq!(
        c.env.frame_skip_min, 2,
        "other env keys keep the preset's values"
    );
    // A command-line preset wins over the file's.
    let c = Config::resolve(Some(Preset::Article), Some("preset = \"article-vanilla\"")).unwrap();
    assert_eq!(c.preset, Preset::Article);
    let err = |t: &str| format!("{:#}", Config::resolve(None, Some(t)).unwrap_err());
    assert!(err("gama = 0.5").contains("gama"), "{}", err("gama = 0.5"));
    assert!(err("[env]\nstickyprob = 1").contains("stickyprob"));
    assert!(err("gamma = 2.0").contains("gamma"));
    assert!(err("batch_size = \"big\"").contains("batch_size"));
    assert!(err("preset = \"nature\"").contains("preset"));
    assert!(err("[env]\nframe_skip_min = 0").contains("frame_skip"));
    assert!(err("not toml at all = = =").contains("TOML"));
    // The resolved config survives its own TOML.
    let c = Config::preset(Preset::ArticleAsWritten);
    assert_eq!(Config::resolve(None, Some(&c.to_toml())).unwrap(), c);
}

/// The learner's reward: the Nature DQN's clip makes every hit worth 1; `reward_scale` with a
/// wider `reward_clip` keeps the game's order (an invader 5 to 30, the mothership 200); the
/// keys default to the clip to [-1, 1] (earlier configs resolve unchanged) and refuse
/// non-positive or absurd values.
#[test]
fn rewards_are_scaled_then_clipped() {
    let strong = Config::preset(Preset::Strong);
    assert_eq!((strong.reward_scale, strong.reward_clip), (1.0, 1.0));
    let hits: Vec<f32> = [0.0, 5.0, 30.0, 200.0, -7.0]
        .iter()
        .map(|&r| strong.reward(r))
        .collect();
    assert_eq!(hits, [0.0, 1.0, 1.0, 1.0, -1.0]);
    let c = Config::resolve(
        Some(Preset::Strong),
        Some("reward_scale = 0.03125\nreward_clip = 10.0\n"),
    )
    .unwrap();
    let hits: Vec<f32> = [5.0, 30.0, 200.0, 400.0, -64.0]
        .iter()
        .map(|&r| c.reward(r))
        .collect();
    assert_eq!(hits, [0.156_25, 0.9375, 6.25, 10.0, -2.0]);
    // Without clipping only the scale applies.
    let c = Config::resolve(Some(Preset::Article), Some("reward_scale = 0.5")).unwrap();
    assert_eq!(c.reward(200.0), 100.0);
    assert_eq!(Config::preset(Preset::Article).reward(200.0), 200.0);
    let err = |t: &str| format!("{:#}", Config::resolve(None, Some(t)).unwrap_err());
    for bad in [
        "reward_scale = 0.0",
        "reward_scale = -1.0",
        "reward_clip = 0.0",
        "reward_clip = 1e9",
        "life_penalty = -1.0",
        "life_penalty = 1e9",
    ] {
        assert!(
            err(bad).contains(bad.split(' ').next().unwrap()),
            "{bad}: {}",
            err(bad)
        );
    }
    assert!(err("reward_clip = nan").contains("reward_clip"));
    assert!(err("life_penalty = nan").contains("life_penalty"));
    // The penalty comes after scaling and clipping: 400 points clip to 1, less 2 lives × 0.5.
    let c = Config::resolve(Some(Preset::Strong), Some("life_penalty = 0.5")).unwrap();
    assert_eq!(c.learner_reward(400.0, 2), 0.0);
    assert_eq!(c.learner_reward(0.0, 1), -0.5);
    assert_eq!(c.learner_reward(30.0, 0), 1.0);
}

#[test]
fn checkpoints_round_trip_and_refuse_damage() {
    let mut agent = Agent::new(toy_config(), Corridor::new());
    for _ in 0..15 {
        agent.play_episode().unwrap();
    }
    let mut counters = agent.counters;
    // A wall time whose shortest decimal form needs 17 digits: serde_json's default float
    // parser reads it back one ulp off (a CI run caught that with a real elapsed time).
    counters.wall_seconds = 1.875_943_518_000_000_1;
    assert!(agent.learner.adam.t > 0);
    let bytes = checkpoint::to_bytes(
        &agent.config,
        &counters,
        &agent.learner,
        &agent.state(),
        None,
    )
    .unwrap();
    let back = checkpoint::from_bytes(&bytes).unwrap();
    assert_eq!(back.config, agent.config);
    assert_eq!(back.counters, counters);
    assert_eq!(back.learner.adam.t, agent.learner.adam.t);
    for (restored, saved) in [
        (&back.learner.online, &agent.learner.online),
        (back.learner.target(), agent.learner.target()),
    ] {
        for (a, b) in restored.params().zip(saved.params()) {
            assert_eq!(a.value, b.value, "{}", a.name);
        }
    }
    assert_eq!(back.learner.adam.m, agent.learner.adam.m);
    assert_eq!(back.learner.adam.v, agent.learner.adam.v);
    // Damaged files are refused with an error, never a panic.
    for cut in [0, 7, 100, bytes.len() / 2, bytes.len() - 1] {
        assert!(
            checkpoint::from_bytes(&bytes[..cut]).is_err(),
            "truncated at {cut}"
        );
    }
    assert!(checkpoint::from_bytes(b"definitely not a checkpoint").is_err());
}

/// One step of the replay model: what the agent did from an entry.
#[derive(Clone, Copy, Debug)]
struct Step {
    action: usize,
    reward: f32,
    done: bool,
}

/// A plain model of the replay memory, kept by episode: every entry ever written (its frame,
/// its episode), each episode's first entry and its steps. Entry `g` is the `g − first`-th
/// observation of its episode, and acted on if the episode has a step from it.
#[derive(Default)]
struct ReplayModel {
    frames: Vec<u8>,
    episode_of: Vec<usize>,
    first: Vec<usize>,
    steps: Vec<Vec<Step>>,
}

/// What sampling entry `g` must give: the newest-last frames of `s` and `s'`, the action, the
/// return `R` over `m` steps, and whether it ended the episode's bootstrapping.
#[derive(Debug, PartialEq)]
struct Sampled {
    s: Vec<u8>,
    next: Vec<u8>,
    action: usize,
    ret: f32,
    m: u32,
    done: bool,
}

impl ReplayModel {
    fn start(&mut self, frame: u8) {
        self.first.push(self.frames.len());
        self.steps.push(Vec::new());
        self.episode_of.push(self.first.len() - 1);
        self.frames.push(frame);
    }

    fn step(&mut self, step: Step, frame: u8) {
        let e = self.first.len() - 1;
        self.steps[e].push(step);
        self.episode_of.push(e);
        self.frames.push(frame);
    }

    /// The transition from entry `g` with states of `k` frames and `n`-step returns discounted
    /// by `gamma`, for a memory of `capacity` entries; `None` if it cannot be sampled: `g` was
    /// overwritten or not acted on, or its state reaches back past the oldest entry held.
    fn sample(&self, g: usize, capacity: usize, k: usize, n: usize, gamma: f32) -> Option<Sampled> {
        let oldest = self.frames.len().saturating_sub(capacity);
        let e = self.episode_of[g];
        let (first, steps) = (self.first[e], &self.steps[e]);
        let i = g - first;
        if g < oldest || i >= steps.len() || (g + 1).saturating_sub(k).max(first) < oldest {
            return None;
        }
        // A state: the last k frames of the episode up to `h`, its first frame repeated
        // before its start.
        let state = |h: usize| -> Vec<u8> {
            (0..k)
                .map(|j| self.frames[(h + j + 1).saturating_sub(k).max(first)])
                .collect()
        };
        let (mut ret, mut discount, mut m, mut done) = (0.0, 1.0, 0, false);
        while m < n {
            let st = steps[i + m];
            ret += discount * st.reward;
            discount *= gamma;
            m += 1;
            if st.done {
                done = true;
                break;
            }
            if i + m == steps.len() {
                break; // the episode was cut there, or this is the newest entry
            }
        }
        Some(Sampled {
            s: state(g),
            next: state(g + m),
            action: steps[i].action,
            ret,
            m: m as u32,
            done,
        })
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: common::cases(32), ..ProptestConfig::default() })]

    /// The replay memory against [`ReplayModel`], written independently from its episodes:
    /// episodes of random lengths (a life lost now and then marked done mid-episode, each
    /// episode ending in a game over or cut short), a small ring that wraps many times, states
    /// of 1 and 4 frames, returns of 1 to 3 steps. At random moments (mid-episode too) every
    /// sampled `s`, `s'`, action, return, step count and done is the model's for its entry,
    /// no entry the model cannot sample is ever drawn, and every one it can is drawn.
    #[test]
    fn replay_samples_what_a_plain_model_says(
        lengths in prop::collection::vec(1usize..8, 1..30), capacity in 5usize..20,
        k in prop_oneof![Just(1usize), Just(4)], n in 1usize..=3, every in 2usize..9,
        seed in any::<u64>(),
    ) {
        const B: usize = 2;
        let gamma = 0.5;
        let mut r = common::rng(seed);
        let mut replay = Replay::new(capacity.max(k + 2), k).with_returns(n, gamma);
        let capacity = replay.capacity();
        let mut model = ReplayModel::default();
        let table: [f32; 256] = std::array::from_fn(|i| i as f32);
        let mut batch = Batch::new(B, [88, 80, k]);
        let per = batch.states.len() / B;
        // Entry g shows frame g mod 251: unique among the entries held.
        let frame_of = |g: usize| (g % 251) as u8;
        let mut pushes = 0;
        let mut check = |replay: &mut Replay, model: &ReplayModel, r: &mut rand_chacha::ChaCha8Rng| -> Result<(), TestCaseError> {
            let written = model.frames.len();
            prop_assert_eq!(replay.written(), written as u64);
            prop_assert_eq!(replay.can_sample(B), written.min(capacity) > B + k);
            let oldest = written.saturating_sub(capacity);
            let want: std::collections::BTreeSet<usize> = (oldest..written)
                .filter(|&g| model.sample(g, capacity, k, n, gamma).is_some())
                .collect();
            if !replay.can_sample(B) || want.is_empty() {
                return Ok(());
            }
            let mut seen = std::collections::BTreeSet::new();
            for _ in 0..2000 {
                replay.sample(r, &table, &mut batch);
                for b in 0..B {
                    let pixel = |t: &Tensor<f32>| -> Vec<u8> {
                        t.data()[b * per..][..k].iter().map(|&v| v as u8).collect()
                    };
                    let (s, next) = (pixel(&batch.states), pixel(&batch.next_states));
                    let g = (oldest..written).find(|&g| frame_of(g) == s[k - 1]).unwrap();
                    let got = Sampled {
                        s, next, action: batch.actions[b], ret: batch.rewards[b],
                        m: batch.steps[b], done: batch.dones[b],
                    };
                    let expected = model.sample(g, capacity, k, n, gamma);
                    prop_assert_eq!(Some(got), expected, "entry {} of {}", g, written);
                    seen.insert(g);
                }
                if seen == want {
                    break;
                }
            }
            prop_assert_eq!(seen, want, "every sampleable entry drawn");
            Ok(())
        };
        for len in lengths {
            let g = model.frames.len();
            replay.push_start(&frame(frame_of(g)));
            model.start(frame_of(g));
            pushes += 1;
            if pushes % every == 0 {
                check(&mut replay, &model, &mut r)?;
            }
            let game_over = r.random_bool(0.5);
            for i in 0..len {
                let step = Step {
                    action: r.random_range(0..6),
                    reward: [-1.0, 0.0, 0.5, 1.0, 2.0][r.random_range(0..5)],
                    done: (i + 1 == len && game_over) || r.random_bool(0.1),
                };
                let g = model.frames.len();
                replay.push_step(step.action, step.reward, step.done, &frame(frame_of(g)));
                model.step(step, frame_of(g));
                pushes += 1;
                if pushes % every == 0 {
                    check(&mut replay, &model, &mut r)?;
                }
            }
        }
        check(&mut replay, &model, &mut r)?;
    }
}
