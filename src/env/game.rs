//! What the agent needs from a game, so the same training loop drives Space Invaders and the
//! small toy games of the tests.

use super::{EnvError, SpaceInvaders, StepResult};

/// An episodic game with a discrete action set and 88x80 grey frames. `Send`, so that the games
/// an agent plays side by side step in parallel ([`crate::dqn::Config::games`]).
pub trait Game: Send {
    /// Number of actions.
    fn n_actions(&self) -> usize;
    /// Starts a new episode.
    fn reset(&mut self);
    /// Plays one agent step.
    fn step(&mut self, action: usize) -> StepResult;
    /// The observation of the latest step (the last frame, or a max-pool of the two).
    fn observation(&self) -> &[u8];
    /// The last two raw (preprocessed) frames of the latest step, older first. The default,
    /// the observation twice, is right only for a game whose observation is its last frame and
    /// that does not flicker (the toy games of the tests); a game that composes its
    /// observation from two frames, as [`SpaceInvaders`] does, returns the two.
    fn last_two_frames(&self) -> (&[u8], &[u8]) {
        (self.observation(), self.observation())
    }
    /// Everything needed to continue the game bit-identically (for checkpoints), or `None` if
    /// this game cannot be saved (then a resumed run starts it afresh).
    fn save_state(&self) -> Option<Vec<u8>> {
        None
    }
    /// Restores a state made by [`save_state`](Self::save_state).
    fn restore_state(&mut self, _state: &[u8]) -> Result<(), EnvError> {
        Err(EnvError::BadState(
            "this game cannot restore a saved state".into(),
        ))
    }
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
    fn save_state(&self) -> Option<Vec<u8>> {
        Some(SpaceInvaders::save_state(self))
    }
    fn restore_state(&mut self, state: &[u8]) -> Result<(), EnvError> {
        SpaceInvaders::restore_state(self, state)
    }
}
