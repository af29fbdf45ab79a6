//! The float colour image and the operations on colour images that more than one stage needs:
//! bilinear sampling (8-bit photos and float images), border padding and a small blur.

use image::RgbImage;

/// An RGB image as interleaved `f32` values in [0, 1].
#[derive(Debug, Clone)]
pub struct RgbImage32 {
    pub width: u32,
    pub height: u32,
    /// `height * width * 3`, row-major, RGB interleaved.
    pub pixels: Vec<f32>,
}

impl RgbImage32 {
    pub fn new(width: u32, height: u32, pixels: Vec<f32>) -> Self {
        assert_eq!(pixels.len(), width as usize * height as usize * 3);
        Self {
            width,
            height,
            pixels,
        }
    }

    /// From an already decoded `image` buffer (any colour type).
    pub fn from_dynamic(image: &image::DynamicImage) -> Self {
        let rgb = image.to_rgb32f();
        Self::new(rgb.width(), rgb.height(), rgb.into_raw())
    }

    /// Luma (BT.601) of every pixel, in [0, 1].
    pub fn to_gray(&self) -> Vec<f32> {
        self.pixels.chunks_exact(3).map(luma).collect()
    }

    /// A copy of the `w x h` window at `(x0, y0)`; the window must lie inside.
    pub fn crop(&self, x0: u32, y0: u32, w: u32, h: u32) -> Self {
        assert!(x0 + w <= self.width && y0 + h <= self.height);
        let mut pixels = Vec::with_capacity(w as usize * h as usize * 3);
        for y in y0..y0 + h {
            let start = (y as usize * self.width as usize + x0 as usize) * 3;
            pixels.extend_from_slice(&self.pixels[start..start + w as usize * 3]);
        }
        Self::new(w, h, pixels)
    }
}

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

/// Bilinear sample of an 8-bit RGB image at `(x, y)` (pixel centres at integers), in [0, 1];
/// None outside `[0, w-1] x [0, h-1]`.
pub fn bilinear_rgb8(image: &RgbImage, x: f32, y: f32) -> Option<[f32; 3]> {
    let (w, h) = (image.width() as f32, image.height() as f32);
    if !(x >= 0.0 && y >= 0.0 && x <= w - 1.0 && y <= h - 1.0) {
        return None;
    }
    let (x0, y0) = (x.floor() as u32, y.floor() as u32);
    let (x1, y1) = (
        (x0 + 1).min(image.width() - 1),
        (y0 + 1).min(image.height() - 1),
    );
    let (fx, fy) = (x - x0 as f32, y - y0 as f32);
    let p = |xx, yy| image.get_pixel(xx, yy).0;
    let (a, b, c, d) = (p(x0, y0), p(x1, y0), p(x0, y1), p(x1, y1));
    let mut out = [0f32; 3];
    for k in 0..3 {
        let top = a[k] as f32 * (1.0 - fx) + b[k] as f32 * fx;
        let bottom = c[k] as f32 * (1.0 - fx) + d[k] as f32 * fx;
        out[k] = (top * (1.0 - fy) + bottom * fy) / 255.0;
    }
    Some(out)
}

impl RgbImage32 {
    /// Bilinear sample of a float image inside its bounds.
    pub fn sample(&self, x: f32, y: f32) -> [f32; 3] {
        let image = self;
        let w = image.width as usize;
        let (x0, y0) = (x.floor() as usize, y.floor() as usize);
        let x1 = (x0 + 1).min(image.width as usize - 1);
        let y1 = (y0 + 1).min(image.height as usize - 1);
        let (fx, fy) = (x - x0 as f32, y - y0 as f32);
        let px = |xx: usize, yy: usize, k: usize| image.pixels[(yy * w + xx) * 3 + k];
        let mut out = [0f32; 3];
        for (k, o) in out.iter_mut().enumerate() {
            let top = px(x0, y0, k) * (1.0 - fx) + px(x1, y0, k) * fx;
            let bottom = px(x0, y1, k) * (1.0 - fx) + px(x1, y1, k) * fx;
            *o = top * (1.0 - fy) + bottom * fy;
        }
        out
    }
}

/// Grey value of one RGB pixel (ITU-R BT.601 weights, as OpenCV's `cvtColor`).
pub fn luma(pixel: &[f32]) -> f32 {
    0.299 * pixel[0] + 0.587 * pixel[1] + 0.114 * pixel[2]
}
