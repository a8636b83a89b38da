//! IMPALA's residual block (Espeholt et al. 2018; Dopamine's `ImpalaEncoder`): a layer made of
//! layers, two 3×3 convolutions around a skip connection.

use super::{Conv2d, Core, Layer, Param, Relu};
use crate::ops::{map2, Precision};
use crate::tensor::{ConvGeom, Float, Tensor};

/// `y = x + conv2(relu(conv1(relu(x))))`, both convolutions 3×3, stride 1, SAME, `C → C`
/// channels, so `y` has `x`'s shape. With the intermediate values the forward pass keeps:
///
/// ```text
/// a = relu(x)            [N, H, W, C]   (relu0's output)
/// h = relu(conv1(a))     [N, H, W, C]   (conv1's output, its ReLU fused)
/// z = conv2(h)           [N, H, W, C]   (conv2's output)
/// y = x + z              [N, H, W, C]
/// ```
///
/// Derivative: `∂y/∂x = I + ∂z/∂x`, so the gradient takes both paths and adds them:
///
/// ```text
/// dH = conv2ᵀ(dY)                 (conv2's backward; also dW2 += hᵀ·dY, db2 += Σ dY)
/// dA = conv1ᵀ(dH ⊙ [h > 0])       (conv1's backward through its ReLU; also dW1, db1)
/// dX = dY + dA ⊙ [x > 0]          (the skip connection, plus relu0's backward)
/// ```
///
/// Parameters, in order: `{name}.conv1.weight` `[3, 3, C, C]`, `{name}.conv1.bias` `[C]`,
/// `{name}.conv2.weight`, `{name}.conv2.bias`.
pub struct Residual<T> {
    /// The name, output `y` and input gradient `dX` ([`Core`]).
    core: Core<T>,
    /// `[H, W, C]`, the shape of one sample's input and output.
    shape: [usize; 3],
    /// `a = relu(x)`.
    relu0: Relu<T>,
    /// `h = relu(conv1(a))`, named `{name}.conv1`.
    conv1: Conv2d<T>,
    /// `z = conv2(h)`, named `{name}.conv2`.
    conv2: Conv2d<T>,
}

impl<T: Float> Residual<T> {
    /// A block over `[h, w, c]` inputs. Its convolutions start as [`Conv2d::new`] draws them
    /// (He weights from a generator seeded by each one's name, zero biases); a network builder
    /// draws them again from its own generator.
    pub fn new(name: &str, [h, w, c]: [usize; 3]) -> Self {
        let g = ConvGeom::input(h, w, c)
            .filters(c, 3, 3)
            .same()
            .unwrap_or_else(|| panic!("{name}: no 3x3 SAME convolution of {h}x{w}x{c}"));
        let mut relu0 = Relu::new(&format!("{name}.relu0"));
        relu0.connect(&[h, w, c]);
        Residual {
            core: Core::new(name),
            shape: [h, w, c],
            relu0,
            conv1: Conv2d::new(&format!("{name}.conv1"), g).with_relu(),
            conv2: Conv2d::new(&format!("{name}.conv2"), g),
        }
    }

    /// Lets the plan run both convolutions by Winograd's minimal filtering
    /// ([`Conv2d::with_winograd`]).
    pub fn with_winograd(mut self, on: bool) -> Self {
        self.conv1 = self.conv1.with_winograd(on);
        self.conv2 = self.conv2.with_winograd(on);
        self
    }

    /// The two convolutions' geometry (both the same: 3×3, stride 1, SAME, `C → C`).
    pub fn geom(&self) -> ConvGeom {
        self.conv1.geom
    }

    /// `y = x + z`, once the inner layers have run (by `forward` or `infer`).
    fn add_skip(&mut self, x: &Tensor<T>) {
        self.check_input(x);
        let z = self.conv2.output();
        self.core.y.set_shape(x.shape());
        map2(self.core.y.data_mut(), x.data(), z.data(), |x, z| x + z);
    }

    /// `y = x + conv2(relu(conv1(relu(x))))` through each inner layer's `forward`, or its
    /// `infer` if `infer`.
    fn pass(&mut self, x: &Tensor<T>, infer: bool) {
        fn run<T: Float>(layer: &mut dyn Layer<T>, x: &Tensor<T>, infer: bool) {
            if infer {
                layer.infer(x)
            } else {
                layer.forward(x)
            }
        }
        self.check_input(x);
        run(&mut self.relu0, x, infer);
        run(&mut self.conv1, self.relu0.output(), infer);
        run(&mut self.conv2, self.conv1.output(), infer);
        self.add_skip(x);
    }

    fn check_input(&self, x: &Tensor<T>) {
        assert_eq!(
            x.shape()[1..],
            self.shape,
            "{}: input shape",
            self.core.name
        );
    }
}

impl<T: Float> Layer<T> for Residual<T> {
    fn core(&self) -> &Core<T> {
        &self.core
    }

    fn output_shape(&self) -> Vec<usize> {
        self.shape.to_vec()
    }

    /// `a = relu(x)`, `h = relu(conv1(a))`, `z = conv2(h)`, `y = x + z`; each inner layer keeps
    /// what its backward pass needs.
    fn forward(&mut self, x: &Tensor<T>) {
        self.pass(x, false);
    }

    /// The same `y` by each inner layer's [`Layer::infer`].
    fn infer(&mut self, x: &Tensor<T>) {
        self.pass(x, true);
    }

    /// The chain rule backwards through conv2, conv1 (with its ReLU) and relu0, then the skip
    /// connection: `dX = dY + relu0ᵀ(conv1ᵀ(conv2ᵀ(dY)))`. conv1's and conv2's parameter
    /// gradients accumulate whether or not `need_dx`.
    fn backward(&mut self, x: &Tensor<T>, dy: &Tensor<T>, need_dx: bool) {
        self.check_input(x);
        assert_eq!(
            dy.shape(),
            x.shape(),
            "{}: upstream gradient",
            self.core.name
        );
        // dH = conv2ᵀ(dY); dW2, db2.
        self.conv2.backward(self.conv1.output(), dy, true);
        // dA = conv1ᵀ(dH ⊙ [h > 0]); dW1, db1.
        self.conv1
            .backward(self.relu0.output(), self.conv2.input_grad(), need_dx);
        if !need_dx {
            return;
        }
        // dA ⊙ [x > 0].
        self.relu0.backward(x, self.conv1.input_grad(), true);
        // dX = dY + dA ⊙ [x > 0].
        let da = self.relu0.input_grad();
        self.core.dx.set_shape(x.shape());
        map2(self.core.dx.data_mut(), dy.data(), da.data(), |dy, da| {
            dy + da
        });
    }

    /// conv1's weight and bias, then conv2's.
    fn visit_params<'a>(&'a self, f: &mut dyn FnMut(&'a Param<T>)) {
        self.conv1.visit_params(f);
        self.conv2.visit_params(f);
    }

    fn visit_params_mut<'a>(&'a mut self, f: &mut dyn FnMut(&'a mut Param<T>)) {
        self.conv1.visit_params_mut(f);
        self.conv2.visit_params_mut(f);
    }

    /// The two convolutions' (the sum and the ReLUs are not multiply-adds).
    fn macs(&self) -> usize {
        self.conv1.macs() + self.conv2.macs()
    }

    fn set_precision(&mut self, precision: Precision) {
        self.conv1.set_precision(precision);
        self.conv2.set_precision(precision);
    }
}
