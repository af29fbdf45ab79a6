//! Images in, poses out. This module orchestrates one search, stage by stage:
//! 1. **network proposals**: encode the template, plan how the image is shown to the network
//!    ([`plan`]), run it on batches of same-sized pieces, read the heatmap's peaks ([`peaks`])
//!    as candidate poses in the public convention ([`Matcher::propose`]);
//! 2. **verification** on the image ([`verification`]): screen every candidate, confirm the best;
//! 3. **classical fallback** ([`classical`]) when no answer reaches `min_score` (for a masked
//!    template always): its peaks go through the same verification;
//! 4. **selection** ([`selection`]): ranges, non-maximum suppression, `min_score`,
//!    `max_instances`.
//!
//! Without verification ([`MatchOptions::verify`] off) the network's poses go straight to the
//! selection, scored by their heatmap value.

pub mod classical;
mod error;
mod limits;
pub mod options;
pub mod peaks;
#[cfg(test)]
mod pipeline_tests;
pub mod plan;
pub mod selection;
pub mod template_mask;
pub mod time_limit;
pub mod verification;

use std::sync::Arc;
use std::time::Instant;

use burn::prelude::*;
use rayon::prelude::*;

use crate::geometry::{Pose, TemplateFrame, TemplateOrigin};
use crate::imaging::GrayImage32;
use crate::imaging::{InputConvention, RgbImage32, resize_rgb, to_network_input};
use crate::model::{
    GridShape, InferenceNetwork, PoseHeads, Precision, PrecisionError, TEMPLATE_GRID, Tdcm,
    TrainedOn,
};
use crate::refine::NoiseLevel;
pub use error::MatchError;
pub use limits::{
    MAX_TEMPLATE_SIDE, MIN_IMAGE_SIDE, MIN_TEMPLATE_SIDE, TEMPLATE_LIMITS, search_limits,
};
pub use options::{
    AngleRange, Contrast, MatchOptions, Method, OptionsError, Polarity, ScaleRange, ValidOptions,
};
use peaks::{MapPlanes, find_peaks, peak_at};
use plan::{MAX_NETWORK_PIXELS, MIN_INPUT_SIDE, ScalePass, Tile};
use selection::select;
pub use template_mask::{MaskError, TemplateMask};
use verification::{Heads, Verifier, verify_candidates, verify_candidates_until};

/// A template after encoding: what the service caches per template ID.
#[derive(Debug, Clone)]
pub struct EncodedTemplate {
    /// Registered size, the reference for reported scales.
    pub width: u32,
    pub height: u32,
    /// `[1, 96, k, k]` depthwise kernels.
    pub kernel: Tensor<4>,
    /// The registered template in grey, for refinement.
    pub gray: Arc<GrayImage32>,
    /// The same for the template with its contrast reversed (`1 − v`): what a search for
    /// [`Polarity::Reversed`] parts uses. Encoded together with the template, in one batch.
    pub reversed_kernel: Tensor<4>,
    pub reversed_gray: Arc<GrayImage32>,
    /// The reference point registered with the template (`None`: its centre). The search
    /// never uses it; answers report where it lands ([`TemplateFrame`]).
    pub origin: Option<TemplateOrigin>,
}

impl EncodedTemplate {
    /// What poses of this template are reported against.
    pub fn frame(&self) -> TemplateFrame {
        TemplateFrame::new(self.width, self.height, self.origin)
    }

    /// The kernels that look for parts of `contrast`.
    pub fn kernel_for(&self, contrast: Contrast) -> &Tensor<4> {
        match contrast {
            Contrast::Same => &self.kernel,
            Contrast::Reversed => &self.reversed_kernel,
        }
    }

    /// The grey template that parts of `contrast` look like.
    pub fn gray_for(&self, contrast: Contrast) -> &GrayImage32 {
        match contrast {
            Contrast::Same => &self.gray,
            Contrast::Reversed => &self.reversed_gray,
        }
    }
}

/// One search to run.
pub struct MatchJob<'a> {
    pub template: &'a EncodedTemplate,
    pub image: &'a RgbImage32,
    pub options: &'a ValidOptions,
    /// When the answer is due ([`MatchOptions::timeout_ms`] after the request arrived): work
    /// still to do then is left out and the answer says it timed out. `None`: no limit.
    pub answer_by: Option<Instant>,
}

