//! The gather GEMM in mixed precision: bf16 operands, f32 sums (issue 19).
//!
//! ```text
//! C[r, j] (= init[r, j]) + Σ_u  a[p[r] + q[u]] · b[u, j, 0]  +  a[p[r] + q[u] + 1] · b[u, j, 1]
//! ```
//!
//! The same product as [`super::GatherGemm`], with its reduction steps taken two at a time: each
//! `u` is a *pair* of steps, whose two `a` values sit next to each other in memory (a
//! convolution's patch runs over a pixel's channels, a dense layer's over a row) and whose two
//! `b` values are packed next to each other ([`pack_pairs`]). That is the operand layout of
//! AVX512-BF16's `vdpbf16ps`, which adds the two products of 16 such pairs into 16 f32 sums in
//! one instruction: twice the multiply-adds of an f32 FMA.
//!
//! `a` and `b` hold bf16 bits ([`super::bf16`]); `c`, the bias and every sum are f32. A product
//! of two bf16 values is exact in f32 (8 + 8 significant bits), so the only roundings are the
//! operands' (at most `2^−8` relative each, [`super::bf16::round_bf16`]) and the f32 additions.
//! The error bound this gives ([`super::bf16::dot_error_bound`]) is what the tests hold the
//! kernel to against the exact product of the unrounded operands.
//!
//! The portable loop [`gather_gemm_bf16_portable`] is the oracle: it adds each pair's products
//! in the order `vdpbf16ps` does (the odd element's first, each addition rounded to f32), so on
//! data without subnormals the AVX512-BF16 kernel matches it bit for bit, and every element of
//! `C` is summed in the order `u = 0, 1, …` whatever the tiling and the thread count.
//! On a CPU with AMX tiles the product runs on them instead (`x86_64/gather_bf16_amx.rs`):
//! sixteen pairs at a time, in the hardware's own order within each sixteen, so its bits differ
//! from the oracle's; it is held to the same error bound.
//! The layers never run the portable loop for speed: without AVX512-BF16 the plan keeps f32
//! ([`crate::ops::plan`]).

use super::bf16::{from_bf16, to_bf16};
use super::cpu::{avx512_twin, took_path, Family, Path};
use super::gather::{portable_rows, GatherGemm};
use rayon::prelude::*;

/// The operands of one bf16 gather GEMM (see the module documentation): [`GatherGemm`] with
/// `A` and `B` in bf16 bits, in pairs of reduction steps, and `C` in f32.
pub type GatherGemmBf16<'a> = GatherGemm<'a, u16, f32>;

impl GatherGemmBf16<'_> {
    /// Panics unless every index the product reaches is inside its slice.
    pub fn check(&self) {
        self.check_steps("gather_gemm_bf16", 2);
    }
}

/// `acc + a₁·b₁ + a₀·b₀` as one lane of `vdpbf16ps` computes it: the odd element's product
/// first, each addition rounded to f32 (the products of bf16 values are exact in f32).
#[inline]
pub fn dot_pair(acc: f32, a: [u16; 2], b: [u16; 2]) -> f32 {
    let s = acc + from_bf16(a[1]) * from_bf16(b[1]);
    s + from_bf16(a[0]) * from_bf16(b[0])
}

/// The portable loops (the oracle of the AVX512-BF16 kernel; see the module documentation).
pub fn gather_gemm_bf16_portable(g: GatherGemmBf16<'_>) {
    g.check();
    let (a, q, b, ldb) = (g.a, g.q, g.b, g.ldb);
    portable_rows(g, |row, pr| {
        for (u, &qu) in q.iter().enumerate() {
            let av = [a[pr + qu], a[pr + qu + 1]];
            for (j, cv) in row.iter_mut().enumerate() {
                let at = 2 * (u * ldb + j);
                *cv = dot_pair(*cv, av, [b[at], b[at + 1]]);
            }
        }
    });
}

