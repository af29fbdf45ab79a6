//! Geometric refinement and verification of coarse poses: local search on the image itself, the
//! step that turns the network's rough answer (a few degrees, ~0.1 in scale) into one usable for
//! alignment, and that tells how well the template really matches there.
//!
//! The score of a pose is the zero-mean normalised cross-correlation (ZNCC) between the template
//! and the image sampled (bilinear) where the pose maps each template pixel ([`TemplatePoints`],
//! the one scorer every stage uses). ZNCC rather than the paper's uncentred cosine similarity:
//! the uncentred score is above 0.9 for almost any alignment on natural images (reference
//! README), so it cannot rank candidates finely.
//!
//! [`refine_pose`] refines one pose the network is already sure of:
//! 1. Angle x scales on a sparse grid of template points: ±30° in 3° steps x five factors
//!    0.7–1.4 per axis; if nothing there scores well, the whole circle in 6° steps (a network
//!    angle can be far off); then scales ±10 % and the angle ±4° in finer steps.
//! 2. Align: all five parameters jointly by Gauss–Newton (Lucas–Kanade with
//!    Levenberg–Marquardt damping, [`align`]) on the image blurred by 2, then 1 pixel, then
//!    sharp, from the grid's best pose and from the initial one; the better-scoring result wins.
//!    The blur widens the basin (a start a few pixels and degrees off still converges); the
//!    sharp level takes the error far below any search step.
//!
//! The refined pose replaces the initial one only if it scores higher, reaches ZNCC >= 0.6 and
//! its centre stays within a third of the object's size, so that refinement does not trade an
//! object the network found for a better-looking neighbour.
//!
//! The matcher's verification (`matcher/verification.rs`) builds on the same pieces to
//! decide between many candidates of one image: the angle x scale search on a downsampled
//! image as a cheap screen, then the fine search and alignment for the survivors.

use crate::geometry::{Pose, wrap_angle_deg};

pub(crate) mod align;
mod blocking;
mod correlate;
mod coverage;
mod curve;
mod detrend;
mod noise;
mod rank;
mod shading;
mod sharpness;

pub use align::Light;
pub(crate) use coverage::{Coverage, CoverageReading};
pub(crate) use curve::LightCurve;
pub(crate) use detrend::PlaneFreePoints;
pub(crate) use noise::{NoiseLevel, NoisePoints};
pub(crate) use rank::RankPoints;
pub(crate) use shading::ShadingPoints;
pub(crate) use sharpness::Sharpness;

use crate::imaging::GrayImage32;

/// ZNCC below which the refined alignment is not trusted (the content is too ambiguous).
const MIN_MATCH_SCORE: f32 = 0.6;

/// Sparse ZNCC under which the ±30° grid around the network's angle is not trusted and the
/// whole circle is searched (a true match at the right angle scores well above this).
const FULL_CIRCLE_BELOW: f32 = 0.8;

/// Blur of the coarse-to-fine alignment levels, in image pixels for an object 36 pixels across
/// (proportionally more for larger objects, whose start is proportionally further off): a wide
/// basin first, then the sharp image for the last fraction of a pixel.
const ALIGN_SIGMAS: [f32; 3] = [2.0, 1.0, 0.0];

/// The refinement's alignment runs until a step lowers its residual by less than this share.
const ALIGN_TOLERANCE: f64 = 1e-5;

/// Every `stride`-th pixel of `template` (at most ~`max_side` per side) that is not ignored
/// (NaN): offsets from the template centre and values.
fn grid_points(template: &GrayImage32, max_side: usize) -> (Vec<(f32, f32)>, Vec<f32>) {
    let stride = template
        .width
        .max(template.height)
        .div_ceil(max_side)
        .max(1);
    let (cx, cy) = (
        (template.width as f32 - 1.0) / 2.0,
        (template.height as f32 - 1.0) / 2.0,
    );
    let mut offsets = Vec::new();
    let mut values = Vec::new();
    for y in (0..template.height).step_by(stride) {
        for x in (0..template.width).step_by(stride) {
            let value = template.values[y * template.width + x];
            // NaN: a pixel the template's mask ignores (matcher/template_mask.rs).
            if !value.is_nan() {
                offsets.push((x as f32 - cx, y as f32 - cy));
                values.push(value);
            }
        }
    }
    (offsets, values)
}

