//! A first network with this library: a 2-16-1 perceptron learns XOR in a few lines, with the
//! same layers, loss and optimizer the DQN uses (`cargo run --release --example first_network`;
//! CI runs it). Each layer's forward and backward pass is in `src/layers/`, read top to bottom.

use invaders::layers::loss::mse;
use invaders::layers::{Dense, Relu, Sequential};
use invaders::optim::Adam;
use invaders::tensor::Tensor;

fn main() {
    let mut net = Sequential::new(); // each layer starts from the He initialiser
    net.push(Dense::new("hidden", 2, 16));
    net.push(Relu::new("relu"));
    net.push(Dense::new("out", 16, 1));
    let x = Tensor::from_vec(&[4, 2], vec![0.0, 0.0, 0.0, 1.0, 1.0, 0.0, 1.0, 1.0]);
    let y = [0.0f32, 1.0, 1.0, 0.0];
    let (mut adam, mut dy) = (Adam::new(0.01), Tensor::zeros(&[4, 1]));
    let mut loss = f32::INFINITY;
    for step in 0..2000 {
        net.zero_grad();
        loss = mse(net.forward(&x).data(), &y, dy.data_mut()); // L and ∂L/∂y
        net.backward(&x, &dy, false); // every parameter's gradient
        adam.step_net(&mut net);
        if step % 500 == 0 {
            println!("step {step:>4}: loss {loss:.5}");
        }
    }
    let out = net.forward(&x).data().to_vec();
    println!("XOR of (0,0) (0,1) (1,0) (1,1): {out:.3?} (loss {loss:.2e})");
    assert!(loss < 1e-3, "the network did not learn XOR: loss {loss}");
}
