//! How a search image is presented to the network: the rescale factor that puts the expected
//! objects at the scale the network was trained for, and the tiles that keep memory bounded.
//!
//! # Scale normalisation
//! The template is resized (anisotropically) to the 36x36 network grid, as in training. The
//! search image is resized *isotropically* by `f = 36 / sqrt(tw·th) / sqrt(lo·hi)`, so that an
//! object at the geometric middle of the requested scale range `[lo, hi]` (default: 1) appears
//! with the template's area on the 36-pixel grid, where the scale heads (0.5–2.0) are centred.
//! Isotropic, because an anisotropic resize would shear rotated objects. Poses are mapped back
//! with the exact per-axis factors actually used (`W'/W`, `H'/H`), and scales are reported
//! relative to the registered template size. A requested range wider than the heads can express
//! in one pass (ratio > 3) is split into several passes at different `f`.
//!
//! # Tiling
//! Up to [`max_whole_pixels`] network pixels run as one piece. Larger inputs run as equal tiles
//! of side at most [`TILE`] that overlap by `2 x` [`TILE_MARGIN`]; each tile owns only the peaks
//! in its core, so every object centre is read in a tile that holds the whole object (an object
//! at the top of the scale range spans at most 2·36·√2 ≈ 102 px, so a 64 px margin covers half of
//! it). GRN normalises over the whole feature map, so tiles see slightly different features than
//! one full pass would; `tests/matching.rs` measures what that costs.

use crate::model::{Precision, TEMPLATE_GRID};

/// Overlap on each side of a tile's core.
pub const TILE_MARGIN: usize = 64;
/// Inputs up to this many network pixels run whole (2048x2048) when the products run in bf16.
/// The activations a forward pass keeps (in the pool, from one frame to the next) are about
/// 0.12 KB per network pixel then — the backbone's 384 hidden channels at a sixteenth of the
/// pixels in bf16 are the largest — so this bounds them near 500 MB.
pub const MAX_WHOLE_PIXELS_BF16: usize = 2048 * 2048;
/// The same for f32 products (1448x1448): about 0.2 KB per network pixel, near 420 MB.
pub const MAX_WHOLE_PIXELS_F32: usize = 1448 * 1448;
/// Largest network piece of a search with a time limit (`MatchOptions::timeout_ms`): the
/// limit is checked between pieces, so this bounds how late an answer may come. A 2048x2048
/// frame is then 4 tiles instead of one whole input (their overlap costs about 15 % more
/// network time).
pub const TIMED_TILE_PIXELS: usize = 1024 * 1024;

/// Inputs up to this many network pixels run whole; larger ones run as tiles. A whole input
/// costs the fewest network pixels (tiles overlap by `2 x` [`TILE_MARGIN`]: a 1930² input
/// in 9 tiles is 30 % more pixels) and sees GRN's whole-image statistics.
pub fn max_whole_pixels(precision: Precision) -> usize {
    match precision {
        Precision::Bf16 => MAX_WHOLE_PIXELS_BF16,
        Precision::F32 | Precision::Auto => MAX_WHOLE_PIXELS_F32,
    }
}
/// Refuse a search that would need more network pixels than this (a tiny template on a huge
/// frame): minutes of CPU that nobody asked for. The service's `max_network_pixels` budget is
/// tighter and must not exceed it.
pub const MAX_NETWORK_PIXELS: u64 = 64_000_000;
/// Smallest network input side; smaller inputs are padded by edge replication.
pub const MIN_INPUT_SIDE: usize = 40;
/// Largest ratio `hi / lo` one pass covers.
const MAX_PASS_RATIO: f32 = 3.0;

/// One rescaling of the search image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScalePass {
    /// Network input size before padding.
    pub width: usize,
    pub height: usize,
    /// Exact factors `width / W`, `height / H`.
    pub factor_x: f32,
    pub factor_y: f32,
}

