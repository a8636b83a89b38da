//! A convolution's products, each by the kernel the [`plan`](crate::ops::plan) picks.
//!
//! [`crate::layers::Conv2d`] holds the maths and calls one function here per product:
//! [`ConvOps::forward`] (`y = border(act(b + conv(x, W)))`), [`ConvOps::infer`] (the same `y` for
//! acting), [`ConvOps::relu_grad`] (`dZ`), [`ConvOps::weight_grad`] (`dW += colsᵀ·dZ`) and
//! [`ConvOps::input_grad`] (`dX = col2im(dZ·Wᵀ)`). Each matches the plan's kernel once. The
//! reference formulation, im2col + GEMM, is written out in this file ([`Kernel::Im2col`], what
//! the f64 gradient checks run); the fast kernels (gather GEMMs, Winograd, the stride phases, the
//! sparse and background products) are in `fast.rs` and compute the same products.

mod fast;

use crate::ops::plan::{self, ConvPlan, Kernel, Precision, Product};
use crate::tensor::cpu::avx512_twin;
use crate::tensor::{col2im, gemm, im2col, Border, ConvGeom, Float, Op, Tensor};
use rayon::prelude::*;

/// What a convolution's products need besides their operands: the layer's geometry and options.
#[derive(Clone, Copy, Debug)]
pub struct ConvSpec {
    /// The layer's geometry ([`ConvSpec::for_input`] gives the one its input is read by).
    pub geom: ConvGeom,
    /// `max(·, 0)` fused into the forward product.
    pub relu: bool,
    /// The zero border written around each output image.
    pub border: Border,
    /// The input's border places (written by the layer before): constants, whose gradient is
    /// not computed (zeros in `dX`).
    pub in_border: Border,
    /// Whether the plan may run the training products by Winograd's minimal filtering.
    pub winograd: bool,
    /// Whether acting may take the sum over the input's nonzero values only.
    pub sparse: bool,
    /// Whether acting on one image may split it into a background and its difference.
    pub background: bool,
    /// The training products' arithmetic.
    pub precision: Precision,
}

impl ConvSpec {
    /// The spec for input `x`: the layer's own, or, when `x` arrives already padded (`[N, HP,
    /// WP, Cin]`, [`ConvGeom::padded`], with a zero border: e.g. a replay batch written that
    /// way), the same convolution as a VALID one over it ([`ConvGeom::as_valid`]), which reads
    /// it in place instead of copying it into a padded buffer. `SAME(x) = VALID(pad(x))` and
    /// both read the same padded layout, so the results are bit-identical.
    pub fn for_input<T: Float>(&self, x: &Tensor<T>) -> ConvSpec {
        let g = self.geom;
        let (hp, wp) = g.padded();
        if !g.reads_input_directly() && x.shape().len() == 4 && x.shape()[1..] == [hp, wp, g.cin] {
            ConvSpec {
                geom: g.as_valid().0,
                ..*self
            }
        } else {
            *self
        }
    }

    /// The bordered output's shape for a batch of `n`.
    pub fn out_shape(&self, n: usize) -> [usize; 4] {
        let (hb, wb) = self.border.around(self.geom.oh, self.geom.ow);
        [n, hb, wb, self.geom.cout]
    }

    /// The kernels of the training products for a batch of `n`.
    fn plan<T: Float>(&self, n: usize) -> ConvPlan {
        plan::conv::<T>(&self.geom, n, self.winograd, self.in_border, self.precision)
    }

    /// Output rows `M = N·OH·OW` of a batch of `n`.
    fn rows(&self, n: usize) -> usize {
        n * self.geom.out_pixels()
    }
}

