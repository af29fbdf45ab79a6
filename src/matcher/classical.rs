//! The classical baseline and weight-free fallback: exhaustive rotation x scale search with
//! zero-mean normalised cross-correlation over an image pyramid, the paper's NCC baseline.
//!
//! At a coarse pyramid level (template about 16 px) every angle (step from the template's
//! radius) and every scale pair of the requested range (25 % steps per axis) is scored at every
//! pixel with a sparse set of template points (every template pixel for a fine texture;
//! bilinear, vectorised along image rows); the best distinct local maxima go to the same
//! verifier as the network's candidates, at full resolution. It needs no weights and checks the
//! network on the same pairs; on held-out pairs it finds as many objects as a masked
//! coarse-to-fine OpenCV NCC (`scripts/opencv_ncc.py`) in less time, 2x less under scale
//! changes (docs/verification.md, "Classical matcher").

use std::time::Instant;

use rayon::prelude::*;

use crate::geometry::Pose;
use crate::imaging::{GrayImage32, gaussian_blur};
use crate::refine::{FLAT_PATCH_SPREAD, Light, PlaneFreePoints, TemplatePoints, zncc};

use super::error::MatchError;
use super::options::{Contrast, MatchOptions};
use super::selection::select;
use super::time_limit::TimeLimit;
use super::verification::{Screened, Verifier, correlation_length};

/// Ratio between neighbouring scales of the coarse grid.
const SCALE_STEP: f32 = 1.25;
/// Angle step of the coarse grid: this many pixels of arc at the template's rim.
const ANGLE_STEP_PX: f32 = 1.5;

/// Blur of the coarse level (its pixels), template and image alike: a fine texture (noise,
/// stripes) keeps some correlation between the grid's angle and scale steps. Measured on the
/// tuning pairs (lomiri and the training corpus, 36x36, S1.5 and multi-instance): recall in
/// scenes 0.956 without, 0.975 at 0.5, 0.978 at 0.7, 0.964 at 0.85; S1.5 Succ 95.7, 96.7,
/// 96.7, 96.7 % (with the verifier holding poses to the scale range).
const COARSE_SIGMA: f32 = 0.7;

/// Template points per side of the coarse level's sparse lattice (every other pixel of a
/// 16-24 px template, every third beyond).
const COARSE_POINTS_SIDE: usize = 12;

/// Correlation length (coarse-level pixels, [`correlation_length`]) below which the coarse
/// level scores every template pixel instead of the sparse grid. A fine texture (wood grain,
/// foliage, noise) decorrelates between grid points, and the grid's angle and scale steps leave
/// the true pose a pixel off, so its sparse score sinks into the chance maxima of the other
/// positions; four times the points average that out, at four times the coarse cost for those
/// templates only. Measured on the tuning pairs (lomiri and the training corpus, S1.5; times of
/// the baseline x86-64 build): Succ 96.5 % sparse everywhere (146 ms), 97.5 % below 1.3
/// (166 ms), 98.0 % below 1.5 (201 ms).
const DENSE_BELOW_CORRELATION_LENGTH: f32 = 1.3;

/// The coarse level's template points: every pixel of a fine texture, a sparse grid otherwise
/// ([`DENSE_BELOW_CORRELATION_LENGTH`]).
fn coarse_points(level_template: &GrayImage32) -> TemplatePoints {
    let side = match correlation_length(level_template) {
        Some(length) if length < DENSE_BELOW_CORRELATION_LENGTH => {
            level_template.width.max(level_template.height)
        }
        _ => COARSE_POINTS_SIDE,
    };
    TemplatePoints::new(level_template, side)
}

/// Distinct coarse peaks confirmed: this many per wanted instance, plus
/// [`PEAKS_BEYOND_INSTANCES`].
const PEAKS_PER_INSTANCE: usize = 4;
const PEAKS_BEYOND_INSTANCES: usize = 4;

/// Most sparse-ZNCC evaluations one search may cost (positions x angles x scale pairs at the
/// coarse level): about 2 s on the two-core target machine (a 224x224 image with a 36x36
/// template over scales 0.8-1.5 costs 7.6 million, 160 ms). Beyond it a search is refused with
/// what to narrow instead of holding the cores for minutes.
pub const MAX_SCORINGS: u64 = 100_000_000;

/// What the exhaustive search visits: the pyramid level and the angle x scale grid.
struct SearchPlan {
    /// Downsampling factor of the coarse level (a power of two).
    factor: f32,
    levels: usize,
    scales: Vec<f32>,
    angles: Vec<f32>,
    /// Coarse positions, `(columns, rows)`: every pixel of the coarse level (a sparse
    /// template's correlation peak is about a pixel wide there).
    grid: (usize, usize),
}

impl SearchPlan {
    /// Shrinks until the template's shorter side is about 16 px.
    fn new(tw: usize, th: usize, iw: usize, ih: usize, options: &MatchOptions) -> Self {
        let (mut tw, mut th, mut iw, mut ih) = (tw, th, iw, ih);
        let mut levels = 0;
        while tw.min(th) >= 32 && iw.min(ih) >= 64 {
            // As `GrayImage32::downsample` halves a side.
            (tw, th, iw, ih) = (tw / 2, th / 2, iw / 2, ih / 2);
            levels += 1;
        }
        // Scales relative to the registered template, the same at every level.
        let (lo, hi) = options.scale_range.map_or((1.0, 1.0), |r| (r.min, r.max));
        let scales: Vec<f32> = if hi > lo {
            let n = ((hi / lo).ln() / SCALE_STEP.ln()).ceil() as usize;
            (0..=n)
                .map(|k| lo * (hi / lo).powf(k as f32 / n as f32))
                .collect()
        } else {
            vec![lo]
        };
        let radius = tw.max(th) as f32 / 2.0;
        let angle_step = (ANGLE_STEP_PX / radius).to_degrees().clamp(2.0, 12.0);
        let angles: Vec<f32> = (0..(360.0 / angle_step).ceil() as usize)
            .map(|k| -180.0 + angle_step * (k as f32 + 0.5))
            .filter(|a| options.angle_range.is_none_or(|r| r.contains(*a)))
            .collect();
        Self {
            factor: (1u32 << levels) as f32,
            levels,
            scales,
            angles,
            grid: (iw, ih),
        }
    }

