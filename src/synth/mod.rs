//! Synthetic template/search pairs with exact ground truth, from any folder of ordinary photos:
//! the paper's Algorithm 1 (crop a box, resize it to the template grid, rotate the image about
//! the box, cut a search window that holds the whole rotated box and no blank border), and a
//! multi-instance set (rotated, scaled copies of one template pasted with a mask into a 4x4 grid).
//! Everything is deterministic from a seed: pair `i` depends only on `(seed, i)`.

pub mod conditions;
mod sampler;

use std::path::{Path, PathBuf};
use std::str::FromStr;

use image::RgbImage;
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use crate::geometry::Pose;
use crate::imaging::{RgbImage32, resize_rgb};
pub use sampler::warp_search_window;

/// Transformation levels of the paper: rotation always U(−180°, 180°), independent scales in a
/// range.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Level {
    /// Rotation only.
    S1,
    /// Scales in 0.8–1.5.
    S1_5,
    /// Scales in 0.5–2.
    S2,
    /// Scales in 0.4–2.5.
    S2_5,
}

impl Level {
    pub fn scale_range(self) -> (f32, f32) {
        match self {
            Self::S1 => (1.0, 1.0),
            Self::S1_5 => (0.8, 1.5),
            Self::S2 => (0.5, 2.0),
            Self::S2_5 => (0.4, 2.5),
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Self::S1 => "S1",
            Self::S1_5 => "S1.5",
            Self::S2 => "S2",
            Self::S2_5 => "S2.5",
        }
    }
}

impl FromStr for Level {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s.to_ascii_uppercase().as_str() {
            "S1" => Ok(Self::S1),
            "S1.5" => Ok(Self::S1_5),
            "S2" => Ok(Self::S2),
            "S2.5" => Ok(Self::S2_5),
            _ => Err(format!("unknown level `{s}`: use S1, S1.5, S2 or S2.5")),
        }
    }
}

/// One pair and its truth. `truth` follows the public pose convention relative to `template`.
#[derive(Debug, Clone)]
pub struct SyntheticPair {
    pub template: RgbImage32,
    pub search: RgbImage32,
    pub truth: Vec<Pose>,
    /// The photo the template was cut from (an index into [`PhotoSet::paths`]), so that results
    /// can be broken down by source.
    pub photo: usize,
}

#[derive(Debug, thiserror::Error)]
pub enum SynthError {
    #[error("{path}: cannot list images: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error(
        "{path}: no usable images (PNG, JPEG, BMP, TIFF, PNM, WebP-free, at least {min_side} px a side) found"
    )]
    NoImages { path: PathBuf, min_side: u32 },
    #[error(
        "could not place a {what} after {tries} tries; use larger photos, smaller templates, or photos with more structure (--min-structure)"
    )]
    Unplaceable { what: String, tries: usize },
}

/// Photos are downscaled to at most this many pixels on the long side: the size of the MS-COCO
/// photos the paper trained and tested on (640x480), so a 36-pixel box holds as much structure
/// as theirs, and a folder of hundreds of 4K wallpapers needs little memory. (Measured with
/// the official checkpoint at S1.5: Succ 26 % at 1024 vs more at 512-640 on plasma wallpapers,
/// where a 36-pixel box at 4K resolution is mostly smooth gradient.)
const MAX_PHOTO_SIDE: u32 = 640;

/// A set of photos to cut pairs from.
pub struct PhotoSet {
    photos: Vec<RgbImage>,
    pub paths: Vec<PathBuf>,
}

impl PhotoSet {
    /// Every decodable image under `dir` (recursively), sorted by path so the set does not
    /// depend on directory order, each downscaled to at most [`MAX_PHOTO_SIDE`].
    pub fn load(dir: &Path, min_side: u32) -> Result<Self, SynthError> {
        let mut files = Vec::new();
        collect_files(dir, &mut files)?;
        files.sort();
        let mut photos = Vec::new();
        let mut paths = Vec::new();
        for path in files {
            let Ok(image) = image::open(&path) else {
                continue;
            };
            let mut rgb = image.to_rgb8();
            let long = rgb.width().max(rgb.height());
            if long > MAX_PHOTO_SIDE {
                let f = MAX_PHOTO_SIDE as f32 / long as f32;
                let (w, h) = (
                    (rgb.width() as f32 * f).round() as u32,
                    (rgb.height() as f32 * f).round() as u32,
                );
                rgb = image::imageops::resize(&rgb, w, h, image::imageops::FilterType::Triangle);
            }
            if rgb.width() >= min_side && rgb.height() >= min_side {
                photos.push(rgb);
                paths.push(path);
            }
        }
        if photos.is_empty() {
            return Err(SynthError::NoImages {
                path: dir.to_owned(),
                min_side,
            });
        }
        Ok(Self { photos, paths })
    }

