//! Layers with hand-written backward passes.
//!
//! Every layer keeps what its backward pass needs from the forward pass, owns its output and input
//! gradient buffers (reused from call to call), and *accumulates* parameter gradients with `+=`, so
//! a caller zeroes them once per step ([`Sequential::zero_grad`]) and can sum gradients over
//! several backward passes. In each file the forward and backward passes stand side by side with
//! the derivation of the latter.
//!
//! Notation used in the doc comments: `x` the layer's input, `y` its output, `dY = ∂L/∂y` the
//! upstream gradient of some scalar loss `L`, and likewise `dX`, `dW`, `db`.

mod conv2d;
mod dense;
mod dueling;
mod flatten;
pub mod init;
mod layer_norm;
pub mod loss;
mod max_pool;
mod quantile_embedding;
mod relu;
mod residual;
mod sequential;

pub use conv2d::Conv2d;
pub use dense::Dense;
pub use dueling::Dueling;
pub use flatten::Flatten;
pub use layer_norm::LayerNorm;
pub use max_pool::MaxPool2d;
pub use quantile_embedding::QuantileEmbedding;
pub use relu::Relu;
pub use residual::Residual;
pub use sequential::Sequential;

use crate::ops::Precision;
use crate::tensor::{Float, Tensor};

/// One trainable tensor and its gradient.
#[derive(Clone, Debug)]
pub struct Param<T> {
    /// Full name, `{layer}.{weight|bias}`, as used in checkpoints.
    pub name: String,
    /// The values.
    pub value: Tensor<T>,
    /// `∂L/∂value`, accumulated by `backward`.
    pub grad: Tensor<T>,
}

impl<T: Float> Param<T> {
    /// A zero-valued parameter of the given shape.
    pub fn zeros(name: String, shape: &[usize]) -> Self {
        Param {
            name,
            value: Tensor::zeros(shape),
            grad: Tensor::zeros(shape),
        }
    }
}

/// What every layer holds besides its parameters and its own state: a name and the two
/// buffers its passes write, reused from call to call.
pub struct Core<T> {
    /// The layer's name; parameters are named `{name}.{kind}`.
    pub name: String,
    /// `y`, the output of the last [`Layer::forward`] or [`Layer::infer`] (`[N, …]`, the layer's
    /// output shape).
    pub y: Tensor<T>,
    /// `dX = ∂L/∂x` (`x`'s shape), from the last [`Layer::backward`] that computed it; a layer
    /// may leave it empty after a backward pass that did not.
    pub dx: Tensor<T>,
}

impl<T: Float> Core<T> {
    /// A layer's name and empty buffers.
    pub fn new(name: &str) -> Self {
        Core {
            name: name.to_string(),
            y: Tensor::empty(),
            dx: Tensor::empty(),
        }
    }
}

/// A differentiable layer.
pub trait Layer<T: Float>: Send {
    /// The layer's name and buffers.
    fn core(&self) -> &Core<T>;

    /// The layer's name; parameters are named `{name}.{kind}`.
    fn name(&self) -> &str {
        &self.core().name
    }

    /// Shape of one sample's output (batch dimension excluded). A layer whose output follows
    /// its input's shape ([`Relu`], [`Flatten`]) knows it once [`Layer::connect`] has told it
    /// the input's; before, it returns an empty shape.
    fn output_shape(&self) -> Vec<usize>;

    /// Tells the layer the shape of one input sample: [`Sequential::push`] calls it with the
    /// output shape of the layer before, so a layer needs no shape its input already gives.
    /// Layers whose shapes are set when they are built ignore it.
    fn connect(&mut self, _input_shape: &[usize]) {}

    /// Computes `y = f(x)` into the layer's output buffer, keeping what backward needs.
    fn forward(&mut self, x: &Tensor<T>);

    /// A forward pass that no backward pass follows (acting): the same `y`, up to rounding,
    /// by whatever kernel is fastest for it. It may discard what the last [`Layer::forward`]
    /// kept for backward, so a backward pass needs a forward pass after it. The default is
    /// [`Layer::forward`].
    fn infer(&mut self, x: &Tensor<T>) {
        self.forward(x)
    }

    /// The output of the last [`Layer::forward`] or [`Layer::infer`].
    fn output(&self) -> &Tensor<T> {
        &self.core().y
    }

    /// Given the same `x` as the last forward pass and `dY`, adds `∂L/∂θ` to every parameter
    /// gradient and, if `need_dx`, writes `dX` into the input-gradient buffer (the first layer of a
    /// network skips it: nothing upstream needs the gradient with respect to the observations).
    fn backward(&mut self, x: &Tensor<T>, dy: &Tensor<T>, need_dx: bool);

    /// `dX` from the last [`Layer::backward`] that computed it.
    fn input_grad(&self) -> &Tensor<T> {
        &self.core().dx
    }

    /// Calls `f` on each parameter, in a fixed order (none by default): weight before bias, and
    /// a layer made of layers ([`Residual`]) visits its children's in order. The order is part
    /// of the checkpoint format.
    ///
    /// A visit rather than a list, so that the walks of a train step over the parameters (the
    /// gradients zeroed, their norm, Adam's update) allocate nothing, while a composite layer
    /// still reaches parameters its children own.
    fn visit_params<'a>(&'a self, _f: &mut dyn FnMut(&'a Param<T>)) {}

    /// [`Layer::visit_params`], mutably: `f` may change the values (a layer that keeps a
    /// derived copy of its weights drops it).
    fn visit_params_mut<'a>(&'a mut self, _f: &mut dyn FnMut(&'a mut Param<T>)) {}

    /// The parameters in [`Layer::visit_params`]'s order, as a list.
    fn params(&self) -> Vec<&Param<T>> {
        let mut list = Vec::new();
        self.visit_params(&mut |p| list.push(p));
        list
    }

    /// The parameters, mutably, in [`Layer::visit_params`]'s order.
    fn params_mut(&mut self) -> Vec<&mut Param<T>> {
        let mut list = Vec::new();
        self.visit_params_mut(&mut |p| list.push(p));
        list
    }

    /// Multiply-adds of one sample's forward pass (for FLOP counts).
    fn macs(&self) -> usize {
        0
    }

    /// Sets the quantile fractions `τ` the next passes evaluate the network at, `N` per sample
    /// of the batch, sample by sample ([`QuantileEmbedding`]); layers that take none ignore them.
    fn set_fractions(&mut self, _taus: &[f64]) {}

    /// The arithmetic of the layer's training products ([`crate::ops::plan::conv`] and
    /// [`crate::ops::plan::dense`] pick their kernels by it). Layers without products ignore
    /// it.
    fn set_precision(&mut self, _precision: Precision) {}
}