impl MatchJob<'_> {
    fn overdue(&self) -> bool {
        self.answer_by.is_some_and(|due| Instant::now() >= due)
    }
}

/// Where the time of one job went.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct MatchTimings {
    pub prepare_ms: f64,
    pub network_ms: f64,
    pub peaks_ms: f64,
    /// Converting the image to grey and screening every candidate (0 without refinement).
    pub screen_ms: f64,
    /// Refining and scoring the candidates that survived the screen.
    pub refine_ms: f64,
    /// The classical fallback (0 when it did not run; [`MatchOptions::classical_fallback`]).
    pub fallback_ms: f64,
}

impl MatchTimings {
    /// Everything after the network: peaks, screening, refinement and the classical fallback.
    pub fn postprocess_ms(&self) -> f64 {
        self.peaks_ms + self.screen_ms + self.refine_ms + self.fallback_ms
    }
}

/// The answer to one job.
#[derive(Debug, Clone)]
pub struct MatchOutcome {
    pub poses: Vec<Pose>,
    pub timings: MatchTimings,
    /// The job's time limit came before its work was done: `poses` are what was verified by
    /// then (network pieces, candidates or the classical fallback left out).
    pub timed_out: bool,
}

/// The network's candidates for one job, before verification.
#[derive(Debug, Clone, Default)]
pub struct Proposal {
    /// Network poses in image coordinates (`score` = `network_score` = heatmap value), best
    /// first: every peak at or above the candidate threshold (`min_score` without refinement),
    /// the best of every tile's up to the budget of the search. Parts of the template's own
    /// contrast ([`Contrast::Same`]; empty when the job's polarity is `reversed`).
    pub candidates: Vec<Pose>,
    /// The same for parts of reversed contrast (empty unless the job's polarity asks for
    /// them); each contrast has its own budget.
    pub reversed: Vec<Pose>,
    /// Time so far (prepare, network, peaks).
    pub timings: MatchTimings,
    /// Network pieces were left out because the job's time limit had come.
    pub timed_out: bool,
    /// Whether the candidates' angle, scales and centres can be believed: the weights were
    /// trained throughout on parts of this template's shape ([`Matcher::heads_for`]).
    pub heads: Heads,
}

/// The network and how to feed it. Not thread-safe by design: one owner (a CLI, the service's
/// model thread) drives it. On the host CPU the network keeps its activation buffers from one
/// search to the next (a large frame's tiles and successive frames reuse them); an owner that
/// goes idle frees them with `matcher.network().release_buffers()`, as the service does.
pub struct Matcher {
    network: InferenceNetwork,
    device: Device,
    convention: InputConvention,
    /// Network inputs up to this many pixels run whole, larger ones are tiled; `None`: what
    /// the network's precision allows ([`plan::max_whole_pixels`]).
    max_whole_pixels: Option<usize>,
    /// Objects' size on the network grid relative to the template grid (see
    /// [`plan::scale_passes`]); [`plan::DEFAULT_GRID_SCALE`] everywhere but in measurements.
    grid_scale: f32,
    /// What the weights were trained on, where their file records it: where a template's parts
    /// fall outside, the verification does not trust the heads ([`Matcher::heads_for`]).
    trained_on: Option<TrainedOn>,
}

/// A network-input piece: one tile of one pass of one job, searched for one contrast.
struct Piece {
    job: usize,
    contrast: Contrast,
    pass: ScalePass,
    tile: Tile,
    /// Network input size (the tile's, after padding small images).
    width: usize,
    height: usize,
    /// The normalised input, planar `[3, height, width]`; handed to the network (left empty)
    /// when the piece runs, so a large frame's input exists once, not as RGB and planar both.
    planar: Vec<f32>,
}

impl Matcher {
    /// Builds the inference network for `device` once (see [`InferenceNetwork::new`]).
    pub fn new(model: Tdcm, device: Device, convention: InputConvention) -> Self {
        Self {
            network: InferenceNetwork::new(model, &device),
            device,
            convention,
            max_whole_pixels: None,
            grid_scale: plan::DEFAULT_GRID_SCALE,
            trained_on: None,
        }
    }