/// `(offsets, values)` without the few points farthest from the template centre that would
/// start a last, mostly empty lane of [`correlate::LANES`] (at most a quarter of a lane): the
/// sampling costs the same per lane however many of its points are real, and the screen
/// samples every candidate a few hundred times (9x9 level points: 81 → 80, six lanes → five).
/// The farthest points go because a small angle error moves them most.
fn in_whole_lanes((offsets, values): (Vec<(f32, f32)>, Vec<f32>)) -> (Vec<(f32, f32)>, Vec<f32>) {
    let lanes = correlate::LANES;
    let extra = offsets.len() % lanes;
    if offsets.len() < lanes || extra == 0 || extra > lanes / 4 {
        return (offsets, values);
    }
    let mut order: Vec<usize> = (0..offsets.len()).collect();
    let distance = |i: usize| offsets[i].0.hypot(offsets[i].1);
    order.sort_by(|&a, &b| distance(a).total_cmp(&distance(b)));
    let mut kept = order[..offsets.len() - extra].to_vec();
    kept.sort_unstable();
    (
        kept.iter().map(|&i| offsets[i]).collect(),
        kept.iter().map(|&i| values[i]).collect(),
    )
}

/// `values` made zero-mean and unit-norm (all zero when they are all the same), and the norm
/// they had after centring (`sqrt(n)` times their standard deviation).
fn unit_weights(values: &[f32]) -> (Vec<f32>, f32) {
    let mean = values.iter().sum::<f32>() / values.len().max(1) as f32;
    let mut weights: Vec<f32> = values.iter().map(|v| v - mean).collect();
    let norm = weights.iter().map(|w| w * w).sum::<f32>().sqrt();
    if norm > 1e-6 {
        weights.iter_mut().for_each(|w| *w /= norm);
    }
    (weights, norm)
}

/// Template points (offsets from the template centre) with zero-mean, unit-norm values.
pub(crate) struct TemplatePoints {
    lanes: correlate::PointLanes,
}

impl TemplatePoints {
    /// Every `stride`-th template pixel (at most ~`max_side` per side).
    pub(crate) fn new(template: &GrayImage32, max_side: usize) -> Self {
        Self::from_points(grid_points(template, max_side))
    }

    /// [`TemplatePoints::new`] in whole lanes ([`in_whole_lanes`]): the screen's points.
    pub(crate) fn in_whole_lanes(template: &GrayImage32, max_side: usize) -> Self {
        Self::from_points(in_whole_lanes(grid_points(template, max_side)))
    }

    fn from_points((offsets, values): (Vec<(f32, f32)>, Vec<f32>)) -> Self {
        let (weights, _) = unit_weights(&values);
        Self {
            lanes: correlate::PointLanes::new(&offsets, &weights),
        }
    }

    /// Offsets from the template centre and zero-mean, unit-norm weights, point by point.
    pub(crate) fn points(&self) -> impl Iterator<Item = ((f32, f32), f32)> + '_ {
        self.lanes.points()
    }

    /// The points that measure a pose's final similarity: the whole template (every pixel up to
    /// 48 a side, a regular subset beyond).
    pub(crate) fn support(template: &GrayImage32) -> Self {
        Self::new(template, 48)
    }

    /// The image where `pose` maps each point, in the points' order: what the readings of a
    /// pose compare with their own template values ([`PoseSamples`]).
    pub(crate) fn samples(&self, image: &GrayImage32, pose: &Pose) -> PoseSamples {
        let mut values = Vec::new();
        self.lanes.samples(image, pose, &mut values);
        PoseSamples { values }
    }

    /// The points' zero-mean, unit-norm weights, in the points' order.
    pub(crate) fn weights(&self) -> &[f32] {
        &self.lanes.weights[..self.lanes.len()]
    }

    /// ZNCC of the template against the image under `pose`, in [-1, 1].
    pub(crate) fn score(&self, image: &GrayImage32, pose: &Pose) -> f32 {
        let sums = self.lanes.sums(image, pose);
        zncc(
            sums.dot as f32,
            sums.sum as f32,
            sums.sum_sq as f32,
            self.lanes.len(),
        )
    }
}

/// The image where a pose maps each of a template's support points ([`grid_points`] up to 48
/// a side, the order of [`TemplatePoints::support`]), sampled once.
///
/// Why: a pose's score is the best of several readings (`matcher/verification.rs`,
/// `Verifier::readings_at`): the blurred templates, the shading, the denoised, the cells'
/// coverage, the rank correlation. Each compares its own template values with the same image
/// samples; sampled by each reading anew they were most of the cost of scoring a pose, which
/// the verifier does some fifty times a pair.
pub(crate) struct PoseSamples {
    values: Vec<f32>,
}

impl PoseSamples {
    /// The samples, one per support point.
    pub(crate) fn values(&self) -> &[f32] {
        &self.values
    }

