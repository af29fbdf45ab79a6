//! The inner loop of every ZNCC the refinement and the verifier compute: sample the image
//! (bilinear, clamped) where a pose maps each template point and sum what the correlation needs.
//!
//! Why a module of its own: the screen of a hundred candidates scores a few hundred poses each,
//! and this loop was most of its time. Points are held in lanes of [`LANES`] (the template's
//! point list padded with copies of its first point, which add nothing), so that the compiler
//! turns the loop into vector arithmetic and gathers on AVX-512 and AVX2, chosen at run time.

use multiversion::multiversion;

use crate::geometry::Pose;
use crate::imaging::{BilinearTap, GrayImage32};

/// Points per vector: sixteen f32 on AVX-512.
pub(super) const LANES: usize = 16;

/// Template points in lanes: offsets `(u, v)` from the template centre and a weight each, the
/// list padded to a multiple of [`LANES`] with copies of the first point of weight 0.
pub(super) struct PointLanes {
    pub(super) us: Vec<f32>,
    pub(super) vs: Vec<f32>,
    pub(super) weights: Vec<f32>,
    /// Real points (before the padding).
    count: usize,
}

/// Sums over the template points of `value = I(W(u, v)) − reference`, `reference` being the
/// first point's sample: Σ value, Σ value², Σ weight·value. Relative to the first sample,
/// because the variance is otherwise a small difference of large sums.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct Sums {
    pub reference: f32,
    pub sum: f64,
    pub sum_sq: f64,
    pub dot: f64,
}

impl PointLanes {
    pub(super) fn new(offsets: &[(f32, f32)], weights: &[f32]) -> Self {
        assert_eq!(offsets.len(), weights.len(), "one weight per point");
        let count = offsets.len();
        let padded = count.div_ceil(LANES) * LANES;
        let first = offsets.first().copied().unwrap_or((0.0, 0.0));
        let pad = |mut values: Vec<f32>, with: f32| {
            values.resize(padded, with);
            values
        };
        Self {
            us: pad(offsets.iter().map(|p| p.0).collect(), first.0),
            vs: pad(offsets.iter().map(|p| p.1).collect(), first.1),
            weights: pad(weights.to_vec(), 0.0),
            count,
        }
    }

    /// Real points (the padding not counted).
    pub(super) fn len(&self) -> usize {
        self.count
    }

    /// The real points: offset and weight.
    pub(super) fn points(&self) -> impl Iterator<Item = ((f32, f32), f32)> + '_ {
        self.us
            .iter()
            .zip(&self.vs)
            .zip(&self.weights)
            .take(self.count)
            .map(|((&u, &v), &w)| ((u, v), w))
    }

    /// [`Sums`] of these points in `image` under `pose` (coordinates clamped to the image).
    pub(super) fn sums(&self, image: &GrayImage32, pose: &Pose) -> Sums {
        self.sums_at(image, &Affine::of(pose, 0.0, 0.0))
    }

    /// The image (bilinear, coordinates clamped) where `pose` maps each real point, in the
    /// points' order, written over `out`.
    pub(super) fn samples(&self, image: &GrayImage32, pose: &Pose, out: &mut Vec<f32>) {
        self.samples_at(image, &Affine::of(pose, 0.0, 0.0), out);
    }

    /// The image (bilinear, coordinates clamped) where `map` puts each real point, in the
    /// points' order, written over `out`.
    pub(super) fn samples_at(&self, image: &GrayImage32, map: &Affine, out: &mut Vec<f32>) {
        assert_eq!(
            image.values.len(),
            image.width * image.height,
            "image values match its size"
        );
        out.clear();
        if self.count == 0 || image.values.is_empty() {
            return;
        }
        out.resize(self.us.len(), 0.0);
        lane_samples(&self.us, &self.vs, image, map, out);
        out.truncate(self.count);
    }

    /// [`Sums`] of these points in `image` where `map` puts them.
    pub(super) fn sums_at(&self, image: &GrayImage32, map: &Affine) -> Sums {
        assert_eq!(
            image.values.len(),
            image.width * image.height,
            "image values match its size"
        );
        if self.count == 0 || image.values.is_empty() {
            return Sums {
                reference: 0.0,
                sum: 0.0,
                sum_sq: 0.0,
                dot: 0.0,
            };
        }
        lane_sums(&self.us, &self.vs, &self.weights, image, map)
    }
}

/// Where template offset `(u, v)` lands: `(x + ax·u + bx·v, y + ay·u + by·v)`.
#[derive(Debug, Clone, Copy)]
pub(super) struct Affine {
    pub x: f32,
    pub y: f32,
    pub ax: f32,
    pub ay: f32,
    pub bx: f32,
    pub by: f32,
}

impl Affine {
    /// The map of `pose` (see the pose convention in [`Pose`]), in coordinates whose origin is
    /// the image's `(origin_x, origin_y)`.
    pub(super) fn of(pose: &Pose, origin_x: f32, origin_y: f32) -> Self {
        let (s, c) = pose.angle_deg.to_radians().sin_cos();
        Self {
            x: pose.x - origin_x,
            y: pose.y - origin_y,
            ax: pose.scale_x * c,
            ay: -pose.scale_x * s,
            bx: pose.scale_y * s,
            by: pose.scale_y * c,
        }
    }

