//! The template branch for inference on the host CPU: burn's backbone modules with the fused
//! GELU+GRN kernel ([`super::gelu_grn`]) in place of burn's element-wise GELU and GRN (about
//! 60 % of the branch's time on flex). A template is tiny (36x36), so the rest of burn's path
//! costs little; the reference modules in `network/` stay free of inference code.

use burn::prelude::*;

use super::gelu_grn::gelu_grn;
use crate::model::network::{
    Backbone, BackboneTrace, ConvNextBlock, GRN_EPS, TemplateEncoder, check_template_grid,
};

/// [`TemplateEncoder::forward_traced`], the same operations in the same order except GELU+GRN.
///
/// # Shapes
/// - `templates`: `[batch, 3, G, G]`, `G` an `8n+4` grid
/// - output: `[batch, 96, G/4, G/4]`, one depthwise kernel per channel
pub(crate) fn encode_templates(
    encoder: &TemplateEncoder,
    templates: Tensor<4>,
) -> (Tensor<4>, BackboneTrace) {
    check_template_grid(&templates);
    backbone_forward(&encoder.backbone, templates)
}

/// [`Backbone::forward_traced`] with the fused GELU+GRN.
fn backbone_forward(backbone: &Backbone, images: Tensor<4>) -> (Tensor<4>, BackboneTrace) {
    let x = backbone.stem_conv.forward(images); // [b, 96, h, w]
    let x = backbone.stem_norm.forward(x.permute([0, 2, 3, 1])); // [b, h, w, 96]
    let stem = x.clone().permute([0, 3, 1, 2]);
    let mut x = stem.clone();
    for block in &backbone.blocks {
        x = block_forward(block, x);
    }
    let stage1 = x.clone();
    let out = backbone.norm.forward(x); // [b, 96, h, w]
    (out, BackboneTrace { stem, stage1 })
}

/// [`ConvNextBlock::forward`] with the fused GELU+GRN.
fn block_forward(block: &ConvNextBlock, x: Tensor<4>) -> Tensor<4> {
    let y = block.conv_dw.forward(x.clone()); // [b, 96, h, w]
    let y = block.norm.forward(y.permute([0, 2, 3, 1])); // [b, h, w, 96]
    let y = block.fc1.forward(y); // [b, h, w, 384]
    let y = gelu_grn(y, block.grn.weight.val(), block.grn.bias.val(), GRN_EPS);
    let y = block.fc2.forward(y); // [b, h, w, 96]
    x + y.permute([0, 3, 1, 2])
}
