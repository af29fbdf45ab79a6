//! Images in: decoding with limits checked from the header before any pixel is allocated,
//! conversion to the network's planar float input under either input convention, resizing,
//! padding, blurring, and the grey float image with its filters (sampling, downsampling, blur,
//! gradients). Image operations live here, not in the stages that use them.

mod decode;
mod gray;
mod rgb;
mod tensor;

pub use decode::{
    DecodeError, ImageLimits, decode_image, decode_image_and_opacity, decode_image_file,
};
pub use gray::{BilinearTap, GrayImage32, gaussian_blur, gradients};
pub use rgb::{RgbImage32, bilinear_rgb8, blur_121, pad_to_min_side};
pub use tensor::{InputConvention, resize_rgb, to_network_input};
