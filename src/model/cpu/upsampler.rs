//! The upsampler and heads for inference on the host CPU, channels-last from start to finish.
//!
//! Same function as [`crate::model::Upsampler`] + [`crate::model::Heads`] (the parity fixtures check this path),
//! computed differently: BatchNorm folded into the preceding convolution once, when the
//! [`CpuUpsampler`] is built from loaded weights, every 3x3 convolution
//! as a row-chunked im2col (each chunk fits in L2) times one matrix through the `gemm` crate, chunks
//! in parallel, pixel shuffles as plain gathers, and the five heads' 1x1 convolutions and output
//! functions applied to each chunk while it is still in cache. burn's generic convolution converts
//! NCHW↔NHWC around every layer and builds the whole im2col matrix at once; on the two-core target
//! machine this path is about twice as fast. Training keeps burn's modules (autodiff).

use burn::prelude::*;
use rayon::prelude::*;

use super::bf16::{self, Bf16Weights};
use super::ops::{BufferPool, Pooled, converted, matmul_bias, values};
use crate::model::Precision;
use crate::model::network::{HEAD_SCALE_MAX, HEAD_SCALE_MIN, Heads, SearchBranch};
use burn::nn::BatchNorm;
use burn::nn::conv::Conv2d;

/// Bytes of im2col buffer per parallel chunk: well inside a 1 MB L2.
const CHUNK_BYTES: usize = 384 * 1024;

/// A 3x3 convolution (padding 1) as an im2col weight matrix.
pub(crate) struct Conv3x3 {
    cin: usize,
    cout: usize,
    /// `[9 * cin, cout]`, row `(ky * 3 + kx) * cin + ci`.
    matrix: Vec<f32>,
    bias: Vec<f32>,
    /// The same weights packed for the bf16 products, when the network runs in bf16.
    bf16: Option<Bf16Weights>,
}

/// An element of im2col patches: f32 for the exact path, bf16 bits for the tiles.
pub(crate) trait Patch: Pooled {
    /// Values per patch row (9 · cin, padded to the tiles' k steps for bf16).
    fn row_len(conv: &Conv3x3) -> usize;
    /// Patch rows a buffer for `pixels` pixels must hold.
    fn rows_for(pixels: usize) -> usize;
    /// `out[pixels, cout] = patches · matrix + bias`.
    fn multiply(conv: &Conv3x3, patches: &[Self], pixels: usize, out: &mut [f32]);
}

impl Patch for f32 {
    fn row_len(conv: &Conv3x3) -> usize {
        9 * conv.cin
    }

    fn rows_for(pixels: usize) -> usize {
        pixels
    }

    fn multiply(conv: &Conv3x3, patches: &[f32], pixels: usize, out: &mut [f32]) {
        conv.multiply(patches, pixels, out);
    }
}

impl Patch for u16 {
    fn row_len(conv: &Conv3x3) -> usize {
        conv.bf16_weights().lhs_stride()
    }

    fn rows_for(pixels: usize) -> usize {
        bf16::padded_rows(pixels)
    }

    fn multiply(conv: &Conv3x3, patches: &[u16], pixels: usize, out: &mut [f32]) {
        bf16::multiply(patches, pixels, conv.bf16_weights(), out);
    }
}

impl Conv3x3 {
    /// From a burn conv, with an optional BatchNorm (inference statistics) folded in.
    fn new(conv: &Conv2d, norm: Option<&BatchNorm>) -> Self {
        Self::from_parts(conv.weight.val(), conv.bias.as_ref().map(|b| b.val()), norm)
    }

