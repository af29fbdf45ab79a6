//! The similarity of a pose under light that changes across the part: the template times a
//! gain that varies linearly over it, plus an offset that does.
//!
//! Why: ZNCC allows one gain and one offset for the whole part. A lamp on one side, a reflector,
//! vignetting or a light falling off across the frame give the part a gain that changes across
//! it (by a third over a part of a fifth of the frame), which the correlation counts as
//! mismatch: a part that is clearly there scores 0.8 instead of 0.99, and a decoy that happens
//! to share the light's slope outscores it. The cells' own gains (`coverage.rs`) absorb part of
//! it; this reading models it exactly: the image samples are explained by `g(u, v)·t + o(u, v)`
//! with `g` and `o` planes over the template (`u`, `v` its offsets), and the similarity is the
//! share of the image's variance, beyond the offset plane, that the gain plane times the
//! template explains (its square root: a correlation, equal to ZNCC when the light is even).
//! A gain that changes sign, or by more than [`MAX_GAIN_RATIO`] across the part, is no light
//! and reads as no match. Three free gains instead of one fit an unrelated patch a little
//! better, so the reading has its own, higher chance level (`matcher/verification.rs`).

use super::PoseSamples;
use crate::imaging::GrayImage32;

/// Largest ratio of the gain at one corner of the part to the gain at another. The light of
/// `posematch eval --condition uneven-light` (1.3 → 0.4 across the frame) changes a part a
/// fifth of the frame across by at most 1.5x.
const MAX_GAIN_RATIO: f64 = 3.0;

/// Over the template's support points (every pixel up to 48 a side, as the similarity's, in
/// its order): an orthonormal basis of the offset plane `[1, u, v]` and of the gain plane times the template
/// `[t, u·t, v·t]` beyond it.
pub(crate) struct ShadingPoints {
    /// Orthonormal over the points: the offset plane's three vectors, then the gain plane's.
    basis: [Vec<f64>; 6],
    /// Per gain vector of `basis` (3..6): its coefficients on `t`, `u·t`, `v·t` (the offset
    /// plane's part left out), to turn a fit back into the gain plane.
    gain_of: [[f64; 3]; 3],
    /// The gain plane's vectors are independent of the offset plane (the template has detail).
    usable: bool,
}

impl ShadingPoints {
    pub(crate) fn new(template: &GrayImage32) -> Self {
        let (offsets, values) = super::grid_points(template, 48);
        let half_w = ((template.width as f64 - 1.0) / 2.0).max(1.0);
        let half_h = ((template.height as f64 - 1.0) / 2.0).max(1.0);
        let mean = values.iter().map(|&t| t as f64).sum::<f64>() / values.len().max(1) as f64;
        let column = |f: &dyn Fn(f64, f64, f64) -> f64| -> Vec<f64> {
            offsets
                .iter()
                .zip(&values)
                .map(|(&(u, v), &t)| f(u as f64 / half_w, v as f64 / half_h, t as f64 - mean))
                .collect()
        };
        let mut basis = [
            column(&|_, _, _| 1.0),
            column(&|u, _, _| u),
            column(&|_, v, _| v),
            column(&|_, _, t| t),
            column(&|u, _, t| u * t),
            column(&|_, v, t| v * t),
        ];
        // Modified Gram–Schmidt, tracking each gain vector's coefficients on the gain columns.
        let mut gain_of = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        let mut usable = !offsets.is_empty();
        for k in 0..6 {
            for j in 0..k {
                let projection = dot(&basis[k], &basis[j]);
                let (done, rest) = basis.split_at_mut(k);
                rest[0]
                    .iter_mut()
                    .zip(&done[j])
                    .for_each(|(x, q)| *x -= projection * q);
                if k >= 3 && j >= 3 {
                    let previous = gain_of[j - 3];
                    for (c, p) in gain_of[k - 3].iter_mut().zip(previous) {
                        *c -= projection * p;
                    }
                }
            }
            let norm = dot(&basis[k], &basis[k]).sqrt();
            if norm < 1e-9 {
                usable = false;
                break;
            }
            basis[k].iter_mut().for_each(|x| *x /= norm);
            if k >= 3 {
                gain_of[k - 3].iter_mut().for_each(|c| *c /= norm);
            }
        }
        Self {
            basis,
            gain_of,
            usable,
        }
    }

