//! 2-D max pooling (NHWC, TensorFlow's SAME/VALID geometry), channel by channel.

use super::{Core, Layer};
use crate::tensor::{ConvGeom, Float, Padding, Tensor};
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
/// The forward pass keeps, for each output value, the index of its *winner* (the input value
/// that is the maximum; `[N, OH, OW, C]`, an offset inside its image). Where several values tie,
/// the first in the window's row-major order (`ky`, then `kx`) wins, as in TensorFlow.
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
    /// input image, from the last forward pass.
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

    /// Each output value is the first maximum of its window, read in row-major order over the
    /// window's pixels inside the image; its offset goes to the winner buffer. One output row
    /// (`OW·C` values) per rayon task.
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
        self.winner.resize(n * g.oh * g.ow * c, 0);
        let row = g.ow * c;
        self.core
            .y
            .data_mut()
            .par_chunks_mut(row)
            .zip(self.winner.par_chunks_mut(row))
            .enumerate()
            .for_each(|(r, (y, win))| {
                let (i, oy) = (r / g.oh, r % g.oh);
                let img = &x.data()[i * g.in_len()..(i + 1) * g.in_len()];
                let (y0, y1) = window(oy, g.sh, g.pad_top, g.kh, g.h);
                for (ox, (yp, wp)) in y
                    .chunks_exact_mut(c)
                    .zip(win.chunks_exact_mut(c))
                    .enumerate()
                {
                    let (x0, x1) = window(ox, g.sw, g.pad_left, g.kw, g.w);
                    // Start from the window's first pixel; a later one wins only if larger.
                    let first = (y0 * g.w + x0) * c;
                    yp.copy_from_slice(&img[first..first + c]);
                    for (ch, w) in wp.iter_mut().enumerate() {
                        *w = (first + ch) as u32;
                    }
                    for iy in y0..y1 {
                        for ix in x0..x1 {
                            let at = (iy * g.w + ix) * c;
                            for (ch, (best, w)) in yp.iter_mut().zip(wp.iter_mut()).enumerate() {
                                let v = img[at + ch];
                                if v > *best {
                                    *best = v;
                                    *w = (at + ch) as u32;
                                }
                            }
                        }
                    }
                }
            });
    }

    /// `dX = 0`, then `dX[winner(o)] += dY[o]` for every output value `o` (a sum where an input
    /// wins several overlapping windows); one image per rayon task. Uses the winners of the last
    /// [`Layer::forward`], which must have seen this `x`.
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
            self.winner.len(),
            n * out_len,
            "{}: backward needs the forward pass of the same batch",
            self.core.name
        );
        self.core.dx.set_shape(x.shape());
        self.core
            .dx
            .data_mut()
            .par_chunks_mut(g.in_len())
            .zip(dy.data().par_chunks(out_len))
            .zip(self.winner.par_chunks(out_len))
            .for_each(|((dx, dy), win)| {
                dx.fill(T::zero());
                for (&d, &w) in dy.iter().zip(win) {
                    dx[w as usize] += d;
                }
            });
    }
}
