//! Acting beside learning (`act_while_learning`, issue #101): each update runs on the pool's
//! other threads while the agent plays the steps through the next update's with the parameters
//! from before it, samples the next update's batch and makes its target pass. The schedule is
//! fixed by `train_every`, so a run's results depend on its seed, not on the thread count; it
//! resumes exactly; where the network does not act (ε = 1 throughout) it makes the turn-taking
//! loop's updates bit for bit.
//! (It learns the toy corridor: `tests/dqn.rs`, `acting_while_learning_learns_a_toy_corridor`.)

mod common;

use common::cli::resumed_like_straight;
use common::corridor::Corridor;
use invaders::dqn::{Agent, Config};

/// The toy corridor's configuration (as `tests/dqn.rs`'s), one update every `train_every` steps.
fn corridor_config(train_every: u64, act_while_learning: bool) -> Config {
    Config {
        gamma: 0.9,
        train_every,
        act_while_learning,
        epsilon_decay_steps: 600,
        epsilon_end: 0.1,
        ..common::small_config(1_000, 16, 64, 25, 3)
    }
}

/// A run of `config` on one corridor (`common::corridor::run`).
fn run(config: Config, episodes: usize, threads: usize) -> common::corridor::Run {
    common::corridor::run(config, episodes, threads, |c| {
        Agent::new(c, Corridor::new())
    })
}

/// The same run on 1, 2 and 4 threads ends with the same rows and weights; it is not the
/// turn-taking run of the same seed (its blocks act with parameters one update old), unless
/// every action is random (ε = 1 throughout): then the two sample the same batches and make the
/// same updates and target copies, in the same order, bit for bit.
#[test]
fn results_depend_on_the_seed_not_the_thread_count() {
    let pipelined = run(corridor_config(4, true), 30, 1);
    assert!(pipelined.1 > 20, "learning ran: {} updates", pipelined.1);
    for threads in [2, 4] {
        assert!(
            run(corridor_config(4, true), 30, threads) == pipelined,
            "{threads} threads differ from 1"
        );
    }
    let serial = run(corridor_config(4, false), 30, 2);
    assert!(
        serial.0 != pipelined.0,
        "acting one update late changes the play"
    );
    // Target copies every 25 steps, and every 7 with an update every 2 steps (episodes of
    // several updates): copies fall between two updates of a block (the next update's target
    // pass, made ahead with the old target network, is dropped) and between episodes (the
    // playing thread's copy of the target network follows it). Either one missed fails here.
    for (train_every, target_update) in [(1, 25), (4, 25), (2, 7)] {
        let random = |beside: bool| Config {
            epsilon_start: 1.0,
            epsilon_end: 1.0,
            target_update,
            ..corridor_config(train_every, beside)
        };
        let serial = run(random(false), 15, 2);
        assert!(serial.1 > 10, "learning ran: {} updates", serial.1);
        assert!(
            run(random(true), 15, 2) == serial,
            "acting at random, every {train_every} steps, target copies every {target_update}: \
             the same updates as taking turns"
        );
    }
}

/// Stopped after 2 episodes and resumed to 4, a run acting beside learning ends as one that ran
/// 4 straight: replay memory, weights and metrics rows (`resumed_like_straight`). Each episode
/// ends with its last update landed, so a checkpoint holds nothing in flight.
#[test]
fn a_run_acting_while_learning_resumes_exactly() {
    let (root, _, _) = resumed_like_straight(
        "invaders-act-while-learning",
        "preset = \"strong\"\nact_while_learning = true\nhidden = 16\nlearning_starts = 40\nreplay_capacity = 150\nbatch_size = 8\ntrain_every = 4\ntarget_update = 50\nepsilon_decay_steps = 600\ncheckpoint_every = 1\nplot_every = 1000\nmax_frames = 0\nepisodes = 4\n[env]\nmax_episode_steps = 60\n",
    );
    let _ = std::fs::remove_dir_all(&root);
}

/// The switch is refused where it has no meaning: with PQN's own loop, and with the notebook's
/// acting by the target network.
#[test]
fn act_while_learning_is_refused_where_it_cannot_apply() {
    use invaders::dqn::Preset;
    let err = |preset, text| {
        Config::resolve(Some(preset), Some(text))
            .unwrap_err()
            .to_string()
    };
    let e = err(Preset::ArticleAsWritten, "act_while_learning = true");
    assert!(e.contains("act_with_target_network"), "{e}");
    let e = err(Preset::Strong, "act_while_learning = true\n[pqn]");
    assert!(e.contains("act_while_learning"), "{e}");
}

/// The target pass that the playing thread makes ahead ([`NextValues`], by a copy of the
/// target network) gives the update the numbers it would compute itself: three updates of
/// `strong`'s network with the pass given and without it end with the same statistics and
/// weights, bit for bit, for each head and target rule (Double DQN with the dueling head,
/// QR-DQN's quantiles, M-IQN's implicit quantiles with Munchausen's bootstrap), in f32 and in
/// bf16. A target copy between the updates keeps the target network moving, and a copy that
/// misses it gives other targets: the step uses the pass it is given.
#[test]
fn the_target_pass_made_ahead_is_the_one_the_update_makes() {
    use invaders::dqn::{Batch, Learner, NextValues, Preset};
    use rand::SeedableRng;
    let heads = [
        "",
        "dueling = false\nquantiles = 8\n",
        "iqn_samples = 8\niqn_target_samples = 8\niqn_policy_samples = 8\nmunchausen_alpha = 0.9\n",
    ];
    for head in heads {
        for precision in ["f32", "bf16"] {
            let text = format!("{head}hidden = 16\nbatch_size = 4\nprecision = \"{precision}\"\n");
            let config = Config::resolve(Some(Preset::Strong), Some(&text)).unwrap();
            let learner =
                || Learner::from_config(&config, 6, &mut rand_chacha::ChaCha8Rng::seed_from_u64(7));
            let (mut own, mut given, mut stale) = (learner(), learner(), learner());
            let mut next = NextValues::new(&config, &given);
            // A copy that misses the target copy below: the pass it gives must change the step.
            let mut missed = NextValues::new(&config, &stale);
            let (rng, mut values) = (&mut rand_chacha::ChaCha8Rng::seed_from_u64(8), Vec::new());
            for step in 0..3 {
                let batch = Batch::random(&config, rng);
                next.compute(&batch, &mut values);
                let a = own.train_step(&batch);
                let b = given.train_step_with(&batch, Some(&values));
                assert_eq!(a, b, "{head}{precision}: step {step}'s statistics");
                assert_eq!(
                    own.targets(),
                    given.targets(),
                    "{head}{precision}: step {step}'s y"
                );
                missed.compute(&batch, &mut values);
                stale.train_step_with(&batch, Some(&values));
                assert!(
                    (own.targets() == stale.targets()) == (step < 2),
                    "{head}{precision}: step {step}: the given pass is what the step uses"
                );
                if step == 1 {
                    for l in [&mut own, &mut given, &mut stale] {
                        l.update_target();
                    }
                    next.sync(&given);
                }
            }
            let weights = |l: &Learner| -> Vec<Vec<f32>> {
                l.online.params().map(|p| p.value.data().to_vec()).collect()
            };
            assert!(
                weights(&own) == weights(&given),
                "{head}{precision}: the weights"
            );
        }
    }
}
