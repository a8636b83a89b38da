//! Rectified linear unit.

use super::Layer;
use crate::ops::vectorized;
use crate::tensor::{Float, Tensor};
use rayon::prelude::*;

/// Elements per rayon task: element-wise work, so any split gives the same result.
const CHUNK: usize = 1 << 15;

/// `y = max(x, 0)`, element-wise, any shape.
pub struct Relu<T> {
    name: String,
    shape: Vec<usize>,
    y: Tensor<T>,
    dx: Tensor<T>,
}

impl<T: Float> Relu<T> {
    /// A ReLU on samples of the given shape (batch excluded).
    pub fn new(name: &str, shape: &[usize]) -> Self {
        Relu {
            name: name.to_string(),
            shape: shape.to_vec(),
            y: Tensor::empty(),
            dx: Tensor::empty(),
        }
    }
}

impl<T: Float> Layer<T> for Relu<T> {
    fn name(&self) -> &str {
        &self.name
    }

    fn output_shape(&self) -> Vec<usize> {
        self.shape.clone()
    }

    /// `y = max(x, 0)`.
    fn forward(&mut self, x: &Tensor<T>) {
        self.y.set_shape(x.shape());
        self.y
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

    fn output(&self) -> &Tensor<T> {
        &self.y
    }

    /// `∂y/∂x` is 1 where `x > 0` and 0 elsewhere (we take 0 at the kink, as TensorFlow does), so
    /// `dX = dY ⊙ [y > 0]`; the mask is read from the saved output, `y > 0 ⇔ x > 0`.
    fn backward(&mut self, _x: &Tensor<T>, dy: &Tensor<T>, need_dx: bool) {
        if !need_dx {
            return;
        }
        self.dx.set_shape(dy.shape());
        self.dx
            .data_mut()
            .par_chunks_mut(CHUNK)
            .zip(dy.data().par_chunks(CHUNK))
            .zip(self.y.data().par_chunks(CHUNK))
            .for_each(|((dx, dy), y)| {
                vectorized(|| {
                    for ((dx, &dy), &y) in dx.iter_mut().zip(dy).zip(y) {
                        *dx = if y > T::zero() { dy } else { T::zero() };
                    }
                })
            });
    }

    fn input_grad(&self) -> &Tensor<T> {
        &self.dx
    }
}
