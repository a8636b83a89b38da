//! Rectified linear unit.

use super::{Core, Layer};
use crate::ops::{map, map2};
use crate::tensor::{Float, Tensor};

/// `y = max(x, 0)`, element-wise, any shape.
pub struct Relu<T> {
    /// The name, output `y` and input gradient `dX` ([`Core`]).
    core: Core<T>,
    /// One sample's shape, from [`Layer::connect`] (empty until then).
    shape: Vec<usize>,
}

impl<T: Float> Relu<T> {
    /// A ReLU; it takes its shape from its input ([`Layer::connect`]).
    pub fn new(name: &str) -> Self {
        Relu {
            core: Core::new(name),
            shape: Vec::new(),
        }
    }
}

impl<T: Float> Layer<T> for Relu<T> {
    fn core(&self) -> &Core<T> {
        &self.core
    }

    fn output_shape(&self) -> Vec<usize> {
        self.shape.clone()
    }

    fn connect(&mut self, input_shape: &[usize]) {
        self.shape = input_shape.to_vec();
    }

    /// `y = max(x, 0)`.
    fn forward(&mut self, x: &Tensor<T>) {
        self.core.y.set_shape(x.shape());
        let zero = T::zero();
        map(self.core.y.data_mut(), x.data(), |x| {
            if x > zero {
                x
            } else {
                zero
            }
        });
    }

    /// `∂y/∂x` is 1 where `x > 0` and 0 elsewhere (we take 0 at the kink, as TensorFlow does), so
    /// `dX = dY ⊙ [y > 0]`; the mask is read from the saved output, `y > 0 ⇔ x > 0`.
    fn backward(&mut self, _x: &Tensor<T>, dy: &Tensor<T>, need_dx: bool) {
        if !need_dx {
            return;
        }
        self.core.dx.set_shape(dy.shape());
        let zero = T::zero();
        let (dx, y) = (self.core.dx.data_mut(), self.core.y.data());
        map2(dx, dy.data(), y, |dy, y| if y > zero { dy } else { zero });
    }
}
