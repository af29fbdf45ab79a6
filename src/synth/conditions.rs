//! What a production line and its camera do to a part that a clean pair does not show: its
//! contrast reversed (a backlight, another coating), a quarter of it covered (a clamp, a cable,
//! a label), and the camera's own conditions (JPEG from a smart camera, defocus, sensor noise,
//! non-linear and uneven light). Each condition turns a generated pair into one with the same
//! exact truth, so that `posematch eval --condition …` measures the matcher under it.

use std::str::FromStr;

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use super::SyntheticPair;
use crate::imaging::{GrayImage32, RgbImage32, gaussian_blur};

/// A condition applied to a pair's search image.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Condition {
    /// The pair as generated.
    #[default]
    Clean,
    /// Every search pixel `v` becomes `1 − v` (255 − pixel): the part dark where its template
    /// is bright.
    Reversed,
    /// One quadrant of the part (chosen per pair) covered by a plain patch of one random
    /// colour (a clamp, a label, a cable's insulation): a quarter of its area hidden.
    OccludedQuarter,
    /// One quadrant covered by texture from elsewhere in the search image (clutter, another
    /// part): a quarter hidden behind something that varies as much as the part does.
    ClutteredQuarter,
    /// The search image JPEG-compressed at quality 30 (a smart camera or gateway saving
    /// bandwidth).
    Jpeg30,
    /// Gaussian defocus of sigma 2 px (depth of field, slight motion).
    Defocus2,
    /// Gaussian noise of sigma 15 grey levels per channel (short exposure, gain).
    Noise15,
    /// Non-linear and darker: `v → 0.6·v^2.2 + 10/255` (gamma 2.2, gain 0.6, offset 10).
    DarkGamma,
    /// Light falling linearly from 1.3 to 0.4 across the frame, in a direction drawn per pair
    /// (an ageing lamp, a reflector on one side); bright pixels saturate.
    UnevenLight,
    /// Every instance wholly covered by texture from elsewhere in the search image: a scene
    /// without the part, where every answer is a false one (how often the score lets a
    /// non-object through).
    Absent,
}

/// What the camera does (issue 41): the held-out table of docs/industrial.md, "Camera
/// conditions".
pub const CAMERA: [Condition; 5] = [
    Condition::Jpeg30,
    Condition::Defocus2,
    Condition::Noise15,
    Condition::DarkGamma,
    Condition::UnevenLight,
];

/// Every condition, in the order of the held-out tables (docs/industrial.md).
pub const ALL: [Condition; 10] = [
    Condition::Clean,
    Condition::Reversed,
    Condition::OccludedQuarter,
    Condition::ClutteredQuarter,
    Condition::Jpeg30,
    Condition::Defocus2,
    Condition::Noise15,
    Condition::DarkGamma,
    Condition::UnevenLight,
    Condition::Absent,
];

impl Condition {
    pub fn name(self) -> &'static str {
        match self {
            Self::Clean => "clean",
            Self::Reversed => "reversed",
            Self::OccludedQuarter => "occluded-quarter",
            Self::ClutteredQuarter => "cluttered-quarter",
            Self::Jpeg30 => "jpeg-30",
            Self::Defocus2 => "defocus-2",
            Self::Noise15 => "noise-15",
            Self::DarkGamma => "dark-gamma",
            Self::UnevenLight => "uneven-light",
            Self::Absent => "absent",
        }
    }
}

impl FromStr for Condition {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        let wanted = s.trim().to_ascii_lowercase();
        ALL.into_iter()
            .find(|condition| condition.name() == wanted)
            .ok_or_else(|| {
                let names: Vec<&str> = ALL.iter().map(|c| c.name()).collect();
                format!(
                    "condition `{}` is unknown: use one of {}",
                    s.chars().take(40).collect::<String>().escape_debug(),
                    names.join(", ")
                )
            })
    }
}

/// Which quadrant of the template a covered pair hides: `(right half, bottom half)`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Quadrant {
    pub right: bool,
    pub bottom: bool,
}

impl Quadrant {
    /// Whether template pixel `(col, row)` of a `width x height` template lies in it.
    pub fn contains(self, col: f32, row: f32, width: u32, height: u32) -> bool {
        let (cx, cy) = ((width as f32 - 1.0) / 2.0, (height as f32 - 1.0) / 2.0);
        (col > cx) == self.right && (row > cy) == self.bottom
    }

