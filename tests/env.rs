//! Tests of the environment with the real (bundled) Space Invaders ROM.

use invaders::env::ale::SCREEN_RGB_LEN;
use invaders::env::{
    max_into, Composer, EnvConfig, EnvError, EnvMode, FrameStack, Normalization, Observer,
    Pipeline, SpaceInvaders, StepResult, FRAME_LEN, FRAME_WIDTH, MSPACMAN_RGB_SUM,
};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

fn env(config: &EnvConfig, seed: u64) -> SpaceInvaders {
    SpaceInvaders::new(config, seed).expect("the bundled ROM loads")
}

fn mode(m: EnvMode) -> EnvConfig {
    EnvConfig::from_mode(m)
}

/// The game in v0 mode with episodes cut at `max_episode_steps` agent steps (`None`: never).
fn v0_capped(max_episode_steps: Option<u32>, seed: u64) -> SpaceInvaders {
    let cfg = EnvConfig {
        max_episode_steps,
        ..mode(EnvMode::V0)
    };
    env(&cfg, seed)
}

/// A fixed pseudo-random action sequence, independent of the environment.
fn actions(n: usize, n_actions: usize, seed: u64) -> Vec<usize> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    (0..n).map(|_| rng.random_range(0..n_actions)).collect()
}

/// Plays `acts` (resetting at episode ends) and records every step and every observation.
fn trajectory(env: &mut SpaceInvaders, acts: &[usize]) -> (Vec<StepResult>, Vec<Vec<u8>>) {
    let mut steps = Vec::new();
    let mut frames = Vec::new();
    for &a in acts {
        let r = env.step(a);
        steps.push(r);
        frames.push(env.observation().to_vec());
        if r.terminal || r.truncated {
            env.reset();
        }
    }
    (steps, frames)
}

#[test]
fn same_seed_and_actions_give_identical_frames_and_rewards() {
    for m in [EnvMode::V0, EnvMode::Nature] {
        let acts = actions(600, 6, 1);
        let (s1, f1) = trajectory(&mut env(&mode(m), 7), &acts);
        let (s2, f2) = trajectory(&mut env(&mode(m), 7), &acts);
        assert_eq!(s1, s2, "{m:?}");
        assert!(f1 == f2, "{m:?}: same frames");
        assert!(
            s1.iter().any(|s| s.reward > 0.0),
            "600 random steps shoot something"
        );
    }
}

#[test]
fn seeds_matter_only_through_randomness() {
    let acts = actions(400, 6, 2);
    // Sticky actions (and random frame skip) on: different seeds give different games.
    let (_, a) = trajectory(&mut env(&mode(EnvMode::V5), 1), &acts);
    let (_, b) = trajectory(&mut env(&mode(EnvMode::V5), 2), &acts);
    assert!(a != b, "sticky actions make seeds matter");
    // Fixed skip, no sticky actions, no no-op starts: the game is deterministic.
    let det = EnvConfig {
        noop_max: 0,
        ..mode(EnvMode::Nature)
    };
    let (sa, a) = trajectory(&mut env(&det, 1), &acts);
    let (sb, b) = trajectory(&mut env(&det, 2), &acts);
    assert_eq!(sa, sb);
    assert!(a == b, "deterministic settings: seeds do not matter");
}

#[test]
fn frame_skip_counts_emulator_frames() {
    let mut v0 = env(&mode(EnvMode::V0), 3);
    let mut seen = [0usize; 5];
    for a in actions(600, 6, 3) {
        let before = v0.ale().frame_number();
        let r = v0.step(a);
        assert_eq!((v0.ale().frame_number() - before) as u32, r.frames);
        if !r.terminal {
            assert!((2..=4).contains(&r.frames), "v0 skip {}", r.frames);
            seen[r.frames as usize] += 1;
        }
        if r.terminal || r.truncated {
            v0.reset();
        }
    }
    assert!(
        seen[2] > 100 && seen[3] > 100 && seen[4] > 100,
        "all of 2, 3, 4 occur: {seen:?}"
    );

    let mut nature = env(&mode(EnvMode::Nature), 3);
    let start = nature.episode().frames;
    assert!(start <= 30, "no-op start of {start} frames");
    for a in actions(200, 6, 4) {
        assert_eq!(nature.step(a).frames, 4);
    }
    assert_eq!(nature.episode().frames, start + 800);
    assert_eq!(nature.episode().steps, 200);
}

