//! Convolution geometry, im2col / col2im, and the direct reference convolution.
//!
//! Shapes (NHWC, TensorFlow's filter layout HWIO):
//! - input `x`: `[N, H, W, Cin]`; filter `w`: `[KH, KW, Cin, Cout]`; bias `b`: `[Cout]`;
//! - output `y`: `[N, OH, OW, Cout]` with
//!   `y[n,oy,ox,co] = b[co] + Σ_{ky,kx,ci} x[n, oy·SH + ky − PT, ox·SW + kx − PL, ci] · w[ky,kx,ci,co]`,
//!   where out-of-range input pixels count as zero (padding).
//!
//! **im2col** lays every output pixel's receptive field out as one row of a matrix
//! `cols[N·OH·OW, KH·KW·Cin]` (column index `(ky·KW + kx)·Cin + ci`, which is exactly how the HWIO
//! filter flattens to `[KH·KW·Cin, Cout]`), so the convolution becomes one GEMM:
//! `Y = cols · W + b`. **col2im** is its adjoint: it adds each row of a `dcols` matrix back onto the
//! input pixels it came from, which is how the input gradient `dX = col2im(dY · Wᵀ)` is formed.

use super::Float;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// How the input is padded.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Padding {
    /// TensorFlow's `SAME`: `OH = ceil(H / SH)`; the total padding
    /// `max((OH − 1)·SH + KH − H, 0)` is split with the smaller half on top (and left), so an odd
    /// total puts the extra row at the bottom (and the extra column on the right).
    #[default]
    Same,
    /// No padding: `OH = floor((H − KH) / SH) + 1`; needs `H ≥ KH`.
    Valid,
}

/// Zero rows and columns written around a layer's output `[N, OH, OW, C]`, making it
/// `[N, top + OH + bottom, left + OW + right, C]`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Border {
    pub top: usize,
    pub bottom: usize,
    pub left: usize,
    pub right: usize,
}

impl Border {
    pub fn is_none(&self) -> bool {
        *self == Border::default()
    }

    /// Height and width of an `h × w` image with this border.
    pub fn around(&self, h: usize, w: usize) -> (usize, usize) {
        (self.top + h + self.bottom, self.left + w + self.right)
    }

    /// Whether row `y` and column `x` of a bordered `hb × wb` image are border places.
    pub fn contains(&self, hb: usize, wb: usize, y: usize, x: usize) -> bool {
        y < self.top || y >= hb - self.bottom || x < self.left || x >= wb - self.right
    }

    /// Sets the border places of `n` bordered images (`h × w × c` inside the border) to zero.
    pub fn zero<T: Float>(&self, data: &mut [T], n: usize, h: usize, w: usize, c: usize) {
        if self.is_none() {
            return;
        }
        let (hb, wb) = self.around(h, w);
        for img in data.chunks_exact_mut(hb * wb * c).take(n) {
            for (y, row) in img.chunks_exact_mut(wb * c).enumerate() {
                if y < self.top || y >= self.top + h {
                    row.fill(T::zero());
                } else {
                    row[..self.left * c].fill(T::zero());
                    row[(self.left + w) * c..].fill(T::zero());
                }
            }
        }
    }

    /// Where each pixel of `n` images of `h × w × c` starts inside the bordered images, in
    /// pixel order (reuses `v`'s buffer).
    pub fn interior_offsets(&self, n: usize, h: usize, w: usize, c: usize, v: &mut Vec<usize>) {
        let (hb, wb) = self.around(h, w);
        v.clear();
        for i in 0..n {
            for y in 0..h {
                let row = (i * hb + self.top + y) * wb + self.left;
                v.extend((0..w).map(|x| (row + x) * c));
            }
        }
    }
}

/// The geometry of one 2-D convolution (everything but the batch size).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ConvGeom {
    /// Input height, width and channels.
    pub h: usize,
    pub w: usize,
    pub cin: usize,
    /// Filter height and width, output channels.
    pub kh: usize,
    pub kw: usize,
    pub cout: usize,
    /// Strides.
    pub sh: usize,
    pub sw: usize,
    /// Output height and width.
    pub oh: usize,
    pub ow: usize,
    /// Padding rows above and columns to the left of the input.
    pub pad_top: usize,
    pub pad_left: usize,
}

/// A convolution's geometry by name rather than by position:
/// `ConvGeom::input(88, 80, 4).filters(32, 8, 8).stride(4, 4).same()` is the article's conv1
/// ([`ConvGeom::new`] with the same numbers). A stride of 1 unless set.
#[derive(Clone, Copy, Debug)]
pub struct GeomBuilder {
    h: usize,
    w: usize,
    cin: usize,
    cout: usize,
    kh: usize,
    kw: usize,
    stride: (usize, usize),
}

