//! The similarity of a pose whatever the light's curve: the correlation of ranks.
//!
//! Why: ZNCC is unchanged by a gain and an offset, not by a curve. A camera with another gamma,
//! a darker exposure that crushes the shadows, a lamp that saturates the highlights all bend the
//! grey levels monotonically, and a part that is clearly there correlates at 0.85–0.9 instead of
//! 0.99. The rank correlation (Spearman's rho: the ZNCC of the values' ranks) is unchanged by
//! every increasing map of the grey levels, and for unrelated patches it is distributed as
//! ZNCC is, so it is held to the same chance level (docs/accuracy.md, "What a score means").

use crate::geometry::Pose;
use crate::imaging::GrayImage32;

/// The template's support points (every pixel up to 48 a side, as the similarity's) with the
/// ranks of their values.
pub(crate) struct RankPoints {
    offsets: Vec<(f32, f32)>,
    /// Ranks of the template values, centred and scaled to unit norm.
    ranks: Vec<f32>,
}

impl RankPoints {
    pub(crate) fn new(template: &GrayImage32) -> Self {
        let (offsets, values) = super::grid_points(template, 48);
        Self {
            ranks: unit_ranks(&values),
            offsets,
        }
    }

    /// Spearman's rho of the template and the image (bilinear samples) at `pose`, in [-1, 1];
    /// -1 where the image is flat there.
    pub(crate) fn similarity(&self, image: &GrayImage32, pose: &Pose) -> f32 {
        if self.offsets.len() < 2 {
            return -1.0;
        }
        let samples: Vec<f32> = super::samples_at(image, pose, &self.offsets).collect();
        let (low, high) = samples
            .iter()
            .fold((f32::INFINITY, f32::NEG_INFINITY), |(l, h), &v| {
                (l.min(v), h.max(v))
            });
        if high - low <= super::FLAT_PATCH_SPREAD {
            return -1.0;
        }
        let ranks = unit_ranks(&samples);
        let dot: f32 = ranks.iter().zip(&self.ranks).map(|(a, b)| a * b).sum();
        dot.clamp(-1.0, 1.0)
    }
}

/// The ranks of `values` (ties share their mean rank), centred and scaled to unit norm; all
/// zero when every value is the same.
fn unit_ranks(values: &[f32]) -> Vec<f32> {
    let mut order: Vec<usize> = (0..values.len()).collect();
    order.sort_by(|&a, &b| values[a].total_cmp(&values[b]));
    let mut ranks = vec![0.0f32; values.len()];
    let mut start = 0;
    while start < order.len() {
        let mut end = start + 1;
        while end < order.len() && values[order[end]] == values[order[start]] {
            end += 1;
        }
        let mean_rank = (start + end - 1) as f32 / 2.0;
        for &i in &order[start..end] {
            ranks[i] = mean_rank;
        }
        start = end;
    }
    let mean = (values.len() as f32 - 1.0) / 2.0;
    ranks.iter_mut().for_each(|r| *r -= mean);
    let norm = ranks.iter().map(|r| r * r).sum::<f32>().sqrt();
    if norm > 1e-6 {
        ranks.iter_mut().for_each(|r| *r /= norm);
    }
    ranks
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::refine::{at_centre, textured};

    #[test]
    fn any_increasing_curve_of_the_grey_levels_keeps_the_rank_similarity_at_one() {
        let template = textured(24, 24, 1);
        let curved = GrayImage32 {
            values: template
                .values
                .iter()
                .map(|v| 0.6 * v.powf(2.2) + 0.04)
                .collect(),
            ..template.clone()
        };
        let pose = at_centre(&template);
        let points = RankPoints::new(&template);
        assert!(points.similarity(&curved, &pose) > 0.999);
        // ZNCC is not: the curve costs it.
        let zncc = super::super::TemplatePoints::support(&template).score(&curved, &pose);
        assert!(zncc < 0.99, "{zncc}");
        // An unrelated patch stays near zero; a flat one is the lowest score.
        let other = GrayImage32 {
            values: template.values.iter().rev().copied().collect(),
            ..template.clone()
        };
        assert!(points.similarity(&other, &pose).abs() < 0.2);
        let flat = GrayImage32::from_fn(24, 24, |_, _| 0.5);
        assert_eq!(points.similarity(&flat, &pose), -1.0);
    }

    #[test]
    fn ties_share_their_mean_rank() {
        let ranks = unit_ranks(&[0.1, 0.5, 0.5, 0.9]);
        assert!(ranks[1] == ranks[2] && ranks[0] < ranks[1] && ranks[1] < ranks[3]);
        assert!(unit_ranks(&[0.3; 5]).iter().all(|&r| r == 0.0));
    }
}