    /// ZNCC of zero-mean, unit-norm `weights` (one per sample, in order) with the samples, in
    /// [-1, 1] ([`zncc`]: a flat patch scores -1).
    pub(crate) fn zncc(&self, weights: &[f32]) -> f32 {
        debug_assert_eq!(weights.len(), self.values.len(), "one weight per sample");
        let Some(&reference) = self.values.first() else {
            return -1.0;
        };
        // Relative to the first sample, as the lanes' sums are (`correlate::Sums`).
        let (mut sum, mut sum_sq, mut dot) = (0f64, 0f64, 0f64);
        for (&sample, &weight) in self.values.iter().zip(weights) {
            let value = f64::from(sample - reference);
            sum += value;
            sum_sq += value * value;
            dot += f64::from(weight) * value;
        }
        zncc(dot as f32, sum as f32, sum_sq as f32, self.values.len())
    }

    /// [`PoseSamples::zncc`] of each of `weights` (up to four at a time), the same numbers.
    /// Why: each sum is added in the samples' order, a dependency from one sample to the next,
    /// so a pass costs about what one sum costs; the sharpness readings correlate three blurred
    /// templates with the same samples, and read side by side they cost one pass.
    pub(crate) fn zncc_each(&self, weights: &[&[f32]]) -> Vec<f32> {
        if weights.iter().any(|w| w.len() != self.values.len()) {
            // Not the support's weights (cannot happen): each as `zncc` reads it.
            return weights.iter().map(|w| self.zncc(w)).collect();
        }
        let mut out = Vec::with_capacity(weights.len());
        for chunk in weights.chunks(4) {
            match *chunk {
                [a] => out.extend(self.zncc_of([a])),
                [a, b] => out.extend(self.zncc_of([a, b])),
                [a, b, c] => out.extend(self.zncc_of([a, b, c])),
                [a, b, c, d] => out.extend(self.zncc_of([a, b, c, d])),
                _ => unreachable!("chunks of one to four"),
            }
        }
        out
    }

    /// [`PoseSamples::zncc`] of `K` weight vectors in one pass over the samples.
    fn zncc_of<const K: usize>(&self, weights: [&[f32]; K]) -> [f32; K] {
        let n = self.values.len();
        let Some(&reference) = self.values.first() else {
            return [-1.0; K];
        };
        let weights = weights.map(|w| &w[..n]);
        let (mut sum, mut sum_sq, mut dots) = (0f64, 0f64, [0f64; K]);
        for (i, &sample) in self.values.iter().enumerate() {
            let value = f64::from(sample - reference);
            sum += value;
            sum_sq += value * value;
            for (dot, w) in dots.iter_mut().zip(&weights) {
                *dot += f64::from(w[i]) * value;
            }
        }
        dots.map(|dot| zncc(dot as f32, sum as f32, sum_sq as f32, n))
    }
}

/// Grey-level spread (standard deviation, image values in [0, 1]) below which an image patch
/// counts as flat: half a grey level of an 8-bit image. A flat patch has nothing to match, and
/// in f32 its variance is lost in the rounding of the sums: before this floor, a plain region
/// of a photo could score above 1 against any template and crowd out the object.
pub(crate) const FLAT_PATCH_SPREAD: f32 = 0.5 / 255.0;

/// ZNCC of zero-mean, unit-norm template weights with `n` image samples, from the samples' sum,
/// sum of squares and weighted sum (`Σ w·(I − Ī) = Σ w·I` because `Σ w = 0`). A flat patch
/// ([`FLAT_PATCH_SPREAD`]) scores -1, the lowest score; the result is in [-1, 1].
/// Branch-free (the flat patch's root is worked out and dropped) so that a row of positions
/// scores in vectors (`matcher/classical.rs`).
#[inline]
pub(crate) fn zncc(dot: f32, sum: f32, sum_sq: f32, n: usize) -> f32 {
    let n = n as f32;
    let variance = sum_sq - sum * sum / n;
    let similarity = (dot / variance.sqrt()).clamp(-1.0, 1.0);
    if variance <= n * FLAT_PATCH_SPREAD * FLAT_PATCH_SPREAD {
        -1.0
    } else {
        similarity
    }
}

/// A pose and its score under one set of [`TemplatePoints`].
#[derive(Debug, Clone, Copy)]
pub(crate) struct Scored {
    pub(crate) pose: Pose,
    pub(crate) score: f32,
}

