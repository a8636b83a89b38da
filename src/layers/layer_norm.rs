//! Layer normalisation (Ba, Kiros & Hinton 2016), with an optional fused ReLU and zero border.

use super::{Core, Layer, Param};
use crate::ops::lanes::{dot, sum};
use crate::ops::vectorized;
use crate::tensor::{Border, Float, Tensor};
use rayon::prelude::*;

/// Added to the variance: keeps `1/σ` finite for a sample whose features are all equal.
const EPS: f64 = 1e-5;

/// Normalises each sample's `F` features to mean 0 and variance 1, then scales and shifts
/// them feature by feature (PyTorch's `nn.LayerNorm(shape)`: the statistics over the whole
/// sample, an affine map per element):
///
/// ```text
/// x  [N, …]  F = the product of a sample's dimensions (`[H, W, C]` after a convolution)
/// μ  = (1/F)·Σ_i x_i            σ² = (1/F)·Σ_i (x_i − μ)²       r = 1/sqrt(σ² + ε)
/// x̂_i = (x_i − μ)·r             y_i = act(γ_i·x̂_i + β_i)        γ starts at 1, β at 0
/// ```
///
/// `act` is the identity or, [`LayerNorm::with_relu`], `max(·, 0)`; [`LayerNorm::with_border`]
/// writes the output of a `[H, W, C]` sample inside a zero border, as [`super::Conv2d`] does
/// for the convolution after it. Where a ReLU follows a layer, normalising its pre-activations
/// keeps their scale fixed however the weights below grow. Lyle et al. (2023) find that it keeps
/// a network trainable as its targets keep changing (plasticity); PQN (Gallici et al. 2024)
/// relies on it for stable TD learning (CleanRL's PQN normalises as this layer does).
///
/// Backward, with `dz_i = dY_i·[y_i > 0]` (the interior of `dY`; no mask without a ReLU):
/// ```text
/// dγ_i += Σ_samples dz_i·x̂_i        dβ_i += Σ_samples dz_i
/// g_i = dz_i·γ_i                    dX_i = r·(g_i − mean(g) − x̂_i·mean(g ⊙ x̂))
/// ```
/// The last line is the derivative through `μ` and `r`: `∂x̂_i/∂x_j = r·(δ_ij − 1/F − x̂_i·x̂_j/F)`.
pub struct LayerNorm<T> {
    /// The name, output `y` and input gradient `dX` ([`Core`]).
    core: Core<T>,
    /// One sample's shape (batch excluded), unbordered.
    shape: Vec<usize>,
    /// `[gain γ, bias β]`, each of one sample's shape.
    params: [Param<T>; 2],
    relu: bool,
    border: Border,
    /// The sample's elements as contiguous runs `(start unbordered, start in the output,
    /// length)`: all `F` at once without a border, else one run per image row inside it. Set
    /// with the border, so no pass allocates it.
    runs: Vec<(usize, usize, usize)>,
    /// `x̂` of the last forward pass, `[N, F]`, unbordered.
    xhat: Vec<T>,
    /// `r = 1/sqrt(σ² + ε)` of each sample of the last forward pass.
    rstd: Vec<T>,
    /// `dz`, then `g = dz ⊙ γ`, of the last backward pass, `[N, F]`.
    dz: Vec<T>,
}

impl<T: Float> LayerNorm<T> {
    /// A layer normalisation of samples of the given shape; gain 1, bias 0.
    pub fn new(name: &str, shape: &[usize]) -> Self {
        let mut gain = Param::zeros(format!("{name}.gain"), shape);
        gain.value.data_mut().fill(T::one());
        LayerNorm {
            core: Core::new(name),
            shape: shape.to_vec(),
            params: [gain, Param::zeros(format!("{name}.bias"), shape)],
            relu: false,
            border: Border::default(),
            runs: vec![(0, 0, shape.iter().product())],
            xhat: Vec::new(),
            rstd: Vec::new(),
            dz: Vec::new(),
        }
    }

    /// Applies a ReLU to the output as it is stored.
    pub fn with_relu(mut self) -> Self {
        self.relu = true;
        self
    }

    /// Writes each `[H, W, C]` output inside a zero border (the next convolution's padding).
    pub fn with_border(mut self, border: Border) -> Self {
        assert!(
            border.is_none() || self.shape.len() == 3,
            "{}: a border needs [H, W, C] samples",
            self.core.name
        );
        self.border = border;
        self.runs = if border.is_none() {
            vec![(0, 0, self.features())]
        } else {
            let (h, w, c) = (self.shape[0], self.shape[1], self.shape[2]);
            let (_, wb) = border.around(h, w);
            (0..h)
                .map(|y| (y * w * c, ((border.top + y) * wb + border.left) * c, w * c))
                .collect()
        };
        self
    }

    /// Features per sample, `F`.
    fn features(&self) -> usize {
        self.shape.iter().product()
    }
}

impl<T: Float> Layer<T> for LayerNorm<T> {
    fn core(&self) -> &Core<T> {
        &self.core
    }

    fn output_shape(&self) -> Vec<usize> {
        if self.border.is_none() {
            return self.shape.clone();
        }
        let (h, w, c) = (self.shape[0], self.shape[1], self.shape[2]);
        let (hb, wb) = self.border.around(h, w);
        vec![hb, wb, c]
    }

