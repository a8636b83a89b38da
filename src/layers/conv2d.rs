//! 2-D convolution (NHWC, HWIO filters, TensorFlow's SAME/VALID padding).

use super::{Layer, Param};
use crate::tensor::{
    col2im, fill_iota, gemm, im2col, pad_input, unpad_input, ConvGeom, Float, GatherGemm, Init, Op,
    ScatterGemm, Tensor,
};

/// `y = conv(x, W) + b`: see [`crate::tensor::ConvGeom`] for the defining sum and the shapes.
///
/// Formulation: im2col + GEMM. The input is unrolled into `cols[N·OH·OW, KH·KW·Cin]` (kept for the
/// backward pass), and `Y[N·OH·OW, Cout] = cols · W[KH·KW·Cin, Cout] + b` is a single matrix
/// product whose result is already the NHWC output.
///
/// Where [`Float::simd`] (f32 on AVX-512), the same products run as gather GEMMs
/// ([`crate::tensor::GatherGemm`]) on a zero-padded copy of the input instead: no im2col matrix is
/// written (16x the input for conv1, 21 MB at batch 48), the forward product starts from the
/// bias, and the weight gradient reduces over all output pixels straight from the padded input.
/// The input gradient `dY·Wᵀ` (with `Wᵀ` packed) is added tile by tile straight onto a padded
/// input gradient ([`crate::tensor::ScatterGemm`], col2im fused), whose interior is then `dX`.
pub struct Conv2d<T> {
    name: String,
    /// The geometry (input and output sizes, strides, padding).
    pub geom: ConvGeom,
    /// `[weight [KH, KW, Cin, Cout], bias [Cout]]` with their gradients.
    pub params: [Param<T>; 2],
    /// `[N·OH·OW, KH·KW·Cin]`, from the last forward pass.
    cols: Vec<T>,
    /// `[N·OH·OW, KH·KW·Cin]`, scratch for the input gradient.
    dcols: Vec<T>,
    y: Tensor<T>,
    dx: Tensor<T>,
    /// Fast path: the zero-padded input of the last forward pass, `[N, HP, WP, Cin]`.
    xpad: Vec<T>,
    /// Fast path: where each output pixel's window starts in `xpad`, and each patch element's
    /// offset from there.
    pixels: Vec<usize>,
    patch: Vec<usize>,
    /// Fast path, input gradient: `m·Cout` per output pixel, `0..Cout`, and `Wᵀ` `[Cout, K]`.
    dy_rows: Vec<usize>,
    iota: Vec<usize>,
    wt: Vec<T>,
    /// Fast path: the input gradient with respect to `xpad`.
    dxpad: Vec<T>,
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
            cols: Vec::new(),
            dcols: Vec::new(),
            y: Tensor::empty(),
            dx: Tensor::empty(),
            xpad: Vec::new(),
            pixels: Vec::new(),
            patch: Vec::new(),
            dy_rows: Vec::new(),
            iota: Vec::new(),
            wt: Vec::new(),
            dxpad: Vec::new(),
        }
    }

    fn rows(&self, n: usize) -> usize {
        n * self.geom.out_pixels()
    }

    /// The backward pass by gather GEMMs (see the type's documentation); same products as
    /// [`Layer::backward`]'s im2col path.
    fn backward_gather(&mut self, dy: &Tensor<T>, need_dx: bool) {
        let g = self.geom;
        let n = dy.batch();
        let (m, k) = (self.rows(n), g.patch_len());
        assert_eq!(
            self.pixels.len(),
            m,
            "{}: backward without forward",
            self.name
        );
        // dW[k, co] += Σ_m xpad[pixels[m] + patch[k]] · dY[m, co]
        T::gather_gemm(GatherGemm {
            a: &self.xpad,
            p: &self.patch,
            q: &self.pixels,
            b: dy.data(),
            ldb: g.cout,
            n: g.cout,
            c: self.params[0].grad.data_mut(),
            ldc: g.cout,
            init: Init::Accumulate,
        });
        let gb = self.params[1].grad.data_mut();
        for row in dy.data().chunks_exact(g.cout) {
            for (g, &d) in gb.iter_mut().zip(row) {
                *g += d;
            }
        }
        if need_dx {
            // dcols[m, k] = Σ_co dY[m, co] · Wᵀ[co, k]
            let w = self.params[0].value.data();
            self.wt.resize(k * g.cout, T::zero());
            for (kk, wrow) in w.chunks_exact(g.cout).enumerate() {
                for (co, &v) in wrow.iter().enumerate() {
                    self.wt[co * k + kk] = v;
                }
            }
            fill_iota(&mut self.dy_rows, m, g.cout);
            fill_iota(&mut self.iota, g.cout, 1);
            // dxpad[pixels[m] + patch[k]] += dcols[m, k], image by image (col2im fused).
            self.dxpad.clear();
            self.dxpad.resize(self.xpad.len(), T::zero());
            T::scatter_gemm(ScatterGemm {
                a: dy.data(),
                p: &self.dy_rows,
                q: &self.iota,
                b: &self.wt,
                ldb: k,
                n: k,
                out: &mut self.dxpad,
                out_rows: &self.pixels,
                out_cols: &self.patch,
                groups: n,
            });
            self.dx.set_shape(&[n, g.h, g.w, g.cin]);
            unpad_input(&g, n, &self.dxpad, self.dx.data_mut());
        }
    }
}

