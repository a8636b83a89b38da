//! Prioritized replay: the sum tree against a linear scan, sampling in proportion to the
//! priorities with the documented loss weights, priorities following the ring, the weighted loss
//! in the learner, and a prioritized run resumed bit for bit.

mod common;

use common::cli::{eval, resumed_like_straight};
use invaders::dqn::{Batch, Learner, Replay, SumTree};
use invaders::env::FRAME_LEN;
use proptest::prelude::*;
use rand::Rng;

proptest! {
    #![proptest_config(ProptestConfig::with_cases(common::cases(64)))]

    /// After any sequence of sets, the total is the sum of the leaves and `find(u)` is the slot a
    /// linear scan of prefix sums gives: the first `i` with `u < p_0 + … + p_i`. Priorities are
    /// multiples of 1/4, so every sum is exact and the two must agree to the last bit.
    #[test]
    fn sum_tree_finds_like_a_linear_scan(
        n in 1usize..150,
        sets in prop::collection::vec((0usize..1000, 0u32..12), 1..300),
        us in prop::collection::vec(0.0f64..1.0, 20),
    ) {
        let mut tree = SumTree::new(n);
        let mut plain = vec![0.0f64; n];
        for (i, q) in sets {
            let (i, p) = (i % n, f64::from(q) / 4.0);
            tree.set(i, p);
            plain[i] = p;
        }
        let total: f64 = plain.iter().sum();
        prop_assert_eq!(tree.total(), total);
        for (i, &p) in plain.iter().enumerate() {
            prop_assert_eq!(tree.get(i), p);
        }
        if total == 0.0 {
            prop_assert_eq!(tree.find(0.0), None);
            return Ok(());
        }
        for u in us {
            let u = u * total;
            let mut prefix = 0.0;
            let want = plain.iter().position(|&p| {
                prefix += p;
                u < prefix
            });
            prop_assert_eq!(tree.find(u), want, "u = {}", u);
        }
    }
}

/// A memory of one episode of 30 steps whose frame values are the entry numbers, so a sampled
/// state says which entry it is (one frame per state, identity normalisation).
fn numbered_memory(alpha: f64, beta: f64) -> (Replay, [f32; 256]) {
    let mut replay = Replay::new(64, 1).with_priorities(alpha, beta);
    replay.push_start(&vec![0u8; FRAME_LEN]);
    for i in 1..=30u8 {
        replay.push_step(0, 0.0, false, &vec![i; FRAME_LEN]);
    }
    let table = common::identity_table();
    (replay, table)
}

/// With α = 1 the chance of an entry is its share of `|δ| + ε`: entry 5 at TD error 9 against
/// 29 entries at 1 is drawn 9/38 of the time (20 000 draws; the bound is many standard
/// deviations wide). Its loss weight is `(N·P)^(−β)` over the batch's largest: with β = 1, the
/// ratio of the priorities, 1/9. The batch names the entries it drew.
#[test]
fn sampling_follows_the_priorities_with_the_documented_weights() {
    let (mut replay, table) = numbered_memory(1.0, 1.0);
    let entries: Vec<u64> = (0..30).collect();
    let td: Vec<f32> = entries
        .iter()
        .map(|&g| if g == 5 { 9.0 } else { -1.0 })
        .collect();
    replay.update_priorities(&entries, &td);
    let mut batch = Batch::new(10, [88, 80, 1]);
    let mut rng = common::rng(3);
    let (mut fives, mut draws) = (0, 0);
    let eps = 1e-6;
    for _ in 0..2000 {
        replay.sample(&mut rng, &table, &mut batch);
        assert_eq!(batch.weights.len(), 10);
        for b in 0..10 {
            let g = batch.states.data()[b * FRAME_LEN] as u64;
            assert_eq!(batch.entries[b], g, "the batch names the entry it drew");
            assert!(g < 30, "entry 30 has not been acted on");
            draws += 1;
            if g == 5 {
                fives += 1;
                let others = batch.entries.iter().any(|&e| e != 5);
                if others {
                    let want = (1.0 + eps) / (9.0 + eps);
                    assert!(
                        (f64::from(batch.weights[b]) - want).abs() < 1e-6,
                        "weight {} against {want}",
                        batch.weights[b]
                    );
                }
            } else {
                assert_eq!(batch.weights[b], 1.0, "the rarest draws weigh 1");
            }
        }
    }
    let share = fives as f64 / draws as f64;
    let want = (9.0 + eps) / (9.0 + eps + 29.0 * (1.0 + eps));
    assert!(
        (share - want).abs() < 0.02,
        "entry 5 drawn {share:.4} of the time, expected {want:.4}"
    );
}

