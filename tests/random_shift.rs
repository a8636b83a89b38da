//! Random shifts of sampled states (`random_shift`, DrQ): the shift of one frame by hand, the
//! replay's shifted batches against its unshifted ones, the configuration key, and a shifted run
//! resumed bit for bit.

mod common;

use common::cli::{online_weights, resumed_like_straight};

use invaders::dqn::{shift_frame, Batch, Config, Preset, Replay};
use invaders::env::{FRAME_HEIGHT, FRAME_LEN, FRAME_WIDTH};
use rand::Rng;

/// A frame whose pixel `(y, x)` is `f(y, x)`.
fn frame_of(f: impl Fn(usize, usize) -> u8) -> Vec<u8> {
    (0..FRAME_LEN)
        .map(|i| f(i / FRAME_WIDTH, i % FRAME_WIDTH))
        .collect()
}

#[test]
fn a_shift_moves_the_frame_and_repeats_its_border() {
    let mut out = vec![0; FRAME_LEN];
    // Each pixel shows its column: moved 3 left, a row reads 3, 4, …, 79, then 79 three more times.
    let columns = frame_of(|_, x| x as u8);
    shift_frame(&columns, 0, 3, &mut out);
    let mut row: Vec<u8> = (3..80).collect();
    row.extend([79; 3]);
    for y in 0..FRAME_HEIGHT {
        assert_eq!(&out[y * FRAME_WIDTH..][..FRAME_WIDTH], &row[..], "row {y}");
    }
    // Each pixel shows its row: moved 2 down, a column reads 0, 0, 0, 1, …, 85.
    let rows = frame_of(|y, _| y as u8);
    shift_frame(&rows, -2, 0, &mut out);
    let mut column = vec![0u8, 0];
    column.extend(0..86);
    for x in 0..FRAME_WIDTH {
        let got: Vec<u8> = (0..FRAME_HEIGHT)
            .map(|y| out[y * FRAME_WIDTH + x])
            .collect();
        assert_eq!(got, column, "column {x}");
    }
    // No shift: the frame itself.
    let any = frame_of(|y, x| (y * 7 + x * 13) as u8);
    shift_frame(&any, 0, 0, &mut out);
    assert_eq!(out, any);
    // Both at once, beyond the frame: 90 up leaves every row the last one, 5 right repeats
    // its first pixel six times.
    shift_frame(&any, 90, -5, &mut out);
    let last = &any[87 * FRAME_WIDTH..];
    let mut row = vec![last[0]; 5];
    row.extend_from_slice(&last[..75]);
    for y in 0..FRAME_HEIGHT {
        assert_eq!(&out[y * FRAME_WIDTH..][..FRAME_WIDTH], &row[..], "row {y}");
    }
}

/// Pixel `(y, x)` of entry `g`'s frame: distinct enough that no two small shifts give one image.
fn stored(g: usize) -> Vec<u8> {
    frame_of(|y, x| ((y * 37 + x * 11 + g * 101 + y * x) % 251) as u8)
}

/// The shift `(dy, dx)` within `pad` that turns the stacked frames `plain` (`[88, 80, k]`,
/// channels last, one byte per value) into `moved`, if one does.
fn find_shift(plain: &[f32], moved: &[f32], k: usize, pad: i64) -> Option<(i64, i64)> {
    let channel =
        |t: &[f32], c: usize| -> Vec<u8> { (0..FRAME_LEN).map(|i| t[i * k + c] as u8).collect() };
    let mut out = vec![0; FRAME_LEN];
    for dy in -pad..=pad {
        for dx in -pad..=pad {
            let all = (0..k).all(|c| {
                shift_frame(&channel(plain, c), dy, dx, &mut out);
                out == channel(moved, c)
            });
            if all {
                return Some((dy, dx));
            }
        }
    }
    None
}

