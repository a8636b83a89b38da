//! The AMX kernel of the bf16 gather GEMM ([`crate::tensor::gather_bf16`]), for Intel Xeons
//! since Sapphire Rapids: `C` in tiles of 16 rows × 16 f32 columns, each grown by the tile
//! matrix product `tdpbf16ps`, which adds a 16-row × 16-pair block of `A` times a 16-pair ×
//! 16-column block of `B` (both bf16 in pairs, the layout of `vdpbf16ps`) into it: 8 192
//! multiply-adds in one instruction, against 32 for one `vdpbf16ps`.
//!
//! ```text
//!            16 pairs                  16 columns                16 columns
//!   16 rows [ A tile ]  ·  16 pairs [  B tile  ]   +=   16 rows [  C tile  ]
//! ```
//!
//! Eight tile registers of 1 KiB: `tmm0`–`tmm3` hold a 16 × 64 panel of `C`, `tmm4` the block
//! of `A`, `tmm5` and `tmm6` blocks of `B` (two, so that one loads while the other is used).
//! For each 16-row block of `C` and each 64-column panel the kernel runs over the reduction 16
//! pairs at a time: it copies the rows' pairs into a 1 KiB buffer ([`pack_a`]: one 64-byte
//! load a row where a row's 16 pairs lie next to each other, as in a convolution's forward
//! pass, where a pixel's channels are contiguous; one a step, transposed in registers, where a
//! step's 16 rows do, as in the weight gradients; a gather a row otherwise), loads it as the
//! `A` tile, and adds
//! its product with each of the panel's `B` tiles (loaded in place where whole, from a
//! zero-padded copy at the edges). `C` is loaded once and stored once per block and panel.
//!
//! **Rounding.** The products of bf16 values are exact in f32, as for `vdpbf16ps`, but the
//! order and rounding of `tdpbf16ps`'s additions inside one block of 16 pairs are the
//! hardware's own (measured on a Xeon here: none of the orders of adding the 32 products one by
//! one, in f32, gives its bits), and it treats subnormal inputs as zero. Its results therefore
//! differ in the last bits from the AVX512-BF16 kernel's and from the portable loops'; the tests
//! hold it to the same error bound against the exact product ([`crate::tensor::bf16`]). Each
//! element of `C` is still summed block by block in the order `u = 0, 16, 32, …`, whatever the
//! tiling of the rows and the thread count, so a run is bit-identical on any number of threads.
//!
//! The tile registers are configured (`ldtilecfg`) at the start of each task and released
//! (`tilerelease`) at its end, on the thread that runs it; the operating system saves them with
//! the thread's state once the process has asked for that ([`crate::tensor::cpu`] does, once).

use crate::tensor::gather::Init;
use crate::tensor::gather_bf16::GatherGemmBf16;
use crate::tensor::x86_64::gather_avx512::{split_rows, Dest, Operands};
use crate::tensor::x86_64::transpose_avx512::block;
use std::arch::asm;
use std::arch::x86_64::*;

/// Rows of a tile (of `A` and `C`).
const TM: usize = 16;
/// Pairs of reduction steps in an `A` tile's row (64 bytes).
const TK: usize = 16;
/// Columns of a `C` (and `B`) tile.
const TN: usize = 16;
/// `C` tiles side by side: a panel of 64 columns.
const PANEL: usize = 4 * TN;

/// The tile configuration `ldtilecfg` reads (palette 1): each of the first 7 tiles 16 rows of
/// 64 bytes.
#[repr(C, align(64))]
struct TileConfig {
    palette: u8,
    start_row: u8,
    reserved: [u8; 14],
    colsb: [u16; 16],
    rows: [u8; 16],
}

const CONFIG: TileConfig = {
    let mut colsb = [0u16; 16];
    let mut rows = [0u8; 16];
    let mut t = 0;
    while t < 7 {
        colsb[t] = 64;
        rows[t] = 16;
        t += 1;
    }
    TileConfig {
        palette: 1,
        start_row: 0,
        reserved: [0; 14],
        colsb,
        rows,
    }
};

/// A task's buffers: the `A` block, a zero-padded `B` block and a 16 × 64 panel of `C`.
#[repr(C, align(64))]
struct Scratch {
    a: [u32; TM * TK],
    b: [u32; TK * TN],
    c: [f32; TM * PANEL],
}

/// `tilezero tmmT`.
///
/// # Safety
/// The tiles configured ([`CONFIG`]).
#[inline(always)]
unsafe fn zero<const T: usize>() {
    asm!("tilezero tmm{t}", t = const T, options(nostack, preserves_flags));
}

