//! A dense layer's products, each by the kernel the [`plan`](crate::ops::plan::dense) picks:
//! the plain GEMM (faer; the portable path), the gather GEMM with rows `i·In` and steps `0..In`
//! (a plain `x·W` by the vectorised kernel), or the bf16 gather GEMM over pairs of reduction
//! steps; for acting, the sum over the input's nonzero values only.
//!
//! Shapes: `x [N, In]`, `W [In, Out]`, `b [Out]`, `y` and `dY [N, Out]`; `In` and `Out` are read
//! off `W` and `b`.

use crate::ops::plan::{self, Kernel, Precision, Product};
use crate::tensor::gather_bf16::{f32s, f32s_mut, pack_pairs, to_bf16_vec};
use crate::tensor::{
    fill_iota, gather_gemm_bf16, gemm, transpose, Float, GatherGemm, GatherGemmBf16, Init,
    Nonzeros, Op, SparseConv, Tensor,
};

/// The buffers of a dense layer's kernels, reused from call to call.
#[derive(Default)]
pub struct DenseOps<T> {
    /// Gather GEMM offset tables: `i·In` per sample, `0..In`, `0..Out` (each product fills what
    /// it uses; acting borrows two for its sample and row tables).
    x_rows: Vec<usize>,
    iota_in: Vec<usize>,
    iota_out: Vec<usize>,
    /// Input gradient: `dYᵀ` `[Out, N]` and `dXᵀ` `[In, N]`, or `Wᵀ` `[Out, In]`
    /// ([`plan::dense_dx_on_wt`]).
    dyt: Vec<T>,
    dxt: Vec<T>,
    wt: Vec<T>,
    /// Acting: the input's nonzeros.
    nz: Nonzeros<T>,
    /// The bf16 operands ([`Kernel::GatherBf16`]) and their pair and row tables.
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
    /// The address and length of the `W` that `w_pairs` was packed from, until
    /// [`DenseOps::weights_changed`] says its values changed; `None` when there is none.
    w_pairs_of: Option<(usize, usize)>,
    /// Weight gradient: `x` and `dY` in pairs of samples.
    x_pairs: Vec<u16>,
    dy_pairs: Vec<u16>,
    /// Input gradient: `W`, and `dYᵀ` in pairs of rows; or `Wᵀ` in pairs of rows, and `dY`
    /// ([`plan::dense_dx_on_wt`]).
    w: Vec<u16>,
    dyt_pairs: Vec<u16>,
}

/// `(In, Out)` of the weights `w` `[In, Out]` with bias `b` `[Out]`.
fn sizes<T>(w: &[T], b: &[T]) -> (usize, usize) {
    (w.len() / b.len(), b.len())
}

impl<T: Float> DenseOps<T> {
    /// Says that the weights' values may have changed since the last product: the next bf16
    /// forward pass packs them again. The layer calls it on every mutable access to its
    /// parameters ([`crate::layers::Layer::params_mut`]: an optimiser's step, a target network's
    /// copy, a checkpoint's load).
    ///
    /// Until then the packed pairs of `W` are reused: dense1's 7 040 × 128 weights are 3.6 MB
    /// of f32 to read and 1.8 MB of pairs to write, which every forward pass did, three per
    /// train step (online on `s`, target on `s'`, online or target once more), where only the
    /// online network's weights change, once a step, and the target's every 2 000 steps.
    pub fn weights_changed(&mut self) {
        self.bf.w_pairs_of = None;
    }

    /// `y = b + x·W` into `y` (`[N, Out]`, sized by the caller); `max(0, y)` if `relu` (the
    /// kernels store it so, no pass of its own).
    pub fn forward(
        &mut self, precision: Precision, x: &Tensor<T>, w: &[T], b: &[T], y: &mut [T], relu: bool,
    ) {
        let ((ni, no), n) = (sizes(w, b), x.batch());
        match plan::ran(Product::DenseForward, plan::dense::<T>(precision, ni, no)) {
            Kernel::Gemm => {
                for row in y.chunks_exact_mut(no) {
                    row.copy_from_slice(b);
                }
                gemm(Op::N, Op::N, n, no, ni, T::one(), x.data(), w, T::one(), y);
                if relu {
                    y.iter_mut().for_each(|v| *v = v.max(T::zero()));
                }
            }
            Kernel::Gather => {
                // Rows i·In, steps 0..In, starting from the bias.
                fill_iota(&mut self.x_rows, n, ni);
                fill_iota(&mut self.iota_in, ni, 1);
                let (p, q) = (&self.x_rows, &self.iota_in);
                let mut g = GatherGemm::new(x.data(), p, q, w, no, y, Init::Bias(b));
                g.relu = relu;
                T::gather_gemm(g);
            }
            Kernel::GatherBf16 => {
                // Pairs of inputs x[n, 2u..2u + 2] against pairs of weight rows.
                fill_iota(&mut self.x_rows, n, ni);
                fill_iota(&mut self.bf_q, ni / 2, 2);
                to_bf16_vec(f32s(x.data()), &mut self.bf.x);
                // `W`'s pairs as packed before, unless they are other weights or changed since.
                let of = Some((w.as_ptr() as usize, w.len()));
                if self.bf.w_pairs_of != of {
                    pack_pairs(f32s(w), ni, no, no, &mut self.bf.w_pairs);
                    self.bf.w_pairs_of = of;
                }
                let (p, q, b) = (&self.x_rows, &self.bf_q, Init::Bias(f32s(b)));
                let (a, w, y) = (&self.bf.x, &self.bf.w_pairs, f32s_mut(y));
                let mut g = GatherGemmBf16::new(a, p, q, w, no, y, b);
                g.relu = relu;
                gather_gemm_bf16(g);
            }
            k => unreachable!("{k:?} computes no dense product"),
        }
    }