/// The buffers of a convolution's kernels, reused from call to call: nothing allocates after
/// the first pass at the largest batch.
pub struct ConvOps<T> {
    /// The layer's name, for messages.
    name: String,
    /// `[N·OH·OW, KH·KW·Cin]`, from the last forward pass by im2col.
    cols: Vec<T>,
    /// `[N·OH·OW, KH·KW·Cin]`, scratch for the input gradient by im2col.
    dcols: Vec<T>,
    /// `[N·OH·OW, Cout]`: the im2col forward product before the ReLU and the border.
    z: Vec<T>,
    /// Where each output pixel starts in the bordered output.
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

impl<T: Float> ConvOps<T> {
    /// Empty buffers for the layer `name`.
    pub fn new(name: &str) -> Self {
        ConvOps {
            name: name.to_string(),
            cols: Vec::new(),
            dcols: Vec::new(),
            z: Vec::new(),
            out_rows: Vec::new(),
            y_clean: 0,
            dx_clean: (0, (0, 0)),
            fast: fast::Scratch::default(),
        }
    }

    /// `y = border(act(b + conv(x, W)))` into `y` (sized here), by the plan's forward kernel:
    /// `w` is `[KH, KW, Cin, Cout]`, `b` is `[Cout]`.
    pub fn forward(&mut self, s: &ConvSpec, x: &Tensor<T>, w: &[T], b: &[T], y: &mut Tensor<T>) {
        let s = s.for_input(x);
        let g = s.geom;
        assert_eq!(
            x.shape()[1..],
            [g.h, g.w, g.cin],
            "{}: input shape",
            self.name
        );
        let n = x.batch();
        y.set_shape(&s.out_shape(n));
        match s.plan::<T>(n).forward() {
            Kernel::Im2col => self.forward_im2col(&s, x, w, b, y),
            Kernel::Gather => self.forward_gather(&s, x, w, b, y),
            Kernel::GatherBf16 => self.forward_bf16(&s, x, w, b, y),
            Kernel::Winograd(kind) => self.forward_winograd(&s, x, kind, w, b, y, false),
            Kernel::WinogradBf16(kind) => self.forward_winograd(&s, x, kind, w, b, y, true),
            k => unreachable!("{k:?} computes no forward product"),
        }
        self.zero_border(&s, n, y);
    }

    /// The forward pass for acting: with `s.background`, one image of which few pixels differ
    /// from the background, as its response plus the difference's
    /// ([`crate::tensor::Background`]); with `s.sparse`, an input of which few values are nonzero,
    /// as the sum over those only ([`crate::tensor::SparseConv`]); otherwise
    /// [`ConvOps::forward`]. The shares are the plan's ([`plan::BACKGROUND_MAX_DIFFERING`],
    /// [`plan::sparse_share`]).
    pub fn infer(&mut self, s: &ConvSpec, x: &Tensor<T>, w: &[T], b: &[T], y: &mut Tensor<T>) {
        if plan::background(s.background, x.batch()) && self.infer_background(s, x, w, b, y) {
            plan::ran(Product::ConvInfer, Kernel::Background);
            return;
        }
        if s.sparse && self.infer_sparse(&s.for_input(x), x, w, b, y) {
            plan::ran(Product::ConvInfer, Kernel::Sparse);
            return;
        }
        self.forward(s, x, w, b, y);
        if let Some(k) = plan::last(Product::ConvForward) {
            plan::ran(Product::ConvInfer, k);
        }
    }

    /// `dZ = dY ⊙ [y > 0]` over the interior of `dY` (or just the interior, without a ReLU),
    /// into `dz` as `[N·OH·OW, Cout]`; `false` (and nothing done) when `dZ` is `dY` itself.
    pub fn relu_grad(
        &mut self, s: &ConvSpec, dy: &Tensor<T>, y: &Tensor<T>, dz: &mut Vec<T>,
    ) -> bool {
        if !s.relu && s.border.is_none() {
            return false;
        }
        let (g, n) = (s.geom, dy.batch());
        // Offsets of one image's pixels inside its bordered output; images in parallel.
        s.border
            .interior_offsets(1, g.oh, g.ow, g.cout, &mut self.out_rows);
        dz.resize(s.rows(n) * g.cout, T::zero());
        let (c, relu, at) = (g.cout, s.relu, &self.out_rows);
        let (hb, wb) = s.border.around(g.oh, g.ow);
        dz.par_chunks_mut(g.out_pixels() * c)
            .zip(dy.data().par_chunks(hb * wb * c))
            .zip(y.data().par_chunks(hb * wb * c))
            .for_each(|((z, dy), y)| mask_rows(z, dy, y, at, c, relu));
        true
    }

