//! Verification of many candidates in one image: the network proposes, the image decides.
//!
//! Why: a network's best peak is not always the object (a weakly trained one is often wrong
//! where the object is among its next few peaks), and its heatmap value is not comparable
//! between templates or weights. So every candidate is checked against the image itself with
//! the refinement's scorer, and the answer's score is the similarity found there.
//!
//! 1. **Screen** ([`Verifier::screen`]), every candidate: the refinement's angle x scales search
//!    (±30° around the network's angle, the whole circle when nothing there fits) at the
//!    candidate's centre, on a pyramid level where the object is 16–32 pixels across (image and
//!    template halved together, as the classical matcher does) with about 12 template points a
//!    side, then ten Gauss–Newton steps of all five parameters on that level blurred by one
//!    pixel. The alignment matters: a weakly trained network's peaks are often several pixels
//!    off the object, where a search at a fixed centre scores the object no better than a
//!    decoy. A fraction of a millisecond per candidate. Where the weights were not trained on
//!    the template's shape ([`Heads::Untrusted`]) the network's scales and centre are not
//!    believed: the screen starts at the expected scale, from a ring of centres around the peak.
//! 2. **Confirm** ([`Verifier::confirm`]), only the candidates that survive the screen: the
//!    refinement's fine search and five-parameter alignment at full resolution, then the
//!    similarity (ZNCC over the template's support) at the refined pose.
//!
//! 3. **Stand out** ([`lift_standing_out`]): an answer that scores far above every other place
//!    the screen scored in the same image reports at least the default `min_score`
//!    (docs/accuracy.md, "What a score means"). JPEG and defocus lower a part's correlation
//!    and its look-alikes' alike; the order holds where the level does not.
//!
//! [`verify_candidates`] runs these over one image's candidates: screen every candidate, confirm
//! the best distinct survivors, lift those that stand out, then hand the confirmed poses to
//! [`super::selection`].

use std::ops::ControlFlow;
use std::sync::{Arc, OnceLock};
use std::time::Instant;

use rayon::prelude::*;

use super::options::MatchOptions;
use super::selection::{ANGLE_MARGIN_DEG, select};
use super::time_limit::TimeLimit;
use crate::geometry::{Pose, rotated_iou, wrap_angle_deg};
use crate::imaging::GrayImage32;
use crate::refine::{
    AngleScaleGrid, Coverage, CoverageReading, Light, LightCurve, NoiseLevel, NoisePoints,
    PlaneFreePoints, RankPoints, Scored, ShadingPoints, Sharpness, TemplatePoints, align,
    align_from, align_from_reach, fine_search, stayed_near,
};

/// Screen ZNCC below which a candidate is not worth confirming: a true object at the right
/// angle scores far above it even with its centre a few pixels off (docs/verification.md).
pub const SCREEN_MIN: f32 = 0.3;

/// Fewer screens than the caller's `max_instances` at or above this, and every candidate is
/// screened again on the level with the light evened out ([`Verifier::screen_evened`]). Under
/// light that falls across the frame (1.3 to 0.4) a part's own candidate was screened to a
/// wrong angle or scale (the gain across the part pulls the alignment), while a clean part's
/// screen reaches 0.97 and costs nothing more. Tuning photos (lomiri, 200 S1.5 pairs, seed 0),
/// found at the defaults: uneven light 91.0 → 94.0 %, dark-gamma 95.5 → 97.0 %, clean 99.5 %,
/// noise 98.5 %, defocus 94.0 %, JPEG 100 % unchanged (docs/industrial.md, "Camera
/// conditions", has the variants measured).
const RESCREEN_BELOW: f32 = 0.97;

/// Half the side of the window whose mean evens out the light on the screening level, in
/// object sides on the level (tuning photos, uneven light / defocus: 1.0 gave 94.0 / 93.5 %,
/// 1.7 94.0 / 94.0 %).
const EVEN_LIGHT_WINDOW: f32 = 1.7;

/// Correlation length (template pixels, [`correlation_length`]) below which the second screen
/// also looks at full resolution ([`Verifier::screen_evened_also_at`]). Tuning sets (grain
/// and lomiri photos, 1000 S1.5 pairs each, seed 0), found at the defaults under
/// `uneven-light` / answers at or above 0.9 in 1000 scenes without the part, grain and lomiri:
/// halved level only 91.0 / 111, 98.1 / 45 %; with the full level below 2.5 94.4 / 112, 98.5
/// / 45; for every template 94.8 / 114, 98.5 / 48.
const FULL_RESOLUTION_BELOW_CORRELATION_LENGTH: f32 = 2.5;

/// Image noise (grey levels, [`NoiseLevel`]) from which the second screen stays on the halved
/// level, whose averaging holds the noise down: clean tuning frames read 1.2–3.1, `noise-15`
/// ones 10–11. Without it the grain set's noisy pairs gained 7 of 1000 and the lomiri set's
/// lost 2, and 1000 noisy scenes without the part gave 4 more answers at or above 0.9 (82 → 83
/// and 36 → 39).
const FULL_RESOLUTION_MAX_NOISE: f32 = 5.0;

/// The score under which a confirmed pose is aligned again under the light's curve
/// ([`Verifier::aligned_under_the_curve`]): the default `min_score`, where an answer would be
/// dropped.
pub const CURVED_BELOW: f32 = 0.9;

/// How much more than the confirmed pose a pose aligned under [`Light::Planes`] must score to
/// replace it ([`Verifier::confirm`]). Four more free parameters fit any place a little better:
/// in the corpus tuning photos' scenes without the part (uneven light, 200) such alignments
/// raised look-alikes by 0.02–0.05 (three over 0.9 at no margin), the parts they found by
/// 0.08–0.8.
pub const SHADED_MARGIN: f32 = 0.07;

/// Survivors of the screen confirmed beyond `max_instances` (near-misses of the screen ranking).
pub const SPARE_SURVIVORS: usize = 1;

/// Largest object size (pixels, the geometric mean of its sides at the expected scale) on the
/// screening level: the image is halved until the object is smaller than this. The mean, not
/// the shorter side: an elongated part (28x52) screened at full resolution has a basin of
/// about a pixel along its short side, too narrow for a peak 4–6 px off; on the half level the
/// same alignment pulls it in (frame of `cargo bench --bench frames`, authors' checkpoint:
/// recall 0.975 → 0.984; tuning photos, 28x52, default weights: verified 80.3 → 89.3 %).
const SCREEN_OBJECT_SIDE: f32 = 32.0;

/// How far beyond the expected scale range an answer's scales may lie (the network covers
/// roughly 0.5–2x of the template's size when no range is given).
const SCALE_SLACK: f32 = 2.5;

/// Largest ratio between an answer's two scales.
const MAX_ANISOTROPY: f32 = 2.5;

/// Blur of the screening level's alignment (level pixels): a basin of a few pixels.
const LEVEL_SIGMA: f32 = 1.0;

/// Angles of the screen's grid at which every scale pair is tried: the best few at the
/// candidate's own scales. Measured on lomiri-wallpapers (500 pairs, default weights, 100
/// candidates): every angle x scales 79.2 % at 80 ms per pair, the best 3 angles 79.6 % at
/// 64 ms, the best 5 79.0 %. At those angles near the network's angle the scale pairs are
/// searched isotropic first, then 3x3 around the best (13 pairs instead of 25; tuning photos,
/// verified Succ default / official: corpus photos 96.4 → 96.6 / 98.8 → 98.4 %, lomiri 98.4 →
/// 97.8 / 99.8 → 100 %, generated noise 300 pairs official 62.3 → 64.3 %; about 2.5 ms less
/// per 224 pair). The best 2 angles instead of 3 saved 1–2 ms more but lost noise pairs
/// (60.3 %).
const SCREEN_ANGLES_KEPT: usize = 3;

/// Screening levels up to this many pixels are blurred once for every candidate's alignment
/// instead of once per candidate (a 224 pair's level: 12 544 pixels, against a window of
/// about 4 000 per candidate and a hundred candidates; the 2048 frame's level, 1024x1024:
/// 12 MB for the level and its gradients, 2048 frame of `cargo bench --bench frames` 1923 →
/// 1873 ms together with the vector sampling). Larger levels keep per-candidate windows,
/// which bound the memory.
const WHOLE_LEVEL_PIXELS: usize = 1 << 20;

/// Gauss–Newton iterations of the screening level's alignment.
const LEVEL_ITERATIONS: usize = 10;

/// The screening level's alignment stops once a step lowers its residual by less than this
/// share: the screen ranks candidates, confirmation makes the pose precise. Tuning photos
/// (S1.5, 500 pairs; verified Succ default / official): corpus photos 97.8 / 98.4 %, lomiri
/// 99.4 / 100 % at 1e-5 and at 1e-2; generated noise (official, 300 pairs) 89.7 → 89.0 %, 85.7
/// → 85.0 %; about 1.5 ms less per 224 pair with the default weights.
const LEVEL_TOLERANCE: f64 = 1e-2;

/// A candidate after the screen: its centre, the best angle and scales found there and their
/// sparse ZNCC on the screening level, in [-1, 1].
#[derive(Debug, Clone, Copy)]
pub struct Screened {
    pub pose: Pose,
    pub score: f32,
}

/// A candidate after confirmation: the refined pose, the template's similarity there (ZNCC
/// over the template's support, in [-1, 1]) and that similarity as a score (see
/// [`Verifier::score`]).
#[derive(Debug, Clone, Copy)]
pub struct Verified {
    pub pose: Pose,
    pub similarity: f32,
    pub score: f32,
}

