//! World units: the map from image pixels to a plane in the world (millimetres on a conveyor),
//! fitted from points whose image and world positions an integrator measured — what Halcon's
//! `image_points_to_world_plane`, Cognex's N-point calibration and Matrox's calibrated matching
//! give their users, so that a robot or PLC gets millimetres without writing the maths itself.
//!
//! Three points fix an affine map (exact at the points); four or more a homography, fitted by
//! least squares on Hartley-normalised coordinates, which also covers a camera that looks at
//! the plane at an angle. The fit's RMS residual tells the integrator how well the points
//! agree. "Calibration" here always means this map; the score's calibration table
//! (`evaluation::calibration`) is another thing.

use serde::{Deserialize, Serialize};

use crate::geometry::{Pose, TemplateFrame, wrap_angle_deg};

/// Fewest and most points a calibration takes.
pub const MIN_POINTS: usize = 3;
pub const MAX_POINTS: usize = 1000;
/// Longest unit name, in characters.
pub const MAX_UNIT_CHARS: usize = 16;

/// One measured correspondence: an image point (pixels; the centre of the top-left pixel is
/// (0, 0)) and where it lies on the world plane.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct CalibrationPoint {
    pub image: [f64; 2],
    pub world: [f64; 2],
}

/// What a calibration file holds (`--calibration FILE.json`) and a registration sends.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CalibrationSpec {
    pub points: Vec<CalibrationPoint>,
    pub unit: String,
}

/// Which map the points determine.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum WorldModel {
    Affine,
    Homography,
}

/// A fitted image-to-world map.
#[derive(Debug, Clone, PartialEq)]
pub struct WorldCalibration {
    spec: CalibrationSpec,
    model: WorldModel,
    /// Row-major 3x3 (the last row is 0 0 1 for an affine map).
    matrix: [f64; 9],
    rms_residual: f64,
}

/// Where a pose's reference point lies in the world, and which way the part faces there.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WorldPlacement {
    pub x: f64,
    pub y: f64,
    /// The template's u axis (its rows, left to right) in the world plane: degrees from the
    /// world X axis towards the world Y axis, (−180, 180].
    pub angle_deg: f32,
}

/// Why points do not make a calibration.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CalibrationError {
    #[error("a calibration needs {MIN_POINTS} to {MAX_POINTS} points; {0} given")]
    PointCount(usize),
    #[error("point {index}: its coordinates must be finite numbers")]
    NotFinite { index: usize },
    #[error(
        "points {first} and {second} have the same {plane} position: each point must be measured at its own place"
    )]
    Duplicated {
        first: usize,
        second: usize,
        plane: &'static str,
    },
    #[error(
        "the {plane} points lie on one line: spread them over the field of view (three points that are not in a row at least)"
    )]
    Collinear { plane: &'static str },
    #[error(
        "the points do not determine a homography (too many of them lie on one line, or they are mirrored against each other): spread four or more over the field of view"
    )]
    Degenerate,
    #[error("the unit must be 1..={MAX_UNIT_CHARS} printable characters, e.g. \"mm\"")]
    Unit,
    #[error("calibration file: {0}")]
    Format(String),
}

impl WorldCalibration {
    /// Fits the map: 3 points affine, ≥ 4 a homography.
    pub fn fit(spec: CalibrationSpec) -> Result<Self, CalibrationError> {
        let unit = spec.unit.trim();
        if unit.is_empty()
            || unit.chars().count() > MAX_UNIT_CHARS
            || unit.chars().any(char::is_control)
        {
            return Err(CalibrationError::Unit);
        }
        let points = &spec.points;
        if !(MIN_POINTS..=MAX_POINTS).contains(&points.len()) {
            return Err(CalibrationError::PointCount(points.len()));
        }
        for (index, p) in points.iter().enumerate() {
            if !p.image.iter().chain(&p.world).all(|v| v.is_finite()) {
                return Err(CalibrationError::NotFinite { index });
            }
        }
        let image: Vec<[f64; 2]> = points.iter().map(|p| p.image).collect();
        let world: Vec<[f64; 2]> = points.iter().map(|p| p.world).collect();
        for (plane, set) in [("image", &image), ("world", &world)] {
            check_distinct(set, plane)?;
            check_not_collinear(set, plane)?;
        }
        let (model, matrix) = if points.len() == 3 {
            (WorldModel::Affine, fit_affine(&image, &world)?)
        } else {
            (WorldModel::Homography, fit_homography(&image, &world)?)
        };
        let mut calibration = Self {
            spec: CalibrationSpec {
                points: spec.points.clone(),
                unit: unit.to_owned(),
            },
            model,
            matrix,
            rms_residual: 0.0,
        };
        let squared: f64 = points
            .iter()
            .map(|p| {
                let (x, y) = calibration.to_world(p.image[0], p.image[1]);
                (x - p.world[0]).powi(2) + (y - p.world[1]).powi(2)
            })
            .sum();
        calibration.rms_residual = (squared / points.len() as f64).sqrt();
        // A homography that sends part of the measured area to infinity (or mirrors it) is no
        // camera's view of a plane.
        if model == WorldModel::Homography {
            let signs: Vec<bool> = image
                .iter()
                .map(|p| calibration.denominator(p[0], p[1]) > 0.0)
                .collect();
            if signs.iter().any(|&s| s != signs[0]) {
                return Err(CalibrationError::Degenerate);
            }
        }
        Ok(calibration)
    }

