//! Fully connected layer.

use super::{Layer, Param};
use crate::tensor::gather_bf16::{f32s, f32s_mut, pack_pairs, to_bf16_vec};
use crate::tensor::plan::{self, Kernel, Precision, Product};
use crate::tensor::{
    fill_iota, gemm, transpose, Float, GatherGemm, Init, Nonzeros, Op, SparseConv, Tensor,
};
use crate::tensor::{gather_gemm_bf16, GatherGemmBf16};

/// `y = x·W + b` with `x: [N, In]`, `W: [In, Out]` (TensorFlow's layout), `b: [Out]`, `y: [N, Out]`.
///
/// An input of any shape `[N, …]` is read as `[N, In]` (each sample's values in memory order,
/// which for NHWC is Keras' `Flatten`), and its gradient comes back in the input's shape: the
/// flatten costs no copy.
pub struct Dense<T> {
    name: String,
    n_in: usize,
    n_out: usize,
    /// `[weight [In, Out], bias [Out]]` with their gradients.
    pub params: [Param<T>; 2],
    y: Tensor<T>,
    dx: Tensor<T>,
    /// Fast path ([`Float::simd`]) offset tables: `i·In` per sample, `0..In`, `0..Out` (each
    /// pass fills what it uses; [`Layer::infer`] borrows two for its sample and row tables).
    x_rows: Vec<usize>,
    iota_in: Vec<usize>,
    iota_out: Vec<usize>,
    /// Fast path, input gradient: `dYᵀ` `[Out, N]` and `dXᵀ` `[In, N]`.
    dyt: Vec<T>,
    dxt: Vec<T>,
    /// [`Layer::infer`] at batch 1 over the input's nonzeros ([`SparseConv`]), and those.
    sparse: bool,
    nz: Nonzeros<T>,
    /// The training products' arithmetic ([`Layer::set_precision`]), and the bf16 operands
    /// ([`Kernel::GatherBf16`]) and their pair and row tables.
    precision: Precision,
    bf: Bf16Operands,
    bf_q: Vec<usize>,
    bf_p: Vec<usize>,
}

/// The bf16 operands of a dense layer's three products, a buffer each so that none is regrown
/// (and zero-filled) from one product to the next: dense1's weights are 0.9 M values.
#[derive(Default)]
struct Bf16Operands {
    /// Forward: `x`, and `W` in pairs of rows.
    x: Vec<u16>,
    w_pairs: Vec<u16>,
    /// Weight gradient: `x` and `dY` in pairs of samples.
    x_pairs: Vec<u16>,
    dy_pairs: Vec<u16>,
    /// Input gradient: `W`, and `dYᵀ` in pairs of rows.
    w: Vec<u16>,
    dyt_pairs: Vec<u16>,
}

impl<T: Float> Dense<T> {
    /// [`Layer::infer`] by [`Layer::forward`], recorded as such for [`plan::last`].
    fn infer_dense(&mut self, x: &Tensor<T>) {
        self.forward(x);
        plan::ran(Product::DenseInfer, self.kernel());
    }

    /// A dense layer with zero weights and bias (initialise them with [`super::init`]).
    ///
    /// # Panics
    /// If `n_in` or `n_out` is zero.
    pub fn new(name: &str, n_in: usize, n_out: usize) -> Self {
        assert!(
            n_in > 0 && n_out > 0,
            "{name}: a dense layer needs inputs and outputs ({n_in} → {n_out})"
        );
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
            x_rows: Vec::new(),
            iota_in: Vec::new(),
            iota_out: Vec::new(),
            dyt: Vec::new(),
            dxt: Vec::new(),
            sparse: false,
            nz: Nonzeros::default(),
            precision: Precision::F32,
            bf: Bf16Operands::default(),
            bf_q: Vec::new(),
            bf_p: Vec::new(),
        }
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
}

impl<T: Float> Dense<T> {
    /// The plan's kernel for this layer's products.
    fn kernel(&self) -> Kernel {
        plan::dense::<T>(self.precision, self.n_in, self.n_out)
    }