/// `2·ln M`, M being the number of effectively independent poses the search tries per image
/// (candidates x angles x scales; the chance level of the best of M unrelated correlations is
/// about `sqrt(2·ln M / N)` for N independent samples). M ≈ 1 100 (`2·ln M` = 14). First
/// M = 10 000 (18.4), fitted on multi-instance scenes of the tuning photos (docs/accuracy.md,
/// "What a score means"); that was more than the data asked for: on the tuning set
/// (lomiri-wallpapers, 200 pairs / 100 scenes, seed 0) 14 found defocused parts 90.0 → 95.5 %
/// and noisy ones 91.0 → 96.5 % at the default `min_score`, with the same answers ≥ 0.9 in the
/// multi-instance scenes (456, 452 right); in scenes without the part 12 answers reached 0.9 as
/// before, 12 → 13 under defocus and 10 → 12 under noise (no more than without the camera
/// condition: likely the template's own source, which the pair generator leaves in the photo).
/// 12 (M ≈ 400) let one more decoy into the multi-instance scenes. Held-out figures in
/// docs/industrial.md, "Camera conditions".
const CHANCE_LOG_HYPOTHESES: f32 = 14.0;

/// The chance level of a template read another way ([`Sharpness`], [`RankPoints`]): as
/// [`chance_similarity`], capped only at [`READING_MAX_CHANCE`]. The whole template's cap lets a
/// smooth template score when it matches near-perfectly; a blurred template is smoother still,
/// and an unrelated smooth patch correlates with it at 0.97, so its reading must be held to its
/// own, higher chance level. Held-out scenes without the part (mate-backgrounds, 200): capped
/// at 0.8 like the whole template's, 11 answers reached 0.9 instead of 8; at 0.97, 8, but
/// defocused parts found fell from 85.5 to 68 %; at 0.9, 8 and 83 %.
fn chance_of_reading(template: &GrayImage32) -> f32 {
    let Some(independent) = independent_pixels(template) else {
        return READING_MAX_CHANCE;
    };
    (CHANCE_LOG_HYPOTHESES / independent.max(1.0))
        .sqrt()
        .min(READING_MAX_CHANCE)
}

/// The highest chance level of a reading ([`chance_of_reading`]): at it, a ZNCC of 0.99 scores
/// 0.9.
const READING_MAX_CHANCE: f32 = 0.9;

/// The chance level is capped here so that a very smooth template can still score (it then
/// needs a near-perfect match).
const MAX_CHANCE: f32 = 0.8;

/// The similarity an unrelated patch reaches by chance once the pose search has bent it to fit:
/// `sqrt(2·ln M / N_eff)`, where `N_eff` is the template's number of effectively independent
/// pixels. A smooth template (sky, a gradient, blur) has few, and any patch correlates with it
/// well; a detailed one has many. `N_eff = area / (π·ℓ²)` with ℓ the template's
/// [`correlation_length`].
pub fn chance_similarity(template: &GrayImage32) -> f32 {
    chance_of_share(independent_pixels(template), 1.0)
}

/// The chance level of the shading reading ([`ShadingPoints`]), `None` where the template is
/// too smooth for it. Three gains are fitted instead of one, so the best of M unrelated fits
/// reaches about `2·ln M + SHADING_EXTRA_LOG` over `N_eff` instead of `2·ln M` (the tail of a
/// chi-square with three degrees of freedom against one: `2·ln(2·ln M)` more). Where that is
/// above [`READING_MAX_CHANCE`] the reading is not made: capped, a smooth template's planes fit
/// smooth patches too well. Tuning set (47 held-out corpus photos + 2 lomiri images, 200 pairs,
/// seed 0), with the reading: uneven-light found 71.5 → 74.5 %; the extra 5.3, 10 or 18 made no
/// difference there, nor did a limit of 0.5 or 0.7 instead of the cap (73.0 / 73.5 %).
fn chance_of_shading(template: &GrayImage32) -> Option<f32> {
    let chance = ((CHANCE_LOG_HYPOTHESES + SHADING_EXTRA_LOG)
        / independent_pixels(template)?.max(1.0))
    .sqrt();
    (chance <= READING_MAX_CHANCE).then_some(chance)
}

/// The highest chance level of a template whose score reads the image with its noise taken out
/// ([`NoisePoints`]). A smooth template's score is `(ZNCC − chance) / (1 − chance)` with chance
/// near its cap 0.8, five times as steep as the correlation: the correction's small lift (and
/// the noise's own fluctuation, which it scales up too) carries look-alikes just under 0.9 over
/// it. Tuning set (47 held-out corpus photos + 2 lomiri images, 200 S1.5 pairs, seed 0), noise
/// of 15 grey levels: found 69.0 % without the reading; with it, limit 1 (every template) 90.5 %,
/// 0.5 90.0 %, 0.35 87.0 %; answers ≥ 0.9 in scenes without the part 23 → 41 / 39 / 37 (41 in
/// clean scenes).
const DENOISED_MAX_CHANCE: f32 = 0.5;

/// `2·ln(2·ln M)` for [`CHANCE_LOG_HYPOTHESES`] = 14 ([`chance_of_shading`]).
const SHADING_EXTRA_LOG: f32 = 5.3;

/// The template's number of effectively independent pixels, `area / (π·ℓ²)`; `None` for a
/// flat template.
fn independent_pixels(template: &GrayImage32) -> Option<f32> {
    let correlation_length = correlation_length(template)?;
    let n = template.values.iter().filter(|v| !v.is_nan()).count() as f32;
    Some(n / (std::f32::consts::PI * correlation_length.powi(2)))
}

/// [`chance_similarity`] of a `share` of a template with `independent` pixels in all: a
/// smaller part bends to fit an unrelated patch more easily.
fn chance_of_share(independent: Option<f32>, share: f32) -> f32 {
    let Some(independent) = independent else {
        return MAX_CHANCE;
    };
    (CHANCE_LOG_HYPOTHESES / (independent * share).max(1.0))
        .sqrt()
        .min(MAX_CHANCE)
}

/// How far apart (pixels) two template pixels must be to vary independently: `ℓ = √2·σ /
/// rms|∇T|` of a Gaussian random field, from the template's grey-level spread σ and mean
/// gradient. About a pixel for fine noise, several for smooth content; `None` for a flat
/// template. Pixels the template's mask ignores (NaN) count in neither.
pub fn correlation_length(template: &GrayImage32) -> Option<f32> {
    let (w, h) = (template.width, template.height);
    let v = &template.values;
    let used = || v.iter().filter(|x| !x.is_nan());
    let n = used().count().max(1) as f32;
    let mean = used().sum::<f32>() / n;
    let sigma = (used().map(|x| (x - mean).powi(2)).sum::<f32>() / n).sqrt();
    let mut gradient_sq = 0.0f32;
    let mut cells = 0usize;
    for y in 0..h.saturating_sub(1) {
        for x in 0..w.saturating_sub(1) {
            let here = v[y * w + x];
            let step = (v[y * w + x + 1] - here).powi(2) + (v[(y + 1) * w + x] - here).powi(2);
            if !step.is_nan() {
                gradient_sq += step;
                cells += 1;
            }
        }
    }
    let cells = cells.max(1) as f32;
    let rms_gradient = (gradient_sq / cells).sqrt();
    if sigma <= 1e-6 || rms_gradient <= 1e-9 {
        return None;
    }
    Some(std::f32::consts::SQRT_2 * sigma / rms_gradient)
}

/// How many more tries (`2·ln M`) a pose counts per unit of `−ln(scale_x·scale_y)` below the
/// template's own size ([`shrunk_chance_factor`]): M ∝ `1/(scale_x·scale_y)²`. The alignment
/// reaches a few image pixels either way whatever the scale, so a pose shrunk to half the
/// template's area slides over twice as many of the template's independent places (M ∝
/// `1/area`), and its template is read by half as many image pixels, which a smooth photo
/// does not resolve further (chance ∝ `1/√pixels` once those are the fewer). Tuning sets
/// (lomiri / grain photos, 1000 S1.5 pairs each, seed 0), answers at or above 0.9 in scenes
/// without the part, at 0 / 2 / 4 / 6: 40 / 37 / 33 / 33 and 76 / 67 / 61 / 59; at 4, parts
/// found at the defaults 0.5 points fewer under defocus (lomiri 98.7 → 98.2 %) and within 0.4
/// points of before (clean, `noise-15`, `jpeg-30`, `dark-gamma`, `uneven-light`, S2.5 clean
/// 78.1 → 78.4 %). The count that fits the template's own size (14) is left as it was above
/// that size (docs/accuracy.md, "What a score means").
const SHRUNK_LOG_HYPOTHESES: f32 = 4.0;

/// The highest chance level [`raised_chance`] raises a reading's to (a ZNCC of 0.995 then
/// scores 0.9).
const SHRUNK_MAX_CHANCE: f32 = 0.95;

/// The factor a reading's chance level is raised by at a pose of scales `scale_x`,
/// `scale_y` ([`raised_chance`]): the count of tries `2·ln M` raised by
/// [`SHRUNK_LOG_HYPOTHESES`] `· ln(1/(scale_x·scale_y))` where the pose is smaller than the
/// template (`chance ∝ √(2·ln M)`); 1 at or above the template's area. A shrunk template fits
/// unrelated texture more easily: in the tuning sets' scenes without the part, most answers at
/// 0.9 below the scales the parts had were at 0.4–0.7 of the template's size. Worked out once
/// per pose, for every reading of it.
fn shrunk_chance_factor(pose: &Pose) -> f32 {
    let area = pose.scale_x * pose.scale_y;
    if area.is_nan() || area >= 1.0 {
        return 1.0;
    }
    let extra = -SHRUNK_LOG_HYPOTHESES * area.max(1e-3).ln();
    ((CHANCE_LOG_HYPOTHESES + extra) / CHANCE_LOG_HYPOTHESES).sqrt()
}

/// `chance` times `factor`, capped at [`SHRUNK_MAX_CHANCE`], never lowered.
fn raised_chance(chance: f32, factor: f32) -> f32 {
    if factor <= 1.0 {
        return chance;
    }
    (chance * factor).min(SHRUNK_MAX_CHANCE).max(chance)
}

/// `(similarity − chance) / (1 − chance)` clamped to [0, 1].
fn above_chance(similarity: f32, chance: f32) -> f32 {
    ((similarity - chance) / (1.0 - chance)).clamp(0.0, 1.0)
}

