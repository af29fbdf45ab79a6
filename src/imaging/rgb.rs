//! Operations on colour float images that more than one stage needs: border padding and a
//! small blur.

use super::RgbImage32;

/// Replicates the last row/column until both sides are at least `min_side`.
pub fn pad_to_min_side(image: RgbImage32, min_side: usize) -> RgbImage32 {
    let (w, h) = (image.width as usize, image.height as usize);
    let (nw, nh) = (w.max(min_side), h.max(min_side));
    if (nw, nh) == (w, h) {
        return image;
    }
    let mut pixels = Vec::with_capacity(nw * nh * 3);
    for y in 0..nh {
        let row = &image.pixels[y.min(h - 1) * w * 3..(y.min(h - 1) + 1) * w * 3];
        pixels.extend_from_slice(row);
        let last = &row[(w - 1) * 3..];
        for _ in w..nw {
            pixels.extend_from_slice(last);
        }
    }
    RgbImage32::new(nw as u32, nh as u32, pixels)
}

/// Separable [1 2 1]/4 blur with clamped borders.
pub fn blur_121(image: &mut RgbImage32) {
    let (w, h) = (image.width as usize, image.height as usize);
    let src = image.pixels.clone();
    let mut tmp = vec![0f32; src.len()];
    for y in 0..h {
        for x in 0..w {
            let (l, r) = (x.saturating_sub(1), (x + 1).min(w - 1));
            for c in 0..3 {
                let at = |xx: usize| src[(y * w + xx) * 3 + c];
                tmp[(y * w + x) * 3 + c] = 0.25 * at(l) + 0.5 * at(x) + 0.25 * at(r);
            }
        }
    }
    for y in 0..h {
        let (t, b) = (y.saturating_sub(1), (y + 1).min(h - 1));
        for x in 0..w {
            for c in 0..3 {
                let at = |yy: usize| tmp[(yy * w + x) * 3 + c];
                image.pixels[(y * w + x) * 3 + c] = 0.25 * at(t) + 0.5 * at(y) + 0.25 * at(b);
            }
        }
    }
}
