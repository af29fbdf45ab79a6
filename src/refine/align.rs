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
//! Under [`Light::Planes`] the gain and the offset are planes over the part instead, fitted the
//! same way: light that changes across the part (`refine/shading.rs`) then pulls the pose no
//! more than even light does.

use multiversion::multiversion;

use super::correlate::{Affine, LANES, LaneTap, PointLanes, fits_lanes};
use crate::geometry::Pose;
use crate::imaging::{BilinearTap, GrayImage32, gaussian_blur, gradients};

/// A blurred window of the search image with its gradients, in window coordinates.
pub(crate) struct GradientWindow {
    x0: f32,
    y0: f32,
    image: GrayImage32,
    gx: Vec<f32>,
    gy: Vec<f32>,
}

impl GradientWindow {
    /// The window of `image` that holds a circle of `radius` around `(cx, cy)`, blurred with a
    /// Gaussian of `sigma` pixels (none when `sigma` is 0), and its central-difference gradients.
    pub(crate) fn new(image: &GrayImage32, cx: f32, cy: f32, radius: f32, sigma: f32) -> Self {
        let (window, x0, y0) = blurred_window(image, cx, cy, radius, sigma);
        let (gx, gy) = gradients(&window);
        Self {
            x0,
            y0,
            image: window,
            gx,
            gy,
        }
    }

    /// The whole of `image`, blurred and with its gradients: one window that serves every
    /// candidate of an image (inside a window's reach the values equal those of
    /// [`GradientWindow::new`], whose margin is the blur's radius).
    pub(crate) fn whole(image: &GrayImage32, sigma: f32) -> Self {
        let (w, h) = (image.width as f32, image.height as f32);
        Self::new(image, 0.5 * w, 0.5 * h, w.max(h) + 1.0, sigma)
    }
}

/// The window of `image` that holds a circle of `radius` around `(cx, cy)`, blurred by a
/// Gaussian of `sigma` pixels, and the image coordinates of its top-left pixel.
pub(crate) fn blurred_window(
    image: &GrayImage32,
    cx: f32,
    cy: f32,
    radius: f32,
    sigma: f32,
) -> (GrayImage32, f32, f32) {
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
        values.extend_from_slice(&image.values[y * image.width + left..=y * image.width + right]);
    }
    let window = gaussian_blur(
        &GrayImage32 {
            width: w,
            height: h,
            values,
        },
        sigma,
    );
    (window, left as f32, top as f32)
}

/// How the image's values are mapped onto the template's while aligning: the photometric
/// model of the residual, fitted in closed form at every step.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Light {
    /// One gain and one offset over the part: minimising the residual maximises ZNCC.
    Even,
    /// A gain and an offset that each change linearly across the part (`α(u, v)·I + β(u, v)`),
    /// as light falling across the frame or a lamp on one side give it.
    Planes,
}

/// Template points: offsets from the template centre and values, taken from the template
/// blurred to match the window's blur at the expected scale.
pub(crate) struct AlignPoints {
    /// The points, each weighted by its template value `T`.
    lanes: PointLanes,
    /// Σ T and Σ (T − mean)², for the closed-form cost.
    sum: f64,
    spread: f64,
    /// The largest `|u|` or `|v|` (at least 1): the planes' coordinates are offsets divided by
    /// it, so that their fit is as well conditioned as the gain's.
    extent: f32,
    /// The moments of [`Light::Planes`]' fit that depend on the points alone.
    plane: PlaneMoments,
}

/// Sums over the template points for the planes' least squares ([`plane_fit`]), with `u`, `v`
/// the offsets divided by the extent: `Σ m` for `m` in `[1, u, v, u², u·v, v²]`, `Σ m·T` for
/// `m` in `[1, u, v]`, and `Σ T²`.
struct PlaneMoments {
    monomials: [f64; 6],
    with_template: [f64; 3],
    template_squares: f64,
}

impl PlaneMoments {
    fn new(offsets: &[(f32, f32)], values: &[f32], extent: f32) -> Self {
        let scale = f64::from(extent).recip();
        let mut moments = Self {
            monomials: [0.0; 6],
            with_template: [0.0; 3],
            template_squares: 0.0,
        };
        for (&(u, v), &t) in offsets.iter().zip(values) {
            let monomials = plane_monomials(u, v, scale);
            let t = f64::from(t);
            for (sum, m) in moments.monomials.iter_mut().zip(monomials) {
                *sum += m;
            }
            for (sum, m) in moments.with_template.iter_mut().zip(&monomials[..3]) {
                *sum += m * t;
            }
            moments.template_squares += t * t;
        }
        moments
    }
}

