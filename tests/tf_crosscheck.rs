//! Cross-check against an independent framework: TensorFlow 2.21.
//!
//! `tools/tf_reference.py` wrote `tests/data/tf_reference.safetensors`: inputs, weights, upstream
//! gradients, outputs and all gradients (computed by `tf.GradientTape`) for the article's three
//! convolutions (88x80x4 input, SAME), an uneven-SAME and a VALID convolution, both dense layers,
//! the whole Q-network, three Keras Adam steps and the two losses.
//!
//! Tolerance: every f32 result must match TensorFlow's to `1e-5 · max|reference|` (elementwise,
//! scaled by the tensor's largest value; the sums run over up to 7040 terms, whose f32 rounding in
//! a different order is around 1e-6 of the scale). The f64 results, computed by TensorFlow in f64,
//! must match to `1e-12 · max|reference|`.

mod common;

use invaders::dqn::article_qnet;
use invaders::layers::init::VarianceScaling;
use invaders::layers::loss::{huber, mse};
use invaders::layers::{Conv2d, Dense, Layer, Param};
use invaders::optim::Adam;
use invaders::tensor::{ConvGeom, Float, Padding, Tensor};
use safetensors::{Dtype, SafeTensors};

const F32_TOL: f64 = 1e-5;
const F64_TOL: f64 = 1e-12;

fn file() -> Vec<u8> {
    std::fs::read(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/tests/data/tf_reference.safetensors"
    ))
    .expect("tests/data/tf_reference.safetensors")
}