    /// The correlation of the template with the image's `samples` at a pose (the support's) under a
    /// gain and an offset that vary linearly across the part, in [0, 1]; -1 where the image is
    /// flat there, the template has no detail, or the fitted gain is no light's
    /// ([`MAX_GAIN_RATIO`], a sign change: reversed contrast is `polarity`'s business).
    pub(crate) fn similarity(&self, samples: &PoseSamples) -> f32 {
        if !self.usable {
            return -1.0;
        }
        debug_assert_eq!(
            samples.values().len(),
            self.basis[0].len(),
            "the support's samples"
        );
        let (energy, coefficients) = self.projections(samples.values());
        let beyond_offset = energy - coefficients[..3].iter().map(|c| c * c).sum::<f64>();
        let n = samples.values().len() as f64;
        let flat = n * (super::FLAT_PATCH_SPREAD as f64).powi(2);
        if beyond_offset <= flat {
            return -1.0;
        }
        let gain: [f64; 3] = std::array::from_fn(|j| {
            (0..3)
                .map(|k| coefficients[3 + k] * self.gain_of[k][j])
                .sum()
        });
        let corners = [(-1.0, -1.0), (1.0, -1.0), (-1.0, 1.0), (1.0, 1.0)]
            .map(|(u, v)| gain[0] + gain[1] * u + gain[2] * v);
        let (low, high) = corners
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &g| {
                (l.min(g), h.max(g))
            });
        if low <= 0.0 || high > MAX_GAIN_RATIO * low {
            return -1.0;
        }
        let explained = coefficients[3..].iter().map(|c| c * c).sum::<f64>();
        ((explained / beyond_offset).sqrt() as f32).clamp(0.0, 1.0)
    }

    /// The samples' energy `Σ s²` and their coefficients on each basis vector `Σ s·q`, in
    /// one pass: seven sums, each added in the points' order as a plain [`dot`] would (the
    /// same numbers), but side by side, so that the pass costs about what one sum did.
    fn projections(&self, samples: &[f32]) -> (f64, [f64; 6]) {
        let n = samples.len();
        if self.basis[0].len() != n {
            // Not the support's samples (cannot happen): the sums as `dot` reads them.
            let wide: Vec<f64> = samples.iter().map(|&s| f64::from(s)).collect();
            return (
                dot(&wide, &wide),
                self.basis.each_ref().map(|q| dot(&wide, q)),
            );
        }
        let [b0, b1, b2, b3, b4, b5] = self.basis.each_ref().map(|q| &q[..n]);
        // Iterator sums start at -0.0, so these do too.
        let mut energy = -0.0f64;
        let mut c = [-0.0f64; 6];
        for i in 0..n {
            let s = f64::from(samples[i]);
            energy += s * s;
            c[0] += s * b0[i];
            c[1] += s * b1[i];
            c[2] += s * b2[i];
            c[3] += s * b3[i];
            c[4] += s * b4[i];
            c[5] += s * b5[i];
        }
        (energy, c)
    }
}

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::refine::{TemplatePoints, at_centre, textured};

    fn lit(template: &GrayImage32, light: impl Fn(f32, f32) -> f32) -> GrayImage32 {
        GrayImage32::from_fn(template.width, template.height, |x, y| {
            template.values[y * template.width + x] * light(x as f32, y as f32)
        })
    }

    #[test]
    fn the_projections_in_one_pass_are_the_dot_products() {
        let template = textured(36, 36, 4);
        let points = ShadingPoints::new(&template);
        let samples: Vec<f32> = textured(36, 36, 9).values;
        let (energy, coefficients) = points.projections(&samples);
        let wide: Vec<f64> = samples.iter().map(|&s| f64::from(s)).collect();
        assert_eq!(energy, dot(&wide, &wide));
        for (c, q) in coefficients.iter().zip(&points.basis) {
            assert_eq!(*c, dot(&wide, q));
        }
    }

    #[test]
    fn light_falling_across_the_part_keeps_the_shading_similarity_at_one() {
        let template = textured(36, 36, 3);
        let pose = at_centre(&template);
        let support = TemplatePoints::support(&template);
        let points = ShadingPoints::new(&template);
        let falling = lit(&template, |x, y| 1.3 - 0.012 * x - 0.005 * y);
        let similarity = points.similarity(&support.samples(&falling, &pose));
        assert!(similarity > 0.999, "{similarity}");
        assert!(points.similarity(&support.samples(&template, &pose)) > 0.999);
        // ZNCC is not: the light costs it.
        let zncc = support.score(&falling, &pose);
        assert!(zncc < 0.99, "{zncc}");
    }

    #[test]
    fn unrelated_reversed_or_unlit_patches_do_not_match() {
        let template = textured(36, 36, 3);
        let pose = at_centre(&template);
        let support = TemplatePoints::support(&template);
        let points = ShadingPoints::new(&template);
        let similarity = |image: &GrayImage32| points.similarity(&support.samples(image, &pose));
        let other = textured(36, 36, 11);
        let unrelated = similarity(&other);
        assert!(unrelated < 0.35, "{unrelated}");
        // Reversed contrast is a negative gain: no light's.
        let reversed = lit(&template, |_, _| 1.0);
        let reversed = GrayImage32 {
            values: reversed.values.iter().map(|v| 1.0 - v).collect(),
            ..reversed
        };
        assert_eq!(similarity(&reversed), -1.0);
        // A gain from 1 to 0 across the part is no light either.
        let dark_half = lit(&template, |x, _| (1.0 - x / 24.0).max(0.0));
        assert_eq!(similarity(&dark_half), -1.0);
        let flat = GrayImage32::from_fn(36, 36, |_, _| 0.5);
        assert_eq!(similarity(&flat), -1.0);
    }
}