    /// Parses and fits a calibration file: `{"points": [{"image": [x, y], "world": [X, Y]},
    /// …], "unit": "mm"}`.
    pub fn from_json(text: &str) -> Result<Self, CalibrationError> {
        let spec: CalibrationSpec =
            serde_json::from_str(text).map_err(|e| CalibrationError::Format(e.to_string()))?;
        Self::fit(spec)
    }

    pub fn spec(&self) -> &CalibrationSpec {
        &self.spec
    }

    pub fn unit(&self) -> &str {
        &self.spec.unit
    }

    pub fn model(&self) -> WorldModel {
        self.model
    }

    /// Root mean square distance, in world units, between the points' world positions and
    /// where the map puts their image positions.
    pub fn rms_residual(&self) -> f64 {
        self.rms_residual
    }

    fn denominator(&self, x: f64, y: f64) -> f64 {
        let m = &self.matrix;
        m[6] * x + m[7] * y + m[8]
    }

    /// The world position of image point `(x, y)`.
    pub fn to_world(&self, x: f64, y: f64) -> (f64, f64) {
        let m = &self.matrix;
        let w = self.denominator(x, y);
        (
            (m[0] * x + m[1] * y + m[2]) / w,
            (m[3] * x + m[4] * y + m[5]) / w,
        )
    }

    /// Where `pose`'s reference point (the template's origin, else its centre) lies in the
    /// world, and the world direction of the template's u axis there.
    pub fn place(&self, pose: &Pose, template: &TemplateFrame) -> WorldPlacement {
        let (px, py) = template.origin_in_image(pose);
        let (px, py) = (px as f64, py as f64);
        let (x, y) = self.to_world(px, py);
        // The template's u axis in the image: (cos a, −sin a) (the pose convention); mapped
        // through the map's derivative at the point.
        let a = (pose.angle_deg as f64).to_radians();
        let (du, dv) = (a.cos(), -a.sin());
        let m = &self.matrix;
        let w = self.denominator(px, py);
        let jacobian = [
            (m[0] - x * m[6]) / w,
            (m[1] - x * m[7]) / w,
            (m[3] - y * m[6]) / w,
            (m[4] - y * m[7]) / w,
        ];
        let dx = jacobian[0] * du + jacobian[1] * dv;
        let dy = jacobian[2] * du + jacobian[3] * dv;
        WorldPlacement {
            x,
            y,
            angle_deg: wrap_angle_deg(dy.atan2(dx).to_degrees() as f32),
        }
    }
}

fn check_distinct(points: &[[f64; 2]], plane: &'static str) -> Result<(), CalibrationError> {
    let spread = extent(points).max(1.0);
    for (first, a) in points.iter().enumerate() {
        for (offset, b) in points[first + 1..].iter().enumerate() {
            if (a[0] - b[0]).hypot(a[1] - b[1]) <= 1e-9 * spread {
                return Err(CalibrationError::Duplicated {
                    first,
                    second: first + 1 + offset,
                    plane,
                });
            }
        }
    }
    Ok(())
}

fn extent(points: &[[f64; 2]]) -> f64 {
    let (mut lo, mut hi) = ([f64::MAX; 2], [f64::MIN; 2]);
    for p in points {
        for k in 0..2 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
    }
    (hi[0] - lo[0]).max(hi[1] - lo[1])
}

