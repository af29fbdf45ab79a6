//! Selection of the answers among verified (or network-only) poses: the caller's angle and scale
//! ranges, rotated-box non-maximum suppression, `min_score` and `max_instances`, best first.

use super::options::MatchOptions;
use crate::geometry::{Pose, rotated_iou};

/// Degrees by which the screen and confirmation look beyond the caller's angle range (the
/// final filter is exact), so that an object at the edge of the range is not missed.
pub(crate) const ANGLE_MARGIN_DEG: f32 = 5.0;

/// A pose's rotated box in the image ([`Pose::corners`]).
type Corners = [(f32, f32); 4];

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
    let mut kept: Vec<(Pose, Corners)> = Vec::new();
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

/// Non-maximum suppression across templates, for callers that search for several templates at
/// once and want one answer per object ([`MatchOptions::suppress_across_templates`]): of two
/// poses of different templates whose rotated boxes (each its own template's size) overlap more
/// than `max_overlap` (IoU), only the better-scoring one is kept. Poses of the same template
/// are left as [`select`] chose them. `poses` carry their template's index into `sizes`; the
/// kept ones come back best first.
pub fn suppress_across_templates(
    mut poses: Vec<(usize, Pose)>,
    sizes: &[(f32, f32)],
    max_overlap: f32,
) -> Vec<(usize, Pose)> {
    poses.sort_by(|a, b| b.1.score.total_cmp(&a.1.score));
    let mut kept: Vec<(usize, Pose, Corners)> = Vec::with_capacity(poses.len());
    for (template, pose) in poses {
        let (tw, th) = sizes[template];
        let corners = pose.corners(tw, th);
        if kept.iter().all(|(other, _, box_)| {
            *other == template || rotated_iou(&corners, box_) <= max_overlap
        }) {
            kept.push((template, pose, corners));
        }
    }
    kept.into_iter().map(|(t, p, _)| (t, p)).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn of_two_templates_on_one_object_only_the_better_scoring_answer_is_kept() {
        let sizes = [(40.0, 20.0), (36.0, 20.0), (40.0, 20.0)];
        let poses = vec![
            (0, Pose::upright(100.0, 100.0, 0.93)),
            // Template 1 at nearly the same place: the same object, scoring higher.
            (1, Pose::upright(101.0, 100.0, 0.97)),
            // Template 0 again, elsewhere: another object, kept.
            (0, Pose::upright(300.0, 100.0, 0.91)),
            // Template 2 beside template 1's answer but hardly overlapping: kept.
            (2, Pose::upright(138.0, 100.0, 0.95)),
        ];
        let kept = suppress_across_templates(poses, &sizes, 0.5);
        let found: Vec<(usize, f32)> = kept.iter().map(|(t, p)| (*t, p.x)).collect();
        assert_eq!(found, vec![(1, 101.0), (2, 138.0), (0, 300.0)]);
    }

    #[test]
    fn overlapping_answers_of_one_template_are_left_as_selected() {
        // `select` already decided between answers of one template (max_overlap may be 1).
        let sizes = [(40.0, 20.0)];
        let poses = vec![
            (0, Pose::upright(100.0, 100.0, 0.93)),
            (0, Pose::upright(101.0, 100.0, 0.92)),
        ];
        assert_eq!(suppress_across_templates(poses, &sizes, 0.5).len(), 2);
    }
}
