//! Layer and train-step benchmarks for the article's Q-network.
//!
//! Throughput is reported as criterion "elements" per second where one element is one
//! floating-point operation, so `Gelem/s` reads as GFLOP/s (a multiply-add counts as 2 FLOPs).
//! Compare with `../shared/bench/tf_step.py` run in the same session (TensorFlow's train step) and
//! `peak.c` (the machine's FMA peak).
//!
//! `cargo bench --bench layers` runs everything; `cargo bench --bench layers -- conv1` one layer.
//! Threads: rayon's default (all cores) unless `RAYON_NUM_THREADS` is set; everything runs on a
//! worker of that pool.

use criterion::{criterion_group, BenchmarkId, Criterion, Throughput};
use invaders::dqn::{article_qnet, random_play_inputs, Batch, Config, Learner, Preset};
use invaders::layers::init::VarianceScaling;
use invaders::layers::{Conv2d, Dense, Layer};
use invaders::tensor::{Border, ConvGeom, Padding, Tensor};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::time::Duration;

/// Cache-line-aligned buffers for the kernels (`invaders::CacheAligned`): the library leaves
/// the allocator to the program.
#[global_allocator]
static GLOBAL: invaders::CacheAligned = invaders::CacheAligned;

fn random(shape: &[usize], rng: &mut impl Rng) -> Tensor<f32> {
    let n = shape.iter().product();
    Tensor::from_vec(shape, (0..n).map(|_| rng.random_range(-1.0..1.0)).collect())
}

fn randomise(layer: &mut dyn Layer<f32>, rng: &mut impl Rng) {
    for p in layer.params_mut() {
        for v in p.value.data_mut() {
            *v = rng.random_range(-0.1..0.1);
        }
    }
}

/// Forward, input gradient and weight gradient of one layer at batch 1 and 48.
fn bench_layer(
    c: &mut Criterion, name: &str, make: &dyn Fn() -> Box<dyn Layer<f32>>, in_shape: &[usize],
) {
    let mut group = c.benchmark_group(name);
    group
        .measurement_time(Duration::from_secs(3))
        .warm_up_time(Duration::from_secs(1));
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    for batch in [1usize, 48] {
        let mut layer = make();
        randomise(layer.as_mut(), &mut rng);
        let mut shape = vec![batch];
        shape.extend_from_slice(in_shape);
        let x = random(&shape, &mut rng);
        layer.forward(&x);
        let dy = random(layer.output().shape(), &mut rng);
        let flops = 2 * layer.macs() as u64 * batch as u64;
        group.throughput(Throughput::Elements(flops));
        group.bench_function(BenchmarkId::new("forward", batch), |b| {
            b.iter(|| layer.forward(&x))
        });
        // The weight gradient alone (what the first layer does), then weight + input gradients;
        // the input gradient's cost is the difference.
        group.bench_function(BenchmarkId::new("weight_grad", batch), |b| {
            b.iter(|| layer.backward(&x, &dy, false))
        });
        group.throughput(Throughput::Elements(2 * flops));
        group.bench_function(BenchmarkId::new("weight_and_input_grad", batch), |b| {
            b.iter(|| layer.backward(&x, &dy, true))
        });
    }
    group.finish();
}

/// Each layer of the article's Q-network as `article_qnet` builds it: conv1 SAME with its ReLU
/// and conv2's padding written around its output; conv2 and conv3 VALID over those bordered
/// inputs (at batch 48 all their products by Winograd, input gradients included); dense1 reading
/// conv3's output in place.
fn layers(c: &mut Criterion) {
    let built = |i: usize| -> Box<dyn Layer<f32>> {
        let mut rng = ChaCha8Rng::seed_from_u64(0);
        let net = article_qnet::<f32>([88, 80, 4], 6, &VarianceScaling::HE, &mut rng);
        net.into_layers().swap_remove(i)
    };
    for (i, name) in ["conv1", "conv2", "conv3"].into_iter().enumerate() {
        let shape = match i {
            0 => vec![88, 80, 4],
            1 => vec![24, 22, 32],
            _ => vec![13, 12, 64],
        };
        bench_layer(c, name, &|| built(i), &shape);
    }
    // conv2 and conv3 as built run by Winograd at batches of 8 or more (`Conv2d::with_winograd`),
    // conv1 does not. Here each the other way, to compare: conv1 by F(2×2, 2×2) over 4×4 blocks,
    // conv2 and conv3 by the direct gather GEMM (their input gradients by stride phase). All
    // GFLOP/s count the direct convolution's multiply-adds.
    let other = |i: usize| -> Box<dyn Layer<f32>> {
        let (h, w, cin, cout, k, s) = [
            (88, 80, 4, 32, 8, 4),
            (22, 20, 32, 64, 4, 2),
            (11, 10, 64, 64, 3, 1),
        ][i];
        let name = format!("conv{}", i + 1);
        let same = ConvGeom::new(h, w, cin, cout, k, k, (s, s), Padding::Same).unwrap();
        let conv = if i == 0 {
            // With conv2's padding around its output, as built.
            let next = Border {
                top: 1,
                bottom: 1,
                left: 1,
                right: 1,
            };
            Conv2d::new(&name, same).with_border(next)
        } else {
            let (valid, border) = same.as_valid();
            Conv2d::new(&name, valid).with_input_border(border)
        };
        Box::new(conv.with_relu().with_winograd(i == 0))
    };
    bench_layer(c, "conv1_winograd", &|| other(0), &[88, 80, 4]);
    bench_layer(c, "conv2_direct", &|| other(1), &[24, 22, 32]);
    bench_layer(c, "conv3_direct", &|| other(2), &[13, 12, 64]);
    bench_layer(c, "dense1", &|| built(3), &[11, 10, 64]);
    bench_layer(
        c,
        "dense2",
        &|| Box::new(Dense::<f32>::new("dense2", 128, 6)),
        &[128],
    );
}

