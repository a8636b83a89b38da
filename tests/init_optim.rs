//! Initialisers and optimizers: statistics of VarianceScaling, Adam and SGD against their
//! closed forms, clipping by global norm.

mod common;

use common::rng;
use invaders::layers::init::{Distribution, FanMode, VarianceScaling, TRUNCATED_NORMAL_STDDEV};
use invaders::layers::{Conv2d, Dense, Flatten, Layer, Param, Relu, Sequential};
use invaders::optim::{clip_grad_norm, global_grad_norm, Adam, Sgd};
use invaders::tensor::{ConvGeom, Padding, Tensor};

fn moments(t: &Tensor<f64>) -> (f64, f64, f64) {
    let n = t.len() as f64;
    let mean = t.data().iter().sum::<f64>() / n;
    let var = t.data().iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n;
    let maxabs = t.data().iter().fold(0.0f64, |m, v| m.max(v.abs()));
    (mean, var, maxabs)
}

#[test]
fn fans_follow_tensorflow() {
    assert_eq!(VarianceScaling::fans(&[8, 8, 4, 32]), (256.0, 2048.0));
    assert_eq!(VarianceScaling::fans(&[7040, 128]), (7040.0, 128.0));
    assert_eq!(VarianceScaling::fans(&[5]), (5.0, 5.0));
}

/// Each distribution and mode has the variance `scale / fan` (within sampling error of 200 000
/// draws: the standard error of a variance estimate is about `var·sqrt(2/n)` = 0.3%), and the
/// truncated normal never exceeds two of its (pre-correction) standard deviations.
#[test]
fn variance_scaling_has_the_right_variance() {
    let shape = [5, 5, 40, 200]; // fan_in 1000, fan_out 5000: 200 000 weights
    for dist in [
        Distribution::TruncatedNormal,
        Distribution::UntruncatedNormal,
        Distribution::Uniform,
    ] {
        for (mode, fan) in [
            (FanMode::FanIn, 1000.0),
            (FanMode::FanOut, 5000.0),
            (FanMode::FanAvg, 3000.0),
        ] {
            let vs = VarianceScaling {
                scale: 2.0,
                mode,
                distribution: dist,
            };
            let mut t = Tensor::<f64>::zeros(&shape);
            vs.fill(&mut t, &mut rng(11));
            let (mean, var, maxabs) = moments(&t);
            let want = 2.0 / fan;
            assert!(
                mean.abs() < 5.0 * (want / t.len() as f64).sqrt(),
                "{dist:?} {mode:?} mean {mean}"
            );
            assert!(
                (var / want - 1.0).abs() < 0.015,
                "{dist:?} {mode:?}: variance {var} vs {want}"
            );
            let bound = match dist {
                Distribution::TruncatedNormal => 2.0 * want.sqrt() / TRUNCATED_NORMAL_STDDEV,
                Distribution::Uniform => (3.0 * want).sqrt(),
                Distribution::UntruncatedNormal => f64::INFINITY,
            };
            assert!(maxabs <= bound, "{dist:?}: {maxabs} > {bound}");
        }
    }
}

#[test]
fn initialisation_is_seeded() {
    let mut a = Tensor::<f32>::zeros(&[3, 3, 2, 4]);
    let mut b = Tensor::<f32>::zeros(&[3, 3, 2, 4]);
    VarianceScaling::HE.fill(&mut a, &mut rng(5));
    VarianceScaling::HE.fill(&mut b, &mut rng(5));
    assert_eq!(a, b);
    VarianceScaling::HE.fill(&mut b, &mut rng(6));
    assert_ne!(a, b);
}

/// Adam against the textbook form with bias-corrected moments (`m̂ = m/(1−β₁ᵗ)`,
/// `v̂ = v/(1−β₂ᵗ)`, `θ −= lr·m̂/(sqrt(v̂) + ε̂)` with `ε̂ = ε/sqrt(1−β₂ᵗ)`, which is algebraically
/// TensorFlow's form), computed independently in f64 over 50 steps of varying gradients.
#[test]
#[allow(clippy::needless_range_loop)] // four parallel arrays, indexed alike
fn adam_matches_closed_form() {
    let (mut m, mut v) = ([0.0f64; 4], [0.0f64; 4]);
    let adam = against_reference(Adam::new(0.01), |t, g, w| {
        for i in 0..4 {
            m[i] = 0.9 * m[i] + 0.1 * g[i];
            v[i] = 0.999 * v[i] + 0.001 * g[i] * g[i];
            let mh = m[i] / (1.0 - 0.9f64.powi(t));
            let vh = v[i] / (1.0 - 0.999f64.powi(t));
            let eps_hat = 1e-8 / (1.0 - 0.999f64.powi(t)).sqrt();
            w[i] -= 0.01 * mh / (vh.sqrt() + eps_hat);
        }
    });
    assert_eq!(adam.t, 50);
}

