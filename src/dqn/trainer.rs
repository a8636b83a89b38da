//! What a training run drives and a checkpoint saves, whichever algorithm learns: the DQN agent
//! ([`Agent`], one game and a replay memory) or the PQN agent ([`PqnAgent`], several games and
//! rollouts).

use super::agent::Counters;
use super::{Agent, AgentState, Config, EpisodeRow, Learner, PqnAgent, Replay};
use crate::env::Game;

/// A run's agent as `train` and the checkpoints see it.
pub trait Trainer {
    /// The run's configuration.
    fn config(&self) -> &Config;
    /// Its progress.
    fn counters(&self) -> &Counters;
    /// Its networks and optimizer.
    fn learner(&self) -> &Learner;
    /// Everything else a checkpoint needs to continue it exactly, but the replay memory.
    fn state(&self) -> AgentState;
    /// The replay memory, if it learns from one.
    fn replay(&self) -> Option<&Replay>;
    /// Plays (and learns) until the next episode ends; that episode's row.
    ///
    /// # Errors
    /// If training diverges.
    fn play_episode(&mut self) -> anyhow::Result<EpisodeRow>;
    /// Whether the run is over: its budget of episodes or frames is spent, and every finished
    /// episode's row has been handed out.
    fn finished(&self) -> bool;
}

/// The methods both agents implement alike: their fields `config`, `counters` and `learner`,
/// and their own `state` and `play_episode`.
macro_rules! alike {
    ($agent:ident) => {
        fn config(&self) -> &Config {
            &self.config
        }
        fn counters(&self) -> &Counters {
            &self.counters
        }
        fn learner(&self) -> &Learner {
            &self.learner
        }
        fn state(&self) -> AgentState {
            $agent::state(self)
        }
        fn play_episode(&mut self) -> anyhow::Result<EpisodeRow> {
            $agent::play_episode(self)
        }
    };
}

impl<G: Game> Trainer for Agent<G> {
    alike!(Agent);
    fn replay(&self) -> Option<&Replay> {
        Some(&self.replay)
    }
    /// With several games side by side, as PQN's: the agent step that crosses a frame budget
    /// finishes every game's step, and the rows of the episodes finished still go out.
    fn finished(&self) -> bool {
        let c = &self.counters;
        c.episodes >= self.config.episodes
            || (self.config.max_frames > 0
                && c.frames >= self.config.max_frames
                && self.pending() == 0)
    }
}

impl<G: Game> Trainer for PqnAgent<G> {
    alike!(PqnAgent);
    fn replay(&self) -> Option<&Replay> {
        None
    }
    /// Rollouts overshoot a frame budget: the rollout that crosses it finishes, and the rows of
    /// the episodes it finished still go out; a call of `play_episode` plays on until some game
    /// ends an episode (at most one episode's length of the longest game in play).
    fn finished(&self) -> bool {
        let c = &self.counters;
        c.episodes >= self.config.episodes
            || (self.config.max_frames > 0
                && c.frames >= self.config.max_frames
                && self.pending() == 0)
    }
}
