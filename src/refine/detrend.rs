//! Correlation with a plane fitted out of both sides: how the screen judges a pose where the
//! light changes across the part.
//!
//! Why: a gain that falls across the frame (a lamp on one side, `--condition uneven-light`)
//! multiplies the part's mean grey level by a ramp. Over a template of little contrast the
//! ramp is larger than the template's own detail, and the plain ZNCC at the part falls far: in
//! 18 of the 26 unevenly lit pairs of the corpus tuning photos with no answer at 0.9, all
//! templates of 5–12 grey levels' spread, it read 0.01–0.79 at the true pose, where the same
//! correlation with a plane `a + b·u + c·v` fitted out of the template and of the image samples
//! alike (least squares over the points' offsets) read 0.87–0.99. The plane takes out the ramp and leaves the detail; it also takes out a
//! template's own linear shading, which is why it judges between two poses of one candidate
//! rather than scoring answers (the score has its own reading for shading, `shading.rs`).

use super::{FLAT_PATCH_SPREAD, PoseSamples, TemplatePoints};

/// Template points' weights with their best-fitting plane over the offsets taken out (unit
/// norm), and what it takes to do the same to image samples.
pub(crate) struct PlaneFreePoints {
    offsets: Vec<(f64, f64)>,
    weights: Vec<f64>,
    /// Inverse of the normal matrix of the plane's least-squares fit, `(AᵀA)⁻¹` for the rows
    /// `(1, u, v)` of the points.
    inverse_normal: [[f64; 3]; 3],
}

impl PlaneFreePoints {
    /// `None` where nothing is left once the plane is out: a template that is a plane (or
    /// flat), or points that lie on one line.
    pub(crate) fn new(points: &TemplatePoints) -> Option<Self> {
        let offsets: Vec<(f64, f64)> = points
            .points()
            .map(|((u, v), _)| (f64::from(u), f64::from(v)))
            .collect();
        let weights: Vec<f64> = points.points().map(|(_, w)| f64::from(w)).collect();
        let mut normal = [[0f64; 3]; 3];
        for &(u, v) in &offsets {
            let row = [1.0, u, v];
            for i in 0..3 {
                for j in 0..3 {
                    normal[i][j] += row[i] * row[j];
                }
            }
        }
        let inverse_normal = inverse_3x3(&normal)?;
        let mut plane_free = Self {
            offsets,
            weights,
            inverse_normal,
        };
        let residual = plane_free.without_plane(&plane_free.weights);
        let norm = residual.iter().map(|w| w * w).sum::<f64>().sqrt();
        if norm < 1e-6 {
            return None;
        }
        plane_free.weights = residual.iter().map(|w| w / norm).collect();
        Some(plane_free)
    }

    /// ZNCC of the plane-free template with `samples` (one per point, in the points' order,
    /// [`TemplatePoints::samples`]) once their own best plane is taken out, in [-1, 1]; -1
    /// where the samples are a plane to within half a grey level ([`FLAT_PATCH_SPREAD`]).
    pub(crate) fn score(&self, samples: &PoseSamples) -> f32 {
        let values = samples.values();
        debug_assert_eq!(values.len(), self.weights.len(), "one sample per point");
        let Some(&reference) = values.first() else {
            return -1.0;
        };
        // Relative to the first sample, as the lanes' sums are: the variance is otherwise a
        // small difference of large sums.
        let mut moments = [0f64; 3];
        let (mut sum_sq, mut dot) = (0f64, 0f64);
        for ((&(u, v), &w), &sample) in self.offsets.iter().zip(&self.weights).zip(values) {
            let value = f64::from(sample - reference);
            moments[0] += value;
            moments[1] += value * u;
            moments[2] += value * v;
            sum_sq += value * value;
            dot += w * value;
        }
        // What the plane explains: mᵀ (AᵀA)⁻¹ m.
        let explained: f64 = (0..3)
            .map(|i| {
                moments[i]
                    * (0..3)
                        .map(|j| self.inverse_normal[i][j] * moments[j])
                        .sum::<f64>()
            })
            .sum();
        let variance = sum_sq - explained;
        let spread = f64::from(FLAT_PATCH_SPREAD);
        if variance <= values.len() as f64 * spread * spread {
            return -1.0;
        }
        // The weights are orthogonal to the plane, so their dot with the samples is their
        // dot with the samples' residual.
        (dot / variance.sqrt()).clamp(-1.0, 1.0) as f32
    }

    /// The plane-free weights (unit norm, orthogonal to every plane over the offsets), one per
    /// point in the points' order.
    pub(crate) fn weights(&self) -> &[f64] {
        &self.weights
    }

    /// `(AᵀA)⁻¹` of the plane's least-squares fit over the points' rows `(1, u, v)`: with the
    /// moments `m = (Σ I, Σ u·I, Σ v·I)` of samples `I`, `mᵀ (AᵀA)⁻¹ m` is what their plane
    /// explains of `Σ I²` (what [`PlaneFreePoints::score`] takes out).
    pub(crate) fn inverse_normal(&self) -> &[[f64; 3]; 3] {
        &self.inverse_normal
    }

