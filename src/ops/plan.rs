//! The kernel plan: which algorithm computes each product of a layer, and why.
//!
//! The layers hold the maths (`y = x·W + b` and its gradients); they ask this module which
//! implementation runs each product for their shape, batch, precision and this CPU, and then
//! call it. Every threshold is a named constant here, with the measurement behind it. This is
//! the first of the two tiers of kernel choice, the algorithm; the second, the instruction set,
//! is each kernel family's own, call by call: its AVX-512, AVX2, AMX or portable loop by the
//! one feature test in [`crate::tensor::cpu`] (whose documentation lists who asks what).
//!
//! | product | portable (f64, or a CPU without AVX2 and FMA) | f32 on AVX2 and FMA, or AVX-512 |
//! |---|---|---|
//! | conv forward | [`Kernel::Im2col`] | [`Kernel::Winograd`] where the layer allows it and the batch is at least [`WINOGRAD_MIN_BATCH`], else [`Kernel::Gather`] |
//! | conv weight gradient | [`Kernel::Im2col`] | as the forward |
//! | conv input gradient | [`Kernel::Im2col`] | input read in place: [`Kernel::Winograd`] where its adjoint fits, else [`Kernel::Phases`]; a padded copy: [`Kernel::Scatter`] |
//! | conv acting | [`Kernel::Background`] or [`Kernel::Sparse`] where the layer allows it and the input is sparse enough ([`BACKGROUND_MAX_DIFFERING`], [`sparse_share`]); else the forward | the same |
//! | dense forward, backward | [`Kernel::Gemm`] | [`Kernel::Gather`] on AVX-512; [`Kernel::Gemm`] on AVX2 |
//! | dense acting | [`Kernel::Sparse`] where allowed and sparse enough ([`dense_sparse_share`]); else the forward | the same |
//!
//! [`kernels`] names what runs here: this crate's family and the instruction set of faer's
//! GEMM (which faer picks from the CPU itself); a checkpoint records it. A run resumed where the
//! name is the same continues bit for bit (with the same thread count). Where it differs the run
//! continues as a valid run, but not bit for bit, and `train --resume` says so: im2col + GEMM
//! sums in another order than the gather GEMM and Winograd, a dense layer takes the gather GEMM
//! on AVX-512 and faer's GEMM on AVX2, and faer's AVX-512 and AVX2 kernels are different code,
//! not promised to sum alike.
//!
//! With [`Precision::Bf16`] on a CPU with AVX512-BF16 ([`bf16_runs`]), the training products
//! take the bf16 gather GEMM ([`crate::tensor::GatherGemmBf16`]: operands rounded to bf16, sums
//! in f32) wherever its pairs of reduction steps exist, [`Kernel::GatherBf16`],
//! [`Kernel::PhasesBf16`] and Winograd's products in bf16, [`Kernel::WinogradBf16`] (see
//! [`conv`] and [`dense`]); acting keeps the sparse and background
//! products, which are faster at batch 1 than any dense product. Without AVX512-BF16 everything
//! runs as in f32.
//!
//! Tests can ask which implementation ran: every choice a layer acts on is recorded per thread
//! ([`last`]), on the thread that called the layer.

use crate::tensor::Border;
use crate::tensor::{ConvGeom, Float, WinogradKind, MAX_PIECES};
use serde::{Deserialize, Serialize};
use std::cell::Cell;

/// The arithmetic of the training products. In bf16 the operands are rounded to bf16 (to
/// nearest even, [`crate::tensor::bf16`]) and the sums stay f32, as do weights, gradients and
/// Adam's state; only where the CPU has AVX512-BF16 ([`bf16_runs`]), elsewhere in f32. `auto`
/// is a request, resolved to one of the two when a run starts
/// (`crate::dqn::resolve_precision`); the layers take it as f32. (The variants' comments are
/// the command line's help.)
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Precision {
    /// f32 operands and sums.
    #[default]
    F32,
    /// bf16 operands, f32 sums (CPUs with AVX512-BF16; elsewhere f32).
    Bf16,
    /// Whichever of f32 and bf16 trains faster on this CPU and thread count, measured when the
    /// run starts and recorded in its config.toml.
    Auto,
}

