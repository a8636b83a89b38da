//! `precision = "auto"`: the arithmetic a run trains in, chosen on the host it starts on.
//!
//! bf16 products are not faster everywhere: on AMD Zen 4 and 5 (AVX512-BF16) the train step
//! takes about 0.7 of its f32 time, on an Intel Xeon with AVX512-BF16 (without the AMX kernels
//! this program does not have) 2.2 times its f32 time. No rule per CPU family would stay true as
//! the kernels change, so `auto` measures: where bf16 runs at all ([`bf16_runs`]), it times
//! [`TIMED`] train steps of the run's own network and batch in each precision, alternating, on
//! the run's thread pool, and takes bf16 only if its median is at least [`BF16_MARGIN`] below
//! f32's (bf16 rounds the operands: when the two are close, f32 is the safer choice, and the
//! margin keeps noise from flipping the choice between runs). Where bf16 does not run, the
//! answer is f32 without a measurement. The resolved value is what the run records in its
//! `config.toml`, so a resumed run, its evaluation and a rerun from that file keep it.

use super::{Batch, Config, Learner};
use crate::ops::plan::{bf16_runs, Precision};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use std::time::Instant;

/// Train steps timed per precision (after [`WARMUP`] each).
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
    /// The medians measured, in milliseconds: `(f32, bf16)`; `None` where nothing was timed.
    pub times_ms: Option<(f64, f64)>,
    /// One sentence for the run's log.
    pub why: String,
}

/// The choice for measured medians (see the module): bf16 only when at least [`BF16_MARGIN`]
/// faster.
pub fn choose(f32_ms: f64, bf16_ms: f64) -> Precision {
    if bf16_ms <= (1.0 - BF16_MARGIN) * f32_ms {
        Precision::Bf16
    } else {
        Precision::F32
    }
}

/// Resolves `config.precision`: itself unless `auto`, else by measurement on the current thread
/// pool (see the module). Takes about `2·(TIMED + WARMUP)` train steps where bf16 runs.
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
            why: "precision auto: f32, as bf16 products do not run on this CPU".into(),
        };
    }
    let (f32_ms, bf16_ms) = time_both(config);
    let precision = choose(f32_ms, bf16_ms);
    Resolved {
        precision,
        times_ms: Some((f32_ms, bf16_ms)),
        why: format!(
            "precision auto: {} (train step {f32_ms:.2} ms in f32, {bf16_ms:.2} ms in bf16 on {} \
             thread(s); bf16 is taken when at least {:.0}% faster)",
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

/// The median train step of `config`'s network and batch in f32 and in bf16, timed alternately
/// on a random batch (the measurement's own generator: the run's streams are not touched).
fn time_both(config: &Config) -> (f64, f64) {
    let mut rng = ChaCha8Rng::seed_from_u64(0x7072_6563);
    let mut learner = Learner::from_config(config, 6, &mut rng);
    let batch = Batch::random(config, &mut rng);
    let mut times = [Vec::new(), Vec::new()];
    for round in 0..WARMUP + TIMED {
        for (k, p) in [Precision::F32, Precision::Bf16].into_iter().enumerate() {
            learner.set_precision(p);
            let t = Instant::now();
            learner.train_step(&batch);
            if round >= WARMUP {
                times[k].push(t.elapsed().as_secs_f64() * 1e3);
            }
        }
    }
    let median = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let [f, b] = times;
    (median(f), median(b))
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