    /// The weights' training record ([`crate::model::WeightsSource::trained_on`]); without one
    /// the heads are trusted everywhere.
    pub fn with_trained_on(mut self, trained_on: Option<TrainedOn>) -> Self {
        self.trained_on = trained_on;
        self
    }

    /// Whether the heads can be believed for `job`: its parts, shown on the grid as the scale
    /// plan shows them (each pass of the caller's scale range on its own), lie inside the shapes
    /// the weights were trained on throughout.
    pub fn heads_for(&self, job: &MatchJob) -> Heads {
        let Some(record) = &self.trained_on else {
            return Heads::Trusted;
        };
        let (lo, hi) = job
            .options
            .scale_range
            .map_or((1.0, 1.0), |r| (r.min, r.max));
        let outside = plan::split_scale_range(lo, hi).into_iter().any(|pass| {
            let shape = GridShape::of_template(job.template.width, job.template.height, pass);
            let shown = GridShape {
                smallest: shape.smallest * self.grid_scale,
                largest: shape.largest * self.grid_scale,
                ..shape
            };
            record.outside(&shown).is_some()
        });
        if outside {
            Heads::Untrusted
        } else {
            Heads::Trusted
        }
    }

    /// Runs the network's large products in `precision` ([`Precision`]); refused where this
    /// machine or device cannot.
    pub fn with_precision(mut self, precision: Precision) -> Result<Self, PrecisionError> {
        self.network = self.network.with_precision(precision)?;
        Ok(self)
    }

    /// Shows objects at `grid_scale` times the template grid (a measurement knob for the scale
    /// plan of large frames; the service and CLI keep 1). Clamped to 0.25..=2.
    pub fn set_grid_scale(&mut self, grid_scale: f32) {
        self.grid_scale = if grid_scale.is_finite() {
            grid_scale.clamp(0.25, 2.0)
        } else {
            1.0
        };
    }

    /// Inputs above `pixels` network pixels run as overlapping tiles (bounded memory; see
    /// [`plan`]). The default depends on the precision: [`plan::max_whole_pixels`].
    pub fn with_max_whole_pixels(mut self, pixels: usize) -> Self {
        self.max_whole_pixels = Some(pixels);
        self
    }

    fn max_whole_pixels(&self) -> usize {
        self.max_whole_pixels
            .unwrap_or_else(|| plan::max_whole_pixels(self.network.precision()))
    }

    pub fn device(&self) -> &Device {
        &self.device
    }

    pub fn network(&self) -> &InferenceNetwork {
        &self.network
    }

    /// Resizes a template to the network grid and encodes it into its kernels.
    pub fn encode_template(&self, template: &RgbImage32) -> Result<EncodedTemplate, MatchError> {
        self.encode_masked_template(template, None)
    }

    /// [`Matcher::encode_template`] with the pixels `mask` ignores left out of every score
    /// and refinement ([`template_mask`]).
    pub fn encode_masked_template(
        &self,
        template: &RgbImage32,
        mask: Option<&TemplateMask>,
    ) -> Result<EncodedTemplate, MatchError> {
        check_template_size(template.width, template.height)?;
        if let Some(mask) = mask {
            mask.check_fits(template.width, template.height)?;
        }
        let mask = mask.filter(|m| !m.uses_everything());
        // The network sees the template as registered, ignored pixels included: it was
        // trained on whole templates, and showing it a neutral patch there instead found fewer
        // parts (template_mask.rs).
        let grid = resize_rgb(template, TEMPLATE_GRID as u32, TEMPLATE_GRID as u32);
        let mut reversed_grid = grid.clone();
        reversed_grid.pixels.iter_mut().for_each(|v| *v = 1.0 - *v);
        let input = to_network_input(&[&grid, &reversed_grid], self.convention, &self.device);
        let [kernel, reversed_kernel] = self
            .network
            .encode_templates(input)
            .chunk(2, 0)
            .try_into()
            .expect("two templates in, two kernels out");
        let gray = GrayImage32::from_rgb(template);
        let gray = match mask {
            Some(mask) => mask.applied_to(&gray),
            None => gray,
        };
        let mut reversed_gray = gray.clone();
        reversed_gray.values.iter_mut().for_each(|v| *v = 1.0 - *v);
        Ok(EncodedTemplate {
            width: template.width,
            height: template.height,
            kernel,
            gray: Arc::new(gray),
            reversed_kernel,
            reversed_gray: Arc::new(reversed_gray),
            origin: None,
        })
    }