/// The bf16 gather GEMM: on AMX tiles where the CPU has them, else AVX512-BF16 where it has
/// that, else the portable loops ([`super::cpu::bf16_gather_path`]). Recorded as
/// [`Family::Bf16`] ([`Path::Amx`] for the tiles).
pub fn gather_gemm_bf16(g: GatherGemmBf16<'_>) {
    match took_path(Family::Bf16, super::cpu::bf16_gather_path()) {
        #[cfg(target_arch = "x86_64")]
        Path::Amx => amx::gather_gemm_bf16(g),
        #[cfg(target_arch = "x86_64")]
        Path::Avx512 => avx512::gather_gemm_bf16(g),
        _ => gather_gemm_bf16_portable(g),
    }
}

avx512_twin! {
    /// `dst = bf16(src)`, element by element, rounded to nearest even ([`to_bf16`]); written as
    /// a plain loop so that it runs 16 lanes wide, with the same bits as the scalar rounding.
    pub fn round_into(src: &[f32], dst: &mut [u16]) {
        for (d, &s) in dst.iter_mut().zip(src) {
            *d = to_bf16(s);
        }
    }
}

/// `dst = bf16(src)`, resized to `src`'s length (its buffer reused); in blocks across the
/// threads when long (dense1's weights, 901 120 values, are rounded at every input gradient).
pub fn to_bf16_vec(src: &[f32], dst: &mut Vec<u16>) {
    dst.resize(src.len(), 0);
    if src.len() <= 2 * PAIRS {
        return round_into(src, dst);
    }
    dst.par_chunks_mut(2 * PAIRS)
        .zip(src.par_chunks(2 * PAIRS))
        .for_each(|(d, s)| round_into(s, d));
}

/// The pair `(lo, hi)` of bf16 values as the 32-bit word a pair is read as: `lo` in the low half
/// (the first `u16` in memory on a little-endian CPU, the only kind with AVX-512).
#[inline(always)]
fn pair_word(lo: f32, hi: f32) -> u32 {
    u32::from(to_bf16(lo)) | u32::from(to_bf16(hi)) << 16
}

/// `dst` as 32-bit words, one per pair, on a little-endian CPU when `dst` is aligned for them and
/// of even length (a whole buffer from the allocator always is); written a word at a time, the
/// packing loops below run 16 pairs wide. `None` otherwise, and they write `u16` by `u16`.
fn pair_words(dst: &mut [u16]) -> Option<&mut [u32]> {
    if cfg!(target_endian = "little") {
        bytemuck::try_cast_slice_mut(dst).ok()
    } else {
        None
    }
}

avx512_twin! {
    /// Packs rows `2u` and `2u + 1` of a row-major `rows × cols` matrix (row stride `ld`) into
    /// pair row `u`: `dst[2·(u·cols + j) + k] = bf16(src[(2u + k)·ld + j])`, with a zero for the
    /// missing row of an odd count. `dst` holds `2·⌈rows/2⌉·cols` values.
    fn pack_rows(src: &[f32], rows: usize, cols: usize, ld: usize, dst: &mut [u16]) {
        if let Some(words) = pair_words(dst) {
            for (u, out) in words.chunks_exact_mut(cols).enumerate() {
                let r0 = &src[2 * u * ld..][..cols];
                if 2 * u + 1 < rows {
                    let r1 = &src[(2 * u + 1) * ld..][..cols];
                    for ((o, &x0), &x1) in out.iter_mut().zip(r0).zip(r1) {
                        *o = pair_word(x0, x1);
                    }
                } else {
                    for (o, &x0) in out.iter_mut().zip(r0) {
                        *o = u32::from(to_bf16(x0));
                    }
                }
            }
            return;
        }
        for (u, out) in dst.chunks_exact_mut(2 * cols).enumerate() {
            let r0 = &src[2 * u * ld..][..cols];
            if 2 * u + 1 < rows {
                let r1 = &src[(2 * u + 1) * ld..][..cols];
                for ((o, &x0), &x1) in out.chunks_exact_mut(2).zip(r0).zip(r1) {
                    o[0] = to_bf16(x0);
                    o[1] = to_bf16(x1);
                }
            } else {
                for (o, &x0) in out.chunks_exact_mut(2).zip(r0) {
                    o[0] = to_bf16(x0);
                    o[1] = 0;
                }
            }
        }
    }
}

