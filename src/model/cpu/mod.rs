//! The network written by hand for the host CPU: its second implementation (see `../mod.rs`),
//! for serving. Channels-last, BatchNorm folded into the convolutions once when
//! built from loaded weights, the large products in f32 (`gemm`) or bf16 ([`bf16`]), the
//! memory-bound stages fused into passes that stay in cache. Held to the burn modules of
//! `../network` by the parity fixtures; only `../inference.rs` chooses between the two.

mod backbone;
pub mod bf16;
mod gelu_grn;
pub mod ops;
mod template;
mod upsampler;

pub use bf16::Bf16Instructions;
pub use gelu_grn::gelu_grn;
pub use upsampler::PoseHeads;

pub(crate) use backbone::{CpuBackbone, CpuFeatures, correlate};
pub(crate) use ops::{BufferPool, converted};
pub(crate) use template::encode_templates;
pub(crate) use upsampler::{CpuUpsampler, Patch, UpsamplerTrace};