    /// Matches one template in one image.
    pub fn match_one(
        &self,
        template: &EncodedTemplate,
        image: &RgbImage32,
        options: &ValidOptions,
    ) -> Result<MatchOutcome, MatchError> {
        self.match_many(&[MatchJob {
            template,
            image,
            options,
            answer_by: options.answer_by(Instant::now()),
        }])
        .pop()
        .expect("one job in, one answer out")
    }

    /// Finds each of `templates` in one `image`: one job per template, sharing the image and
    /// the time limit (counted from now). Same-sized network pieces are batched together, and
    /// consecutive pieces of identical input (templates of the same area get the same scale
    /// plan) run the search backbone once.
    pub fn match_templates(
        &self,
        templates: &[&EncodedTemplate],
        image: &RgbImage32,
        options: &ValidOptions,
    ) -> Vec<Result<MatchOutcome, MatchError>> {
        let answer_by = options.answer_by(Instant::now());
        let jobs: Vec<MatchJob> = templates
            .iter()
            .map(|&template| MatchJob {
                template,
                image,
                options,
                answer_by,
            })
            .collect();
        self.match_many(&jobs)
    }

    /// Matches several independent jobs, batching same-sized network pieces together.
    pub fn match_many(&self, jobs: &[MatchJob]) -> Vec<Result<MatchOutcome, MatchError>> {
        self.match_many_wanted(jobs, &|_| true)
            .into_iter()
            .map(|answer| answer.expect("every job is wanted"))
            .collect()
    }

    /// [`Matcher::match_many`] for callers that may leave: after the network, a job for which
    /// `still_wanted(index)` is false is not verified or refined and answers `None`.
    pub fn match_many_wanted(
        &self,
        jobs: &[MatchJob],
        still_wanted: &dyn Fn(usize) -> bool,
    ) -> Vec<Option<Result<MatchOutcome, MatchError>>> {
        let proposals = self.propose(jobs);
        // Asked once the network is done, for every job at once: the verifications below run
        // side by side.
        let wanted: Vec<bool> = (0..jobs.len()).map(still_wanted).collect();
        // Each job's verification is its own, so they run in parallel: one job's serial steps
        // (its verifier's setup, the selection, the classical fallback's pyramid) then leave
        // no core idle.
        proposals
            .into_par_iter()
            .zip(jobs.par_iter())
            .zip(wanted.into_par_iter())
            .map(|((proposal, job), wanted)| wanted.then(|| proposal.map(|p| answer(job, p))))
            .collect()
    }