/// The article's train step at batch 48 (online forward + backward + Adam, target forward on the
/// next states): 4.33 GFLOP by `../shared/bench/README.md`'s count. And the batch-1 forward
/// used for acting.
fn train_step(c: &mut Criterion) {
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let mut learner = Learner::new([88, 80, 4], 6, 1e-3, 0.97, &mut rng);
    // Laid out as the agent's batches are: inside conv1's padding (a zero border).
    let mut batch = Batch::padded(48, [88, 80, 4], Padding::Same);
    for states in [&mut batch.states, &mut batch.next_states] {
        *states = random(states.shape(), &mut rng);
        batch.border.zero(states.data_mut(), 48, 88, 80, 4);
    }
    for i in 0..48 {
        batch.actions[i] = rng.random_range(0..6);
        batch.rewards[i] = rng.random_range(0.0..1.0);
        batch.dones[i] = rng.random_bool(0.1);
    }
    let macs = learner.online.macs() as u64;
    let first_layer_macs = learner.online.layers()[0].macs() as u64;
    // 3 passes of 48 samples (online forward, weight gradients, target forward) + input
    // gradients of every layer but the first.
    let flops = 2 * 48 * (3 * macs + (macs - first_layer_macs));
    let mut group = c.benchmark_group("train_step");
    group
        .measurement_time(Duration::from_secs(8))
        .warm_up_time(Duration::from_secs(2));
    group.throughput(Throughput::Elements(flops));
    group.bench_function("batch48", |b| b.iter(|| learner.train_step(&batch)));
    let x1 = random(&[1, 88, 80, 4], &mut rng);
    group.throughput(Throughput::Elements(2 * macs));
    group.bench_function("act_forward_batch1", |b| {
        b.iter(|| learner.online.forward(&x1).data()[0])
    });
    // As the agent acts: sparse products where the activations' zeros allow.
    group.bench_function("act_infer_batch1", |b| {
        b.iter(|| learner.online.infer(&x1).data()[0])
    });
    group.finish();
}

