//! The TDCM network, in two implementations of one function:
//! - [`network`]: burn modules, layer for layer the paper's checkpoint — the reference, and what
//!   training (autodiff) and other backends run;
//! - [`cpu`]: written by hand for serving speed on the host CPU, held to parity with the
//!   reference by the fixtures (`tests/parity.rs`).
//!
//! [`InferenceNetwork`] is the one place that chooses between them. No images, no poses here.

mod cost;
pub mod cpu;
mod device;
mod inference;
pub mod network;
mod precision;

pub use cost::multiply_adds;
pub use cpu::PoseHeads;
pub use device::{DeviceError, available_backends, is_host_cpu, select_device};
pub use inference::InferenceNetwork;
pub use network::{
    Backbone, BackboneConfig, BackboneTrace, ConvNextBlock, DEFAULT_WEIGHTS, DEFAULT_WEIGHTS_NAME,
    GlobalResponseNorm, GridEnvelope, GridShape, HEAD_SCALE_MAX, HEAD_SCALE_MIN, Head, Heads,
    LoadError, MatchMaps, Outside, PYTORCH_KEY_MAP, SearchBranch, SearchTrace, TEMPLATE_GRID, Tdcm,
    TdcmConfig, TemplateEncoder, TrainedOn, TrainedOnError, Upsampler, WeightsFormat,
    WeightsSource, depthwise_correlation, export_pytorch_safetensors, load_weights,
    load_weights_from_bytes, save_weights,
};
pub use precision::{Precision, PrecisionError};
