#!/usr/bin/env python3
"""Generate the TensorFlow reference values that tests/tf_crosscheck.rs compares against.

Run from the repository root with a Python that has TensorFlow installed:

    python3 -m venv /tmp/ref
    /tmp/ref/bin/pip install tensorflow-cpu==2.21.0 numpy
    /tmp/ref/bin/python tools/tf_reference.py

It writes tests/data/tf_reference.bin and then reloads that file and re-derives a number of values
with plain numpy (an independent im2col convolution, dense layers, pooling, the losses and the
Adam update) as a self-check.

Only TensorFlow's *outputs* are stored. Every input (x, weights, biases, the upstream gradient
dy) is drawn by `draw` below from the tensor's name, and tests/tf_crosscheck.rs draws the same
values with the same few lines of Rust, so the file stays small (about 4 MB) and holds no network.

`draw(name, shape, lo, hi)`: value i (row-major, i = 0, 1, ...) is
    z = splitmix64(fnv1a64(name) + (i + 1) * 0x9E3779B97F4A7C15)
    u = (z >> 11) * 2^-53                      # uniform in [0, 1), exact in f64
    value = f32(lo + (hi - lo) * u)            # computed in f64, rounded to nearest f32
The f64 cases cast those f32 values exactly to f64.

Conventions (all TensorFlow-native):
  * activations NHWC, batch N = 2;
  * conv filters HWIO  = [KH, KW, Cin, Cout];
  * dense weights      = [In, Out], y = x @ w + b;
  * single-layer outputs are PRE-activation (no ReLU);
  * for every layer case, the "loss" is L = sum(y * dy), so dx/dw/db are exactly the
    vector-Jacobian products the Rust backward pass must produce.

TF "SAME" padding (per spatial dim, input size `in`, kernel k, stride s):
    out       = ceil(in / s)
    pad_total = max((out - 1) * s + k - in, 0)
    pad_before = pad_total // 2        (top / left)
    pad_after  = pad_total - pad_before (bottom / right: gets the extra one)
"VALID": out = floor((in - k) / s) + 1, no padding. Max pooling pads with -inf.

The two 7040 x 128 weight gradients (dense1's, alone and in the Q-network) are stored as a
sketch: dw @ R with R = draw(f"{name}.sketch", [128, 8], -1, 1), a [7040, 8] product computed in
float64 and stored in float32. A wrong value anywhere in dw changes its row of the sketch, at a
sixteenth of the bytes.

File format (tests/data/tf_reference.bin): a text header, then the data.
    invaders-tf-reference 1
    # comment lines
    NAME DTYPE DIM...        one line per tensor (DTYPE f32 or f64; a scalar has dims "1")
    end
followed by every tensor's values, little-endian, in the header's order, with nothing between.
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

N = 2
REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
OUT = os.path.join(REPO, "tests", "data", "tf_reference.bin")
MAGIC = "invaders-tf-reference 1"
SKETCH = 8

tensors = {}


def fnv1a64(name):
    h = 0xCBF29CE484222325
    for byte in name.encode():
        h = ((h ^ byte) * 0x100000001B3) & 0xFFFFFFFFFFFFFFFF
    return h


def draw(name, shape, lo=-1.0, hi=1.0):
    """The inputs' generator (see the module's doc): uniform in [lo, hi), as float32."""
    n = math.prod(shape)
    i = np.arange(1, n + 1, dtype=np.uint64)
    with np.errstate(over="ignore"):
        z = np.uint64(fnv1a64(name)) + i * np.uint64(0x9E3779B97F4A7C15)
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        z = z ^ (z >> np.uint64(31))
    u = (z >> np.uint64(11)).astype(np.float64) * 2.0**-53
    return (lo + (hi - lo) * u).astype(np.float32).reshape(shape)


def he(name, shape, fan_in):
    """He-uniform weights: uniform in ±sqrt(6 / fan_in)."""
    a = math.sqrt(6.0 / fan_in)
    return draw(name, shape, -a, a)


def put(name, value, dtype=np.float32):
    """Store a TensorFlow output (as a contiguous array of `dtype`) under `name`."""
    assert value is not None, f"{name}: missing (gradient not recorded?)"
    arr = np.ascontiguousarray(np.asarray(value, dtype=dtype))
    assert name not in tensors, name
    tensors[name] = arr


def sketch(name, dw):
    """dw @ R in float64 (R drawn from the name), for a gradient too large to store whole."""
    r = draw(f"{name}.sketch", [dw.shape[-1], SKETCH]).astype(np.float64)
    return np.asarray(dw, np.float64) @ r


# --------------------------------------------------------------------------
# Single conv2d layers: y = conv2d(x, w, stride, padding) + b
# --------------------------------------------------------------------------
def conv_case(name, h, w_, cin, cout, kh, kw, stride, padding):
    x = draw(f"{name}.x", [N, h, w_, cin])
    w = he(f"{name}.w", [kh, kw, cin, cout], kh * kw * cin)
    b = draw(f"{name}.b", [cout], -0.1, 0.1)
    for dtype, suffix in [(np.float32, ""), (np.float64, ".f64")]:
        tx, tw, tb = (tf.constant(a.astype(dtype)) for a in (x, w, b))
        with tf.GradientTape() as tape:
            tape.watch([tx, tw, tb])
            y = tf.nn.conv2d(tx, tw, strides=stride, padding=padding) + tb
            dy = draw(f"{name}.dy", list(y.shape))
            loss = tf.reduce_sum(y * tf.constant(dy.astype(dtype)))
        dx, dw, db = tape.gradient(loss, [tx, tw, tb])
        for k, v in dict(y=y, dx=dx, dw=dw, db=db).items():
            put(f"{name}.{k}{suffix}", v, dtype)


# The three convolutions of the article's Q-network (88x80 crop, 4 stacked frames), all "SAME".
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
    x = draw(f"{name}.x", [N, n_in])
    w = he(f"{name}.w", [n_in, n_out], n_in)
    b = draw(f"{name}.b", [n_out], -0.1, 0.1)
    dy = draw(f"{name}.dy", [N, n_out])
    for dtype, suffix in [(np.float32, "")] + ([(np.float64, ".f64")] if f64 else []):
        tx, tw, tb = (tf.constant(a.astype(dtype)) for a in (x, w, b))
        with tf.GradientTape() as tape:
            tape.watch([tx, tw, tb])
            y = tf.matmul(tx, tw) + tb
            loss = tf.reduce_sum(y * tf.constant(dy.astype(dtype)))
        dx, dw, db = tape.gradient(loss, [tx, tw, tb])
        put(f"{name}.y{suffix}", y, dtype)
        put(f"{name}.dx{suffix}", dx, dtype)
        if n_in * n_out > 100_000:
            put(f"{name}.dw.sketch{suffix}", sketch(f"{name}.dw", dw.numpy()), dtype)
        else:
            put(f"{name}.dw{suffix}", dw, dtype)
        put(f"{name}.db{suffix}", db, dtype)


dense_case("dense1", 7040, 128, f64=False)  # 11*10*64 = 7040 (big: f32 only, dw sketched)
dense_case("dense2", 128, 6)


# --------------------------------------------------------------------------
# Max pooling, no parameters: y = max over each window, padded places -inf.
# "pool_impala" is the IMPALA encoder's pooling (3x3, stride 2, SAME) as its third stage meets it
# on the 88x80 frame (22x20, 32 channels); "pool_ties" draws from only five values, so many windows hold their maximum
# twice or more, and TensorFlow's gradient goes to one of them (which one is what it checks).
# --------------------------------------------------------------------------
def pool_case(name, h, w_, c, k, s, padding, ties=False):
    x = draw(f"{name}.x", [N, h, w_, c])
    if ties:
        x = np.round(x * 2.0).astype(np.float32) / np.float32(2.0)  # {-1, -0.5, 0, 0.5, 1}
    for dtype, suffix in [(np.float32, ""), (np.float64, ".f64")]:
        tx = tf.constant(x.astype(dtype))
        with tf.GradientTape() as tape:
            tape.watch(tx)
            y = tf.nn.max_pool2d(tx, ksize=k, strides=s, padding=padding)
            dy = draw(f"{name}.dy", list(y.shape))
            loss = tf.reduce_sum(y * tf.constant(dy.astype(dtype)))
        put(f"{name}.y{suffix}", y, dtype)
        put(f"{name}.dx{suffix}", tape.gradient(loss, tx), dtype)


pool_case("pool_impala", 22, 20, 32, 3, 2, "SAME")  # -> [2, 11, 10, 32]
pool_case("pool_odd", 9, 7, 3, 3, 2, "SAME")        # -> [2, 5, 4, 3]; pads (1,1) and (1,1)
pool_case("pool_valid", 10, 9, 2, 3, 2, "VALID")    # -> [2, 4, 4, 2]
pool_case("pool_ties", 12, 10, 4, 3, 2, "SAME", ties=True)


# --------------------------------------------------------------------------
# A small IMPALA encoder (src/dqn/qnet.rs, `impala_encoder`): per stage a 3x3 SAME convolution,
# a 3x3 stride-2 SAME max pool and residual blocks `h + conv2(relu(conv1(relu(h))))` (both 3x3
# SAME), then a ReLU. Two stages of 4 and 8 channels, one block each, on 22x20x3 inputs:
# 22x20 -> 11x10 -> 6x5. Weights He-uniform, biases in ±0.1, all drawn by their library names.
# --------------------------------------------------------------------------
ENCODER_CHANNELS = [4, 8]


def encoder_params():
    """(name, shape) of every parameter, in the library's order."""
    out, cin = [], 3
    for i, ch in enumerate(ENCODER_CHANNELS):
        st = f"stage{i + 1}"
        out += [(f"{st}.conv.weight", [3, 3, cin, ch]), (f"{st}.conv.bias", [ch])]
        for conv in ("conv1", "conv2"):
            out += [(f"{st}.block1.{conv}.weight", [3, 3, ch, ch]),
                    (f"{st}.block1.{conv}.bias", [ch])]
        cin = ch
    return out


