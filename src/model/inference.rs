//! The network as the matcher runs it: for answers, not gradients. Built once from loaded
//! weights, it chooses its kernels then: on the host CPU (flex, ndarray) the fused GELU+GRN
//! kernel and the [`HostDecoder`] (BatchNorm folded, weights laid out for the gemms — once, not
//! per call); anywhere else burn's modules, exactly as training runs them. Both paths compute the
//! same function; the parity tests check each one explicitly against the official fixtures.

use burn::prelude::*;

use super::backbone::{BackboneTrace, GeluGrn, PointwiseBf16};
use super::device::is_host_cpu;
use super::host_decoder::{HostDecoder, PoseHeads};
use super::tdcm::{MatchMaps, SearchTrace, Tdcm, depthwise_correlation};
use super::{Precision, PrecisionError};

/// Loaded weights plus the kernels chosen to run them.
pub struct InferenceNetwork {
    model: Tdcm,
    /// `Some` when inference runs on the host CPU kernels.
    host: Option<HostDecoder>,
    /// The search backbone's pointwise layers for the AMX tiles, at [`Precision::Bf16`].
    pointwise: Option<Vec<PointwiseBf16>>,
}

impl InferenceNetwork {
    /// The host CPU kernels when `device` is a host CPU backend without autodiff, burn's
    /// modules otherwise.
    pub fn new(model: Tdcm, device: &Device) -> Self {
        if is_host_cpu(device) {
            Self::host(model)
        } else {
            Self::modules(model)
        }
    }

    /// The host CPU kernels, whatever the device (they read every tensor into host memory).
    pub fn host(model: Tdcm) -> Self {
        let host = Some(HostDecoder::new(&model.search_matcher));
        Self {
            model,
            host,
            pointwise: None,
        }
    }

    /// burn's modules throughout, as training and GPU devices run them.
    pub fn modules(model: Tdcm) -> Self {
        Self {
            model,
            host: None,
            pointwise: None,
        }
    }

    /// Runs the search branch's large products (backbone pointwise layers, decoder and head
    /// convolutions) in `precision` (see [`Precision`]); the template branch stays f32 (its
    /// cost is negligible). Refused where the machine or the device cannot run it.
    pub fn with_precision(mut self, precision: Precision) -> Result<Self, PrecisionError> {
        precision.check_machine()?;
        let Some(decoder) = &mut self.host else {
            return match precision {
                Precision::F32 => Ok(self),
                Precision::Bf16 => Err(PrecisionError::NotHostCpu),
            };
        };
        decoder.set_precision(precision);
        self.pointwise = (precision == Precision::Bf16).then(|| {
            let blocks = &self.model.search_matcher.backbone.blocks;
            blocks.iter().map(PointwiseBf16::new).collect()
        });
        Ok(self)
    }

    /// The arithmetic of the search branch's products.
    pub fn precision(&self) -> Precision {
        if self.pointwise.is_some() {
            Precision::Bf16
        } else {
            Precision::F32
        }
    }

    pub fn model(&self) -> &Tdcm {
        &self.model
    }

    /// Whether this network runs the host CPU kernels.
    pub fn runs_host_kernels(&self) -> bool {
        self.host.is_some()
    }

    fn gelu_grn(&self) -> GeluGrn {
        if self.host.is_some() {
            GeluGrn::Fused
        } else {
            GeluGrn::Modules
        }
    }

    /// Templates → depthwise kernels. See [`super::TemplateEncoder::forward`] for shapes.
    pub fn encode_templates(&self, templates: Tensor<4>) -> Tensor<4> {
        self.encode_templates_traced(templates).0
    }

    pub fn encode_templates_traced(&self, templates: Tensor<4>) -> (Tensor<4>, BackboneTrace) {
        self.model
            .template_encoder
            .forward_traced(templates, self.gelu_grn())
    }

    /// Search images against their kernels → the five maps. See
    /// [`super::SearchMatcher::forward`] for shapes.
    ///
    /// On the host CPU the samples of a batch run one after another. Every layer is already
    /// compute-bound at batch 1 (its gemms have tens of thousands of rows), so a batch buys no
    /// weight reuse; what it costs is cache: at batch 4 the backbone's activations after fc1
    /// (~19 MB at 224x224) spill out of L2/L3 and the memory-bound stages (GELU+GRN,
    /// LayerNorm, residuals) slow by 20-40 % (measured with `examples/profile.rs`), which made a
    /// batch of 4 cost 12 % more per pair than four single passes.
    pub fn forward(&self, images: Tensor<4>, kernels: Tensor<4>) -> MatchMaps {
        self.forward_for_peaks(images, kernels, PoseHeads::Everywhere)
    }

    /// [`InferenceNetwork::forward`] evaluating the pose heads only where `pose` says (on the
    /// host CPU; other backends compute every head).
    pub fn forward_for_peaks(
        &self,
        images: Tensor<4>,
        kernels: Tensor<4>,
        pose: PoseHeads,
    ) -> MatchMaps {
        let Some(decoder) = &self.host else {
            return self.model.search_matcher.forward(images, kernels);
        };
        let backbone = &self.model.search_matcher.backbone;
        let per_sample = (0..images.dims()[0])
            .map(|i| {
                let (features, _) = backbone.forward_with(
                    images.clone().narrow(0, i, 1),
                    GeluGrn::Fused,
                    self.pointwise.as_deref(),
                );
                let correlation = depthwise_correlation(features, kernels.clone().narrow(0, i, 1));
                decoder.forward(correlation, false, pose).0
            })
            .collect();
        MatchMaps {
            stacked: Tensor::cat(per_sample, 0),
        }
    }

    /// Like [`InferenceNetwork::forward`] (whole batch at once), with every intermediate the
    /// parity fixtures store.
    pub fn forward_traced(
        &self,
        images: Tensor<4>,
        kernels: Tensor<4>,
    ) -> (MatchMaps, SearchTrace) {
        let Some(decoder) = &self.host else {
            return self.model.search_matcher.forward_traced(images, kernels);
        };
        let (features, backbone) = self.model.search_matcher.backbone.forward_with(
            images,
            GeluGrn::Fused,
            self.pointwise.as_deref(),
        );
        let correlation = depthwise_correlation(features.clone(), kernels);
        let (stacked, trace) = decoder.forward(correlation.clone(), true, PoseHeads::Everywhere);
        let trace = trace.expect("trace requested");
        let search_trace = SearchTrace {
            backbone,
            features,
            correlation,
            fusion: trace.fusion,
            bn1: trace.bn1,
            bn2: trace.bn2,
        };
        (MatchMaps { stacked }, search_trace)
    }
}
