//! 2-D convolution (NHWC, HWIO filters, TensorFlow's SAME/VALID padding), with an optional fused
//! ReLU and an optional zero border written around the output.
//!
//! This file is the maths: the layer's parameters and geometry, and its forward and backward
//! passes by im2col + GEMM, each beside its derivation. Which kernel computes each product for a
//! shape, batch, precision and CPU is decided by [`crate::tensor::plan::conv`]; the fast ones
//! (gather GEMMs, Winograd, the sparse and background products for acting) live in
//! `conv2d/fast.rs` and compute the same products.

mod fast;

use super::{Layer, Param};
use crate::tensor::cpu::avx512_twin;
use crate::tensor::plan::{self, Kernel, Precision, Product};
use crate::tensor::{col2im, gemm, im2col, Border, ConvGeom, Float, Op, Tensor};
use rayon::prelude::*;

/// `y = border(act(conv(x, W) + b))`: see [`crate::tensor::ConvGeom`] for the defining sum and
/// the shapes; `act` is the identity or, [`Conv2d::with_relu`], `max(·, 0)`; `border` writes zero
/// rows and columns around each output image, [`Conv2d::with_border`].
///
/// Formulation: im2col + GEMM. The input is unrolled into `cols[N·OH·OW, KH·KW·Cin]` (kept for the
/// backward pass), and `Z[N·OH·OW, Cout] = cols · W[KH·KW·Cin, Cout] + b` is a single matrix
/// product whose result is already the NHWC output. The gradients are two more products:
/// `dW += colsᵀ·dZ` and `dX = col2im(dZ·Wᵀ)` ([`Layer::backward`]).
///
/// The same products may run by other kernels, chosen by [`crate::tensor::plan::conv`] (f32 on
/// AVX-512: gather GEMMs that write no im2col matrix; Winograd's minimal filtering,
/// [`Conv2d::with_winograd`]), and acting by sparse ones ([`Conv2d::with_sparse_inference`],
/// [`Conv2d::with_background_inference`]).
///
/// The fused ReLU and the border are what a separate [`super::Relu`] layer and the next layer's
/// padding would otherwise do, each a pass over the whole activation: at batch 48 that is about
/// 11 MB of memory traffic per forward pass of the article's network.
pub struct Conv2d<T> {
    name: String,
    /// The geometry (input and output sizes, strides, padding).
    pub geom: ConvGeom,
    /// `[weight [KH, KW, Cin, Cout], bias [Cout]]` with their gradients.
    pub params: [Param<T>; 2],
    relu: bool,
    border: Border,
    /// Border places of the input (written by the layer before): constants, so their gradient
    /// is not computed and `dX` holds zeros there.
    in_border: Border,
    /// The kernels the plan may pick besides the dense products: Winograd for training, the
    /// sparse and background products for acting.
    winograd: bool,
    sparse: bool,
    background: bool,
    /// The training products' arithmetic ([`Layer::set_precision`]).
    precision: Precision,
    /// `[N·OH·OW, KH·KW·Cin]`, from the last forward pass.
    cols: Vec<T>,
    /// `[N·OH·OW, KH·KW·Cin]`, scratch for the input gradient.
    dcols: Vec<T>,
    /// `[N, OH, OW, Cout]`: the product before the ReLU and the border (im2col path), then
    /// the gradient with respect to it, `dZ` (every path, when there is a ReLU or a border).
    z: Vec<T>,
    y: Tensor<T>,
    dx: Tensor<T>,
    /// Where each output pixel starts in the bordered output `y`.
    out_rows: Vec<usize>,
    /// How many leading images of `y`'s buffer have their border places zeroed. Every kernel
    /// writes only the interior and the buffer never shrinks (it grows with zeros), so a border
    /// zeroed once stays zero: the train step zeroes nothing after its first call.
    y_clean: usize,
    /// The same for `dX`'s input-border places, with the input size `(H, W)` they were zeroed
    /// for (a pre-padded and a plain input lay `dX` out differently).
    dx_clean: (usize, (usize, usize)),
    /// The fast kernels' buffers.
    fast: fast::Scratch<T>,
}

