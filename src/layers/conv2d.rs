//! 2-D convolution (NHWC, HWIO filters, TensorFlow's SAME/VALID padding), with an optional fused
//! ReLU and an optional zero border written around the output.

use super::{Layer, Param};
use crate::tensor::cpu::avx512_twin;
use crate::tensor::{
    col2im, fill_iota, gemm, im2col, pad_input, unpad_input, winograd_conv, winograd_filters,
    winograd_filters_s2d, winograd_filters_s2d_adjoint, winograd_wgrad, Background, Border,
    ConvGeom, Float, GatherGemm, Init, Nonzeros, Op, ScatterGemm, SparseConv, Tensor, WinogradKind,
    WinogradScratch, WinogradShape, MAX_PIECES, SKIP_OUTPUT,
};
use rayon::prelude::*;

/// `y = border(act(conv(x, W) + b))`: see [`crate::tensor::ConvGeom`] for the defining sum and
/// the shapes; `act` is the identity or, [`Conv2d::with_relu`], `max(·, 0)`; `border` writes zero
/// rows and columns around each output image, [`Conv2d::with_border`].
///
/// Formulation: im2col + GEMM. The input is unrolled into `cols[N·OH·OW, KH·KW·Cin]` (kept for the
/// backward pass), and `Z[N·OH·OW, Cout] = cols · W[KH·KW·Cin, Cout] + b` is a single matrix
/// product whose result is already the NHWC output.
///
/// Where [`Float::simd`] (f32 on AVX-512), the same products run as gather GEMMs
/// ([`crate::tensor::GatherGemm`]) on a zero-padded copy of the input instead (or on the input
/// itself when it needs no padding, e.g. when the layer before wrote the border): no im2col matrix
/// is written (16x the input for conv1, 21 MB at batch 48), the forward product starts from the
/// bias and stores `max(·, 0)` straight into the interior of the bordered output, and the weight
/// gradient reduces over all output pixels straight from the padded input. The input gradient:
/// for an input read in place, one gather GEMM per stride phase writes each `dX` value once
/// (`Conv2d::dx_by_phases`); otherwise `dZ·Wᵀ` (with `Wᵀ` packed) is added tile by tile straight
/// onto a padded input gradient ([`crate::tensor::ScatterGemm`], col2im fused), whose interior
/// is then `dX`. [`Conv2d::with_winograd`] replaces these products by Winograd's minimal
/// filtering where the shape allows it (conv2 and conv3 of the article's network, including their
/// input gradients).
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
    /// `[N·OH·OW, KH·KW·Cin]`, from the last forward pass.
    cols: Vec<T>,
    /// `[N·OH·OW, KH·KW·Cin]`, scratch for the input gradient.
    dcols: Vec<T>,
    /// `[N, OH, OW, Cout]`: the product before the ReLU and the border (portable path), then
    /// the gradient with respect to it, `dZ` (both paths, when there is a ReLU or a border).
    z: Vec<T>,
    y: Tensor<T>,
    dx: Tensor<T>,
    /// How many leading images of `y`'s buffer have their border places zeroed. Every kernel
    /// writes only the interior and the buffer never shrinks (it grows with zeros), so a border
    /// zeroed once stays zero: the train step zeroes nothing after its first call.
    y_clean: usize,
    /// The same for `dX`'s input-border places, with the input size `(H, W)` they were zeroed
    /// for (a pre-padded and a plain input lay `dX` out differently).
    dx_clean: (usize, (usize, usize)),
    /// Fast path: the zero-padded input of the last forward pass, `[N, HP, WP, Cin]`.
    xpad: Vec<T>,
    /// Fast path: where each output pixel's window starts in `xpad`, and each patch element's
    /// offset from there.
    pixels: Vec<usize>,
    patch: Vec<usize>,
    /// Where each output pixel starts in the bordered output `y`.
    out_rows: Vec<usize>,
    /// Fast path, input gradient: `m·Cout` per output pixel, `0..Cout`, and `Wᵀ` `[Cout, K]`.
    dy_rows: Vec<usize>,
    iota: Vec<usize>,
    wt: Vec<T>,
    /// Fast path: the input gradient with respect to `xpad`.
    dxpad: Vec<T>,
    /// Fast path, input gradient by phases: `dZ` inside a zero border, and one phase's row
    /// starts in it, destinations in `dX`, tap offsets and packed taps `[taps·Cout, Cin]`.
    dzpad: Vec<T>,
    ph_p: Vec<usize>,
    ph_rows: Vec<usize>,
    ph_q: Vec<usize>,
    ph_w: Vec<T>,
    /// Fast path: run the forward product and the weight gradient by Winograd's minimal
    /// filtering ([`crate::tensor::winograd_conv`], [`crate::tensor::winograd_wgrad`]), and also
    /// the input gradient of an input read in place (for blocks, one they tile exactly). `None`:
    /// the direct gather GEMMs.
    winograd: Option<WinogradKind>,
    /// Winograd: the transformed filters (`[16, I, O]`, `[9, s²I, O]`, or `[9, O, s²I]` for the
    /// input gradient over blocks), the output pixel offsets (for that input gradient, one per
    /// pixel of each block, [`SKIP_OUTPUT`] for the input border's), the scratch.
    wino_u: Vec<T>,
    /// The adjoint filter before its transform (`[2, 2, Cout, s²·Cin]`, strided filters).
    wino_w: Vec<T>,
    wino_pix: Vec<usize>,
    wino: WinogradScratch<T>,
    /// [`Layer::infer`] at batch 1 by [`SparseConv`] (the input is a ReLU's output), with the
    /// input's nonzeros, each output pixel's window start and each tap's offset, in pixels.
    sparse: bool,
    nz: Nonzeros<T>,
    sp_windows: Vec<usize>,
    sp_taps: Vec<usize>,
    /// [`Layer::infer`] at batch 1 as a constant background plus a sparse difference
    /// ([`Background`]): for a layer that reads frames.
    background: bool,
    bg: Background<T>,
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
            cols: Vec::new(),
            dcols: Vec::new(),
            z: Vec::new(),
            y: Tensor::empty(),
            dx: Tensor::empty(),
            y_clean: 0,
            dx_clean: (0, (0, 0)),
            xpad: Vec::new(),
            pixels: Vec::new(),
            patch: Vec::new(),
            out_rows: Vec::new(),
            dy_rows: Vec::new(),
            iota: Vec::new(),
            wt: Vec::new(),
            dxpad: Vec::new(),
            dzpad: Vec::new(),
            ph_p: Vec::new(),
            ph_rows: Vec::new(),
            ph_q: Vec::new(),
            ph_w: Vec::new(),
            winograd: None,
            wino_u: Vec::new(),
            wino_w: Vec::new(),
            wino_pix: Vec::new(),
            wino: WinogradScratch::default(),
            sparse: false,
            nz: Nonzeros::default(),
            sp_windows: Vec::new(),
            sp_taps: Vec::new(),
            background: false,
            bg: Background::default(),
        }
    }

    /// Acts ([`Layer::infer`] at batch 1) by a product over the input's nonzero values only
    /// ([`crate::tensor::SparseConv`]): for a layer whose input is a ReLU's output, which in a
    /// trained network is mostly exact zeros. Off by default; [`crate::dqn::article_qnet`]
    /// turns it on for conv2 and conv3.
    pub fn with_sparse_inference(mut self, on: bool) -> Self {
        self.sparse = on;
        self
    }

    /// Acts ([`Layer::infer`] at batch 1) by splitting the input into a constant background
    /// and its difference from it, which on game frames is mostly zeros
    /// ([`crate::tensor::Background`]): the background's response costs no pass over the image
    /// and the difference's is summed over its pixels that differ. For a layer that reads
    /// frames; if more than an eighth of the pixels differ, the dense product. Off by default;
    /// [`crate::dqn::article_qnet`] turns it on for conv1.
    pub fn with_background_inference(mut self, on: bool) -> Self {
        self.background = on;
        self
    }

    /// Runs the forward product on the fast path by Winograd's minimal filtering
    /// ([`crate::tensor::winograd_conv`]) instead of the direct gather GEMM, where the shape
    /// has one (other shapes ignore it):
    /// - a 3×3 stride-1 filter by F(2×2, 3×3): 4/9 of the multiply-adds; also the input gradient
    ///   when the input is read in place (the adjoint is again a 3×3 stride-1 convolution) and
    ///   the weight gradient ([`crate::tensor::winograd_wgrad`]: the transforms' adjoints);
    /// - a `2s × 2s` filter of stride `s` (conv1: 8×8 stride 4; conv2: 4×4 stride 2) by F(2×2,
    ///   2×2) over `s × s` pixel blocks: 9/16 of the multiply-adds; also the weight gradient, and
    ///   the input gradient when the input is read in place and its blocks tile it exactly (the
    ///   adjoint is a 2×2 convolution over blocks,
    ///   [`crate::tensor::winograd_filters_s2d_adjoint`]); otherwise that stays direct, by
    ///   phases.
    ///
    /// Off by default;
    /// [`crate::dqn::article_qnet`] turns it on for conv2 and conv3. Batches under 8 keep the
    /// direct product: the filters are transformed on every call, and at batch 1 (acting)
    /// F(2×2, 3×3) measured 30% slower for conv3. The products reduce over fewer values (64
    /// channels for conv3, 128 for conv2) and the transforms add passes over tiles 2.25× the
    /// input, so the saving is less than the multiply-adds: measured on the 1-thread train step,
    /// conv3's forward and input gradient about 2–5%, its weight gradient about 4% and conv2's
    /// forward about 2%; conv2's weight gradient went from 4.7 to 3.6 ms, its input gradient
    /// from 5.1–7.2 to 3.9–4.4 ms (`kbench net`, one thread, 3 alternating rounds). conv1's
    /// forward (4 input channels, so 9 products of only 64 × 32 per 8×8 pixels, and 5.9 MB of
    /// input read by a transform that cannot hide the memory behind arithmetic) cost 2% of the
    /// step, and its weight gradient measured level.
    pub fn with_winograd(mut self, on: bool) -> Self {
        let g = self.geom;
        self.winograd = match (g.kh, g.kw, g.sh, g.sw) {
            _ if !on => None,
            (3, 3, 1, 1) => Some(WinogradKind::F2x3),
            (kh, kw, sh, sw) if kh == kw && sh == sw && kh == 2 * sh => Some(WinogradKind::S2d(sh)),
            _ => None,
        };
        self
    }

    /// The Winograd kind a batch of `n` runs by: only batches of at least 8, since the filter
    /// transform on every call costs more than Winograd saves on one image (acting).
    fn use_winograd(&self, n: usize) -> Option<WinogradKind> {
        self.winograd.filter(|_| n >= 8)
    }

    /// The forward product of a batch of `n` as a Winograd convolution: VALID over the (padded)
    /// input, every input tile (4×4 pixels, or 3×3 blocks of s×s) of a 2×2 output tile, into the
    /// bordered output.
    fn winograd_shape(&self, n: usize, kind: WinogradKind) -> WinogradShape {
        let g = self.geom;
        let (hp, wp) = g.padded();
        let (hb, wb) = self.border.around(g.oh, g.ow);
        WinogradShape {
            n,
            h: hp,
            w: wp,
            ci: g.cin,
            oh: g.oh,
            ow: g.ow,
            pad_top: 0,
            pad_left: 0,
            co: g.cout,
            out_image: hb * wb * g.cout,
            out_pieces: 1,
            kind,
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

    fn rows(&self, n: usize) -> usize {
        n * self.geom.out_pixels()
    }

    /// The output shape for a batch of `n`.
    fn out_shape(&self, n: usize) -> [usize; 4] {
        let (hb, wb) = self.border.around(self.geom.oh, self.geom.ow);
        [n, hb, wb, self.geom.cout]
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

    /// Zeroes the input border's places of `dX` in the images not zeroed before, or in all `n`
    /// if `overwritten` (a path that wrote every place of `dX`).
    fn zero_input_border(&mut self, n: usize, overwritten: bool) {
        let (g, b) = (self.geom, self.in_border);
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

    /// `dX` for an input read directly, by phases: a gather GEMM per `(iy mod SH, ix mod SW)`.
    ///
    /// Input row `iy = a·SH + py` meets the filter rows `ky = py + SH·j` (`j < J`, the phase's
    /// taps), through output rows `oy = a − j`; columns likewise. So
    /// `dX[a·SH+py, b·SW+px, ci] = Σ_{j,l,co} dZ[a−j, b−l, co] · W[py+SH·j, px+SW·l, ci, co]`,
    /// with `dZ` read as zero outside the image: every input pixel of a phase is one row of a
    /// GEMM that reduces over the phase's `J·L·Cout` taps, gathered from `dZ` inside a zero
    /// border (taps in reverse order, so the offsets are non-negative). Each `dX` value is
    /// written once (no scatter, no overlapping adds), `Cin` columns wide.
    fn dx_by_phases(&mut self, dz: &[T], n: usize) {
        let g = self.geom;
        let (sh, sw, co, ci) = (g.sh, g.sw, g.cout, g.cin);
        // dZ inside a border of (max taps − 1) above/left and enough below/right.
        let (tj, tl) = (g.kh.div_ceil(sh) - 1, g.kw.div_ceil(sw) - 1);
        let hz = tj + g.oh.max((g.h - 1) / sh + 1);
        let wz = tl + g.ow.max((g.w - 1) / sw + 1);
        // Every place written on every call (the interior copied, the border zeroed), so the
        // buffer is reused without clearing it first.
        self.dzpad.resize(n * hz * wz * co, T::zero());
        self.dzpad
            .par_chunks_mut(hz * wz * co)
            .zip(dz.par_chunks(g.out_pixels() * co))
            .for_each(|(pad, img)| {
                for (zy, row) in pad.chunks_exact_mut(wz * co).enumerate() {
                    match zy.checked_sub(tj).filter(|&oy| oy < g.oh) {
                        Some(oy) => {
                            let (left, rest) = row.split_at_mut(tl * co);
                            let (mid, right) = rest.split_at_mut(g.ow * co);
                            left.fill(T::zero());
                            mid.copy_from_slice(&img[oy * g.ow * co..][..g.ow * co]);
                            right.fill(T::zero());
                        }
                        None => row.fill(T::zero()),
                    }
                }
            });
        let w = self.params[0].value.data();
        let b = self.in_border;
        for py in 0..sh.min(g.h) {
            for px in 0..sw.min(g.w) {
                // Taps of this phase (none if the filter is smaller than the stride).
                let (nj, nl) = (
                    g.kh.saturating_sub(py).div_ceil(sh),
                    g.kw.saturating_sub(px).div_ceil(sw),
                );
                self.ph_p.clear();
                self.ph_rows.clear();
                for i in 0..n {
                    for (a, iy) in (py..g.h).step_by(sh).enumerate() {
                        for (bb, ix) in (px..g.w).step_by(sw).enumerate() {
                            if b.contains(g.h, g.w, iy, ix) {
                                continue;
                            }
                            let (zy, zx) = (a + tj + 1 - nj.max(1), bb + tl + 1 - nl.max(1));
                            self.ph_p.push(((i * hz + zy) * wz + zx) * co);
                            self.ph_rows.push(((i * g.h + iy) * g.w + ix) * ci);
                        }
                    }
                }
                // Tap (j', l', c) is dZ row j' and column l' of the window, filter row
                // py + SH·(J − 1 − j') and column px + SW·(L − 1 − l').
                self.ph_q.clear();
                self.ph_w.clear();
                for jr in 0..nj {
                    for lr in 0..nl {
                        let (ky, kx) = (py + sh * (nj - 1 - jr), px + sw * (nl - 1 - lr));
                        for c in 0..co {
                            self.ph_q.push((jr * wz + lr) * co + c);
                            let wrow = ((ky * g.kw + kx) * ci) * co + c;
                            self.ph_w.extend((0..ci).map(|k| w[wrow + k * co]));
                        }
                    }
                }
                T::gather_gemm(GatherGemm {
                    a: &self.dzpad,
                    p: &self.ph_p,
                    q: &self.ph_q,
                    b: &self.ph_w,
                    ldb: ci,
                    n: ci,
                    c: self.dx.data_mut(),
                    ldc: ci,
                    c_rows: Some(&self.ph_rows),
                    init: Init::Zero,
                    relu: false,
                });
            }
        }
        self.zero_input_border(n, false);
    }

    /// The forward pass by a gather GEMM (see the type's documentation).
    fn forward_gather(&mut self, x: &Tensor<T>) {
        let g = self.geom;
        let n = x.batch();
        let a: &[T] = if g.reads_input_directly() {
            x.data()
        } else {
            pad_input(&g, n, x.data(), &mut self.xpad);
            &self.xpad
        };
        g.gather_offsets(n, &mut self.pixels, &mut self.patch);
        let c_rows = if self.border.is_none() {
            None
        } else {
            self.border
                .interior_offsets(n, g.oh, g.ow, g.cout, &mut self.out_rows);
            Some(&self.out_rows[..])
        };
        if let Some(kind) = self.use_winograd(n) {
            // VALID over the (padded) input: every input tile (4×4 pixels, or 3×3 blocks of
            // s×s) of a 2×2 output tile.
            let w = self.params[0].value.data();
            match kind {
                WinogradKind::F2x3 => winograd_filters(w, g.cin, g.cout, false, &mut self.wino_u),
                WinogradKind::S2d(s) => winograd_filters_s2d(w, s, g.cin, g.cout, &mut self.wino_u),
            }
            self.border
                .interior_offsets(1, g.oh, g.ow, g.cout, &mut self.wino_pix);
            let shape = self.winograd_shape(n, kind);
            let bias = Some(self.params[1].value.data());
            let y = self.y.data_mut();
            winograd_conv(
                shape,
                a,
                &self.wino_u,
                bias,
                self.relu,
                y,
                &self.wino_pix,
                &mut self.wino,
            );
            return;
        }
        T::gather_gemm(GatherGemm {
            a,
            p: &self.pixels,
            q: &self.patch,
            b: self.params[0].value.data(),
            ldb: g.cout,
            n: g.cout,
            c: self.y.data_mut(),
            ldc: g.cout,
            c_rows,
            init: Init::Bias(self.params[1].value.data()),
            relu: self.relu,
        });
    }

    /// The backward pass by gather GEMMs (see the type's documentation); same products as
    /// [`Layer::backward`]'s im2col path. `dz` is `[N·OH·OW, Cout]`.
    fn backward_gather(&mut self, x: &Tensor<T>, dz: &[T], need_dx: bool) {
        let g = self.geom;
        let n = x.batch();
        let (m, k) = (self.rows(n), g.patch_len());
        assert_eq!(
            self.pixels.len(),
            m,
            "{}: backward without forward",
            self.name
        );
        let direct = g.reads_input_directly();
        let a = if direct { x.data() } else { &self.xpad };
        let wino = self.use_winograd(n);
        let f2x3 = wino == Some(WinogradKind::F2x3);
        // Blocks that tile the (padded) input exactly: the input gradient over them by Winograd
        // (each block's s² pixels stored as pieces, at most MAX_PIECES).
        let s2d = match wino {
            Some(WinogradKind::S2d(s))
                if g.h == s * (g.oh + 1) && g.w == s * (g.ow + 1) && s * s <= MAX_PIECES =>
            {
                Some(s)
            }
            _ => None,
        };
        if let Some(kind) = wino {
            // dW by Winograd: the products' adjoints over the (padded) input's tiles.
            let shape = self.winograd_shape(n, kind);
            let dw = self.params[0].grad.data_mut();
            winograd_wgrad(shape, a, dz, dw, &mut self.wino);
        } else {
            // dW[k, co] += Σ_m xpad[pixels[m] + patch[k]] · dZ[m, co]
            T::gather_gemm(GatherGemm {
                a,
                p: &self.patch,
                q: &self.pixels,
                b: dz,
                ldb: g.cout,
                n: g.cout,
                c: self.params[0].grad.data_mut(),
                ldc: g.cout,
                c_rows: None,
                init: Init::Accumulate,
                relu: false,
            });
        }
        // dX by Winograd where the input is read in place: the filters of the adjoint
        // convolution into `wino_u`, where each output goes into `wino_pix`, and its shape.
        let b = self.in_border;
        let w = self.params[0].value.data();
        let adjoint = if !(need_dx && direct) {
            None
        } else if f2x3 && b.top <= 2 && b.left <= 2 {
            // The adjoint convolution of dZ (the rotated, transposed filter): interior input
            // pixel (iy, ix) = (oy + top, ox + left) collects Σ dZ[iy − ky, ix − kx]·Wᵀ[ky, kx],
            // i.e. dZ read at oy + ky' − (2 − top), ky' = 2 − ky.
            let (ih, iw) = (g.h - b.top - b.bottom, g.w - b.left - b.right);
            winograd_filters(w, g.cin, g.cout, true, &mut self.wino_u);
            b.interior_offsets(1, ih, iw, g.cin, &mut self.wino_pix);
            Some(WinogradShape {
                n,
                h: g.oh,
                w: g.ow,
                ci: g.cout,
                oh: ih,
                ow: iw,
                pad_top: 2 - b.top,
                pad_left: 2 - b.left,
                co: g.cin,
                out_image: g.in_len(),
                out_pieces: 1,
                kind: WinogradKind::F2x3,
            })
        } else if let Some(s) = s2d {
            // Over s × s blocks, the adjoint convolution of dZ is 2×2 over blocks, by F(2×2,
            // 2×2) (see `winograd_filters_s2d_adjoint`): block (Y, X) collects dZ[Y − by,
            // X − bx] for by, bx < 2, i.e. dZ read from one pixel above and to the left. Each
            // block's s² pixels are stored as pieces, except the input border's.
            winograd_filters_s2d_adjoint(w, s, g.cin, g.cout, &mut self.wino_w, &mut self.wino_u);
            self.wino_pix.clear();
            for by in 0..=g.oh {
                for bx in 0..=g.ow {
                    for (dy, dx) in (0..s).flat_map(|dy| (0..s).map(move |dx| (dy, dx))) {
                        let (iy, ix) = (s * by + dy, s * bx + dx);
                        self.wino_pix.push(if b.contains(g.h, g.w, iy, ix) {
                            SKIP_OUTPUT
                        } else {
                            (iy * g.w + ix) * g.cin
                        });
                    }
                }
            }
            Some(WinogradShape {
                n,
                h: g.oh,
                w: g.ow,
                ci: g.cout,
                oh: g.oh + 1,
                ow: g.ow + 1,
                pad_top: 1,
                pad_left: 1,
                co: s * s * g.cin,
                out_image: g.in_len(),
                out_pieces: s * s,
                kind: WinogradKind::S2d(1),
            })
        } else {
            None
        };
        if let Some(shape) = adjoint {
            self.dx.set_shape(&[n, g.h, g.w, g.cin]);
            let (u, pix) = (&self.wino_u, &self.wino_pix);
            let dx = self.dx.data_mut();
            winograd_conv(shape, dz, u, None, false, dx, pix, &mut self.wino);
            self.zero_input_border(n, false);
        } else if need_dx && direct {
            self.dx.set_shape(&[n, g.h, g.w, g.cin]);
            self.dx_by_phases(dz, n);
        } else if need_dx {
            // dcols[m, k] = Σ_co dZ[m, co] · Wᵀ[co, k]
            self.wt.resize(k * g.cout, T::zero());
            for (kk, wrow) in w.chunks_exact(g.cout).enumerate() {
                for (co, &v) in wrow.iter().enumerate() {
                    self.wt[co * k + kk] = v;
                }
            }
            fill_iota(&mut self.dy_rows, m, g.cout);
            fill_iota(&mut self.iota, g.cout, 1);
            // dxpad[pixels[m] + patch[k]] += dcols[m, k], image by image (col2im fused).
            self.dx.set_shape(&[n, g.h, g.w, g.cin]);
            self.dxpad.clear();
            self.dxpad.resize(self.xpad.len(), T::zero());
            T::scatter_gemm(ScatterGemm {
                a: dz,
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
            unpad_input(&g, n, &self.dxpad, self.dx.data_mut());
            self.zero_input_border(n, true);
        }
    }

    /// The backward pass by im2col + GEMM (the portable path). `dz` is `[N·OH·OW, Cout]`.
    fn backward_im2col(&mut self, dz: &[T], n: usize, need_dx: bool) {
        let g = self.geom;
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
            self.zero_input_border(n, true);
        }
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

    /// [`Layer::forward`] with `self.geom` the input's geometry.
    fn forward_as(&mut self, x: &Tensor<T>) {
        let g = self.geom;
        assert_eq!(
            x.shape()[1..],
            [g.h, g.w, g.cin],
            "{}: input shape",
            self.name
        );
        let n = x.batch();
        let (m, k) = (self.rows(n), g.patch_len());
        self.y.set_shape(&self.out_shape(n));
        if T::simd() {
            self.forward_gather(x);
            self.zero_border(n);
            return;
        }
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
        self.zero_border(n);
    }

    /// [`Layer::infer`] by [`SparseConv`], with `self.geom` the input's geometry: output pixel
    /// `(i, oy, ox)`'s window starts at padded pixel `(i, oy·SH, ox·SW)` and tap `(ky, kx)` is
    /// `ky·WP + kx` pixels further on.
    fn infer_sparse(&mut self, x: &Tensor<T>) {
        let g = self.geom;
        let n = x.batch();
        assert_eq!(
            x.shape()[1..],
            [g.h, g.w, g.cin],
            "{}: input shape",
            self.name
        );
        self.y.set_shape(&self.out_shape(n));
        let a: &[T] = if g.reads_input_directly() {
            x.data()
        } else {
            pad_input(&g, n, x.data(), &mut self.xpad);
            &self.xpad
        };
        // The sparse product loads a weight row from L2 for every nonzero value and tap, where
        // the dense one shares each load between several output pixels: at batch 1 on one
        // thread they cross at about 22% nonzero for conv2 and conv3 (`cargo bench --bench
        // layers -- sparse_act`). A batch's dense product is faster per image still (Winograd,
        // both threads), so a batch takes the sparse one only under a tenth. The count includes
        // the zero border the layer before wrote: an initial network's conv2 and conv3 inputs on
        // game frames are 43% and 36% nonzero by it, a trained network's 5% and 1%.
        let (hp, wp) = g.padded();
        let share = if n == 1 { 5 } else { 10 };
        if !self.nz.collect_sparse(a, g.cin, hp * wp * g.cin, share) {
            return self.forward_as(x);
        }
        self.sp_windows.clear();
        for i in 0..n {
            for oy in 0..g.oh {
                let row = (i * hp + oy * g.sh) * wp;
                self.sp_windows.extend((0..g.ow).map(|ox| row + ox * g.sw));
            }
        }
        self.sp_taps.clear();
        for ky in 0..g.kh {
            self.sp_taps.extend((0..g.kw).map(|kx| ky * wp + kx));
        }
        self.border
            .interior_offsets(n, g.oh, g.ow, g.cout, &mut self.out_rows);
        SparseConv {
            x: &self.nz,
            windows: &self.sp_windows,
            taps: &self.sp_taps,
            w: self.params[0].value.data(),
            bias: self.params[1].value.data(),
            relu: self.relu,
            y: self.y.data_mut(),
            rows: &self.out_rows,
        }
        .run();
        self.zero_border(n);
        // What the last forward pass left for backward no longer matches `y`: a backward pass
        // now fails its "backward without forward" check instead of mixing the two.
        self.pixels.clear();
        self.cols.clear();
    }

    /// [`Layer::infer`] of one image by [`Background`], with `self.geom` the layer's own
    /// geometry. `false` (nothing written) if more than an eighth of the pixels differ from the
    /// background.
    fn infer_background(&mut self, x: &Tensor<T>) -> bool {
        let g = self.geom;
        let (hp, wp) = g.padded();
        let padded = !g.reads_input_directly() && x.shape()[1..] == [hp, wp, g.cin];
        assert!(
            padded || x.shape()[1..] == [g.h, g.w, g.cin],
            "{}: input shape {:?}",
            self.name,
            x.shape()
        );
        // Game frames have 5–13% of their pixels differing (9% typically). With differing
        // pixels scattered at random, the split's per-pixel work made it 14% faster than the
        // dense product at a tenth and 1.6–1.8× slower at a fifth (`cargo bench --bench layers
        // -- sparse_act/conv1`).
        if !self.bg.split(&g, x.data(), padded, g.h * g.w / 8) {
            return false;
        }
        self.y.set_shape(&self.out_shape(1));
        self.border
            .interior_offsets(1, g.oh, g.ow, g.cout, &mut self.out_rows);
        let [w, b] = &self.params;
        self.bg.conv(
            &g,
            w.value.data(),
            b.value.data(),
            self.relu,
            self.y.data_mut(),
            &self.out_rows,
        );
        self.zero_border(1);
        // As in `infer_sparse`: a backward pass now fails its check.
        self.pixels.clear();
        self.cols.clear();
        true
    }

    /// [`Layer::backward`] with `self.geom` the input's geometry.
    fn backward_as(&mut self, x: &Tensor<T>, dy: &Tensor<T>, need_dx: bool) {
        let g = self.geom;
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
        // db += Σ_rows dZ (the same on both paths).
        let gb = self.params[1].grad.data_mut();
        for row in dz.chunks_exact(g.cout) {
            for (g, &d) in gb.iter_mut().zip(row) {
                *g += d;
            }
        }
        if T::simd() {
            self.backward_gather(x, dz, need_dx);
        } else {
            self.backward_im2col(dz, n, need_dx);
        }
        self.z = z;
    }
}

impl<T: Float> Layer<T> for Conv2d<T> {
    fn name(&self) -> &str {
        &self.name
    }

    fn output_shape(&self) -> Vec<usize> {
        self.out_shape(1)[1..].to_vec()
    }

    /// `cols = im2col(x)`, then `Z = b + cols·W` (bias broadcast first, GEMM accumulates), then
    /// `y = border(act(Z))`.
    ///
    /// The input may also arrive already padded (see [`Conv2d::input_geometry`]).
    fn forward(&mut self, x: &Tensor<T>) {
        // The body reads `self.geom`: for a pre-padded input it runs with the VALID geometry,
        // and the layer's own is put back after.
        let own = self.geom;
        self.geom = self.input_geometry(x);
        self.forward_as(x);
        self.geom = own;
    }

    /// With [`Conv2d::with_background_inference`], one image of which at most an eighth of the
    /// pixels differ from the background: its response plus the difference's ([`Background`]).
    /// With [`Conv2d::with_sparse_inference`], if at most a fifth of the (padded) input is
    /// nonzero (a tenth for a batch): the sum over the nonzero values only ([`SparseConv`]).
    /// Otherwise [`Layer::forward`].
    fn infer(&mut self, x: &Tensor<T>) {
        if self.background && x.batch() == 1 && self.infer_background(x) {
            return;
        }
        if !self.sparse {
            return self.forward(x);
        }
        let own = self.geom;
        self.geom = self.input_geometry(x);
        self.infer_sparse(x);
        self.geom = own;
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
        let own = self.geom;
        self.geom = self.input_geometry(x);
        self.backward_as(x, dy, need_dx);
        self.geom = own;
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