/// `tileloadd tmmT, [ptr + stride·row]`: 16 rows of 64 bytes.
///
/// # Safety
/// The tiles configured; 16 rows of 64 bytes readable at `ptr`, `stride` bytes apart.
#[inline(always)]
unsafe fn load<const T: usize>(ptr: *const u8, stride: usize) {
    asm!(
        "tileloadd tmm{t}, [{p} + {s}*1]",
        t = const T, p = in(reg) ptr, s = in(reg) stride,
        options(nostack, preserves_flags, readonly)
    );
}

/// `tilestored [ptr + stride·row], tmmT`.
///
/// # Safety
/// The tiles configured; 16 rows of 64 bytes writable at `ptr`, `stride` bytes apart.
#[inline(always)]
unsafe fn store<const T: usize>(ptr: *mut u8, stride: usize) {
    asm!(
        "tilestored [{p} + {s}*1], tmm{t}",
        t = const T, p = in(reg) ptr, s = in(reg) stride,
        options(nostack, preserves_flags)
    );
}

/// `tdpbf16ps tmmC, tmm4, tmmB`: `C += A · B` with `A` in `tmm4`.
///
/// # Safety
/// The tiles configured.
#[inline(always)]
unsafe fn dot<const C: usize, const B: usize>() {
    asm!("tdpbf16ps tmm{c}, tmm4, tmm{b}", c = const C, b = const B, options(nostack, preserves_flags));
}

/// Panel tile `t` (0 to 3): `f::<t>()`.
macro_rules! on_tile {
    ($t:expr, $f:ident $(::<$($g:tt),*>)?) => {
        match $t {
            0 => $f::<0 $($(, $g)*)?>,
            1 => $f::<1 $($(, $g)*)?>,
            2 => $f::<2 $($(, $g)*)?>,
            _ => $f::<3 $($(, $g)*)?>,
        }
    };
}

/// How the pairs of one `A` block lie in memory, which decides how [`pack_a`] copies them.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Layout {
    /// A row's pairs next to each other (`q` steps by one pair): one 64-byte load a row (a
    /// convolution's forward pass and input gradient, where a pixel's channels are contiguous).
    Rows,
    /// A step's pairs next to each other across the rows (`p` steps by one pair): one 64-byte
    /// load a step, the 16 × 16 block then transposed in registers (the weight gradients, whose
    /// rows are the patch's elements and whose steps are output pixels).
    Columns,
    /// Neither: one 16-lane gather a row, where `q` fits 32-bit offsets.
    Gather,
    /// Neither, and `q` too large for a gather's offsets: pair by pair.
    Scalar,
}

/// Whether each offset is one pair (two `u16`) past the one before.
fn pair_run(v: &[usize]) -> bool {
    v.windows(2).all(|w| w[1].wrapping_sub(w[0]) == 2)
}

/// Copies the `A` block of rows `p` (at most 16) and pairs `q` (at most 16) into `dst`, a row
/// of 16 pair words per row of `C`, zero past the last pair and (for [`Layout::Columns`]) past
/// the last row, as `layout` says ([`Layout::Rows`] only where `q` is a run).
///
/// # Safety
/// AVX-512F; every pair `a[p[i] + q[k]..][..2]` readable.
#[target_feature(enable = "avx512f")]
#[inline]
unsafe fn pack_a(
    a: *const u16, p: &[usize], q: &[usize], layout: Layout, dst: &mut [u32; TM * TK],
) {
    let kb = q.len();
    let mask: __mmask16 = ((1u32 << kb) - 1) as __mmask16;
    let out = dst.as_mut_ptr() as *mut __m512i;
    match layout {
        Layout::Rows => {
            for (i, &pi) in p.iter().enumerate() {
                let v = _mm512_maskz_loadu_epi32(mask, a.add(pi + q[0]) as *const i32);
                _mm512_store_si512(out.add(i), v);
            }
        }
        Layout::Columns => {
            let rows: __mmask16 = ((1u32 << p.len()) - 1) as __mmask16;
            let cols: [__m512; TK] = std::array::from_fn(|k| {
                if k < kb {
                    let at = a.add(p[0] + q[k]) as *const i32;
                    _mm512_castsi512_ps(_mm512_maskz_loadu_epi32(rows, at))
                } else {
                    _mm512_setzero_ps()
                }
            });
            // Shuffles move bits: a pair word comes out as it went in.
            for (i, v) in block(cols).into_iter().enumerate() {
                _mm512_store_si512(out.add(i), _mm512_castps_si512(v));
            }
        }
        Layout::Gather => {
            let mut offsets = [0i32; TK];
            for (o, &qk) in offsets.iter_mut().zip(q) {
                *o = qk as i32;
            }
            let idx = _mm512_loadu_si512(offsets.as_ptr() as *const __m512i);
            for (i, &pi) in p.iter().enumerate() {
                let base = a.add(pi) as *const i32;
                let v = _mm512_mask_i32gather_epi32::<2>(_mm512_setzero_si512(), mask, idx, base);
                _mm512_store_si512(out.add(i), v);
            }
        }
        Layout::Scalar => {
            for (i, &pi) in p.iter().enumerate() {
                let row = &mut dst[i * TK..][..TK];
                for (o, &qk) in row.iter_mut().zip(q) {
                    *o = (a.add(pi + qk) as *const u32).read_unaligned();
                }
                row[kb..].fill(0);
            }
        }
    }
}