impl<T: Float> Conv2d<T> {
    /// A convolution with zero weights and bias (initialise them with [`super::init`]).
    pub fn new(name: &str, geom: ConvGeom) -> Self {
        let wshape = [geom.kh, geom.kw, geom.cin, geom.cout];
        Conv2d {
            name: name.to_string(),
            geom,
            params: [
                Param::zeros(format!("{name}.weight"), &wshape),
                Param::zeros(format!("{name}.bias"), &[geom.cout]),
            ],
            relu: false,
            border: Border::default(),
            in_border: Border::default(),
            winograd: false,
            sparse: false,
            background: false,
            precision: Precision::F32,
            cols: Vec::new(),
            dcols: Vec::new(),
            z: Vec::new(),
            y: Tensor::empty(),
            dx: Tensor::empty(),
            out_rows: Vec::new(),
            y_clean: 0,
            dx_clean: (0, (0, 0)),
            fast: fast::Scratch::default(),
        }
    }

    /// Applies `max(·, 0)` to the output (a fused ReLU: `∂y/∂z = [y > 0]`).
    pub fn with_relu(mut self) -> Self {
        self.relu = true;
        self
    }

    /// Writes the output with a zero border around each image, typically the next layer's
    /// SAME padding, so that layer runs as VALID over it ([`ConvGeom::as_valid`]). The gradient
    /// that arrives for border places is ignored: they are constants.
    pub fn with_border(mut self, border: Border) -> Self {
        self.border = border;
        self.y_clean = 0;
        self
    }

    /// Declares which places of the input are the previous layer's zero border (interior
    /// `(H − top − bottom) × (W − left − right)`): their gradient is left out (zeros in `dX`).
    pub fn with_input_border(mut self, border: Border) -> Self {
        assert!(
            border.top + border.bottom < self.geom.h && border.left + border.right < self.geom.w,
            "{}: input border larger than the input",
            self.name
        );
        self.in_border = border;
        self.dx_clean = (0, (0, 0));
        self
    }

    /// Lets the plan run the training products by Winograd's minimal filtering
    /// ([`crate::tensor::winograd_conv`]) where the filter shape has one
    /// ([`plan::winograd_kind`]: 3×3 stride 1, or `2s × 2s` stride `s`) and the batch is large
    /// enough ([`plan::WINOGRAD_MIN_BATCH`]); see [`plan::conv`] for which products and what
    /// it measured. The same sums, rounded differently. Off by default;
    /// [`crate::dqn::article_qnet`] turns it on where [`plan::winograd_pays`] (conv2, conv3).
    pub fn with_winograd(mut self, on: bool) -> Self {
        self.winograd = on;
        self
    }

    /// Acts ([`Layer::infer`]) by a product over the input's nonzero values only
    /// ([`crate::tensor::SparseConv`]) when few are nonzero ([`plan::sparse_share`]): for a layer
    /// whose input is a ReLU's output, which in a trained network is mostly exact zeros. Off by
    /// default; [`crate::dqn::article_qnet`] turns it on for conv2 and conv3.
    pub fn with_sparse_inference(mut self, on: bool) -> Self {
        self.sparse = on;
        self
    }

    /// Acts ([`Layer::infer`] at batch 1) by splitting the input into a constant background
    /// and its difference from it, which on game frames is mostly zeros
    /// ([`crate::tensor::Background`]): the background's response costs no pass over the image
    /// and the difference's is summed over its pixels that differ. For a layer that reads
    /// frames; if too many pixels differ ([`plan::BACKGROUND_MAX_DIFFERING`]), the dense
    /// product. Off by default; [`crate::dqn::article_qnet`] turns it on for conv1.
    pub fn with_background_inference(mut self, on: bool) -> Self {
        self.background = on;
        self
    }