fn load<T: Float>(st: &SafeTensors, name: &str) -> Tensor<T> {
    let v = st.tensor(name).unwrap_or_else(|_| panic!("missing {name}"));
    let want = if T::DTYPE == "F32" {
        Dtype::F32
    } else {
        Dtype::F64
    };
    assert_eq!(v.dtype(), want, "{name}: dtype");
    let data: Vec<T> = bytemuck::pod_collect_to_vec(v.data());
    Tensor::from_vec(v.shape(), data)
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

/// Runs one layer forward and backward on the stored case and compares y, dx, dw, db.
fn check_case<T: Float>(
    st: &SafeTensors, case: &str, suffix: &str, layer: &mut dyn Layer<T>, tol: f64,
) {
    let get = |k: &str| load::<T>(st, &format!("{case}.{k}{suffix}"));
    let x = get("x");
    set(&mut layer.params_mut()[0], &get("w"));
    set(&mut layer.params_mut()[1], &get("b"));
    layer.forward(&x);
    assert_matches(
        &format!("{case}{suffix}.y"),
        layer.output().data(),
        &get("y"),
        tol,
    );
    layer.backward(&x, &get("dy"), true);
    assert_matches(
        &format!("{case}{suffix}.dx"),
        layer.input_grad().data(),
        &get("dx"),
        tol,
    );
    assert_matches(
        &format!("{case}{suffix}.dw"),
        layer.params()[0].grad.data(),
        &get("dw"),
        tol,
    );
    assert_matches(
        &format!("{case}{suffix}.db"),
        layer.params()[1].grad.data(),
        &get("db"),
        tol,
    );
}

/// `(name, input h, w, cin, cout, kh, kw, stride, padding)` of each stored convolution.
const CONVS: [(&str, [usize; 7], usize, Padding); 5] = [
    ("conv1", [88, 80, 4, 32, 8, 8, 0], 4, Padding::Same),
    ("conv2", [22, 20, 32, 64, 4, 4, 0], 2, Padding::Same),
    ("conv3", [11, 10, 64, 64, 3, 3, 0], 1, Padding::Same),
    ("conv_odd", [9, 7, 3, 5, 4, 4, 0], 3, Padding::Same),
    ("conv_valid", [10, 9, 2, 3, 3, 2, 0], 2, Padding::Valid),
];

fn conv_layer<T: Float>(spec: &(&str, [usize; 7], usize, Padding)) -> Conv2d<T> {
    let (name, [h, w, cin, cout, kh, kw, _], s, pad) = *spec;
    Conv2d::new(
        name,
        ConvGeom::new(h, w, cin, cout, kh, kw, (s, s), pad).unwrap(),
    )
}

#[test]
fn convolutions_match_tensorflow() {
    let bytes = file();
    let st = SafeTensors::deserialize(&bytes).unwrap();
    for spec in &CONVS {
        check_case::<f32>(&st, spec.0, "", &mut conv_layer(spec), F32_TOL);
        check_case::<f64>(&st, spec.0, ".f64", &mut conv_layer(spec), F64_TOL);
    }
}

#[test]
fn dense_layers_match_tensorflow() {
    let bytes = file();
    let st = SafeTensors::deserialize(&bytes).unwrap();
    check_case::<f32>(
        &st,
        "dense1",
        "",
        &mut Dense::new("dense1", 7040, 128),
        F32_TOL,
    );
    check_case::<f32>(
        &st,
        "dense2",
        "",
        &mut Dense::new("dense2", 128, 6),
        F32_TOL,
    );
    check_case::<f64>(
        &st,
        "dense2",
        ".f64",
        &mut Dense::new("dense2", 128, 6),
        F64_TOL,
    );
}

#[test]
fn article_qnet_matches_tensorflow() {
    let bytes = file();
    let st = SafeTensors::deserialize(&bytes).unwrap();
    let mut net = article_qnet::<f32>([88, 80, 4], 6, &VarianceScaling::HE, &mut common::rng(0));
    for p in net.params_mut() {
        let t = load(&st, &format!("qnet.{}", p.name));
        set(p, &t);
    }
    let x = load::<f32>(&st, "qnet.x");
    net.zero_grad();
    assert_matches(
        "qnet.q",
        net.forward(&x).data(),
        &load(&st, "qnet.q"),
        F32_TOL,
    );
    let dx = net.backward(&x, &load(&st, "qnet.dq"), true).unwrap();
    assert_matches("qnet.dx", dx.data(), &load(&st, "qnet.dx"), F32_TOL);
    for p in net.params() {
        assert_matches(
            &p.name,
            p.grad.data(),
            &load(&st, &format!("qnet.grad.{}", p.name)),
            F32_TOL,
        );
    }
}

#[test]
fn adam_matches_keras() {
    let bytes = file();
    let st = SafeTensors::deserialize(&bytes).unwrap();
    let mut p = Param::<f32>::zeros("w".into(), &[5, 3]);
    set(&mut p, &load(&st, "adam.w0"));
    let mut adam = Adam::new(1e-3);
    for t in 1..=3 {
        p.grad
            .data_mut()
            .copy_from_slice(load::<f32>(&st, &format!("adam.g{t}")).data());
        adam.step(std::iter::once(&mut p));
        assert_matches(
            &format!("adam.w{t}"),
            p.value.data(),
            &load(&st, &format!("adam.w{t}")),
            1e-6,
        );
    }
}

#[test]
fn losses_match_keras() {
    let bytes = file();
    let st = SafeTensors::deserialize(&bytes).unwrap();
    let (pred, target) = (
        load::<f32>(&st, "loss.pred"),
        load::<f32>(&st, "loss.target"),
    );
    let mut grad = vec![0.0f32; pred.len()];
    let l = mse(pred.data(), target.data(), &mut grad);
    assert_matches("mse", &[l], &load(&st, "loss.mse"), 1e-6);
    assert_matches("mse grad", &grad, &load(&st, "loss.mse_grad"), 1e-6);
    let l = huber(pred.data(), target.data(), 1.0, &mut grad);
    assert_matches("huber", &[l], &load(&st, "loss.huber"), 1e-6);
    assert_matches("huber grad", &grad, &load(&st, "loss.huber_grad"), 1e-6);
}
