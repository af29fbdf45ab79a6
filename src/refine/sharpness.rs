//! The similarity of a pose read at the image's own sharpness: the template blurred as the
//! camera blurred the part, the image smoothed where its noise would drown the detail.
//!
//! Why: the template is registered sharp and clean; a defocused camera (sigma 2 px) turns a
//! perfect pose's ZNCC from 0.99 into about 0.85, and sensor noise of 15 grey levels into about
//! 0.9, so a part that is clearly there falls below the default `min_score` and is dropped.
//! Comparing like with like restores it: the template blurred by the defocus correlates with
//! the defocused part as the sharp template does with a sharp part, and both blurred by the same
//! small kernel average the noise out of the correlation. Which blur the camera applied is not
//! known, so each pose is read at a few sharpnesses ([`READINGS`]) and the best reading counts;
//! each reading is held to the chance level of its own (blurred, hence less detailed) template,
//! so an unrelated patch gains nothing from the choice (docs/accuracy.md, "What a score
//! means").

use std::collections::HashMap;
use std::sync::{Arc, Mutex, OnceLock, PoisonError};

use super::align::blurred_window;
use super::blocking::Blocking;
use super::noise::NoiseLevel;
use super::{PoseSamples, TemplatePoints};
use crate::geometry::Pose;
use crate::imaging::{GrayImage32, gaussian_blur};

/// Readings beyond the sharp one, as `(defocus, smoothing)` in image pixels: the template is
/// blurred by `sqrt(defocus² + smoothing²)` (the camera's blur and the smoothing together), the
/// image by `smoothing`. The readings that smooth the image are read only in an image that
/// shows a camera's noise ([`SMOOTHING_MIN_NOISE`]) or a codec's blocks ([`Blocking`]).
pub(crate) const READINGS: [(f32, f32); 4] = [(1.0, 0.0), (2.0, 0.0), (3.0, 0.0), (0.0, 1.5)];

/// Least noise of an image, in grey levels (Donoho's estimate, [`NoiseLevel`]), at which the
/// readings that smooth it are read (or where it shows JPEG's blocks: compression removes the
/// finest detail, so such an image reads as quiet while smoothing still averages its blocks out
/// of the correlation). Why: smoothing is there to average a noisy camera's noise
/// out of the correlation; in an image without noise to speak of it lends nothing to a part and
/// lets a smooth template (correlation length 4–8 px, whose blurred copy is held to the capped
/// chance level) match any smooth patch: in 1000 lomiri tuning scenes without the part, 20 of
/// the 40 false answers at or above 0.9 left after the other readings were smoothing readings.
/// Clean tuning scenes read 1.2–3.1 grey levels, the same under `noise-15` 10–11. Tuning sets
/// only (1000 S1.5 pairs, seed 0; docs/industrial.md, 2026-12-04): false answers ≥ 0.9 without
/// the part 48 → 40 (lomiri) and 113 → 76 (grain), every condition's found parts unchanged.
pub(crate) const SMOOTHING_MIN_NOISE: f32 = 5.0;

/// Steps per octave of the template blur that [`Sharpness`] keeps blurred templates for: a
/// pose's blur in template pixels (the reading's over the pose's scale) is rounded to the
/// nearest step, at most 2.2 % off. Why: the verifier reads some fifty poses a pair at four
/// blurs each, and blurring the template, gathering its points and measuring its chance level
/// anew for each was a tenth of a pair's time (`perf`, held-out mate pairs); the poses of one
/// pair have few distinct scales once rounded, so each blurred template is made a few times
/// per pair instead of two hundred.
const BLUR_STEPS_PER_OCTAVE: f32 = 16.0;

/// Images up to this many pixels are smoothed whole, once, for the readings that smooth the
/// image; larger ones a window around each pose. Why: smoothing a window of a 36x36 part costs
/// about 4000 pixels a pose and the verifier reads some fifty poses a pair, so up to about
/// 200 000 pixels the whole image costs less; a 2048x2048 frame would cost as much as a
/// thousand windows.
const SMOOTH_WHOLE_IMAGE_PIXELS: usize = 1 << 18;

