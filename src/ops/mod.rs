//! The one door between the layers and the kernels.
//!
//! A layer holds the maths of its products (`Z = x·W + b`, `dW += xᵀ·dZ`, `dX = dZ·Wᵀ`) and
//! calls one function here per product; this module asks the [`plan`] which kernel computes it
//! for the shape, batch, precision and CPU, runs that kernel on the layer's slices and keeps the
//! kernel's buffers (offset tables, padded copies, packed bf16 operands) from call to call.
//!
//! A kernel is chosen in two tiers. The [`plan`] chooses the algorithm (im2col + GEMM, the
//! gather GEMM, Winograd, the sparse or background product; f32 or bf16), and is the only place
//! that does. The family it chose then picks its instruction set (AVX-512, AVX2, AMX's tiles
//! or its portable loop) call by call, from the one feature test in [`crate::tensor::cpu`]
//! (its module documentation lists which family asks what). The kernels themselves live in
//! [`crate::tensor`] (portable loops, and each architecture's code under `tensor/x86_64/`), with
//! the plain reference kernels ([`crate::tensor::conv2d_reference`],
//! [`crate::tensor::gemm_reference`], [`crate::tensor::im2col`]) they are tested against.
//!
//! | layer product | here |
//! |---|---|
//! | convolution forward, acting | [`ConvOps::forward`], [`ConvOps::infer`] |
//! | convolution `dZ`, `dW`, `dX` | [`ConvOps::relu_grad`], [`ConvOps::weight_grad`], [`ConvOps::input_grad`] |
//! | dense forward, acting, `dW`, `dX` | [`DenseOps::forward`], [`DenseOps::infer`], [`DenseOps::weight_grad`], [`DenseOps::input_grad`] |
//! | small plain products (quantile embedding) | [`gemm`] |
//! | element-wise loops (ReLU, the residual sum) | [`map`], [`map2`], [`vectorized`] |
//! | sums over a sample or a gradient (layer normalisation, the gradient's norm) | [`lanes`] |

mod conv;
mod dense;
pub mod lanes;
pub mod plan;

pub use conv::{ConvOps, ConvSpec};
pub use dense::DenseOps;
pub use plan::Precision;

/// The plain GEMM (faer): `C = α·op(A)·op(B) + β·C`, for products too small or too irregular for
/// a planned kernel (the quantile embedding's).
pub use crate::tensor::{gemm, Op};

/// Runs an element-wise loop compiled for the widest vectors this CPU has (a layer's loop over
/// its values, e.g. the ReLU's).
pub use crate::tensor::vectorized;

/// Elements per rayon task of [`map`] and [`map2`]: element-wise work, so any split gives the
/// same result.
const CHUNK: usize = 1 << 15;

/// `out[i] = f(a[i])` for every `i`, in chunks across the threads, each compiled for the widest
/// vectors this CPU has ([`vectorized`]). The slices have one length.
pub fn map<T: crate::tensor::Float>(out: &mut [T], a: &[T], f: impl Fn(T) -> T + Sync) {
    use rayon::prelude::*;
    assert_eq!(out.len(), a.len(), "map: lengths");
    out.par_chunks_mut(CHUNK)
        .zip(a.par_chunks(CHUNK))
        .for_each(|(out, a)| {
            vectorized(|| {
                for (o, &a) in out.iter_mut().zip(a) {
                    *o = f(a);
                }
            })
        });
}

/// `out[i] = f(a[i], b[i])` for every `i`, as [`map`].
pub fn map2<T: crate::tensor::Float>(
    out: &mut [T], a: &[T], b: &[T], f: impl Fn(T, T) -> T + Sync,
) {
    use rayon::prelude::*;
    assert!(out.len() == a.len() && a.len() == b.len(), "map2: lengths");
    out.par_chunks_mut(CHUNK)
        .zip(a.par_chunks(CHUNK))
        .zip(b.par_chunks(CHUNK))
        .for_each(|((out, a), b)| {
            vectorized(|| {
                for ((o, &a), &b) in out.iter_mut().zip(a).zip(b) {
                    *o = f(a, b);
                }
            })
        });
}
