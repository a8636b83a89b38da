//! Prints a fingerprint (FNV-1a over the bits) of everything the article's network computes for
//! fixed seeds: forward, backward and inference passes at several batches and input layouts, and
//! a few train steps, at 1 and 2 threads; in f32 (the fast paths where the CPU has them), bf16
//! (its products where the CPU has AVX512-BF16) and f64 (im2col + GEMM). For refactors that must not change a bit: run it before and after, with and
//! without `INVADERS_NO_SIMD=1`, and compare the outputs:
//! `cargo run --release --example fingerprint > before.txt`.
//!
//! The numbers depend on the CPU (which kernels run), so they are compared between two builds on
//! one machine, never stored in the repository.

use invaders::dqn::{article_qnet, Batch, Learner, TargetRule};
use invaders::layers::init::VarianceScaling;
use invaders::layers::Sequential;
use invaders::ops::plan::Precision;
use invaders::tensor::{Float, Padding, Tensor};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// Cache-line-aligned buffers for the kernels (`invaders::CacheAligned`): the library leaves
/// the allocator to the program.
#[global_allocator]
static GLOBAL: invaders::CacheAligned = invaders::CacheAligned;

/// FNV-1a over the values' bits.
fn hash<T: Float>(v: &[T]) -> u64 {
    let mut h = 0xcbf2_9ce4_8422_2325u64;
    for &x in v {
        for b in bytemuck::bytes_of(&x) {
            h = (h ^ u64::from(*b)).wrapping_mul(0x100_0000_01b3);
        }
    }
    h
}

fn params_hash<T: Float>(net: &Sequential<T>) -> u64 {
    let all: Vec<T> = net.params().flat_map(|p| p.value.data().to_vec()).collect();
    hash(&all)
}

fn grads_hash<T: Float>(net: &Sequential<T>) -> u64 {
    let all: Vec<T> = net.params().flat_map(|p| p.grad.data().to_vec()).collect();
    hash(&all)
}

/// `[n, h, w, c]` of random values in [0, 1), or game-frame-like ones: a constant background
/// with about a tenth of the pixels different (what conv1's background split accepts).
fn input<T: Float>(shape: &[usize], frames: bool, rng: &mut impl Rng) -> Tensor<T> {
    let len = shape.iter().product();
    let data = (0..len)
        .map(|_| {
            if !frames || rng.random_range(0..10) == 0 {
                T::of(rng.random_range(0.0..1.0))
            } else {
                T::of(0.25)
            }
        })
        .collect();
    Tensor::from_vec(shape, data)
}

/// Puts `v` around `x`'s images as a zero border of `b` places on every side.
fn bordered<T: Float>(x: &Tensor<T>, b: usize) -> Tensor<T> {
    let [n, h, w, c] = [x.shape()[0], x.shape()[1], x.shape()[2], x.shape()[3]];
    let (hb, wb) = (h + 2 * b, w + 2 * b);
    let mut out = Tensor::zeros(&[n, hb, wb, c]);
    let (src, dst) = (x.data(), out.data_mut());
    for i in 0..n {
        for y in 0..h {
            let s = ((i * h + y) * w) * c;
            let d = ((i * hb + y + b) * wb + b) * c;
            dst[d..d + w * c].copy_from_slice(&src[s..s + w * c]);
        }
    }
    out
}

fn passes<T: Float>(tag: &str, input_shape: [usize; 3], batches: &[usize], precision: Precision) {
    let mut rng = ChaCha8Rng::seed_from_u64(21);
    let mut net: Sequential<T> = article_qnet(input_shape, 6, &VarianceScaling::HE, &mut rng);
    net.set_precision(precision);
    let [h, w, c] = input_shape;
    for &n in batches {
        for frames in [false, true] {
            let x = input::<T>(&[n, h, w, c], frames, &mut rng);
            let y = net.forward(&x).clone();
            let dy = input::<T>(&[n, 6], false, &mut rng);
            net.zero_grad();
            net.backward(&x, &dy, true);
            let dx = net.layers()[0].input_grad().data().to_vec();
            // The same input inside conv1's SAME padding (2 rows/columns for 88 × 80): conv1
            // reads it in place.
            let xb = bordered(&x, 2);
            let yb = net.forward(&xb).clone();
            net.zero_grad();
            net.backward(&xb, &dy, false);
            let gb = grads_hash(&net);
            let inf = net.infer(&x).clone();
            println!(
                "{tag} n={n} frames={frames}: fwd {:016x} grads {:016x} dx {:016x} \
                 bordered fwd {:016x} grads {:016x} infer {:016x}",
                hash(y.data()),
                grads_hash(&net),
                hash(&dx),
                hash(yb.data()),
                gb,
                hash(inf.data())
            );
        }
    }
    // Sparse acting: biases pushed down so that the ReLUs leave mostly zeros, as in a trained
    // network, and conv2 and conv3 take the sparse product.
    for (bias, &n) in [-0.2, -0.4]
        .into_iter()
        .flat_map(|b| batches.iter().map(move |n| (b, n)))
    {
        for p in net.params_mut() {
            if p.name.ends_with(".bias") && p.name.starts_with("conv") {
                p.value.data_mut().fill(T::of(bias));
            }
        }
        let x = input::<T>(&[n, h, w, c], true, &mut rng);
        let inf = net.infer(&x).clone();
        let fwd = net.forward(&x).clone();
        // The share of nonzero outputs of conv1 and conv2 (the inputs of the sparse products).
        let nz = |l: usize| {
            let y = net.layers()[l].output().data();
            y.iter().filter(|&&v| v != T::zero()).count() * 100 / y.len()
        };
        println!(
            "{tag} sparse {bias} n={n}: infer {:016x} fwd {:016x} ({}%, {}% nonzero)",
            hash(inf.data()),
            hash(fwd.data()),
            nz(0),
            nz(1)
        );
    }
}

