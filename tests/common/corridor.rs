//! A toy game for the learning tests.

use invaders::env::{Game, StepResult, FRAME_LEN, FRAME_WIDTH};

/// A corridor of `LEN` cells drawn as a bright vertical band at the agent's cell. Actions: 0 =
/// left, 1 = right. Reaching the last cell gives reward 1 and ends the episode; every other step
/// gives 0; episodes are cut after `LIMIT` steps. The optimal policy walks right: return 1 in
/// `LEN − 1` steps, and `Q*(cell i, right) = γ^(LEN − 2 − i)`.
pub struct Corridor {
    /// The agent's cell.
    pub pos: usize,
    steps: u32,
    frame: Vec<u8>,
}

/// Cells.
pub const LEN: usize = 4;
/// Steps before an episode is cut.
pub const LIMIT: u32 = 12;

impl Corridor {
    /// The agent at cell 0.
    pub fn new() -> Self {
        let mut c = Corridor {
            pos: 0,
            steps: 0,
            frame: vec![0; FRAME_LEN],
        };
        c.draw();
        c
    }
    /// Redraws the frame after `pos` changed.
    pub fn draw(&mut self) {
        let band = FRAME_WIDTH / LEN;
        for (i, p) in self.frame.iter_mut().enumerate() {
            *p = if (i % FRAME_WIDTH) / band == self.pos {
                255
            } else {
                0
            };
        }
    }
}

impl Game for Corridor {
    fn n_actions(&self) -> usize {
        2
    }
    fn reset(&mut self) {
        self.pos = 0;
        self.steps = 0;
        self.draw();
    }
    fn step(&mut self, action: usize) -> StepResult {
        assert!(
            self.pos != LEN - 1 && self.steps < LIMIT,
            "a step after the episode's end"
        );
        self.pos = if action == 1 {
            self.pos + 1
        } else {
            self.pos.saturating_sub(1)
        };
        self.steps += 1;
        self.draw();
        let terminal = self.pos == LEN - 1;
        let reward = if terminal { 1.0 } else { 0.0 };
        super::toy_step(reward, terminal, !terminal && self.steps >= LIMIT)
    }
    fn observation(&self) -> &[u8] {
        &self.frame
    }
    fn save_state(&self) -> Option<Vec<u8>> {
        Some(
            [
                [self.pos as u8],
                self.steps.to_le_bytes()[..1].try_into().unwrap(),
            ]
            .concat(),
        )
    }
    fn restore_state(&mut self, state: &[u8]) -> Result<(), invaders::env::EnvError> {
        let [pos, steps] = state else {
            return Err(invaders::env::EnvError::BadState(
                "a corridor's state is 2 bytes".into(),
            ));
        };
        self.pos = *pos as usize;
        self.steps = *steps as u32;
        self.draw();
        Ok(())
    }
}

impl Default for Corridor {
    fn default() -> Self {
        Corridor::new()
    }
}

/// Asserts that an agent has learned the corridor at `cell` from its values `q` there: moving
/// right is greedy, and its value is within 0.15 of `Q*(cell, right) = γ^(LEN − 2 − cell)`, γ = 0.9.
pub fn assert_learned(cell: usize, q: &[f32]) {
    let want = 0.9f32.powi((LEN - 2 - cell) as i32);
    assert_eq!(invaders::dqn::argmax(q), 1, "cell {cell}: Q = {q:?}");
    assert!(
        (q[1] - want).abs() < 0.15,
        "cell {cell}: Q(right) = {}, want about {want}",
        q[1]
    );
}

/// What a corridor run leaves, for comparing two: each episode's metrics row (without its wall
/// time), the train steps, and both networks' weights.
#[allow(dead_code)]
pub type Run = (Vec<String>, u64, Vec<Vec<f32>>);

/// A run of `config` on corridors, the agent made by `make` (with `config.games` corridors, or
/// one): its [`Run`] after `episodes` rows on a pool of `threads` threads.
#[allow(dead_code)]
pub fn run(
    config: invaders::dqn::Config, episodes: usize, threads: usize,
    make: impl FnOnce(invaders::dqn::Config) -> invaders::dqn::Agent<Corridor> + Send,
) -> Run {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    pool.install(|| {
        let mut agent = make(config);
        let rows = (0..episodes)
            .map(|_| {
                let row = agent.play_episode().unwrap().csv();
                row.rsplit_once(',').unwrap().0.to_string()
            })
            .collect();
        let nets = [&agent.learner.online, agent.learner.target()];
        let weights = nets
            .iter()
            .flat_map(|n| {
                n.params()
                    .map(|p| p.value.data().to_vec())
                    .collect::<Vec<_>>()
            })
            .collect();
        (rows, agent.counters.train_steps, weights)
    })
}

/// [`run`] with the configuration's games, all corridors (`Agent::with_games`).
#[allow(dead_code)]
pub fn run_games(config: invaders::dqn::Config, episodes: usize, threads: usize) -> Run {
    run(config, episodes, threads, |c| {
        let games = (0..c.games).map(|_| Corridor::new()).collect();
        invaders::dqn::Agent::with_games(c, games).unwrap()
    })
}