    /// A template mask (`true` = use) that leaves this quadrant out.
    pub fn mask_out(self, width: u32, height: u32) -> Vec<bool> {
        (0..width * height)
            .map(|i| !self.contains((i % width) as f32, (i / width) as f32, width, height))
            .collect()
    }
}

/// `pair` under `condition`, deterministic from `(seed, index)`; for
/// [`Condition::OccludedQuarter`] also the quadrant it covered.
pub fn apply(
    pair: SyntheticPair,
    condition: Condition,
    seed: u64,
    index: u64,
) -> (SyntheticPair, Option<Quadrant>) {
    let mut rng = StdRng::seed_from_u64(
        seed.rotate_left(17) ^ index.wrapping_mul(0xD1B5_4A32_D192_ED03) ^ 0xC0DE,
    );
    match condition {
        Condition::Clean => (pair, None),
        Condition::Reversed => {
            let mut pair = pair;
            pair.search.pixels.iter_mut().for_each(|v| *v = 1.0 - *v);
            (pair, None)
        }
        Condition::OccludedQuarter | Condition::ClutteredQuarter => {
            let quadrant = Quadrant {
                right: rng.random_bool(0.5),
                bottom: rng.random_bool(0.5),
            };
            let mut pair = pair;
            let cover_with = if condition == Condition::OccludedQuarter {
                Cover::Plain([rng.random(), rng.random(), rng.random()])
            } else {
                Cover::Texture
            };
            cover(&mut pair, Some(quadrant), cover_with, &mut rng);
            (pair, Some(quadrant))
        }
        Condition::Absent => {
            let mut pair = pair;
            cover(&mut pair, None, Cover::Texture, &mut rng);
            (pair, None)
        }
        Condition::Jpeg30 | Condition::Defocus2 | Condition::Noise15 => {
            let mut pair = pair;
            pair.search = match condition {
                Condition::Jpeg30 => jpeg_round_trip(&pair.search, 30),
                Condition::Defocus2 => defocus(&pair.search, 2.0),
                _ => with_noise(&pair.search, 15.0 / 255.0, &mut rng),
            };
            (pair, None)
        }
        Condition::DarkGamma => {
            let mut pair = pair;
            for v in &mut pair.search.pixels {
                *v = (0.6 * v.max(0.0).powf(2.2) + 10.0 / 255.0).clamp(0.0, 1.0);
            }
            (pair, None)
        }
        Condition::UnevenLight => {
            let mut pair = pair;
            let direction: f32 = rng.random_range(0.0..std::f32::consts::TAU);
            uneven_light(&mut pair.search, direction, (1.3, 0.4));
            (pair, None)
        }
    }
}

/// `image` encoded as a JPEG of `quality` (1–100) and decoded again.
fn jpeg_round_trip(image: &RgbImage32, quality: u8) -> RgbImage32 {
    let bytes: Vec<u8> = image
        .pixels
        .iter()
        .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
        .collect();
    let mut encoded = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut encoded, quality)
        .encode(
            &bytes,
            image.width,
            image.height,
            image::ExtendedColorType::Rgb8,
        )
        .expect("an RGB buffer of its own size encodes");
    let decoded = image::load_from_memory_with_format(&encoded, image::ImageFormat::Jpeg)
        .expect("a JPEG just encoded decodes");
    RgbImage32::from_dynamic(&decoded)
}

/// Each channel of `image` blurred by a Gaussian of `sigma` pixels.
fn defocus(image: &RgbImage32, sigma: f32) -> RgbImage32 {
    let (w, h) = (image.width as usize, image.height as usize);
    let mut pixels = image.pixels.clone();
    for channel in 0..3 {
        let plane = GrayImage32 {
            width: w,
            height: h,
            values: image
                .pixels
                .iter()
                .skip(channel)
                .step_by(3)
                .copied()
                .collect(),
        };
        let blurred = gaussian_blur(&plane, sigma);
        for (to, v) in pixels
            .iter_mut()
            .skip(channel)
            .step_by(3)
            .zip(blurred.values)
        {
            *to = v;
        }
    }
    RgbImage32::new(image.width, image.height, pixels)
}

