//! PoseMatch: find a registered template in camera images and return every instance's in-plane
//! pose (centre, rotation, two scales, score), using the TDCM network.
//!
//! Layers, lowest first: [`model`] (the network: burn modules and a CPU implementation, weights),
//! [`imaging`] (image files, normalisation, resizing), [`geometry`] (pose convention, rotated
//! boxes), [`refine`] (scoring, alignment and pose refinement on the image), [`matcher`]
//! (images in, poses out: network proposals, verification, classical fallback, selection),
//! [`engine`] (template registry and store, the model thread), [`grpc`] (transport), [`http`]
//! (the same API as JSON, the setup page) and [`cli`]
//! on top. Beside them: [`synth`] (pairs with known truth), [`evaluation`] (the paper's
//! metrics) and [`train`] (training on the CPU). One word, one meaning: `docs/glossary.md`.

pub mod cli;
pub mod config;
pub mod engine;
pub mod evaluation;
pub mod geometry;
pub mod grpc;
pub mod http;
pub mod imaging;
pub mod matcher;
pub mod model;
pub mod refine;
pub mod synth;
pub mod train;
pub mod world;

/// What unit tests share.
#[cfg(test)]
mod test_support {
    use std::io::Write;

    /// Reports a test that cannot run on this machine (a CPU without the instructions it
    /// tests). Written to the process's stderr directly, not through `eprintln!`, which the test
    /// harness captures: `cargo test` shows the line even though the test passes. Not a failure
    /// in CI either: hardware is not a dependency CI can install.
    pub(crate) fn cannot_run(why: &str) {
        let thread = std::thread::current();
        let test = thread.name().unwrap_or("a test");
        let _ = writeln!(std::io::stderr().lock(), "SKIPPED {test}: {why}");
    }
}