impl GeomBuilder {
    /// `cout` filters of `kh × kw`.
    pub fn filters(self, cout: usize, kh: usize, kw: usize) -> Self {
        GeomBuilder {
            cout,
            kh,
            kw,
            ..self
        }
    }

    /// Strides down and across.
    pub fn stride(self, sh: usize, sw: usize) -> Self {
        GeomBuilder {
            stride: (sh, sw),
            ..self
        }
    }

    /// With `padding`; `None` if the shape is impossible (see [`ConvGeom::new`]).
    pub fn padding(self, padding: Padding) -> Option<ConvGeom> {
        let GeomBuilder {
            h,
            w,
            cin,
            cout,
            kh,
            kw,
            stride,
        } = self;
        ConvGeom::new(h, w, cin, cout, kh, kw, stride, padding)
    }

    /// SAME padding (TensorFlow's: the output is the input divided by the stride, rounded up).
    pub fn same(self) -> Option<ConvGeom> {
        self.padding(Padding::Same)
    }

    /// VALID padding (no padding).
    pub fn valid(self) -> Option<ConvGeom> {
        self.padding(Padding::Valid)
    }
}

impl ConvGeom {
    /// Starts a geometry for `[h, w, cin]` inputs ([`GeomBuilder`]).
    pub fn input(h: usize, w: usize, cin: usize) -> GeomBuilder {
        GeomBuilder {
            h,
            w,
            cin,
            cout: 0,
            kh: 0,
            kw: 0,
            stride: (1, 1),
        }
    }

    /// Works out output size and padding by TensorFlow's rules. `None` if the shape is impossible
    /// (a zero size or stride, or a VALID filter larger than the input).
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        h: usize, w: usize, cin: usize, cout: usize, kh: usize, kw: usize, stride: (usize, usize),
        padding: Padding,
    ) -> Option<ConvGeom> {
        let (sh, sw) = stride;
        if [h, w, cin, cout, kh, kw, sh, sw].contains(&0) {
            return None;
        }
        let (oh, ow, pad_top, pad_left) = match padding {
            Padding::Same => {
                let oh = h.div_ceil(sh);
                let ow = w.div_ceil(sw);
                let pad_h = ((oh - 1) * sh + kh).saturating_sub(h);
                let pad_w = ((ow - 1) * sw + kw).saturating_sub(w);
                (oh, ow, pad_h / 2, pad_w / 2)
            }
            Padding::Valid => {
                if kh > h || kw > w {
                    return None;
                }
                ((h - kh) / sh + 1, (w - kw) / sw + 1, 0, 0)
            }
        };
        Some(ConvGeom {
            h,
            w,
            cin,
            kh,
            kw,
            cout,
            sh,
            sw,
            oh,
            ow,
            pad_top,
            pad_left,
        })
    }

    /// Length of one im2col row: `KH·KW·Cin`.
    pub fn patch_len(&self) -> usize {
        self.kh * self.kw * self.cin
    }

    /// Values per input image: `H·W·Cin`.
    pub fn in_len(&self) -> usize {
        self.h * self.w * self.cin
    }

    /// Output pixels per image: `OH·OW`.
    pub fn out_pixels(&self) -> usize {
        self.oh * self.ow
    }

    /// Multiply-adds of one image's forward pass.
    pub fn macs(&self) -> usize {
        self.out_pixels() * self.patch_len() * self.cout
    }

    /// Whether the kernels can read the input as it is: no padding, and every input row and
    /// column is read (so [`ConvGeom::padded`] is the input's own size).
    pub fn reads_input_directly(&self) -> bool {
        self.pad_top == 0 && self.pad_left == 0 && self.padded() == (self.h, self.w)
    }

    /// The same convolution written as a VALID one over an input that already carries its
    /// padding as a zero border: `(geometry over the bordered input, the border)`.
    ///
    /// `SAME(x) = VALID(border(x))`, so a layer that writes its output with this border (see
    /// [`crate::layers::Conv2d::with_border`]) saves the next layer its copy into a padded buffer,
    /// and that layer's input gradient needs no copy back out of one.
    pub fn as_valid(&self) -> (ConvGeom, Border) {
        let (hp, wp) = self.padded();
        let border = Border {
            top: self.pad_top,
            bottom: hp - self.pad_top - self.h,
            left: self.pad_left,
            right: wp - self.pad_left - self.w,
        };
        let valid = ConvGeom::new(
            hp,
            wp,
            self.cin,
            self.cout,
            self.kh,
            self.kw,
            (self.sh, self.sw),
            Padding::Valid,
        )
        .expect("a padded input holds every window");
        debug_assert_eq!((valid.oh, valid.ow), (self.oh, self.ow));
        (valid, border)
    }

    /// Height and width of the zero-padded input the gather kernels read: the padding above and
    /// to the left, the image, and enough below and to the right for the last window.
    pub fn padded(&self) -> (usize, usize) {
        (
            (self.pad_top + self.h).max((self.oh - 1) * self.sh + self.kh),
            (self.pad_left + self.w).max((self.ow - 1) * self.sw + self.kw),
        )
    }

    /// Offsets for the gather GEMM over the padded input `[N, HP, WP, Cin]`
    /// ([`ConvGeom::padded`]): `pixels[m]` where output pixel `m = (i, oy, ox)`'s window starts,
    /// `patch[k]` where patch element `k = (ky, kx, ci)` sits relative to that start, so
    /// `cols[m, k] = xpad[pixels[m] + patch[k]]`. Reuses the vectors' buffers.
    pub fn gather_offsets(&self, n: usize, pixels: &mut Vec<usize>, patch: &mut Vec<usize>) {
        let (hp, wp) = self.padded();
        let c = self.cin;
        pixels.clear();
        for i in 0..n {
            for oy in 0..self.oh {
                for ox in 0..self.ow {
                    pixels.push(((i * hp + oy * self.sh) * wp + ox * self.sw) * c);
                }
            }
        }
        patch.clear();
        for ky in 0..self.kh {
            for kx in 0..self.kw {
                patch.extend((0..c).map(|ci| (ky * wp + kx) * c + ci));
            }
        }
    }

    /// The input row read by output row `oy` at filter row `ky`, if inside the image.
    #[inline]
    fn in_row(&self, oy: usize, ky: usize) -> Option<usize> {
        (oy * self.sh + ky)
            .checked_sub(self.pad_top)
            .filter(|&iy| iy < self.h)
    }

    /// The input column read by output column `ox` at filter column `kx`, if inside the image.
    #[inline]
    fn in_col(&self, ox: usize, kx: usize) -> Option<usize> {
        (ox * self.sw + kx)
            .checked_sub(self.pad_left)
            .filter(|&ix| ix < self.w)
    }
}

