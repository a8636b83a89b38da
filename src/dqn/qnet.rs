//! The article's Q-network.

use crate::layers::init::VarianceScaling;
use crate::layers::{Conv2d, Dense, Flatten, Relu, Sequential};
use crate::tensor::{ConvGeom, Float, Padding};
use rand::Rng;

/// Builds the article's Q-network for `[H, W, C]` inputs and `n_actions` outputs:
///
/// ```text
/// input  [N, 88, 80, C]        (C = 1 for `vanilla`, 4 for the stacks)
/// conv1  32 @ 8x8, stride 4, SAME, ReLU  -> [N, 22, 20, 32]
/// conv2  64 @ 4x4, stride 2, SAME, ReLU  -> [N, 11, 10, 64]
/// conv3  64 @ 3x3, stride 1, SAME, ReLU  -> [N, 11, 10, 64]
/// flatten                                -> [N, 7040]
/// dense1 128, ReLU                       -> [N, 128]
/// dense2 n_actions, linear               -> [N, n_actions]   one Q-value per action
/// ```
///
/// Weights are drawn with `init` (the article: VarianceScaling(2.0), i.e. [`VarianceScaling::HE`]),
/// biases start at zero. Any input size works (the gradient checks use small ones).
pub fn article_qnet<T: Float>(
    input: [usize; 3],
    n_actions: usize,
    init: &VarianceScaling,
    rng: &mut impl Rng,
) -> Sequential<T> {
    let [h, w, c] = input;
    let mut net = Sequential::new();
    let mut shape = [h, w, c];
    for (i, (cout, k, s)) in [(32, 8, 4), (64, 4, 2), (64, 3, 1)].into_iter().enumerate() {
        let g = ConvGeom::new(
            shape[0],
            shape[1],
            shape[2],
            cout,
            k,
            k,
            (s, s),
            Padding::Same,
        )
        .expect("SAME convolution of a non-empty input");
        net.push(Conv2d::new(&format!("conv{}", i + 1), g));
        shape = [g.oh, g.ow, cout];
        net.push(Relu::new(&format!("relu{}", i + 1), &shape));
    }
    net.push(Flatten::new("flatten", &shape));
    let flat = shape.iter().product();
    net.push(Dense::new("dense1", flat, 128));
    net.push(Relu::new("relu4", &[128]));
    net.push(Dense::new("dense2", 128, n_actions));
    for p in net.params_mut() {
        if p.name.ends_with(".weight") {
            init.fill(&mut p.value, rng);
        }
    }
    net
}
