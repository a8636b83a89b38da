//! The AVX-512 and AVX2 transforms against their portable twins, bit for bit: each is the
//! same additions and subtractions in the same order, lane by lane (no multiplication, no
//! fused operation), so any difference is a wrong index or a wrong sign.
use super::wgrad::output_adjoint;
use super::*;
use crate::tensor::cpu;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

/// The loop this host must run the transforms on, judged without the library's check:
/// AVX-512 on x86-64 with AVX-512F and FMA, AVX2 with AVX2 and FMA, unless
/// `INVADERS_NO_SIMD` (both) or `INVADERS_NO_AVX512` (the first) is set. Says once where
/// the SIMD loops are not checked.
fn host_path() -> Path {
    #[cfg(target_arch = "x86_64")]
    let (avx512, avx2) = (
        is_x86_feature_detected!("avx512f") && is_x86_feature_detected!("fma"),
        is_x86_feature_detected!("avx2") && is_x86_feature_detected!("fma"),
    );
    #[cfg(not(target_arch = "x86_64"))]
    let (avx512, avx2) = (false, false);
    let simd = std::env::var_os("INVADERS_NO_SIMD").is_none();
    let path = if avx512 && simd && std::env::var_os("INVADERS_NO_AVX512").is_none() {
        Path::Avx512
    } else if avx2 && simd {
        Path::Avx2
    } else {
        Path::Portable
    };
    if path != Path::Avx512 {
        static NOTE: std::sync::Once = std::sync::Once::new();
        #[allow(clippy::print_stderr)] // a test's note
        NOTE.call_once(|| {
            eprintln!(
                "skip: the AVX-512 Winograd transforms are not checked here ({}); the \
                 {path:?} ones are compared with the portable loops",
                cpu::why_portable().unwrap_or_default()
            )
        });
    }
    assert_eq!(cpu::path(), path, "the library's CPU check disagrees");
    path
}

/// One recorded call of `path`.
fn once(path: Path) -> cpu::Paths {
    cpu::Paths {
        avx512: u64::from(path == Path::Avx512),
        portable: u64::from(path == Path::Portable),
        avx2: u64::from(path == Path::Avx2),
        amx: 0,
    }
}

fn values(n: usize, rng: &mut ChaCha8Rng) -> Vec<f32> {
    (0..n).map(|_| rng.random_range(-1.0f32..1.0)).collect()
}

fn same_bits(what: &str, a: &[f32], b: &[f32]) {
    assert_eq!(a.len(), b.len(), "{what}: lengths");
    for (i, (x, y)) in a.iter().zip(b).enumerate() {
        assert!(x.to_bits() == y.to_bits(), "{what}[{i}]: {x} vs {y}");
    }
}

/// The shapes the layers run, small, and one of odd channel counts: F(2×2, 3×3) with odd
/// output edges (a tile's second row and column dropped) and padding; F(2×2, 2×2) over
/// 2×2 blocks (conv2) and 4×4 blocks of 4 channels (conv1's, 16 values per block row);
/// over blocks of one pixel with the output in 4 pieces (conv2's input gradient).
fn shapes() -> Vec<WinogradShape> {
    let shape = |h, w, ci, oh, ow, pad, co, pieces, kind| WinogradShape {
        n: 3,
        h,
        w,
        ci,
        oh,
        ow,
        pad_top: pad,
        pad_left: pad,
        co,
        out_image: oh * ow * co,
        out_pieces: pieces,
        kind,
    };
    vec![
        shape(9, 7, 16, 9, 7, 1, 32, 1, WinogradKind::F2x3),
        shape(6, 6, 64, 4, 4, 0, 64, 1, WinogradKind::F2x3),
        shape(12, 12, 32, 5, 5, 0, 64, 1, WinogradKind::S2d(2)),
        shape(16, 16, 4, 3, 3, 0, 32, 1, WinogradKind::S2d(4)),
        shape(5, 5, 64, 6, 6, 1, 128, 4, WinogradKind::S2d(1)),
        // Rows of 12 input and 20 output channels: no whole vectors for any SIMD loop.
        shape(5, 5, 12, 5, 5, 1, 20, 1, WinogradKind::F2x3),
    ]
}