/// The right operand of a product whose reduction runs over the `rows` rows of a row-major
/// matrix (row stride `ld`, `cols` columns): pairs of rows interleaved, as
/// [`GatherGemmBf16::b`] reads them with `ldb = cols`. Returns the number of pairs.
///
/// Large matrices (a weight gradient's `dZ`: conv1's is 21 120 rows of 32 at batch 48) are
/// packed in blocks of pair rows across the threads.
pub fn pack_pairs(src: &[f32], rows: usize, cols: usize, ld: usize, dst: &mut Vec<u16>) -> usize {
    let pairs = rows.div_ceil(2);
    dst.resize(2 * pairs * cols, 0);
    // Pair rows per task: about `PAIRS` pairs of values.
    let block = PAIRS.div_ceil(cols.max(1));
    if pairs <= block {
        pack_pairs_into(src, rows, cols, ld, dst);
        return pairs;
    }
    dst.par_chunks_mut(2 * block * cols)
        .enumerate()
        .for_each(|(k, out)| {
            let r0 = 2 * k * block;
            let n = (rows - r0).min(2 * block);
            pack_pairs_into(&src[r0 * ld..], n, cols, ld, out);
        });
    pairs
}

/// [`pack_pairs`] into a slice of exactly `2·⌈rows/2⌉·cols` values.
pub fn pack_pairs_into(src: &[f32], rows: usize, cols: usize, ld: usize, dst: &mut [u16]) {
    assert!(cols <= ld || rows <= 1, "pack_pairs: cols > ld");
    assert!(
        rows == 0 || src.len() >= (rows - 1) * ld + cols,
        "pack_pairs: source too short"
    );
    assert_eq!(
        dst.len(),
        2 * rows.div_ceil(2) * cols,
        "pack_pairs: destination"
    );
    pack_rows(src, rows, cols, ld, dst);
}

/// A value as the bf16 bits a pair holds: an f32 rounded to nearest even, a bf16 as it is.
trait AsBf16: Copy {
    fn bf16(self) -> u16;
}

impl AsBf16 for f32 {
    #[inline(always)]
    fn bf16(self) -> u16 {
        to_bf16(self)
    }
}

impl AsBf16 for u16 {
    #[inline(always)]
    fn bf16(self) -> u16 {
        self
    }
}

avx512_twin! {
    /// `dst[2i] = bf16(src[i])`, `dst[2i + 1] = bf16(src[i + d])` (0 past the end of `src`)
    /// for the `dst.len() / 2` pairs, `src` holding at least as many values.
    fn shift_pairs<T: AsBf16>(src: &[T], d: usize, dst: &mut [u16]) {
        let n = dst.len() / 2;
        if let Some(words) = pair_words(dst) {
            // The pairs with a partner, then the last `d` values alone.
            let (both, alone) = words.split_at_mut(src.len().saturating_sub(d).min(n));
            for ((o, &lo), &hi) in both.iter_mut().zip(src).zip(&src[d.min(src.len())..]) {
                *o = u32::from(lo.bf16()) | u32::from(hi.bf16()) << 16;
            }
            for (o, &lo) in alone.iter_mut().zip(&src[both.len()..]) {
                *o = u32::from(lo.bf16());
            }
            return;
        }
        for (i, o) in dst.chunks_exact_mut(2).enumerate() {
            o[0] = src[i].bf16();
            o[1] = src.get(i + d).map_or(0, |&v| v.bf16());
        }
    }
}

/// Pairs per task of [`shift_pairs_par`], and values per task (as pairs of them) of
/// [`pack_pairs`] and [`to_bf16_vec`].
const PAIRS: usize = 1 << 15;