    fn scorings(&self) -> u64 {
        (self.grid.0 * self.grid.1) as u64
            * self.angles.len() as u64
            * (self.scales.len() * self.scales.len()) as u64
    }
}

/// Refuses a search that would cost more than [`MAX_SCORINGS`], saying what to narrow.
pub fn check_work(
    tw: u32,
    th: u32,
    iw: u32,
    ih: u32,
    options: &MatchOptions,
) -> Result<(), MatchError> {
    let plan = SearchPlan::new(tw as usize, th as usize, iw as usize, ih as usize, options);
    // Each contrast the polarity asks for is a search of its own.
    let scorings = plan.scorings() * options.polarity.contrasts().len() as u64;
    if scorings > MAX_SCORINGS {
        return Err(MatchError::ClassicalTooSlow {
            scorings,
            limit: MAX_SCORINGS,
        });
    }
    Ok(())
}

/// Finds the template in the image, in each contrast the options' polarity asks for; poses in
/// the public convention, best first. The caller checks the cost first ([`check_work`]).
pub fn ncc_match(template: &GrayImage32, image: &GrayImage32, options: &MatchOptions) -> Vec<Pose> {
    ncc_match_until(template, image, options, None).poses
}

/// What the classical matcher found by its time limit.
#[derive(Debug, Clone)]
pub struct ClassicalOutcome {
    pub poses: Vec<Pose>,
    /// Angles were left unsearched or peaks unconfirmed because the time limit had come.
    pub timed_out: bool,
}

/// [`ncc_match`] until `answer_by` (the options' `timeout_ms` after the request arrived): an
/// angle of the coarse search not started by then is left out (each takes a few milliseconds
/// on a 224 image, up to a few hundred on a 2048x2048 frame: the granularity of the limit), and
/// so is a peak not yet confirmed; the answer is what was found, with `timed_out`.
pub fn ncc_match_until(
    template: &GrayImage32,
    image: &GrayImage32,
    options: &MatchOptions,
    answer_by: Option<Instant>,
) -> ClassicalOutcome {
    let limit = TimeLimit::new(answer_by);
    let contrasts = options.polarity.contrasts();
    let mut poses = Vec::new();
    for &contrast in contrasts {
        poses.extend(match contrast {
            Contrast::Same => ncc_match_contrast(template, image, options, &limit),
            Contrast::Reversed => {
                let mut reversed = template.clone();
                reversed.values.iter_mut().for_each(|v| *v = 1.0 - *v);
                ncc_match_contrast(&reversed, image, options, &limit)
            }
        });
    }
    if contrasts.len() > 1 {
        poses = select(
            poses,
            options,
            template.width as f32,
            template.height as f32,
        );
    }
    ClassicalOutcome {
        poses,
        timed_out: limit.missed(),
    }
}

/// [`ncc_match`] for one contrast (the template's own).
fn ncc_match_contrast(
    template: &GrayImage32,
    image: &GrayImage32,
    options: &MatchOptions,
    limit: &TimeLimit,
) -> Vec<Pose> {
    let plan = SearchPlan::new(
        template.width,
        template.height,
        image.width,
        image.height,
        options,
    );
    let search = CoarseSearch {
        plan,
        points: coarse_points,
        peaks: PEAKS_PER_INSTANCE * options.max_instances + PEAKS_BEYOND_INSTANCES,
        max_point_samples: u64::MAX,
        limit,
    };
    let peaks = coarse_peaks(template, image, search).expect("no limit on the work");
    confirm_peaks(template, image, options, peaks, limit)
}

/// Most template-point samples (positions x angles x scale pairs x points, coarse level) that
/// the network path's classical fallback ([`fallback_candidates`]) may cost: about 65 ms on
/// the two-core target machine. A 224x224 image with a 36x36 template costs 35 million (about
/// 7.5 ms), so images up to about 650x650 pixels (or a region of interest of that size) get the
/// fallback and larger ones rely on the network alone.
pub const FALLBACK_MAX_POINT_SAMPLES: u64 = 300_000_000;

/// Distinct coarse peaks that the fallback hands to verification beyond
/// [`PEAKS_PER_INSTANCE`] per wanted instance. Its coarse level scores the sparse lattice
/// even for a fine texture (unlike [`coarse_points`]) and leaves the precision to the screen
/// of more peaks: on generated noise photos (tuning; authors' checkpoint, S1.5, 300 pairs;
/// four grey / six coloured photos) every pixel and 4 peaks found 91.7 / 85.3 % at 21 ms per
/// fallback, the lattice and 4 peaks 86.7 / 83.3 %, the lattice and 16 peaks 89.7 / 85.7 % at
/// 12 ms (28 peaks: 89.7 / 86.0 %).
const FALLBACK_PEAKS_BEYOND_INSTANCES: usize = 16;

/// A masked template's fallback searches the expected scale and this factor either side: its
/// network candidates are weak (docs/industrial.md, "Masks"), so the classical search carries
/// more of the search. Tuning set (47 held-out corpus photos + 2 lomiri images, 200 S1.5
/// pairs, a quarter covered and masked), found at the default `min_score`, plain cover /
/// clutter: one scale 84.0 / 91.0 % at 90 / 86 ms a pair, three 89.0 / 93.0 % at 123 ms.
const MASKED_FALLBACK_SCALE_STEP: f32 = 1.25;