    /// The network's half of [`Matcher::match_many`]: every job's candidates (network poses in
    /// image coordinates, best heatmap value first), before verification and selection.
    pub fn propose(&self, jobs: &[MatchJob]) -> Vec<Result<Proposal, MatchError>> {
        let start = Instant::now();
        let mut results: Vec<Result<Proposal, MatchError>> = Vec::with_capacity(jobs.len());
        let mut pieces = Vec::new();
        for (index, job) in jobs.iter().enumerate() {
            match prepare(
                index,
                job,
                // A job with a time limit runs in tiles of at most TIMED_TILE_PIXELS, so the
                // limit is checked between tiles rather than after a whole frame.
                if job.answer_by.is_some() {
                    self.max_whole_pixels().min(plan::TIMED_TILE_PIXELS)
                } else {
                    self.max_whole_pixels()
                },
                self.grid_scale,
                self.convention,
            ) {
                Ok(job_pieces) => {
                    pieces.extend(job_pieces);
                    results.push(Ok(Proposal {
                        heads: self.heads_for(job),
                        ..Proposal::default()
                    }));
                }
                Err(e) => results.push(Err(e)),
            }
        }
        let prepare_ms = ms_since(start);
        let (mut network_ms, mut peaks_ms) = (0.0, 0.0);
        // Same-sized pieces share a forward pass.
        pieces.sort_by_key(|p| (p.width, p.height));
        for group in pieces.chunk_by_mut(|a, b| (a.width, a.height) == (b.width, b.height)) {
            // One forward holds at most max_whole_pixels network pixels (bounded memory): large
            // tiles go one at a time, small images together. How many jobs come at once is the
            // caller's choice (the service's `max_batch_size`), not limited again here.
            let pixels = group[0].width * group[0].height;
            // A job with a time limit runs its pieces one at a time, so that the limit is
            // checked between tiles (a batch of tiles costs no less than the tiles one by one
            // on the CPU; docs/speed.md).
            let per_batch = if group.iter().any(|p| jobs[p.job].answer_by.is_some()) {
                1
            } else {
                (self.max_whole_pixels() / pixels).max(1)
            };
            for batch in group.chunks_mut(per_batch) {
                // A job past its time limit gets no more network pieces (one piece is the
                // granularity: a 2048 frame's tile, docs/service.md "Time limits").
                if batch.iter().all(|p| jobs[p.job].overdue()) {
                    for piece in batch.iter() {
                        if let Ok(proposal) = &mut results[piece.job] {
                            proposal.timed_out = true;
                        }
                    }
                    continue;
                }
                let t = Instant::now();
                let maps = self.run_network(jobs, batch);
                network_ms += ms_since(t);
                let t = Instant::now();
                let per_piece = maps.len() / batch.len();
                for (piece, maps) in batch.iter().zip(maps.chunks_exact(per_piece)) {
                    if let Ok(proposal) = &mut results[piece.job] {
                        let poses = piece_poses(piece, maps, &jobs[piece.job], proposal.heads);
                        match piece.contrast {
                            Contrast::Same => proposal.candidates.extend(poses),
                            Contrast::Reversed => proposal.reversed.extend(poses),
                        }
                    }
                }
                self.network.recycle(maps);
                peaks_ms += ms_since(t);
            }
        }
        let count = results.iter().filter(|r| r.is_ok()).count().max(1) as f64;
        for (proposal, job) in results.iter_mut().zip(jobs) {
            let Ok(proposal) = proposal else { continue };
            for candidates in [&mut proposal.candidates, &mut proposal.reversed] {
                candidates.sort_by(|a, b| b.network_score.total_cmp(&a.network_score));
                // The budget holds for the whole search, not per tile: a 2048 frame is 9
                // tiles, and 9 budgets of low peaks cost the screen more than they find
                // (docs/verification.md).
                candidates.truncate(peak_limit(job.options, proposal.heads));
            }
            proposal.timings = MatchTimings {
                prepare_ms: prepare_ms / count,
                network_ms: network_ms / count,
                peaks_ms: peaks_ms / count,
                ..MatchTimings::default()
            };
        }
        results
    }

    /// One forward pass over same-sized pieces; returns the five planes of each, concatenated
    /// as `[piece][score, sign, cos, scale_x, scale_y]` (for [`InferenceNetwork::recycle`] once
    /// read).
    fn run_network(&self, jobs: &[MatchJob], batch: &mut [Piece]) -> Vec<f32> {
        let (width, height) = (batch[0].width, batch[0].height);
        let planar = if let [piece] = batch {
            std::mem::take(&mut piece.planar)
        } else {
            batch
                .iter_mut()
                .flat_map(|p| std::mem::take(&mut p.planar))
                .collect()
        };
        let kernels = Tensor::cat(
            batch
                .iter()
                .map(|p| jobs[p.job].template.kernel_for(p.contrast).clone())
                .collect(),
            0,
        );
        // Peak reading reads the pose maps at peaks above its threshold (and a peak's neighbours
        // above half the peak): the pose heads are needed only there.
        let least = batch
            .iter()
            .map(|p| peak_threshold(jobs[p.job].options))
            .fold(f32::INFINITY, f32::min);
        self.network.search_maps(
            planar,
            [batch.len(), height, width],
            kernels,
            PoseHeads::WhereScoreAtLeast(0.5 * least),
        )
    }
}

