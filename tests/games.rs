//! Several games side by side (`games`, issue #101): one acting pass for all of them, the
//! emulators stepped in parallel, each game in its own lane of the replay memory. A run's
//! results depend on its seed, not on the thread count; it resumes exactly; one game is the
//! one-game loop bit for bit. (It learns the toy corridor: `tests/dqn.rs`,
//! `games_side_by_side_learn_a_toy_corridor`; the lanes: `replay_lanes_keep_each_games_transitions_apart`.)

mod common;

use common::cli::resumed_like_straight;
use common::corridor::Corridor;
use invaders::dqn::{Agent, Config, Preset};

/// The toy corridor's configuration (as `tests/dqn.rs`'s) with `games` games side by side.
fn corridor_config(games: usize) -> Config {
    beside(games, false)
}

/// The same, each update beside the play (`act_while_learning`) if `act_while_learning`.
fn beside(games: usize, act_while_learning: bool) -> Config {
    Config {
        gamma: 0.9,
        train_every: 4,
        games,
        act_while_learning,
        epsilon_decay_steps: 600,
        epsilon_end: 0.1,
        ..common::small_config(1_008, 16, 64, 25, 3)
    }
}

/// A run of `config` on corridors: `Agent::new` on one if `one`, else `Agent::with_games`
/// (`common::corridor::run`).
fn run(config: Config, episodes: usize, threads: usize, one: bool) -> common::corridor::Run {
    if one {
        common::corridor::run(config, episodes, threads, |c| {
            Agent::new(c, Corridor::new())
        })
    } else {
        common::corridor::run_games(config, episodes, threads)
    }
}

/// Three games side by side on 1, 2 and 4 threads end with the same rows and weights; their
/// episodes are numbered in the order they end, and their rows count the agent steps of all
/// three. One game through `Agent::with_games` is `Agent::new`'s run bit for bit.
#[test]
fn results_depend_on_the_seed_not_the_thread_count() {
    let three = run(corridor_config(3), 30, 1, false);
    assert!(three.1 > 20, "learning ran: {} updates", three.1);
    for threads in [2, 4] {
        assert!(
            run(corridor_config(3), 30, threads, false) == three,
            "{threads} threads differ from 1"
        );
    }
    let numbers: Vec<u64> = three
        .0
        .iter()
        .map(|r| r.split(',').next().unwrap().parse().unwrap())
        .collect();
    assert_eq!(
        numbers,
        (1..=30).collect::<Vec<_>>(),
        "rows in the order episodes end"
    );
    let steps: Vec<u64> = three
        .0
        .iter()
        .map(|r| r.split(',').nth(1).unwrap().parse().unwrap())
        .collect();
    assert!(
        steps.windows(2).all(|w| w[0] <= w[1]),
        "agent steps grow: {steps:?}"
    );
    let lengths: u64 = three
        .0
        .iter()
        .map(|r| r.split(',').nth(4).unwrap().parse::<u64>().unwrap())
        .sum();
    assert!(
        lengths <= steps[29] && steps[29] < lengths + 3 * 12,
        "the rows' lengths add up to the agent steps, but for the 3 episodes in progress"
    );
    let one = run(corridor_config(1), 20, 2, false);
    assert!(
        one == run(corridor_config(1), 20, 2, true),
        "one game as Agent::new"
    );
    assert!(one.0 != three.0[..20], "three games play otherwise");
}

/// Three games side by side with each update beside the play (`act_while_learning`): the same
/// rows and weights on 1, 2 and 4 threads; not the turn-taking run (the passes act with
/// parameters one update old), unless every action is random (ε = 1): then the same batches,
/// updates and target copies in the same order, bit for bit (the same weights and episodes; the
/// rows' loss statistics aside), with target copies between two updates and inside a chain
/// (every 7 agent steps, an update every 4 or every 3).
#[test]
fn games_beside_the_update_depend_on_the_seed_not_the_thread_count() {
    let piped = run(beside(3, true), 30, 1, false);
    assert!(piped.1 > 20, "learning ran: {} updates", piped.1);
    for threads in [2, 4] {
        assert!(
            run(beside(3, true), 30, threads, false) == piped,
            "{threads} threads differ from 1"
        );
    }
    assert!(
        run(beside(3, false), 30, 2, false).0 != piped.0,
        "acting one update late changes the play"
    );
    for (train_every, target_update) in [(4, 25), (3, 7)] {
        let random = |act_while_learning: bool| Config {
            epsilon_start: 1.0,
            epsilon_end: 1.0,
            train_every,
            target_update,
            ..beside(3, act_while_learning)
        };
        // The rows' loss statistics are those of the updates that landed during each episode,
        // which land later beside the play: the rows are compared without them.
        let plain = |(rows, steps, weights): common::corridor::Run| {
            let rows: Vec<String> = rows
                .iter()
                .map(|r| r.split(',').take(6).collect::<Vec<_>>().join(","))
                .collect();
            (rows, steps, weights)
        };
        let serial = plain(run(random(false), 20, 2, false));
        assert!(serial.1 > 10, "learning ran: {} updates", serial.1);
        let other = plain(run(random(true), 20, 2, false));
        assert!(
            other == serial,
            "acting at random, every {train_every} steps, target copies every {target_update}: \
             the same updates as taking turns"
        );
    }
}

