//! The search backbone for inference on the host CPU, channels-last from the stem to the
//! features, and the correlation with the template's kernels.
//!
//! Same function as [`crate::model::Backbone`] + [`crate::model::depthwise_correlation`] (the parity fixtures
//! check this path), computed so that a large frame is not bound by the stages between the
//! products. burn runs each ConvNeXt block as six full passes over the image (depthwise
//! convolution, permute + LayerNorm, fc1, GELU + GRN, fc2, permute + residual) with a fresh
//! activation per pass; here a block is two passes over pixel chunks that stay in cache:
//!
//! 1. depthwise 7x7 + LayerNorm + fc1 + GELU per chunk, keeping each channel's sum of squares
//!    (the only whole-image quantity, GRN's norms), the 384-channel activation stored once
//!    (in bf16 when the network runs in bf16);
//! 2. GRN folded into fc2 — `fc2(z·s + b) = z·(diag(s)·W) + (b·W + bias)`, with the per-channel
//!    `s` of this image — and the residual added in place.
//!
//! The stem (4x4 patchify + LayerNorm) is one pass, the closing BatchNorm a scale and shift.

use burn::nn::conv::Conv2d;
use rayon::prelude::*;

use super::bf16::{self, Bf16Weights};
use super::ops::{
    BufferPool, Pooled, add_in_place, depthwise_pixels, gelu_with_squares, layer_norm_rows,
    matmul_bias, scale_shift_rows, values,
};
use crate::model::Precision;
use crate::model::network::{Backbone, ConvNextBlock, GRN_EPS, LAYER_NORM_EPS};

/// Pixels per parallel chunk: the chunk's fc1 output (256 x 384 f32, 384 KiB) stays in L2.
/// A multiple of the tile routine's 32-row blocks.
const CHUNK_PIXELS: usize = 256;
/// Side of the depthwise convolution in each block.
const BLOCK_KERNEL: usize = 7;

/// A dense layer `[k] → [n]` as a row-major matrix, with its packed bf16 copy.
struct Dense {
    k: usize,
    n: usize,
    matrix: Vec<f32>,
    bias: Vec<f32>,
    bf16: Option<Bf16Weights>,
}

impl Dense {
    fn new(matrix: Vec<f32>, k: usize, n: usize, bias: Vec<f32>) -> Self {
        assert!(
            matrix.len() == k * n && bias.len() == n,
            "dense layer shape; this is a bug"
        );
        Self {
            k,
            n,
            matrix,
            bias,
            bf16: None,
        }
    }

    fn set_precision(&mut self, precision: Precision) {
        self.bf16 = (precision == Precision::Bf16)
            .then(|| Bf16Weights::new(&self.matrix, self.k, self.n, &self.bias));
    }
}

/// LayerNorm parameters.
struct Norm {
    gamma: Vec<f32>,
    beta: Vec<f32>,
}

impl Norm {
    fn new(norm: &burn::nn::LayerNorm) -> Self {
        let gamma = values(norm.gamma.val());
        let beta = norm
            .beta
            .as_ref()
            .map_or(vec![0.0; gamma.len()], |b| values(b.val()));
        Self { gamma, beta }
    }

    fn apply(&self) -> (&[f32], &[f32], f32) {
        (&self.gamma, &self.beta, LAYER_NORM_EPS as f32)
    }
}

struct HostBlock {
    /// `[49, channels]`, tap `ky * 7 + kx`.
    depthwise: Vec<f32>,
    depthwise_bias: Vec<f32>,
    norm: Norm,
    fc1: Dense,
    grn_weight: Vec<f32>,
    grn_bias: Vec<f32>,
    fc2: Dense,
}

impl HostBlock {
    fn new(block: &ConvNextBlock) -> Self {
        let (depthwise, depthwise_bias) = depthwise_taps(&block.conv_dw);
        let linear = |layer: &burn::nn::Linear| {
            let [k, n] = layer.weight.dims();
            let matrix = values(layer.weight.val().reshape([k * n]));
            let bias = layer
                .bias
                .as_ref()
                .map_or(vec![0.0; n], |b| values(b.val()));
            Dense::new(matrix, k, n, bias)
        };
        Self {
            depthwise,
            depthwise_bias,
            norm: Norm::new(&block.norm),
            fc1: linear(&block.fc1),
            grn_weight: values(block.grn.weight.val()),
            grn_bias: values(block.grn.bias.val()),
            fc2: linear(&block.fc2),
        }
    }

