//! The public pose convention and the rotated-box maths built on it.
//!
//! A template pixel offset `(u, v)` from the template centre (u right, v down) maps to the image
//! point `(x + sx·u·cos a + sy·v·sin a, y − sx·u·sin a + sy·v·cos a)`. Positive `a` turns
//! counter-clockwise on screen, range (−180°, 180°]. `scale_x` = object width in the image /
//! registered template width. The centre of the top-left pixel is (0, 0).

use serde::{Deserialize, Serialize};

/// One found instance.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    pub x: f32,
    pub y: f32,
    pub angle_deg: f32,
    pub scale_x: f32,
    pub scale_y: f32,
    /// How well the template matches the image at this pose, in [0, 1]: the verified similarity
    /// (ZNCC over the template at the refined pose, negative values as 0; at least 0.9 where the
    /// answer stands out from the image's other places, docs/accuracy.md "What a score
    /// means"), or the network's heatmap value where nothing verified it (`no_refine`).
    pub score: f32,
    /// The network's heatmap value at the instance's peak (0 where no network was involved).
    #[serde(default)]
    pub network_score: f32,
}

impl Pose {
    /// An upright pose at scale 1 with `score` and no heatmap value (tests).
    #[cfg(test)]
    pub fn upright(x: f32, y: f32, score: f32) -> Self {
        Self {
            x,
            y,
            angle_deg: 0.0,
            scale_x: 1.0,
            scale_y: 1.0,
            score,
            network_score: 0.0,
        }
    }

    /// Image position of template offset `(u, v)` (template pixels from its centre).
    pub fn map_point(&self, u: f32, v: f32) -> (f32, f32) {
        let (s, c) = self.angle_deg.to_radians().sin_cos();
        (
            self.x + self.scale_x * u * c + self.scale_y * v * s,
            self.y - self.scale_x * u * s + self.scale_y * v * c,
        )
    }

    /// The 2x3 affine map `[a, b, c, d, e, f]` from template pixel coordinates (column, row;
    /// the centre of the top-left template pixel is (0, 0)) of a `template_width x
    /// template_height` template to image coordinates under this pose: `x' = a·col + b·row + c`,
    /// `y' = d·col + e·row + f` (OpenCV's `warpAffine` matrix, row-major). Exactly
    /// [`Pose::map_point`] with `(u, v)` the offset from the template centre.
    pub fn transform(&self, template_width: f32, template_height: f32) -> [f32; 6] {
        let (s, c) = self.angle_deg.to_radians().sin_cos();
        let (a, b) = (self.scale_x * c, self.scale_y * s);
        let (d, e) = (-self.scale_x * s, self.scale_y * c);
        let (cx, cy) = ((template_width - 1.0) / 2.0, (template_height - 1.0) / 2.0);
        [
            a,
            b,
            self.x - a * cx - b * cy,
            d,
            e,
            self.y - d * cx - e * cy,
        ]
    }

    /// The four image corners of a `template_width x template_height` template placed at this
    /// pose: top-left, top-right, bottom-right, bottom-left (in template orientation).
    pub fn corners(&self, template_width: f32, template_height: f32) -> [(f32, f32); 4] {
        let (hw, hh) = (template_width / 2.0, template_height / 2.0);
        [
            self.map_point(-hw, -hh),
            self.map_point(hw, -hh),
            self.map_point(hw, hh),
            self.map_point(-hw, hh),
        ]
    }
}

/// A template's reference point (Halcon's `set_shape_model_origin`, Matrox's reference
/// origin): where a robot grips or a PLC measures, in template pixel coordinates (column, row;
/// the centre of the top-left pixel is (0, 0)). Each pose reports where it lands (`origin_x`,
/// `origin_y`); `x`, `y` stay the template centre, the public contract. It may lie outside the
/// template (a gripping point beside the part), up to [`TemplateOrigin::REACH`] template sizes
/// beyond its edges.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TemplateOrigin {
    pub x: f32,
    pub y: f32,
}

impl TemplateOrigin {
    /// How far outside the template, in template widths (heights), an origin may lie.
    pub const REACH: f32 = 3.0;