/// `image` with independent Gaussian noise of `sigma` (values in [0, 1]) on every channel of
/// every pixel, clamped to [0, 1].
fn with_noise(image: &RgbImage32, sigma: f32, rng: &mut StdRng) -> RgbImage32 {
    let mut pixels = image.pixels.clone();
    for v in &mut pixels {
        // Box–Muller: one normal draw from two uniform ones.
        let u1: f32 = rng.random_range(f32::EPSILON..1.0);
        let u2: f32 = rng.random();
        let normal = (-2.0 * u1.ln()).sqrt() * (std::f32::consts::TAU * u2).cos();
        *v = (*v + sigma * normal).clamp(0.0, 1.0);
    }
    RgbImage32::new(image.width, image.height, pixels)
}

/// Multiplies `image` by a gain falling linearly from `gains.0` to `gains.1` across the frame
/// along `direction` (radians; 0 = left to right), clamped to [0, 1].
fn uneven_light(image: &mut RgbImage32, direction: f32, gains: (f32, f32)) {
    let (w, h) = (image.width as f32, image.height as f32);
    let (dy, dx) = direction.sin_cos();
    // The frame's extent along the direction: its corners' projections.
    let along = |x: f32, y: f32| x * dx + y * dy;
    let corners = [
        along(0.0, 0.0),
        along(w - 1.0, 0.0),
        along(0.0, h - 1.0),
        along(w - 1.0, h - 1.0),
    ];
    let low = corners.iter().copied().fold(f32::INFINITY, f32::min);
    let high = corners.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    let span = (high - low).max(1.0);
    for (i, pixel) in image.pixels.chunks_exact_mut(3).enumerate() {
        let (x, y) = (
            (i % image.width as usize) as f32,
            (i / image.width as usize) as f32,
        );
        let t = (along(x, y) - low) / span;
        let gain = gains.0 + (gains.1 - gains.0) * t;
        for v in pixel {
            *v = (*v * gain).clamp(0.0, 1.0);
        }
    }
}

/// `pair` under each of `conditions` in turn (each drawing from its own stream), with the
/// quadrant the last covering condition covered.
pub fn apply_all(
    pair: SyntheticPair,
    conditions: &[Condition],
    seed: u64,
    index: u64,
) -> (SyntheticPair, Option<Quadrant>) {
    conditions
        .iter()
        .enumerate()
        .fold((pair, None), |(pair, covered), (k, &condition)| {
            let (pair, now) = apply(pair, condition, seed.wrapping_add(k as u64), index);
            (pair, now.or(covered))
        })
}

/// What covers a quadrant.
enum Cover {
    /// One colour.
    Plain([f32; 3]),
    /// The image's pixels at one random offset, at least the object's size away (wrapping
    /// around the image).
    Texture,
}

