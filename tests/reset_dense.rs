//! Resets of the dense layers (`reset_dense_at`, against lost plasticity): the configuration
//! key, the learner's reset over each architecture (what is drawn afresh, what is kept, and the
//! bf16 products' packed weights after it), and in real runs: a reset at a run's last agent
//! step against the same run without it, and runs with resets resumed bit for bit.

mod common;

use common::cli::{ok, online_weights, resumed_like_straight, tmp_with_file, train, write_file};

use invaders::dqn::{qnet, Config, Head, Learner, Preset};
use invaders::layers::init::VarianceScaling;
use invaders::layers::Sequential;
use invaders::ops::plan::Precision;

/// Whether a parameter belongs to the convolutions, which a reset keeps.
fn in_trunk(name: &str) -> bool {
    ["conv", "ln1.", "ln2.", "ln3."]
        .iter()
        .any(|p| name.starts_with(p))
}

#[test]
fn the_key_is_checked_and_recorded_only_when_set() {
    let strong = Config::resolve(Some(Preset::Strong), None).unwrap();
    assert!(strong.reset_dense_at.is_empty());
    assert!(
        !strong.to_toml().contains("reset_dense_at"),
        "presets' records unchanged"
    );
    let c = Config::resolve(
        Some(Preset::Strong),
        Some("reset_dense_at = [500000, 1000000]"),
    )
    .unwrap();
    assert_eq!(c.reset_dense_at, [500_000, 1_000_000]);
    let again = Config::resolve(None, Some(&c.to_toml())).unwrap();
    assert_eq!(again.reset_dense_at, c.reset_dense_at);
    for bad in ["[0]", "[5, 5]", "[9, 3]", "[20000000000]"] {
        let err = Config::resolve(
            Some(Preset::Strong),
            Some(&format!("reset_dense_at = {bad}")),
        )
        .unwrap_err()
        .to_string();
        assert!(
            err.contains("reset_dense_at must list increasing agent steps"),
            "{bad}: {err}"
        );
    }
    let err = Config::resolve(Some(Preset::Strong), Some("reset_dense_at = [-1]"))
        .unwrap_err()
        .to_string();
    assert!(err.contains("reset_dense_at"), "{err}");
}

/// Over the preset's network, with layer normalisation, and with an implicit quantile head
/// whose embedding enters at the convolutional features: after `reset_dense` every parameter
/// after the convolutions holds the fresh network's values and a zero first moment, every
/// convolution's parameter its own values and moments; the second moments and the target
/// network are untouched. In bf16 (where the CPU has it) the next pass multiplies the new
/// weights, not a packed copy of the old ones: it equals a pass of a network built with them.
#[test]
fn a_reset_draws_the_layers_after_the_convolutions_afresh_and_keeps_the_rest() {
    let variants = [
        ("the preset", "", 4),
        ("layer normalisation", "layer_norm = true", 6),
        (
            "IQN on the features",
            "iqn_samples = 4\niqn_target_samples = 4\niqn_policy_samples = 4\niqn_merge = \"features\"",
            6,
        ),
    ];
    for (what, keys, expect_reset) in variants {
        for precision in [Precision::F32, Precision::Bf16] {
            let mut c = Config::resolve(Some(Preset::Strong), Some(keys)).unwrap();
            c.precision = precision;
            let mut learner = Learner::from_config(&c, 6, &mut common::rng(1));
            // Moments as after training: distinct non-zero values.
            for p in learner.online.params() {
                let m = common::uniform::<f32>(p.value.shape(), &mut common::rng(2));
                learner.adam.m.push(m);
                let v = common::uniform::<f32>(p.value.shape(), &mut common::rng(3));
                learner.adam.v.push(v);
            }
            learner.adam.t = 1_000;
            // Weights as after training: every value moved (the biases start at zero).
            for p in learner.online.params_mut() {
                p.value.data_mut().iter_mut().for_each(|w| *w += 0.25);
            }
            // Two states of the preset's shape; conv1 pads them itself.
            let x = common::uniform::<f32>(&[2, 88, 80, 4], &mut common::rng(4));
            if c.iqn().is_some() {
                learner.online.set_fractions(&[0.1, 0.4, 0.6, 0.9]);
            }
            // A pass before the reset: bf16's products pack the weights they read.
            learner.online.forward(&x);
            let before: Vec<Vec<f32>> = learner
                .online
                .params()
                .map(|p| p.value.data().to_vec())
                .collect();
            let target: Vec<Vec<f32>> = learner
                .target()
                .params()
                .map(|p| p.value.data().to_vec())
                .collect();
            let (m0, v0) = (learner.adam.m.clone(), learner.adam.v.clone());
            let fresh: Sequential<f32> = qnet(
                c.input_shape(),
                6,
                Head::of(&c),
                &VarianceScaling::HE,
                &mut common::rng(99),
            );
            let reset = learner.reset_dense(&fresh);
            assert_eq!(reset, expect_reset, "{what}: tensors reset");
            let params = learner.online.params().zip(fresh.params()).enumerate();
            for (i, (p, f)) in params {
                let tag = format!("{what}, {precision:?}: {}", p.name);
                if in_trunk(&p.name) {
                    assert_eq!(p.value.data(), &before[i][..], "{tag} kept");
                    assert_eq!(learner.adam.m[i], m0[i], "{tag}: m kept");
                } else {
                    assert_eq!(p.value.data(), f.value.data(), "{tag} drawn afresh");
                    assert_ne!(p.value.data(), &before[i][..], "{tag} changed");
                    assert!(
                        learner.adam.m[i].data().iter().all(|&m| m == 0.0),
                        "{tag}: m zeroed"
                    );
                }
                assert_eq!(learner.adam.v[i], v0[i], "{tag}: v kept");
            }
            let target_after: Vec<Vec<f32>> = learner
                .target()
                .params()
                .map(|p| p.value.data().to_vec())
                .collect();
            assert_eq!(target_after, target, "{what}: the target network kept");
            assert_eq!(learner.adam.t, 1_000, "{what}: Adam's step count kept");
            // The next pass reads the new weights.
            let mut same = qnet::<f32>(
                c.input_shape(),
                6,
                Head::of(&c),
                &VarianceScaling::HE,
                &mut common::rng(7),
            );
            same.copy_params_from(&learner.online);
            same.set_precision(c.precision);
            if c.iqn().is_some() {
                same.set_fractions(&[0.1, 0.4, 0.6, 0.9]);
            }
            let got = learner.online.forward(&x).data().to_vec();
            let want = same.forward(&x).data().to_vec();
            assert_eq!(got, want, "{what}, {precision:?}: the pass after the reset");
        }
    }
}

