//! The paper's metrics on pairs with known truth, for `posematch eval`: Loc.Err (px), ScaleErr
//! (mean |Δsx|, |Δsy|), Rot.Err (°, wrapped), mIoU of rotated boxes, Succ (IoU ≥ 0.5), time per
//! pair; and precision/recall at IoU ≥ 0.5 with greedy matching for multi-instance images.

use std::time::Instant;

use serde::Serialize;

use crate::geometry::{Pose, angle_distance_deg, rotated_iou};
use crate::matcher::{MatchError, MatchOptions, Matcher};
use crate::refine::{GrayImage32, refine_pose};
use crate::synth::SyntheticPair;

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

/// One pair through the network: its poses and time, then the refined poses and the
/// refinement's time (the same poses and 0 ms when `refine` is off).
pub struct PairRun {
    pub coarse: Vec<Pose>,
    pub coarse_ms: f64,
    pub refined: Vec<Pose>,
    pub refine_ms: f64,
}

/// Matches one generated pair with `options` (whose own `refine` should be off: refinement is
/// timed separately here).
pub fn match_pair(
    matcher: &Matcher,
    pair: &SyntheticPair,
    options: &MatchOptions,
    refine: bool,
) -> Result<PairRun, MatchError> {
    let start = Instant::now();
    let encoded = matcher.encode_template(&pair.template)?;
    let coarse = matcher.match_one(&encoded, &pair.search, options)?.poses;
    let coarse_ms = start.elapsed().as_secs_f64() * 1e3;
    if !refine {
        return Ok(PairRun {
            refined: coarse.clone(),
            coarse,
            coarse_ms,
            refine_ms: 0.0,
        });
    }
    let start = Instant::now();
    let image = GrayImage32::from_rgb(&pair.search);
    let refined = coarse
        .iter()
        .map(|p| refine_pose(&encoded.gray, &image, p))
        .collect();
    Ok(PairRun {
        coarse,
        coarse_ms,
        refined,
        refine_ms: start.elapsed().as_secs_f64() * 1e3,
    })
}

/// The paper's table rows for single-instance pairs: the network alone and with refinement.
pub fn evaluate_pairs(
    matcher: &Matcher,
    pairs: &[SyntheticPair],
    options: &MatchOptions,
) -> Result<(Summary, Summary), MatchError> {
    let (mut coarse, mut refined) = (Vec::new(), Vec::new());
    for pair in pairs {
        let run = match_pair(matcher, pair, options, true)?;
        let truth = &pair.truth[0];
        let (tw, th) = (pair.template.width as f32, pair.template.height as f32);
        let error = |poses: &[Pose]| poses.first().map(|p| pair_error(p, truth, tw, th));
        coarse.push((error(&run.coarse), run.coarse_ms));
        refined.push((error(&run.refined), run.coarse_ms + run.refine_ms));
    }
    Ok((summarise(&coarse), summarise(&refined)))
}

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
    let mut true_positives = 0;
    for (_, i, j) in candidates {
        if !used_p[i] && !used_t[j] {
            used_p[i] = true;
            used_t[j] = true;
            true_positives += 1;
        }
    }
    DetectionCounts {
        true_positives,
        predictions: predicted.len(),
        objects: truth.len(),
    }
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