/// One reading's similarity and the chance level of its blurred template.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct SharpnessReading {
    /// Which of [`READINGS`]: `(defocus, smoothing)` in image pixels.
    pub blur: (f32, f32),
    /// ZNCC of the blurred template with the (smoothed) image at the pose, in [-1, 1].
    pub similarity: f32,
    /// The blurred template's [`Sharpness::chance`] level.
    pub chance: f32,
}

/// The template blurred by one step of [`BLUR_STEPS_PER_OCTAVE`]: its support points and its
/// chance level.
struct BlurredTemplate {
    points: TemplatePoints,
    chance: f32,
}

/// Reads a template at a pose in one image at each of [`READINGS`].
pub(crate) struct Sharpness<'a> {
    template: &'a GrayImage32,
    image: &'a GrayImage32,
    /// The chance level of a template (the verifier's `chance_similarity`).
    chance: fn(&GrayImage32) -> f32,
    /// The blurred templates made so far, by step of [`BLUR_STEPS_PER_OCTAVE`] (the verifier
    /// reads poses from several threads).
    blurred: Mutex<HashMap<i32, Arc<BlurredTemplate>>>,
    /// The whole image smoothed for each reading that smooths it, made on first use (an image
    /// of at most [`SMOOTH_WHOLE_IMAGE_PIXELS`]).
    smoothed: [OnceLock<GrayImage32>; READINGS.len()],
    /// Whether the image is noisy or compressed enough for the readings that smooth it
    /// ([`SMOOTHING_MIN_NOISE`]), measured on first use.
    needs_smoothing: OnceLock<bool>,
    /// The image's noise ([`NoiseLevel`], estimated once by the caller).
    noise: NoiseLevel,
}

impl<'a> Sharpness<'a> {
    pub(crate) fn new(
        template: &'a GrayImage32,
        image: &'a GrayImage32,
        noise: NoiseLevel,
        chance: fn(&GrayImage32) -> f32,
    ) -> Self {
        Self {
            template,
            image,
            noise,
            chance,
            blurred: Mutex::new(HashMap::new()),
            smoothed: Default::default(),
            needs_smoothing: OnceLock::new(),
        }
    }

    /// The template blurred by about `sigma` template pixels: the nearest step of
    /// [`BLUR_STEPS_PER_OCTAVE`], made on first use.
    fn blurred(&self, sigma: f32) -> Arc<BlurredTemplate> {
        let step = (sigma.max(1e-3).log2() * BLUR_STEPS_PER_OCTAVE).round() as i32;
        let made = self.made_blurred().get(&step).cloned();
        if let Some(blurred) = made {
            return blurred;
        }
        // Made outside the lock: two threads may make the same step; the first one kept wins.
        let template =
            blurred_template(self.template, (step as f32 / BLUR_STEPS_PER_OCTAVE).exp2());
        let blurred = Arc::new(BlurredTemplate {
            points: TemplatePoints::support(&template),
            chance: (self.chance)(&template),
        });
        self.made_blurred().entry(step).or_insert(blurred).clone()
    }

    /// The blurred templates made so far, locked (a panic elsewhere leaves them usable: each
    /// entry is inserted whole).
    fn made_blurred(&self) -> std::sync::MutexGuard<'_, HashMap<i32, Arc<BlurredTemplate>>> {
        self.blurred.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Whether the image is noisy or compressed enough for the readings that smooth it.
    fn needs_smoothing(&self) -> bool {
        *self.needs_smoothing.get_or_init(|| {
            self.noise.grey_levels() >= SMOOTHING_MIN_NOISE
                || Blocking::estimate(self.image).compressed()
        })
    }