/// Runs `adam` for 50 steps on four weights starting at `[0.5, −1, 2, 0]`, with gradients
/// `g_i(t) = sin(7t + 3i)·(i + 1)`, beside `reference(t, g, w)`, which applies step `t` to its
/// own copy `w` in f64; after each step the two agree to 1e-12. Returns the optimiser.
fn against_reference(
    mut adam: Adam<f64>, mut reference: impl FnMut(i32, &[f64; 4], &mut [f64; 4]),
) -> Adam<f64> {
    let mut w = [0.5f64, -1.0, 2.0, 0.0];
    let mut p = Param::<f64>::zeros("w".into(), &[4]);
    p.value.data_mut().copy_from_slice(&w);
    for t in 1..=50 {
        let g: [f64; 4] =
            std::array::from_fn(|i| ((t * 7 + i as i32 * 3) as f64).sin() * (i + 1) as f64);
        p.grad.data_mut().copy_from_slice(&g);
        assert!(adam.step(std::iter::once(&mut p)), "step {t}: all finite");
        reference(t, &g, &mut w);
        for (&ours, &want) in p.value.data().iter().zip(&w) {
            assert!((ours - want).abs() < 1e-12, "step {t}: {ours} vs {want}");
        }
    }
    adam
}

/// Rectified Adam against `torch.optim.RAdam`'s form, computed independently in f64 over 50
/// steps: `m̂ = m/(1−β₁ᵗ)`; `ρ_t = ρ∞ − 2tβ₂ᵗ/(1−β₂ᵗ)` with `ρ∞ = 2/(1−β₂) − 1`; while
/// `ρ_t ≤ 5` (steps 1 to 5 at β₂ = 0.999) the step is `lr·m̂`, after it
/// `lr·m̂·r_t·sqrt(1−β₂ᵗ)/(sqrt(v) + ε)` with `r_t` the variance rectification. Also checks the
/// first rectified factor against its value worked by hand: at t = 6, `ρ_6 ≈ 5.9942`,
/// `r_6 ≈ 0.0258`.
#[test]
#[allow(clippy::needless_range_loop)] // four parallel arrays, indexed alike
fn radam_matches_closed_form() {
    let mut adam = Adam::new(0.01);
    adam.rectified = true;
    let (mut m, mut v) = ([0.0f64; 4], [0.0f64; 4]);
    let (b1, b2, lr, eps) = (0.9f64, 0.999f64, 0.01f64, 1e-8f64);
    let rho_inf = 2.0 / (1.0 - b2) - 1.0;
    let mut adaptive_steps = 0;
    against_reference(adam, |t, g, w| {
        let rho = rho_inf - 2.0 * t as f64 * b2.powi(t) / (1.0 - b2.powi(t));
        let r = ((rho - 4.0) * (rho - 2.0) * rho_inf / ((rho_inf - 4.0) * (rho_inf - 2.0) * rho))
            .sqrt();
        if t == 6 {
            assert!((rho - 5.9942).abs() < 1e-3, "rho_6 = {rho}");
            assert!((r - 0.0258).abs() < 1e-3, "r_6 = {r}");
        }
        adaptive_steps += (rho > 5.0) as u32;
        for i in 0..4 {
            m[i] = b1 * m[i] + (1.0 - b1) * g[i];
            v[i] = b2 * v[i] + (1.0 - b2) * g[i] * g[i];
            let mh = m[i] / (1.0 - b1.powi(t));
            w[i] -= if rho > 5.0 {
                lr * mh * r * (1.0 - b2.powi(t)).sqrt() / (v[i].sqrt() + eps)
            } else {
                lr * mh
            };
        }
    });
    assert_eq!(adaptive_steps, 45, "steps 6 to 50 adaptive");
}

