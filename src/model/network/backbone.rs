//! The feature extractor both branches share in structure (not weights): the stem and stage 1 of
//! ConvNeXt-V2 tiny followed by a BatchNorm, exactly as the reference README describes it.
//!
//! Details that change the numbers and are easy to get wrong: LayerNorm eps is 1e-6, GELU is the
//! exact erf form, and GRN sums over the *whole* feature map (so features depend on image size).

use burn::module::Param;
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::{
    BatchNorm, BatchNormConfig, Gelu, LayerNorm, LayerNormConfig, Linear, LinearConfig,
    PaddingConfig2d,
};
use burn::prelude::*;

/// ConvNeXt LayerNorm epsilon (timm default for ConvNeXt-V2).
pub(crate) const LAYER_NORM_EPS: f64 = 1e-6;
/// GRN denominator epsilon.
pub(crate) const GRN_EPS: f64 = 1e-6;
/// BatchNorm epsilon (PyTorch default).
pub(crate) const BATCH_NORM_EPS: f64 = 1e-5;

/// Sizes of one backbone. The paper's network uses 96 channels, MLP ratio 4, three blocks.
#[derive(Config, Debug)]
pub struct BackboneConfig {
    #[config(default = 96)]
    pub channels: usize,
    #[config(default = 384)]
    pub hidden: usize,
    #[config(default = 3)]
    pub blocks: usize,
}

impl BackboneConfig {
    pub fn init(&self, device: &Device) -> Backbone {
        Backbone {
            stem_conv: Conv2dConfig::new([3, self.channels], [4, 4])
                .with_stride([4, 4])
                .init(device),
            stem_norm: LayerNormConfig::new(self.channels)
                .with_epsilon(LAYER_NORM_EPS)
                .init(device),
            blocks: (0..self.blocks)
                .map(|_| ConvNextBlock::new(self.channels, self.hidden, device))
                .collect(),
            norm: BatchNormConfig::new(self.channels)
                .with_epsilon(BATCH_NORM_EPS)
                .init(device),
        }
    }
}

/// Stem (4x4 patchify + LayerNorm), three ConvNeXt-V2 blocks, BatchNorm.
#[derive(Module, Debug)]
pub struct Backbone {
    pub stem_conv: Conv2d,
    pub stem_norm: LayerNorm,
    pub blocks: Vec<ConvNextBlock>,
    pub norm: BatchNorm,
}

/// Intermediate outputs, kept only when a parity test asks for them.
pub struct BackboneTrace {
    pub stem: Tensor<4>,
    pub stage1: Tensor<4>,
}

impl Backbone {
    /// # Shapes
    /// - `images`: `[batch, 3, H, W]`, normalised
    /// - output: `[batch, channels, H/4, W/4]`
    pub fn forward(&self, images: Tensor<4>) -> Tensor<4> {
        self.forward_traced(images).0
    }

    /// Like [`Backbone::forward`], also returning the stem and stage-1 outputs.
    pub fn forward_traced(&self, images: Tensor<4>) -> (Tensor<4>, BackboneTrace) {
        let x = self.stem_conv.forward(images); // [b, 96, h, w]
        // LayerNorm over channels: work channels-last for the whole stage.
        let x = self.stem_norm.forward(x.permute([0, 2, 3, 1])); // [b, h, w, 96]
        let stem = x.clone().permute([0, 3, 1, 2]);
        let mut x = stem.clone();
        for block in &self.blocks {
            x = block.forward(x);
        }
        let stage1 = x.clone();
        let out = self.norm.forward(x); // [b, 96, h, w]
        (out, BackboneTrace { stem, stage1 })
    }
}

/// One ConvNeXt-V2 block: `x + fc2(grn(gelu(fc1(norm(dwconv7x7(x))))))`.
#[derive(Module, Debug)]
pub struct ConvNextBlock {
    pub conv_dw: Conv2d,
    pub norm: LayerNorm,
    pub fc1: Linear,
    pub activation: Gelu,
    pub grn: GlobalResponseNorm,
    pub fc2: Linear,
}

impl ConvNextBlock {
    fn new(channels: usize, hidden: usize, device: &Device) -> Self {
        Self {
            conv_dw: Conv2dConfig::new([channels, channels], [7, 7])
                .with_groups(channels)
                .with_padding(PaddingConfig2d::Explicit(3, 3, 3, 3))
                .init(device),
            norm: LayerNormConfig::new(channels)
                .with_epsilon(LAYER_NORM_EPS)
                .init(device),
            fc1: LinearConfig::new(channels, hidden).init(device),
            activation: Gelu::new(),
            grn: GlobalResponseNorm::new(hidden, device),
            fc2: LinearConfig::new(hidden, channels).init(device),
        }
    }

    /// # Shapes
    /// - `x`: `[batch, channels, h, w]` → same
    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let y = self.conv_dw.forward(x.clone()); // [b, 96, h, w]
        let y = self.norm.forward(y.permute([0, 2, 3, 1])); // [b, h, w, 96]
        let y = self.fc1.forward(y); // [b, h, w, 384]
        let y = self.grn.forward(self.activation.forward(y));
        let y = self.fc2.forward(y); // [b, h, w, 96]
        x + y.permute([0, 3, 1, 2])
    }
}

/// ConvNeXt-V2 Global Response Normalisation over a channels-last map.
#[derive(Module, Debug)]
pub struct GlobalResponseNorm {
    pub weight: Param<Tensor<1>>,
    pub bias: Param<Tensor<1>>,
}

impl GlobalResponseNorm {
    fn new(channels: usize, device: &Device) -> Self {
        Self {
            weight: Param::from_tensor(Tensor::zeros([channels], device)),
            bias: Param::from_tensor(Tensor::zeros([channels], device)),
        }
    }

    /// `z + bias + weight * z * N`, `N_c = G_c / (mean_c G + eps)`, `G_c = ||z_c||₂` over all
    /// positions of the sample.
    ///
    /// # Shapes
    /// - `z`: `[batch, h, w, channels]` → same
    pub fn forward(&self, z: Tensor<4>) -> Tensor<4> {
        let [_, _, _, channels] = z.dims();
        let g = z.clone().square().sum_dim(1).sum_dim(2).sqrt(); // [b, 1, 1, c]
        let n = g.clone() / (g.mean_dim(3) + GRN_EPS); // [b, 1, 1, c]
        let weight = self.weight.val().reshape([1, 1, 1, channels]);
        let bias = self.bias.val().reshape([1, 1, 1, channels]);
        z.clone() + bias + weight * z * n
    }
}
