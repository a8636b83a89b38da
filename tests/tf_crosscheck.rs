//! Cross-check against an independent framework: TensorFlow 2.21.
//!
//! `tools/tf_reference.py` wrote `tests/data/tf_reference.bin`: TensorFlow's outputs and all
//! gradients (computed by `tf.GradientTape`) for the article's three convolutions (88x80x4 input,
//! SAME), an uneven-SAME and a VALID convolution, both dense layers, four max poolings (the IMPALA
//! encoder's 3x3 stride-2 SAME one, uneven SAME, VALID, and one full of ties), a small IMPALA
//! encoder (its residual blocks included), the whole Q-network, three Keras Adam steps and the
//! two losses. The file holds no inputs: every input,
//! weight and upstream gradient is drawn from its name by [`draw`], here and in the script alike.
//! The two 7040 x 128 weight gradients are stored as a sketch, `dw · R` with `R` drawn `[128, 8]`.
//!
//! Tolerance: every f32 result must match TensorFlow's to `1e-5 · max|reference|` (elementwise,
//! scaled by the tensor's largest value; the sums run over up to 7040 terms, whose f32 rounding in
//! a different order is around 1e-6 of the scale). The f64 results, computed by TensorFlow in f64,
//! must match to `1e-12 · max|reference|`.

mod common;

use invaders::dqn::{article_qnet, impala_encoder};
use invaders::layers::init::VarianceScaling;
use invaders::layers::loss::{huber, mse};
use invaders::layers::{Conv2d, Dense, Layer, MaxPool2d, Param};
use invaders::optim::Adam;
use invaders::tensor::{ConvGeom, Float, Padding, Tensor};
use std::collections::HashMap;

const F32_TOL: f64 = 1e-5;
const F64_TOL: f64 = 1e-12;

/// The reference file: each tensor's dtype (`"f32"` or `"f64"`), shape and little-endian bytes.
struct Reference(HashMap<String, (String, Vec<usize>, Vec<u8>)>);

/// Reads `tests/data/tf_reference.bin`: the line `invaders-tf-reference 1`, `#` comments, one line
/// `NAME DTYPE DIM...` a tensor, the line `end`, then the tensors' values in the lines' order.
fn reference() -> Reference {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/tests/data/tf_reference.bin");
    let bytes = std::fs::read(path).expect(path);
    let end = bytes
        .windows(5)
        .position(|w| w == b"\nend\n")
        .expect("no `end` line")
        + 5;
    let header = std::str::from_utf8(&bytes[..end]).expect("header is text");
    let mut lines = header.lines();
    assert_eq!(lines.next(), Some("invaders-tf-reference 1"), "{path}");
    let (mut at, mut out) = (end, HashMap::new());
    for line in lines.filter(|l| !l.starts_with('#') && *l != "end") {
        let mut words = line.split_whitespace();
        let (name, dtype) = (words.next().unwrap(), words.next().unwrap());
        let shape: Vec<usize> = words.map(|d| d.parse().unwrap()).collect();
        let size = if dtype == "f32" { 4 } else { 8 };
        let len = shape.iter().product::<usize>() * size;
        let data = bytes[at..at + len].to_vec();
        out.insert(name.to_string(), (dtype.to_string(), shape, data));
        at += len;
    }
    assert_eq!(at, bytes.len(), "{path}: trailing bytes");
    Reference(out)
}

impl Reference {
    /// TensorFlow's tensor `name`, in `T` (which must be the stored dtype).
    fn get<T: Float>(&self, name: &str) -> Tensor<T> {
        let (dtype, shape, data) = self.0.get(name).unwrap_or_else(|| panic!("missing {name}"));
        assert_eq!(dtype, &T::DTYPE.to_lowercase(), "{name}: dtype");
        let values = data
            .chunks_exact(std::mem::size_of::<T>())
            .map(|b| match b.len() {
                4 => T::from(f32::from_le_bytes(b.try_into().unwrap())).unwrap(),
                _ => T::from(f64::from_le_bytes(b.try_into().unwrap())).unwrap(),
            })
            .collect();
        Tensor::from_vec(shape, values)
    }
}

