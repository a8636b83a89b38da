//! Acting on game frames: a convolution split into a constant background and a sparse
//! difference.
//!
//! conv1 reads frames, not a ReLU's output: none of its input is zero, but most of it is
//! background. On Space Invaders, 91% of the `article` preset's input values are the black
//! background's −1, and only 9% of its pixels differ from it in any of the stacked frames. With
//! `B` the image whose every pixel is the background `β` (and zero in the padding, as the input
//! is there), the convolution is linear in its input:
//!
//! `conv(x) = b + conv(B) + conv(x − B)`, and `x − B` is zero wherever the frame is background.
//!
//! **The background's response needs no pass over the image.** Output pixel `(oy, ox)` meets
//! `β` at every tap whose input place is inside the image, so
//! `conv(B)[oy, ox, :] = Σ_{ky ∈ R(oy)} Σ_{kx ∈ C(ox)} S[ky, kx, :]`, with
//! `S[ky, kx, :] = Σ_ci β_ci·W[ky, kx, ci, :]` and `R(oy)` the taps with
//! `0 ≤ oy·SH + ky − pad_top < H` (all `KH` of them away from the edges; `C(ox)` likewise).
//! Few distinct ranges occur (three each for conv1), so the sums are taken once per pair.
//!
//! **The difference is summed over the pixels that differ**, each scattered into the outputs
//! whose windows hold it (`(KH/SH)·(KW/SW)` of them, 4 for conv1): a differing padded pixel
//! `(py, px)` adds `Σ_ci d_ci·W[py − oy·SH, px − ox·SW, ci, :]` to output `(oy, ox)`. That is
//! the dense product's work times the share of pixels that differ, with no per-tap lookups.
//!
//! `β` is the image's first pixel (top left), background on Atari frames. Any choice is exact;
//! a poor one only leaves many pixels differing, and the caller then takes the dense product.
//! The result agrees with the dense product up to rounding, not bit for bit: the terms are
//! grouped differently. (On AVX-512 each pixel's sum is taken by fused multiply-adds, and the
//! portable loops round each product, so the two also differ by rounding; each is deterministic.)

use super::cpu::{took_path, Family, Path};
use super::{ConvGeom, Float};
use std::ops::Range;

/// The buffers of one image's split (see the module's documentation), reused from call to call.
#[derive(Clone, Debug, Default)]
pub struct Background<T> {
    /// `β`, one value per input channel, and repeated for each pixel of a row.
    beta: Vec<T>,
    tiled: Vec<T>,
    /// The pixels that differ from `β`: their place `(py, px)` in the padded input, and
    /// `d = x − β` there, `[pixels, Cin]`.
    at: Vec<(usize, usize)>,
    diff: Vec<T>,
    /// `S` `[KH·KW, Cout]`, and its sums over each distinct column range `[KH, |C|, Cout]`.
    taps: Vec<T>,
    partial: Vec<T>,
    /// The distinct tap ranges `lo..hi`, and which one each output row (column) has.
    row_ranges: Vec<(usize, usize)>,
    col_ranges: Vec<(usize, usize)>,
    row_of: Vec<usize>,
    col_of: Vec<usize>,
    /// Whether the last split listed every differing pixel (it did not give up).
    complete: bool,
    /// `b + conv(B)` for each pair of ranges, `[|R|, |C|, Cout]`.
    rect: Vec<T>,
    /// `[OH·OW, Cout]`: `b + conv(B)`, then the difference's terms added.
    acc: Vec<T>,
    /// The outputs whose windows hold each padded row (column).
    out_rows: Vec<Range<usize>>,
    out_cols: Vec<Range<usize>>,
}