#[test]
fn sampled_states_are_shifted_copies_with_a_fresh_shift_each() {
    const B: usize = 4;
    const PAD: usize = 4;
    let k = 4;
    let fill = |replay: &mut Replay| {
        // Two episodes, so states also repeat an episode's first frame.
        let mut g = 0;
        for len in [30, 25] {
            replay.push_start(&stored(g));
            g += 1;
            for t in 0..len {
                replay.push_step(t % 6, 1.0, t + 1 == len, &stored(g));
                g += 1;
            }
        }
    };
    let mut plain = Replay::new(100, k).with_returns(3, 0.9);
    let mut shifted = Replay::new(100, k)
        .with_returns(3, 0.9)
        .with_random_shift(PAD);
    fill(&mut plain);
    fill(&mut shifted);
    let table: [f32; 256] = std::array::from_fn(|i| i as f32);
    let (mut a, mut b) = (Batch::new(B, [88, 80, k]), Batch::new(B, [88, 80, k]));
    let per = FRAME_LEN * k;
    let mut seen = std::collections::BTreeSet::new();
    let mut differ = 0;
    for round in 0..150u64 {
        // The same draws of entries: the shifts are drawn after them.
        plain.sample(&mut common::rng(round), &table, &mut a);
        shifted.sample(&mut common::rng(round), &table, &mut b);
        assert_eq!(a.actions, b.actions);
        assert_eq!(a.rewards, b.rewards);
        assert_eq!(a.steps, b.steps);
        assert_eq!(a.dones, b.dones);
        for i in 0..B {
            let s = |t: &Batch| t.states.data()[i * per..][..per].to_vec();
            let n = |t: &Batch| t.next_states.data()[i * per..][..per].to_vec();
            let pad = PAD as i64;
            let ds = find_shift(&s(&a), &s(&b), k, pad).expect("the state is a shift within PAD");
            let dn = find_shift(&n(&a), &n(&b), k, pad).expect("so is the next state");
            seen.insert(ds);
            seen.insert(dn);
            differ += usize::from(ds != dn);
        }
    }
    // 1 200 draws of 81 shifts: each one comes up (about 15 times on average).
    assert_eq!(
        seen.len(),
        (2 * PAD + 1).pow(2),
        "every shift in [-4, 4]² drawn"
    );
    assert!(
        differ > 550,
        "s and s' shifted independently: {differ} of 600 differ"
    );
}

#[test]
fn no_shift_samples_exactly_as_before_and_draws_nothing() {
    let mut plain = Replay::new(64, 4).with_returns(3, 0.99);
    let mut zero = Replay::new(64, 4)
        .with_returns(3, 0.99)
        .with_random_shift(0);
    for replay in [&mut plain, &mut zero] {
        replay.push_start(&stored(0));
        for g in 1..40 {
            replay.push_step(g % 6, 0.5, false, &stored(g));
        }
    }
    let table: [f32; 256] = std::array::from_fn(|i| i as f32 / 255.0);
    let (mut a, mut b) = (Batch::new(8, [88, 80, 4]), Batch::new(8, [88, 80, 4]));
    let (mut ra, mut rb) = (common::rng(7), common::rng(7));
    plain.sample(&mut ra, &table, &mut a);
    zero.sample(&mut rb, &table, &mut b);
    assert_eq!(a.states.data(), b.states.data());
    assert_eq!(a.next_states.data(), b.next_states.data());
    assert_eq!(
        ra.random::<u64>(),
        rb.random::<u64>(),
        "the same random numbers used"
    );
}

#[test]
fn the_key_is_checked_and_recorded_only_when_set() {
    let strong = Config::resolve(Some(Preset::Strong), None).unwrap();
    assert_eq!(strong.random_shift, 0);
    assert!(
        !strong.to_toml().contains("random_shift"),
        "presets' records unchanged"
    );
    let c = Config::resolve(Some(Preset::Strong), Some("random_shift = 4")).unwrap();
    assert_eq!(c.random_shift, 4);
    assert!(c.to_toml().contains("random_shift = 4"));
    let again = Config::resolve(None, Some(&c.to_toml())).unwrap();
    assert_eq!(again.random_shift, 4);
    let err = Config::resolve(Some(Preset::Strong), Some("random_shift = 17"))
        .unwrap_err()
        .to_string();
    assert!(err.contains("random_shift must be at most 16"), "{err}");
}

/// A run with shifts stopped after 2 episodes and resumed to 4 ends as 4 episodes straight (the
/// shifts come from the sampling stream the checkpoint keeps), and learns otherwise than the same
/// run without them.
#[test]
fn a_shifted_run_resumes_exactly_and_differs_from_an_unshifted_one() {
    let config = "hidden = 16\nn_step = 3\nlearning_starts = 40\nreplay_capacity = 150\nbatch_size = 8\ntarget_update = 50\nepsilon_decay_steps = 600\ncheckpoint_every = 1\nplot_every = 1000\n[env]\nmax_episode_steps = 60\n";
    let (root, _, [(shifted, _), _]) =
        resumed_like_straight("invaders-shift", &format!("random_shift = 4\n{config}"));
    let (plain_root, _, [(plain, _), _]) = resumed_like_straight("invaders-noshift", config);
    assert_eq!(shifted.config.random_shift, 4);
    assert_ne!(
        online_weights(&shifted),
        online_weights(&plain),
        "the shifts changed learning"
    );
    let _ = std::fs::remove_dir_all(&root);
    let _ = std::fs::remove_dir_all(&plain_root);
}