    pub fn len(&self) -> usize {
        self.photos.len()
    }

    pub fn is_empty(&self) -> bool {
        self.photos.is_empty()
    }

    /// Adds another set's photos after these (several folders as one training set).
    pub fn extend(&mut self, other: PhotoSet) {
        self.photos.extend(other.photos);
        self.paths.extend(other.paths);
    }
}

fn collect_files(dir: &Path, out: &mut Vec<PathBuf>) -> Result<(), SynthError> {
    let io = |source| SynthError::Io {
        path: dir.to_owned(),
        source,
    };
    for entry in std::fs::read_dir(dir).map_err(io)? {
        let path = entry.map_err(io)?.path();
        if path.is_dir() {
            collect_files(&path, out)?;
        } else if path.extension().and_then(|e| e.to_str()).is_some_and(|e| {
            matches!(
                e.to_ascii_lowercase().as_str(),
                "png" | "jpg" | "jpeg" | "bmp" | "tif" | "tiff" | "pnm" | "ppm" | "pgm"
            )
        }) {
            out.push(path);
        }
    }
    Ok(())
}

/// What pairs to make.
#[derive(Debug, Clone, Copy)]
pub struct PairSpec {
    pub level: Level,
    /// Registered template size (the paper: 12x12, 28x52, 36x36, 124x124).
    pub template_width: u32,
    pub template_height: u32,
    /// Search window side (the paper: 224).
    pub search_side: u32,
    /// Least [`template_structure`] a template must have; flatter boxes are drawn again.
    /// [`DEFAULT_MIN_STRUCTURE`] stands in for the paper's object boxes; 0 accepts any box.
    pub min_structure: f32,
}

/// Default least structure of a template (mean gradient magnitude, grey levels per pixel).
///
/// The paper cuts templates from MS-COCO *object* boxes, which always hold an object's edges; a
/// box drawn at random on a wallpaper is often a patch of sky or a smooth gradient that no
/// matcher can localise (nor can any factory template: Halcon refuses a shape model without
/// enough contrast). Measured with the official checkpoint on 100 plasma pairs at S1.5: the
/// network put the centre within 5 px for 4 % of the templates in the flattest quartile
/// (below 1.5) and 44 % / 88 % / 80 % in the others (quartile bounds 5.3 and 9.5). 6 keeps
/// boxes with visible edges or texture and drops flat ones.
pub const DEFAULT_MIN_STRUCTURE: f32 = 6.0;

/// How much structure a template holds: the mean magnitude of its grey-level gradient (forward
/// differences, grey levels 0–255 per pixel).
pub fn template_structure(template: &RgbImage32) -> f32 {
    let (w, h) = (template.width as usize, template.height as usize);
    if w < 2 || h < 2 {
        return 0.0;
    }
    let grey = template.to_gray();
    let mut total = 0.0;
    for y in 0..h - 1 {
        for x in 0..w - 1 {
            let v = grey[y * w + x];
            let gx = grey[y * w + x + 1] - v;
            let gy = grey[(y + 1) * w + x] - v;
            total += (gx * gx + gy * gy).sqrt();
        }
    }
    255.0 * total / ((w - 1) * (h - 1)) as f32
}

const TRIES: usize = 200;

fn rng_for(seed: u64, index: u64) -> StdRng {
    StdRng::seed_from_u64(seed ^ index.wrapping_mul(0x9E37_79B9_7F4A_7C15))
}

fn to_f32(image: &RgbImage) -> RgbImage32 {
    RgbImage32::from_dynamic(&image::DynamicImage::ImageRgb8(image.clone()))
}