    fn from_parts(weight: Tensor<4>, bias: Option<Tensor<1>>, norm: Option<&BatchNorm>) -> Self {
        let [cout, cin, kh, kw] = weight.dims();
        assert!(
            kh == 3 && kw == 3,
            "3x3 convolution expected; this is a bug"
        );
        let w: Vec<f32> = weight
            .into_data()
            .try_into_vec()
            .expect("parameters are f32; this is a bug");
        let mut bias = bias.map_or(vec![0.0; cout], values);
        let mut scale = vec![1.0f32; cout];
        if let Some(bn) = norm {
            let (gamma, beta) = (values(bn.gamma.val()), values(bn.beta.val()));
            let (mean, var) = (
                values(bn.running_mean.value()),
                values(bn.running_var.value()),
            );
            for co in 0..cout {
                let s = gamma[co] / (var[co] as f64 + bn.epsilon).sqrt() as f32;
                scale[co] = s;
                bias[co] = (bias[co] - mean[co]) * s + beta[co];
            }
        }
        let mut matrix = vec![0f32; 9 * cin * cout];
        for co in 0..cout {
            for ci in 0..cin {
                for k in 0..9 {
                    matrix[(k * cin + ci) * cout + co] = w[(co * cin + ci) * 9 + k] * scale[co];
                }
            }
        }
        Self {
            cin,
            cout,
            matrix,
            bias,
            bf16: None,
        }
    }

    /// Lays the weights out for the bf16 products or drops that copy (f32).
    fn set_precision(&mut self, precision: Precision) {
        self.bf16 = (precision == Precision::Bf16)
            .then(|| Bf16Weights::new(&self.matrix, 9 * self.cin, self.cout, &self.bias));
    }

    fn bf16_weights(&self) -> &Bf16Weights {
        self.bf16
            .as_ref()
            .expect("bf16 patches only where the weights were laid out; this is a bug")
    }

    /// Rows per chunk for an image `width` wide.
    fn chunk_rows<T: Patch>(&self, width: usize) -> usize {
        (CHUNK_BYTES / (width * T::row_len(self) * size_of::<T>())).max(1)
    }

    /// Fills `patches` (`[rows * width, T::row_len]`) for output rows `y0..y0 + rows`.
    fn im2col<T: Patch>(
        &self,
        input: &[T],
        height: usize,
        width: usize,
        y0: usize,
        rows: usize,
        patches: &mut [T],
    ) {
        let cin = self.cin;
        let row_len = T::row_len(self);
        for (p, patch) in patches
            .chunks_exact_mut(row_len)
            .take(rows * width)
            .enumerate()
        {
            let (y, x) = (y0 + p / width, p % width);
            for ky in 0..3 {
                let sy = y as isize + ky as isize - 1;
                if sy >= 0 && sy < height as isize && x >= 1 && x + 1 < width {
                    // The row's three taps are three adjacent pixels: one copy.
                    let src = (sy as usize * width + x - 1) * cin;
                    patch[ky * 3 * cin..(ky + 1) * 3 * cin]
                        .copy_from_slice(&input[src..src + 3 * cin]);
                    continue;
                }
                for kx in 0..3 {
                    let sx = x as isize + kx as isize - 1;
                    let dst = &mut patch[(ky * 3 + kx) * cin..(ky * 3 + kx + 1) * cin];
                    if sy < 0 || sy >= height as isize || sx < 0 || sx >= width as isize {
                        dst.fill(T::default());
                    } else {
                        let src = (sy as usize * width + sx as usize) * cin;
                        dst.copy_from_slice(&input[src..src + cin]);
                    }
                }
            }
        }
    }

    /// `out[rows * width, cout] = patches · matrix + bias`.
    fn multiply(&self, patches: &[f32], pixels: usize, out: &mut [f32]) {
        let (k, n) = (9 * self.cin, self.cout);
        matmul_bias(patches, pixels, k, &self.matrix, n, &self.bias, out);
    }

    /// The convolution over a whole channels-last image: `[h * w, cin]` → `[h * w, cout]` in
    /// `U` (a pooled buffer).
    fn forward<T: Patch, U: Pooled>(
        &self,
        input: &[T],
        height: usize,
        width: usize,
        pool: &mut BufferPool,
    ) -> Vec<U> {
        self.forward_rows(input, height, width, 0..height, pool)
    }

