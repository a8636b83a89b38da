//! Gradient checks of the IMPALA encoder's pieces (issue #99): the residual block alone and the
//! encoder as a `Sequential`, against central finite differences in f64 (as `tests/gradcheck.rs`
//! does for the other layers; see `common::check_layer`), and known values of the block.

mod common;

use common::*;
use invaders::dqn::{article_qnet, impala_encoder, qnet, Batch, Config, Encoder, Head, Learner};
use invaders::layers::init::VarianceScaling;
use invaders::layers::{Conv2d, Layer, Residual, Sequential};
use invaders::tensor::Tensor;
use proptest::prelude::*;

proptest! {
    #![proptest_config(ProptestConfig { cases: common::cases(96), ..ProptestConfig::default() })]

    /// `MaxPool2d` (its forward pass a vectorised select, its winners found in the backward
    /// pass) against the plain definition, one loop per output value: windows 1..4 square,
    /// strides 1..3, SAME and VALID, channels 1..19 (runs of 8 and what is left), and values
    /// drawn from 4 levels, so most windows hold ties, which go to the first maximum in
    /// row-major order; `y` and `dX` equal to the bit.
    #[test]
    fn max_pool_matches_its_definition(
        h in 1usize..9, w in 1usize..9, c in 1usize..20, k in 1usize..=4, s in 1usize..=3,
        same in any::<bool>(), n in 1usize..3, seed in any::<u64>(),
    ) {
        use invaders::layers::MaxPool2d;
        use invaders::tensor::{ConvGeom, Padding};
        use rand::Rng;
        let pad = if same { Padding::Same } else { Padding::Valid };
        let Some(g) = ConvGeom::new(h, w, c, c, k, k, (s, s), pad) else {
            return Ok(()); // VALID with a window larger than the image
        };
        let mut r = rng(seed);
        let x = Tensor::<f32>::from_vec(&[n, h, w, c], (0..n * h * w * c).map(|_| r.random_range(0..4) as f32).collect());
        let dy = uniform::<f32>(&[n, g.oh, g.ow, c], &mut r);
        let mut pool = MaxPool2d::<f32>::new("pool", g);
        pool.forward(&x);
        pool.backward(&x, &dy, true);
        let (mut y, mut dx) = (vec![0.0f32; dy.len()], vec![0.0f32; x.len()]);
        for i in 0..n {
            for oy in 0..g.oh {
                for ox in 0..g.ow {
                    for ch in 0..c {
                        let o = ((i * g.oh + oy) * g.ow + ox) * c + ch;
                        let mut best: Option<(f32, usize)> = None;
                        for ky in 0..k {
                            for kx in 0..k {
                                let (iy, ix) = ((oy * s + ky) as isize - g.pad_top as isize, (ox * s + kx) as isize - g.pad_left as isize);
                                if iy < 0 || ix < 0 || iy >= h as isize || ix >= w as isize {
                                    continue;
                                }
                                let at = ((i * h + iy as usize) * w + ix as usize) * c + ch;
                                if best.is_none_or(|(b, _)| x.data()[at] > b) {
                                    best = Some((x.data()[at], at));
                                }
                            }
                        }
                        let (v, at) = best.expect("every window holds a pixel of the image");
                        y[o] = v;
                        dx[at] += dy.data()[o];
                    }
                }
            }
        }
        prop_assert_eq!(pool.output().data(), &y[..]);
        prop_assert_eq!(pool.input_grad().data(), &dx[..]);
    }

    /// The residual block `y = x + conv2(relu(conv1(relu(x))))`: images 1..5 x 1..5, 1..3
    /// channels, batch 1..2, every input and parameter entry. Its two ReLUs have kinks: the
    /// input is drawn at least 1e-3 from zero (relu0), and cases with a pre-activation of conv1
    /// within 1e-3 of zero are redrawn, so no step of `±H` crosses a kink.
    #[test]
    fn residual_gradients(
        h in 1usize..=5, w in 1usize..=5, c in 1usize..=3, n in 1usize..=2, seed in any::<u64>(),
    ) {
        let mut block = Residual::<f64>::new("block", [h, w, c]);
        randomise(&mut block, seed);
        let mut r = rng(seed ^ 1);
        let x = uniform_away_from_zero(&[n, h, w, c], 1e-3, &mut r);
        // conv1's pre-activations: the same convolution without its ReLU, on relu(x).
        let mut plain = Conv2d::<f64>::new("plain", block.geom());
        let conv1: Vec<&Tensor<f64>> = block.params()[..2].iter().map(|p| &p.value).collect();
        set_params(&mut plain, &conv1);
        let a = Tensor::from_vec(x.shape(), x.data().iter().map(|v| v.max(0.0)).collect());
        plain.forward(&a);
        prop_assume!(plain.output().data().iter().all(|z| z.abs() > 1e-3));
        let dy = uniform(&[n, h, w, c], &mut r);
        check_layer(&mut block, &x, &dy, 1000, seed).map_err(TestCaseError::fail)?;
    }
}