impl<T: Float> Background<T> {
    /// Reads `β` from one image `x` (`[H, W, Cin]` of the geometry `g`, or `[HP, WP, Cin]`
    /// already inside its padding if `padded`) and lists its pixels that differ from `β`.
    /// Returns `false`, giving up at the end of the row where the count passes `limit` (the
    /// caller then takes the dense product, having paid for a part of the scan only), or at
    /// once if `β` is not finite. [`Background::conv`] needs a split that returned `true`.
    pub fn split(&mut self, g: &ConvGeom, x: &[T], padded: bool, limit: usize) -> bool {
        let (hp, wp) = g.padded();
        let c = g.cin;
        let len = if padded { hp * wp } else { g.h * g.w } * c;
        assert_eq!(x.len(), len, "Background: image size");
        // Where row `iy` of the image starts: `first + iy·row`.
        let (first, row) = if padded {
            ((g.pad_top * wp + g.pad_left) * c, wp * c)
        } else {
            (0, g.w * c)
        };
        self.beta.clear();
        self.beta.extend_from_slice(&x[first..first + c]);
        self.complete = false;
        if !self.beta.iter().all(|b| b.is_finite()) {
            // conv(B) + conv(x − B) would turn an infinite background into ∞ − ∞ = NaN.
            return false;
        }
        // β once per pixel of a row, to compare a row with it 16 values at a time.
        self.tiled.clear();
        for _ in 0..g.w {
            self.tiled.extend_from_slice(&self.beta);
        }
        self.at.clear();
        self.diff.resize(g.h * g.w * c, T::zero());
        let rows = (0..g.h).map(|iy| &x[first + iy * row..][..g.w * c]);
        let path = if T::simd() {
            Path::Avx512
        } else if T::gather_simd() {
            Path::Avx2
        } else {
            Path::Portable
        };
        self.complete = match took_path(Family::BackgroundSplit, path) {
            // SAFETY: `simd` holds only where the CPU runs AVX-512F; `T` is f32 there.
            #[cfg(target_arch = "x86_64")]
            Path::Avx512 => unsafe { avx512::split(self, g, rows, limit) },
            // SAFETY: `gather_simd` without `simd`: the CPU runs AVX2 and FMA.
            #[cfg(target_arch = "x86_64")]
            Path::Avx2 => unsafe { super::x86_64::acting_avx2::split(self, g, rows, limit) },
            _ => self.split_portable(g, rows, limit),
        };
        self.complete
    }