    /// fc2 with this image's GRN folded in, from the per-channel sums of squares of the GELU
    /// output: `N_c = G_c / (mean G + eps)`, `G_c = sqrt(squares_c)`; GRN is
    /// `z·(1 + w_c·N_c) + b_c`.
    fn fc2_with_grn(&self, squares: &[f64], bf16: bool) -> Dense {
        let norms: Vec<f64> = squares.iter().map(|s| s.sqrt()).collect();
        let mean = norms.iter().sum::<f64>() / norms.len() as f64;
        let (k, n) = (self.fc2.k, self.fc2.n);
        let mut matrix = self.fc2.matrix.clone();
        let mut bias = self.fc2.bias.clone();
        for c in 0..k {
            let scale = 1.0 + self.grn_weight[c] * (norms[c] / (mean + GRN_EPS)) as f32;
            let row = &mut matrix[c * n..(c + 1) * n];
            for (b, w) in bias.iter_mut().zip(row.iter()) {
                *b += self.grn_bias[c] * *w;
            }
            row.iter_mut().for_each(|w| *w *= scale);
        }
        let mut dense = Dense::new(matrix, k, n, bias);
        if bf16 {
            dense.set_precision(Precision::Bf16);
        }
        dense
    }
}

/// A depthwise convolution's weights `[c, 1, k, k]` as taps `[k * k, c]`, and its bias.
fn depthwise_taps(conv: &Conv2d) -> (Vec<f32>, Vec<f32>) {
    let [c, _, k, _] = conv.weight.dims();
    let bias = conv.bias.as_ref().map_or(vec![0.0; c], |b| values(b.val()));
    (
        channels_last_taps(&values(conv.weight.val().reshape([c * k * k])), c, k),
        bias,
    )
}

/// `[c, k, k]` → `[k * k, c]`.
fn channels_last_taps(weights: &[f32], channels: usize, k: usize) -> Vec<f32> {
    let mut taps = vec![0f32; weights.len()];
    for c in 0..channels {
        for t in 0..k * k {
            taps[t * channels + c] = weights[c * k * k + t];
        }
    }
    taps
}

/// Per-thread buffers of pass 1.
struct Scratch {
    /// A chunk after depthwise + LayerNorm, `[CHUNK_PIXELS, channels]`.
    normed: Vec<f32>,
    /// The same rounded to bf16 in the tile routine's row layout (bf16 only).
    lhs: Vec<u16>,
    /// fc1's f32 output before it is rounded into the hidden activation (bf16 only).
    activation: Vec<f32>,
}

/// The 384-channel activation between fc1 and fc2 of one block, in the products' element type.
enum Hidden {
    F32(Vec<f32>),
    /// Rows padded to whole 32-row blocks for the tile routine.
    Bf16(Vec<u16>),
}

/// What one image's backbone produced, channels-last.
pub(crate) struct CpuFeatures {
    pub height: usize,
    pub width: usize,
    /// `[height, width, channels]`, after the closing BatchNorm.
    pub features: Vec<f32>,
    /// The stem's and stage 1's outputs, when traced.
    pub stem: Option<Vec<f32>>,
    pub stage1: Option<Vec<f32>>,
}

/// The search backbone on the host CPU, built once from loaded weights.
pub(crate) struct CpuBackbone {
    channels: usize,
    /// Stem as a `[3·4·4, channels]` matrix over patches ordered `(ci, ky, kx)`.
    stem: Dense,
    stem_norm: Norm,
    blocks: Vec<HostBlock>,
    /// The closing BatchNorm (inference statistics) as a scale and shift.
    out_scale: Vec<f32>,
    out_shift: Vec<f32>,
    /// Whether fc1 and fc2 run in bf16.
    bf16: bool,
}

impl CpuBackbone {
    pub(crate) fn new(backbone: &Backbone) -> Self {
        let [channels, cin, kh, kw] = backbone.stem_conv.weight.dims();
        let patch = cin * kh * kw;
        let weights = values(backbone.stem_conv.weight.val().reshape([channels * patch]));
        let mut matrix = vec![0f32; patch * channels];
        for co in 0..channels {
            for p in 0..patch {
                matrix[p * channels + co] = weights[co * patch + p];
            }
        }
        let stem_bias = backbone
            .stem_conv
            .bias
            .as_ref()
            .map_or(vec![0.0; channels], |b| values(b.val()));
        let bn = &backbone.norm;
        let (gamma, beta) = (values(bn.gamma.val()), values(bn.beta.val()));
        let (mean, var) = (
            values(bn.running_mean.value()),
            values(bn.running_var.value()),
        );
        let out_scale: Vec<f32> = (0..channels)
            .map(|c| gamma[c] / (var[c] as f64 + bn.epsilon).sqrt() as f32)
            .collect();
        let out_shift = (0..channels)
            .map(|c| beta[c] - mean[c] * out_scale[c])
            .collect();
        Self {
            channels,
            stem: Dense::new(matrix, patch, channels, stem_bias),
            stem_norm: Norm::new(&backbone.stem_norm),
            blocks: backbone.blocks.iter().map(HostBlock::new).collect(),
            out_scale,
            out_shift,
            bf16: false,
        }
    }