    /// `dW += colsᵀ·dZ` for the input `x` of the last forward pass, by the plan's weight
    /// gradient kernel: `dz` is `[N·OH·OW, Cout]`, `dw` is `[KH, KW, Cin, Cout]`.
    pub fn weight_grad(&mut self, s: &ConvSpec, x: &Tensor<T>, dz: &[T], dw: &mut [T]) {
        let s = s.for_input(x);
        let plan = s.plan::<T>(x.batch());
        match plan.weight_grad() {
            Kernel::Im2col => self.wgrad_im2col(&s, x.batch(), dz, dw),
            Kernel::Gather => self.wgrad_gather(&s, x, dz, dw),
            Kernel::GatherBf16 => self.wgrad_bf16(&s, x, dz, dw, plan.planned_forward()),
            Kernel::Winograd(kind) => self.wgrad_winograd(&s, x, kind, dz, dw, false),
            Kernel::WinogradBf16(kind) => self.wgrad_winograd(&s, x, kind, dz, dw, true),
            k => unreachable!("{k:?} computes no weight gradient"),
        }
    }

    /// `dX = col2im(dZ·Wᵀ)` into `dx` (sized here, zeros at the input border's places), by the
    /// plan's input gradient kernel. For an input that arrived already padded, `dX` is the
    /// gradient with respect to it, border places included (the VALID convolution's).
    pub fn input_grad(
        &mut self, s: &ConvSpec, x: &Tensor<T>, dz: &[T], w: &[T], dx: &mut Tensor<T>,
    ) {
        let s = s.for_input(x);
        let (g, n) = (s.geom, x.batch());
        dx.set_shape(&[n, g.h, g.w, g.cin]);
        let kernel = s.plan::<T>(n).input_grad();
        match kernel {
            Kernel::Im2col => self.dx_im2col(&s, n, dz, w, dx),
            Kernel::Winograd(kind) => self.dx_winograd(&s, n, kind, dz, w, dx, false),
            Kernel::WinogradBf16(kind) => self.dx_winograd(&s, n, kind, dz, w, dx, true),
            Kernel::Phases => self.dx_by_phases(&s, n, dz, w, dx, false),
            Kernel::PhasesBf16 => self.dx_by_phases(&s, n, dz, w, dx, true),
            Kernel::Scatter => self.dx_by_scatter(&s, n, dz, w, dx),
            k => unreachable!("{k:?} computes no input gradient"),
        }
        // The im2col and scatter kernels write every place of dX, the others the interior only.
        let overwritten = matches!(kernel, Kernel::Im2col | Kernel::Scatter);
        self.zero_input_border(&s, n, dx, overwritten);
    }

    /// `cols = im2col(x)`, `Z = b + cols·W` (bias broadcast first, the GEMM accumulates), then
    /// `y = act(Z)` into the interior of the bordered output.
    fn forward_im2col(&mut self, s: &ConvSpec, x: &Tensor<T>, w: &[T], b: &[T], y: &mut Tensor<T>) {
        let (g, n) = (s.geom, x.batch());
        let (m, k) = (s.rows(n), g.patch_len());
        self.cols.resize(m * k, T::zero());
        im2col(&g, n, x.data(), &mut self.cols);
        self.z.resize(m * g.cout, T::zero());
        for row in self.z.chunks_exact_mut(g.cout) {
            row.copy_from_slice(b);
        }
        let one = T::one();
        gemm(
            Op::N,
            Op::N,
            m,
            g.cout,
            k,
            one,
            &self.cols,
            w,
            one,
            &mut self.z,
        );
        s.border
            .interior_offsets(n, g.oh, g.ow, g.cout, &mut self.out_rows);
        let y = y.data_mut();
        for (zrow, &at) in self.z.chunks_exact(g.cout).zip(&self.out_rows) {
            for (yv, &zv) in y[at..at + g.cout].iter_mut().zip(zrow) {
                *yv = if s.relu { zv.max(T::zero()) } else { zv };
            }
        }
    }