/// Each shape's transforms as chosen for f32 (recorded on this thread) and as the portable
/// loops, with the path asserted: the host's SIMD family where it runs one (on AVX-512 for
/// whole vectors only), else portable.
fn twins(s: &WinogradShape, len: usize) -> (Transforms, Transforms) {
    let before = (
        cpu::paths(Family::WinogradInput),
        cpu::paths(Family::WinogradOutput),
    );
    let fast = Transforms::choose::<f32>(s, len);
    let path = host_path();
    // AVX-512 takes only whole vectors (`transforms_need_whole_vectors`); the AVX2 family
    // handles the rest itself.
    let on = |n: usize| match path {
        Path::Avx512 if !n.is_multiple_of(L) => Path::Portable,
        p => p,
    };
    let want = (on(s.seg()), on(len));
    assert_eq!((fast.input, fast.output), want, "{s:?}");
    let ran = (
        cpu::paths(Family::WinogradInput).since(before.0),
        cpu::paths(Family::WinogradOutput).since(before.1),
    );
    assert_eq!(ran, (once(want.0), once(want.1)), "recorded paths");
    let f64s = Transforms::choose::<f64>(s, len);
    assert_eq!(
        (f64s.input, f64s.output),
        (Path::Portable, Path::Portable),
        "f64 runs the portable loops"
    );
    (fast, Transforms::portable())
}

/// The transforms take their AVX-512 loops only for whole vectors: block rows of 8 input
/// values and pieces of 24 output channels stay portable on an AVX-512 host. The AVX2
/// loops (the portable ones compiled for AVX2) take any length.
#[test]
fn transforms_need_whole_vectors() {
    let path = host_path();
    let shape = |ci, co| WinogradShape {
        n: 1,
        h: 4,
        w: 4,
        ci,
        oh: 2,
        ow: 2,
        pad_top: 0,
        pad_left: 0,
        co,
        out_image: 4 * co,
        out_pieces: 1,
        kind: WinogradKind::F2x3,
    };
    let on = |whole: bool| match path {
        Path::Avx512 if !whole => Path::Portable,
        p => p,
    };
    for (ci, co, input, output) in [
        (8, 24, on(false), on(false)),
        (16, 24, on(true), on(false)),
        (8, 48, on(false), on(true)),
        (48, 48, on(true), on(true)),
    ] {
        let before = cpu::paths(Family::WinogradInput);
        let t = Transforms::choose::<f32>(&shape(ci, co), co);
        assert_eq!((t.input, t.output), (input, output), "{ci} → {co} channels");
        let ran = cpu::paths(Family::WinogradInput).since(before);
        assert_eq!(ran, once(input));
    }
}

/// The input transform, tile-major (the forward pass) and place-major (the weight
/// gradient), over images whose tiles reach past their edges (zeros read there).
#[test]
fn input_transforms_match_their_portable_twins() {
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    for s in shapes() {
        let (fast, portable) = twins(&s, s.co / s.out_pieces);
        let x = values(s.n * s.h * s.w * s.ci, &mut rng);
        let mut pixels = Vec::new();
        input_offsets(&s, &mut pixels);
        let zeros = vec![0.0f32; s.seg()];
        let (ty, tx) = s.tiles();
        let run = |t: Transforms, by_place: bool| {
            let chunk = Chunk {
                s,
                fast: t,
                images: if by_place { 1 } else { s.n },
                x: if by_place { &x[..s.h * s.w * s.ci] } else { &x },
                u: Filters::Same(&[]),
                bias: None,
                relu: false,
                pixels: &pixels,
                out_pixels: &[],
            };
            // NaN where nothing is written: the same places must stay untouched.
            let mut v = vec![f32::NAN; s.n * ty * tx * s.v_stride()];
            if by_place {
                chunk.input_by_place(&mut v, &zeros);
            } else {
                chunk.input(&mut v, &zeros);
            }
            v.iter().map(|x| x.to_bits()).collect::<Vec<u32>>()
        };
        for by_place in [false, true] {
            assert!(
                run(fast, by_place) == run(portable, by_place),
                "{s:?}, place-major {by_place}"
            );
        }
    }
}

