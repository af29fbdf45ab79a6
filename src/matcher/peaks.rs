//! From the five network maps to candidate poses, in the network's own pixel grid.
//!
//! The official peak reading reads everything at the single arg-max pixel and averages the (row, col)
//! of the >0.5 pixels within 15 px. We find every local maximum; for each one the centre is the
//! centroid of its neighbourhood weighted by `score − score_peak/2` (sub-pixel, robust to the
//! plateau shape), and angle and scales are read at the peak pixel as the official peak reading does.
//! (Averaging the angle over the neighbourhood as a circular mean is available as
//! [`neighbourhood_angle_deg`]; whether it beats the peak reading is for `posematch eval` to
//! show, so the default stays with the checkpoint authors' reading.)

/// The five maps of one image, row-major, `width x height` each.
pub struct MapPlanes<'a> {
    pub width: usize,
    pub height: usize,
    pub score: &'a [f32],
    pub sign: &'a [f32],
    pub cos: &'a [f32],
    pub scale_x: &'a [f32],
    pub scale_y: &'a [f32],
}

/// A pose in network pixels, scales relative to the network template grid.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NetworkPeak {
    pub x: f32,
    pub y: f32,
    pub angle_deg: f32,
    pub scale_x: f32,
    pub scale_y: f32,
    pub score: f32,
}

/// Largest radius (network pixels) of the neighbourhood averaged around a peak, as in the
/// official peak reading.
const MAX_RADIUS: f32 = 15.0;
/// Local-maximum window half-size.
const PEAK_WINDOW: usize = 2;

/// Local maxima of the score map at or above `min_score`, best first, at most `limit`.
pub fn find_peaks(planes: &MapPlanes, min_score: f32, limit: usize) -> Vec<(usize, usize)> {
    let (w, h) = (planes.width, planes.height);
    let s = planes.score;
    let mut peaks = Vec::new();
    for row in 0..h {
        for col in 0..w {
            let v = s[row * w + col];
            if v < min_score {
                continue;
            }
            let mut is_max = true;
            'window: for r in row.saturating_sub(PEAK_WINDOW)..(row + PEAK_WINDOW + 1).min(h) {
                for c in col.saturating_sub(PEAK_WINDOW)..(col + PEAK_WINDOW + 1).min(w) {
                    let n = s[r * w + c];
                    // Ties go to the first pixel in row-major order, like the official arg-max.
                    if n > v || (n == v && (r, c) < (row, col)) {
                        is_max = false;
                        break 'window;
                    }
                }
            }
            if is_max {
                peaks.push((row, col));
            }
        }
    }
    peaks.sort_by(|a, b| s[b.0 * w + b.1].total_cmp(&s[a.0 * w + a.1]));
    peaks.truncate(limit);
    peaks
}

/// Sub-pixel pose around the peak at `(row, col)`.
pub fn peak_at(planes: &MapPlanes, row: usize, col: usize) -> NetworkPeak {
    let (w, h) = (planes.width, planes.height);
    let at = |r: usize, c: usize| r * w + c;
    let i = at(row, col);
    let peak_score = planes.score[i];
    // The averaging radius shrinks for small objects so neighbours do not blend in.
    let object_side = 36.0 * planes.scale_x[i].min(planes.scale_y[i]);
    let radius = (0.4 * object_side).clamp(2.0, MAX_RADIUS);
    let threshold = 0.5 * peak_score;
    let reach = radius.ceil() as usize;
    let (mut sw, mut sx, mut sy) = (0f64, 0f64, 0f64);
    for r in row.saturating_sub(reach)..(row + reach + 1).min(h) {
        for c in col.saturating_sub(reach)..(col + reach + 1).min(w) {
            let (dr, dc) = (r as f32 - row as f32, c as f32 - col as f32);
            if dr * dr + dc * dc > radius * radius {
                continue;
            }
            let j = at(r, c);
            let weight = (planes.score[j] - threshold) as f64;
            if weight <= 0.0 {
                continue;
            }
            sw += weight;
            sx += weight * c as f64;
            sy += weight * r as f64;
        }
    }
    // The peak itself always has positive weight, so sw > 0.
    let angle = pixel_angle_rad(planes.sign[i], planes.cos[i]).to_degrees() as f32;
    NetworkPeak {
        x: (sx / sw) as f32,
        y: (sy / sw) as f32,
        angle_deg: crate::geometry::wrap_angle_deg(angle),
        scale_x: planes.scale_x[i],
        scale_y: planes.scale_y[i],
        score: peak_score,
    }
}