/// `Adam::step` says whether every weight it wrote is finite (the divergence guard's check), and
/// still updates every weight when one is not: here a NaN gradient in the first of two 20 000-value
/// parameters' chunks, and an infinite weight in the second's last chunk.
#[test]
fn adam_reports_a_non_finite_weight_and_updates_the_rest() {
    let n = 20_000; // more than one of Adam's 16 384-value chunks
    let mut a = Param::<f32>::zeros("a".into(), &[n]);
    let mut b = Param::<f32>::zeros("b".into(), &[n]);
    a.grad.data_mut().fill(1.0);
    b.grad.data_mut().fill(1.0);
    let mut adam = Adam::new(0.01f32);
    assert!(adam.step([&mut a, &mut b].into_iter()));
    a.grad.data_mut()[0] = f32::NAN;
    assert!(!adam.step([&mut a, &mut b].into_iter()));
    assert!(a.value.data()[0].is_nan());
    // Every other weight took its second step of −lr·m̂/(sqrt(v̂) + ε̂) = −0.01 (a constant gradient).
    for (i, &w) in a.value.data()[1..].iter().chain(b.value.data()).enumerate() {
        assert!((w + 0.02).abs() < 1e-6, "weight {i}: {w}");
    }
    // A weight already infinite (finite moments): reported; the others step; once it is
    // finite again, so is the report.
    let mut c = Param::<f32>::zeros("c".into(), &[n]);
    let mut d = Param::<f32>::zeros("d".into(), &[n]);
    c.grad.data_mut().fill(1.0);
    d.grad.data_mut().fill(1.0);
    d.value.data_mut()[n - 1] = f32::INFINITY;
    let mut adam = Adam::new(0.01f32);
    assert!(!adam.step([&mut c, &mut d].into_iter()));
    assert!((c.value.data()[n - 1] + 0.01).abs() < 1e-6);
    assert!((d.value.data()[0] + 0.01).abs() < 1e-6);
    d.value.data_mut()[n - 1] = 0.0;
    assert!(adam.step([&mut c, &mut d].into_iter()));
}

#[test]
fn sgd_and_clipping() {
    // A dense layer 2 -> 1: a weight of 2 values (set to 0) and a bias of 1, with gradients
    // (3, 0) and 4.
    let mut net = Sequential::<f64>::new();
    net.push(Dense::new("d", 2, 1));
    {
        let mut ps = net.params_mut();
        let w = ps.next().unwrap();
        w.value.fill_zero();
        w.grad.data_mut().copy_from_slice(&[3.0, 0.0]);
        ps.next().unwrap().grad.data_mut().copy_from_slice(&[4.0]);
    }
    assert_eq!(global_grad_norm(&net), 5.0);
    // Below the threshold nothing changes.
    assert_eq!(clip_grad_norm(&mut net, 10.0), 5.0);
    assert_eq!(net.params().nth(1).unwrap().grad.data(), &[4.0]);
    // Above it the whole vector is scaled to the threshold.
    assert_eq!(clip_grad_norm(&mut net, 1.0), 5.0);
    assert!((global_grad_norm(&net) - 1.0).abs() < 1e-15);
    let g: Vec<f64> = net.params().flat_map(|p| p.grad.data().to_vec()).collect();
    assert!(
        (g[0] - 0.6).abs() < 1e-15 && g[1] == 0.0 && (g[2] - 0.8).abs() < 1e-15,
        "{g:?}"
    );
    Sgd::new(0.5).step(net.params_mut());
    let v: Vec<f64> = net.params().flat_map(|p| p.value.data().to_vec()).collect();
    assert!(
        (v[0] + 0.3).abs() < 1e-15 && (v[2] + 0.4).abs() < 1e-15,
        "{v:?}"
    );
}