/// The inputs' generator, the same as `draw` in `tools/tf_reference.py`: value `i` of tensor
/// `name` is `lo + (hi − lo)·u` rounded to f32, with `u = (z >> 11)·2⁻⁵³` and `z` the SplitMix64
/// of `fnv1a64(name) + (i + 1)·0x9E3779B97F4A7C15`.
fn draw<T: Float>(name: &str, shape: &[usize], lo: f64, hi: f64) -> Tensor<T> {
    let seed = name.bytes().fold(0xCBF2_9CE4_8422_2325_u64, |h, b| {
        (h ^ u64::from(b)).wrapping_mul(0x0100_0000_01B3)
    });
    let values = (1..=shape.iter().product::<usize>() as u64)
        .map(|i| {
            let mut z = seed.wrapping_add(i.wrapping_mul(0x9E37_79B9_7F4A_7C15));
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            z ^= z >> 31;
            let u = (z >> 11) as f64 * 2f64.powi(-53);
            T::from((lo + (hi - lo) * u) as f32).unwrap()
        })
        .collect();
    Tensor::from_vec(shape, values)
}

/// He-uniform weights, as the script draws them: uniform in `±√(6 / fan_in)`.
fn he<T: Float>(name: &str, shape: &[usize], fan_in: usize) -> Tensor<T> {
    let a = (6.0 / fan_in as f64).sqrt();
    draw(name, shape, -a, a)
}

/// `dw · R` in f64, `R = draw("{name}.sketch", [Out, 8])`: what the script stores of a gradient
/// too large to keep whole.
fn sketch<T: Float>(name: &str, dw: &Tensor<T>) -> Vec<T> {
    let out = *dw.shape().last().unwrap();
    let r = draw::<f64>(&format!("{name}.sketch"), &[out, 8], -1.0, 1.0);
    let r = r.data();
    dw.data()
        .chunks(out)
        .flat_map(|row| {
            (0..8).map(move |j| {
                let v: f64 = (0..out)
                    .map(|k| row[k].to_f64().unwrap() * r[k * 8 + j])
                    .sum();
                T::from(v).unwrap()
            })
        })
        .collect()
}

/// Asserts `max |ours − theirs| ≤ tol · max |theirs|`.
fn assert_matches<T: Float>(what: &str, ours: &[T], theirs: &Tensor<T>, tol: f64) {
    assert_eq!(ours.len(), theirs.len(), "{what}: length");
    let scale = theirs
        .data()
        .iter()
        .map(|v| v.to_f64().unwrap().abs())
        .fold(0.0, f64::max);
    let err = ours
        .iter()
        .zip(theirs.data())
        .map(|(a, b)| (a.to_f64().unwrap() - b.to_f64().unwrap()).abs())
        .fold(0.0, f64::max);
    assert!(
        err <= tol * scale,
        "{what}: max error {err:e} > {tol:e} x scale {scale:e}"
    );
}

fn set<T: Float>(p: &mut Param<T>, t: &Tensor<T>) {
    assert_eq!(p.value.shape(), t.shape(), "{}: shape", p.name);
    p.value.data_mut().copy_from_slice(t.data());
}

/// Runs one layer forward and backward on case `case`'s drawn inputs (`x` in ±1, He weights,
/// biases in ±0.1, `dy` in ±1) and compares y, dx, dw (or its sketch) and db with TensorFlow's.
fn check_case<T: Float>(
    re: &Reference, case: &str, suffix: &str, layer: &mut dyn Layer<T>, x_shape: &[usize], tol: f64,
) {
    let theirs = |k: &str| re.get::<T>(&format!("{case}.{k}{suffix}"));
    let x = draw::<T>(&format!("{case}.x"), x_shape, -1.0, 1.0);
    let w_shape = layer.params()[0].value.shape().to_vec();
    let fan_in = w_shape[..w_shape.len() - 1].iter().product();
    set(
        layer.params_mut()[0],
        &he(&format!("{case}.w"), &w_shape, fan_in),
    );
    let b_shape = layer.params()[1].value.shape().to_vec();
    set(
        layer.params_mut()[1],
        &draw(&format!("{case}.b"), &b_shape, -0.1, 0.1),
    );
    layer.forward(&x);
    let y_shape = layer.output().shape().to_vec();
    assert_matches(
        &format!("{case}{suffix}.y"),
        layer.output().data(),
        &theirs("y"),
        tol,
    );
    let dy = draw::<T>(&format!("{case}.dy"), &y_shape, -1.0, 1.0);
    layer.backward(&x, &dy, true);
    assert_matches(
        &format!("{case}{suffix}.dx"),
        layer.input_grad().data(),
        &theirs("dx"),
        tol,
    );
    let dw = &layer.params()[0].grad;
    if dw.len() > 100_000 {
        let ours = sketch(&format!("{case}.dw"), dw);
        assert_matches(
            &format!("{case}{suffix}.dw.sketch"),
            &ours,
            &theirs("dw.sketch"),
            tol,
        );
    } else {
        assert_matches(&format!("{case}{suffix}.dw"), dw.data(), &theirs("dw"), tol);
    }
    assert_matches(
        &format!("{case}{suffix}.db"),
        layer.params()[1].grad.data(),
        &theirs("db"),
        tol,
    );
}

