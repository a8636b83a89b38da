#!/usr/bin/env python3
"""Generate the TensorFlow reference tensors that the Rust tests compare against.

Run from the repository root with a Python that has TensorFlow installed:

    python3 -m venv /tmp/ref
    /tmp/ref/bin/pip install tensorflow-cpu==2.21.0 safetensors numpy
    /tmp/ref/bin/python tools/tf_reference.py

It writes tests/data/tf_reference.safetensors and then reloads that file and
re-derives a number of values with plain numpy (an independent im2col
convolution, dense layers, the losses and the Adam update) as a self-check.

Conventions (all TensorFlow-native):
  * activations NHWC, batch N = 2;
  * conv filters HWIO  = [KH, KW, Cin, Cout];
  * dense weights      = [In, Out], y = x @ w + b;
  * single-layer outputs are PRE-activation (no ReLU);
  * for every layer case, the "loss" is L = sum(y * dy) with a random upstream
    gradient dy, so dx/dw/db are exactly the vector-Jacobian products the Rust
    backward pass must produce.

TF "SAME" padding (per spatial dim, input size `in`, kernel k, stride s):
    out       = ceil(in / s)
    pad_total = max((out - 1) * s + k - in, 0)
    pad_before = pad_total // 2        (top / left)
    pad_after  = pad_total - pad_before (bottom / right: gets the extra one)
"VALID": out = floor((in - k) / s) + 1, no padding.

Tensors are float32. For the conv and dense2 cases, float64 versions are also
stored under the same names with suffix ".f64" (e.g. "conv1.dw.f64"). Their
inputs (x, w, b, dy) are the float32 values cast exactly to float64, and their
outputs are computed by TensorFlow in float64 (TF's CPU conv2d and matmul, and
their gradients, do support float64). dense1 and qnet are float32 only, to keep
the file small.

Scalars (the losses) are stored with shape [1].
"""

import math
import os
import sys

# Use TF's default Eigen CPU kernels rather than oneDNN so the float32 numbers
# are reproducible across machines with different ISA extensions. This must be
# set before tensorflow is imported. Also silence the INFO log spam.
os.environ.setdefault("TF_ENABLE_ONEDNN_OPTS", "0")
os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")

import numpy as np
import tensorflow as tf
import keras
from safetensors.numpy import save_file, load_file

SEED = 20240607
N = 2
REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
OUT = os.path.join(REPO, "tests", "data", "tf_reference.safetensors")

rng = np.random.default_rng(SEED)
tensors = {}


def put(name, value, dtype=np.float32):
    """Store a tensor (as a contiguous array of `dtype`) under `name`."""
    assert value is not None, f"{name}: missing (gradient not recorded?)"
    arr = np.ascontiguousarray(np.asarray(value, dtype=dtype))
    assert name not in tensors, name
    tensors[name] = arr


def randn(*shape, scale=1.0):
    """N(0, 1) * scale, rounded to float32 (so the f64 cases use exactly the same values)."""
    return (rng.standard_normal(shape) * scale).astype(np.float32)


# --------------------------------------------------------------------------
# Single conv2d layers: y = conv2d(x, w, stride, padding) + b
# --------------------------------------------------------------------------
def conv_case(name, h, w_, cin, cout, kh, kw, stride, padding, f64=True):
    x = randn(N, h, w_, cin)
    w = randn(kh, kw, cin, cout, scale=math.sqrt(2.0 / (kh * kw * cin)))
    b = randn(cout, scale=0.1)

    dy = None  # drawn on first use, once y's shape is known

    def run(dtype):
        nonlocal dy
        tx, tw, tb = (tf.constant(a.astype(dtype)) for a in (x, w, b))
        with tf.GradientTape() as tape:
            tape.watch([tx, tw, tb])
            y = tf.nn.conv2d(tx, tw, strides=stride, padding=padding) + tb
            if dy is None:
                dy = randn(*y.shape)
            loss = tf.reduce_sum(y * tf.constant(dy.astype(dtype)))
        dx, dw, db = tape.gradient(loss, [tx, tw, tb])
        suffix = ".f64" if dtype == np.float64 else ""
        for k, v in dict(x=x, w=w, b=b, y=y, dy=dy, dx=dx, dw=dw, db=db).items():
            put(f"{name}.{k}{suffix}", v, dtype)

    run(np.float32)
    if f64:
        run(np.float64)