/// Turns a job's candidates into its answers: verified, with the classical fallback (see the
/// module doc), or as the network gave them.
pub fn answer(job: &MatchJob, proposal: Proposal) -> MatchOutcome {
    let size = (job.template.width as f32, job.template.height as f32);
    let mut timings = proposal.timings;
    let start = Instant::now();
    let contrasts = job.options.polarity.contrasts();
    let by_contrast = [
        (Contrast::Same, proposal.candidates),
        (Contrast::Reversed, proposal.reversed),
    ];
    let mut timed_out = proposal.timed_out;
    let poses = if job.options.verify {
        let image = GrayImage32::from_rgb(job.image);
        timings.screen_ms = start.elapsed().as_secs_f64() * 1e3;
        let mut poses = Vec::new();
        for (contrast, candidates) in by_contrast {
            if !contrasts.contains(&contrast) {
                continue;
            }
            let verified = verify_candidates_until(
                job.template.gray_for(contrast),
                size,
                &image,
                candidates,
                job.options,
                proposal.heads,
                job.answer_by,
            );
            timings.refine_ms += verified.confirm_ms;
            timings.screen_ms += verified.screen_ms;
            timed_out |= verified.timed_out;
            poses.extend(verified.poses);
        }
        if contrasts.len() > 1 {
            // One object seen in both contrasts is one answer.
            poses = select(poses, job.options, size.0, size.1);
        }
        if job.overdue() {
            // The fallback is a search of its own: not started once the time is up.
            timed_out |= job.options.classical_fallback
                && !poses
                    .iter()
                    .any(|p| p.score >= job.options.effective_min_score());
        } else {
            let (found, fallback_ms) = with_classical_fallbacks(
                job.template,
                &image,
                poses,
                job.options,
                job.options.effective_min_score(),
            );
            timings.fallback_ms = fallback_ms;
            poses = found;
        }
        poses
    } else {
        let candidates = by_contrast.into_iter().flat_map(|(_, c)| c).collect();
        let poses = select(candidates, job.options, size.0, size.1);
        timings.peaks_ms += start.elapsed().as_secs_f64() * 1e3;
        poses
    };
    MatchOutcome {
        poses,
        timings,
        timed_out,
    }
}

/// [`with_classical_fallback`] for each contrast the options' polarity asks for, until an
/// answer reaches `trigger_score`.
pub fn with_classical_fallbacks(
    template: &EncodedTemplate,
    image: &GrayImage32,
    answers: Vec<Pose>,
    options: &MatchOptions,
    trigger_score: f32,
) -> (Vec<Pose>, f64) {
    let mut poses = answers;
    let mut total_ms = 0.0;
    for &contrast in options.polarity.contrasts() {
        let (found, ms) = with_classical_fallback(
            template.gray_for(contrast),
            image,
            poses,
            options,
            trigger_score,
        );
        poses = found;
        total_ms += ms;
    }
    (poses, total_ms)
}

/// A noise reading ([`NoiseLevel`]) from which an image counts as noisy for the fallback: every
/// frame with noise of 15 grey levels reads 10–11, clean and JPEG-compressed ones under 5.
const NOISY_FROM_GREY_LEVELS: f32 = 5.0;

/// Least score of an answer that only the quarter-less searches of a noisy image found. Under
/// noise of 15 grey levels a part of fine grain can escape the whole template's classical
/// search and screen, and the same searches without each quarter of the template (as for
/// covered parts: [`MatchOptions::expects_covered_parts`]) reach it — its coarse template, so
/// its peaks, differ; left out a scattered quarter of the pixels instead they reach none of
/// them. Four more searches also give a decoy four more chances, so their answers count from
/// this score, not from `min_score`. Grain tuning set (`scripts/grain-photos.py`, 1000 S1.5
/// pairs, seed 0, defaults), before → at `min_score` → at 0.95: `noise-15` found 92.4 → 93.4 →
/// 93.3 %, answers ≥ 0.9 in 1000 scenes without the part under that noise 53 → 58 → 53
/// (docs/industrial.md, "Camera conditions").
const NOISY_WIDER_SEARCH_BAR: f32 = 0.95;

