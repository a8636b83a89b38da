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
    /// The distinct values among `taus`, in order of first use (`U` of them), and for each of
    /// the `B·N` rows the index of its fraction among them: a pass's policy midpoints are the
    /// same `K` fractions for every sample, so their cosines and products are computed once.
    distinct: Vec<f64>,
    row_of: Vec<usize>,
    /// Each distinct fraction's bits and its index (kept between passes: no allocation).
    first: std::collections::HashMap<u64, usize>,
    /// `[U, E]`: the cosines of the distinct fractions of the last pass.
    cos: Vec<T>,
    /// `[B·N, E]`: the cosines row by row, for the weight gradient (built from `cos` only when
    /// some fraction repeats).
    cos_rows: Vec<T>,
    /// `[U, F]`: `Σ_j c_j W_jf` of the distinct fractions.
    pre: Vec<T>,
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
            distinct: Vec::new(),
            row_of: Vec::new(),
            first: std::collections::HashMap::new(),
            cos: Vec::new(),
            cos_rows: Vec::new(),
            pre: Vec::new(),
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

    /// The forward pass; `keep` writes `φ` row by row for [`Layer::backward`]. Each row's
    /// values are those of a pass over all `B·N` rows: a row of the GEMM does not depend on the
    /// others (`a_fractions_row_does_not_depend_on_the_others`, below).
    fn pass(&mut self, x: &Tensor<T>, keep: bool) {
        let (e, f) = (self.dim, self.width);
        let b = x.len() / f;
        assert_eq!(b * f, x.len(), "{}: input is not [B, {f}]", self.core.name);
        let n = self.per_sample(b);
        let rows = b * n;
        let first = &mut self.first;
        first.clear();
        self.distinct.clear();
        self.row_of.clear();
        for &tau in &self.taus {
            let next = first.len();
            let u = *first.entry(tau.to_bits()).or_insert(next);
            if u == next {
                self.distinct.push(tau);
            }
            self.row_of.push(u);
        }
        let u = self.distinct.len();
        self.cos.resize(u * e, T::zero());
        self.pre.resize(u * f, T::zero());
        cosine_rows(&self.distinct, e, &mut self.cos);
        let (w, bias) = (self.params[0].value.data(), self.params[1].value.data());
        gemm(
            Op::N,
            Op::N,
            u,
            f,
            e,
            T::one(),
            &self.cos,
            w,
            T::zero(),
            &mut self.pre,
        );
        self.core.y.set_shape(&[rows, f]);
        if keep {
            self.phi.resize(rows * f, T::zero());
        }
        let (pre, row_of) = (&self.pre, &self.row_of);
        // Sample `s`'s `N` rows of `y` (and of `φ` if kept) from its features `xs`.
        let fill = |s: usize, y: &mut [T], xs: &[T], mut phi: Option<&mut [T]>| {
            for (i, y) in y.chunks_exact_mut(f).enumerate() {
                let u = row_of[s * n + i];
                let p = &pre[u * f..(u + 1) * f];
                for (j, (y, ((&xv, &pv), &bv))) in
                    y.iter_mut().zip(xs.iter().zip(p).zip(bias)).enumerate()
                {
                    let v = relu(pv + bv);
                    if let Some(phi) = phi.as_mut() {
                        phi[i * f + j] = v;
                    }
                    *y = xv * v;
                }
            }
        };
        let y = self.core.y.data_mut().par_chunks_mut(n * f);
        let xs = x.data().par_chunks(f);
        if keep {
            let phi = self.phi.par_chunks_mut(n * f);
            y.zip(xs)
                .zip(phi)
                .enumerate()
                .for_each(|(s, ((y, xs), phi))| fill(s, y, xs, Some(phi)));
        } else {
            y.zip(xs)
                .enumerate()
                .for_each(|(s, (y, xs))| fill(s, y, xs, None));
        }
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

/// `max(0, v)`.
fn relu<T: Float>(v: T) -> T {
    if v > T::zero() {
        v
    } else {
        T::zero()
    }
}

/// [`cosines`] of each fraction in `taus`, one row of `e` values each (`c`: `[taus.len(), e]`),
/// eight fractions at a time: the recurrence is a chain of dependent multiply-adds (latency-
/// bound for one fraction), so eight independent chains side by side fill the vector lanes.
/// Each lane does exactly [`cosines`]' arithmetic, so the values are the same bits.
fn cosine_rows<T: Float>(taus: &[f64], e: usize, c: &mut [T]) {
    const L: usize = 8;
    let mut rows = c.chunks_exact_mut(L * e);
    let mut groups = taus.chunks_exact(L);
    for (block, group) in rows.by_ref().zip(groups.by_ref()) {
        let c1: [f64; L] = std::array::from_fn(|l| (std::f64::consts::PI * group[l]).cos());
        let (mut prev, mut cur) = ([1.0f64; L], c1);
        for j in 0..e {
            for l in 0..L {
                block[l * e + j] = T::of(cur[l]);
                (prev[l], cur[l]) = (cur[l], 2.0 * c1[l] * cur[l] - prev[l]);
            }
        }
    }
    for (c, &tau) in rows
        .into_remainder()
        .chunks_exact_mut(e)
        .zip(groups.remainder())
    {
        cosines(tau, c);
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

    /// `y_(bi)f = x_bf · max(0, Σ_j cos(π j τ_bi) W_jf + b_f)`: the cosines and one GEMM
    /// `[U, E]·[E, F]` over the `U` distinct fractions, then the bias, the ReLU and the product,
    /// sample by sample, keeping `φ` for the backward pass.
    fn forward(&mut self, x: &Tensor<T>) {
        self.pass(x, true);
    }

    /// [`Layer::forward`] without keeping `φ` (no backward pass follows).
    fn infer(&mut self, x: &Tensor<T>) {
        self.pass(x, false);
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
        // The cosines row by row: those of the distinct fractions if no fraction repeated.
        let cos = if self.distinct.len() == rows {
            &self.cos
        } else {
            self.cos_rows.clear();
            for &u in &self.row_of {
                self.cos_rows
                    .extend_from_slice(&self.cos[u * e..(u + 1) * e]);
            }
            &self.cos_rows
        };
        gemm(
            Op::T,
            Op::N,
            e,
            f,
            rows,
            T::one(),
            cos,
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

    fn visit_params<'a>(&'a self, f: &mut dyn FnMut(&'a Param<T>)) {
        self.params.iter().for_each(f);
    }

    fn visit_params_mut<'a>(&'a mut self, f: &mut dyn FnMut(&'a mut Param<T>)) {
        self.params.iter_mut().for_each(f);
    }

    /// Per sample, for each of its fractions: the embedding's dense layer and the product.
    fn macs(&self) -> usize {
        self.dim * self.width + self.width
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A pass's rows are those of each fraction alone: with the step's sizes (64 cosines, 128
    /// features, 32 samples of 32 midpoints and 32 drawn fractions, the midpoints computed once)
    /// each output row is bit for bit that of a pass over its own sample and fraction, in
    /// `forward` and `infer`.
    #[test]
    fn a_fractions_row_does_not_depend_on_the_others() {
        let (e, f, b, n) = (64, 128, 32, 64);
        let mut layer = QuantileEmbedding::<f32>::new("iqn", e, f);
        let mut seed = 1u64;
        let mut next = move || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((seed >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
        };
        for p in layer.params_mut() {
            p.value
                .data_mut()
                .iter_mut()
                .for_each(|v| *v = 0.2 * next());
        }
        let mids: Vec<f64> = (0..32).map(|i| (2 * i + 1) as f64 / 64.0).collect();
        let taus: Vec<f64> = (0..b)
            .flat_map(|_| {
                let drawn: Vec<f64> = (0..32).map(|_| 0.5 + 0.5 * next() as f64).collect();
                mids.iter().copied().chain(drawn).collect::<Vec<_>>()
            })
            .collect();
        let x = Tensor::from_vec(&[b, f], (0..b * f).map(|_| next()).collect());
        layer.set_fractions(&taus);
        layer.forward(&x);
        let all = layer.output().clone();
        layer.infer(&x);
        assert_eq!(
            layer.output().data(),
            all.data(),
            "infer gives forward's values"
        );
        let mut one = QuantileEmbedding::<f32>::new("one", e, f);
        for (p, q) in one.params_mut().iter_mut().zip(layer.params()) {
            p.value.data_mut().copy_from_slice(q.value.data());
        }
        for (row, &tau) in taus.iter().enumerate() {
            let s = row / n;
            one.set_fractions(&[tau]);
            one.forward(&Tensor::from_vec(
                &[1, f],
                x.data()[s * f..(s + 1) * f].to_vec(),
            ));
            let got = &all.data()[row * f..(row + 1) * f];
            assert!(
                got.iter()
                    .zip(one.output().data())
                    .all(|(a, b)| a.to_bits() == b.to_bits()),
                "row {row}"
            );
        }
    }

    /// Eight fractions side by side give each fraction's cosines bit for bit, for every count
    /// of fractions (whole groups of eight and a remainder) and in both precisions.
    #[test]
    fn cosine_rows_are_each_fractions_cosines() {
        for count in [1, 7, 8, 9, 16, 21] {
            let taus: Vec<f64> = (0..count)
                .map(|i| (i as f64 + 0.37) / count as f64)
                .collect();
            let e = 64;
            let mut rows = vec![0.0f32; count * e];
            cosine_rows(&taus, e, &mut rows);
            let mut rows64 = vec![0.0f64; count * e];
            cosine_rows(&taus, e, &mut rows64);
            for (i, &tau) in taus.iter().enumerate() {
                let mut one = vec![0.0f32; e];
                cosines(tau, &mut one);
                let mut one64 = vec![0.0f64; e];
                cosines(tau, &mut one64);
                for j in 0..e {
                    assert_eq!(
                        rows[i * e + j].to_bits(),
                        one[j].to_bits(),
                        "{count} {i} {j}"
                    );
                    assert_eq!(rows64[i * e + j].to_bits(), one64[j].to_bits());
                    let exact = (std::f64::consts::PI * (j + 1) as f64 * tau).cos();
                    assert!((one64[j] - exact).abs() < 1e-12, "{tau} {j}");
                }
            }
        }
    }
}