/// `(name, input h, w, cin, cout, kh, kw, stride, padding)` of each stored convolution.
const CONVS: [(&str, [usize; 6], usize, Padding); 5] = [
    ("conv1", [88, 80, 4, 32, 8, 8], 4, Padding::Same),
    ("conv2", [22, 20, 32, 64, 4, 4], 2, Padding::Same),
    ("conv3", [11, 10, 64, 64, 3, 3], 1, Padding::Same),
    ("conv_odd", [9, 7, 3, 5, 4, 4], 3, Padding::Same),
    ("conv_valid", [10, 9, 2, 3, 3, 2], 2, Padding::Valid),
];

#[test]
fn convolutions_match_tensorflow() {
    let re = reference();
    for &(name, [h, w, cin, cout, kh, kw], s, pad) in &CONVS {
        let geom = ConvGeom::new(h, w, cin, cout, kh, kw, (s, s), pad).unwrap();
        let x = [2, h, w, cin];
        check_case::<f32>(&re, name, "", &mut Conv2d::new(name, geom), &x, F32_TOL);
        check_case::<f64>(&re, name, ".f64", &mut Conv2d::new(name, geom), &x, F64_TOL);
    }
}

#[test]
fn dense_layers_match_tensorflow() {
    let re = reference();
    let mut dense1 = Dense::<f32>::new("dense1", 7040, 128);
    check_case(&re, "dense1", "", &mut dense1, &[2, 7040], F32_TOL);
    let mut dense2 = Dense::<f32>::new("dense2", 128, 6);
    check_case(&re, "dense2", "", &mut dense2, &[2, 128], F32_TOL);
    let mut dense2 = Dense::<f64>::new("dense2", 128, 6);
    check_case(&re, "dense2", ".f64", &mut dense2, &[2, 128], F64_TOL);
}

/// `(name, input h, w, c, window k, stride, padding, ties)` of each stored pooling; `ties`
/// rounds the drawn input to `{−1, −½, 0, ½, 1}`, so most windows hold their maximum twice or
/// more and TensorFlow's choice of winner (the first in row-major order) is what is checked.
const POOLS: [(&str, [usize; 5], Padding, bool); 4] = [
    ("pool_impala", [22, 20, 32, 3, 2], Padding::Same, false),
    ("pool_odd", [9, 7, 3, 3, 2], Padding::Same, false),
    ("pool_valid", [10, 9, 2, 3, 2], Padding::Valid, false),
    ("pool_ties", [12, 10, 4, 3, 2], Padding::Same, true),
];

fn check_pool<T: Float>(re: &Reference, spec: &(&str, [usize; 5], Padding, bool), suffix: &str) {
    let &(name, [h, w, c, k, s], pad, ties) = spec;
    // Drawn in f32 and rounded there (half to even, as numpy rounds), then cast exactly.
    let x32 = draw::<f32>(&format!("{name}.x"), &[2, h, w, c], -1.0, 1.0);
    let values = x32.data().iter().map(|&v| match ties {
        true => T::from((v * 2.0).round_ties_even() / 2.0).unwrap(),
        false => T::from(v).unwrap(),
    });
    let x = Tensor::from_vec(x32.shape(), values.collect());
    let tol = if suffix.is_empty() { F32_TOL } else { F64_TOL };
    let mut pool = MaxPool2d::<T>::square(name, [h, w, c], k, s, pad);
    pool.forward(&x);
    let theirs = |what: &str| re.get::<T>(&format!("{name}.{what}{suffix}"));
    assert_matches(
        &format!("{name}{suffix}.y"),
        pool.output().data(),
        &theirs("y"),
        tol,
    );
    let dy = draw::<T>(&format!("{name}.dy"), pool.output().shape(), -1.0, 1.0);
    pool.backward(&x, &dy, true);
    let dx = pool.input_grad().data();
    assert_matches(&format!("{name}{suffix}.dx"), dx, &theirs("dx"), tol);
}

#[test]
fn max_poolings_match_tensorflow() {
    let re = reference();
    for spec in &POOLS {
        check_pool::<f32>(&re, spec, "");
        check_pool::<f64>(&re, spec, ".f64");
    }
}

/// A small IMPALA encoder (`impala_encoder`: two stages of 4 and 8 channels, one residual block
/// each, on 22x20x3 inputs) against the same network built of TensorFlow's ops: its output,
/// input gradient and every parameter's gradient, in f32 and in f64.
#[test]
fn impala_encoder_matches_tensorflow() {
    let re = reference();
    check_encoder::<f32>(&re, "", F32_TOL);
    check_encoder::<f64>(&re, ".f64", F64_TOL);
}

