//! The curve of the light at a pose: the monotone map from the image's grey levels to the
//! template's that pairs their quantiles.
//!
//! Why: the alignment minimises a residual under one gain and one offset, so under a gamma
//! (a darkened, non-linear exposure) the pose it settles at is a few tenths of a pixel or a
//! degree off, and the rank reading of the score, which a monotone curve leaves alone only at
//! the exact pose, falls under the default `min_score` there. Seen through this curve the
//! image has the template's grey levels again, and the same alignment lands on the part.
//! Estimated at a pose already near the part, the quantile pairing needs no correspondence of
//! single pixels: only that template and image show the same part.

/// Knots of the curve: at most this many quantiles, paired.
const KNOTS: usize = 33;

/// A monotone, piecewise linear map from image grey levels to template grey levels.
pub(crate) struct LightCurve {
    /// `(image, template)` grey levels, both strictly increasing in the image's.
    knots: Vec<(f32, f32)>,
}

impl LightCurve {
    /// The curve that takes the quantiles of `image` (samples at a pose) to the same quantiles
    /// of `template` (the template's values at the same points); `None` where the samples hold
    /// too few distinct grey levels to tell a curve (a flat patch, a few values) or any is not
    /// finite (the pose maps points outside the image).
    pub(crate) fn pairing(image: &[f32], template: &[f32]) -> Option<Self> {
        if image.len() != template.len()
            || image.len() < KNOTS
            || image.iter().chain(template).any(|v| !v.is_finite())
        {
            return None;
        }
        let mut from = image.to_vec();
        from.sort_by(f32::total_cmp);
        let mut to = template.to_vec();
        to.sort_by(f32::total_cmp);
        let mut knots: Vec<(f32, f32)> = Vec::with_capacity(KNOTS);
        for k in 0..KNOTS {
            let i = (from.len() - 1) * k / (KNOTS - 1);
            if knots.last().is_none_or(|&(last, _)| from[i] > last + 1e-6) {
                knots.push((from[i], to[i]));
            }
        }
        (knots.len() >= 4).then_some(Self { knots })
    }

    /// The template grey level the curve gives image grey level `v` (held at the ends).
    pub(crate) fn apply(&self, v: f32) -> f32 {
        let (first, last) = (self.knots[0], self.knots[self.knots.len() - 1]);
        if v <= first.0 {
            return first.1;
        }
        if v >= last.0 {
            return last.1;
        }
        let j = self.knots.partition_point(|&(image, _)| image <= v);
        let (a, b) = (self.knots[j - 1], self.knots[j]);
        a.1 + (b.1 - a.1) * (v - a.0) / (b.0 - a.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_gamma_is_undone_to_within_a_grey_level() {
        let template: Vec<f32> = (0..400).map(|i| ((i * 37) % 400) as f32 / 400.0).collect();
        let dark: Vec<f32> = template
            .iter()
            .map(|v| 0.6 * v.powf(2.2) + 10.0 / 255.0)
            .collect();
        let curve = LightCurve::pairing(&dark, &template).expect("enough grey levels");
        for (d, t) in dark.iter().zip(&template) {
            assert!(
                (curve.apply(*d) - t).abs() < 1.5 / 255.0 + 0.02 * (1.0 - t),
                "{d} {t}"
            );
        }
        // Monotone, and held at the ends.
        assert_eq!(curve.apply(-1.0), curve.apply(0.0));
        assert!(curve.apply(0.3) <= curve.apply(0.31));
    }

    #[test]
    fn too_few_grey_levels_or_points_outside_tell_no_curve() {
        let flat = vec![0.5f32; 100];
        let template: Vec<f32> = (0..100).map(|i| i as f32 / 100.0).collect();
        assert!(LightCurve::pairing(&flat, &template).is_none());
        let mut outside = template.clone();
        outside[3] = f32::NAN;
        assert!(LightCurve::pairing(&outside, &template).is_none());
        assert!(LightCurve::pairing(&template[..10], &template[..10]).is_none());
    }
}
