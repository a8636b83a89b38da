//! Flatten: `[N, H, W, C]` to `[N, H·W·C]`.

use super::{Core, Layer};
use crate::tensor::{Float, Tensor};

/// Reshapes each sample to a vector, in NHWC order (so `index = (h·W + w)·C + c`, the order
/// TensorFlow's `Flatten` uses on NHWC tensors). The values are copied unchanged; the backward pass
/// is the same reshape in the other direction.
pub struct Flatten<T> {
    /// The name, output `y` and input gradient `dX` ([`Core`]).
    core: Core<T>,
    in_shape: Vec<usize>,
}

impl<T: Float> Flatten<T> {
    /// A flatten for samples of shape `in_shape` (batch excluded).
    pub fn new(name: &str, in_shape: &[usize]) -> Self {
        Flatten {
            core: Core::new(name),
            in_shape: in_shape.to_vec(),
        }
    }
}

impl<T: Float> Layer<T> for Flatten<T> {
    fn core(&self) -> &Core<T> {
        &self.core
    }

    fn output_shape(&self) -> Vec<usize> {
        vec![self.in_shape.iter().product()]
    }

    /// `y[n, i] = x[n, …]` with the same row-major order.
    fn forward(&mut self, x: &Tensor<T>) {
        assert_eq!(
            &x.shape()[1..],
            &self.in_shape[..],
            "{}: input shape",
            self.core.name
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