/// A block lists its four parameters, conv1's then conv2's, weight before bias, named after
/// the block (the names checkpoints use), the same through `params_mut`.
#[test]
fn residual_params_in_order() {
    let mut block = Residual::<f32>::new("stage2.block1", [5, 4, 3]);
    let want = [
        ("stage2.block1.conv1.weight", vec![3, 3, 3, 3]),
        ("stage2.block1.conv1.bias", vec![3]),
        ("stage2.block1.conv2.weight", vec![3, 3, 3, 3]),
        ("stage2.block1.conv2.bias", vec![3]),
    ];
    let got: Vec<(String, Vec<usize>)> = block
        .params()
        .iter()
        .map(|p| (p.name.clone(), p.value.shape().to_vec()))
        .collect();
    let want: Vec<(String, Vec<usize>)> = want
        .iter()
        .map(|(n, s)| (n.to_string(), s.clone()))
        .collect();
    assert_eq!(got, want);
    let names: Vec<String> = block.params_mut().iter().map(|p| p.name.clone()).collect();
    let want_names: Vec<String> = want.into_iter().map(|(n, _)| n).collect();
    assert_eq!(names, want_names);
    assert_eq!(block.output_shape(), [5, 4, 3]);
    // Two 3x3 C -> C convolutions over every pixel.
    assert_eq!(block.macs(), 2 * 5 * 4 * 3 * 9 * 3);
}

/// With zero weights and biases both convolutions give 0, so `y = x` and `dX = dY`; conv2's
/// bias gradient is `Σ dY` per channel (it adds to every pixel), and every other gradient is 0
/// (`h = relu(0) = 0` multiplies `dW2`, and `W2 = 0` stops the gradient before conv1).
#[test]
fn residual_with_zero_weights_is_the_identity() {
    let mut block = Residual::<f64>::new("block", [3, 4, 2]);
    for p in block.params_mut() {
        p.value.fill_zero();
    }
    let mut r = rng(5);
    let x = uniform::<f64>(&[2, 3, 4, 2], &mut r);
    let dy = uniform::<f64>(&[2, 3, 4, 2], &mut r);
    block.forward(&x);
    assert_eq!(block.output().data(), x.data());
    block.infer(&x);
    assert_eq!(block.output().data(), x.data());
    block.forward(&x);
    block.backward(&x, &dy, true);
    assert_eq!(block.input_grad().data(), dy.data());
    let mut db2 = [0.0; 2];
    for (i, d) in dy.data().iter().enumerate() {
        db2[i % 2] += d;
    }
    let params = block.params();
    assert!(params[0].grad.data().iter().all(|&g| g == 0.0));
    assert!(params[1].grad.data().iter().all(|&g| g == 0.0));
    assert!(params[2].grad.data().iter().all(|&g| g == 0.0));
    for (g, want) in params[3].grad.data().iter().zip(db2) {
        assert!((g - want).abs() < 1e-12, "db2 {g} vs {want}");
    }
}

/// Worked by hand on 1x1 images with one channel: a 3x3 SAME convolution of a 1x1 image reads
/// only its centre tap (the rest is padding), so with centre taps `w1 = 3`, `w2 = 0.5` and
/// biases `b1 = −1`, `b2 = 0.25`, `y = x + 0.5·relu(3·relu(x) − 1) + 0.25`:
/// - `x = 2`: `h = relu(6 − 1) = 5`, `y = 2 + 2.5 + 0.25 = 4.75`, and with `dY = 1`,
///   `dX = 1 + w2·w1 = 2.5`;
/// - `x = −2`: `relu(x) = 0`, `h = relu(−1) = 0`, `y = −2 + 0.25 = −1.75`, `dX = dY = 1`.
///
/// Gradients: `dW2 = Σ h·dY = 5`, `db2 = Σ dY = 2`, `dW1 = Σ w2·[h > 0]·relu(x) = 1`,
/// `db1 = Σ w2·[h > 0] = 0.5` (only the first sample passes conv1's ReLU).
#[test]
fn residual_known_values() {
    let mut block = Residual::<f64>::new("block", [1, 1, 1]);
    let centre = |v: f64| {
        let mut w = vec![0.0; 9];
        w[4] = v;
        Tensor::from_vec(&[3, 3, 1, 1], w)
    };
    let (w1, b1) = (centre(3.0), Tensor::from_vec(&[1], vec![-1.0]));
    let (w2, b2) = (centre(0.5), Tensor::from_vec(&[1], vec![0.25]));
    set_params(&mut block, &[&w1, &b1, &w2, &b2]);
    let x = Tensor::from_vec(&[2, 1, 1, 1], vec![2.0, -2.0]);
    block.forward(&x);
    assert_eq!(block.output().data(), [4.75, -1.75]);
    block.backward(&x, &Tensor::from_vec(&[2, 1, 1, 1], vec![1.0, 1.0]), true);
    assert_eq!(block.input_grad().data(), [2.5, 1.0]);
    let grads: Vec<f64> = block
        .params()
        .iter()
        .map(|p| p.grad.data().iter().sum())
        .collect();
    assert_eq!(grads, [1.0, 0.5, 5.0, 2.0]);
}