def encoder_draws():
    return {name: he(f"encoder.{name}", shape, math.prod(shape[:-1])) if len(shape) > 1
            else draw(f"encoder.{name}", shape, -0.1, 0.1) for name, shape in encoder_params()}


def encoder_forward(x, P, conv, pool):
    """The encoder with `conv(h, w)` (SAME, stride 1) and `pool(h)` given: TF's or numpy's."""
    relu = lambda v: v * (v > 0) if isinstance(v, np.ndarray) else tf.nn.relu(v)
    h = x
    for i in range(len(ENCODER_CHANNELS)):
        st = f"stage{i + 1}"
        h = pool(conv(h, P[f"{st}.conv.weight"]) + P[f"{st}.conv.bias"])
        b = f"{st}.block1"
        t = relu(conv(relu(h), P[f"{b}.conv1.weight"]) + P[f"{b}.conv1.bias"])
        h = h + conv(t, P[f"{b}.conv2.weight"]) + P[f"{b}.conv2.bias"]
    return relu(h)


ex = draw("encoder.x", [N, 22, 20, 3])
for dtype, suffix in [(np.float32, ""), (np.float64, ".f64")]:
    P = {k: tf.Variable(v.astype(dtype)) for k, v in encoder_draws().items()}
    tx = tf.constant(ex.astype(dtype))
    with tf.GradientTape() as tape:
        tape.watch(tx)
        y = encoder_forward(
            tx, P,
            lambda h, w: tf.nn.conv2d(h, w, strides=1, padding="SAME"),
            lambda h: tf.nn.max_pool2d(h, ksize=3, strides=2, padding="SAME"),
        )
        dy = draw("encoder.dy", list(y.shape))
        loss = tf.reduce_sum(y * tf.constant(dy.astype(dtype)))
    names = [n for n, _ in encoder_params()]
    grads = tape.gradient(loss, [tx] + [P[n] for n in names])
    put(f"encoder.y{suffix}", y, dtype)
    put(f"encoder.dx{suffix}", grads[0], dtype)
    for n, g in zip(names, grads[1:]):
        put(f"encoder.grad.{n}{suffix}", g, dtype)


