//! 2-D convolution (NHWC, HWIO filters, TensorFlow's SAME/VALID padding), with an optional fused
//! ReLU and an optional zero border written around the output.
//!
//! This file is the maths: the layer's parameters and geometry, and its forward and backward
//! passes, each beside its derivation. Each product is one call to [`crate::ops::ConvOps`],
//! which runs it by the kernel [`crate::ops::plan::conv`] picks for the shape, batch, precision
//! and CPU (im2col + GEMM, the reference; gather GEMMs, Winograd, the sparse and background
//! products for acting).

use super::init::VarianceScaling;
use super::{Core, Layer, Param};
use crate::ops::{ConvOps, ConvSpec, Precision};
use crate::tensor::{Border, ConvGeom, Float, Tensor};

/// `y = border(act(conv(x, W) + b))`: see [`crate::tensor::ConvGeom`] for the defining sum and
/// the shapes; `act` is the identity or, [`Conv2d::with_relu`], `max(·, 0)`; `border` writes zero
/// rows and columns around each output image, [`Conv2d::with_border`].
///
/// Formulation: im2col + GEMM. The input is unrolled into `cols[N·OH·OW, KH·KW·Cin]` (kept for the
/// backward pass), and `Z[N·OH·OW, Cout] = cols · W[KH·KW·Cin, Cout] + b` is a single matrix
/// product whose result is already the NHWC output. The gradients are two more products:
/// `dW += colsᵀ·dZ` and `dX = col2im(dZ·Wᵀ)` ([`Layer::backward`]).
///
/// The same products may run by other kernels, chosen by [`crate::ops::plan::conv`] (f32 with
/// AVX-512 or AVX2: gather GEMMs that write no im2col matrix; Winograd's minimal filtering,
/// [`Conv2d::with_winograd`]), and acting by sparse ones ([`Conv2d::with_sparse_inference`],
/// [`Conv2d::with_background_inference`]).
///
/// The fused ReLU and the border are what a separate [`super::Relu`] layer and the next layer's
/// padding would otherwise do, each a pass over the whole activation: at batch 48 that is about
/// 11 MB of memory traffic per forward pass of the article's network.
pub struct Conv2d<T> {
    /// The name, output `y` and input gradient `dX` ([`Core`]).
    core: Core<T>,
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
    /// `[N·OH·OW, Cout]`: `dZ`, the gradient with respect to the product before the ReLU and
    /// the border (when there is either; else `dZ` is `dY`).
    dz: Vec<T>,
    /// The products' kernels and their buffers.
    ops: ConvOps<T>,
}

impl<T: Float> Conv2d<T> {
    /// A convolution that starts ready to train: weights drawn by [`VarianceScaling::HE`] (the
    /// article's He initialiser) from [`super::init::named_rng`] of its name, bias zero. Draw
    /// them from your own generator with [`Conv2d::init`].
    pub fn new(name: &str, geom: ConvGeom) -> Self {
        let wshape = [geom.kh, geom.kw, geom.cin, geom.cout];
        Conv2d {
            core: Core::new(name),
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
            dz: Vec::new(),
            ops: ConvOps::new(name),
        }
        .init(&VarianceScaling::HE, &mut super::init::named_rng(name))
    }

    /// Draws the weights again by `init` from `rng`, and zeroes the bias.
    pub fn init(mut self, init: &VarianceScaling, rng: &mut impl rand::Rng) -> Self {
        init.fill(&mut self.params[0].value, rng);
        self.params[1].value.fill_zero();
        self
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
        self.ops = ConvOps::new(&self.core.name);
        self
    }

    /// Declares which places of the input are the previous layer's zero border (interior
    /// `(H − top − bottom) × (W − left − right)`): their gradient is left out (zeros in `dX`).
    pub fn with_input_border(mut self, border: Border) -> Self {
        assert!(
            border.top + border.bottom < self.geom.h && border.left + border.right < self.geom.w,
            "{}: input border larger than the input",
            self.core.name
        );
        self.in_border = border;
        self.ops = ConvOps::new(&self.core.name);
        self
    }

    /// Lets the plan run the training products by Winograd's minimal filtering
    /// ([`crate::tensor::winograd_conv`]) where the filter shape has one
    /// ([`plan::winograd_kind`](crate::ops::plan::winograd_kind): 3×3 stride 1, or `2s × 2s` stride `s`) and the batch is large
    /// enough ([`plan::WINOGRAD_MIN_BATCH`](crate::ops::plan::WINOGRAD_MIN_BATCH)); see [`plan::conv`](crate::ops::plan::conv) for which products and what
    /// it measured. The same sums, rounded differently. Off by default;
    /// [`crate::dqn::article_qnet`] turns it on where [`plan::winograd_pays`](crate::ops::plan::winograd_pays) (conv2, conv3).
    pub fn with_winograd(mut self, on: bool) -> Self {
        self.winograd = on;
        self
    }

