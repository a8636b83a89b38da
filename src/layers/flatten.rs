//! Flatten: `[N, H, W, C]` to `[N, H·W·C]`.

use super::{Core, Layer};
use crate::tensor::{Float, Tensor};

/// Reshapes each sample to a vector, in NHWC order (so `index = (h·W + w)·C + c`, the order
/// TensorFlow's `Flatten` uses on NHWC tensors). The values are copied unchanged; the backward pass
/// is the same reshape in the other direction.
pub struct Flatten<T> {
    /// The name, output `y` and input gradient `dX` ([`Core`]).
    core: Core<T>,
    /// One input sample's shape, from [`Layer::connect`] (empty until then: any input).
    in_shape: Vec<usize>,
}

impl<T: Float> Flatten<T> {
    /// A flatten; it takes its input's shape from the layer before ([`Layer::connect`]).
    pub fn new(name: &str) -> Self {
        Flatten {
            core: Core::new(name),
            in_shape: Vec::new(),
        }
    }
}

impl<T: Float> Layer<T> for Flatten<T> {
    fn core(&self) -> &Core<T> {
        &self.core
    }

    fn output_shape(&self) -> Vec<usize> {
        match self.in_shape.is_empty() {
            true => Vec::new(),
            false => vec![self.in_shape.iter().product()],
        }
    }

    fn connect(&mut self, input_shape: &[usize]) {
        self.in_shape = input_shape.to_vec();
    }

    /// `y[n, i] = x[n, …]` with the same row-major order.
    fn forward(&mut self, x: &Tensor<T>) {
        assert!(
            self.in_shape.is_empty() || x.shape()[1..] == self.in_shape[..],
            "{}: input shape {:?}, connected to {:?}",
            self.core.name,
            &x.shape()[1..],
            self.in_shape
        );
        self.core
            .y
            .set_shape(&[x.batch(), x.len() / x.batch().max(1)]);
        self.core.y.data_mut().copy_from_slice(x.data());
    }

    /// A reshape is a permutation-free identity on the values: `dX = reshape(dY)`.
    fn backward(&mut self, x: &Tensor<T>, dy: &Tensor<T>, need_dx: bool) {
        if need_dx {
            self.core.dx.set_shape(x.shape());
            self.core.dx.data_mut().copy_from_slice(dy.data());
        }
    }
}
