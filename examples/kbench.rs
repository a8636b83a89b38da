//! Times one layer operation or the train step for a fixed number of iterations, for use under
//! `perf stat` when the machine is shared (CPU time and cycles are robust to preemption where
//! criterion's wall time is not): `cargo run --release --example kbench -- conv1 fwd 50`.

use invaders::dqn::{Batch, Learner};
use invaders::layers::{Conv2d, Dense, Layer};
use invaders::tensor::{ConvGeom, Padding, Tensor};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::time::Instant;

fn random(shape: &[usize], rng: &mut impl Rng) -> Tensor<f32> {
    let n = shape.iter().product();
    Tensor::from_vec(shape, (0..n).map(|_| rng.random_range(-1.0..1.0)).collect())
}

/// This process's user + system CPU time in seconds (from /proc, 10 ms ticks).
fn cpu_seconds() -> f64 {
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let rest = stat.rsplit(')').next().unwrap_or("");
    let f: Vec<f64> = rest
        .split_whitespace()
        .map(|v| v.parse().unwrap_or(0.0))
        .collect();
    (f.get(11).unwrap_or(&0.0) + f.get(12).unwrap_or(&0.0)) / 100.0
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let (what, op, iters) = (
        args[1].as_str(),
        args[2].as_str(),
        args[3].parse::<usize>().unwrap(),
    );
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    if what == "step" {
        let mut learner = Learner::new([88, 80, 4], 6, 1e-3, 0.97, &mut rng);
        let mut batch = Batch::new(48, [88, 80, 4]);
        batch.states = random(&[48, 88, 80, 4], &mut rng);
        batch.next_states = random(&[48, 88, 80, 4], &mut rng);
        let x1 = random(&[1, 88, 80, 4], &mut rng);
        learner.train_step(&batch);
        let (t, c0) = (Instant::now(), cpu_seconds());
        for _ in 0..iters {
            if op == "act" {
                learner.online.forward(&x1);
            } else {
                learner.train_step(&batch);
            }
        }
        let ms = t.elapsed().as_secs_f64() * 1e3 / iters as f64;
        let cpu = (cpu_seconds() - c0) * 1e3 / iters as f64;
        println!("{what} {op}: {ms:.3} ms wall, {cpu:.3} ms CPU per iteration");
        return;
    }
    let batch: usize = args.get(4).map_or(48, |b| b.parse().unwrap());
    let (mut layer, shape): (Box<dyn Layer<f32>>, Vec<usize>) = match what {
        "conv1" | "conv2" | "conv3" => {
            let (h, w, cin, cout, k, s) = match what {
                "conv1" => (88, 80, 4, 32, 8, 4),
                "conv2" => (22, 20, 32, 64, 4, 2),
                _ => (11, 10, 64, 64, 3, 1),
            };
            let g = ConvGeom::new(h, w, cin, cout, k, k, (s, s), Padding::Same).unwrap();
            (Box::new(Conv2d::new(what, g)), vec![batch, h, w, cin])
        }
        "dense1" => (Box::new(Dense::new(what, 7040, 128)), vec![batch, 7040]),
        _ => (Box::new(Dense::new(what, 128, 6)), vec![batch, 128]),
    };
    for p in layer.params_mut() {
        for v in p.value.data_mut() {
            *v = rng.random_range(-0.1..0.1);
        }
    }
    let x = random(&shape, &mut rng);
    layer.forward(&x);
    let dy = random(layer.output().shape(), &mut rng);
    let flops = 2.0 * layer.macs() as f64 * batch as f64;
    let (t, c0) = (Instant::now(), cpu_seconds());
    for _ in 0..iters {
        match op {
            "fwd" => layer.forward(&x),
            "wgrad" => layer.backward(&x, &dy, false),
            _ => layer.backward(&x, &dy, true),
        }
    }
    let s = t.elapsed().as_secs_f64() / iters as f64;
    let cpu = (cpu_seconds() - c0) / iters as f64;
    let f = if op == "both" { 2.0 * flops } else { flops };
    println!(
        "{what} {op} batch {batch}: {:.3} ms wall, {:.3} ms CPU, {:.1} GFLOP/s by CPU time",
        s * 1e3,
        cpu * 1e3,
        f / cpu / 1e9
    );
}
