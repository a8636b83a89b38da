//! Helpers shared by the integration tests.
#![allow(dead_code)]

pub mod cli;
pub mod corridor;
pub mod hostile;

use invaders::layers::{Conv2d, Dense, Layer, Sequential};
use invaders::ops::plan::Precision;
use invaders::tensor::cpu::{self, Family};
use invaders::tensor::{
    conv2d_reference, conv2d_reference_backward, pad_input, Border, ConvGeom, Float, Padding,
    Tensor,
};
use proptest::prelude::*;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Proptest cases for a property: `default`, or `PROPTEST_CASES` from the environment for a
/// longer (or shorter) sweep, e.g. `PROPTEST_CASES=2000 cargo test --release --test gradcheck`.
pub fn cases(default: u32) -> u32 {
    std::env::var("PROPTEST_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// A seeded generator.
pub fn rng(seed: u64) -> ChaCha8Rng {
    ChaCha8Rng::seed_from_u64(seed)
}

/// A tensor of uniform values in [-1, 1).
pub fn uniform<T: Float>(shape: &[usize], rng: &mut impl Rng) -> Tensor<T> {
    let n = shape.iter().product();
    Tensor::from_vec(
        shape,
        (0..n).map(|_| T::of(rng.random_range(-1.0..1.0))).collect(),
    )
}

/// Uniform values in [-1, 1) kept at least `margin` away from zero (so a ReLU's kink is never
/// within a finite-difference step).
pub fn uniform_away_from_zero(shape: &[usize], margin: f64, rng: &mut impl Rng) -> Tensor<f64> {
    let n = shape.iter().product();
    let data = (0..n)
        .map(|_| {
            let v: f64 = rng.random_range(margin..1.0);
            if rng.random_bool(0.5) {
                v
            } else {
                -v
            }
        })
        .collect();
    Tensor::from_vec(shape, data)
}

/// `Σ a·b`.
pub fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// Whether `a` and `b` agree to `atol + rtol·max(|a|, |b|)`.
pub fn close(a: f64, b: f64, atol: f64, rtol: f64) -> bool {
    (a - b).abs() <= atol + rtol * a.abs().max(b.abs())
}

/// Finite-difference step and tolerances for the f64 gradient checks. Central differences of a
/// function that is linear (conv, dense) or piecewise linear away from its kinks (ReLU) in the
/// perturbed value are exact up to rounding, about 1e-16·|S|/H ≈ 1e-10 here, so 1e-7 leaves room
/// for rounding while any wrong index (an error of the size of a whole term, ~1e-2) fails.
pub const H: f64 = 1e-5;
pub const ATOL: f64 = 1e-7;
pub const RTOL: f64 = 1e-6;

/// Which entries of a tensor of `len` to check: all of them up to `max`, else a seeded sample.
pub fn indices(len: usize, max: usize, rng: &mut impl Rng) -> Vec<usize> {
    if len <= max {
        (0..len).collect()
    } else {
        (0..max).map(|_| rng.random_range(0..len)).collect()
    }
}

/// The gradient check of one layer: the scalar `S = Σ f(x)·dY` has `∂S/∂θ` equal to what
/// `backward` accumulates for `dY`. Compares every input-gradient entry and every parameter
/// gradient entry (up to `max_per_tensor` sampled per tensor) with central finite differences.
/// Also checks that a second backward pass *adds* the same gradient again (accumulation with +=).
pub fn check_layer(
    layer: &mut dyn Layer<f64>, x: &Tensor<f64>, dy: &Tensor<f64>, max_per_tensor: usize, seed: u64,
) -> Result<(), String> {
    let mut rng = rng(seed);
    for p in layer.params_mut() {
        p.grad.fill_zero();
    }
    layer.forward(x);
    if layer.output().shape() != dy.shape() {
        return Err(format!(
            "output shape {:?} != {:?}",
            layer.output().shape(),
            dy.shape()
        ));
    }
    layer.backward(x, dy, true);
    let dx = layer.input_grad().clone();
    let grads: Vec<Tensor<f64>> = layer.params().iter().map(|p| p.grad.clone()).collect();
    if dx.shape() != x.shape() {
        return Err(format!(
            "dx shape {:?} != x shape {:?}",
            dx.shape(),
            x.shape()
        ));
    }
    let objective = |layer: &mut dyn Layer<f64>, x: &Tensor<f64>| {
        layer.forward(x);
        dot(layer.output().data(), dy.data())
    };
    let mut xp = x.clone();
    for i in indices(x.len(), max_per_tensor, &mut rng) {
        let num = central(xp.data()[i], |v| {
            xp.data_mut()[i] = v;
            objective(layer, &xp)
        });
        if !close(dx.data()[i], num, ATOL, RTOL) {
            return Err(format!(
                "dx[{i}]: backward {} vs numeric {num}",
                dx.data()[i]
            ));
        }
    }
    for (k, grad) in grads.iter().enumerate() {
        for i in indices(grad.len(), max_per_tensor, &mut rng) {
            let num = central(layer.params()[k].value.data()[i], |v| {
                layer.params_mut()[k].value.data_mut()[i] = v;
                objective(layer, x)
            });
            if !close(grad.data()[i], num, ATOL, RTOL) {
                let name = &layer.params()[k].name;
                return Err(format!(
                    "{name}[{i}]: backward {} vs numeric {num}",
                    grad.data()[i]
                ));
            }
        }
    }
    // Accumulation: a second backward on the same forward adds the same gradient again.
    layer.forward(x);
    layer.backward(x, dy, true);
    for (k, grad) in grads.iter().enumerate() {
        for (i, (&twice, &once)) in layer.params()[k]
            .grad
            .data()
            .iter()
            .zip(grad.data())
            .enumerate()
        {
            if !close(twice, 2.0 * once, 1e-12, 1e-12) {
                return Err(format!(
                    "param {k}[{i}] does not accumulate: {twice} vs 2x{once}"
                ));
            }
        }
    }
    Ok(())
}

/// Fills a layer's parameters with uniform values in [-1, 1).
pub fn randomise(layer: &mut dyn Layer<f64>, seed: u64) {
    let mut r = rng(seed);
    for p in layer.params_mut() {
        let t: Tensor<f64> = uniform(p.value.shape(), &mut r);
        p.value.data_mut().copy_from_slice(t.data());
    }
}

/// `(f(v + H) − f(v − H)) / 2H`, the central difference at `v` of `f`, which sets one entry to
/// the value it is given and returns the loss there; the entry is set back to `v` after.
pub fn central(v: f64, mut f: impl FnMut(f64) -> f64) -> f64 {
    let (sp, sm) = (f(v + H), f(v - H));
    f(v);
    (sp - sm) / (2.0 * H)
}

/// Checks a network's input gradient and its parameters' gradients, from one forward and
/// backward pass with upstream gradient `dy`, against central differences of
/// `L = Σ dy · net(x)`, at the entries `pick(len, is_input)` chooses. Returns the gradients
/// (named, in `params()` order).
pub fn check_sequential(
    net: &mut Sequential<f64>, x: &Tensor<f64>, dy: &Tensor<f64>,
    mut pick: impl FnMut(usize, bool) -> Vec<usize>,
) -> Vec<(String, Tensor<f64>)> {
    net.zero_grad();
    net.forward(x);
    let dx = net.backward(x, dy, true).unwrap().clone();
    let grads: Vec<(String, Tensor<f64>)> = net
        .params()
        .map(|p| (p.name.clone(), p.grad.clone()))
        .collect();
    let objective =
        |net: &mut Sequential<f64>, x: &Tensor<f64>| dot(net.forward(x).data(), dy.data());
    let mut xp = x.clone();
    for i in pick(x.len(), true) {
        let num = central(xp.data()[i], |v| {
            xp.data_mut()[i] = v;
            objective(net, &xp)
        });
        assert!(
            close(dx.data()[i], num, ATOL, RTOL),
            "dx[{i}]: {} vs {num}",
            dx.data()[i]
        );
    }
    for (k, (name, grad)) in grads.iter().enumerate() {
        for i in pick(grad.len(), false) {
            let at = net.params().nth(k).unwrap().value.data()[i];
            let num = central(at, |v| {
                net.params_mut().nth(k).unwrap().value.data_mut()[i] = v;
                objective(net, x)
            });
            assert!(
                close(grad.data()[i], num, ATOL, RTOL),
                "{name}[{i}]: {} vs {num}",
                grad.data()[i]
            );
        }
    }
    grads
}

/// `max |a − b| ≤ tol · (1 + max |b|)`, compared in f64, for proptest.
pub fn assert_close<T: Float>(what: &str, a: &[T], b: &[T], tol: f64) -> Result<(), TestCaseError> {
    prop_assert_eq!(a.len(), b.len());
    let scale = 1.0
        + b.iter()
            .fold(0.0f64, |m, v| m.max(v.to_f64().unwrap().abs()));
    for (i, (x, y)) in a.iter().zip(b).enumerate() {
        let d = (x.to_f64().unwrap() - y.to_f64().unwrap()).abs();
        prop_assert!(d <= tol * scale, "{}[{}]: {} vs {}", what, i, x, y);
    }
    Ok(())
}

/// Sets a layer's parameters (in its order: weight, bias) to the given values.
pub fn set_params<T: Float>(layer: &mut dyn Layer<T>, values: &[&Tensor<T>]) {
    for (p, v) in layer.params_mut().iter_mut().zip(values) {
        p.value.data_mut().copy_from_slice(v.data());
    }
}

/// One forward and backward pass of a fresh `ni → no` dense layer (with its fused ReLU if `relu`)
/// in `precision`, on uniform draws from `r` in this order: `W` `[ni, no]`, `b` `[no]`, `x`
/// `[n, ni]`, `dY` `[n, no]`. Returns the layer (its output, `dW`, `db` and `dX` kept) and
/// `[W, b, x, dY]`.
pub fn dense_pass(
    ni: usize, no: usize, n: usize, relu: bool, precision: Precision, r: &mut impl Rng,
) -> (Dense<f32>, [Tensor<f32>; 4]) {
    let mut layer = Dense::<f32>::new("d", ni, no);
    if relu {
        layer = layer.with_relu();
    }
    layer.set_precision(precision);
    let (w, b) = (uniform::<f32>(&[ni, no], r), uniform::<f32>(&[no], r));
    set_params(&mut layer, &[&w, &b]);
    let x = uniform::<f32>(&[n, ni], r);
    let dy = uniform::<f32>(&[n, no], r);
    layer.forward(&x);
    layer.backward(&x, &dy, true);
    (layer, [w, b, x, dy])
}

/// Whether this host must run the f32 kernels' AVX-512 loops, judged without the library's own
/// check: x86-64 with AVX-512F and FMA, and neither `INVADERS_NO_SIMD` nor `INVADERS_NO_AVX512`
/// set. Where not, says once on stderr which feature is missing: the tests then prove that the
/// AVX2 loops (for the families that have them, where the CPU has AVX2) or the portable ones
/// ran, and the AVX-512 ones go unchecked on this host.
pub fn avx512_expected() -> bool {
    static NOTE: std::sync::Once = std::sync::Once::new();
    #[cfg(target_arch = "x86_64")]
    let (f, fma) = (
        is_x86_feature_detected!("avx512f"),
        is_x86_feature_detected!("fma"),
    );
    #[cfg(not(target_arch = "x86_64"))]
    let (f, fma) = (false, false);
    let off = std::env::var_os("INVADERS_NO_SIMD").is_some();
    let no512 = std::env::var_os("INVADERS_NO_AVX512").is_some();
    let on = f && fma && !off && !no512;
    if !on {
        NOTE.call_once(|| {
            let why = if off {
                "INVADERS_NO_SIMD is set".to_string()
            } else if no512 {
                "INVADERS_NO_AVX512 is set".to_string()
            } else {
                let missing: Vec<&str> = [("avx512f", f), ("fma", fma)]
                    .into_iter()
                    .filter_map(|(n, has)| (!has).then_some(n))
                    .collect();
                format!("this CPU lacks {}", missing.join(" and "))
            };
            eprintln!(
                "skip: AVX-512 kernels not checked on this host ({why}); asserting the AVX2 \
                 (where the CPU has it) or portable loops ran instead"
            );
        });
    }
    assert_eq!(
        cpu::avx512(),
        on,
        "the library's CPU check disagrees with the host"
    );
    on
}

/// Whether this host must run the AVX2 family (for the kernels that have it): AVX2 and FMA, no
/// AVX-512 run ([`avx512_expected`]), `INVADERS_NO_SIMD` unset.
pub fn avx2_expected() -> bool {
    #[cfg(target_arch = "x86_64")]
    let has = is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma");
    #[cfg(not(target_arch = "x86_64"))]
    let has = false;
    let on = has && !avx512_expected() && std::env::var_os("INVADERS_NO_SIMD").is_none();
    assert_eq!(
        cpu::avx2(),
        on,
        "the library's AVX2 check disagrees with the host"
    );
    on
}

/// The families with an AVX2 loop.
fn has_avx2(family: Family) -> bool {
    matches!(
        family,
        Family::Gather
            | Family::Scatter
            | Family::WinogradInput
            | Family::WinogradOutput
            | Family::Nonzeros
            | Family::BackgroundSplit
    )
}

/// Runs `f` and asserts that every call of `family` in it, on this thread, ran one loop, and
/// that there was at least one: the AVX-512 loop if `avx512`, else the AVX2 loop where the
/// family has one and this host runs it ([`avx2_expected`]), else the portable loop.
pub fn on_path<R>(family: Family, avx512: bool, what: &str, f: impl FnOnce() -> R) -> R {
    let expected = if avx512 {
        cpu::Path::Avx512
    } else if has_avx2(family) && avx2_expected() {
        cpu::Path::Avx2
    } else {
        cpu::Path::Portable
    };
    on_exactly(family, expected, what, f)
}

/// Runs `f` and asserts that every call of `family` in it, on this thread, ran the `expected`
/// loop, and that there was at least one.
pub fn on_exactly<R>(family: Family, expected: cpu::Path, what: &str, f: impl FnOnce() -> R) -> R {
    let before = cpu::paths(family);
    let out = f();
    let p = cpu::paths(family).since(before);
    assert!(
        p.avx512 + p.portable + p.avx2 + p.amx > 0,
        "{what}: no {family:?} kernel ran"
    );
    let ran = (p.avx512 > 0, p.avx2 > 0, p.portable > 0, p.amx > 0);
    let want = (
        expected == cpu::Path::Avx512,
        expected == cpu::Path::Avx2,
        expected == cpu::Path::Portable,
        expected == cpu::Path::Amx,
    );
    assert_eq!(
        ran, want,
        "{what}: the {family:?} kernels ran {p:?}, expected only the {expected:?} loop"
    );
    out
}

/// A square convolution for the property tests: a `k × k` filter of stride `s` over
/// `h × w × cin` images, to `cout` channels.
#[derive(Clone, Copy, Debug)]
pub struct Square {
    pub k: usize,
    pub s: usize,
    pub h: usize,
    pub w: usize,
    pub cin: usize,
    pub cout: usize,
}

impl Square {
    /// Its geometry, SAME or VALID. SAME takes any size, kernels larger than the input
    /// included; VALID gets the input grown to fit the kernel.
    pub fn geom(&self, same: bool) -> ConvGeom {
        let (pad, h, w) = if same {
            (Padding::Same, self.h, self.w)
        } else {
            (Padding::Valid, self.h.max(self.k), self.w.max(self.k))
        };
        let Square {
            k, s, cin, cout, ..
        } = *self;
        ConvGeom::new(h, w, cin, cout, k, k, (s, s), pad).unwrap()
    }
}

/// The reference convolution's output `act(conv(x, W) + b)` (`act` the ReLU if `relu`) for a
/// batch of `n`.
pub fn reference_forward<T: Float>(
    g: &ConvGeom, n: usize, x: &[T], w: &[T], b: &[T], relu: bool,
) -> Vec<T> {
    let mut y = vec![T::zero(); n * g.oh * g.ow * g.cout];
    conv2d_reference(g, n, x, w, b, &mut y);
    if relu {
        y.iter_mut().for_each(|v| *v = v.max(T::zero()));
    }
    y
}

/// The reference convolution's gradients `(dX, dW, db)` for `dY` (or `dZ`, past a ReLU) over a
/// batch of `n`.
pub fn reference_grads<T: Float>(
    g: &ConvGeom, n: usize, x: &[T], w: &[T], dy: &[T],
) -> (Vec<T>, Vec<T>, Vec<T>) {
    let (mut dx, mut dw, mut db) = (
        vec![T::zero(); x.len()],
        vec![T::zero(); w.len()],
        vec![T::zero(); g.cout],
    );
    conv2d_reference_backward(g, n, x, w, dy, &mut dx, &mut dw, &mut db);
    (dx, dw, db)
}

/// `x` (`n` images of `g`'s input) inside its SAME padding, as one `[n, HP, WP, Cin]` tensor.
pub fn padded_input<T: Float>(g: &ConvGeom, n: usize, x: &Tensor<T>) -> Tensor<T> {
    let (hp, wp) = g.padded();
    let mut xp = Vec::new();
    pad_input(g, n, x.data(), &mut xp);
    Tensor::from_vec(&[n, hp, wp, g.cin], xp)
}

/// Sets a two-parameter layer's weight and bias to uniform values drawn from `r` (in that
/// order, at the layer's own shapes); returns them.
pub fn random_params<T: Float>(
    layer: &mut dyn Layer<T>, r: &mut impl Rng,
) -> (Tensor<T>, Tensor<T>) {
    let shapes: Vec<Vec<usize>> = layer
        .params()
        .iter()
        .map(|p| p.value.shape().to_vec())
        .collect();
    assert_eq!(shapes.len(), 2, "a weight and a bias");
    let (w, b) = (uniform(&shapes[0], r), uniform(&shapes[1], r));
    set_params(layer, &[&w, &b]);
    (w, b)
}

/// Gives `layer` random parameters ([`random_params`]), runs it forward on an `x` of `x_shape`
/// and backward with a `dY` of `dy_shape` (uniform, drawn from `r` after the parameters), and
/// appends its output, input gradient and weight gradient to `out`.
pub fn forward_backward_into(
    layer: &mut dyn Layer<f32>, x_shape: &[usize], dy_shape: &[usize], r: &mut impl Rng,
    out: &mut Vec<f32>,
) {
    random_params(layer, r);
    let x = uniform::<f32>(x_shape, r);
    let dy = uniform::<f32>(dy_shape, r);
    layer.forward(&x);
    layer.backward(&x, &dy, true);
    out.extend_from_slice(layer.output().data());
    out.extend_from_slice(layer.input_grad().data());
    out.extend_from_slice(layer.params()[0].grad.data());
}

/// What [`forward_backward_into`] appends for `conv` on `n` images, then for a 700 → 130 dense
/// layer on 9 rows, both at `precision`, drawing from `r`.
pub fn conv_and_dense_passes(
    mut conv: Conv2d<f32>, n: usize, precision: Precision, r: &mut impl Rng,
) -> Vec<f32> {
    let mut out = Vec::new();
    let g = conv.geom;
    conv.set_precision(precision);
    forward_backward_into(
        &mut conv,
        &[n, g.h, g.w, g.cin],
        &[n, g.oh, g.ow, g.cout],
        r,
        &mut out,
    );
    let mut dense = Dense::<f32>::new("d", 700, 130);
    dense.set_precision(precision);
    forward_backward_into(&mut dense, &[9, 700], &[9, 130], r, &mut out);
    out
}

/// Asserts that `run` gives the same result on rayon pools of 1, 2 and 3 threads.
pub fn same_on_1_2_3_threads<R: PartialEq + std::fmt::Debug + Send>(run: impl Fn() -> R + Sync) {
    let on = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(&run)
    };
    let one = on(1);
    assert_eq!(one, on(2));
    assert_eq!(one, on(3));
}

/// The values as f64.
pub fn f64s(v: &[f32]) -> Vec<f64> {
    v.iter().map(|&x| f64::from(x)).collect()
}

/// The absolute values as f64.
pub fn abs64(v: &[f32]) -> Vec<f64> {
    v.iter().map(|&x| f64::from(x).abs()).collect()
}

/// `γ_N = N·u/(1 − N·u)` for f32 (`u = 2⁻²⁴`): a sum of `N` rounded additions (or fused
/// multiply-adds) is within `γ_N·Σ|terms|` of the exact sum, in any order (Higham, Accuracy and
/// Stability of Numerical Algorithms, §3.1).
pub fn gamma(n: usize) -> f64 {
    let nu = n as f64 * f64::powi(2.0, -24);
    nu / (1.0 - nu)
}

/// The article's preset on the vanilla pipeline (one frame a state, no stacking), the base of
/// the small hand-checked agents.
pub fn vanilla_config() -> invaders::dqn::Config {
    let mut c = invaders::dqn::Config::preset(invaders::dqn::Preset::Article);
    c.pipeline = invaders::env::Pipeline::Vanilla;
    c
}

/// A toy game's step: one life, one frame, and the given reward and ends.
pub fn toy_step(reward: f32, terminal: bool, truncated: bool) -> invaders::env::StepResult {
    invaders::env::StepResult {
        reward,
        terminal,
        truncated,
        lives: 1,
        frames: 1,
    }
}

/// [`vanilla_config`] cut down for a toy game: a replay memory of `replay_capacity` entries,
/// batches of `batch_size`, learning from agent step `learning_starts`, the target network copied
/// every `target_update` steps, and `seed`.
pub fn small_config(
    replay_capacity: usize, batch_size: usize, learning_starts: u64, target_update: u64, seed: u64,
) -> invaders::dqn::Config {
    let mut c = vanilla_config();
    c.replay_capacity = replay_capacity;
    c.batch_size = batch_size;
    c.learning_starts = learning_starts;
    c.target_update = target_update;
    c.seed = seed;
    c
}

/// The article's three convolutions: `(h, w, cin, cout, k, s)`, each a `k × k` filter of
/// stride `s`, SAME.
pub const ARTICLE_CONVS: [(usize, usize, usize, usize, usize, usize); 3] = [
    (88, 80, 4, 32, 8, 4),
    (22, 20, 32, 64, 4, 2),
    (11, 10, 64, 64, 3, 1),
];

/// The 256-entry table that maps each byte to its own value, for `Replay::sample`.
pub fn identity_table() -> [f32; 256] {
    std::array::from_fn(|i| i as f32)
}

/// The reference convolution's bordered output `border(act(conv(x, W) + b))` (`act` the ReLU
/// if `relu`) for a batch of `n`, and where each output pixel starts in it.
#[allow(clippy::too_many_arguments)]
pub fn reference_output<T: Float>(
    g: &ConvGeom, n: usize, x: &[T], w: &[T], b: &[T], border: Border, relu: bool,
) -> (Vec<T>, Vec<usize>) {
    let c = g.cout;
    let z = reference_forward(g, n, x, w, b, false);
    let (hb, wb) = border.around(g.oh, g.ow);
    let mut at = Vec::new();
    border.interior_offsets(n, g.oh, g.ow, c, &mut at);
    let mut y = vec![T::zero(); n * hb * wb * c];
    for (zrow, &o) in z.chunks_exact(c).zip(&at) {
        for (yv, &zv) in y[o..o + c].iter_mut().zip(zrow) {
            *yv = if relu { zv.max(T::zero()) } else { zv };
        }
    }
    (y, at)
}

/// `dZ = dY ⊙ [y > 0]` (just `dY` without `relu`) at the output pixels starting at `at`, `c`
/// channels each, with the ReLU's mask from the layer's own output `y`: a fast kernel rounds
/// differently from the reference, and a sum within rounding of zero may fall on either side.
pub fn reference_dz<T: Float>(dy: &[T], y: &[T], at: &[usize], c: usize, relu: bool) -> Vec<T> {
    let mut dz = vec![T::zero(); at.len() * c];
    for (dzrow, &o) in dz.chunks_exact_mut(c).zip(at) {
        let (d, yv) = (&dy[o..o + c], &y[o..o + c]);
        for ((dz, &g), &yv) in dzrow.iter_mut().zip(d).zip(yv) {
            *dz = if !relu || yv > T::zero() {
                g
            } else {
                T::zero()
            };
        }
    }
    dz
}

/// Whether this host should run the AVX512-BF16 loop: AVX-512 as the other kernels,
/// AVX512-BF16, and `INVADERS_NO_BF16` unset; says once why not.
pub fn bf16_expected() -> bool {
    #[cfg(target_arch = "x86_64")]
    let has = is_x86_feature_detected!("avx512bf16");
    #[cfg(not(target_arch = "x86_64"))]
    let has = false;
    let off = std::env::var_os("INVADERS_NO_BF16").is_some();
    let on = avx512_expected() && has && !off;
    if !on && (!has || off) {
        static NOTE: std::sync::Once = std::sync::Once::new();
        NOTE.call_once(|| {
            let why = if off {
                "INVADERS_NO_BF16 is set"
            } else {
                "this CPU lacks avx512bf16"
            };
            eprintln!("note: {why}: the bf16 tests check the reference loop")
        });
    }
    assert_eq!(invaders::tensor::cpu::avx512_bf16(), on);
    on
}