# --------------------------------------------------------------------------
# The whole Q-network, float32:
#   conv1 -> ReLU -> conv2 -> ReLU -> conv3 -> ReLU -> flatten (NHWC order)
#   -> dense 128 -> ReLU -> dense 6 (linear)
# Weights He-uniform; biases small and non-zero so that bias bugs are visible.
# --------------------------------------------------------------------------
QNET_SHAPES = [
    ("conv1", (8, 8, 4, 32), 4),
    ("conv2", (4, 4, 32, 64), 2),
    ("conv3", (3, 3, 64, 64), 1),
    ("dense1", (7040, 128), None),
    ("dense2", (128, 6), None),
]
params = {}
for lname, shape, _ in QNET_SHAPES:
    fan_in = math.prod(shape[:-1])
    params[f"{lname}.weight"] = tf.Variable(he(f"qnet.{lname}.weight", list(shape), fan_in))
    params[f"{lname}.bias"] = tf.Variable(draw(f"qnet.{lname}.bias", [shape[-1]], -0.05, 0.05))

qx = tf.constant(draw("qnet.x", [N, 88, 80, 4], 0.0, 1.0))
dq = draw("qnet.dq", [N, 6])
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
put("qnet.q", q)
put("qnet.dx", grads[0])
for k, g in zip(names, grads[1:]):
    if k == "dense1.weight":
        put(f"qnet.grad.{k}.sketch", sketch(f"qnet.grad.{k}", g.numpy()))
    else:
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
var = tf.Variable(draw("adam.w0", [5, 3]))
opt = keras.optimizers.Adam(amsgrad=False, **ADAM)
for t in (1, 2, 3):
    opt.apply_gradients([(tf.constant(draw(f"adam.g{t}", [5, 3])), var)])
    put(f"adam.w{t}", var.numpy())


