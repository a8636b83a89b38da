//! The article's Q-network, and the IMPALA encoder.

use super::config::ARTICLE_HIDDEN;
use crate::layers::init::VarianceScaling;
use crate::layers::{
    Conv2d, Dense, Dueling, LayerNorm, MaxPool2d, QuantileEmbedding, Relu, Residual, Sequential,
};
use crate::ops::plan;
use crate::tensor::{Border, ConvGeom, Float, Padding, Tensor};
use rand::Rng;

/// The convolutions as the article defines them: `(filters, kernel size, stride)`, SAME (VALID
/// where [`Head::padding`] says so).
const CONVS: [(usize, usize, usize); 3] = [(32, 8, 4), (64, 4, 2), (64, 3, 1)];

/// Builds the article's Q-network for `[H, W, C]` inputs and `n_actions` outputs:
///
/// ```text
/// input  [N, 88, 80, C]        (C = 1 for `vanilla`, 4 for the stacks)
/// conv1  32 @ 8x8, stride 4, SAME, ReLU  -> [N, 22, 20, 32]
/// conv2  64 @ 4x4, stride 2, SAME, ReLU  -> [N, 11, 10, 64]
/// conv3  64 @ 3x3, stride 1, SAME, ReLU  -> [N, 11, 10, 64]
/// flatten (dense1 reads it in place)     -> [N, 7040]
/// dense1 128, ReLU                       -> [N, 128]
/// dense2 n_actions, linear               -> [N, n_actions]   one Q-value per action
/// ```
///
/// With VALID padding (`padding = "valid"`, the Nature DQN's; [`Head::padding`]) the
/// convolutions give `[N, 21, 19, 32]`, `[N, 9, 8, 64]` and `[N, 7, 6, 64]`, and dense1 reads
/// 2 688 features: 0.62 times the multiply-adds per sample.
///
/// Weights are drawn with `init` (the article: VarianceScaling(2.0), i.e. [`VarianceScaling::HE`]),
/// biases start at zero. Any input size works with SAME padding (the gradient checks use small
/// ones); VALID needs at least 36 x 36.
///
/// How it is laid out in memory: each convolution applies its ReLU as it stores its output
/// ([`Conv2d::with_relu`]), and conv1 and conv2 write their outputs with the next layer's SAME
/// padding already around them as a zero border ([`Conv2d::with_border`]), so conv2 and conv3 run
/// as VALID convolutions over `[N, 24, 22, 32]` and `[N, 13, 12, 64]`
/// ([`ConvGeom::as_valid`]). The arithmetic is the table's; what goes is a ReLU pass and a
/// padding copy per layer (about 11 MB of memory traffic per batch-48 forward pass). conv1 reads
/// a training batch in place too when it arrives inside conv1's padding ([`input_border`]).
/// conv2 and conv3 run by Winograd's minimal filtering at batches of 8 or more
/// ([`Conv2d::with_winograd`], [`plan::winograd_pays`]): the same sums, rounded differently.
pub fn article_qnet<T: Float>(
    input: [usize; 3], n_actions: usize, init: &VarianceScaling, rng: &mut impl Rng,
) -> Sequential<T> {
    qnet(input, n_actions, Head::ARTICLE, init, rng)
}

/// The network's options beyond the article's: the convolutions' padding, dense1's width,
/// whether a dueling combine follows dense2, how many values (atoms) each action's output has, an
/// implicit quantile head, and layer normalisation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Head {
    /// The convolutions' padding: SAME (the article's) or VALID (the Nature DQN's).
    pub padding: Padding,
    /// Units of dense1 (the article: 128).
    pub hidden: usize,
    /// A dueling combine after dense2 ([`Dueling`]).
    pub dueling: bool,
    /// Values per action: 1 for a Q-value, `N` for a quantile head's `N` quantiles (QR-DQN), laid
    /// out action by action (`[A, N]` per sample).
    pub atoms: usize,
    /// An implicit quantile head (IQN): each state evaluated at quantile fractions `τ`, one
    /// output row `[A]` per fraction ([`Iqn`]).
    pub iqn: Option<Iqn>,
    /// A [`LayerNorm`] before each convolution's and dense1's ReLU.
    pub layer_norm: bool,
    /// The convolutions before dense1: the article's three, or the IMPALA encoder.
    pub encoder: Encoder,
    /// The IMPALA encoder's widths and depth (with `encoder = Impala`).
    pub impala: Impala,
}

