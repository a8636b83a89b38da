//! Experience replay that stores each 88x80 frame once.
//!
//! A transition `(s, a, r, s', done)` with stacked states would store every frame `2k` times
//! (k = 4 frames in `s` and again in `s'`). Instead the memory is a ring of *entries*, one per
//! environment observation: entry `g` holds the composite frame seen at that time and, once the
//! agent has acted on it, the action taken, the reward received and whether the step ended the
//! episode. A state is rebuilt at sampling time as the last `k` frames up to an entry, repeating
//! the episode's first frame where the episode is younger than `k` (as the frame stack does at
//! reset), so consecutive episodes never mix.
//!
//! Memory: one frame is 7 040 bytes, plus 8 bytes of transition data per entry. Measured with
//! `cargo run --release --example replay_memory -- N` (resident set size when full): 20 000
//! transitions take 134 MiB and 1 000 000 take 6 722 MiB (7.05 GB), against about 9 GB for the
//! notebook's float64 stacks of 20 000. Pages are touched as the ring fills, so the resident size
//! grows with the entries actually written.
//!
//! # Prioritized replay
//!
//! [`Replay::with_priorities`] samples entry `i` with probability `P(i) = p_i / Σ p` instead of
//! uniformly (Schaul et al. 2016), where `p_i = (|δ_i| + ε)^α` and `δ_i` is the TD error of the
//! entry's last train step ([`Replay::update_priorities`]); an entry never trained on has the
//! largest priority seen so far, so it is drawn soon. The batch is drawn stratified: the
//! priority mass is cut into `B` equal segments and one entry is drawn from each. Sampling out of
//! proportion biases the gradient, so each sample's loss is weighted by
//! `w_i = (N · P(i))^(−β) / max_j w_j` (`N` entries held; `max` over the batch, as Dopamine does).
//! The priorities live in a [`SumTree`] over the slots; a slot's priority is 0 while its entry
//! cannot be sampled (not yet acted on, or overwritten).
//!
//! # Random shifts
//!
//! [`Replay::with_random_shift`] moves each sampled state by a random whole number of pixels,
//! `dy, dx ∈ [−pad, pad]`, drawn anew for every `s` and every `s'` of a batch (all `k` frames of
//! one state move together): pixel `(y, x)` of the shifted frame is pixel
//! `(clamp(y + dy), clamp(x + dx))` of the stored one, i.e. the frame padded by repeating its
//! border rows and columns `pad` times, then cropped back to 88x80 at a random offset (DrQ,
//! Kostrikov et al. 2021, whose DQN on Atari pads 84x84 by 4). The learner then fits Q-values
//! that cannot depend on where exactly the screen sits, only on what is where relative to what;
//! acting sees the frames as they are.
//!
//! # Several games
//!
//! [`Replay::with_lanes`] splits the ring into `L` lanes, one per game played side by side
//! ([`super::Config::games`]): lane `l` holds the entries `l, l + L, l + 2L, …`, in the slots
//! `l, l + L, …` (entry `g` still lives in slot `g % capacity`), and keeps its own counter. A
//! state is rebuilt, and an n-step return summed, along its lane (entry `g − L` before `g`,
//! `g + L` after), so one game's frames never enter another's states; each lane forgets its own
//! oldest entries. Uniform sampling draws a slot in use and keeps it if its entry is
//! sampleable; prioritized sampling needs nothing new (its tree is over slots). With one lane
//! every rule above is the one-game memory's, draw for draw.

mod shift;

use super::input_border;
use super::sumtree::SumTree;
use crate::env::{write_stacked_input_bordered, FRAME_HEIGHT, FRAME_LEN, FRAME_WIDTH};
use crate::tensor::bf16::to_bf16;
use crate::tensor::{Border, Padding, Tensor};
use rand::Rng;
pub use shift::shift_frame;

/// Replay flag bit: the step from this entry ended the episode.
pub const FLAG_DONE: u8 = 1;
/// Replay flag bit: this entry is the first observation of an episode.
pub const FLAG_START: u8 = 2;
/// Replay flag bit: the agent acted on this entry.
pub const FLAG_ACTED: u8 = 4;

