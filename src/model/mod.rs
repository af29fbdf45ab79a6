//! The TDCM network in burn: layer for layer the function of the paper's official checkpoint
//! (see `../shared/reference/README.md`), split into a template encoder and a search matcher,
//! plus weight loading and backend selection. No images, no poses: tensors in, tensors out.

mod backbone;
mod bf16;
pub use bf16::{Bf16Kernel, kernel as bf16_kernel, product_gflops};
mod cost;
mod device;
mod fused;
mod host_backbone;
pub use fused::gelu_grn;
mod host_decoder;
mod host_ops;
pub use host_decoder::PoseHeads;
mod inference;
pub use inference::InferenceNetwork;
mod precision;
pub use precision::{Precision, PrecisionError};
mod tdcm;
mod weights;

pub use backbone::{
    Backbone, BackboneConfig, BackboneTrace, ConvNextBlock, GeluGrn, GlobalResponseNorm,
};
pub use cost::multiply_adds;
pub use device::{DeviceError, available_backends, is_host_cpu, select_device};
pub use tdcm::{
    Decoder, HEAD_SCALE_MAX, HEAD_SCALE_MIN, Head, Heads, MatchMaps, SearchMatcher, SearchTrace,
    TEMPLATE_GRID, Tdcm, TdcmConfig, TemplateEncoder, depthwise_correlation,
};
pub use weights::{
    DEFAULT_WEIGHTS, DEFAULT_WEIGHTS_NAME, LoadError, PYTORCH_KEY_MAP, WeightsFormat,
    WeightsSource, export_pytorch_safetensors, load_weights, load_weights_from_bytes, save_weights,
};
