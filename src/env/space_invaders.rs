//! The Space Invaders environment: one agent step = one action repeated for a few emulator frames.
//!
//! An agent does not act on every one of the Atari's 60 frames per second: each agent step
//! repeats the chosen action for `k` frames ("frame skip") and sums the rewards. This wrapper does
//! the repeating itself (the emulator runs with frame skip 1), so it can keep the last *two* raw
//! frames of every step: DeepMind's agents take their element-wise maximum, because the Atari
//! draws some sprites only on every other frame.
//!
//! **Sticky actions** (Machado et al. 2018) make the game stochastic: on every emulator frame,
//! with probability `sticky_prob`, the console keeps executing the previous action instead of the
//! new one. ALE can do this itself, but it keeps the previous action outside its saveable state,
//! so an emulator restored from a save would not continue identically. We therefore switch ALE's
//! version off and implement the very same rule here, with our own seeded random generator, whose
//! state is saved along with everything else.
//!
//! Each step yields the last two raw frames preprocessed to 88 x 80 grey
//! ([`last_two_frames`](SpaceInvaders::last_two_frames)); the [`pipeline`](super::pipeline) turns
//! them into the network's input.

use rand::{Rng, RngCore, SeedableRng};
use rand_chacha::ChaCha8Rng;

use super::ale::{Ale, AleSettings, SCREEN_RGB_LEN};
use super::preprocess::{max_into, preprocess_rgb, FRAME_LEN};
use super::{EnvConfig, EnvError};

/// ALE's id of the "do nothing" action.
const NOOP: i32 = 0;

/// What one agent step did.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StepResult {
    /// Sum of the game's rewards over the step's frames (Space Invaders: 5 to 30 per invader,
    /// up to 200 for the mothership).
    pub reward: f32,
    /// The game is over (all lives lost). Bootstrapping must stop here.
    pub terminal: bool,
    /// The episode was cut by `max_episode_steps` while the game was still running (never true
    /// together with `terminal`). The value of the next state is still meaningful.
    pub truncated: bool,
    /// Lives left after the step.
    pub lives: i32,
    /// Emulator frames played during this step.
    pub frames: u32,
}

/// Running statistics of the current episode.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct EpisodeStats {
    /// Sum of rewards since reset (the game's score).
    pub score: f64,
    /// Agent steps since reset.
    pub steps: u32,
    /// Emulator frames since reset, including the no-op frames played by the reset itself.
    pub frames: u64,
}

/// Space Invaders through the ALE, with the configured frame skip, sticky actions and limits.
///
/// `Send` but not `Sync` (it owns a C++ emulator, [`Ale`]): one thread at a time steps it.
pub struct SpaceInvaders {
    ale: Ale,
    config: EnvConfig,
    /// ALE ids of the actions the agent chooses from (index = agent action).
    actions: Vec<i32>,
    /// Drives frame skip draws, sticky actions and no-op starts.
    rng: ChaCha8Rng,
    /// The action the console is currently executing (what a sticky frame repeats).
    held_action: i32,
    /// RGB screens of the second-to-last and the last emulated frame.
    rgb_prev: Vec<u8>,
    rgb_last: Vec<u8>,
    /// The same two frames, preprocessed to 88 x 80, and the observation made from them.
    frame_prev: Vec<u8>,
    frame_last: Vec<u8>,
    observation: Vec<u8>,
    stats: EpisodeStats,
    lives: i32,
    /// The episode ended (terminal or truncated) and needs a reset before the next step.
    finished: bool,
}

impl SpaceInvaders {
    /// Builds the emulator with `config` and starts the first episode.
    ///
    /// `seed` determines everything random: frame skips, sticky actions and no-op starts.
    pub fn new(config: &EnvConfig, seed: u64) -> Result<Self, EnvError> {
        config.validate()?;
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let settings = AleSettings {
            random_seed: (rng.next_u32() >> 1) as i32,
            repeat_action_probability: 0.0,
            verbose: config.ale_verbose,
        };
        let ale = Ale::new(&settings, config.rom.as_deref())?;
        let actions = if config.full_action_set {
            ale.legal_action_set().to_vec()
        } else {
            ale.minimal_action_set().to_vec()
        };
        let mut env = SpaceInvaders {
            ale,
            config: config.clone(),
            actions,
            rng,
            held_action: NOOP,
            rgb_prev: vec![0; SCREEN_RGB_LEN],
            rgb_last: vec![0; SCREEN_RGB_LEN],
            frame_prev: vec![0; FRAME_LEN],
            frame_last: vec![0; FRAME_LEN],
            observation: vec![0; FRAME_LEN],
            stats: EpisodeStats::default(),
            lives: 0,
            finished: false,
        };
        env.reset();
        Ok(env)
    }

    /// The configuration this environment was built with.
    pub fn config(&self) -> &EnvConfig {
        &self.config
    }

    /// Number of actions the agent chooses from (6, or 18 with the full action set).
    pub fn n_actions(&self) -> usize {
        self.actions.len()
    }

