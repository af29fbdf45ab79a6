//! PoseMatch: find a registered template in camera images and return every instance's in-plane
//! pose (centre, rotation, two scales, score), using the TDCM network.
//!
//! Layers, lowest first: [`model`] (burn network, weights), [`imaging`] (decode, normalise,
//! resize), [`geometry`] (pose convention, rotated boxes), [`refine`] (refinement and
//! verification on the image), [`matcher`] (images in, poses out), [`engine`] (template
//! registry, batching model thread), [`grpc`] (transport) and [`cli`] on top. Beside them:
//! [`synth`] (pairs with known truth), [`evaluation`] (the paper's metrics) and [`train`]
//! (training on the CPU).

pub mod cli;
pub mod engine;
pub mod evaluation;
pub mod geometry;
pub mod grpc;
pub mod imaging;
pub mod matcher;
pub mod model;
pub mod refine;
pub mod synth;
pub mod train;