/// The IMPALA encoder's shape: three stages of `channels`, `blocks` residual blocks each.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Impala {
    /// Each stage's channels (Dopamine's: [`IMPALA_CHANNELS`]).
    pub channels: [usize; 3],
    /// Residual blocks per stage (Dopamine's: [`IMPALA_BLOCKS`]).
    pub blocks: usize,
}

impl Impala {
    /// Dopamine's `ImpalaEncoder`: 16, 32 and 32 channels, 2 blocks per stage.
    pub const DOPAMINE: Impala = Impala {
        channels: IMPALA_CHANNELS,
        blocks: IMPALA_BLOCKS,
    };
}

/// The convolutional trunk of the Q-network, before dense1.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Encoder {
    /// The article's three convolutions, conv1 to conv3 ([`article_qnet`]).
    #[default]
    Article,
    /// The IMPALA encoder ([`impala_encoder`]) of the head's [`Impala`] shape (Dopamine's:
    /// channels [`IMPALA_CHANNELS`], [`IMPALA_BLOCKS`] residual blocks per stage); SAME padding
    /// only, no layer normalisation.
    Impala,
}

/// The IMPALA encoder's channels per stage, as Dopamine's `ImpalaEncoder`.
pub const IMPALA_CHANNELS: [usize; 3] = [16, 32, 32];

/// The IMPALA encoder's residual blocks per stage, as Dopamine's.
pub const IMPALA_BLOCKS: usize = 2;

/// An implicit quantile network's settings (Dabney et al. 2018): where the cosine embedding of
/// `τ` enters ([`QuantileEmbedding`]), its size, and how many fractions each pass takes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Iqn {
    /// Cosines per fraction (Dopamine: 64).
    pub embedding: usize,
    /// Where the embedding multiplies the features.
    pub merge: IqnMerge,
    /// `N`: fractions drawn per state for the online network's quantiles in the loss (Dopamine:
    /// 64).
    pub samples: usize,
    /// `N'`: fractions drawn per next state for the target's samples (Dopamine: 64).
    pub target_samples: usize,
    /// `K`: fractions that give `Q(s, a)`, the mean of `Z_τ(s, a)`, for acting and for picking
    /// the bootstrapped action. Here the midpoints `(2k + 1)/(2K)`, a quadrature of the mean
    /// without noise (Dopamine draws 32 at random).
    pub policy_samples: usize,
}

/// Where an implicit quantile head's embedding enters the network.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum IqnMerge {
    /// After the convolutions, as Dopamine's IQN: dense1 then runs once per fraction (`B·N`
    /// rows of 7040 inputs), the cost of which grows with `N`.
    Features,
    /// After dense1 and its ReLU, followed by a dense layer of the same width and a ReLU: the
    /// trunk runs once per state, and only two small layers per fraction.
    #[default]
    Hidden,
}

impl Head {
    /// The article's: 128 units, one Q-value per action.
    pub const ARTICLE: Head = Head {
        padding: Padding::Same,
        hidden: ARTICLE_HIDDEN,
        dueling: false,
        atoms: 1,
        iqn: None,
        layer_norm: false,
        encoder: Encoder::Article,
        impala: Impala::DOPAMINE,
    };