    /// Every reading of [`READINGS`] at `pose` (those that smooth the image only where it
    /// needs smoothing), whose samples in the image (the template's support's) are `samples`.
    pub(crate) fn read(&self, samples: &PoseSamples, pose: &Pose) -> Vec<SharpnessReading> {
        let scale = (pose.scale_x * pose.scale_y).abs().sqrt().max(0.05);
        let blurred_readings: Vec<_> = READINGS
            .iter()
            .zip(&self.smoothed)
            .filter(|&(&(_, smoothing), _)| smoothing <= 0.0 || self.needs_smoothing())
            .map(|(&blur, smoothed)| {
                let (defocus, smoothing) = blur;
                (
                    blur,
                    smoothed,
                    self.blurred(defocus.hypot(smoothing) / scale),
                )
            })
            .collect();
        // The readings that leave the image as it is correlate with the same samples: side by
        // side, in one pass.
        let sharp_weights: Vec<&[f32]> = blurred_readings
            .iter()
            .filter(|((_, smoothing), ..)| *smoothing <= 0.0)
            .map(|(_, _, blurred)| blurred.points.weights())
            .collect();
        let mut sharp = samples.zncc_each(&sharp_weights).into_iter();
        blurred_readings
            .iter()
            .map(|&((defocus, smoothing), smoothed, ref blurred)| {
                let similarity = if smoothing <= 0.0 {
                    sharp.next().expect("one correlation per sharp reading")
                } else {
                    self.smoothed_similarity(blurred, smoothed, smoothing, pose)
                };
                SharpnessReading {
                    blur: (defocus, smoothing),
                    similarity,
                    chance: blurred.chance,
                }
            })
            .collect()
    }

    /// The `blurred` template's ZNCC with the image smoothed by `smoothing` at `pose`: the
    /// whole image smoothed once (`smoothed`, made on first use) where it is small enough,
    /// else a window around the pose.
    fn smoothed_similarity(
        &self,
        blurred: &BlurredTemplate,
        smoothed: &OnceLock<GrayImage32>,
        smoothing: f32,
        pose: &Pose,
    ) -> f32 {
        if self.image.width * self.image.height <= SMOOTH_WHOLE_IMAGE_PIXELS {
            let smoothed = smoothed.get_or_init(|| gaussian_blur(self.image, smoothing));
            return blurred.points.score(smoothed, pose);
        }
        let reach = (self.template.width as f32 * pose.scale_x.abs())
            .hypot(self.template.height as f32 * pose.scale_y.abs())
            / 2.0
            + 2.0;
        let (window, x0, y0) = blurred_window(
            self.image,
            pose.x,
            pose.y,
            reach + 3.0 * smoothing,
            smoothing,
        );
        blurred.points.score(
            &window,
            &Pose {
                x: pose.x - x0,
                y: pose.y - y0,
                ..*pose
            },
        )
    }
}