/// [`shift_pairs`] of all of `src` into `dst` (`2·src.len()` values), in blocks of pairs
/// across the threads (conv1's input at batch 48 makes 6 MB of pairs): block `k` reads
/// `src` from its first value to its last value's partner.
fn shift_pairs_par<T: AsBf16 + Sync>(src: &[T], d: usize, dst: &mut [u16]) {
    assert_eq!(dst.len(), 2 * src.len(), "shift_pairs: destination");
    dst.par_chunks_mut(2 * PAIRS)
        .enumerate()
        .for_each(|(k, out)| {
            let i0 = k * PAIRS;
            let end = (i0 + out.len() / 2 + d).min(src.len());
            shift_pairs(&src[i0..end], d, out);
        });
}

/// Each value paired with the one `d` places after it: `dst[2i..2i + 2] = bf16(src[i]),
/// bf16(src[i + d])`, zero past the end. A gather over `dst` at `2·(p + q)` then reads the
/// values at `p + q` and `p + q + d` as one pair: a convolution's weight gradient reads its
/// input at two output pixels `d = SW·Cin` apart, as one pair of reduction steps.
pub fn pack_shifted(src: &[f32], d: usize, dst: &mut Vec<u16>) {
    dst.resize(2 * src.len(), 0);
    shift_pairs_par(src, d, dst);
}

/// [`pack_shifted`] of values already rounded to bf16 (no rounding, only the pairing):
/// `pair_shifted(bf16(x))` is `pack_shifted(x)` bit for bit, reading half the bytes. A
/// convolution's weight gradient pairs the input its forward pass already rounded.
pub fn pair_shifted(src: &[u16], d: usize, dst: &mut Vec<u16>) {
    dst.resize(2 * src.len(), 0);
    shift_pairs_par(src, d, dst);
}

/// The f32 values of a slice of `T` that is f32 (what the bf16 kernels read and write: the
/// plan picks them for f32 layers only).
///
/// # Panics
/// If `T` is not f32.
pub fn f32s<T: super::Float>(s: &[T]) -> &[f32] {
    assert_eq!(T::DTYPE, "F32", "bf16 products are for f32 layers");
    bytemuck::cast_slice(s)
}

/// [`f32s`], mutably.
pub fn f32s_mut<T: super::Float>(s: &mut [T]) -> &mut [f32] {
    assert_eq!(T::DTYPE, "F32", "bf16 products are for f32 layers");
    bytemuck::cast_slice_mut(s)
}

/// The pair table of a reduction whose steps `q` come two by two next to each other
/// (`q[2u + 1] = q[2u] + 1`, an even count): `q[0], q[2], …`, into `pairs`. `false` (and
/// `pairs` unspecified) otherwise, e.g. a convolution's patch with an odd row length.
pub fn pair_steps(q: &[usize], pairs: &mut Vec<usize>) -> bool {
    pairs.clear();
    if !q.len().is_multiple_of(2) {
        return false;
    }
    for s in q.chunks_exact(2) {
        if s[0].checked_add(1) != Some(s[1]) {
            return false;
        }
        pairs.push(s[0]);
    }
    true
}

