//! The fast kernels of a convolution's products, as chosen by [`crate::ops::plan::conv`]: the gather GEMMs
//! on a padded input (or the input itself), Winograd's minimal filtering, and for acting the
//! sparse and background products. Each computes the same products as the im2col kernel in
//! `mod.rs`, which is the reference they are tested against (`tests/kernels.rs`,
//! `tests/sparse.rs`); the f64 gradient checks run that one.
//!
//! Where the input is read: a zero-padded copy `xpad` (`[N, HP, WP, Cin]`), or the input itself
//! when it needs no padding (e.g. when the layer before wrote the border). The forward product
//! starts from the bias and stores `max(·, 0)` straight into the interior of the bordered
//! output; the weight gradient reduces over all output pixels straight from the padded input.

use super::{ConvOps, ConvSpec};
use crate::ops::plan::{self, Kernel};
use crate::tensor::gather_bf16::{
    f32s, f32s_mut, pack_pairs, pack_shifted, pair_shifted, pair_steps, round_into, to_bf16_vec,
};
use crate::tensor::{
    fill_iota, gather_gemm_bf16, pad_input, unpad_input, winograd_conv, winograd_conv_bf16,
    winograd_filters, winograd_filters_bf16, winograd_filters_s2d, winograd_filters_s2d_adjoint,
    winograd_wgrad, winograd_wgrad_bf16, Background, ConvGeom, Float, GatherGemm, GatherGemmBf16,
    Init, Nonzeros, ScatterGemm, SparseConv, Tensor, WinogradKind, WinogradScratch, WinogradShape,
    SKIP_OUTPUT,
};
use rayon::prelude::*;

/// The fast kernels' buffers, reused from call to call.
#[derive(Default)]
pub(super) struct Scratch<T> {
    /// The zero-padded input of the last forward pass, `[N, HP, WP, Cin]`.
    pub(super) xpad: Vec<T>,
    /// Where each output pixel's window starts in `xpad` (empty until a forward pass, and after
    /// acting: a backward pass checks it), and each patch element's offset from there.
    pub(super) pixels: Vec<usize>,
    patch: Vec<usize>,
    /// Input gradient by scatter: `m·Cout` per output pixel, `0..Cout`, and `Wᵀ` `[Cout, K]`.
    dy_rows: Vec<usize>,
    iota: Vec<usize>,
    wt: Vec<T>,
    /// The input gradient with respect to `xpad`.
    dxpad: Vec<T>,
    /// Input gradient by phases: `dZ` inside a zero border, and one phase's row starts in it,
    /// destinations in `dX`, tap offsets and packed taps `[taps·Cout, Cin]`.
    dzpad: Vec<T>,
    ph_p: Vec<usize>,
    ph_rows: Vec<usize>,
    ph_q: Vec<usize>,
    ph_w: Vec<T>,
    /// Winograd: the transformed filters (`[16, I, O]`, `[9, s²I, O]`, or `[9, O, s²I]` for the
    /// input gradient over blocks), the adjoint filter before its transform (`[2, 2, Cout,
    /// s²·Cin]`, strided filters), the output pixel offsets (for that input gradient, one per
    /// pixel of each block, [`SKIP_OUTPUT`] for the input border's), the scratch.
    wino_u: Vec<T>,
    wino_w: Vec<T>,
    wino_pix: Vec<usize>,
    wino: WinogradScratch<T>,
    /// Sparse acting: the input's nonzeros, each output pixel's window start and each tap's
    /// offset, in pixels.
    nz: Nonzeros<T>,
    sp_windows: Vec<usize>,
    sp_taps: Vec<usize>,
    /// Background acting.
    bg: Background<T>,
    /// The bf16 products ([`Kernel::GatherBf16`], [`Kernel::PhasesBf16`]), a buffer per operand
    /// so that none is regrown (and zero-filled) from one product to the next: the forward
    /// pass's input in bf16 (kept: the weight gradient pairs it as it is) and its packed `W`;
    /// the weight gradient's input paired with the next output pixel's and its packed `dZ`; the
    /// input gradient's `dZ` inside its zero border, in bf16, and a phase's packed taps; the
    /// pair table and the weight gradient's row table (patch offsets doubled: pairs are two
    /// values wide).
    bf_x: Vec<u16>,
    /// The input `bf_x` was rounded from (its address and length), so that the weight gradient
    /// pairs it only for that input.
    bf_x_of: Option<(usize, usize)>,
    bf_w: Vec<u16>,
    bf_xs: Vec<u16>,
    bf_dz: Vec<u16>,
    bf_dzpad: Vec<u16>,
    bf_taps: Vec<u16>,
    bf_q: Vec<usize>,
    bf_p: Vec<usize>,
}

