//! The Deep Q-Network: the Q-network, replay memory, configuration and training loop.

mod acting;
mod agent;
pub mod checkpoint;
mod config;
mod heads;
mod learner;
mod pqn;
mod precision;
mod qnet;
mod replay;
mod sumtree;
pub mod tensorboard;
mod trainer;

pub use acting::{greedy, play_evaluation_episode, random_play_inputs};
pub use agent::{Agent, AgentState, EpisodeRow, GameSlot, LoopTimes};
pub use config::{
    merge_toml, Config, Pqn, Preset, ARTICLE_HIDDEN, IMPORTANCE_EXPONENT, MAX_PQN_GAMES,
    NO_EPISODE_LIMIT, PRIORITY_EXPONENT, STRONG_FRAMES, STRONG_V1_FRAMES,
};
pub use learner::{argmax, greedy_atoms, Learner, Munchausen, NextValues, StepStats, TargetRule};
pub use pqn::{game_seed, q_lambda_returns, Player, PqnAgent};
pub use precision::{resolve_precision, Resolved};
pub use qnet::{
    article_qnet, impala_encoder, input_border, midpoints, qnet, Encoder, Head, Impala, Iqn,
    IqnMerge, IMPALA_BLOCKS, IMPALA_CHANNELS,
};
pub use replay::{shift_frame, Batch, Replay, FLAG_ACTED, FLAG_DONE, FLAG_START, PRIORITY_EPSILON};
pub use sumtree::SumTree;
pub use trainer::Trainer;