    /// `dW += colsᵀ·dZ` (`[K, M]·[M, Cout]`) with the last forward pass's `cols`.
    fn wgrad_im2col(&mut self, s: &ConvSpec, n: usize, dz: &[T], dw: &mut [T]) {
        let (m, k) = (s.rows(n), s.geom.patch_len());
        assert_eq!(
            self.cols.len(),
            m * k,
            "{}: backward without forward",
            self.name
        );
        let one = T::one();
        gemm(
            Op::T,
            Op::N,
            k,
            s.geom.cout,
            m,
            one,
            &self.cols,
            dz,
            one,
            dw,
        );
    }

    /// `dcols = dZ·Wᵀ` (`[M, Cout]·[Cout, K]`), then `dX = col2im(dcols)`.
    fn dx_im2col(&mut self, s: &ConvSpec, n: usize, dz: &[T], w: &[T], dx: &mut Tensor<T>) {
        let g = s.geom;
        let (m, k) = (s.rows(n), g.patch_len());
        assert_eq!(
            self.cols.len(),
            m * k,
            "{}: backward without forward",
            self.name
        );
        self.dcols.resize(m * k, T::zero());
        let (one, zero) = (T::one(), T::zero());
        gemm(
            Op::N,
            Op::T,
            m,
            k,
            g.cout,
            one,
            dz,
            w,
            zero,
            &mut self.dcols,
        );
        col2im(&g, n, &self.dcols, dx.data_mut());
    }

    /// Zeroes the border places of `y` (the kernels write only the interior) in the images
    /// not zeroed before (see the `y_clean` field).
    fn zero_border(&mut self, s: &ConvSpec, n: usize, y: &mut Tensor<T>) {
        let g = s.geom;
        if n > self.y_clean {
            let (hb, wb) = s.border.around(g.oh, g.ow);
            let rest = &mut y.data_mut()[self.y_clean * hb * wb * g.cout..];
            s.border.zero(rest, n - self.y_clean, g.oh, g.ow, g.cout);
            self.y_clean = n;
        }
    }

    /// Zeroes the input border's places of `dX` (input geometry `s.geom`) in the images not
    /// zeroed before, or in all `n` if `overwritten` (a kernel that wrote every place of `dX`).
    fn zero_input_border(&mut self, s: &ConvSpec, n: usize, dx: &mut Tensor<T>, overwritten: bool) {
        let (g, b) = (s.geom, s.in_border);
        let (h, w) = (g.h - b.top - b.bottom, g.w - b.left - b.right);
        if overwritten || self.dx_clean.1 != (g.h, g.w) {
            self.dx_clean = (0, (g.h, g.w));
        }
        let clean = self.dx_clean.0;
        if n > clean {
            let rest = &mut dx.data_mut()[clean * g.h * g.w * g.cin..];
            b.zero(rest, n - clean, h, w, g.cin);
            self.dx_clean.0 = n;
        }
    }
}

avx512_twin! {
    /// `dZ` row by row for one image (see [`ConvOps::relu_grad`]): row `m` of `z` is `dY`'s
    /// pixel at `at[m]`, times `[y > 0]` if `relu`. A function of its own compiled for AVX-512
    /// ([`avx512_twin`]): a closure handed to [`crate::tensor::vectorized`] is not always
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