/// Rows `0..p.len()` of one task's part of `C` (`c` points at the start of its part).
///
/// # Safety
/// AVX-512F and AMX tiles usable (permission granted, [`crate::tensor::cpu::amx`]); the bounds
/// of [`GatherGemmBf16::check`] hold for these rows.
#[target_feature(enable = "avx512f")]
unsafe fn task(
    op: Operands<'_, u16>, p: &[usize], c: *mut f32, dest: Dest<'_>, init: Init<'_, f32>,
) {
    let (a, q, b, ldb, n, relu) = (op.a, op.q, op.b, op.ldb, op.n, op.relu);
    let mut s = Scratch {
        a: [0; TM * TK],
        b: [0; TK * TN],
        c: [0.0; TM * PANEL],
    };
    let (nr, pairs) = (p.len(), q.len());
    let cstride = PANEL * 4;
    // Offsets a 16-lane gather can take (signed 32-bit).
    let wide = crate::tensor::gather::largest(q) <= i32::MAX as usize;
    asm!("ldtilecfg [{}]", in(reg) &CONFIG as *const TileConfig, options(nostack, readonly));
    for j0 in (0..n).step_by(PANEL) {
        let cols = (n - j0).min(PANEL);
        let tiles = cols.div_ceil(TN);
        for r0 in (0..nr).step_by(TM) {
            let h = (nr - r0).min(TM);
            let columns = pair_run(&p[r0..r0 + h]);
            // The panel's starting values.
            match init {
                Init::Zero => {
                    for t in 0..tiles {
                        on_tile!(t, zero)();
                    }
                }
                _ => {
                    for i in 0..h {
                        let row = &mut s.c[i * PANEL..][..cols];
                        match init {
                            Init::Bias(bias) => row.copy_from_slice(&bias[j0..j0 + cols]),
                            _ => {
                                let from = c.add(dest.at(r0 + i) + j0);
                                row.copy_from_slice(std::slice::from_raw_parts(from, cols));
                            }
                        }
                    }
                    for t in 0..tiles {
                        let at = s.c.as_ptr().add(t * TN) as *const u8;
                        on_tile!(t, load)(at, cstride);
                    }
                }
            }
            for u0 in (0..pairs).step_by(TK) {
                let kb = (pairs - u0).min(TK);
                let qb = &q[u0..u0 + kb];
                let layout = if pair_run(qb) {
                    Layout::Rows
                } else if columns {
                    Layout::Columns
                } else if wide {
                    Layout::Gather
                } else {
                    Layout::Scalar
                };
                pack_a(a.as_ptr(), &p[r0..r0 + h], qb, layout, &mut s.a);
                load::<4>(s.a.as_ptr() as *const u8, TK * 4);
                for t in 0..tiles {
                    let j = j0 + t * TN;
                    let w = (n - j).min(TN);
                    let at = b.as_ptr().add(2 * (u0 * ldb + j));
                    let (ptr, stride) = if kb == TK && w == TN {
                        (at as *const u8, 4 * ldb)
                    } else {
                        // The block's edge: its pairs and columns copied, zeros around them.
                        let cmask: __mmask16 = ((1u32 << w) - 1) as __mmask16;
                        let out = s.b.as_mut_ptr() as *mut __m512i;
                        for k in 0..TK {
                            let v = if k < kb {
                                let from = at.add(2 * k * ldb) as *const i32;
                                _mm512_maskz_loadu_epi32(cmask, from)
                            } else {
                                _mm512_setzero_si512()
                            };
                            _mm512_store_si512(out.add(k), v);
                        }
                        (s.b.as_ptr() as *const u8, TN * 4)
                    };
                    if t % 2 == 0 {
                        load::<5>(ptr, stride);
                        on_tile!(t, dot::<5>)();
                    } else {
                        load::<6>(ptr, stride);
                        on_tile!(t, dot::<6>)();
                    }
                }
            }
            for t in 0..tiles {
                let at = s.c.as_mut_ptr().add(t * TN) as *mut u8;
                on_tile!(t, store)(at, cstride);
            }
            for i in 0..h {
                let to = std::slice::from_raw_parts_mut(c.add(dest.at(r0 + i) + j0), cols);
                for (o, &v) in to.iter_mut().zip(&s.c[i * PANEL..][..cols]) {
                    *o = if relu { v.max(0.0) } else { v };
                }
            }
        }
    }
    asm!("tilerelease", options(nostack, preserves_flags));
}