/// Whether products asked for in `precision` run in bf16 on this CPU: [`Precision::Bf16`] and
/// AVX512-BF16 ([`crate::tensor::cpu::avx512_bf16`]).
pub fn bf16_runs(precision: Precision) -> bool {
    precision == Precision::Bf16 && crate::tensor::cpu::avx512_bf16()
}

/// The kernels this CPU runs training products with in `precision`, by name: this crate's
/// family, `"amx-bf16"` (the bf16 gather GEMM on AMX tiles), `"avx512-bf16"`, `"avx512"`,
/// `"avx2"` or `"portable"`, and, where faer's GEMM takes
/// another instruction set than that family's ([`crate::tensor::cpu::faer_path`]: a family
/// switched off by `INVADERS_NO_AVX512` or `INVADERS_NO_SIMD`), faer's after it, as in
/// `"portable, faer avx2"`. A checkpoint records it, so that a run resumed where another name
/// applies can say that it continues, but not bit for bit.
pub fn kernels(precision: Precision) -> String {
    use crate::tensor::cpu::{faer_path, path, Path};
    let name = |p: Path| match p {
        Path::Avx512 => "avx512",
        Path::Avx2 => "avx2",
        Path::Portable => "portable",
        Path::Amx => "amx",
    };
    let ours = if bf16_runs(precision) && crate::tensor::cpu::amx() {
        "amx-bf16"
    } else if bf16_runs(precision) {
        "avx512-bf16"
    } else {
        name(path())
    };
    if faer_path() == path() {
        ours.to_string()
    } else {
        format!("{ours}, faer {}", name(faer_path()))
    }
}

/// A product a layer computes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Product {
    /// A convolution's forward pass (also acting when no sparse product ran).
    ConvForward,
    /// A convolution's weight gradient.
    ConvWeightGrad,
    /// A convolution's input gradient.
    ConvInputGrad,
    /// A convolution's [`crate::layers::Layer::infer`]: [`Kernel::Sparse`],
    /// [`Kernel::Background`] or, when neither ran, the forward pass's kernel.
    ConvInfer,
    /// A dense layer's forward pass.
    DenseForward,
    /// A dense layer's weight and input gradients.
    DenseBackward,
    /// A dense layer's [`crate::layers::Layer::infer`].
    DenseInfer,
}

const PRODUCTS: usize = 7;

/// An implementation of a product.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kernel {
    /// im2col, then one GEMM (faer) for the forward pass and the weight gradient; for the input
    /// gradient a GEMM then col2im. The portable reference path, any precision: what the f64
    /// gradient checks run.
    Im2col,
    /// A plain GEMM (faer) on the layer's rows: a dense layer's portable path.
    Gemm,
    /// The gather GEMM ([`crate::tensor::GatherGemm`]; AVX-512 or AVX2), reading the (padded) input
    /// through offset tables: no im2col matrix is written.
    Gather,
    /// A convolution's input gradient for an input read in place, by one gather GEMM per stride
    /// phase over `dZ` in a zero border: each `dX` value written once.
    Phases,
    /// A convolution's input gradient `dZ·Wᵀ` added tile by tile onto a padded input gradient
    /// ([`crate::tensor::ScatterGemm`], col2im fused).
    Scatter,
    /// Winograd's minimal filtering ([`crate::tensor::winograd_conv`]).
    Winograd(WinogradKind),
    /// Winograd's minimal filtering with its products in bf16
    /// ([`crate::tensor::winograd_conv_bf16`]): transforms in f32, the transformed operands
    /// rounded to bf16, sums in f32.
    WinogradBf16(WinogradKind),
    /// The bf16 gather GEMM ([`crate::tensor::GatherGemmBf16`]): a convolution's forward pass
    /// (pairs of patch values, next to each other in a pixel's channels) and weight gradient
    /// (pairs of horizontally adjacent output pixels), a dense layer's three products.
    GatherBf16,
    /// A convolution's input gradient by stride phases ([`Kernel::Phases`]) in bf16: pairs of
    /// output channels of `dZ`.
    PhasesBf16,
    /// The sum over the input's nonzero values only ([`crate::tensor::SparseConv`]).
    Sparse,
    /// A constant background's response plus the sparse difference's
    /// ([`crate::tensor::Background`]).
    Background,
}

thread_local! {
    static LAST: [Cell<Option<Kernel>>; PRODUCTS] = const { [const { Cell::new(None) }; PRODUCTS] };
}

