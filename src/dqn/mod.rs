//! The Deep Q-Network: the Q-network, replay memory and training loop.

mod qnet;

pub use qnet::article_qnet;