#[test]
fn noop_starts_vary_and_stay_within_the_limit() {
    let mut e = env(&mode(EnvMode::Nature), 5);
    let mut counts = std::collections::BTreeSet::new();
    for _ in 0..20 {
        e.reset();
        let f = e.episode().frames;
        assert!(f <= 30);
        counts.insert(f);
    }
    assert!(counts.len() >= 5, "random no-op counts: {counts:?}");
    let none = EnvConfig {
        noop_max: 0,
        ..mode(EnvMode::Nature)
    };
    assert_eq!(env(&none, 5).episode().frames, 0);
}

/// Sticky actions measured through the game. Every episode starts identically (no no-op starts)
/// and with NOOP held; after 201 NOOP frames (the game reads the joystick only from about frame
/// 200, and only on every other frame) we press FIRE for one frame. That frame either fires (the
/// new action) or repeats NOOP (sticky), and the very same frame's screen tells which. Over many episodes the
/// sticky fraction must be about `sticky_prob`.
#[test]
fn sticky_actions_repeat_the_previous_action_with_the_set_probability() {
    let one_frame = |sticky| EnvConfig {
        frame_skip_min: 1,
        frame_skip_max: 1,
        sticky_prob: sticky,
        noop_max: 0,
        max_episode_steps: None,
        ..mode(EnvMode::Nature)
    };
    let play = |e: &mut SpaceInvaders, last: usize| {
        e.reset();
        for _ in 0..201 {
            e.step(0);
        }
        e.step(last);
        e.screen_rgb().to_vec()
    };
    let mut det = env(&one_frame(0.0), 0);
    let after_noop = play(&mut det, 0);
    let after_fire = play(&mut det, 1);
    assert!(
        after_noop != after_fire,
        "FIRE must change the frame for this test to work"
    );
    assert!(
        play(&mut det, 1) == after_fire,
        "deterministic without stickiness"
    );

    for (p, trials, tolerance) in [(0.25, 400, 0.09), (1.0, 20, 0.0)] {
        let mut e = env(&one_frame(p), 17);
        let mut sticky = 0;
        for _ in 0..trials {
            let screen = play(&mut e, 1);
            if screen == after_noop {
                sticky += 1;
            } else {
                assert!(screen == after_fire, "the frame shows either NOOP or FIRE");
            }
        }
        let measured = sticky as f64 / trials as f64;
        // 400 Bernoulli(0.25) trials: std 0.022, so 0.09 is four standard deviations.
        assert!(
            (measured - p).abs() <= tolerance,
            "sticky fraction {measured}, expected {p}"
        );
    }
}

#[test]
fn step_limit_truncates() {
    let mut e = v0_capped(Some(25), 0);
    for i in 1..=25 {
        let r = e.step(0);
        assert!(!r.terminal);
        assert_eq!(r.truncated, i == 25, "step {i}");
    }
    assert!(e.is_finished());
    e.reset();
    assert!(!e.is_finished() && e.episode().steps == 0);
    assert!(!e.step(0).truncated);
}

#[test]
#[should_panic(expected = "finished episode")]
fn stepping_a_finished_episode_panics() {
    let mut e = v0_capped(Some(1), 0);
    e.step(0);
    e.step(0);
}

#[test]
fn action_sets() {
    let e = env(&mode(EnvMode::V0), 0);
    assert_eq!(e.n_actions(), 6);
    assert_eq!(e.action_ids(), &[0, 1, 3, 4, 11, 12]); // NOOP FIRE RIGHT LEFT RIGHTFIRE LEFTFIRE
    let full = env(
        &EnvConfig {
            full_action_set: true,
            ..mode(EnvMode::V0)
        },
        0,
    );
    assert_eq!(full.n_actions(), 18);
    assert_eq!(full.action_ids(), (0..18).collect::<Vec<_>>().as_slice());
}

/// An independent reading of the article's `obs[25:201:2, ::2].mean(axis=2)`, floored.
fn reference_preprocess(rgb: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    for y in (25..201).step_by(2) {
        for x in (0..160).step_by(2) {
            let p = &rgb[(y * 160 + x) * 3..(y * 160 + x) * 3 + 3];
            out.push(((p[0] as f64 + p[1] as f64 + p[2] as f64) / 3.0).floor() as u8);
        }
    }
    out
}