/// The angle x scales grid searched around a pose at its fixed centre.
pub(crate) struct AngleScaleGrid {
    /// Angle step near the start (degrees), searched within ±30°.
    pub(crate) near_step_deg: f32,
    /// Scale factors per axis near the start.
    pub(crate) near_factors: Vec<f32>,
    /// Angle step over the rest of the circle, searched when nothing near scores
    /// [`FULL_CIRCLE_BELOW`].
    pub(crate) far_step_deg: f32,
    /// Scale factors per axis over the rest of the circle.
    pub(crate) far_factors: Vec<f32>,
    /// `Some(n)`: score every angle at the start's scales first and try the scale factors
    /// only at the `n` best angles (the screen's shortcut); `None`: every angle x scales.
    pub(crate) angles_first: Option<usize>,
    /// Near the start, score the isotropic scale pairs (`f·sx, f·sy` for each near factor `f`)
    /// first and then only the 3x3 pairs one factor step around the best of them (13 pairs
    /// instead of 25; the screen's shortcut: docs/verification.md); otherwise every
    /// pair of near factors.
    pub(crate) isotropic_first: bool,
    /// Search near the start's mirrored angle (`-angle`) too, as a second start: the network
    /// reads an angle as `±acos(cos)` with the sign from its sign map, and the sign is the
    /// head it gets wrong most (docs/verification.md).
    pub(crate) mirrored_start: bool,
}

/// The `keep` angles of `angles` at which the template at `start`'s scales scores best.
pub(crate) fn best_angles(
    points: &TemplatePoints,
    image: &GrayImage32,
    start: &Pose,
    angles: Vec<f32>,
    keep: usize,
) -> Vec<f32> {
    let mut scored: Vec<(f32, f32)> = angles
        .into_iter()
        .map(|angle_deg| {
            let pose = Pose {
                angle_deg,
                ..*start
            };
            (points.score(image, &pose), angle_deg)
        })
        .collect();
    scored.sort_by(|a, b| b.0.total_cmp(&a.0));
    scored
        .into_iter()
        .take(keep)
        .map(|(_, angle)| angle)
        .collect()
}

impl AngleScaleGrid {
    /// The refinement's grid (full-resolution sparse points): 3° near, 6° far.
    pub(crate) fn refinement() -> Self {
        Self {
            near_step_deg: 3.0,
            near_factors: (0..5).map(|k| 0.7f32 * 2f32.powf(k as f32 / 4.0)).collect(),
            far_step_deg: 6.0,
            far_factors: (0..3).map(|k| 0.85f32 * 1.18f32.powi(k)).collect(),
            angles_first: None,
            isotropic_first: false,
            mirrored_start: false,
        }
    }

    /// Searches angle x scales around `start` (its centre fixed) for the best score under
    /// `points`, trying only angles that `allowed` accepts: ±30° first (and ±30° around the
    /// mirrored angle with `mirrored_start`), the rest of the circle when nothing there reaches
    /// [`FULL_CIRCLE_BELOW`] (a weakly trained network, a symmetric-looking part).
    pub(crate) fn search(
        &self,
        points: &TemplatePoints,
        image: &GrayImage32,
        start: &Pose,
        allowed: &dyn Fn(f32) -> bool,
    ) -> Scored {
        self.search_windows(points, image, start, allowed)
            .into_iter()
            .max_by(|a, b| a.score.total_cmp(&b.score))
            .expect("the start itself is always scored")
    }