    /// The same `y` for acting. With `sparse`: `y = b + Σ_{i : x_i ≠ 0} x_i·W[i, :]`, reading
    /// only the weight rows of nonzero inputs, at batch 1 always, for a batch if at most a tenth
    /// of the inputs are nonzero ([`plan::dense_sparse_share`]); otherwise
    /// [`DenseOps::forward`]; `max(0, y)` if `relu`.
    #[allow(clippy::too_many_arguments)]
    pub fn infer(
        &mut self, precision: Precision, sparse: bool, x: &Tensor<T>, w: &[T], b: &[T],
        y: &mut [T], relu: bool,
    ) {
        let ((ni, no), n) = (sizes(w, b), x.batch());
        let share = plan::dense_sparse_share(n);
        if !sparse || !self.nz.collect_sparse(x.data(), ni, ni, share) {
            self.forward(precision, x, w, b, y, relu);
            plan::ran(Product::DenseInfer, plan::dense::<T>(precision, ni, no));
            return;
        }
        plan::ran(Product::DenseInfer, Kernel::Sparse);
        // Sample i is "pixel" i with one tap; its row of y starts at i·Out.
        fill_iota(&mut self.x_rows, n, 1);
        fill_iota(&mut self.iota_out, n, no);
        SparseConv {
            x: &self.nz,
            windows: &self.x_rows,
            taps: &[0],
            w,
            bias: b,
            relu,
            y,
            rows: &self.iota_out,
        }
        .run();
    }

    /// `dW += xᵀ·dY` (`[In, N]·[N, Out]`) into `dw`.
    pub fn weight_grad(&mut self, precision: Precision, x: &Tensor<T>, dy: &[T], dw: &mut [T]) {
        let (n, no) = (x.batch(), dy.len() / x.batch());
        let ni = dw.len() / no;
        match plan::ran(Product::DenseBackward, plan::dense::<T>(precision, ni, no)) {
            Kernel::Gemm => gemm(
                Op::T,
                Op::N,
                ni,
                no,
                n,
                T::one(),
                x.data(),
                dy,
                T::one(),
                dw,
            ),
            Kernel::Gather => {
                // dW[i, j] += Σ_n x[n, i]·dY[n, j]: rows i (offsets 0..In), steps n (n·In).
                fill_iota(&mut self.x_rows, n, ni);
                fill_iota(&mut self.iota_in, ni, 1);
                let (p, q) = (&self.iota_in, &self.x_rows);
                T::gather_gemm(GatherGemm::new(
                    x.data(),
                    p,
                    q,
                    dy,
                    no,
                    dw,
                    Init::Accumulate,
                ));
            }
            Kernel::GatherBf16 => {
                // Over pairs of samples, both packed in pairs of rows (an odd batch padded with
                // a zero sample): dW[i, j] += Σ_u x2[u, i]·dY2[u, j], rows i (pair offsets 2i),
                // steps u (2u·In).
                let pairs = pack_pairs(f32s(x.data()), n, ni, ni, &mut self.bf.x_pairs);
                pack_pairs(f32s(dy), n, no, no, &mut self.bf.dy_pairs);
                fill_iota(&mut self.bf_p, ni, 2);
                fill_iota(&mut self.bf_q, pairs, 2 * ni);
                let (a, b, dw) = (&self.bf.x_pairs, &self.bf.dy_pairs, f32s_mut(dw));
                let (p, q, sum) = (&self.bf_p, &self.bf_q, Init::Accumulate);
                gather_gemm_bf16(GatherGemmBf16::new(a, p, q, b, no, dw, sum));
            }
            k => unreachable!("{k:?} computes no dense product"),
        }
    }

