//! A stack of layers applied in order.

use super::{Layer, Param};
use crate::tensor::{Float, Tensor};

/// Layers applied one after another: `y = f_L(… f_2(f_1(x)))`.
///
/// The backward pass walks the layers in reverse, handing each the input it saw (the previous
/// layer's output, or the network's input `x` for the first) and the gradient of its output (the
/// next layer's input gradient, or the caller's `dY` for the last): the chain rule, one link per
/// layer.
pub struct Sequential<T> {
    layers: Vec<Box<dyn Layer<T>>>,
}

impl<T: Float> Sequential<T> {
    /// An empty network.
    pub fn new() -> Self {
        Sequential { layers: Vec::new() }
    }

    /// Appends a layer, telling it the output shape of the one before ([`Layer::connect`]).
    pub fn push(&mut self, mut layer: impl Layer<T> + 'static) {
        if let Some(before) = self.layers.last() {
            layer.connect(&before.output_shape());
        }
        self.layers.push(Box::new(layer));
    }

    /// Appends every layer of `other`, in order.
    pub fn append(&mut self, other: Sequential<T>) {
        self.layers.extend(other.layers);
    }

    /// Shape of one sample's output (of the last layer).
    pub fn output_shape(&self) -> Vec<usize> {
        self.layers
            .last()
            .map(|l| l.output_shape())
            .unwrap_or_default()
    }

    /// Values in one sample's output (the product of [`Sequential::output_shape`]): the input
    /// width of a dense layer pushed next.
    pub fn output_len(&self) -> usize {
        self.output_shape().iter().product()
    }

    /// The layers, in order.
    pub fn layers(&self) -> &[Box<dyn Layer<T>>] {
        &self.layers
    }

    /// The layers, mutably (to time or drive them one at a time).
    pub fn layers_mut(&mut self) -> &mut [Box<dyn Layer<T>>] {
        &mut self.layers
    }

    /// The layers, taken out of the network.
    pub fn into_layers(self) -> Vec<Box<dyn Layer<T>>> {
        self.layers
    }

    /// Runs every layer on `x` and returns the last output.
    pub fn forward(&mut self, x: &Tensor<T>) -> &Tensor<T> {
        self.chain(x, |layer, input| layer.forward(input))
    }

    /// [`Sequential::forward`] for acting: every layer's [`Layer::infer`] (a batch-1 pass
    /// skips the zeros the ReLUs leave). A backward pass needs a forward pass after it.
    pub fn infer(&mut self, x: &Tensor<T>) -> &Tensor<T> {
        self.chain(x, |layer, input| layer.infer(input))
    }

    /// Runs `pass` on each layer in turn, each reading the output of the one before.
    fn chain(&mut self, x: &Tensor<T>, pass: impl Fn(&mut dyn Layer<T>, &Tensor<T>)) -> &Tensor<T> {
        for i in 0..self.layers.len() {
            let (before, rest) = self.layers.split_at_mut(i);
            let input = before.last().map_or(x, |l| l.output());
            pass(rest[0].as_mut(), input);
        }
        self.output()
    }

    /// The output of the last forward pass.
    pub fn output(&self) -> &Tensor<T> {
        self.layers.last().expect("empty network").output()
    }

    /// Back-propagates `dY` (the gradient of the loss with respect to the output of the last
    /// forward pass, which must have been on this same `x`), adding every parameter's gradient.
    /// Returns `dX` if `need_input_grad`.
    pub fn backward(
        &mut self, x: &Tensor<T>, dy: &Tensor<T>, need_input_grad: bool,
    ) -> Option<&Tensor<T>> {
        for i in (0..self.layers.len()).rev() {
            let (before, rest) = self.layers.split_at_mut(i);
            let (layer, after) = rest.split_first_mut().expect("i < len");
            let input = before.last().map_or(x, |l| l.output());
            let upstream = after.first().map_or(dy, |l| l.input_grad());
            layer.backward(input, upstream, i > 0 || need_input_grad);
        }
        if need_input_grad {
            self.layers.first().map(|l| l.input_grad())
        } else {
            None
        }
    }

    /// Every parameter, layer by layer, weight before bias (each layer's as a list: for a walk
    /// that must not allocate, [`Sequential::visit_params`]).
    pub fn params(&self) -> impl Iterator<Item = &Param<T>> {
        self.layers.iter().flat_map(|l| l.params())
    }

    /// Every parameter, mutably.
    pub fn params_mut(&mut self) -> impl Iterator<Item = &mut Param<T>> {
        self.layers.iter_mut().flat_map(|l| l.params_mut())
    }

    /// Calls `f` on every parameter in [`Sequential::params`]'s order, allocating nothing
    /// ([`Layer::visit_params`]).
    pub fn visit_params<'a>(&'a self, mut f: impl FnMut(&'a Param<T>)) {
        for layer in &self.layers {
            layer.visit_params(&mut f);
        }
    }

    /// [`Sequential::visit_params`], mutably.
    pub fn visit_params_mut<'a>(&'a mut self, mut f: impl FnMut(&'a mut Param<T>)) {
        for layer in &mut self.layers {
            layer.visit_params_mut(&mut f);
        }
    }

    /// Sets every parameter gradient to zero (gradients accumulate across `backward` calls).
    pub fn zero_grad(&mut self) {
        self.visit_params_mut(|p| p.grad.fill_zero());
    }

    /// Copies every parameter's values from a network of the same architecture (the DQN's
    /// target-network update).
    ///
    /// Layer by layer, each of the other's parameters to the one in the same place, found by a
    /// visit that counts (a layer holds a few): it allocates nothing, as it runs once per block
    /// of agent steps with `act_while_learning`.
    pub fn copy_params_from(&mut self, other: &Sequential<T>) {
        assert_eq!(
            self.layers.len(),
            other.layers.len(),
            "copy_params_from: architectures differ"
        );
        for (mine, theirs) in self.layers.iter_mut().zip(&other.layers) {
            let mut i = 0;
            theirs.visit_params(&mut |p| {
                let (mut j, mut found) = (0, false);
                mine.visit_params_mut(&mut |q| {
                    if j == i {
                        assert_eq!(q.name, p.name, "copy_params_from: architectures differ");
                        q.value.data_mut().copy_from_slice(p.value.data());
                        found = true;
                    }
                    j += 1;
                });
                assert!(found, "copy_params_from: architectures differ");
                i += 1;
            });
            let mut n = 0;
            mine.visit_params(&mut |_| n += 1);
            assert_eq!(n, i, "copy_params_from: architectures differ");
        }
    }

    /// The number of trainable scalars.
    pub fn param_count(&self) -> usize {
        self.params().map(|p| p.value.len()).sum()
    }

    /// Multiply-adds of one sample's forward pass.
    pub fn macs(&self) -> usize {
        self.layers.iter().map(|l| l.macs()).sum()
    }

    /// Sets the quantile fractions of the next passes ([`Layer::set_fractions`]): an implicit
    /// quantile network's [`super::QuantileEmbedding`] turns each input sample into `N` rows,
    /// one per fraction.
    pub fn set_fractions(&mut self, taus: &[f64]) {
        for l in &mut self.layers {
            l.set_fractions(taus);
        }
    }

    /// Sets every layer's training arithmetic ([`Layer::set_precision`]).
    pub fn set_precision(&mut self, precision: crate::ops::plan::Precision) {
        for l in &mut self.layers {
            l.set_precision(precision);
        }
    }
}

impl<T: Float> Default for Sequential<T> {
    fn default() -> Self {
        Self::new()
    }
}