/// Records that `kernel` runs `product` on this thread, and returns it.
pub fn ran(product: Product, kernel: Kernel) -> Kernel {
    LAST.with(|l| l[product as usize].set(Some(kernel)));
    kernel
}

/// The implementation that last ran `product` on this thread (`None` before the first).
pub fn last(product: Product) -> Option<Kernel> {
    LAST.with(|l| l[product as usize].get())
}

/// Batches under this keep the direct product instead of Winograd: the filters are transformed
/// on every call, and at batch 1 (acting) F(2×2, 3×3) measured 30% slower for conv3.
pub const WINOGRAD_MIN_BATCH: usize = 8;

/// Winograd for layers with at least this many input channels
/// ([`crate::dqn::article_qnet`]: conv2 with 32, conv3 with 64). conv1 (4 input channels, so 9
/// products of only 64 × 32 per 8×8 pixels, and 5.9 MB of input read by a transform that cannot
/// hide the memory behind arithmetic) measured the train step 2% slower by F(2×2, 2×2) over
/// 4×4 blocks, and its weight gradient alone level. Between 4 and 32 nothing was measured.
pub const WINOGRAD_MIN_INPUT_CHANNELS: usize = 32;

/// Whether Winograd's `kind` pays in bf16 ([`Kernel::WinogradBf16`]) for a convolution's
/// `product`, against the direct bf16 product: that one does twice an f32 FMA's multiply-adds
/// per instruction, so Winograd's saving must beat its transforms at that rate. Measured on
/// AMD Zen 4, one thread, batch 48 (`kbench conv3w fwd 300 48 bf16` and the like, `kbench net
/// x 100 bf16`, 2026-12-07, alternating):
/// - conv3 (F(2×2, 3×3)): forward 1.44–1.50 ms against the direct 1.88–1.90, input gradient
///   1.9 against 2.3, weight gradient 1.65–1.81 against 1.94–2.04 (6 rounds);
/// - conv2 (F(2×2, 2×2) over 2×2 blocks): forward 1.47 against 1.64–1.87, weight gradient
///   1.80–2.24 against 2.04–2.26 (6 rounds); but its input gradient (the adjoint over blocks of
///   one pixel, whose 64 transformed channels give short reductions) 2.4 against 1.8 by phases
///   ([`Kernel::PhasesBf16`]).
pub fn winograd_bf16_pays(kind: WinogradKind, product: Product) -> bool {
    match (kind, product) {
        (WinogradKind::F2x3, _) => true,
        (WinogradKind::S2d(_), Product::ConvInputGrad) => false,
        (WinogradKind::S2d(_), _) => true,
    }
}

/// Whether Winograd pays for a layer of geometry `g` ([`WINOGRAD_MIN_INPUT_CHANNELS`]):
/// the network builder's default for [`crate::layers::Conv2d::with_winograd`].
pub fn winograd_pays(g: &ConvGeom) -> bool {
    winograd_kind(g).is_some() && g.cin >= WINOGRAD_MIN_INPUT_CHANNELS
}

/// The Winograd algorithm for a filter shape, if it has one:
/// - a 3×3 stride-1 filter by F(2×2, 3×3): 4/9 of the multiply-adds;
/// - a `2s × 2s` filter of stride `s` (conv1: 8×8 stride 4; conv2: 4×4 stride 2) by F(2×2,
///   2×2) over `s × s` pixel blocks: 9/16 of the multiply-adds.
pub fn winograd_kind(g: &ConvGeom) -> Option<WinogradKind> {
    match (g.kh, g.kw, g.sh, g.sw) {
        (3, 3, 1, 1) => Some(WinogradKind::F2x3),
        (kh, kw, sh, sw) if kh == kw && sh == sw && kh == 2 * sh => Some(WinogradKind::S2d(sh)),
        _ => None,
    }
}

/// The kernels of a convolution's training products for one batch (see [`conv`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ConvPlan {
    forward: Kernel,
    weight_grad: Kernel,
    input_grad: Kernel,
}

impl ConvPlan {
    /// The forward product's kernel (recorded as run, [`last`]).
    pub fn forward(&self) -> Kernel {
        ran(Product::ConvForward, self.forward)
    }

    /// The weight gradient's kernel (recorded as run).
    pub fn weight_grad(&self) -> Kernel {
        ran(Product::ConvWeightGrad, self.weight_grad)
    }