    /// The geometry for input `x`: the layer's own, or, when `x` arrives already padded
    /// (`[N, HP, WP, Cin]`, [`ConvGeom::padded`], with a zero border: e.g. a replay batch
    /// written that way), the same convolution as a VALID one over it ([`ConvGeom::as_valid`]),
    /// which reads it in place instead of copying it into a padded buffer. `SAME(x) =
    /// VALID(pad(x))` and both read the same padded layout, so the results are bit-identical.
    pub fn input_geometry(&self, x: &Tensor<T>) -> ConvGeom {
        let g = self.geom;
        let (hp, wp) = g.padded();
        if !g.reads_input_directly() && x.shape().len() == 4 && x.shape()[1..] == [hp, wp, g.cin] {
            g.as_valid().0
        } else {
            g
        }
    }

    fn rows(&self, n: usize) -> usize {
        n * self.geom.out_pixels()
    }

    /// The output shape for a batch of `n`.
    fn out_shape(&self, n: usize) -> [usize; 4] {
        let (hb, wb) = self.border.around(self.geom.oh, self.geom.ow);
        [n, hb, wb, self.geom.cout]
    }

    /// `cols = im2col(x)`, `Z = b + cols·W` (bias broadcast first, the GEMM accumulates), then
    /// `y = act(Z)` into the interior of the bordered output ([`Kernel::Im2col`]), with `g` the
    /// input's geometry.
    fn forward_im2col(&mut self, g: ConvGeom, x: &Tensor<T>) {
        let n = x.batch();
        let (m, k) = (self.rows(n), g.patch_len());
        self.cols.resize(m * k, T::zero());
        im2col(&g, n, x.data(), &mut self.cols);
        self.z.resize(m * g.cout, T::zero());
        for row in self.z.chunks_exact_mut(g.cout) {
            row.copy_from_slice(self.params[1].value.data());
        }
        gemm(
            Op::N,
            Op::N,
            m,
            g.cout,
            k,
            T::one(),
            &self.cols,
            self.params[0].value.data(),
            T::one(),
            &mut self.z,
        );
        self.border
            .interior_offsets(n, g.oh, g.ow, g.cout, &mut self.out_rows);
        let y = self.y.data_mut();
        for (zrow, &at) in self.z.chunks_exact(g.cout).zip(&self.out_rows) {
            for (yv, &zv) in y[at..at + g.cout].iter_mut().zip(zrow) {
                *yv = if self.relu { zv.max(T::zero()) } else { zv };
            }
        }
    }

    /// `dW += colsᵀ·dZ` and `dX = col2im(dZ·Wᵀ)` by GEMMs ([`Kernel::Im2col`]), with `g` the
    /// input's geometry. `dz` is `[N·OH·OW, Cout]`.
    fn backward_im2col(&mut self, g: ConvGeom, dz: &[T], n: usize, need_dx: bool) {
        let (m, k) = (self.rows(n), g.patch_len());
        assert_eq!(
            self.cols.len(),
            m * k,
            "{}: backward without forward",
            self.name
        );
        let gw = self.params[0].grad.data_mut();
        gemm(
            Op::T,
            Op::N,
            k,
            g.cout,
            m,
            T::one(),
            &self.cols,
            dz,
            T::one(),
            gw,
        );
        if need_dx {
            self.dcols.resize(m * k, T::zero());
            gemm(
                Op::N,
                Op::T,
                m,
                k,
                g.cout,
                T::one(),
                dz,
                self.params[0].value.data(),
                T::zero(),
                &mut self.dcols,
            );
            self.dx.set_shape(&[n, g.h, g.w, g.cin]);
            col2im(&g, n, &self.dcols, self.dx.data_mut());
            self.zero_input_border(g, n, true);
        }
    }

