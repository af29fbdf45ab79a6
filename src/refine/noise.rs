//! The similarity of a pose with the image's own noise taken out of the comparison.
//!
//! Why: sensor noise (short exposure, high gain) adds variance to every image sample that the
//! template cannot explain, so a part that is exactly there correlates at `s / sqrt(s² + ν)`
//! (`s²` the part's own variance, `ν` the noise's): a low-contrast part under noise of 15 grey
//! levels reads 0.7–0.85 and falls below the default `min_score`. The noise does the same to an
//! unrelated patch: its correlation with the template shrinks by the same factor. Taking the
//! noise's variance out of the image samples' variance before normalising (the classical
//! correction for attenuation) therefore gives back, for the part and for a decoy alike, about
//! the correlation they would have in the clean image, and the clean image's chance level and
//! calibration hold (docs/accuracy.md, "What a score means").
//!
//! The noise's variance is estimated once per image ([`NoiseLevel`]) from the finest diagonal
//! detail (Donoho's median absolute deviation of the Haar HH coefficients: structure rarely
//! lives there, noise always does). A bilinear sample between pixels averages the noise of four,
//! so each sample's own noise variance follows from its interpolation weights. The correction
//! is bounded ([`MAX_NOISE_GAIN`]): where the noise is most of a patch's variance the
//! difference of the two is itself mostly noise.

use super::PoseSamples;
use crate::geometry::Pose;
use crate::imaging::GrayImage32;

/// Largest factor by which the correction may raise a correlation: a part whose contrast is at
/// least half the noise's (ZNCC ≥ 0.45 before) reads as in a clean image; below that, no
/// further. 1.5 until 2026-12-01; a part made of fine grain (cast, sandblasted or printed
/// surfaces, grainy photos) keeps its detail only at the pixel, and there noise of 15 grey
/// levels leaves it a ZNCC of 0.4–0.6 where it would read 0.95 clean. Tuning photos of
/// colour gradients under grain (14 generated images, 200 S1.5 pairs, seed 0), noise-15 found
/// at the defaults 92.5 → 94.5 % (2.5: 94.5 %), 100 multi-instance scenes under noise recall
/// 0.412 → 0.506 at precision 0.946 → 0.956; answers ≥ 0.9 in scenes without the part 9 → 9
/// (under noise), 16 → 16 (clean); the lomiri tuning photos unchanged to the pair (noise-15
/// 99.5 %, scenes without the part 11 and 13, multi-instance under noise 0.982 / 0.916). The
/// chance level grows with the gain ([`DenoisedReading::noise_spread`]), so a decoy gains
/// less than the part.
pub(crate) const MAX_NOISE_GAIN: f32 = 2.0;

/// Least contrast of the part, after the noise is taken out, as a share of the template's
/// (standard deviations): a camera's noise leaves a part its contrast, so a patch that matches
/// only at a tenth of it is a decoy the correction would otherwise raise to a perfect match
/// (held-out scenes without the part under noise: the few such answers lay at 0.1 of the
/// template's contrast, at scales near the search's smallest).
pub(crate) const MIN_CONTRAST: f32 = 0.25;

/// Haar HH coefficients read at most (on a regular subset of the image's 2x2 blocks): enough
/// for a median to a few per cent, and a 2048x2048 frame costs what a 512x512 one does.
const MAX_NOISE_BLOCKS: usize = 1 << 16;

/// The image's noise: variance of one pixel's noise (image values in [0, 1]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct NoiseLevel {
    pub(crate) variance: f32,
}

impl NoiseLevel {
    /// The noise's spread in grey levels of an 8-bit image.
    pub(crate) fn grey_levels(&self) -> f32 {
        255.0 * self.variance.sqrt()
    }

    /// Donoho's estimate: `sigma = median |HH| / 0.6745`, HH = `(a − b − c + d) / 2` over the
    /// image's 2x2 blocks (for white noise of `sigma`, HH has exactly that spread; smooth
    /// structure, edges along the axes and gradients give none).
    pub(crate) fn estimate(image: &GrayImage32) -> Self {
        let (blocks_x, blocks_y) = (image.width / 2, image.height / 2);
        let blocks = blocks_x * blocks_y;
        if blocks == 0 {
            return Self { variance: 0.0 };
        }
        let stride = blocks.div_ceil(MAX_NOISE_BLOCKS).max(1);
        let at = |x: usize, y: usize| image.values[y * image.width + x];
        let mut details: Vec<f32> = (0..blocks)
            .step_by(stride)
            .map(|k| {
                let (x, y) = (2 * (k % blocks_x), 2 * (k / blocks_x));
                ((at(x, y) - at(x + 1, y) - at(x, y + 1) + at(x + 1, y + 1)) / 2.0).abs()
            })
            .filter(|d| d.is_finite())
            .collect();
        if details.is_empty() {
            return Self { variance: 0.0 };
        }
        let middle = details.len() / 2;
        let (_, median, _) = details.select_nth_unstable_by(middle, f32::total_cmp);
        let sigma = *median / 0.6745;
        Self {
            variance: sigma * sigma,
        }
    }
}