/// The product on AMX tiles, split over rayon by blocks of rows whose size depends only on the
/// shape. Call only where [`crate::tensor::cpu::amx`] holds.
pub fn gather_gemm_bf16(g: GatherGemmBf16<'_>) {
    assert!(crate::tensor::cpu::amx(), "gather_gemm_bf16: AMX needed");
    g.check();
    if g.is_empty() {
        return;
    }
    let op = Operands::of(&g);
    let init = g.init;
    let leaf = |pr: &[usize], cc: &mut [f32], dest: Dest<'_>| {
        // SAFETY: AMX checked above (with the permission to use it); `check` proved every `a`,
        // `b` and bias index in bounds, and this task's rows of C lie inside `cc` (rows
        // increase and the next task's part starts where its first row does), which no other
        // task touches.
        unsafe { task(op, pr, cc.as_mut_ptr(), dest, init) }
    };
    // `q` counts pairs: two reduction steps each.
    let steps = 2 * g.q.len();
    split_rows(g.c, g.p, g.c_rows, g.ldc, g.n, steps, TM, &leaf);
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// Packs the block of `A` at rows `p` and steps `q` the way `layout` says.
    fn packed(a: &[u16], p: &[usize], q: &[usize], layout: Layout) -> [u32; TM * TK] {
        let mut dst = Scratch {
            a: [0xDEAD_BEEF; TM * TK],
            b: [0; TK * TN],
            c: [0.0; TM * PANEL],
        };
        // SAFETY: AVX-512F checked by the caller; the offsets stay inside `a` (below).
        unsafe { pack_a(a.as_ptr(), p, q, layout, &mut dst.a) };
        dst.a
    }

    /// Every way of packing an `A` block gives the same words, that of its definition: row `i`,
    /// step `k` the pair at `a[p[i] + q[k]]`, zero past the last step; full and partial blocks,
    /// steps one pair apart or scattered. (The AMX kernel only runs on CPUs with AMX; its packing
    /// needs AVX-512F alone, so any AVX-512 host checks it here.)
    #[test]
    fn every_layout_packs_the_same_block() {
        if !crate::tensor::cpu::avx512() {
            return;
        }
        let mut r = rand::rngs::StdRng::seed_from_u64(3);
        let a: Vec<u16> = (0..4096).map(|_| r.random()).collect();
        for (h, kb) in [(16, 16), (16, 5), (7, 16), (1, 1), (3, 11)] {
            let first = r.random_range(0..40);
            let p: Vec<usize> = (0..h).map(|i| first + 2 * i).collect();
            let start = r.random_range(0..1000);
            let run: Vec<usize> = (0..kb).map(|k| start + 2 * k).collect();
            let scattered: Vec<usize> = (0..kb).map(|k| start + 2 * k + 6 * (k / 3)).collect();
            for q in [&run, &scattered] {
                let mut want = [0u32; TM * TK];
                for (i, &pi) in p.iter().enumerate() {
                    for (k, &qk) in q.iter().enumerate() {
                        let at = pi + qk;
                        want[i * TK + k] = u32::from(a[at]) | u32::from(a[at + 1]) << 16;
                    }
                }
                let mut layouts = vec![Layout::Columns, Layout::Gather, Layout::Scalar];
                if pair_run(q) {
                    layouts.push(Layout::Rows);
                }
                for layout in layouts {
                    let got = packed(&a, &p, q, layout);
                    // Rows past `h` are the buffer's own (never stored), but for `Columns`,
                    // which writes all 16 (zeros).
                    let rows = if layout == Layout::Columns { TM } else { h };
                    assert_eq!(
                        got[..rows * TK],
                        want[..rows * TK],
                        "h {h}, kb {kb}, run {}",
                        pair_run(q)
                    );
                }
            }
        }
    }
}
