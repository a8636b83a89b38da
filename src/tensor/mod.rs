//! Tensors and the kernels under the layers.
//!
//! A [`Tensor`] is a shape and a flat row-major buffer. Images are NHWC: batch, height, width,
//! channels, channels fastest, so one pixel's channels are contiguous and a convolution's patch
//! rows are contiguous runs of memory. ndarray views are available for reading and slicing.
//!
//! Buffers are allocated once and reused: [`Tensor::set_shape`] changes the shape in place and only
//! allocates when the new size exceeds every size seen before, so after the first pass at the
//! largest batch nothing in a forward or backward pass allocates. In a program that opts in to
//! [`CacheAligned`] as its global allocator (the `invaders` binary, the benchmarks and examples
//! do), every buffer of 1 KiB or more starts on a 64-byte cache line, so the kernels' AVX-512
//! vectors never straddle two lines; the kernels assume no alignment for correctness.

mod align;
mod background;
pub mod bf16;
mod conv;
pub mod cpu;
mod float;
mod gather;
pub mod gather_bf16;
mod gemm;
mod sparse;
mod transpose;
mod winograd;
#[cfg(target_arch = "x86_64")]
mod x86_64;

pub use align::CacheAligned;
pub use background::Background;
pub use conv::{
    col2im, conv2d_reference, conv2d_reference_backward, im2col, pad_input, unpad_input, Border,
    ConvGeom, GeomBuilder, Padding,
};
pub use cpu::vectorized;
pub use float::Float;
pub use gather::{
    fill_iota, gather_gemm_portable, scatter_gemm_portable, GatherGemm, Init, ScatterGemm,
};
pub use gather_bf16::{gather_gemm_bf16, gather_gemm_bf16_portable, GatherGemmBf16};
pub use gemm::{gemm, gemm_faer, gemm_matrixmultiply, gemm_reference, Op};
pub use sparse::{Nonzeros, SparseConv};
pub use transpose::transpose;
pub use winograd::{
    winograd_conv, winograd_conv_bf16, winograd_filters, winograd_filters_bf16,
    winograd_filters_s2d, winograd_filters_s2d_adjoint, winograd_wgrad, winograd_wgrad_bf16,
    WinogradKind, WinogradScratch, WinogradShape, MAX_PIECES, SKIP_OUTPUT,
};

use ndarray::{ArrayViewD, ArrayViewMutD, IxDyn};

/// A dense row-major tensor of `T` with a reusable buffer.
///
/// The buffer never shrinks: its first `len` values are the tensor, and a tensor that goes from
/// batch 48 to batch 1 and back (acting, then training, with the same network) neither
/// reallocates nor refills.
///
/// An f32 tensor may also keep its values rounded to bf16, written by whoever wrote the values
/// ([`Tensor::write_with_bf16`]): a product in bf16 then reads them ([`Tensor::bf16`]) instead of
/// rounding the values again, once per pass that reads them (a train step reads each batch of
/// states in two or three forward passes). Every other mutable access drops them.
#[derive(Clone, Debug)]
pub struct Tensor<T> {
    shape: Vec<usize>,
    data: Vec<T>,
    len: usize,
    /// `bf16[i] = to_bf16(data[i])` for `i < len` while `bf16_kept`; a buffer reused like `data`.
    bf16: Vec<u16>,
    bf16_kept: bool,
}

impl<T: PartialEq> PartialEq for Tensor<T> {
    fn eq(&self, other: &Self) -> bool {
        self.shape == other.shape && self.data[..self.len] == other.data[..other.len]
    }
}

impl<T: Float> Tensor<T> {
    /// A tensor of zeros.
    pub fn zeros(shape: &[usize]) -> Self {
        let len = shape.iter().product();
        Tensor {
            shape: shape.to_vec(),
            data: vec![T::zero(); len],
            len,
            bf16: Vec::new(),
            bf16_kept: false,
        }
    }

    /// An empty tensor (shape `[0]`), to be sized by [`Tensor::set_shape`] on first use.
    pub fn empty() -> Self {
        Tensor {
            shape: vec![0],
            data: Vec::new(),
            len: 0,
            bf16: Vec::new(),
            bf16_kept: false,
        }
    }

