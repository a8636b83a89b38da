//! What the agent needs from a game, so the same training loop drives Space Invaders and the
//! small toy games of the tests.

use super::{SpaceInvaders, StepResult};

/// An episodic game with a discrete action set and 88x80 grey frames.
pub trait Game {
    /// Number of actions.
    fn n_actions(&self) -> usize;
    /// Starts a new episode.
    fn reset(&mut self);
    /// Plays one agent step.
    fn step(&mut self, action: usize) -> StepResult;
    /// The last two raw (preprocessed) frames of the latest step, older first.
    fn last_two_frames(&self) -> (&[u8], &[u8]);
    /// The observation of the latest step (the last frame, or a max-pool of the two).
    fn observation(&self) -> &[u8];
}

impl Game for SpaceInvaders {
    fn n_actions(&self) -> usize {
        SpaceInvaders::n_actions(self)
    }
    fn reset(&mut self) {
        SpaceInvaders::reset(self)
    }
    fn step(&mut self, action: usize) -> StepResult {
        SpaceInvaders::step(self, action)
    }
    fn last_two_frames(&self) -> (&[u8], &[u8]) {
        SpaceInvaders::last_two_frames(self)
    }
    fn observation(&self) -> &[u8] {
        SpaceInvaders::observation(self)
    }
}