/// A new entry gets the largest priority set so far; the newest entry (not acted on yet) has
/// none; once the ring wraps, an overwritten entry's slot holds the new entry's priority, so an
/// overwritten entry is never drawn.
#[test]
fn priorities_follow_the_ring() {
    let mut replay = Replay::new(8, 1).with_priorities(0.5, 0.5);
    replay.push_start(&vec![0u8; FRAME_LEN]);
    replay.push_step(0, 0.0, false, &vec![1u8; FRAME_LEN]);
    let (p, max) = replay.priorities().unwrap();
    assert_eq!((p, max), (vec![1.0, 0.0], 1.0));
    replay.update_priorities(&[0], &[15.0]);
    let big = (15.0f64 + 1e-6).sqrt();
    replay.push_step(0, 0.0, false, &vec![2u8; FRAME_LEN]);
    let (p, max) = replay.priorities().unwrap();
    assert_eq!((p, max), (vec![big, big, 0.0], big));
    // Wrap: entries 0..=2 are overwritten by 8..=10; 10 is the newest.
    for i in 3..=10u8 {
        replay.push_step(0, 0.0, false, &vec![i; FRAME_LEN]);
    }
    let (p, _) = replay.priorities().unwrap();
    assert_eq!(p[10 % 8], 0.0, "the newest entry");
    assert!(p.iter().enumerate().all(|(s, &v)| s == 2 || v == big));
    let table = common::identity_table();
    let mut batch = Batch::new(4, [88, 80, 1]);
    let mut rng = common::rng(5);
    for _ in 0..200 {
        replay.sample(&mut rng, &table, &mut batch);
        for &g in &batch.entries {
            assert!((3..=9).contains(&g), "drew entry {g}");
        }
    }
}

fn small_learner() -> Learner {
    Learner::new([12, 10, 1], 3, 1e-3, 0.9, &mut common::rng(9))
}

fn small_batch(rng: &mut impl Rng) -> Batch {
    let mut b = Batch::new(4, [12, 10, 1]);
    for v in b.states.data_mut() {
        *v = rng.random_range(-1.0..1.0);
    }
    for v in b.next_states.data_mut() {
        *v = rng.random_range(-1.0..1.0);
    }
    b.actions = vec![0, 1, 2, 1];
    b.rewards = vec![1.0, -1.0, 0.5, 0.0];
    b
}

fn params(l: &Learner) -> Vec<Vec<f32>> {
    l.online.params().map(|p| p.value.data().to_vec()).collect()
}

/// Weights of 1 change nothing (the same update, bit for bit); a weight of 0 removes a
/// transition from the update, so its reward no longer matters; a weight of 1 does not.
#[test]
fn the_learner_weights_each_transition_loss() {
    let mut rng = common::rng(2);
    let plain = small_batch(&mut rng);
    let (mut a, mut b) = (small_learner(), small_learner());
    a.train_step(&plain);
    let mut ones = small_batch(&mut common::rng(2));
    ones.weights = vec![1.0; 4];
    b.train_step(&ones);
    assert_eq!(params(&a), params(&b), "weights of 1");
    assert_eq!(a.td_errors(), b.td_errors());
    assert_eq!(a.td_errors().len(), 4);

    let step = |w1: f32, r1: f32| {
        let mut batch = small_batch(&mut common::rng(2));
        batch.weights = vec![1.0, w1, 0.5, 1.0];
        batch.rewards[1] = r1;
        let mut l = small_learner();
        l.train_step(&batch);
        params(&l)
    };
    assert_eq!(step(0.0, -1.0), step(0.0, 7.0), "a weight of 0");
    assert_ne!(step(1.0, -1.0), step(1.0, 7.0), "a weight of 1");
}

/// A prioritized run (with a dueling quantile head, 4 quantiles, and a narrow dense layer) stopped
/// after 2 episodes and resumed to 4 ends with the same weights, replay memory, priorities and
/// metrics as 4 episodes straight; its checkpoint evaluates (the action count read back from a
/// quantile head).
#[test]
fn prioritized_run_resumes_exactly() {
    let (root, straight, [(_, ra), (_, rb)]) = resumed_like_straight(
        "invaders-per",
        "prioritized = true\nquantiles = 4\ndueling = true\nhidden = 16\nn_step = 3\nlearning_starts = 40\nreplay_capacity = 150\nbatch_size = 8\ntarget_update = 50\nepsilon_decay_steps = 600\ncheckpoint_every = 1\nplot_every = 1000\n[env]\nmax_episode_steps = 60\n",
    );
    assert!(ra.written() > 150, "the ring wrapped");
    let (pa, pb) = (ra.priorities().unwrap(), rb.priorities().unwrap());
    assert!(pa.0.iter().any(|&p| p != pa.1), "priorities were updated");
    assert_eq!(pa, pb, "priorities");
    let out = eval(&straight, "1");
    assert!(out.contains("mean"), "{out}");
    let _ = std::fs::remove_dir_all(&root);
}