/// Pair `index` of the set defined by `(photos, spec, seed)` (Algorithm 1).
pub fn make_pair(
    photos: &PhotoSet,
    spec: &PairSpec,
    seed: u64,
    index: u64,
) -> Result<SyntheticPair, SynthError> {
    let mut rng = rng_for(seed, index);
    let (lo, hi) = spec.level.scale_range();
    let (tw, th) = (spec.template_width, spec.template_height);
    let side = spec.search_side as f32;
    for _ in 0..TRIES {
        let photo_index = rng.random_range(0..photos.len());
        let photo = &photos.photos[photo_index];
        let (pw, ph) = (photo.width(), photo.height());
        let sx = rng.random_range(lo..=hi);
        let sy = rng.random_range(lo..=hi);
        // The box in the photo, in whole pixels; its true scale follows from the rounded size.
        let bw = (sx * tw as f32).round().max(2.0) as u32;
        let bh = (sy * th as f32).round().max(2.0) as u32;
        if bw + 2 > pw || bh + 2 > ph {
            continue;
        }
        let angle: f32 = rng.random_range(-180.0..180.0);
        let (s, c) = angle.to_radians().sin_cos();
        // Half extent of the rotated box in the search window.
        let ex = (bw as f32 * c.abs() + bh as f32 * s.abs()) / 2.0;
        let ey = (bw as f32 * s.abs() + bh as f32 * c.abs()) / 2.0;
        if 2.0 * ex + 2.0 > side || 2.0 * ey + 2.0 > side {
            continue;
        }
        let x0 = rng.random_range(0..=pw - bw);
        let y0 = rng.random_range(0..=ph - bh);
        // Box centre in pixel-centre coordinates.
        let (cx, cy) = (
            x0 as f32 + (bw as f32 - 1.0) / 2.0,
            y0 as f32 + (bh as f32 - 1.0) / 2.0,
        );
        // Where the object centre lands in the window: anywhere that keeps the box inside.
        let xc = rng.random_range(ex..=side - 1.0 - ex);
        let yc = rng.random_range(ey..=side - 1.0 - ey);
        let truth = Pose {
            x: xc,
            y: yc,
            angle_deg: angle,
            scale_x: bw as f32 / tw as f32,
            scale_y: bh as f32 / th as f32,
            score: 1.0,
            network_score: 0.0,
        };
        let Some(search) = warp_search_window(photo, spec.search_side, (cx, cy), &truth) else {
            continue; // the window would show blank border
        };
        let crop = image::imageops::crop_imm(photo, x0, y0, bw, bh).to_image();
        let template = resize_rgb(&to_f32(&crop), tw, th);
        if template_structure(&template) < spec.min_structure {
            continue; // a flat patch, not an object
        }
        return Ok(SyntheticPair {
            template,
            search,
            truth: vec![truth],
            photo: photo_index,
        });
    }
    Err(SynthError::Unplaceable {
        what: format!("{tw}x{th} template at {}", spec.level.name()),
        tries: TRIES,
    })
}

