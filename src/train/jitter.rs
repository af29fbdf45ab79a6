//! Photometric jitter of training search images — brightness, contrast, non-linear and uneven
//! light, blur and sensor noise — so that the model survives factory lighting and optics that
//! differ from when the template was registered. Geometry is untouched: the labels stay exact.
//!
//! The camera conditions of issue 41 set the ranges: a gamma up to 2.2 (dark-gamma), light
//! falling to 0.4 of its level across the frame (uneven-light), noise up to 15 grey levels
//! (noise-15). Until 2026-12-02 the jitter had none of the first two and noise only to 7.6 grey
//! levels, and the network's best peak was the part in half as many unevenly lit pairs as clean
//! ones (docs/industrial.md, "Camera conditions"). `training/pairs.py` `jitter` draws the same
//! distribution on the GPU (the same steps in the same order; its random numbers are torch's).

use rand::Rng;
use rand::rngs::StdRng;

use crate::imaging::RgbImage32;

/// Probability of a gamma, of a ramp of light, of a blur and of noise.
pub const GAMMA_SHARE: f64 = 0.3;
pub const RAMP_SHARE: f64 = 0.3;
pub const BLUR_SHARE: f64 = 0.3;
pub const NOISE_SHARE: f64 = 0.5;
/// Gamma drawn log-uniformly in this range (values in [0, 1] raised to it).
pub const GAMMA_RANGE: (f32, f32) = (0.5, 2.2);
/// A ramp's gain at its dark end and at its bright end, each drawn uniformly in these ranges.
pub const RAMP_DARK_GAIN: (f32, f32) = (0.4, 0.9);
pub const RAMP_BRIGHT_GAIN: (f32, f32) = (1.0, 1.3);
/// Largest noise sigma (image values in [0, 1]): 15 grey levels.
pub const MAX_NOISE_SIGMA: f32 = 15.0 / 255.0;

/// Applies, in this order: a random brightness offset (±0.1) and contrast factor (0.7–1.3 about
/// the mean); with probability [`GAMMA_SHARE`] a gamma (values clamped to [0, 1] first); with
/// probability [`RAMP_SHARE`] a gain falling linearly across the image in a random direction;
/// with probability [`BLUR_SHARE`] a [1 2 1]/4 blur; with probability [`NOISE_SHARE`] Gaussian
/// noise (σ up to [`MAX_NOISE_SIGMA`]); then clamps to [0, 1].
pub fn jitter(image: &mut RgbImage32, rng: &mut StdRng) {
    let brightness: f32 = rng.random_range(-0.1..0.1);
    let contrast: f32 = rng.random_range(0.7..1.3);
    let mean = image.pixels.iter().sum::<f32>() / image.pixels.len().max(1) as f32;
    for v in &mut image.pixels {
        *v = (*v - mean) * contrast + mean + brightness;
    }
    if rng.random_bool(GAMMA_SHARE) {
        let (low, high) = (GAMMA_RANGE.0.ln(), GAMMA_RANGE.1.ln());
        let gamma = rng.random_range(low..high).exp();
        for v in &mut image.pixels {
            *v = v.clamp(0.0, 1.0).powf(gamma);
        }
    }
    if rng.random_bool(RAMP_SHARE) {
        let ramp = LightRamp {
            direction: rng.random_range(0.0..std::f32::consts::TAU),
            dark_gain: rng.random_range(RAMP_DARK_GAIN.0..RAMP_DARK_GAIN.1),
            bright_gain: rng.random_range(RAMP_BRIGHT_GAIN.0..RAMP_BRIGHT_GAIN.1),
        };
        ramp.apply(image);
    }
    if rng.random_bool(BLUR_SHARE) {
        crate::imaging::blur_121(image);
    }
    if rng.random_bool(NOISE_SHARE) {
        let sigma: f32 = rng.random_range(0.0..MAX_NOISE_SIGMA);
        for v in &mut image.pixels {
            // Box–Muller from two uniforms.
            let (a, b): (f32, f32) = (rng.random_range(1e-7..1.0), rng.random());
            *v += sigma * (-2.0 * a.ln()).sqrt() * (std::f32::consts::TAU * b).cos();
        }
    }
    for v in &mut image.pixels {
        *v = v.clamp(0.0, 1.0);
    }
}

/// Light that falls linearly across the image: `bright_gain` at the image's extreme point
/// towards `direction` (radians, x right, y down), `dark_gain` at the opposite one.
struct LightRamp {
    direction: f32,
    dark_gain: f32,
    bright_gain: f32,
}