    /// [`AngleScaleGrid::search`]'s best pose in each window it searched (the start's, the
    /// mirrored start's, the rest of the circle), the start's first: starts for an alignment,
    /// which can pull a centre a few pixels off onto the object only from the right angle.
    pub(crate) fn search_windows(
        &self,
        points: &TemplatePoints,
        image: &GrayImage32,
        start: &Pose,
        allowed: &dyn Fn(f32) -> bool,
    ) -> Vec<Scored> {
        let at_start = Scored {
            pose: *start,
            score: if allowed(wrap_angle_deg(start.angle_deg)) {
                points.score(image, start)
            } else {
                f32::NEG_INFINITY
            },
        };
        let best_of = |offsets: &mut dyn Iterator<Item = f32>,
                       factors: &[f32],
                       isotropic_first: bool|
         -> Scored {
            let mut best = Scored {
                pose: *start,
                score: f32::NEG_INFINITY,
            };
            let angles: Vec<f32> = offsets
                .map(|offset| start.angle_deg + offset)
                .filter(|&angle| allowed(wrap_angle_deg(angle)))
                .collect();
            let angles = match self.angles_first {
                Some(keep) => best_angles(points, image, start, angles, keep),
                None => angles,
            };
            let mut try_pose = |angle_deg: f32, factor_x: f32, factor_y: f32| -> f32 {
                let pose = Pose {
                    angle_deg,
                    scale_x: start.scale_x * factor_x,
                    scale_y: start.scale_y * factor_y,
                    ..*start
                };
                let score = points.score(image, &pose);
                if score > best.score {
                    best = Scored { pose, score };
                }
                score
            };
            for angle_deg in angles {
                if isotropic_first && factors.len() > 1 {
                    let step = factors[1] / factors[0];
                    let mut isotropic = (f32::NEG_INFINITY, 1.0f32);
                    for &factor in factors {
                        let score = try_pose(angle_deg, factor, factor);
                        if score > isotropic.0 {
                            isotropic = (score, factor);
                        }
                    }
                    let factor = isotropic.1;
                    for (kx, ky) in (-1..=1).flat_map(|kx| (-1..=1).map(move |ky| (kx, ky))) {
                        if (kx, ky) != (0, 0) {
                            try_pose(angle_deg, factor * step.powi(kx), factor * step.powi(ky));
                        }
                    }
                } else {
                    for &factor_x in factors {
                        for &factor_y in factors {
                            try_pose(angle_deg, factor_x, factor_y);
                        }
                    }
                }
            }
            best
        };
        let near = (30.0 / self.near_step_deg).floor() as i32;
        let own = best_of(
            &mut (-near..=near).map(|k| k as f32 * self.near_step_deg),
            &self.near_factors,
            self.isotropic_first,
        );
        let mut windows = vec![if own.score > at_start.score {
            own
        } else {
            at_start
        }];
        if self.mirrored_start {
            // The mirrored start's window, as offsets from the start, without what the first
            // window covers already.
            let mirrored = best_of(
                &mut (-near..=near)
                    .map(|k| -2.0 * start.angle_deg + k as f32 * self.near_step_deg)
                    .filter(|&offset| wrap_angle_deg(offset).abs() > 30.0),
                &self.near_factors,
                self.isotropic_first,
            );
            windows.push(mirrored);
        }
        if windows.iter().all(|w| w.score < FULL_CIRCLE_BELOW) {
            let first = (near as f32 * self.near_step_deg / self.far_step_deg).floor() as i32 + 1;
            let last = (360.0 / self.far_step_deg).ceil() as i32 - first;
            windows.push(best_of(
                &mut (first..=last).map(|k| k as f32 * self.far_step_deg),
                &self.far_factors,
                false,
            ));
        }
        windows.retain(|w| w.score > f32::NEG_INFINITY);
        if windows.is_empty() {
            // Nothing allowed (cannot happen for a non-empty angle range and the whole circle).
            windows.push(Scored {
                pose: *start,
                score: points.score(image, start),
            });
        }
        windows
    }
}

/// Scales ±10 % (5x5 factors), then the angle ±4° in 1° steps, around `best` (centre fixed).
pub(crate) fn fine_search(
    points: &TemplatePoints,
    image: &GrayImage32,
    mut best: Scored,
    allowed: &dyn Fn(f32) -> bool,
) -> Scored {
    let try_pose = |pose: Pose, best: &mut Scored| {
        if !allowed(wrap_angle_deg(pose.angle_deg)) {
            return;
        }
        let score = points.score(image, &pose);
        if score > best.score {
            *best = Scored { pose, score };
        }
    };
    let base = best.pose;
    for i in -2..=2 {
        for j in -2..=2 {
            let pose = Pose {
                scale_x: base.scale_x * (1.0 + 0.05 * i as f32),
                scale_y: base.scale_y * (1.0 + 0.05 * j as f32),
                ..base
            };
            try_pose(pose, &mut best);
        }
    }
    let base = best.pose;
    for k in -4..=4 {
        let pose = Pose {
            angle_deg: base.angle_deg + k as f32,
            ..base
        };
        try_pose(pose, &mut best);
    }
    best
}

/// Half the side of the windows [`align_from`] reads around its `around` pose, for starts up
/// to `largest_scale`, before the blur's margin.
fn align_window_radius(template: &GrayImage32, largest_scale: f32) -> f32 {
    let longest_side = template.width.max(template.height) as f32;
    0.75 * longest_side * largest_scale.max(1.0) * 1.5 + 8.0
}

/// How much wider than [`ALIGN_SIGMAS`] [`align_from`] blurs for a template at `mean_scale`.
fn align_blur_factor(template: &GrayImage32, mean_scale: f32) -> f32 {
    let object_side = (template.width * template.height) as f32;
    (object_side.sqrt() * mean_scale / 36.0).max(1.0)
}

/// How far from `around` (each way) [`align_from`] reads the image, starting at scales up to
/// `largest_scale`: a caller that hands it a crop must keep this much around the pose.
pub(crate) fn align_from_reach(template: &GrayImage32, largest_scale: f32, around: &Pose) -> f32 {
    let mean_scale = (around.scale_x * around.scale_y).abs().sqrt().max(0.1);
    let widest_sigma = ALIGN_SIGMAS.iter().copied().fold(1.0f32, f32::max);
    align_window_radius(template, largest_scale)
        + 3.0 * widest_sigma * align_blur_factor(template, mean_scale)
}