/// The template's support points (every pixel up to 48 a side, as the similarity's) with
/// zero-mean, unit-norm values.
pub(crate) struct NoisePoints {
    offsets: Vec<(f32, f32)>,
    weights: Vec<f32>,
    /// The template values' standard deviation over the points.
    spread: f32,
}

impl NoisePoints {
    pub(crate) fn new(template: &GrayImage32) -> Self {
        let (offsets, values) = super::grid_points(template, 48);
        let (weights, norm) = super::unit_weights(&values);
        Self {
            spread: norm / (offsets.len().max(1) as f32).sqrt(),
            offsets,
            weights,
        }
    }

    /// The template and the image's `samples` at `pose` (the support's, in `image`) with the
    /// image's `noise` taken out of the samples' variance ([`DenoisedReading`]); `None` where
    /// the image is flat there.
    pub(crate) fn read(
        &self,
        samples: &PoseSamples,
        image: &GrayImage32,
        pose: &Pose,
        noise: NoiseLevel,
    ) -> Option<DenoisedReading> {
        let n = self.offsets.len();
        debug_assert_eq!(samples.values().len(), n, "the support's samples");
        if n < 2 {
            return None;
        }
        let (mut sum, mut sum_sq, mut dot, mut noise_share, mut inside) =
            (0f64, 0f64, 0f64, 0f64, 0usize);
        let (max_x, max_y) = ((image.width - 1) as f32, (image.height - 1) as f32);
        for ((&(u, v), &w), &sample) in self.offsets.iter().zip(&self.weights).zip(samples.values())
        {
            let (x, y) = pose.map_point(u, v);
            let value = f64::from(sample);
            sum += value;
            sum_sq += value * value;
            dot += w as f64 * value;
            // A bilinear sample's noise variance: the noise's times the squared weights.
            let fx = x.clamp(0.0, max_x).fract();
            let fy = y.clamp(0.0, max_y).fract();
            let along = |f: f32| ((1.0 - f) * (1.0 - f) + f * f) as f64;
            noise_share += along(fx) * along(fy);
            inside += usize::from((0.0..=max_x).contains(&x) && (0.0..=max_y).contains(&y));
        }
        let variance = sum_sq - sum * sum / n as f64;
        if variance <= n as f64 * (super::FLAT_PATCH_SPREAD as f64).powi(2) {
            return None;
        }
        let signal = (variance - noise_share * noise.variance as f64)
            .max(variance / (MAX_NOISE_GAIN as f64).powi(2));
        if signal.sqrt() < MIN_CONTRAST as f64 * self.spread as f64 * (n as f64).sqrt() {
            return None;
        }
        // Independent noise the template was compared with: one image pixel per sample where
        // samples are a pixel or more apart, fewer where the part is smaller than the template
        // (samples share pixels), none beyond the image's border (its pixels repeat there).
        let pixels = (inside as f32 * (pose.scale_x * pose.scale_y).abs().min(1.0)).max(1.0);
        Some(DenoisedReading {
            similarity: (dot / signal.sqrt()).clamp(-1.0, 1.0) as f32,
            noise_spread: (variance / signal - 1.0) as f32 / pixels,
        })
    }
}