/// Acting's sparse products against the dense batch-1 forward pass, for the three layers that
/// read a ReLU's output, as `article_qnet` builds them, on inputs with 2% to 50% nonzero values
/// (a trained network's are 1–5%, an initial one's about 40%). Above a fifth nonzero the
/// convolutions' `infer` goes back to the dense product (after counting the nonzeros), which is
/// where the two cross. And conv1 split into background and difference
/// (`Conv2d::with_background_inference`) on 64 game frames (random play through the `article`
/// pipeline; 5–13% of their pixels differ from the background, 9% typically), cycled as
/// `invaders bench` does, and on frames whose differing pixels are scattered at random over 2% to
/// 25% of places, the worst case for it (dense above an eighth). Throughput counts the dense
/// product's FLOPs.
fn sparse_act(c: &mut Criterion) {
    let mut group = c.benchmark_group("sparse_act");
    group
        .measurement_time(Duration::from_secs(2))
        .warm_up_time(Duration::from_millis(500));
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let mut net = article_qnet::<f32>([88, 80, 4], 6, &VarianceScaling::HE, &mut rng);
    net.forward(&random(&[1, 88, 80, 4], &mut rng));
    let shapes: Vec<Vec<usize>> = net.layers()[..3]
        .iter()
        .map(|l| l.output().shape().to_vec())
        .collect();
    let mut layers = net.into_layers();
    let conv1 = &mut layers[0];
    group.throughput(Throughput::Elements(2 * conv1.macs() as u64));
    let frames = random_play_inputs(
        &Config::preset(Preset::Article),
        64,
        10,
        &mut ChaCha8Rng::seed_from_u64(1),
    )
    .expect("Space Invaders");
    for (pass, name) in [(0, "forward"), (1, "infer")] {
        let mut k = 0;
        group.bench_function(format!("conv1/{name}/frames"), |b| {
            b.iter(|| {
                k = (k + 1) % frames.len();
                if pass == 0 {
                    conv1.forward(&frames[k])
                } else {
                    conv1.infer(&frames[k])
                }
            })
        });
    }
    for percent in [2u32, 10, 15, 20, 25] {
        let mut x = random(&[1, 88, 80, 4], &mut rng);
        for (p, px) in x.data_mut().chunks_exact_mut(4).enumerate() {
            if p == 0 || rng.random_range(0..100) >= percent {
                px.fill(-1.0);
            }
        }
        group.bench_function(format!("conv1/forward/{percent}%"), |b| {
            b.iter(|| conv1.forward(&x))
        });
        group.bench_function(format!("conv1/infer/{percent}%"), |b| {
            b.iter(|| conv1.infer(&x))
        });
    }
    for (i, layer) in layers[1..4].iter_mut().enumerate() {
        // Layer i + 1 reads layer i's output (conv1's, conv2's, conv3's shape).
        let in_shape = &shapes[i];
        let name = ["conv2", "conv3", "dense1"][i];
        group.throughput(Throughput::Elements(2 * layer.macs() as u64));
        for percent in [2u32, 10, 15, 20, 25, 50] {
            let mut x = random(in_shape, &mut rng);
            for v in x.data_mut() {
                if rng.random_range(0..100) >= percent {
                    *v = 0.0;
                } else {
                    *v = v.abs();
                }
            }
            group.bench_function(format!("{name}/forward/{percent}%"), |b| {
                b.iter(|| layer.forward(&x))
            });
            group.bench_function(format!("{name}/infer/{percent}%"), |b| {
                b.iter(|| layer.infer(&x))
            });
        }
    }
    group.finish();
}

criterion_group!(
    benches,
    layers,
    train_step,
    sparse_act,
    gemm_kernels,
    gather_kernels
);

/// criterion's `main`, run on a rayon pool worker as the `invaders` commands are
/// (`cli::train::in_pool`): kernels called from outside the pool would each pay a hand-over to
/// it and back. `RAYON_NUM_THREADS` sets the pool's size.
fn main() {
    let pool = rayon::ThreadPoolBuilder::new()
        .build()
        .expect("a thread pool");
    pool.install(|| {
        benches();
        Criterion::default().configure_from_args().final_summary();
    });
}

/// matrixmultiply against faer on the GEMMs of the article's layers at batch 48 (forward
/// `cols·W`, weight gradient `colsᵀ·dY`, input gradient `dY·Wᵀ`), to choose a kernel per shape.
fn gemm_kernels(c: &mut Criterion) {
    use invaders::tensor::{gemm_faer, gemm_matrixmultiply, Op};
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    // (name, M rows, K, N) of Y[M×N] = X[M×K]·W[K×N]
    let shapes = [
        ("conv1", 48 * 22 * 20, 8 * 8 * 4, 32),
        ("conv2", 48 * 11 * 10, 4 * 4 * 32, 64),
        ("conv3", 48 * 11 * 10, 3 * 3 * 64, 64),
        ("dense1", 48, 7040, 128),
    ];
    let mut group = c.benchmark_group("gemm");
    group
        .measurement_time(Duration::from_secs(2))
        .warm_up_time(Duration::from_millis(500));
    for (name, m, k, n) in shapes {
        let x = random(&[m, k], &mut rng);
        let w = random(&[k, n], &mut rng);
        let dy = random(&[m, n], &mut rng);
        let mut y = vec![0.0f32; m * n];
        let mut dw = vec![0.0f32; k * n];
        let mut dx = vec![0.0f32; m * k];
        group.throughput(Throughput::Elements(2 * (m * k * n) as u64));
        type G = fn(Op, Op, usize, usize, usize, f32, &[f32], &[f32], f32, &mut [f32]);
        for (kernel, f) in [
            ("matrixmultiply", gemm_matrixmultiply::<f32> as G),
            ("faer", gemm_faer::<f32> as G),
        ] {
            group.bench_function(format!("{name}/forward/{kernel}"), |b| {
                b.iter(|| f(Op::N, Op::N, m, n, k, 1.0, x.data(), w.data(), 0.0, &mut y))
            });
            group.bench_function(format!("{name}/weight_grad/{kernel}"), |b| {
                b.iter(|| {
                    f(
                        Op::T,
                        Op::N,
                        k,
                        n,
                        m,
                        1.0,
                        x.data(),
                        dy.data(),
                        1.0,
                        &mut dw,
                    )
                })
            });
            group.bench_function(format!("{name}/input_grad/{kernel}"), |b| {
                b.iter(|| {
                    f(
                        Op::N,
                        Op::T,
                        m,
                        k,
                        n,
                        1.0,
                        dy.data(),
                        w.data(),
                        0.0,
                        &mut dx,
                    )
                })
            });
        }
    }
    group.finish();
}

