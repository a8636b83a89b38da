//! # invaders
//!
//! A from-scratch, CPU-only deep-learning library with hand-written kernels, and a Deep Q-Network
//! built on it that learns Atari Space Invaders through the Arcade Learning Environment.
//!
//! * [`tensor`]: NHWC tensors, GEMM and convolution kernels (with plain reference kernels).
//! * [`ops`]: the one door from the layers to the kernels: each product by the kernel the plan
//!   picks for its shape, batch, precision and CPU.
//! * [`layers`]: `Conv2d`, `Dense`, `ReLU`, `Flatten`, `Sequential`, initialisers and losses,
//!   each with its forward and backward pass side by side.
//! * [`optim`]: Adam and SGD.
//! * [`mod@env`]: Space Invaders through the ALE, the article's preprocessing and frame pipelines.
//! * [`dqn`]: the agent, its replay memory and the training loop.

// The library prints nothing: messages are the program's (src/cli/streams.rs).
#![deny(clippy::print_stdout, clippy::print_stderr)]

pub mod dqn;
pub mod env;
pub mod layers;
pub mod ops;
pub mod optim;
pub mod tensor;

pub use tensor::CacheAligned;