    /// Acts ([`Layer::infer`]) by a product over the input's nonzero values only
    /// ([`crate::tensor::SparseConv`]) when few are nonzero ([`plan::sparse_share`](crate::ops::plan::sparse_share)): for a layer
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
    /// frames; if too many pixels differ ([`plan::BACKGROUND_MAX_DIFFERING`](crate::ops::plan::BACKGROUND_MAX_DIFFERING)), the dense
    /// product. Off by default; [`crate::dqn::article_qnet`] turns it on for conv1.
    pub fn with_background_inference(mut self, on: bool) -> Self {
        self.background = on;
        self
    }

    /// The geometry for input `x`: the layer's own, or, when `x` arrives already padded, the
    /// same convolution as a VALID one over it ([`ConvSpec::for_input`]).
    pub fn input_geometry(&self, x: &Tensor<T>) -> ConvGeom {
        self.spec().for_input(x).geom
    }

    /// The layer's options, as its products take them.
    fn spec(&self) -> ConvSpec {
        ConvSpec {
            geom: self.geom,
            relu: self.relu,
            border: self.border,
            in_border: self.in_border,
            winograd: self.winograd,
            sparse: self.sparse,
            background: self.background,
            precision: self.precision,
        }
    }
}

impl<T: Float> Layer<T> for Conv2d<T> {
    fn core(&self) -> &Core<T> {
        &self.core
    }

    fn output_shape(&self) -> Vec<usize> {
        self.spec().out_shape(1)[1..].to_vec()
    }

    /// `y = border(act(b + im2col(x)·W))`: `Z[N·OH·OW, Cout] = cols · W[KH·KW·Cin, Cout] + b`,
    /// with `cols = im2col(x)` the input unrolled into one patch per output pixel, then the
    /// ReLU and the border. The input may also arrive already padded
    /// ([`Conv2d::input_geometry`]).
    fn forward(&mut self, x: &Tensor<T>) {
        let [w, b] = &self.params;
        let (w, b) = (w.value.data(), b.value.data());
        self.ops.forward(&self.spec(), x, w, b, &mut self.core.y);
    }

    /// The same `y`, for acting: with [`Conv2d::with_background_inference`] one image as a
    /// constant background's response plus its sparse difference's
    /// ([`crate::tensor::Background`]); with [`Conv2d::with_sparse_inference`] the sum over the
    /// input's nonzero values only ([`crate::tensor::SparseConv`]); where those do not pay,
    /// [`Layer::forward`].
    fn infer(&mut self, x: &Tensor<T>) {
        let [w, b] = &self.params;
        let (w, b) = (w.value.data(), b.value.data());
        self.ops.infer(&self.spec(), x, w, b, &mut self.core.y);
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
        let s = self.spec();
        let g = s.for_input(x).geom;
        let n = dy.batch();
        assert_eq!(
            dy.shape(),
            s.out_shape(n),
            "{}: upstream gradient",
            self.core.name
        );
        assert_eq!(
            x.shape()[1..],
            [g.h, g.w, g.cin],
            "{}: input",
            self.core.name
        );
        // dZ = dY ⊙ [y > 0] over the interior (or dY itself, without a ReLU and a border).
        let own = self.ops.relu_grad(&s, dy, &self.core.y, &mut self.dz);
        let dz = if own { &self.dz[..] } else { dy.data() };
        let [w, b] = &mut self.params;
        // db += Σ_rows dZ
        let db = b.grad.data_mut();
        for row in dz.chunks_exact(g.cout) {
            for (g, &d) in db.iter_mut().zip(row) {
                *g += d;
            }
        }
        // dW += colsᵀ·dZ
        self.ops.weight_grad(&s, x, dz, w.grad.data_mut());
        // dX = col2im(dZ·Wᵀ)
        if need_dx {
            self.ops
                .input_grad(&s, x, dz, w.value.data(), &mut self.core.dx);
        }
    }

    fn visit_params<'a>(&'a self, f: &mut dyn FnMut(&'a Param<T>)) {
        self.params.iter().for_each(f);
    }

    fn visit_params_mut<'a>(&'a mut self, f: &mut dyn FnMut(&'a mut Param<T>)) {
        self.params.iter_mut().for_each(f);
    }

    fn macs(&self) -> usize {
        self.geom.macs()
    }

    fn set_precision(&mut self, precision: Precision) {
        self.precision = precision;
    }
}
