//! What a template and a search image may be, checked from their headers before any pixel is
//! decoded.

use crate::imaging::ImageLimits;

/// Smallest template side we accept (the network sees it on a 36x36 grid; below this there is
/// nothing to match).
pub const MIN_TEMPLATE_SIDE: u32 = 8;
/// Largest template side we accept.
pub const MAX_TEMPLATE_SIDE: u32 = 512;
/// Smallest search image side.
pub const MIN_IMAGE_SIDE: u32 = 32;

/// What a template image may be, checked from its header before any pixel is decoded.
pub const TEMPLATE_LIMITS: ImageLimits = ImageLimits {
    max_pixels: MAX_TEMPLATE_SIDE as u64 * MAX_TEMPLATE_SIDE as u64,
    min_side: MIN_TEMPLATE_SIDE,
    max_side: MAX_TEMPLATE_SIDE,
};

/// What a search image may be: at least [`MIN_IMAGE_SIDE`] a side, at most `max_pixels`.
pub fn search_limits(max_pixels: u64) -> ImageLimits {
    ImageLimits {
        max_pixels,
        min_side: MIN_IMAGE_SIDE,
        max_side: u32::MAX,
    }
}