/// Multi-instance image `index`: a 320x320 background cut from one photo, a template (any
/// width and height) cut from another place, and 2–8 copies of it (rotated, independently scaled within the level, masked)
/// in distinct cells of a 4x4 grid, so that no two overlap. The template needs at least
/// `min_structure` (see [`PairSpec::min_structure`]).
pub fn make_multi_instance(
    photos: &PhotoSet,
    level: Level,
    (template_width, template_height): (u32, u32),
    min_structure: f32,
    seed: u64,
    index: u64,
) -> Result<SyntheticPair, SynthError> {
    const SIDE: u32 = 320;
    const CELLS: u32 = 4;
    let cell = (SIDE / CELLS) as f32;
    let mut rng = rng_for(seed ^ 0x005E_ED0F_1A57, index);
    let (lo, hi) = level.scale_range();
    for _ in 0..TRIES {
        let background_photo = &photos.photos[rng.random_range(0..photos.len())];
        let template_index = rng.random_range(0..photos.len());
        let template_photo = &photos.photos[template_index];
        if background_photo.width() < SIDE
            || background_photo.height() < SIDE
            || template_photo.width() < template_width
            || template_photo.height() < template_height
        {
            continue;
        }
        let bx = rng.random_range(0..=background_photo.width() - SIDE);
        let by = rng.random_range(0..=background_photo.height() - SIDE);
        let mut search =
            to_f32(&image::imageops::crop_imm(background_photo, bx, by, SIDE, SIDE).to_image());
        let tx = rng.random_range(0..=template_photo.width() - template_width);
        let ty = rng.random_range(0..=template_photo.height() - template_height);
        let template = to_f32(
            &image::imageops::crop_imm(template_photo, tx, ty, template_width, template_height)
                .to_image(),
        );
        if template_structure(&template) < min_structure {
            continue;
        }
        let count = rng.random_range(2..=8usize);
        let mut cells: Vec<u32> = (0..CELLS * CELLS).collect();
        // Fisher–Yates with our rng, first `count` cells.
        for i in 0..count {
            let j = rng.random_range(i..cells.len());
            cells.swap(i, j);
        }
        let mut truth = Vec::new();
        for &c in &cells[..count] {
            let angle: f32 = rng.random_range(-180.0..180.0);
            let (s, co) = angle.to_radians().sin_cos();
            let mut sx = rng.random_range(lo..=hi);
            let mut sy = rng.random_range(lo..=hi);
            // Keep each rotated copy inside its cell (shrink if the level allows more).
            let (tw, th) = (template_width as f32, template_height as f32);
            let extent = |sx: f32, sy: f32| {
                (sx * tw * co.abs() + sy * th * s.abs()).max(sx * tw * s.abs() + sy * th * co.abs())
            };
            let fit = (cell - 4.0) / extent(sx, sy);
            if fit < 1.0 {
                sx *= fit;
                sy *= fit;
            }
            let half = extent(sx, sy) / 2.0;
            let (cx0, cy0) = ((c % CELLS) as f32 * cell, (c / CELLS) as f32 * cell);
            let slack = (cell / 2.0 - half - 1.0).max(0.0);
            let x = cx0 + cell / 2.0 - 0.5 + rng.random_range(-slack..=slack);
            let y = cy0 + cell / 2.0 - 0.5 + rng.random_range(-slack..=slack);
            let pose = Pose {
                x,
                y,
                angle_deg: angle,
                scale_x: sx,
                scale_y: sy,
                score: 1.0,
                network_score: 0.0,
            };
            sampler::paste(&mut search, &template, &pose);
            truth.push(pose);
        }
        return Ok(SyntheticPair {
            template,
            search,
            truth,
            photo: template_index,
        });
    }
    Err(SynthError::Unplaceable {
        what: "multi-instance scene".into(),
        tries: TRIES,
    })
}

/// A machined part drawn procedurally, `width x height` (the paper's industrial part is
/// 28x52): a brushed body with a large and a small hole and a notch on one side, so that no
/// rotation maps it onto itself. Needs no photos, so benchmarks and tests run anywhere.
pub fn procedural_part(width: u32, height: u32) -> RgbImage32 {
    let (w, h) = (width as f32, height as f32);
    let mut pixels = Vec::with_capacity((width * height * 3) as usize);
    for y in 0..height {
        for x in 0..width {
            let (fx, fy) = (x as f32 + 0.5, y as f32 + 0.5);
            let brushed = 0.62 + 0.05 * (fy * 1.7).sin() + 0.08 * (fx / w - 0.5);
            let hole = |cx: f32, cy: f32, r: f32| (fx - cx).hypot(fy - cy) < r;
            let notch = fx > w * 0.75 && (fy - h * 0.42).abs() < h * 0.08;
            let rim = fx < 1.5 || fy < 1.5 || fx > w - 1.5 || fy > h - 1.5;
            let v = if hole(w * 0.5, h * 0.23, w * 0.16) || notch {
                0.12
            } else if hole(w * 0.5, h * 0.78, w * 0.09) {
                0.2
            } else if rim {
                0.85
            } else {
                brushed
            };
            pixels.extend_from_slice(&[v, v * 0.97, v * 0.9]);
        }
    }
    RgbImage32::new(width, height, pixels)
}

/// A `side x side` frame holding `rows x cols` copies of `part` at scale 1 and any angle, one
/// per cell of a grid with a random offset inside its cell, on a procedural low-contrast
/// background: the paper's industrial case (144 parts on a 2048x2048 frame), with exact truth.
/// Deterministic from `seed`.
pub fn parts_frame(
    part: &RgbImage32,
    side: u32,
    rows: u32,
    cols: u32,
    seed: u64,
) -> (RgbImage32, Vec<Pose>) {
    let mut rng = rng_for(seed ^ 0x0FAB_F4A3, 0);
    let phase: f32 = rng.random_range(0.0..std::f32::consts::TAU);
    let mut pixels = Vec::with_capacity((side * side * 3) as usize);
    for y in 0..side {
        for x in 0..side {
            let (fx, fy) = (x as f32, y as f32);
            let v = 0.35
                + 0.06 * (fx * 0.013 + phase).sin() * (fy * 0.017).cos()
                + 0.03 * ((fx + fy) * 0.11 + phase).sin();
            pixels.extend_from_slice(&[v * 0.95, v, v * 1.05]);
        }
    }
    let frame = RgbImage32::new(side, side, pixels);
    paste_parts(frame, part, rows, cols, &mut rng)
}

