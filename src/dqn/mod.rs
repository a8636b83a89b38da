//! The Deep Q-Network: the Q-network, replay memory and training loop.

mod learner;
mod qnet;

pub use learner::{argmax, Batch, Learner, StepStats};
pub use qnet::article_qnet;