/// Which way a [`Reading`] compared the template with the image (docs/accuracy.md, "What a
/// score means").
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ReadingKind {
    /// ZNCC of the whole template.
    Whole,
    /// Spearman's rho: unchanged by any increasing curve of the light ([`RankPoints`]).
    Rank,
    /// A gain and an offset that change across the part ([`ShadingPoints`]).
    Shading,
    /// The image's noise taken out of its variance ([`NoisePoints`]).
    Denoised,
    /// The template blurred by `defocus`, both by `smoothing` image pixels ([`Sharpness`]).
    Sharpness { defocus: f32, smoothing: f32 },
    /// The visible cells' similarity, weighed by their share of the structure ([`Coverage`]).
    Visible,
}

/// One reading of a pose: a similarity, the chance level an unrelated patch reaches that way,
/// and the share of the template it speaks for.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Reading {
    pub kind: ReadingKind,
    pub similarity: f32,
    pub chance: f32,
    /// 1 for the whole template; the visible share for [`ReadingKind::Visible`].
    pub share: f32,
}

impl Reading {
    fn whole(kind: ReadingKind, similarity: f32, chance: f32) -> Self {
        Self {
            kind,
            similarity,
            chance,
            share: 1.0,
        }
    }

    /// The reading with its chance level raised by `factor` ([`shrunk_chance_factor`]), where
    /// the pose is smaller than the template.
    fn raised_by(self, factor: f32) -> Self {
        Self {
            chance: raised_chance(self.chance, factor),
            ..self
        }
    }

    /// `share × (similarity − chance) / (1 − chance)`, clamped: what this reading scores.
    pub fn score(&self) -> f32 {
        self.share * above_chance(self.similarity, self.chance)
    }
}

/// Screens and confirms candidates of one template in one image.
pub struct Verifier<'a> {
    template: &'a GrayImage32,
    image: &'a GrayImage32,
    /// Answers outside the caller's angle range are not searched.
    allowed: Arc<dyn Fn(f32) -> bool + Send + Sync + 'a>,
    /// Pixels of the full image per pixel of the screening level.
    level_factor: f32,
    level_image: std::borrow::Cow<'a, GrayImage32>,
    /// Shorter and longer side of the template on the level.
    level_template_sides: (f32, f32),
    level_points: TemplatePoints,
    /// The level points with their plane taken out, to judge the second screen
    /// ([`Verifier::screen_evened`]); `None` for a template that is a plane.
    level_plane_free: Option<PlaneFreePoints>,
    level_grid: AngleScaleGrid,
    /// The level template's points for the level alignment (blurred like its window).
    level_align: align::AlignPoints,
    /// The blurred level with its gradients, where it is small enough to keep
    /// ([`WHOLE_LEVEL_PIXELS`]).
    level_gradients: Option<align::GradientWindow>,
    /// The level with the light evened out, made on first use ([`Verifier::screen_evened`]).
    evened_level: OnceLock<ScreeningLevel>,
    /// Half the side of the window that evens it, in level pixels.
    even_light_radius: usize,
    /// Full-resolution points of the fine search.
    sparse: TemplatePoints,
    /// Every template pixel: the similarity.
    support: TemplatePoints,
    /// [`chance_similarity`] of the template.
    chance: f32,
    /// [`independent_pixels`] of the template (the chance level of a visible part).
    independent: Option<f32>,
    /// The template in cells: how much of it is visible ([`Verifier::score_at`]).
    coverage: Coverage,
    /// The template read at the image's sharpness ([`Verifier::score_at`]).
    sharpness: Sharpness<'a>,
    /// The template's ranks: its similarity under any curve of the light
    /// ([`Verifier::score_at`]).
    ranks: RankPoints,
    /// [`chance_of_reading`] of the template.
    rank_chance: f32,
    /// The template under light that changes across the part ([`Verifier::score_at`]).
    shading: ShadingPoints,
    /// [`chance_of_shading`] of the template (`None`: too smooth for the reading).
    shading_chance: Option<f32>,
    /// The template compared with the image's noise taken out ([`Verifier::score_at`]), and
    /// that noise; `None` for a template too smooth for the reading ([`DENOISED_MAX_CHANCE`]).
    denoised: Option<(NoisePoints, NoiseLevel)>,
    /// The image's noise, estimated once ([`NoiseLevel`]).
    noise: NoiseLevel,
    /// Scales an answer may have ([`Verifier::plausible`]).
    scale_bounds: (f32, f32),
    /// The caller's scale range, which a confirmed pose is held to ([`Verifier::confirm`]).
    required_scales: Option<(f32, f32)>,
    /// The geometric mean of the expected scale range (1 without one).
    expected_scale: f32,
    /// The object's size in the image (pixels, the geometric mean of its sides at the expected
    /// scale).
    object_side: f32,
    /// Whether the network's angle, scales and centre are believed ([`Verifier::screen`]).
    heads: Heads,
}

/// Whether the network's heads can be believed at a candidate: their angle and scales, and
/// their centre to within the screen's reach. They cannot where the part's shape on the
/// network's grid lies outside what the weights were trained on throughout
/// ([`crate::model::TrainedOn`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum Heads {
    #[default]
    Trusted,
    Untrusted,
}

/// Centres on a ring around an untrusted candidate that are screened too, and the ring's
/// radius as a share of the object's size. Frame of `cargo bench --bench frames` (144 28x52
/// parts, default weights, 2 frames): the network's peaks lie 7–8 px off the parts it misses;
/// screened at the expected scale from the candidate alone recall 0.635 → 0.729, with 8 ring
/// centres at 6 px (0.16 of sqrt(28·52)) 0.965 at 3.5x the screen's time. Tuning photos (28x52,
/// S1.5, 200 pairs), verified Succ 77.5 % → 83.5 % (no ring), 92.5 % (4 centres), 93.5 % (6 or
/// 8), 92.5 % (8 at 0.24); 28 → 60 ms a pair.
const RING_STARTS: usize = 8;
const RING_RADIUS: f32 = 0.16;

impl<'a> Verifier<'a> {
    /// `scale_range` is the range of the objects' scale relative to the template that the
    /// caller asked for (`None`: about 1, not enforced); `allowed` says which angles an answer
    /// may have.
    pub fn new(
        template: &'a GrayImage32,
        image: &'a GrayImage32,
        scale_range: Option<(f32, f32)>,
        allowed: impl Fn(f32) -> bool + Send + Sync + 'a,
    ) -> Self {
        Self::screening_below(
            template,
            image,
            scale_range,
            Arc::new(allowed),
            SCREEN_OBJECT_SIDE,
        )
    }

    /// [`Verifier::new`] with a screening level on which the object is smaller than
    /// `screen_side` pixels (the image halved until it is; [`SCREEN_OBJECT_SIDE`] by default).
    fn screening_below(
        template: &'a GrayImage32,
        image: &'a GrayImage32,
        scale_range: Option<(f32, f32)>,
        allowed: Arc<dyn Fn(f32) -> bool + Send + Sync + 'a>,
        screen_side: f32,
    ) -> Self {
        let scales = scale_range.unwrap_or((1.0, 1.0));
        let expected_scale = (scales.0 * scales.1).sqrt().max(0.05);
        let noise = NoiseLevel::estimate(image);
        let mut level_template = std::borrow::Cow::Borrowed(template);
        let mut level_image = std::borrow::Cow::Borrowed(image);
        let mut level_factor = 1.0f32;
        let object_side = |t: &GrayImage32| ((t.width * t.height) as f32).sqrt() * expected_scale;
        while object_side(&level_template) >= screen_side
            && level_image.width.min(level_image.height) >= 64
        {
            level_template = std::borrow::Cow::Owned(level_template.downsample());
            level_image = std::borrow::Cow::Owned(level_image.downsample());
            level_factor *= 2.0;
        }
        // Angle steps that move the template's corners by about one level pixel near the
        // start and 1.5 over the rest of the circle.
        let radius = (level_template.width as f32).hypot(level_template.height as f32) / 2.0
            * expected_scale;
        let level_grid = AngleScaleGrid {
            near_step_deg: (1.0 / radius).to_degrees().clamp(2.0, 6.0),
            near_factors: (0..5).map(|k| 0.7f32 * 2f32.powf(k as f32 / 4.0)).collect(),
            far_step_deg: (1.5 / radius).to_degrees().clamp(3.0, 10.0),
            far_factors: (0..3).map(|k| 0.85f32 * 1.18f32.powi(k)).collect(),
            angles_first: Some(SCREEN_ANGLES_KEPT),
            isotropic_first: true,
            mirrored_start: true,
        };
        let level_points = TemplatePoints::in_whole_lanes(&level_template, 12);
        let level_plane_free = PlaneFreePoints::new(&level_points);
        Self {
            template,
            image,
            allowed,
            level_factor,
            level_points,
            level_plane_free,
            level_align: align::AlignPoints::new(
                &level_template,
                LEVEL_SIGMA / expected_scale,
                12,
                true,
            ),
            level_template_sides: (
                level_template.width.min(level_template.height) as f32,
                level_template.width.max(level_template.height) as f32,
            ),
            level_gradients: (level_image.width * level_image.height <= WHOLE_LEVEL_PIXELS)
                .then(|| align::GradientWindow::whole(&level_image, LEVEL_SIGMA)),
            evened_level: OnceLock::new(),
            even_light_radius: (EVEN_LIGHT_WINDOW * object_side(&level_template))
                .round()
                .max(1.0) as usize,
            level_image,
            level_grid,
            sparse: TemplatePoints::new(template, 20),
            support: TemplatePoints::support(template),
            chance: chance_similarity(template),
            independent: independent_pixels(template),
            coverage: Coverage::new(template),
            sharpness: Sharpness::new(template, image, noise, chance_of_reading),
            ranks: RankPoints::new(template),
            rank_chance: chance_of_reading(template),
            shading: ShadingPoints::new(template),
            shading_chance: chance_of_shading(template),
            denoised: (chance_similarity(template) <= DENOISED_MAX_CHANCE)
                .then(|| (NoisePoints::new(template), noise)),
            noise,
            scale_bounds: (scales.0 / SCALE_SLACK, scales.1 * SCALE_SLACK),
            required_scales: scale_range,
            expected_scale,
            object_side: ((template.width * template.height) as f32).sqrt() * expected_scale,
            heads: Heads::Trusted,
        }
    }