/// Any template's fallback searches each axis at the expected scale divided and multiplied by
/// this (four scale pairs) where that fits [`FALLBACK_MAX_POINT_SAMPLES`]: the coarse level's
/// correlation holds about a scale step either side, so the pairs cover 0.7–1.45 of the
/// expected scale on each axis, where one scale lost the parts stretched on one axis. Under
/// `--condition dark-gamma` the pose is lost wherever the network's candidates do not verify,
/// and a search at the expected scale alone missed every such part whose larger axis was near
/// 1.4 (tuning set: 47 held-out corpus photos + 2 lomiri images, 200 S1.5 pairs, seed 0; the
/// classical matcher over the whole range found 5 of the 9 without an answer, at one scale
/// none). Same set, found at the defaults, one scale → four pairs: dark-gamma 89.5 → 91.5 %,
/// noise-15 95.0 → 96.0 %, uneven-light 74.0 → 75.5 %, clean 95.0 % unchanged; a scene without
/// the part, where the fallback always runs, 69–76 → 93–95 ms (answers ≥ 0.9 40 → 41). The
/// light evened out for the fallback's search as well (the screen's second look), alone or
/// beside the plain search, added two or three unevenly lit parts at 15–60 ms more a scene
/// without the part: not kept.
const FALLBACK_SCALE_FACTOR: f32 = 1.2;

/// The classical search as the network path's fallback, for when none of the network's
/// candidates verifies (docs/verification.md): its best distinct coarse peaks, as
/// candidates for the same verification as the network's (`network_score` 0). Every angle of
/// the caller's range at a few scale pairs around the template's expected scale (the
/// geometric middle of the caller's scale range, 1 without one): the widest of
/// [`MASKED_FALLBACK_SCALE_STEP`] (a masked template only), [`FALLBACK_SCALE_FACTOR`] and the
/// expected scale alone that fits [`FALLBACK_MAX_POINT_SAMPLES`], so that its cost stays near
/// the network's; the screen and confirmation then find the object's own scale. `None` (not
/// searched) when even the expected scale alone would cost more.
pub fn fallback_candidates(
    template: &GrayImage32,
    image: &GrayImage32,
    options: &MatchOptions,
) -> Option<Vec<Pose>> {
    let expected = options.scale_range.map_or(1.0, |r| (r.min * r.max).sqrt());
    let step = MASKED_FALLBACK_SCALE_STEP;
    let factor = FALLBACK_SCALE_FACTOR;
    let mut scale_sets = vec![vec![expected / factor, expected * factor], vec![expected]];
    if template.ignores_pixels() {
        scale_sets.insert(0, vec![expected / step, expected, expected * step]);
    }
    scale_sets.into_iter().find_map(|scales| {
        let mut plan = SearchPlan::new(
            template.width,
            template.height,
            image.width,
            image.height,
            options,
        );
        plan.scales = scales;
        let search = CoarseSearch {
            plan,
            points: |level_template| TemplatePoints::new(level_template, COARSE_POINTS_SIDE),
            peaks: PEAKS_PER_INSTANCE * options.max_instances + FALLBACK_PEAKS_BEYOND_INSTANCES,
            max_point_samples: FALLBACK_MAX_POINT_SAMPLES,
            limit: &TimeLimit::new(None),
        };
        coarse_peaks(template, image, search)
    })
}

/// One coarse search: where it looks, with which template points, how many distinct peaks it
/// keeps, the most template-point samples it may cost and until when it may search.
struct CoarseSearch<'a> {
    plan: SearchPlan,
    points: fn(&GrayImage32) -> TemplatePoints,
    peaks: usize,
    max_point_samples: u64,
    limit: &'a TimeLimit,
}

