//! The cosine embedding of quantile fractions that implicit quantile networks (IQN, Dabney et
//! al. 2018) multiply into a state's features.

use super::{Core, Layer, Param};
use crate::ops::{gemm, Op};
use crate::tensor::{Float, Tensor};
use rayon::prelude::*;

/// Evaluates a state's features at `N` quantile fractions `τ ∈ (0, 1)` each: for every sample
/// `b` of the input `x` (`[B, F]`) and each of its fractions `τ_bi` (set by
/// [`Layer::set_fractions`], `B·N` of them, sample by sample), one output row
///
/// ```text
/// c_j(τ)   = cos(π j τ),                 j = 1..E       (the embedding, E = `dim`)
/// φ(τ)_f   = max(0, Σ_j c_j(τ) W_jf + b_f),  f = 1..F  (a dense layer and a ReLU)
/// y_(bi)f  = x_bf · φ(τ_bi)_f                          (the features, gated per fraction)
/// ```
///
/// so `y` is `[B·N, F]`, row `b·N + i`: the layers after it (dense, dueling) see `B·N` samples
/// and give each fraction's value `Z_τ(s, a)`. Dopamine's IQN uses `E = 64` and `j = 1..E`, and
/// puts the layer after the convolutions (`F = 3136` there); the network builder here may put it
/// after the first dense layer instead, where `F` is that layer's width and it costs far less
/// ([`crate::dqn::Head`]).
///
/// Backward, with `p = Σ_j c_j W_jf + b_f` (so `φ = max(0, p)`):
///
/// ```text
/// dX_bf = Σ_i dY_(bi)f · φ(τ_bi)_f            (x_b is used by each of its N rows)
/// dP_(bi)f = dY_(bi)f · x_bf · [p > 0]
/// dW_jf = Σ_(bi) c_j(τ_bi) · dP_(bi)f,   db_f = Σ_(bi) dP_(bi)f
/// ```
///
/// No gradient flows to `τ` (the fractions are sampled, not learned).
pub struct QuantileEmbedding<T> {
    /// The name, output `y` and input gradient `dX` ([`Core`]).
    core: Core<T>,
    /// `E`, cosines per fraction.
    dim: usize,
    /// `F`, the feature width.
    width: usize,
    /// `W: [E, F]` and `b: [F]`.
    params: Vec<Param<T>>,
    /// The fractions of the next passes, `B·N` of them.
    taus: Vec<f64>,
    /// `[B·N, E]`: the cosines of the last forward pass.
    cos: Vec<T>,
    /// `[B·N, F]`: `φ` of the last forward pass (the ReLU's output; its mask is `φ > 0`).
    phi: Vec<T>,
    /// `[B·N, F]`: `dP` of the last backward pass.
    dp: Vec<T>,
}

impl<T: Float> QuantileEmbedding<T> {
    /// An embedding of `dim` cosines into `width` features, weights and biases zero (the caller
    /// initialises the weight).
    pub fn new(name: &str, dim: usize, width: usize) -> Self {
        assert!(dim > 0 && width > 0, "QuantileEmbedding: empty");
        QuantileEmbedding {
            core: Core::new(name),
            dim,
            width,
            params: vec![
                Param::zeros(format!("{name}.weight"), &[dim, width]),
                Param::zeros(format!("{name}.bias"), &[width]),
            ],
            taus: Vec::new(),
            cos: Vec::new(),
            phi: Vec::new(),
            dp: Vec::new(),
        }
    }

    /// Fractions per sample: `B·N` fractions over a batch of `B`.
    fn per_sample(&self, batch: usize) -> usize {
        let n = self.taus.len() / batch.max(1);
        assert!(
            batch > 0 && n > 0 && n * batch == self.taus.len(),
            "{}: {} fractions set for a batch of {batch}",
            self.core.name,
            self.taus.len()
        );
        n
    }
}

/// `c_j = cos(π j τ)` for `j = 1..=c.len()`, by the recurrence
/// `cos(jθ) = 2 cos θ · cos((j − 1)θ) − cos((j − 2)θ)` in f64 (one cosine per fraction instead of
/// `E`; the recurrence's rounding stays below 1e-13 for the embeddings allowed).
fn cosines<T: Float>(tau: f64, c: &mut [T]) {
    let c1 = (std::f64::consts::PI * tau).cos();
    let (mut prev, mut cur) = (1.0f64, c1);
    for c in c.iter_mut() {
        *c = T::of(cur);
        (prev, cur) = (cur, 2.0 * c1 * cur - prev);
    }
}

impl<T: Float> Layer<T> for QuantileEmbedding<T> {
    fn core(&self) -> &Core<T> {
        &self.core
    }

    fn output_shape(&self) -> Vec<usize> {
        vec![self.width]
    }

    fn set_fractions(&mut self, taus: &[f64]) {
        self.taus.clear();
        self.taus.extend_from_slice(taus);
    }

