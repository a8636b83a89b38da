//! Rectified linear unit.

use super::{Core, Layer};
use crate::ops::vectorized;
use crate::tensor::{Float, Tensor};
use rayon::prelude::*;

/// Elements per rayon task: element-wise work, so any split gives the same result.
const CHUNK: usize = 1 << 15;

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
        self.core
            .y
            .data_mut()
            .par_chunks_mut(CHUNK)
            .zip(x.data().par_chunks(CHUNK))
            .for_each(|(y, x)| {
                vectorized(|| {
                    for (y, &x) in y.iter_mut().zip(x) {
                        *y = if x > T::zero() { x } else { T::zero() };
                    }
                })
            });
    }

    /// `∂y/∂x` is 1 where `x > 0` and 0 elsewhere (we take 0 at the kink, as TensorFlow does), so
    /// `dX = dY ⊙ [y > 0]`; the mask is read from the saved output, `y > 0 ⇔ x > 0`.
    fn backward(&mut self, _x: &Tensor<T>, dy: &Tensor<T>, need_dx: bool) {
        if !need_dx {
            return;
        }
        self.core.dx.set_shape(dy.shape());
        self.core
            .dx
            .data_mut()
            .par_chunks_mut(CHUNK)
            .zip(dy.data().par_chunks(CHUNK))
            .zip(self.core.y.data().par_chunks(CHUNK))
            .for_each(|((dx, dy), y)| {
                vectorized(|| {
                    for ((dx, &dy), &y) in dx.iter_mut().zip(dy).zip(y) {
                        *dx = if y > T::zero() { dy } else { T::zero() };
                    }
                })
            });
    }
}
