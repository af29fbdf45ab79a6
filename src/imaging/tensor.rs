//! From pixels to network input: resizing (fast_image_resize, antialiased when shrinking) and
//! normalisation under the two input conventions the official checkpoint knows.

use burn::prelude::*;
use fast_image_resize::images::{Image, ImageRef};
use fast_image_resize::{FilterType, PixelType, ResizeAlg, ResizeOptions, Resizer};

use super::RgbImage32;
use super::rgb::luma;

/// How pixels become network input values. Written `imagenet` or `gray` (`grey`) in flags and
/// settings; this is the one parser of those words.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Deserialize, serde::Serialize)]
#[serde(try_from = "String", into = "String")]
pub enum InputConvention {
    /// The authors' training convention: RGB, ImageNet mean/std. Finds clearly more objects
    /// with the official checkpoint (reference README), so it is the default.
    #[default]
    ImagenetRgb,
    /// The authors' `test.py` demo: grey replicated to 3 channels, `(v - 0.5) / 0.5`.
    Gray,
}

impl std::str::FromStr for InputConvention {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "imagenet" => Ok(Self::ImagenetRgb),
            "gray" | "grey" => Ok(Self::Gray),
            other => Err(format!(
                "unknown input convention `{other}`: use \"imagenet\" or \"gray\""
            )),
        }
    }
}

impl From<InputConvention> for String {
    fn from(convention: InputConvention) -> Self {
        match convention {
            InputConvention::ImagenetRgb => "imagenet",
            InputConvention::Gray => "gray",
        }
        .into()
    }
}

impl TryFrom<String> for InputConvention {
    type Error = String;

    fn try_from(s: String) -> Result<Self, String> {
        s.parse()
    }
}

const IMAGENET_MEAN: [f32; 3] = [0.485, 0.456, 0.406];
const IMAGENET_STD: [f32; 3] = [0.229, 0.224, 0.225];

impl InputConvention {
    /// Planar `[3, h, w]` values for one image (rows in parallel: a large frame's input is
    /// tens of megabytes).
    pub fn normalise(self, image: &RgbImage32) -> Vec<f32> {
        use rayon::prelude::*;
        let (w, n) = (
            image.width as usize,
            image.width as usize * image.height as usize,
        );
        let mut planar = vec![0.0f32; 3 * n];
        if n == 0 {
            return planar;
        }
        let (mean, std, gray) = match self {
            Self::ImagenetRgb => (IMAGENET_MEAN, IMAGENET_STD, false),
            Self::Gray => ([0.5; 3], [0.5; 3], true),
        };
        planar.par_chunks_mut(n).enumerate().for_each(|(c, plane)| {
            plane
                .par_chunks_mut(w)
                .zip(image.pixels.par_chunks(3 * w))
                .for_each(|(out, pixels)| {
                    for (o, p) in out.iter_mut().zip(pixels.chunks_exact(3)) {
                        let v = if gray { luma(p) } else { p[c] };
                        *o = (v - mean[c]) / std[c];
                    }
                });
        });
        planar
    }
}

/// Stacks same-sized images into a `[batch, 3, h, w]` tensor.
pub fn to_network_input(
    images: &[&RgbImage32],
    convention: InputConvention,
    device: &Device,
) -> Tensor<4> {
    let (w, h) = (images[0].width as usize, images[0].height as usize);
    let mut data = Vec::with_capacity(images.len() * 3 * w * h);
    for image in images {
        assert!(image.width as usize == w && image.height as usize == h);
        data.extend(convention.normalise(image));
    }
    Tensor::from_data(TensorData::new(data, [images.len(), 3, h, w]), device)
}

/// Resizes to exactly `width x height` (bilinear; antialiased when shrinking). A same-size
/// request returns a copy without resampling.
pub fn resize_rgb(image: &RgbImage32, width: u32, height: u32) -> RgbImage32 {
    if image.width == width && image.height == height {
        return image.clone();
    }
    // Both images are viewed in place as bytes: no conversion copies of a frame that can be
    // tens of megabytes.
    let src = ImageRef::new(
        image.width,
        image.height,
        bytemuck::cast_slice(&image.pixels),
        PixelType::F32x3,
    )
    .expect("buffer length and alignment match the image; this is a bug");
    let mut pixels = vec![0f32; width as usize * height as usize * 3];
    {
        let mut dst = Image::from_slice_u8(
            width,
            height,
            bytemuck::cast_slice_mut(&mut pixels),
            PixelType::F32x3,
        )
        .expect("buffer length and alignment match the image; this is a bug");
        let options = ResizeOptions::new().resize_alg(ResizeAlg::Convolution(FilterType::Bilinear));
        Resizer::new()
            .resize(&src, &mut dst, &options)
            .expect("same pixel type on both sides; this is a bug");
    }
    RgbImage32::new(width, height, pixels)
}