# The three convolutions of the article's Q-network (84x84 Atari frames cropped
# to 88x80, 4 stacked frames), all "SAME".
conv_case("conv1", 88, 80, 4, 32, 8, 8, 4, "SAME")   # -> [2, 22, 20, 32]
conv_case("conv2", 22, 20, 32, 64, 4, 4, 2, "SAME")  # -> [2, 11, 10, 64]
conv_case("conv3", 11, 10, 64, 64, 3, 3, 1, "SAME")  # -> [2, 11, 10, 64]
# Uneven SAME padding: H: out=3, pad_total=(3-1)*3+4-9=1 -> (0 top, 1 bottom);
#                      W: out=3, pad_total=(3-1)*3+4-7=3 -> (1 left, 2 right).
conv_case("conv_odd", 9, 7, 3, 5, 4, 4, 3, "SAME")    # -> [2, 3, 3, 5]
# VALID: H: (10-3)//2+1 = 4, W: (9-2)//2+1 = 4.
conv_case("conv_valid", 10, 9, 2, 3, 3, 2, 2, "VALID")  # -> [2, 4, 4, 3]


# --------------------------------------------------------------------------
# Dense layers: y = x @ w + b, w is [In, Out]
# --------------------------------------------------------------------------
def dense_case(name, n_in, n_out, f64=True):
    x = randn(N, n_in)
    w = randn(n_in, n_out, scale=math.sqrt(2.0 / n_in))
    b = randn(n_out, scale=0.1)
    dy = randn(N, n_out)
    dtypes = [np.float32] + ([np.float64] if f64 else [])
    for dtype in dtypes:
        tx, tw, tb = (tf.constant(a.astype(dtype)) for a in (x, w, b))
        with tf.GradientTape() as tape:
            tape.watch([tx, tw, tb])
            y = tf.matmul(tx, tw) + tb
            loss = tf.reduce_sum(y * tf.constant(dy.astype(dtype)))
        dx, dw, db = tape.gradient(loss, [tx, tw, tb])
        suffix = ".f64" if dtype == np.float64 else ""
        for k, v in dict(x=x, w=w, b=b, y=y, dy=dy, dx=dx, dw=dw, db=db).items():
            put(f"{name}.{k}{suffix}", v, dtype)


dense_case("dense1", 7040, 128, f64=False)  # 11*10*64 = 7040 (big: f32 only)
dense_case("dense2", 128, 6)


# --------------------------------------------------------------------------
# The whole Q-network, float32:
#   conv1 -> ReLU -> conv2 -> ReLU -> conv3 -> ReLU -> flatten (NHWC order)
#   -> dense 128 -> ReLU -> dense 6 (linear)
# Weights: VarianceScaling(scale=2.0, mode="fan_in", distribution="truncated_normal")
# (He init); biases small random non-zero so that bias bugs are visible.
# --------------------------------------------------------------------------
QNET_SHAPES = [
    ("conv1", (8, 8, 4, 32), 4),
    ("conv2", (4, 4, 32, 64), 2),
    ("conv3", (3, 3, 64, 64), 1),
    ("dense1", (7040, 128), None),
    ("dense2", (128, 6), None),
]
params = {}
for i, (lname, shape, _) in enumerate(QNET_SHAPES):
    init = keras.initializers.VarianceScaling(
        scale=2.0, mode="fan_in", distribution="truncated_normal", seed=SEED + i
    )
    params[f"{lname}.weight"] = tf.Variable(np.asarray(init(shape), np.float32))
    params[f"{lname}.bias"] = tf.Variable(randn(shape[-1], scale=0.05))

qx = tf.constant(rng.random((N, 88, 80, 4), dtype=np.float64).astype(np.float32))
dq = randn(N, 6)
with tf.GradientTape() as tape:
    tape.watch(qx)
    h = qx
    for lname, shape, stride in QNET_SHAPES[:3]:
        h = tf.nn.conv2d(h, params[f"{lname}.weight"], strides=stride, padding="SAME")
        h = tf.nn.relu(h + params[f"{lname}.bias"])
    h = tf.reshape(h, [N, 11 * 10 * 64])  # NHWC flatten: index = (y*10 + x)*64 + c
    h = tf.nn.relu(tf.matmul(h, params["dense1.weight"]) + params["dense1.bias"])
    q = tf.matmul(h, params["dense2.weight"]) + params["dense2.bias"]
    loss = tf.reduce_sum(q * tf.constant(dq))
names = list(params)
grads = tape.gradient(loss, [qx] + [params[k] for k in names])
put("qnet.x", qx)
for k in names:
    put(f"qnet.{k}", params[k])
put("qnet.q", q)
put("qnet.dq", dq)
put("qnet.dx", grads[0])
for k, g in zip(names, grads[1:]):
    put(f"qnet.grad.{k}", g)