    /// `y = act(γ ⊙ x̂ + β)`, sample by sample (its sums in [`crate::ops::lanes`]: the same
    /// bits at any thread count); keeps `x̂` and `r` for backward.
    fn forward(&mut self, x: &Tensor<T>) {
        let f = self.features();
        let n = x.len() / f;
        assert_eq!(
            x.len(),
            n * f,
            "{}: input is not [N, {:?}]",
            self.core.name,
            self.shape
        );
        let out = self.output_shape();
        let per_out: usize = out.iter().product();
        let mut shape = vec![n];
        shape.extend_from_slice(&out);
        self.core.y.set_shape(&shape);
        self.xhat.resize(n * f, T::zero());
        self.rstd.resize(n, T::zero());
        let (relu, runs) = (self.relu, &self.runs);
        if !self.border.is_none() {
            let (h, w, c) = (self.shape[0], self.shape[1], self.shape[2]);
            self.border.zero(self.core.y.data_mut(), n, h, w, c);
        }
        let [gain, bias] = &self.params;
        let (gain, bias) = (gain.value.data(), bias.value.data());
        let inv_f = T::of(1.0 / f as f64);
        let eps = T::of(EPS);
        self.core.y.data_mut()[..n * per_out]
            .par_chunks_mut(per_out)
            .zip(x.data().par_chunks(f))
            .zip(self.xhat.par_chunks_mut(f).zip(self.rstd.par_iter_mut()))
            .for_each(|((y, x), (xhat, rstd))| {
                vectorized(|| {
                    let mean = sum(x) * inv_f;
                    for (h, &x) in xhat.iter_mut().zip(x) {
                        *h = x - mean;
                    }
                    let r = T::one() / (dot(xhat, xhat) * inv_f + eps).sqrt();
                    *rstd = r;
                    for h in xhat.iter_mut() {
                        *h *= r;
                    }
                    for &(i, o, len) in runs {
                        let y = &mut y[o..o + len];
                        let (h, g, b) = (&xhat[i..i + len], &gain[i..i + len], &bias[i..i + len]);
                        for (((y, &h), &g), &b) in y.iter_mut().zip(h).zip(g).zip(b) {
                            let z = g * h + b;
                            *y = if relu && z <= T::zero() { T::zero() } else { z };
                        }
                    }
                })
            });
    }

    fn backward(&mut self, _x: &Tensor<T>, dy: &Tensor<T>, need_dx: bool) {
        let f = self.features();
        let n = self.rstd.len();
        let per_out: usize = self.output_shape().iter().product();
        assert_eq!(
            dy.len(),
            n * per_out,
            "{}: upstream gradient",
            self.core.name
        );
        let (relu, runs) = (self.relu, &self.runs);
        // dz = the interior of dY, times [y > 0] with a ReLU.
        self.dz.resize(n * f, T::zero());
        self.dz
            .par_chunks_mut(f)
            .zip(dy.data().par_chunks(per_out))
            .zip(self.core.y.data().par_chunks(per_out))
            .for_each(|((dz, dy), y)| {
                vectorized(|| {
                    for &(i, o, len) in runs {
                        let (dz, dy, y) = (&mut dz[i..i + len], &dy[o..o + len], &y[o..o + len]);
                        for ((dz, &d), &y) in dz.iter_mut().zip(dy).zip(y) {
                            *dz = if relu && y <= T::zero() { T::zero() } else { d };
                        }
                    }
                })
            });
        // dγ += Σ_samples dz ⊙ x̂, dβ += Σ_samples dz: per feature, samples in order.
        const CHUNK: usize = 1 << 12;
        let [gain, bias] = &mut self.params;
        let (dz, xhat) = (&self.dz, &self.xhat);
        gain.grad
            .data_mut()
            .par_chunks_mut(CHUNK)
            .zip(bias.grad.data_mut().par_chunks_mut(CHUNK))
            .enumerate()
            .for_each(|(k, (dg, db))| {
                let at = k * CHUNK;
                vectorized(|| {
                    for s in 0..n {
                        let (dz, xh) = (&dz[s * f + at..], &xhat[s * f + at..]);
                        for (((dg, db), &d), &h) in dg.iter_mut().zip(db.iter_mut()).zip(dz).zip(xh)
                        {
                            *dg += d * h;
                            *db += d;
                        }
                    }
                })
            });
        if !need_dx {
            return;
        }
        // dX = r·(g − mean(g) − x̂·mean(g ⊙ x̂)), g = dz ⊙ γ.
        self.core
            .dx
            .set_shape(&[&[n][..], &self.shape[..]].concat());
        let gain = gain.value.data();
        let inv_f = T::of(1.0 / f as f64);
        self.core.dx.data_mut()[..n * f]
            .par_chunks_mut(f)
            .zip(self.dz.par_chunks_mut(f))
            .zip(self.xhat.par_chunks(f).zip(self.rstd.par_iter()))
            .for_each(|((dx, g), (xhat, &r))| {
                vectorized(|| {
                    for (g, &gamma) in g.iter_mut().zip(gain) {
                        *g *= gamma;
                    }
                    let mean_g = sum(g) * inv_f;
                    let mean_gx = dot(g, xhat) * inv_f;
                    for ((dx, &g), &h) in dx.iter_mut().zip(g.iter()).zip(xhat) {
                        *dx = r * (g - mean_g - h * mean_gx);
                    }
                })
            });
    }

    fn visit_params<'a>(&'a self, f: &mut dyn FnMut(&'a Param<T>)) {
        self.params.iter().for_each(f);
    }

    fn visit_params_mut<'a>(&'a mut self, f: &mut dyn FnMut(&'a mut Param<T>)) {
        self.params.iter_mut().for_each(f);
    }
}
