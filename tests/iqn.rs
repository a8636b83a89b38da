//! The implicit quantile head (IQN) and Munchausen targets in real runs: a run with both stopped
//! and resumed ends exactly as one never stopped, and its checkpoint and exported model play.
//! (The layer's gradient check and the loss's are in `tests/gradcheck.rs`; the targets by hand
//! in `tests/learner.rs`; learning the toy corridor in `tests/dqn.rs`.)

mod common;

use common::cli::{eval, invaders, ok, resumed_like_straight};

#[test]
fn iqn_munchausen_run_resumes_exactly_and_plays() {
    let (root, straight, [(ca, _), _]) = resumed_like_straight(
        "invaders-iqn",
        "preset = \"strong-v1\"\niqn_samples = 4\niqn_target_samples = 5\niqn_policy_samples = 3\niqn_embedding = 8\nmunchausen_alpha = 0.9\nprioritized = true\nhidden = 16\nlearning_starts = 40\nreplay_capacity = 150\nbatch_size = 8\ntarget_update = 50\nepsilon_decay_steps = 600\ncheckpoint_every = 1\nplot_every = 1000\nmax_frames = 0\nepisodes = 10\n[env]\nmax_episode_steps = 60\n",
    );
    assert!(
        ca.learner.online.params().any(|p| p.name == "iqn.weight"),
        "the checkpoint holds the embedding"
    );
    // The checkpoint and its exported model play, and alike.
    let model = root.join("model.safetensors");
    ok(&invaders(&[
        "export",
        "--checkpoint",
        straight.to_str().unwrap(),
        "--out",
        model.to_str().unwrap(),
    ]));
    let play = |what: &std::path::Path| {
        eval(what, "2")
            .lines()
            .last()
            .unwrap()
            .rsplit_once(": ")
            .unwrap()
            .1
            .to_string()
    };
    assert_eq!(play(&straight), play(&model));
    let _ = std::fs::remove_dir_all(&root);
}
