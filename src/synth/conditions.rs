//! What a production line does to a part that a clean pair does not show: its contrast
//! reversed (a backlight, another coating) or a quarter of it covered (a clamp, a cable, a
//! label). Each condition turns a generated pair into one with the same exact truth, so that
//! `posematch eval --condition …` measures the matcher under it.

use std::str::FromStr;

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use super::SyntheticPair;
use crate::imaging::RgbImage32;

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
}

impl Condition {
    pub fn name(self) -> &'static str {
        match self {
            Self::Clean => "clean",
            Self::Reversed => "reversed",
            Self::OccludedQuarter => "occluded-quarter",
            Self::ClutteredQuarter => "cluttered-quarter",
        }
    }
}

impl FromStr for Condition {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s.trim().to_ascii_lowercase().as_str() {
            "clean" => Ok(Self::Clean),
            "reversed" => Ok(Self::Reversed),
            "occluded-quarter" => Ok(Self::OccludedQuarter),
            "cluttered-quarter" => Ok(Self::ClutteredQuarter),
            _ => Err(format!(
                "condition `{}` is unknown: use clean, reversed, occluded-quarter or cluttered-quarter",
                s.chars().take(40).collect::<String>().escape_debug()
            )),
        }
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
            cover(&mut pair, quadrant, cover_with, &mut rng);
            (pair, Some(quadrant))
        }
    }
}

/// What covers a quadrant.
enum Cover {
    /// One colour.
    Plain([f32; 3]),
    /// The image's pixels at one random offset, at least the object's size away (wrapping
    /// around the image).
    Texture,
}

/// Replaces the image pixels where every instance shows `quadrant` of the template with
/// `cover_with`.
fn cover(pair: &mut SyntheticPair, quadrant: Quadrant, cover_with: Cover, rng: &mut StdRng) {
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
                if inside && quadrant.contains(col, row, tw, th) {
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
}