    /// Output rows `rows` of the convolution over a whole channels-last image `[h * w, cin]`:
    /// `[rows.len() * w, cout]` (a pooled buffer) in the next layer's element type `U`,
    /// converted chunk by chunk while in cache (no f32 copy of the whole output).
    fn forward_rows<T: Patch, U: Pooled>(
        &self,
        input: &[T],
        height: usize,
        width: usize,
        rows: std::ops::Range<usize>,
        pool: &mut BufferPool,
    ) -> Vec<U> {
        let chunk_rows = self.chunk_rows::<T>(width);
        let mut out = pool.take::<U>(rows.len() * width * self.cout);
        out.par_chunks_mut(chunk_rows * width * self.cout)
            .enumerate()
            .for_each_init(
                || {
                    (
                        vec![T::default(); T::rows_for(chunk_rows * width) * T::row_len(self)],
                        vec![0f32; chunk_rows * width * self.cout],
                    )
                },
                |(patches, values), (chunk, out)| {
                    let y0 = rows.start + chunk * chunk_rows;
                    let n = (rows.end - y0).min(chunk_rows);
                    self.im2col(input, height, width, y0, n, patches);
                    let values = &mut values[..n * width * self.cout];
                    T::multiply(self, patches, n * width, values);
                    U::convert_into(values, out);
                },
            );
        out
    }
}

/// ReLU then PixelShuffle(2), channels-last, into the next layer's element type:
/// `[h, w, 4c]` → `[2h, 2w, c]` in `out` (`input.len()` values; rows follow from the length),
/// `out[2y + i, 2x + j, ch] = max(in[y, x, 4ch + 2i + j], 0)`.
fn relu_shuffle_into<T: Patch>(input: &[f32], width: usize, channels_in: usize, out: &mut [T]) {
    let c = channels_in / 4;
    out.par_chunks_mut(2 * width * c).enumerate().for_each_init(
        || vec![0f32; 2 * width * c],
        |row, (oy, out)| {
            let (y, i) = (oy / 2, oy % 2);
            for ox in 0..2 * width {
                let (x, j) = (ox / 2, ox % 2);
                let src = &input[(y * width + x) * channels_in..][..channels_in];
                let dst = &mut row[ox * c..(ox + 1) * c];
                for (ch, d) in dst.iter_mut().enumerate() {
                    *d = src[4 * ch + 2 * i + j].max(0.0);
                }
            }
            T::convert_into(row, out);
        },
    );
}

/// Where the pose heads (sign, cos, scale_x, scale_y) are evaluated. The score head runs at
/// every pixel; a search reads the pose heads only at peaks of the score (and their
/// neighbours above half the peak), so it may skip them elsewhere: four fifths of the heads'
/// 3x3 convolution, about a fifth of the network's multiply-adds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum PoseHeads {
    /// Every pixel: the complete maps (what the parity fixtures compare).
    Everywhere,
    /// Only where the score is at least this; elsewhere the four pose maps hold NaN.
    WhereScoreAtLeast(f32),
}

/// The five heads: a 3x3 conv 24 → 5·12, ReLU, per-head 1x1 conv 12 → 1, output functions.
struct HeadsCpu {
    hidden: Conv3x3,
    /// The same 3x3 convolution split: the score head's 12 channels, and the other four
    /// heads' 48 (for [`PoseHeads::WhereScoreAtLeast`]).
    score_hidden: Conv3x3,
    pose_hidden: Conv3x3,
    /// `[5][12]` weights and `[5]` biases of the 1x1 convolutions.
    output_weight: Vec<[f32; 12]>,
    output_bias: Vec<f32>,
}

