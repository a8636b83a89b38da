//! Times one layer operation or the train step for a fixed number of iterations, for use under
//! `perf stat` when the machine is shared (CPU time and cycles are robust to preemption where
//! criterion's wall time is not): `cargo run --release --example kbench -- conv1 fwd 50`;
//! `-- step train 30` (and `step act 300`) for the whole train step with its minimum and median;
//! `-- step strong 30 [FILE]` for the `strong` preset's train step (or a configuration file's on
//! it, an implicit quantile head's fractions drawn per step); `-- step infer 300` for acting as
//! `invaders bench` times it (game frames from random play, an article network after `bench`'s
//! 33 train steps, `Sequential::infer` and the argmax), for profiling under `perf`;
//! `-- net x 30` for each layer of the article's network as built (fused ReLUs, borders);
//! `-- act strong 300 [FILE]` for acting as `strong`'s runs act (batch 1, game frames);
//! `-- layers strong 1000 [FILE]` for each layer of `strong`'s network (or a configuration's
//! on it) at the train step's batch, an implicit quantile head's layers at their `B·N` rows;
//! `conv1p` and `conv2p` are conv1 and conv2 as built (VALID over a bordered input); a layer's
//! batch and then `bf16` after the count time its bf16 products (`-- conv1p wgrad 300 48 bf16`).

use invaders::dqn::{Batch, Config, Learner};
use invaders::layers::{Conv2d, Dense, Layer};
use invaders::tensor::{ConvGeom, Padding, Tensor};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::time::Instant;

/// Cache-line-aligned buffers for the kernels (`invaders::CacheAligned`): the library leaves
/// the allocator to the program.
#[global_allocator]
static GLOBAL: invaders::CacheAligned = invaders::CacheAligned;

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

/// Runs `f(i)` for `i < iters`: each call's wall time in ms, sorted, and the CPU time per call
/// in ms (all threads).
fn timed(iters: usize, mut f: impl FnMut(usize)) -> (Vec<f64>, f64) {
    let (mut times, c0) = (Vec::with_capacity(iters), cpu_seconds());
    for i in 0..iters {
        let t = Instant::now();
        f(i);
        times.push(t.elapsed().as_secs_f64() * 1e3);
    }
    let cpu = (cpu_seconds() - c0) * 1e3 / iters as f64;
    times.sort_by(f64::total_cmp);
    (times, cpu)
}

/// `strong`'s configuration, or that of a configuration file on it.
fn strong_config(file: Option<&String>) -> invaders::dqn::Config {
    let text = file.map(|p| std::fs::read_to_string(p).unwrap());
    invaders::dqn::Config::resolve(Some(invaders::dqn::Preset::Strong), text.as_deref()).unwrap()
}

/// Times acting as `invaders bench` does (game frames from random play, `Head::greedy` at batch
/// 1 by `learner`'s online network) over `iters` actions, and prints it as `what`.
fn time_acting(
    what: &str, config: &invaders::dqn::Config, learner: &mut Learner, iters: usize,
    rng: &mut ChaCha8Rng,
) {
    let frames = invaders::dqn::random_play_inputs(config, 64, 10, rng).unwrap();
    let head = invaders::dqn::Head::of(config);
    let (times, cpu) = timed(iters, |i| {
        head.greedy(&mut learner.online, &frames[i % frames.len()], 6);
    });
    println!(
        "{what}: {cpu:.3} ms CPU, min {:.3} median {:.3} per action",
        times[0],
        times[iters / 2]
    );
}

/// CPU time per call of `f` over `iters` calls, in ms (clock ticks of 10 ms: give enough
/// iterations), robust to a shared host.
fn cpu_per_call(iters: usize, f: &mut dyn FnMut()) -> f64 {
    let t = cpu_seconds();
    for _ in 0..iters {
        f();
    }
    (cpu_seconds() - t) * 1e3 / iters as f64
}

fn main() {
    // On a pool worker, as the `invaders` commands run (see `cli::train::in_pool`);
    // RAYON_NUM_THREADS sets the size.
    let pool = rayon::ThreadPoolBuilder::new().build().unwrap();
    pool.install(run);
}