/// `Adam::step_net` (the train step's, by [`Sequential::visit_params_mut`]) is `Adam::step`
/// over `params_mut()` bit for bit, three steps of a network with a residual block (whose
/// parameters are its convolutions'), a layer normalisation and a dense layer; and the visits
/// see the parameters in `params()`'s order. `Sequential::copy_params_from`, which pairs them by
/// the same visits, copies every one and refuses another architecture.
#[test]
fn adam_on_a_network_is_adam_over_its_parameter_list() {
    let net = || {
        let mut net = Sequential::<f64>::new();
        net.push(invaders::layers::Residual::new("block", [5, 4, 3]));
        net.push(invaders::layers::LayerNorm::new("ln", &[5, 4, 3]));
        net.push(Flatten::new("flat"));
        net.push(Dense::new("d", 60, 2));
        net
    };
    let (mut a, mut b) = (net(), net());
    let mut names = Vec::new();
    a.visit_params(|p| names.push(p.name.clone()));
    let listed: Vec<String> = a.params().map(|p| p.name.clone()).collect();
    assert_eq!(names, listed);
    assert_eq!(names.len(), 8, "{names:?}");
    let (mut adam_a, mut adam_b) = (Adam::new(0.01), Adam::new(0.01));
    let mut r = rng(4);
    let x = common::uniform::<f64>(&[2, 5, 4, 3], &mut r);
    let dy = common::uniform::<f64>(&[2, 2], &mut r);
    for _ in 0..3 {
        for (net, adam, by_list) in [(&mut a, &mut adam_a, true), (&mut b, &mut adam_b, false)] {
            net.zero_grad();
            net.forward(&x);
            net.backward(&x, &dy, false);
            assert!(if by_list {
                adam.step(net.params_mut())
            } else {
                adam.step_net(net)
            });
        }
    }
    for (pa, pb) in a.params().zip(b.params()) {
        assert_eq!(pa.value.data(), pb.value.data(), "{}", pa.name);
    }
    assert_eq!((adam_a.t, adam_a.m.len()), (adam_b.t, 8));
    // Copying parameters (the target network's update) takes every one, in place, across a
    // layer made of layers; another architecture is refused.
    let mut c = net();
    c.copy_params_from(&a);
    for (pa, pc) in a.params().zip(c.params()) {
        assert_eq!(pa.value.data(), pc.value.data(), "{}", pa.name);
    }
    let mut other = Sequential::<f64>::new();
    other.push(invaders::layers::Residual::new("block", [5, 4, 3]));
    other.push(invaders::layers::LayerNorm::new("ln", &[5, 4, 3]));
    other.push(Flatten::new("flat"));
    other.push(Dense::new("e", 60, 2));
    let refused =
        std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| other.copy_params_from(&a)));
    assert!(refused.is_err(), "a differently named layer is refused");
}

/// A dense layer and a convolution start from the article's He initialiser without being told:
/// drawn from a generator seeded by the name (the same layer twice starts the same, another
/// name differently), bias zero, and the weights' variance near `2 / fan_in`. `init` draws them
/// again from the caller's generator, exactly as `VarianceScaling::fill` does.
#[test]
fn layers_start_from_he_drawn_by_their_name() {
    let variance = |t: &Tensor<f64>| t.data().iter().map(|v| v * v).sum::<f64>() / t.len() as f64;
    let a = Dense::<f64>::new("a", 400, 300);
    assert_eq!(
        a.params()[0].value,
        Dense::<f64>::new("a", 400, 300).params()[0].value
    );
    assert_ne!(
        a.params()[0].value,
        Dense::<f64>::new("b", 400, 300).params()[0].value
    );
    assert!(a.params()[1].value.data().iter().all(|&b| b == 0.0));
    let v = variance(&a.params()[0].value);
    assert!(
        (v / (2.0 / 400.0) - 1.0).abs() < 0.02,
        "dense: variance {v}"
    );
    let geom = ConvGeom::new(12, 12, 8, 64, 3, 3, (1, 1), Padding::Same).unwrap();
    let c = Conv2d::<f64>::new("c", geom);
    let v = variance(&c.params()[0].value);
    assert!((v / (2.0 / 72.0) - 1.0).abs() < 0.05, "conv: variance {v}");
    assert!(c.params()[1].value.data().iter().all(|&b| b == 0.0));
    let mut want = Tensor::<f64>::zeros(&[400, 300]);
    VarianceScaling::HE.fill(&mut want, &mut rng(9));
    let mine = Dense::<f64>::new("a", 400, 300).init(&VarianceScaling::HE, &mut rng(9));
    assert_eq!(mine.params()[0].value, want);
}

/// A `Sequential` tells each layer its input's shape, so ReLU and Flatten need none: after a
/// 3x3 SAME convolution of a 6x5x2 input to 4 channels, the ReLU's output is `[6, 5, 4]` and
/// the Flatten's `[120]`, the width a dense layer pushed next reads.
#[test]
fn sequential_tells_each_layer_its_input_shape() {
    let mut net = Sequential::<f32>::new();
    net.push(Conv2d::new(
        "conv",
        ConvGeom::new(6, 5, 2, 4, 3, 3, (1, 1), Padding::Same).unwrap(),
    ));
    net.push(Relu::new("relu"));
    assert_eq!(net.output_shape(), [6, 5, 4]);
    net.push(Flatten::new("flat"));
    assert_eq!(net.output_shape(), [120]);
    net.push(Dense::new("out", net.output_len(), 3));
    let y = net.forward(&Tensor::zeros(&[2, 6, 5, 2]));
    assert_eq!(y.shape(), [2, 3]);
}
