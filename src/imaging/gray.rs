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
    /// Whether some pixels are ignored (NaN: a template's mask leaves them out).
    pub fn ignores_pixels(&self) -> bool {
        self.values.iter().any(|v| v.is_nan())
    }

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
///
/// Each pass adds one kernel tap at a time over a whole row (the interior of a row for the
/// horizontal pass, whose borders clamp), so the adds vectorise; every pixel still sums its
/// taps in kernel order from zero, the order of the direct formula, so the result is the
/// same bit for bit.
pub fn gaussian_blur(image: &GrayImage32, sigma: f32) -> GrayImage32 {
    if sigma < 0.3 {
        return image.clone();
    }
    let radius = (3.0 * sigma).ceil() as usize;
    let mut kernel: Vec<f32> = (-(radius as isize)..=radius as isize)
        .map(|k| (-(k * k) as f32 / (2.0 * sigma * sigma)).exp())
        .collect();
    let total: f32 = kernel.iter().sum();
    kernel.iter_mut().for_each(|k| *k /= total);
    let (w, h) = (image.width, image.height);
    if w == 0 || h == 0 {
        return image.clone();
    }
    let mut horizontal = vec![0f32; image.values.len()];
    for (source, row) in image
        .values
        .chunks_exact(w)
        .zip(horizontal.chunks_exact_mut(w))
    {
        let clamped = |x: usize| {
            kernel.iter().enumerate().fold(0.0, |acc, (k, weight)| {
                let source_x = (x + k).saturating_sub(radius).min(w - 1);
                acc + weight * source[source_x]
            })
        };
        // Pixels whose taps all fall inside the row.
        let interior = radius..w.saturating_sub(radius).max(radius);
        for x in (0..interior.start.min(w)).chain(interior.end..w) {
            row[x] = clamped(x);
        }
        if !interior.is_empty() {
            for (k, &weight) in kernel.iter().enumerate() {
                let shifted = &source[interior.start + k - radius..interior.end + k - radius];
                add_scaled(&mut row[interior.clone()], shifted, weight);
            }
        }
    }
    let mut values = vec![0f32; image.values.len()];
    for (y, row) in values.chunks_exact_mut(w).enumerate() {
        for (k, &weight) in kernel.iter().enumerate() {
            let source_y = (y + k).saturating_sub(radius).min(h - 1);
            add_scaled(row, &horizontal[source_y * w..(source_y + 1) * w], weight);
        }
    }
    GrayImage32 {
        width: image.width,
        height: image.height,
        values,
    }
}

/// `out[i] += weight · values[i]`.
#[multiversion::multiversion(targets("x86_64+avx512f", "x86_64+avx2+fma"))]
fn add_scaled(out: &mut [f32], values: &[f32], weight: f32) {
    for (o, v) in out.iter_mut().zip(values) {
        *o += weight * v;
    }
}

/// Central-difference gradients (one-sided at the border).
pub fn gradients(image: &GrayImage32) -> (Vec<f32>, Vec<f32>) {
    let (w, h) = (image.width, image.height);
    let v = &image.values;
    let mut gx = vec![0f32; w * h];
    let mut gy = vec![0f32; w * h];
    if w == 0 || h == 0 {
        return (gx, gy);
    }
    for (y, (gx_row, gy_row)) in gx
        .chunks_exact_mut(w)
        .zip(gy.chunks_exact_mut(w))
        .enumerate()
    {
        let (t, b) = (y.saturating_sub(1), (y + 1).min(h - 1));
        differences(
            gy_row,
            &v[b * w..(b + 1) * w],
            &v[t * w..(t + 1) * w],
            (b - t).max(1) as f32,
        );
        let row = &v[y * w..(y + 1) * w];
        if w >= 3 {
            differences(&mut gx_row[1..w - 1], &row[2..], &row[..w - 2], 2.0);
        }
        for x in [0, w - 1] {
            let (l, r) = (x.saturating_sub(1), (x + 1).min(w - 1));
            gx_row[x] = (row[r] - row[l]) / (r - l).max(1) as f32;
        }
    }
    (gx, gy)
}