fn run() {
    let args: Vec<String> = std::env::args().collect();
    let (what, op, iters) = (
        args[1].as_str(),
        args[2].as_str(),
        args[3].parse::<usize>().unwrap(),
    );
    let mut rng = ChaCha8Rng::seed_from_u64(0);
    if what == "step" && op == "infer" {
        let config = invaders::dqn::Config::preset(invaders::dqn::Preset::Article);
        let mut learner = Learner::from_config(&config, 6, &mut rng);
        // As in `bench`, whose acting follows its timed train steps on a random batch.
        let batch = Batch::random(&config, &mut rng);
        for _ in 0..33 {
            learner.train_step(&batch);
        }
        time_acting("step infer", &config, &mut learner, iters, &mut rng);
        return;
    }
    if what == "step" && op == "strong" {
        // `strong`'s train step, or that of a configuration on it (`-- step strong 100 FILE`),
        // on a random batch as `invaders bench --config` times it, fractions drawn per step.
        let config = strong_config(args.get(4));
        let (mut learner, mut batch) = trained(&config, 1, &mut rng);
        let (times, cpu) = timed(iters, |_| {
            train_once(&config, &mut learner, &mut batch, &mut rng)
        });
        println!(
            "step strong: {cpu:.3} ms CPU, min {:.3} median {:.3} per step (batch {})",
            times[0],
            times[iters / 2],
            config.batch_size
        );
        return;
    }
    if what == "act" && op == "strong" {
        // Acting as `strong`'s runs act (or a configuration's on it: `-- act strong 300 FILE`):
        // the online network after a few train steps, game frames from random play,
        // `Head::greedy` at batch 1 (an implicit quantile head's `K` policy midpoints).
        let config = strong_config(args.get(4));
        let (mut learner, _) = trained(&config, 5, &mut rng);
        time_acting("act strong", &config, &mut learner, iters, &mut rng);
        return;
    }
    if what == "layers" && op == "strong" {
        // Each layer of `strong`'s network (or a configuration's on it: `-- layers strong 100
        // FILE`) at the train step's batch, with an implicit quantile head's `N` fractions per
        // state: CPU time per call of forward, infer, the weight gradient alone, and dX.
        let config = strong_config(args.get(4));
        let mut learner = Learner::from_config(&config, 6, &mut rng);
        let mut batch = Batch::random(&config, &mut rng);
        if let Some(iqn) = config.iqn() {
            batch.draw_fractions(&mut rng, iqn.samples, iqn.target_samples);
            learner.online.set_fractions(&batch.taus);
        }
        let net = &mut learner.online;
        net.forward(&batch.states);
        let mut inputs = vec![batch.states.clone()];
        for l in net.layers().iter() {
            inputs.push(l.output().clone());
        }
        let mut total = [0.0; 4];
        for (i, l) in net.layers_mut().iter_mut().enumerate() {
            let dy = random(inputs[i + 1].shape(), &mut rng);
            let time = |f: &mut dyn FnMut()| cpu_per_call(iters, f);
            let fwd = time(&mut || l.forward(&inputs[i]));
            let inf = time(&mut || l.infer(&inputs[i]));
            let wg = time(&mut || l.backward(&inputs[i], &dy, false));
            let both = time(&mut || l.backward(&inputs[i], &dy, true));
            for (t, v) in total.iter_mut().zip([fwd, inf, wg, both - wg]) {
                *t += v;
            }
            println!(
                "{:10} rows {:5}  fwd {fwd:.3}  infer {inf:.3}  wgrad {wg:.3}  dx {:.3} ms",
                l.name(),
                inputs[i].batch(),
                both - wg
            );
        }
        let [fwd, inf, wg, dx] = total;
        println!(
            "{:10} {:10}  fwd {fwd:.3}  infer {inf:.3}  wgrad {wg:.3}  dx {dx:.3} ms",
            "all", ""
        );
        return;
    }
    if what == "step" {
        let mut learner = Learner::new([88, 80, 4], 6, 1e-3, 0.97, &mut rng);
        if args.get(4).map(String::as_str) == Some("bf16") {
            learner.set_precision(invaders::ops::plan::Precision::Bf16);
        }
        // Laid out as the agent's batches are: inside conv1's padding (a zero border).
        let mut batch = Batch::padded(48, [88, 80, 4], Padding::Same);
        for states in [&mut batch.states, &mut batch.next_states] {
            *states = random(states.shape(), &mut rng);
            batch.border.zero(states.data_mut(), 48, 88, 80, 4);
            // Rounded to bf16 once, as an agent's batch in bf16 is (f32 ignores it).
            states.keep_bf16();
        }
        batch.keep_bf16 = true;
        let x1 = random(&[1, 88, 80, 4], &mut rng);
        learner.train_step(&batch);
        let (times, cpu) = timed(iters, |_| {
            if op == "act" {
                learner.online.forward(&x1);
            } else {
                learner.train_step(&batch);
            }
        });
        let mean = times.iter().sum::<f64>() / iters as f64;
        // The minimum is the machine's quiet moments: on a shared host it is the steadiest
        // figure for comparing two builds.
        println!(
            "{what} {op}: {mean:.3} ms wall, {cpu:.3} ms CPU, min {:.3} median {:.3} per iteration",
            times[0],
            times[iters / 2]
        );
        return;
    }
    if what == "net" {
        // Each layer of the article's network as built (fused ReLUs, borders), batch 48.
        let init = invaders::layers::init::VarianceScaling::HE;
        let mut net = invaders::dqn::article_qnet::<f32>([88, 80, 4], 6, &init, &mut rng);
        if args.get(4).map(String::as_str) == Some("bf16") {
            net.set_precision(invaders::ops::plan::Precision::Bf16);
        }
        let x = random(&[48, 88, 80, 4], &mut rng);
        net.forward(&x);
        let mut inputs = vec![x];
        for l in net.layers().iter() {
            inputs.push(l.output().clone());
        }
        let layers = net.layers_mut();
        for (i, l) in layers.iter_mut().enumerate() {
            let dy = random(inputs[i + 1].shape(), &mut rng);
            let flops = 2.0 * l.macs() as f64 * 48.0;
            let time = |f: &mut dyn FnMut()| cpu_per_call(iters, f);
            let fwd = time(&mut || l.forward(&inputs[i]));
            let wg = time(&mut || l.backward(&inputs[i], &dy, false));
            let both = time(&mut || l.backward(&inputs[i], &dy, true));
            println!(
                "{:8} fwd {fwd:.3} ms ({:.0} GFLOP/s)  wgrad {wg:.3} ms ({:.0})  dx {:.3} ms ({:.0})",
                l.name(),
                flops / fwd / 1e6,
                flops / wg / 1e6,
                both - wg,
                flops / (both - wg) / 1e6
            );
        }
        return;
    }
    let batch: usize = args.get(4).map_or(48, |b| b.parse().unwrap());
    let (mut layer, shape): (Box<dyn Layer<f32>>, Vec<usize>) = match what {
        "conv1p" => {
            // conv1 as the train step runs it: VALID over a batch written inside its padding.
            let g = ConvGeom::new(92, 84, 4, 32, 8, 8, (4, 4), Padding::Valid).unwrap();
            (
                Box::new(Conv2d::new(what, g).with_relu()),
                vec![batch, 92, 84, 4],
            )
        }
        "conv2p" => {
            // conv2 as `article_qnet` builds it: VALID over conv1's bordered output, Winograd.
            let g = ConvGeom::new(24, 22, 32, 64, 4, 4, (2, 2), Padding::Valid).unwrap();
            let one = invaders::tensor::Border {
                top: 1,
                bottom: 1,
                left: 1,
                right: 1,
            };
            let conv = Conv2d::new(what, g)
                .with_relu()
                .with_winograd(true)
                .with_input_border(one)
                .with_border(one);
            (Box::new(conv), vec![batch, 24, 22, 32])
        }
        "conv1" | "conv2" | "conv3" | "conv1w" | "conv2w" | "conv3w" => {
            // `convNw`: the same layer with Winograd on.
            let (h, w, cin, cout, k, s) = match &what[..5] {
                "conv1" => (88, 80, 4, 32, 8, 4),
                "conv2" => (22, 20, 32, 64, 4, 2),
                _ => (11, 10, 64, 64, 3, 1),
            };
            let g = ConvGeom::new(h, w, cin, cout, k, k, (s, s), Padding::Same).unwrap();
            let conv = Conv2d::new(what, g).with_winograd(what.ends_with('w'));
            (Box::new(conv), vec![batch, h, w, cin])
        }
        "dense1" => (Box::new(Dense::new(what, 7040, 128)), vec![batch, 7040]),
        _ => (Box::new(Dense::new(what, 128, 6)), vec![batch, 128]),
    };
    if args.get(5).map(String::as_str) == Some("bf16") {
        layer.set_precision(invaders::ops::plan::Precision::Bf16);
    }
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
        "{what} {op} batch {batch}: {:.3} ms wall, {:.3} ms CPU, {:.1} GFLOP/s by CPU time, {:.1} GFLOP/s by wall time",
        s * 1e3,
        cpu * 1e3,
        f / cpu / 1e9,
        f / s / 1e9
    );
}

/// A learner of `config` and a random batch of it, after `steps` train steps on that batch.
fn trained(config: &Config, steps: usize, rng: &mut ChaCha8Rng) -> (Learner, Batch) {
    let mut learner = Learner::from_config(config, 6, rng);
    let mut batch = Batch::random(config, rng);
    for _ in 0..steps {
        train_once(config, &mut learner, &mut batch, rng);
    }
    (learner, batch)
}

/// One train step on `batch`, an implicit quantile head's fractions drawn for it first.
fn train_once(config: &Config, learner: &mut Learner, batch: &mut Batch, rng: &mut ChaCha8Rng) {
    if let Some(iqn) = config.iqn() {
        batch.draw_fractions(rng, iqn.samples, iqn.target_samples);
    }
    learner.train_step(batch);
}