/// The input the fast kernels read: `x` itself where the geometry reads it in place, else its
/// zero-padded copy `xpad` (written by [`ConvOps::read_input`]).
fn input<'a, T: Float>(g: &ConvGeom, x: &'a Tensor<T>, xpad: &'a [T]) -> &'a [T] {
    if g.reads_input_directly() {
        x.data()
    } else {
        xpad
    }
}

/// Where each output pixel starts in the bordered output, or `None` without a border (the
/// output rows are then consecutive).
fn bordered_rows<'a>(s: &ConvSpec, n: usize, rows: &'a mut Vec<usize>) -> Option<&'a [usize]> {
    let g = s.geom;
    if s.border.is_none() {
        None
    } else {
        s.border.interior_offsets(n, g.oh, g.ow, g.cout, rows);
        Some(&rows[..])
    }
}

impl<T: Float> ConvOps<T> {
    /// Pads `x` into `xpad` where it cannot be read in place, and lays out where each output
    /// pixel's window starts (`pixels`) and each patch element's offset from there (`patch`):
    /// what the forward products read, and the backward products after them.
    fn read_input(&mut self, g: &ConvGeom, x: &Tensor<T>) {
        if !g.reads_input_directly() {
            pad_input(g, x.batch(), x.data(), &mut self.fast.xpad);
        }
        g.gather_offsets(x.batch(), &mut self.fast.pixels, &mut self.fast.patch);
        self.fast.bf_x_of = None;
    }

    /// Checks that the last forward pass laid out this batch's windows (see `read_input`).
    fn check_forward(&self, s: &ConvSpec, n: usize) {
        assert_eq!(
            self.fast.pixels.len(),
            s.rows(n),
            "{}: backward without forward",
            self.name
        );
    }