/// Writes `cols[N·OH·OW, KH·KW·Cin]` from `x[N, H, W, Cin]` (zeros where the patch is padding).
/// Parallel over images.
pub fn im2col<T: Float>(g: &ConvGeom, n: usize, x: &[T], cols: &mut [T]) {
    let (pl, il) = (g.patch_len(), g.in_len());
    assert_eq!(x.len(), n * il, "im2col: input size");
    assert_eq!(cols.len(), n * g.out_pixels() * pl, "im2col: cols size");
    cols.par_chunks_mut(g.out_pixels() * pl)
        .zip(x.par_chunks(il))
        .for_each(|(cols, x)| {
            for oy in 0..g.oh {
                for ox in 0..g.ow {
                    let row = &mut cols[(oy * g.ow + ox) * pl..][..pl];
                    for ky in 0..g.kh {
                        for kx in 0..g.kw {
                            let dst = &mut row[(ky * g.kw + kx) * g.cin..][..g.cin];
                            match (g.in_row(oy, ky), g.in_col(ox, kx)) {
                                (Some(iy), Some(ix)) => {
                                    dst.copy_from_slice(&x[(iy * g.w + ix) * g.cin..][..g.cin])
                                }
                                _ => dst.fill(T::zero()),
                            }
                        }
                    }
                }
            }
        });
}

/// Copies `x[N, H, W, Cin]` into `xpad[N, HP, WP, Cin]` ([`ConvGeom::padded`]) with zeros
/// around it. Parallel over images.
pub fn pad_input<T: Float>(g: &ConvGeom, n: usize, x: &[T], xpad: &mut Vec<T>) {
    let (hp, wp) = g.padded();
    let (c, il) = (g.cin, g.in_len());
    assert_eq!(x.len(), n * il, "pad_input: input size");
    xpad.resize(n * hp * wp * c, T::zero());
    xpad.par_chunks_mut(hp * wp * c)
        .zip(x.par_chunks(il))
        .for_each(|(xp, x)| {
            for (iy, row) in xp.chunks_exact_mut(wp * c).enumerate() {
                match iy.checked_sub(g.pad_top).filter(|&y| y < g.h) {
                    Some(y) => {
                        let (left, rest) = row.split_at_mut(g.pad_left * c);
                        let (mid, right) = rest.split_at_mut(g.w * c);
                        left.fill(T::zero());
                        mid.copy_from_slice(&x[y * g.w * c..][..g.w * c]);
                        right.fill(T::zero());
                    }
                    None => row.fill(T::zero()),
                }
            }
        });
}