const RUN: &str = "hidden = 16\nn_step = 3\nlearning_starts = 40\nreplay_capacity = 150\nbatch_size = 8\ntarget_update = 50\nepsilon_decay_steps = 600\ncheckpoint_every = 1\nplot_every = 1000\n[env]\nmax_episode_steps = 60\n";

/// Two runs of 4 episodes of 60 agent steps, one resetting at its last agent step (240, after
/// that step's gradient step): the convolutions, the target network and Adam's second moments
/// end as in the run without the reset; the dense layers differ, with zero first moments.
#[test]
fn a_reset_at_the_last_step_changes_only_the_dense_layers() {
    let (root, with) = tmp_with_file(
        "invaders-reset",
        "last",
        "with.toml",
        &format!("reset_dense_at = [240]\n{RUN}"),
    );
    let without = write_file(&root, "without.toml", RUN);
    let (a, b) = (root.join("a"), root.join("b"));
    ok(&train(with.to_str().unwrap(), 4, 4, &a));
    ok(&train(without.to_str().unwrap(), 4, 4, &b));
    let load = |dir: &std::path::Path| invaders::dqn::checkpoint::load_run(dir).unwrap().0;
    let (ca, cb) = (load(&a), load(&b));
    assert_eq!(ca.counters.agent_steps, 240, "the reset step is the last");
    assert_eq!(ca.counters.agent_steps, cb.counters.agent_steps);
    assert_eq!(ca.counters.train_steps, cb.counters.train_steps);
    let mut heads = 0;
    let pairs = ca.learner.online.params().zip(cb.learner.online.params());
    for (i, (p, q)) in pairs.enumerate() {
        if in_trunk(&p.name) {
            assert_eq!(p.value, q.value, "{} kept", p.name);
            assert_eq!(ca.learner.adam.m[i], cb.learner.adam.m[i], "{}: m", p.name);
        } else {
            heads += 1;
            assert_ne!(p.value, q.value, "{} drawn afresh", p.name);
            assert!(ca.learner.adam.m[i].data().iter().all(|&m| m == 0.0));
            assert!(cb.learner.adam.m[i].data().iter().any(|&m| m != 0.0));
        }
        assert_eq!(ca.learner.adam.v[i], cb.learner.adam.v[i], "{}: v", p.name);
    }
    assert_eq!(heads, 4, "dense1 and dense2, weights and biases");
    let targets = ca
        .learner
        .target()
        .params()
        .zip(cb.learner.target().params());
    for (p, q) in targets {
        assert_eq!(p.value, q.value, "target {}", p.name);
    }
    let _ = std::fs::remove_dir_all(&root);
}

/// Resets before and after a stop (agent steps 100 and 170; the run stops after episode 2, at
/// step 120): resumed, the run ends as the one never stopped, and otherwise than without resets.
#[test]
fn a_run_with_resets_resumes_exactly() {
    let (root, _, [(reset, _), _]) = resumed_like_straight(
        "invaders-resets",
        &format!("reset_dense_at = [100, 170]\n{RUN}"),
    );
    let (plain_root, _, [(plain, _), _]) = resumed_like_straight("invaders-noresets", RUN);
    assert_eq!(reset.config.reset_dense_at, [100, 170]);
    assert_ne!(
        online_weights(&reset),
        online_weights(&plain),
        "the resets changed learning"
    );
    let _ = std::fs::remove_dir_all(&root);
    let _ = std::fs::remove_dir_all(&plain_root);
}
