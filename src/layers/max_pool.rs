//! 2-D max pooling (NHWC, TensorFlow's SAME/VALID geometry), channel by channel.

use super::{Core, Layer};
use crate::tensor::{vectorized, ConvGeom, Float, Padding, Tensor};
use rayon::prelude::*;

/// `y[n, oy, ox, c] = max_{ky, kx} x[n, oy·SH + ky − PT, ox·SW + kx − PL, c]`: the largest value
/// of each channel in a `KH × KW` window, the windows laid out as a convolution's
/// ([`ConvGeom`], with `Cout = Cin = C`).
///
/// Shapes: input `x` `[N, H, W, C]`, output `y` `[N, OH, OW, C]`, with `OH = ⌈H/SH⌉` for SAME and
/// `OH = ⌊(H − KH)/SH⌋ + 1` for VALID (likewise `OW`). SAME pads as TensorFlow does (the smaller
/// half on top and left), and a padded place counts as `−∞`: it never wins, so every window
/// takes the maximum of its pixels inside the image (each window holds at least one).
///
/// The forward pass keeps only `y`. The backward pass finds each output value's *winner*, the
/// input value that is its maximum: the first pixel of the window, in row-major order (`ky`, then
/// `kx`), whose value equals it, which is where TensorFlow's first maximum of a tie is too (a
/// window whose first pixel is NaN has a NaN output, and that pixel wins).
///
/// Derivative: away from ties, `y_o = x_{w(o)}` for the winner `w(o)`, so `∂y_o/∂x_i = [i = w(o)]`
/// and `dX_i = Σ_o dY_o·[i = w(o)]`: each output's gradient goes to its winner, and an input
/// that wins several overlapping windows (stride smaller than the window) collects the sum of
/// theirs; every other input gets 0. At a tie the maximum is not differentiable; like TensorFlow
/// we take the derivative of the first maximum. No parameters.
pub struct MaxPool2d<T> {
    /// The name, output `y` and input gradient `dX` ([`Core`]).
    core: Core<T>,
    /// The geometry (input and output sizes, window, strides, padding); `cout == cin`.
    pub geom: ConvGeom,
    /// `[N, OH, OW, C]`: for each output value, its winner's offset `(h·W + w)·C + c` inside its
    /// input image, found by the last backward pass.
    winner: Vec<u32>,
}

impl<T: Float> MaxPool2d<T> {
    /// A pooling of the given geometry, whose `cout` must equal its `cin` (a pooling keeps the
    /// channels).
    pub fn new(name: &str, geom: ConvGeom) -> Self {
        assert_eq!(
            geom.cout, geom.cin,
            "{name}: a pooling keeps the channels (cout = cin)"
        );
        assert!(
            geom.in_len() <= u32::MAX as usize,
            "{name}: an image of {} values is too large",
            geom.in_len()
        );
        MaxPool2d {
            core: Core::new(name),
            geom,
            winner: Vec::new(),
        }
    }

    /// A `k × k` pooling of stride `s` (down and across) over `[h, w, c]` inputs, with `padding`.
    /// Panics if the shape is impossible (a zero size, or a VALID window larger than the input).
    pub fn square(name: &str, [h, w, c]: [usize; 3], k: usize, s: usize, padding: Padding) -> Self {
        let geom = ConvGeom::new(h, w, c, c, k, k, (s, s), padding).unwrap_or_else(|| {
            panic!("{name}: no {k}x{k} stride-{s} {padding:?} pooling of {h}x{w}x{c}")
        });
        Self::new(name, geom)
    }
}

/// The input rows (or columns) `lo..hi` of output row `o`'s window: `o·s − pad .. o·s − pad + k`
/// clipped to the image `0..len` (the padding, `−∞`, never wins).
#[inline]
fn window(o: usize, s: usize, pad: usize, k: usize, len: usize) -> (usize, usize) {
    let start = o * s;
    let (lo, hi) = (
        start.saturating_sub(pad),
        (start + k).saturating_sub(pad).min(len),
    );
    debug_assert!(lo < hi, "a window with no pixel inside the image");
    (lo, hi)
}

impl<T: Float> Layer<T> for MaxPool2d<T> {
    fn core(&self) -> &Core<T> {
        &self.core
    }

    fn output_shape(&self) -> Vec<usize> {
        vec![self.geom.oh, self.geom.ow, self.geom.cin]
    }

    /// Each output value is the maximum of its window's pixels inside the image, each channel
    /// starting from the first pixel and taking a later value only where it is larger (so a NaN
    /// first pixel stays); a select, not a branch, so that the loop over the channels runs in
    /// vectors. One output row (`OW·C` values) per rayon task.
    fn forward(&mut self, x: &Tensor<T>) {
        let g = self.geom;
        let c = g.cin;
        assert_eq!(
            x.shape()[1..],
            [g.h, g.w, c],
            "{}: input shape",
            self.core.name
        );
        let n = x.batch();
        self.core.y.set_shape(&[n, g.oh, g.ow, c]);
        let row = g.ow * c;
        self.core
            .y
            .data_mut()
            .par_chunks_mut(row)
            .enumerate()
            .for_each(|(r, y)| {
                let (i, oy) = (r / g.oh, r % g.oh);
                let img = &x.data()[i * g.in_len()..(i + 1) * g.in_len()];
                let (y0, y1) = window(oy, g.sh, g.pad_top, g.kh, g.h);
                vectorized(|| {
                    for (ox, yp) in y.chunks_exact_mut(c).enumerate() {
                        let (x0, x1) = window(ox, g.sw, g.pad_left, g.kw, g.w);
                        let first = (y0 * g.w + x0) * c;
                        yp.copy_from_slice(&img[first..first + c]);
                        for iy in y0..y1 {
                            for ix in x0..x1 {
                                let at = (iy * g.w + ix) * c;
                                max_into(yp, &img[at..at + c]);
                            }
                        }
                    }
                })
            });
    }

