//! The network as the matcher runs it: for answers, not gradients. Built once from loaded
//! weights, it chooses its implementation then: on the host CPU (flex, ndarray) the implementation of
//! [`super::cpu`] (BatchNorm folded, weights laid out for the products — once, not per call);
//! anywhere else the burn modules of [`super::network`], exactly as training runs them. This is
//! the only file that uses both. Both paths compute the
//! same function; the parity tests check each one explicitly against the official fixtures.

use std::sync::{Mutex, PoisonError};

use burn::prelude::*;

use super::cpu::{
    self, BufferPool, CpuBackbone, CpuFeatures, CpuUpsampler, Patch, PoseHeads, UpsamplerTrace,
    converted, correlate,
};
use super::device::is_host_cpu;
use super::network::{BackboneTrace, MatchMaps, SearchTrace, Tdcm};
use super::{Precision, PrecisionError};

/// Loaded weights plus the implementation chosen to run them.
pub struct InferenceNetwork {
    model: Tdcm,
    /// `Some` when inference runs on the CPU implementation.
    host: Option<CpuSearch>,
}

/// The search branch on the CPU implementation.
struct CpuSearch {
    backbone: CpuBackbone,
    upsampler: CpuUpsampler,
    precision: Precision,
    /// Activation buffers kept between samples until [`InferenceNetwork::release_buffers`].
    pool: Mutex<BufferPool>,
}

/// Channels-last intermediates of one sample, for the parity fixtures.
struct CpuSampleTrace {
    stem: Vec<f32>,
    stage1: Vec<f32>,
    features: Vec<f32>,
    correlation: Vec<f32>,
    upsampler: UpsamplerTrace,
}

/// Where one sample's maps go in its batch's: sample `index` of `samples`, `per_sample`
/// values each.
#[derive(Clone, Copy)]
struct BatchMaps {
    index: usize,
    samples: usize,
    per_sample: usize,
}

/// One search sample's inputs: the normalised image `[3, height, width]` (planar) and its
/// template's kernels `[channels, k, k]`.
struct SampleInput<'a> {
    image: &'a [f32],
    height: usize,
    width: usize,
    kernels: &'a [f32],
    k: usize,
}

impl CpuSearch {
    fn new(model: &Tdcm) -> Self {
        Self {
            backbone: CpuBackbone::new(&model.search_matcher.backbone),
            upsampler: CpuUpsampler::new(&model.search_matcher),
            precision: Precision::F32,
            pool: Mutex::default(),
        }
    }

    /// One search sample: `image` planar `[3, height, width]`, `kernels` `[channels, k, k]`
    /// → its maps `[5, 4h, 4w]` (planes) as sample `index` of `maps`, and the intermediates
    /// when `trace`. `maps` holds the whole batch's maps; an empty one is taken from the pool
    /// once the backbone's features are back there (a large frame's features buffer then
    /// holds its maps: the two are never needed at once).
    /// `shared` carries the backbone's features between consecutive samples of one image (the
    /// template-independent half of a search: both contrasts of `Polarity::Either`): taken
    /// instead of running the backbone when it holds some, and left holding this sample's
    /// when `keep` (the next sample searches the same image).
    #[allow(clippy::too_many_arguments)]
    fn sample(
        &self,
        image: &[f32],
        height: usize,
        width: usize,
        kernels: &[f32],
        k: usize,
        trace: bool,
        pose: PoseHeads,
        maps: &mut Vec<f32>,
        maps_for: BatchMaps,
        shared: (&mut Option<CpuFeatures>, bool),
    ) -> Option<CpuSampleTrace> {
        // Concurrent samples each take what the pool holds (possibly nothing), never wait.
        let mut pool =
            std::mem::take(&mut *self.pool.lock().unwrap_or_else(PoisonError::into_inner));
        let sample = SampleInput {
            image,
            height,
            width,
            kernels,
            k,
        };
        let trace = if self.upsampler.takes_bf16() {
            self.sample_with::<u16>(sample, trace, pose, &mut pool, (maps, maps_for), shared)
        } else {
            self.sample_with::<f32>(sample, trace, pose, &mut pool, (maps, maps_for), shared)
        };
        self.pool
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .absorb(pool);
        trace
    }