# --------------------------------------------------------------------------
# Losses (mean reduction over the 8 elements).
#   mse   = mean((p - t)^2),          d/dp = 2 (p - t) / n
#   huber = mean(h(p - t)), delta=1:  h(d) = 0.5 d^2          if |d| <= 1
#                                          = |d| - 0.5        otherwise
#           d/dp = clip(p - t, -1, 1) / n
# The targets are pred + LOSS_OFFSETS (in f32), so both branches of the Huber loss are taken.
# --------------------------------------------------------------------------
LOSS_OFFSETS = np.array([0.1, -0.5, 0.9, -0.99, 1.5, -2.0, 3.0, -1.2], np.float32)
pred = draw("loss.pred", [8])
target = pred + LOSS_OFFSETS
tp, tt = tf.constant(pred), tf.constant(target)
with tf.GradientTape(persistent=True) as tape:
    tape.watch(tp)
    mse = keras.losses.MeanSquaredError()(tt, tp)
    huber = keras.losses.Huber(delta=1.0)(tt, tp)
put("loss.mse", np.reshape(mse, [1]))
put("loss.mse_grad", tape.gradient(mse, tp))
put("loss.huber", np.reshape(huber, [1]))
put("loss.huber_grad", tape.gradient(huber, tp))
del tape