/// `[1, u, v, u², u·v, v²]` of the offset `(u, v)` times `scale`: the planes' monomials.
fn plane_monomials(u: f32, v: f32, scale: f64) -> [f64; 6] {
    let (u, v) = (f64::from(u) * scale, f64::from(v) * scale);
    [1.0, u, v, u * u, u * v, v * v]
}

impl AlignPoints {
    /// Every `stride`-th pixel of `template` blurred by `sigma` template pixels; with
    /// `whole_lanes`, without the farthest few that would start a last lane
    /// ([`super::in_whole_lanes`]).
    pub(crate) fn new(
        template: &GrayImage32,
        sigma: f32,
        max_side: usize,
        whole_lanes: bool,
    ) -> Self {
        let points = super::grid_points(&gaussian_blur(template, sigma), max_side);
        let (offsets, values) = if whole_lanes {
            super::in_whole_lanes(points)
        } else {
            points
        };
        let sum: f64 = values.iter().map(|&t| t as f64).sum();
        let mean = sum / values.len().max(1) as f64;
        let spread = values.iter().map(|&t| (t as f64 - mean).powi(2)).sum();
        let extent = offsets
            .iter()
            .map(|&(u, v)| u.abs().max(v.abs()))
            .fold(1.0f32, f32::max);
        Self {
            lanes: PointLanes::new(&offsets, &values),
            sum,
            spread,
            extent,
            plane: PlaneMoments::new(&offsets, &values, extent),
        }
    }
}