#[test]
fn preprocessing_matches_an_independent_computation_and_contrast_is_a_no_op() {
    let cfg = EnvConfig {
        max_pool_last_two: false,
        ..mode(EnvMode::V0)
    };
    let mut e = env(&cfg, 11);
    let contrast = EnvConfig {
        contrast_rgb_sum: Some(MSPACMAN_RGB_SUM),
        ..cfg.clone()
    };
    let mut c = env(&contrast, 11);
    let mut colours = std::collections::BTreeSet::new();
    let mut ms_pacman_pixels = 0;
    for (i, a) in actions(1500, 6, 5).into_iter().enumerate() {
        let r = e.step(a);
        let rc = c.step(a);
        assert_eq!(r, rc);
        let rgb = e.screen_rgb();
        assert_eq!(rgb.len(), SCREEN_RGB_LEN);
        for p in rgb.chunks_exact(3) {
            colours.insert([p[0], p[1], p[2]]);
            ms_pacman_pixels +=
                (p[0] as u16 + p[1] as u16 + p[2] as u16 == MSPACMAN_RGB_SUM) as usize;
        }
        if i % 10 == 0 {
            assert!(
                e.last_two_frames().1 == reference_preprocess(rgb).as_slice(),
                "step {i}"
            );
            assert!(e.observation() == e.last_two_frames().1);
        }
        assert!(
            c.observation() == e.observation(),
            "the contrast step changed a frame"
        );
        if r.terminal || r.truncated {
            e.reset();
            c.reset();
        }
    }
    assert!(
        colours.len() >= 5,
        "a real game has several colours: {colours:?}"
    );
    assert_eq!(ms_pacman_pixels, 0);
}

/// The mothership (purple, RGB 151 25 122) flies in screen rows 12 to 19, above the article's
/// crop (rows 25 to 200, `the_mothership_crop_keeps_the_ship_band_and_the_playfield` in
/// `src/env/preprocess.rs`): random play that fires half the time meets it, and the `mothership`
/// crop's frame shows it in its top 4 rows. The rows that crop leaves out (20 to 29, 198 to 200)
/// hold nothing but a one-pixel shot, and the ground, on every screen of 3 000 steps and more.
#[test]
fn the_mothership_crop_sees_the_ship_that_the_article_crop_cannot() {
    use invaders::env::Crop;
    const SHIP: [u8; 3] = invaders::env::MOTHERSHIP_RGB;
    let cfg = EnvConfig {
        downsample: invaders::env::Downsample::Max,
        crop: Crop::Mothership,
        ..mode(EnvMode::V5)
    };
    let mut e = env(&cfg, 3);
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let lit = |rgb: &[u8], y: usize| {
        rgb[y * 160 * 3..(y + 1) * 160 * 3]
            .chunks_exact(3)
            .filter(|p| p.iter().any(|&v| v > 0))
            .count()
    };
    let (mut seen, mut steps) = (0, 0);
    while (seen < 20 || steps < 3_000) && steps < 20_000 {
        let a = if rng.random_bool(0.5) {
            1
        } else {
            rng.random_range(0..6)
        };
        let r = e.step(a);
        steps += 1;
        let rgb = e.screen_rgb();
        for y in 20..30 {
            assert!(
                lit(rgb, y) <= 2,
                "step {steps}: screen row {y} holds more than a shot"
            );
        }
        let ground = lit(rgb, 198);
        assert!(
            (198..201).all(|y| lit(rgb, y) == ground),
            "rows 198 to 200 are the ground"
        );
        let ship_rows = (12..20).filter(|&y| {
            rgb[y * 160 * 3..(y + 1) * 160 * 3]
                .chunks_exact(3)
                .any(|p| p == SHIP)
        });
        let rows = ship_rows.count();
        assert_eq!(rows > 0, invaders::env::mothership_on_screen(rgb));
        if rows >= 6 {
            seen += 1;
            let frame = e.last_two_frames().1;
            let top: u32 = frame[..4 * FRAME_WIDTH].iter().map(|&v| v as u32).sum();
            assert!(
                top > 0,
                "step {steps}: the ship is on screen but not in the frame"
            );
        }
        if r.terminal || r.truncated {
            e.reset();
        }
    }
    assert!(
        seen >= 20,
        "the mothership appears in {seen} of {steps} steps of random play"
    );
}

