//! The paper's metrics on pairs with known truth, for `posematch eval`: Loc.Err (px), ScaleErr
//! (mean |Δsx|, |Δsy|), Rot.Err (°, wrapped), mIoU of rotated boxes, Succ (IoU ≥ 0.5), time per
//! pair; and precision/recall at IoU ≥ 0.5 with greedy matching for multi-instance images.

mod calibration;

use std::time::Instant;

use serde::Serialize;

use crate::geometry::{Pose, angle_distance_deg, rotated_iou};
use crate::imaging::GrayImage32;
use crate::matcher::selection::select;
use crate::matcher::{
    MatchError, MatchJob, MatchOptions, Matcher, Proposal, TemplateMask, ValidOptions,
};
use crate::matcher::{answer, with_classical_fallbacks};
use crate::refine::refine_pose;
use crate::synth::SyntheticPair;
pub use calibration::{Calibration, path_changes};

/// IoU at which a prediction counts as the object (the paper's Succ).
pub const SUCCESS_IOU: f32 = 0.5;

/// How one single-instance prediction compares with the truth.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct PairError {
    pub centre_px: f32,
    pub scale: f32,
    pub rotation_deg: f32,
    pub iou: f32,
}

/// Compares a prediction with the truth for a `tw x th` template.
pub fn pair_error(predicted: &Pose, truth: &Pose, tw: f32, th: f32) -> PairError {
    PairError {
        centre_px: (predicted.x - truth.x).hypot(predicted.y - truth.y),
        scale: ((predicted.scale_x - truth.scale_x).abs()
            + (predicted.scale_y - truth.scale_y).abs())
            / 2.0,
        rotation_deg: angle_distance_deg(predicted.angle_deg, truth.angle_deg),
        iou: rotated_iou(&predicted.corners(tw, th), &truth.corners(tw, th)),
    }
}

/// The paper-style table row for a set of single-instance pairs.
#[derive(Debug, Clone, Default, Serialize)]
pub struct Summary {
    pub pairs: usize,
    /// Mean centre error over successful pairs (px).
    pub loc_err_px: f32,
    /// Mean of (|Δsx| + |Δsy|)/2 over successful pairs.
    pub scale_err: f32,
    /// Mean wrapped rotation error over successful pairs (°).
    pub rot_err_deg: f32,
    /// Mean IoU over all pairs (a miss counts 0).
    pub miou: f32,
    /// Fraction of pairs with IoU ≥ 0.5.
    pub success: f32,
    /// Mean wall time per pair (ms).
    pub ms_per_pair: f64,
}

/// One pair (or multi-instance scene) through the three paths `posematch eval` compares, from
/// one network pass: each path's answers and its time per pair (template encoding and the
/// network included in each).
pub struct PairRun {
    /// The network's peaks as they come (heatmap scores, no refinement).
    pub network: Vec<Pose>,
    pub network_ms: f64,
    /// The same poses refined one by one (the path before verification; empty unless asked).
    pub refined: Vec<Pose>,
    pub refined_ms: f64,
    /// Verified candidates (the default path): every answer whatever its score; apply
    /// `min_score` to them (it cuts a suffix, so this equals running with it).
    pub verified: Vec<Pose>,
    pub verified_ms: f64,
}

/// Which paths besides the network's own [`match_pair`] runs (the others stay empty).
#[derive(Debug, Clone, Copy)]
pub struct Paths {
    pub refined: bool,
    pub verified: bool,
}