    /// The verifier with the network's heads believed or not ([`Verifier::screen`]).
    pub fn with_heads(self, heads: Heads) -> Self {
        Self { heads, ..self }
    }

    /// [`Verifier::new`] with the caller's scale range and angle range (answers within
    /// [`ANGLE_MARGIN_DEG`] of it).
    pub fn for_options(
        template: &'a GrayImage32,
        image: &'a GrayImage32,
        options: &'a MatchOptions,
    ) -> Self {
        Self::new(
            template,
            image,
            options.scale_range.map(|r| (r.min, r.max)),
            |angle| {
                options
                    .angle_range
                    .is_none_or(|r| r.contains_within(angle, ANGLE_MARGIN_DEG))
            },
        )
    }

    /// Whether a pose's scales are those of a plausible object: within [`SCALE_SLACK`] of the
    /// expected range and no more than [`MAX_ANISOTROPY`] times wider than high or vice versa.
    /// The alignment can otherwise squash the template into a line, whose profile correlates
    /// with any texture.
    fn plausible(&self, pose: &Pose) -> bool {
        let (lo, hi) = self.scale_bounds;
        let ratio = pose.scale_x / pose.scale_y;
        (lo..=hi).contains(&pose.scale_x)
            && (lo..=hi).contains(&pose.scale_y)
            && (1.0 / MAX_ANISOTROPY..=MAX_ANISOTROPY).contains(&ratio)
    }

    /// A similarity as a score in [0, 1]: how far above chance it is, `(ZNCC − chance) /
    /// (1 − chance)` clamped to [0, 1], with the template's [`chance_similarity`]. For a
    /// detailed template chance is small and the score close to the ZNCC; for a smooth one
    /// only a near-perfect match scores high. This is what makes one `min_score` mean the same
    /// for every template.
    pub fn score(&self, similarity: f32) -> f32 {
        above_chance(similarity, self.chance)
    }

    /// The score of the template at `pose`: the best of three kinds of reading (docs/accuracy.md,
    /// "What a score means"):
    /// - the whole template's similarity above chance ([`Verifier::score`]);
    /// - the template at the image's sharpness: blurred as a defocused camera blurs the part,
    ///   or blurred together with the image where noise would drown its detail, each above the
    ///   chance level of its blurred template ([`Sharpness`]), the rank correlation, which
    ///   no increasing curve of the light changes ([`RankPoints`]), the correlation under a
    ///   gain and an offset that change across the part ([`ShadingPoints`]), and, for a
    ///   detailed template, the correlation with the image's noise taken out of the image's
    ///   variance ([`NoisePoints`], held to its chance level plus the noise's fluctuation);
    /// - the share of the template that is visible (by area with structure, cell by cell:
    ///   [`Coverage`]) times the visible cells' similarity above the chance level of that
    ///   smaller part.
    ///
    /// A clean, sharp part scores as before (every reading agrees); a defocused, noisy or
    /// differently exposed one scores about what a clean one would; a part with a quarter covered scores about 0.75 instead
    /// of collapsing with the whole-template correlation; an unrelated patch has few matching
    /// cells, and a blurred template's higher chance level takes back what the blur gave it.
    pub fn score_at(&self, pose: &Pose) -> f32 {
        let mut best = 0.0f32;
        self.each_reading(pose, |reading| {
            best = best.max(reading.score());
            ControlFlow::Continue(())
        });
        best
    }

    /// Whether [`Verifier::score_at`] of `pose` is at least `bar`, reading only until one
    /// reading reaches it (the rank correlation, which sorts the samples, last).
    pub fn score_reaches(&self, pose: &Pose, bar: f32) -> bool {
        if bar <= 0.0 {
            return true;
        }
        let mut reached = false;
        self.each_reading(pose, |reading| {
            if reading.score() >= bar {
                reached = true;
                return ControlFlow::Break(());
            }
            ControlFlow::Continue(())
        });
        reached
    }

    /// Every reading [`Verifier::score_at`] takes the best of, each with its similarity and
    /// chance level: what a score was made of, for diagnosis (`examples/diagnose`).
    pub fn readings_at(&self, pose: &Pose) -> Vec<Reading> {
        let mut readings = Vec::new();
        self.each_reading(pose, |reading| {
            readings.push(reading);
            ControlFlow::Continue(())
        });
        readings
    }

    /// Hands each reading of `pose` to `visit` until it breaks: the cheap ones first (the
    /// blurred templates' come together, all read before the first is visited), the rank
    /// correlation, which sorts the samples, last.
    fn each_reading(&self, pose: &Pose, mut visit: impl FnMut(Reading) -> ControlFlow<()>) {
        let factor = shrunk_chance_factor(pose);
        let mut visit = |reading: Reading| visit(reading.raised_by(factor));
        // Every reading compares its own template values with the same image samples.
        let samples = self.support.samples(self.image, pose);
        let whole = Reading::whole(
            ReadingKind::Whole,
            samples.zncc(self.support.weights()),
            self.chance,
        );
        if visit(whole).is_break() {
            return;
        }
        for reading in self.sharpness.read(&samples, pose) {
            let (defocus, smoothing) = reading.blur;
            let reading = Reading::whole(
                ReadingKind::Sharpness { defocus, smoothing },
                reading.similarity,
                reading.chance,
            );
            if visit(reading).is_break() {
                return;
            }
        }
        if let Some(chance) = self.shading_chance {
            let reading = Reading::whole(
                ReadingKind::Shading,
                self.shading.similarity(&samples),
                chance,
            );
            if visit(reading).is_break() {
                return;
            }
        }
        if let Some(reading) = self
            .denoised
            .as_ref()
            .and_then(|(points, noise)| points.read(&samples, self.image, pose, *noise))
        {
            let chance =
                (self.chance.powi(2) + CHANCE_LOG_HYPOTHESES * reading.noise_spread).sqrt();
            let reading = Reading::whole(
                ReadingKind::Denoised,
                reading.similarity,
                chance.min(READING_MAX_CHANCE),
            );
            if visit(reading).is_break() {
                return;
            }
        }
        let visible = |reading: CoverageReading| Reading {
            kind: ReadingKind::Visible,
            similarity: reading.visible_similarity,
            chance: chance_of_share(self.independent, reading.visible_points),
            share: reading.visible,
        };
        if let Some((reading, worst_hidden)) = self.coverage.readings(&samples) {
            if visit(visible(reading)).is_break() {
                return;
            }
            // A covered cell that correlates by chance, counted as hidden ([`Coverage`]).
            if let Some(reading) = worst_hidden
                && visit(visible(reading)).is_break()
            {
                return;
            }
        }
        let _ = visit(Reading::whole(
            ReadingKind::Rank,
            self.ranks.similarity(&samples),
            self.rank_chance,
        ));
    }

    /// The similarity of the template at `pose`: ZNCC over its support, in [-1, 1].
    pub fn similarity(&self, pose: &Pose) -> f32 {
        self.support.score(self.image, pose)
    }

    /// The cheap first look at a candidate, on the screening level: the best angle and scales
    /// at its centre, then a short alignment of all five parameters on the blurred level, which
    /// pulls a centre a few pixels off onto the object (a weak network's peaks often are).
    ///
    /// With [`Heads::Untrusted`] the network's scales are not believed — the search starts at
    /// the expected scale — nor its centre to within the screen's reach: the candidate is
    /// screened from [`RING_STARTS`] more centres on a ring around it too, and the best screen
    /// of all is kept.
    pub fn screen(&self, candidate: &Pose) -> Screened {
        match self.heads {
            Heads::Trusted => self.screen_at(candidate),
            Heads::Untrusted => {
                let start = Pose {
                    scale_x: self.expected_scale,
                    scale_y: self.expected_scale,
                    ..*candidate
                };
                let radius = RING_RADIUS * self.object_side;
                (0..RING_STARTS)
                    .map(|k| {
                        let a = k as f32 * std::f32::consts::TAU / RING_STARTS as f32;
                        Pose {
                            x: start.x + radius * a.cos(),
                            y: start.y + radius * a.sin(),
                            ..start
                        }
                    })
                    .map(|ring_start| self.screen_at(&ring_start))
                    .fold(self.screen_at(&start), |best, s| {
                        if s.score > best.score { s } else { best }
                    })
            }
        }
    }

    fn screen_at(&self, candidate: &Pose) -> Screened {
        self.screen_on(candidate, &self.level_image, self.level_gradients.as_ref())
    }

    /// A second look at a candidate whose [`Verifier::screen`] gave `first`: screened again on
    /// the level with the light evened out (each pixel divided by the mean of a window
    /// [`EVEN_LIGHT_WINDOW`] object sides either way: a gain that changes across the frame
    /// becomes nearly constant over the part), and kept where that pose correlates better on
    /// the level itself with a plane fitted out of template and image alike
    /// ([`PlaneFreePoints`]: what is left of a ramp of light over the part does not count), so
    /// a screen that evening the light leads astray changes nothing. The screen's score is
    /// then that correlation (or the first screen's own, where the first pose stays and its
    /// own is higher). A first screen that already reached [`RESCREEN_BELOW`] is kept as it is.
    ///
    /// Judged by the plain ZNCC on the level (until 2026-11-29), the second screen's pose
    /// lost to the first wherever a low-contrast part's own correlation was spoilt by the ramp;
    /// tuning photos (47 held-out corpus photos + 2 lomiri images; the 20 lomiri photos; 200
    /// S1.5 pairs, seed 0), `uneven-light` found 75.5 → 78.0 % and 94.0 → 95.0 %, clean,
    /// `dark-gamma` and `noise-15` unchanged, answers ≥ 0.9 in scenes without the part 41 → 42
    /// and 13 → 13 (`absent,uneven-light` 34 → 35, 12 → 12).
    pub fn screen_evened(&self, candidate: &Pose, first: Screened) -> Screened {
        if first.score >= RESCREEN_BELOW {
            return first;
        }
        let evened = self.evened_level.get_or_init(|| {
            let image = evened_light(&self.level_image, self.even_light_radius);
            let gradients = (image.width * image.height <= WHOLE_LEVEL_PIXELS)
                .then(|| align::GradientWindow::whole(&image, LEVEL_SIGMA));
            ScreeningLevel { image, gradients }
        });
        let second = self.screen_on(candidate, &evened.image, evened.gradients.as_ref());
        let Some(plane_free) = &self.level_plane_free else {
            // A template that is a plane: the plain ZNCC judges.
            let score = self
                .level_points
                .score(&self.level_image, &self.on_level(&second.pose));
            return if score > first.score {
                Screened {
                    pose: second.pose,
                    score,
                }
            } else {
                first
            };
        };
        let judged = |pose: &Pose| {
            plane_free.score(
                &self
                    .level_points
                    .samples(&self.level_image, &self.on_level(pose)),
            )
        };
        let (first_judged, second_judged) = (judged(&first.pose), judged(&second.pose));
        if second_judged > first_judged {
            Screened {
                pose: second.pose,
                score: second_judged,
            }
        } else {
            Screened {
                score: first_judged.max(first.score),
                ..first
            }
        }
    }