#[cfg(target_arch = "x86_64")]
use super::x86_64::gather_bf16_amx as amx;
#[cfg(target_arch = "x86_64")]
use super::x86_64::gather_bf16_avx512 as avx512;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pairs_are_found_only_where_steps_come_two_by_two() {
        let mut v = Vec::new();
        assert!(pair_steps(&[4, 5, 10, 11], &mut v));
        assert_eq!(v, [4, 10]);
        assert!(!pair_steps(&[4, 5, 10], &mut v));
        assert!(!pair_steps(&[4, 6], &mut v));
        assert!(!pair_steps(&[usize::MAX, 0], &mut v));
    }

    #[test]
    fn rows_are_packed_in_pairs_with_a_zero_after_an_odd_count() {
        // 3 rows × 2 columns, row stride 3.
        let src = [1.0, 2.0, 9.0, 3.0, 4.0, 9.0, 5.0, 6.0];
        let mut dst = Vec::new();
        assert_eq!(pack_pairs(&src, 3, 2, 3, &mut dst), 2);
        let f: Vec<f32> = dst.iter().map(|&b| from_bf16(b)).collect();
        assert_eq!(f, [1.0, 3.0, 2.0, 4.0, 5.0, 0.0, 6.0, 0.0]);
    }

    /// The packing loops give the same bits written a pair word at a time (an aligned buffer)
    /// and `u16` by `u16` (the same buffer one place on, misaligned for words).
    #[test]
    fn word_and_halfword_packing_agree() {
        let src: Vec<f32> = (0..7 * 5).map(|i| (i as f32 - 11.3) * 0.37).collect();
        let (rows, cols, ld) = (7usize, 4, 5);
        let len = 2 * rows.div_ceil(2) * cols;
        let (mut words, mut halves) = (vec![0u16; len], vec![0u16; len + 1]);
        assert!(pair_words(&mut words).is_some() && pair_words(&mut halves[1..]).is_none());
        pack_rows(&src, rows, cols, ld, &mut words);
        pack_rows(&src, rows, cols, ld, &mut halves[1..]);
        assert_eq!(words, halves[1..]);
        for d in [0, 3, 34, 35, 40] {
            let (mut words, mut halves) =
                (vec![0u16; 2 * src.len()], vec![0u16; 2 * src.len() + 1]);
            shift_pairs(&src, d, &mut words);
            shift_pairs(&src, d, &mut halves[1..]);
            assert_eq!(words, halves[1..], "d = {d}");
            // Pairing values already in bf16 gives the same bits, by words or by halves.
            let bf: Vec<u16> = src.iter().map(|&x| to_bf16(x)).collect();
            let mut paired = vec![0u16; 2 * src.len() + 1];
            shift_pairs(&bf, d, &mut paired[1..]);
            assert_eq!(words, paired[1..], "d = {d}, halves");
            shift_pairs(&bf, d, &mut paired[..2 * src.len()]);
            assert_eq!(words, paired[..2 * src.len()], "d = {d}, words");
        }
    }

    /// Pairing in blocks across threads gives what one pass gives: each block's values meet
    /// their partners in the next block, or past the end, where `d` sends them.
    #[test]
    fn pairs_in_parallel_blocks_are_one_pass() {
        let n = 3 * PAIRS + 17;
        let src: Vec<f32> = (0..n)
            .map(|i| ((i * 7919) % 1000) as f32 * 0.013 - 6.0)
            .collect();
        for d in [0, 1, 336, PAIRS - 1, PAIRS + 5, n - 3, n + 2] {
            let (mut one, mut par) = (vec![0u16; 2 * n], vec![7u16; 2 * n]);
            shift_pairs(&src, d, &mut one);
            shift_pairs_par(&src, d, &mut par);
            assert!(one == par, "d = {d}");
        }
        // And rows in pairs, an odd count and a stride past the columns.
        let (rows, cols, ld) = (2 * PAIRS.div_ceil(24) * 3 + 1, 24, 26);
        let src: Vec<f32> = (0..rows * ld)
            .map(|i| (i % 977) as f32 * 0.3 - 100.0)
            .collect();
        let mut one = vec![0u16; 2 * rows.div_ceil(2) * cols];
        pack_pairs_into(&src, rows, cols, ld, &mut one);
        let mut par = vec![5u16; 3];
        assert_eq!(pack_pairs(&src, rows, cols, ld, &mut par), rows.div_ceil(2));
        assert!(one == par, "pack_pairs");
        // And plain rounding, a NaN and an odd tail included.
        let mut src = src;
        src[2 * PAIRS + 3] = f32::NAN;
        let one: Vec<u16> = src.iter().map(|&x| to_bf16(x)).collect();
        let mut par = vec![1u16; 2];
        to_bf16_vec(&src, &mut par);
        assert!(one == par, "to_bf16_vec");
    }
}