/// Runs one generated pair. `options` are the verified path's (refinement on); the network path
/// keeps its peaks at or above `network_min_score` (heatmap). `mask`: the template's, if any.
pub fn match_pair(
    matcher: &Matcher,
    pair: &SyntheticPair,
    mask: Option<&TemplateMask>,
    options: &ValidOptions,
    network_min_score: f32,
    paths: Paths,
) -> Result<PairRun, MatchError> {
    let start = Instant::now();
    let encoded = matcher.encode_masked_template(&pair.template, mask)?;
    // One network pass serves all three paths: enough peaks for either.
    let heads = matcher.heads_for(&MatchJob {
        template: &encoded,
        image: &pair.search,
        options,
        answer_by: None,
    });
    let budget = options.candidate_budget_for(heads);
    let propose_options = ValidOptions::derived(MatchOptions {
        candidate_threshold: options.candidate_threshold.min(network_min_score),
        max_candidates: budget.max(4 * options.max_instances + 16),
        verify: true,
        ..(**options).clone()
    });
    let job = MatchJob {
        template: &encoded,
        image: &pair.search,
        options: &propose_options,
        answer_by: None,
    };
    let proposal = matcher
        .propose(std::slice::from_ref(&job))
        .pop()
        .expect("one job in, one proposal out")?;
    let network_ms = ms_since(start);
    let (tw, th) = (pair.template.width as f32, pair.template.height as f32);
    let network_options = MatchOptions {
        min_score: Some(network_min_score),
        verify: false,
        ..(**options).clone()
    };
    let network: Vec<Pose> = select(
        proposal
            .candidates
            .iter()
            .chain(&proposal.reversed)
            .filter(|p| p.network_score >= network_min_score)
            .copied()
            .collect(),
        &network_options,
        tw,
        th,
    );
    let start = Instant::now();
    let image = GrayImage32::from_rgb(&pair.search);
    let refined = if paths.refined {
        network
            .iter()
            .map(|p| refine_pose(encoded.gray_for(options.polarity.contrasts()[0]), &image, p))
            .collect()
    } else {
        Vec::new()
    };
    let refined_ms = network_ms + ms_since(start);
    if !paths.verified {
        return Ok(PairRun {
            network,
            network_ms,
            refined,
            refined_ms,
            verified: Vec::new(),
            verified_ms: 0.0,
        });
    }
    let start = Instant::now();
    // Every answer whatever its score (for the calibration table); the classical fallback
    // runs below, when none reaches the caller's `min_score`, as in `answer`.
    let verified_options = ValidOptions::derived(MatchOptions {
        min_score: Some(f32::MIN_POSITIVE),
        covered_parts: Some(options.expects_covered_parts(&encoded.gray)),
        classical_fallback: false,
        ..(**options).clone()
    });
    let candidates_of = |poses: Vec<Pose>| {
        poses
            .into_iter()
            .filter(|p| p.network_score >= options.candidate_threshold)
            .take(budget)
            .collect()
    };
    let verified = answer(
        &MatchJob {
            options: &verified_options,
            ..job
        },
        Proposal {
            candidates: candidates_of(proposal.candidates),
            reversed: candidates_of(proposal.reversed),
            timings: proposal.timings,
            timed_out: false,
            heads: proposal.heads,
        },
    )
    .poses;
    let (verified, _) = with_classical_fallbacks(
        &encoded,
        &image,
        verified,
        &MatchOptions {
            classical_fallback: options.classical_fallback,
            ..(*verified_options).clone()
        },
        options.effective_min_score(),
    );
    Ok(PairRun {
        network,
        network_ms,
        refined,
        refined_ms,
        verified,
        verified_ms: network_ms + ms_since(start),
    })
}

fn ms_since(start: Instant) -> f64 {
    start.elapsed().as_secs_f64() * 1e3
}

/// The paper's table rows for single-instance pairs: the network's best peak alone and
/// refined (how the network itself is doing; used while training).
pub fn evaluate_pairs(
    matcher: &Matcher,
    pairs: &[SyntheticPair],
) -> Result<(Summary, Summary), MatchError> {
    let options = MatchOptions {
        max_instances: 1,
        ..MatchOptions::default()
    }
    .validate()
    .expect("one instance with default options is valid");
    let (mut network, mut refined) = (Vec::new(), Vec::new());
    for pair in pairs {
        let paths = Paths {
            refined: true,
            verified: false,
        };
        let run = match_pair(matcher, pair, None, &options, ANY_PEAK, paths)?;
        let truth = &pair.truth[0];
        let (tw, th) = (pair.template.width as f32, pair.template.height as f32);
        let error = |poses: &[Pose]| poses.first().map(|p| pair_error(p, truth, tw, th));
        network.push((error(&run.network), run.network_ms));
        refined.push((error(&run.refined), run.refined_ms));
    }
    Ok((summarise(&network), summarise(&refined)))
}

/// Heatmap threshold under which the network's best peak is still taken as its answer on
/// single-instance pairs (they always hold the object, as in the paper and the official peak reading).
pub const ANY_PEAK: f32 = 0.01;

/// Aggregates per-pair results: `None` means nothing was found.
pub fn summarise(results: &[(Option<PairError>, f64)]) -> Summary {
    let n = results.len().max(1) as f32;
    let successes: Vec<&PairError> = results
        .iter()
        .filter_map(|(e, _)| e.as_ref())
        .filter(|e| e.iou >= SUCCESS_IOU)
        .collect();
    let s = successes.len().max(1) as f32;
    Summary {
        pairs: results.len(),
        loc_err_px: successes.iter().map(|e| e.centre_px).sum::<f32>() / s,
        scale_err: successes.iter().map(|e| e.scale).sum::<f32>() / s,
        rot_err_deg: successes.iter().map(|e| e.rotation_deg).sum::<f32>() / s,
        miou: results
            .iter()
            .filter_map(|(e, _)| e.map(|e| e.iou))
            .sum::<f32>()
            / n,
        success: successes.len() as f32 / n,
        ms_per_pair: results.iter().map(|(_, ms)| ms).sum::<f64>() / results.len().max(1) as f64,
    }
}