/// A window of a pass's network input and the part of it whose peaks it owns.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Tile {
    pub x0: usize,
    pub y0: usize,
    pub width: usize,
    pub height: usize,
    /// Owned core, in pass coordinates, half-open.
    pub core_x: (usize, usize),
    pub core_y: (usize, usize),
}

/// The isotropic factor for a template of `tw x th` and an expected scale range.
pub fn scale_factor(template_grid: usize, tw: u32, th: u32, lo: f32, hi: f32) -> f32 {
    template_grid as f32 / ((tw as f32 * th as f32).sqrt() * (lo * hi).sqrt())
}

/// Splits `[lo, hi]` into geometric sub-ranges of ratio at most [`MAX_PASS_RATIO`].
pub fn split_scale_range(lo: f32, hi: f32) -> Vec<(f32, f32)> {
    let passes = ((hi / lo).ln() / MAX_PASS_RATIO.ln()).ceil().max(1.0) as usize;
    let step = (hi / lo).powf(1.0 / passes as f32);
    (0..passes)
        .map(|k| (lo * step.powi(k as i32), lo * step.powi(k as i32 + 1)))
        .collect()
}

/// Objects' size on the network grid relative to the template grid that the service and the
/// CLI use: the size the network was trained around.
pub const DEFAULT_GRID_SCALE: f32 = 1.0;

/// The passes that show a `iw x ih` image to the network for a `tw x th` template whose objects
/// are expected at scales `lo..hi`, shown at `grid_scale` times the template's grid size
/// ([`DEFAULT_GRID_SCALE`]; below it the frame is shrunk further, which costs `grid_scale²` of
/// the network pixels; how far recall holds is measured by `cargo bench --bench frames` with
/// `POSEMATCH_BENCH_GRID_SCALES`).
pub fn scale_passes(
    tw: u32,
    th: u32,
    iw: u32,
    ih: u32,
    lo: f32,
    hi: f32,
    grid_scale: f32,
) -> Vec<ScalePass> {
    split_scale_range(lo, hi)
        .into_iter()
        .map(|(a, b)| {
            scale_pass(
                iw,
                ih,
                grid_scale * scale_factor(TEMPLATE_GRID, tw, th, a, b),
            )
        })
        .collect()
}

/// Network pixels of a set of passes, padding to [`MIN_INPUT_SIDE`] included: the cost of one
/// search (about 0.5 µs per pixel on two cores at f32, 0.24 at bf16, refinement included;
/// docs/service.md, "Compute budget").
pub fn network_pixels(passes: &[ScalePass]) -> u64 {
    passes
        .iter()
        .map(|p| p.width.max(MIN_INPUT_SIDE) as u64 * p.height.max(MIN_INPUT_SIDE) as u64)
        .sum()
}

/// The pass for an image `W x H` at factor `f`.
pub fn scale_pass(image_width: u32, image_height: u32, f: f32) -> ScalePass {
    let width = ((image_width as f32 * f).round() as usize).max(1);
    let height = ((image_height as f32 * f).round() as usize).max(1);
    ScalePass {
        width,
        height,
        factor_x: width as f32 / image_width as f32,
        factor_y: height as f32 / image_height as f32,
    }
}

/// Tiles covering a `width x height` input. One tile when it has at most `max_whole_pixels`;
/// otherwise the fewest square-budget tiles (side at most `sqrt(max_whole_pixels)`) per axis, all the same size (so they batch
/// together), each owning its core.
pub fn tiles(width: usize, height: usize, max_whole_pixels: usize) -> Vec<Tile> {
    if width * height <= max_whole_pixels {
        return vec![Tile {
            x0: 0,
            y0: 0,
            width,
            height,
            core_x: (0, width),
            core_y: (0, height),
        }];
    }
    // Square tiles of the same pixel budget; at least 4x the margin so cores stay useful.
    let side = (((max_whole_pixels as f64).sqrt() as usize) / 4 * 4).max(4 * TILE_MARGIN);
    let mut out = Vec::new();
    let (ys, xs) = (axis_spans(height, side), axis_spans(width, side));
    for &(y0, h, core_y) in &ys {
        for &(x0, w, core_x) in &xs {
            out.push(Tile {
                x0,
                y0,
                width: w,
                height: h,
                core_x,
                core_y,
            });
        }
    }
    out
}