/// The best distinct local maxima of a coarse search, at full resolution and scored by the
/// coarse level's ZNCC; `None` when it would cost more than its template-point samples.
fn coarse_peaks(
    template: &GrayImage32,
    image: &GrayImage32,
    search: CoarseSearch<'_>,
) -> Option<Vec<Pose>> {
    let plan = search.plan;
    let mut level_template = template.clone();
    for _ in 0..plan.levels {
        level_template = level_template.downsample();
    }
    let level_template = gaussian_blur(&level_template, COARSE_SIGMA);
    let points = (search.points)(&level_template);
    let samples = plan
        .scorings()
        .saturating_mul(points.points().count() as u64);
    if samples > search.max_point_samples {
        return None;
    }
    let mut level_image = image.clone();
    for _ in 0..plan.levels {
        level_image = level_image.downsample();
    }
    let level_image = gaussian_blur(&level_image, COARSE_SIGMA);
    let factor = plan.factor;
    let hi = plan.scales.iter().copied().fold(1.0f32, f32::max);
    let (scales, angles) = (&plan.scales, &plan.angles);
    // Best score per coarse position, with the angle and scale pair that gave it: one map per
    // angle, in parallel, then the best over angles (the first of equal scores wins).
    let (gw, gh) = plan.grid;
    let pairs: Vec<(f32, f32)> = scales
        .iter()
        .flat_map(|&scale_x| scales.iter().map(move |&scale_y| (scale_x, scale_y)))
        .collect();
    let padded = Padded::new(&level_image, &points, hi);
    let plane_free = PlaneFreePoints::new(&points);
    let scorer = RowScorer::new(&points, plane_free.as_ref());
    let per_angle: Vec<BestMap> = angles
        .par_iter()
        .map(|&angle_deg| {
            let mut best = BestMap::new(gw * gh);
            if !search.limit.in_time() {
                return best;
            }
            for (pair, &scales) in pairs.iter().enumerate() {
                padded.score_rows(&scorer, angle_deg, scales, (gw, gh), |gy, row| {
                    let cells = gy * gw..(gy + 1) * gw;
                    keep_better(
                        &mut best.score[cells.clone()],
                        &mut best.which[cells],
                        row,
                        pair as u32,
                    );
                });
            }
            best
        })
        .collect();
    let mut best = vec![(-1.0f32, 0u32, 0u32); gw * gh];
    for (angle, map) in per_angle.iter().enumerate() {
        for ((cell, &score), &pair) in best.iter_mut().zip(&map.score).zip(&map.which) {
            if score > cell.0 {
                *cell = (score, angle as u32, pair);
            }
        }
    }
    // Local maxima of the best-score map, strongest first.
    let mut peaks: Vec<(f32, usize)> = Vec::new();
    for gy in 0..gh {
        for gx in 0..gw {
            let s = best[gy * gw + gx].0;
            let is_max = (gy.saturating_sub(1)..(gy + 2).min(gh))
                .all(|y| (gx.saturating_sub(1)..(gx + 2).min(gw)).all(|x| best[y * gw + x].0 <= s));
            if is_max && s > 0.2 {
                peaks.push((s, gy * gw + gx));
            }
        }
    }
    peaks.sort_by(|a, b| b.0.total_cmp(&a.0));
    // Distinct places only: a peak within half the template's shorter side of a stronger one
    // is the same place (texture along an edge gives a ridge of peaks).
    let radius = level_template.width.min(level_template.height) as f32 / 2.0;
    let at = |cell: usize| ((cell % gw) as f32, (cell / gw) as f32);
    let wanted = search.peaks;
    let mut distinct: Vec<(f32, usize)> = Vec::with_capacity(wanted);
    for (score, cell) in peaks {
        if distinct.len() == wanted {
            break;
        }
        let (x, y) = at(cell);
        if distinct.iter().all(|&(_, other)| {
            let (ox, oy) = at(other);
            (ox - x).hypot(oy - y) >= radius
        }) {
            distinct.push((score, cell));
        }
    }
    Some(
        distinct
            .into_iter()
            .map(|(score, cell)| {
                let (x, y) = at(cell);
                let (_, angle, pair) = best[cell];
                let (scale_x, scale_y) = pairs[pair as usize];
                Pose {
                    // Back to full resolution: pixel centres scale as (x + 0.5)·f − 0.5.
                    x: (x + 0.5) * factor - 0.5,
                    y: (y + 0.5) * factor - 0.5,
                    angle_deg: angles[angle as usize],
                    scale_x,
                    scale_y,
                    score: score.clamp(0.0, 1.0),
                    network_score: 0.0,
                }
            })
            .collect(),
    )
}

/// The best score of each coarse position over one angle's scale pairs, and which pair gave it
/// (an index into the search's pairs).
struct BestMap {
    score: Vec<f32>,
    which: Vec<u32>,
}

impl BestMap {
    /// Nothing scored yet: every position at -1, the lowest score.
    fn new(cells: usize) -> Self {
        Self {
            score: vec![-1.0; cells],
            which: vec![0; cells],
        }
    }
}

/// Keeps, position by position, the better of `best` and `row` (a row of one scale pair's
/// scores, `pair`), the earlier on a tie. Branch-free so that it vectorises.
#[multiversion::multiversion(targets("x86_64+avx512f", "x86_64+avx2"))]
fn keep_better(best: &mut [f32], which: &mut [u32], row: &[f32], pair: u32) {
    for ((b, w), &s) in best.iter_mut().zip(which.iter_mut()).zip(row) {
        let better = s > *b;
        *b = if better { s } else { *b };
        *w = if better { pair } else { *w };
    }
}

/// Confirms every coarse peak (refinement on; the coarse search already chose angle and
/// scales, so without a screen) and selects the answers; without refinement the peaks as they
/// are, scored by the coarse level's sparse ZNCC.
fn confirm_peaks(
    template: &GrayImage32,
    image: &GrayImage32,
    options: &MatchOptions,
    peaks: Vec<Pose>,
    limit: &TimeLimit,
) -> Vec<Pose> {
    let verifier = Verifier::for_options(template, image, options);
    let poses: Vec<Pose> = peaks
        .into_par_iter()
        .filter(|_| limit.in_time())
        .map(|initial| {
            if !options.verify {
                return initial;
            }
            // The score is the similarity at the refined pose, as for the network's answers.
            let verified = verifier.confirm(
                &Screened {
                    pose: initial,
                    score: initial.score,
                },
                &initial,
                Light::Even,
            );
            Pose {
                score: verified.score,
                ..verified.pose
            }
        })
        .collect();
    select(
        poses,
        options,
        template.width as f32,
        template.height as f32,
    )
}

/// The coarse level with its border replicated far enough that every template point of every
/// searched pose lands inside: the exhaustive search then reads pixels without a bounds check
/// or a clamp. Bilinear sampling of the padded image equals [`GrayImage32::sample`]'s clamped
/// sampling of the original, less the image's mean (which no ZNCC sees).
struct Padded {
    values: Vec<f32>,
    width: usize,
    pad: usize,
}

impl Padded {
    fn new(image: &GrayImage32, points: &TemplatePoints, max_scale: f32) -> Self {
        let reach = points
            .points()
            .map(|((u, v), _)| u.hypot(v))
            .fold(0f32, f32::max);
        let pad = (reach * max_scale).ceil() as usize + 2;
        let width = image.width + 2 * pad;
        let height = image.height + 2 * pad;
        let mut values = Vec::with_capacity(width * height);
        for y in 0..height {
            let sy = y.saturating_sub(pad).min(image.height - 1);
            let row = &image.values[sy * image.width..(sy + 1) * image.width];
            values.extend(std::iter::repeat_n(row[0], pad));
            values.extend_from_slice(row);
            values.extend(std::iter::repeat_n(row[image.width - 1], pad));
        }
        // Centred on the image's mean: the scores' variances are differences of sums of
        // squares, which stay far above f32 rounding only for values near zero (see `zncc`).
        let mean = image.values.iter().sum::<f32>() / image.values.len() as f32;
        values.iter_mut().for_each(|v| *v -= mean);
        Self { values, width, pad }
    }

