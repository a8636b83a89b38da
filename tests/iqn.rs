//! The implicit quantile head (IQN) and Munchausen targets in real runs: a run with both stopped
//! and resumed ends exactly as one never stopped, and its checkpoint and exported model play.
//! (The layer's gradient check and the loss's are in `tests/gradcheck.rs`; the targets by hand
//! in `tests/learner.rs`; learning the toy corridor in `tests/dqn.rs`.)

mod common;

use common::cli::{
    invaders, metrics_but_wall_time, ok, online_weights, straight_and_resumed, tmp_with_file,
};
use invaders::dqn::checkpoint;

#[test]
fn iqn_munchausen_run_resumes_exactly_and_plays() {
    let (root, cfg) = tmp_with_file(
        "invaders-iqn",
        "resume",
        "config.toml",
        "preset = \"strong\"\niqn_samples = 4\niqn_target_samples = 5\niqn_policy_samples = 3\niqn_embedding = 8\nmunchausen_alpha = 0.9\nprioritized = true\nhidden = 16\nlearning_starts = 40\nreplay_capacity = 150\nbatch_size = 8\ntarget_update = 50\nepsilon_decay_steps = 600\ncheckpoint_every = 1\nplot_every = 1000\nmax_frames = 0\nepisodes = 10\n[env]\nmax_episode_steps = 60\n",
    );
    let (straight, split) = straight_and_resumed(&root, &cfg, 4, 2, 4);
    let (ca, ra) = checkpoint::load_run(&straight).unwrap();
    let (cb, rb) = checkpoint::load_run(&split).unwrap();
    assert!(ca.counters.train_steps > 20, "learning ran");
    assert!(
        ca.learner.online.params().any(|p| p.name == "iqn.weight"),
        "the checkpoint holds the embedding"
    );
    assert!(
        ra.unwrap().parts() == rb.unwrap().parts(),
        "replay memories"
    );
    assert_eq!(online_weights(&ca), online_weights(&cb), "online weights");
    assert_eq!(
        metrics_but_wall_time(&straight),
        metrics_but_wall_time(&split)
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
        let out = ok(&invaders(&[
            "eval",
            "--checkpoint",
            what.to_str().unwrap(),
            "--episodes",
            "2",
            "--threads",
            "1",
        ]));
        out.lines()
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
