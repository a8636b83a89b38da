//! Fully connected layer.

use super::{Layer, Param};
use crate::tensor::{gemm, Float, Op, Tensor};

/// `y = x·W + b` with `x: [N, In]`, `W: [In, Out]` (TensorFlow's layout), `b: [Out]`, `y: [N, Out]`.
pub struct Dense<T> {
    name: String,
    n_in: usize,
    n_out: usize,
    /// `[weight [In, Out], bias [Out]]` with their gradients.
    pub params: [Param<T>; 2],
    y: Tensor<T>,
    dx: Tensor<T>,
}

impl<T: Float> Dense<T> {
    /// A dense layer with zero weights and bias (initialise them with [`super::init`]).
    pub fn new(name: &str, n_in: usize, n_out: usize) -> Self {
        Dense {
            name: name.to_string(),
            n_in,
            n_out,
            params: [
                Param::zeros(format!("{name}.weight"), &[n_in, n_out]),
                Param::zeros(format!("{name}.bias"), &[n_out]),
            ],
            y: Tensor::empty(),
            dx: Tensor::empty(),
        }
    }
}

impl<T: Float> Layer<T> for Dense<T> {
    fn name(&self) -> &str {
        &self.name
    }

    fn output_shape(&self) -> Vec<usize> {
        vec![self.n_out]
    }

    /// `y[n, j] = b[j] + Σ_i x[n, i]·W[i, j]`: one GEMM, then the bias on each row.
    fn forward(&mut self, x: &Tensor<T>) {
        assert_eq!(x.shape()[1..], [self.n_in], "{}: input shape", self.name);
        let n = x.batch();
        self.y.set_shape(&[n, self.n_out]);
        let y = self.y.data_mut();
        for row in y.chunks_exact_mut(self.n_out) {
            row.copy_from_slice(self.params[1].value.data());
        }
        gemm(
            Op::N,
            Op::N,
            n,
            self.n_out,
            self.n_in,
            T::one(),
            x.data(),
            self.params[0].value.data(),
            T::one(),
            y,
        );
    }

    fn output(&self) -> &Tensor<T> {
        &self.y
    }

    /// Differentiating `y[n, j] = b[j] + Σ_i x[n, i]·W[i, j]`:
    /// - `∂L/∂W[i, j] = Σ_n x[n, i]·dY[n, j]`, i.e. `dW += xᵀ·dY` (`[In, N]·[N, Out]`);
    /// - `∂L/∂b[j] = Σ_n dY[n, j]`, the column sums of `dY`;
    /// - `∂L/∂x[n, i] = Σ_j dY[n, j]·W[i, j]`, i.e. `dX = dY·Wᵀ` (`[N, Out]·[Out, In]`).
    fn backward(&mut self, x: &Tensor<T>, dy: &Tensor<T>, need_dx: bool) {
        let n = x.batch();
        assert_eq!(
            dy.shape(),
            [n, self.n_out],
            "{}: upstream gradient shape",
            self.name
        );
        let gw = self.params[0].grad.data_mut();
        gemm(
            Op::T,
            Op::N,
            self.n_in,
            self.n_out,
            n,
            T::one(),
            x.data(),
            dy.data(),
            T::one(),
            gw,
        );
        let gb = self.params[1].grad.data_mut();
        for row in dy.data().chunks_exact(self.n_out) {
            for (g, &d) in gb.iter_mut().zip(row) {
                *g += d;
            }
        }
        if need_dx {
            self.dx.set_shape(&[n, self.n_in]);
            let dx = self.dx.data_mut();
            gemm(
                Op::N,
                Op::T,
                n,
                self.n_in,
                self.n_out,
                T::one(),
                dy.data(),
                self.params[0].value.data(),
                T::zero(),
                dx,
            );
        }
    }

    fn input_grad(&self) -> &Tensor<T> {
        &self.dx
    }

    fn params(&self) -> &[Param<T>] {
        &self.params
    }

    fn params_mut(&mut self) -> &mut [Param<T>] {
        &mut self.params
    }

    fn macs(&self) -> usize {
        self.n_in * self.n_out
    }
}