    /// `y = b + x·W` by the bf16 gather GEMM: pairs of inputs `x[n, 2u..2u + 2]` against pairs
    /// of weight rows.
    fn forward_bf16(&mut self, x: &Tensor<T>) {
        let (n, ni, no) = (x.batch(), self.n_in, self.n_out);
        fill_iota(&mut self.x_rows, n, ni);
        fill_iota(&mut self.bf_q, ni / 2, 2);
        to_bf16_vec(f32s(x.data()), &mut self.bf.x);
        pack_pairs(
            f32s(self.params[0].value.data()),
            ni,
            no,
            no,
            &mut self.bf.w_pairs,
        );
        gather_gemm_bf16(GatherGemmBf16 {
            a: &self.bf.x,
            p: &self.x_rows,
            q: &self.bf_q,
            b: &self.bf.w_pairs,
            ldb: no,
            n: no,
            c: f32s_mut(self.y.data_mut()),
            ldc: no,
            c_rows: None,
            init: Init::Bias(f32s(self.params[1].value.data())),
            relu: false,
        });
    }

    /// The backward pass by the bf16 gather GEMM: `dW += xᵀ·dY` over pairs of samples (both
    /// packed in pairs of rows, an odd batch padded with a zero sample), `dXᵀ = W·dYᵀ` over
    /// pairs of outputs.
    fn backward_bf16(&mut self, x: &Tensor<T>, dy: &Tensor<T>, need_dx: bool) {
        let (n, ni, no) = (x.batch(), self.n_in, self.n_out);
        // dW[i, j] += Σ_u x2[u, i]·dY2[u, j]: rows i (pair offsets 2i), steps u (2u·In).
        let pairs = pack_pairs(f32s(x.data()), n, ni, ni, &mut self.bf.x_pairs);
        pack_pairs(f32s(dy.data()), n, no, no, &mut self.bf.dy_pairs);
        fill_iota(&mut self.bf_p, ni, 2);
        fill_iota(&mut self.bf_q, pairs, 2 * ni);
        gather_gemm_bf16(GatherGemmBf16 {
            a: &self.bf.x_pairs,
            p: &self.bf_p,
            q: &self.bf_q,
            b: &self.bf.dy_pairs,
            ldb: no,
            n: no,
            c: f32s_mut(self.params[0].grad.data_mut()),
            ldc: no,
            c_rows: None,
            init: Init::Accumulate,
            relu: false,
        });
        let gb = self.params[1].grad.data_mut();
        for row in dy.data().chunks_exact(no) {
            for (g, &d) in gb.iter_mut().zip(row) {
                *g += d;
            }
        }
        if need_dx {
            // dXᵀ[i, n] = Σ_u W[i, 2u..2u + 2]·dYᵀ2[u, n]: W's rows read in place, as in f32.
            self.dyt.resize(no * n, T::zero());
            transpose(dy.data(), n, no, &mut self.dyt);
            to_bf16_vec(f32s(self.params[0].value.data()), &mut self.bf.w);
            pack_pairs(f32s(&self.dyt), no, n, n, &mut self.bf.dyt_pairs);
            fill_iota(&mut self.x_rows, ni, no);
            fill_iota(&mut self.bf_q, no / 2, 2);
            self.dxt.resize(ni * n, T::zero());
            gather_gemm_bf16(GatherGemmBf16 {
                a: &self.bf.w,
                p: &self.x_rows,
                q: &self.bf_q,
                b: &self.bf.dyt_pairs,
                ldb: n,
                n,
                c: f32s_mut(&mut self.dxt),
                ldc: n,
                c_rows: None,
                init: Init::Zero,
                relu: false,
            });
            self.dx.set_shape(x.shape());
            transpose(&self.dxt, ni, n, self.dx.data_mut());
        }
    }

