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

use super::TemplatePoints;
use super::align::blurred_window;
use crate::geometry::Pose;
use crate::imaging::{GrayImage32, gaussian_blur};

/// Readings beyond the sharp one, as `(defocus, smoothing)` in image pixels: the template is
/// blurred by `sqrt(defocus² + smoothing²)` (the camera's blur and the smoothing together), the
/// image by `smoothing`.
pub(crate) const READINGS: [(f32, f32); 4] = [(1.0, 0.0), (2.0, 0.0), (3.0, 0.0), (0.0, 1.5)];

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

/// Reads a template at a pose at each of [`READINGS`].
pub(crate) struct Sharpness<'a> {
    template: &'a GrayImage32,
    /// The chance level of a template (the verifier's `chance_similarity`).
    chance: fn(&GrayImage32) -> f32,
}

impl<'a> Sharpness<'a> {
    pub(crate) fn new(template: &'a GrayImage32, chance: fn(&GrayImage32) -> f32) -> Self {
        Self { template, chance }
    }

    /// Every reading of [`READINGS`] at `pose` in `image`.
    pub(crate) fn read(&self, image: &GrayImage32, pose: &Pose) -> Vec<SharpnessReading> {
        let scale = (pose.scale_x * pose.scale_y).abs().sqrt().max(0.05);
        let reach = (self.template.width as f32 * pose.scale_x.abs())
            .hypot(self.template.height as f32 * pose.scale_y.abs())
            / 2.0
            + 2.0;
        let mut smoothed: Vec<(f32, GrayImage32, f32, f32)> = Vec::new();
        READINGS
            .iter()
            .map(|&(defocus, smoothing)| {
                let template = blurred_template(self.template, defocus.hypot(smoothing) / scale);
                let points = TemplatePoints::support(&template);
                let similarity = if smoothing <= 0.0 {
                    points.score(image, pose)
                } else {
                    if !smoothed.iter().any(|(s, ..)| *s == smoothing) {
                        let (window, x0, y0) = blurred_window(
                            image,
                            pose.x,
                            pose.y,
                            reach + 3.0 * smoothing,
                            smoothing,
                        );
                        smoothed.push((smoothing, window, x0, y0));
                    }
                    let (_, window, x0, y0) = smoothed
                        .iter()
                        .find(|(s, ..)| *s == smoothing)
                        .expect("smoothed just above");
                    points.score(
                        window,
                        &Pose {
                            x: pose.x - x0,
                            y: pose.y - y0,
                            ..*pose
                        },
                    )
                };
                SharpnessReading {
                    blur: (defocus, smoothing),
                    similarity,
                    chance: (self.chance)(&template),
                }
            })
            .collect()
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
        let pose = Pose {
            x: 47.5,
            y: 47.5,
            angle_deg: 0.0,
            scale_x: 1.0,
            scale_y: 1.0,
            score: 0.0,
            network_score: 0.0,
        };
        let sharp = TemplatePoints::support(&template).score(&defocused, &pose);
        let readings = Sharpness::new(&template, chance).read(&defocused, &pose);
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
