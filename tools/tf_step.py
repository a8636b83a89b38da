"""Times the seed article's Q-network train step (batch 48) in TensorFlow on CPU.

Usage: python tf_step.py THREADS [STEPS]
Prints one line: framework, threads, median ms per train step, per-sample forward ms.

The reference for `invaders bench` (docs/performance.md): the same network, batch, loss and
optimiser. Set-up, once (TensorFlow is about 1.5 GB):

    python3 -m venv /tmp/ref && /tmp/ref/bin/pip install -q tensorflow-cpu==2.21.0
    /tmp/ref/bin/python tools/tf_step.py 1; /tmp/ref/bin/python tools/tf_step.py 2
"""
import os, sys, time, statistics
threads = int(sys.argv[1]); steps = int(sys.argv[2]) if len(sys.argv) > 2 else 50
os.environ["TF_CPP_MIN_LOG_LEVEL"] = "3"
import numpy as np
import tensorflow as tf
tf.config.threading.set_intra_op_parallelism_threads(threads)
tf.config.threading.set_inter_op_parallelism_threads(1)
B, H, W, C, A = 48, 88, 80, 4, 6
init = tf.keras.initializers.VarianceScaling(scale=2.0)
def qnet():
    return tf.keras.Sequential([
        tf.keras.Input((H, W, C)),
        tf.keras.layers.Conv2D(32, 8, 4, "same", activation="relu", kernel_initializer=init),
        tf.keras.layers.Conv2D(64, 4, 2, "same", activation="relu", kernel_initializer=init),
        tf.keras.layers.Conv2D(64, 3, 1, "same", activation="relu", kernel_initializer=init),
        tf.keras.layers.Flatten(),
        tf.keras.layers.Dense(128, activation="relu", kernel_initializer=init),
        tf.keras.layers.Dense(A, kernel_initializer=init),
    ])
main, target = qnet(), qnet()
opt = tf.keras.optimizers.Adam(1e-3)
rng = np.random.default_rng(0)
s = tf.constant(rng.random((B, H, W, C), dtype=np.float32))
s2 = tf.constant(rng.random((B, H, W, C), dtype=np.float32))
a = tf.constant(rng.integers(0, A, B), dtype=tf.int32)
r = tf.constant(rng.random(B, dtype=np.float32))
d = tf.constant((rng.random(B) < 0.1).astype(np.float32))
@tf.function
def train_step():
    y = r + 0.97 * tf.reduce_max(target(s2), axis=1) * (1.0 - d)
    with tf.GradientTape() as tape:
        q = tf.reduce_sum(main(s) * tf.one_hot(a, A), axis=1)
        loss = tf.reduce_mean(tf.square(y - q))
    g = tape.gradient(loss, main.trainable_variables)
    opt.apply_gradients(zip(g, main.trainable_variables))
    return loss
@tf.function
def act(x):
    return tf.argmax(main(x), axis=1)
x1 = s[:1]
for _ in range(5): train_step(); act(x1)
ts = []
for _ in range(steps):
    t = time.perf_counter(); train_step().numpy(); ts.append(time.perf_counter() - t)
fs = []
for _ in range(200):
    t = time.perf_counter(); act(x1).numpy(); fs.append(time.perf_counter() - t)
print(f"tensorflow {tf.__version__} threads={threads} train_step_ms={statistics.median(ts)*1e3:.2f} act_ms={statistics.median(fs)*1e3:.3f}")