    #[inline(always)]
    pub(super) fn apply(&self, u: f32, v: f32) -> (f32, f32) {
        (
            self.x + self.ax * u + self.bx * v,
            self.y + self.ay * u + self.by * v,
        )
    }
}

#[multiversion(targets("x86_64+avx512f+avx512vl+avx512bw+avx512dq", "x86_64+avx2+fma"))]
fn lane_sums(us: &[f32], vs: &[f32], weights: &[f32], image: &GrayImage32, map: &Affine) -> Sums {
    let (values, width, height) = (&image.values[..], image.width, image.height);
    let at = |u: f32, v: f32| {
        let (x, y) = map.apply(u, v);
        // SAFETY: the caller checked `values.len() == width * height`.
        unsafe { BilinearTap::new(width, height, x, y).apply_unchecked(values) }
    };
    let reference = at(us[0], vs[0]);
    let mut sum = [0f64; LANES];
    let mut sum_sq = [0f64; LANES];
    let mut dot = [0f64; LANES];
    for ((u, v), w) in us
        .chunks_exact(LANES)
        .zip(vs.chunks_exact(LANES))
        .zip(weights.chunks_exact(LANES))
    {
        for lane in 0..LANES {
            let value = (at(u[lane], v[lane]) - reference) as f64;
            sum[lane] += value;
            sum_sq[lane] += value * value;
            dot[lane] += w[lane] as f64 * value;
        }
    }
    Sums {
        reference,
        sum: sum.iter().sum(),
        sum_sq: sum_sq.iter().sum(),
        dot: dot.iter().sum(),
    }
}

#[multiversion(targets("x86_64+avx512f+avx512vl+avx512bw+avx512dq", "x86_64+avx2+fma"))]
fn lane_samples(us: &[f32], vs: &[f32], image: &GrayImage32, map: &Affine, out: &mut [f32]) {
    let (values, width, height) = (&image.values[..], image.width, image.height);
    for ((u, v), out) in us
        .chunks_exact(LANES)
        .zip(vs.chunks_exact(LANES))
        .zip(out.chunks_exact_mut(LANES))
    {
        for lane in 0..LANES {
            let (x, y) = map.apply(u[lane], v[lane]);
            // SAFETY: the caller checked `values.len() == width * height`.
            out[lane] = unsafe { BilinearTap::new(width, height, x, y).apply_unchecked(values) };
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The lanes give the sums of the plain point-by-point loop (up to the order of the
    /// additions), for point counts that do and do not fill the lanes, and poses that reach
    /// past the image's border.
    #[test]
    fn lane_sums_equal_the_point_by_point_sums() {
        let image = GrayImage32 {
            width: 23,
            height: 17,
            values: (0..23 * 17)
                .map(|i| ((i * 7919) % 101) as f32 / 101.0)
                .collect(),
        };
        for count in [1usize, 15, 16, 17, 81, 324] {
            let offsets: Vec<(f32, f32)> = (0..count)
                .map(|i| ((i % 19) as f32 - 9.0, (i / 19) as f32 - 8.0))
                .collect();
            let weights: Vec<f32> = (0..count).map(|i| (i as f32 * 0.37).sin()).collect();
            let lanes = PointLanes::new(&offsets, &weights);
            assert_eq!(lanes.len(), count);
            for (x, y, angle_deg, scale_x, scale_y) in [
                (11.0, 8.0, 0.0, 1.0, 1.0),
                (10.3, 7.6, 33.0, 0.8, 1.3),
                (1.0, 20.0, -140.0, 1.7, 0.6),
            ] {
                let pose = Pose {
                    x,
                    y,
                    angle_deg,
                    scale_x,
                    scale_y,
                    score: 0.0,
                    network_score: 0.0,
                };
                let got = lanes.sums(&image, &pose);
                let (s, c) = pose.angle_deg.to_radians().sin_cos();
                let at = |(u, v): (f32, f32)| {
                    image.sample(
                        pose.x + pose.scale_x * c * u + pose.scale_y * s * v,
                        pose.y - pose.scale_x * s * u + pose.scale_y * c * v,
                    )
                };
                let reference = at(offsets[0]);
                let (mut sum, mut sum_sq, mut dot) = (0f64, 0f64, 0f64);
                for (&p, &w) in offsets.iter().zip(&weights) {
                    let value = (at(p) - reference) as f64;
                    sum += value;
                    sum_sq += value * value;
                    dot += w as f64 * value;
                }
                let close = |a: f64, b: f64| (a - b).abs() <= 1e-6 * (1.0 + b.abs());
                assert!(
                    close(got.sum, sum) && close(got.sum_sq, sum_sq) && close(got.dot, dot),
                    "{count} points at {pose:?}: {got:?} against ({sum}, {sum_sq}, {dot})"
                );
            }
        }
    }
}
