//! Fully connected layer.

use super::init::VarianceScaling;
use super::{Core, Layer, Param};
use crate::ops::{DenseOps, Precision};
use crate::tensor::{Float, Tensor};

/// `y = x·W + b` with `x: [N, In]`, `W: [In, Out]` (TensorFlow's layout), `b: [Out]`, `y: [N, Out]`.
///
/// An input of any shape `[N, …]` is read as `[N, In]` (each sample's values in memory order,
/// which for NHWC is Keras' `Flatten`), and its gradient comes back in the input's shape: the
/// flatten costs no copy. Each product is one call to [`DenseOps`], which runs it by the kernel
/// [`crate::ops::plan::dense`] picks.
pub struct Dense<T> {
    /// The name, output `y` and input gradient `dX` ([`Core`]).
    core: Core<T>,
    n_in: usize,
    n_out: usize,
    /// `[weight [In, Out], bias [Out]]` with their gradients. Private: the weights change only
    /// through [`Layer::visit_params_mut`] (and so [`Layer::params_mut`]), which tells the kernels ([`DenseOps::weights_changed`]).
    params: [Param<T>; 2],
    /// Whether acting may take the sum over the input's nonzeros ([`Dense::with_sparse_inference`]).
    sparse: bool,
    /// Whether the output is `max(0, x·W + b)` ([`Dense::with_relu`]).
    relu: bool,
    /// `dZ = dY ⊙ [y > 0]` `[N, Out]` of the last backward pass, with a ReLU.
    dz: Vec<T>,
    /// The training products' arithmetic ([`Layer::set_precision`]).
    precision: Precision,
    /// The products' kernels and their buffers.
    ops: DenseOps<T>,
}

impl<T: Float> Dense<T> {
    /// A dense layer that starts ready to train: weights drawn by [`VarianceScaling::HE`] (the
    /// article's He initialiser) from [`super::init::named_rng`] of its name, bias zero. Draw
    /// them from your own generator with [`Dense::init`].
    ///
    /// # Panics
    /// If `n_in` or `n_out` is zero.
    pub fn new(name: &str, n_in: usize, n_out: usize) -> Self {
        assert!(
            n_in > 0 && n_out > 0,
            "{name}: a dense layer needs inputs and outputs ({n_in} → {n_out})"
        );
        Dense {
            core: Core::new(name),
            n_in,
            n_out,
            params: [
                Param::zeros(format!("{name}.weight"), &[n_in, n_out]),
                Param::zeros(format!("{name}.bias"), &[n_out]),
            ],
            sparse: false,
            relu: false,
            dz: Vec::new(),
            precision: Precision::F32,
            ops: DenseOps::default(),
        }
        .init(&VarianceScaling::HE, &mut super::init::named_rng(name))
    }

    /// Draws the weights again by `init` from `rng`, and zeroes the bias.
    pub fn init(mut self, init: &VarianceScaling, rng: &mut impl rand::Rng) -> Self {
        init.fill(&mut self.params[0].value, rng);
        self.params[1].value.fill_zero();
        self
    }

    /// Acts ([`Layer::infer`] at batch 1) by `y = b + Σ_{i : x_i ≠ 0} x_i·W[i, :]`, reading only
    /// the weight rows of nonzero inputs ([`crate::tensor::SparseConv`] with one pixel and one
    /// tap): for a layer whose input is a ReLU's output. dense1's 3.6 MB of weights do not fit in
    /// L2, so reading them bounds a batch-1 forward pass, and a trained network's conv3 output is
    /// about 96% zeros. Off by default; [`crate::dqn::article_qnet`] turns it on for dense1.
    pub fn with_sparse_inference(mut self, on: bool) -> Self {
        self.sparse = on;
        self
    }

    /// Applies a ReLU as the products store the output: `y = max(0, x·W + b)`, the same values as
    /// a [`super::Relu`] after the layer without its pass and its buffer. Backward then masks
    /// `dY` by `[y > 0]` (which is `[x·W + b > 0]`) before the three products below.
    pub fn with_relu(mut self) -> Self {
        self.relu = true;
        self
    }