/// `answers` and, when none of them reaches `trigger_score` (the caller's `min_score`; for a
/// template with a mask whatever they reach) and `options` ask for it, those of the classical
/// fallback ([`classical::fallback_candidates`],
/// verified like the network's candidates; `network_score` 0), selected together under
/// `options`; with the milliseconds the fallback took (0 when it did not run). Where covered
/// parts are expected, or the image is noisy ([`NOISY_FROM_GREY_LEVELS`]; answers from
/// [`NOISY_WIDER_SEARCH_BAR`]), and still nothing reaches `trigger_score`, the fallback also
/// searches with each quarter of the template left out.
pub fn with_classical_fallback(
    template: &GrayImage32,
    image: &GrayImage32,
    answers: Vec<Pose>,
    options: &MatchOptions,
    trigger_score: f32,
) -> (Vec<Pose>, f64) {
    // A masked template's network candidates are weak (the network is shown the ignored
    // pixels too, and the part differs there): its classical search always runs.
    let verified = answers.iter().any(|p| p.score >= trigger_score);
    if !options.classical_fallback || (verified && !template.ignores_pixels()) {
        return (answers, 0.0);
    }
    let start = Instant::now();
    let mut poses = answers;
    let size = (template.width as f32, template.height as f32);
    if let Some(candidates) = classical::fallback_candidates(template, image, options) {
        poses.extend(verify_candidates(template, size, image, candidates, options).poses);
        poses = select(poses, options, size.0, size.1);
    }
    let nothing_verified = !poses.iter().any(|p| p.score >= trigger_score);
    if nothing_verified && let Some(bar) = quarter_less_bar(template, image, options) {
        // The classical search correlates the whole template too: a covered quarter hides
        // the part from it as from the verification, so it searches without each quarter.
        // Under noise the same four searches reach parts that the whole template's misses.
        let scorer = Verifier::for_options(template, image, options);
        for partial in verification::without_each_quarter(template) {
            if let Some(candidates) = classical::fallback_candidates(&partial, image, options) {
                let found = verification::verify_partial(
                    &partial, &scorer, size, image, candidates, options, None,
                );
                poses.extend(found.poses.into_iter().filter(|p| p.score >= bar));
            }
        }
        poses = select(poses, options, size.0, size.1);
    }
    (poses, start.elapsed().as_secs_f64() * 1e3)
}

/// The least score of the fallback's quarter-less searches' answers where they run: any where
/// covered parts are expected, [`NOISY_WIDER_SEARCH_BAR`] in a noisy image
/// ([`NOISY_FROM_GREY_LEVELS`]); `None` (not searched) elsewhere.
fn quarter_less_bar(
    template: &GrayImage32,
    image: &GrayImage32,
    options: &MatchOptions,
) -> Option<f32> {
    if options.expects_covered_parts(template) {
        Some(f32::NEG_INFINITY)
    } else if NoiseLevel::estimate(image).grey_levels() >= NOISY_FROM_GREY_LEVELS {
        Some(NOISY_WIDER_SEARCH_BAR)
    } else {
        None
    }
}

/// The least heatmap value of a peak the peak reading considers. With verification every peak
/// above the low candidate threshold is worth a look (up to [`peak_limit`]); without it the
/// heatmap value is the answer's score.
fn peak_threshold(options: &ValidOptions) -> f32 {
    if options.verify {
        options.candidate_threshold
    } else {
        options.effective_min_score()
    }
}

/// How many peaks the peak reading keeps: the candidate budget with verification (more where
/// the heads are not trusted), a few per instance without.
fn peak_limit(options: &ValidOptions, heads: Heads) -> usize {
    if options.verify {
        options.candidate_budget_for(heads)
    } else {
        4 * options.max_instances + 16
    }
}