    /// The input gradient's kernel (recorded as run).
    pub fn input_grad(&self) -> Kernel {
        ran(Product::ConvInputGrad, self.input_grad)
    }

    /// The forward product's kernel, not recorded: for a backward pass that asks what its
    /// forward pass ran.
    pub fn planned_forward(&self) -> Kernel {
        self.forward
    }
}

/// The kernels for a convolution of (input) geometry `g` on a batch of `n` in precision `T`,
/// with Winograd allowed or not, whose input has the zero border `in_border` (written by the
/// layer before; its gradient is not computed).
///
/// - Where [`Float::gather_simd`] (f32 on AVX-512, or on AVX2 and FMA): the gather GEMM, on a zero-padded copy of the input
///   or on the input itself when it needs no padding. It writes no im2col matrix (16× the input
///   for conv1, 21 MB at batch 48), starts from the bias and stores `max(·, 0)` straight into
///   the bordered output. Otherwise im2col + GEMM, which any precision runs.
/// - Winograd (allowed, shape has one, batch at least [`WINOGRAD_MIN_BATCH`]): measured on the
///   1-thread train step, conv3's forward and input gradient about 2–5% faster, its weight
///   gradient about 4% and conv2's forward about 2%; conv2's weight gradient went from 4.7 to
///   3.6 ms, its input gradient from 5.1–7.2 to 3.9–4.4 ms (`kbench net`, one thread, 3
///   alternating rounds). The products reduce over few values (64 channels for conv3, 128 for
///   conv2) and the transforms add passes over tiles 2.25× the input, so the saving is less
///   than the multiply-adds. On AVX2 (Zen 3, 1 thread, `kbench conv2p`, 2 alternating rounds)
///   conv2's forward went from 5.3–5.5 to 4.7 ms, its weight and input gradients together
///   from 13.2 to 11.4 ms, and the train step from 71.5 to 65.1 ms.
/// - The input gradient by Winograd needs the input read in place (its adjoint is again a
///   convolution over it): F(2×2, 3×3) when the input border is at most 2 above and left (the
///   adjoint's padding), F(2×2, 2×2) over blocks when the blocks tile the input exactly and a
///   block has at most [`MAX_PIECES`] pixels. Otherwise, for an input read in place, by stride
///   phases (each `dX` value written once); for a padded copy, scattered onto the padded
///   gradient.
///
/// In bf16 ([`bf16_runs`]; f32 layers only, as [`Float::simd`]) the products take bf16
/// kernels wherever their pairs exist:
/// - [`Kernel::WinogradBf16`] where f32 would take Winograd, [`winograd_bf16_pays`] for the
///   kind and product, and the pairs exist (forward: `s²·Cin` even transformed channels; input
///   gradient: `Cout` even; weight gradient: pairs of tiles, always): conv3's three products,
///   conv2's forward pass and weight gradient;
/// - else [`Kernel::GatherBf16`]: the forward pass where a patch row (`KW·Cin` values) has an
///   even length, the weight gradient where an output row (`OW` pixels) has;
/// - else, for the input gradient of an input read in place with an even `Cout`,
///   [`Kernel::PhasesBf16`];
/// - else the f32 kernel.
pub fn conv<T: Float>(
    g: &ConvGeom, n: usize, winograd: bool, in_border: Border, precision: Precision,
) -> ConvPlan {
    if T::simd() && bf16_runs(precision) {
        let f32_plan = conv::<T>(g, n, false, in_border, Precision::F32);
        let pick = |ok: bool, bf16: Kernel, other: Kernel| if ok { bf16 } else { other };
        // Winograd in bf16 where f32 would take it, the kind pays in bf16 and the transformed
        // channels pair up (forward: `s²·Cin` of them; input gradient: `Cout`).
        let wino = conv::<T>(g, n, winograd, in_border, Precision::F32);
        let wino_bf16 = |k: Kernel, channels: usize, product: Product| match k {
            Kernel::Winograd(kind)
                if winograd_bf16_pays(kind, product) && channels.is_multiple_of(2) =>
            {
                Some(Kernel::WinogradBf16(kind))
            }
            _ => None,
        };
        let s2 = winograd_kind(g).map_or(1, |k| k.block() * k.block());
        return ConvPlan {
            forward: wino_bf16(wino.forward, s2 * g.cin, Product::ConvForward).unwrap_or(pick(
                (g.kw * g.cin).is_multiple_of(2),
                Kernel::GatherBf16,
                f32_plan.forward,
            )),
            // The weight gradient's pairs are pairs of tiles (any count: an odd one is padded).
            weight_grad: wino_bf16(wino.weight_grad, 2, Product::ConvWeightGrad).unwrap_or(pick(
                g.ow.is_multiple_of(2),
                Kernel::GatherBf16,
                f32_plan.weight_grad,
            )),
            input_grad: wino_bf16(wino.input_grad, g.cout, Product::ConvInputGrad).unwrap_or(pick(
                f32_plan.input_grad == Kernel::Phases && g.cout.is_multiple_of(2),
                Kernel::PhasesBf16,
                f32_plan.input_grad,
            )),
        };
    }
    if !T::gather_simd() {
        return ConvPlan {
            forward: Kernel::Im2col,
            weight_grad: Kernel::Im2col,
            input_grad: Kernel::Im2col,
        };
    }
    let wino = winograd_kind(g).filter(|_| winograd && n >= WINOGRAD_MIN_BATCH);
    let direct = g.reads_input_directly();
    let b = in_border;
    let input_grad = match wino {
        Some(WinogradKind::F2x3) if direct && b.top <= 2 && b.left <= 2 => {
            Kernel::Winograd(WinogradKind::F2x3)
        }
        Some(WinogradKind::S2d(s))
            if direct && g.h == s * (g.oh + 1) && g.w == s * (g.ow + 1) && s * s <= MAX_PIECES =>
        {
            Kernel::Winograd(WinogradKind::S2d(s))
        }
        _ if direct => Kernel::Phases,
        _ => Kernel::Scatter,
    };
    let product = wino.map_or(Kernel::Gather, Kernel::Winograd);
    ConvPlan {
        forward: product,
        weight_grad: product,
        input_grad,
    }
}