/// `(start, length, owned core)` of each tile along one axis of length `len`, tiles at most
/// `max_side` long.
fn axis_spans(len: usize, max_side: usize) -> Vec<(usize, usize, (usize, usize))> {
    if len <= max_side {
        return vec![(0, len, (0, len))];
    }
    let inner = len - 2 * TILE_MARGIN;
    let count = inner.div_ceil(max_side - 2 * TILE_MARGIN);
    let core = inner.div_ceil(count);
    // Network inputs are multiples of 4 where possible.
    let side = ((core + 2 * TILE_MARGIN).div_ceil(4) * 4).min(len);
    (0..count)
        .map(|k| {
            let nominal = TILE_MARGIN + k * core;
            let core_start = if k == 0 { 0 } else { nominal };
            let core_end = if k + 1 == count { len } else { nominal + core };
            let start = (nominal - TILE_MARGIN).min(len - side);
            (start, side, (core_start, core_end))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tile_cores_partition_the_input_and_keep_a_margin() {
        for (w, h) in [
            (2048, 2048),
            (1000, 700),
            (3000, 1025),
            (5000, 300),
            (1030, 1030),
        ] {
            let tiles = tiles(w, h, 200_000);
            assert!(tiles.iter().all(|t| t.width <= 444 && t.height <= 444));
            assert!(
                tiles
                    .iter()
                    .all(|t| (t.width, t.height) == (tiles[0].width, tiles[0].height))
            );
            let mut owner = vec![0u8; w * h];
            for t in &tiles {
                assert!(t.x0 + t.width <= w && t.y0 + t.height <= h);
                for y in t.core_y.0..t.core_y.1 {
                    for x in t.core_x.0..t.core_x.1 {
                        owner[y * w + x] += 1;
                    }
                }
                // The core keeps TILE_MARGIN of context except at the input's edges.
                assert!(t.core_x.0 == 0 || t.core_x.0 >= t.x0 + TILE_MARGIN);
                assert!(t.core_x.1 == w || t.core_x.1 + TILE_MARGIN <= t.x0 + t.width);
                assert!(t.core_y.0 == 0 || t.core_y.0 >= t.y0 + TILE_MARGIN);
                assert!(t.core_y.1 == h || t.core_y.1 + TILE_MARGIN <= t.y0 + t.height);
            }
            assert!(owner.iter().all(|&n| n == 1), "{w}x{h}");
        }
    }

    #[test]
    fn scale_factor_centres_the_requested_range() {
        assert_eq!(scale_factor(36, 36, 36, 1.0, 1.0), 1.0);
        assert!((scale_factor(36, 120, 120, 1.0, 1.0) - 0.3).abs() < 1e-6);
        assert!((scale_factor(36, 36, 36, 2.0, 8.0) - 0.25).abs() < 1e-6);
        let parts = split_scale_range(0.25, 4.0);
        assert_eq!(parts.len(), 3);
        assert!((parts[0].0 - 0.25).abs() < 1e-6 && (parts[2].1 - 4.0).abs() < 1e-4);
        assert_eq!(split_scale_range(0.8, 1.5).len(), 1);
    }

    #[test]
    fn grid_scale_shrinks_every_pass() {
        let today = scale_passes(28, 52, 2048, 2048, 1.0, 1.0, DEFAULT_GRID_SCALE);
        assert!((today[0].factor_x - scale_factor(36, 28, 52, 1.0, 1.0)).abs() < 1e-3);
        let half = scale_passes(28, 52, 2048, 2048, 1.0, 1.0, 0.5);
        assert_eq!(half.len(), today.len());
        assert!(half[0].width.abs_diff(today[0].width / 2) <= 1);
        assert!(network_pixels(&half) * 4 <= network_pixels(&today) + 4 * 2048);
    }
}