    /// The forward product of a batch of `n` as a Winograd convolution: VALID over the (padded)
    /// input, every input tile (4×4 pixels, or 3×3 blocks of s×s) of a 2×2 output tile, into the
    /// bordered output.
    fn winograd_shape(s: &ConvSpec, n: usize, kind: WinogradKind) -> WinogradShape {
        let g = s.geom;
        let (hp, wp) = g.padded();
        let (hb, wb) = s.border.around(g.oh, g.ow);
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

    /// `Z = b + x·W` by the gather GEMM ([`Kernel::Gather`]): row `m` gathers output pixel `m`'s
    /// patch through the offset tables, starting from the bias, `max(·, 0)` stored straight into
    /// the bordered output.
    pub(super) fn forward_gather(
        &mut self, s: &ConvSpec, x: &Tensor<T>, w: &[T], b: &[T], y: &mut Tensor<T>,
    ) {
        let g = s.geom;
        self.read_input(&g, x);
        let (a, f) = (input(&g, x, &self.fast.xpad), &self.fast);
        let c_rows = bordered_rows(s, x.batch(), &mut self.out_rows);
        let z = GatherGemm::new(
            a,
            &f.pixels,
            &f.patch,
            w,
            g.cout,
            y.data_mut(),
            Init::Bias(b),
        );
        T::gather_gemm(GatherGemm {
            c_rows,
            relu: s.relu,
            ..z
        });
    }

    /// `Z = b + x·W` in bf16 ([`Kernel::GatherBf16`]): pairs of patch values (a pixel's
    /// channels, next to each other) against pairs of filter rows. The input in bf16 is the
    /// one `x` keeps ([`Tensor::bf16`]: a batch of states) where the layer reads it in place,
    /// else rounded here.
    pub(super) fn forward_bf16(
        &mut self, s: &ConvSpec, x: &Tensor<T>, w: &[T], b: &[T], y: &mut Tensor<T>,
    ) {
        let g = s.geom;
        self.read_input(&g, x);
        let f = &mut self.fast;
        assert!(
            pair_steps(&f.patch, &mut f.bf_q),
            "{}: patch pairs",
            self.name
        );
        let a = match x.bf16().filter(|_| g.reads_input_directly()) {
            Some(kept) => {
                f.bf_x_of = None;
                kept
            }
            None => {
                to_bf16_vec(f32s(input(&g, x, &f.xpad)), &mut f.bf_x);
                f.bf_x_of = Some((x.data().as_ptr() as usize, x.len()));
                &f.bf_x[..]
            }
        };
        pack_pairs(f32s(w), g.patch_len(), g.cout, g.cout, &mut f.bf_w);
        let (y, b) = (f32s_mut(y.data_mut()), Init::Bias(f32s(b)));
        let z = GatherGemmBf16::new(a, &f.pixels, &f.bf_q, &f.bf_w, g.cout, y, b);
        let c_rows = bordered_rows(s, x.batch(), &mut self.out_rows);
        gather_gemm_bf16(GatherGemmBf16 {
            c_rows,
            relu: s.relu,
            ..z
        });
    }

    /// `Z = b + x·W` by Winograd's minimal filtering ([`Kernel::Winograd`], or
    /// [`Kernel::WinogradBf16`] with `bf16`): VALID over the (padded) input, every input tile
    /// (4×4 pixels, or 3×3 blocks of s×s) of a 2×2 output tile.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn forward_winograd(
        &mut self, s: &ConvSpec, x: &Tensor<T>, kind: WinogradKind, w: &[T], b: &[T],
        y: &mut Tensor<T>, bf16: bool,
    ) {
        let g = s.geom;
        self.read_input(&g, x);
        let f = &mut self.fast;
        match kind {
            WinogradKind::F2x3 => winograd_filters(w, g.cin, g.cout, false, &mut f.wino_u),
            WinogradKind::S2d(k) => winograd_filters_s2d(w, k, g.cin, g.cout, &mut f.wino_u),
        }
        s.border
            .interior_offsets(1, g.oh, g.ow, g.cout, &mut f.wino_pix);
        let shape = Self::winograd_shape(s, x.batch(), kind);
        let a = input(&g, x, &f.xpad);
        let (u, pix, y) = (&f.wino_u, &f.wino_pix, y.data_mut());
        if bf16 {
            winograd_filters_bf16(f32s(u), shape.channels(), g.cout, &mut f.bf_w);
            let ub = &f.bf_w;
            winograd_conv_bf16(shape, a, ub, Some(b), s.relu, y, pix, &mut f.wino);
        } else {
            winograd_conv(shape, a, u, Some(b), s.relu, y, pix, &mut f.wino);
        }
    }

    /// `dW[k, co] += Σ_m xpad[pixels[m] + patch[k]]·dZ[m, co]` by the gather GEMM.
    pub(super) fn wgrad_gather(&mut self, s: &ConvSpec, x: &Tensor<T>, dz: &[T], dw: &mut [T]) {
        self.check_forward(s, x.batch());
        let g = s.geom;
        let (a, f) = (input(&g, x, &self.fast.xpad), &self.fast);
        let sum = Init::Accumulate;
        T::gather_gemm(GatherGemm::new(a, &f.patch, &f.pixels, dz, g.cout, dw, sum));
    }

