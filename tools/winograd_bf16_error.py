#!/usr/bin/env python3
"""How much error Winograd's F(2x2, 3x3) adds when its transformed operands are bf16.

The question behind it (issue 41, docs/performance.md "Series I"): conv3 (3x3/1, 64 -> 64)
runs on bf16 operands by the direct product today; Winograd's transforms would cut its
multiply-adds 2.25 times, but then the *transformed* input V = Bt d B and filter
U = G g Gt are what is rounded to bf16, and the inverse transform At M A adds their
errors back up. This compares, against the exact (f64) convolution of a sparse,
non-negative input (as a ReLU leaves it) and He-initialised filters:

  * direct bf16: x and w rounded to bf16, every product and sum exact;
  * Winograd bf16: V and U rounded to bf16, the rest exact.

Both keep only the operands' rounding (the f32 sums of the kernels add a little more to
each). Needs numpy:  /tmp/ref/bin/python tools/winograd_bf16_error.py
"""
import numpy as np


def bf16(x):
    """x rounded to the nearest bf16 (ties to even), as f32."""
    b = np.asarray(x, dtype=np.float32).view(np.uint32).astype(np.uint64)
    r = ((b + 0x7FFF + ((b >> 16) & 1)) >> 16) << 16
    return r.astype(np.uint32).view(np.float32).astype(np.float64)


BT = np.array([[1, 0, -1, 0], [0, 1, 1, 0], [0, -1, 1, 0], [0, 1, 0, -1]], dtype=np.float64)
G = np.array([[1, 0, 0], [0.5, 0.5, 0.5], [0.5, -0.5, 0.5], [0, 0, 1]], dtype=np.float64)
AT = np.array([[1, 1, 1, 0], [0, 1, -1, -1]], dtype=np.float64)


def conv_valid(x, w):
    """VALID 3x3 convolution, NHWC x HWIO, in f64."""
    n, h, wd, _ = x.shape
    out = np.zeros((n, h - 2, wd - 2, w.shape[3]))
    for i in range(3):
        for j in range(3):
            out += x[:, i:i + h - 2, j:j + wd - 2, :] @ w[i, j]
    return out


def winograd(x, w, round_operands):
    """The same convolution by F(2x2, 3x3) over 4x4 input tiles at stride 2."""
    n, h, wd, _ = x.shape
    u = np.einsum("ai,ijck,bj->abck", G, w, G)
    if round_operands:
        u = bf16(u)
    out = np.zeros((n, h - 2, wd - 2, w.shape[3]))
    for ty in range((h - 2) // 2):
        for tx in range((wd - 2) // 2):
            d = x[:, 2 * ty:2 * ty + 4, 2 * tx:2 * tx + 4, :]
            v = np.einsum("ai,nijc,bj->nabc", BT, d, BT)
            if round_operands:
                v = bf16(v)
            m = np.einsum("nabc,abck->nabk", v, u)
            out[:, 2 * ty:2 * ty + 2, 2 * tx:2 * tx + 2, :] = np.einsum("ia,nabk,jb->nijk", AT, m, AT)
    return out


def main():
    rng = np.random.default_rng(0)
    n, h, c, k = 8, 12, 64, 64
    for trial in range(3):
        x = np.maximum(rng.standard_normal((n, h, h, c)), 0) * (rng.random((n, h, h, c)) < 0.5)
        w = rng.standard_normal((3, 3, c, k)) * np.sqrt(2 / (9 * c))
        exact = conv_valid(x, w)
        rel = lambda y: np.linalg.norm(y - exact) / np.linalg.norm(exact)
        top = lambda y: np.max(np.abs(y - exact)) / np.max(np.abs(exact))
        assert rel(winograd(x, w, False)) < 1e-12, "the transforms are wrong"
        direct = conv_valid(bf16(x), bf16(w))
        wino = winograd(x, w, True)
        print(f"trial {trial}: relative error (norm, largest) direct bf16 {rel(direct):.2e} "
              f"{top(direct):.2e}, Winograd bf16 {rel(wino):.2e} {top(wino):.2e}: "
              f"{rel(wino) / rel(direct):.2f}x")


if __name__ == "__main__":
    main()
