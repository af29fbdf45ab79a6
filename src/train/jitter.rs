//! Photometric jitter of training search images — brightness, contrast, blur and sensor noise —
//! so that the model survives factory lighting and optics that differ from when the template
//! was registered. Geometry is untouched: the labels stay exact.

use rand::Rng;
use rand::rngs::StdRng;

use crate::imaging::RgbImage32;

/// Applies a random brightness offset (±0.1), contrast factor (0.7–1.3 about the mean), with
/// probability 0.3 a [1 2 1]/4 blur, and with probability 0.5 Gaussian noise (σ up to 0.03),
/// then clamps to [0, 1].
pub fn jitter(image: &mut RgbImage32, rng: &mut StdRng) {
    let brightness: f32 = rng.random_range(-0.1..0.1);
    let contrast: f32 = rng.random_range(0.7..1.3);
    let mean = image.pixels.iter().sum::<f32>() / image.pixels.len().max(1) as f32;
    for v in &mut image.pixels {
        *v = (*v - mean) * contrast + mean + brightness;
    }
    if rng.random_bool(0.3) {
        crate::imaging::blur_121(image);
    }
    if rng.random_bool(0.5) {
        let sigma: f32 = rng.random_range(0.0..0.03);
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
}