/// [`parts_frame`] on `background` (any photo; its size is the frame's): the same part laid out
/// the same way over real clutter, where the procedural background is plain.
pub fn parts_frame_on(
    background: RgbImage32,
    part: &RgbImage32,
    rows: u32,
    cols: u32,
    seed: u64,
) -> (RgbImage32, Vec<Pose>) {
    let mut rng = rng_for(seed ^ 0x0FAB_F4A3, 1);
    paste_parts(background, part, rows, cols, &mut rng)
}

/// A `side x side` circuit board drawn procedurally: green solder mask, copper traces (straight
/// and at 45°), tinned pads and vias, black chip bodies with their pins, white silkscreen
/// outlines. Why: the industrial frame's other background: where the procedural frame is plain
/// and the photos are natural, a board is man-made clutter of straight edges, corners and
/// near-identical repeated shapes, what a part on a line is seen against. Needs no photos, and
/// is deterministic from `seed`.
pub fn circuit_board(side: u32, seed: u64) -> RgbImage32 {
    const MASK: [f32; 3] = [0.08, 0.33, 0.16];
    const COPPER: [f32; 3] = [0.2, 0.48, 0.2];
    const TIN: [f32; 3] = [0.78, 0.77, 0.72];
    const CHIP: [f32; 3] = [0.07, 0.07, 0.08];
    const SILK: [f32; 3] = [0.92, 0.92, 0.88];
    let mut rng = rng_for(seed ^ 0xB0A2_D5EE, 2);
    let n = side as usize;
    let mut pixels = vec![0.0f32; n * n * 3];
    for y in 0..n {
        for x in 0..n {
            let grain = 0.015 * ((x as f32 * 0.21).sin() + (y as f32 * 0.17).cos());
            for (k, c) in MASK.iter().enumerate() {
                pixels[(y * n + x) * 3 + k] = c + grain;
            }
        }
    }
    let fill = |pixels: &mut [f32], x0: i64, y0: i64, x1: i64, y1: i64, colour: [f32; 3]| {
        for y in y0.max(0)..y1.min(n as i64) {
            for x in x0.max(0)..x1.min(n as i64) {
                let at = (y as usize * n + x as usize) * 3;
                pixels[at..at + 3].copy_from_slice(&colour);
            }
        }
    };
    let area = (side as f32 / 1024.0).powi(2);
    // Traces: chains of straight and diagonal runs, each ending on a via.
    for _ in 0..(220.0 * area) as usize {
        let width = rng.random_range(3..10i64);
        let (mut x, mut y) = (
            rng.random_range(0..side as i64),
            rng.random_range(0..side as i64),
        );
        for _ in 0..rng.random_range(2..6) {
            let (dx, dy) =
                [(1, 0), (0, 1), (1, 1), (1, -1), (-1, 0), (0, -1)][rng.random_range(0..6usize)];
            for _ in 0..rng.random_range(20..260) {
                fill(&mut pixels, x, y, x + width, y + width, COPPER);
                x += dx;
                y += dy;
            }
        }
        let r = width + 4;
        fill(&mut pixels, x - r, y - r, x + r + width, y + r + width, TIN);
        fill(
            &mut pixels,
            x - 2,
            y - 2,
            x + width + 2,
            y + width + 2,
            CHIP,
        );
    }
    // Components: a chip body with pins on two or four sides and its silkscreen outline, or a
    // two-pad part (resistor, capacitor).
    for _ in 0..(140.0 * area) as usize {
        let (x, y) = (
            rng.random_range(0..side as i64),
            rng.random_range(0..side as i64),
        );
        if rng.random_bool(0.4) {
            let (w, h) = (rng.random_range(40..140i64), rng.random_range(40..140i64));
            fill(&mut pixels, x - 6, y - 6, x + w + 6, y + h + 6, SILK);
            fill(&mut pixels, x - 4, y - 4, x + w + 4, y + h + 4, MASK);
            let four = rng.random_bool(0.5);
            let mut pin = 6;
            while pin + 4 < w {
                fill(&mut pixels, x + pin, y - 12, x + pin + 4, y, TIN);
                fill(&mut pixels, x + pin, y + h, x + pin + 4, y + h + 12, TIN);
                pin += 10;
            }
            let mut pin = 6;
            while four && pin + 4 < h {
                fill(&mut pixels, x - 12, y + pin, x, y + pin + 4, TIN);
                fill(&mut pixels, x + w, y + pin, x + w + 12, y + pin + 4, TIN);
                pin += 10;
            }
            fill(&mut pixels, x, y, x + w, y + h, CHIP);
        } else {
            let (long, short) = (rng.random_range(16..40i64), rng.random_range(8..18i64));
            let (w, h) = if rng.random_bool(0.5) {
                (long, short)
            } else {
                (short, long)
            };
            fill(&mut pixels, x - 3, y - 3, x + w + 3, y + h + 3, SILK);
            fill(&mut pixels, x - 1, y - 1, x + w + 1, y + h + 1, MASK);
            let pad = (w.min(h) * 2 / 3).max(4);
            if w > h {
                fill(&mut pixels, x, y, x + pad, y + h, TIN);
                fill(&mut pixels, x + w - pad, y, x + w, y + h, TIN);
            } else {
                fill(&mut pixels, x, y, x + w, y + pad, TIN);
                fill(&mut pixels, x, y + h - pad, x + w, y + h, TIN);
            }
        }
    }
    RgbImage32::new(side, side, pixels)
}

