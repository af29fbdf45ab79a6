//! The similarity of a pose whatever the light's curve: the correlation of ranks.
//!
//! Why: ZNCC is unchanged by a gain and an offset, not by a curve. A camera with another gamma,
//! a darker exposure that crushes the shadows, a lamp that saturates the highlights all bend the
//! grey levels monotonically, and a part that is clearly there correlates at 0.85–0.9 instead of
//! 0.99. The rank correlation (Spearman's rho: the ZNCC of the values' ranks) is unchanged by
//! every increasing map of the grey levels, and for unrelated patches it is distributed as
//! ZNCC is, so it is held to the same chance level (docs/accuracy.md, "What a score means").

use super::PoseSamples;
use crate::imaging::GrayImage32;

/// The ranks of the template's support values (every pixel up to 48 a side, as the
/// similarity's), in the support's order.
pub(crate) struct RankPoints {
    /// Ranks of the template values, centred and scaled to unit norm.
    ranks: Vec<f32>,
}

impl RankPoints {
    pub(crate) fn new(template: &GrayImage32) -> Self {
        let (_, values) = super::grid_points(template, 48);
        Self {
            ranks: unit_ranks(&values),
        }
    }

    /// Spearman's rho of the template and the image's `samples` at a pose (the support's), in
    /// [-1, 1]; -1 where the image is flat there.
    pub(crate) fn similarity(&self, samples: &PoseSamples) -> f32 {
        let samples = samples.values();
        debug_assert_eq!(samples.len(), self.ranks.len(), "the support's samples");
        if self.ranks.len() < 2 {
            return -1.0;
        }
        let (low, high) = samples
            .iter()
            .fold((f32::INFINITY, f32::NEG_INFINITY), |(l, h), &v| {
                (l.min(v), h.max(v))
            });
        if high - low <= super::FLAT_PATCH_SPREAD {
            return -1.0;
        }
        let ranks = unit_ranks(samples);
        let dot: f32 = ranks.iter().zip(&self.ranks).map(|(a, b)| a * b).sum();
        dot.clamp(-1.0, 1.0)
    }
}

/// The ranks of `values` (ties share their mean rank), centred and scaled to unit norm; all
/// zero when every value is the same.
fn unit_ranks(values: &[f32]) -> Vec<f32> {
    // Each value's order-preserving bits above its index, sorted as plain integers: several
    // times faster than sorting indices by a comparison of the values they point to, and the
    // verifier ranks a pose's samples at every pose it scores.
    let mut order: Vec<u64> = values
        .iter()
        .enumerate()
        .map(|(i, v)| u64::from(ordered_bits(*v)) << 32 | i as u64)
        .collect();
    order.sort_unstable();
    let value_of = |key: u64| (key >> 32) as u32;
    let mut ranks = vec![0.0f32; values.len()];
    let mut start = 0;
    while start < order.len() {
        let mut end = start + 1;
        while end < order.len() && value_of(order[end]) == value_of(order[start]) {
            end += 1;
        }
        let mean_rank = (start + end - 1) as f32 / 2.0;
        for &key in &order[start..end] {
            ranks[key as u32 as usize] = mean_rank;
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

/// `value`'s bits, mapped so that the integers order as the values do (`-0.0` as `0.0`, a tie).
fn ordered_bits(value: f32) -> u32 {
    let bits = if value == 0.0 { 0 } else { value.to_bits() };
    if bits >> 31 == 1 {
        !bits
    } else {
        bits | 1 << 31
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::refine::{TemplatePoints, at_centre, textured};

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
        let support = TemplatePoints::support(&template);
        let points = RankPoints::new(&template);
        assert!(points.similarity(&support.samples(&curved, &pose)) > 0.999);
        // ZNCC is not: the curve costs it.
        let zncc = support.score(&curved, &pose);
        assert!(zncc < 0.99, "{zncc}");
        // An unrelated patch stays near zero; a flat one is the lowest score.
        let other = GrayImage32 {
            values: template.values.iter().rev().copied().collect(),
            ..template.clone()
        };
        assert!(points.similarity(&support.samples(&other, &pose)).abs() < 0.2);
        let flat = GrayImage32::from_fn(24, 24, |_, _| 0.5);
        assert_eq!(points.similarity(&support.samples(&flat, &pose)), -1.0);
    }

    #[test]
    fn ties_share_their_mean_rank() {
        let ranks = unit_ranks(&[0.1, 0.5, 0.5, 0.9]);
        assert!(ranks[1] == ranks[2] && ranks[0] < ranks[1] && ranks[1] < ranks[3]);
        // Negative values rank in order too, and zeros of either sign tie.
        let ranks = unit_ranks(&[0.0, -2.0, 3.0, -0.5, -0.0]);
        assert!(ranks[1] < ranks[3] && ranks[3] < ranks[0] && ranks[0] < ranks[2]);
        assert_eq!(ranks[0], ranks[4]);
        assert!(unit_ranks(&[0.3; 5]).iter().all(|&r| r == 0.0));
    }
}
