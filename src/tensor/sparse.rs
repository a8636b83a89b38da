//! Acting on sparse activations: products that skip the exact zeros a ReLU leaves.
//!
//! Every layer after the first reads a ReLU's output, and a trained Q-network's are mostly
//! exact zeros: on Space Invaders frames, the 800-episode `article` run's conv1, conv2 and conv3
//! outputs are 95%, 99% and 96% zeros, counting the zero borders they write (an initial
//! network's 57%, 64% and 48%). A zero input adds
//! nothing to any output, so a product that visits only the nonzero inputs does the same sums
//! with a fraction of the work, and for dense1 (7040 × 128 weights, 3.6 MB, more than L2) a
//! fraction of the memory traffic, which is what bounds a batch-1 forward pass.
//!
//! This is for acting (batch 1, no backward pass): a batch of 48 has few places that are zero in
//! every sample, so training keeps the dense kernels.
//!
//! The product, for one image in NHWC: output row `r` (a pixel) is
//! `y[r, :] = act(b + Σ_t Σ_{ci : x[p_r + o_t, ci] ≠ 0} x[p_r + o_t, ci] · W[t, ci, :])`
//! over the taps `t` (filter places, each an offset `o_t` from the window's first pixel `p_r`).
//! A dense layer is the case of one pixel, one tap and one row. The terms are summed from the
//! bias in ascending tap and channel order, the order of the AVX-512 gather kernel's batch-1
//! product, by the same fused multiply-adds; a skipped `fma(0, w, s)` is `s` exactly, so on
//! AVX-512 these layers act with the forward pass's bits (up to the sign of a zero). The portable
//! loops (f64, other CPUs) agree with faer's blocked GEMM up to rounding. The one difference: a
//! `0 · w` that would turn an infinite or NaN weight into NaN is skipped.
//!
//! conv1 reads frames, which have no zeros but a constant background: acting splits that off
//! instead ([`super::Background`]), and agrees with the forward pass up to rounding.

use super::cpu::{took_path, Family, Path};
use super::Float;

/// The nonzero values of an image `[P, C]` (pixels, channels), pixel by pixel: pixel `p`'s are
/// channels `index[start[p]..start[p + 1]]` with values `value[start[p]..start[p + 1]]`.
/// The buffers are reused from call to call.
#[derive(Clone, Debug, Default)]
pub struct Nonzeros<T> {
    pub(super) start: Vec<usize>,
    pub(super) index: Vec<u32>,
    pub(super) value: Vec<T>,
}

impl<T: Float> Nonzeros<T> {
    /// Collects the nonzero values of `x` (`[P, c]`), keeping each pixel's in channel order.
    ///
    /// Branch-free: every value is written to the next free place, which then moves on only
    /// if the value is nonzero (the signs of a ReLU's inputs are coin flips to a predictor).
    pub fn collect(&mut self, x: &[T], c: usize) {
        assert!(
            c > 0 && x.len().is_multiple_of(c),
            "Nonzeros: {} values in pixels of {c}",
            x.len()
        );
        assert!(c <= u32::MAX as usize, "Nonzeros: {c} channels");
        let pixels = x.len() / c;
        self.start.resize(pixels + 1, 0);
        // 16 spare places: the SIMD path stores whole vectors, the scalar one the last value
        // even when zero.
        self.index.resize(x.len() + 16, 0);
        self.value.resize(x.len() + 16, T::zero());
        let path = if T::simd() {
            if c.is_multiple_of(16) {
                Path::Avx512
            } else {
                Path::Portable
            }
        } else if T::gather_simd() {
            Path::Avx2
        } else {
            Path::Portable
        };
        match took_path(Family::Nonzeros, path) {
            // SAFETY: `simd` holds only where the CPU runs AVX-512F; `T` is f32 there.
            #[cfg(target_arch = "x86_64")]
            Path::Avx512 => unsafe { avx512::collect(self, x, c) },
            // SAFETY: `gather_simd` without `simd`: the CPU runs AVX2 and FMA.
            #[cfg(target_arch = "x86_64")]
            Path::Avx2 => unsafe { super::x86_64::acting_avx2::collect(self, x, c) },
            _ => self.collect_portable(x, c),
        }
    }

    /// [`Nonzeros::collect`]'s portable loop (also what the AVX2 family compiles for AVX2), on
    /// buffers sized by it.
    #[inline(always)]
    pub(super) fn collect_portable(&mut self, x: &[T], c: usize) {
        let pixels = x.len() / c;
        let mut k = 0;
        for (p, px) in x.chunks_exact(c).enumerate() {
            self.start[p] = k;
            for (ci, &v) in px.iter().enumerate() {
                self.index[k] = ci as u32;
                self.value[k] = v;
                k += (v != T::zero()) as usize;
            }
        }
        self.start[pixels] = k;
    }