/// The points' spread across their best-fitting line must be more than a millionth of their
/// spread along it.
fn check_not_collinear(points: &[[f64; 2]], plane: &'static str) -> Result<(), CalibrationError> {
    let n = points.len() as f64;
    let (mx, my) = (
        points.iter().map(|p| p[0]).sum::<f64>() / n,
        points.iter().map(|p| p[1]).sum::<f64>() / n,
    );
    let (mut sxx, mut sxy, mut syy) = (0.0, 0.0, 0.0);
    for p in points {
        let (dx, dy) = (p[0] - mx, p[1] - my);
        sxx += dx * dx;
        sxy += dx * dy;
        syy += dy * dy;
    }
    let mean = (sxx + syy) / 2.0;
    let root = (((sxx - syy) / 2.0).powi(2) + sxy * sxy).sqrt();
    let (large, small) = (mean + root, (mean - root).max(0.0));
    if large <= 0.0 || small.sqrt() <= 1e-6 * large.sqrt() {
        return Err(CalibrationError::Collinear { plane });
    }
    Ok(())
}

/// The affine map through three (non-collinear) correspondences, as a 3x3 matrix.
fn fit_affine(image: &[[f64; 2]], world: &[[f64; 2]]) -> Result<[f64; 9], CalibrationError> {
    // Rows [x y 1] · [a b c]ᵀ = X (and likewise for Y), least squares by normal equations.
    let mut ata = [0.0; 9];
    let (mut atx, mut aty) = ([0.0; 3], [0.0; 3]);
    for (p, w) in image.iter().zip(world) {
        let row = [p[0], p[1], 1.0];
        for i in 0..3 {
            for j in 0..3 {
                ata[i * 3 + j] += row[i] * row[j];
            }
            atx[i] += row[i] * w[0];
            aty[i] += row[i] * w[1];
        }
    }
    let abc =
        solve(ata.to_vec(), atx.to_vec()).ok_or(CalibrationError::Collinear { plane: "image" })?;
    let def =
        solve(ata.to_vec(), aty.to_vec()).ok_or(CalibrationError::Collinear { plane: "image" })?;
    Ok([
        abc[0], abc[1], abc[2], def[0], def[1], def[2], 0.0, 0.0, 1.0,
    ])
}

/// Hartley normalisation: moves the points' centroid to 0 and their mean distance to √2.
fn normalisation(points: &[[f64; 2]]) -> [f64; 9] {
    let n = points.len() as f64;
    let (mx, my) = (
        points.iter().map(|p| p[0]).sum::<f64>() / n,
        points.iter().map(|p| p[1]).sum::<f64>() / n,
    );
    let mean_distance = points
        .iter()
        .map(|p| (p[0] - mx).hypot(p[1] - my))
        .sum::<f64>()
        / n;
    let s = std::f64::consts::SQRT_2 / mean_distance;
    [s, 0.0, -s * mx, 0.0, s, -s * my, 0.0, 0.0, 1.0]
}

fn apply(m: &[f64; 9], p: [f64; 2]) -> [f64; 2] {
    let w = m[6] * p[0] + m[7] * p[1] + m[8];
    [
        (m[0] * p[0] + m[1] * p[1] + m[2]) / w,
        (m[3] * p[0] + m[4] * p[1] + m[5]) / w,
    ]
}

fn multiply(a: &[f64; 9], b: &[f64; 9]) -> [f64; 9] {
    let mut out = [0.0; 9];
    for i in 0..3 {
        for j in 0..3 {
            out[i * 3 + j] = (0..3).map(|k| a[i * 3 + k] * b[k * 3 + j]).sum();
        }
    }
    out
}

/// The inverse of a similarity normalisation (`s, 0, tx; 0, s, ty; 0, 0, 1`).
fn invert_normalisation(m: &[f64; 9]) -> [f64; 9] {
    let s = m[0];
    [
        1.0 / s,
        0.0,
        -m[2] / s,
        0.0,
        1.0 / s,
        -m[5] / s,
        0.0,
        0.0,
        1.0,
    ]
}

