//! Continuous alignment of all five pose parameters: Gauss–Newton (Lucas–Kanade) with
//! Levenberg–Marquardt damping on a coarse-to-fine pair of blurred images.
//!
//! Why: a grid search over angle and scales lands within a step of the truth at best, and
//! parabolic fits per parameter ignore how the parameters trade against each other (a wrong
//! centre is partly explained by a wrong angle). Minimising the photometric residual over the
//! five parameters jointly, with the image gradient telling each step where to go, converges to a
//! small fraction of a pixel and degree where the template has structure, in a few iterations of
//! one pass over the template points each. Blurring first widens the basin so that a start a
//! few pixels and degrees off still converges.
//!
//! The residual is `α·I(W(u; p)) + β − T(u)` with the gain `α` and offset `β` re-fitted in closed
//! form every iteration, so minimising it is maximising the zero-mean normalised correlation the
//! rest of the refinement scores with (lighting changes between template and image cost nothing).

use crate::geometry::Pose;
use crate::imaging::{BilinearTap, GrayImage32, gaussian_blur, gradients};

/// A blurred window of the search image with its gradients, in window coordinates.
pub(super) struct GradientWindow {
    x0: f32,
    y0: f32,
    image: GrayImage32,
    gx: Vec<f32>,
    gy: Vec<f32>,
}

impl GradientWindow {
    /// The window of `image` that holds a circle of `radius` around `(cx, cy)`, blurred with a
    /// Gaussian of `sigma` pixels (none when `sigma` is 0), and its central-difference gradients.
    pub(super) fn new(image: &GrayImage32, cx: f32, cy: f32, radius: f32, sigma: f32) -> Self {
        let clamp = |v: f32, hi: usize| (v.floor().max(0.0) as usize).min(hi.saturating_sub(1));
        let (left, right) = (
            clamp(cx - radius, image.width),
            clamp(cx + radius + 1.0, image.width),
        );
        let (top, bottom) = (
            clamp(cy - radius, image.height),
            clamp(cy + radius + 1.0, image.height),
        );
        let (w, h) = (right - left + 1, bottom - top + 1);
        let mut values = Vec::with_capacity(w * h);
        for y in top..=bottom {
            values
                .extend_from_slice(&image.values[y * image.width + left..=y * image.width + right]);
        }
        let window = gaussian_blur(
            &GrayImage32 {
                width: w,
                height: h,
                values,
            },
            sigma,
        );
        let (gx, gy) = gradients(&window);
        Self {
            x0: left as f32,
            y0: top as f32,
            image: window,
            gx,
            gy,
        }
    }

    /// Bilinear tap at image coordinates `(x, y)`, clamped to the window.
    #[inline]
    fn tap(&self, x: f32, y: f32) -> BilinearTap {
        BilinearTap::new(
            self.image.width,
            self.image.height,
            x - self.x0,
            y - self.y0,
        )
    }

    /// Value at image coordinates `(x, y)` (bilinear, clamped to the window).
    #[inline]
    fn value(&self, x: f32, y: f32) -> f32 {
        self.tap(x, y).apply(&self.image.values)
    }

    /// Value and gradient at image coordinates `(x, y)` (bilinear, clamped to the window).
    #[inline]
    fn sample(&self, x: f32, y: f32) -> (f32, f32, f32) {
        let tap = self.tap(x, y);
        (
            tap.apply(&self.image.values),
            tap.apply(&self.gx),
            tap.apply(&self.gy),
        )
    }
}

/// Template points: offsets from the template centre and values, taken from the template
/// blurred to match the window's blur at the expected scale.
pub(super) struct AlignPoints {
    offsets: Vec<(f32, f32)>,
    values: Vec<f32>,
    /// Σ T and Σ (T − mean)², for the closed-form cost.
    sum: f64,
    spread: f64,
}

impl AlignPoints {
    /// Every `stride`-th pixel of `template` blurred by `sigma` template pixels.
    pub(super) fn new(template: &GrayImage32, sigma: f32, max_side: usize) -> Self {
        let (offsets, values) = super::grid_points(&gaussian_blur(template, sigma), max_side);
        let sum: f64 = values.iter().map(|&t| t as f64).sum();
        let mean = sum / values.len().max(1) as f64;
        let spread = values.iter().map(|&t| (t as f64 - mean).powi(2)).sum();
        Self {
            offsets,
            values,
            sum,
            spread,
        }
    }
}