    /// [`CpuSearch::sample`] with the upsampler's activations in `T`.
    fn sample_with<T: Patch>(
        &self,
        sample: SampleInput,
        trace: bool,
        pose: PoseHeads,
        pool: &mut BufferPool,
        (maps, maps_for): (&mut Vec<f32>, BatchMaps),
        (shared, keep): (&mut Option<CpuFeatures>, bool),
    ) -> Option<CpuSampleTrace> {
        let SampleInput {
            image,
            height,
            width,
            kernels,
            k,
        } = sample;
        let mut out = match shared.take() {
            Some(features) if !trace => features,
            _ => self.backbone.forward(image, height, width, trace, pool),
        };
        let (h, w) = (out.height, out.width);
        let (stem, stage1) = (out.stem.take(), out.stage1.take());
        // The features go back to the pool once correlated, unless traced or kept for the
        // next sample.
        let (correlation, traced) = if trace {
            let correlation = correlate::<f32>(&out.features, h, w, kernels, k, pool);
            (
                converted::<T>(&correlation, pool),
                Some((out.features, correlation)),
            )
        } else {
            let correlation = correlate::<T>(&out.features, h, w, kernels, k, pool);
            if keep {
                *shared = Some(out);
            } else {
                pool.give(out.features);
            }
            (correlation, None)
        };
        if maps.is_empty() {
            *maps = pool.take::<f32>(maps_for.samples * maps_for.per_sample);
        }
        let maps = &mut maps[maps_for.index * maps_for.per_sample..][..maps_for.per_sample];
        let upsampler = self
            .upsampler
            .forward(correlation, h, w, trace, pose, pool, maps);
        upsampler
            .zip(traced)
            .map(|(upsampler, (features, correlation))| CpuSampleTrace {
                stem: stem.expect("traced"),
                stage1: stage1.expect("traced"),
                features,
                correlation,
                upsampler,
            })
    }
}

/// A tensor's values in logical (row-major) order.
fn host_values(t: Tensor<4>) -> Vec<f32> {
    t.into_data()
        .try_into_vec()
        .expect("activations are f32; this is a bug")
}

/// Channels-last samples `[h, w, c]` → one `[batch, c, h, w]` tensor.
fn nchw_tensor(samples: &[&[f32]], h: usize, w: usize, c: usize, device: &Device) -> Tensor<4> {
    let data: Vec<f32> = samples.iter().flat_map(|s| s.iter().copied()).collect();
    Tensor::<4>::from_data(TensorData::new(data, [samples.len(), h, w, c]), device)
        .permute([0, 3, 1, 2])
}

impl InferenceNetwork {
    /// The CPU implementation when `device` is a host CPU backend without autodiff, burn's
    /// modules otherwise.
    pub fn new(model: Tdcm, device: &Device) -> Self {
        if is_host_cpu(device) {
            Self::host(model)
        } else {
            Self::modules(model)
        }
    }

    /// The CPU implementation, whatever the device (they read every tensor into host memory).
    pub fn host(model: Tdcm) -> Self {
        let host = Some(CpuSearch::new(&model));
        Self { model, host }
    }

    /// burn's modules throughout, as training and GPU devices run them.
    pub fn modules(model: Tdcm) -> Self {
        Self { model, host: None }
    }

    /// Runs the search branch's large products (backbone pointwise layers, upsampler and head
    /// convolutions) in `precision` (see [`Precision`]); the template branch stays f32 (its
    /// cost is negligible). Refused where the machine or the device cannot run it.
    pub fn with_precision(mut self, precision: Precision) -> Result<Self, PrecisionError> {
        let precision = precision.resolve(self.host.is_some());
        precision.check_machine()?;
        let Some(host) = &mut self.host else {
            return match precision {
                Precision::Bf16 => Err(PrecisionError::NotHostCpu),
                Precision::F32 | Precision::Auto => Ok(self),
            };
        };
        host.backbone.set_precision(precision);
        host.upsampler.set_precision(precision);
        host.precision = precision;
        Ok(self)
    }

