//! Plain stochastic gradient descent.

use crate::layers::Param;
use crate::tensor::Float;

/// `θ ← θ − lr·g`.
#[derive(Clone, Debug)]
pub struct Sgd<T> {
    /// Learning rate.
    pub lr: T,
}

impl<T: Float> Sgd<T> {
    /// SGD with the given learning rate.
    pub fn new(lr: T) -> Self {
        Sgd { lr }
    }

    /// One update of every parameter from its gradient.
    pub fn step<'a>(&mut self, params: impl Iterator<Item = &'a mut Param<T>>) {
        for p in params {
            for (v, &g) in p.value.data_mut().iter_mut().zip(p.grad.data()) {
                *v -= self.lr * g;
            }
        }
    }
}