#[test]
fn pipelines_compose_by_their_definitions_on_real_frames() {
    let cfg = mode(EnvMode::V0);
    let mut e = env(&cfg, 21);
    let mut max = Composer::new(Pipeline::StackMax);
    let mut run = Composer::new(Pipeline::StackRunningMax);
    let mut plain = Composer::new(Pipeline::Stack);
    let (p, l) = e.last_two_frames();
    run.reset(p, l, e.observation());
    let mut since_reset = e.observation().to_vec();
    let mut trails = false;
    let mut flicker = false;
    for (i, a) in actions(800, 6, 6).into_iter().enumerate() {
        let r = e.step(a);
        let (p, l) = e.last_two_frames();
        let o = e.observation();
        let m = max.step(p, l, o).to_vec();
        for j in 0..FRAME_LEN {
            assert_eq!(m[j], p[j].max(l[j]));
        }
        flicker |= m != l;
        assert!(plain.step(p, l, o) == o);
        let before = run.frame().to_vec();
        let now = run.step(p, l, o).to_vec();
        for j in 0..FRAME_LEN {
            since_reset[j] = since_reset[j].max(o[j]);
            assert!(now[j] >= before[j], "running max is monotone");
        }
        assert!(
            now == since_reset,
            "running max equals the max of all frames since reset"
        );
        trails |= now != o;
        if r.terminal || r.truncated || i == 400 {
            e.reset();
            let (p, l) = e.last_two_frames();
            assert!(
                run.reset(p, l, e.observation()) == e.observation(),
                "reset clears it"
            );
            since_reset = e.observation().to_vec();
        }
    }
    assert!(
        flicker,
        "the max of two frames differs from the last frame somewhere"
    );
    assert!(trails, "a running max leaves trails");
}

#[test]
fn observer_stacks_composites_oldest_first_as_nhwc() {
    let mut e = env(&mode(EnvMode::V0), 4);
    let table = Normalization::Symmetric.table();
    for pipeline in [
        Pipeline::Vanilla,
        Pipeline::Stack,
        Pipeline::StackMax,
        Pipeline::StackRunningMax,
    ] {
        e.reset();
        let k = pipeline.channels();
        let mut obs = Observer::new(pipeline);
        let mut history = vec![obs.reset(&e).to_vec()];
        let mut input = vec![0.0f32; obs.input_len()];
        assert_eq!(input.len(), FRAME_LEN * k);
        for a in actions(30, 6, 7) {
            e.step(a);
            history.push(obs.step(&e).to_vec());
        }
        obs.write_input(&table, &mut input);
        let newest: Vec<&Vec<u8>> = history.iter().rev().take(k).rev().collect();
        for (y, x) in [(0, 0), (44, 40), (87, 79), (60, 3)] {
            let px = y * FRAME_WIDTH + x;
            for c in 0..k {
                assert_eq!(
                    input[px * k + c],
                    Normalization::Symmetric.apply(newest[c][px])
                );
            }
        }
        // A stack fresh from reset holds k copies of the first frame.
        let mut s = FrameStack::new(k);
        s.reset(&history[0]);
        for c in 0..k {
            assert!(s.get(c) == history[0].as_slice());
        }
    }
}

#[test]
fn episodes_end_and_lives_count_down_from_three() {
    let mut e = v0_capped(None, 9);
    assert_eq!(e.lives(), 3);
    let mut lives_seen = vec![3];
    let mut rng = ChaCha8Rng::seed_from_u64(9);
    let mut score = 0.0;
    loop {
        let r = e.step(rng.random_range(0..6));
        score += r.reward as f64;
        assert!(
            r.lives <= *lives_seen.last().unwrap(),
            "lives never increase here"
        );
        if r.lives < *lives_seen.last().unwrap() {
            lives_seen.push(r.lives);
        }
        if r.terminal {
            break;
        }
        assert!(e.episode().steps < 20_000, "a random game ends");
    }
    assert_eq!(lives_seen, vec![3, 2, 1, 0]);
    assert_eq!(e.episode().score, score);
    assert!(score > 0.0);
    e.reset();
    assert_eq!(e.lives(), 3);
    assert_eq!(e.episode().score, 0.0);
}

#[test]
fn save_and_restore_continue_bit_identically() {
    for m in [EnvMode::V0, EnvMode::Nature, EnvMode::V5] {
        let cfg = mode(m);
        let mut a = env(&cfg, 13);
        let acts = actions(700, 6, 8);
        trajectory(&mut a, &acts[..300]);
        let saved = a.save_state();
        let (sa, fa) = trajectory(&mut a, &acts[300..]);
        let rgb_a = a.screen_rgb().to_vec();
        let stats_a = a.episode();
        // A fresh environment built with another seed continues exactly like the original.
        let mut b = env(&cfg, 999);
        b.restore_state(&saved).unwrap();
        let (sb, fb) = trajectory(&mut b, &acts[300..]);
        assert_eq!(sa, sb, "{m:?}");
        assert!(fa == fb, "{m:?}: same frames");
        assert!(rgb_a == b.screen_rgb(), "{m:?}: same colour screen");
        assert_eq!(stats_a, b.episode());
    }
}

