//! The inner loop of every ZNCC the refinement and the verifier compute: sample the image
//! (bilinear, clamped) where a pose maps each template point and sum what the correlation needs.
//!
//! Why a module of its own: the screen of a hundred candidates scores a few hundred poses each,
//! and this loop was most of its time. Points are held in lanes of [`LANES`] (the template's
//! point list padded with copies of its first point, which add nothing), so that the compiler
//! turns the loop into vector arithmetic and gathers on AVX-512 and AVX2, chosen at run time.
//! Indices are 32-bit and coordinates convert unchecked (after clamping), so that a gather
//! reads sixteen samples and the conversion stays in vectors; lanes sum a block of points in
//! `f32` before adding it to `f64` totals. With 64-bit indices, saturating conversions and
//! `f64` lanes the loop gathered eight at a time and converted coordinates one by one: 200
//! saved tuning pairs through `match --pairs` took 5.9–6.2 s against 5.1–5.3 s, with the same
//! answers found on every tuning condition (docs/industrial.md, "Time against the filing day").

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

/// Whether the lane loops may sample a `width x height` plane with 32-bit indices and `f32`
/// coordinates ([`LaneTap`]), so that a vector gathers sixteen samples, not eight: its values
/// fit an `i32` index and each side an `f32` exactly. Any image the service accepts does; a
/// larger plane takes [`BilinearTap`]'s 64-bit path.
pub(super) fn fits_lanes(width: usize, height: usize) -> bool {
    const EXACT_IN_F32: usize = 1 << 24;
    width
        .checked_mul(height)
        .is_some_and(|pixels| pixels <= i32::MAX as usize)
        && width <= EXACT_IN_F32
        && height <= EXACT_IN_F32
}

/// Chunks of [`LANES`] points summed in `f32` before the block's sums are added to the `f64`
/// totals: 128 samples of at most 1 in magnitude per lane lose no more than a few units of
/// `f32`'s last place, and the totals stay as exact as before.
const CHUNKS_PER_BLOCK: usize = 8;

/// Where a bilinear sample of a row-major `width x height` plane reads, coordinates clamped
/// to it, as [`BilinearTap`] reads it but with 32-bit indices, so that a vector loop gathers
/// sixteen samples at once (the plane [`fits_lanes`]).
#[derive(Debug, Clone, Copy)]
pub(super) struct LaneTap {
    top_left: i32,
    /// 1 where the right neighbour is inside the plane, else 0 (clamped).
    right: i32,
    /// The width where the neighbour below is inside the plane, else 0 (clamped).
    down: i32,
    fx: f32,
    fy: f32,
}

impl LaneTap {
    /// Requires `1 <= width, height` and a plane that [`fits_lanes`].
    #[inline(always)]
    pub(super) fn new(width: i32, height: i32, x: f32, y: f32) -> Self {
        let x = x.clamp(0.0, (width - 1) as f32);
        let y = y.clamp(0.0, (height - 1) as f32);
        // A NaN coordinate reads the first column or row (`max` takes the number) and samples
        // NaN (its weight is NaN), as `BilinearTap` does; the unchecked conversion, unlike
        // `as`, vectorises.
        // SAFETY: both lie in [0, side − 1], which an i32 holds (the plane fits the lanes).
        let (x0, y0): (i32, i32) =
            unsafe { (x.max(0.0).to_int_unchecked(), y.max(0.0).to_int_unchecked()) };
        Self {
            top_left: y0 * width + x0,
            right: i32::from(x0 < width - 1),
            down: if y0 < height - 1 { width } else { 0 },
            fx: x - x0 as f32,
            fy: y - y0 as f32,
        }
    }