/// The replay memory. Entries are numbered by a global counter `g` that never wraps; entry `g`
/// lives in slot `g % capacity`.
pub struct Replay {
    capacity: usize,
    /// Frames per state (1 for `vanilla`, 4 for the stacks).
    k: usize,
    /// `[capacity, 88·80]` u8 frames.
    frames: Vec<u8>,
    actions: Vec<u8>,
    rewards: Vec<f32>,
    /// Whether the step from this entry ended the episode for good (no bootstrapping from `s'`).
    dones: Vec<bool>,
    /// Whether this entry is the first observation of an episode.
    starts: Vec<bool>,
    /// Whether the agent acted on this entry (so the next entry of its lane, `g + lanes`, is its
    /// `s'`).
    acted: Vec<bool>,
    /// Steps of the sampled returns (1: the one-step TD target).
    n_step: usize,
    /// The discount the n-step returns are summed with.
    gamma: f32,
    /// Games written side by side, each into its own lane ([`Replay::with_lanes`]; 1: one).
    lanes: usize,
    /// Entries written so far into each lane (lane-local counters).
    written: Vec<u64>,
    /// Scratch: the sampled entries.
    picks: Vec<u64>,
    /// Prioritized sampling, if on.
    priorities: Option<Priorities>,
    /// The largest random shift of a sampled state, in pixels (0: none; [`Replay::with_random_shift`]).
    shift: usize,
    /// Scratch: one state's shifted frames, `[k, 88·80]`.
    shifted: Vec<u8>,
}

/// The state of prioritized sampling ([`Replay::with_priorities`]).
#[derive(Clone, Debug)]
struct Priorities {
    /// `p_i` per slot, 0 where nothing can be sampled.
    tree: SumTree,
    /// `α`: how strongly priorities skew the sampling (0: uniform).
    alpha: f64,
    /// `β`: how much of the skew the loss weights undo (1: all of it).
    beta: f64,
    /// The largest `p_i` ever set: the priority of new entries.
    max: f64,
}

/// `ε` in `p = (|δ| + ε)^α`: keeps an entry with a zero TD error drawable.
pub const PRIORITY_EPSILON: f64 = 1e-6;

impl Replay {
    /// An empty memory of `capacity` entries (= transitions) and states of `k` frames.
    pub fn new(capacity: usize, k: usize) -> Self {
        assert!(
            capacity > k + 1,
            "replay capacity must exceed the stack size + 1"
        );
        Replay {
            capacity,
            k,
            frames: vec![0; capacity * FRAME_LEN],
            actions: vec![0; capacity],
            rewards: vec![0.0; capacity],
            dones: vec![false; capacity],
            starts: vec![false; capacity],
            acted: vec![false; capacity],
            n_step: 1,
            gamma: 1.0,
            lanes: 1,
            written: vec![0],
            picks: Vec::new(),
            priorities: None,
            shift: 0,
            shifted: Vec::new(),
        }
    }

    /// The same memory moving each sampled state by up to `pad` pixels each way (module
    /// documentation, "Random shifts"); 0 leaves states as stored and draws no random numbers.
    pub fn with_random_shift(mut self, pad: usize) -> Self {
        assert!(
            pad < FRAME_HEIGHT.min(FRAME_WIDTH),
            "a shift smaller than the frame"
        );
        self.shift = pad;
        self
    }

    /// The same memory sampling in proportion to `(|δ| + ε)^alpha` with loss weights
    /// `(N · P)^(−beta)` (module documentation, "Prioritized replay").
    pub fn with_priorities(mut self, alpha: f64, beta: f64) -> Self {
        assert!(
            (0.0..=1.0).contains(&alpha) && (0.0..=1.0).contains(&beta),
            "priority exponents in [0, 1]"
        );
        self.priorities = Some(Priorities {
            tree: SumTree::new(self.capacity),
            alpha,
            beta,
            max: 1.0,
        });
        self
    }