    /// `y_(bi)f = x_bf · max(0, Σ_j cos(π j τ_bi) W_jf + b_f)`: the cosines, one GEMM
    /// `[B·N, E]·[E, F]`, then the bias, the ReLU and the product, sample by sample.
    fn forward(&mut self, x: &Tensor<T>) {
        let (e, f) = (self.dim, self.width);
        let b = x.len() / f;
        assert_eq!(b * f, x.len(), "{}: input is not [B, {f}]", self.core.name);
        let n = self.per_sample(b);
        let rows = b * n;
        self.cos.resize(rows * e, T::zero());
        self.phi.resize(rows * f, T::zero());
        self.core.y.set_shape(&[rows, f]);
        for (c, &tau) in self.cos.chunks_exact_mut(e).zip(&self.taus) {
            cosines(tau, c);
        }
        let (w, bias) = (self.params[0].value.data(), self.params[1].value.data());
        gemm(
            Op::N,
            Op::N,
            rows,
            f,
            e,
            T::one(),
            &self.cos,
            w,
            T::zero(),
            &mut self.phi,
        );
        self.phi
            .par_chunks_mut(n * f)
            .zip(self.core.y.data_mut().par_chunks_mut(n * f))
            .zip(x.data().par_chunks(f))
            .for_each(|((phi, y), xs)| {
                for (phi, y) in phi.chunks_exact_mut(f).zip(y.chunks_exact_mut(f)) {
                    for (((p, y), &xv), &bv) in phi.iter_mut().zip(y).zip(xs).zip(bias) {
                        let v = *p + bv;
                        *p = if v > T::zero() { v } else { T::zero() };
                        *y = xv * *p;
                    }
                }
            });
    }

    /// `dX_b = Σ_i dY_(bi) ⊙ φ_(bi)` and `dP = dY ⊙ x_b ⊙ [φ > 0]`, sample by sample; then
    /// `dW += Cᵀ·dP` (one GEMM `[E, B·N]·[B·N, F]`) and `db += Σ_rows dP`.
    fn backward(&mut self, x: &Tensor<T>, dy: &Tensor<T>, need_dx: bool) {
        let (e, f) = (self.dim, self.width);
        let b = x.len() / f;
        let n = self.per_sample(b);
        let rows = b * n;
        assert_eq!(
            dy.len(),
            rows * f,
            "{}: dY is not [B·N, {f}]",
            self.core.name
        );
        if need_dx {
            self.core.dx.set_shape(x.shape());
        } else {
            self.core.dx.set_shape(&[0]);
        }
        self.dp.resize(rows * f, T::zero());
        let dx_chunks: Vec<&mut [T]> = if need_dx {
            self.core.dx.data_mut().chunks_exact_mut(f).collect()
        } else {
            Vec::new()
        };
        let phi = &self.phi;
        self.dp
            .par_chunks_mut(n * f)
            .enumerate()
            .zip(dy.data().par_chunks(n * f))
            .for_each(|((s, dp), dys)| {
                let xs = &x.data()[s * f..(s + 1) * f];
                let phis = &phi[s * n * f..(s + 1) * n * f];
                for ((dp, dyr), pr) in dp
                    .chunks_exact_mut(f)
                    .zip(dys.chunks_exact(f))
                    .zip(phis.chunks_exact(f))
                {
                    for (((d, &g), &p), &xv) in dp.iter_mut().zip(dyr).zip(pr).zip(xs) {
                        *d = if p > T::zero() { g * xv } else { T::zero() };
                    }
                }
            });
        if need_dx {
            dx_chunks.into_par_iter().enumerate().for_each(|(s, dx)| {
                dx.fill(T::zero());
                let rows_s = s * n * f..(s + 1) * n * f;
                for (dyr, pr) in dy.data()[rows_s.clone()]
                    .chunks_exact(f)
                    .zip(phi[rows_s].chunks_exact(f))
                {
                    for ((d, &g), &p) in dx.iter_mut().zip(dyr).zip(pr) {
                        *d += g * p;
                    }
                }
            });
        }
        let [wp, bp] = &mut self.params[..] else {
            unreachable!("a weight and a bias")
        };
        gemm(
            Op::T,
            Op::N,
            e,
            f,
            rows,
            T::one(),
            &self.cos,
            &self.dp,
            T::one(),
            wp.grad.data_mut(),
        );
        for dpr in self.dp.chunks_exact(f) {
            for (db, &d) in bp.grad.data_mut().iter_mut().zip(dpr) {
                *db += d;
            }
        }
    }

    fn params(&self) -> &[Param<T>] {
        &self.params
    }

    fn params_mut(&mut self) -> &mut [Param<T>] {
        &mut self.params
    }

    /// Per sample, for each of its fractions: the embedding's dense layer and the product.
    fn macs(&self) -> usize {
        self.dim * self.width + self.width
    }
}