/// Replaces the image pixels where every instance shows `quadrant` of the template (`None`:
/// all of it) with `cover_with`.
fn cover(
    pair: &mut SyntheticPair,
    quadrant: Option<Quadrant>,
    cover_with: Cover,
    rng: &mut StdRng,
) {
    let (tw, th) = (pair.template.width, pair.template.height);
    let search = &pair.search;
    let (w, h) = (search.width as i64, search.height as i64);
    let source = search.pixels.clone();
    let mut pixels = search.pixels.clone();
    for truth in &pair.truth {
        let reach = (truth.scale_x * tw as f32).hypot(truth.scale_y * th as f32) as i64 + 2;
        let shift = |rng: &mut StdRng, side: i64| {
            let least = reach.min(side / 2).max(1);
            let magnitude = rng.random_range(least..=(side - least).max(least));
            magnitude.rem_euclid(side)
        };
        let (dx, dy) = (shift(rng, w), shift(rng, h));
        let (s, c) = truth.angle_deg.to_radians().sin_cos();
        let (cx, cy) = ((tw as f32 - 1.0) / 2.0, (th as f32 - 1.0) / 2.0);
        for y in 0..h {
            for x in 0..w {
                // The inverse of the pose: image point → template pixel.
                let (px, py) = (x as f32 - truth.x, y as f32 - truth.y);
                let u = (px * c - py * s) / truth.scale_x;
                let v = (px * s + py * c) / truth.scale_y;
                let (col, row) = (u + cx, v + cy);
                let inside =
                    col >= -0.5 && col <= tw as f32 - 0.5 && row >= -0.5 && row <= th as f32 - 0.5;
                if inside && quadrant.is_none_or(|q| q.contains(col, row, tw, th)) {
                    let to = (y * w + x) as usize * 3;
                    match cover_with {
                        Cover::Plain(colour) => pixels[to..to + 3].copy_from_slice(&colour),
                        Cover::Texture => {
                            let from = (((y + dy) % h) * w + (x + dx) % w) as usize * 3;
                            pixels[to..to + 3].copy_from_slice(&source[from..from + 3]);
                        }
                    }
                }
            }
        }
    }
    pair.search = RgbImage32::new(search.width, search.height, pixels);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Pose;

    fn pair() -> SyntheticPair {
        let (w, h) = (64u32, 64u32);
        let pixels = (0..w * h * 3).map(|i| (i % 251) as f32 / 255.0).collect();
        SyntheticPair {
            template: RgbImage32::new(8, 8, vec![0.5; 8 * 8 * 3]),
            search: RgbImage32::new(w, h, pixels),
            truth: vec![Pose {
                x: 31.5,
                y: 31.5,
                angle_deg: 30.0,
                scale_x: 2.0,
                scale_y: 2.0,
                score: 1.0,
                network_score: 0.0,
            }],
            photo: 0,
        }
    }

    #[test]
    fn reversing_maps_every_pixel_to_its_complement() {
        let clean = pair();
        let (reversed, quadrant) = apply(clean.clone(), Condition::Reversed, 1, 2);
        assert!(quadrant.is_none());
        for (a, b) in clean.search.pixels.iter().zip(&reversed.search.pixels) {
            assert!((a + b - 1.0).abs() < 1e-6);
        }
    }

    #[test]
    fn a_covered_quarter_changes_about_a_quarter_of_the_part_and_nothing_else() {
        let clean = pair();
        let (covered, quadrant) = apply(clean.clone(), Condition::ClutteredQuarter, 3, 4);
        let quadrant = quadrant.expect("a covered pair names its quadrant");
        let changed: Vec<usize> = clean
            .search
            .pixels
            .chunks_exact(3)
            .zip(covered.search.pixels.chunks_exact(3))
            .enumerate()
            .filter(|(_, (a, b))| a != b)
            .map(|(i, _)| i)
            .collect();
        // The part covers 16x16 = 256 image pixels; a quarter of it is about 64.
        assert!((48..=80).contains(&changed.len()), "{}", changed.len());
        let truth = clean.truth[0];
        let (s, c) = truth.angle_deg.to_radians().sin_cos();
        for i in changed {
            let (px, py) = ((i % 64) as f32 - truth.x, (i / 64) as f32 - truth.y);
            let (col, row) = ((px * c - py * s) / 2.0 + 3.5, (px * s + py * c) / 2.0 + 3.5);
            assert!(
                quadrant.contains(col, row, 8, 8),
                "pixel {i} outside the quadrant"
            );
        }
        let mask = quadrant.mask_out(8, 8);
        assert_eq!(mask.iter().filter(|&&used| !used).count(), 16);
    }

    /// A textured 48x48 pair (a hash of the position) for the camera conditions.
    fn textured_pair() -> SyntheticPair {
        let mut pair = pair();
        let (w, h) = (48u32, 48u32);
        pair.search = RgbImage32::new(
            w,
            h,
            (0..w * h * 3)
                .map(|i| ((i / 3).wrapping_mul(2_654_435_761) % 1000) as f32 / 1000.0 * 0.6 + 0.2)
                .collect(),
        );
        pair
    }

    fn mean(values: &[f32]) -> f32 {
        values.iter().sum::<f32>() / values.len() as f32
    }

    /// Mean squared difference between horizontal neighbours: how sharp an image is.
    fn sharpness(image: &RgbImage32) -> f32 {
        let row = image.width as usize * 3;
        let diffs: Vec<f32> = image
            .pixels
            .chunks_exact(row)
            .flat_map(|r| r.windows(4).map(|w| (w[3] - w[0]).powi(2)))
            .collect();
        mean(&diffs)
    }

    #[test]
    fn an_absent_part_is_wholly_replaced() {
        let clean = textured_pair();
        let (absent, quadrant) = apply(clean.clone(), Condition::Absent, 3, 4);
        assert!(quadrant.is_none());
        let changed = clean
            .search
            .pixels
            .chunks_exact(3)
            .zip(absent.search.pixels.chunks_exact(3))
            .filter(|(a, b)| a != b)
            .count();
        // The part covers 16x16 = 256 image pixels.
        assert!((220..=290).contains(&changed), "{changed}");
    }

    #[test]
    fn conditions_in_turn_are_each_one_as_alone_then_the_next() {
        let clean = textured_pair();
        for condition in ALL {
            let (one, covered) = apply(clean.clone(), condition, 7, 8);
            let (listed, listed_covered) = apply_all(clean.clone(), &[condition], 7, 8);
            assert_eq!(
                one.search.pixels,
                listed.search.pixels,
                "{}",
                condition.name()
            );
            assert_eq!(covered, listed_covered);
        }
        let (absent, _) = apply(clean.clone(), Condition::Absent, 7, 8);
        let (both, _) = apply_all(clean, &[Condition::Absent, Condition::DarkGamma], 7, 8);
        for (a, b) in absent.search.pixels.iter().zip(&both.search.pixels) {
            assert!((b - (0.6 * a.powf(2.2) + 10.0 / 255.0)).abs() < 1e-5);
        }
    }

    #[test]
    fn every_condition_has_a_name_that_parses_back() {
        for condition in ALL {
            assert_eq!(condition.name().parse::<Condition>(), Ok(condition));
        }
        let error = "blurry".parse::<Condition>().unwrap_err();
        assert!(error.contains("defocus-2"), "{error}");
    }

    #[test]
    fn camera_conditions_keep_the_truth_and_change_the_image_as_named() {
        let clean = textured_pair();
        let apply = |condition| apply(clean.clone(), condition, 5, 6).0;
        let jpeg = apply(Condition::Jpeg30);
        let error = mean(
            &clean
                .search
                .pixels
                .iter()
                .zip(&jpeg.search.pixels)
                .map(|(a, b)| (a - b).abs())
                .collect::<Vec<_>>(),
        );
        assert!(error > 0.01 && error < 0.2, "JPEG mean error {error}");
        assert!(sharpness(&apply(Condition::Defocus2).search) < 0.2 * sharpness(&clean.search));
        let noisy = apply(Condition::Noise15);
        let differences: Vec<f32> = clean
            .search
            .pixels
            .iter()
            .zip(&noisy.search.pixels)
            .map(|(a, b)| b - a)
            .collect();
        let spread = mean(&differences.iter().map(|d| d * d).collect::<Vec<_>>()).sqrt();
        assert!(
            (spread * 255.0 - 15.0).abs() < 1.0,
            "noise sigma {}",
            spread * 255.0
        );
        let dark = apply(Condition::DarkGamma);
        for (a, b) in clean.search.pixels.iter().zip(&dark.search.pixels) {
            assert!((b - (0.6 * a.powf(2.2) + 10.0 / 255.0)).abs() < 1e-5);
        }
        let lit = apply(Condition::UnevenLight);
        let gains: Vec<f32> = clean
            .search
            .pixels
            .iter()
            .zip(&lit.search.pixels)
            .filter(|(a, b)| **b < 1.0 && **a > 0.0)
            .map(|(a, b)| b / a)
            .collect();
        let (low, high) = gains
            .iter()
            .fold((f32::INFINITY, 0.0f32), |(l, h), &g| (l.min(g), h.max(g)));
        assert!(
            (low - 0.4).abs() < 0.02 && (high - 1.3).abs() < 0.02,
            "{low}..{high}"
        );
        for condition in CAMERA {
            let (changed, quadrant) = super::apply(clean.clone(), condition, 5, 6);
            assert!(quadrant.is_none());
            assert_eq!(changed.truth, clean.truth);
            assert_eq!(changed.template.pixels, clean.template.pixels);
            assert!(
                changed
                    .search
                    .pixels
                    .iter()
                    .all(|v| (0.0..=1.0).contains(v))
            );
        }
    }
}