    /// The head a configuration asks for.
    pub fn of(config: &super::Config) -> Head {
        Head {
            padding: config.padding,
            hidden: config.hidden,
            dueling: config.dueling,
            atoms: config.atoms(),
            iqn: config.iqn(),
            layer_norm: config.layer_norm,
            encoder: config.encoder,
            impala: Impala {
                channels: config.impala_channels,
                blocks: config.impala_blocks,
            },
        }
    }

    /// The zero border around `[H, W, C]` states that the network's first convolution reads in
    /// place as its padding ([`input_border`] for the article's conv1; one pixel around for the
    /// IMPALA encoder's 3x3 SAME `stage1.conv`).
    pub fn input_border(&self, input: [usize; 3]) -> Border {
        match self.encoder {
            Encoder::Article => input_border(input, self.padding),
            Encoder::Impala => {
                let [h, w, c] = input;
                let g = ConvGeom::input(h, w, c)
                    .filters(self.impala.channels[0], 3, 3)
                    .same()
                    .expect("a 3x3 SAME convolution of any input");
                g.as_valid().1
            }
        }
    }

    /// `argmax_a Q(x, a)` for one state `x` (`[1, H, W, C]`), by `net` built with this head: the
    /// largest Q-value, the largest mean of a quantile head's atoms, or the largest mean over an
    /// implicit quantile head's `K` policy fractions. A batch-1 [`Sequential::infer`] (acting).
    pub fn greedy(&self, net: &mut Sequential<f32>, x: &Tensor<f32>, n_actions: usize) -> usize {
        super::learner::greedy(self, net, x, n_actions)
    }
}

/// The `k` midpoint fractions `(2i + 1)/(2k)`, `i = 0..k`, repeated for each of `batch` states.
pub fn midpoints(k: usize, batch: usize) -> Vec<f64> {
    (0..batch)
        .flat_map(|_| (0..k).map(move |i| midpoint(i, k)))
        .collect()
}

/// The `i`-th of `k` midpoints, `(2i + 1)/2k`.
pub fn midpoint(i: usize, k: usize) -> f64 {
    (2 * i + 1) as f64 / (2 * k) as f64
}