/// All five parameters jointly, coarse to fine (Gauss–Newton on blurred images, see [`align`]),
/// under `light`'s photometric model, from each of `starts`; the pose with the highest ZNCC
/// under `support` wins. `around` is the pose whose neighbourhood the blurred windows cover
/// (the candidate's).
pub(crate) fn align_from(
    template: &GrayImage32,
    support: &TemplatePoints,
    image: &GrayImage32,
    starts: &[Pose],
    around: &Pose,
    light: align::Light,
) -> Scored {
    let longest_side = template.width.max(template.height) as f32;
    let largest_scale = starts
        .iter()
        .map(|p| p.scale_x.max(p.scale_y))
        .fold(1.0f32, f32::max);
    let radius = align_window_radius(template, largest_scale);
    let mean_scale = (around.scale_x * around.scale_y).abs().sqrt().max(0.1);
    let blur_factor = align_blur_factor(template, mean_scale);
    let mut sigmas: Vec<f32> = ALIGN_SIGMAS.iter().map(|s| s * blur_factor).collect();
    if blur_factor > 1.5 {
        sigmas.insert(2, 1.0); // no big jump from a wide blur to the sharp image
    }
    let levels: Vec<(align::AlignPoints, align::GradientWindow)> = sigmas
        .iter()
        .map(|&sigma| {
            // Blurred levels need fewer points: about two per blur radius.
            let max_side = if sigma > 0.0 {
                ((longest_side * mean_scale / sigma) as usize).clamp(12, 40)
            } else {
                40
            };
            (
                align::AlignPoints::new(template, sigma / mean_scale, max_side, false),
                align::GradientWindow::new(image, around.x, around.y, radius + 3.0 * sigma, sigma),
            )
        })
        .collect();
    let mut best = Scored {
        pose: *around,
        score: f32::NEG_INFINITY,
    };
    for start in starts {
        let mut pose = *start;
        for (points, window) in &levels {
            pose = align::align(points, window, &pose, 20, ALIGN_TOLERANCE, light);
        }
        let score = support.score(image, &pose);
        if score > best.score {
            best = Scored { pose, score };
        }
    }
    best
}

/// Whether `pose` stayed near `reference`: within a third of the object's size, so that
/// refinement does not trade the object a candidate stands for for a better-looking neighbour.
pub(crate) fn stayed_near(template: &GrayImage32, reference: &Pose, pose: &Pose) -> bool {
    let side = template.width.min(template.height) as f32;
    let moved = (pose.x - reference.x).hypot(pose.y - reference.y);
    moved <= side.max(8.0) * reference.scale_x.min(reference.scale_y) / 3.0
}

/// Refinement of one pose. `template` is the registered template (grey), `image` the search.
/// The score is left as it was (the caller's).
pub fn refine_pose(template: &GrayImage32, image: &GrayImage32, initial: &Pose) -> Pose {
    let sparse = TemplatePoints::new(template, 20);
    let support = TemplatePoints::support(template);
    let initial_score = support.score(image, initial);
    let any_angle = |_: f32| true;
    // 1. Angle and scales together (the network's scale is its coarsest output, and a wrong
    //    scale hides the right angle), then finer steps.
    let searched = AngleScaleGrid::refinement().search(&sparse, image, initial, &any_angle);
    let searched = fine_search(&sparse, image, searched, &any_angle);
    // 2. All five parameters jointly, from the grid's best and from the network's own pose.
    let best = align_from(
        template,
        &support,
        image,
        &[searched.pose, *initial],
        initial,
        align::Light::Even,
    );
    // Keep the network's pose unless the refined one is better, clearly a match (as the paper
    // keeps its estimate when every candidate scores below a threshold), and no jump to a
    // neighbour.
    if best.score <= initial_score
        || best.score < MIN_MATCH_SCORE
        || !stayed_near(template, initial, &best.pose)
    {
        return *initial;
    }
    Pose {
        angle_deg: wrap_angle_deg(best.pose.angle_deg),
        ..best.pose
    }
}

/// The pose that lays `template` over itself (an image of its size): the readings' tests.
#[cfg(test)]
pub(crate) fn at_centre(template: &GrayImage32) -> Pose {
    Pose {
        x: (template.width as f32 - 1.0) / 2.0,
        y: (template.height as f32 - 1.0) / 2.0,
        angle_deg: 0.0,
        scale_x: 1.0,
        scale_y: 1.0,
        score: 0.0,
        network_score: 0.0,
    }
}