/// The homography taking `image` to `world`, least squares with h₃₃ = 1 on normalised
/// coordinates (which keeps h₃₃ far from 0 for any view of a plane).
fn fit_homography(image: &[[f64; 2]], world: &[[f64; 2]]) -> Result<[f64; 9], CalibrationError> {
    let (ni, nw) = (normalisation(image), normalisation(world));
    let mut ata = [0.0; 64];
    let mut atb = [0.0; 8];
    for (p, q) in image.iter().zip(world) {
        let [x, y] = apply(&ni, *p);
        let [u, v] = apply(&nw, *q);
        let rows = [
            ([x, y, 1.0, 0.0, 0.0, 0.0, -u * x, -u * y], u),
            ([0.0, 0.0, 0.0, x, y, 1.0, -v * x, -v * y], v),
        ];
        for (row, b) in rows {
            for i in 0..8 {
                for j in 0..8 {
                    ata[i * 8 + j] += row[i] * row[j];
                }
                atb[i] += row[i] * b;
            }
        }
    }
    let h = solve(ata.to_vec(), atb.to_vec()).ok_or(CalibrationError::Degenerate)?;
    let normalised = [h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7], 1.0];
    let m = multiply(&invert_normalisation(&nw), &multiply(&normalised, &ni));
    if !m.iter().all(|v| v.is_finite()) || m[8].abs() < f64::EPSILON {
        return Err(CalibrationError::Degenerate);
    }
    Ok(m.map(|v| v / m[8]))
}

