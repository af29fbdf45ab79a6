//! The Template-Aware Dynamic Convolution Matcher, split the way the service uses it: a
//! [`TemplateEncoder`] turns a template into depthwise kernels once (cached per template ID) and a
//! [`SearchBranch`] runs a batch of search images, each against its own kernels, into the five
//! output maps.

use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::{BatchNorm, BatchNormConfig, PaddingConfig2d, PixelShuffle, PixelShuffleConfig};
use burn::prelude::*;
use burn::tensor::activation::{relu, sigmoid, tanh};
use burn::tensor::module::conv2d;
use burn::tensor::ops::ConvOptions;

use super::backbone::{BATCH_NORM_EPS, Backbone, BackboneConfig, BackboneTrace};

/// Side of the square grid the network sees a template at (the official checkpoint: 36).
/// It must be `8n + 4` so that the template features have an odd side (`2n + 1`) and the
/// correlation output keeps the search feature size.
pub const TEMPLATE_GRID: usize = 36;

/// Smallest and largest scale the official scale heads can express (`sigmoid * 1.5 + 0.5`).
pub const HEAD_SCALE_MIN: f32 = 0.5;
pub const HEAD_SCALE_MAX: f32 = 2.0;

/// Whole-network configuration.
#[derive(Config, Debug)]
pub struct TdcmConfig {
    #[config(default = "BackboneConfig::new()")]
    pub backbone: BackboneConfig,
    /// Upsampler width after the fusion conv (`conv1` outputs twice this).
    #[config(default = 96)]
    pub decoder_channels: usize,
    /// Hidden width of each head.
    #[config(default = 12)]
    pub head_hidden: usize,
}

impl TdcmConfig {
    pub fn init(&self, device: &Device) -> Tdcm {
        Tdcm {
            template_encoder: TemplateEncoder {
                backbone: self.backbone.init(device),
            },
            search_matcher: SearchBranch::new(self, device),
        }
    }
}

/// Both halves of the network; the unit that weights are loaded into and saved from.
#[derive(Module, Debug)]
pub struct Tdcm {
    pub template_encoder: TemplateEncoder,
    pub search_matcher: SearchBranch,
}

/// Template branch: template image → per-channel correlation kernels.
#[derive(Module, Debug)]
pub struct TemplateEncoder {
    pub backbone: Backbone,
}

impl TemplateEncoder {
    /// # Shapes
    /// - `templates`: `[batch, 3, G, G]` with `G` = [`TEMPLATE_GRID`]
    /// - output: `[batch, 96, G/4, G/4]`, one depthwise kernel per channel
    pub fn forward(&self, templates: Tensor<4>) -> Tensor<4> {
        self.forward_traced(templates).0
    }

    /// Like [`TemplateEncoder::forward`], plus the backbone's intermediates.
    pub fn forward_traced(&self, templates: Tensor<4>) -> (Tensor<4>, BackboneTrace) {
        check_template_grid(&templates);
        self.backbone.forward_traced(templates)
    }
}

/// Templates must come on an `8n+4` grid (the correlation's kernels are then odd-sized and
/// centred); anything else is a bug in the caller, not bad input.
pub(crate) fn check_template_grid(templates: &Tensor<4>) {
    let [_, _, h, w] = templates.dims();
    assert!(
        h % 8 == 4 && w % 8 == 4,
        "template grid {h}x{w} is not 8n+4; this is a bug in the caller"
    );
}

/// The five output maps at the search image's resolution (`4*floor(H/4)` x `4*floor(W/4)`).
#[derive(Debug, Clone)]
pub struct MatchMaps {
    /// `[batch, 5, H, W]`, channels:
    /// 0. score: object-centre heatmap in (0, 1);
    /// 1. sign: probability that the rotation angle is positive;
    /// 2. cos: cosine of the rotation angle in (-1, 1);
    /// 3. scale_x: object width / network template grid, in (0.5, 2);
    /// 4. scale_y: object height / network template grid, in (0.5, 2).
    pub stacked: Tensor<4>,
}