fn check_encoder<T: Float>(re: &Reference, suffix: &str, tol: f64) {
    let he_init = &VarianceScaling::HE;
    let mut net = impala_encoder::<T>([22, 20, 3], &[4, 8], 1, he_init, &mut common::rng(0));
    for p in net.params_mut() {
        let shape = p.value.shape().to_vec();
        let name = format!("encoder.{}", p.name);
        let value = match shape.len() {
            1 => draw(&name, &shape, -0.1, 0.1),
            _ => he(&name, &shape, shape[..shape.len() - 1].iter().product()),
        };
        set(p, &value);
    }
    let x = draw::<T>("encoder.x", &[2, 22, 20, 3], -1.0, 1.0);
    net.zero_grad();
    let theirs = |what: &str| re.get::<T>(&format!("encoder.{what}{suffix}"));
    assert_matches("encoder.y", net.forward(&x).data(), &theirs("y"), tol);
    let dy = draw::<T>("encoder.dy", net.output().shape(), -1.0, 1.0);
    let dx = net.backward(&x, &dy, true).unwrap();
    assert_matches("encoder.dx", dx.data(), &theirs("dx"), tol);
    for p in net.params() {
        let what = format!("grad.{}", p.name);
        assert_matches(&what, p.grad.data(), &theirs(&what), tol);
    }
}

#[test]
fn article_qnet_matches_tensorflow() {
    let re = reference();
    let mut net = article_qnet::<f32>([88, 80, 4], 6, &VarianceScaling::HE, &mut common::rng(0));
    for p in net.params_mut() {
        let shape = p.value.shape().to_vec();
        let name = format!("qnet.{}", p.name);
        let value = if p.name.ends_with(".weight") {
            he(&name, &shape, shape[..shape.len() - 1].iter().product())
        } else {
            draw(&name, &shape, -0.05, 0.05)
        };
        set(p, &value);
    }
    let x = draw::<f32>("qnet.x", &[2, 88, 80, 4], 0.0, 1.0);
    net.zero_grad();
    assert_matches("qnet.q", net.forward(&x).data(), &re.get("qnet.q"), F32_TOL);
    let dq = draw::<f32>("qnet.dq", &[2, 6], -1.0, 1.0);
    let dx = net.backward(&x, &dq, true).unwrap();
    assert_matches("qnet.dx", dx.data(), &re.get("qnet.dx"), F32_TOL);
    for p in net.params() {
        let name = format!("qnet.grad.{}", p.name);
        if p.grad.len() > 100_000 {
            let ours = sketch(&name, &p.grad);
            assert_matches(&name, &ours, &re.get(&format!("{name}.sketch")), F32_TOL);
        } else {
            assert_matches(&name, p.grad.data(), &re.get(&name), F32_TOL);
        }
    }
}

#[test]
fn adam_matches_keras() {
    let re = reference();
    let mut p = Param::<f32>::zeros("w".into(), &[5, 3]);
    set(&mut p, &draw("adam.w0", &[5, 3], -1.0, 1.0));
    let mut adam = Adam::new(1e-3);
    for t in 1..=3 {
        let g = draw::<f32>(&format!("adam.g{t}"), &[5, 3], -1.0, 1.0);
        p.grad.data_mut().copy_from_slice(g.data());
        adam.step(std::iter::once(&mut p));
        let theirs = re.get(&format!("adam.w{t}"));
        assert_matches(&format!("adam.w{t}"), p.value.data(), &theirs, 1e-6);
    }
}

#[test]
fn losses_match_keras() {
    let re = reference();
    let pred = draw::<f32>("loss.pred", &[8], -1.0, 1.0);
    // The script's targets: pred + these offsets, in f32, so both Huber branches are taken.
    let offsets = [0.1f32, -0.5, 0.9, -0.99, 1.5, -2.0, 3.0, -1.2];
    let target: Vec<f32> = pred
        .data()
        .iter()
        .zip(offsets)
        .map(|(p, o)| p + o)
        .collect();
    let mut grad = vec![0.0f32; pred.len()];
    let l = mse(pred.data(), &target, &mut grad);
    assert_matches("mse", &[l], &re.get("loss.mse"), 1e-6);
    assert_matches("mse grad", &grad, &re.get("loss.mse_grad"), 1e-6);
    let l = huber(pred.data(), &target, 1.0, &mut grad);
    assert_matches("huber", &[l], &re.get("loss.huber"), 1e-6);
    assert_matches("huber grad", &grad, &re.get("loss.huber_grad"), 1e-6);
}