    /// ALE ids of the agent's actions, in agent-action order.
    pub fn action_ids(&self) -> &[i32] {
        &self.actions
    }

    /// Starts a new episode: resets the game, then plays a random number of no-op frames in
    /// `0..=noop_max`. Both "last two frames" are the reset screen when no frame was played.
    pub fn reset(&mut self) {
        loop {
            self.ale.reset_game();
            // Like ALE's own reset, a new game starts with no action held.
            self.held_action = NOOP;
            self.stats = EpisodeStats::default();
            self.finished = false;
            self.capture();
            self.rgb_prev.copy_from_slice(&self.rgb_last);
            self.frame_prev.copy_from_slice(&self.frame_last);
            let noops = if self.config.noop_max > 0 {
                self.rng.random_range(0..=self.config.noop_max)
            } else {
                0
            };
            for _ in 0..noops {
                self.ale.act(NOOP);
                self.stats.frames += 1;
                self.capture();
            }
            // 30 no-ops cannot end a game of Space Invaders, but be safe.
            if !self.ale.game_over() {
                break;
            }
        }
        self.lives = self.ale.lives();
        self.make_observation();
    }

    /// Plays one agent step with agent action `action` (an index below
    /// [`n_actions`](Self::n_actions)).
    ///
    /// The action is repeated for a number of frames drawn in `frame_skip_min..=frame_skip_max`,
    /// stopping early if the game ends.
    ///
    /// # Panics
    /// If `action` is out of range, or if the episode has already ended (call
    /// [`reset`](Self::reset) after a terminal or truncated step).
    pub fn step(&mut self, action: usize) -> StepResult {
        assert!(
            action < self.actions.len(),
            "action {action} out of range 0..{}",
            self.actions.len()
        );
        assert!(
            !self.finished,
            "step() called on a finished episode; call reset() first"
        );
        let wanted = self.actions[action];
        let skip = if self.config.frame_skip_min == self.config.frame_skip_max {
            self.config.frame_skip_min
        } else {
            self.rng
                .random_range(self.config.frame_skip_min..=self.config.frame_skip_max)
        };
        let mut reward = 0i64;
        let mut frames = 0u32;
        let mut terminal = false;
        for i in 0..skip {
            if self.config.sticky_prob == 0.0 || self.rng.random::<f64>() >= self.config.sticky_prob
            {
                self.held_action = wanted;
            }
            reward += self.ale.act(self.held_action) as i64;
            frames += 1;
            terminal = self.ale.game_over();
            // Keep the last two frames (when the game ends early, the one before the last may
            // be older: the emulator does not let us go back for it).
            if i + 2 >= skip || terminal {
                self.capture();
            }
            if terminal {
                break;
            }
        }
        self.stats.steps += 1;
        self.stats.frames += frames as u64;
        self.stats.score += reward as f64;
        self.lives = self.ale.lives();
        let truncated = !terminal
            && self.stats.steps
                >= self
                    .config
                    .max_episode_steps
                    .unwrap_or(super::config::MAX_EPISODE_STEPS);
        self.finished = terminal || truncated;
        self.make_observation();
        StepResult {
            reward: reward as f32,
            terminal,
            truncated,
            lives: self.lives,
            frames,
        }
    }

    /// Shifts the last frame to "previous" and grabs and preprocesses the current screen.
    fn capture(&mut self) {
        std::mem::swap(&mut self.rgb_prev, &mut self.rgb_last);
        std::mem::swap(&mut self.frame_prev, &mut self.frame_last);
        self.ale.screen_rgb(&mut self.rgb_last);
        preprocess_rgb(
            &self.rgb_last,
            self.config.contrast_rgb_sum,
            self.config.crop,
            self.config.downsample,
            &mut self.frame_last,
        );
    }

    fn make_observation(&mut self) {
        if self.config.max_pool_last_two {
            max_into(&self.frame_prev, &self.frame_last, &mut self.observation);
        } else {
            self.observation.copy_from_slice(&self.frame_last);
        }
    }

    /// The last two raw frames of the latest step (or reset), oldest first, each preprocessed to
    /// 88 x 80 grey.
    pub fn last_two_frames(&self) -> (&[u8], &[u8]) {
        (&self.frame_prev, &self.frame_last)
    }

    /// The environment's observation of the latest step: the max of the last two frames if
    /// `max_pool_last_two`, otherwise the last frame (88 x 80 grey).
    pub fn observation(&self) -> &[u8] {
        &self.observation
    }

    /// The last emulated frame in colour, `210 * 160 * 3` bytes (row-major RGB), for recordings.
    pub fn screen_rgb(&self) -> &[u8] {
        &self.rgb_last
    }

    /// Statistics of the current episode.
    pub fn episode(&self) -> EpisodeStats {
        self.stats
    }

    /// Lives left.
    pub fn lives(&self) -> i32 {
        self.lives
    }