    /// The same memory split into `lanes` lanes of `capacity / lanes` entries each, for as many
    /// games played side by side (module documentation, "Several games"). Lane `l` holds the
    /// entries `l, l + lanes, l + 2·lanes, …` in the slots `l + lanes·j`; [`push_start_in`] and
    /// [`push_step_in`] write to one lane.
    ///
    /// [`push_start_in`]: Self::push_start_in
    /// [`push_step_in`]: Self::push_step_in
    ///
    /// # Panics
    /// If `lanes` is 0 or does not divide the capacity, if a lane would hold no more than a
    /// state's frames and one more, or if anything has been written.
    pub fn with_lanes(mut self, lanes: usize) -> Self {
        assert!(
            lanes >= 1 && self.capacity.is_multiple_of(lanes),
            "the lanes divide the capacity"
        );
        assert!(
            self.capacity / lanes > self.k + 1,
            "each lane's capacity must exceed the stack size + 1"
        );
        assert!(self.is_empty(), "lanes are set before anything is written");
        self.lanes = lanes;
        self.written = vec![0; lanes];
        self
    }

    /// The same memory sampling `n`-step returns discounted by `gamma` ([`Replay::sample`]).
    pub fn with_returns(mut self, n: usize, gamma: f32) -> Self {
        assert!(n >= 1, "returns of at least one step");
        self.n_step = n;
        self.gamma = gamma;
        self
    }

    /// The number of entries held (at most `capacity`).
    pub fn len(&self) -> usize {
        let cap = self.lane_capacity() as u64;
        self.written.iter().map(|&w| w.min(cap) as usize).sum()
    }

    /// Whether nothing has been stored.
    pub fn is_empty(&self) -> bool {
        self.written.iter().all(|&w| w == 0)
    }

    /// The number of lanes ([`Replay::with_lanes`]; 1 without).
    pub fn lanes(&self) -> usize {
        self.lanes
    }

    /// Entries written into each lane so far.
    pub fn lane_written(&self) -> &[u64] {
        &self.written
    }

    /// The entries one lane holds at most.
    fn lane_capacity(&self) -> usize {
        self.capacity / self.lanes
    }

    /// The slots in use, in whole rows of `lanes` slots: the rows a checkpoint saves (every held
    /// entry's slot is below it; with one lane, `len`).
    pub fn rows(&self) -> usize {
        rows(&self.written, self.lane_capacity())
    }

    /// The capacity in entries.
    pub fn capacity(&self) -> usize {
        self.capacity
    }

    /// Entries written since creation, in all lanes (with one lane, the global counter).
    pub fn written(&self) -> u64 {
        self.written.iter().sum()
    }

    fn slot(&self, g: u64) -> usize {
        (g % self.capacity as u64) as usize
    }

    /// The lane of entry `g`.
    fn lane(&self, g: u64) -> usize {
        (g % self.lanes as u64) as usize
    }

    /// The entry lane `l` writes next.
    fn next(&self, l: usize) -> u64 {
        self.written[l] * self.lanes as u64 + l as u64
    }

    /// The oldest entry lane `l` holds (or will hold first).
    fn oldest(&self, l: usize) -> u64 {
        let cap = self.lane_capacity() as u64;
        self.written[l].saturating_sub(cap) * self.lanes as u64 + l as u64
    }

    fn push_frame(&mut self, lane: usize, frame: &[u8], start: bool) {
        let s = self.slot(self.next(lane));
        if let Some(p) = &mut self.priorities {
            p.tree.set(s, 0.0); // not acted on yet (and whatever it held is gone)
        }
        self.frames[s * FRAME_LEN..][..FRAME_LEN].copy_from_slice(frame);
        self.starts[s] = start;
        self.acted[s] = false;
        self.written[lane] += 1;
    }

    /// Stores the first observation of an episode.
    pub fn push_start(&mut self, frame: &[u8]) {
        self.push_start_in(0, frame);
    }

    /// Stores the first observation of an episode of the game written to `lane`.
    pub fn push_start_in(&mut self, lane: usize, frame: &[u8]) {
        self.push_frame(lane, frame, true);
    }

    /// Records that the agent took `action` in the latest entry, received `reward`, and saw
    /// `next_frame`; `done` means the episode ended for good (a time limit is not `done`: the
    /// state still has a future, so its value is still bootstrapped).
    pub fn push_step(&mut self, action: usize, reward: f32, done: bool, next_frame: &[u8]) {
        self.push_step_in(0, action, reward, done, next_frame);
    }