    /// `dW` in bf16: `dW[k, co] += Σ_m x[pixels[m] + patch[k]]·dZ[m, co]` over pairs of output
    /// pixels (2u, 2u + 1), next to each other in a row (`OW` even, the plan's condition), so
    /// `SW·Cin` apart in the input: the input paired with itself shifted by that, against pairs
    /// of rows of dZ. `forward` is the kernel the forward pass ran.
    pub(super) fn wgrad_bf16(
        &mut self, s: &ConvSpec, x: &Tensor<T>, dz: &[T], dw: &mut [T], forward: Kernel,
    ) {
        let (g, n) = (s.geom, x.batch());
        self.check_forward(s, n);
        let f = &mut self.fast;
        let a = input(&g, x, &f.xpad);
        let d = g.sw * g.cin;
        f.bf_q.clear();
        for pair in f.pixels.chunks_exact(2) {
            assert_eq!(pair[1], pair[0] + d, "{}: pixel pairs", self.name);
            f.bf_q.push(2 * pair[0]);
        }
        f.bf_p.clear();
        f.bf_p.extend(f.patch.iter().map(|&k| 2 * k));
        let rounded = Some((x.data().as_ptr() as usize, x.len()));
        if let Some(kept) = x.bf16().filter(|_| g.reads_input_directly()) {
            // The input keeps its rounding (a batch of states): pair that.
            pair_shifted(kept, d, &mut f.bf_xs);
        } else if forward == Kernel::GatherBf16 && f.bf_x_of == rounded {
            // The forward pass rounded this input already: pair it as it is.
            assert_eq!(f.bf_x.len(), a.len(), "{}: bf16 input", self.name);
            pair_shifted(&f.bf_x, d, &mut f.bf_xs);
        } else {
            pack_shifted(f32s(a), d, &mut f.bf_xs);
        }
        pack_pairs(f32s(dz), s.rows(n), g.cout, g.cout, &mut f.bf_dz);
        let (dw, sum) = (f32s_mut(dw), Init::Accumulate);
        gather_gemm_bf16(GatherGemmBf16::new(
            &f.bf_xs, &f.bf_p, &f.bf_q, &f.bf_dz, g.cout, dw, sum,
        ));
    }

    /// `dW` by Winograd: the products' adjoints over the (padded) input's tiles, in bf16 with
    /// `bf16` ([`Kernel::WinogradBf16`]).
    #[allow(clippy::too_many_arguments)]
    pub(super) fn wgrad_winograd(
        &mut self, s: &ConvSpec, x: &Tensor<T>, kind: WinogradKind, dz: &[T], dw: &mut [T],
        bf16: bool,
    ) {
        self.check_forward(s, x.batch());
        let shape = Self::winograd_shape(s, x.batch(), kind);
        let a = input(&s.geom, x, &self.fast.xpad);
        if bf16 {
            winograd_wgrad_bf16(shape, a, dz, dw, &mut self.fast.wino);
        } else {
            winograd_wgrad(shape, a, dz, dw, &mut self.fast.wino);
        }
    }