fn train(threads: usize, precision: Precision) {
    let input = [88, 80, 4];
    let mut rng = ChaCha8Rng::seed_from_u64(24);
    let mut learner = Learner::new(input, 6, 1e-3, 0.99, &mut rng);
    learner.set_precision(precision);
    learner.rule = if threads == 2 {
        TargetRule::Double
    } else {
        TargetRule::Max
    };
    for step in 0..4 {
        let mut batch = if step % 2 == 0 {
            Batch::padded(32, input, Padding::Same)
        } else {
            Batch::new(32, input)
        };
        let b = batch.border;
        let fill = |t: &mut Tensor<f32>, rng: &mut ChaCha8Rng| {
            let s = t.shape().to_vec();
            for i in 0..s[0] {
                for y in b.top..s[1] - b.bottom {
                    for x in b.left..s[2] - b.right {
                        for ch in 0..s[3] {
                            let at = ((i * s[1] + y) * s[2] + x) * s[3] + ch;
                            t.data_mut()[at] = rng.random_range(0..4) as f32 / 3.0;
                        }
                    }
                }
            }
        };
        fill(&mut batch.states, &mut rng);
        fill(&mut batch.next_states, &mut rng);
        for i in 0..batch.len() {
            batch.actions[i] = rng.random_range(0..6);
            batch.rewards[i] = rng.random_range(0..3) as f32;
            batch.dones[i] = rng.random_range(0..8) == 0;
        }
        let s = learner.train_step(&batch);
        println!(
            "train {precision:?} t={threads} step {step}: loss {:08x} maxq {:08x} norm {:08x} params {:016x}",
            s.loss.to_bits(),
            s.mean_max_q.to_bits(),
            s.grad_norm.to_bits(),
            params_hash(&learner.online)
        );
    }
}

/// `strong` with M-IQN's head (32 fractions, Munchausen targets; `docs/strong/levers/m-iqn.toml`)
/// in `precision`: four train steps on random batches with their fractions drawn, then acting
/// (the `K` policy midpoints) on a few of their states.
fn train_iqn(threads: usize, precision: Precision) {
    let text = format!(
        "precision = \"{}\"\niqn_samples = 32\niqn_target_samples = 32\n\
         iqn_policy_samples = 32\nmunchausen_alpha = 0.9\n",
        if precision == Precision::Bf16 {
            "bf16"
        } else {
            "f32"
        }
    );
    let config =
        invaders::dqn::Config::resolve(Some(invaders::dqn::Preset::Strong), Some(&text)).unwrap();
    let iqn = config.iqn().unwrap();
    let mut rng = ChaCha8Rng::seed_from_u64(25);
    let mut learner = Learner::from_config(&config, 6, &mut rng);
    let head = invaders::dqn::Head::of(&config);
    for step in 0..4 {
        let mut batch = Batch::random(&config, &mut rng);
        batch.draw_fractions(&mut rng, iqn.samples, iqn.target_samples);
        let s = learner.train_step(&batch);
        let [h, w, c] = config.input_shape();
        let actions: Vec<usize> = (0..3)
            .map(|_| {
                let x = input::<f32>(&[1, h, w, c], true, &mut rng);
                head.greedy(&mut learner.online, &x, 6)
            })
            .collect();
        println!(
            "m-iqn {precision:?} t={threads} step {step}: loss {:08x} maxq {:08x} norm {:08x} \
             params {:016x} targets {:016x} acts {actions:?}",
            s.loss.to_bits(),
            s.mean_max_q.to_bits(),
            s.grad_norm.to_bits(),
            params_hash(&learner.online),
            hash(learner.targets())
        );
    }
}

fn main() {
    for threads in [1, 2] {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            for (name, precision) in [("f32", Precision::F32), ("bf16", Precision::Bf16)] {
                let tag = format!("{name} t={threads}");
                passes::<f32>(&tag, [88, 80, 4], &[1, 4, 8, 48], precision);
                passes::<f32>(&format!("{tag} c1"), [88, 80, 1], &[1, 8], precision);
                train(threads, precision);
                train_iqn(threads, precision);
            }
            passes::<f64>(
                &format!("f64 t={threads}"),
                [36, 32, 2],
                &[1, 8],
                Precision::F32,
            );
        });
    }
}
