//! Training targets from a pair's true poses, as the paper builds them: an elliptical Gaussian
//! heatmap deformed by each object's pose, the valid region where it is at least 0.5, and the
//! parameter maps (sign and cosine of the angle, both scales) filled in that region.
//!
//! The deformation follows the public pose convention rather than the paper's matrix: a
//! template offset `(u, v)` lands at `d = A·(u, v)` from the centre with
//! `A = [[sx·cos a, sy·sin a], [−sx·sin a, sy·cos a]]` (angle counter-clockwise on screen, y
//! down), so `G(A⁻¹·d)` is the Gaussian of the template's own coordinates carried onto the
//! image: its ellipse has the object's orientation and aspect.

use crate::geometry::Pose;

/// Spread of the Gaussian in template pixels, as a fraction of the template's side. At 36x36
/// this is σ = 6 template pixels: the ≥ 0.5 region is an ellipse of radius ~7 template pixels
/// (about a fifth of the object), wide enough to give the parameter maps a few dozen supervised
/// pixels, narrow enough that neighbouring instances never share them.
pub const SIGMA_FRACTION: f32 = 1.0 / 6.0;

/// Threshold of the heatmap that defines the supervised region (the paper: 0.5).
pub const VALID_THRESHOLD: f32 = 0.5;

/// Dense targets for one `width x height` search image, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct LabelMaps {
    pub width: usize,
    pub height: usize,
    /// Soft centre heatmap in [0, 1] (the maximum over instances).
    pub heatmap: Vec<f32>,
    /// 1 where the heatmap is ≥ [`VALID_THRESHOLD`], else 0.
    pub valid: Vec<f32>,
    /// 1 for a positive (counter-clockwise) angle, 0 otherwise, where valid.
    pub sign: Vec<f32>,
    /// cos(angle), where valid.
    pub cos: Vec<f32>,
    /// Scales relative to the template grid, where valid.
    pub scale_x: Vec<f32>,
    pub scale_y: Vec<f32>,
}

impl LabelMaps {
    /// Targets for `truths` (poses relative to a `template_width x template_height` template).
    pub fn render(
        width: usize,
        height: usize,
        truths: &[Pose],
        template_width: f32,
        template_height: f32,
    ) -> Self {
        let n = width * height;
        let mut maps = Self {
            width,
            height,
            heatmap: vec![0.0; n],
            valid: vec![0.0; n],
            sign: vec![0.0; n],
            cos: vec![0.0; n],
            scale_x: vec![0.0; n],
            scale_y: vec![0.0; n],
        };
        let (sigma_u, sigma_v) = (
            template_width * SIGMA_FRACTION,
            template_height * SIGMA_FRACTION,
        );
        for truth in truths {
            let (s, c) = truth.angle_deg.to_radians().sin_cos();
            let (sx, sy) = (truth.scale_x.max(1e-3), truth.scale_y.max(1e-3));
            // A = [[sx·c, sy·s], [−sx·s, sy·c]]; det = sx·sy; A⁻¹ = [[c/sx, −s/sx], [s/sy, c/sy]].
            let reach = 3.5 * sigma_u.max(sigma_v) * sx.max(sy);
            let x0 = (truth.x - reach).floor().max(0.0) as usize;
            let y0 = (truth.y - reach).floor().max(0.0) as usize;
            let x1 = ((truth.x + reach).ceil() as usize).min(width.saturating_sub(1));
            let y1 = ((truth.y + reach).ceil() as usize).min(height.saturating_sub(1));
            for y in y0..=y1 {
                for x in x0..=x1 {
                    let (dx, dy) = (x as f32 - truth.x, y as f32 - truth.y);
                    let u = (c * dx - s * dy) / sx;
                    let v = (s * dx + c * dy) / sy;
                    let g = (-0.5 * ((u / sigma_u).powi(2) + (v / sigma_v).powi(2))).exp();
                    let i = y * width + x;
                    if g > maps.heatmap[i] {
                        maps.heatmap[i] = g;
                        if g >= VALID_THRESHOLD {
                            maps.valid[i] = 1.0;
                            maps.sign[i] = if truth.angle_deg > 0.0 { 1.0 } else { 0.0 };
                            maps.cos[i] = c;
                            maps.scale_x[i] = truth.scale_x;
                            maps.scale_y[i] = truth.scale_y;
                        }
                    }
                }
            }
        }
        maps
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pose(x: f32, y: f32, angle_deg: f32, scale_x: f32, scale_y: f32) -> Pose {
        Pose {
            x,
            y,
            angle_deg,
            scale_x,
            scale_y,
            score: 1.0,
            network_score: 0.0,
        }
    }

    #[test]
    fn peak_at_the_centre_and_parameters_in_the_valid_region() {
        let truth = pose(20.0, 30.0, -120.0, 1.3, 0.8);
        let maps = LabelMaps::render(64, 64, &[truth], 36.0, 36.0);
        assert_eq!(maps.heatmap[30 * 64 + 20], 1.0);
        let valid: usize = maps.valid.iter().map(|&v| v as usize).sum();
        assert!(valid > 20, "{valid} valid pixels");
        for i in 0..64 * 64 {
            if maps.valid[i] == 1.0 {
                assert!(maps.heatmap[i] >= 0.5);
                assert_eq!(maps.sign[i], 0.0);
                assert!((maps.cos[i] - (-0.5)).abs() < 1e-6);
                assert_eq!((maps.scale_x[i], maps.scale_y[i]), (1.3, 0.8));
            } else {
                assert!(maps.heatmap[i] < 0.5);
                assert_eq!(maps.cos[i], 0.0);
            }
        }
    }

    #[test]
    fn the_ellipse_follows_the_object_axes() {
        // sx = 2, sy = 1: the object is twice as wide as tall along its own x axis. Rotated by
        // +90° (counter-clockwise on screen), its x axis points up, so the heatmap is long in y.
        let truth = pose(32.0, 32.0, 90.0, 2.0, 1.0);
        let maps = LabelMaps::render(64, 64, &[truth], 36.0, 36.0);
        let at = |x: usize, y: usize| maps.heatmap[y * 64 + x];
        // σ_u = 6 template px → 12 image px along the object's x axis (image y); σ_v → 6 px.
        let along_y = at(32, 44);
        let along_x = at(44, 32);
        assert!((along_y - (-0.5f32).exp()).abs() < 1e-3, "{along_y}");
        assert!((along_x - (-0.5f32 * 4.0).exp()).abs() < 1e-3, "{along_x}");
        assert_eq!(maps.sign[32 * 64 + 32], 1.0);
    }

    #[test]
    fn nearer_instance_owns_each_pixel() {
        let a = pose(10.0, 10.0, 30.0, 1.0, 1.0);
        let b = pose(50.0, 50.0, -60.0, 1.5, 1.5);
        let maps = LabelMaps::render(64, 64, &[a, b], 36.0, 36.0);
        assert!((maps.cos[10 * 64 + 10] - 30f32.to_radians().cos()).abs() < 1e-6);
        assert_eq!(maps.scale_x[50 * 64 + 50], 1.5);
    }
}