    /// [`Background::differing`] with the portable block comparison (also what the AVX2 family
    /// compiles for AVX2).
    #[inline(always)]
    pub(super) fn split_portable<'x>(
        &mut self, g: &ConvGeom, rows: impl Iterator<Item = &'x [T]>, limit: usize,
    ) -> bool
    where
        T: 'x,
    {
        self.differing(g, rows, limit, |block, tiled| {
            block
                .iter()
                .zip(tiled)
                .fold(false, |any, (&v, &b)| any | (v != b))
        })
    }

    /// [`Background::split`]'s scan over the image's `rows`. Most 16-value blocks of a row
    /// equal `β`'s tiling (`differs(block, tiling)` is false: one comparison on AVX-512); only
    /// the pixels of the others are looked at one by one.
    #[inline(always)]
    pub(super) fn differing<'x>(
        &mut self, g: &ConvGeom, rows: impl Iterator<Item = &'x [T]>, limit: usize,
        differs: impl Fn(&[T], &[T]) -> bool,
    ) -> bool
    where
        T: 'x,
    {
        let c = g.cin;
        for (iy, values) in rows.enumerate() {
            let mut next = 0;
            for (j, (block, tiled)) in values.chunks(16).zip(self.tiled.chunks(16)).enumerate() {
                if !differs(block, tiled) {
                    continue;
                }
                // The pixels this block touches, after any a block before listed.
                let from = (16 * j / c).max(next);
                next = (16 * j + block.len()).div_ceil(c);
                for ix in from..next {
                    let px = &values[ix * c..][..c];
                    if px != &self.beta[..] {
                        let d = &mut self.diff[self.at.len() * c..][..c];
                        for ((d, &v), &b) in d.iter_mut().zip(px).zip(&self.beta) {
                            *d = v - b;
                        }
                        self.at.push((g.pad_top + iy, g.pad_left + ix));
                    }
                }
            }
            if self.at.len() > limit {
                return false;
            }
        }
        true
    }

    /// `act(conv(x) + b)` for the image of the last [`Background::split`], with weights `w`
    /// `[KH, KW, Cin, Cout]` and bias `b` `[Cout]`: output pixel `r` (row-major) is written at
    /// `y[rows[r]..rows[r] + Cout]`, and `act` is `max(·, 0)` if `relu`.
    pub fn conv(
        &mut self, g: &ConvGeom, w: &[T], bias: &[T], relu: bool, y: &mut [T], rows: &[usize],
    ) {
        let cout = g.cout;
        assert_eq!(w.len(), g.kh * g.kw * g.cin * cout, "Background: weights");
        assert_eq!(
            (bias.len(), self.beta.len()),
            (cout, g.cin),
            "Background: bias"
        );
        assert_eq!(rows.len(), g.oh * g.ow, "Background: output rows");
        assert!(self.complete, "Background: conv after a split that gave up");
        match took_path(Family::Background, super::sparse::acting_path::<T>(cout)) {
            // SAFETY: `simd` holds only where the CPU runs AVX-512F; `T` is f32 there, `cout` a
            // multiple of 16 up to 128.
            #[cfg(target_arch = "x86_64")]
            Path::Avx512 => unsafe { avx512::conv(self, g, w, bias, relu, y, rows) },
            // SAFETY: AVX2 and FMA, `T` f32, `cout` a multiple of 8 (`acting_path`).
            #[cfg(target_arch = "x86_64")]
            Path::Avx2 => unsafe {
                super::x86_64::acting_avx2::background_conv(self, g, w, bias, relu, y, rows)
            },
            _ => self.run(g, w, bias, relu, y, rows, add_products),
        }
    }

    /// [`Background::conv`]'s body, with `add` the kernel that adds a pixel's terms into an
    /// output ([`Background::scatter`]).
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    pub(super) fn run(
        &mut self, g: &ConvGeom, w: &[T], bias: &[T], relu: bool, y: &mut [T], rows: &[usize],
        add: impl Fn(&mut [T], &[T], &[T]),
    ) {
        self.response(g, w, bias);
        self.scatter(g, w, add);
        for (a, &r) in self.acc.chunks_exact(g.cout).zip(rows) {
            for (y, &a) in y[r..r + g.cout].iter_mut().zip(a) {
                *y = if relu { a.max(T::zero()) } else { a };
            }
        }
    }

    /// `acc = b + conv(B)`.
    #[inline(always)]
    fn response(&mut self, g: &ConvGeom, w: &[T], bias: &[T]) {
        let (kh, kw, cin, cout) = (g.kh, g.kw, g.cin, g.cout);
        // S[t, :] = Σ_ci β_ci·W[t, ci, :].
        self.taps.clear();
        self.taps.resize(kh * kw * cout, T::zero());
        for (s, wt) in self
            .taps
            .chunks_exact_mut(cout)
            .zip(w.chunks_exact(cin * cout))
        {
            for (&b, wrow) in self.beta.iter().zip(wt.chunks_exact(cout)) {
                for (s, &wv) in s.iter_mut().zip(wrow) {
                    *s += b * wv;
                }
            }
        }
        tap_ranges(
            g.oh,
            g.sh,
            g.pad_top,
            g.h,
            kh,
            &mut self.row_ranges,
            &mut self.row_of,
        );
        tap_ranges(
            g.ow,
            g.sw,
            g.pad_left,
            g.w,
            kw,
            &mut self.col_ranges,
            &mut self.col_of,
        );
        // partial[ky, j, :] = Σ_{kx ∈ C_j} S[ky, kx, :].
        let nc = self.col_ranges.len();
        self.partial.clear();
        self.partial.resize(kh * nc * cout, T::zero());
        for (ky, part) in self.partial.chunks_exact_mut(nc * cout).enumerate() {
            for (p, &(lo, hi)) in part.chunks_exact_mut(cout).zip(&self.col_ranges) {
                for s in self.taps[(ky * kw + lo) * cout..(ky * kw + hi) * cout].chunks_exact(cout)
                {
                    for (p, &s) in p.iter_mut().zip(s) {
                        *p += s;
                    }
                }
            }
        }
        // rect[i, j, :] = b + Σ_{ky ∈ R_i} partial[ky, j, :].
        self.rect.clear();
        for &(lo, hi) in &self.row_ranges {
            for j in 0..nc {
                let at = self.rect.len();
                self.rect.extend_from_slice(bias);
                for ky in lo..hi {
                    let p = &self.partial[(ky * nc + j) * cout..][..cout];
                    for (r, &p) in self.rect[at..].iter_mut().zip(p) {
                        *r += p;
                    }
                }
            }
        }
        self.acc.clear();
        for &i in &self.row_of {
            for &j in &self.col_of {
                self.acc
                    .extend_from_slice(&self.rect[(i * nc + j) * cout..][..cout]);
            }
        }
    }

    /// `acc += conv(x − B)`, pixel by differing pixel: `add(a, d, w)` adds one pixel's
    /// `Σ_ci d[ci]·w[ci, :]` (`w` `[Cin, Cout]`) to one output `a`.
    #[inline(always)]
    fn scatter(&mut self, g: &ConvGeom, w: &[T], add: impl Fn(&mut [T], &[T], &[T])) {
        let (cin, cout) = (g.cin, g.cout);
        // The outputs whose window holds padded row `py`, `oy·SH ≤ py < oy·SH + KH`, for each
        // `py` (a table: a division per pixel would cost more than its products), and columns.
        let (hp, wp) = g.padded();
        let windows = |n: usize, k: usize, s: usize, o: usize, to: &mut Vec<_>| {
            to.clear();
            to.extend(
                (0..n).map(|p: usize| (p + 1).saturating_sub(k).div_ceil(s)..(p / s + 1).min(o)),
            );
        };
        windows(hp, g.kh, g.sh, g.oh, &mut self.out_rows);
        windows(wp, g.kw, g.sw, g.ow, &mut self.out_cols);
        for (&(py, px), d) in self.at.iter().zip(self.diff.chunks_exact(cin)) {
            for oy in self.out_rows[py].clone() {
                let ky = py - oy * g.sh;
                for ox in self.out_cols[px].clone() {
                    let kx = px - ox * g.sw;
                    let a = &mut self.acc[(oy * g.ow + ox) * cout..][..cout];
                    let wt = &w[(ky * g.kw + kx) * cin * cout..][..cin * cout];
                    add(a, d, wt);
                }
            }
        }
    }
}