    /// [`push_step`](Self::push_step) for the game written to `lane`.
    pub fn push_step_in(
        &mut self, lane: usize, action: usize, reward: f32, done: bool, next_frame: &[u8],
    ) {
        assert!(self.written[lane] > 0, "push_start comes first");
        let s = self.slot(self.next(lane) - self.lanes as u64);
        self.actions[s] = u8::try_from(action).expect("action index fits a byte");
        self.rewards[s] = reward;
        self.dones[s] = done;
        self.acted[s] = true;
        if let Some(p) = &mut self.priorities {
            p.tree.set(s, p.max);
        }
        self.push_frame(lane, next_frame, false);
    }

    /// Whether entry `g` can be sampled: it and its successor in its lane are held, and it was
    /// acted on.
    fn valid(&self, g: u64) -> bool {
        let l = self.lane(g);
        g >= self.oldest(l) && g + (self.lanes as u64) < self.next(l) && self.acted[self.slot(g)]
    }

    /// The `k` frames of the state ending at entry `g`, oldest first, or `None` if they reach back
    /// past the oldest entry held (the ring has overwritten them).
    fn state_frames(&self, g: u64) -> Option<[&[u8]; 4]> {
        let mut out: [&[u8]; 4] = [&[]; 4];
        let (mut e, oldest) = (g, self.oldest(self.lane(g)));
        for i in (0..self.k).rev() {
            out[i] = &self.frames[self.slot(e) * FRAME_LEN..][..FRAME_LEN];
            if i > 0 && !self.starts[self.slot(e)] {
                if e == oldest {
                    return None;
                }
                e -= self.lanes as u64;
            }
        }
        Some(out)
    }

    /// Whether at least `n` transitions can be sampled.
    pub fn can_sample(&self, n: usize) -> bool {
        // Each lane's newest entry has no successor yet.
        self.len() > n + self.k + self.lanes - 1
    }

    /// Frames per state.
    pub fn frames_per_state(&self) -> usize {
        self.k
    }

    /// The held entries for a checkpoint, in slot order (row `g % capacity` holds entry `g`):
    /// `(frames [rows · 88·80], actions [rows], rewards [rows], flags [rows])` with flag bits
    /// [`FLAG_DONE`], [`FLAG_START`], [`FLAG_ACTED`], over the [`rows`](Self::rows) in use (with
    /// lanes, a lane behind the others leaves rows of its own unwritten: their flags are 0).
    pub fn parts(&self) -> (&[u8], &[u8], &[f32], Vec<u8>) {
        let len = self.rows();
        let flags = (0..len)
            .map(|s| {
                let mut f = 0;
                if self.dones[s] {
                    f |= FLAG_DONE;
                }
                if self.starts[s] {
                    f |= FLAG_START;
                }
                if self.acted[s] {
                    f |= FLAG_ACTED;
                }
                f
            })
            .collect();
        (
            &self.frames[..len * FRAME_LEN],
            &self.actions[..len],
            &self.rewards[..len],
            flags,
        )
    }

    /// Replaces the contents with `parts` as made by [`parts`](Self::parts) of a memory of the
    /// same capacity and lanes that had written `written` entries into each lane, the frames
    /// written by `read_frames` straight into the memory's first `rows · 88·80` bytes (a loader
    /// streams a file into them without a second copy of the memory). Every length and flag is
    /// checked first; on an error from those checks nothing is changed, on one from
    /// `read_frames` the frames may be partly overwritten (discard the memory).
    pub fn restore(
        &mut self, written: &[u64], actions: &[u8], rewards: &[f32], flags: &[u8],
        read_frames: impl FnOnce(&mut [u8]) -> Result<(), String>,
    ) -> Result<(), String> {
        if written.len() != self.lanes {
            return Err(format!(
                "counters of {} lanes for a memory of {}",
                written.len(),
                self.lanes
            ));
        }
        let len = rows(written, self.lane_capacity());
        if actions.len() != len || rewards.len() != len || flags.len() != len {
            return Err(format!(
                "{written:?} entries written into a memory of {} need {len} rows of each array",
                self.capacity
            ));
        }
        if let Some(i) = flags
            .iter()
            .position(|f| f & !(FLAG_DONE | FLAG_START | FLAG_ACTED) != 0)
        {
            return Err(format!("unknown flag bits {:#x} in row {i}", flags[i]));
        }
        if let Some(i) = rewards.iter().position(|r| !r.is_finite()) {
            return Err(format!("non-finite reward in row {i}"));
        }
        read_frames(&mut self.frames[..len * FRAME_LEN])?;
        self.actions[..len].copy_from_slice(actions);
        self.rewards[..len].copy_from_slice(rewards);
        for (s, &f) in flags.iter().enumerate() {
            self.dones[s] = f & FLAG_DONE != 0;
            self.starts[s] = f & FLAG_START != 0;
            self.acted[s] = f & FLAG_ACTED != 0;
        }
        self.written = written.to_vec();
        Ok(())
    }