    /// `dX = dY·Wᵀ` (`[N, Out]·[Out, In]`) into `dx` (sized by the caller). The vectorised
    /// kernels compute `dXᵀ = W·dYᵀ`, reading `W`'s rows in place (no 3.6 MB transpose of
    /// dense1's weights); only `dY` (tiny) and the result are transposed.
    pub fn input_grad(
        &mut self, precision: Precision, x: &Tensor<T>, dy: &[T], w: &[T], dx: &mut [T],
    ) {
        let n = x.batch();
        let (ni, no) = (x.len() / n, dy.len() / n);
        let kernel = plan::dense::<T>(precision, ni, no);
        if kernel == Kernel::Gemm {
            let (one, zero) = (T::one(), T::zero());
            return gemm(Op::N, Op::T, n, ni, no, one, dy, w, zero, dx);
        }
        if plan::dense_dx_on_wt(n, ni, no) {
            return self.input_grad_on_wt(kernel, n, ni, no, dy, w, dx);
        }
        self.dyt.resize(no * n, T::zero());
        transpose(dy, n, no, &mut self.dyt);
        fill_iota(&mut self.x_rows, ni, no);
        self.dxt.resize(ni * n, T::zero());
        match kernel {
            Kernel::Gather => {
                // dXᵀ[i, n] = Σ_j W[i, j]·dYᵀ[j, n].
                fill_iota(&mut self.iota_out, no, 1);
                let (p, q, dxt) = (&self.x_rows, &self.iota_out, &mut self.dxt);
                T::gather_gemm(GatherGemm::new(w, p, q, &self.dyt, n, dxt, Init::Zero));
            }
            Kernel::GatherBf16 => {
                // dXᵀ[i, n] = Σ_u W[i, 2u..2u + 2]·dYᵀ2[u, n], over pairs of outputs.
                to_bf16_vec(f32s(w), &mut self.bf.w);
                pack_pairs(f32s(&self.dyt), no, n, n, &mut self.bf.dyt_pairs);
                fill_iota(&mut self.bf_q, no / 2, 2);
                let (a, b, dxt) = (&self.bf.w, &self.bf.dyt_pairs, f32s_mut(&mut self.dxt));
                let (p, q) = (&self.x_rows, &self.bf_q);
                gather_gemm_bf16(GatherGemmBf16::new(a, p, q, b, n, dxt, Init::Zero));
            }
            k => unreachable!("{k:?} computes no dense product"),
        }
        // dX = (dXᵀ)ᵀ.
        transpose(&self.dxt, ni, n, dx);
    }

    /// `dX = dY·Wᵀ` on `Wᵀ` (`[Out, In]`, transposed here; [`plan::dense_dx_on_wt`]): a
    /// forward pass of `dY` through `Wᵀ`, rows `n·Out` of `dY`, steps `0..Out` (bf16: pairs of
    /// outputs, `Wᵀ` packed in pairs of rows).
    #[allow(clippy::too_many_arguments)]
    fn input_grad_on_wt(
        &mut self, kernel: Kernel, n: usize, ni: usize, no: usize, dy: &[T], w: &[T], dx: &mut [T],
    ) {
        self.wt.resize(no * ni, T::zero());
        transpose(w, ni, no, &mut self.wt);
        let wt = &self.wt;
        fill_iota(&mut self.x_rows, n, no);
        match kernel {
            Kernel::Gather => {
                // dX[n, i] = Σ_j dY[n, j]·Wᵀ[j, i].
                fill_iota(&mut self.iota_out, no, 1);
                let (p, q) = (&self.x_rows, &self.iota_out);
                T::gather_gemm(GatherGemm::new(dy, p, q, wt, ni, dx, Init::Zero));
            }
            Kernel::GatherBf16 => {
                // dX[n, i] = Σ_u dY[n, 2u..2u + 2]·Wᵀ2[u, i], over pairs of outputs.
                to_bf16_vec(f32s(dy), &mut self.bf.dyt_pairs);
                pack_pairs(f32s(wt), no, ni, ni, &mut self.bf.w);
                fill_iota(&mut self.bf_q, no / 2, 2);
                let (a, b, dx) = (&self.bf.dyt_pairs, &self.bf.w, f32s_mut(dx));
                let (p, q) = (&self.x_rows, &self.bf_q);
                gather_gemm_bf16(GatherGemmBf16::new(a, p, q, b, ni, dx, Init::Zero));
            }
            k => unreachable!("{k:?} computes no dense product"),
        }
    }
}