    /// `dZ = dY ⊙ [y > 0]` over the interior of `dY` (or just the interior, without a ReLU),
    /// into `self.z` as `[N·OH·OW, Cout]`; `false` (and nothing done) when `dZ` is `dY` itself.
    fn pre_activation_grad(&mut self, dy: &Tensor<T>) -> bool {
        if !self.relu && self.border.is_none() {
            return false;
        }
        let (g, n) = (self.geom, dy.batch());
        // Offsets of one image's pixels inside its bordered output; images in parallel.
        self.border
            .interior_offsets(1, g.oh, g.ow, g.cout, &mut self.out_rows);
        self.z.resize(self.rows(n) * g.cout, T::zero());
        let (c, relu, at) = (g.cout, self.relu, &self.out_rows);
        let (hb, wb) = self.border.around(g.oh, g.ow);
        self.z
            .par_chunks_mut(g.out_pixels() * c)
            .zip(dy.data().par_chunks(hb * wb * c))
            .zip(self.y.data().par_chunks(hb * wb * c))
            .for_each(|((z, dy), y)| mask_rows(z, dy, y, at, c, relu));
        true
    }

    /// Zeroes the border places of `y` (the kernels write only the interior) in the images
    /// not zeroed before (see the `y_clean` field).
    fn zero_border(&mut self, n: usize) {
        let g = self.geom;
        if n > self.y_clean {
            let (hb, wb) = self.border.around(g.oh, g.ow);
            let rest = &mut self.y.data_mut()[self.y_clean * hb * wb * g.cout..];
            self.border.zero(rest, n - self.y_clean, g.oh, g.ow, g.cout);
            self.y_clean = n;
        }
    }

    /// Zeroes the input border's places of `dX` (input geometry `g`) in the images not zeroed before, or in all `n`
    /// if `overwritten` (a path that wrote every place of `dX`).
    fn zero_input_border(&mut self, g: ConvGeom, n: usize, overwritten: bool) {
        let b = self.in_border;
        let (h, w) = (g.h - b.top - b.bottom, g.w - b.left - b.right);
        if overwritten || self.dx_clean.1 != (g.h, g.w) {
            self.dx_clean = (0, (g.h, g.w));
        }
        let clean = self.dx_clean.0;
        if n > clean {
            let rest = &mut self.dx.data_mut()[clean * g.h * g.w * g.cin..];
            b.zero(rest, n - clean, h, w, g.cin);
            self.dx_clean.0 = n;
        }
    }
}

avx512_twin! {
    /// `dZ` row by row for one image (see [`Conv2d::pre_activation_grad`]): row `m` of `z` is
    /// `dY`'s pixel at `at[m]`, times `[y > 0]` if `relu`. A function of its own compiled for
    /// AVX-512 ([`avx512_twin`]): a closure handed to [`crate::tensor::vectorized`] is not always
    /// inlined into it (this loop was, and ran 4 lanes wide at 3% of a train step).
    fn mask_rows<T: Float>(z: &mut [T], dy: &[T], y: &[T], at: &[usize], c: usize, relu: bool) {
        for (dz, &o) in z.chunks_exact_mut(c).zip(at) {
            let (d, yv) = (&dy[o..o + c], &y[o..o + c]);
            if relu {
                // A select, not a branch: the sign of `y` is a coin flip.
                for ((dz, &d), &yv) in dz.iter_mut().zip(d).zip(yv) {
                    *dz = if yv > T::zero() { d } else { T::zero() };
                }
            } else {
                dz.copy_from_slice(d);
            }
        }
    }
}

impl<T: Float> Layer<T> for Conv2d<T> {
    fn name(&self) -> &str {
        &self.name
    }

    fn output_shape(&self) -> Vec<usize> {
        self.out_shape(1)[1..].to_vec()
    }

