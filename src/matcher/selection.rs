//! Selection of the answers among verified (or network-only) poses: the caller's angle and scale
//! ranges, rotated-box non-maximum suppression, `min_score` and `max_instances`, best first.

use super::options::MatchOptions;
use crate::geometry::{Pose, rotated_iou};

/// Degrees by which the screen and confirmation look beyond the caller's angle range (the
/// final filter is exact), so that an object at the edge of the range is not missed.
pub(crate) const ANGLE_MARGIN_DEG: f32 = 5.0;

/// Range filters, rotated-box non-maximum suppression, `min_score`, best first, at most
/// `max_instances`.
pub fn select(mut poses: Vec<Pose>, options: &MatchOptions, tw: f32, th: f32) -> Vec<Pose> {
    poses.retain(|p| {
        options.angle_range.is_none_or(|r| r.contains(p.angle_deg))
            && options
                .scale_range
                .is_none_or(|r| r.contains(p.scale_x) && r.contains(p.scale_y))
    });
    poses.sort_by(|a, b| b.score.total_cmp(&a.score));
    let mut kept: Vec<(Pose, [(f32, f32); 4])> = Vec::new();
    for pose in poses {
        if kept.len() == options.max_instances || pose.score < options.effective_min_score() {
            break;
        }
        let corners = pose.corners(tw, th);
        if kept
            .iter()
            .all(|(_, other)| rotated_iou(&corners, other) <= options.max_overlap)
        {
            kept.push((pose, corners));
        }
    }
    kept.into_iter().map(|(p, _)| p).collect()
}