    /// Runs fc1 and fc2 in `precision` (resolved: f32 or bf16) from now on (the caller
    /// checked that the machine can).
    pub(crate) fn set_precision(&mut self, precision: Precision) {
        self.bf16 = precision == Precision::Bf16;
        for block in &mut self.blocks {
            block.fc1.set_precision(precision);
        }
    }

    pub(crate) fn channels(&self) -> usize {
        self.channels
    }

    /// One normalised image `[3, height, width]` (planar) → features
    /// `[height / 4, width / 4, channels]` (a buffer from `pool`, which also lends the
    /// activations).
    pub(crate) fn forward(
        &self,
        image: &[f32],
        height: usize,
        width: usize,
        trace: bool,
        pool: &mut BufferPool,
    ) -> CpuFeatures {
        let (h, w) = (height / 4, width / 4);
        let mut x = self.stem(image, height, width, pool);
        let stem = trace.then(|| x.clone());
        for block in &self.blocks {
            self.block(block, &mut x, h, w, pool);
        }
        let stage1 = trace.then(|| x.clone());
        x.par_chunks_mut(CHUNK_PIXELS * self.channels)
            .for_each(|rows| scale_shift_rows(rows, &self.out_scale, &self.out_shift));
        CpuFeatures {
            height: h,
            width: w,
            features: x,
            stem,
            stage1,
        }
    }

    /// 4x4 patchify with stride 4, then LayerNorm: `[3, H, W]` → `[H/4 · W/4, channels]`.
    fn stem(&self, image: &[f32], height: usize, width: usize, pool: &mut BufferPool) -> Vec<f32> {
        let (h, w, c) = (height / 4, width / 4, self.channels);
        let planes = self.stem.k / 16;
        assert!(
            image.len() == planes * height * width,
            "stem: image is not [{planes}, {height}, {width}]; this is a bug"
        );
        let mut out = pool.take::<f32>(h * w * c);
        out.par_chunks_mut(CHUNK_PIXELS * c)
            .enumerate()
            .for_each_init(
                || vec![0f32; CHUNK_PIXELS * self.stem.k],
                |patches, (chunk, out)| {
                    let first = chunk * CHUNK_PIXELS;
                    let n = out.len() / c;
                    for (i, patch) in patches.chunks_exact_mut(self.stem.k).take(n).enumerate() {
                        let (y, x) = ((first + i) / w, (first + i) % w);
                        for ci in 0..planes {
                            for ky in 0..4 {
                                let src = (ci * height + 4 * y + ky) * width + 4 * x;
                                patch[ci * 16 + ky * 4..ci * 16 + ky * 4 + 4]
                                    .copy_from_slice(&image[src..src + 4]);
                            }
                        }
                    }
                    matmul_bias(
                        patches,
                        n,
                        self.stem.k,
                        &self.stem.matrix,
                        c,
                        &self.stem.bias,
                        out,
                    );
                    let (gamma, beta, eps) = self.stem_norm.apply();
                    layer_norm_rows(out, gamma, beta, eps);
                },
            );
        out
    }