    /// The `n`-step return from entry `g` (valid): `(R, m, done)` with
    /// `R = r_g + γ r_{g+1} + … + γ^{m−1} r_{g+m−1}` over the `m ≤ n` steps taken before the episode
    /// ended (`done`: for good, so nothing is bootstrapped), the episode was cut, or the memory's
    /// newest step was reached; the target then bootstraps from the state at entry `g + m`.
    fn n_step_return(&self, g: u64) -> (f32, u32, bool) {
        let (mut ret, mut discount, mut j) = (0.0f32, 1.0f32, g);
        for m in 1..=self.n_step as u32 {
            let s = self.slot(j);
            ret += discount * self.rewards[s];
            if self.dones[s] {
                return (ret, m, true);
            }
            // The lane's next entry has no action when the episode was cut there, or it is the
            // newest.
            let after = j + self.lanes as u64;
            if m as usize == self.n_step || !self.valid(after) {
                return (ret, m, false);
            }
            discount *= self.gamma;
            j = after;
        }
        unreachable!("n_step >= 1")
    }

    /// The entry held in slot `s` (the one of the last `capacity` written that lives there).
    fn entry_in_slot(&self, s: usize) -> u64 {
        // The lane's own counter `j` of the entry in its slot `s / lanes`.
        let (l, n) = (s % self.lanes, self.lanes as u64);
        let cap = self.lane_capacity() as u64;
        let base = self.written[l].saturating_sub(cap);
        let j = base + ((s / self.lanes) as u64 + cap - base % cap) % cap;
        j * n + l as u64
    }

    /// Whether entry `g` can be sampled with its whole state.
    fn sampleable(&self, g: u64) -> bool {
        self.valid(g) && self.state_frames(g).is_some()
    }