/// The article's Q-network ([`article_qnet`]) with `head.hidden` units in dense1 (the article:
/// 128) and `head.atoms` outputs per action (1; a quantile head's `N`), and a dueling head if
/// `head.dueling`: dense2 then has `(1 + n_actions)·atoms` outputs, the state value and one
/// advantage per action, which [`Dueling`] combines into `n_actions·atoms` outputs
/// (`Q = V + A − mean A`, atom by atom). With `head.layer_norm`, a [`LayerNorm`] normalises
/// each convolution's and dense1's pre-activations (`ln1` to `ln4`) and applies their ReLU,
/// writing the border the convolution would otherwise have written. With
/// `head.encoder = Impala` the IMPALA encoder ([`impala_encoder`]) takes the three
/// convolutions' place, and dense1 reads its `[11, 10, 32]` output (3 520 features).
pub fn qnet<T: Float>(
    input: [usize; 3], n_actions: usize, head: Head, init: &VarianceScaling, rng: &mut impl Rng,
) -> Sequential<T> {
    let mut net = Sequential::new();
    if head.encoder == Encoder::Impala {
        assert!(
            head.padding == Padding::Same && !head.layer_norm,
            "the IMPALA encoder is SAME and has no layer normalisation"
        );
        net.append(impala_encoder(
            input,
            &head.impala.channels,
            head.impala.blocks,
            init,
            rng,
        ));
    }
    // The three convolutions as the article defines them (SAME, or VALID if the head says so),
    // on the unbordered shapes; none after the IMPALA encoder.
    let convs = match head.encoder {
        Encoder::Article => conv_geometries(input, head.padding),
        Encoder::Impala => Vec::new(),
    };
    for (i, g) in convs.iter().enumerate() {
        // conv1 pads its own input (the network's input); the others read their padding from
        // the border the layer before wrote (and skip its gradient: it is a constant).
        let name = format!("conv{}", i + 1);
        let mut conv = if i == 0 {
            Conv2d::new(&name, *g)
        } else {
            let (valid, padding) = g.as_valid();
            Conv2d::new(&name, valid).with_input_border(padding)
        };
        let border = convs
            .get(i + 1)
            .map(|next| next.as_valid().1)
            .unwrap_or_default();
        // Winograd where the plan says it pays: conv2 (F(2×2, 2×2) over 2×2 blocks) and conv3
        // (F(2×2, 3×3)), not conv1 (4 input channels).
        // conv2 and conv3 read a ReLU's output: acting skips its zeros. conv1 reads frames:
        // acting skips their background.
        conv = conv
            .with_winograd(plan::winograd_pays(g))
            .with_sparse_inference(i > 0)
            .with_background_inference(i == 0);
        if head.layer_norm {
            // The normalisation takes the ReLU and the border the convolution would have
            // written.
            net.push(conv);
            let ln = LayerNorm::new(&format!("ln{}", i + 1), &[g.oh, g.ow, g.cout]);
            net.push(ln.with_relu().with_border(border));
        } else {
            net.push(conv.with_relu().with_border(border));
        }
    }
    // Flatten: dense1 reads each [11, 10, 64] NHWC output as its 7040-vector in place (VALID:
    // [7, 6, 64], 2688).
    let flat = net.output_len();
    let Head {
        hidden,
        dueling,
        atoms,
        iqn,
        layer_norm,
        ..
    } = head;
    if let Some(Iqn {
        embedding,
        merge: IqnMerge::Features,
        ..
    }) = iqn
    {
        net.push(QuantileEmbedding::new("iqn", embedding, flat));
    }
    net.push(Dense::new("dense1", flat, hidden).with_sparse_inference(true));
    if layer_norm {
        net.push(LayerNorm::new("ln4", &[hidden]).with_relu());
    } else {
        net.push(Relu::new("relu4"));
    }
    if let Some(Iqn {
        embedding,
        merge: IqnMerge::Hidden,
        ..
    }) = iqn
    {
        net.push(QuantileEmbedding::new("iqn", embedding, hidden));
        // Its ReLU stored by the products (1 024 rows and more per pass: no pass of its own).
        net.push(Dense::new("dense_tau", hidden, hidden).with_relu());
    }
    if dueling {
        net.push(Dense::new("dense2", hidden, (1 + n_actions) * atoms));
        net.push(Dueling::with_atoms("dueling", n_actions, atoms));
    } else {
        net.push(Dense::new("dense2", hidden, n_actions * atoms));
    }
    for p in net.params_mut() {
        if p.name.ends_with(".weight") {
            init.fill(&mut p.value, rng);
        }
    }
    net
}

/// The three convolutions' geometries for `[H, W, C]` inputs with `padding`, each over the
/// unbordered output of the one before. VALID needs inputs of at least 36 x 36 (conv3's 3 x 3
/// window over conv2's output); panics on smaller ones.
fn conv_geometries(input: [usize; 3], padding: Padding) -> Vec<ConvGeom> {
    let mut shape = input;
    CONVS
        .iter()
        .map(|&(cout, k, s)| {
            let g = ConvGeom::input(shape[0], shape[1], shape[2])
                .filters(cout, k, k)
                .stride(s, s)
                .padding(padding)
                .unwrap_or_else(|| {
                    panic!("{padding:?} convolutions of {input:?} inputs: the input is too small")
                });
            shape = [g.oh, g.ow, cout];
            g
        })
        .collect()
}

/// conv1's padding of `[H, W, C]` inputs as a zero border: states written inside it
/// ([`crate::dqn::Batch::with_border`]) are read by conv1 in place, as the equivalent VALID
/// convolution ([`crate::layers::Conv2d::input_geometry`]); the results are bit-identical.
/// For the article's 88 x 80 input with SAME padding: 2 rows above and below, 2 columns left
/// and right; with VALID padding, none.
pub fn input_border(input: [usize; 3], padding: Padding) -> Border {
    conv_geometries(input, padding)[0].as_valid().1
}