#[test]
fn restore_rejects_garbage_and_other_settings() {
    let mut e = env(&mode(EnvMode::V0), 0);
    assert!(matches!(
        e.restore_state(b"nonsense"),
        Err(EnvError::BadState(_))
    ));
    let saved = e.save_state();
    assert!(matches!(
        e.restore_state(&saved[..saved.len() - 10]),
        Err(EnvError::BadState(_))
    ));
    let mut other = env(&mode(EnvMode::Nature), 0);
    assert!(matches!(
        other.restore_state(&saved),
        Err(EnvError::BadState(_))
    ));
    e.restore_state(&saved).unwrap();
}

#[test]
fn bad_rom_paths_and_configs_give_errors() {
    let missing = EnvConfig {
        rom: Some("/nonexistent/space_invaders.bin".into()),
        ..mode(EnvMode::V0)
    };
    assert!(matches!(
        SpaceInvaders::new(&missing, 0),
        Err(EnvError::RomNotFound(_))
    ));
    let dir = std::env::temp_dir().join(format!("invaders-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let empty = dir.join("empty.bin");
    std::fs::write(&empty, b"").unwrap();
    let cfg = EnvConfig {
        rom: Some(empty),
        ..mode(EnvMode::V0)
    };
    assert!(matches!(
        SpaceInvaders::new(&cfg, 0),
        Err(EnvError::RomEmpty(_))
    ));
    let cfg = EnvConfig {
        rom: Some(dir.clone()),
        ..mode(EnvMode::V0)
    };
    assert!(matches!(
        SpaceInvaders::new(&cfg, 0),
        Err(EnvError::RomEmpty(_))
    ));
    // A copy of the real ROM under another name works: it is renamed for ALE.
    let copy = dir.join("my-rom.a26");
    std::fs::write(&copy, ale::BundledRom::SpaceInvaders.data()).unwrap();
    let cfg = EnvConfig {
        rom: Some(copy),
        ..mode(EnvMode::V0)
    };
    let mut e = SpaceInvaders::new(&cfg, 0).unwrap();
    assert_eq!(e.n_actions(), 6);
    e.step(1);
    std::fs::remove_dir_all(&dir).unwrap();
    let bad = EnvConfig {
        frame_skip_min: 0,
        ..mode(EnvMode::V0)
    };
    assert!(matches!(
        SpaceInvaders::new(&bad, 0),
        Err(EnvError::InvalidConfig(_))
    ));
}

#[test]
fn max_pooled_observation_in_nature_mode() {
    let mut e = env(&mode(EnvMode::Nature), 2);
    let mut out = vec![0u8; FRAME_LEN];
    for a in actions(100, 6, 9) {
        e.step(a);
        let (p, l) = e.last_two_frames();
        max_into(p, l, &mut out);
        assert!(e.observation() == out.as_slice());
    }
}

/// An evaluation in another mode plays that mode's game on the frames the network was trained
/// on: the protocol's `v5` keeps a run's max-pooling of the last two frames (and its
/// downsampling), and does not add it to a run trained without.
#[test]
fn an_evaluation_keeps_what_the_network_sees() {
    let pooled = EnvConfig {
        max_pool_last_two: true,
        downsample: invaders::env::preprocess::Downsample::Max,
        ..mode(EnvMode::V0)
    };
    let v5 = pooled.for_evaluation(EnvMode::V5);
    assert!(v5.max_pool_last_two);
    assert_eq!(v5.downsample, invaders::env::preprocess::Downsample::Max);
    assert_eq!((v5.frame_skip_min, v5.frame_skip_max), (4, 4));
    assert_eq!(v5.sticky_prob, 0.25);
    assert_eq!(v5.max_episode_steps, Some(27_000));
    let plain = mode(EnvMode::V5).for_evaluation(EnvMode::Nature);
    assert!(!plain.max_pool_last_two, "nature's pooling is not added");
    assert_eq!(plain.noop_max, 30);
}