/// White noise in [0.2, 0.8], a hash of the position and the seed: the refinement's tests'
/// texture, detailed at every pixel.
#[cfg(test)]
pub(crate) fn textured(width: usize, height: usize, seed: usize) -> GrayImage32 {
    GrayImage32::from_fn(width, height, |x, y| {
        let mut h = (x as u64) << 32 ^ (y as u64) << 12 ^ (seed as u64).wrapping_mul(0x9E37);
        h = (h ^ (h >> 31)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        h = (h ^ (h >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        0.2 + 0.6 * ((h >> 40) as f32 / (1u64 << 24) as f32)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn correlations_read_side_by_side_are_those_read_one_by_one() {
        let template = textured(36, 36, 2);
        let image = textured(80, 70, 5);
        let support = TemplatePoints::support(&template);
        let blurred: Vec<TemplatePoints> = [1.0, 2.0, 3.0, 0.7, 1.4]
            .iter()
            .map(|&sigma| TemplatePoints::support(&crate::imaging::gaussian_blur(&template, sigma)))
            .collect();
        let weights: Vec<&[f32]> = std::iter::once(support.weights())
            .chain(blurred.iter().map(TemplatePoints::weights))
            .collect();
        for (x, angle) in [(30.0, 0.0), (41.3, 27.0), (52.8, -140.0)] {
            let pose = Pose {
                x,
                y: 33.6,
                angle_deg: angle,
                scale_x: 1.05,
                scale_y: 0.92,
                score: 0.0,
                network_score: 0.0,
            };
            let samples = support.samples(&image, &pose);
            let one_by_one: Vec<f32> = weights.iter().map(|w| samples.zncc(w)).collect();
            // Six weight vectors: a pass of four and one of two, bit for bit the same.
            assert_eq!(samples.zncc_each(&weights), one_by_one);
        }
    }

    #[test]
    fn a_flat_patch_scores_lowest_however_bright() {
        // A plain region of a bright photo: grey 0.8 with a ripple far below half a grey level.
        // In f32 its sums of squares differ by rounding only; before the flat-patch floor this
        // scored above 1 and out-ranked the object.
        let image = GrayImage32::from_fn(40, 40, |x, y| {
            0.8 + 1e-4 * (((y * 40 + x) * 7919 % 13) as f32 / 13.0)
        });
        let template = GrayImage32::from_fn(12, 12, |x, y| ((y * 12 + x) * 31 % 17) as f32 / 17.0);
        let points = TemplatePoints::new(&template, 12);
        let pose = Pose {
            x: 20.0,
            y: 20.0,
            angle_deg: 17.0,
            scale_x: 1.1,
            scale_y: 0.9,
            score: 0.0,
            network_score: 0.0,
        };
        assert_eq!(points.score(&image, &pose), -1.0);
        // Any patch with contrast stays within [-1, 1].
        let textured = GrayImage32 {
            values: image
                .values
                .iter()
                .enumerate()
                .map(|(i, v)| v + 0.1 * ((i as f32) * 0.37).sin())
                .collect(),
            ..image
        };
        assert!((-1.0..=1.0).contains(&points.score(&textured, &pose)));
    }

    /// A smooth random-looking texture.
    fn texture(w: usize, h: usize) -> GrayImage32 {
        let mut values = Vec::with_capacity(w * h);
        for y in 0..h {
            for x in 0..w {
                let (fx, fy) = (x as f32, y as f32);
                values.push(
                    0.5 + 0.2 * (fx * 0.21 + fy * 0.07).sin() * (fy * 0.17).cos()
                        + 0.15 * ((fx * 0.05 - fy * 0.11).sin() * 4.0).sin(),
                );
            }
        }
        GrayImage32 {
            width: w,
            height: h,
            values,
        }
    }

    /// Centre within 0.2 px and angle within 0.3° of the truth.
    fn assert_centre_and_angle(refined: &Pose, truth: &Pose) {
        assert!(
            (refined.x - truth.x).abs() < 0.2 && (refined.y - truth.y).abs() < 0.2,
            "{refined:?}"
        );
        assert!(
            (refined.angle_deg - truth.angle_deg).abs() < 0.3,
            "{refined:?}"
        );
    }

    /// A textured image, a true pose in it and the 36x36 template that pose maps onto it.
    fn posed_texture() -> (GrayImage32, Pose, GrayImage32) {
        let image = texture(160, 160);
        let truth = Pose {
            x: 80.3,
            y: 79.6,
            angle_deg: 33.0,
            scale_x: 1.2,
            scale_y: 0.9,
            score: 1.0,
            network_score: 0.0,
        };
        let template = cut_template(&image, &truth);
        (image, truth, template)
    }

    /// The 36x36 template that `truth` maps onto `image`.
    fn cut_template(image: &GrayImage32, truth: &Pose) -> GrayImage32 {
        let (tw, th) = (36usize, 36usize);
        let mut values = Vec::new();
        for b in 0..th {
            for a in 0..tw {
                let (x, y) = truth.map_point(a as f32 - 17.5, b as f32 - 17.5);
                values.push(image.sample(x, y));
            }
        }
        GrayImage32 {
            width: tw,
            height: th,
            values,
        }
    }

    /// A part whose texture is horizontal stripes, 1.3x wider than its template: along the
    /// stripes a narrower template fits as well, so a search started below the caller's scale
    /// range would stay there (and the answer would be filtered away). The verifier holds it
    /// to the range, where the part still matches.
    #[test]
    fn a_striped_part_is_confirmed_within_the_scale_range() {
        let stripes = |y: f32| 0.5 + 0.3 * (y * 0.9).sin() + 0.1 * (y * 0.31).sin();
        let (cx, cy, half_w, half_h) = (80.0f32, 80.0f32, 36.0 * 1.3 / 2.0, 18.0f32);
        let mut values = Vec::new();
        for y in 0..160 {
            for x in 0..160 {
                let inside = (x as f32 - cx).abs() <= half_w && (y as f32 - cy).abs() <= half_h;
                values.push(if inside { stripes(y as f32) } else { 0.45 });
            }
        }
        let image = GrayImage32 {
            width: 160,
            height: 160,
            values,
        };
        let truth = Pose {
            x: cx,
            y: cy,
            angle_deg: 0.0,
            scale_x: 1.3,
            scale_y: 1.0,
            score: 1.0,
            network_score: 0.0,
        };
        let template = cut_template(&image, &truth);
        let verifier = crate::matcher::verification::Verifier::new(
            &template,
            &image,
            Some((1.0, 1.5)),
            |_| true,
        );
        let start = Pose {
            scale_x: 0.7,
            ..truth
        };
        let confirmed = verifier.confirm(
            &crate::matcher::verification::Screened {
                pose: start,
                score: 0.0,
            },
            &start,
            Light::Even,
        );
        let pose = confirmed.pose;
        assert!(
            (1.0..=1.5).contains(&pose.scale_x) && (1.0..=1.5).contains(&pose.scale_y),
            "{pose:?}"
        );
        assert!(confirmed.similarity > 0.9, "{confirmed:?}");
    }

    #[test]
    fn recovers_a_known_pose_from_a_rough_start() {
        let (image, truth, template) = posed_texture();
        let rough = Pose {
            x: 81.0,
            y: 79.0,
            angle_deg: 27.0,
            scale_x: 1.1,
            scale_y: 1.0,
            score: 0.8,
            network_score: 0.0,
        };
        let refined = refine_pose(&template, &image, &rough);
        assert_centre_and_angle(&refined, &truth);
        assert!(
            (refined.scale_x - truth.scale_x).abs() < 0.01
                && (refined.scale_y - truth.scale_y).abs() < 0.01,
            "{refined:?}"
        );
        assert_eq!(refined.score, rough.score);
    }

    /// Light falling steeply across the part (its gain 1.5x from one side to the other): the
    /// alignment under [`Light::Planes`] lands on the part; under [`Light::Even`] the ramp
    /// pulls it off.
    #[test]
    fn light_falling_across_the_part_pulls_the_even_alignment_not_the_planes_one() {
        let (image, truth, template) = posed_texture();
        let lit = GrayImage32::from_fn(image.width, image.height, |x, y| {
            image.values[y * image.width + x] * (1.5 - 0.008 * x as f32)
        });
        let support = TemplatePoints::support(&template);
        let start = Pose {
            x: truth.x + 1.0,
            y: truth.y - 0.8,
            angle_deg: truth.angle_deg + 2.0,
            ..truth
        };
        let aligned = |light| align_from(&template, &support, &lit, &[start], &start, light).pose;
        let error = |pose: &Pose| (pose.x - truth.x).hypot(pose.y - truth.y);
        let (even, planes) = (aligned(Light::Even), aligned(Light::Planes));
        assert_centre_and_angle(&planes, &truth);
        assert!(error(&planes) < 0.05, "{planes:?}");
        assert!(error(&even) > 2.0 * error(&planes), "{even:?} {planes:?}");
    }

    #[test]
    fn recovers_an_angle_far_outside_the_local_grid() {
        let (image, truth, template) = posed_texture();
        // A weakly trained network: centre roughly right, angle 110° off.
        let rough = Pose {
            x: 81.5,
            y: 78.5,
            angle_deg: 143.0,
            scale_x: 1.1,
            scale_y: 1.0,
            score: 0.6,
            network_score: 0.0,
        };
        let refined = refine_pose(&template, &image, &rough);
        assert_centre_and_angle(&refined, &truth);
    }
}