    /// `dX` by Winograd, for an input read in place: the adjoint convolution of `dZ`, its
    /// filters into `wino_u` and where each output goes into `wino_pix`; its products in bf16
    /// with `bf16` ([`Kernel::WinogradBf16`]).
    #[allow(clippy::too_many_arguments)]
    pub(super) fn dx_winograd(
        &mut self, s: &ConvSpec, n: usize, kind: WinogradKind, dz: &[T], w: &[T],
        dx: &mut Tensor<T>, bf16: bool,
    ) {
        let (g, b) = (s.geom, s.in_border);
        let f = &mut self.fast;
        let shape = match kind {
            WinogradKind::F2x3 => {
                // The adjoint convolution of dZ (the rotated, transposed filter): interior input
                // pixel (iy, ix) = (oy + top, ox + left) collects Σ dZ[iy − ky, ix − kx]·Wᵀ[ky, kx],
                // i.e. dZ read at oy + ky' − (2 − top), ky' = 2 − ky.
                let (ih, iw) = (g.h - b.top - b.bottom, g.w - b.left - b.right);
                winograd_filters(w, g.cin, g.cout, true, &mut f.wino_u);
                b.interior_offsets(1, ih, iw, g.cin, &mut f.wino_pix);
                WinogradShape {
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
                }
            }
            WinogradKind::S2d(s) => {
                // Over s × s blocks, the adjoint convolution of dZ is 2×2 over blocks, by F(2×2,
                // 2×2) (see `winograd_filters_s2d_adjoint`): block (Y, X) collects dZ[Y − by,
                // X − bx] for by, bx < 2, i.e. dZ read from one pixel above and to the left. Each
                // block's s² pixels are stored as pieces, except the input border's.
                winograd_filters_s2d_adjoint(w, s, g.cin, g.cout, &mut f.wino_w, &mut f.wino_u);
                f.wino_pix.clear();
                for by in 0..=g.oh {
                    for bx in 0..=g.ow {
                        for (dy, dx) in (0..s).flat_map(|dy| (0..s).map(move |dx| (dy, dx))) {
                            let (iy, ix) = (s * by + dy, s * bx + dx);
                            f.wino_pix.push(if b.contains(g.h, g.w, iy, ix) {
                                SKIP_OUTPUT
                            } else {
                                (iy * g.w + ix) * g.cin
                            });
                        }
                    }
                }
                WinogradShape {
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
                }
            }
        };
        let (u, pix, dx) = (&f.wino_u, &f.wino_pix, dx.data_mut());
        if bf16 {
            winograd_filters_bf16(f32s(u), shape.channels(), shape.co, &mut f.bf_w);
            winograd_conv_bf16(shape, dz, &f.bf_w, None, false, dx, pix, &mut f.wino);
        } else {
            winograd_conv(shape, dz, u, None, false, dx, pix, &mut f.wino);
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
    pub(super) fn dx_by_phases(
        &mut self, s: &ConvSpec, n: usize, dz: &[T], w: &[T], dx: &mut Tensor<T>, bf16: bool,
    ) {
        let g = s.geom;
        let (sh, sw, co, ci) = (g.sh, g.sw, g.cout, g.cin);
        // dZ inside a border of (max taps − 1) above/left and enough below/right.
        let (tj, tl) = (g.kh.div_ceil(sh) - 1, g.kw.div_ceil(sw) - 1);
        let hz = tj + g.oh.max((g.h - 1) / sh + 1);
        let wz = tl + g.ow.max((g.w - 1) / sw + 1);
        // In bf16 the border is written in bf16 straight away (rounded once, read half as
        // wide), not as f32 first.
        let pad = Padded {
            rows: g.oh,
            row: g.ow * co,
            above: tj,
            left: tl * co,
            height: hz,
            width: wz * co,
        };
        if bf16 {
            pad.write(f32s(dz), n, 0, &mut self.fast.bf_dzpad, |d, s| {
                round_into(s, d)
            });
        } else {
            pad.write(dz, n, T::zero(), &mut self.fast.dzpad, |d, s| {
                d.copy_from_slice(s)
            });
        }
        let b = s.in_border;
        for py in 0..sh.min(g.h) {
            for px in 0..sw.min(g.w) {
                // Taps of this phase (none if the filter is smaller than the stride).
                let (nj, nl) = (
                    g.kh.saturating_sub(py).div_ceil(sh),
                    g.kw.saturating_sub(px).div_ceil(sw),
                );
                self.fast.ph_p.clear();
                self.fast.ph_rows.clear();
                for i in 0..n {
                    for (a, iy) in (py..g.h).step_by(sh).enumerate() {
                        for (bb, ix) in (px..g.w).step_by(sw).enumerate() {
                            if b.contains(g.h, g.w, iy, ix) {
                                continue;
                            }
                            let (zy, zx) = (a + tj + 1 - nj.max(1), bb + tl + 1 - nl.max(1));
                            self.fast.ph_p.push(((i * hz + zy) * wz + zx) * co);
                            self.fast.ph_rows.push(((i * g.h + iy) * g.w + ix) * ci);
                        }
                    }
                }
                // Tap (j', l', c) is dZ row j' and column l' of the window, filter row
                // py + SH·(J − 1 − j') and column px + SW·(L − 1 − l').
                self.fast.ph_q.clear();
                self.fast.ph_w.clear();
                for jr in 0..nj {
                    for lr in 0..nl {
                        let (ky, kx) = (py + sh * (nj - 1 - jr), px + sw * (nl - 1 - lr));
                        for c in 0..co {
                            self.fast.ph_q.push((jr * wz + lr) * co + c);
                            let wrow = ((ky * g.kw + kx) * ci) * co + c;
                            self.fast.ph_w.extend((0..ci).map(|k| w[wrow + k * co]));
                        }
                    }
                }
                if bf16 {
                    // Pairs of output channels: `Cout` even (the plan's condition).
                    let f = &mut self.fast;
                    assert!(
                        pair_steps(&f.ph_q, &mut f.bf_q),
                        "{}: phase taps",
                        self.name
                    );
                    pack_pairs(f32s(&f.ph_w), f.ph_q.len(), ci, ci, &mut f.bf_taps);
                    let (dx, zero) = (f32s_mut(dx.data_mut()), Init::Zero);
                    let z = GatherGemmBf16::new(
                        &f.bf_dzpad,
                        &f.ph_p,
                        &f.bf_q,
                        &f.bf_taps,
                        ci,
                        dx,
                        zero,
                    );
                    gather_gemm_bf16(GatherGemmBf16 {
                        c_rows: Some(&f.ph_rows),
                        ..z
                    });
                    continue;
                }
                let (f, dx, zero) = (&self.fast, dx.data_mut(), Init::Zero);
                let z = GatherGemm::new(&f.dzpad, &f.ph_p, &f.ph_q, &f.ph_w, ci, dx, zero);
                T::gather_gemm(GatherGemm {
                    c_rows: Some(&f.ph_rows),
                    ..z
                });
            }
        }
    }

    /// `dX` for a padded copy of the input: `dZ·Wᵀ` (with `Wᵀ` packed) added tile by tile onto
    /// the padded input gradient (col2im fused), whose interior is then `dX`.
    pub(super) fn dx_by_scatter(
        &mut self, s: &ConvSpec, n: usize, dz: &[T], w: &[T], dx: &mut Tensor<T>,
    ) {
        let g = s.geom;
        let (m, k) = (s.rows(n), g.patch_len());
        // dcols[m, k] = Σ_co dZ[m, co] · Wᵀ[co, k]
        self.fast.wt.resize(k * g.cout, T::zero());
        for (kk, wrow) in w.chunks_exact(g.cout).enumerate() {
            for (co, &v) in wrow.iter().enumerate() {
                self.fast.wt[co * k + kk] = v;
            }
        }
        fill_iota(&mut self.fast.dy_rows, m, g.cout);
        fill_iota(&mut self.fast.iota, g.cout, 1);
        // dxpad[pixels[m] + patch[k]] += dcols[m, k], image by image (col2im fused).
        self.fast.dxpad.clear();
        self.fast.dxpad.resize(self.fast.xpad.len(), T::zero());
        T::scatter_gemm(ScatterGemm {
            a: dz,
            p: &self.fast.dy_rows,
            q: &self.fast.iota,
            b: &self.fast.wt,
            ldb: k,
            n: k,
            out: &mut self.fast.dxpad,
            out_rows: &self.fast.pixels,
            out_cols: &self.fast.patch,
            groups: n,
        });
        unpad_input(&g, n, &self.fast.dxpad, dx.data_mut());
    }

    /// Acting by [`SparseConv`], with `s` for the input; `false` (nothing
    /// written) if the input is not sparse enough ([`plan::sparse_share`]): output pixel
    /// `(i, oy, ox)`'s window starts at padded pixel `(i, oy·SH, ox·SW)` and tap `(ky, kx)` is
    /// `ky·WP + kx` pixels further on.
    pub(super) fn infer_sparse(
        &mut self, s: &ConvSpec, x: &Tensor<T>, w: &[T], b: &[T], y: &mut Tensor<T>,
    ) -> bool {
        let g = s.geom;
        let n = x.batch();
        assert_eq!(
            x.shape()[1..],
            [g.h, g.w, g.cin],
            "{}: input shape",
            self.name
        );
        y.set_shape(&s.out_shape(n));
        let a: &[T] = if g.reads_input_directly() {
            x.data()
        } else {
            pad_input(&g, n, x.data(), &mut self.fast.xpad);
            &self.fast.xpad
        };
        // The sparse product loads a weight row from L2 for every nonzero value and tap, where
        // the dense one shares each load between several output pixels: at batch 1 on one
        // thread they cross at about 22% nonzero for conv2 and conv3 (`cargo bench --bench
        // layers -- sparse_act`). A batch's dense product is faster per image still (Winograd,
        // both threads), so a batch takes the sparse one only under a tenth. The count includes
        // the zero border the layer before wrote: an initial network's conv2 and conv3 inputs on
        // game frames are 43% and 36% nonzero by it, a trained network's 5% and 1%.
        let (hp, wp) = g.padded();
        let share = plan::sparse_share(n);
        if !self
            .fast
            .nz
            .collect_sparse(a, g.cin, hp * wp * g.cin, share)
        {
            return false;
        }
        self.fast.sp_windows.clear();
        for i in 0..n {
            for oy in 0..g.oh {
                let row = (i * hp + oy * g.sh) * wp;
                self.fast
                    .sp_windows
                    .extend((0..g.ow).map(|ox| row + ox * g.sw));
            }
        }
        self.fast.sp_taps.clear();
        for ky in 0..g.kh {
            self.fast.sp_taps.extend((0..g.kw).map(|kx| ky * wp + kx));
        }
        s.border
            .interior_offsets(n, g.oh, g.ow, g.cout, &mut self.out_rows);
        SparseConv {
            x: &self.fast.nz,
            windows: &self.fast.sp_windows,
            taps: &self.fast.sp_taps,
            w,
            bias: b,
            relu: s.relu,
            y: y.data_mut(),
            rows: &self.out_rows,
        }
        .run();
        self.zero_border(s, n, y);
        // What the last forward pass left for backward no longer matches `y`: a backward pass
        // now fails its "backward without forward" check instead of mixing the two.
        self.fast.pixels.clear();
        self.cols.clear();
        true
    }

    /// Acting on one image by [`Background`], with `s` the layer's own
    /// geometry. `false` (nothing written) if more than an eighth of the pixels differ from the
    /// background.
    pub(super) fn infer_background(
        &mut self, s: &ConvSpec, x: &Tensor<T>, w: &[T], b: &[T], y: &mut Tensor<T>,
    ) -> bool {
        let g = s.geom;
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
        if !self.fast.bg.split(
            &g,
            x.data(),
            padded,
            g.h * g.w / plan::BACKGROUND_MAX_DIFFERING,
        ) {
            return false;
        }
        y.set_shape(&s.out_shape(1));
        s.border
            .interior_offsets(1, g.oh, g.ow, g.cout, &mut self.out_rows);
        self.fast
            .bg
            .conv(&g, w, b, s.relu, y.data_mut(), &self.out_rows);
        self.zero_border(s, 1, y);
        // As in `infer_sparse`: a backward pass now fails its check.
        self.fast.pixels.clear();
        self.cols.clear();
        true
    }
}

/// Where `dZ` goes inside a zero border (the input gradient by phases): each of an image's
/// `rows` rows (`row` values) lands `above` rows down and `left` values in, in an image of
/// `height` rows of `width` values.
struct Padded {
    rows: usize,
    row: usize,
    above: usize,
    left: usize,
    height: usize,
    width: usize,
}

impl Padded {
    /// `dst` = the `n` images of `src` inside their border, `put` writing (copying or rounding)
    /// one row's interior. Every place is written on every call (the border with `zero`), so
    /// the buffer is reused without clearing it first.
    fn write<S: Sync, E: Copy + Send + Sync>(
        &self, src: &[S], n: usize, zero: E, dst: &mut Vec<E>, put: impl Fn(&mut [E], &[S]) + Sync,
    ) {
        dst.resize(n * self.height * self.width, zero);
        dst.par_chunks_mut(self.height * self.width)
            .zip(src.par_chunks(self.rows * self.row))
            .for_each(|(pad, img)| {
                for (zy, out) in pad.chunks_exact_mut(self.width).enumerate() {
                    match zy.checked_sub(self.above).filter(|&y| y < self.rows) {
                        Some(y) => {
                            let (left, rest) = out.split_at_mut(self.left);
                            let (mid, right) = rest.split_at_mut(self.row);
                            left.fill(zero);
                            put(mid, &img[y * self.row..][..self.row]);
                            right.fill(zero);
                        }
                        None => out.fill(zero),
                    }
                }
            });
    }
}
