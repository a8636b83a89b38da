//! Measures the resident memory of a full replay memory.
//!
//! `cargo run --release --example replay_memory -- 20000` (or `1000000`): fills a `Replay` of that
//! many transitions with frames and prints the process's resident set size before and after.

use invaders::dqn::Replay;
use invaders::env::FRAME_LEN;

/// Cache-line-aligned buffers for the kernels (`invaders::CacheAligned`): the library leaves
/// the allocator to the program.
#[global_allocator]
static GLOBAL: invaders::CacheAligned = invaders::CacheAligned;

fn rss_mb() -> f64 {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    let kb: f64 = status
        .lines()
        .find(|l| l.starts_with("VmRSS:"))
        .and_then(|l| l.split_whitespace().nth(1))
        .and_then(|v| v.parse().ok())
        .unwrap_or(f64::NAN);
    kb / 1024.0
}

fn main() {
    let n: usize = std::env::args()
        .nth(1)
        .and_then(|a| a.parse().ok())
        .unwrap_or(20_000);
    let before = rss_mb();
    let mut replay = Replay::new(n, 4);
    let after_alloc = rss_mb();
    let mut frame = vec![0u8; FRAME_LEN];
    replay.push_start(&frame);
    for i in 0..n {
        frame.fill((i % 251) as u8 + 1);
        replay.push_step(i % 6, 1.0, i % 1000 == 999, &frame);
    }
    let full = rss_mb();
    println!(
        "replay of {n} transitions: RSS {before:.0} MB at start, {after_alloc:.0} MB after allocation, {full:.0} MB when full ({:.0} MB for the memory, {:.1} bytes per transition)",
        full - before,
        (full - before) * 1048576.0 / n as f64
    );
}
