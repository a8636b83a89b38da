//! The filter transforms `U = G·g·Gᵀ` (of a convolution, of its input gradient, over `s × s`
//! blocks) and their adjoints `dg = Gᵀ·dU·G` for the weight gradient.

use super::*;

/// The transformed filters `U_ξ = G·g·Gᵀ`, `[16, I, O]` (each `U_ξ` a row-major `I × O` matrix,
/// the right operand of the ξ-th GEMM), from HWIO weights `w: [3, 3, Cin, Cout]`.
///
/// Without `adjoint`, the filter of the convolution itself: `I = Cin`, `O = Cout`. With it, the
/// filter of its input gradient: `g'[ky, kx, co, ci] = w[2 − ky, 2 − kx, ci, co]` (`I = Cout`,
/// `O = Cin`), since `dX[iy, ix] = Σ dZ[iy − ky, ix − kx] · w[ky, kx]ᵀ` is a correlation of `dZ`
/// with the rotated filter.
pub fn winograd_filters<T: Float>(w: &[T], cin: usize, cout: usize, adjoint: bool, u: &mut Vec<T>) {
    assert_eq!(w.len(), 9 * cin * cout, "winograd_filters: weights");
    let (ni, no) = if adjoint { (cout, cin) } else { (cin, cout) };
    u.clear();
    u.resize(16 * ni * no, T::zero());
    let half = T::of(0.5);
    // One input channel `i` and `L` output channels at a time, in lanes on the stack (so the
    // loops vectorise and nothing is allocated): the 9 taps, G·g, then (G·g)·Gᵀ into U's rows.
    for i in 0..ni {
        for o0 in (0..no).step_by(L) {
            let l = (no - o0).min(L);
            let mut g = [[T::zero(); L]; 9];
            for (k, g) in g.iter_mut().enumerate() {
                if adjoint {
                    let (ky, kx) = (2 - k / 3, 2 - k % 3);
                    for (j, v) in g[..l].iter_mut().enumerate() {
                        *v = w[((ky * 3 + kx) * cin + o0 + j) * cout + i];
                    }
                } else {
                    *g = load(&w[(k * cin + i) * cout + o0..], l);
                }
            }
            // G·g (4×3): rows g₀, ½(g₀+g₁+g₂), ½(g₀−g₁+g₂), g₂ of each column.
            let mut gg = [[T::zero(); L]; 12];
            for c in 0..3 {
                let (g0, g1, g2) = (&g[c], &g[3 + c], &g[6 + c]);
                gg[c] = *g0;
                gg[3 + c] = std::array::from_fn(|j| half * (g0[j] + g1[j] + g2[j]));
                gg[6 + c] = std::array::from_fn(|j| half * (g0[j] - g1[j] + g2[j]));
                gg[9 + c] = *g2;
            }
            // (G·g)·Gᵀ (4×4): the same combinations of each row.
            for r in 0..4 {
                let (a, b, e) = (&gg[3 * r], &gg[3 * r + 1], &gg[3 * r + 2]);
                let row: [Lanes<T>; 4] = [
                    *a,
                    std::array::from_fn(|j| half * (a[j] + b[j] + e[j])),
                    std::array::from_fn(|j| half * (a[j] - b[j] + e[j])),
                    *e,
                ];
                for (c, val) in row.iter().enumerate() {
                    store(&mut u[((4 * r + c) * ni + i) * no + o0..], val, l);
                }
            }
        }
    }
}

/// The transformed filters of F(2×2, 2×2) over `s × s` blocks, `[9, s²·Cin, Cout]`, from HWIO
/// weights `w: [2s, 2s, Cin, Cout]`.
///
/// The block filter is `g[by, bx, (dy·s + dx)·Cin + c, o] = w[s·by + dy, s·bx + dx, c, o]`
/// (`by, bx < 2`), and `U = G·g·Gᵀ` with `G`'s rows `(1, 0)`, `(1, 1)`, `(0, 1)`: place
/// `(r, c)` is the sum of the taps `by ∈ rows[r]`, `bx ∈ rows[c]`. Sums of weights only, exact
/// up to one rounding per addition.
pub fn winograd_filters_s2d<T: Float>(w: &[T], s: usize, cin: usize, cout: usize, u: &mut Vec<T>) {
    let k = 2 * s;
    assert_eq!(w.len(), k * k * cin * cout, "winograd_filters_s2d: weights");
    let ni = s * s * cin;
    u.clear();
    u.resize(9 * ni * cout, T::zero());
    const ROWS: [&[usize]; 3] = [&[0], &[0, 1], &[1]];
    for dy in 0..s {
        for dx in 0..s {
            for c in 0..cin {
                let i = (dy * s + dx) * cin + c;
                for (r, rows) in ROWS.iter().enumerate() {
                    for (cc, cols) in ROWS.iter().enumerate() {
                        let dst = ((3 * r + cc) * ni + i) * cout;
                        for &by in *rows {
                            for &bx in *cols {
                                let src = (((s * by + dy) * k + s * bx + dx) * cin + c) * cout;
                                for o in 0..cout {
                                    u[dst + o] += w[src + o];
                                }
                            }
                        }
                    }
                }
            }
        }
    }
}

