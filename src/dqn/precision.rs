//! `precision = "auto"`: the arithmetic a run trains in, chosen on the host it starts on.
//!
//! bf16 products are not faster everywhere: on AMD Zen 4 and 5 (AVX512-BF16) the train step
//! takes about 0.7 of its f32 time; on an Intel Xeon with AMX it took 2.2 times its f32 time on
//! `vdpbf16ps` and 0.7–0.75 once the bf16 products ran on the tiles (docs/performance-history.md,
//! series G and H). No rule per CPU family would stay true as the kernels change, so `auto`
//! measures: where bf16 runs at all ([`bf16_runs`]), it times [`TIMED`] train steps of the run's
//! own network and batch in each precision, alternating, on the run's thread pool, and takes
//! bf16 only if its fastest step is at least [`BF16_MARGIN`] below f32's (bf16 rounds the
//! operands: when the two are close, f32 is the safer choice, and the margin keeps noise from
//! flipping the choice between runs). The fastest step, not the median: a neighbour on the host
//! only ever lengthens a step, and a burst of it over half of one precision's steps moved the
//! median enough to pick f32 on an AMD Zen 4 where bf16 is 25% faster (1 call in 12, 2 threads;
//! docs/performance-history.md, series I). Where the first [`TIMED`] pairs leave the two within
//! [`BF16_MARGIN`] of each other, [`TIMED`] more are timed and pooled. Where bf16 does not run,
//! the answer is f32 without a measurement. The resolved value is what the run records in its
//! `config.toml`, so a resumed run, its evaluation and a rerun from that file keep it.

use super::{Batch, Config, Learner};
use crate::ops::plan::{bf16_runs, Precision};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use std::time::Instant;

/// Train steps timed per precision in one block (after [`WARMUP`] each); a second block where
/// the first is not clear.
pub const TIMED: usize = 7;

/// Untimed train steps per precision first (buffers, caches).
pub const WARMUP: usize = 2;

/// bf16 is taken only if its train step is at least this share faster than f32's.
pub const BF16_MARGIN: f64 = 0.10;

/// What `auto` resolved to, and why.
#[derive(Clone, Debug, PartialEq)]
pub struct Resolved {
    /// f32 or bf16.
    pub precision: Precision,
    /// The fastest train steps measured, in milliseconds: `(f32, bf16)`; `None` where nothing was
    /// timed.
    pub times_ms: Option<(f64, f64)>,
    /// One sentence for the run's log.
    pub why: String,
}

/// The choice for measured step times (see the module): bf16 only when at least
/// [`BF16_MARGIN`] faster.
pub fn choose(f32_ms: f64, bf16_ms: f64) -> Precision {
    if bf16_ms <= (1.0 - BF16_MARGIN) * f32_ms {
        Precision::Bf16
    } else {
        Precision::F32
    }
}

/// Resolves `config.precision`: itself unless `auto`, else by measurement on the current thread
/// pool (see the module). Takes `2·(TIMED + WARMUP)` train steps where bf16 runs, `2·TIMED`
/// more where those leave it unclear.
pub fn resolve_precision(config: &Config) -> Resolved {
    if config.precision != Precision::Auto {
        return Resolved {
            precision: config.precision,
            times_ms: None,
            why: format!("precision {:?} as configured", config.precision),
        };
    }
    if !bf16_runs(Precision::Bf16) {
        return Resolved {
            precision: Precision::F32,
            times_ms: None,
            why: format!(
                "precision auto: f32, as bf16 products do not run here ({})",
                crate::tensor::cpu::why_no_bf16().unwrap_or_default()
            ),
        };
    }
    let (f32_ms, bf16_ms) = time_both(config);
    let precision = choose(f32_ms, bf16_ms);
    Resolved {
        precision,
        times_ms: Some((f32_ms, bf16_ms)),
        why: format!(
            "precision auto: {} (fastest train step {f32_ms:.2} ms in f32, {bf16_ms:.2} ms in \
             bf16 on {} thread(s); bf16 is taken when at least {:.0}% faster)",
            if precision == Precision::Bf16 {
                "bf16"
            } else {
                "f32"
            },
            rayon::current_num_threads(),
            100.0 * BF16_MARGIN
        ),
    }
}