impl LightRamp {
    fn apply(&self, image: &mut RgbImage32) {
        let (w, h) = (image.width as usize, image.height as usize);
        let (dx, dy) = (self.direction.cos(), self.direction.sin());
        let (cx, cy) = ((w as f32 - 1.0) / 2.0, (h as f32 - 1.0) / 2.0);
        // Projections of the pixel centres onto the direction span [-extent/2, extent/2].
        let extent = (dx.abs() * (w as f32 - 1.0) + dy.abs() * (h as f32 - 1.0)).max(1.0);
        for y in 0..h {
            for x in 0..w {
                let toward = ((x as f32 - cx) * dx + (y as f32 - cy) * dy) / extent + 0.5;
                let gain = self.dark_gain + (self.bright_gain - self.dark_gain) * toward;
                for v in &mut image.pixels[(y * w + x) * 3..(y * w + x) * 3 + 3] {
                    *v *= gain;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::SeedableRng;

    #[test]
    fn jitter_is_deterministic_bounded_and_changes_the_image() {
        let image = RgbImage32::new(
            16,
            16,
            (0..16 * 16 * 3).map(|i| (i % 97) as f32 / 97.0).collect(),
        );
        let run = |seed| {
            let mut copy = image.clone();
            jitter(&mut copy, &mut StdRng::seed_from_u64(seed));
            copy
        };
        assert_eq!(run(3).pixels, run(3).pixels);
        assert_ne!(run(3).pixels, image.pixels);
        assert!(run(4).pixels.iter().all(|v| (0.0..=1.0).contains(v)));
    }

    #[test]
    fn a_ramp_of_light_spans_its_gains_across_the_image_in_its_direction() {
        let grey = RgbImage32::new(9, 5, vec![0.5; 9 * 5 * 3]);
        let at = |image: &RgbImage32, x: usize, y: usize| image.pixels[(y * 9 + x) * 3 + 1];
        // Brightest to the right (direction 0): the left column at the dark gain.
        let mut image = grey.clone();
        LightRamp {
            direction: 0.0,
            dark_gain: 0.4,
            bright_gain: 1.2,
        }
        .apply(&mut image);
        assert!((at(&image, 0, 2) - 0.2).abs() < 1e-5);
        assert!((at(&image, 8, 0) - 0.6).abs() < 1e-5);
        assert!((at(&image, 4, 4) - 0.4).abs() < 1e-5);
        // Towards the bottom-left corner: that corner brightest, the top-right darkest.
        let mut image = grey.clone();
        LightRamp {
            direction: 0.75 * std::f32::consts::PI,
            dark_gain: 0.4,
            bright_gain: 1.2,
        }
        .apply(&mut image);
        assert!((at(&image, 0, 4) - 0.6).abs() < 1e-5);
        assert!((at(&image, 8, 0) - 0.2).abs() < 1e-5);
    }

    #[test]
    fn over_many_images_the_jitter_draws_gammas_ramps_and_noise_at_their_shares() {
        // A flat mid-grey image tells each step apart: a gamma moves its mean without
        // spreading it, a ramp spreads it smoothly (left against right, or top against
        // bottom), noise spreads it from pixel to pixel. training/tests/test_trainer.py
        // measures the GPU trainer's jitter the same way, with the same bounds.
        let (w, h) = (32usize, 32usize);
        let (mut ramps, mut noisy, mut flat, mut moved) = (0, 0, 0, 0);
        let trials = 400;
        for seed in 0..trials {
            let mut image = RgbImage32::new(w as u32, h as u32, vec![0.5; w * h * 3]);
            jitter(&mut image, &mut StdRng::seed_from_u64(seed));
            let grey = |x: usize, y: usize| image.pixels[(y * w + x) * 3];
            let half_mean = |xs: std::ops::Range<usize>, ys: std::ops::Range<usize>| {
                let n = (xs.len() * ys.len()) as f32;
                let mut total = 0.0;
                for y in ys {
                    for x in xs.clone() {
                        total += grey(x, y);
                    }
                }
                total / n
            };
            let across = (half_mean(0..w / 2, 0..h) - half_mean(w / 2..w, 0..h)).abs();
            let down = (half_mean(0..w, 0..h / 2) - half_mean(0..w, h / 2..h)).abs();
            if across.max(down) > 0.03 {
                ramps += 1;
            }
            let step: f32 = (1..w)
                .map(|x| (grey(x, 7) - grey(x - 1, 7)).abs())
                .sum::<f32>()
                / (w - 1) as f32;
            if step > 0.01 {
                noisy += 1;
            }
            if across.max(down) < 0.01 {
                flat += 1;
                if (half_mean(0..w, 0..h) - 0.5).abs() > 0.12 {
                    moved += 1;
                }
            }
        }
        let share = |count: i32| count as f64 / trials as f64;
        // A ramp in a direction near a diagonal still differs by well over 0.03 between
        // halves; a few ramps with gains close together do not (hence the lower bound).
        assert!(
            (0.2..0.36).contains(&share(ramps)),
            "ramps {}",
            share(ramps)
        );
        // Noise of sigma below about 0.01 hides under the pixel step threshold.
        assert!(
            (0.35..0.55).contains(&share(noisy)),
            "noisy {}",
            share(noisy)
        );
        // A gamma moves an unramped image's level beyond what brightness alone (0.5 ± 0.1)
        // reaches.
        let moved_share = moved as f64 / flat as f64;
        assert!((0.1..0.3).contains(&moved_share), "moved {moved_share}");
    }
}