    /// True after a terminal or truncated step, until [`reset`](Self::reset).
    pub fn is_finished(&self) -> bool {
        self.finished
    }

    /// Direct access to the emulator (for tests and diagnostics).
    pub fn ale(&self) -> &Ale {
        &self.ale
    }

    /// Serialises everything needed to continue this episode exactly: the emulator, our random
    /// generator, the held action, counters and the current frames (about 120 KB).
    pub fn save_state(&self) -> Vec<u8> {
        let mut w = Vec::with_capacity(SCREEN_RGB_LEN + 3 * FRAME_LEN + 16_384);
        w.extend_from_slice(STATE_MAGIC);
        put_bytes(&mut w, self.config.dynamics_fingerprint().as_bytes());
        w.extend_from_slice(&self.rng.get_seed());
        w.extend_from_slice(&self.rng.get_stream().to_le_bytes());
        w.extend_from_slice(&self.rng.get_word_pos().to_le_bytes());
        w.extend_from_slice(&self.held_action.to_le_bytes());
        w.extend_from_slice(&self.stats.score.to_le_bytes());
        w.extend_from_slice(&self.stats.steps.to_le_bytes());
        w.extend_from_slice(&self.stats.frames.to_le_bytes());
        w.extend_from_slice(&self.lives.to_le_bytes());
        w.push(self.finished as u8);
        w.extend_from_slice(&self.frame_prev);
        w.extend_from_slice(&self.frame_last);
        w.extend_from_slice(&self.rgb_last);
        put_bytes(&mut w, &self.ale.save_state());
        w
    }

    /// Restores a state made by [`save_state`](Self::save_state) of an environment with the same
    /// dynamics settings (the seed it was built with does not matter). Afterwards the same
    /// actions give the same frames and rewards as in the saved environment.
    pub fn restore_state(&mut self, bytes: &[u8]) -> Result<(), EnvError> {
        let mut r = Reader(bytes);
        if r.take(STATE_MAGIC.len())? != STATE_MAGIC {
            return Err(EnvError::BadState(
                "not a saved Space Invaders environment".into(),
            ));
        }
        let fingerprint = r.bytes()?;
        if fingerprint != self.config.dynamics_fingerprint().as_bytes() {
            return Err(EnvError::BadState(format!(
                "saved with different settings ({}) than this environment's ({})",
                String::from_utf8_lossy(fingerprint),
                self.config.dynamics_fingerprint()
            )));
        }
        let seed: [u8; 32] = r.array()?;
        let stream = u64::from_le_bytes(r.array()?);
        let word_pos = u128::from_le_bytes(r.array()?);
        let held_action = i32::from_le_bytes(r.array()?);
        let score = f64::from_le_bytes(r.array()?);
        let steps = u32::from_le_bytes(r.array()?);
        let frames = u64::from_le_bytes(r.array()?);
        let lives = i32::from_le_bytes(r.array()?);
        let finished = r.take(1)?[0] != 0;
        let frame_prev = r.take(FRAME_LEN)?;
        let frame_last = r.take(FRAME_LEN)?;
        let rgb_last = r.take(SCREEN_RGB_LEN)?;
        let ale_state = r.bytes()?;
        if !r.0.is_empty() || !(0..18).contains(&held_action) {
            return Err(EnvError::BadState("malformed environment state".into()));
        }
        self.ale.restore_state(ale_state)?;
        let mut rng = ChaCha8Rng::from_seed(seed);
        rng.set_stream(stream);
        rng.set_word_pos(word_pos);
        self.rng = rng;
        self.held_action = held_action;
        self.stats = EpisodeStats {
            score,
            steps,
            frames,
        };
        self.lives = lives;
        self.finished = finished;
        self.frame_prev.copy_from_slice(frame_prev);
        self.frame_last.copy_from_slice(frame_last);
        self.rgb_last.copy_from_slice(rgb_last);
        self.make_observation();
        Ok(())
    }
}

const STATE_MAGIC: &[u8] = b"invaders-env-state-v1";

fn put_bytes(w: &mut Vec<u8>, b: &[u8]) {
    w.extend_from_slice(&(b.len() as u64).to_le_bytes());
    w.extend_from_slice(b);
}

/// A cursor over a saved state that turns running out of bytes into an error.
struct Reader<'a>(&'a [u8]);

impl<'a> Reader<'a> {
    fn take(&mut self, n: usize) -> Result<&'a [u8], EnvError> {
        if self.0.len() < n {
            return Err(EnvError::BadState("truncated environment state".into()));
        }
        let (head, tail) = self.0.split_at(n);
        self.0 = tail;
        Ok(head)
    }

    fn array<const N: usize>(&mut self) -> Result<[u8; N], EnvError> {
        Ok(self.take(N)?.try_into().expect("length checked"))
    }

    fn bytes(&mut self) -> Result<&'a [u8], EnvError> {
        let n = u64::from_le_bytes(self.array()?);
        self.take(usize::try_from(n).map_err(|_| EnvError::BadState("bad length".into()))?)
    }
}