    /// Frees the activation buffers the CPU implementation keep between samples (they let the tiles
    /// of a frame, and frames that follow each other, reuse memory instead of faulting in and
    /// zeroing fresh pages: 7 % of a large frame). They grow to the largest piece seen (a
    /// 2048x2048 frame's 1930² pixels at bf16: about 400 MB, its maps included) and stay until
    /// this is called; the service calls it when its model thread has been idle for a second.
    pub fn release_buffers(&self) {
        if let Some(host) = &self.host {
            *host.pool.lock().unwrap_or_else(PoisonError::into_inner) = BufferPool::default();
        }
    }

    /// Takes back the values of maps this network returned (`MatchMaps::stacked`, read out)
    /// once the caller is done with them, for the next search's maps or activations.
    pub fn recycle(&self, values: Vec<f32>) {
        if let Some(host) = &self.host {
            host.pool
                .lock()
                .unwrap_or_else(PoisonError::into_inner)
                .give(values);
        }
    }

    /// The arithmetic of the search branch's products.
    pub fn precision(&self) -> Precision {
        self.host
            .as_ref()
            .map_or(Precision::F32, |host| host.precision)
    }

    pub fn model(&self) -> &Tdcm {
        &self.model
    }

    /// Whether this network runs the CPU implementation.
    pub fn runs_host_kernels(&self) -> bool {
        self.host.is_some()
    }

    /// Templates → depthwise kernels. See [`super::TemplateEncoder::forward`] for shapes.
    pub fn encode_templates(&self, templates: Tensor<4>) -> Tensor<4> {
        self.encode_templates_traced(templates).0
    }

    pub fn encode_templates_traced(&self, templates: Tensor<4>) -> (Tensor<4>, BackboneTrace) {
        if self.host.is_some() {
            cpu::encode_templates(&self.model.template_encoder, templates)
        } else {
            self.model.template_encoder.forward_traced(templates)
        }
    }

    /// Search images against their kernels → the five maps. See
    /// [`super::SearchBranch::forward`] for shapes.
    pub fn forward(&self, images: Tensor<4>, kernels: Tensor<4>) -> MatchMaps {
        let Some(host) = &self.host else {
            return self.model.search_matcher.forward(images, kernels);
        };
        let device = images.device();
        let batch = SearchBatch::from_tensors(images, kernels);
        let maps = host.search(&batch, PoseHeads::Everywhere, false).0;
        let [h, w] = batch.map_size();
        MatchMaps {
            stacked: Tensor::from_data(TensorData::new(maps, [batch.batch, 5, h, w]), &device),
        }
    }

    /// The matcher's search: planar images `[batch, 3, height, width]` against their kernels
    /// `[batch, 96, k, k]` → the five maps as plain values `[batch, 5, 4⌊height/4⌋,
    /// 4⌊width/4⌋]`, the pose heads evaluated only where `pose` says (on the host CPU; burn's
    /// modules compute every head). On the host CPU the images go to the kernels as they are,
    /// with no tensor in between; hand the values back with [`InferenceNetwork::recycle`].
    ///
    /// On the host CPU the samples of a batch run one after another. Every layer is already
    /// compute-bound at batch 1 (its gemms have tens of thousands of rows), so a batch buys no
    /// weight reuse; what it costs is cache: at batch 4 the backbone's activations after fc1
    /// (~19 MB at 224x224) spill out of L2/L3 and the memory-bound stages (GELU+GRN,
    /// LayerNorm, residuals) slow by 20-40 % (measured with `examples/profile.rs`), which made a
    /// batch of 4 cost 12 % more per pair than four single passes.
    pub fn search_maps(
        &self,
        images: Vec<f32>,
        [batch, height, width]: [usize; 3],
        kernels: Tensor<4>,
        pose: PoseHeads,
    ) -> Vec<f32> {
        let Some(host) = &self.host else {
            let device = kernels.device();
            let images =
                Tensor::from_data(TensorData::new(images, [batch, 3, height, width]), &device);
            return self
                .model
                .search_matcher
                .forward(images, kernels)
                .stacked
                .into_data()
                .try_into_vec()
                .expect("network output is f32; this is a bug");
        };
        let batch = SearchBatch::new(images, [batch, height, width], kernels);
        host.search(&batch, pose, false).0
    }