    /// The same verifier screening at full resolution, for the second screen
    /// ([`Verifier::screen_evened_also_at`]) of a fine texture
    /// ([`FULL_RESOLUTION_BELOW_CORRELATION_LENGTH`]) in an image without noise to speak of
    /// ([`FULL_RESOLUTION_MAX_NOISE`]); `None` elsewhere, and where this verifier already
    /// screens at full resolution.
    pub fn full_resolution_twin(&self) -> Option<Verifier<'a>> {
        let fine = correlation_length(self.template)
            .is_some_and(|length| length < FULL_RESOLUTION_BELOW_CORRELATION_LENGTH);
        if self.level_factor <= 1.0 || !fine {
            return None;
        }
        (self.noise.grey_levels() < FULL_RESOLUTION_MAX_NOISE).then(|| {
            Self::screening_below(
                self.template,
                self.image,
                self.required_scales,
                Arc::clone(&self.allowed),
                f32::INFINITY,
            )
            .with_heads(self.heads)
        })
    }

    /// [`Verifier::screen_evened`], and where there is a `twin` at full resolution
    /// ([`Verifier::full_resolution_twin`]) and the halved level's second screen stays under
    /// [`RESCREEN_BELOW`], the same second screen there too; the pose with the higher score
    /// ([`Verifier::score_at`]) is kept. On the halved level the grain of a
    /// fine texture is averaged away, so under light that changes across the part its second
    /// screen can settle at a wrong angle that the full level's alignment does not take; the
    /// halved level keeps the poses it screens better (a darkened image's, say). Tuning sets
    /// (grain and lomiri photos, 1000 S1.5 pairs each, seed 0; docs/industrial.md, "Camera
    /// conditions"), found at the defaults: grain `uneven-light` 91.0 → 94.4 %, lomiri 98.1 →
    /// 98.5 %, every other condition within a pair or two.
    pub fn screen_evened_also_at(
        &self,
        twin: Option<&Verifier>,
        candidate: &Pose,
        first: Screened,
    ) -> Screened {
        let halved = self.screen_evened(candidate, first);
        let Some(twin) = twin else {
            return halved;
        };
        if halved.score >= RESCREEN_BELOW {
            return halved;
        }
        let full = twin.screen_evened(candidate, first);
        let same = full.pose.x == halved.pose.x && full.pose.y == halved.pose.y;
        if !same && !self.score_reaches(&halved.pose, self.score_at(&full.pose)) {
            Screened {
                pose: full.pose,
                score: halved.score.max(full.score),
            }
        } else {
            halved
        }
    }

    /// `pose` (full resolution) on the screening level.
    fn on_level(&self, pose: &Pose) -> Pose {
        let f = self.level_factor;
        Pose {
            x: (pose.x + 0.5) / f - 0.5,
            y: (pose.y + 0.5) / f - 0.5,
            ..*pose
        }
    }

    fn screen_on(
        &self,
        candidate: &Pose,
        level_image: &GrayImage32,
        level_gradients: Option<&align::GradientWindow>,
    ) -> Screened {
        let f = self.level_factor;
        let on_level = self.on_level(candidate);
        let windows = self.level_grid.search_windows(
            &self.level_points,
            level_image,
            &on_level,
            &*self.allowed,
        );
        let mut best = *windows
            .iter()
            .max_by(|a, b| a.score.total_cmp(&b.score))
            .expect("search_windows returns at least one pose");
        let (short, long) = self.level_template_sides;
        let largest_scale = windows
            .iter()
            .map(|w| w.pose.scale_x.max(w.pose.scale_y))
            .fold(0.0f32, f32::max);
        let reach = long * largest_scale * 0.75 + 4.0;
        let own_window;
        let window = match level_gradients {
            Some(whole) => whole,
            None => {
                own_window = align::GradientWindow::new(
                    level_image,
                    on_level.x,
                    on_level.y,
                    reach + 3.0 * LEVEL_SIGMA,
                    LEVEL_SIGMA,
                );
                &own_window
            }
        };
        // Aligned from each window's best: the grid scores angles at the candidate's centre,
        // and with that centre a few pixels off a wrong angle can outscore the right one.
        // Also from the candidate's own pose: where the grain of a part is averaged half away
        // on this level and noise covers the rest, every window's best can be a wrong angle
        // while the network's was right (tuning sets, 200 S1.5 pairs, seed 0, found at the
        // defaults: grain noise-15 94.5 → 96.0 %, dark-gamma 98.5 → 99.5 %, clean 99.0 →
        // 100 %; lomiri clean and noise-15 99.5 → 100 %; the answers without the part
        // unchanged; docs/industrial.md, "Camera conditions").
        let network_start = self.held_to_range(on_level);
        for start in windows.iter().map(|w| &w.pose).chain([&network_start]) {
            let aligned = align::align(
                &self.level_align,
                window,
                start,
                LEVEL_ITERATIONS,
                LEVEL_TOLERANCE,
                Light::Even,
            );
            let moved = (aligned.x - on_level.x).hypot(aligned.y - on_level.y);
            let score = self.level_points.score(level_image, &aligned);
            if score > best.score
                && self.plausible(&aligned)
                && moved <= short * on_level.scale_x.min(on_level.scale_y) / 3.0
                && (self.allowed)(wrap_angle_deg(aligned.angle_deg))
            {
                best = Scored {
                    pose: aligned,
                    score,
                };
            }
        }
        Screened {
            pose: Pose {
                x: (best.pose.x + 0.5) * f - 0.5,
                y: (best.pose.y + 0.5) * f - 0.5,
                ..best.pose
            },
            score: best.score,
        }
    }

    /// Refines a screened candidate at full resolution and measures the similarity there. The
    /// alignment starts from the screened pose's fine search and from the candidate's own pose
    /// (the better fit wins; tuning sets, 47 held-out corpus photos + 2 lomiri images and 20
    /// lomiri photos, 200 S1.5 pairs, seed 0: noise-15 93.5 → 94.0 % and 99.0 → 99.5 %,
    /// uneven-light 82.0 → 82.5 %, defocus-2 96.5 → 97.0 % on the lomiri photos, every other
    /// condition and the answers without the part unchanged). The alignment may move the
    /// centre by at most a third of the object from where the screen left it (otherwise it
    /// found a neighbour, which has its own candidate; measured from the
    /// network's candidate instead, a screen that had already moved nearly that far left the
    /// alignment no room, and the coarser fine-search pose was kept); it is kept only if it is
    /// more similar. Both poses are held to the caller's scale range: where the template fits
    /// along a direction in which it looks the same (stripes, a plain band), a smaller scale
    /// fits as well as the object's own and the search drifts below the range; the object is
    /// still there, at the range's bound.
    ///
    /// Under [`Light::Planes`] (the image's screens found the light uneven:
    /// [`wants_second_screen`]) the confirmed pose is aligned once more with a gain and an
    /// offset that change across the part, and that pose is kept where it scores more than
    /// [`SHADED_MARGIN`] higher: under light that falls across the part the alignment of one
    /// gain and one offset settles beside the part, where the ramp correlates best, and every
    /// reading of the score there is low.
    ///
    /// A confirmed pose that scores under [`CURVED_BELOW`] is aligned once more on the image
    /// seen through the light's curve at that pose ([`Verifier::aligned_under_the_curve`]) and
    /// replaced where that scores higher.
    pub fn confirm(&self, screened: &Screened, candidate: &Pose, light: Light) -> Verified {
        let verified = self.confirm_lit(screened, candidate, light);
        if verified.score >= CURVED_BELOW || verified.similarity <= -1.0 {
            return verified;
        }
        match self.aligned_under_the_curve(&verified.pose, &screened.pose) {
            Some(curved) if curved.score > verified.score => curved,
            _ => verified,
        }
    }

    /// `pose` aligned again (one gain and one offset, from `pose`) on the image around it with
    /// its grey levels mapped onto the template's by the curve that pairs their quantiles there
    /// ([`LightCurve`]); held to the caller's range and checked as [`Verifier::confirm`] checks
    /// an alignment (plausible scales, near `screened`, an allowed angle); scored on the image
    /// itself. `None` where no curve can be told or the alignment is not a plausible answer.
    ///
    /// Why: under a gamma the alignment of one gain and one offset settles a little beside
    /// the part, where every reading of the score is lower than at the part. Tuning sets (1000
    /// S1.5 pairs each, seed 0; docs/industrial.md, "Camera conditions"), found at the
    /// defaults: lomiri `dark-gamma` 96.8 → 97.3 %, every other condition and the answers at or
    /// above 0.9 in scenes without the part within one of 1000, about 2 % more time a pair
    /// where nothing scores 0.9 (every candidate of a scene without the part).
    pub(crate) fn aligned_under_the_curve(&self, pose: &Pose, screened: &Pose) -> Option<Verified> {
        let samples = self.support.samples(self.image, pose);
        // The template's grey levels up to a gain and an offset, which the alignment ignores:
        // spread as a photo's (0.2), far above a flat patch's.
        let spread = 0.2 * (samples.values().len() as f32).sqrt();
        let levels: Vec<f32> = self
            .support
            .weights()
            .iter()
            .map(|w| 0.5 + spread * w)
            .collect();
        let curve = LightCurve::pairing(samples.values(), &levels)?;
        // The window `align_from` reads around `pose`, and two pixels for the bilinear samples.
        let radius = align_from_reach(self.template, pose.scale_x.max(pose.scale_y), pose) + 2.0;
        let x0 = (pose.x - radius).floor().max(0.0) as usize;
        let y0 = (pose.y - radius).floor().max(0.0) as usize;
        let x1 = ((pose.x + radius).ceil().max(0.0) as usize + 1).min(self.image.width);
        let y1 = ((pose.y + radius).ceil().max(0.0) as usize + 1).min(self.image.height);
        if x1 < x0 + 8 || y1 < y0 + 8 {
            return None;
        }
        let seen = GrayImage32::from_fn(x1 - x0, y1 - y0, |x, y| {
            curve.apply(self.image.values[(y + y0) * self.image.width + x + x0])
        });
        let (dx, dy) = (x0 as f32, y0 as f32);
        let start = Pose {
            x: pose.x - dx,
            y: pose.y - dy,
            ..*pose
        };
        let aligned = align_from(
            self.template,
            &self.support,
            &seen,
            &[start],
            &start,
            Light::Even,
        )
        .pose;
        let held = self.held_to_range(Pose {
            x: aligned.x + dx,
            y: aligned.y + dy,
            angle_deg: wrap_angle_deg(aligned.angle_deg),
            ..aligned
        });
        (self.plausible(&held)
            && stayed_near(self.template, screened, &held)
            && (self.allowed)(held.angle_deg))
        .then(|| Verified {
            pose: held,
            similarity: self.similarity(&held),
            score: self.score_at(&held),
        })
    }

    /// [`Verifier::confirm`] without the alignment under the light's curve (`light` as there).
    pub(crate) fn confirm_lit(
        &self,
        screened: &Screened,
        candidate: &Pose,
        light: Light,
    ) -> Verified {
        let start = Scored {
            pose: screened.pose,
            score: self.sparse.score(self.image, &screened.pose),
        };
        let fine =
            self.held_to_range(fine_search(&self.sparse, self.image, start, &*self.allowed).pose);
        let fine_similarity = self.similarity(&fine);
        // The candidate's own pose as a second start, where the screen moved it: along a
        // direction in which the part looks nearly the same (an edge, a smooth blob) the
        // screen's grid can settle at a wrong scale or angle that the alignment from there
        // does not leave, while the network's pose lies in the right basin.
        let mut starts = vec![fine];
        if *candidate != screened.pose {
            starts.push(self.held_to_range(*candidate));
        }
        let aligned = align_from(
            self.template,
            &self.support,
            self.image,
            &starts,
            candidate,
            Light::Even,
        );
        let held = self.held_to_range(aligned.pose);
        let aligned = if held == aligned.pose {
            aligned
        } else {
            Scored {
                pose: held,
                score: self.similarity(&held),
            }
        };
        let keep_aligned = aligned.score > fine_similarity
            && self.plausible(&aligned.pose)
            && stayed_near(self.template, &screened.pose, &aligned.pose)
            && (self.allowed)(wrap_angle_deg(aligned.pose.angle_deg));
        let (pose, similarity) = if keep_aligned {
            (aligned.pose, aligned.score)
        } else if self.plausible(&fine) {
            (fine, fine_similarity)
        } else {
            (fine, -1.0) // no plausible object here
        };
        let verified = Verified {
            pose: Pose {
                angle_deg: wrap_angle_deg(pose.angle_deg),
                ..pose
            },
            similarity,
            score: if similarity > -1.0 {
                self.score_at(&pose)
            } else {
                0.0
            },
        };
        if light == Light::Even || similarity <= -1.0 {
            return verified;
        }
        let shaded = align_from(
            self.template,
            &self.support,
            self.image,
            &[verified.pose],
            candidate,
            Light::Planes,
        );
        let held = self.held_to_range(shaded.pose);
        let score = self.score_at(&held);
        if score > verified.score + SHADED_MARGIN
            && self.plausible(&held)
            && stayed_near(self.template, &screened.pose, &held)
            && (self.allowed)(wrap_angle_deg(held.angle_deg))
        {
            Verified {
                pose: Pose {
                    angle_deg: wrap_angle_deg(held.angle_deg),
                    ..held
                },
                similarity: self.similarity(&held),
                score,
            }
        } else {
            verified
        }
    }

    /// `pose` with its scales clamped to the caller's range; unchanged without a range.
    fn held_to_range(&self, pose: Pose) -> Pose {
        match self.required_scales {
            Some((lo, hi)) => Pose {
                scale_x: pose.scale_x.clamp(lo, hi),
                scale_y: pose.scale_y.clamp(lo, hi),
                ..pose
            },
            None => pose,
        }
    }
}