/// `template` blurred by a Gaussian of `sigma` template pixels; pixels a mask ignores (NaN)
/// stay ignored and lend nothing to their neighbours (normalised convolution).
pub(crate) fn blurred_template(template: &GrayImage32, sigma: f32) -> GrayImage32 {
    if !template.ignores_pixels() {
        return gaussian_blur(template, sigma);
    }
    let used = |v: f32| if v.is_nan() { 0.0 } else { 1.0 };
    let weights = gaussian_blur(
        &GrayImage32 {
            values: template.values.iter().map(|&v| used(v)).collect(),
            ..*template
        },
        sigma,
    );
    let weighted = gaussian_blur(
        &GrayImage32 {
            values: template
                .values
                .iter()
                .map(|&v| if v.is_nan() { 0.0 } else { v })
                .collect(),
            ..*template
        },
        sigma,
    );
    GrayImage32 {
        values: template
            .values
            .iter()
            .zip(weighted.values.iter().zip(&weights.values))
            .map(|(&v, (&sum, &weight))| {
                if v.is_nan() || weight <= 1e-6 {
                    f32::NAN
                } else {
                    sum / weight
                }
            })
            .collect(),
        ..*template
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::refine::textured;

    /// `template` pasted unrotated at scale 1 into `background` with its centre at `(cx, cy)`.
    fn pasted(
        template: &GrayImage32,
        background: &GrayImage32,
        cx: usize,
        cy: usize,
    ) -> GrayImage32 {
        let mut image = background.clone();
        let (x0, y0) = (cx - template.width / 2, cy - template.height / 2);
        for y in 0..template.height {
            for x in 0..template.width {
                image.values[(y0 + y) * image.width + x0 + x] =
                    template.values[y * template.width + x];
            }
        }
        image
    }

    fn chance(template: &GrayImage32) -> f32 {
        crate::matcher::verification::chance_similarity(template)
    }

    #[test]
    fn a_defocused_part_reads_as_sharp_with_the_template_blurred_alike() {
        let template = textured(36, 36, 1);
        let scene = pasted(&template, &textured(96, 96, 2), 48, 48);
        let defocused = gaussian_blur(&scene, 2.0);
        let pose = Pose::upright(47.5, 47.5, 0.0);
        let support = TemplatePoints::support(&template);
        let sharp = support.score(&defocused, &pose);
        let readings = Sharpness::new(
            &template,
            &defocused,
            NoiseLevel::estimate(&defocused),
            chance,
        )
        .read(&support.samples(&defocused, &pose), &pose);
        let best = readings
            .iter()
            .map(|r| r.similarity)
            .fold(f32::MIN, f32::max);
        assert!(sharp < 0.8, "the sharp template reads {sharp}");
        assert!(best > 0.9, "the best reading is {best} (sharp {sharp})");
        // Every blurred reading is held to a higher chance level than the sharp template's.
        assert!(readings.iter().all(|r| r.chance > chance(&template)));
    }

    #[test]
    fn a_blur_rounded_to_its_step_reads_as_the_exact_blur() {
        let template = textured(36, 36, 1);
        let scene = gaussian_blur(&pasted(&template, &textured(96, 96, 2), 48, 48), 2.0);
        let sharpness = Sharpness::new(&template, &scene, NoiseLevel::estimate(&scene), chance);
        // Scales whose blurs fall between the steps, and on one.
        for scale in [0.83f32, 1.0, 1.07, 1.31] {
            let pose = Pose {
                x: 47.5,
                y: 47.5,
                angle_deg: 0.0,
                scale_x: scale,
                scale_y: scale,
                score: 0.0,
                network_score: 0.0,
            };
            let support = TemplatePoints::support(&template);
            let readings = sharpness.read(&support.samples(&scene, &pose), &pose);
            for reading in readings.iter().filter(|r| r.blur.1 == 0.0) {
                let exact = blurred_template(&template, reading.blur.0 / scale);
                let similarity = TemplatePoints::support(&exact).score(&scene, &pose);
                // Off by under 0.01 (0.006 at a wrong scale, where the similarity is steep).
                assert!(
                    (reading.similarity - similarity).abs() < 0.01,
                    "scale {scale}, {reading:?}: exact {similarity}"
                );
                // The chance level follows the blur's width: at most the rounding's 2.2 % off.
                let exact_chance = chance(&exact);
                assert!(
                    (reading.chance - exact_chance).abs() <= 0.025 * exact_chance,
                    "scale {scale}, {reading:?}: exact chance {exact_chance}"
                );
            }
        }
        // Each step was made once: three blurs a scale, some shared between scales.
        let made = sharpness.blurred.lock().unwrap().len();
        assert!((4..=16).contains(&made), "{made} blurred templates");
    }

    #[test]
    fn the_image_smoothed_whole_or_in_a_window_reads_alike() {
        let template = textured(36, 36, 1);
        let small = pasted(&template, &textured(96, 96, 2), 48, 48);
        // The same scene inside a frame too large to smooth whole.
        let (offset, side) = (300, 560);
        assert!(side * side > SMOOTH_WHOLE_IMAGE_PIXELS && 96 * 96 <= SMOOTH_WHOLE_IMAGE_PIXELS);
        // Textured around it too: a frame of one flat grey would read as without noise, where
        // the image is not smoothed at all.
        let around = textured(side, side, 5);
        let large = GrayImage32::from_fn(side, side, |x, y| {
            let (u, v) = (x.wrapping_sub(offset), y.wrapping_sub(offset));
            if u < 96 && v < 96 {
                small.values[v * 96 + u]
            } else {
                around.values[y * side + x]
            }
        });
        let smoothed = |image: &GrayImage32, x: f32, y: f32| {
            let pose = Pose {
                x,
                y,
                angle_deg: 20.0,
                scale_x: 1.1,
                scale_y: 0.9,
                score: 0.0,
                network_score: 0.0,
            };
            let samples = TemplatePoints::support(&template).samples(image, &pose);
            let readings = Sharpness::new(&template, image, NoiseLevel::estimate(image), chance)
                .read(&samples, &pose);
            readings.iter().find(|r| r.blur.1 > 0.0).unwrap().similarity
        };
        let whole = smoothed(&small, 47.5, 47.5);
        let window = smoothed(&large, 347.5, 347.5);
        assert!(
            (whole - window).abs() < 1e-4,
            "whole {whole}, window {window}"
        );
    }

    /// `image` through a JPEG round trip at `quality` (8-bit grey).
    fn jpeg(image: &GrayImage32, quality: u8) -> GrayImage32 {
        let bytes: Vec<u8> = (image.values.iter())
            .map(|v| (v * 255.0).round().clamp(0.0, 255.0) as u8)
            .collect();
        let mut encoded = Vec::new();
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut encoded, quality)
            .encode(
                &bytes,
                image.width as u32,
                image.height as u32,
                image::ExtendedColorType::L8,
            )
            .expect("encodes");
        let decoded = image::load_from_memory(&encoded)
            .expect("decodes")
            .to_luma8();
        GrayImage32::from_fn(image.width, image.height, |x, y| {
            f32::from(decoded.get_pixel(x as u32, y as u32).0[0]) / 255.0
        })
    }

    #[test]
    fn the_image_is_smoothed_only_where_it_is_noisy_or_compressed() {
        let template = gaussian_blur(&textured(36, 36, 1), 3.0);
        let quiet = pasted(&template, &gaussian_blur(&textured(96, 96, 2), 3.0), 48, 48);
        // The same scene under noise of about 13 grey levels.
        let grain = textured(96, 96, 7);
        let noisy = GrayImage32 {
            values: (quiet.values.iter().zip(&grain.values))
                .map(|(v, g)| v + 0.3 * (g - 0.5))
                .collect(),
            ..quiet.clone()
        };
        let pose = Pose::upright(47.5, 47.5, 0.0);
        let support = TemplatePoints::support(&template);
        let smoothing_readings = |image: &GrayImage32| {
            Sharpness::new(&template, image, NoiseLevel::estimate(image), chance)
                .read(&support.samples(image, &pose), &pose)
                .iter()
                .filter(|r| r.blur.1 > 0.0)
                .count()
        };
        let smoothing = READINGS.iter().filter(|r| r.1 > 0.0).count();
        assert!(smoothing > 0);
        assert_eq!(smoothing_readings(&quiet), 0);
        assert_eq!(smoothing_readings(&noisy), smoothing);
        // Compression leaves the scene quiet but blocked.
        let compressed = jpeg(&quiet, 30);
        assert!(NoiseLevel::estimate(&compressed).grey_levels() < SMOOTHING_MIN_NOISE);
        assert_eq!(smoothing_readings(&compressed), smoothing);
    }

    #[test]
    fn a_masked_template_stays_masked_when_blurred() {
        let mut template = textured(20, 20, 3);
        for y in 0..10 {
            for x in 0..10 {
                template.values[y * 20 + x] = f32::NAN;
            }
        }
        let blurred = blurred_template(&template, 2.0);
        for (before, after) in template.values.iter().zip(&blurred.values) {
            assert_eq!(before.is_nan(), after.is_nan());
            if !after.is_nan() {
                assert!((0.2..=0.8).contains(after));
            }
        }
    }
}
