//! Errors of the environment module.

use std::path::PathBuf;

/// Everything that can go wrong while building, configuring or restoring an environment.
///
/// Misuse that is a programming error (an action index out of range, stepping a finished
/// episode, a buffer of the wrong length) panics instead, like slice indexing does.
#[derive(Debug, thiserror::Error)]
pub enum EnvError {
    /// A configuration value is out of range (frame skip 0, min > max, sticky outside [0, 1], ...).
    #[error("invalid environment configuration: {0}")]
    InvalidConfig(String),
    /// The ROM file given with `--rom` does not exist.
    #[error("ROM file not found: {}", .0.display())]
    RomNotFound(PathBuf),
    /// The ROM file exists but could not be read.
    #[error("cannot read ROM file {}: {source}", .path.display())]
    RomUnreadable {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The ROM file is empty (or not a regular file).
    #[error("ROM file {} is empty or not a regular file", .0.display())]
    RomEmpty(PathBuf),
    /// The file is not a Space Invaders ROM this program knows.
    #[error(
        "{} is not a Space Invaders ROM ({size} bytes, CRC-32 {crc:08x}; the known dump has 4096 bytes, CRC-32 d1ef5725)",
        .path.display()
    )]
    RomUnknown {
        path: PathBuf,
        size: usize,
        crc: u32,
    },
    /// The private temporary copy of the ROM (the ALE loads a ROM from a file) could not be
    /// written in the temporary directory `dir`.
    #[error(
        "cannot write the ROM's temporary copy (the emulator loads it from a file) under {} \
         (set TMPDIR to a writable directory)",
        .dir.display()
    )]
    TempRom {
        dir: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// The ALE refused to give us an emulator or an action set.
    #[error("the Arcade Learning Environment failed: {0}")]
    Ale(String),
    /// A saved state is malformed or belongs to a differently configured environment.
    #[error("cannot restore environment state: {0}")]
    BadState(String),
}