# --------------------------------------------------------------------------
# Write.
# --------------------------------------------------------------------------
HEADER_COMMENTS = [
    "generator tools/tf_reference.py (inputs drawn from each name; see its doc)",
    f"tensorflow {tf.__version__}, keras {keras.__version__}, numpy {np.__version__}, "
    f"TF_ENABLE_ONEDNN_OPTS={os.environ['TF_ENABLE_ONEDNN_OPTS']}",
    "layout: activations NHWC; conv filters HWIO [KH,KW,Cin,Cout]; dense w [In,Out]",
    "gradients: dx/dw/db of sum(y*dy); .f64 = computed by TF in float64; "
    ".sketch = dw @ draw(NAME.sketch, [Out, 8])",
    "adam: learning_rate=1e-3 beta_1=0.9 beta_2=0.999 epsilon=1e-8 amsgrad=False",
    "loss: mean reduction over 8 elements; Huber delta=1.0",
]


def write(path):
    lines = [MAGIC] + [f"# {c}" for c in HEADER_COMMENTS]
    for name, arr in tensors.items():
        dtype = {np.dtype(np.float32): "f32", np.dtype(np.float64): "f64"}[arr.dtype]
        dims = " ".join(str(d) for d in arr.shape) or "1"
        lines.append(f"{name} {dtype} {dims}")
    lines.append("end")
    with open(path, "wb") as f:
        f.write(("\n".join(lines) + "\n").encode())
        for arr in tensors.values():
            f.write(arr.astype(arr.dtype.newbyteorder("<")).tobytes())


def read(path):
    """The reader the Rust test mirrors: header lines, then the data in their order."""
    blob = open(path, "rb").read()
    end = blob.index(b"\nend\n") + len(b"\nend\n")
    lines = blob[:end].decode().splitlines()
    assert lines[0] == MAGIC, lines[0]
    out, at = {}, end
    for line in lines[1:-1]:
        if line.startswith("#"):
            continue
        name, dtype, *dims = line.split()
        dt = np.dtype("<f4" if dtype == "f32" else "<f8")
        shape = [int(d) for d in dims]
        n = math.prod(shape)
        out[name] = np.frombuffer(blob, dt, n, at).reshape(shape)
        at += n * dt.itemsize
    assert at == len(blob), "trailing bytes"
    return out


os.makedirs(os.path.dirname(OUT), exist_ok=True)
write(OUT)
print(f"wrote {OUT}: {len(tensors)} tensors, {os.path.getsize(OUT)} bytes")