    /// Fills `batch` with transitions drawn (with replacement) from those held, normalising frames
    /// with `table`: uniformly, or in proportion to their priorities
    /// ([`Replay::with_priorities`]; then `batch.weights` holds the loss weights and
    /// `batch.entries` the entries, for [`Replay::update_priorities`]). Each is
    /// `(s_g, a_g, R, s_{g+m}, done)` with the `n`-step return `R` over `m` steps
    /// ([`Replay::with_returns`]; `m = 1`, `R = r_g` by default).
    pub fn sample(&mut self, rng: &mut impl Rng, table: &[f32; 256], batch: &mut Batch) {
        assert!(self.k <= 4, "states of at most 4 frames");
        assert!(
            self.can_sample(batch.len()),
            "too few transitions to sample"
        );
        let mut picks = std::mem::take(&mut self.picks);
        picks.clear();
        batch.weights.clear();
        batch.entries.clear();
        match &self.priorities {
            None if self.lanes == 1 => {
                let (lo, hi) = (self.oldest(0), self.next(0) - 1);
                while picks.len() < batch.len() {
                    let g = rng.random_range(lo..hi);
                    if self.sampleable(g) {
                        picks.push(g);
                    }
                }
            }
            None => {
                // A slot in use at random, again until it holds a sampleable entry: uniform over
                // the sampleable entries of every lane.
                let rows = self.rows();
                while picks.len() < batch.len() {
                    let g = self.entry_in_slot(rng.random_range(0..rows));
                    if self.sampleable(g) {
                        picks.push(g);
                    }
                }
            }
            Some(p) => {
                // One draw from each of B equal segments of the priority mass; an entry whose
                // state reaches past the oldest frame held is drawn again (from anywhere after
                // a few tries, so a segment of only such entries cannot stall it).
                let total = p.tree.total();
                let segment = total / batch.len() as f64;
                for i in 0..batch.len() {
                    let mut tries = 0;
                    let g = loop {
                        let u = if tries < 8 {
                            (i as f64 + rng.random::<f64>()) * segment
                        } else {
                            rng.random::<f64>() * total
                        };
                        let s = p.tree.find(u).expect("sampleable entries have priorities");
                        let g = self.entry_in_slot(s);
                        if self.sampleable(g) {
                            break g;
                        }
                        tries += 1;
                    };
                    picks.push(g);
                }
                // w = (N·P)^(−β), over the batch's largest.
                let n = self.len() as f64;
                for &g in &picks {
                    let prob = p.tree.get(self.slot(g)) / total;
                    batch.weights.push((n * prob).powf(-p.beta) as f32);
                }
                let max = batch.weights.iter().fold(0.0f32, |m, &w| m.max(w));
                for w in &mut batch.weights {
                    *w /= max;
                }
                batch.entries.extend_from_slice(&picks);
            }
        }
        let border = batch.border;
        // The bytes' bf16 roundings, where the batch keeps them (`Batch::keep_bf16`).
        let rounded: Option<[u16; 256]> = batch
            .keep_bf16
            .then(|| std::array::from_fn(|v| to_bf16(table[v])));
        let mut shifted = std::mem::take(&mut self.shifted);
        shifted.resize(self.k * FRAME_LEN, 0);
        let pad = self.shift as i64;
        for (i, &g) in picks.iter().enumerate() {
            let (ret, m, done) = self.n_step_return(g);
            batch.actions[i] = self.actions[self.slot(g)] as usize;
            batch.rewards[i] = ret;
            batch.steps[i] = m;
            batch.dones[i] = done;
            let tables = (table, rounded.as_ref());
            let next = g + u64::from(m) * self.lanes as u64;
            for (entry, out) in [(g, &mut batch.states), (next, &mut batch.next_states)] {
                let state = self
                    .state_frames(entry)
                    .expect("a sampled entry and a later one of its episode are held");
                if pad == 0 {
                    write_state(&state[..self.k], tables, border, i, out);
                } else {
                    let dy = rng.random_range(-pad..=pad);
                    let dx = rng.random_range(-pad..=pad);
                    for (frame, to) in state[..self.k]
                        .iter()
                        .zip(shifted.chunks_exact_mut(FRAME_LEN))
                    {
                        shift_frame(frame, dy, dx, to);
                    }
                    let mut frames: [&[u8]; 4] = [&[]; 4];
                    for (f, c) in frames.iter_mut().zip(shifted.chunks_exact(FRAME_LEN)) {
                        *f = c;
                    }
                    write_state(&frames[..self.k], tables, border, i, out);
                }
            }
        }
        self.shifted = shifted;
        self.picks = picks;
    }

    /// Sets the priorities of the sampled `entries` from their TD errors `td`:
    /// `p = (|δ| + ε)^α` ([`PRIORITY_EPSILON`]). Entries no longer held are skipped; without
    /// prioritized sampling this does nothing.
    pub fn update_priorities(&mut self, entries: &[u64], td: &[f32]) {
        let held: Vec<(u64, u64)> = (0..self.lanes)
            .map(|l| (self.oldest(l), self.next(l)))
            .collect();
        let lanes = self.lanes as u64;
        let Some(p) = &mut self.priorities else {
            return;
        };
        assert_eq!(entries.len(), td.len(), "one TD error per entry");
        for (&g, &d) in entries.iter().zip(td) {
            let s = (g % self.capacity as u64) as usize;
            let (oldest, next) = held[(g % lanes) as usize];
            if g >= oldest && g < next && self.acted[s] {
                let v = (f64::from(d.abs()) + PRIORITY_EPSILON).powf(p.alpha);
                if v.is_finite() {
                    p.tree.set(s, v);
                    p.max = p.max.max(v);
                }
            }
        }
    }