impl HeadsCpu {
    fn new(heads: &Heads) -> Self {
        let all = heads.all();
        let (weight, bias) = heads.stacked_hidden();
        let hidden = Conv3x3::from_parts(weight.clone(), Some(bias.clone()), None);
        let score_hidden = Conv3x3::from_parts(
            weight.clone().narrow(0, 0, 12),
            Some(bias.clone().narrow(0, 0, 12)),
            None,
        );
        let pose_hidden =
            Conv3x3::from_parts(weight.narrow(0, 12, 48), Some(bias.narrow(0, 12, 48)), None);
        let mut output_weight = Vec::new();
        let mut output_bias = Vec::new();
        for h in all {
            let w = values(h.conv1x1.weight.val().reshape([12]));
            output_weight.push(w.try_into().expect("12 hidden channels per head"));
            output_bias.push(values(h.conv1x1.bias.as_ref().expect("heads have biases").val())[0]);
        }
        Self {
            hidden,
            score_hidden,
            pose_hidden,
            output_weight,
            output_bias,
        }
    }

    fn set_precision(&mut self, precision: Precision) {
        for conv in [
            &mut self.hidden,
            &mut self.score_hidden,
            &mut self.pose_hidden,
        ] {
            conv.set_precision(precision);
        }
    }

    /// Head `head`'s output from its 12 hidden values (before ReLU).
    fn output(&self, head: usize, hidden: &[f32]) -> f32 {
        let mut logit = self.output_bias[head];
        for (v, w) in hidden.iter().zip(&self.output_weight[head]) {
            logit += v.max(0.0) * w;
        }
        match head {
            2 => logit.tanh(),
            0 | 1 => sigmoid(logit),
            _ => sigmoid(logit) * (HEAD_SCALE_MAX - HEAD_SCALE_MIN) + HEAD_SCALE_MIN,
        }
    }

    /// Output rows `rows` of the heads over `input` (`[height * width, 24]`, zero beyond its
    /// edges) → the five planes (score, sign, cos, scale_x, scale_y) at those pixels, written
    /// from row `plane_row` of `planes` (`[5, plane_len]`, rows `width` long).
    #[allow(clippy::too_many_arguments)]
    fn forward_rows<T: Patch>(
        &self,
        input: &[T],
        height: usize,
        width: usize,
        rows: std::ops::Range<usize>,
        pose: PoseHeads,
        pool: &mut BufferPool,
        planes: &mut [f32],
        plane_row: usize,
    ) {
        let chunk_rows = self.hidden.chunk_rows::<T>(width);
        let k = T::row_len(&self.hidden);
        let pixels = rows.len() * width;
        let mut pixel_major = pool.take::<f32>(pixels * 5);
        pixel_major
            .par_chunks_mut(chunk_rows * width * 5)
            .enumerate()
            .for_each_init(
                || {
                    (
                        vec![T::default(); T::rows_for(chunk_rows * width) * k],
                        vec![0f32; chunk_rows * width * self.hidden.cout],
                        Vec::<T>::new(),
                        Vec::<usize>::new(),
                    )
                },
                |(patches, features, gathered, selected), (chunk, out)| {
                    let y0 = rows.start + chunk * chunk_rows;
                    let n = (rows.end - y0).min(chunk_rows);
                    self.hidden.im2col(input, height, width, y0, n, patches);
                    let out = &mut out[..n * width * 5];
                    match pose {
                        PoseHeads::Everywhere => {
                            T::multiply(&self.hidden, patches, n * width, features);
                            for (f, o) in features.chunks_exact(60).zip(out.chunks_exact_mut(5)) {
                                for (head, value) in o.iter_mut().enumerate() {
                                    *value = self.output(head, &f[head * 12..head * 12 + 12]);
                                }
                            }
                        }
                        PoseHeads::WhereScoreAtLeast(least) => {
                            T::multiply(&self.score_hidden, patches, n * width, features);
                            selected.clear();
                            for (p, (f, o)) in features
                                .chunks_exact(12)
                                .zip(out.chunks_exact_mut(5))
                                .enumerate()
                            {
                                o[0] = self.output(0, f);
                                o[1..].fill(f32::NAN);
                                if o[0] >= least {
                                    selected.push(p);
                                }
                            }
                            if selected.is_empty() {
                                return;
                            }
                            gathered.clear();
                            for &p in selected.iter() {
                                gathered.extend_from_slice(&patches[p * k..(p + 1) * k]);
                            }
                            gathered.resize(T::rows_for(selected.len()) * k, T::default());
                            let pose_features = &mut features[..selected.len() * 48];
                            T::multiply(&self.pose_hidden, gathered, selected.len(), pose_features);
                            for (&p, f) in selected.iter().zip(pose_features.chunks_exact(48)) {
                                for head in 1..5 {
                                    out[p * 5 + head] =
                                        self.output(head, &f[(head - 1) * 12..head * 12]);
                                }
                            }
                        }
                    }
                },
            );
        let plane_len = planes.len() / 5;
        planes
            .par_chunks_mut(plane_len)
            .enumerate()
            .for_each(|(head, plane)| {
                let plane = &mut plane[plane_row * width..][..pixels];
                for (v, o) in plane.iter_mut().zip(pixel_major.chunks_exact(5)) {
                    *v = o[head];
                }
            });
        pool.give(pixel_major);
    }
}

fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

/// One sample's intermediates, channels-last, for the parity fixtures: the fusion
/// convolution's output `[h, w, 96]` and the two pre-ReLU BatchNorm outputs.
pub struct UpsamplerTrace {
    pub fusion: Vec<f32>,
    pub bn1: Vec<f32>,
    pub bn2: Vec<f32>,
}

/// Upsampler + heads on the host CPU, with BatchNorm folded and every weight laid out for the
/// gemms once, at construction.
pub struct CpuUpsampler {
    fusion: Conv3x3,
    conv1: Conv3x3,
    conv2: Conv3x3,
    heads: HeadsCpu,
}

impl CpuUpsampler {
    pub fn new(matcher: &SearchBranch) -> Self {
        Self {
            fusion: Conv3x3::new(&matcher.fusion, None),
            conv1: Conv3x3::new(&matcher.decoder.conv1, Some(&matcher.decoder.bn1)),
            conv2: Conv3x3::new(&matcher.decoder.conv2, Some(&matcher.decoder.bn2)),
            heads: HeadsCpu::new(&matcher.heads),
        }
    }

    /// Runs the convolutions' products in `precision` from now on (the caller checked that the
    /// machine can).
    pub fn set_precision(&mut self, precision: Precision) {
        for conv in [&mut self.fusion, &mut self.conv1, &mut self.conv2] {
            conv.set_precision(precision);
        }
        self.heads.set_precision(precision);
    }

    /// Whether the products take bf16 patches (`u16` activations) rather than f32: the element
    /// type [`CpuUpsampler::forward`] wants its input in.
    pub fn takes_bf16(&self) -> bool {
        self.fusion.bf16.is_some()
    }