    /// The sample of `plane`.
    ///
    /// # Safety
    /// `plane.len()` is the `width * height` the tap was made for: every corner lies inside
    /// (`x0 + right <= width - 1`, `y0 * width + down <= (height - 1) * width`).
    #[inline(always)]
    pub(super) unsafe fn apply_unchecked(&self, plane: &[f32]) -> f32 {
        let i = self.top_left;
        // SAFETY: the caller's guarantee above.
        let (a, b, c, d) = unsafe {
            (
                *plane.get_unchecked(i as usize),
                *plane.get_unchecked((i + self.right) as usize),
                *plane.get_unchecked((i + self.down) as usize),
                *plane.get_unchecked((i + self.down + self.right) as usize),
            )
        };
        let top = a + (b - a) * self.fx;
        let bottom = c + (d - c) * self.fx;
        top + (bottom - top) * self.fy
    }
}

#[multiversion(targets("x86_64+avx512f+avx512vl+avx512bw+avx512dq", "x86_64+avx2+fma"))]
fn lane_sums(us: &[f32], vs: &[f32], weights: &[f32], image: &GrayImage32, map: &Affine) -> Sums {
    let (values, width, height) = (&image.values[..], image.width, image.height);
    if !fits_lanes(width, height) {
        return wide_lane_sums(us, vs, weights, image, map);
    }
    let (w32, h32) = (width as i32, height as i32);
    let at = |u: f32, v: f32| {
        let (x, y) = map.apply(u, v);
        // SAFETY: the caller checked `values.len() == width * height`, and it fits 32 bits.
        unsafe { LaneTap::new(w32, h32, x, y).apply_unchecked(values) }
    };
    let reference = at(us[0], vs[0]);
    let mut sum = [0f64; LANES];
    let mut sum_sq = [0f64; LANES];
    let mut dot = [0f64; LANES];
    let block = LANES * CHUNKS_PER_BLOCK;
    for ((u, v), w) in us
        .chunks(block)
        .zip(vs.chunks(block))
        .zip(weights.chunks(block))
    {
        let mut block_sum = [0f32; LANES];
        let mut block_sum_sq = [0f32; LANES];
        let mut block_dot = [0f32; LANES];
        for ((u, v), w) in u
            .chunks_exact(LANES)
            .zip(v.chunks_exact(LANES))
            .zip(w.chunks_exact(LANES))
        {
            for lane in 0..LANES {
                let value = at(u[lane], v[lane]) - reference;
                block_sum[lane] += value;
                block_sum_sq[lane] += value * value;
                block_dot[lane] += w[lane] * value;
            }
        }
        for lane in 0..LANES {
            sum[lane] += block_sum[lane] as f64;
            sum_sq[lane] += block_sum_sq[lane] as f64;
            dot[lane] += block_dot[lane] as f64;
        }
    }
    Sums {
        reference,
        sum: sum.iter().sum(),
        sum_sq: sum_sq.iter().sum(),
        dot: dot.iter().sum(),
    }
}

/// [`lane_sums`] for a plane too large for 32-bit indices.
fn wide_lane_sums(
    us: &[f32],
    vs: &[f32],
    weights: &[f32],
    image: &GrayImage32,
    map: &Affine,
) -> Sums {
    let (values, width, height) = (&image.values[..], image.width, image.height);
    let at = |u: f32, v: f32| {
        let (x, y) = map.apply(u, v);
        BilinearTap::new(width, height, x, y).apply(values)
    };
    let reference = at(us[0], vs[0]);
    let (mut sum, mut sum_sq, mut dot) = (0f64, 0f64, 0f64);
    for ((&u, &v), &w) in us.iter().zip(vs).zip(weights) {
        let value = (at(u, v) - reference) as f64;
        sum += value;
        sum_sq += value * value;
        dot += w as f64 * value;
    }
    Sums {
        reference,
        sum,
        sum_sq,
        dot,
    }
}