    /// The coarse score ([`RowScorer`]) at `angle_deg` and the scales at every pixel of the
    /// `gw x gh` image, handed a row at a time to `visit(gy, scores)`. On integer positions
    /// each point's bilinear weights are the same everywhere, so they are worked out once per
    /// pose and a row of positions is one vectorised pass per point.
    fn score_rows(
        &self,
        scorer: &RowScorer,
        angle_deg: f32,
        (scale_x, scale_y): (f32, f32),
        (gw, gh): (usize, usize),
        mut visit: impl FnMut(usize, &[f32]),
    ) {
        let (s, c) = angle_deg.to_radians().sin_cos();
        let (ax, ay) = (scale_x * c, -scale_x * s);
        let (bx, by) = (scale_y * s, scale_y * c);
        let taps: Vec<PointTap> = scorer
            .points
            .iter()
            .map(|point| {
                let (u, v) = point.offset;
                let (dx, dy) = (ax * u + bx * v, ay * u + by * v);
                let (fx, fy) = (dx - dx.floor(), dy - dy.floor());
                let x = (dx.floor() as isize + self.pad as isize) as usize;
                let y = (dy.floor() as isize + self.pad as isize) as usize;
                PointTap {
                    offset: y * self.width + x,
                    bilinear: [
                        (1.0 - fx) * (1.0 - fy),
                        fx * (1.0 - fy),
                        (1.0 - fx) * fy,
                        fx * fy,
                    ],
                    point: *point,
                }
            })
            .collect();
        let mut sums = RowSums::new(gw);
        let mut scores = vec![0f32; gw];
        let row_width = self.width;
        for gy in 0..gh {
            sums.clear();
            let row = RowOfPositions {
                values: &self.values,
                start: gy * row_width,
                row_width,
                len: gw,
            };
            accumulate_row(&row, &taps, &mut sums);
            match &scorer.plane {
                Some(plane) => plane_free_row(&sums, plane, taps.len(), &mut scores),
                None => zncc_row(&sums, taps.len(), &mut scores),
            }
            visit(gy, &scores);
        }
    }
}

/// What the coarse search scores at a position: the template's plane-free correlation, the
/// ZNCC with a plane `a + b·u + c·v` fitted out of the template and of the image samples alike
/// ([`PlaneFreePoints`]); the plain ZNCC only for a template that is itself a plane.
///
/// Why: a lamp on one side multiplies a part by a ramp of light. Over a part whose detail is
/// faint against its mean grey (fine grain over a gradient, a matt surface), the ramp is
/// larger than the detail on the coarse level, where the search decides which places the
/// verification sees at all; the plain ZNCC at the part then falls below chance peaks
/// elsewhere. On the generated grain tuning photos (`scripts/grain-photos.py`), 200 unevenly
/// lit S1.5 pairs, of the 23 that neither the network nor this search found, the truth's
/// coarse position was the best of its map at the true angle and scales in 12 by the plain ZNCC
/// (median 0.41 there) and in all 23 by the plane-free one (median 0.89). Taking the better of
/// the two instead lets a part's own gradient match the ramp elsewhere: a plain peak of 0.98
/// away from the part (test `a_faint_part_under_a_ramp_of_light_is_the_fallbacks_first_candidate`),
/// and on the tuning photos it found no part that the plane-free score alone missed
/// (docs/industrial.md, "Camera conditions").
struct RowScorer {
    points: Vec<CoarsePoint>,
    /// `(AᵀA)⁻¹` of the plane's fit ([`PlaneFreePoints::inverse_normal`]); `None` where the
    /// template is itself a plane and the plain ZNCC is scored.
    plane: Option<[[f32; 3]; 3]>,
}

/// One template point of the coarse search: its offset from the template centre and its
/// weight (plane-free where the search scores the plane-free correlation, the zero-mean
/// unit-norm template value otherwise).
#[derive(Clone, Copy)]
struct CoarsePoint {
    offset: (f32, f32),
    weight: f32,
}

impl RowScorer {
    fn new(points: &TemplatePoints, plane_free: Option<&PlaneFreePoints>) -> Self {
        let weights: Vec<f32> = match plane_free {
            Some(plane_free) => plane_free.weights().iter().map(|&w| w as f32).collect(),
            None => points.points().map(|(_, w)| w).collect(),
        };
        Self {
            points: points
                .points()
                .zip(weights)
                .map(|((offset, _), weight)| CoarsePoint { offset, weight })
                .collect(),
            plane: plane_free.map(|p| p.inverse_normal().map(|row| row.map(|v| v as f32))),
        }
    }
}

/// One row of coarse positions of the padded image: where [`Padded::score_rows`] spends its
/// time.
struct RowOfPositions<'a> {
    values: &'a [f32],
    /// Index of the row's first position's own pixel (the tap offsets are relative to it).
    start: usize,
    row_width: usize,
    len: usize,
}

/// A template point in the grid scorer: index of its top-left neighbour relative to the
/// position, its bilinear weights, and the point itself.
struct PointTap {
    offset: usize,
    bilinear: [f32; 4],
    point: CoarsePoint,
}

/// The sums over a row of positions that a coarse score is made of: the samples' sum, sum of
/// squares, dot with the points' weights, and moments along the template's axes (`Σ u·I`,
/// `Σ v·I`, for the plane-free correlation).
struct RowSums {
    sum: Vec<f32>,
    sum_sq: Vec<f32>,
    dot: Vec<f32>,
    moment_u: Vec<f32>,
    moment_v: Vec<f32>,
}

impl RowSums {
    fn new(len: usize) -> Self {
        Self {
            sum: vec![0.0; len],
            sum_sq: vec![0.0; len],
            dot: vec![0.0; len],
            moment_u: vec![0.0; len],
            moment_v: vec![0.0; len],
        }
    }