    /// Checks that `(x, y)` is finite and within [`Self::REACH`] of a `width x height` template.
    pub fn new(x: f32, y: f32, width: u32, height: u32) -> Result<Self, String> {
        let (w, h) = (width as f32, height as f32);
        let within = |v: f32, size: f32| {
            v.is_finite() && v >= -Self::REACH * size - 0.5 && v <= (Self::REACH + 1.0) * size - 0.5
        };
        if within(x, w) && within(y, h) {
            Ok(Self { x, y })
        } else {
            Err(format!(
                "the template origin ({x}, {y}) is not a point of the {width}x{height} template or near it: give template pixel coordinates (column, row; the top-left pixel's centre is 0,0), at most {} template sizes outside it",
                Self::REACH
            ))
        }
    }

    /// The template centre, where a template without an origin is measured from.
    pub fn centre(width: u32, height: u32) -> Self {
        Self {
            x: (width as f32 - 1.0) / 2.0,
            y: (height as f32 - 1.0) / 2.0,
        }
    }
}

/// A registered template's geometry as poses are reported against it: its size (the reference
/// of the scales and of [`Pose::transform`]) and its reference point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TemplateFrame {
    pub width: u32,
    pub height: u32,
    /// The registered origin, or `None` for the template centre.
    pub origin: Option<TemplateOrigin>,
}

impl TemplateFrame {
    pub fn new(width: u32, height: u32, origin: Option<TemplateOrigin>) -> Self {
        Self {
            width,
            height,
            origin,
        }
    }

    /// The reference point: the registered origin or the centre.
    pub fn reference_point(&self) -> TemplateOrigin {
        self.origin
            .unwrap_or_else(|| TemplateOrigin::centre(self.width, self.height))
    }

    /// Where the reference point lands in the image under `pose`.
    pub fn origin_in_image(&self, pose: &Pose) -> (f32, f32) {
        let centre = TemplateOrigin::centre(self.width, self.height);
        let point = self.reference_point();
        pose.map_point(point.x - centre.x, point.y - centre.y)
    }

    /// [`Pose::transform`] for this template.
    pub fn transform(&self, pose: &Pose) -> [f32; 6] {
        pose.transform(self.width as f32, self.height as f32)
    }
}

/// Wraps any angle in degrees into (−180, 180].
pub fn wrap_angle_deg(angle: f32) -> f32 {
    let mut a = angle % 360.0;
    if a <= -180.0 {
        a += 360.0;
    } else if a > 180.0 {
        a -= 360.0;
    }
    a
}

/// Smallest absolute difference between two angles, in [0, 180].
pub fn angle_distance_deg(a: f32, b: f32) -> f32 {
    wrap_angle_deg(a - b).abs()
}

/// Area of a simple polygon (shoelace), positive for either orientation.
pub fn polygon_area(points: &[(f32, f32)]) -> f32 {
    let n = points.len();
    let twice: f32 = (0..n)
        .map(|i| {
            let (x0, y0) = points[i];
            let (x1, y1) = points[(i + 1) % n];
            x0 * y1 - x1 * y0
        })
        .sum();
    twice.abs() / 2.0
}

/// Intersection of two convex polygons (Sutherland–Hodgman).
pub fn convex_intersection(subject: &[(f32, f32)], clip: &[(f32, f32)]) -> Vec<(f32, f32)> {
    // Orient the clip polygon counter-clockwise in maths coordinates so "inside" is to the left.
    let signed: f32 = (0..clip.len())
        .map(|i| {
            let (x0, y0) = clip[i];
            let (x1, y1) = clip[(i + 1) % clip.len()];
            x0 * y1 - x1 * y0
        })
        .sum();
    let mut clip = clip.to_vec();
    if signed < 0.0 {
        clip.reverse();
    }
    let mut output = subject.to_vec();
    for i in 0..clip.len() {
        if output.is_empty() {
            break;
        }
        let a = clip[i];
        let b = clip[(i + 1) % clip.len()];
        let side = |p: (f32, f32)| (b.0 - a.0) * (p.1 - a.1) - (b.1 - a.1) * (p.0 - a.0);
        let input = std::mem::take(&mut output);
        for j in 0..input.len() {
            let p = input[j];
            let q = input[(j + 1) % input.len()];
            let (sp, sq) = (side(p), side(q));
            if sp >= 0.0 {
                output.push(p);
            }
            if (sp >= 0.0) != (sq >= 0.0) {
                let t = sp / (sp - sq);
                output.push((p.0 + t * (q.0 - p.0), p.1 + t * (q.1 - p.1)));
            }
        }
    }
    output
}