# --------------------------------------------------------------------------
# Adam, Keras semantics (keras/src/optimizers/adam.py, Keras 3.x), t = 1, 2, 3:
#     m_t = m_{t-1} + (g_t - m_{t-1}) * (1 - beta_1)      # = b1*m + (1-b1)*g
#     v_t = v_{t-1} + (g_t^2 - v_{t-1}) * (1 - beta_2)    # = b2*v + (1-b2)*g^2
#     alpha_t = lr * sqrt(1 - beta_2^t) / (1 - beta_1^t)
#     w_t = w_{t-1} - alpha_t * m_t / (sqrt(v_t) + epsilon)
# i.e. the bias correction is folded into the learning rate and epsilon is
# added to sqrt(v_t) (NOT to sqrt(v_hat_t)). This is the "epsilon hat" form of
# Kingma & Ba, Algorithm 1 footnote; it equals the textbook
#     w -= lr * m_hat / (sqrt(v_hat) + eps * sqrt(1 - beta_2^t)).
# m, v start at zero. Note Keras' default epsilon is 1e-7; we use 1e-8.
# --------------------------------------------------------------------------
ADAM = dict(learning_rate=1e-3, beta_1=0.9, beta_2=0.999, epsilon=1e-8)
w0 = randn(5, 3)
var = tf.Variable(w0)
opt = keras.optimizers.Adam(amsgrad=False, **ADAM)
put("adam.w0", w0)
for t in (1, 2, 3):
    g = randn(5, 3)
    opt.apply_gradients([(tf.constant(g), var)])
    put(f"adam.g{t}", g)
    put(f"adam.w{t}", var.numpy())


# --------------------------------------------------------------------------
# Losses (mean reduction over the 8 elements).
#   mse   = mean((p - t)^2),          d/dp = 2 (p - t) / n
#   huber = mean(h(p - t)), delta=1:  h(d) = 0.5 d^2          if |d| <= 1
#                                          = |d| - 0.5        otherwise
#           d/dp = clip(p - t, -1, 1) / n
# --------------------------------------------------------------------------
pred = randn(8)
target = pred + np.array([0.1, -0.5, 0.9, -0.99, 1.5, -2.0, 3.0, -1.2], np.float32)
tp, tt = tf.constant(pred), tf.constant(target)
with tf.GradientTape(persistent=True) as tape:
    tape.watch(tp)
    mse = keras.losses.MeanSquaredError()(tt, tp)
    huber = keras.losses.Huber(delta=1.0)(tt, tp)
put("loss.pred", pred)
put("loss.target", target)
put("loss.mse", np.reshape(mse, [1]))
put("loss.mse_grad", tape.gradient(mse, tp))
put("loss.huber", np.reshape(huber, [1]))
put("loss.huber_grad", tape.gradient(huber, tp))
del tape


# --------------------------------------------------------------------------
# Write.
# --------------------------------------------------------------------------
metadata = {
    "generator": "tools/tf_reference.py",
    "tensorflow_version": tf.__version__,
    "keras_version": keras.__version__,
    "numpy_version": np.__version__,
    "TF_ENABLE_ONEDNN_OPTS": os.environ["TF_ENABLE_ONEDNN_OPTS"],
    "seed": str(SEED),
    "layout": "activations NHWC; conv filters HWIO [KH,KW,Cin,Cout]; dense w [In,Out]",
    "gradients": "dx/dw/db are gradients of sum(y*dy) (vector-Jacobian products)",
    "f64": "conv*, dense2 also stored as float64 with suffix .f64 (computed by TF in float64)",
    "adam": "learning_rate=1e-3 beta_1=0.9 beta_2=0.999 epsilon=1e-8 amsgrad=False; "
    "w -= lr*sqrt(1-b2^t)/(1-b1^t) * m / (sqrt(v) + eps)",
    "loss": "mean reduction over 8 elements; Huber delta=1.0",
    "tolerances": "suggested: f32 vs f32 reference rel/abs ~1e-4 (conv1/dense1 sums over "
    "up to 7040 terms, use ~1e-3 relative on large gradients); f64 vs .f64 ~1e-10",
}
os.makedirs(os.path.dirname(OUT), exist_ok=True)
save_file(tensors, OUT, metadata=metadata)
print(f"wrote {OUT}: {len(tensors)} tensors, {os.path.getsize(OUT)} bytes")