    /// Like [`InferenceNetwork::forward`], with every intermediate the parity fixtures store.
    pub fn forward_traced(
        &self,
        images: Tensor<4>,
        kernels: Tensor<4>,
    ) -> (MatchMaps, SearchTrace) {
        let Some(host) = &self.host else {
            return self.model.search_matcher.forward_traced(images, kernels);
        };
        let device = images.device();
        let batch = SearchBatch::from_tensors(images, kernels);
        let (maps, traces) = host.search(&batch, PoseHeads::Everywhere, true);
        let [map_h, map_w] = batch.map_size();
        let (h, w) = (batch.height / 4, batch.width / 4);
        let tensor = |part: fn(&CpuSampleTrace) -> &[f32], h: usize, w: usize, c: usize| {
            let parts: Vec<&[f32]> = traces.iter().map(part).collect();
            nchw_tensor(&parts, h, w, c, &device)
        };
        let c = host.backbone.channels();
        let search_trace = SearchTrace {
            backbone: BackboneTrace {
                stem: tensor(|t| &t.stem, h, w, c),
                stage1: tensor(|t| &t.stage1, h, w, c),
            },
            features: tensor(|t| &t.features, h, w, c),
            correlation: tensor(|t| &t.correlation, h, w, c),
            fusion: tensor(|t| &t.upsampler.fusion, h, w, c),
            bn1: tensor(|t| &t.upsampler.bn1, h, w, 2 * c),
            bn2: tensor(|t| &t.upsampler.bn2, 2 * h, 2 * w, c),
        };
        let stacked = Tensor::from_data(
            TensorData::new(maps, [batch.batch, 5, map_h, map_w]),
            &device,
        );
        (MatchMaps { stacked }, search_trace)
    }
}

/// A batch of search samples in host memory: planar images `[batch, 3, height, width]` and
/// their kernels `[batch, channels, k, k]`.
struct SearchBatch {
    images: Vec<f32>,
    batch: usize,
    height: usize,
    width: usize,
    kernels: Vec<f32>,
    /// Side of each depthwise kernel.
    kernel_side: usize,
}

impl SearchBatch {
    /// Planar images `[batch, 3, height, width]` as given, and the kernels `[batch, channels,
    /// k, k]` read into host memory.
    fn new(images: Vec<f32>, [batch, height, width]: [usize; 3], kernels: Tensor<4>) -> Self {
        let kernel_side = kernels.dims()[2];
        Self {
            images,
            batch,
            height,
            width,
            kernels: host_values(kernels),
            kernel_side,
        }
    }

    /// Both operands read out of their tensors.
    fn from_tensors(images: Tensor<4>, kernels: Tensor<4>) -> Self {
        let [batch, _, height, width] = images.dims();
        Self::new(host_values(images), [batch, height, width], kernels)
    }

    /// Sides of the maps: `4⌊side/4⌋`.
    fn map_size(&self) -> [usize; 2] {
        [self.height / 4 * 4, self.width / 4 * 4]
    }
}