/// The same run stopped after 2 episodes and resumed to 4, 3 Space Invaders games with each
/// update beside the play, ends as one that ran 4 straight.
#[test]
fn games_beside_the_update_resume_exactly() {
    let (root, _, _) = resumed_like_straight(
        "invaders-games-beside",
        "preset = \"strong\"\ngames = 3\nact_while_learning = true\nhidden = 16\nlearning_starts = 40\nreplay_capacity = 300\nbatch_size = 8\ntrain_every = 4\ntarget_update = 50\nepsilon_decay_steps = 600\ncheckpoint_every = 1\nplot_every = 1000\nmax_frames = 0\nepisodes = 4\n[env]\nmax_episode_steps = 60\n",
    );
    let _ = std::fs::remove_dir_all(&root);
}

/// Stopped after 2 episodes and resumed to 4, a run of 3 Space Invaders games side by side ends
/// as one that ran 4 straight: replay memory (its lanes), weights and metrics rows
/// (`resumed_like_straight`); the checkpoint holds every game's emulator, stacks and episode in
/// progress, and the rows not yet written.
#[test]
fn a_run_of_games_side_by_side_resumes_exactly() {
    let (root, _, [(ckpt, replay), _]) = resumed_like_straight(
        "invaders-games",
        "preset = \"strong\"\ngames = 3\nhidden = 16\nlearning_starts = 40\nreplay_capacity = 300\nbatch_size = 8\ntrain_every = 4\ntarget_update = 50\nepsilon_decay_steps = 600\ncheckpoint_every = 1\nplot_every = 1000\nmax_frames = 0\nepisodes = 4\n[env]\nmax_episode_steps = 60\n",
    );
    assert_eq!(ckpt.config.games, 3);
    assert_eq!(replay.lanes(), 3);
    assert!(
        replay.lane_written().iter().all(|&w| w > 0),
        "every lane written"
    );
    assert_eq!(ckpt.agent.other_games.len(), 2);
    let _ = std::fs::remove_dir_all(&root);
}

/// `games` is refused where it cannot apply: out of range, a replay memory its lanes do not
/// divide, PQN (which has `pqn.games`), the notebook's fake terminal transition, and acting
/// beside learning with more games than agent steps between updates; and `Agent::with_games`
/// refuses games other than the configuration's.
#[test]
fn games_are_refused_where_they_cannot_apply() {
    let err = |preset, text: &str| {
        Config::resolve(Some(preset), Some(text))
            .unwrap_err()
            .to_string()
    };
    let e = err(Preset::Strong, "games = 0");
    assert!(e.contains("games must be in 1..="), "{e}");
    let e = err(Preset::Strong, "games = 300");
    assert!(e.contains("games must be in 1..="), "{e}");
    let e = err(Preset::Strong, "games = 3\nreplay_capacity = 1000");
    assert!(e.contains("multiple of games"), "{e}");
    let e = err(Preset::Strong, "games = 2\n[pqn]");
    assert!(e.contains("pqn.games"), "{e}");
    let e = err(Preset::ArticleAsWritten, "games = 2");
    assert!(e.contains("fake_terminal_transition"), "{e}");
    let e = err(Preset::Strong, "games = 32\nact_while_learning = true");
    assert!(
        e.contains("train_every (16) must be at least games (32)"),
        "{e}"
    );
    let ok = Config::resolve(
        Some(Preset::Strong),
        Some("games = 16\nact_while_learning = true"),
    );
    assert!(ok.is_ok());
    let config = corridor_config(3);
    let e = Agent::with_games(config, vec![Corridor::new(), Corridor::new()])
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("3 games"), "{e}");
    assert!(Config::resolve(Some(Preset::Strong), Some("games = 4")).is_ok());
}