# ==========================================================================
# Self-check: reload and recompute independently with numpy.
# ==========================================================================
def same_pad(n, k, s):
    out = -(-n // s)
    total = max((out - 1) * s + k - n, 0)
    return out, total // 2, total - total // 2


def windows(x, kh, kw, stride, padding, fill):
    """[n, oh, ow, kh, kw, c]: every window of x (NHWC), padded places set to `fill`."""
    n, h, wd, c = x.shape
    if padding == "SAME":
        oh, pt, pb = same_pad(h, kh, stride)
        ow, pl, pr = same_pad(wd, kw, stride)
    else:
        oh, ow = (h - kh) // stride + 1, (wd - kw) // stride + 1
        pt = pb = pl = pr = 0
    xp = np.pad(x, ((0, 0), (pt, pb), (pl, pr), (0, 0)), constant_values=fill)
    cols = np.empty((n, oh, ow, kh, kw, c), x.dtype)
    for i in range(kh):
        for j in range(kw):
            cols[:, :, :, i, j, :] = xp[:, i : i + stride * oh : stride, j : j + stride * ow : stride, :]
    return cols


def np_conv(x, w, stride, padding):
    """Independent im2col convolution, x NHWC, w HWIO."""
    kh, kw, _, co = w.shape
    cols = windows(x, kh, kw, stride, padding, 0.0)
    n, oh, ow = cols.shape[:3]
    return (cols.reshape(n * oh * ow, -1) @ w.reshape(-1, co)).reshape(n, oh, ow, co)


def check(name, got, want, tol):
    err = np.max(np.abs(got - want)) / max(1.0, np.max(np.abs(want)))
    status = "ok" if err <= tol else "FAIL"
    print(f"  {status:4} {name:28} max scaled err {err:.2e}")
    return err <= tol


T = read(OUT)
ok = True
print("self-check:")
CONVS = [("conv1", 88, 80, 4, 32, 8, 4, "SAME"), ("conv2", 22, 20, 32, 64, 4, 2, "SAME"),
         ("conv3", 11, 10, 64, 64, 3, 1, "SAME"), ("conv_odd", 9, 7, 3, 5, 4, 3, "SAME")]
for name, h, wd, ci, co, k, s, pad in CONVS + [("conv_valid", 10, 9, 2, 3, None, 2, "VALID")]:
    kh, kw = (k, k) if k else (3, 2)
    x = draw(f"{name}.x", [N, h, wd, ci]).astype(np.float64)
    w = he(f"{name}.w", [kh, kw, ci, co], kh * kw * ci).astype(np.float64)
    b = draw(f"{name}.b", [co], -0.1, 0.1).astype(np.float64)
    for sfx, tol in [("", 1e-5), (".f64", 1e-12)]:
        y = np_conv(x, w, s, pad) + b
        dy = draw(f"{name}.dy", list(y.shape)).astype(np.float64)
        ok &= check(f"{name}.y{sfx}", y, T[f"{name}.y{sfx}"], tol)
        ok &= check(f"{name}.db{sfx}", dy.sum(axis=(0, 1, 2)), T[f"{name}.db{sfx}"], tol)
        # sum(conv(x, e) * dy) == <dw, e> for any direction e (the loss is linear in w).
        e = np.random.default_rng(1).standard_normal(w.shape)
        ok &= check(f"{name}.dw{sfx} (dir)", np.sum(np_conv(x, e, s, pad) * dy),
                    np.sum(T[f"{name}.dw{sfx}"] * e), tol * 10)
        e = np.random.default_rng(2).standard_normal(x.shape)
        ok &= check(f"{name}.dx{sfx} (dir)", np.sum(np_conv(e, w, s, pad) * dy),
                    np.sum(T[f"{name}.dx{sfx}"] * e), tol * 10)
for name, n_in, n_out, sfx in [("dense1", 7040, 128, ""), ("dense2", 128, 6, ""),
                               ("dense2", 128, 6, ".f64")]:
    tol = 1e-12 if sfx else 1e-5
    x = draw(f"{name}.x", [N, n_in]).astype(np.float64)
    w = he(f"{name}.w", [n_in, n_out], n_in).astype(np.float64)
    b = draw(f"{name}.b", [n_out], -0.1, 0.1).astype(np.float64)
    dy = draw(f"{name}.dy", [N, n_out]).astype(np.float64)
    ok &= check(f"{name}.y{sfx}", x @ w + b, T[f"{name}.y{sfx}"], tol)
    ok &= check(f"{name}.dx{sfx}", dy @ w.T, T[f"{name}.dx{sfx}"], tol)
    if f"{name}.dw.sketch{sfx}" in T:
        ok &= check(f"{name}.dw.sketch{sfx}", sketch(f"{name}.dw", x.T @ dy),
                    T[f"{name}.dw.sketch{sfx}"], tol)
    else:
        ok &= check(f"{name}.dw{sfx}", x.T @ dy, T[f"{name}.dw{sfx}"], tol)
for name, h, wd, c, k, s, pad, ties in [("pool_impala", 22, 20, 32, 3, 2, "SAME", False),
                                        ("pool_odd", 9, 7, 3, 3, 2, "SAME", False),
                                        ("pool_valid", 10, 9, 2, 3, 2, "VALID", False),
                                        ("pool_ties", 12, 10, 4, 3, 2, "SAME", True)]:
    x = draw(f"{name}.x", [N, h, wd, c])
    if ties:
        x = np.round(x * 2.0).astype(np.float32) / np.float32(2.0)
    x = x.astype(np.float64)
    cols = windows(x, k, k, s, pad, -np.inf)
    n, oh, ow = cols.shape[:3]
    y = cols.max(axis=(3, 4))
    dy = draw(f"{name}.dy", list(y.shape)).astype(np.float64)
    # Each output's gradient to the first maximum of its window (row-major), summed.
    flat = cols.transpose(0, 1, 2, 5, 3, 4).reshape(n, oh, ow, c, k * k)
    first = flat.argmax(axis=-1)
    pt = same_pad(h, k, s)[1] if pad == "SAME" else 0
    pl = same_pad(wd, k, s)[1] if pad == "SAME" else 0
    dx = np.zeros_like(x)
    for b_ in range(n):
        for oy in range(oh):
            for ox in range(ow):
                for ch in range(c):
                    j = first[b_, oy, ox, ch]
                    dx[b_, oy * s + j // k - pt, ox * s + j % k - pl, ch] += dy[b_, oy, ox, ch]
    for sfx, tol in [("", 1e-6), (".f64", 1e-12)]:
        ok &= check(f"{name}.y{sfx}", y, T[f"{name}.y{sfx}"], tol)
        ok &= check(f"{name}.dx{sfx} (first max)", dx, T[f"{name}.dx{sfx}"], tol)
# The encoder's forward in numpy (im2col convolution, max over windows).
P = {k: v.astype(np.float64) for k, v in encoder_draws().items()}
y = encoder_forward(
    draw("encoder.x", [N, 22, 20, 3]).astype(np.float64), P,
    lambda h, w: np_conv(h, w, 1, "SAME"),
    lambda h: windows(h, 3, 3, 2, "SAME", -np.inf).max(axis=(3, 4)),
)
for sfx, tol in [("", 1e-5), (".f64", 1e-12)]:
    ok &= check(f"encoder.y{sfx}", y, T[f"encoder.y{sfx}"], tol)
# Q-network forward in numpy.
h = draw("qnet.x", [N, 88, 80, 4], 0.0, 1.0).astype(np.float64)
P = {}
for lname, shape, _ in QNET_SHAPES:
    P[lname] = (he(f"qnet.{lname}.weight", list(shape), math.prod(shape[:-1])).astype(np.float64),
                draw(f"qnet.{lname}.bias", [shape[-1]], -0.05, 0.05).astype(np.float64))
for lname, _, s in QNET_SHAPES[:3]:
    h = np.maximum(np_conv(h, P[lname][0], s, "SAME") + P[lname][1], 0)
h = np.maximum(h.reshape(N, -1) @ P["dense1"][0] + P["dense1"][1], 0)
ok &= check("qnet.q", h @ P["dense2"][0] + P["dense2"][1], T["qnet.q"], 1e-5)
# Adam in numpy with the formula documented above.
w, m, v = draw("adam.w0", [5, 3]).astype(np.float64), 0.0, 0.0
lr, b1, b2, eps = 1e-3, 0.9, 0.999, 1e-8
for t in (1, 2, 3):
    gr = draw(f"adam.g{t}", [5, 3]).astype(np.float64)
    m = m + (gr - m) * (1 - b1)
    v = v + (gr * gr - v) * (1 - b2)
    w = w - lr * math.sqrt(1 - b2**t) / (1 - b1**t) * m / (np.sqrt(v) + eps)
    ok &= check(f"adam.w{t}", w, T[f"adam.w{t}"], 1e-6)
# Losses.
d = pred.astype(np.float64) - target.astype(np.float64)
ok &= check("loss.mse", np.mean(d * d), T["loss.mse"][0], 1e-6)
ok &= check("loss.mse_grad", 2 * d / d.size, T["loss.mse_grad"], 1e-6)
hub = np.where(np.abs(d) <= 1, 0.5 * d * d, np.abs(d) - 0.5)
ok &= check("loss.huber", np.mean(hub), T["loss.huber"][0], 1e-6)
ok &= check("loss.huber_grad", np.clip(d, -1, 1) / d.size, T["loss.huber_grad"], 1e-6)

print("self-check", "PASSED" if ok else "FAILED")
sys.exit(0 if ok else 1)