/// The taps `lo..hi` (of `k`) that land inside an input of `size` for each of `n` outputs with
/// this stride and padding before: `0 ≤ o·stride + t − pad < size`. Consecutive outputs mostly
/// share one; `of[o]` is the index of output `o`'s in `ranges`.
fn tap_ranges(
    n: usize, stride: usize, pad: usize, size: usize, k: usize, ranges: &mut Vec<(usize, usize)>,
    of: &mut Vec<usize>,
) {
    ranges.clear();
    of.clear();
    for o in 0..n {
        let lo = pad.saturating_sub(o * stride).min(k);
        let hi = (pad + size).saturating_sub(o * stride).clamp(lo, k);
        if ranges.last() != Some(&(lo, hi)) {
            ranges.push((lo, hi));
        }
        of.push(ranges.len() - 1);
    }
}

/// `a[:] += Σ_ci d[ci]·w[ci, :]` (`w` `[Cin, Cout]`, `Cout = a.len()`): the pixel's sum first,
/// then one addition into `a` (consecutive pixels add into the same outputs, and only that
/// addition waits for the one before). The portable kernel and the AVX-512 one's oracle.
fn add_products<T: Float>(a: &mut [T], d: &[T], w: &[T]) {
    let cout = a.len();
    for (co, a) in a.iter_mut().enumerate() {
        let mut p = T::zero();
        for (ci, &dv) in d.iter().enumerate() {
            p += dv * w[ci * cout + co];
        }
        *a += p;
    }
}

#[cfg(target_arch = "x86_64")]
use super::x86_64::background_avx512 as avx512;