/// Intersection over union of two convex quadrilaterals (rotated boxes).
pub fn rotated_iou(a: &[(f32, f32); 4], b: &[(f32, f32); 4]) -> f32 {
    let area_a = polygon_area(a);
    let area_b = polygon_area(b);
    if area_a <= 0.0 || area_b <= 0.0 {
        return 0.0;
    }
    let inter = polygon_area(&convex_intersection(a, b));
    let union = area_a + area_b - inter;
    if union <= 0.0 { 0.0 } else { inter / union }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_transform_maps_template_pixels_as_the_pose_convention_does() {
        let p = pose(40.5, -3.25, 33.0, 1.3, 0.7);
        let (tw, th) = (36.0, 20.0);
        let [a, b, c, d, e, f] = p.transform(tw, th);
        for (col, row) in [(0.0, 0.0), (35.0, 19.0), (17.5, 9.5), (3.0, 14.0)] {
            let (u, v) = (col - (tw - 1.0) / 2.0, row - (th - 1.0) / 2.0);
            let (x, y) = p.map_point(u, v);
            assert!((a * col + b * row + c - x).abs() < 1e-4);
            assert!((d * col + e * row + f - y).abs() < 1e-4);
        }
    }

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
    fn positive_angle_turns_counter_clockwise_on_screen() {
        // The template's "right" (u = 1) must point up on screen (y decreases) at +90°.
        let (x, y) = pose(10.0, 10.0, 90.0, 1.0, 1.0).map_point(1.0, 0.0);
        assert!((x - 10.0).abs() < 1e-5 && (y - 9.0).abs() < 1e-5, "{x} {y}");
    }

    #[test]
    fn scales_apply_along_template_axes() {
        let (x, y) = pose(0.0, 0.0, 0.0, 2.0, 3.0).map_point(1.0, 1.0);
        assert_eq!((x, y), (2.0, 3.0));
    }

    #[test]
    fn wrap_covers_both_ends() {
        assert_eq!(wrap_angle_deg(180.0), 180.0);
        assert_eq!(wrap_angle_deg(-180.0), 180.0);
        assert_eq!(wrap_angle_deg(190.0), -170.0);
        assert_eq!(wrap_angle_deg(-190.0), 170.0);
        assert_eq!(wrap_angle_deg(720.0 + 45.0), 45.0);
        assert!((angle_distance_deg(179.0, -179.0) - 2.0).abs() < 1e-4);
    }

    #[test]
    fn iou_of_hand_computed_boxes() {
        // Two axis-aligned 2x2 squares shifted by 1: intersection 2, union 6.
        let a = pose(0.0, 0.0, 0.0, 1.0, 1.0).corners(2.0, 2.0);
        let b = pose(1.0, 0.0, 0.0, 1.0, 1.0).corners(2.0, 2.0);
        assert!((rotated_iou(&a, &b) - 2.0 / 6.0).abs() < 1e-5);
        // A 2x2 square and itself turned by 45°: the octagon has area 8(√2 − 1).
        let c = pose(0.0, 0.0, 45.0, 1.0, 1.0).corners(2.0, 2.0);
        let inter = 8.0 * (2f32.sqrt() - 1.0);
        let expected = inter / (8.0 - inter);
        assert!((rotated_iou(&a, &c) - expected).abs() < 1e-4);
        // Disjoint.
        let d = pose(10.0, 0.0, 30.0, 1.0, 1.0).corners(2.0, 2.0);
        assert_eq!(rotated_iou(&a, &d), 0.0);
    }
}
