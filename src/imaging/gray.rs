//! The single-channel float image that refinement, verification and the classical matcher
//! work on, and the operations on it: bilinear sampling, 2x downsampling, Gaussian blur and
//! gradients. Image operations live here, not in the stages that use them.

use super::RgbImage32;

/// A single-channel float image.
#[derive(Debug, Clone)]
pub struct GrayImage32 {
    pub width: usize,
    pub height: usize,
    pub values: Vec<f32>,
}

impl GrayImage32 {
    pub fn from_rgb(image: &RgbImage32) -> Self {
        Self {
            width: image.width as usize,
            height: image.height as usize,
            values: image.to_gray(),
        }
    }

    /// The image whose pixel `(x, y)` is `value(x, y)`.
    pub fn from_fn(width: usize, height: usize, value: impl Fn(usize, usize) -> f32) -> Self {
        Self {
            width,
            height,
            values: (0..width * height)
                .map(|i| value(i % width, i / width))
                .collect(),
        }
    }

    /// Half the size (2x2 box filter; an odd last row or column is repeated).
    pub fn downsample(&self) -> GrayImage32 {
        let (w, h) = ((self.width / 2).max(1), (self.height / 2).max(1));
        let at = |x: usize, y: usize| {
            self.values[y.min(self.height - 1) * self.width + x.min(self.width - 1)]
        };
        let mut values = Vec::with_capacity(w * h);
        for y in 0..h {
            for x in 0..w {
                values.push(
                    (at(2 * x, 2 * y)
                        + at(2 * x + 1, 2 * y)
                        + at(2 * x, 2 * y + 1)
                        + at(2 * x + 1, 2 * y + 1))
                        / 4.0,
                );
            }
        }
        GrayImage32 {
            width: w,
            height: h,
            values,
        }
    }

    /// Bilinear sample with the coordinates clamped to the image.
    #[inline]
    pub fn sample(&self, x: f32, y: f32) -> f32 {
        BilinearTap::new(self.width, self.height, x, y).apply(&self.values)
    }
}

/// Where a bilinear sample of a `width x height` plane reads (coordinates clamped to the plane)
/// and with what weights. One tap serves several planes of the same size (an image and its
/// gradients) at the cost of one.
#[derive(Debug, Clone, Copy)]
pub struct BilinearTap {
    /// Indices of the four neighbours: top-left, top-right, bottom-left, bottom-right.
    corners: [usize; 4],
    fx: f32,
    fy: f32,
}

impl BilinearTap {
    #[inline(always)]
    pub fn new(width: usize, height: usize, x: f32, y: f32) -> Self {
        let x = x.clamp(0.0, (width - 1) as f32);
        let y = y.clamp(0.0, (height - 1) as f32);
        let (x0, y0) = (x as usize, y as usize);
        let (x1, y1) = ((x0 + 1).min(width - 1), (y0 + 1).min(height - 1));
        Self {
            corners: [
                y0 * width + x0,
                y0 * width + x1,
                y1 * width + x0,
                y1 * width + x1,
            ],
            fx: x - x0 as f32,
            fy: y - y0 as f32,
        }
    }

    /// The sample of `plane` (row-major, the size the tap was made for).
    #[inline]
    pub fn apply(&self, plane: &[f32]) -> f32 {
        let [a, b, c, d] = self.corners;
        let top = plane[a] + (plane[b] - plane[a]) * self.fx;
        let bottom = plane[c] + (plane[d] - plane[c]) * self.fx;
        top + (bottom - top) * self.fy
    }

    /// [`BilinearTap::apply`] without bounds checks, for vector loops (gathers).
    ///
    /// # Safety
    /// `plane.len()` is the `width * height` the tap was made for (its corners lie inside:
    /// `new` clamps the coordinates, and a NaN coordinate converts to 0).
    #[inline(always)]
    pub unsafe fn apply_unchecked(&self, plane: &[f32]) -> f32 {
        let [a, b, c, d] = self.corners;
        // SAFETY: every corner is below width * height = plane.len() (the caller's guarantee).
        let (a, b, c, d) = unsafe {
            (
                *plane.get_unchecked(a),
                *plane.get_unchecked(b),
                *plane.get_unchecked(c),
                *plane.get_unchecked(d),
            )
        };
        let top = a + (b - a) * self.fx;
        let bottom = c + (d - c) * self.fx;
        top + (bottom - top) * self.fy
    }
}

/// Separable Gaussian blur with clamped borders; a copy when `sigma` is below 0.3.
pub fn gaussian_blur(image: &GrayImage32, sigma: f32) -> GrayImage32 {
    if sigma < 0.3 {
        return image.clone();
    }
    let radius = (3.0 * sigma).ceil() as isize;
    let mut kernel: Vec<f32> = (-radius..=radius)
        .map(|k| (-(k * k) as f32 / (2.0 * sigma * sigma)).exp())
        .collect();
    let total: f32 = kernel.iter().sum();
    kernel.iter_mut().for_each(|k| *k /= total);
    let (w, h) = (image.width as isize, image.height as isize);
    let mut horizontal = vec![0f32; image.values.len()];
    for y in 0..h {
        for x in 0..w {
            let mut acc = 0.0;
            for (k, weight) in kernel.iter().enumerate() {
                let xx = (x + k as isize - radius).clamp(0, w - 1);
                acc += weight * image.values[(y * w + xx) as usize];
            }
            horizontal[(y * w + x) as usize] = acc;
        }
    }
    let mut values = vec![0f32; image.values.len()];
    for y in 0..h {
        for x in 0..w {
            let mut acc = 0.0;
            for (k, weight) in kernel.iter().enumerate() {
                let yy = (y + k as isize - radius).clamp(0, h - 1);
                acc += weight * horizontal[(yy * w + x) as usize];
            }
            values[(y * w + x) as usize] = acc;
        }
    }
    GrayImage32 {
        width: image.width,
        height: image.height,
        values,
    }
}

/// Central-difference gradients (one-sided at the border).
pub fn gradients(image: &GrayImage32) -> (Vec<f32>, Vec<f32>) {
    let (w, h) = (image.width, image.height);
    let v = &image.values;
    let mut gx = vec![0f32; w * h];
    let mut gy = vec![0f32; w * h];
    for y in 0..h {
        for x in 0..w {
            let (l, r) = (x.saturating_sub(1), (x + 1).min(w - 1));
            let (t, b) = (y.saturating_sub(1), (y + 1).min(h - 1));
            gx[y * w + x] = (v[y * w + r] - v[y * w + l]) / (r - l).max(1) as f32;
            gy[y * w + x] = (v[b * w + x] - v[t * w + x]) / (b - t).max(1) as f32;
        }
    }
    (gx, gy)
}