    /// One sample's channels-last correlation `[h, w, 96]`, in the products' element type
    /// ([`CpuUpsampler::takes_bf16`]) → its five maps `[5, 4h, 4w]` (planes) in `maps`, and the
    /// intermediates when `trace`. Activations come from and go back to `pool`: each goes back
    /// as soon as the next layer has read it, so at most two whole-image activations are alive
    /// at a time.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn forward<T: Patch>(
        &self,
        correlation: Vec<T>,
        h: usize,
        w: usize,
        trace: bool,
        pose: PoseHeads,
        pool: &mut BufferPool,
        maps: &mut [f32],
    ) -> Option<UpsamplerTrace> {
        let (fused, fusion) = if trace {
            let fusion: Vec<f32> = self.fusion.forward(&correlation, h, w, pool);
            (converted::<T>(&fusion, pool), Some(fusion))
        } else {
            (self.fusion.forward(&correlation, h, w, pool), None)
        }; // [h, w, 96]
        pool.give(correlation);
        let (input, bn1) = self.conv1_shuffled(&fused, h, w, trace, pool); // [2h, 2w, 48]
        pool.give(fused);
        let band = tail_band_rows(2 * h, 2 * w, self.conv2.cout);
        let bn2 = self.tail(&input, 2 * h, 2 * w, band, trace, pose, pool, maps);
        pool.give(input);
        trace.then(|| UpsamplerTrace {
            fusion: fusion.expect("traced"),
            bn1: bn1.expect("traced"),
            bn2: bn2.expect("traced"),
        })
    }

    /// conv1 (+ BatchNorm) → ReLU + PixelShuffle over `input` (`[h * w, 96]`) →
    /// `[2h, 2w, 48]` in `T` (a pooled buffer), band by band of rows so that conv1's f32
    /// output (192 channels) exists only for one band; that output too when `trace`.
    fn conv1_shuffled<T: Patch>(
        &self,
        input: &[T],
        h: usize,
        w: usize,
        trace: bool,
        pool: &mut BufferPool,
    ) -> (Vec<T>, Option<Vec<f32>>) {
        let cout = self.conv1.cout;
        let mut bn1 = trace.then(|| Vec::with_capacity(h * w * cout));
        let mut shuffled = pool.take::<T>(h * w * cout);
        let band = tail_band_rows(h, w, cout);
        for y0 in (0..h).step_by(band) {
            let y1 = (y0 + band).min(h);
            let x: Vec<f32> = self.conv1.forward_rows(input, h, w, y0..y1, pool);
            if let Some(bn1) = &mut bn1 {
                bn1.extend_from_slice(&x);
            }
            relu_shuffle_into(&x, w, cout, &mut shuffled[y0 * w * cout..y1 * w * cout]);
            pool.give(x);
        }
        (shuffled, bn1)
    }

    /// conv2 (+ BatchNorm) → ReLU + PixelShuffle → heads over `input` (`[h * w, 48]`, half
    /// resolution) → the five full-resolution planes in `maps`; conv2's output when `trace`.
    ///
    /// Band by band of `band` half-resolution rows, so the two largest activations of the
    /// network (conv2's 96 channels at half resolution, the heads' 24 at full resolution:
    /// about 0.14 KB per network pixel at bf16) exist only for one band at a time and stay in
    /// cache from one layer to the next. The heads' 3x3 convolution reads one row beyond each band: the last
    /// two full-resolution rows of a band are carried into the next, and each band's heads
    /// stop one row short of its end (the last band runs to the bottom edge), so every value
    /// is computed once and equals the whole-image computation.
    #[allow(clippy::too_many_arguments)]
    fn tail<T: Patch>(
        &self,
        input: &[T],
        height: usize,
        width: usize,
        band: usize,
        trace: bool,
        pose: PoseHeads,
        pool: &mut BufferPool,
        maps: &mut [f32],
    ) -> Option<Vec<f32>> {
        let (full_height, full_width) = (2 * height, 2 * width);
        let row_len = full_width * self.conv2.cout / 4;
        let band = band.clamp(1, height.max(1));
        let mut bn2 = trace.then(|| Vec::with_capacity(height * width * self.conv2.cout));
        // Full-resolution rows: up to two carried from the previous band, then this band's.
        let mut full = pool.take::<T>((2 + 2 * band) * row_len);
        let (mut carried, mut done) = (0, 0);
        for y0 in (0..height).step_by(band) {
            let y1 = (y0 + band).min(height);
            let x: Vec<f32> = self.conv2.forward_rows(input, height, width, y0..y1, pool);
            if let Some(bn2) = &mut bn2 {
                bn2.extend_from_slice(&x);
            }
            let local_rows = carried + 2 * (y1 - y0);
            relu_shuffle_into(
                &x,
                width,
                self.conv2.cout,
                &mut full[carried * row_len..local_rows * row_len],
            );
            pool.give(x);
            // Local row 0 is full-resolution row `first`.
            let first = 2 * y0 - carried;
            let end = if y1 == height {
                full_height
            } else {
                2 * y1 - 1
            };
            self.heads.forward_rows(
                &full[..local_rows * row_len],
                local_rows,
                full_width,
                done - first..end - first,
                pose,
                pool,
                maps,
                done,
            );
            done = end;
            full.copy_within((local_rows - 2) * row_len..local_rows * row_len, 0);
            carried = 2;
        }
        pool.give(full);
        bn2
    }
}