    fn clear(&mut self) {
        for sums in [
            &mut self.sum,
            &mut self.sum_sq,
            &mut self.dot,
            &mut self.moment_u,
            &mut self.moment_v,
        ] {
            sums.fill(0.0);
        }
    }
}

/// Adds every point's bilinear sample at every position of the row to the running sums.
/// Compiled for baseline x86-64 and again for AVX2 and AVX-512, chosen at run time
/// (`multiversion`): 8 or 16 lanes instead of 4 on the classical search's hot loop (tuning
/// pairs at S1.5, two cores: 163 ms per pair on baseline x86-64, 82 ms with AVX-512). No
/// version fuses multiply-adds, so all round alike.
///
/// Four points a pass over the row: each position's sums take the four samples one after
/// another, in the points' order (the same numbers as a pass per point), but are read and
/// written once instead of four times. With a pass per point the loop loaded and stored the
/// five sums for every sample it took, and was a third of a scene's time where the classical
/// fallback ran (`perf`, held-out mate pairs).
#[multiversion::multiversion(targets("x86_64+avx512f", "x86_64+avx2"))]
fn accumulate_row(row: &RowOfPositions, taps: &[PointTap], sums: &mut RowSums) {
    let (gw, row_width) = (row.len, row.row_width);
    // Equal-length slices, so that the loops below run without bounds checks and vectorise.
    let sum = &mut sums.sum[..gw];
    let sum_sq = &mut sums.sum_sq[..gw];
    let dot = &mut sums.dot[..gw];
    let moment_u = &mut sums.moment_u[..gw];
    let moment_v = &mut sums.moment_v[..gw];
    // The neighbours of every position in the row: top left, top right, bottom left, bottom
    // right.
    let neighbours = |tap: &PointTap| -> [&[f32]; 4] {
        let start = row.start + tap.offset;
        let top = &row.values[start..start + gw + 1];
        let bottom = &row.values[start + row_width..start + row_width + gw + 1];
        [&top[..gw], &top[1..], &bottom[..gw], &bottom[1..]]
    };
    let mut fours = taps.chunks_exact(4);
    for four in &mut fours {
        let [a, b, c, d] = [&four[0], &four[1], &four[2], &four[3]];
        let [a0, a1, a2, a3] = neighbours(a);
        let [b0, b1, b2, b3] = neighbours(b);
        let [c0, c1, c2, c3] = neighbours(c);
        let [d0, d1, d2, d3] = neighbours(d);
        let [aw0, aw1, aw2, aw3] = a.bilinear;
        let [bw0, bw1, bw2, bw3] = b.bilinear;
        let [cw0, cw1, cw2, cw3] = c.bilinear;
        let [dw0, dw1, dw2, dw3] = d.bilinear;
        for i in 0..gw {
            let va = aw0 * a0[i] + aw1 * a1[i] + aw2 * a2[i] + aw3 * a3[i];
            let vb = bw0 * b0[i] + bw1 * b1[i] + bw2 * b2[i] + bw3 * b3[i];
            let vc = cw0 * c0[i] + cw1 * c1[i] + cw2 * c2[i] + cw3 * c3[i];
            let vd = dw0 * d0[i] + dw1 * d1[i] + dw2 * d2[i] + dw3 * d3[i];
            sum[i] = sum[i] + va + vb + vc + vd;
            sum_sq[i] = sum_sq[i] + va * va + vb * vb + vc * vc + vd * vd;
            dot[i] = dot[i]
                + a.point.weight * va
                + b.point.weight * vb
                + c.point.weight * vc
                + d.point.weight * vd;
            moment_u[i] = moment_u[i]
                + a.point.offset.0 * va
                + b.point.offset.0 * vb
                + c.point.offset.0 * vc
                + d.point.offset.0 * vd;
            moment_v[i] = moment_v[i]
                + a.point.offset.1 * va
                + b.point.offset.1 * vb
                + c.point.offset.1 * vc
                + d.point.offset.1 * vd;
        }
    }
    for tap in fours.remainder() {
        let [w00, w01, w10, w11] = tap.bilinear;
        let CoarsePoint {
            offset: (u, v),
            weight,
        } = tap.point;
        let [t0, t1, b0, b1] = neighbours(tap);
        for i in 0..gw {
            let value = w00 * t0[i] + w01 * t1[i] + w10 * b0[i] + w11 * b1[i];
            sum[i] += value;
            sum_sq[i] += value * value;
            dot[i] += weight * value;
            moment_u[i] += u * value;
            moment_v[i] += v * value;
        }
    }
}

/// [`zncc`] of every position of a row, from its sums over the `n` points (in vectors: `zncc`
/// has no branch).
#[multiversion::multiversion(targets("x86_64+avx512f", "x86_64+avx2"))]
fn zncc_row(sums: &RowSums, n: usize, scores: &mut [f32]) {
    for (((score, &d), &s), &q) in scores
        .iter_mut()
        .zip(&sums.dot)
        .zip(&sums.sum)
        .zip(&sums.sum_sq)
    {
        *score = zncc(d, s, q, n);
    }
}