/// A small encoder (2 stages of 3 and 2 channels, 1 block each, 7 x 6 x 2 inputs: 7 x 6 → 4 x 3
/// → 2 x 2) end to end through `Sequential`, against finite differences for the input and every
/// entry of every parameter. Biases are non-zero. The values the pools and ReLUs see are
/// continuous draws, so a tie or a kink within the step `H` is improbable, and seed 3 has none.
#[test]
fn impala_encoder_gradients() {
    let mut r = rng(3);
    let mut net: Sequential<f64> =
        impala_encoder([7, 6, 2], &[3, 2], 1, &VarianceScaling::HE, &mut r);
    assert_eq!(net.output_shape(), [2, 2, 2]);
    for p in net.params_mut() {
        if p.name.ends_with(".bias") {
            let t: Tensor<f64> = uniform(p.value.shape(), &mut r);
            for (v, t) in p.value.data_mut().iter_mut().zip(t.data()) {
                *v = 0.1 * t;
            }
        }
    }
    let x = uniform::<f64>(&[2, 7, 6, 2], &mut r);
    let dy = uniform::<f64>(&[2, 2, 2, 2], &mut r);
    let grads = check_sequential(&mut net, &x, &dy, |len, _| (0..len).collect());
    // A zero gradient everywhere would pass trivially: the check must see some signal.
    assert!(grads
        .iter()
        .all(|(_, g)| g.data().iter().any(|&v| v != 0.0)));
}

/// Dopamine's encoder (`[16, 32, 32]`, 2 blocks per stage) on the 88 x 80 x 4 frame: the shapes
/// and multiply-adds its doc comment gives, its parameters in order, and `infer` giving
/// `forward`'s output.
#[test]
fn impala_encoder_on_the_frame() {
    let mut net: Sequential<f32> = impala_encoder(
        [88, 80, 4],
        &[16, 32, 32],
        2,
        &VarianceScaling::HE,
        &mut rng(1),
    );
    let shapes: Vec<(String, Vec<usize>)> = net
        .layers()
        .iter()
        .map(|l| (l.name().to_string(), l.output_shape()))
        .collect();
    // A stage: its convolution's output, then the pool's, which both blocks keep.
    let stage = |s: usize, conv: [usize; 3], pool: [usize; 3]| {
        let named = |layer: &str, shape: [usize; 3]| (format!("stage{s}.{layer}"), shape.to_vec());
        [
            named("conv", conv),
            named("pool", pool),
            named("block1", pool),
            named("block2", pool),
        ]
    };
    let mut want = [
        stage(1, [88, 80, 16], [44, 40, 16]),
        stage(2, [44, 40, 32], [22, 20, 32]),
        stage(3, [22, 20, 32], [11, 10, 32]),
    ]
    .concat();
    want.push(("relu".to_string(), vec![11, 10, 32]));
    assert_eq!(shapes, want);
    assert_eq!(net.macs(), 52_715_520);
    let blocks: usize = net
        .layers()
        .iter()
        .filter(|l| l.name().contains(".block"))
        .map(|l| l.macs())
        .sum();
    assert_eq!(blocks, 36_495_360);
    let one_channel: Sequential<f32> = impala_encoder(
        [88, 80, 1],
        &[16, 32, 32],
        2,
        &VarianceScaling::HE,
        &mut rng(1),
    );
    assert_eq!(one_channel.macs(), 49_674_240);
    // For scale, the article's whole Q-network (6 actions) on the same frame.
    let article: Sequential<f32> = article_qnet([88, 80, 4], 6, &VarianceScaling::HE, &mut rng(1));
    assert_eq!(article.macs(), 12_165_888);
    let names: Vec<String> = net.params().map(|p| p.name.clone()).collect();
    assert_eq!(names.len(), 3 * 2 + 6 * 4);
    assert_eq!(
        names[..6],
        [
            "stage1.conv.weight",
            "stage1.conv.bias",
            "stage1.block1.conv1.weight",
            "stage1.block1.conv1.bias",
            "stage1.block1.conv2.weight",
            "stage1.block1.conv2.bias"
        ]
    );
    assert_eq!(names[29], "stage3.block2.conv2.bias");
    // Weights drawn, biases at zero.
    for p in net.params() {
        let zero = p.value.data().iter().all(|&v| v == 0.0);
        assert_eq!(zero, p.name.ends_with(".bias"), "{}", p.name);
    }
    let x = uniform::<f32>(&[2, 88, 80, 4], &mut rng(2));
    let y = net.forward(&x).clone();
    assert_eq!(y.shape(), [2, 11, 10, 32]);
    assert!(y.data().iter().all(|&v| v >= 0.0) && y.data().iter().any(|&v| v > 0.0));
    let inferred = net.infer(&x).clone();
    assert_close("infer", inferred.data(), y.data(), 1e-5).unwrap();
}