/// The gather-GEMM kernels alone (what `Conv2d` and `Dense` run on AVX-512), on the article's
/// shapes at batch 48: a convolution's forward product straight from the padded input, its weight
/// gradient, and its input gradient with col2im fused (scatter GEMM); dense1's forward product.
/// GFLOP/s as for the layers. `cargo bench --bench layers -- gather`.
fn gather_kernels(c: &mut Criterion) {
    use invaders::tensor::{fill_iota, pad_input, Float, GatherGemm, Init, ScatterGemm};
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    let mut group = c.benchmark_group("gather");
    group
        .measurement_time(Duration::from_secs(2))
        .warm_up_time(Duration::from_millis(500));
    let n = 48;
    for (name, [h, w, cin], cout, k, s) in [
        ("conv1", [88, 80, 4], 32, 8, 4),
        ("conv2", [22, 20, 32], 64, 4, 2),
        ("conv3", [11, 10, 64], 64, 3, 1),
    ] {
        let g = ConvGeom::new(h, w, cin, cout, k, k, (s, s), Padding::Same).unwrap();
        let x = random(&[n, h, w, cin], &mut rng);
        let wt = random(&[g.patch_len(), cout], &mut rng);
        let wtt = random(&[cout, g.patch_len()], &mut rng);
        let bias = vec![0.1f32; cout];
        let dy = random(&[n * g.out_pixels(), cout], &mut rng);
        let (mut xpad, mut pixels, mut patch) = (Vec::new(), Vec::new(), Vec::new());
        pad_input(&g, n, x.data(), &mut xpad);
        g.gather_offsets(n, &mut pixels, &mut patch);
        let (mut dy_rows, mut iota) = (Vec::new(), Vec::new());
        fill_iota(&mut dy_rows, pixels.len(), cout);
        fill_iota(&mut iota, cout, 1);
        let mut y = vec![0.0f32; pixels.len() * cout];
        let mut dw = vec![0.0f32; g.patch_len() * cout];
        let mut dxpad = vec![0.0f32; xpad.len()];
        group.throughput(Throughput::Elements(2 * (n * g.macs()) as u64));
        group.bench_function(format!("{name}/forward"), |b| {
            b.iter(|| {
                f32::gather_gemm(GatherGemm {
                    a: &xpad,
                    p: &pixels,
                    q: &patch,
                    b: wt.data(),
                    ldb: cout,
                    n: cout,
                    c: &mut y,
                    ldc: cout,
                    c_rows: None,
                    init: Init::Bias(&bias),
                    relu: false,
                })
            })
        });
        group.bench_function(format!("{name}/weight_grad"), |b| {
            b.iter(|| {
                f32::gather_gemm(GatherGemm {
                    a: &xpad,
                    p: &patch,
                    q: &pixels,
                    b: dy.data(),
                    ldb: cout,
                    n: cout,
                    c: &mut dw,
                    ldc: cout,
                    c_rows: None,
                    init: Init::Accumulate,
                    relu: false,
                })
            })
        });
        group.bench_function(format!("{name}/input_grad"), |b| {
            b.iter(|| {
                f32::scatter_gemm(ScatterGemm {
                    a: dy.data(),
                    p: &dy_rows,
                    q: &iota,
                    b: wtt.data(),
                    ldb: g.patch_len(),
                    n: g.patch_len(),
                    out: &mut dxpad,
                    out_rows: &pixels,
                    out_cols: &patch,
                    groups: n,
                })
            })
        });
    }
    let (ni, no) = (7040, 128);
    let x = random(&[n, ni], &mut rng);
    let wt = random(&[ni, no], &mut rng);
    let (mut rows, mut steps) = (Vec::new(), Vec::new());
    fill_iota(&mut rows, n, ni);
    fill_iota(&mut steps, ni, 1);
    let mut y = vec![0.0f32; n * no];
    group.throughput(Throughput::Elements(2 * (n * ni * no) as u64));
    group.bench_function("dense1/forward", |b| {
        b.iter(|| {
            f32::gather_gemm(GatherGemm {
                a: x.data(),
                p: &rows,
                q: &steps,
                b: wt.data(),
                ldb: no,
                n: no,
                c: &mut y,
                ldc: no,
                c_rows: None,
                init: Init::Zero,
                relu: false,
            })
        })
    });
    group.finish();
}