impl CpuSearch {
    /// Every sample of `batch` → the batch's maps (planes, `[batch, 5, H, W]`), and each
    /// sample's intermediates when `trace`.
    fn search(
        &self,
        batch: &SearchBatch,
        pose: PoseHeads,
        trace: bool,
    ) -> (Vec<f32>, Vec<CpuSampleTrace>) {
        if batch.batch == 0 {
            return (Vec::new(), Vec::new());
        }
        let image_len = 3 * batch.height * batch.width;
        let kernel_len = self.backbone.channels() * batch.kernel_side * batch.kernel_side;
        assert!(
            batch.images.len() == batch.batch * image_len
                && batch.kernels.len() == batch.batch * kernel_len,
            "{} image and {} kernel values for {} samples of {}x{} and kernels {k}x{k}; this is a bug",
            batch.images.len(),
            batch.kernels.len(),
            batch.batch,
            batch.height,
            batch.width,
            k = batch.kernel_side,
        );
        let [map_h, map_w] = batch.map_size();
        // Every value is written (the pose heads' skipped pixels hold NaN), so the maps may
        // come from the pool: a caller that hands them back ([`InferenceNetwork::recycle`])
        // keeps a large frame's 20 bytes per pixel from being allocated anew every frame.
        let mut maps = Vec::new();
        let mut traces = Vec::new();
        // Consecutive samples of one image (both contrasts of `Polarity::Either`) run the
        // backbone once: comparing the inputs costs a pass over them, the backbone a third of
        // a network pass.
        let image = |i: usize| &batch.images[i * image_len..(i + 1) * image_len];
        let mut shared = None;
        for i in 0..batch.batch {
            let keep = !trace && i + 1 < batch.batch && image(i + 1) == image(i);
            let traced = self.sample(
                image(i),
                batch.height,
                batch.width,
                &batch.kernels[i * kernel_len..(i + 1) * kernel_len],
                batch.kernel_side,
                trace,
                pose,
                &mut maps,
                BatchMaps {
                    index: i,
                    samples: batch.batch,
                    per_sample: 5 * map_h * map_w,
                },
                (&mut shared, keep),
            );
            if trace {
                traces.push(traced.expect("a traced sample returns its trace"));
            }
        }
        (maps, traces)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::TdcmConfig;
    use burn::tensor::Distribution;

    /// The untraced path converts activations while they are in cache and returns them to the
    /// pool early; the traced path (what the parity fixtures check) keeps every f32
    /// intermediate. Both must give the same maps, bit for bit, in every precision.
    #[test]
    fn traced_and_untraced_searches_give_the_same_maps() {
        let device = Default::default();
        let model = TdcmConfig::new().init(&device);
        let mut precisions = vec![Precision::F32];
        if cpu::bf16::available() {
            precisions.push(Precision::Bf16);
        }
        for precision in precisions {
            let network = InferenceNetwork::host(model.clone())
                .with_precision(precision)
                .unwrap();
            let template = Tensor::<4>::random([1, 3, 36, 36], Distribution::Default, &device);
            let kernels = network.encode_templates(template);
            let image = Tensor::<4>::random([2, 3, 72, 88], Distribution::Default, &device);
            let plain = network.forward(image.clone(), kernels.clone().repeat_dim(0, 2));
            let (traced, _) = network.forward_traced(image, kernels.repeat_dim(0, 2));
            let (a, b): (Vec<f32>, Vec<f32>) = (
                plain.stacked.into_data().try_into_vec().unwrap(),
                traced.stacked.into_data().try_into_vec().unwrap(),
            );
            assert_eq!(a.len(), 2 * 5 * 72 * 88);
            assert!(
                a.iter().zip(&b).all(|(x, y)| x.to_bits() == y.to_bits()),
                "{precision:?}: maps differ"
            );
        }
    }

    /// One image searched with two kernels in a row (what `Polarity::Either` sends) runs the
    /// backbone once; the maps are those of two separate searches, bit for bit.
    #[test]
    fn consecutive_samples_of_one_image_share_the_backbone_exactly() {
        let device = Default::default();
        let model = TdcmConfig::new().init(&device);
        let network = InferenceNetwork::host(model)
            .with_precision(Precision::F32)
            .unwrap();
        let templates = Tensor::<4>::random([2, 3, 36, 36], Distribution::Default, &device);
        let kernels = network.encode_templates(templates);
        let image = Tensor::<4>::random([1, 3, 72, 88], Distribution::Default, &device);
        let shared = network.forward(image.clone().repeat_dim(0, 2), kernels.clone());
        // The traced path never shares: every sample runs its own backbone.
        let (separate, _) = network.forward_traced(image.repeat_dim(0, 2), kernels);
        let (a, b): (Vec<f32>, Vec<f32>) = (
            shared.stacked.into_data().try_into_vec().unwrap(),
            separate.stacked.into_data().try_into_vec().unwrap(),
        );
        assert_eq!(a.len(), 2 * 5 * 72 * 88);
        assert!(a.iter().zip(&b).all(|(x, y)| x.to_bits() == y.to_bits()));
        // The two kernels differ, so the maps must too: the second sample saw its own kernel.
        let half = a.len() / 2;
        assert!(a[..half].iter().zip(&a[half..]).any(|(x, y)| x != y));
    }
}