/// The transformed filters of a strided convolution's input gradient over `s × s` blocks,
/// `[9, Cout, s²·Cin]`, from HWIO weights `w: [2s, 2s, Cin, Cout]` (`wt` is scratch).
///
/// The gradient of block `(Y, X)` of the (padded) input, channel `c = (dy·s + dx)·Cin + i`
/// (pixel `(s·Y + dy, s·X + dx)`, channel `i`), collects every output the block feeds:
///
/// ```text
/// dXb[Y, X, c] = Σ_{by, bx < 2} Σ_o dZ[Y − by, X − bx, o] · w[s·by + dy, s·bx + dx, i, o]
/// ```
///
/// with `dZ` zero outside its image: a 2×2 stride-1 convolution of `dZ` padded by one pixel above
/// and to the left, with the filter `g'[ky, kx, o, c] = w[s·(1 − ky) + dy, s·(1 − kx) + dx, i, o]`
/// (rotated by 180° over blocks, channel axes swapped). That is F(2×2, 2×2) over blocks of one
/// pixel, [`WinogradKind::S2d`]`(1)`, whose `s²·Cin`-channel output "pixels" are stored as `s²`
/// pixels of `Cin` channels ([`WinogradShape::out_pieces`]).
pub fn winograd_filters_s2d_adjoint<T: Float>(
    w: &[T], s: usize, cin: usize, cout: usize, wt: &mut Vec<T>, u: &mut Vec<T>,
) {
    let k = 2 * s;
    assert_eq!(w.len(), k * k * cin * cout, "winograd_filters_s2d_adjoint");
    let ni = s * s * cin;
    wt.clear();
    wt.resize(4 * cout * ni, T::zero());
    for ky in 0..2 {
        for kx in 0..2 {
            for dy in 0..s {
                for dx in 0..s {
                    for i in 0..cin {
                        let src = (((s * (1 - ky) + dy) * k + s * (1 - kx) + dx) * cin + i) * cout;
                        let dst = (ky * 2 + kx) * cout * ni + (dy * s + dx) * cin + i;
                        for (o, &v) in w[src..src + cout].iter().enumerate() {
                            wt[dst + o * ni] = v;
                        }
                    }
                }
            }
        }
    }
    winograd_filters_s2d(wt, 1, cout, ni, u);
}

/// `dw[ky, kx, i, o] += (Gᵀ·dU_{·}[i, o]·G)[ky, kx]`: the adjoint of [`winograd_filters`]. In one
/// dimension `Gᵀ` maps `(u₀, u₁, u₂, u₃)` to `(u₀ + ½u₁ + ½u₂, ½u₁ − ½u₂, ½u₁ + ½u₂ + u₃)`.
pub(super) fn filter_adjoint<T: Float>(du: &[T], ci: usize, co: usize, dw: &mut [T]) {
    let half = T::of(0.5);
    let gt = |u: [T; 4]| -> [T; 3] {
        [
            u[0] + half * u[1] + half * u[2],
            half * u[1] - half * u[2],
            half * u[1] + half * u[2] + u[3],
        ]
    };
    for i in 0..ci {
        for o in 0..co {
            let u: [T; 16] = std::array::from_fn(|xi| du[(xi * ci + i) * co + o]);
            // Gᵀ on the left (each column), then G on the right (each row).
            let cols: [[T; 3]; 4] =
                std::array::from_fn(|c| gt([u[c], u[4 + c], u[8 + c], u[12 + c]]));
            for ky in 0..3 {
                let row = gt([cols[0][ky], cols[1][ky], cols[2][ky], cols[3][ky]]);
                for (kx, &val) in row.iter().enumerate() {
                    dw[((ky * 3 + kx) * ci + i) * co + o] += val;
                }
            }
        }
    }
}

/// The adjoint of [`winograd_filters_s2d`]: `dU [9, s²·Cin, Cout]` to the block filter's
/// gradient `dg = Gᵀ·dU·G` (in one dimension `(u₀, u₁, u₂) ↦ (u₀ + u₁, u₁ + u₂)`), added into
/// `dw [2s, 2s, Cin, Cout]` at `dw[s·by + dy, s·bx + dx, c] += dg[by, bx, (dy·s + dx)·Cin + c]`.
pub(super) fn filter_adjoint_s2d<T: Float>(
    du: &[T], s: usize, cin: usize, cout: usize, dw: &mut [T],
) {
    let k = 2 * s;
    let ni = s * s * cin;
    let gt = |u: [T; 3]| -> [T; 2] { [u[0] + u[1], u[1] + u[2]] };
    for dy in 0..s {
        for dx in 0..s {
            for c in 0..cin {
                let i = (dy * s + dx) * cin + c;
                for o in 0..cout {
                    let u: [T; 9] = std::array::from_fn(|xi| du[(xi * ni + i) * cout + o]);
                    // Gᵀ on the left (each column), then G on the right (each row).
                    let cols: [[T; 2]; 3] =
                        std::array::from_fn(|cc| gt([u[cc], u[3 + cc], u[6 + cc]]));
                    for by in 0..2 {
                        let row = gt([cols[0][by], cols[1][by], cols[2][by]]);
                        for (bx, &val) in row.iter().enumerate() {
                            dw[(((s * by + dy) * k + s * bx + dx) * cin + c) * cout + o] += val;
                        }
                    }
                }
            }
        }
    }
}
