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
    let (keys, order) = sorted_by_value(values);
    let mut ranks = vec![0.0f32; values.len()];
    let mut start = 0;
    while start < order.len() {
        let mut end = start + 1;
        while end < order.len() && keys[end] == keys[start] {
            end += 1;
        }
        let mean_rank = (start + end - 1) as f32 / 2.0;
        for &index in &order[start..end] {
            ranks[index as usize] = mean_rank;
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

/// The values' order-preserving bits ([`ordered_bits`]) sorted, and the index of each value in
/// that order; equal values keep their indices' order. Why a least-significant-digit radix
/// sort of the bits, a byte a pass (a pass whose byte all values share is skipped): the
/// verifier ranks a pose's samples at every pose it scores (some 1300 values, a few hundred
/// poses a pair), and this is several times faster than sorting the bits above their indices
/// as 64-bit integers, with the same order.
fn sorted_by_value(values: &[f32]) -> (Vec<u32>, Vec<u32>) {
    let n = values.len();
    let mut keys: Vec<u32> = values.iter().map(|&v| ordered_bits(v)).collect();
    let mut order: Vec<u32> = (0..n as u32).collect();
    let mut counts = [[0usize; 256]; 4];
    for &key in &keys {
        for (byte, count) in counts.iter_mut().enumerate() {
            count[(key >> (8 * byte)) as usize & 0xff] += 1;
        }
    }
    let (mut spare_keys, mut spare_order) = (vec![0u32; n], vec![0u32; n]);
    for (byte, count) in counts.iter().enumerate() {
        if count.contains(&n) {
            continue;
        }
        let mut next = [0usize; 256];
        let mut total = 0;
        for (slot, &c) in next.iter_mut().zip(count) {
            *slot = total;
            total += c;
        }
        for (&key, &index) in keys.iter().zip(&order) {
            let digit = (key >> (8 * byte)) as usize & 0xff;
            spare_keys[next[digit]] = key;
            spare_order[next[digit]] = index;
            next[digit] += 1;
        }
        std::mem::swap(&mut keys, &mut spare_keys);
        std::mem::swap(&mut order, &mut spare_order);
    }
    (keys, order)
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
    fn the_radix_order_is_the_order_of_the_values_then_their_indices() {
        let values: Vec<f32> = (0..1500u32)
            .map(|i| {
                let h = i.wrapping_mul(2_654_435_761) >> 7;
                // Ties (a few hundred distinct values), negatives and both zeros.
                ((h % 400) as f32 - 100.0) / 300.0 * if i % 97 == 0 { 0.0 } else { 1.0 }
            })
            .chain([
                -0.0,
                0.0,
                f32::MIN_POSITIVE,
                -f32::MIN_POSITIVE,
                1e30,
                -1e30,
            ])
            .collect();
        let (keys, order) = sorted_by_value(&values);
        let mut expected: Vec<u64> = values
            .iter()
            .enumerate()
            .map(|(i, v)| u64::from(ordered_bits(*v)) << 32 | i as u64)
            .collect();
        expected.sort_unstable();
        assert_eq!(
            order,
            expected.iter().map(|&k| k as u32).collect::<Vec<_>>()
        );
        assert_eq!(
            keys,
            expected
                .iter()
                .map(|&k| (k >> 32) as u32)
                .collect::<Vec<_>>()
        );
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
