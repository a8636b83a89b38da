//! `cargo +nightly fuzz run checkpoint`: checkpoint bytes must load or give an error, never panic.
//! Seed the corpus with a real checkpoint (see `examples/fuzz_loop.rs` for one way to make it).
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(c) = invaders::dqn::checkpoint::from_bytes(data) {
        assert!(c.learner.non_finite_param().is_none());
        c.config.validate().expect("a loaded config is valid");
    }
});