/// Pastes `rows x cols` copies of `part` into `frame`, one per grid cell (see [`parts_frame`]).
fn paste_parts(
    mut frame: RgbImage32,
    part: &RgbImage32,
    rows: u32,
    cols: u32,
    rng: &mut impl Rng,
) -> (RgbImage32, Vec<Pose>) {
    let (cell_w, cell_h) = (
        frame.width as f32 / cols as f32,
        frame.height as f32 / rows as f32,
    );
    let reach = (part.width as f32).hypot(part.height as f32) / 2.0 + 2.0;
    let mut truth = Vec::with_capacity((rows * cols) as usize);
    for r in 0..rows {
        for c in 0..cols {
            let slack_x = (cell_w / 2.0 - reach).max(0.0);
            let slack_y = (cell_h / 2.0 - reach).max(0.0);
            let pose = Pose {
                x: (c as f32 + 0.5) * cell_w - 0.5 + rng.random_range(-slack_x..=slack_x),
                y: (r as f32 + 0.5) * cell_h - 0.5 + rng.random_range(-slack_y..=slack_y),
                angle_deg: rng.random_range(-180.0..180.0),
                scale_x: 1.0,
                scale_y: 1.0,
                score: 1.0,
                network_score: 0.0,
            };
            sampler::paste(&mut frame, part, &pose);
            truth.push(pose);
        }
    }
    (frame, truth)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_circuit_board_is_deterministic_and_holds_mask_copper_tin_and_chips() {
        let board = circuit_board(512, 3);
        assert_eq!(board.pixels, circuit_board(512, 3).pixels);
        assert_ne!(board.pixels, circuit_board(512, 4).pixels);
        let share = |colour: [f32; 3]| {
            board
                .pixels
                .chunks_exact(3)
                .filter(|p| p.iter().zip(colour).all(|(a, b)| (a - b).abs() < 0.04))
                .count() as f32
                / (512.0 * 512.0)
        };
        // Mostly solder mask, with every other kind of surface present.
        assert!(share([0.08, 0.33, 0.16]) > 0.3);
        for colour in [[0.2, 0.48, 0.2], [0.78, 0.77, 0.72], [0.07, 0.07, 0.08]] {
            assert!(share(colour) > 0.005, "{colour:?}: {}", share(colour));
        }
    }

    /// A folder with two synthetic "photos" (smooth textures).
    fn photo_dir() -> tempfile::TempDir {
        let dir = tempfile::tempdir().unwrap();
        for (k, (w, h)) in [(640u32, 480u32), (500, 700)].into_iter().enumerate() {
            let image = RgbImage::from_fn(w, h, |x, y| {
                let (fx, fy) = (x as f32 + 37.0 * k as f32, y as f32);
                let v = |a: f32, b: f32| {
                    (127.0
                        + 60.0 * (fx * a).sin() * (fy * b).cos()
                        + 50.0 * ((fx * b - fy * a) * 0.7).sin()) as u8
                };
                image::Rgb([v(0.05, 0.08), v(0.09, 0.03), v(0.02, 0.11)])
            });
            image
                .save(dir.path().join(format!("photo{k}.png")))
                .unwrap();
        }
        dir
    }

    /// Mean absolute difference between the template and the search sampled at the truth.
    fn truth_residual(pair: &SyntheticPair, truth: &Pose) -> f32 {
        let (tw, th) = (pair.template.width as usize, pair.template.height as usize);
        let mut total = 0.0;
        let mut count = 0;
        // Inner pixels only: the template was resampled (antialiased) from the box.
        for b in 2..th - 2 {
            for a in 2..tw - 2 {
                let (x, y) = truth.map_point(
                    a as f32 - (tw as f32 - 1.0) / 2.0,
                    b as f32 - (th as f32 - 1.0) / 2.0,
                );
                let s = pair.search.sample(x, y);
                let t = &pair.template.pixels[(b * tw + a) * 3..(b * tw + a) * 3 + 3];
                total += (0..3).map(|k| (s[k] - t[k]).abs()).sum::<f32>() / 3.0;
                count += 1;
            }
        }
        total / count as f32
    }

    #[test]
    fn pairs_are_deterministic_and_their_truth_is_exact() {
        let dir = photo_dir();
        let photos = PhotoSet::load(dir.path(), 224).unwrap();
        let spec = PairSpec {
            level: Level::S1_5,
            template_width: 28,
            template_height: 52,
            search_side: 224,
            // The smooth test photos (about 3-5 grey levels per pixel) keep the truth check
            // exact under resampling; the criterion itself is tested below.
            min_structure: 1.0,
        };
        for index in 0..8 {
            let a = make_pair(&photos, &spec, 7, index).unwrap();
            let b = make_pair(&photos, &spec, 7, index).unwrap();
            assert_eq!(a.truth, b.truth);
            assert_eq!(a.search.pixels, b.search.pixels);
            let t = a.truth[0];
            assert!(
                (0.8..=1.5 + 0.02).contains(&t.scale_x) && (0.8..=1.5 + 0.02).contains(&t.scale_y),
                "{t:?}"
            );
            let residual = truth_residual(&a, &t);
            assert!(
                residual < 0.03,
                "pair {index}: template and search disagree at the truth ({residual})"
            );
            // A wrong pose does not fit: the check above can fail.
            let wrong = Pose {
                angle_deg: t.angle_deg + 20.0,
                ..t
            };
            assert!(truth_residual(&a, &wrong) > 2.0 * residual);
        }
        assert_ne!(
            make_pair(&photos, &spec, 8, 0).unwrap().truth,
            make_pair(&photos, &spec, 7, 0).unwrap().truth
        );
    }

    #[test]
    fn multi_instance_truth_is_exact_and_disjoint() {
        let dir = photo_dir();
        let photos = PhotoSet::load(dir.path(), 320).unwrap();
        // Square and elongated templates alike.
        for (w, h) in [(36u32, 36u32), (28, 52)] {
            let pair = make_multi_instance(&photos, Level::S1_5, (w, h), 1.0, 3, 0).unwrap();
            assert_eq!((pair.template.width, pair.template.height), (w, h));
            assert!((2..=8).contains(&pair.truth.len()));
            for t in &pair.truth {
                assert!(truth_residual(&pair, t) < 0.03);
                for (x, y) in t.corners(w as f32, h as f32) {
                    assert!(
                        (0.0..320.0).contains(&x) && (0.0..320.0).contains(&y),
                        "{t:?}"
                    );
                }
            }
            let (w, h) = (w as f32, h as f32);
            for (i, a) in pair.truth.iter().enumerate() {
                for b in &pair.truth[i + 1..] {
                    let iou = crate::geometry::rotated_iou(&a.corners(w, h), &b.corners(w, h));
                    assert_eq!(iou, 0.0);
                }
            }
        }
    }

    #[test]
    fn structure_tells_flat_patches_from_objects() {
        let flat = RgbImage32 {
            width: 36,
            height: 36,
            pixels: vec![0.4; 36 * 36 * 3],
        };
        assert_eq!(template_structure(&flat), 0.0);
        // A vertical step of 0.5 in every row: one edge pixel in 35 columns of differences.
        let mut step = flat.clone();
        for y in 0..36 {
            for x in 18..36 {
                step.pixels[(y * 36 + x) * 3..(y * 36 + x) * 3 + 3].fill(0.9);
            }
        }
        let expected = 255.0 * 0.5 / 35.0;
        assert!((template_structure(&step) - expected).abs() < 1e-3);

        // Photos of one flat colour yield no pair under the default, and any box under 0.
        let dir = tempfile::tempdir().unwrap();
        RgbImage::from_pixel(400, 300, image::Rgb([90, 120, 200]))
            .save(dir.path().join("sky.png"))
            .unwrap();
        let photos = PhotoSet::load(dir.path(), 224).unwrap();
        let mut spec = PairSpec {
            level: Level::S1,
            template_width: 36,
            template_height: 36,
            search_side: 224,
            min_structure: DEFAULT_MIN_STRUCTURE,
        };
        assert!(matches!(
            make_pair(&photos, &spec, 0, 0),
            Err(SynthError::Unplaceable { .. })
        ));
        spec.min_structure = 0.0;
        assert!(make_pair(&photos, &spec, 0, 0).is_ok());
    }

    #[test]
    fn a_parts_frame_holds_every_part_where_its_truth_says() {
        let part = procedural_part(28, 52);
        let (frame, truth) = parts_frame(&part, 512, 3, 3, 7);
        assert_eq!((frame.width, frame.height, truth.len()), (512, 512, 9));
        for pose in &truth {
            // The large hole (dark) sits 0.27 of the height above the centre, the brushed body
            // (light) at the centre, the background (darker) beyond the part's reach.
            let at = |u: f32, v: f32| {
                let (s, c) = pose.angle_deg.to_radians().sin_cos();
                frame.sample(pose.x + u * c + v * s, pose.y - u * s + v * c)[0]
            };
            assert!(at(0.0, -52.0 * 0.27) < 0.2, "{pose:?}");
            assert!(at(0.0, 0.0) > 0.5, "{pose:?}");
            // 35 px out along the part's axis: off this part (half-diagonal 29.7), and off
            // any neighbour whose centre is far enough from that point.
            let (s, c) = pose.angle_deg.to_radians().sin_cos();
            let (px, py) = (pose.x + 35.0 * s, pose.y + 35.0 * c);
            if truth.iter().all(|t| (t.x - px).hypot(t.y - py) > 31.0) {
                assert!(at(0.0, 35.0) < 0.45, "{pose:?}");
            }
        }
        let (again, _) = parts_frame(&part, 512, 3, 3, 7);
        assert_eq!(again.pixels, frame.pixels, "deterministic from the seed");
    }

    #[test]
    fn parts_laid_on_a_photo_leave_it_unchanged_between_them() {
        let part = procedural_part(28, 52);
        let background = RgbImage32::new(
            300,
            240,
            (0..300 * 240)
                .flat_map(|i| {
                    let v = 0.3 + 0.2 * ((i % 300) as f32 * 0.05).sin();
                    [v, v, v]
                })
                .collect(),
        );
        let (frame, truth) = parts_frame_on(background.clone(), &part, 2, 3, 4);
        assert_eq!((frame.width, frame.height, truth.len()), (300, 240, 6));
        for pose in &truth {
            let (s, c) = pose.angle_deg.to_radians().sin_cos();
            // The brushed body at the centre, the large hole above it.
            assert!(frame.sample(pose.x, pose.y)[0] > 0.5, "{pose:?}");
            let (hx, hy) = (pose.x - 52.0 * 0.27 * s, pose.y - 52.0 * 0.27 * c);
            assert!(frame.sample(hx, hy)[0] < 0.2, "{pose:?}");
        }
        // Pixels beyond every part's reach keep the photo's value.
        let reach = 30.0;
        for y in (0..240).step_by(7) {
            for x in (0..300).step_by(7) {
                if truth
                    .iter()
                    .all(|t| (t.x - x as f32).hypot(t.y - y as f32) > reach)
                {
                    let i = (y * 300 + x) * 3;
                    assert_eq!(frame.pixels[i], background.pixels[i], "({x}, {y})");
                }
            }
        }
    }
}