    /// The winners first: for each output value, the window's pixels are read from the last to
    /// the first, and a pixel equal to `y` replaces the winner so far, so the first equal pixel
    /// is the one left (the first pixel where none is equal: a NaN). Then `dX = 0` and
    /// `dX[winner(o)] += dY[o]` for every output value `o` (a sum where an input wins several
    /// overlapping windows). One image per rayon task. Uses `y` of the last [`Layer::forward`],
    /// which must have seen this `x`.
    fn backward(&mut self, x: &Tensor<T>, dy: &Tensor<T>, need_dx: bool) {
        if !need_dx {
            return;
        }
        let g = self.geom;
        let n = dy.batch();
        let out_len = g.oh * g.ow * g.cin;
        assert_eq!(
            dy.shape(),
            [n, g.oh, g.ow, g.cin],
            "{}: upstream gradient",
            self.core.name
        );
        assert_eq!(x.batch(), n, "{}: input batch", self.core.name);
        assert_eq!(
            self.core.y.shape(),
            dy.shape(),
            "{}: backward needs the forward pass of the same batch",
            self.core.name
        );
        self.winner.resize(n * out_len, 0);
        self.core.dx.set_shape(x.shape());
        let c = g.cin;
        self.core
            .dx
            .data_mut()
            .par_chunks_mut(g.in_len())
            .zip(x.data().par_chunks(g.in_len()))
            .zip(self.core.y.data().par_chunks(out_len))
            .zip(dy.data().par_chunks(out_len))
            .zip(self.winner.par_chunks_mut(out_len))
            .for_each(|((((dx, img), y), dy), win)| {
                vectorized(|| {
                    let outputs = y.chunks_exact(c).zip(win.chunks_exact_mut(c));
                    for (o, (yp, wp)) in outputs.enumerate() {
                        let (oy, ox) = (o / g.ow, o % g.ow);
                        let (y0, y1) = window(oy, g.sh, g.pad_top, g.kh, g.h);
                        let (x0, x1) = window(ox, g.sw, g.pad_left, g.kw, g.w);
                        let first = ((y0 * g.w + x0) * c) as u32;
                        for (ch, w) in wp.iter_mut().enumerate() {
                            *w = first + ch as u32;
                        }
                        for iy in (y0..y1).rev() {
                            for ix in (x0..x1).rev() {
                                let at = (iy * g.w + ix) * c;
                                winners_at(wp, &img[at..at + c], yp, at as u32);
                            }
                        }
                    }
                });
                dx.fill(T::zero());
                for (&d, &w) in dy.iter().zip(win.iter()) {
                    dx[w as usize] += d;
                }
            });
    }
}

/// `w[ch] = at + ch` where `x[ch] == y[ch]`, for one pixel `x` of a window (its offset `at`):
/// in runs of 8 channels, a length the compiler sees, so that each run is a few vector
/// instructions (a compare and a blend), then the channels left over.
#[inline(always)]
fn winners_at<T: Float>(w: &mut [u32], x: &[T], y: &[T], at: u32) {
    const RUN: usize = 8;
    let done = w.len() / RUN * RUN;
    let runs = x.chunks_exact(RUN).zip(y.chunks_exact(RUN));
    for (k, (w, (x, y))) in w.chunks_exact_mut(RUN).zip(runs).enumerate() {
        let base = at + (k * RUN) as u32;
        // Local arrays: the compiler then keeps the run in registers, a compare and a blend.
        let (x, y): ([T; RUN], [T; RUN]) = (x.try_into().unwrap(), y.try_into().unwrap());
        let mut won: [u32; RUN] = w.try_into().unwrap();
        for j in 0..RUN {
            won[j] = if x[j] == y[j] {
                base + j as u32
            } else {
                won[j]
            };
        }
        w.copy_from_slice(&won);
    }
    for ch in done..w.len() {
        w[ch] = if x[ch] == y[ch] {
            at + ch as u32
        } else {
            w[ch]
        };
    }
}

/// `y[ch] = x[ch]` where `x[ch] > y[ch]`, for one pixel `x` of a window: in runs of 8
/// channels, as [`winners_at`], each a vector compare-and-select (`vmaxps` for f32).
#[inline(always)]
fn max_into<T: Float>(y: &mut [T], x: &[T]) {
    const RUN: usize = 8;
    let done = y.len() / RUN * RUN;
    for (y, x) in y.chunks_exact_mut(RUN).zip(x.chunks_exact(RUN)) {
        // Local arrays: the compiler then keeps the run in a register.
        let (mut best, v): ([T; RUN], [T; RUN]) = (y.try_into().unwrap(), x.try_into().unwrap());
        for j in 0..RUN {
            best[j] = if v[j] > best[j] { v[j] } else { best[j] };
        }
        y.copy_from_slice(&best);
    }
    for (y, &x) in y[done..].iter_mut().zip(&x[done..]) {
        *y = if x > *y { x } else { *y };
    }
}