/// Levenberg–Marquardt iterations of the five parameters from `start`; returns the pose with
/// the lowest normalised residual found (never worse than `start`).
pub(super) fn align(
    points: &AlignPoints,
    window: &GradientWindow,
    start: &Pose,
    iterations: usize,
) -> Pose {
    let mut pose = *start;
    let Some(mut cost) = residual_cost(points, window, &pose) else {
        return pose;
    };
    let mut damping = 1e-3f64;
    for _ in 0..iterations {
        let Some((hessian, gradient)) = normal_equations(points, window, &pose) else {
            break;
        };
        let mut improved = false;
        for _ in 0..6 {
            let mut system = hessian;
            for (k, row) in system.iter_mut().enumerate() {
                row[k] += damping * hessian[k][k].max(1e-9);
            }
            let Some(step) = solve5(system, gradient) else {
                damping *= 10.0;
                continue;
            };
            let candidate = apply(&pose, &step);
            if !(0.05..=20.0).contains(&candidate.scale_x)
                || !(0.05..=20.0).contains(&candidate.scale_y)
            {
                damping *= 10.0;
                continue;
            }
            match residual_cost(points, window, &candidate) {
                Some(c) if c < cost => {
                    let converged = (cost - c) < 1e-5 * cost.max(1e-12);
                    pose = candidate;
                    cost = c;
                    damping = (damping * 0.3).max(1e-7);
                    improved = !converged;
                    break;
                }
                _ => damping *= 10.0,
            }
        }
        if !improved {
            break;
        }
    }
    pose
}

/// Parameter step `[dx, dy, dθ (rad), dsx, dsy]` applied to a pose.
fn apply(pose: &Pose, step: &[f64; 5]) -> Pose {
    Pose {
        x: pose.x - step[0] as f32,
        y: pose.y - step[1] as f32,
        angle_deg: pose.angle_deg - (step[2] as f32).to_degrees(),
        scale_x: pose.scale_x - step[3] as f32,
        scale_y: pose.scale_y - step[4] as f32,
        ..*pose
    }
}

/// Samples the window at every template point under `pose`.
fn sample_all(points: &AlignPoints, window: &GradientWindow, pose: &Pose) -> Vec<(f32, f32, f32)> {
    let (s, c) = pose.angle_deg.to_radians().sin_cos();
    points
        .offsets
        .iter()
        .map(|&(u, v)| {
            window.sample(
                pose.x + pose.scale_x * u * c + pose.scale_y * v * s,
                pose.y - pose.scale_x * u * s + pose.scale_y * v * c,
            )
        })
        .collect()
}

/// Gain and offset `(α, β)` that best map image values onto template values.
fn photometric_fit(points: &AlignPoints, samples: &[(f32, f32, f32)]) -> Option<(f64, f64)> {
    let n = samples.len() as f64;
    let (mut si, mut st, mut sii, mut sit) = (0f64, 0f64, 0f64, 0f64);
    for (&(i, _, _), &t) in samples.iter().zip(&points.values) {
        let (i, t) = (i as f64, t as f64);
        si += i;
        st += t;
        sii += i * i;
        sit += i * t;
    }
    let variance = sii - si * si / n;
    if variance <= 1e-9 {
        return None;
    }
    let alpha = (sit - si * st / n) / variance;
    Some((alpha, (st - alpha * si) / n))
}

/// Residual sum of squares after the photometric fit, relative to the template's variance
/// (`1 − ZNCC²`), or `None` where the image is flat or the match inverted.
fn residual_cost(points: &AlignPoints, window: &GradientWindow, pose: &Pose) -> Option<f64> {
    let (s, c) = pose.angle_deg.to_radians().sin_cos();
    let n = points.values.len() as f64;
    let (mut si, mut sii, mut sit) = (0f64, 0f64, 0f64);
    for (&(u, v), &t) in points.offsets.iter().zip(&points.values) {
        let i = window.value(
            pose.x + pose.scale_x * u * c + pose.scale_y * v * s,
            pose.y - pose.scale_x * u * s + pose.scale_y * v * c,
        ) as f64;
        si += i;
        sii += i * i;
        sit += i * t as f64;
    }
    let variance = sii - si * si / n;
    let covariance = sit - si * points.sum / n;
    if variance <= 1e-9 || covariance <= 0.0 {
        return None;
    }
    // min over α, β of Σ(αI + β − T)² = S_tt − S_it² / S_ii (centred sums).
    Some(1.0 - covariance * covariance / (variance * points.spread.max(1e-12)))
}