/// The input transform rounded to bf16 as it is stored (AVX-512) and rounded after it (the
/// portable loops, then `round_into`): the same bits, for random images and for one whose
/// only nonzero pixel holds values that test the rounding itself (the transform passes a lone
/// pixel through as ±itself): NaNs (quieted by the transform's arithmetic, payloads kept),
/// infinities, subnormals, ties either way, a value that rounds up to infinity.
#[test]
fn input_transforms_rounded_as_stored_match_rounded_after() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    let special = [
        f32::NAN,
        f32::from_bits(0xFFA0_1234),
        f32::from_bits(0x7F80_0001),
        // Payloads that a plain rounding would carry into the sign or round to zero.
        f32::from_bits(0x7FFF_FFFF),
        f32::from_bits(0xFFFF_FFF0),
        f32::INFINITY,
        f32::NEG_INFINITY,
        1e-40,
        -1.4e-45,
        f32::MAX,
        -3.3953e38,
        1.0 + 2f32.powi(-8),
        1.0 + 3.0 * 2f32.powi(-8),
        -(1.0 + 2f32.powi(-8) + 2f32.powi(-20)),
        0.0,
        -0.0,
    ];
    for s in shapes() {
        let (fast, portable) = twins(&s, s.co / s.out_pieces);
        let mut x = values(s.n * s.h * s.w * s.ci, &mut rng);
        // Image 1: zeros but for pixel (1, 1), its channels cycling through `special`.
        let image = s.h * s.w * s.ci;
        x[image..2 * image].fill(0.0);
        for c in 0..s.ci {
            x[image + (s.w + 1) * s.ci + c] = special[c % special.len()];
        }
        let mut pixels = Vec::new();
        input_offsets(&s, &mut pixels);
        let zeros = vec![0.0f32; s.seg()];
        let (ty, tx) = s.tiles();
        let run = |t: Transforms| {
            let chunk = Chunk {
                s,
                fast: t,
                images: s.n,
                x: &x,
                u: Filters::Same(&[]),
                bias: None,
                relu: false,
                pixels: &pixels,
                out_pixels: &[],
            };
            let mut v = vec![0.0f32; s.v_stride()];
            // 0xDEAD where nothing is written: the same places must stay untouched.
            let mut vb = vec![0xDEADu16; s.n * ty * tx * s.v_stride()];
            chunk.input_bf16(&mut v, &mut vb, &zeros);
            vb
        };
        assert!(run(fast) == run(portable), "{s:?}");
    }
}

/// The bf16 weight gradient's `V` and `dM` rounded into pairs of tiles as the AVX-512
/// transforms store them, and transformed by the portable loops then packed: the same `dU`,
/// bit for bit (odd tile counts included: the last pair's zero halves).
#[test]
fn weight_gradient_pairs_rounded_as_stored_match_packed_after() {
    let mut rng = ChaCha8Rng::seed_from_u64(4);
    for s in shapes().into_iter().filter(|s| s.out_pieces == 1) {
        let (fast, portable) = twins(&s, s.co);
        let x = values(s.n * s.h * s.w * s.ci, &mut rng);
        let dz = values(s.n * s.oh * s.ow * s.co, &mut rng);
        let du = |t| super::wgrad::chunk_du_bf16(s, &x, &dz, t);
        let (a, b) = (du(fast), du(portable));
        same_bits(&format!("{s:?}"), &a, &b);
    }
}

/// The output transform with and without bias and ReLU, into pieces, some skipped.
#[test]
fn output_transforms_match_their_portable_twins() {
    let mut rng = ChaCha8Rng::seed_from_u64(2);
    for s in shapes() {
        let len = s.co / s.out_pieces;
        let (fast, portable) = twins(&s, len);
        let (ty, tx) = s.tiles();
        let m = values(s.n * ty * tx * s.m_stride(), &mut rng);
        let bias = values(s.co, &mut rng);
        let out_pixels: Vec<usize> = (0..s.oh * s.ow * s.out_pieces)
            .map(|i| {
                if i % 7 == 3 {
                    SKIP_OUTPUT
                } else {
                    (i / s.out_pieces) * s.co + (i % s.out_pieces) * len
                }
            })
            .collect();
        for (with_bias, relu) in [(false, false), (true, false), (true, true)] {
            let run = |t: Transforms| {
                let chunk = Chunk {
                    s,
                    fast: t,
                    images: s.n,
                    x: &[],
                    u: Filters::Same(&[]),
                    bias: with_bias.then_some(&bias[..]),
                    relu,
                    pixels: &[],
                    out_pixels: &out_pixels,
                };
                let mut out = vec![f32::NAN; s.n * s.out_image];
                chunk.output(&m, &mut out);
                out
            };
            same_bits(
                &format!("{s:?} bias {with_bias} relu {relu}"),
                &run(fast),
                &run(portable),
            );
        }
    }
}

/// The output transform's adjoint (the weight gradient's `dM = A·dY·Aᵀ`), zeros past the
/// odd edges.
#[test]
fn output_adjoints_match_their_portable_twins() {
    let mut rng = ChaCha8Rng::seed_from_u64(3);
    for s in shapes().into_iter().filter(|s| s.out_pieces == 1) {
        let (fast, portable) = twins(&s, s.co);
        let (ty, tx) = s.tiles();
        let dz = values(s.n * s.oh * s.ow * s.co, &mut rng);
        let run = |t: Transforms| {
            let mut m = vec![f32::NAN; s.places() * s.n * ty * tx * s.co];
            output_adjoint(&s, &dz, &mut m, t.output);
            m
        };
        same_bits(&format!("{s:?}"), &run(fast), &run(portable));
    }
}
