//! A bounded mutation fuzzer for the two parsers that read outside data, for machines without
//! `cargo fuzz` (which needs nightly and libFuzzer; the same entry points are the targets in
//! `fuzz/fuzz_targets/`):
//!
//! ```sh
//! cargo run --release --example fuzz_loop -- 300      # seconds (default 60)
//! ```
//!
//! It makes a real checkpoint (one short Space Invaders episode with learning), then for the given
//! time mutates it (byte flips mostly in the JSON header, truncations, insertions, splices of
//! header text, length-field edits) into `checkpoint::from_bytes`, and mutates a real config
//! (character edits, values swapped for edge cases, keys dropped or duplicated) into
//! `Config::resolve`. Every panic is caught, its input written to `fuzz-crash-N`, and the run
//! exits non-zero. It prints how many inputs each parser saw, accepted and refused.

use std::panic::{catch_unwind, AssertUnwindSafe};
use std::time::{Duration, Instant};

use invaders::dqn::checkpoint;
use invaders::dqn::{Agent, Config, Preset};
use invaders::env::SpaceInvaders;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Cache-line-aligned buffers for the kernels (`invaders::CacheAligned`): the library leaves
/// the allocator to the program.
#[global_allocator]
static GLOBAL: invaders::CacheAligned = invaders::CacheAligned;

fn seed_checkpoint() -> Vec<u8> {
    let mut c = Config::preset(Preset::Article);
    c.learning_starts = 20;
    c.replay_capacity = 100;
    c.batch_size = 4;
    c.env.max_episode_steps = Some(40);
    let env = SpaceInvaders::new(&c.env, 0).expect("the emulator starts");
    let mut agent = Agent::new(c, env);
    agent.play_episode().expect("a finite episode");
    checkpoint::to_bytes(
        &agent.config,
        &agent.counters,
        &agent.learner,
        &agent.state(),
        None,
    )
    .expect("serialises")
}

const EDGE: &[&str] = &[
    "0",
    "-1",
    "1",
    "1e309",
    "-1e309",
    "nan",
    "inf",
    "-inf",
    "18446744073709551615",
    "18446744073709551616",
    "-9223372036854775809",
    "0.5",
    "\"\"",
    "\"x\"",
    "[]",
    "{}",
    "true",
    "1e-320",
    "4294967296",
    "\"article-vanilla\"",
    "\"stack\"",
    "\"v4\"",
];

fn mutate_bytes(rng: &mut ChaCha8Rng, seed: &[u8]) -> Vec<u8> {
    let mut b = seed.to_vec();
    let header = 8 + u64::from_le_bytes(b[..8].try_into().unwrap()) as usize;
    let n = rng.random_range(1..=4);
    for _ in 0..n {
        match rng.random_range(0..10) {
            0..=4 => {
                let at = rng.random_range(0..header.min(b.len()).max(1));
                if at < b.len() {
                    b[at] ^= 1 << rng.random_range(0..8);
                }
            }
            5 => {
                let at = rng.random_range(0..=b.len());
                b.truncate(at);
            }
            6 => {
                let at = rng.random_range(8..header.min(b.len()).max(9));
                let len = rng.random_range(1..16);
                let junk: Vec<u8> = (0..len).map(|_| rng.random()).collect();
                b.splice(at.min(b.len())..at.min(b.len()), junk);
            }
            7 => {
                // Splice a piece of the header text over another.
                if header <= b.len() && header > 40 {
                    let from = rng.random_range(8..header - 20);
                    let to = rng.random_range(8..header - 20);
                    let len = rng.random_range(1..20);
                    let piece = b[from..from + len].to_vec();
                    b[to..to + len].copy_from_slice(&piece);
                }
            }
            8 => {
                let len: u64 = match rng.random_range(0..3) {
                    0 => rng.random(),
                    1 => rng.random_range(0..b.len() as u64 + 10),
                    _ => (header as u64 - 8)
                        .wrapping_add(rng.random_range(0..8))
                        .wrapping_sub(4),
                };
                if b.len() >= 8 {
                    b[..8].copy_from_slice(&len.to_le_bytes());
                }
            }
            _ => {
                let at = rng.random_range(0..b.len().max(1));
                if at < b.len() {
                    b[at] = rng.random();
                }
            }
        }
    }
    b
}