#[multiversion(targets("x86_64+avx512f+avx512vl+avx512bw+avx512dq", "x86_64+avx2+fma"))]
fn lane_samples(us: &[f32], vs: &[f32], image: &GrayImage32, map: &Affine, out: &mut [f32]) {
    let (values, width, height) = (&image.values[..], image.width, image.height);
    if !fits_lanes(width, height) {
        for ((&u, &v), out) in us.iter().zip(vs).zip(out) {
            let (x, y) = map.apply(u, v);
            *out = BilinearTap::new(width, height, x, y).apply(values);
        }
        return;
    }
    let (w32, h32) = (width as i32, height as i32);
    for ((u, v), out) in us
        .chunks_exact(LANES)
        .zip(vs.chunks_exact(LANES))
        .zip(out.chunks_exact_mut(LANES))
    {
        for lane in 0..LANES {
            let (x, y) = map.apply(u[lane], v[lane]);
            // SAFETY: the caller checked `values.len() == width * height`, and it fits 32 bits.
            out[lane] = unsafe { LaneTap::new(w32, h32, x, y).apply_unchecked(values) };
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The 32-bit tap reads what the 64-bit one reads: inside, on and past every border, NaN
    /// at a NaN coordinate, in a one-pixel-wide plane.
    #[test]
    fn the_lane_tap_samples_as_the_bilinear_tap() {
        for (width, height) in [(23usize, 17usize), (1, 9), (9, 1), (1, 1)] {
            let values: Vec<f32> = (0..width * height)
                .map(|i| ((i * 7919) % 101) as f32 / 101.0)
                .collect();
            assert!(fits_lanes(width, height));
            let places = [
                (0.0, 0.0),
                (3.25, 2.5),
                (width as f32 - 1.0, height as f32 - 1.0),
                (width as f32 - 1.5, 0.75),
                (-4.0, 30.0),
                (100.0, -2.5),
                (f32::NAN, 1.5),
                (2.5, f32::NAN),
            ];
            for (x, y) in places {
                let want = BilinearTap::new(width, height, x, y).apply(&values);
                // SAFETY: the plane is width x height and fits the lanes.
                let got = unsafe {
                    LaneTap::new(width as i32, height as i32, x, y).apply_unchecked(&values)
                };
                assert!(
                    (got - want).abs() <= 1e-6 || (got.is_nan() && want.is_nan()),
                    "{width}x{height} at ({x}, {y}): {got} against {want}"
                );
            }
        }
        assert!(!fits_lanes(1 << 25, 1));
        assert!(!fits_lanes(1 << 16, 1 << 16));
        assert!(!fits_lanes(usize::MAX, 2));
    }

    /// The path for planes beyond the lanes sums as the lanes do.
    #[test]
    fn wide_planes_sum_as_the_lanes_do() {
        let image = GrayImage32 {
            width: 31,
            height: 12,
            values: (0..31 * 12)
                .map(|i| ((i * 104_729) % 211) as f32 / 211.0)
                .collect(),
        };
        let offsets: Vec<(f32, f32)> = (0..150)
            .map(|i| ((i % 15) as f32 - 7.0, (i / 15) as f32 - 5.0))
            .collect();
        let weights: Vec<f32> = (0..150).map(|i| (i as f32 * 0.61).cos()).collect();
        let lanes = PointLanes::new(&offsets, &weights);
        let map = Affine {
            x: 14.2,
            y: 6.7,
            ax: 0.9,
            ay: -0.3,
            bx: 0.35,
            by: 1.1,
        };
        let narrow = lane_sums(&lanes.us, &lanes.vs, &lanes.weights, &image, &map);
        let wide = wide_lane_sums(&lanes.us, &lanes.vs, &lanes.weights, &image, &map);
        let close = |a: f64, b: f64| (a - b).abs() <= 1e-5 * (1.0 + b.abs());
        assert_eq!(narrow.reference, wide.reference);
        assert!(
            close(narrow.sum, wide.sum)
                && close(narrow.sum_sq, wide.sum_sq)
                && close(narrow.dot, wide.dot),
            "{narrow:?} against {wide:?}"
        );
    }

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