impl<T: Float> Layer<T> for Conv2d<T> {
    fn name(&self) -> &str {
        &self.name
    }

    fn output_shape(&self) -> Vec<usize> {
        vec![self.geom.oh, self.geom.ow, self.geom.cout]
    }

    /// `cols = im2col(x)`, then `Y = b + cols·W` (bias broadcast first, GEMM accumulates).
    fn forward(&mut self, x: &Tensor<T>) {
        let g = self.geom;
        assert_eq!(
            x.shape()[1..],
            [g.h, g.w, g.cin],
            "{}: input shape",
            self.name
        );
        let n = x.batch();
        let (m, k) = (self.rows(n), g.patch_len());
        if T::simd() {
            pad_input(&g, n, x.data(), &mut self.xpad);
            g.gather_offsets(n, &mut self.pixels, &mut self.patch);
            self.y.set_shape(&[n, g.oh, g.ow, g.cout]);
            T::gather_gemm(GatherGemm {
                a: &self.xpad,
                p: &self.pixels,
                q: &self.patch,
                b: self.params[0].value.data(),
                ldb: g.cout,
                n: g.cout,
                c: self.y.data_mut(),
                ldc: g.cout,
                init: Init::Bias(self.params[1].value.data()),
            });
            return;
        }
        self.cols.resize(m * k, T::zero());
        im2col(&g, n, x.data(), &mut self.cols);
        self.y.set_shape(&[n, g.oh, g.ow, g.cout]);
        let y = self.y.data_mut();
        for row in y.chunks_exact_mut(g.cout) {
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
            y,
        );
    }

    fn output(&self) -> &Tensor<T> {
        &self.y
    }

    /// With `Y = cols·W + b` (`M = N·OH·OW` rows, `K = KH·KW·Cin`):
    /// - `dW += colsᵀ·dY` (`[K, M]·[M, Cout]`): each weight meets every input value it multiplied;
    /// - `db += Σ_rows dY`;
    /// - `dcols = dY·Wᵀ` (`[M, Cout]·[Cout, K]`), then `dX = col2im(dcols)`: an input pixel that
    ///   appears in several patches (overlapping windows) collects the gradient of each.
    fn backward(&mut self, _x: &Tensor<T>, dy: &Tensor<T>, need_dx: bool) {
        let g = self.geom;
        let n = dy.batch();
        assert_eq!(
            dy.shape(),
            [n, g.oh, g.ow, g.cout],
            "{}: upstream gradient shape",
            self.name
        );
        let (m, k) = (self.rows(n), g.patch_len());
        if T::simd() {
            self.backward_gather(dy, need_dx);
            return;
        }
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
            dy.data(),
            T::one(),
            gw,
        );
        let gb = self.params[1].grad.data_mut();
        for row in dy.data().chunks_exact(g.cout) {
            for (g, &d) in gb.iter_mut().zip(row) {
                *g += d;
            }
        }
        if need_dx {
            self.dcols.resize(m * k, T::zero());
            gemm(
                Op::N,
                Op::T,
                m,
                k,
                g.cout,
                T::one(),
                dy.data(),
                self.params[0].value.data(),
                T::zero(),
                &mut self.dcols,
            );
            self.dx.set_shape(&[n, g.h, g.w, g.cin]);
            col2im(&g, n, &self.dcols, self.dx.data_mut());
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
        self.geom.macs()
    }
}
