//! `cargo +nightly fuzz run config`: any text must resolve to a valid configuration or give an
//! error, never panic.
#![no_main]

use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(text) = std::str::from_utf8(data) {
        if let Ok(c) = invaders::dqn::Config::resolve(None, Some(text)) {
            c.validate().expect("a resolved config is valid");
            // The resolved config survives its own TOML.
            let again = invaders::dqn::Config::resolve(None, Some(&c.to_toml()))
                .expect("a resolved config resolves again");
            assert_eq!(again, c);
        }
    }
});