    /// The priorities for a checkpoint: `(p per held slot in slot order, the largest ever)`,
    /// or `None` without prioritized sampling.
    pub fn priorities(&self) -> Option<(Vec<f64>, f64)> {
        self.priorities
            .as_ref()
            .map(|p| ((0..self.rows()).map(|s| p.tree.get(s)).collect(), p.max))
    }

    /// Restores what [`priorities`](Self::priorities) gave, after [`restore`](Self::restore).
    /// Each value must be finite and `>= 0`, positive exactly where the entry was acted on, and
    /// at most `max`.
    pub fn restore_priorities(&mut self, values: &[f64], max: f64) -> Result<(), String> {
        let len = self.rows();
        let acted = &self.acted;
        let Some(p) = &mut self.priorities else {
            return Err("this memory does not sample by priority".into());
        };
        if values.len() != len {
            return Err(format!("{} priorities for {len} entries", values.len()));
        }
        if !(max.is_finite() && max > 0.0) {
            return Err(format!("bad largest priority {max}"));
        }
        for (s, &v) in values.iter().enumerate() {
            if !(v.is_finite() && v >= 0.0 && v <= max) || (v > 0.0) != acted[s] {
                return Err(format!("bad priority {v} in row {s}"));
            }
        }
        for (s, &v) in values.iter().enumerate() {
            p.tree.set(s, v);
        }
        p.max = max;
        Ok(())
    }
}

/// The rows in use of a memory whose lanes of `lane_capacity` entries have written `written`
/// entries each: the longest lane's, in whole rows of `written.len()` slots.
fn rows(written: &[u64], lane_capacity: usize) -> usize {
    let longest = written.iter().map(|&w| w.min(lane_capacity as u64)).max();
    longest.unwrap_or(0) as usize * written.len()
}

/// Writes state `i` of a batch's `states` from its frames through `tables`: the values, and
/// their bf16 roundings as well where a table of those is given.
pub(super) fn write_state(
    frames: &[&[u8]], tables: (&[f32; 256], Option<&[u16; 256]>), border: Border, i: usize,
    states: &mut Tensor<f32>,
) {
    let per = states.len() / states.batch();
    match tables {
        (values, Some(rounded)) => states.write_with_bf16(|x, x16| {
            write_stacked_input_bordered(frames, values, border, &mut x[i * per..][..per]);
            write_stacked_input_bordered(frames, rounded, border, &mut x16[i * per..][..per]);
        }),
        (values, None) => {
            let x = &mut states.data_mut()[i * per..][..per];
            write_stacked_input_bordered(frames, values, border, x);
        }
    }
}

/// A minibatch of transitions `(s, a, r, s', done)`, laid out for the network.
pub struct Batch {
    /// `[B, H, W, C]`, normalised network inputs (inside `border`, if any).
    pub states: Tensor<f32>,
    /// `[B]`, indices into the action set.
    pub actions: Vec<usize>,
    /// `[B]`: the (n-step, discounted) returns `R` up to `s'`.
    pub rewards: Vec<f32>,
    /// `[B]`: the steps `m` from `s` to `s'` (1 for the one-step target); `s'` is discounted by `γ^m`.
    pub steps: Vec<u32>,
    /// `[B, H, W, C]`, likewise.
    pub next_states: Tensor<f32>,
    /// `[B]`, whether `s'` is terminal (then there is no future to bootstrap from).
    pub dones: Vec<bool>,
    /// `[B]` loss weights of prioritized sampling ([`super::Replay::with_priorities`]), or empty: all 1.
    pub weights: Vec<f32>,
    /// `[B]` the replay entries drawn, when sampling is prioritized (else empty).
    pub entries: Vec<u64>,
    /// `[B, N]`: an implicit quantile head's fractions `τ` for the online network's quantiles of
    /// each state ([`Batch::draw_fractions`]; else empty).
    pub taus: Vec<f64>,
    /// `[B, N']`: its fractions for the target's samples of each next state.
    pub target_taus: Vec<f64>,
    /// The zero border around each state image: none, or the network's first padding
    /// ([`input_border`]), so that conv1 reads the states in place (it would otherwise copy each
    /// batch into a padded buffer, about 11 MB of memory traffic per train step at batch 48).
    pub border: Border,
    /// Whether the states keep their values rounded to bf16 as well
    /// ([`Tensor::write_with_bf16`]), for a learner whose products run in bf16: conv1 then
    /// reads them in each of the train step's forward passes instead of rounding 5.4 MB of
    /// states (at batch 48) in each. Off for a new batch; the agent sets it.
    pub keep_bf16: bool,
}