/// The interior of a padded `[N, HP, WP, Cin]` tensor ([`ConvGeom::padded`]) into `x[N, H, W,
/// Cin]`: the inverse of [`pad_input`] (and the adjoint's last step: gradient that landed on
/// padding is dropped). Parallel over images.
pub fn unpad_input<T: Float>(g: &ConvGeom, n: usize, xpad: &[T], x: &mut [T]) {
    let (hp, wp) = g.padded();
    let (c, il) = (g.cin, g.in_len());
    assert_eq!(x.len(), n * il, "unpad_input: input size");
    assert_eq!(xpad.len(), n * hp * wp * c, "unpad_input: padded size");
    x.par_chunks_mut(il)
        .zip(xpad.par_chunks(hp * wp * c))
        .for_each(|(x, xp)| {
            for (y, row) in x.chunks_exact_mut(g.w * c).enumerate() {
                row.copy_from_slice(&xp[((y + g.pad_top) * wp + g.pad_left) * c..][..g.w * c]);
            }
        });
}

/// The adjoint of [`im2col`]: `dx[N, H, W, Cin] = Σ` of every `dcols` entry onto the input value
/// it was copied from (padding entries are dropped). Overwrites `dx`. Parallel over images.
pub fn col2im<T: Float>(g: &ConvGeom, n: usize, dcols: &[T], dx: &mut [T]) {
    let (pl, il) = (g.patch_len(), g.in_len());
    assert_eq!(dx.len(), n * il, "col2im: input size");
    assert_eq!(dcols.len(), n * g.out_pixels() * pl, "col2im: cols size");
    dx.par_chunks_mut(il)
        .zip(dcols.par_chunks(g.out_pixels() * pl))
        .for_each(|(dx, dcols)| {
            dx.fill(T::zero());
            for oy in 0..g.oh {
                for ox in 0..g.ow {
                    let row = &dcols[(oy * g.ow + ox) * pl..][..pl];
                    for ky in 0..g.kh {
                        let Some(iy) = g.in_row(oy, ky) else { continue };
                        for kx in 0..g.kw {
                            let Some(ix) = g.in_col(ox, kx) else { continue };
                            let src = &row[(ky * g.kw + kx) * g.cin..][..g.cin];
                            let dst = &mut dx[(iy * g.w + ix) * g.cin..][..g.cin];
                            for (d, &s) in dst.iter_mut().zip(src) {
                                *d += s;
                            }
                        }
                    }
                }
            }
        });
}

/// The reference convolution: the defining sum, written as plainly as possible, with no
/// im2col and no GEMM. The oracle for every fast convolution kernel. `y` is overwritten.
pub fn conv2d_reference<T: Float>(g: &ConvGeom, n: usize, x: &[T], w: &[T], b: &[T], y: &mut [T]) {
    for i in 0..n {
        for oy in 0..g.oh {
            for ox in 0..g.ow {
                for co in 0..g.cout {
                    let mut s = b[co];
                    for ky in 0..g.kh {
                        for kx in 0..g.kw {
                            let (Some(iy), Some(ix)) = (g.in_row(oy, ky), g.in_col(ox, kx)) else {
                                continue;
                            };
                            for ci in 0..g.cin {
                                s += x[((i * g.h + iy) * g.w + ix) * g.cin + ci]
                                    * w[((ky * g.kw + kx) * g.cin + ci) * g.cout + co];
                            }
                        }
                    }
                    y[((i * g.oh + oy) * g.ow + ox) * g.cout + co] = s;
                }
            }
        }
    }
}

/// The reference backward pass of [`conv2d_reference`], from the same sum:
/// `dx[n,iy,ix,ci] = Σ dy[n,oy,ox,co]·w[ky,kx,ci,co]`, `dw[ky,kx,ci,co] = Σ dy[n,oy,ox,co]·x[n,iy,ix,ci]`
/// and `db[co] = Σ dy[n,oy,ox,co]`, over every `(oy, ox, ky, kx)` that connects the two.
/// Overwrites `dx`, `dw` and `db`.
#[allow(clippy::too_many_arguments)]
pub fn conv2d_reference_backward<T: Float>(
    g: &ConvGeom, n: usize, x: &[T], w: &[T], dy: &[T], dx: &mut [T], dw: &mut [T], db: &mut [T],
) {
    dx.fill(T::zero());
    dw.fill(T::zero());
    db.fill(T::zero());
    for i in 0..n {
        for oy in 0..g.oh {
            for ox in 0..g.ow {
                for co in 0..g.cout {
                    let d = dy[((i * g.oh + oy) * g.ow + ox) * g.cout + co];
                    db[co] += d;
                    for ky in 0..g.kh {
                        for kx in 0..g.kw {
                            let (Some(iy), Some(ix)) = (g.in_row(oy, ky), g.in_col(ox, kx)) else {
                                continue;
                            };
                            for ci in 0..g.cin {
                                let xi = ((i * g.h + iy) * g.w + ix) * g.cin + ci;
                                let wi = ((ky * g.kw + kx) * g.cin + ci) * g.cout + co;
                                dx[xi] += d * w[wi];
                                dw[wi] += d * x[xi];
                            }
                        }
                    }
                }
            }
        }
    }
}