    /// Wraps a buffer; `data.len()` must equal the product of `shape`.
    pub fn from_vec(shape: &[usize], data: Vec<T>) -> Self {
        assert_eq!(
            data.len(),
            shape.iter().product::<usize>(),
            "Tensor::from_vec: {} values for shape {:?}",
            data.len(),
            shape
        );
        Tensor {
            shape: shape.to_vec(),
            len: data.len(),
            data,
            bf16: Vec::new(),
            bf16_kept: false,
        }
    }

    /// Changes the shape, growing the buffer only if needed. The contents are unspecified
    /// afterwards (old values, or zeros where the buffer grew); callers overwrite them.
    pub fn set_shape(&mut self, shape: &[usize]) {
        self.bf16_kept = false;
        if self.shape != shape {
            self.shape.clear();
            self.shape.extend_from_slice(shape);
        }
        self.len = shape.iter().product();
        if self.data.len() < self.len {
            self.data.resize(self.len, T::zero());
        }
    }

    /// Sets every element to zero.
    pub fn fill_zero(&mut self) {
        self.data_mut().fill(T::zero());
    }

    /// The shape, outermost dimension first.
    pub fn shape(&self) -> &[usize] {
        &self.shape
    }

    /// The number of elements.
    pub fn len(&self) -> usize {
        self.len
    }

    /// Whether the tensor has no elements.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// The elements in row-major order.
    pub fn data(&self) -> &[T] {
        &self.data[..self.len]
    }

    /// The elements in row-major order, mutably.
    pub fn data_mut(&mut self) -> &mut [T] {
        self.bf16_kept = false;
        &mut self.data[..self.len]
    }

    /// The values rounded to bf16 (to nearest even), if whoever wrote the values kept them
    /// ([`Tensor::write_with_bf16`]); `None` otherwise.
    pub fn bf16(&self) -> Option<&[u16]> {
        self.bf16_kept.then(|| &self.bf16[..self.len])
    }

    /// An ndarray view.
    pub fn view(&self) -> ArrayViewD<'_, T> {
        ArrayViewD::from_shape(IxDyn(&self.shape), self.data()).expect("shape matches data")
    }

    /// A mutable ndarray view.
    pub fn view_mut(&mut self) -> ArrayViewMutD<'_, T> {
        self.bf16_kept = false;
        let len = self.len;
        ArrayViewMutD::from_shape(IxDyn(&self.shape), &mut self.data[..len])
            .expect("shape matches data")
    }

    /// The size of the leading (batch) dimension.
    pub fn batch(&self) -> usize {
        self.shape[0]
    }

    /// Copies `other`'s shape and values into `self`, reusing `self`'s buffer.
    pub fn copy_from(&mut self, other: &Tensor<T>) {
        self.set_shape(&other.shape);
        self.data_mut().copy_from_slice(other.data());
    }
}

impl Tensor<f32> {
    /// Writes values and keeps them rounded to bf16 as well: `write(values, rounded)` changes
    /// any values it likes and sets `rounded[i] = bf16::to_bf16(values[i])` for each `i` it
    /// changes (a table of both, say, for values drawn from 256 bytes). Before it runs, `rounded`
    /// already holds the rounding of every value (of the values as they are, rounded here
    /// where they were not kept), so places it leaves alone stay right. [`Tensor::bf16`] gives
    /// them until the next other mutable access.
    pub fn write_with_bf16(&mut self, write: impl FnOnce(&mut [f32], &mut [u16])) {
        let len = self.len;
        if self.bf16.len() < len {
            self.bf16.resize(len, 0);
        }
        if !self.bf16_kept {
            gather_bf16::round_into(&self.data[..len], &mut self.bf16[..len]);
        }
        write(&mut self.data[..len], &mut self.bf16[..len]);
        self.bf16_kept = true;
    }

    /// Rounds the values to bf16 now and keeps the rounding ([`Tensor::write_with_bf16`]
    /// writing nothing).
    pub fn keep_bf16(&mut self) {
        self.write_with_bf16(|_, _| {});
    }
}