impl Batch {
    /// An empty batch for inputs of shape `[H, W, C]`, to be filled by the replay memory.
    pub fn new(batch: usize, input: [usize; 3]) -> Self {
        Batch::with_border(batch, input, Border::default())
    }

    /// An empty batch laid out for the article's network with convolutions padded by
    /// `padding`: states inside conv1's padding ([`input_border`]; none for VALID), which conv1
    /// then reads in place. What the agent trains on.
    pub fn padded(batch: usize, input: [usize; 3], padding: Padding) -> Self {
        Batch::with_border(batch, input, input_border(input, padding))
    }

    /// An empty batch whose states are `[H + top + bottom, W + left + right, C]` images with
    /// the `[H, W, C]` input inside a zero border (the replay memory writes only the interior).
    pub fn with_border(batch: usize, input: [usize; 3], border: Border) -> Self {
        let (hb, wb) = border.around(input[0], input[1]);
        let shape = [batch, hb, wb, input[2]];
        Batch {
            states: Tensor::zeros(&shape),
            actions: vec![0; batch],
            rewards: vec![0.0; batch],
            steps: vec![1; batch],
            next_states: Tensor::zeros(&shape),
            dones: vec![false; batch],
            weights: Vec::new(),
            entries: Vec::new(),
            taus: Vec::new(),
            target_taus: Vec::new(),
            border,
            keep_bf16: false,
        }
    }

    /// A batch for `config`'s network filled at random, laid out as the agent's (states inside
    /// conv1's padding, [`Batch::padded`]): states uniform in [−1, 1), actions among 6, rewards
    /// in [0, 1), one transition in 20 terminal, and an implicit quantile head's fractions. The
    /// workload of the benchmarks and of `precision = "auto"`'s measurement.
    pub fn random(config: &super::Config, rng: &mut impl Rng) -> Batch {
        let input = config.input_shape();
        let border = super::Head::of(config).input_border(input);
        let mut b = Batch::with_border(config.batch_size, input, border);
        for states in [&mut b.states, &mut b.next_states] {
            for v in states.data_mut() {
                *v = rng.random_range(-1.0..1.0);
            }
            let [h, w, c] = input;
            b.border.zero(states.data_mut(), config.batch_size, h, w, c);
            // As an agent's batch in bf16 keeps them (f32 products ignore them).
            states.keep_bf16();
        }
        b.keep_bf16 = true;
        for i in 0..b.len() {
            b.actions[i] = rng.random_range(0..6);
            b.rewards[i] = rng.random_range(0.0..1.0);
            b.dones[i] = rng.random_bool(0.05);
        }
        if let Some(iqn) = config.iqn() {
            b.draw_fractions(rng, iqn.samples, iqn.target_samples);
        }
        b
    }

    /// Draws an implicit quantile head's fractions, uniform on `[0, 1)`: `n` per state and
    /// `n_target` per next state (IQN trains at fresh fractions every step).
    pub fn draw_fractions(&mut self, rng: &mut impl Rng, n: usize, n_target: usize) {
        let b = self.len();
        self.taus.clear();
        self.taus.extend((0..b * n).map(|_| rng.random::<f64>()));
        self.target_taus.clear();
        self.target_taus
            .extend((0..b * n_target).map(|_| rng.random::<f64>()));
    }

    /// The number of transitions.
    pub fn len(&self) -> usize {
        self.actions.len()
    }

    /// Whether the batch is empty.
    pub fn is_empty(&self) -> bool {
        self.actions.is_empty()
    }
}
