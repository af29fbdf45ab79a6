//! Images in: decoding with limits checked from the header before any pixel is allocated,
//! conversion to the network's planar float input under either input convention, and resizing.

mod decode;
mod tensor;

pub use decode::{DecodeError, ImageLimits, RgbImage32, decode_image, decode_image_file};
pub use tensor::{InputConvention, resize_rgb, to_network_input};
