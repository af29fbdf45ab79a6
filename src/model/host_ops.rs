//! Pieces the host CPU kernels ([`super::host_backbone`], [`super::host_decoder`]) share:
//! reading parameters out of burn, the f32 matrix product with a bias, and the memory-bound
//! per-pixel loops.
//!
//! The loops are compiled for several instruction sets and chosen at run time (`multiversion`):
//! the binary targets baseline x86-64 (SSE2, 4 lanes), which would leave the stages between the
//! products (depthwise convolutions, normalisations, GELU) at a quarter of what AVX-512 does.
//! Sums across channels are accumulated in 16 explicit lanes, so they vectorise and give the
//! same result on every instruction set.

use burn::prelude::*;
use multiversion::multiversion;

/// A parameter vector's values.
pub(super) fn values(t: Tensor<1>) -> Vec<f32> {
    t.into_data()
        .try_into_vec()
        .expect("parameters are f32; this is a bug")
}

/// `out[m, n] = lhs[m, k] · rhs[k, n] + bias[n]`, row-major, on this thread.
pub(super) fn matmul_bias(
    lhs: &[f32],
    m: usize,
    k: usize,
    rhs: &[f32],
    n: usize,
    bias: &[f32],
    out: &mut [f32],
) {
    assert!(
        lhs.len() >= m * k && out.len() >= m * n && rhs.len() == k * n && bias.len() == n,
        "matmul_bias: operands do not fit [{m}, {k}] x [{k}, {n}]; this is a bug"
    );
    for row in out.chunks_exact_mut(n).take(m) {
        row.copy_from_slice(bias);
    }
    // SAFETY: the three buffers are distinct, row-major and at least as large as the dimensions
    // passed (asserted above); gemm reads lhs/rhs and writes dst within them.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            out.as_mut_ptr(),
            1,
            n as isize,
            true,
            lhs.as_ptr(),
            1,
            k as isize,
            rhs.as_ptr(),
            1,
            n as isize,
            1.0,
            1.0,
            false,
            false,
            false,
            gemm::Parallelism::None,
        );
    }
}

/// Lanes of the explicit partial sums (one AVX-512 register of f32).
const LANES: usize = 16;

/// `sum(values)` in [`LANES`] partial sums, then those in order.
#[inline(always)]
fn lane_sum(values: &[f32]) -> f32 {
    let mut lanes = [0f32; LANES];
    let mut chunks = values.chunks_exact(LANES);
    for chunk in &mut chunks {
        for (l, v) in lanes.iter_mut().zip(chunk) {
            *l += *v;
        }
    }
    for (l, v) in lanes.iter_mut().zip(chunks.remainder()) {
        *l += *v;
    }
    lanes.iter().sum()
}

/// `sum((values - mean)²)` like [`lane_sum`].
#[inline(always)]
fn lane_squared_deviation(values: &[f32], mean: f32) -> f32 {
    let mut lanes = [0f32; LANES];
    let mut chunks = values.chunks_exact(LANES);
    for chunk in &mut chunks {
        for (l, v) in lanes.iter_mut().zip(chunk) {
            *l += (*v - mean) * (*v - mean);
        }
    }
    for (l, v) in lanes.iter_mut().zip(chunks.remainder()) {
        *l += (*v - mean) * (*v - mean);
    }
    lanes.iter().sum()
}

/// LayerNorm over each row of `rows` (`[pixels, channels]`), in place:
/// `(v - mean) / sqrt(var + eps) · gamma + beta`, biased variance.
#[inline(always)]
fn layer_norm_row(row: &mut [f32], gamma: &[f32], beta: &[f32], eps: f32) {
    let channels = row.len() as f32;
    let mean = lane_sum(row) / channels;
    let inv = 1.0 / (lane_squared_deviation(row, mean) / channels + eps).sqrt();
    for ((v, g), b) in row.iter_mut().zip(gamma).zip(beta) {
        *v = (*v - mean) * inv * *g + *b;
    }
}

/// LayerNorm over every row of `rows` (`[pixels, gamma.len()]`), in place.
#[multiversion(targets("x86_64+avx512f+avx512vl+avx512bw+avx512dq", "x86_64+avx2+fma"))]
pub(super) fn layer_norm_rows(rows: &mut [f32], gamma: &[f32], beta: &[f32], eps: f32) {
    for row in rows.chunks_exact_mut(gamma.len()) {
        layer_norm_row(row, gamma, beta, eps);
    }
}