# ==========================================================================
# Self-check: reload and recompute independently with numpy.
# ==========================================================================
def same_pad(n, k, s):
    out = -(-n // s)
    total = max((out - 1) * s + k - n, 0)
    return out, total // 2, total - total // 2


def np_conv(x, w, stride, padding):
    """Independent im2col convolution, x NHWC, w HWIO."""
    n, h, wd, c = x.shape
    kh, kw, _, co = w.shape
    if padding == "SAME":
        oh, pt, pb = same_pad(h, kh, stride)
        ow, pl, pr = same_pad(wd, kw, stride)
    else:
        oh, ow = (h - kh) // stride + 1, (wd - kw) // stride + 1
        pt = pb = pl = pr = 0
    xp = np.pad(x, ((0, 0), (pt, pb), (pl, pr), (0, 0)))
    cols = np.empty((n, oh, ow, kh, kw, c), x.dtype)
    for i in range(kh):
        for j in range(kw):
            cols[:, :, :, i, j, :] = xp[:, i : i + stride * oh : stride, j : j + stride * ow : stride, :]
    return (cols.reshape(n * oh * ow, -1) @ w.reshape(-1, co)).reshape(n, oh, ow, co)


def check(name, got, want, tol):
    err = np.max(np.abs(got - want)) / max(1.0, np.max(np.abs(want)))
    status = "ok" if err <= tol else "FAIL"
    print(f"  {status:4} {name:28} max scaled err {err:.2e}")
    return err <= tol


T = load_file(OUT)
ok = True
print("self-check:")
for name, s, pad in [("conv1", 4, "SAME"), ("conv2", 2, "SAME"), ("conv3", 1, "SAME"),
                     ("conv_odd", 3, "SAME"), ("conv_valid", 2, "VALID")]:
    for sfx, tol in [("", 1e-5), (".f64", 1e-12)]:
        g = lambda k: T[f"{name}.{k}{sfx}"].astype(np.float64)
        x, w, b, dy = g("x"), g("w"), g("b"), g("dy")
        ok &= check(f"{name}.y{sfx}", np_conv(x, w, s, pad) + b, g("y"), tol)
        ok &= check(f"{name}.db{sfx}", dy.sum(axis=(0, 1, 2)), g("db"), tol)
        # dw via finite direction: <dw, e> = d/de sum(conv(x, w+e) * dy) is linear,
        # so sum(conv(x, e)*dy) == <dw, e> for any e.
        e = np.random.default_rng(1).standard_normal(w.shape)
        ok &= check(f"{name}.dw{sfx} (dir)", np.sum(np_conv(x, e, s, pad) * dy),
                    np.sum(g("dw") * e), tol * 10)
        e = np.random.default_rng(2).standard_normal(x.shape)
        ok &= check(f"{name}.dx{sfx} (dir)", np.sum(np_conv(e, w, s, pad) * dy),
                    np.sum(g("dx") * e), tol * 10)
for name, sfx in [("dense1", ""), ("dense2", ""), ("dense2", ".f64")]:
    g = lambda k: T[f"{name}.{k}{sfx}"].astype(np.float64)
    tol = 1e-12 if sfx else 1e-5
    ok &= check(f"{name}.y{sfx}", g("x") @ g("w") + g("b"), g("y"), tol)
    ok &= check(f"{name}.dx{sfx}", g("dy") @ g("w").T, g("dx"), tol)
    ok &= check(f"{name}.dw{sfx}", g("x").T @ g("dy"), g("dw"), tol)
# Q-network forward in numpy.
g = lambda k: T[k].astype(np.float64)
h = g("qnet.x")
for lname, _, s in QNET_SHAPES[:3]:
    h = np.maximum(np_conv(h, g(f"qnet.{lname}.weight"), s, "SAME") + g(f"qnet.{lname}.bias"), 0)
h = np.maximum(h.reshape(N, -1) @ g("qnet.dense1.weight") + g("qnet.dense1.bias"), 0)
ok &= check("qnet.q", h @ g("qnet.dense2.weight") + g("qnet.dense2.bias"), g("qnet.q"), 1e-5)
# Adam in numpy with the formula documented above.
w, m, v = g("adam.w0"), 0.0, 0.0
lr, b1, b2, eps = 1e-3, 0.9, 0.999, 1e-8
for t in (1, 2, 3):
    gr = g(f"adam.g{t}")
    m = m + (gr - m) * (1 - b1)
    v = v + (gr * gr - v) * (1 - b2)
    w = w - lr * math.sqrt(1 - b2**t) / (1 - b1**t) * m / (np.sqrt(v) + eps)
    ok &= check(f"adam.w{t}", w, g(f"adam.w{t}"), 1e-6)
# Losses.
d = g("loss.pred") - g("loss.target")
ok &= check("loss.mse", np.mean(d * d), g("loss.mse")[0], 1e-6)
ok &= check("loss.mse_grad", 2 * d / d.size, g("loss.mse_grad"), 1e-6)
hub = np.where(np.abs(d) <= 1, 0.5 * d * d, np.abs(d) - 0.5)
ok &= check("loss.huber", np.mean(hub), g("loss.huber")[0], 1e-6)
ok &= check("loss.huber_grad", np.clip(d, -1, 1) / d.size, g("loss.huber_grad"), 1e-6)

print("self-check", "PASSED" if ok else "FAILED")
sys.exit(0 if ok else 1)
