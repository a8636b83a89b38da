//! Space Invaders through the Arcade Learning Environment, and the article's frame processing.
//!
//! The path from the console to the network, one file per step:
//!
//! 1. [`ale`]: the emulator (a safe wrapper over ALE 0.6) with the bundled ROM.
//! 2. [`config`]: how the game is played ([`EnvMode`] `v0`, `nature`, `v5`, and every knob).
//! 3. [`space_invaders`]: agent steps with frame skip, sticky actions, no-op starts and time
//!    limits; each step keeps its last two raw frames.
//! 4. [`preprocess`]: crop + downsample + grey to 88 x 80 `u8`, and normalisation to `f32`.
//! 5. [`pipeline`]: one composite frame per step ([`Composer`]), the last `k` of them stacked
//!    ([`FrameStack`]) into the network's NHWC input.
//!
//! ```no_run
//! use invaders::env::{EnvConfig, EnvMode, Normalization, Observer, Pipeline, SpaceInvaders};
//! let mut env = SpaceInvaders::new(&EnvConfig::from_mode(EnvMode::V0), 0)?;
//! let mut obs = Observer::new(Pipeline::StackMax);
//! let table = Normalization::Symmetric.table();
//! let mut input = vec![0.0f32; obs.input_len()];
//! obs.reset(&env);
//! loop {
//!     obs.write_input(&table, &mut input); // the network would choose from this
//!     let r = env.step(1); // FIRE
//!     obs.step(&env);
//!     if r.terminal || r.truncated {
//!         break;
//!     }
//! }
//! println!("score {}", env.episode().score);
//! # Ok::<(), invaders::env::EnvError>(())
//! ```

pub mod ale;
pub mod config;
mod error;
pub mod game;
pub mod pipeline;
pub mod preprocess;
pub mod space_invaders;

pub use config::{EnvConfig, EnvMode};
pub use error::EnvError;
pub use game::Game;
pub use pipeline::{
    write_stacked_input, write_stacked_input_bordered, Composer, FrameStack, Observer, Pipeline,
};
pub use preprocess::{
    max_into, mothership_on_screen, normalize_into, preprocess_rgb, Crop, Downsample,
    Normalization, FRAME_HEIGHT, FRAME_LEN, FRAME_WIDTH, MOTHERSHIP_RGB, MSPACMAN_RGB_SUM,
};
pub use space_invaders::{EpisodeStats, SpaceInvaders, StepResult};
