//! Fused inference code for the one part of the backbone that burn's element-wise ops make
//! slow on the CPU: GELU followed by GRN over the 384-channel MLP activation. burn evaluates
//! exact GELU with a scalar `erff` per element and GRN as several full passes plus strided
//! reductions (together ~60 % of a 224x224 forward on flex); here it is two passes over the
//! channels-last data with a vectorisable erf. Training (autodiff devices) keeps the tensor-op
//! path so gradients flow; both paths compute the same function (unit-tested below and by the
//! parity fixtures).

use burn::prelude::*;
use rayon::prelude::*;

/// `erf(x)` as a rational approximation on [-4, 4] (outside, erf is ±1 in f32): odd numerator,
/// even denominator in `x²`. Absolute error below 1e-6 (tested against libm), branch-free, so
/// the loops that call it vectorise. (Plain `a * b + c`, not `mul_add`: without a target FMA
/// feature `mul_add` becomes a slow library call.)
#[inline(always)]
pub fn erf_f32(x: f32) -> f32 {
    let x = x.clamp(-4.0, 4.0);
    let x2 = x * x;
    let mut p = -2.726_142_3e-10_f32;
    p = p * x2 + 2.770_681_4e-8;
    p = p * x2 + -2.101_024e-6;
    p = p * x2 + -5.692_506_4e-5;
    p = p * x2 + -7.349_906e-4;
    p = p * x2 + -2.954_600_2e-3;
    p = p * x2 + -1.609_603_3e-2;
    let mut q = -1.456_607_2e-5_f32;
    q = q * x2 + -2.133_740_6e-4;
    q = q * x2 + -1.682_827e-3;
    q = q * x2 + -7.373_329e-3;
    q = q * x2 + -1.426_474e-2;
    x * p / q
}

/// Exact-form GELU, `0.5·x·(1 + erf(x/√2))`.
#[inline(always)]
pub fn gelu_f32(x: f32) -> f32 {
    0.5 * x * (1.0 + erf_f32(x * std::f32::consts::FRAC_1_SQRT_2))
}

/// GELU then GRN, for inference.
///
/// # Shapes
/// - `z`: `[batch, h, w, channels]` (fc1 output, before GELU)
/// - `weight`, `bias`: `[channels]`
/// - output: like `z`
pub fn gelu_grn(z: Tensor<4>, weight: Tensor<1>, bias: Tensor<1>, eps: f64) -> Tensor<4> {
    let device = z.device();
    let [b, h, w, c] = z.dims();
    let mut values: Vec<f32> = z
        .into_data()
        .try_into_vec()
        .expect("activations are f32; this is a bug");
    let weight: Vec<f32> = weight.into_data().try_into_vec().expect("f32 parameters");
    let bias: Vec<f32> = bias.into_data().try_into_vec().expect("f32 parameters");
    let plane = h * w * c;
    // Rows per parallel chunk: enough work per task, few partial sums to merge.
    let rows_per_chunk = (h * w).div_ceil(rayon::current_num_threads() * 4).max(16);
    for sample in values.chunks_exact_mut(plane) {
        // Pass 1: GELU in place, per-chunk sums of squares per channel.
        let partials: Vec<Vec<f32>> = sample
            .par_chunks_mut(rows_per_chunk * c)
            .map(|chunk| {
                let mut sums = vec![0f32; c];
                for row in chunk.chunks_exact_mut(c) {
                    for (v, s) in row.iter_mut().zip(sums.iter_mut()) {
                        let g = gelu_f32(*v);
                        *v = g;
                        *s += g * g;
                    }
                }
                sums
            })
            .collect();
        let mut norms = vec![0f64; c];
        for partial in &partials {
            for (n, s) in norms.iter_mut().zip(partial) {
                *n += *s as f64;
            }
        }
        norms.iter_mut().for_each(|n| *n = n.sqrt());
        let mean = norms.iter().sum::<f64>() / c as f64;
        // Pass 2: z + bias + weight·z·N = z·(1 + weight·N) + bias.
        let scale: Vec<f32> = norms
            .iter()
            .zip(&weight)
            .map(|(n, w)| 1.0 + w * (n / (mean + eps)) as f32)
            .collect();
        sample.par_chunks_mut(rows_per_chunk * c).for_each(|chunk| {
            for row in chunk.chunks_exact_mut(c) {
                for ((v, s), b) in row.iter_mut().zip(&scale).zip(&bias) {
                    *v = *v * *s + *b;
                }
            }
        });
    }
    Tensor::from_data(TensorData::new(values, [b, h, w, c]), &device)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn erf_matches_libm_within_1e_6() {
        let mut worst = 0f32;
        for i in -60_000..=60_000 {
            let x = i as f32 * 1e-4;
            worst = worst.max((erf_f32(x) - libm::erff(x)).abs());
        }
        assert!(worst < 1e-6, "max |erf error| {worst:e}");
        assert!((erf_f32(10.0) - 1.0).abs() < 1e-6 && (erf_f32(-10.0) + 1.0).abs() < 1e-6);
        assert!(erf_f32(f32::NAN).is_nan());
    }
}