    /// Collects the nonzero values of `x` (images of `image` values, pixels of `c`) if at most
    /// `1/share` of them are nonzero, and says whether it did; otherwise the lists are not to
    /// be used and the caller takes the dense product. A batch is judged by its first image
    /// first, so a dense batch (an initial network's) costs one image's count.
    pub fn collect_sparse(&mut self, x: &[T], c: usize, image: usize, share: usize) -> bool {
        if x.len() > image {
            self.collect(&x[..image], c);
            if self.len() > image / share {
                return false;
            }
        }
        self.collect(x, c);
        self.len() <= x.len() / share
    }

    /// How many values are nonzero.
    pub fn len(&self) -> usize {
        self.start.last().copied().unwrap_or(0)
    }

    /// Whether every value is zero.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The nonzero channels and values of pixel `p`.
    #[inline]
    pub fn pixel(&self, p: usize) -> (&[u32], &[T]) {
        let (a, b) = (self.start[p], self.start[p + 1]);
        (&self.index[a..b], &self.value[a..b])
    }
}

/// The sparse product of one image (see the module's documentation).
pub struct SparseConv<'a, T> {
    /// The input's nonzeros, by pixel ([`Nonzeros::collect`] with `Cin` channels).
    pub x: &'a Nonzeros<T>,
    /// `p_r`: the pixel where output row `r`'s window starts.
    pub windows: &'a [usize],
    /// `o_t`: each tap's pixel offset from the window's start, in the weights' tap order.
    pub taps: &'a [usize],
    /// Weights `[taps, Cin, Cout]`.
    pub w: &'a [T],
    /// Bias `[Cout]`.
    pub bias: &'a [T],
    /// Apply `max(·, 0)`.
    pub relu: bool,
    /// The output; row `r` is written at `y[rows[r]..rows[r] + Cout]`.
    pub y: &'a mut [T],
    pub rows: &'a [usize],
}

impl<T: Float> SparseConv<'_, T> {
    /// Computes every output row (one thread: a batch-1 product is too small to split).
    pub fn run(self) {
        let cout = self.bias.len();
        assert_eq!(self.windows.len(), self.rows.len(), "SparseConv: rows");
        let cin = self.w.len() / (self.taps.len() * cout).max(1);
        assert_eq!(
            self.w.len(),
            self.taps.len() * cin * cout,
            "SparseConv: weights"
        );
        if cout == 0 || self.windows.is_empty() {
            return;
        }
        match took_path(Family::Sparse, acting_path::<T>(cout)) {
            // SAFETY: `simd` holds only where the CPU runs AVX-512F; `T` is f32 there, `cout` a
            // multiple of 16 up to 128.
            #[cfg(target_arch = "x86_64")]
            Path::Avx512 => unsafe { avx512::run(self, cin, cout) },
            // SAFETY: `gather_simd` without `simd`: AVX2 and FMA, `T` f32, `cout` a multiple
            // of 8.
            #[cfg(target_arch = "x86_64")]
            Path::Avx2 => unsafe { super::x86_64::acting_avx2::sparse_run(self, cin, cout) },
            _ => self.run_portable(cin, cout),
        }
    }

    /// [`SparseConv::run`]'s portable loop: each product rounded, then added.
    fn run_portable(self, cin: usize, cout: usize) {
        // Each row is summed in place in `y`: no scratch, nothing allocated per call.
        for (&p, &r) in self.windows.iter().zip(self.rows) {
            let out = &mut self.y[r..r + cout];
            out.copy_from_slice(self.bias);
            for (t, &o) in self.taps.iter().enumerate() {
                let wt = &self.w[t * cin * cout..][..cin * cout];
                let (index, value) = self.x.pixel(p + o);
                for (&ci, &v) in index.iter().zip(value) {
                    let row = &wt[ci as usize * cout..][..cout];
                    for (a, &wv) in out.iter_mut().zip(row) {
                        *a += v * wv;
                    }
                }
            }
            if self.relu {
                for o in out.iter_mut() {
                    *o = o.max(T::zero());
                }
            }
        }
    }
}

/// The loop a sparse or background product of `cout` output channels runs: AVX-512 for f32
/// where it runs and `cout` is a multiple of 16 up to 128 (one register per 16 channels); AVX2
/// and FMA for f32 where they run instead and `cout` is a multiple of 8 (columns of up to 64
/// channels at a time); else the portable loop. The SIMD loops give the same bits: each output
/// channel is the same fused multiply-adds in the same order.
pub(super) fn acting_path<T: Float>(cout: usize) -> Path {
    if T::simd() {
        if cout.is_multiple_of(16) && cout <= 128 {
            Path::Avx512
        } else {
            Path::Portable
        }
    } else if T::gather_simd() && cout.is_multiple_of(8) {
        Path::Avx2
    } else {
        Path::Portable
    }
}

#[cfg(target_arch = "x86_64")]
use super::x86_64::sparse_avx512 as avx512;