/// Each position's plane-free correlation: the dot of the plane-free weights with the samples
/// over the samples' spread about their own plane
/// (`Σ I² − mᵀ (AᵀA)⁻¹ m`), -1 where that spread is flat ([`FLAT_PATCH_SPREAD`]), as
/// [`PlaneFreePoints::score`] reads one pose.
#[multiversion::multiversion(targets("x86_64+avx512f", "x86_64+avx2"))]
fn plane_free_row(sums: &RowSums, inverse: &[[f32; 3]; 3], n: usize, scores: &mut [f32]) {
    let flat = n as f32 * FLAT_PATCH_SPREAD * FLAT_PATCH_SPREAD;
    let [[a, b, c], [_, d, e], [_, _, f]] = *inverse;
    let len = scores.len();
    let (sum, sum_sq) = (&sums.sum[..len], &sums.sum_sq[..len]);
    let (dot, mu, mv) = (
        &sums.dot[..len],
        &sums.moment_u[..len],
        &sums.moment_v[..len],
    );
    for i in 0..len {
        let (m0, m1, m2) = (sum[i], mu[i], mv[i]);
        // The inverse is symmetric: mᵀ N m from its upper triangle.
        let explained = a * m0 * m0
            + d * m1 * m1
            + f * m2 * m2
            + 2.0 * (b * m0 * m1 + c * m0 * m2 + e * m1 * m2);
        let variance = sum_sq[i] - explained;
        let similarity = (dot[i] / variance.max(f32::MIN_POSITIVE).sqrt()).clamp(-1.0, 1.0);
        scores[i] = if variance <= flat { -1.0 } else { similarity };
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn four_points_a_pass_sum_as_one_point_a_pass() {
        let (row_width, rows) = (41usize, 6usize);
        let values: Vec<f32> = (0..row_width * rows)
            .map(|i| ((i * 7919) % 113) as f32 / 113.0)
            .collect();
        let row = RowOfPositions {
            values: &values,
            start: 3,
            row_width,
            len: 30,
        };
        let tap = |k: usize| {
            let fx = (k as f32 * 0.37).fract();
            let fy = (k as f32 * 0.61).fract();
            PointTap {
                offset: k % 5 + (k % 3) * row_width,
                bilinear: [
                    (1.0 - fx) * (1.0 - fy),
                    fx * (1.0 - fy),
                    (1.0 - fx) * fy,
                    fx * fy,
                ],
                point: CoarsePoint {
                    offset: (k as f32 - 4.5, 2.0 - (k % 4) as f32),
                    weight: (k as f32 * 0.9).sin(),
                },
            }
        };
        // Counts with and without points left over after the fours.
        for count in [1usize, 4, 7, 13] {
            let taps: Vec<PointTap> = (0..count).map(tap).collect();
            let mut together = RowSums::new(row.len);
            accumulate_row(&row, &taps, &mut together);
            let mut one_by_one = RowSums::new(row.len);
            for tap in &taps {
                accumulate_row(&row, std::slice::from_ref(tap), &mut one_by_one);
            }
            assert_eq!(together.sum, one_by_one.sum);
            assert_eq!(together.sum_sq, one_by_one.sum_sq);
            assert_eq!(together.dot, one_by_one.dot);
            assert_eq!(together.moment_u, one_by_one.moment_u);
            assert_eq!(together.moment_v, one_by_one.moment_v);
        }
    }

    #[test]
    fn the_grid_scorer_equals_the_pointwise_score_borders_included() {
        let (w, h) = (40usize, 30usize);
        let image = GrayImage32 {
            width: w,
            height: h,
            values: (0..w * h)
                .map(|i| ((i % w) as f32 * 0.37).sin() * ((i / w) as f32 * 0.21).cos())
                .collect(),
        };
        let template = GrayImage32 {
            width: 12,
            height: 10,
            values: (0..120).map(|i| ((i * 7919) % 97) as f32 / 97.0).collect(),
        };
        let points = TemplatePoints::new(&template, 12);
        let padded = Padded::new(&image, &points, 1.4);
        let plane_free = PlaneFreePoints::new(&points).expect("the template is no plane");
        let plain = RowScorer::new(&points, None);
        let plane_free_scorer = RowScorer::new(&points, Some(&plane_free));
        for (angle_deg, scale_x, scale_y) in [(0.0, 1.0, 1.0), (-63.0, 1.4, 0.8), (171.0, 0.9, 1.3)]
        {
            let pose = Pose {
                x: 0.0,
                y: 0.0,
                angle_deg,
                scale_x,
                scale_y,
                score: 0.0,
                network_score: 0.0,
            };
            let grid = (w, h);
            let at = |gx: usize, gy: usize| Pose {
                x: gx as f32,
                y: gy as f32,
                ..pose
            };
            let mut visited = 0;
            padded.score_rows(&plain, angle_deg, (scale_x, scale_y), grid, |gy, row| {
                for (gx, &fast) in row.iter().enumerate() {
                    let slow = points.score(&image, &at(gx, gy));
                    assert!(
                        (fast - slow).abs() < 1e-4,
                        "{:?}: {fast} vs {slow}",
                        at(gx, gy)
                    );
                    visited += 1;
                }
            });
            assert_eq!(visited, grid.0 * grid.1);
            // The plane-free correlation, as one pose reads it.
            padded.score_rows(
                &plane_free_scorer,
                angle_deg,
                (scale_x, scale_y),
                grid,
                |gy, row| {
                    for (gx, &fast) in row.iter().enumerate() {
                        let pose = at(gx, gy);
                        let slow = plane_free.score(&points.samples(&image, &pose));
                        assert!((fast - slow).abs() < 1e-3, "{pose:?}: {fast} vs {slow}");
                    }
                },
            );
        }
    }

    #[test]
    fn a_fine_texture_is_scored_at_every_pixel_a_smooth_one_on_a_grid() {
        let (w, h) = (18usize, 18usize);
        let noise = GrayImage32::from_fn(w, h, |x, y| ((y * w + x) * 7919 % 97) as f32 / 97.0);
        let smooth =
            GrayImage32::from_fn(w, h, |x, y| (x as f32 * 0.3).sin() * (y as f32 * 0.2).cos());
        assert_eq!(coarse_points(&noise).points().count(), w * h);
        assert_eq!(coarse_points(&smooth).points().count(), 9 * 9);
    }

    #[test]
    fn finds_a_rotated_copy_without_any_weights() {
        let (w, h) = (96usize, 96usize);
        let texture = |x: f32, y: f32| {
            0.5 + 0.2 * (x * 0.23 + y * 0.05).sin() * (y * 0.19).cos()
                + 0.15 * ((x * 0.07 - y * 0.13).sin() * 4.0).sin()
        };
        let image = GrayImage32 {
            width: w,
            height: h,
            values: (0..w * h)
                .map(|i| texture((i % w) as f32, (i / w) as f32))
                .collect(),
        };
        let truth = Pose {
            x: 47.2,
            y: 50.6,
            angle_deg: -62.0,
            scale_x: 1.0,
            scale_y: 1.0,
            score: 1.0,
            network_score: 0.0,
        };
        let values = (0..24 * 24)
            .map(|i| {
                let (x, y) = truth.map_point((i % 24) as f32 - 11.5, (i / 24) as f32 - 11.5);
                texture(x, y)
            })
            .collect();
        let template = GrayImage32 {
            width: 24,
            height: 24,
            values,
        };
        let options = MatchOptions {
            max_instances: 1,
            ..MatchOptions::default()
        };
        let found = ncc_match(&template, &image, &options);
        let p = found[0];
        assert!(
            (p.x - truth.x).abs() < 0.3 && (p.y - truth.y).abs() < 0.3,
            "{p:?}"
        );
        assert!(
            crate::geometry::angle_distance_deg(p.angle_deg, truth.angle_deg) < 0.5,
            "{p:?}"
        );
    }

    /// A 36x36 template of what `scene` shows under `truth`: the part the search should find
    /// there.
    fn part_at(truth: &Pose, scene: impl Fn(f32, f32) -> f32) -> GrayImage32 {
        GrayImage32::from_fn(36, 36, |u, v| {
            let (x, y) = truth.map_point(u as f32 - 17.5, v as f32 - 17.5);
            scene(x, y)
        })
    }

    #[test]
    fn the_fallback_proposes_a_part_stretched_on_one_axis_at_a_stretched_scale_pair() {
        // Value noise on a 4 px lattice: detail that a scale 1.4 off on one axis spoils.
        let lattice = crate::refine::textured(64, 64, 7);
        let texture = |x: f32, y: f32| lattice.sample(x / 4.0, y / 4.0);
        let image = GrayImage32::from_fn(224, 224, |x, y| texture(x as f32, y as f32));
        let truth = Pose {
            x: 120.3,
            y: 97.8,
            angle_deg: 35.0,
            scale_x: 1.42,
            scale_y: 0.86,
            score: 1.0,
            network_score: 0.0,
        };
        let template = part_at(&truth, texture);
        let found = fallback_candidates(&template, &image, &MatchOptions::default())
            .expect("a 224x224 search with a 36x36 template fits the fallback's budget");
        let nearest = found
            .iter()
            .min_by(|a, b| {
                let distance = |p: &Pose| (p.x - truth.x).hypot(p.y - truth.y);
                distance(a).total_cmp(&distance(b))
            })
            .expect("candidates");
        assert!(
            (nearest.x - truth.x).hypot(nearest.y - truth.y) < 4.0,
            "{nearest:?}"
        );
        // Proposed wider than high, as the part is: the screen starts from the right side.
        assert!(
            nearest.scale_x > 1.1 && nearest.scale_y < 0.9,
            "{nearest:?}"
        );
    }

    #[test]
    fn a_faint_part_under_a_ramp_of_light_is_the_fallbacks_first_candidate() {
        // Fine grain of a few grey levels over a gradient (the grain tuning photos), and a lamp
        // on one side: the gain falls from 1.3 to 0.4 across the frame.
        let grain = crate::refine::textured(64, 64, 5);
        let scene = |x: f32, y: f32| {
            0.3 + 0.3 * x / 223.0 + 0.1 * y / 223.0 + 0.04 * (grain.sample(x / 4.0, y / 4.0) - 0.5)
        };
        let truth = Pose {
            x: 150.4,
            y: 81.7,
            angle_deg: 25.0,
            scale_x: 1.1,
            scale_y: 1.1,
            score: 1.0,
            network_score: 0.0,
        };
        let template = part_at(&truth, scene);
        let lit = GrayImage32::from_fn(224, 224, |x, y| {
            let gain = 1.3 - 0.9 * (x as f32 + y as f32) / 446.0;
            (scene(x as f32, y as f32) * gain).clamp(0.0, 1.0)
        });
        let found = fallback_candidates(&template, &lit, &MatchOptions::default())
            .expect("a 224x224 search with a 36x36 template fits the fallback's budget");
        let first = found.first().expect("candidates");
        assert!(
            (first.x - truth.x).hypot(first.y - truth.y) < 4.0,
            "{first:?}"
        );
    }

    #[test]
    fn a_passed_time_limit_answers_at_once_and_says_it_timed_out() {
        let (w, h) = (128usize, 128usize);
        let texture = |x: f32, y: f32| 0.5 + 0.2 * (x * 0.23 + y * 0.05).sin() * (y * 0.19).cos();
        let image = GrayImage32 {
            width: w,
            height: h,
            values: (0..w * h)
                .map(|i| texture((i % w) as f32, (i / w) as f32))
                .collect(),
        };
        let template = GrayImage32 {
            width: 32,
            height: 32,
            values: (0..32 * 32)
                .map(|i| texture((i % 32) as f32 + 100.0, (i / 32) as f32 + 60.0))
                .collect(),
        };
        let options = MatchOptions::default();
        let unlimited = ncc_match_until(&template, &image, &options, None);
        assert!(!unlimited.timed_out && !unlimited.poses.is_empty());
        // Due before it starts: no angle is searched, no peak confirmed.
        let passed = ncc_match_until(&template, &image, &options, Some(Instant::now()));
        assert!(passed.timed_out);
        assert!(passed.poses.is_empty(), "{:?}", passed.poses);
    }
}