/// The fastest train step of `config`'s network and batch in f32 and in bf16, timed alternately
/// on a random batch (the measurement's own generator: the run's streams are not touched): one
/// block of [`TIMED`] pairs, a second where the first leaves the two within [`BF16_MARGIN`].
fn time_both(config: &Config) -> (f64, f64) {
    let mut rng = ChaCha8Rng::seed_from_u64(0x7072_6563);
    let mut learner = Learner::from_config(config, 6, &mut rng);
    let batch = Batch::random(config, &mut rng);
    let mut fastest = [f64::INFINITY; 2];
    // One step in each precision, f32 first; their times kept when `timed`.
    let mut pair = |fastest: &mut [f64; 2], timed: bool| {
        for (k, p) in [Precision::F32, Precision::Bf16].into_iter().enumerate() {
            learner.set_precision(p);
            let t = Instant::now();
            learner.train_step(&batch);
            if timed {
                fastest[k] = fastest[k].min(t.elapsed().as_secs_f64() * 1e3);
            }
        }
    };
    for round in 0..WARMUP + TIMED {
        pair(&mut fastest, round >= WARMUP);
    }
    if !clear(fastest[0], fastest[1]) {
        for _ in 0..TIMED {
            pair(&mut fastest, true);
        }
    }
    (fastest[0], fastest[1])
}

/// Whether step times `f32_ms` and `bf16_ms` decide without a second block: either precision at
/// least [`BF16_MARGIN`] faster than the other.
fn clear(f32_ms: f64, bf16_ms: f64) -> bool {
    choose(f32_ms, bf16_ms) == Precision::Bf16 || f32_ms <= (1.0 - BF16_MARGIN) * bf16_ms
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::dqn::Preset;

    /// bf16 only when clearly faster: the Xeon's 63 ms against 29 ms in f32 picks f32, Zen 5's
    /// 12.7 against 17.2 bf16, a near tie f32.
    #[test]
    fn auto_takes_bf16_only_when_clearly_faster() {
        assert_eq!(choose(28.7, 63.3), Precision::F32);
        assert_eq!(choose(17.2, 12.7), Precision::Bf16);
        assert_eq!(choose(10.0, 9.5), Precision::F32);
        assert_eq!(choose(10.0, 9.0), Precision::Bf16);
    }

    /// A second block is timed only inside the margin: Zen 4's 19.3 ms in f32 against 19.5 in
    /// bf16 (the misjudged call, medians) is not clear, nor is 10 against 9.5; either precision
    /// 10% faster is.
    #[test]
    fn a_second_block_only_where_unclear() {
        assert!(!clear(19.3, 19.5));
        assert!(!clear(10.0, 9.5));
        assert!(clear(10.0, 9.0));
        assert!(clear(9.0, 10.0));
        assert!(clear(28.7, 63.3));
    }

    /// `auto` resolves to f32 or bf16, never stays `auto`; a fixed precision stays as it is; on a
    /// CPU without bf16 products it is f32 without a measurement.
    #[test]
    fn auto_resolves_to_a_precision_that_runs() {
        let mut c = Config::preset(Preset::Strong);
        c.batch_size = 4;
        c.precision = Precision::Auto;
        let r = resolve_precision(&c);
        assert_ne!(r.precision, Precision::Auto);
        if bf16_runs(Precision::Bf16) {
            let (f, b) = r.times_ms.expect("measured");
            assert_eq!(r.precision, choose(f, b), "{}", r.why);
        } else {
            assert_eq!((r.precision, r.times_ms), (Precision::F32, None));
        }
        c.precision = Precision::Bf16;
        assert_eq!(resolve_precision(&c).precision, Precision::Bf16);
    }
}