type Matrix5 = [[f64; 5]; 5];

/// `JᵀJ` and `Jᵀr` of the residuals at `pose`.
#[allow(clippy::needless_range_loop)] // index form mirrors the matrix algebra
fn normal_equations(
    points: &AlignPoints,
    window: &GradientWindow,
    pose: &Pose,
) -> Option<(Matrix5, [f64; 5])> {
    let samples = sample_all(points, window, pose);
    let (alpha, beta) = photometric_fit(points, &samples)?;
    let (s, c) = pose.angle_deg.to_radians().sin_cos();
    let (s, c) = (s as f64, c as f64);
    let (sx, sy) = (pose.scale_x as f64, pose.scale_y as f64);
    let mut hessian = [[0f64; 5]; 5];
    let mut gradient = [0f64; 5];
    for ((&(u, v), &(i, gx, gy)), &t) in points.offsets.iter().zip(&samples).zip(&points.values) {
        let (u, v, gx, gy) = (u as f64, v as f64, gx as f64 * alpha, gy as f64 * alpha);
        let r = alpha * i as f64 + beta - t as f64;
        // d(x_img, y_img) / d(θ, sx, sy) for x = x0 + sx·u·c + sy·v·s, y = y0 − sx·u·s + sy·v·c.
        let dtheta = (-sx * u * s + sy * v * c, -sx * u * c - sy * v * s);
        let jac = [
            gx,
            gy,
            gx * dtheta.0 + gy * dtheta.1,
            gx * u * c - gy * u * s,
            gx * v * s + gy * v * c,
        ];
        for a in 0..5 {
            gradient[a] += jac[a] * r;
            for b in a..5 {
                hessian[a][b] += jac[a] * jac[b];
            }
        }
    }
    for a in 0..5 {
        for b in 0..a {
            hessian[a][b] = hessian[b][a];
        }
    }
    Some((hessian, gradient))
}

/// Solves the 5x5 system by Gaussian elimination with partial pivoting.
#[allow(clippy::needless_range_loop)] // index form mirrors the matrix algebra
fn solve5(mut m: Matrix5, mut rhs: [f64; 5]) -> Option<[f64; 5]> {
    for col in 0..5 {
        let pivot = (col..5).max_by(|&a, &b| m[a][col].abs().total_cmp(&m[b][col].abs()))?;
        if m[pivot][col].abs() < 1e-12 {
            return None;
        }
        m.swap(col, pivot);
        rhs.swap(col, pivot);
        for row in col + 1..5 {
            let f = m[row][col] / m[col][col];
            for k in col..5 {
                m[row][k] -= f * m[col][k];
            }
            rhs[row] -= f * rhs[col];
        }
    }
    let mut x = [0f64; 5];
    for row in (0..5).rev() {
        let tail: f64 = (row + 1..5).map(|k| m[row][k] * x[k]).sum();
        x[row] = (rhs[row] - tail) / m[row][row];
    }
    x.iter().all(|v| v.is_finite()).then_some(x)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn solves_a_known_system() {
        let m = [
            [4.0, 1.0, 0.0, 0.0, 0.5],
            [1.0, 3.0, 0.2, 0.0, 0.0],
            [0.0, 0.2, 5.0, 1.0, 0.0],
            [0.0, 0.0, 1.0, 2.0, 0.3],
            [0.5, 0.0, 0.0, 0.3, 6.0],
        ];
        let x = [1.0, -2.0, 0.5, 3.0, -1.0];
        let rhs: Vec<f64> = m
            .iter()
            .map(|row| row.iter().zip(&x).map(|(a, b)| a * b).sum())
            .collect();
        let solved = solve5(m, rhs.try_into().unwrap()).unwrap();
        for (a, b) in solved.iter().zip(&x) {
            assert!((a - b).abs() < 1e-9, "{solved:?}");
        }
    }

    #[test]
    fn blur_keeps_a_constant_image_and_its_mass() {
        let flat = GrayImage32 {
            width: 9,
            height: 7,
            values: vec![0.25; 63],
        };
        let blurred = gaussian_blur(&flat, 1.5);
        assert!(blurred.values.iter().all(|v| (v - 0.25).abs() < 1e-6));
    }
}