/// A depthwise `k x k` convolution (zero padding `k / 2`, stride 1) of a channels-last
/// `[height, width, channels]` image at the pixels `first..first + out.len() / channels`
/// (row-major indices), written to `out`; `taps` is `[k * k, channels]`, tap `ky * k + kx`.
/// With `norm`, each output pixel is then LayerNormed (`gamma`, `beta`, `eps`).
#[multiversion(targets("x86_64+avx512f+avx512vl+avx512bw+avx512dq", "x86_64+avx2+fma"))]
#[allow(clippy::too_many_arguments)]
pub(super) fn depthwise_pixels(
    input: &[f32],
    height: usize,
    width: usize,
    taps: &[f32],
    k: usize,
    bias: Option<&[f32]>,
    norm: Option<(&[f32], &[f32], f32)>,
    first: usize,
    out: &mut [f32],
) {
    let channels = taps.len() / (k * k);
    let half = k / 2;
    for (i, acc) in out.chunks_exact_mut(channels).enumerate() {
        let (y, x) = ((first + i) / width, (first + i) % width);
        match bias {
            Some(bias) => acc.copy_from_slice(bias),
            None => acc.fill(0.0),
        }
        let ky0 = half.saturating_sub(y);
        let ky1 = k.min(height + half - y);
        let kx0 = half.saturating_sub(x);
        let kx1 = k.min(width + half - x);
        for ky in ky0..ky1 {
            let sy = y + ky - half;
            for kx in kx0..kx1 {
                let sx = x + kx - half;
                let src = &input[(sy * width + sx) * channels..(sy * width + sx + 1) * channels];
                let tap = &taps[(ky * k + kx) * channels..(ky * k + kx + 1) * channels];
                for ((a, v), t) in acc.iter_mut().zip(src).zip(tap) {
                    *a += *v * *t;
                }
            }
        }
        if let Some((gamma, beta, eps)) = norm {
            layer_norm_row(acc, gamma, beta, eps);
        }
    }
}

/// GELU (exact form) in place over `[pixels, channels]` rows, adding each channel's sum of
/// squares of the result to `squares` (`[channels]`).
#[multiversion(targets("x86_64+avx512f+avx512vl+avx512bw+avx512dq", "x86_64+avx2+fma"))]
pub(super) fn gelu_with_squares(rows: &mut [f32], squares: &mut [f32]) {
    for row in rows.chunks_exact_mut(squares.len()) {
        for (v, s) in row.iter_mut().zip(squares.iter_mut()) {
            let g = super::fused::gelu_f32(*v);
            *v = g;
            *s += g * g;
        }
    }
}

/// `rows[p] += add[p]` elementwise (same lengths).
#[multiversion(targets("x86_64+avx512f+avx512vl+avx512bw+avx512dq", "x86_64+avx2+fma"))]
pub(super) fn add_in_place(rows: &mut [f32], add: &[f32]) {
    for (r, a) in rows.iter_mut().zip(add) {
        *r += *a;
    }
}

/// `rows[p, c] = rows[p, c] · scale[c] + shift[c]` over `[pixels, channels]` rows.
#[multiversion(targets("x86_64+avx512f+avx512vl+avx512bw+avx512dq", "x86_64+avx2+fma"))]
pub(super) fn scale_shift_rows(rows: &mut [f32], scale: &[f32], shift: &[f32]) {
    for row in rows.chunks_exact_mut(scale.len()) {
        for ((v, s), b) in row.iter_mut().zip(scale).zip(shift) {
            *v = *v * *s + *b;
        }
    }
}

/// `max(v, 0)` in place.
#[multiversion(targets("x86_64+avx512f+avx512vl+avx512bw+avx512dq", "x86_64+avx2+fma"))]
pub(super) fn relu_in_place(values: &mut [f32]) {
    for v in values.iter_mut() {
        *v = v.max(0.0);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn depthwise_pixels_equal_a_direct_convolution_at_every_border() {
        let (h, w, c, k) = (5, 7, 20, 3);
        let input: Vec<f32> = (0..h * w * c).map(|i| (i % 13) as f32 - 6.0).collect();
        let taps: Vec<f32> = (0..k * k * c)
            .map(|i| (i % 7) as f32 * 0.25 - 0.5)
            .collect();
        let bias: Vec<f32> = (0..c).map(|i| i as f32).collect();
        let mut out = vec![0f32; h * w * c];
        depthwise_pixels(&input, h, w, &taps, k, Some(&bias), None, 0, &mut out);
        for y in 0..h {
            for x in 0..w {
                for ch in 0..c {
                    let mut expected = bias[ch];
                    for ky in 0..k {
                        for kx in 0..k {
                            let (sy, sx) =
                                (y as isize + ky as isize - 1, x as isize + kx as isize - 1);
                            if sy >= 0 && sx >= 0 && (sy as usize) < h && (sx as usize) < w {
                                expected += input[(sy as usize * w + sx as usize) * c + ch]
                                    * taps[(ky * k + kx) * c + ch];
                            }
                        }
                    }
                    assert_eq!(out[(y * w + x) * c + ch], expected, "({y}, {x}, {ch})");
                }
            }
        }
        // A window of pixels gives the same values as the whole image.
        let mut part = vec![0f32; 9 * c];
        depthwise_pixels(&input, h, w, &taps, k, Some(&bias), None, 12, &mut part);
        assert_eq!(part, out[12 * c..21 * c]);
    }

    #[test]
    fn layer_norm_rows_normalise_each_pixel() {
        let mut rows: Vec<f32> = (0..3 * 96).map(|i| ((i * 37) % 101) as f32).collect();
        let gamma = vec![2.0f32; 96];
        let beta = vec![1.0f32; 96];
        layer_norm_rows(&mut rows, &gamma, &beta, 1e-6);
        for row in rows.chunks_exact(96) {
            let mean = row.iter().map(|v| (v - 1.0) / 2.0).sum::<f32>() / 96.0;
            let var = row
                .iter()
                .map(|v| ((v - 1.0) / 2.0 - mean).powi(2))
                .sum::<f32>()
                / 96.0;
            assert!(
                mean.abs() < 1e-5 && (var - 1.0).abs() < 1e-4,
                "{mean} {var}"
            );
        }
    }
}