    /// Checks that `x` is a batch of `[N, In]` and sizes the output.
    fn check_input(&mut self, x: &Tensor<T>) {
        assert_eq!(
            x.shape()[1..].iter().product::<usize>(),
            self.n_in,
            "{}: input shape",
            self.core.name
        );
        self.core.y.set_shape(&[x.batch(), self.n_out]);
    }
}

impl<T: Float> Layer<T> for Dense<T> {
    fn core(&self) -> &Core<T> {
        &self.core
    }

    fn output_shape(&self) -> Vec<usize> {
        vec![self.n_out]
    }

    /// `y[n, j] = b[j] + Σ_i x[n, i]·W[i, j]`: one product, starting from the bias.
    fn forward(&mut self, x: &Tensor<T>) {
        self.check_input(x);
        let [w, b] = &self.params;
        let (w, b) = (w.value.data(), b.value.data());
        let y = self.core.y.data_mut();
        self.ops.forward(self.precision, x, w, b, y, self.relu);
    }

    /// The same `y` for acting: with [`Dense::with_sparse_inference`], the sum over nonzero
    /// inputs only where few are nonzero; otherwise [`Layer::forward`].
    fn infer(&mut self, x: &Tensor<T>) {
        self.check_input(x);
        let [w, b] = &self.params;
        let (w, b) = (w.value.data(), b.value.data());
        let y = self.core.y.data_mut();
        let (precision, sparse, relu) = (self.precision, self.sparse, self.relu);
        self.ops.infer(precision, sparse, x, w, b, y, relu);
    }

    /// Differentiating `y[n, j] = b[j] + Σ_i x[n, i]·W[i, j]`:
    /// - `∂L/∂W[i, j] = Σ_n x[n, i]·dY[n, j]`, i.e. `dW += xᵀ·dY` (`[In, N]·[N, Out]`);
    /// - `∂L/∂b[j] = Σ_n dY[n, j]`, the column sums of `dY`;
    /// - `∂L/∂x[n, i] = Σ_j dY[n, j]·W[i, j]`, i.e. `dX = dY·Wᵀ` (`[N, Out]·[Out, In]`).
    ///
    /// With a ReLU ([`Dense::with_relu`]) each of them reads `dZ = dY ⊙ [y > 0]` for `dY`.
    fn backward(&mut self, x: &Tensor<T>, dy: &Tensor<T>, need_dx: bool) {
        let n = x.batch();
        assert_eq!(
            dy.shape(),
            [n, self.n_out],
            "{}: upstream gradient",
            self.core.name
        );
        let dy = if self.relu {
            self.dz.clear();
            let y = self.core.y.data();
            let mask = |(&g, &v): (&T, &T)| if v > T::zero() { g } else { T::zero() };
            self.dz.extend(dy.data().iter().zip(y).map(mask));
            &self.dz[..]
        } else {
            dy.data()
        };
        let [w, b] = &mut self.params;
        self.ops
            .weight_grad(self.precision, x, dy, w.grad.data_mut());
        let db = b.grad.data_mut();
        for row in dy.chunks_exact(self.n_out) {
            for (g, &d) in db.iter_mut().zip(row) {
                *g += d;
            }
        }
        if need_dx {
            self.core.dx.set_shape(x.shape());
            let dx = self.core.dx.data_mut();
            self.ops
                .input_grad(self.precision, x, dy, w.value.data(), dx);
        }
    }

    fn visit_params<'a>(&'a self, f: &mut dyn FnMut(&'a Param<T>)) {
        self.params.iter().for_each(f);
    }

    /// The parameters to change: the bf16 kernels' packed copy of the weights is dropped
    /// ([`DenseOps::weights_changed`]), since the caller may change them.
    fn visit_params_mut<'a>(&'a mut self, f: &mut dyn FnMut(&'a mut Param<T>)) {
        self.ops.weights_changed();
        self.params.iter_mut().for_each(f);
    }

    fn macs(&self) -> usize {
        self.n_in * self.n_out
    }

    fn set_precision(&mut self, precision: Precision) {
        self.precision = precision;
    }
}