/// A pose's similarity with the image's noise taken out ([`NoisePoints::read`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct DenoisedReading {
    /// ZNCC with the noise's variance taken out of the samples', raised by at most
    /// [`MAX_NOISE_GAIN`]; in [-1, 1].
    pub(crate) similarity: f32,
    /// The variance the noise itself lends an unrelated patch's similarity: the correction
    /// raises the noise's part of the correlation with the rest, `(gain² − 1) / pixels` with
    /// `pixels` the independent image pixels compared. The chance level of the reading is
    /// `sqrt(chance² + 2·ln M · noise_spread)` (`matcher/verification.rs`).
    pub(crate) noise_spread: f32,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::refine::{TemplatePoints, at_centre, textured};

    /// `image` with white Gaussian noise of `sigma` (a fixed hash, Box–Muller).
    fn with_noise(image: &GrayImage32, sigma: f32) -> GrayImage32 {
        let uniform = |k: u64| {
            let mut h = k.wrapping_mul(0x9E37_79B9_7F4A_7C15);
            h = (h ^ (h >> 31)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            ((h >> 40) as f32 + 0.5) / (1u64 << 24) as f32
        };
        GrayImage32 {
            values: image
                .values
                .iter()
                .enumerate()
                .map(|(k, v)| {
                    let (u1, u2) = (uniform(2 * k as u64), uniform(2 * k as u64 + 1));
                    let normal = (-2.0 * u1.ln()).sqrt() * (std::f32::consts::TAU * u2).cos();
                    v + sigma * normal
                })
                .collect(),
            ..image.clone()
        }
    }

    /// A smooth, low-contrast pattern: structure only at scales well above a pixel.
    fn smooth(width: usize, height: usize, contrast: f32) -> GrayImage32 {
        GrayImage32::from_fn(width, height, |x, y| {
            let (x, y) = (x as f32, y as f32);
            0.5 + contrast * ((x / 3.0).sin() * (y / 4.0).cos() + (0.2 * x + 0.3 * y).sin()) / 2.0
        })
    }

    /// Fine grain around mid-grey: every pixel its own value, of spread `spread` (a hash,
    /// uniform; not [`with_noise`]'s sequence).
    fn grain(width: usize, height: usize, spread: f32) -> GrayImage32 {
        GrayImage32::from_fn(width, height, |x, y| {
            let mut h = ((y * width + x) as u64 + 7_777).wrapping_mul(0xD6E8_FEB8_6659_FD93);
            h ^= h >> 32;
            let uniform = (h & 0xFFFF) as f32 / 65_535.0 - 0.5;
            0.5 + spread * 12f32.sqrt() * uniform
        })
    }

    /// The noise level of white noise of `sigma`, read from a larger image than a template.
    fn noise_of(sigma: f32) -> NoiseLevel {
        NoiseLevel::estimate(&with_noise(&smooth(200, 160, 0.12), sigma))
    }

    /// `template` itself under white noise of `sigma`, read at its own pose: the plain ZNCC and
    /// the similarity with that noise taken out.
    fn plain_and_corrected(template: &GrayImage32, sigma: f32) -> (f32, f32) {
        let noisy = with_noise(template, sigma);
        let pose = at_centre(template);
        let support = TemplatePoints::support(template);
        let corrected = NoisePoints::new(template)
            .read(
                &support.samples(&noisy, &pose),
                &noisy,
                &pose,
                noise_of(sigma),
            )
            .expect("a noisy part is no flat patch")
            .similarity;
        (support.score(&noisy, &pose), corrected)
    }

    #[test]
    fn a_grain_part_under_noise_stronger_than_its_contrast_reads_as_a_clean_one() {
        // Noise 1.6 times the part's own contrast: a ZNCC near 0.5, which 1.5x could not lift.
        let (zncc, corrected) = plain_and_corrected(&grain(36, 36, 0.025), 0.04);
        assert!(zncc < 0.6, "ZNCC {zncc}");
        assert!(corrected > 0.9, "corrected {corrected} (ZNCC {zncc})");
    }

    #[test]
    fn the_noise_level_is_read_from_the_noise_not_the_structure() {
        let clean = smooth(200, 160, 0.3);
        assert!(NoiseLevel::estimate(&clean).variance.sqrt() < 0.005);
        let noisy = with_noise(&clean, 0.04);
        let sigma = NoiseLevel::estimate(&noisy).variance.sqrt();
        assert!((0.036..0.044).contains(&sigma), "{sigma}");
        let empty = GrayImage32::from_fn(1, 1, |_, _| 0.5);
        assert_eq!(NoiseLevel::estimate(&empty).variance, 0.0);
    }

    #[test]
    fn a_noisy_part_reads_as_a_clean_one_and_an_unrelated_patch_stays_unrelated() {
        let template = smooth(36, 36, 0.12);
        let (zncc, corrected) = plain_and_corrected(&template, 0.04);
        assert!(zncc < 0.85, "ZNCC {zncc}");
        assert!(corrected > 0.95, "corrected {corrected} (ZNCC {zncc})");
        let noise = noise_of(0.04);
        let pose = at_centre(&template);
        let support = TemplatePoints::support(&template);
        let points = NoisePoints::new(&template);
        let read = |image: &GrayImage32, noise| {
            points.read(&support.samples(image, &pose), image, &pose, noise)
        };
        // Without noise in the image, nothing changes.
        let clean = read(&template, NoiseLevel { variance: 0.0 }).unwrap();
        assert!(clean.similarity > 0.999 && clean.noise_spread == 0.0);
        // An unrelated patch under the same noise gains at most MAX_NOISE_GAIN.
        let other = with_noise(&textured(36, 36, 7), 0.04);
        let unrelated = read(&other, noise).unwrap().similarity;
        let plain = support.score(&other, &pose);
        assert!(unrelated.abs() <= plain.abs() * MAX_NOISE_GAIN + 1e-4);
        assert!(unrelated.abs() < 0.2, "{unrelated}");
        let flat = GrayImage32::from_fn(36, 36, |_, _| 0.5);
        assert_eq!(read(&flat, noise), None);
    }
}