/// The IMPALA encoder (Espeholt et al. 2018, Dopamine's `ImpalaEncoder`) for `[H, W, C]` inputs:
/// for each stage `i` (`channels[i]` channels) a 3x3 stride-1 SAME convolution, a 3x3 stride-2
/// SAME max-pool ([`MaxPool2d`]) and `blocks_per_stage` residual blocks ([`Residual`]); after the
/// last stage a ReLU, as Dopamine applies before flattening. It ends in features, not Q-values:
/// a head (dense layers) goes after it, reading its output in place as a vector.
///
/// With Dopamine's `channels = [16, 32, 32]` and 2 blocks per stage, on the 88 x 80 frame:
///
/// ```text
/// input                                    [N, 88, 80, C]
/// stage1.conv    16 @ 3x3, stride 1, SAME  [N, 88, 80, 16]
/// stage1.pool    3x3, stride 2, SAME       [N, 44, 40, 16]
/// stage1.block1, stage1.block2             [N, 44, 40, 16]
/// stage2.conv    32 @ 3x3                  [N, 44, 40, 32]
/// stage2.pool                              [N, 22, 20, 32]
/// stage2.block1, stage2.block2             [N, 22, 20, 32]
/// stage3.conv    32 @ 3x3                  [N, 22, 20, 32]
/// stage3.pool                              [N, 11, 10, 32]
/// stage3.block1, stage3.block2             [N, 11, 10, 32]
/// relu                                     [N, 11, 10, 32]   3 520 features
/// ```
///
/// Multiply-adds per sample ([`Sequential::macs`]): 52 715 520 for `C = 4` (49 674 240 for
/// `C = 1`), of which the twelve residual convolutions are 36 495 360; the article's whole
/// Q-network is 12 165 888 at `C = 4`.
///
/// Parameters are named `stage{i}.conv.weight`, `stage{i}.block{j}.conv1.weight` and so on,
/// stage by stage in the table's order. Weights are drawn with `init`, biases start at zero.
/// The 3x3 convolutions run by Winograd's minimal filtering where the plan says it pays
/// ([`plan::winograd_pays`]: 32 input channels or more). Any input size works (every layer is
/// SAME).
pub fn impala_encoder<T: Float>(
    input: [usize; 3], channels: &[usize], blocks_per_stage: usize, init: &VarianceScaling,
    rng: &mut impl Rng,
) -> Sequential<T> {
    let mut net = Sequential::new();
    let [mut h, mut w, mut c] = input;
    for (i, &ch) in channels.iter().enumerate() {
        let stage = format!("stage{}", i + 1);
        let g = ConvGeom::input(h, w, c)
            .filters(ch, 3, 3)
            .same()
            .unwrap_or_else(|| panic!("{stage}: no 3x3 SAME convolution of {h}x{w}x{c}"));
        net.push(Conv2d::new(&format!("{stage}.conv"), g).with_winograd(plan::winograd_pays(&g)));
        let pool = MaxPool2d::square(&format!("{stage}.pool"), [h, w, ch], 3, 2, Padding::Same);
        [h, w, c] = [pool.geom.oh, pool.geom.ow, ch];
        net.push(pool);
        for j in 0..blocks_per_stage {
            let block = Residual::new(&format!("{stage}.block{}", j + 1), [h, w, c]);
            let winograd = plan::winograd_pays(&block.geom());
            net.push(block.with_winograd(winograd));
        }
    }
    net.push(Relu::new("relu"));
    for p in net.params_mut() {
        if p.name.ends_with(".weight") {
            init.fill(&mut p.value, rng);
        }
    }
    net
}