/// Circular mean of the per-pixel angles `sign · acos(cos)` within `radius` of the peak, weighted
/// by `score − score_peak/2` (a plain mean of sign and cos breaks near 0° and 180°, where the sign
/// map flips).
pub fn neighbourhood_angle_deg(planes: &MapPlanes, row: usize, col: usize, radius: f32) -> f32 {
    let (w, h) = (planes.width, planes.height);
    let threshold = 0.5 * planes.score[row * w + col];
    let reach = radius.ceil() as usize;
    let (mut sc, mut ss) = (0f64, 0f64);
    for r in row.saturating_sub(reach)..(row + reach + 1).min(h) {
        for c in col.saturating_sub(reach)..(col + reach + 1).min(w) {
            let (dr, dc) = (r as f32 - row as f32, c as f32 - col as f32);
            let j = r * w + c;
            let weight = (planes.score[j] - threshold) as f64;
            if dr * dr + dc * dc > radius * radius || weight <= 0.0 {
                continue;
            }
            let angle = pixel_angle_rad(planes.sign[j], planes.cos[j]);
            sc += weight * angle.cos();
            ss += weight * angle.sin();
        }
    }
    crate::geometry::wrap_angle_deg(ss.atan2(sc).to_degrees() as f32)
}

/// The angle a single pixel votes for: `±acos(cos)`, positive when the sign map says so.
fn pixel_angle_rad(sign: f32, cos: f32) -> f64 {
    let magnitude = (cos.clamp(-1.0, 1.0) as f64).acos();
    if sign > 0.5 { magnitude } else { -magnitude }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Synthetic maps: a Gaussian bump centred at a sub-pixel position with constant parameters.
    fn bump(w: usize, h: usize, cx: f32, cy: f32, angle_deg: f32) -> [Vec<f32>; 5] {
        let mut score = vec![0.0; w * h];
        for r in 0..h {
            for c in 0..w {
                let d2 = (c as f32 - cx).powi(2) + (r as f32 - cy).powi(2);
                score[r * w + c] = (-d2 / (2.0 * 3.0f32.powi(2))).exp();
            }
        }
        let a = angle_deg.to_radians();
        let sign = vec![if a > 0.0 { 0.9 } else { 0.1 }; w * h];
        [
            score,
            sign,
            vec![a.cos(); w * h],
            vec![1.2; w * h],
            vec![0.8; w * h],
        ]
    }

    fn planes(m: &[Vec<f32>; 5], w: usize, h: usize) -> MapPlanes<'_> {
        MapPlanes {
            width: w,
            height: h,
            score: &m[0],
            sign: &m[1],
            cos: &m[2],
            scale_x: &m[3],
            scale_y: &m[4],
        }
    }

    #[test]
    fn recovers_sub_pixel_centre_and_parameters() {
        let m = bump(64, 48, 30.3, 20.7, -135.0);
        let p = planes(&m, 64, 48);
        let peaks = find_peaks(&p, 0.5, 10);
        assert_eq!(peaks, vec![(21, 30)]);
        let d = peak_at(&p, 21, 30);
        assert!(
            (d.x - 30.3).abs() < 0.05 && (d.y - 20.7).abs() < 0.05,
            "{d:?}"
        );
        assert!((d.angle_deg + 135.0).abs() < 1e-3, "{d:?}");
        assert!((d.scale_x - 1.2).abs() < 1e-5 && (d.scale_y - 0.8).abs() < 1e-5);
    }

    #[test]
    fn angle_mean_survives_the_sign_flip_at_180() {
        // Half the pixels say +179°, half say −179° (sign map split): the answer is 180°, not 0°.
        let w = 21;
        let mut m = bump(w, w, 10.0, 10.0, 179.0);
        for r in 0..w {
            for c in 0..w {
                m[1][r * w + c] = if c < 10 { 0.9 } else { 0.1 };
            }
        }
        let a = neighbourhood_angle_deg(&planes(&m, w, w), 10, 10, 15.0);
        assert!(crate::geometry::angle_distance_deg(a, 180.0) < 1.01, "{a}");
    }

    #[test]
    fn finds_every_separate_peak_best_first() {
        let a = bump(80, 40, 15.0, 20.0, 10.0);
        let b = bump(80, 40, 60.0, 18.0, 10.0);
        let score: Vec<f32> = a[0]
            .iter()
            .zip(&b[0])
            .map(|(x, y)| x.max(0.9 * y))
            .collect();
        let m = [
            score,
            a[1].clone(),
            a[2].clone(),
            a[3].clone(),
            a[4].clone(),
        ];
        let peaks = find_peaks(&planes(&m, 80, 40), 0.5, 10);
        assert_eq!(peaks, vec![(20, 15), (18, 60)]);
        assert!(find_peaks(&planes(&m, 80, 40), 0.95, 10).len() == 1);
    }
}
