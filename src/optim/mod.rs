//! Optimizers: they read each parameter's accumulated gradient and update its value.
//!
//! Parameters are visited in the network's fixed order (layer by layer, weight before bias), and
//! an optimizer's per-parameter state is kept in that same order.

mod adam;
mod sgd;

pub use adam::Adam;
pub use sgd::Sgd;

use crate::layers::Sequential;
use crate::ops::lanes::Lanes;
use crate::tensor::cpu::avx512_twin;
use crate::tensor::Float;

/// The global L2 norm of all gradients: `sqrt(Σ_p Σ_i g_p[i]²)`.
///
/// Summed in [`crate::ops::lanes`] (lane `l` takes each gradient's elements `l, l + 16, …`, then the lanes
/// are added pairwise): one fixed order on every machine, and vectorisable, where one running sum
/// would be a chain of a million dependent additions (about 2 ms per train step).
pub fn global_grad_norm<T: Float>(net: &Sequential<T>) -> T {
    let mut lanes = Lanes::default();
    net.visit_params(|p| add_squares(&mut lanes, p.grad.data()));
    lanes.total().sqrt()
}

avx512_twin! {
    /// `lanes += g ⊙ g` lane by lane. A function of its own compiled for AVX-512
    /// ([`avx512_twin`]): handed to [`crate::tensor::vectorized`] as a closure, it was not
    /// inlined and ran 4 lanes wide, 1.7% of the article's bf16 train step on one thread.
    fn add_squares<T: Float>(lanes: &mut Lanes<T>, g: &[T]) {
        lanes.add_products(g, g)
    }
}

/// Clipping by global norm (`tf.clip_by_global_norm`): if the global norm `‖g‖` of the network's
/// gradients exceeds `max_norm`, every gradient is multiplied by `max_norm / ‖g‖`, which shortens
/// the whole update without changing its direction. Returns the norm before clipping.
pub fn clip_grad_norm<T: Float>(net: &mut Sequential<T>, max_norm: T) -> T {
    let norm = global_grad_norm(net);
    if norm > max_norm {
        let s = max_norm / norm;
        net.visit_params_mut(|p| {
            for g in p.grad.data_mut() {
                *g *= s;
            }
        });
    }
    norm
}
