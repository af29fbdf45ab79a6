//! Which template pixels count: a region known to vary (a date code, a serial number, a window
//! onto the conveyor) is left out of every score and of the refinement. Halcon takes any ROI,
//! PatMax a training mask, Matrox don't-care masks, OpenCV `matchTemplate` a mask: this is ours.
//!
//! Ignored pixels never reach a score: the grey template the verification works on holds NaN
//! there, and every place that turns a template into points skips NaN (`refine::grid_points`;
//! blurs and downsampling spread it, so the ignored area only grows at coarser levels, never
//! shrinks). The network is shown the template as registered, ignored pixels included: it was
//! trained on whole templates, and a neutral patch there (the used pixels' mean colour) found
//! fewer parts with a quarter of them covered and masked (mate-backgrounds, S1.5, 200 pairs,
//! default weights: 76.5 % against 80.0 % under a plain cover, 89.5 % against 90.5 % under
//! clutter).

use crate::imaging::{GrayImage32, RgbImage32};

/// Fewest used pixels a mask must leave: fewer cannot be told from chance.
pub const MIN_USED_PIXELS: usize = 16;

/// A template mask: `true` = use the pixel, `false` = ignore it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TemplateMask {
    width: u32,
    height: u32,
    used: Vec<bool>,
}

/// Why a mask cannot be used.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum MaskError {
    #[error(
        "the template mask is {mask_width}x{mask_height} but the template is {width}x{height}: give a mask of the template's size"
    )]
    Size {
        mask_width: u32,
        mask_height: u32,
        width: u32,
        height: u32,
    },
    #[error(
        "the template mask leaves {used} pixels to use (at least {MIN_USED_PIXELS} needed): 0 means ignore, any other value use"
    )]
    TooFewUsed { used: usize },
}

impl TemplateMask {
    /// From one flag per pixel, row-major (`used.len()` must be `width * height`).
    pub fn new(width: u32, height: u32, used: Vec<bool>) -> Result<Self, MaskError> {
        assert_eq!(
            used.len(),
            width as usize * height as usize,
            "one flag per mask pixel"
        );
        let count = used.iter().filter(|&&u| u).count();
        if count < MIN_USED_PIXELS {
            return Err(MaskError::TooFewUsed { used: count });
        }
        Ok(Self {
            width,
            height,
            used,
        })
    }

    /// From a decoded mask image: black (every channel 0) = ignore, anything else = use.
    pub fn from_image(image: &RgbImage32) -> Result<Self, MaskError> {
        let used = image
            .pixels
            .chunks_exact(3)
            .map(|p| p.iter().any(|&v| v > 0.5 / 255.0))
            .collect();
        Self::new(image.width, image.height, used)
    }

    pub fn width(&self) -> u32 {
        self.width
    }

    pub fn height(&self) -> u32 {
        self.height
    }

    /// One flag per pixel, row-major.
    pub fn used(&self) -> &[bool] {
        &self.used
    }

    /// Whether every pixel is used (the mask changes nothing).
    pub fn uses_everything(&self) -> bool {
        self.used.iter().all(|&u| u)
    }

    /// Refuses a mask whose size is not the template's.
    pub fn check_fits(&self, width: u32, height: u32) -> Result<(), MaskError> {
        if (self.width, self.height) == (width, height) {
            Ok(())
        } else {
            Err(MaskError::Size {
                mask_width: self.width,
                mask_height: self.height,
                width,
                height,
            })
        }
    }

    /// The mask as an 8-bit grey PNG (0 = ignore, 255 = use): how it is stored and returned.
    pub fn to_png(&self) -> Vec<u8> {
        let pixels: Vec<u8> = self.used.iter().map(|&u| if u { 255 } else { 0 }).collect();
        let mut png = Vec::new();
        image::GrayImage::from_raw(self.width, self.height, pixels)
            .expect("one byte per pixel")
            .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
            .expect("encoding a PNG in memory cannot fail");
        png
    }

    /// `gray` with every ignored pixel NaN (see the module doc).
    pub fn applied_to(&self, gray: &GrayImage32) -> GrayImage32 {
        let mut out = gray.clone();
        for (value, &used) in out.values.iter_mut().zip(&self.used) {
            if !used {
                *value = f32::NAN;
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_mask_of_another_size_or_without_enough_used_pixels_is_refused() {
        let mask = TemplateMask::new(8, 8, vec![true; 64]).unwrap();
        assert!(mask.check_fits(8, 8).is_ok());
        let wrong = mask.check_fits(9, 8).unwrap_err().to_string();
        assert!(wrong.contains("8x8") && wrong.contains("9x8"), "{wrong}");
        let empty = TemplateMask::new(8, 8, vec![false; 64]).unwrap_err();
        assert_eq!(empty, MaskError::TooFewUsed { used: 0 });
        let black = RgbImage32::new(8, 8, vec![0.0; 8 * 8 * 3]);
        assert!(TemplateMask::from_image(&black).is_err());
    }

    #[test]
    fn the_verification_sees_nan_where_ignored_and_the_mask_survives_its_png() {
        let used: Vec<bool> = (0..16 * 4).map(|i| i % 16 < 8).collect();
        let mask = TemplateMask::new(16, 4, used).unwrap();
        let template = RgbImage32::new(
            16,
            4,
            (0..16 * 4)
                .flat_map(|i| {
                    let v = if i % 16 < 8 { 0.2 } else { 0.9 };
                    [v, v, v]
                })
                .collect(),
        );
        let gray = mask.applied_to(&GrayImage32::from_rgb(&template));
        for (i, v) in gray.values.iter().enumerate() {
            assert_eq!(v.is_nan(), i % 16 >= 8, "pixel {i}");
        }
        let png = mask.to_png();
        let back = crate::imaging::decode_image(&png, "mask", Default::default()).unwrap();
        assert_eq!(TemplateMask::from_image(&back).unwrap(), mask);
    }
}