    /// The backward pass by gather GEMMs, for [`Float::simd`] types: the same three products.
    fn backward_gather(&mut self, x: &Tensor<T>, dy: &Tensor<T>, need_dx: bool) {
        let (n, ni, no) = (x.batch(), self.n_in, self.n_out);
        // dW[i, j] += Σ_n x[n, i]·dY[n, j]: rows i (offsets 0..In), steps n (offsets n·In).
        fill_iota(&mut self.x_rows, n, ni);
        fill_iota(&mut self.iota_in, ni, 1);
        T::gather_gemm(GatherGemm {
            a: x.data(),
            p: &self.iota_in,
            q: &self.x_rows,
            b: dy.data(),
            ldb: no,
            n: no,
            c: self.params[0].grad.data_mut(),
            ldc: no,
            c_rows: None,
            init: Init::Accumulate,
            relu: false,
        });
        let gb = self.params[1].grad.data_mut();
        for row in dy.data().chunks_exact(no) {
            for (g, &d) in gb.iter_mut().zip(row) {
                *g += d;
            }
        }
        if need_dx {
            // dXᵀ[i, n] = Σ_j W[i, j]·dYᵀ[j, n]: W's rows are read in place (no 3.6 MB
            // transpose of dense1's weights); only dY (tiny) and the result are transposed.
            self.dyt.resize(no * n, T::zero());
            transpose(dy.data(), n, no, &mut self.dyt);
            fill_iota(&mut self.x_rows, ni, no);
            fill_iota(&mut self.iota_out, no, 1);
            self.dxt.resize(ni * n, T::zero());
            T::gather_gemm(GatherGemm {
                a: self.params[0].value.data(),
                p: &self.x_rows,
                q: &self.iota_out,
                b: &self.dyt,
                ldb: n,
                n,
                c: &mut self.dxt,
                ldc: n,
                c_rows: None,
                init: Init::Zero,
                relu: false,
            });
            // dX = (dXᵀ)ᵀ.
            self.dx.set_shape(x.shape());
            transpose(&self.dxt, ni, n, self.dx.data_mut());
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
        assert_eq!(
            x.shape()[1..].iter().product::<usize>(),
            self.n_in,
            "{}: input shape",
            self.name
        );
        let n = x.batch();
        self.y.set_shape(&[n, self.n_out]);
        let kernel = plan::ran(Product::DenseForward, self.kernel());
        if kernel == Kernel::GatherBf16 {
            return self.forward_bf16(x);
        }
        if kernel == Kernel::Gather {
            // y = b + x·W by the gather GEMM (rows i·In, steps 0..In), starting from the bias.
            fill_iota(&mut self.x_rows, n, self.n_in);
            fill_iota(&mut self.iota_in, self.n_in, 1);
            T::gather_gemm(GatherGemm {
                a: x.data(),
                p: &self.x_rows,
                q: &self.iota_in,
                b: self.params[0].value.data(),
                ldb: self.n_out,
                n: self.n_out,
                c: self.y.data_mut(),
                ldc: self.n_out,
                c_rows: None,
                init: Init::Bias(self.params[1].value.data()),
                relu: false,
            });
            return;
        }
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

    /// With [`Dense::with_sparse_inference`]: at batch 1, the sum over nonzero inputs only; for
    /// a batch, the same sample by sample if at most a tenth of the inputs are nonzero (the
    /// dense product reads each weight row once for the whole batch, the sparse one once per
    /// sample that needs it). Otherwise [`Layer::forward`].
    fn infer(&mut self, x: &Tensor<T>) {
        let n = x.batch();
        if !self.sparse {
            return self.infer_dense(x);
        }
        assert_eq!(x.len(), n * self.n_in, "{}: input shape", self.name);
        let share = plan::dense_sparse_share(n);
        if !self
            .nz
            .collect_sparse(x.data(), self.n_in, self.n_in, share)
        {
            return self.infer_dense(x);
        }
        plan::ran(Product::DenseInfer, Kernel::Sparse);
        self.y.set_shape(&[n, self.n_out]);
        // Sample i is "pixel" i with one tap; its row of y starts at i·Out.
        fill_iota(&mut self.x_rows, n, 1);
        fill_iota(&mut self.iota_out, n, self.n_out);
        SparseConv {
            x: &self.nz,
            windows: &self.x_rows,
            taps: &[0],
            w: self.params[0].value.data(),
            bias: self.params[1].value.data(),
            relu: false,
            y: self.y.data_mut(),
            rows: &self.iota_out,
        }
        .run();
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
        let kernel = plan::ran(Product::DenseBackward, self.kernel());
        if kernel == Kernel::GatherBf16 {
            return self.backward_bf16(x, dy, need_dx);
        }
        if kernel == Kernel::Gather {
            self.backward_gather(x, dy, need_dx);
            return;
        }
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
            self.dx.set_shape(x.shape());
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

    fn set_precision(&mut self, precision: Precision) {
        self.precision = precision;
    }
}