/// A convolution's acting ([`crate::layers::Layer::infer`]) by [`Kernel::Background`] takes one
/// image of which at most `1/BACKGROUND_MAX_DIFFERING` of the pixels differ from the
/// background. Game frames have 5–13% of their pixels differing (9% typically). With differing
/// pixels scattered at random, the split's per-pixel work made it 14% faster than the dense
/// product at a tenth and 1.6–1.8× slower at a fifth (`cargo bench --bench layers --
/// sparse_act/conv1`).
pub const BACKGROUND_MAX_DIFFERING: usize = 8;

/// Whether acting on a batch of `n` may try [`Kernel::Background`] (allowed by the layer: it
/// reads frames): one image only.
pub fn background(allowed: bool, n: usize) -> bool {
    allowed && n == 1
}

/// Acting by [`Kernel::Sparse`] on one image takes an input of which at most
/// `1/SPARSE_MAX_NONZERO_ONE` is nonzero. The sparse product loads a weight row from L2 for every
/// nonzero value and tap, where the dense one shares each load between several output pixels:
/// at batch 1 on one thread they cross at about 22% nonzero for conv2 and conv3 (`cargo bench
/// --bench layers -- sparse_act`). The count includes the zero border the layer before wrote:
/// an initial network's conv2 and conv3 inputs on game frames are 43% and 36% nonzero by it, a
/// trained network's 5% and 1%.
pub const SPARSE_MAX_NONZERO_ONE: usize = 5;

/// The same for a batch: a batch's dense product is faster per image still (Winograd, both
/// threads), so a batch takes the sparse one only under a tenth.
pub const SPARSE_MAX_NONZERO_BATCH: usize = 10;

/// `share` for [`crate::tensor::Nonzeros::collect_sparse`] when a convolution acts on a batch
/// of `n`: the sparse product runs if at most `1/share` of the (padded) input is nonzero.
pub fn sparse_share(n: usize) -> usize {
    if n == 1 {
        SPARSE_MAX_NONZERO_ONE
    } else {
        SPARSE_MAX_NONZERO_BATCH
    }
}

/// The same for a dense layer: one sample always takes the sparse product (a GEMV reads every
/// weight row, the sparse one only the nonzero inputs' rows); a batch only under a tenth
/// nonzero ([`SPARSE_MAX_NONZERO_BATCH`]: the dense product reads each weight row once for
/// the whole batch, the sparse one once per sample that needs it).
pub fn dense_sparse_share(n: usize) -> usize {
    if n == 1 {
        1
    } else {
        SPARSE_MAX_NONZERO_BATCH
    }
}