impl MatchMaps {
    /// Channel order of [`MatchMaps::stacked`].
    pub const CHANNELS: [&'static str; 5] = ["score", "sign", "cos", "scale_x", "scale_y"];

    /// One map, `[batch, 1, H, W]`, by its index in [`MatchMaps::CHANNELS`].
    pub fn channel(&self, index: usize) -> Tensor<4> {
        let [b, _, h, w] = self.stacked.dims();
        self.stacked
            .clone()
            .slice([0..b, index..index + 1, 0..h, 0..w])
    }
}

/// Every intermediate tensor the parity fixtures store.
pub struct SearchTrace {
    pub backbone: BackboneTrace,
    pub features: Tensor<4>,
    pub correlation: Tensor<4>,
    pub fusion: Tensor<4>,
    pub bn1: Tensor<4>,
    pub bn2: Tensor<4>,
}

/// Search branch: backbone, correlation, upsampler (the field `decoder`, named as in the
/// checkpoint and our weight files) and heads.
#[derive(Module, Debug)]
pub struct SearchBranch {
    pub backbone: Backbone,
    /// 3x3 conv over the correlation (the checkpoint calls it `pointwise_conv`).
    pub fusion: Conv2d,
    pub decoder: Upsampler,
    pub heads: Heads,
}

impl SearchBranch {
    fn new(config: &TdcmConfig, device: &Device) -> Self {
        let c = config.backbone.channels;
        let d = config.decoder_channels;
        let conv3x3 = |cin: usize, cout: usize| {
            Conv2dConfig::new([cin, cout], [3, 3])
                .with_padding(PaddingConfig2d::Explicit(1, 1, 1, 1))
                .init(device)
        };
        Self {
            backbone: config.backbone.init(device),
            fusion: conv3x3(c, c),
            decoder: Upsampler {
                conv1: conv3x3(c, 2 * d),
                bn1: BatchNormConfig::new(2 * d)
                    .with_epsilon(BATCH_NORM_EPS)
                    .init(device),
                conv2: conv3x3(2 * d / 4, d),
                bn2: BatchNormConfig::new(d)
                    .with_epsilon(BATCH_NORM_EPS)
                    .init(device),
                shuffle: PixelShuffleConfig::new(2).init(),
            },
            heads: Heads::new(d / 4, config.head_hidden, device),
        }
    }

    /// # Shapes
    /// - `images`: `[batch, 3, H, W]`, normalised, `H, W >= 4`
    /// - `kernels`: `[batch, 96, k, k]`, `k` odd, from [`TemplateEncoder::forward`]
    ///
    /// burn's modules throughout: differentiable and for any device. Inference on the host CPU
    /// goes through [`crate::model::InferenceNetwork`] instead.
    pub fn forward(&self, images: Tensor<4>, kernels: Tensor<4>) -> MatchMaps {
        let features = self.backbone.forward(images);
        let correlation = depthwise_correlation(features, kernels);
        self.maps_from_correlation(correlation).0
    }

    pub fn forward_traced(
        &self,
        images: Tensor<4>,
        kernels: Tensor<4>,
    ) -> (MatchMaps, SearchTrace) {
        let (features, backbone) = self.backbone.forward_traced(images);
        let correlation = depthwise_correlation(features.clone(), kernels);
        let (maps, (fusion, bn1, bn2)) = self.maps_from_correlation(correlation.clone());
        let trace = SearchTrace {
            backbone,
            features,
            correlation,
            fusion,
            bn1,
            bn2,
        };
        (maps, trace)
    }