/// Whether a job's candidates are screened a second time, on the level with the light evened
/// out ([`Verifier::screen_evened`]): fewer than `wanted` (the caller's `max_instances`) of
/// their first `screens` reach [`RESCREEN_BELOW`].
pub fn wants_second_screen<'a>(
    screens: impl IntoIterator<Item = &'a Screened>,
    wanted: usize,
) -> bool {
    screens
        .into_iter()
        .filter(|screen| screen.score >= RESCREEN_BELOW)
        .count()
        < wanted
}

/// Screened candidates beyond the survivors' budget that are ranked by their score before the
/// survivors are chosen ([`rank_by_score`]). Tuning set (47 held-out corpus photos + 2 lomiri
/// images, S1.5, 200 pairs, seed 0, default weights), found at the defaults with 0 / 8 / 18 /
/// 38 / 98 ranked beyond the two survivors: clean 91.5 / 93.0 / 95.0 / 95.5 / 95.5 %,
/// uneven-light 70.5 / 71.0 / 71.5 / 71.5 / 72.0 %, noise-15 68.0 / 69.0 / 69.0 / 69.5 / 69.5 %,
/// defocus-2 76.5 / 79.0 / 80.5 / 80.0 / – %, at 0 / 1 / 2 / 4 / 12 ms more a pair (27–30 ms).
/// 48 since 2026-11-28 (18 before): the ranked screens are also the other places an answer
/// must stand out from ([`lift_standing_out`]); with twenty the image's decoys are too few to
/// say how high they reach (same set, floor 0.6, margin 0.3, jpeg-30 / defocus-2
/// found 93.0 / 93.0 % with 20 ranked, 93.5 / 93.0 % with 50; answers ≥ 0.9 in the three
/// scenes-without-the-part sets 48 / 44 / 43 against 45 / 42 / 41), about 2 ms more a pair.
pub const RANKED_BEYOND_SURVIVORS: usize = 48;

/// Orders the best `count` screens (by the screen's sparse ZNCC, `screened` sorted so) by the
/// score at their screened pose ([`Verifier::score_at`], at full resolution), ahead of the
/// rest. Why: the screen's ZNCC on a sparse, halved template is what a part loses first under
/// light that varies across it, defocus or noise, and a decoy's few pixels more of it put the
/// part below the survivors; the score reads the template every way the answer is scored, so
/// the part the answer would have found comes first. Candidates screened below [`SCREEN_MIN`]
/// keep their place (at the end); past the time limit the screen's order stands. Returns the
/// scores read with their screened poses, best first (none where nothing was ranked), for
/// [`lift_standing_out`].
fn rank_by_score(
    verifier: &Verifier,
    screened: &mut Vec<(Pose, Screened)>,
    count: usize,
    limit: &TimeLimit,
) -> Vec<(f32, Pose)> {
    let count = count.min(screened.len());
    if count < 2 || !limit.in_time() {
        return Vec::new();
    }
    let best: Vec<(Pose, Screened)> = screened.drain(..count).collect();
    let mut ranked: Vec<(f32, (Pose, Screened))> = best
        .into_par_iter()
        .map(|(candidate, screen)| {
            let score = if screen.score >= SCREEN_MIN && limit.in_time() {
                verifier.score_at(&screen.pose)
            } else {
                -1.0
            };
            (score, (candidate, screen))
        })
        .collect();
    // Stable: equal scores keep the screen's order.
    ranked.sort_by(|a, b| b.0.total_cmp(&a.0));
    let scores = ranked
        .iter()
        .filter(|(score, _)| *score >= 0.0)
        .map(|(score, (_, screen))| (*score, screen.pose))
        .collect();
    let rest = std::mem::take(screened);
    screened.extend(ranked.into_iter().map(|(_, screened)| screened));
    screened.extend(rest);
    scores
}

/// Least score of an answer that can stand out ([`lift_standing_out`]).
pub const STAND_OUT_FLOOR: f32 = 0.6;
/// Width of the band of scores that no other place reached, below an answer that stands out.
/// Tuning set (47 held-out corpus photos + 2 lomiri images, S1.5, 200 pairs, seed 0), found at
/// the defaults with no lift / margin 0.3 / 0.35 / 0.4 / 0.5: jpeg-30 84.5 / 93.0 / 91.5 /
/// 90.5 / 88.0 %, defocus-2 87.0 / 92.5 / 92.5 / 91.0 / 89.0 %; answers ≥ 0.9 in scenes
/// without the part (`absent`, `absent,jpeg-30`, `absent,defocus-2`) 39 / 44 / 43 / 40 / 40,
/// 33 / 42 / 40 / 39 / 37, 39 / 41 / 40 / 39 / 39 — at 0.4 the new ones are copies of the part
/// that the textures repeat but one (same angle, scales 0.7x).
pub const STAND_OUT_MARGIN: f32 = 0.4;
/// The score an answer that stands out reports at least: the default `min_score`'s level, 0.9,
/// rounded up to the next `f32` so that it is at least 0.9 in double precision too (a client
/// that reads the `float` as a double and compares it with 0.9 keeps it; 0.9 as an `f32` is
/// 0.89999998 as a double).
pub const STAND_OUT_SCORE: f32 = f32::from_bits(0.9f32.to_bits() + 1);
/// Boxes overlapping by more than this (IoU) are one place.
const SAME_PLACE_IOU: f32 = 0.1;
/// Factor by which an answer's scales are changed, one axis or both, to ask whether its own
/// pose stands out ([`best_stretched_score`]).
const SCALE_STEP: f32 = 1.25;
/// Least lead of an answer over its own pose at other scales ([`SCALE_STEP`]) for it to stand
/// out.
pub const STAND_OUT_OWN_MARGIN: f32 = 0.1;