fn ms_since(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

fn check_template_size(width: u32, height: u32) -> Result<(), MatchError> {
    let ok = |s: u32| (MIN_TEMPLATE_SIDE..=MAX_TEMPLATE_SIDE).contains(&s);
    if ok(width) && ok(height) {
        Ok(())
    } else {
        Err(MatchError::TemplateSize { width, height })
    }
}

/// The size rules every matcher applies to a `tw x th` template and an `iw x ih` image.
pub fn check_pair_sizes(tw: u32, th: u32, iw: u32, ih: u32) -> Result<(), MatchError> {
    check_template_size(tw, th)?;
    if iw < MIN_IMAGE_SIDE || ih < MIN_IMAGE_SIDE {
        return Err(MatchError::ImageTooSmall {
            width: iw,
            height: ih,
        });
    }
    if tw > iw || th > ih {
        return Err(MatchError::TemplateLargerThanImage { tw, th, iw, ih });
    }
    Ok(())
}

/// The scale passes of a search, or [`MatchError::TooMuchWork`] when they would need more than
/// `budget` network pixels (see [`plan::network_pixels`]). The service checks its configured
/// budget before queueing; the matcher applies the hard limit [`MAX_NETWORK_PIXELS`].
/// `grid_scale`: see [`plan::scale_passes`].
pub fn check_network_budget(
    tw: u32,
    th: u32,
    iw: u32,
    ih: u32,
    options: &ValidOptions,
    budget: u64,
    grid_scale: f32,
) -> Result<Vec<ScalePass>, MatchError> {
    let (lo, hi) = options.scale_range.map_or((1.0, 1.0), |r| (r.min, r.max));
    let passes = plan::scale_passes(tw, th, iw, ih, lo, hi, grid_scale);
    let pixels = plan::network_pixels(&passes);
    if pixels > budget {
        return Err(MatchError::TooMuchWork {
            tw,
            th,
            iw,
            ih,
            lo,
            hi,
            pixels,
            budget,
        });
    }
    Ok(passes)
}

/// Checks a job's sizes and cuts it into network pieces.
fn prepare(
    index: usize,
    job: &MatchJob,
    max_whole_pixels: usize,
    grid_scale: f32,
    convention: InputConvention,
) -> Result<Vec<Piece>, MatchError> {
    let (tw, th) = (job.template.width, job.template.height);
    let (iw, ih) = (job.image.width, job.image.height);
    check_pair_sizes(tw, th, iw, ih)?;
    let passes = check_network_budget(tw, th, iw, ih, job.options, MAX_NETWORK_PIXELS, grid_scale)?;
    let mut pieces = Vec::new();
    for pass in passes {
        let resized = resize_rgb(job.image, pass.width as u32, pass.height as u32);
        let padded = crate::imaging::pad_to_min_side(resized, MIN_INPUT_SIDE);
        for tile in plan::tiles(
            padded.width as usize,
            padded.height as usize,
            max_whole_pixels,
        ) {
            let mut planar =
                if tile.width == padded.width as usize && tile.height == padded.height as usize {
                    convention.normalise(&padded)
                } else {
                    convention.normalise(&padded.crop(
                        tile.x0 as u32,
                        tile.y0 as u32,
                        tile.width as u32,
                        tile.height as u32,
                    ))
                };
            // The last contrast takes the input, the others a copy.
            let contrasts = job.options.polarity.contrasts();
            for (k, &contrast) in contrasts.iter().enumerate() {
                pieces.push(Piece {
                    job: index,
                    contrast,
                    pass,
                    tile,
                    width: tile.width,
                    height: tile.height,
                    planar: if k + 1 == contrasts.len() {
                        std::mem::take(&mut planar)
                    } else {
                        planar.clone()
                    },
                });
            }
        }
    }
    Ok(pieces)
}

/// Peaks of one piece that it owns, as poses in the original image.
fn piece_poses(piece: &Piece, maps: &[f32], job: &MatchJob, heads: Heads) -> Vec<Pose> {
    // The network output is 4*floor(side/4).
    let w = piece.width / 4 * 4;
    let h = piece.height / 4 * 4;
    let n = w * h;
    let planes = MapPlanes {
        width: w,
        height: h,
        score: &maps[..n],
        sign: &maps[n..2 * n],
        cos: &maps[2 * n..3 * n],
        scale_x: &maps[3 * n..4 * n],
        scale_y: &maps[4 * n..5 * n],
    };
    let (threshold, limit) = (peak_threshold(job.options), peak_limit(job.options, heads));
    let pass = piece.pass;
    let tile = piece.tile;
    let grid = TEMPLATE_GRID as f32;
    find_peaks(&planes, threshold, limit)
        .into_iter()
        .filter_map(|(row, col)| {
            let (gx, gy) = (tile.x0 + col, tile.y0 + row);
            let owned = (tile.core_x.0..tile.core_x.1).contains(&gx)
                && (tile.core_y.0..tile.core_y.1).contains(&gy)
                && gx < pass.width
                && gy < pass.height;
            owned.then(|| {
                let p = peak_at(&planes, row, col);
                Pose {
                    x: (tile.x0 as f32 + p.x + 0.5) / pass.factor_x - 0.5,
                    y: (tile.y0 as f32 + p.y + 0.5) / pass.factor_y - 0.5,
                    angle_deg: p.angle_deg,
                    scale_x: p.scale_x * grid / (pass.factor_x * job.template.width as f32),
                    scale_y: p.scale_y * grid / (pass.factor_y * job.template.height as f32),
                    score: p.score,
                    network_score: p.score,
                }
            })
        })
        .collect()
}
