//! Why a search cannot run: bad sizes, a search beyond its compute budget. Every message says
//! what the caller should change.

use super::limits::{MAX_TEMPLATE_SIDE, MIN_IMAGE_SIDE, MIN_TEMPLATE_SIDE};

#[derive(Debug, thiserror::Error)]
pub enum MatchError {
    #[error(
        "template is {width}x{height}; each side must be between {MIN_TEMPLATE_SIDE} and {MAX_TEMPLATE_SIDE} pixels"
    )]
    TemplateSize { width: u32, height: u32 },
    #[error("search image is {width}x{height}; each side must be at least {MIN_IMAGE_SIDE} pixels")]
    ImageTooSmall { width: u32, height: u32 },
    #[error(
        "template ({tw}x{th}) is larger than the search image ({iw}x{ih}); pass a larger image or register a smaller template"
    )]
    TemplateLargerThanImage { tw: u32, th: u32, iw: u32, ih: u32 },
    #[error(
        "matching a {tw}x{th} template in a {iw}x{ih} image at scales {lo}..{hi} needs {pixels} network pixels, over the budget of {budget} per request; narrow the scale range (scale_min/scale_max) or search a smaller region (roi)"
    )]
    TooMuchWork {
        tw: u32,
        th: u32,
        iw: u32,
        ih: u32,
        lo: f32,
        hi: f32,
        pixels: u64,
        budget: u64,
    },
    #[error(
        "the classical matcher would score {scorings} template placements here (limit {limit}); crop the image (roi), narrow the angle or scale range, or use the network (method tdcm)"
    )]
    ClassicalTooSlow { scorings: u64, limit: u64 },
    #[error(transparent)]
    Mask(#[from] super::template_mask::MaskError),
}