/// The encoder in f32, by whatever kernels the plan picks for this CPU (batch 8 and 32 channels:
/// Winograd for the residual convolutions where it pays), against the same encoder in f64 (the
/// im2col + GEMM path the gradient checks prove): the output, the input gradient and every
/// parameter gradient agree to `1e-3·(1 + m)`, `m` the largest magnitude of the f64 tensor.
#[test]
fn impala_encoder_f32_matches_f64() {
    let mut r = rng(11);
    let (input, channels) = ([16, 12, 4], [8, 32]);
    let mut wide: Sequential<f64> =
        impala_encoder(input, &channels, 1, &VarianceScaling::HE, &mut r);
    let mut narrow: Sequential<f32> =
        impala_encoder(input, &channels, 1, &VarianceScaling::HE, &mut r);
    for (p, q) in narrow.params_mut().zip(wide.params_mut()) {
        let t: Tensor<f64> = uniform(q.value.shape(), &mut r);
        for (v, (w, t)) in p
            .value
            .data_mut()
            .iter_mut()
            .zip(q.value.data_mut().iter_mut().zip(t.data()))
        {
            if q.name.ends_with(".bias") {
                *w = 0.1 * t;
            }
            *v = *w as f32;
        }
    }
    let x = uniform::<f64>(&[8, 16, 12, 4], &mut r);
    let dy = uniform::<f64>(&[8, 4, 3, 32], &mut r);
    let f32s =
        |t: &Tensor<f64>| Tensor::from_vec(t.shape(), t.data().iter().map(|&v| v as f32).collect());
    let f64s = |t: &Tensor<f32>| t.data().iter().map(|&v| v as f64).collect::<Vec<f64>>();
    let (x32, dy32) = (f32s(&x), f32s(&dy));
    wide.zero_grad();
    narrow.zero_grad();
    let y = wide.forward(&x).clone();
    let y32 = narrow.forward(&x32).clone();
    assert_close("y", &f64s(&y32), y.data(), 1e-3).unwrap();
    let dx = wide.backward(&x, &dy, true).unwrap().clone();
    let dx32 = narrow.backward(&x32, &dy32, true).unwrap().clone();
    assert_close("dx", &f64s(&dx32), dx.data(), 1e-3).unwrap();
    for (p, q) in narrow.params().zip(wide.params()) {
        assert_eq!(p.name, q.name);
        assert_close(&p.name, &f64s(&p.grad), q.grad.data(), 1e-3).unwrap();
    }
}

/// The Q-network with `encoder = Impala` (the encoder, dense1 of 8 units, dense2 of 6) on a
/// 9 x 8 x 2 input (→ 5 x 4 → 3 x 2 → 2 x 1), against finite differences at 40 entries of the
/// input and of each parameter. Seed 8 puts no ReLU kink or pooling tie within the step.
#[test]
fn impala_qnet_gradients() {
    let mut r = rng(8);
    let head = Head {
        hidden: 8,
        encoder: Encoder::Impala,
        ..Head::ARTICLE
    };
    let mut net = qnet::<f64>([9, 8, 2], 6, head, &VarianceScaling::HE, &mut r);
    let names: Vec<&str> = net.layers().iter().map(|l| l.name()).collect();
    assert_eq!(names[0], "stage1.conv");
    assert_eq!(names[names.len() - 3..], ["dense1", "relu4", "dense2"]);
    for p in net.params_mut() {
        if p.name.ends_with(".bias") {
            let t: Tensor<f64> = uniform(p.value.shape(), &mut r);
            for (v, t) in p.value.data_mut().iter_mut().zip(t.data()) {
                *v = 0.1 * t;
            }
        }
    }
    let x = uniform::<f64>(&[2, 9, 8, 2], &mut r);
    let dy = uniform::<f64>(&[2, 6], &mut r);
    check_sequential(&mut net, &x, &dy, |len, _| indices(len, 40, &mut r));
}