/// Rows per band of a banded convolution ([`CpuUpsampler::tail`], `conv1_shuffled`) over an
/// image `height x width` with `channels` output channels: the band's f32 output about 4 MB
/// (L2/L3-sized), at least a few rows per thread so every core has chunks, equal bands.
fn tail_band_rows(height: usize, width: usize, channels: usize) -> usize {
    const BAND_BYTES: usize = 4 << 20;
    let rows = (BAND_BYTES / (width * channels * size_of::<f32>()))
        .max(4 * rayon::current_num_threads())
        .clamp(1, height.max(1));
    // Equal bands.
    height.div_ceil(height.div_ceil(rows))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::TdcmConfig;

    /// `len` standard normal values.
    fn random_values(len: usize) -> Vec<f32> {
        Tensor::<1>::random(
            [len],
            burn::tensor::Distribution::Normal(0.0, 1.0),
            &Default::default(),
        )
        .into_data()
        .try_into_vec()
        .unwrap()
    }

    #[test]
    fn the_tail_band_by_band_equals_the_whole_image_at_once() {
        let device = Default::default();
        let model = TdcmConfig::new().init(&device);
        let upsampler = CpuUpsampler::new(&model.search_matcher);
        let (h, w) = (13, 7);
        let input = random_values(h * w * 48);
        let mut pool = BufferPool::default();
        let mut run = |band, pose| {
            let mut maps = vec![f32::INFINITY; 5 * 4 * h * w];
            let bn2 = upsampler.tail(&input, h, w, band, true, pose, &mut pool, &mut maps);
            (maps, bn2.expect("traced"))
        };
        for pose in [PoseHeads::Everywhere, PoseHeads::WhereScoreAtLeast(0.5)] {
            let (whole, whole_bn2) = run(h, pose);
            assert!(whole.iter().all(|v| v.is_finite() || v.is_nan()));
            assert_eq!(whole_bn2.len(), h * w * 96);
            for band in [1, 2, 5, 12] {
                let (maps, bn2) = run(band, pose);
                assert_eq!(bn2, whole_bn2, "conv2 with bands of {band} rows");
                for (p, (a, b)) in maps.iter().zip(&whole).enumerate() {
                    assert!(
                        a.to_bits() == b.to_bits(),
                        "bands of {band} rows, value {p}: {a} vs {b}"
                    );
                }
            }
        }
    }

    #[test]
    fn pose_heads_where_the_score_is_high_equal_the_full_maps_there() {
        let device = Default::default();
        let model = TdcmConfig::new().init(&device);
        let upsampler = CpuUpsampler::new(&model.search_matcher);
        let correlation = random_values(9 * 11 * 96);
        let mut pool = BufferPool::default();
        let mut planes = |pose| {
            let mut maps = vec![0f32; 5 * 36 * 44];
            upsampler.forward(
                correlation.clone(),
                9,
                11,
                false,
                pose,
                &mut pool,
                &mut maps,
            );
            maps
        };
        let full = planes(PoseHeads::Everywhere);
        let n = full.len() / 5;
        let mut scores = full[..n].to_vec();
        scores.sort_by(f32::total_cmp);
        let least = scores[n / 2];
        let partial = planes(PoseHeads::WhereScoreAtLeast(least));
        let mut kept = 0;
        for p in 0..n {
            assert!((full[p] - partial[p]).abs() < 1e-6, "score at {p}");
            for head in 1..5 {
                let (a, b) = (full[head * n + p], partial[head * n + p]);
                if full[p] >= least {
                    assert!((a - b).abs() < 1e-5, "head {head} at {p}: {a} vs {b}");
                } else {
                    assert!(b.is_nan(), "head {head} at {p} should be skipped");
                }
            }
            kept += usize::from(full[p] >= least);
        }
        assert!(kept >= n / 2 && kept < n, "{kept} of {n}");
    }
}
