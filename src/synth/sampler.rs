//! Geometric sampling for the synthetic pairs: the search window under a pose and pasting a
//! template at a pose (the pixel reads are `imaging`'s).

use image::RgbImage;

use crate::geometry::Pose;
use crate::imaging::{RgbImage32, bilinear_rgb8};

/// Inverse of the pose map with unit scales: a search offset `(p, q)` from the object centre
/// back to the source offset (template orientation).
fn unrotate(angle_deg: f32, p: f32, q: f32) -> (f32, f32) {
    let (s, c) = angle_deg.to_radians().sin_cos();
    (p * c - q * s, p * s + q * c)
}

/// The `side x side` search window in which the photo, rotated about `centre` by the pose's
/// angle, shows the box centre at `(pose.x, pose.y)`. None if any window pixel would fall
/// outside the photo (blank border).
pub fn warp_search_window(
    photo: &RgbImage,
    side: u32,
    centre: (f32, f32),
    pose: &Pose,
) -> Option<RgbImage32> {
    let last = side as f32 - 1.0;
    for (i, j) in [(0.0, 0.0), (last, 0.0), (0.0, last), (last, last)] {
        let (u, v) = unrotate(pose.angle_deg, i - pose.x, j - pose.y);
        bilinear_rgb8(photo, centre.0 + u, centre.1 + v)?;
    }
    let mut pixels = Vec::with_capacity((side * side * 3) as usize);
    for j in 0..side {
        for i in 0..side {
            let (u, v) = unrotate(pose.angle_deg, i as f32 - pose.x, j as f32 - pose.y);
            let rgb = bilinear_rgb8(photo, centre.0 + u, centre.1 + v)?;
            pixels.extend_from_slice(&rgb);
        }
    }
    Some(RgbImage32::new(side, side, pixels))
}

/// Pastes `template` at `pose` (with its scales) into `canvas`, masked to the template's area.
pub fn paste(canvas: &mut RgbImage32, template: &RgbImage32, pose: &Pose) {
    let (tw, th) = (template.width as f32, template.height as f32);
    let (s, c) = pose.angle_deg.to_radians().sin_cos();
    let reach = ((tw * pose.scale_x).hypot(th * pose.scale_y) / 2.0).ceil() as i32 + 1;
    let (cx, cy) = (pose.x.round() as i32, pose.y.round() as i32);
    for j in (cy - reach).max(0)..(cy + reach).min(canvas.height as i32) {
        for i in (cx - reach).max(0)..(cx + reach).min(canvas.width as i32) {
            let (p, q) = (i as f32 - pose.x, j as f32 - pose.y);
            // Inverse of the pose map: unrotate, then unscale.
            let (u, v) = (
                (p * c - q * s) / pose.scale_x,
                (p * s + q * c) / pose.scale_y,
            );
            let (tx, ty) = (u + (tw - 1.0) / 2.0, v + (th - 1.0) / 2.0);
            if tx < -0.5 || ty < -0.5 || tx > tw - 0.5 || ty > th - 0.5 {
                continue;
            }
            let rgb = template.sample(tx.clamp(0.0, tw - 1.0), ty.clamp(0.0, th - 1.0));
            let k = ((j as u32 * canvas.width + i as u32) * 3) as usize;
            canvas.pixels[k..k + 3].copy_from_slice(&rgb);
        }
    }
}