/// `encoder = "impala"` in a configuration: the learner's network is the encoder and the
/// article's dense layers (dense1 reads 3 520 features), the training batch is laid out inside
/// stage1.conv's one-pixel padding, a training step runs and keeps the weights finite, and
/// `reset_dense` draws dense1 and dense2 afresh, not the encoder. A
/// configuration that asks for the encoder with `layer_norm` or VALID padding is refused.
#[test]
fn impala_config_trains_a_step() {
    let config = Config::resolve(None, Some("encoder = \"impala\"\nbatch_size = 8\n")).unwrap();
    config.validate().unwrap();
    assert_eq!(config.encoder, Encoder::Impala);
    assert!(config.to_toml().contains("encoder = \"impala\""));
    let mut learner = Learner::from_config(&config, 6, &mut rng(1));
    let dense1 = learner
        .online
        .params()
        .find(|p| p.name == "dense1.weight")
        .unwrap();
    assert_eq!(dense1.value.shape(), [3520, 128]);
    let batch = Batch::random(&config, &mut rng(2));
    assert_eq!(batch.states.shape(), [8, 90, 82, 4]);
    let stats = learner.train_step(&batch);
    assert!(stats.loss.is_finite() && stats.grad_norm > 0.0 && stats.weights_finite);
    // reset_dense_at draws the dense layers afresh and keeps the encoder.
    let fresh = qnet::<f32>(
        config.input_shape(),
        6,
        Head::of(&config),
        &VarianceScaling::HE,
        &mut rng(3),
    );
    assert_eq!(learner.reset_dense(&fresh), 4);
    for bad in ["layer_norm = true", "padding = \"valid\""] {
        let text = format!("encoder = \"impala\"\n{bad}\n");
        assert!(Config::resolve(None, Some(&text)).is_err(), "{bad}");
    }
    assert_eq!(
        Config::resolve(None, None).unwrap().encoder,
        Encoder::Article
    );
}

/// `impala_channels` and `impala_blocks` thin the encoder: 8, 16 and 16 channels with one block
/// per stage give that network (dense1 reads 11 x 10 x 16 features, three blocks), whose
/// multiply-adds fall below Dopamine's; out-of-range shapes, and the keys without
/// `encoder = "impala"`, are refused.
#[test]
fn impala_channels_and_blocks_thin_the_encoder() {
    let text = "encoder = \"impala\"\nimpala_channels = [8, 16, 16]\nimpala_blocks = 1\n";
    let config = Config::resolve(None, Some(text)).unwrap();
    assert_eq!(config.impala_channels, [8, 16, 16]);
    assert_eq!(
        Config::resolve(None, Some(&config.to_toml())).unwrap(),
        config
    );
    let head = Head::of(&config);
    let net = qnet::<f32>(
        config.input_shape(),
        6,
        head,
        &VarianceScaling::HE,
        &mut rng(1),
    );
    let names: Vec<&str> = net.layers().iter().map(|l| l.name()).collect();
    assert_eq!(names.iter().filter(|n| n.contains(".block")).count(), 3);
    let dense1 = net.params().find(|p| p.name == "dense1.weight").unwrap();
    assert_eq!(dense1.value.shape(), [11 * 10 * 16, 128]);
    let dopamine = Config::resolve(None, Some("encoder = \"impala\"\n")).unwrap();
    let full = qnet::<f32>(
        dopamine.input_shape(),
        6,
        Head::of(&dopamine),
        &VarianceScaling::HE,
        &mut rng(1),
    );
    assert!(
        net.macs() * 4 < full.macs(),
        "{} vs {}",
        net.macs(),
        full.macs()
    );
    for bad in [
        "encoder = \"impala\"\nimpala_channels = [0, 16, 16]",
        "encoder = \"impala\"\nimpala_channels = [8, 16, 1000]",
        "encoder = \"impala\"\nimpala_blocks = 9",
        "impala_blocks = 1",
        "impala_channels = [8, 16, 16]",
    ] {
        let err = format!("{:#}", Config::resolve(None, Some(bad)).unwrap_err());
        assert!(err.contains("impala_"), "{bad}: {err}");
    }
}