/// The best score of `pose`'s place at a quarter more or less along either axis or both: how
/// well the template also fits there stretched. Why: a template whose pattern repeats along
/// one axis (stripes, grain) fits a stretched pose as well as the right one, and such places
/// line up along the pattern, all above the rest of the image together; their scales are
/// undetermined and the answers no more than the image's texture.
fn best_stretched_score(verifier: &Verifier, pose: &Pose) -> f32 {
    let (up, down) = (SCALE_STEP, 1.0 / SCALE_STEP);
    [
        (up, 1.0),
        (down, 1.0),
        (1.0, up),
        (1.0, down),
        (up, up),
        (down, down),
    ]
    .into_iter()
    .map(|(fx, fy)| {
        let stretched = Pose {
            scale_x: pose.scale_x * fx,
            scale_y: pose.scale_y * fy,
            ..*pose
        };
        verifier.score_at(&stretched)
    })
    .fold(0.0, f32::max)
}

/// Raises the answers that stand out from every other place the search scored in the same
/// image to [`STAND_OUT_SCORE`] (docs/accuracy.md, "What a score means": standing out). Why:
/// JPEG and defocus take a part's fine detail, and a detailed template's correlation then falls
/// to 0.6–0.85 while the image's look-alikes fall with it; the part's order among them holds
/// (tuning photos: every JPEG and defocus loss scored above the same template's best answer in
/// the same scene without the part), its level does not.
///
/// The places are the `answers` (confirmed, their score) and the `ranked` screens that overlap
/// none of them (their score at the screened pose, [`rank_by_score`]). Sorted by score, the
/// lowest band of [`STAND_OUT_MARGIN`] that no place falls in, with a place at
/// [`STAND_OUT_FLOOR`] or more just above it, splits them: the answers above it stand out (as
/// in Lowe's ratio test, the best is compared with the next best that is not the same thing;
/// several parts of one template in a frame stand out together). No place below the band (too
/// few candidates to say how high the image's decoys reach, or no screen ranked): nothing
/// stands out. Only the
/// image decides, not the network's heatmap, whose values are the weights' own scale: with a
/// heatmap gate (0.2, margin 0.3) the tuning set found fewer parts (jpeg-30 88.5 %, defocus-2
/// 90.5 %, against 90.5 / 91.0 % at margin 0.4 without it) with as many answers without the
/// part (40 / 38 / 40).
///
/// An answer stands out only where its own pose does too: `stretched` gives the best score of
/// its place at other scales ([`best_stretched_score`]), which must lie [`STAND_OUT_OWN_MARGIN`]
/// below its own.
fn lift_standing_out(
    answers: &mut [Pose],
    ranked: &[(f32, Pose)],
    (tw, th): (f32, f32),
    stretched: impl Fn(&Pose) -> f32,
) {
    if ranked.is_empty() {
        return;
    }
    let answer_corners: Vec<_> = answers.iter().map(|pose| pose.corners(tw, th)).collect();
    let mut scores: Vec<f32> = answers.iter().map(|pose| pose.score).collect();
    scores.extend(ranked.iter().filter_map(|(score, screened)| {
        let corners = screened.corners(tw, th);
        answer_corners
            .iter()
            .all(|answer| rotated_iou(&corners, answer) <= SAME_PLACE_IOU)
            .then_some(*score)
    }));
    scores.sort_by(|a, b| b.total_cmp(a));
    let Some(lowest_standing_out) = scores
        .windows(2)
        .rev()
        .find(|pair| pair[0] >= STAND_OUT_FLOOR && pair[0] - pair[1] >= STAND_OUT_MARGIN)
        .map(|pair| pair[0])
    else {
        return;
    };
    for answer in answers {
        if answer.score >= lowest_standing_out
            && answer.score < STAND_OUT_SCORE
            && answer.score - stretched(answer) >= STAND_OUT_OWN_MARGIN
        {
            answer.score = STAND_OUT_SCORE;
        }
    }
}

/// A candidate that passed the screen, with its screened box for the duplicate check.
struct Survivor {
    candidate: Pose,
    screen: Screened,
    corners: [(f32, f32); 4],
}

/// The answers of one job and where the verification's time went.
pub struct Verification {
    pub poses: Vec<Pose>,
    pub screen_ms: f64,
    pub confirm_ms: f64,
    /// Candidates were left unscreened or unconfirmed because the time limit had come.
    pub timed_out: bool,
}

/// Verifies `candidates` (network poses in image coordinates, `network_score` set) of a
/// `template` in `image`, then selects the answers.
pub fn verify_candidates(
    template: &GrayImage32,
    size: (f32, f32),
    image: &GrayImage32,
    candidates: Vec<Pose>,
    options: &MatchOptions,
) -> Verification {
    verify_candidates_until(
        template,
        size,
        image,
        candidates,
        options,
        Heads::Trusted,
        None,
    )
}

/// [`verify_candidates`] until `answer_by`: a candidate not yet screened or confirmed then is
/// left out (each takes a fraction of a millisecond to a few milliseconds, the granularity of
/// the limit), and the verification says it timed out.
///
/// When covered parts are expected ([`MatchOptions::expects_covered_parts`]) the candidates
/// are verified five times: with the whole template and with each quarter of it ignored. The
/// screen, the alignment and the similarity all correlate the whole template, and a cover
/// (a plain clamp, clutter) spoils each of them; the template without the covered quarter
/// finds the part as a mask does. Every answer is then scored with the whole template
/// ([`Verifier::score_at`]), so a part with a quarter covered still scores what its visible
/// share says (about 0.75), not as a whole part. The network's candidates are the same for
/// all five (it is shown the template as registered); the verification costs five times.
pub fn verify_candidates_until(
    template: &GrayImage32,
    size: (f32, f32),
    image: &GrayImage32,
    candidates: Vec<Pose>,
    options: &MatchOptions,
    heads: Heads,
    answer_by: Option<Instant>,
) -> Verification {
    if !options.expects_covered_parts(template) || candidates.is_empty() {
        return verify_template(template, size, image, candidates, options, heads, answer_by);
    }
    let mut all = verify_template(
        template,
        size,
        image,
        candidates.clone(),
        options,
        heads,
        answer_by,
    );
    let scorer = Verifier::for_options(template, image, options).with_heads(heads);
    for partial in without_each_quarter(template) {
        let found = verify_partial(
            &partial,
            &scorer,
            size,
            image,
            candidates.clone(),
            options,
            answer_by,
        );
        all.screen_ms += found.screen_ms;
        all.confirm_ms += found.confirm_ms;
        all.timed_out |= found.timed_out;
        all.poses.extend(found.poses);
    }
    all.poses = select(all.poses, options, size.0, size.1);
    all
}

/// `template` four times, each with one quarter ignored (NaN): top left, top right, bottom
/// left, bottom right; a quarter that would leave fewer than 16 used pixels (a mask already
/// ignores most of the rest) is left out.
pub fn without_each_quarter(template: &GrayImage32) -> Vec<GrayImage32> {
    let (w, h) = (template.width, template.height);
    (0..4)
        .filter_map(|quarter| {
            let mut partial = template.clone();
            for y in 0..h {
                for x in 0..w {
                    let right = usize::from(2 * x >= w);
                    let bottom = usize::from(2 * y >= h);
                    if right + 2 * bottom == quarter {
                        partial.values[y * w + x] = f32::NAN;
                    }
                }
            }
            let used = partial.values.iter().filter(|v| !v.is_nan()).count();
            (used >= 16).then_some(partial)
        })
        .collect()
}

/// Verifies `candidates` with `partial` (the template with a part ignored) and scores each
/// answer with `whole`, the whole template's verifier ([`Verifier::score_at`]): found as the
/// visible part, scored as the part. The heads are trusted as far as `whole` trusts them.
pub fn verify_partial(
    partial: &GrayImage32,
    whole: &Verifier,
    size: (f32, f32),
    image: &GrayImage32,
    candidates: Vec<Pose>,
    options: &MatchOptions,
    answer_by: Option<Instant>,
) -> Verification {
    let mut found = verify_template(
        partial,
        size,
        image,
        candidates,
        options,
        whole.heads,
        answer_by,
    );
    for pose in &mut found.poses {
        pose.score = whole.score_at(pose);
    }
    found.poses = select(found.poses, options, size.0, size.1);
    found
}

/// [`verify_candidates_until`] for one template (whole or with a quarter ignored).
fn verify_template(
    template: &GrayImage32,
    (tw, th): (f32, f32),
    image: &GrayImage32,
    candidates: Vec<Pose>,
    options: &MatchOptions,
    heads: Heads,
    answer_by: Option<Instant>,
) -> Verification {
    if candidates.is_empty() {
        return Verification {
            poses: Vec::new(),
            screen_ms: 0.0,
            confirm_ms: 0.0,
            timed_out: false,
        };
    }
    let limit = TimeLimit::new(answer_by);
    let start = Instant::now();
    let verifier = Verifier::for_options(template, image, options).with_heads(heads);
    let mut screened: Vec<(Pose, Screened)> = candidates
        .into_par_iter()
        .filter(|_| limit.in_time())
        .map(|candidate| (candidate, verifier.screen(&candidate)))
        .collect();
    let light = if wants_second_screen(
        screened.iter().map(|(_, screen)| screen),
        options.max_instances,
    ) {
        Light::Planes
    } else {
        Light::Even
    };
    if light == Light::Planes {
        let twin = verifier.full_resolution_twin();
        screened = screened
            .into_par_iter()
            .filter(|_| limit.in_time())
            .map(|(candidate, first)| {
                let second = verifier.screen_evened_also_at(twin.as_ref(), &candidate, first);
                (candidate, second)
            })
            .collect();
    }
    // Best screen first, the best few of them by their score; near-duplicates (the same object
    // seen by two peaks) need no second confirmation.
    screened.sort_by(|a, b| b.1.score.total_cmp(&a.1.score));
    let budget = options.max_instances + SPARE_SURVIVORS;
    let ranked = rank_by_score(
        &verifier,
        &mut screened,
        budget + RANKED_BEYOND_SURVIVORS,
        &limit,
    );
    let mut survivors: Vec<Survivor> = Vec::new();
    for (candidate, screen) in screened {
        if survivors.len() == budget || screen.score < SCREEN_MIN {
            break;
        }
        let corners = screen.pose.corners(tw, th);
        if survivors
            .iter()
            .all(|other| rotated_iou(&corners, &other.corners) <= options.max_overlap)
        {
            survivors.push(Survivor {
                candidate,
                screen,
                corners,
            });
        }
    }
    let screen_ms = start.elapsed().as_secs_f64() * 1e3;
    let start = Instant::now();
    let mut confirmed: Vec<Pose> = survivors
        .into_par_iter()
        .filter(|_| limit.in_time())
        .map(
            |Survivor {
                 candidate, screen, ..
             }| {
                let verified = verifier.confirm(&screen, &candidate, light);
                Pose {
                    score: verified.score,
                    network_score: candidate.network_score,
                    ..verified.pose
                }
            },
        )
        .collect();
    lift_standing_out(&mut confirmed, &ranked, (tw, th), |answer| {
        best_stretched_score(&verifier, answer)
    });
    let poses = select(confirmed, options, tw, th);
    Verification {
        poses,
        screen_ms,
        confirm_ms: start.elapsed().as_secs_f64() * 1e3,
        timed_out: limit.missed(),
    }
}

