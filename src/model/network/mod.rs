//! The TDCM network as burn modules: the reference implementation (see `../mod.rs`). Template
//! encoder, search branch (backbone, correlation, upsampler, heads) and weight loading, written
//! for clarity and autodiff; inference code for speed live in `../cpu`, not here.

mod backbone;
mod tdcm;
mod trained_on;
mod weights;

pub use backbone::{Backbone, BackboneConfig, BackboneTrace, ConvNextBlock, GlobalResponseNorm};
pub(crate) use backbone::{GRN_EPS, LAYER_NORM_EPS};
pub(crate) use tdcm::check_template_grid;
pub use tdcm::{
    HEAD_SCALE_MAX, HEAD_SCALE_MIN, Head, Heads, MatchMaps, SearchBranch, SearchTrace,
    TEMPLATE_GRID, Tdcm, TdcmConfig, TemplateEncoder, Upsampler, depthwise_correlation,
};
pub use trained_on::{GridEnvelope, GridShape, Outside, TrainedOn, TrainedOnError};
pub use weights::{
    DEFAULT_WEIGHTS, DEFAULT_WEIGHTS_NAME, LoadError, PYTORCH_KEY_MAP, WeightsFormat,
    WeightsSource, export_pytorch_safetensors, load_weights, load_weights_from_bytes, save_weights,
};