/// Solves the `n x n` system `a · x = b` (`a` row-major) by Gaussian elimination with partial
/// pivoting; `None` when it is singular or nearly so.
fn solve(mut a: Vec<f64>, mut b: Vec<f64>) -> Option<Vec<f64>> {
    let n = b.len();
    debug_assert_eq!(a.len(), n * n);
    let scale = a.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    if scale == 0.0 {
        return None;
    }
    for col in 0..n {
        let pivot =
            (col..n).max_by(|&i, &j| a[i * n + col].abs().total_cmp(&a[j * n + col].abs()))?;
        if a[pivot * n + col].abs() <= 1e-12 * scale {
            return None;
        }
        if pivot != col {
            for k in 0..n {
                a.swap(pivot * n + k, col * n + k);
            }
            b.swap(pivot, col);
        }
        for row in col + 1..n {
            let factor = a[row * n + col] / a[col * n + col];
            for k in col..n {
                a[row * n + k] -= factor * a[col * n + k];
            }
            b[row] -= factor * b[col];
        }
    }
    let mut x = vec![0.0; n];
    for row in (0..n).rev() {
        let rest: f64 = (row + 1..n).map(|k| a[row * n + k] * x[k]).sum();
        x[row] = (b[row] - rest) / a[row * n + row];
    }
    x.iter().all(|v| v.is_finite()).then_some(x)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec(points: &[([f64; 2], [f64; 2])]) -> CalibrationSpec {
        CalibrationSpec {
            points: points
                .iter()
                .map(|&(image, world)| CalibrationPoint { image, world })
                .collect(),
            unit: "mm".into(),
        }
    }

    /// A camera looking at a plane at an angle: an exact homography.
    const VIEW: [f64; 9] = [0.21, 0.03, -12.0, -0.02, 0.19, 40.0, 0.0001, -0.00005, 1.0];

    fn view(p: [f64; 2]) -> [f64; 2] {
        apply(&VIEW, p)
    }

    #[test]
    fn three_points_give_the_affine_map_exactly() {
        // 0.1 mm per pixel, turned by 30 degrees, shifted.
        let (s, c) = 30f64.to_radians().sin_cos();
        let map = |p: [f64; 2]| {
            [
                0.1 * (c * p[0] - s * p[1]) + 5.0,
                0.1 * (s * p[0] + c * p[1]) - 2.0,
            ]
        };
        let image = [[10.0, 20.0], [600.0, 35.0], [200.0, 470.0]];
        let calibration =
            WorldCalibration::fit(spec(&image.map(|p| (p, map(p))))).expect("three good points");
        assert_eq!(calibration.model(), WorldModel::Affine);
        assert!(calibration.rms_residual() < 1e-9);
        let (x, y) = calibration.to_world(321.5, 123.25);
        let [ex, ey] = map([321.5, 123.25]);
        assert!((x - ex).abs() < 1e-9 && (y - ey).abs() < 1e-9, "{x} {y}");
    }

    #[test]
    fn four_or_more_points_give_the_homography_and_its_residual() {
        let image = [
            [0.0, 0.0],
            [1000.0, 10.0],
            [990.0, 760.0],
            [20.0, 740.0],
            [500.0, 380.0],
            [250.0, 600.0],
        ];
        let calibration = WorldCalibration::fit(spec(&image.map(|p| (p, view(p))))).unwrap();
        assert_eq!(calibration.model(), WorldModel::Homography);
        assert!(
            calibration.rms_residual() < 1e-9,
            "{}",
            calibration.rms_residual()
        );
        for p in [[123.0, 456.0], [900.0, 100.0]] {
            let (x, y) = calibration.to_world(p[0], p[1]);
            let [ex, ey] = view(p);
            assert!((x - ex).abs() < 1e-6 && (y - ey).abs() < 1e-6);
        }
        // A point measured 0.5 units off: a residual the integrator can see.
        let mut noisy = spec(&image.map(|p| (p, view(p))));
        noisy.points[4].world[0] += 0.5;
        let rms = WorldCalibration::fit(noisy).unwrap().rms_residual();
        assert!(rms > 0.05 && rms < 0.5, "{rms}");
    }

    #[test]
    fn a_pose_is_placed_at_its_reference_point_with_its_world_direction() {
        // World = image pixels times 0.1 with Y up (world Y = −0.1·y): a counter-clockwise
        // turn on screen is a counter-clockwise turn in the world.
        let image = [[0.0, 0.0], [100.0, 0.0], [0.0, 100.0]];
        let calibration =
            WorldCalibration::fit(spec(&image.map(|p| (p, [0.1 * p[0], -0.1 * p[1]])))).unwrap();
        let pose = Pose {
            x: 50.0,
            y: 40.0,
            angle_deg: 30.0,
            scale_x: 1.0,
            scale_y: 1.0,
            score: 1.0,
            network_score: 0.0,
        };
        let centred = TemplateFrame::new(21, 11, None);
        let placed = calibration.place(&pose, &centred);
        assert!((placed.x - 5.0).abs() < 1e-6 && (placed.y + 4.0).abs() < 1e-6);
        assert!(
            (placed.angle_deg - 30.0).abs() < 1e-4,
            "{}",
            placed.angle_deg
        );
        // An origin at the template's right edge, middle row: 10 px along the turned u axis.
        let origin = crate::geometry::TemplateOrigin::new(20.0, 5.0, 21, 11).unwrap();
        let placed = calibration.place(&pose, &TemplateFrame::new(21, 11, Some(origin)));
        let (ox, oy) = pose.map_point(10.0, 0.0);
        assert!((placed.x - 0.1 * ox as f64).abs() < 1e-5);
        assert!((placed.y + 0.1 * oy as f64).abs() < 1e-5);
    }

    #[test]
    fn bad_points_are_refused_with_what_to_fix() {
        let line = [[0.0, 0.0], [10.0, 10.0], [20.0, 20.0], [35.0, 35.0]];
        assert_eq!(
            WorldCalibration::fit(spec(&line.map(|p| (p, view(p))))),
            Err(CalibrationError::Collinear { plane: "image" })
        );
        let twice = [[0.0, 0.0], [100.0, 0.0], [0.0, 100.0], [100.0, 0.0]];
        assert!(matches!(
            WorldCalibration::fit(spec(&twice.map(|p| (p, view(p))))),
            Err(CalibrationError::Duplicated {
                first: 1,
                second: 3,
                plane: "image"
            })
        ));
        let two = [[0.0, 0.0], [100.0, 0.0]];
        assert_eq!(
            WorldCalibration::fit(spec(&two.map(|p| (p, p)))),
            Err(CalibrationError::PointCount(2))
        );
        let mut nan = spec(&[[0.0, 0.0], [100.0, 0.0], [0.0, 100.0]].map(|p| (p, p)));
        nan.points[2].world[1] = f64::NAN;
        assert_eq!(
            WorldCalibration::fit(nan),
            Err(CalibrationError::NotFinite { index: 2 })
        );
        let mut no_unit = spec(&[[0.0, 0.0], [100.0, 0.0], [0.0, 100.0]].map(|p| (p, p)));
        no_unit.unit = " ".into();
        assert_eq!(WorldCalibration::fit(no_unit), Err(CalibrationError::Unit));
        // Three in a row of four: no homography through them and a fourth point.
        let three_in_a_row = [[0.0, 0.0], [50.0, 0.0], [100.0, 0.0], [50.0, 80.0]];
        assert!(WorldCalibration::fit(spec(&three_in_a_row.map(|p| (p, view(p))))).is_err());
        assert!(matches!(
            WorldCalibration::from_json(r#"{"points": [], "unit": "mm", "extra": 1}"#),
            Err(CalibrationError::Format(_))
        ));
    }
}
