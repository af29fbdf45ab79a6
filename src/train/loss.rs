//! The paper's training losses on the network's five output maps, all with equal weight:
//! a soft focal-style centre loss normalised by the number of positives, a cross-entropy on the
//! angle's sign, and L1 on the angle's cosine and on both scales, the last three only inside
//! the valid region (heatmap ≥ 0.5).

use burn::prelude::*;

use super::labels::LabelMaps;

/// Probabilities are clamped away from 0 and 1 before taking logarithms.
const EPS: f32 = 1e-6;

/// A batch of [`LabelMaps`] as `[batch, 1, H, W]` tensors.
pub struct LabelTensors {
    pub heatmap: Tensor<4>,
    pub valid: Tensor<4>,
    pub sign: Tensor<4>,
    pub cos: Tensor<4>,
    pub scale_x: Tensor<4>,
    pub scale_y: Tensor<4>,
}

impl LabelTensors {
    /// Stacks same-sized label maps.
    pub fn stack(maps: &[LabelMaps], device: &Device) -> Self {
        let (w, h) = (maps[0].width, maps[0].height);
        let batch = maps.len();
        let field = |pick: fn(&LabelMaps) -> &Vec<f32>| {
            let mut values = Vec::with_capacity(batch * w * h);
            for m in maps {
                assert_eq!(
                    (m.width, m.height),
                    (w, h),
                    "label maps of one batch differ"
                );
                values.extend_from_slice(pick(m));
            }
            Tensor::<1>::from_floats(values.as_slice(), device).reshape([batch, 1, h, w])
        };
        Self {
            heatmap: field(|m| &m.heatmap),
            valid: field(|m| &m.valid),
            sign: field(|m| &m.sign),
            cos: field(|m| &m.cos),
            scale_x: field(|m| &m.scale_x),
            scale_y: field(|m| &m.scale_y),
        }
    }
}

/// The loss terms of one batch (scalars), and their sum.
pub struct Losses {
    pub total: Tensor<1>,
    pub centre: Tensor<1>,
    pub sign: Tensor<1>,
    pub cos: Tensor<1>,
    pub scale_x: Tensor<1>,
    pub scale_y: Tensor<1>,
}

/// `maps`: the network's `[batch, 5, H, W]` output (score, sign, cos, scale_x, scale_y, output
/// functions applied); `labels` of the same size.
pub fn losses(maps: Tensor<4>, labels: &LabelTensors) -> Losses {
    let [b, _, h, w] = maps.dims();
    let channel = |k: usize| maps.clone().slice([0..b, k..k + 1, 0..h, 0..w]);
    let (score, sign, cos, scale_x, scale_y) =
        (channel(0), channel(1), channel(2), channel(3), channel(4));
    let valid = labels.valid.clone();
    let positives = valid.clone().sum().clamp_min(1.0);

    // Centre: BCE against the soft label where the label is ≥ 0.5, −log(1 − p) elsewhere.
    let p = score.clamp(EPS, 1.0 - EPS);
    let y = labels.heatmap.clone();
    let bce = (y.clone() * p.clone().log() + (y.neg() + 1.0) * (p.clone().neg() + 1.0).log()).neg();
    let negative = (p.neg() + 1.0).log().neg();
    let invalid = valid.clone().neg() + 1.0;
    let centre = (valid.clone() * bce + invalid * negative).sum() / positives.clone();

    // Sign: binary cross-entropy inside the valid region.
    let q = sign.clamp(EPS, 1.0 - EPS);
    let t = labels.sign.clone();
    let sign_ce = (t.clone() * q.clone().log() + (t.neg() + 1.0) * (q.neg() + 1.0).log()).neg();
    let sign = (valid.clone() * sign_ce).sum() / positives.clone();

    let l1 = |predicted: Tensor<4>, target: &Tensor<4>| {
        (valid.clone() * (predicted - target.clone()).abs()).sum() / positives.clone()
    };
    let cos = l1(cos, &labels.cos);
    let scale_x = l1(scale_x, &labels.scale_x);
    let scale_y = l1(scale_y, &labels.scale_y);
    let total = centre.clone() + sign.clone() + cos.clone() + scale_x.clone() + scale_y.clone();
    Losses {
        total,
        centre,
        sign,
        cos,
        scale_x,
        scale_y,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Pose;

    fn scalar(t: Tensor<1>) -> f32 {
        t.into_data().try_to_vec::<f32>().unwrap()[0]
    }

    /// Output maps built from label maps: perfect parameters, a chosen score map.
    fn maps_from(labels: &LabelMaps, score: &[f32], device: &Device) -> Tensor<4> {
        let (w, h) = (labels.width, labels.height);
        let sign: Vec<f32> = labels.sign.iter().map(|s| s * 0.998 + 0.001).collect();
        let channels = [
            score.to_vec(),
            sign,
            labels.cos.clone(),
            labels.scale_x.clone(),
            labels.scale_y.clone(),
        ]
        .concat();
        Tensor::<1>::from_floats(channels.as_slice(), device).reshape([1, 5, h, w])
    }

    #[test]
    fn a_perfect_prediction_costs_less_than_a_wrong_one() {
        let device = Device::default();
        let truth = Pose {
            x: 20.0,
            y: 18.0,
            angle_deg: 40.0,
            scale_x: 1.2,
            scale_y: 0.9,
            score: 1.0,
            network_score: 0.0,
        };
        let labels = LabelMaps::render(40, 36, &[truth], 36.0, 36.0);
        let tensors = LabelTensors::stack(std::slice::from_ref(&labels), &device);
        let perfect = losses(maps_from(&labels, &labels.heatmap, &device), &tensors);
        // Parameters exact: their L1 terms vanish, the sign CE is tiny.
        assert!(scalar(perfect.cos) < 1e-6);
        assert!(scalar(perfect.scale_x) < 1e-6);
        assert!(scalar(perfect.sign) < 0.01);
        let flat = vec![0.5; 40 * 36];
        let wrong = losses(maps_from(&labels, &flat, &device), &tensors);
        assert!(scalar(wrong.centre) > scalar(perfect.centre) + 1.0);

        // Hand check of the centre loss on one positive and one negative pixel.
        let heat = Tensor::<1>::from_floats([0.8f32, 0.1], &device).reshape([1, 1, 1, 2]);
        let small = LabelTensors {
            valid: Tensor::<1>::from_floats([1.0f32, 0.0], &device).reshape([1, 1, 1, 2]),
            sign: heat.zeros_like(),
            cos: heat.zeros_like(),
            scale_x: heat.zeros_like(),
            scale_y: heat.zeros_like(),
            heatmap: heat,
        };
        let predicted = Tensor::<1>::from_floats(
            [0.6f32, 0.3, 0.5, 0.5, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
            &device,
        )
        .reshape([1, 5, 1, 2]);
        let expected = -(0.8 * 0.6f32.ln() + 0.2 * 0.4f32.ln()) - 0.7f32.ln();
        let got = scalar(losses(predicted, &small).centre);
        assert!((got - expected).abs() < 1e-5, "{got} vs {expected}");
    }
}