/// Multi-instance counts, micro-averaged over images.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct DetectionCounts {
    pub true_positives: usize,
    pub predictions: usize,
    pub objects: usize,
}

impl DetectionCounts {
    pub fn precision(&self) -> f32 {
        self.true_positives as f32 / self.predictions.max(1) as f32
    }
    pub fn recall(&self) -> f32 {
        self.true_positives as f32 / self.objects.max(1) as f32
    }
    pub fn add(&mut self, other: DetectionCounts) {
        self.true_positives += other.true_positives;
        self.predictions += other.predictions;
        self.objects += other.objects;
    }
}

/// Greedy matching: pairs (prediction, object) by descending IoU, each used once, IoU ≥ 0.5.
pub fn match_detections(predicted: &[Pose], truth: &[Pose], tw: f32, th: f32) -> DetectionCounts {
    let matched = matched_predictions(predicted, truth, tw, th);
    DetectionCounts {
        true_positives: matched.iter().filter(|&&m| m).count(),
        predictions: predicted.len(),
        objects: truth.len(),
    }
}

/// Per prediction, whether the greedy matching of [`match_detections`] pairs it with an object.
pub fn matched_predictions(predicted: &[Pose], truth: &[Pose], tw: f32, th: f32) -> Vec<bool> {
    let mut candidates = Vec::new();
    for (i, p) in predicted.iter().enumerate() {
        for (j, t) in truth.iter().enumerate() {
            let iou = rotated_iou(&p.corners(tw, th), &t.corners(tw, th));
            if iou >= SUCCESS_IOU {
                candidates.push((iou, i, j));
            }
        }
    }
    candidates.sort_by(|a, b| b.0.total_cmp(&a.0));
    let (mut used_p, mut used_t) = (vec![false; predicted.len()], vec![false; truth.len()]);
    for (_, i, j) in candidates {
        if !used_p[i] && !used_t[j] {
            used_p[i] = true;
            used_t[j] = true;
        }
    }
    used_p
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pose(x: f32, y: f32, angle_deg: f32, sx: f32, sy: f32) -> Pose {
        Pose {
            x,
            y,
            angle_deg,
            scale_x: sx,
            scale_y: sy,
            score: 1.0,
            network_score: 0.0,
        }
    }

    #[test]
    fn errors_of_a_hand_computed_case() {
        let truth = pose(10.0, 10.0, 179.0, 1.0, 1.0);
        let predicted = pose(13.0, 14.0, -179.0, 1.2, 0.9);
        let e = pair_error(&predicted, &truth, 10.0, 10.0);
        assert!((e.centre_px - 5.0).abs() < 1e-5);
        assert!(
            (e.rotation_deg - 2.0).abs() < 1e-3,
            "wrap-around at ±180: {}",
            e.rotation_deg
        );
        assert!((e.scale - 0.15).abs() < 1e-5);
        // Two 10x10 squares shifted by (3, 4) at nearly the same angle: IoU ≈ 42/158.
        assert!((e.iou - 42.0 / 158.0).abs() < 0.05, "{}", e.iou);
    }

    #[test]
    fn summary_and_greedy_matching() {
        let a = pose(0.0, 0.0, 0.0, 1.0, 1.0);
        let far = pose(100.0, 0.0, 0.0, 1.0, 1.0);
        let results = vec![
            (Some(pair_error(&a, &a, 10.0, 10.0)), 2.0),
            (Some(pair_error(&far, &a, 10.0, 10.0)), 4.0),
            (None, 6.0),
        ];
        let s = summarise(&results);
        assert!((s.success - 1.0 / 3.0).abs() < 1e-6);
        assert!((s.miou - 1.0 / 3.0).abs() < 1e-6);
        assert_eq!(s.loc_err_px, 0.0);
        assert!((s.ms_per_pair - 4.0).abs() < 1e-9);
        // Two objects, three predictions: one exact, one duplicate of it, one far away.
        let b = pose(50.0, 0.0, 0.0, 1.0, 1.0);
        let c = match_detections(&[a, a, far], &[a, b], 10.0, 10.0);
        assert_eq!(
            c,
            DetectionCounts {
                true_positives: 1,
                predictions: 3,
                objects: 2
            }
        );
        assert!((c.precision() - 1.0 / 3.0).abs() < 1e-6 && (c.recall() - 0.5).abs() < 1e-6);
    }
}