/// A dense layer's forward or backward kernel in precision `T`: the gather GEMM where
/// [`Float::simd`] (rows `i·In` and steps `0..In` make it a plain `x·W`), else the GEMM; in
/// bf16 ([`bf16_runs`]) the bf16 gather GEMM, whose pairs are pairs of inputs (forward), of
/// outputs (input gradient) and of samples (weight gradient, an odd batch padded with a zero
/// sample), for a layer whose `In` and `Out` are even.
pub fn dense<T: Float>(precision: Precision, n_in: usize, n_out: usize) -> Kernel {
    let pairs = n_in.is_multiple_of(2) && n_out.is_multiple_of(2);
    if T::simd() && bf16_runs(precision) && pairs {
        Kernel::GatherBf16
    } else if T::simd() {
        Kernel::Gather
    } else {
        Kernel::Gemm
    }
}

/// Whether a dense layer's input gradient `dX = dY·Wᵀ` (`[N, Out]·[Out, In]`) runs on `Wᵀ`
/// (one transpose of the `In × Out` weights) rather than as `dXᵀ = W·dYᵀ` (reading `W`'s rows
/// in place, but transposing `dY` and the result, `N × Out` and `N × In` values): the smaller
/// transpose. dense1 at a batch of 32 (7 040 × 128 weights) reads `W` in place; the layers of
/// an implicit quantile head at 1 024 rows, and dense2 at any batch, transpose `W`. Each
/// element of `dX` is the same sum over the outputs in the same order either way.
pub fn dense_dx_on_wt(n: usize, n_in: usize, n_out: usize) -> bool {
    n * (n_in + n_out) > n_in * n_out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::layers::{Conv2d, Layer};
    use crate::tensor::{Padding, Tensor};

    /// The layer records what it ran: f64 always takes im2col (what the gradient checks test);
    /// f32 takes the plan's fast kernels (Winograd, gather, scatter) where the CPU has AVX-512 or
    /// AVX2 and FMA, else im2col.
    #[test]
    fn the_layer_reports_the_kernel_it_ran() {
        let g = ConvGeom::new(10, 10, 32, 16, 3, 3, (1, 1), Padding::Valid).unwrap();
        let x = Tensor::<f64>::zeros(&[8, 10, 10, 32]);
        let mut conv = Conv2d::<f64>::new("c", g).with_winograd(true);
        conv.forward(&x);
        assert_eq!(last(Product::ConvForward), Some(Kernel::Im2col));
        let dy = Tensor::<f64>::zeros(&[8, 8, 8, 16]);
        conv.backward(&x, &dy, true);
        assert_eq!(last(Product::ConvWeightGrad), Some(Kernel::Im2col));
        assert_eq!(last(Product::ConvInputGrad), Some(Kernel::Im2col));

        let x = Tensor::<f32>::zeros(&[8, 10, 10, 32]);
        let mut conv = Conv2d::<f32>::new("c", g).with_winograd(true);
        conv.forward(&x);
        let expected = if f32::gather_simd() {
            Kernel::Winograd(WinogradKind::F2x3)
        } else {
            Kernel::Im2col
        };
        assert_eq!(last(Product::ConvForward), Some(expected));
        conv.forward(&Tensor::zeros(&[1, 10, 10, 32]));
        let at_one = if f32::gather_simd() {
            Kernel::Gather
        } else {
            Kernel::Im2col
        };
        assert_eq!(
            last(Product::ConvForward),
            Some(at_one),
            "batch 1: no Winograd"
        );

        // A padded copy of the input (SAME): its input gradient is scattered.
        let same = ConvGeom::new(10, 10, 32, 16, 3, 3, (1, 1), Padding::Same).unwrap();
        let mut conv = Conv2d::<f32>::new("c", same);
        conv.forward(&x);
        conv.backward(&x, &Tensor::zeros(&[8, 10, 10, 16]), true);
        let (forward, input_grad) = if f32::gather_simd() {
            (Kernel::Gather, Kernel::Scatter)
        } else {
            (Kernel::Im2col, Kernel::Im2col)
        };
        assert_eq!(last(Product::ConvForward), Some(forward));
        assert_eq!(last(Product::ConvInputGrad), Some(input_grad));
    }
}