    /// One ConvNeXt-V2 block in place on `x` (`[h · w, channels]`).
    fn block(&self, block: &HostBlock, x: &mut [f32], h: usize, w: usize, pool: &mut BufferPool) {
        let (pixels, c, hidden_c) = (h * w, self.channels, block.fc1.n);
        // Pass 1: depthwise + LayerNorm + fc1 + GELU per chunk, sums of squares per channel.
        let x_in: &[f32] = x;
        let expand = |first: usize, scratch: &mut Scratch, out: &mut [f32]| {
            let n = out.len() / hidden_c;
            let normed = &mut scratch.normed[..n * c];
            let (gamma, beta, eps) = block.norm.apply();
            depthwise_pixels(
                x_in,
                h,
                w,
                &block.depthwise,
                BLOCK_KERNEL,
                Some(&block.depthwise_bias),
                Some((gamma, beta, eps)),
                first,
                normed,
            );
            match &block.fc1.bf16 {
                None => {
                    let fc1 = &block.fc1;
                    matmul_bias(normed, n, c, &fc1.matrix, hidden_c, &fc1.bias, out);
                }
                Some(weights) => {
                    let stride = weights.lhs_stride();
                    for (row, values) in scratch
                        .lhs
                        .chunks_exact_mut(stride)
                        .zip(normed.chunks_exact(c))
                    {
                        bf16::round_into(values, &mut row[..c]);
                    }
                    bf16::multiply(&scratch.lhs, n, weights, out);
                }
            }
            let mut squares = vec![0f32; hidden_c];
            gelu_with_squares(out, &mut squares);
            squares
        };
        let scratch = || Scratch {
            normed: vec![0f32; CHUNK_PIXELS * c],
            lhs: match &block.fc1.bf16 {
                Some(weights) => vec![0u16; CHUNK_PIXELS * weights.lhs_stride()],
                None => Vec::new(),
            },
            activation: if self.bf16 {
                vec![0f32; CHUNK_PIXELS * hidden_c]
            } else {
                Vec::new()
            },
        };
        let (hidden, partials): (Hidden, Vec<Vec<f32>>) = if !self.bf16 {
            let mut hidden = pool.take::<f32>(pixels * hidden_c);
            let partials = hidden
                .par_chunks_mut(CHUNK_PIXELS * hidden_c)
                .enumerate()
                .map_init(scratch, |scratch, (chunk, out)| {
                    expand(chunk * CHUNK_PIXELS, scratch, out)
                })
                .collect();
            (Hidden::F32(hidden), partials)
        } else {
            // Rows padded to whole tile blocks (the tile routine discards their products).
            let mut hidden = pool.take::<u16>(bf16::padded_rows(pixels) * hidden_c);
            let partials = hidden
                .par_chunks_mut(CHUNK_PIXELS * hidden_c)
                .enumerate()
                .map_init(scratch, |scratch, (chunk, out)| {
                    let first = chunk * CHUNK_PIXELS;
                    let n = (pixels - first).min(CHUNK_PIXELS);
                    let mut activation = std::mem::take(&mut scratch.activation);
                    let squares = expand(first, scratch, &mut activation[..n * hidden_c]);
                    bf16::round_into(&activation[..n * hidden_c], &mut out[..n * hidden_c]);
                    scratch.activation = activation;
                    squares
                })
                .collect();
            (Hidden::Bf16(hidden), partials)
        };
        let mut squares = vec![0f64; hidden_c];
        for partial in &partials {
            for (s, p) in squares.iter_mut().zip(partial) {
                *s += *p as f64;
            }
        }
        // Pass 2: fc2 with GRN folded in, added to the residual.
        let fc2 = block.fc2_with_grn(&squares, self.bf16);
        x.par_chunks_mut(CHUNK_PIXELS * c)
            .enumerate()
            .for_each_init(
                || vec![0f32; CHUNK_PIXELS * c],
                |product, (chunk, rows)| {
                    let first = chunk * CHUNK_PIXELS;
                    let n = rows.len() / c;
                    match (&hidden, &fc2.bf16) {
                        (Hidden::F32(hidden), _) => {
                            let lhs = &hidden[first * hidden_c..(first + n) * hidden_c];
                            matmul_bias(lhs, n, hidden_c, &fc2.matrix, c, &fc2.bias, product);
                        }
                        (Hidden::Bf16(hidden), Some(weights)) => {
                            bf16::multiply(&hidden[first * hidden_c..], n, weights, product);
                        }
                        (Hidden::Bf16(_), None) => {
                            unreachable!("bf16 activations come with bf16 weights")
                        }
                    }
                    add_in_place(rows, &product[..n * c]);
                },
            );
        match hidden {
            Hidden::F32(buffer) => pool.give(buffer),
            Hidden::Bf16(buffer) => pool.give(buffer),
        }
    }
}

/// Depthwise correlation of channels-last features `[h, w, c]` with one sample's kernels
/// `[c, k, k]` (zero padding `k / 2`) → `[h, w, c]` in the element type the next layer's
/// products take (a buffer from `pool`; converted chunk by chunk while in cache).
pub(crate) fn correlate<T: Pooled>(
    features: &[f32],
    h: usize,
    w: usize,
    kernels: &[f32],
    k: usize,
    pool: &mut BufferPool,
) -> Vec<T> {
    let c = kernels.len() / (k * k);
    let taps = channels_last_taps(kernels, c, k);
    // The backbone's hidden activations are free now, and the upsampler's shuffled activations
    // want a buffer of their size later, when the correlation's is free again.
    let mut out = pool.take_largest::<T>(h * w * c);
    out.par_chunks_mut(CHUNK_PIXELS * c)
        .enumerate()
        .for_each_init(
            || vec![0f32; CHUNK_PIXELS * c],
            |values, (chunk, out)| {
                let values = &mut values[..out.len()];
                depthwise_pixels(
                    features,
                    h,
                    w,
                    &taps,
                    k,
                    None,
                    None,
                    chunk * CHUNK_PIXELS,
                    values,
                );
                T::convert_into(values, out);
            },
        );
    out
}