fn mutate_text(rng: &mut ChaCha8Rng, seed: &str) -> String {
    let mut lines: Vec<String> = seed.lines().map(str::to_string).collect();
    for _ in 0..rng.random_range(1..=3) {
        if lines.is_empty() {
            break;
        }
        let i = rng.random_range(0..lines.len());
        match rng.random_range(0..5) {
            0 => {
                if let Some((k, _)) = lines[i].split_once(" = ") {
                    lines[i] = format!("{k} = {}", EDGE[rng.random_range(0..EDGE.len())]);
                }
            }
            1 => {
                lines.remove(i);
            }
            2 => {
                let l = lines[i].clone();
                lines.insert(rng.random_range(0..lines.len()), l);
            }
            3 => {
                let mut bytes = lines[i].clone().into_bytes();
                if !bytes.is_empty() {
                    let at = rng.random_range(0..bytes.len());
                    bytes[at] = rng.random_range(0x20..0x7f);
                }
                lines[i] = String::from_utf8_lossy(&bytes).into_owned();
            }
            _ => {
                let c = char::from_u32(rng.random_range(0..0x3000)).unwrap_or('?');
                let at = rng.random_range(0..=lines[i].len());
                if lines[i].is_char_boundary(at) {
                    lines[i].insert(at, c);
                }
            }
        }
    }
    lines.join("\n")
}

#[derive(Default)]
struct Tally {
    runs: u64,
    ok: u64,
    err: u64,
}

fn main() {
    let secs: u64 = std::env::args()
        .nth(1)
        .map(|s| s.parse().expect("seconds"))
        .unwrap_or(60);
    let mut rng = ChaCha8Rng::seed_from_u64(
        std::env::args()
            .nth(2)
            .map(|s| s.parse().expect("seed"))
            .unwrap_or(1),
    );
    std::panic::set_hook(Box::new(|_| {}));
    let ckpt = seed_checkpoint();
    let mut config_seeds: Vec<String> = [
        Preset::Article,
        Preset::ArticleVanilla,
        Preset::ArticleAsWritten,
    ]
    .iter()
    .map(|&p| Config::preset(p).to_toml())
    .collect();
    config_seeds.push("preset = \"article-vanilla\"\nseed = 3\n[env]\nmode = \"v4\"\n".into());
    let (mut c_tally, mut t_tally) = (Tally::default(), Tally::default());
    let mut crashes = 0;
    let start = Instant::now();
    let budget = Duration::from_secs(secs);
    while start.elapsed() < budget {
        let input = mutate_bytes(&mut rng, &ckpt);
        c_tally.runs += 1;
        match catch_unwind(AssertUnwindSafe(|| checkpoint::from_bytes(&input).is_ok())) {
            Ok(true) => c_tally.ok += 1,
            Ok(false) => c_tally.err += 1,
            Err(_) => {
                crashes += 1;
                std::fs::write(format!("fuzz-crash-{crashes}.safetensors"), &input).unwrap();
            }
        }
        for _ in 0..20 {
            let seed = &config_seeds[rng.random_range(0..config_seeds.len())];
            let text = mutate_text(&mut rng, seed);
            t_tally.runs += 1;
            let r = catch_unwind(AssertUnwindSafe(|| {
                Config::resolve(None, Some(&text)).map(|c| {
                    let again = Config::resolve(None, Some(&c.to_toml())).expect("resolves again");
                    assert_eq!(again, c, "round trip");
                })
            }));
            match r {
                Ok(Ok(())) => t_tally.ok += 1,
                Ok(Err(_)) => t_tally.err += 1,
                Err(_) => {
                    crashes += 1;
                    std::fs::write(format!("fuzz-crash-{crashes}.toml"), &text).unwrap();
                }
            }
        }
    }
    println!(
        "{:.0} s: checkpoint::from_bytes {} inputs ({} loaded, {} refused); Config::resolve {} inputs ({} valid, {} refused); {crashes} panics",
        start.elapsed().as_secs_f64(),
        c_tally.runs,
        c_tally.ok,
        c_tally.err,
        t_tally.runs,
        t_tally.ok,
        t_tally.err
    );
    if crashes > 0 {
        std::process::exit(1);
    }
}