    fn maps_from_correlation(
        &self,
        correlation: Tensor<4>,
    ) -> (MatchMaps, (Tensor<4>, Tensor<4>, Tensor<4>)) {
        let fusion = self.fusion.forward(correlation); // [b, 96, h, w]
        let (x, bn1, bn2) = self.decoder.forward(fusion.clone()); // [b, 24, 4h, 4w]
        let maps = MatchMaps {
            stacked: self.heads.forward(x),
        };
        (maps, (fusion, bn1, bn2))
    }
}

/// Per-sample depthwise correlation: sample `i`'s search features, channel `c`, are
/// cross-correlated with sample `i`'s kernel for channel `c`; zero padding keeps the size; no bias.
///
/// # Shapes
/// - `features`: `[batch, c, h, w]`
/// - `kernels`: `[batch, c, k, k]`
/// - output: `[batch, c, h, w]`
pub fn depthwise_correlation(features: Tensor<4>, kernels: Tensor<4>) -> Tensor<4> {
    let [b, c, h, w] = features.dims();
    let [kb, kc, kh, kw] = kernels.dims();
    assert!(
        kb == b && kc == c && kh % 2 == 1 && kw % 2 == 1,
        "kernels {:?} do not fit features {:?}; this is a bug",
        kernels.dims(),
        features.dims()
    );
    // Fold the batch into the channel axis so one grouped conv does every sample.
    let x = features.reshape([1, b * c, h, w]);
    let weight = kernels.reshape([b * c, 1, kh, kw]);
    let options = ConvOptions::new([1, 1], [kh / 2, kw / 2], [1, 1], b * c);
    conv2d(x, weight, None, options).reshape([b, c, h, w])
}

/// Two (conv3x3 → BatchNorm → ReLU → PixelShuffle x2) stages: 1/4 resolution → full.
#[derive(Module, Debug)]
pub struct Upsampler {
    pub conv1: Conv2d,
    pub bn1: BatchNorm,
    pub conv2: Conv2d,
    pub bn2: BatchNorm,
    pub shuffle: PixelShuffle,
}

impl Upsampler {
    /// # Shapes
    /// - `x`: `[batch, 96, h, w]` → `[batch, 24, 4h, 4w]` (plus both pre-ReLU BatchNorm outputs)
    fn forward(&self, x: Tensor<4>) -> (Tensor<4>, Tensor<4>, Tensor<4>) {
        let bn1 = self.bn1.forward(self.conv1.forward(x)); // [b, 192, h, w]
        let x = self.shuffle.forward(relu(bn1.clone())); // [b, 48, 2h, 2w]
        let bn2 = self.bn2.forward(self.conv2.forward(x)); // [b, 96, 2h, 2w]
        let x = self.shuffle.forward(relu(bn2.clone())); // [b, 24, 4h, 4w]
        (x, bn1, bn2)
    }
}

/// One prediction head's weights: conv3x3 → ReLU → conv1x1, then its output function. The five
/// heads run together in [`Heads::forward`].
#[derive(Module, Debug)]
pub struct Head {
    pub conv3x3: Conv2d,
    pub conv1x1: Conv2d,
}

impl Head {
    fn new(channels: usize, hidden: usize, device: &Device) -> Self {
        Self {
            conv3x3: Conv2dConfig::new([channels, hidden], [3, 3])
                .with_padding(PaddingConfig2d::Explicit(1, 1, 1, 1))
                .init(device),
            conv1x1: Conv2dConfig::new([hidden, 1], [1, 1]).init(device),
        }
    }
}

/// The five heads with their output functions.
#[derive(Module, Debug)]
pub struct Heads {
    pub score: Head,
    pub sign: Head,
    pub cos: Head,
    pub scale_x: Head,
    pub scale_y: Head,
}

impl Heads {
    /// The five hidden 3x3 convolutions as one with 60 outputs: weights `[60, 24, 3, 3]` and
    /// biases `[60]`, heads in [`MatchMaps::CHANNELS`] order.
    pub fn stacked_hidden(&self) -> (Tensor<4>, Tensor<1>) {
        let heads = self.all();
        let weight = Tensor::cat(heads.iter().map(|h| h.conv3x3.weight.val()).collect(), 0);
        let bias = Tensor::cat(
            heads
                .iter()
                .map(|h| h.conv3x3.bias.as_ref().expect("heads have biases").val())
                .collect(),
            0,
        );
        (weight, bias)
    }

    /// The heads in [`MatchMaps::CHANNELS`] order.
    pub fn all(&self) -> [&Head; 5] {
        [
            &self.score,
            &self.sign,
            &self.cos,
            &self.scale_x,
            &self.scale_y,
        ]
    }

    fn new(channels: usize, hidden: usize, device: &Device) -> Self {
        Self {
            score: Head::new(channels, hidden, device),
            sign: Head::new(channels, hidden, device),
            cos: Head::new(channels, hidden, device),
            scale_x: Head::new(channels, hidden, device),
            scale_y: Head::new(channels, hidden, device),
        }
    }

    /// All five heads as one conv3x3 (24 → 60) and one grouped conv1x1 (60 → 5): the same
    /// function as five separate heads, but the 3x3 convolution reads its full-resolution input
    /// once instead of five times.
    ///
    /// # Shapes
    /// - `x`: `[batch, 24, H, W]`
    /// - output: `[batch, 5, H, W]`, channels in [`MatchMaps::CHANNELS`] order, output functions
    ///   applied
    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let heads = self.all();
        let (w3, b3) = self.stacked_hidden();
        let w1 = Tensor::cat(heads.iter().map(|h| h.conv1x1.weight.val()).collect(), 0);
        let b1 = Tensor::cat(
            heads
                .iter()
                .map(|h| h.conv1x1.bias.as_ref().expect("heads have biases").val())
                .collect(),
            0,
        );
        let x = relu(conv2d(
            x,
            w3,
            Some(b3),
            ConvOptions::new([1, 1], [1, 1], [1, 1], 1),
        )); // [b, 60, H, W]
        let logits = conv2d(
            x,
            w1,
            Some(b1),
            ConvOptions::new([1, 1], [0, 0], [1, 1], heads.len()),
        ); // [b, 5, H, W]
        let [b, _, h, w] = logits.dims();
        let probabilities = sigmoid(logits.clone()); // score, sign, scale_x, scale_y
        let cos = tanh(logits.slice([0..b, 2..3, 0..h, 0..w]));
        let scales = probabilities.clone().slice([0..b, 3..5, 0..h, 0..w])
            * (HEAD_SCALE_MAX - HEAD_SCALE_MIN)
            + HEAD_SCALE_MIN;
        Tensor::cat(
            vec![probabilities.slice([0..b, 0..2, 0..h, 0..w]), cos, scales],
            1,
        )
    }
}