    /// `values` (one per point) less their least-squares plane over the offsets.
    fn without_plane(&self, values: &[f64]) -> Vec<f64> {
        let mut moments = [0f64; 3];
        for (&(u, v), &value) in self.offsets.iter().zip(values) {
            moments[0] += value;
            moments[1] += value * u;
            moments[2] += value * v;
        }
        let plane: Vec<f64> = (0..3)
            .map(|i| (0..3).map(|j| self.inverse_normal[i][j] * moments[j]).sum())
            .collect();
        self.offsets
            .iter()
            .zip(values)
            .map(|(&(u, v), &value)| value - (plane[0] + plane[1] * u + plane[2] * v))
            .collect()
    }
}

/// The inverse of a 3x3 matrix by its adjugate; `None` when it is (nearly) singular.
fn inverse_3x3(m: &[[f64; 3]; 3]) -> Option<[[f64; 3]; 3]> {
    let cofactor = |r: usize, c: usize| {
        let (r0, r1) = ((r + 1) % 3, (r + 2) % 3);
        let (c0, c1) = ((c + 1) % 3, (c + 2) % 3);
        m[r0][c0] * m[r1][c1] - m[r0][c1] * m[r1][c0]
    };
    let determinant: f64 = (0..3).map(|c| m[0][c] * cofactor(0, c)).sum();
    let scale = m.iter().flatten().map(|v| v.abs()).fold(0.0, f64::max);
    if determinant.abs() <= 1e-12 * scale.powi(3) {
        return None;
    }
    let mut inverse = [[0f64; 3]; 3];
    for (r, row) in inverse.iter_mut().enumerate() {
        for (c, value) in row.iter_mut().enumerate() {
            // The adjugate is the transposed cofactor matrix.
            *value = cofactor(c, r) / determinant;
        }
    }
    Some(inverse)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Pose;
    use crate::imaging::GrayImage32;
    use crate::refine::{at_centre, textured};

    /// A textured template of little contrast, and the same under a gain that falls by a
    /// quarter across it (0.5 → 0.4 of a bright mean): what `uneven-light` does to a smooth
    /// part at the frame's dark end.
    fn dim_template_under_a_ramp() -> (GrayImage32, GrayImage32) {
        let detail = textured(36, 36, 3);
        let template = GrayImage32::from_fn(36, 36, |x, y| {
            0.6 + 0.04 * (detail.values[y * 36 + x] - 0.5)
        });
        let lit = GrayImage32::from_fn(36, 36, |x, y| {
            template.values[y * 36 + x] * (0.5 - 0.1 * x as f32 / 35.0)
        });
        (template, lit)
    }

    #[test]
    fn a_ramp_of_light_across_a_dim_part_leaves_the_plane_free_correlation_high() {
        let (template, lit) = dim_template_under_a_ramp();
        let points = TemplatePoints::new(&template, 36);
        let pose: Pose = at_centre(&template);
        let plain = points.score(&lit, &pose);
        let plane_free = PlaneFreePoints::new(&points)
            .expect("a textured template is no plane")
            .score(&points.samples(&lit, &pose));
        assert!(plane_free > 0.99, "plane-free {plane_free}");
        assert!(
            plain < 0.8,
            "the plain ZNCC is what the ramp spoils: {plain}"
        );
    }

    #[test]
    fn without_a_ramp_it_is_one_at_the_part_and_low_on_other_texture() {
        let template = textured(36, 36, 3);
        let points = TemplatePoints::new(&template, 36);
        let plane_free = PlaneFreePoints::new(&points).expect("no plane");
        let pose = at_centre(&template);
        let own = plane_free.score(&points.samples(&template, &pose));
        let other = plane_free.score(&points.samples(&textured(36, 36, 11), &pose));
        assert!(own > 0.999, "{own}");
        assert!(other < 0.5, "{other}");
    }

    #[test]
    fn a_template_that_is_a_plane_has_nothing_left_to_correlate() {
        let ramp = GrayImage32::from_fn(20, 20, |x, y| 0.2 + 0.01 * x as f32 + 0.02 * y as f32);
        let points = TemplatePoints::new(&ramp, 20);
        assert!(PlaneFreePoints::new(&points).is_none());
    }

    #[test]
    fn the_inverse_times_the_matrix_is_the_identity() {
        let m = [[4.0, 1.0, 2.0], [1.0, 3.0, 0.5], [2.0, 0.5, 5.0]];
        let inverse = inverse_3x3(&m).expect("invertible");
        for (i, row) in m.iter().enumerate() {
            for j in 0..3 {
                let product: f64 = row.iter().zip(&inverse).map(|(a, b)| a * b[j]).sum();
                let identity = if i == j { 1.0 } else { 0.0 };
                assert!((product - identity).abs() < 1e-12, "{i},{j}: {product}");
            }
        }
        assert!(inverse_3x3(&[[1.0, 2.0, 3.0], [2.0, 4.0, 6.0], [0.0, 1.0, 1.0]]).is_none());
    }
}
