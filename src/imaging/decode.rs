//! Decoding any format the `image` crate reads (PNG, JPEG, BMP, TIFF, PNM; 8/16-bit grey, RGB,
//! RGBA) into one float RGB representation. A hostile file cannot make us allocate: the header is
//! read with a small memory allowance (a huge ICC profile or text chunk is refused there), its
//! size is checked against [`ImageLimits`], and only then is the image decoded, with an allowance
//! of the announced size.

use std::io::Cursor;
use std::path::Path;

use image::{ImageReader, Limits};

use super::RgbImage32;

/// Memory the header pass may use (metadata chunks such as ICC profiles and text included).
const HEADER_MAX_ALLOC: u64 = 4 << 20;

/// Bounds on what we agree to decode.
#[derive(Debug, Clone, Copy)]
pub struct ImageLimits {
    /// Largest accepted `width * height`.
    pub max_pixels: u64,
    /// Smallest accepted side.
    pub min_side: u32,
    /// Largest accepted side.
    pub max_side: u32,
}

impl Default for ImageLimits {
    fn default() -> Self {
        // 40 megapixels: the largest industrial frames we promise to handle.
        Self {
            max_pixels: 40_000_000,
            min_side: 1,
            max_side: u32::MAX,
        }
    }
}

impl ImageLimits {
    /// Checks a size (from a header or a raw buffer's fields) before any pixel buffer exists.
    pub fn check(&self, what: &str, width: u32, height: u32) -> Result<(), DecodeError> {
        let what = what.to_owned();
        let pixels = width as u64 * height as u64;
        if width > self.max_side || height > self.max_side {
            return Err(DecodeError::SideTooLong {
                what,
                width,
                height,
                max_side: self.max_side,
            });
        }
        if pixels > self.max_pixels {
            return Err(DecodeError::TooLarge {
                what,
                width,
                height,
                pixels,
                limit: self.max_pixels,
            });
        }
        if width < self.min_side || height < self.min_side {
            return Err(DecodeError::TooSmall {
                what,
                width,
                height,
                min_side: self.min_side,
            });
        }
        Ok(())
    }
}

#[derive(Debug, thiserror::Error)]
pub enum DecodeError {
    #[error("{what}: the image data is empty")]
    Empty { what: String },
    #[error("{what}: cannot read the file: {source}")]
    Io {
        what: String,
        #[source]
        source: std::io::Error,
    },
    #[error("{what}: not a supported image (PNG, JPEG, BMP, TIFF, PNM expected): {message}")]
    Unsupported { what: String, message: String },
    #[error(
        "{what}: the header says {width}x{height} = {pixels} pixels, above the limit of {limit}; crop or downscale the image"
    )]
    TooLarge {
        what: String,
        width: u32,
        height: u32,
        pixels: u64,
        limit: u64,
    },
    #[error(
        "{what}: the header says {width}x{height}; each side must be at most {max_side} pixels; crop or downscale the image"
    )]
    SideTooLong {
        what: String,
        width: u32,
        height: u32,
        max_side: u32,
    },
    #[error("{what}: {width}x{height} is too small; each side must be at least {min_side} pixels")]
    TooSmall {
        what: String,
        width: u32,
        height: u32,
        min_side: u32,
    },
    #[error("{what}: the image is corrupt or truncated: {message}")]
    Corrupt { what: String, message: String },
    #[error(
        "{what}: decoding would need more memory than an image of its size ({message}); strip large metadata (ICC profile, text chunks) or re-encode it"
    )]
    TooMuchMemory { what: String, message: String },
}

/// Reads and decodes an image file. `what` names it in errors ("template", "image", a path).
pub fn decode_image_file(path: &Path, limits: ImageLimits) -> Result<RgbImage32, DecodeError> {
    let what = path.display().to_string();
    let bytes = std::fs::read(path).map_err(|source| DecodeError::Io {
        what: what.clone(),
        source,
    })?;
    decode_image(&bytes, &what, limits)
}

/// Decodes encoded bytes, checking the header's size against `limits` before decoding.
pub fn decode_image(
    bytes: &[u8],
    what: &str,
    limits: ImageLimits,
) -> Result<RgbImage32, DecodeError> {
    Ok(RgbImage32::from_dynamic(&decode_dynamic(
        bytes, what, limits,
    )?))
}

/// [`decode_image`], and which pixels are opaque (alpha at least half) where the image has an
/// alpha channel with a pixel that is not: a template drawn with its don't-care area
/// transparent. `None` for images without alpha or wholly opaque ones.
pub fn decode_image_and_opacity(
    bytes: &[u8],
    what: &str,
    limits: ImageLimits,
) -> Result<(RgbImage32, Option<Vec<bool>>), DecodeError> {
    let image = decode_dynamic(bytes, what, limits)?;
    let opaque = image.color().has_alpha().then(|| {
        image
            .to_luma_alpha32f()
            .pixels()
            .map(|p| p.0[1] >= 0.5)
            .collect::<Vec<bool>>()
    });
    let opaque = opaque.filter(|o| o.iter().any(|&opaque| !opaque));
    Ok((RgbImage32::from_dynamic(&image), opaque))
}

fn decode_dynamic(
    bytes: &[u8],
    what: &str,
    limits: ImageLimits,
) -> Result<image::DynamicImage, DecodeError> {
    let what = what.to_owned();
    if bytes.is_empty() {
        return Err(DecodeError::Empty { what });
    }
    let unsupported = |message: String| DecodeError::Unsupported {
        what: what.clone(),
        message,
    };
    let reader = || {
        ImageReader::new(Cursor::new(bytes))
            .with_guessed_format()
            .map_err(|e| unsupported(e.to_string()))
    };
    let mut probe = reader()?;
    if probe.format().is_none() {
        return Err(unsupported("unrecognised file signature".into()));
    }
    let failed = |e: image::ImageError| match e {
        image::ImageError::Unsupported(_) => unsupported(e.to_string()),
        image::ImageError::Limits(_) => DecodeError::TooMuchMemory {
            what: what.clone(),
            message: e.to_string(),
        },
        _ => DecodeError::Corrupt {
            what: what.clone(),
            message: e.to_string(),
        },
    };
    let mut header_limits = Limits::default();
    header_limits.max_alloc = Some(HEADER_MAX_ALLOC);
    probe.limits(header_limits);
    let (width, height) = probe.into_dimensions().map_err(failed)?;
    limits.check(&what, width, height)?;
    let pixels = width as u64 * height as u64;
    let mut reader = reader()?;
    let mut decode_limits = Limits::default();
    decode_limits.max_image_width = Some(width);
    decode_limits.max_image_height = Some(height);
    // Room for a 16-bit RGBA decode of the announced size, and no more.
    decode_limits.max_alloc = Some(pixels * 8 + HEADER_MAX_ALLOC);
    reader.limits(decode_limits);
    reader.decode().map_err(failed)
}