    /// `y = border(act(b + im2col(x)·W))`, by the kernel the plan picks for this batch
    /// (im2col and one GEMM on the portable path).
    ///
    /// The input may also arrive already padded (see [`Conv2d::input_geometry`]).
    fn forward(&mut self, x: &Tensor<T>) {
        let g = self.input_geometry(x);
        assert_eq!(
            x.shape()[1..],
            [g.h, g.w, g.cin],
            "{}: input shape",
            self.name
        );
        let n = x.batch();
        self.y.set_shape(&self.out_shape(n));
        match plan::conv::<T>(&g, n, self.winograd, self.in_border, self.precision).forward() {
            Kernel::Im2col => self.forward_im2col(g, x),
            fast => self.forward_fast(g, x, fast),
        }
        self.zero_border(n);
    }

    /// With [`Conv2d::with_background_inference`], one image of which few pixels differ from
    /// the background: its response plus the difference's ([`crate::tensor::Background`]).
    /// With [`Conv2d::with_sparse_inference`], an input of which few values are nonzero: the
    /// sum over those only ([`crate::tensor::SparseConv`]). Otherwise [`Layer::forward`]. The
    /// shares are the plan's ([`plan::BACKGROUND_MAX_DIFFERING`], [`plan::sparse_share`]).
    fn infer(&mut self, x: &Tensor<T>) {
        if plan::background(self.background, x.batch()) && self.infer_background(x) {
            plan::ran(Product::ConvInfer, Kernel::Background);
            return;
        }
        if self.sparse && self.infer_sparse(self.input_geometry(x), x) {
            plan::ran(Product::ConvInfer, Kernel::Sparse);
            return;
        }
        self.forward(x);
        if let Some(k) = plan::last(Product::ConvForward) {
            plan::ran(Product::ConvInfer, k);
        }
    }

    fn output(&self) -> &Tensor<T> {
        &self.y
    }

    /// With `Z = cols·W + b` (`M = N·OH·OW` rows, `K = KH·KW·Cin`) and `dZ` the interior of `dY`
    /// times `[y > 0]` when there is a ReLU (border places are constants: no gradient):
    /// - `dW += colsᵀ·dZ` (`[K, M]·[M, Cout]`): each weight meets every input value it multiplied;
    /// - `db += Σ_rows dZ`;
    /// - `dcols = dZ·Wᵀ` (`[M, Cout]·[Cout, K]`), then `dX = col2im(dcols)`: an input pixel that
    ///   appears in several patches (overlapping windows) collects the gradient of each.
    ///
    /// For an input that arrived already padded, `dX` is the gradient with respect to it, border
    /// places included (the VALID convolution's).
    fn backward(&mut self, x: &Tensor<T>, dy: &Tensor<T>, need_dx: bool) {
        let g = self.input_geometry(x);
        let n = dy.batch();
        assert_eq!(
            dy.shape(),
            self.out_shape(n),
            "{}: upstream gradient shape",
            self.name
        );
        assert_eq!(x.shape()[1..], [g.h, g.w, g.cin], "{}: input", self.name);
        // dZ lives in `self.z` (taken out for the products, put back: no allocation) or is dY.
        let own = self.pre_activation_grad(dy);
        let z = std::mem::take(&mut self.z);
        let dz = if own { &z[..] } else { dy.data() };
        // db += Σ_rows dZ (the same on every path).
        let gb = self.params[1].grad.data_mut();
        for row in dz.chunks_exact(g.cout) {
            for (g, &d) in gb.iter_mut().zip(row) {
                *g += d;
            }
        }
        let plan = plan::conv::<T>(&g, n, self.winograd, self.in_border, self.precision);
        match plan.weight_grad() {
            Kernel::Im2col => {
                if need_dx {
                    plan.input_grad();
                }
                self.backward_im2col(g, dz, n, need_dx)
            }
            _ => self.backward_fast(g, x, dz, plan, need_dx),
        }
        self.z = z;
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
        self.geom.macs()
    }

    fn set_precision(&mut self, precision: Precision) {
        self.precision = precision;
    }
}