/// `out[i] = (ahead[i] − behind[i]) / divisor`.
#[multiversion::multiversion(targets("x86_64+avx512f", "x86_64+avx2+fma"))]
fn differences(out: &mut [f32], ahead: &[f32], behind: &[f32], divisor: f32) {
    for ((o, a), b) in out.iter_mut().zip(ahead).zip(behind) {
        *o = (a - b) / divisor;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The blur by its formula, one pixel at a time, borders clamped.
    fn blurred_directly(image: &GrayImage32, sigma: f32) -> Vec<f32> {
        let radius = (3.0 * sigma).ceil() as isize;
        let mut kernel: Vec<f32> = (-radius..=radius)
            .map(|k| (-(k * k) as f32 / (2.0 * sigma * sigma)).exp())
            .collect();
        let total: f32 = kernel.iter().sum();
        kernel.iter_mut().for_each(|k| *k /= total);
        let (w, h) = (image.width as isize, image.height as isize);
        let at =
            |x: isize, y: isize| image.values[(y.clamp(0, h - 1) * w + x.clamp(0, w - 1)) as usize];
        let horizontal: Vec<f32> = (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                kernel
                    .iter()
                    .enumerate()
                    .fold(0.0, |acc, (k, c)| acc + c * at(x + k as isize - radius, y))
            })
            .collect();
        (0..w * h)
            .map(|i| {
                let (x, y) = (i % w, i / w);
                kernel.iter().enumerate().fold(0.0, |acc, (k, c)| {
                    let yy = (y + k as isize - radius).clamp(0, h - 1);
                    acc + c * horizontal[(yy * w + x) as usize]
                })
            })
            .collect()
    }

    #[test]
    fn the_blur_equals_its_formula_bit_for_bit_at_every_size() {
        // Rows shorter than the kernel, as long as it, and longer; sigmas of 1 to 7 taps a side.
        for (w, h) in [(1, 1), (3, 2), (7, 5), (13, 4), (40, 31)] {
            let image = GrayImage32::from_fn(w, h, |x, y| ((x * 31 + y * 17) % 23) as f32 / 7.0);
            for sigma in [0.4, 1.0, 1.5, 2.3] {
                let fast = gaussian_blur(&image, sigma);
                let direct = blurred_directly(&image, sigma);
                assert_eq!((fast.width, fast.height), (w, h));
                assert!(
                    fast.values
                        .iter()
                        .zip(&direct)
                        .all(|(a, b)| a.to_bits() == b.to_bits()),
                    "{w}x{h}, sigma {sigma}"
                );
            }
        }
        let flat = GrayImage32::from_fn(9, 9, |_, _| 0.25);
        assert!(
            gaussian_blur(&flat, 1.0)
                .values
                .iter()
                .all(|&v| (v - 0.25).abs() < 1e-6)
        );
    }

    #[test]
    fn gradients_are_central_differences_one_sided_at_the_border() {
        for (w, h) in [(1, 1), (2, 3), (5, 1), (9, 7)] {
            let image = GrayImage32::from_fn(w, h, |x, y| ((x * 13 + y * 29) % 19) as f32 / 3.0);
            let (gx, gy) = gradients(&image);
            let at = |x: usize, y: usize| image.values[y * w + x];
            for y in 0..h {
                for x in 0..w {
                    let (l, r) = (x.saturating_sub(1), (x + 1).min(w - 1));
                    let (t, b) = (y.saturating_sub(1), (y + 1).min(h - 1));
                    let expected_x = (at(r, y) - at(l, y)) / (r - l).max(1) as f32;
                    let expected_y = (at(x, b) - at(x, t)) / (b - t).max(1) as f32;
                    assert_eq!(
                        gx[y * w + x].to_bits(),
                        expected_x.to_bits(),
                        "{w}x{h} gx at {x},{y}"
                    );
                    assert_eq!(
                        gy[y * w + x].to_bits(),
                        expected_y.to_bits(),
                        "{w}x{h} gy at {x},{y}"
                    );
                }
            }
        }
    }
}
