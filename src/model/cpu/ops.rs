//! Pieces the CPU implementation (the backbone and the upsampler) share:
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
pub(crate) fn values(t: Tensor<1>) -> Vec<f32> {
    t.into_data()
        .try_into_vec()
        .expect("parameters are f32; this is a bug")
}

/// `out[m, n] = lhs[m, k] · rhs[k, n] + bias[n]`, row-major, on this thread.
pub fn matmul_bias(
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
    if m == 1 {
        // gemm multiplies a single row as a matrix-vector product, which rounds differently
        // from its block product for two or more rows; a pixel must get the same bits whether its
        // chunk holds one pixel or many, so one row goes through the block product as two.
        let mut pair = Vec::with_capacity(2 * k);
        pair.extend_from_slice(&lhs[..k]);
        pair.extend_from_slice(&lhs[..k]);
        let mut pair_out = vec![0f32; 2 * n];
        matmul_bias(&pair, 2, k, rhs, n, bias, &mut pair_out);
        out[..n].copy_from_slice(&pair_out[..n]);
        return;
    }
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

/// Large activation buffers kept from one forward pass to the next, so that the tiles of a
/// frame do not each fault in and zero a few hundred megabytes of fresh memory (a fifth of a
/// bf16 forward went to `memset` and the OS's page clearing). A taken buffer's contents
/// are unspecified: whoever takes one overwrites all of it.
#[derive(Default)]
pub(crate) struct BufferPool {
    f32s: Vec<Vec<f32>>,
    u16s: Vec<Vec<u16>>,
}

/// Element types the pool keeps: f32, and bf16 bits (`u16`) for the bf16 products' inputs.
pub(crate) trait Pooled: Copy + Default + Send + Sync {
    fn shelf(pool: &mut BufferPool) -> &mut Vec<Vec<Self>>;
    /// `values` in this element type, into `out` (same length).
    fn convert_into(values: &[f32], out: &mut [Self]);
}

impl Pooled for f32 {
    fn shelf(pool: &mut BufferPool) -> &mut Vec<Vec<f32>> {
        &mut pool.f32s
    }

    fn convert_into(values: &[f32], out: &mut [f32]) {
        out.copy_from_slice(values);
    }
}

impl Pooled for u16 {
    fn shelf(pool: &mut BufferPool) -> &mut Vec<Vec<u16>> {
        &mut pool.u16s
    }

    fn convert_into(values: &[f32], out: &mut [u16]) {
        super::bf16::round_into(values, out);
    }
}

/// `values` converted to `T`, in parallel chunks (a pooled buffer).
pub(crate) fn converted<T: Pooled>(values: &[f32], pool: &mut BufferPool) -> Vec<T> {
    use rayon::prelude::*;
    const CHUNK: usize = 64 * 1024;
    let mut out = pool.take::<T>(values.len());
    out.par_chunks_mut(CHUNK)
        .zip(values.par_chunks(CHUNK))
        .for_each(|(out, values)| T::convert_into(values, out));
    out
}

impl BufferPool {
    /// A buffer of `len` values: the smallest kept one that holds them, else the largest,
    /// grown (only growth is zeroed).
    pub(crate) fn take<T: Pooled>(&mut self, len: usize) -> Vec<T> {
        let shelf = T::shelf(self);
        let fits = (0..shelf.len())
            .filter(|&i| shelf[i].capacity() >= len)
            .min_by_key(|&i| shelf[i].capacity());
        let chosen = fits.or_else(|| (0..shelf.len()).max_by_key(|&i| shelf[i].capacity()));
        let mut buffer = chosen.map(|i| shelf.swap_remove(i)).unwrap_or_default();
        if buffer.len() >= len {
            buffer.truncate(len);
        } else {
            buffer.resize(len, T::default());
        }
        buffer
    }

    /// [`BufferPool::take`] from the largest kept buffer, whatever the smallest fitting one:
    /// for an activation whose neighbours in time are larger (the correlation takes the
    /// backbone's hidden activations' buffer, so the upsampler's next, larger request finds it
    /// free again instead of growing a second one).
    pub(crate) fn take_largest<T: Pooled>(&mut self, len: usize) -> Vec<T> {
        let shelf = T::shelf(self);
        let largest = (0..shelf.len()).max_by_key(|&i| shelf[i].capacity());
        let mut buffer = largest.map(|i| shelf.swap_remove(i)).unwrap_or_default();
        buffer.resize(len, T::default());
        buffer
    }

    /// Keeps `buffer` for a later [`BufferPool::take`].
    pub(crate) fn give<T: Pooled>(&mut self, buffer: Vec<T>) {
        if buffer.capacity() > 0 {
            T::shelf(self).push(buffer);
        }
    }

    /// Everything `other` keeps, kept here too.
    pub(crate) fn absorb(&mut self, other: BufferPool) {
        self.f32s.extend(other.f32s);
        self.u16s.extend(other.u16s);
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
pub(crate) fn layer_norm_rows(rows: &mut [f32], gamma: &[f32], beta: &[f32], eps: f32) {
    for row in rows.chunks_exact_mut(gamma.len()) {
        layer_norm_row(row, gamma, beta, eps);
    }
}

/// A depthwise `k x k` convolution (zero padding `k / 2`, stride 1) of a channels-last
/// `[height, width, channels]` image at the pixels `first..first + out.len() / channels`
/// (row-major indices), written to `out`; `taps` is `[k * k, channels]`, tap `ky * k + kx`.
/// With `norm`, each output pixel is then LayerNormed (`gamma`, `beta`, `eps`).
///
/// Channels go in blocks of [`LANES`] held in registers across the taps, [`RUN`] horizontally
/// adjacent pixels at a time where the whole window lies inside the row. For the kernel sizes
/// the network uses (7 in the backbone, 9 for the correlation with a 36-pixel template) a run
/// slides along the row: each input vector is loaded once and feeds every pixel of the run
/// whose window covers it, and a kernel row's taps are loaded once per run, so loads no longer
/// outnumber multiply-adds. Every output still adds its taps in the same order (rows, then
/// columns, ascending), so all paths give the same bits.
#[multiversion(targets("x86_64+avx512f+avx512vl+avx512bw+avx512dq", "x86_64+avx2+fma"))]
#[allow(clippy::too_many_arguments)]
pub(crate) fn depthwise_pixels(
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
    assert!(
        channels.is_multiple_of(LANES) && taps.len() == k * k * channels && k % 2 == 1,
        "depthwise: {channels} channels (a multiple of {LANES}), odd k; this is a bug"
    );
    let half = k / 2;
    let pixels = out.len() / channels;
    let avx512 = has_avx512f();
    let mut i = 0;
    while i < pixels {
        let (y, x) = ((first + i) / width, (first + i) % width);
        let ky = half.saturating_sub(y)..k.min(height + half - y);
        let run = if x >= half && x + RUN + half <= width && i + RUN <= pixels {
            RUN
        } else {
            1
        };
        let out_run = &mut out[i * channels..(i + run) * channels];
        for block in (0..channels).step_by(LANES) {
            let mut acc = [[0f32; LANES]; RUN];
            if let Some(bias) = bias {
                for a in acc.iter_mut().take(run) {
                    a.copy_from_slice(&bias[block..block + LANES]);
                }
            }
            for ky in ky.clone() {
                let sy = y + ky - half;
                if run == RUN {
                    // The run's window on this kernel row starts at pixel x - half.
                    let row = &input[(sy * width + x - half) * channels + block..];
                    let taps_row = &taps[ky * k * channels + block..];
                    match k {
                        7 => slide::<7>(&mut acc, row, taps_row, channels, avx512),
                        9 => slide::<9>(&mut acc, row, taps_row, channels, avx512),
                        _ => {
                            for kx in 0..k {
                                let tap = lanes_at(taps_row, kx * channels);
                                for (p, a) in acc.iter_mut().enumerate() {
                                    let src = lanes_at(row, (p + kx) * channels);
                                    for l in 0..LANES {
                                        a[l] = src[l].mul_add(tap[l], a[l]);
                                    }
                                }
                            }
                        }
                    }
                } else {
                    for kx in half.saturating_sub(x)..k.min(width + half - x) {
                        let tap = &taps[(ky * k + kx) * channels + block..][..LANES];
                        let src = (sy * width + x + kx - half) * channels + block;
                        let src = &input[src..src + LANES];
                        for l in 0..LANES {
                            acc[0][l] = src[l].mul_add(tap[l], acc[0][l]);
                        }
                    }
                }
            }
            for (p, a) in acc.iter().take(run).enumerate() {
                out_run[p * channels + block..p * channels + block + LANES].copy_from_slice(a);
            }
        }
        if let Some((gamma, beta, eps)) = norm {
            for row in out_run.chunks_exact_mut(channels) {
                layer_norm_row(row, gamma, beta, eps);
            }
        }
        i += run;
    }
}

/// Pixels per run of [`depthwise_pixels`]: eight accumulators plus a kernel row of up to nine
/// taps fit in the 32 vector registers of AVX-512 (`slide` unrolls for `RUN + K - 1 <= 16`).
const RUN: usize = 8;

/// [`LANES`] values of `values` from `at`.
#[inline(always)]
fn lanes_at(values: &[f32], at: usize) -> &[f32; LANES] {
    values[at..at + LANES].try_into().expect("LANES values")
}

/// One kernel row of `K` taps over a run: `acc[p] += Σ_kx row[p + kx] · taps_row[kx]`, each
/// sum in ascending `kx`, with `row` and `taps_row` `channels` apart per pixel / tap. Each
/// input vector is loaded once for the (up to `K`) pixels whose window covers it; `avx512`
/// ([`has_avx512f`]) picks the register routine.
#[inline(always)]
fn slide<const K: usize>(
    acc: &mut [[f32; LANES]; RUN],
    row: &[f32],
    taps_row: &[f32],
    channels: usize,
    avx512: bool,
) {
    #[cfg(target_arch = "x86_64")]
    if avx512 {
        // SAFETY: the CPU has AVX-512F (`avx512` comes from `has_avx512f`).
        unsafe { slide_avx512::<K>(acc, row, taps_row, channels) };
        return;
    }
    for j in 0..RUN + K - 1 {
        let src = lanes_at(row, j * channels);
        for (p, a) in acc.iter_mut().enumerate() {
            // Input j is tap j - p of pixel p (j ascending: taps in ascending order).
            if j >= p && j - p < K {
                let tap = lanes_at(taps_row, (j - p) * channels);
                for l in 0..LANES {
                    a[l] = src[l].mul_add(tap[l], a[l]);
                }
            }
        }
    }
}

/// Whether this CPU runs [`slide_avx512`].
fn has_avx512f() -> bool {
    #[cfg(target_arch = "x86_64")]
    return std::arch::is_x86_feature_detected!("avx512f");
    #[cfg(not(target_arch = "x86_64"))]
    false
}

/// [`slide`] in AVX-512 registers: eight accumulators and the row's `K` taps stay in registers
/// (the loops are unrolled in full: input `J`, pixel `P` are literals), which the compiler
/// did not manage from the portable loops. `_mm512_fmadd_ps` rounds once, like `mul_add`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
// The unrolled literals make some expressions trivial (`0 * channels`, `J >= J`).
#[allow(
    clippy::erasing_op,
    clippy::eq_op,
    clippy::identity_op,
    clippy::absurd_extreme_comparisons,
    unused_comparisons
)]
unsafe fn slide_avx512<const K: usize>(
    acc: &mut [[f32; LANES]; RUN],
    row: &[f32],
    taps_row: &[f32],
    channels: usize,
) {
    use std::arch::x86_64::{__m512, _mm512_fmadd_ps, _mm512_loadu_ps, _mm512_storeu_ps};
    const { assert!(RUN == 8 && RUN + K - 1 <= 16, "the unrolled ranges below") };
    let load = |values: &[f32; LANES]| -> __m512 {
        // SAFETY: 16 f32 in bounds; AVX-512F is enabled for this function.
        unsafe { _mm512_loadu_ps(values.as_ptr()) }
    };
    let taps: [__m512; K] = std::array::from_fn(|kx| load(lanes_at(taps_row, kx * channels)));
    let mut sums: [__m512; RUN] = std::array::from_fn(|p| load(&acc[p]));
    seq_macro::seq!(J in 0..16 {
        if J < RUN + K - 1 {
            let src = load(lanes_at(row, J * channels));
            seq_macro::seq!(P in 0..8 {
                // Input J is tap J - P of pixel P (J ascending: taps in ascending order).
                if J >= P && J - P < K {
                    sums[P] = _mm512_fmadd_ps(src, taps[J - P], sums[P]);
                }
            });
        }
    });
    for (a, sum) in acc.iter_mut().zip(sums) {
        // SAFETY: 16 f32 in bounds.
        unsafe { _mm512_storeu_ps(a.as_mut_ptr(), sum) };
    }
}

/// GELU (exact form) in place over `[pixels, channels]` rows, adding each channel's sum of
/// squares of the result to `squares` (`[channels]`).
#[multiversion(targets("x86_64+avx512f+avx512vl+avx512bw+avx512dq", "x86_64+avx2+fma"))]
pub(crate) fn gelu_with_squares(rows: &mut [f32], squares: &mut [f32]) {
    for row in rows.chunks_exact_mut(squares.len()) {
        for (v, s) in row.iter_mut().zip(squares.iter_mut()) {
            let g = super::gelu_grn::gelu_f32(*v);
            *v = g;
            *s += g * g;
        }
    }
}

/// `rows[p] += add[p]` elementwise (same lengths).
#[multiversion(targets("x86_64+avx512f+avx512vl+avx512bw+avx512dq", "x86_64+avx2+fma"))]
pub(crate) fn add_in_place(rows: &mut [f32], add: &[f32]) {
    for (r, a) in rows.iter_mut().zip(add) {
        *r += *a;
    }
}

/// `rows[p, c] = rows[p, c] · scale[c] + shift[c]` over `[pixels, channels]` rows.
#[multiversion(targets("x86_64+avx512f+avx512vl+avx512bw+avx512dq", "x86_64+avx2+fma"))]
pub(crate) fn scale_shift_rows(rows: &mut [f32], scale: &[f32], shift: &[f32]) {
    for row in rows.chunks_exact_mut(scale.len()) {
        for ((v, s), b) in row.iter_mut().zip(scale).zip(shift) {
            *v = *v * *s + *b;
        }
    }
}

/// `max(v, 0)` in place.
#[multiversion(targets("x86_64+avx512f+avx512vl+avx512bw+avx512dq", "x86_64+avx2+fma"))]
pub(crate) fn relu_in_place(values: &mut [f32]) {
    for v in values.iter_mut() {
        *v = v.max(0.0);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_row_gets_the_same_bits_whatever_the_number_of_rows() {
        // The heads' shapes (k 216, n 12 and 60) and a backbone's (k 96, n 384).
        for (k, n) in [(216, 12), (216, 60), (96, 384)] {
            let m = 37;
            let lhs: Vec<f32> = (0..m * k)
                .map(|i| ((i * 7919) % 103) as f32 / 31.0 - 1.6)
                .collect();
            let rhs: Vec<f32> = (0..k * n)
                .map(|i| ((i * 104_729) % 89) as f32 / 67.0 - 0.65)
                .collect();
            let bias: Vec<f32> = (0..n).map(|i| i as f32 / 7.0 - 1.0).collect();
            let mut all = vec![0f32; m * n];
            matmul_bias(&lhs, m, k, &rhs, n, &bias, &mut all);
            for rows in [1, 2, 3, 8, 16] {
                for first in (0..m - rows).step_by(5) {
                    let mut some = vec![0f32; rows * n];
                    matmul_bias(&lhs[first * k..], rows, k, &rhs, n, &bias, &mut some);
                    assert_eq!(
                        some,
                        all[first * n..(first + rows) * n],
                        "k {k}, n {n}: {rows} rows from row {first}"
                    );
                }
            }
        }
    }

    #[test]
    fn depthwise_runs_give_the_bits_of_single_pixels_for_every_kernel_size() {
        let (h, w, c) = (11, 29, 32);
        let input: Vec<f32> = (0..h * w * c)
            .map(|i| ((i * 7919) % 61) as f32 / 17.0 - 1.7)
            .collect();
        for k in [3, 5, 7, 9] {
            let taps: Vec<f32> = (0..k * k * c)
                .map(|i| ((i * 104_729) % 37) as f32 / 29.0 - 0.6)
                .collect();
            let mut whole = vec![0f32; h * w * c];
            depthwise_pixels(&input, h, w, &taps, k, None, None, 0, &mut whole);
            let half = (k / 2) as isize;
            for p in 0..h * w {
                // One pixel at a time never forms a run.
                let mut single = vec![0f32; c];
                depthwise_pixels(&input, h, w, &taps, k, None, None, p, &mut single);
                assert_eq!(single, whole[p * c..(p + 1) * c], "k {k}, pixel {p}");
                let (y, x) = ((p / w) as isize, (p % w) as isize);
                for ch in 0..c {
                    let mut expected = 0f64;
                    for ky in 0..k as isize {
                        for kx in 0..k as isize {
                            let (sy, sx) = (y + ky - half, x + kx - half);
                            if sy >= 0 && sx >= 0 && sy < h as isize && sx < w as isize {
                                expected += input[(sy as usize * w + sx as usize) * c + ch] as f64
                                    * taps[(ky as usize * k + kx as usize) * c + ch] as f64;
                            }
                        }
                    }
                    let got = whole[p * c + ch] as f64;
                    assert!((got - expected).abs() < 1e-4, "k {k}: {got} vs {expected}");
                }
            }
        }
    }

    #[test]
    fn depthwise_pixels_equal_a_direct_convolution_at_every_border() {
        let (h, w, c, k) = (5, 9, 32, 3);
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
                    let got = out[(y * w + x) * c + ch];
                    assert!(
                        (got - expected).abs() < 1e-5,
                        "({y}, {x}, {ch}): {got} vs {expected}"
                    );
                }
            }
        }
        // A window of pixels (runs start elsewhere) gives the same values as the whole image.
        let mut part = vec![0f32; 13 * c];
        depthwise_pixels(&input, h, w, &taps, k, Some(&bias), None, 12, &mut part);
        assert_eq!(part, out[12 * c..25 * c]);
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