/// A screening level image with, where small enough to keep, its blurred gradients.
struct ScreeningLevel {
    image: GrayImage32,
    gradients: Option<align::GradientWindow>,
}

/// `image` with the light evened out: each pixel divided by the mean of the `(2·radius + 1)²`
/// window around it (clipped at the border; an integral image, so any radius costs the same),
/// times a half to keep the values near the image's range. A mean under 0.02 (black) divides
/// as 0.02.
fn evened_light(image: &GrayImage32, radius: usize) -> GrayImage32 {
    let (w, h) = (image.width, image.height);
    let mut integral = vec![0.0f64; (w + 1) * (h + 1)];
    for y in 0..h {
        let mut row = 0.0f64;
        for x in 0..w {
            row += f64::from(image.values[y * w + x]);
            integral[(y + 1) * (w + 1) + x + 1] = integral[y * (w + 1) + x + 1] + row;
        }
    }
    GrayImage32::from_fn(w, h, |x, y| {
        let (x0, x1) = (x.saturating_sub(radius), (x + radius + 1).min(w));
        let (y0, y1) = (y.saturating_sub(radius), (y + radius + 1).min(h));
        let sum =
            integral[y1 * (w + 1) + x1] - integral[y0 * (w + 1) + x1] - integral[y1 * (w + 1) + x0]
                + integral[y0 * (w + 1) + x0];
        let mean = (sum / ((x1 - x0) * (y1 - y0)) as f64) as f32;
        0.5 * image.values[y * w + x] / mean.max(0.02)
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::refine::textured;

    /// Relative spread (standard deviation over mean) of `a / b` over the interior pixels.
    fn ratio_spread(a: &GrayImage32, b: &GrayImage32, margin: usize) -> f32 {
        let ratios: Vec<f32> = (margin..a.height - margin)
            .flat_map(|y| (margin..a.width - margin).map(move |x| y * a.width + x))
            .map(|i| a.values[i] / b.values[i])
            .collect();
        let mean = ratios.iter().sum::<f32>() / ratios.len() as f32;
        let var = ratios.iter().map(|r| (r - mean).powi(2)).sum::<f32>() / ratios.len() as f32;
        var.sqrt() / mean
    }

    fn chance_at_scales(chance: f32, pose: &Pose) -> f32 {
        raised_chance(chance, shrunk_chance_factor(pose))
    }

    #[test]
    fn a_pose_smaller_than_the_template_is_held_to_a_higher_chance_level() {
        let at = |scale_x, scale_y| Pose {
            scale_x,
            scale_y,
            ..Pose::upright(0.0, 0.0, 0.0)
        };
        // At or above the template's area: the template's own chance level.
        for (sx, sy) in [(1.0, 1.0), (1.5, 0.7), (2.0, 2.0)] {
            assert_eq!(chance_at_scales(0.4, &at(sx, sy)), 0.4, "{sx}/{sy}");
        }
        // Half the area: 2·ln M from 14 to 14 + 4·ln 2.
        let half = chance_at_scales(0.4, &at(0.5, 1.0));
        let expected =
            0.4 * ((CHANCE_LOG_HYPOTHESES + 4.0 * 2f32.ln()) / CHANCE_LOG_HYPOTHESES).sqrt();
        assert!((half - expected).abs() < 1e-6, "{half} against {expected}");
        assert!(chance_at_scales(0.4, &at(0.5, 0.5)) > half);
        // Capped, never lowered.
        assert_eq!(chance_at_scales(0.9, &at(0.1, 0.1)), SHRUNK_MAX_CHANCE);
        assert_eq!(chance_at_scales(0.97, &at(0.1, 0.1)), 0.97);
        assert_eq!(chance_at_scales(0.4, &at(f32::NAN, 1.0)), 0.4);
        // A smooth template (chance at its cap 0.8) correlating at 0.985: 0.9 at its own size,
        // under it at 0.6 of it either way.
        let reading = Reading::whole(ReadingKind::Whole, 0.985, MAX_CHANCE);
        let raised = |pose| reading.raised_by(shrunk_chance_factor(&pose)).score();
        assert!(raised(at(1.0, 1.0)) >= 0.9);
        assert!(raised(at(0.6, 0.6)) < 0.9);
    }

    #[test]
    fn evening_the_light_takes_out_a_gain_that_falls_across_the_frame() {
        let scene = textured(160, 120, 5);
        // Gain 1.3 at the left edge, 0.4 at the right, as in `--condition uneven-light`.
        let lit = GrayImage32::from_fn(160, 120, |x, y| {
            scene.values[y * 160 + x] * (1.3 - 0.9 * x as f32 / 159.0)
        });
        let evened = evened_light(&lit, 20);
        let before = ratio_spread(&lit, &scene, 20);
        let after = ratio_spread(&evened, &scene, 20);
        assert!(before > 0.2, "the light's own spread {before}");
        assert!(after < 0.1, "left after evening {after} (before {before})");
    }

    /// Screens scored `scores`, each at its own place away from (0..200, 0) where the answers
    /// lie.
    fn decoys(scores: &[f32]) -> Vec<(f32, Pose)> {
        scores
            .iter()
            .enumerate()
            .map(|(i, &score)| (score, Pose::upright(50.0 * i as f32, 300.0, score)))
            .collect()
    }

    const SIZE: (f32, f32) = (36.0, 36.0);

    #[test]
    fn an_answer_that_stands_out_from_every_other_place_reports_the_default_min_score() {
        let mut answers = vec![Pose::upright(100.0, 0.0, 0.72)];
        let mut ranked = decoys(&[0.31, 0.25, 0.2]);
        // The answer's own screen is the same place, not a decoy.
        ranked.push((0.7, Pose::upright(101.0, 1.0, 0.7)));
        lift_standing_out(&mut answers, &ranked, SIZE, |_| 0.0);
        assert_eq!(answers[0].score, STAND_OUT_SCORE);
        assert!(
            f64::from(answers[0].score) >= 0.9,
            "passes min_score 0.9 as a double"
        );
        // An answer above the default level keeps its own score.
        let mut answers = vec![Pose::upright(100.0, 0.0, 0.97)];
        lift_standing_out(&mut answers, &ranked, SIZE, |_| 0.0);
        assert_eq!(answers[0].score, 0.97);
    }

    #[test]
    fn an_answer_that_fits_as_well_stretched_does_not_stand_out() {
        let ranked = decoys(&[0.31, 0.25, 0.2]);
        let mut answers = vec![Pose::upright(100.0, 0.0, 0.72)];
        lift_standing_out(&mut answers, &ranked, SIZE, |_| 0.7);
        assert_eq!(answers[0].score, 0.72);
        lift_standing_out(&mut answers, &ranked, SIZE, |_| 0.72 - STAND_OUT_OWN_MARGIN);
        assert_eq!(answers[0].score, STAND_OUT_SCORE);
    }

    #[test]
    fn an_answer_with_a_decoy_within_the_margin_is_not_lifted() {
        let mut answers = vec![Pose::upright(100.0, 0.0, 0.72)];
        lift_standing_out(&mut answers, &decoys(&[0.35, 0.3, 0.2]), SIZE, |_| 0.0);
        assert_eq!(answers[0].score, 0.72);
    }

    #[test]
    fn an_answer_below_the_floor_is_not_lifted() {
        let mut answers = vec![Pose::upright(0.0, 0.0, STAND_OUT_FLOOR - 0.02)];
        lift_standing_out(&mut answers, &decoys(&[0.1, 0.05]), SIZE, |_| 0.0);
        assert_eq!(answers[0].score, STAND_OUT_FLOOR - 0.02);
    }

    #[test]
    fn several_parts_above_the_same_empty_band_stand_out_together() {
        let mut answers = vec![
            Pose::upright(0.0, 0.0, 0.8),
            Pose::upright(100.0, 0.0, 0.76),
            Pose::upright(200.0, 0.0, 0.3),
        ];
        lift_standing_out(&mut answers, &decoys(&[0.3, 0.25, 0.2]), SIZE, |_| 0.0);
        let scores: Vec<f32> = answers.iter().map(|a| a.score).collect();
        assert_eq!(scores, [STAND_OUT_SCORE, STAND_OUT_SCORE, 0.3]);
    }

    #[test]
    fn with_no_other_place_scored_nothing_stands_out() {
        let mut answers = vec![Pose::upright(100.0, 0.0, 0.8)];
        lift_standing_out(
            &mut answers,
            &[(0.78, Pose::upright(100.0, 0.0, 0.78))],
            SIZE,
            |_| 0.0,
        );
        assert_eq!(answers[0].score, 0.8);
    }
}
