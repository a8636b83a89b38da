//! Weight initialisers with TensorFlow's exact semantics.
//!
//! `VarianceScaling(scale, mode, distribution)` draws weights with variance `scale / fan`, where
//! `fan` is the layer's fan-in, fan-out or their mean. For a convolution filter `[KH, KW, Cin, Cout]`
//! the receptive field `KH·KW` multiplies both: `fan_in = KH·KW·Cin`, `fan_out = KH·KW·Cout`; for a
//! dense `[In, Out]`, `fan_in = In`, `fan_out = Out`. The article uses `scale = 2.0`, `fan_in`,
//! truncated normal: He initialisation, which keeps the variance of ReLU activations constant
//! from layer to layer.

use crate::tensor::{Float, Tensor};
use rand::Rng;
use rand_distr::{Distribution as _, StandardNormal};
use serde::{Deserialize, Serialize};

/// Which fan divides the scale.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FanMode {
    /// Number of inputs to one output unit.
    FanIn,
    /// Number of outputs one input unit feeds.
    FanOut,
    /// `(fan_in + fan_out) / 2`.
    FanAvg,
}

/// The distribution the weights are drawn from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Distribution {
    /// Normal, redrawn outside two standard deviations. Truncation shrinks the variance by the
    /// factor `0.87962566103423978²` (the standard deviation of a unit normal truncated to
    /// `[−2, 2]`), so TensorFlow divides the standard deviation by that constant first.
    TruncatedNormal,
    /// Plain normal with standard deviation `sqrt(scale / fan)`.
    UntruncatedNormal,
    /// Uniform on `[−limit, limit]` with `limit = sqrt(3·scale / fan)` (variance `limit² / 3`).
    Uniform,
}

/// Standard deviation of a unit normal truncated to `[−2, 2]`.
pub const TRUNCATED_NORMAL_STDDEV: f64 = 0.879_625_661_034_239_8;

/// `tf.keras.initializers.VarianceScaling`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct VarianceScaling {
    /// Target variance times the fan.
    pub scale: f64,
    /// Which fan.
    pub mode: FanMode,
    /// Which distribution.
    pub distribution: Distribution,
}

impl VarianceScaling {
    /// The article's initialiser (He normal): scale 2, fan-in, truncated normal.
    pub const HE: VarianceScaling = VarianceScaling {
        scale: 2.0,
        mode: FanMode::FanIn,
        distribution: Distribution::TruncatedNormal,
    };

    /// `(fan_in, fan_out)` of a weight shape by TensorFlow's rule: the last two dimensions are
    /// (inputs, outputs) and any leading ones form the receptive field.
    pub fn fans(shape: &[usize]) -> (f64, f64) {
        match shape {
            [] => (1.0, 1.0),
            [n] => (*n as f64, *n as f64),
            _ => {
                let rf: usize = shape[..shape.len() - 2].iter().product();
                let (i, o) = (shape[shape.len() - 2], shape[shape.len() - 1]);
                ((i * rf) as f64, (o * rf) as f64)
            }
        }
    }

    /// The variance the drawn weights have: `scale / max(1, fan)`.
    pub fn variance(&self, shape: &[usize]) -> f64 {
        let (fi, fo) = Self::fans(shape);
        let fan = match self.mode {
            FanMode::FanIn => fi,
            FanMode::FanOut => fo,
            FanMode::FanAvg => (fi + fo) / 2.0,
        };
        self.scale / fan.max(1.0)
    }

    /// Fills `t` (whose shape decides the fans) with fresh draws.
    pub fn fill<T: Float>(&self, t: &mut Tensor<T>, rng: &mut impl Rng) {
        let var = self.variance(t.shape());
        match self.distribution {
            Distribution::TruncatedNormal => {
                let sd = var.sqrt() / TRUNCATED_NORMAL_STDDEV;
                for v in t.data_mut() {
                    *v = T::of(sd * truncated_unit_normal(rng));
                }
            }
            Distribution::UntruncatedNormal => {
                let sd = var.sqrt();
                for v in t.data_mut() {
                    let z: f64 = StandardNormal.sample(rng);
                    *v = T::of(sd * z);
                }
            }
            Distribution::Uniform => {
                let limit = (3.0 * var).sqrt();
                for v in t.data_mut() {
                    *v = T::of(rng.random_range(-limit..limit));
                }
            }
        }
    }
}

/// A unit normal draw, redrawn until it lies within `[−2, 2]` (as `tf.random.truncated_normal`).
fn truncated_unit_normal(rng: &mut impl Rng) -> f64 {
    loop {
        let z: f64 = StandardNormal.sample(rng);
        if z.abs() <= 2.0 {
            return z;
        }
    }
}

/// A generator seeded by a layer's name (its FNV-1a hash): where a layer draws its weights when
/// no generator is given ([`crate::layers::Dense::new`], [`crate::layers::Conv2d::new`]), so a
/// network built twice starts the same, and two layers of one network start differently.
pub fn named_rng(name: &str) -> rand_chacha::ChaCha8Rng {
    use rand::SeedableRng;
    let hash = name.bytes().fold(0xCBF2_9CE4_8422_2325_u64, |h, b| {
        (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01B3)
    });
    rand_chacha::ChaCha8Rng::seed_from_u64(hash)
}