/// Levenberg–Marquardt iterations of the five parameters from `start`, at most `iterations`
/// and until a step lowers the normalised residual by less than `tolerance` of itself;
/// returns the pose with the lowest residual found (never worse than `start`).
pub(crate) fn align(
    points: &AlignPoints,
    window: &GradientWindow,
    start: &Pose,
    iterations: usize,
    tolerance: f64,
    light: Light,
) -> Pose {
    let mut pose = *start;
    let Some(mut cost) = residual_cost(points, window, &pose, light) else {
        return pose;
    };
    let mut damping = 1e-3f64;
    for _ in 0..iterations {
        let Some((hessian, gradient)) = normal_equations(points, window, &pose, light) else {
            break;
        };
        let mut improved = false;
        for _ in 0..6 {
            let mut system = hessian;
            for (k, row) in system.iter_mut().enumerate() {
                row[k] += damping * hessian[k][k].max(1e-9);
            }
            let Some(step) = solve(system, gradient) else {
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
            match residual_cost(points, window, &candidate, light) {
                Some(c) if c < cost => {
                    let converged = (cost - c) < tolerance * cost.max(1e-12);
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

/// Residual sum of squares after the photometric fit, relative to the template's variance
/// (`1 − ZNCC²` under [`Light::Even`]), or `None` where the image is flat or the match inverted.
fn residual_cost(
    points: &AlignPoints,
    window: &GradientWindow,
    pose: &Pose,
    light: Light,
) -> Option<f64> {
    let map = Affine::of(pose, window.x0, window.y0);
    match light {
        Light::Even => {
            let n = points.lanes.len() as f64;
            // Sums of I − reference: variance and covariance do not change with the shift.
            let sums = points.lanes.sums_at(&window.image, &map);
            let (si, sii, sit) = (sums.sum, sums.sum_sq, sums.dot);
            let variance = sii - si * si / n;
            let covariance = sit - si * points.sum / n;
            if variance <= 1e-9 || covariance <= 0.0 {
                return None;
            }
            // min over α, β of Σ(αI + β − T)² = S_tt − S_it² / S_ii (centred sums).
            Some(1.0 - covariance * covariance / (variance * points.spread.max(1e-12)))
        }
        Light::Planes => plane_fit(points, window, &map).map(|fit| fit.cost),
    }
}

/// The photometric planes of [`Light::Planes`] fitted at one pose: `α(u, v) = gain · [1, u, v]`
/// and `β(u, v) = offset · [1, u, v]` in template offsets, and the residual they leave relative
/// to the template's variance.
struct PlaneFit {
    gain: [f32; 3],
    offset: [f32; 3],
    cost: f64,
}

/// Least squares of `Σ (α(u, v)·I + β(u, v) − T)²` over the six coefficients, the image sampled
/// where `map` puts the points; `None` where the image is flat there or the gain is not
/// positive over the whole part (contrast inverted there, as [`Light::Even`] refuses it).
fn plane_fit(points: &AlignPoints, window: &GradientWindow, map: &Affine) -> Option<PlaneFit> {
    let mut samples = Vec::new();
    points.lanes.samples_at(&window.image, map, &mut samples);
    let n = samples.len() as f64;
    let mean = samples.iter().map(|&i| f64::from(i)).sum::<f64>() / n.max(1.0);
    let scale = f64::from(points.extent).recip();
    // The regressors are `x = [I', u·I', v·I', 1, u, v]` with `I' = I − mean` and `u`, `v`
    // scaled; every entry of `Σ x·xᵀ` and `Σ x·T` is a moment `Σ m·I'²`, `Σ m·I'` or
    // `Σ m·T·I'` of a monomial `m` of `[1, u, v, u², u·v, v²]`, or one of the points' own
    // ([`PlaneMoments`]): one pass over the samples.
    let (mut squares, mut linear, mut with_template) = ([0f64; 6], [0f64; 6], [0f64; 3]);
    for (((u, v), t), &i) in points.lanes.points().zip(&samples) {
        let monomials = plane_monomials(u, v, scale);
        let i = f64::from(i) - mean;
        for ((square, line), m) in squares.iter_mut().zip(&mut linear).zip(monomials) {
            let term = m * i;
            *line += term;
            *square += term * i;
        }
        let ti = f64::from(t) * i;
        for (sum, m) in with_template.iter_mut().zip(&monomials[..3]) {
            *sum += m * ti;
        }
    }
    if squares[0] <= 1e-9 {
        return None;
    }
    let [a0, a1, a2, a3, a4, a5] = squares;
    let [b0, b1, b2, b3, b4, b5] = linear;
    let [g0, g1, g2, g3, g4, g5] = points.plane.monomials;
    let normal = [
        [a0, a1, a2, b0, b1, b2],
        [a1, a3, a4, b1, b3, b4],
        [a2, a4, a5, b2, b4, b5],
        [b0, b1, b2, g0, g1, g2],
        [b1, b3, b4, g1, g3, g4],
        [b2, b4, b5, g2, g4, g5],
    ];
    let [t0, t1, t2] = points.plane.with_template;
    let rhs = [
        with_template[0],
        with_template[1],
        with_template[2],
        t0,
        t1,
        t2,
    ];
    let c = solve(normal, rhs)?;
    // The gain at the template's farthest corner is `c0 ± c1 ± c2` (scaled offsets within ±1).
    if c[0] <= c[1].abs() + c[2].abs() {
        return None;
    }
    // At the least-squares solution the residual is `Σ T² − c·(Σ x·T)`.
    let fitted: f64 = c.iter().zip(&rhs).map(|(c, r)| c * r).sum();
    let residual = (points.plane.template_squares - fitted).max(0.0);
    // Back to raw offsets and raw image values: α·(I − mean) + β = α·I + (β − α·mean).
    let gain = [c[0], c[1] * scale, c[2] * scale];
    let offset = [
        c[3] - c[0] * mean,
        c[4] * scale - c[1] * scale * mean,
        c[5] * scale - c[2] * scale * mean,
    ];
    Some(PlaneFit {
        gain: gain.map(|g| g as f32),
        offset: offset.map(|o| o as f32),
        cost: residual / points.spread.max(1e-12),
    })
}

type Matrix5 = [[f64; 5]; 5];

/// `JᵀJ` and `Jᵀr` of the residuals `r = α·I + β − T` at `pose`, the photometric model fitted
/// in closed form first; `None` where the image is flat there.
fn normal_equations(
    points: &AlignPoints,
    window: &GradientWindow,
    pose: &Pose,
    light: Light,
) -> Option<(Matrix5, [f64; 5])> {
    let map = Affine::of(pose, window.x0, window.y0);
    let (gain, offset) = match light {
        Light::Even => {
            let n = points.lanes.len() as f64;
            let sums = points.lanes.sums_at(&window.image, &map);
            let (si, sii, sit) = (sums.sum, sums.sum_sq, sums.dot);
            let variance = sii - si * si / n;
            if variance <= 1e-9 {
                return None;
            }
            // Gain and offset that best map image values onto template values (on the shifted
            // values, then the offset moved back by the shift).
            let alpha = (sit - si * points.sum / n) / variance;
            let beta = (points.sum - alpha * si) / n - alpha * sums.reference as f64;
            ([alpha as f32, 0.0, 0.0], [beta as f32, 0.0, 0.0])
        }
        Light::Planes => {
            let fit = plane_fit(points, window, &map)?;
            (fit.gain, fit.offset)
        }
    };
    let moments = jacobian_moments(&points.lanes, window, &map, pose, gain, offset);
    let mut hessian = [[0f64; 5]; 5];
    let gradient = moments.gradient.map(f64::from);
    for ((a, b), m) in UPPER_TRIANGLE.into_iter().zip(moments.hessian) {
        hessian[a][b] = m as f64;
        hessian[b][a] = hessian[a][b];
    }
    Some((hessian, gradient))
}

/// Σ jjᵀ (upper triangle, row by row) and Σ j·r over the template points, with `j` the
/// derivative of `α·I` at a point by `[x, y, θ, sx, sy]` and `r = α·I + β − T`, where
/// `α = gain · [1, u, v]` and `β = offset · [1, u, v]` (constant under [`Light::Even`]).
struct JacobianMoments {
    hessian: [f32; 15],
    gradient: [f32; 5],
}

/// The entries `(a, b)`, `a <= b`, of a symmetric 5x5 matrix, row by row.
const UPPER_TRIANGLE: [(usize, usize); 15] = [
    (0, 0),
    (0, 1),
    (0, 2),
    (0, 3),
    (0, 4),
    (1, 1),
    (1, 2),
    (1, 3),
    (1, 4),
    (2, 2),
    (2, 3),
    (2, 4),
    (3, 3),
    (3, 4),
    (4, 4),
];

#[multiversion(targets("x86_64+avx512f+avx512vl+avx512bw+avx512dq", "x86_64+avx2+fma"))]
fn jacobian_moments(
    lanes: &PointLanes,
    window: &GradientWindow,
    map: &Affine,
    pose: &Pose,
    gain: [f32; 3],
    offset: [f32; 3],
) -> JacobianMoments {
    let (width, height) = (window.image.width, window.image.height);
    let buffers = [&window.image.values[..], &window.gx[..], &window.gy[..]];
    for buffer in buffers {
        assert_eq!(
            buffer.len(),
            width * height,
            "window buffers match its size"
        );
    }
    // Windows that fit the lanes (all but absurd ones) gather with 32-bit indices.
    let narrow = fits_lanes(width, height);
    let (s, c) = pose.angle_deg.to_radians().sin_cos();
    let (sx, sy) = (pose.scale_x, pose.scale_y);
    let mut hessian = [[0f32; LANES]; 15];
    let mut gradient = [[0f32; LANES]; 5];
    let real = lanes.len();
    for (chunk, ((u, v), t)) in lanes
        .us
        .chunks_exact(LANES)
        .zip(lanes.vs.chunks_exact(LANES))
        .zip(lanes.weights.chunks_exact(LANES))
        .enumerate()
    {
        let (mut i, mut gx, mut gy) = ([0f32; LANES], [0f32; LANES], [0f32; LANES]);
        for lane in 0..LANES {
            let (x, y) = map.apply(u[lane], v[lane]);
            // SAFETY: every buffer is width x height (asserted above); a `LaneTap` only where
            // the window fits the lanes.
            unsafe {
                [i[lane], gx[lane], gy[lane]] = if narrow {
                    let tap = LaneTap::new(width as i32, height as i32, x, y);
                    buffers.map(|buffer| tap.apply_unchecked(buffer))
                } else {
                    let tap = BilinearTap::new(width, height, x, y);
                    buffers.map(|buffer| tap.apply_unchecked(buffer))
                };
            }
        }
        for lane in 0..LANES {
            let (u, v) = (u[lane], v[lane]);
            // The padding (copies of the first point) adds nothing.
            let weight = if chunk * LANES + lane < real {
                1.0
            } else {
                0.0
            };
            let alpha = gain[0] + gain[1] * u + gain[2] * v;
            let beta = offset[0] + offset[1] * u + offset[2] * v;
            let r = (alpha * i[lane] + beta - t[lane]) * weight;
            let (gx, gy) = (gx[lane] * weight * alpha, gy[lane] * weight * alpha);
            // d(x_img, y_img) / d(θ, sx, sy) for x = x0 + sx·u·c + sy·v·s,
            // y = y0 − sx·u·s + sy·v·c.
            let dtheta = (-sx * u * s + sy * v * c, -sx * u * c - sy * v * s);
            let jac = [
                gx,
                gy,
                gx * dtheta.0 + gy * dtheta.1,
                gx * u * c - gy * u * s,
                gx * v * s + gy * v * c,
            ];
            for (sum, j) in gradient.iter_mut().zip(jac) {
                sum[lane] += j * r;
            }
            for (sum, (a, b)) in hessian.iter_mut().zip(UPPER_TRIANGLE) {
                sum[lane] += jac[a] * jac[b];
            }
        }
    }
    JacobianMoments {
        hessian: hessian.map(|lanes| lanes.iter().sum()),
        gradient: gradient.map(|lanes| lanes.iter().sum()),
    }
}

/// Solves the NxN system by Gaussian elimination with partial pivoting.
#[allow(clippy::needless_range_loop)] // index form mirrors the matrix algebra
fn solve<const N: usize>(mut m: [[f64; N]; N], mut rhs: [f64; N]) -> Option<[f64; N]> {
    for col in 0..N {
        let pivot = (col..N).max_by(|&a, &b| m[a][col].abs().total_cmp(&m[b][col].abs()))?;
        if m[pivot][col].abs() < 1e-12 {
            return None;
        }
        m.swap(col, pivot);
        rhs.swap(col, pivot);
        for row in col + 1..N {
            let f = m[row][col] / m[col][col];
            for k in col..N {
                m[row][k] -= f * m[col][k];
            }
            rhs[row] -= f * rhs[col];
        }
    }
    let mut x = [0f64; N];
    for row in (0..N).rev() {
        let tail: f64 = (row + 1..N).map(|k| m[row][k] * x[k]).sum();
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
        let solved = solve(m, rhs.try_into().unwrap()).unwrap();
        for (a, b) in solved.iter().zip(&x) {
            assert!((a - b).abs() < 1e-9, "{solved:?}");
        }
    }

    #[test]
    fn solves_a_six_by_six_system_as_the_planes_fit_needs() {
        let m: [[f64; 6]; 6] = std::array::from_fn(|a| {
            std::array::from_fn(|b| {
                if a == b {
                    6.0
                } else {
                    1.0 / (1 + a + b) as f64
                }
            })
        });
        let x = [0.5, -1.0, 2.0, 0.25, -3.0, 1.5];
        let rhs = m.map(|row| row.iter().zip(&x).map(|(a, b)| a * b).sum());
        let solved = solve(m, rhs).unwrap();
        for (a, b) in solved.iter().zip(&x) {
            assert!((a - b).abs() < 1e-9, "{solved:?}");
        }
    }

    #[test]
    fn the_planes_fit_leaves_the_residual_its_gain_and_offset_leave() {
        // The template is a crop of the scene; the scene is lit unevenly and the pose is a
        // little off, so that the fit leaves a residual.
        let scene = crate::refine::textured(80, 70, 3);
        let template = GrayImage32::from_fn(24, 20, |x, y| scene.values[(25 + y) * 80 + 28 + x]);
        let image = GrayImage32::from_fn(80, 70, |x, y| {
            scene.values[y * 80 + x] * (0.5 + x as f32 / 80.0) + 0.1
        });
        let points = AlignPoints::new(&template, 0.0, 24, false);
        let window = GradientWindow::whole(&image, 0.0);
        let pose = Pose {
            x: 28.0 + 11.5 + 0.3,
            y: 25.0 + 9.5 - 0.2,
            angle_deg: 2.0,
            scale_x: 1.03,
            scale_y: 0.98,
            score: 0.0,
            network_score: 0.0,
        };
        let map = Affine::of(&pose, window.x0, window.y0);
        let fit = plane_fit(&points, &window, &map).expect("a textured patch fits");
        let mut samples = Vec::new();
        points.lanes.samples_at(&window.image, &map, &mut samples);
        let plane = |c: [f32; 3], u: f32, v: f32| f64::from(c[0] + c[1] * u + c[2] * v);
        let residual: f64 = points
            .lanes
            .points()
            .zip(&samples)
            .map(|(((u, v), t), &i)| {
                let model = plane(fit.gain, u, v) * f64::from(i) + plane(fit.offset, u, v);
                (model - f64::from(t)).powi(2)
            })
            .sum();
        let direct = residual / points.spread;
        assert!(
            (fit.cost - direct).abs() < 1e-5 * direct.max(1e-3),
            "{} vs {direct}",
            fit.cost
        );
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
