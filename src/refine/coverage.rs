//! How much of a part is there: the template split into cells, each correlated on its own.
//!
//! Why: one ZNCC over the whole template collapses when a quarter of the part is covered (a
//! clamp, a cable, a label): the covered pixels add image variance and no covariance, and the
//! chance-corrected score of a clearly visible part falls from above 0.9 to about 0.5. Halcon's
//! score is the visible share of the model; this is ours: the share of the template's area with
//! structure whose cell matches ([`CoverageReading::visible`]), and how well the visible cells match
//! ([`CoverageReading::visible_similarity`]), together or each cell with its own gain and
//! offset: a light that falls across the part (a lamp on one side, a reflector) changes the
//! gain from cell to cell, which one ZNCC over all the cells counts as mismatch. The verifier
//! turns both into one score (`matcher/verification.rs`, docs/accuracy.md "What a score
//! means").

use super::PoseSamples;
use crate::imaging::GrayImage32;

/// Cells per side of the template.
const CELLS_PER_SIDE: usize = 4;

/// A cell's ZNCC at or below this counts as not matching at all, at or above
/// [`CELL_MATCHES`] as matching; linear between. A covered cell correlates with the template
/// only by chance (about ±0.3 for a 9x9 cell of a 36x36 template); a visible one of a right
/// pose well above 0.5 even under blur.
const CELL_UNRELATED: f32 = 0.2;
const CELL_MATCHES: f32 = 0.5;

/// A cell whose template spread is below this (values in [0, 1]; two grey levels) holds no
/// structure: it weighs nothing in the visible share and always counts as visible.
const FLAT_CELL_SPREAD: f32 = 2.0 / 255.0;

/// A flat cell counts in the visible similarity where the image there lies within this share
/// of the structure's spread (in the image) of the level the matching structured cells'
/// gain and offset predict for it. Why: a flat cell counts for nothing in the visible share
/// and was always taken as visible, so a cover over a blank quarter added its own grey to the
/// visible similarity — contrast with none of the template's — and such a part read 0.4–0.9
/// at its own pose (`covered_probe`, lomiri tuning photos: 13 of the 18 parts whose own pose
/// scored under 0.7). Where the flat cell lies at the predicted level it still tells the
/// part's grey against its structure, so it counts. Tuning set (lomiri photos, 1000 S1.5
/// pairs, `--min-score 0.7`), found before → after: plain cover 86.9 → 88.8 %, clutter 85.4 →
/// 87.3 %; answers in scenes without the part at or above 0.7 (500) 69 → 69, at or above 0.9
/// (1000, defaults) 45 → 45. Leaving flat cells out altogether measured the same but one more
/// false answer at 0.9.
const FLAT_CELL_FIT: f64 = 0.5;

/// A matching cell whose own ZNCC is under this may be a covered one that correlates by chance
/// (a textured cover over a smooth part: a cell of it at 0.5–0.9): the verifier also reads the
/// pose with the worst such cell counted as hidden ([`Coverage::measure_worst_hidden`]), and
/// the better reading counts. Why: with that cell among the visible ones a smooth part
/// (chance level 0.8) read 0.96–0.97 where 0.99 was needed (`covered_probe --condition
/// cluttered-quarter`, lomiri tuning photos: 10 of the 21 parts whose own pose scored under
/// 0.7 went over it).
const WORST_CELL_BELOW: f32 = 0.9;

/// Points of a matching cell nearer than this (template pixels) to a neighbouring cell that
/// does not match count in neither the visible similarity nor the visible points. A cover's
/// edge runs through the part wherever it lies, and a bilinear sample within an image pixel
/// of it mixes the cover into the visible side; a smooth part, whose chance level is high
/// (0.8), loses most of its score to that one row (`covered_probe`, lomiri tuning photos: the
/// part's own pose read at 0.89–0.94 where 0.98 would score 0.7). A template pixel 1.5 away
/// is an image pixel away at every scale down to 0.67. Tuning set (lomiri photos, 1000 S1.5
/// pairs, `--min-score 0.7`), found before → after: plain cover 85.3 → 85.9 %, clutter 85.2 →
/// 87.0 %; answers in scenes without the part at or above 0.7 (500) 67 → 67, at or above
/// 0.9 (1000) 23 → 23.
const COVER_EDGE: f32 = 1.5;

/// The eight neighbouring cells, `(column, row)` steps; a point's [`Cell::near`] has bit `k`
/// set where it lies within [`COVER_EDGE`] of neighbour `k`.
const NEIGHBOURS: [(i64, i64); 8] = [
    (-1, -1),
    (0, -1),
    (1, -1),
    (-1, 0),
    (1, 0),
    (-1, 1),
    (0, 1),
    (1, 1),
];

/// Sums of one cell of points in the image, in f64: enough to combine cells into one ZNCC.
#[derive(Debug, Clone, Copy, Default)]
struct CellSums {
    n: f64,
    /// Σ t, Σ t² of the template values (centred on the whole template's mean).
    t: f64,
    tt: f64,
    /// Σ I, Σ I², Σ t·I of the image samples.
    i: f64,
    ii: f64,
    ti: f64,
}

impl CellSums {
    fn add(&mut self, other: &CellSums) {
        self.n += other.n;
        self.t += other.t;
        self.tt += other.tt;
        self.i += other.i;
        self.ii += other.ii;
        self.ti += other.ti;
    }

    /// ZNCC of the summed points, in [-1, 1]; -1 for a flat image patch (as
    /// [`super::zncc`]).
    fn zncc(&self) -> f32 {
        if self.n < 2.0 {
            return -1.0;
        }
        let var_t = self.tt - self.t * self.t / self.n;
        let var_i = self.ii - self.i * self.i / self.n;
        let flat = self.n * f64::from(super::FLAT_PATCH_SPREAD).powi(2);
        if var_i <= flat || var_t <= 1e-12 {
            return -1.0;
        }
        let cov = self.ti - self.t * self.i / self.n;
        (cov / (var_t * var_i).sqrt()).clamp(-1.0, 1.0) as f32
    }
}

struct Cell {
    /// Its points: indices into the support's points (and so into a pose's samples), with
    /// their template values centred on the whole template's mean.
    indices: Vec<usize>,
    values: Vec<f32>,
    /// Σ t and Σ t² of its template values.
    t: f64,
    tt: f64,
    /// What it counts for in the visible share: its points, 0 when flat
    /// ([`Coverage::new`]).
    weight: f32,
    /// Its place in the grid: `(column, row)`.
    place: (usize, usize),
    /// Per point, the neighbours ([`NEIGHBOURS`]) whose edge it lies near ([`COVER_EDGE`]).
    near: Vec<u8>,
}

/// The template's support points (in the support's order) in [`CELLS_PER_SIDE`]² cells.
pub(crate) struct Coverage {
    cells: Vec<Cell>,
    total_weight: f32,
    points: usize,
}

/// What [`Coverage::measure`] found at one pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct CoverageReading {
    /// Share of the template's structured area whose cell matches, in [0, 1]: a quarter
    /// covered is 0.75 whatever that quarter held.
    pub visible: f32,
    /// How well the matching cells match, in [-1, 1]: the better of one ZNCC over them
    /// together (which also counts the contrast between cells: what finds a part with a
    /// quarter covered) and their own ZNCCs, each cell with its own gain and offset, averaged
    /// by their points (which holds where light varies across the part, and one ZNCC falls).
    /// For unrelated patches the average spreads as one ZNCC over the same points does (an
    /// average of k independent correlations of n points varies as one of k·n), so the same
    /// chance level holds.
    pub visible_similarity: f32,
    /// Share of the support points in the matching cells, in (0, 1].
    pub visible_points: f32,
}

impl Coverage {
    /// Every template pixel up to 48 a side (the similarity's support), in cells. Each cell
    /// with structure counts for its points in the visible share, as each of a shape model's
    /// edge points counts once in Halcon's. Weighing a cell by its grey-level variance instead
    /// made the share of a covered quarter depend on its contrast (0.45–0.94 for a quarter),
    /// and a quarter covered scored under 0.7 in a fifth of the pairs. Tuning set (lomiri
    /// photos, 200 S1.5 pairs, `--min-score 0.7`), found by variance / by area: plain cover
    /// 70.5 / 84.0 %, clutter 74.5 / 83.0 %; clean 99.5 / 99.5 %; answers at or above 0.7 in
    /// scenes without the part 37 / 37.
    pub(crate) fn new(template: &GrayImage32) -> Self {
        let (offsets, values) = super::grid_points(template, 48);
        let mean = values.iter().sum::<f32>() / values.len().max(1) as f32;
        let (cx, cy) = (
            (template.width as f32 - 1.0) / 2.0,
            (template.height as f32 - 1.0) / 2.0,
        );
        let cell_side = (
            template.width as f32 / CELLS_PER_SIDE as f32,
            template.height as f32 / CELLS_PER_SIDE as f32,
        );
        // A point's cell, and the neighbours whose edge it lies near.
        let cell_of = |(u, v): (f32, f32)| {
            let (x, y) = (u + cx + 0.5, v + cy + 0.5);
            let col = ((x / cell_side.0) as usize).min(CELLS_PER_SIDE - 1);
            let row = ((y / cell_side.1) as usize).min(CELLS_PER_SIDE - 1);
            let left = x - col as f32 * cell_side.0 < COVER_EDGE;
            let right = (col + 1) as f32 * cell_side.0 - x < COVER_EDGE;
            let top = y - row as f32 * cell_side.1 < COVER_EDGE;
            let bottom = (row + 1) as f32 * cell_side.1 - y < COVER_EDGE;
            let near_x = |dx: i64| (dx == -1 && left) || (dx == 1 && right);
            let near_y = |dy: i64| (dy == -1 && top) || (dy == 1 && bottom);
            let near = NEIGHBOURS
                .iter()
                .enumerate()
                .filter(|&(_, &(dx, dy))| (dx == 0 || near_x(dx)) && (dy == 0 || near_y(dy)))
                .fold(0u8, |bits, (k, _)| bits | 1 << k);
            (row * CELLS_PER_SIDE + col, near)
        };
        // Each cell's points, centred values and nearness to its neighbours.
        let mut indices_of = vec![Vec::new(); CELLS_PER_SIDE * CELLS_PER_SIDE];
        let mut values_of: Vec<Vec<f32>> = vec![Vec::new(); CELLS_PER_SIDE * CELLS_PER_SIDE];
        let mut near_of: Vec<Vec<u8>> = vec![Vec::new(); CELLS_PER_SIDE * CELLS_PER_SIDE];
        for (index, (&offset, &value)) in offsets.iter().zip(&values).enumerate() {
            let (cell, near) = cell_of(offset);
            indices_of[cell].push(index);
            values_of[cell].push(value - mean);
            near_of[cell].push(near);
        }
        let cells: Vec<Cell> = indices_of
            .into_iter()
            .zip(values_of)
            .zip(near_of)
            .enumerate()
            .filter(|(_, ((indices, _), _))| !indices.is_empty())
            .map(|(grid_index, ((indices, values), near))| {
                let n = values.len() as f64;
                let t: f64 = values.iter().map(|&v| f64::from(v)).sum();
                let tt: f64 = values.iter().map(|&v| f64::from(v).powi(2)).sum();
                let spread_sq = (tt - t * t / n).max(0.0);
                let flat = spread_sq / n < f64::from(FLAT_CELL_SPREAD).powi(2);
                Cell {
                    indices,
                    values,
                    t,
                    tt,
                    weight: if flat { 0.0 } else { n as f32 },
                    place: (grid_index % CELLS_PER_SIDE, grid_index / CELLS_PER_SIDE),
                    near,
                }
            })
            .collect();
        Self {
            total_weight: cells.iter().map(|c| c.weight).sum(),
            points: offsets.len(),
            cells,
        }
    }

    fn sums(cell: &Cell, samples: &[f32]) -> CellSums {
        let (mut i, mut ii, mut ti) = (0f64, 0f64, 0f64);
        for (&index, &t) in cell.indices.iter().zip(&cell.values) {
            let sample = f64::from(samples[index]);
            i += sample;
            ii += sample * sample;
            ti += f64::from(t) * sample;
        }
        CellSums {
            n: cell.indices.len() as f64,
            t: cell.t,
            tt: cell.tt,
            i,
            ii,
            ti,
        }
    }

    /// [`Coverage::sums`] of the cell's points that lie near none of the `away` neighbours
    /// ([`Cell::near`] bits).
    fn sums_away_from(cell: &Cell, samples: &[f32], away: u8) -> CellSums {
        let mut sums = CellSums::default();
        for ((&index, &t), &near) in cell.indices.iter().zip(&cell.values).zip(&cell.near) {
            if near & away == 0 {
                let (t, sample) = (f64::from(t), f64::from(samples[index]));
                sums.n += 1.0;
                sums.t += t;
                sums.tt += t * t;
                sums.i += sample;
                sums.ii += sample * sample;
                sums.ti += t * sample;
            }
        }
        sums
    }

    /// The neighbours ([`NEIGHBOURS`] bits) of the cell at `place` that do not match, by the
    /// `matching` flags of the grid (`None`: no cell there).
    fn unmatched_neighbours(place: (usize, usize), matching: &[Option<bool>]) -> u8 {
        NEIGHBOURS
            .iter()
            .enumerate()
            .filter(|&(_, &(dx, dy))| {
                let (col, row) = (place.0 as i64 + dx, place.1 as i64 + dy);
                let side = CELLS_PER_SIDE as i64;
                (0..side).contains(&col)
                    && (0..side).contains(&row)
                    && matching[(row * side + col) as usize] == Some(false)
            })
            .fold(0u8, |bits, (k, _)| bits | 1 << k)
    }

    /// The flat cells' sums where the image there sits at the level the matching structured
    /// cells (`structured`, summed) predict: their gain and offset applied to the flat cell's
    /// template values leave a residual of at most [`FLAT_CELL_FIT`] of the structure's spread
    /// in the image. A flat cell tells nothing of the pose by itself, but its grey level
    /// against the structure's does, where it is not covered.
    fn flat_cells_at_level(&self, cell_sums: &[CellSums], structured: &CellSums) -> CellSums {
        let mut flat = CellSums::default();
        let n = structured.n;
        if n < 2.0 {
            return flat;
        }
        let var_t = structured.tt - structured.t * structured.t / n;
        if var_t <= 1e-12 {
            return flat;
        }
        let gain = (structured.ti - structured.t * structured.i / n) / var_t;
        let offset = (structured.i - gain * structured.t) / n;
        let spread = gain.abs() * (var_t / n).sqrt();
        for (cell, sums) in self.cells.iter().zip(cell_sums) {
            if cell.weight > 0.0 || sums.n < 1.0 {
                continue;
            }
            // Mean square of I − (gain·t + offset) over the cell, from its sums.
            let residual_sq = (sums.ii - 2.0 * gain * sums.ti - 2.0 * offset * sums.i
                + gain * gain * sums.tt
                + 2.0 * gain * offset * sums.t
                + offset * offset * sums.n)
                / sums.n;
            if residual_sq.max(0.0).sqrt() <= FLAT_CELL_FIT * spread {
                flat.add(sums);
            }
        }
        flat
    }

    /// The template's cells in the image's `samples` at a pose (the support's). `None` for a
    /// template without structure in any cell (nothing to tell a covered cell from a visible
    /// one).
    #[cfg(test)]
    pub(crate) fn measure(&self, samples: &PoseSamples) -> Option<CoverageReading> {
        self.readings(samples).map(|(reading, _)| reading)
    }

    /// [`Coverage::measure`] with the worst matching structured cell counted as hidden, where
    /// its own ZNCC is under [`WORST_CELL_BELOW`]; `None` where none is.
    #[cfg(test)]
    pub(crate) fn measure_worst_hidden(&self, samples: &PoseSamples) -> Option<CoverageReading> {
        self.readings(samples)
            .and_then(|(_, worst_hidden)| worst_hidden)
    }

    /// [`Coverage::measure`] and [`Coverage::measure_worst_hidden`] from one pass over the
    /// samples (the verifier reads both at every pose).
    pub(crate) fn readings(
        &self,
        samples: &PoseSamples,
    ) -> Option<(CoverageReading, Option<CoverageReading>)> {
        if self.total_weight <= 0.0 || self.points == 0 {
            return None;
        }
        let samples = samples.values();
        debug_assert_eq!(samples.len(), self.points, "the support's samples");
        let mut visible = 0.0f32;
        // On the stack: every reading of every pose passes here.
        let mut matching = [None; CELLS_PER_SIDE * CELLS_PER_SIDE];
        let mut cell_sums = [CellSums::default(); CELLS_PER_SIDE * CELLS_PER_SIDE];
        for (cell, sums_here) in self.cells.iter().zip(&mut cell_sums) {
            let sums = Self::sums(cell, samples);
            let matches = if cell.weight > 0.0 {
                ((sums.zncc() - CELL_UNRELATED) / (CELL_MATCHES - CELL_UNRELATED)).clamp(0.0, 1.0)
            } else {
                1.0
            };
            visible += cell.weight * matches;
            matching[cell.place.1 * CELLS_PER_SIDE + cell.place.0] = Some(matches >= 1.0);
            *sums_here = sums;
        }
        let reading = self.reading(samples, visible, &matching, &cell_sums);
        let worst = self
            .cells
            .iter()
            .zip(&cell_sums)
            .filter(|(cell, _)| {
                cell.weight > 0.0
                    && matching[cell.place.1 * CELLS_PER_SIDE + cell.place.0] == Some(true)
            })
            .map(|(cell, sums)| (cell, sums.zncc()))
            .min_by(|a, b| a.1.total_cmp(&b.1));
        let worst_hidden = match worst {
            Some((cell, zncc)) if zncc < WORST_CELL_BELOW => {
                let mut matching = matching;
                matching[cell.place.1 * CELLS_PER_SIDE + cell.place.0] = Some(false);
                Some(self.reading(samples, visible - cell.weight, &matching, &cell_sums))
            }
            _ => None,
        };
        Some((reading, worst_hidden))
    }

    /// The reading of the cells flagged `matching`, `visible` their summed weight.
    fn reading(
        &self,
        samples: &[f32],
        visible: f32,
        matching: &[Option<bool>],
        cell_sums: &[CellSums],
    ) -> CoverageReading {
        // The structured cells that match; flat ones are judged after, by their level.
        let mut together = CellSums::default();
        let mut cells_similarity = 0.0f64;
        for (cell, &sums) in self.cells.iter().zip(cell_sums) {
            if cell.weight <= 0.0
                || matching[cell.place.1 * CELLS_PER_SIDE + cell.place.0] != Some(true)
            {
                continue;
            }
            let away = Self::unmatched_neighbours(cell.place, matching);
            let sums = if away == 0 {
                sums
            } else {
                Self::sums_away_from(cell, samples, away)
            };
            if sums.n > 0.0 {
                together.add(&sums);
                cells_similarity += f64::from(sums.zncc()) * sums.n;
            }
        }
        let structured_points = together.n;
        let flat_at_level = self.flat_cells_at_level(cell_sums, &together);
        together.add(&flat_at_level);
        CoverageReading {
            visible: (visible / self.total_weight).clamp(0.0, 1.0),
            visible_similarity: if together.n > 0.0 {
                together
                    .zncc()
                    .max((cells_similarity / structured_points.max(1.0)) as f32)
            } else {
                -1.0
            },
            visible_points: (together.n / self.points as f64) as f32,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Pose;
    use crate::refine::{TemplatePoints, textured};

    fn at(x: f32, y: f32) -> Pose {
        Pose {
            x,
            y,
            angle_deg: 0.0,
            scale_x: 1.0,
            scale_y: 1.0,
            score: 0.0,
            network_score: 0.0,
        }
    }

    /// The template's coverage at `pose` in `image`.
    fn measure(
        template: &GrayImage32,
        image: &GrayImage32,
        pose: &Pose,
    ) -> Option<CoverageReading> {
        let samples = TemplatePoints::support(template).samples(image, pose);
        Coverage::new(template).measure(&samples)
    }

    /// The template pasted into a textured image at (40, 30) with its top-left corner.
    fn scene(template: &GrayImage32, covered_quarter: bool) -> GrayImage32 {
        let background = textured(120, 100, 7);
        GrayImage32::from_fn(120, 100, |x, y| {
            let (u, v) = (x as i64 - 40, y as i64 - 30);
            let inside =
                (0..template.width as i64).contains(&u) && (0..template.height as i64).contains(&v);
            let hidden = covered_quarter
                && u >= template.width as i64 / 2
                && v >= template.height as i64 / 2;
            if inside && !hidden {
                template.values[v as usize * template.width + u as usize]
            } else {
                background.values[y * 120 + x]
            }
        })
    }

    #[test]
    fn a_visible_part_is_wholly_visible_and_a_covered_quarter_is_missing() {
        let template = textured(36, 36, 1);
        let pose = at(40.0 + 17.5, 30.0 + 17.5);
        let clean_scene = scene(&template, false);
        let whole = TemplatePoints::support(&template).score(&clean_scene, &pose);
        assert!(whole > 0.999, "whole-template ZNCC {whole}");
        let clean = measure(&template, &clean_scene, &pose).unwrap();
        assert!(clean.visible > 0.999, "{clean:?}");
        assert!(clean.visible_similarity > 0.999, "{clean:?}");
        assert!((clean.visible_points - 1.0).abs() < 1e-6, "{clean:?}");
        let covered = measure(&template, &scene(&template, true), &pose).unwrap();
        assert!((0.7..0.82).contains(&covered.visible), "{covered:?}");
        assert!(covered.visible_similarity > 0.999, "{covered:?}");
        assert!((covered.visible_points - 0.75).abs() < 0.07, "{covered:?}");
    }

    #[test]
    fn the_covers_edge_does_not_spoil_a_smooth_parts_visible_cells() {
        // A smooth part (about 100 grey levels of slow waves) half a pixel off the image grid,
        // so that every sample mixes two image pixels, with its bottom-right quarter under a
        // dark plain cover whose edge lies a quarter pixel inside the quarter.
        let smooth = |u: f32, v: f32| 0.5 + 0.2 * (u / 6.0).sin() * (v / 7.0).cos();
        let template = GrayImage32::from_fn(36, 36, |x, y| smooth(x as f32, y as f32));
        let (x0, y0) = (40.5, 30.5);
        let background = textured(120, 100, 7);
        let image = GrayImage32::from_fn(120, 100, |x, y| {
            let (u, v) = (x as f32 - x0, y as f32 - y0);
            let inside = (-0.5..35.5).contains(&u) && (-0.5..35.5).contains(&v);
            if inside && u > 17.25 && v > 17.25 {
                0.1
            } else if inside {
                smooth(u, v)
            } else {
                background.values[y * 120 + x]
            }
        });
        let pose = at(x0 + 17.5, y0 + 17.5);
        let covered = measure(&template, &image, &pose).unwrap();
        // The edge spoils some cells beside the cover outright (each cell's own match is
        // judged on all its points); the matching ones beside it are read without their row
        // or column next to the cover: 0.988 here, 0.966 with it.
        assert!((0.5..0.82).contains(&covered.visible), "{covered:?}");
        assert!(covered.visible_similarity > 0.98, "{covered:?}");
        assert!(
            covered.visible_points < covered.visible - 0.02,
            "the points beside the cover left out: {covered:?}"
        );
    }

    #[test]
    fn a_cover_over_a_blank_quarter_neither_helps_nor_hurts() {
        // The bottom-right quarter of the template is blank (one grey), and a dark plain
        // cover lies over it: the part's structure is all there.
        let base = textured(36, 36, 1);
        let template = GrayImage32::from_fn(36, 36, |x, y| {
            if x >= 18 && y >= 18 {
                0.5
            } else {
                base.values[y * 36 + x]
            }
        });
        let background = textured(120, 100, 7);
        let scene = |covered: bool| {
            GrayImage32::from_fn(120, 100, |x, y| {
                let (u, v) = (x as i64 - 40, y as i64 - 30);
                let inside = (0..36).contains(&u) && (0..36).contains(&v);
                if covered && inside && u >= 18 && v >= 18 {
                    0.05
                } else if inside {
                    template.values[v as usize * 36 + u as usize]
                } else {
                    background.values[y * 120 + x]
                }
            })
        };
        let pose = at(40.0 + 17.5, 30.0 + 17.5);
        let covered = measure(&template, &scene(true), &pose).unwrap();
        assert!(covered.visible > 0.999, "{covered:?}");
        // The blank cells, under a cover of another grey, would add the cover's contrast to
        // the visible similarity and none of the template's: 0.62 when they counted.
        assert!(covered.visible_similarity > 0.99, "{covered:?}");
        assert!((covered.visible_points - 0.75).abs() < 0.07, "{covered:?}");
        // Uncovered, the blank cells sit at the level the rest predicts, and count.
        let clean = measure(&template, &scene(false), &pose).unwrap();
        assert!(clean.visible_similarity > 0.999, "{clean:?}");
        assert!((clean.visible_points - 1.0).abs() < 1e-6, "{clean:?}");
    }

    #[test]
    fn a_cell_that_matches_by_chance_can_be_counted_as_hidden() {
        // The template's bottom-right cell half mixed with texture from elsewhere: it still
        // correlates (0.5–0.9), and spoils the visible similarity of the rest.
        let template = textured(36, 36, 1);
        let clean_scene = scene(&template, false);
        let other = textured(120, 100, 11);
        let image = GrayImage32::from_fn(120, 100, |x, y| {
            let (u, v) = (x as i64 - 40, y as i64 - 30);
            let v_here = clean_scene.values[y * 120 + x];
            if (27..36).contains(&u) && (27..36).contains(&v) {
                0.5 * v_here + 0.5 * other.values[y * 120 + x]
            } else {
                v_here
            }
        });
        let samples =
            TemplatePoints::support(&template).samples(&image, &at(40.0 + 17.5, 30.0 + 17.5));
        let coverage = Coverage::new(&template);
        let all = coverage.measure(&samples).unwrap();
        let worst_hidden = coverage.measure_worst_hidden(&samples).unwrap();
        assert!(all.visible > 0.999, "{all:?}");
        assert!(all.visible_similarity < 0.99, "{all:?}");
        assert!(
            (worst_hidden.visible - 15.0 / 16.0).abs() < 0.02,
            "{worst_hidden:?}"
        );
        assert!(worst_hidden.visible_similarity > 0.999, "{worst_hidden:?}");
        // A clean part has no such cell.
        let clean_samples =
            TemplatePoints::support(&template).samples(&clean_scene, &at(40.0 + 17.5, 30.0 + 17.5));
        assert!(coverage.measure_worst_hidden(&clean_samples).is_none());
    }

    #[test]
    fn a_covered_quarter_is_a_quarter_whatever_its_contrast() {
        // The covered (bottom-right) quarter holds four times the contrast of the rest:
        // weighed by variance it would be 16 of 19 parts of the structure.
        let base = textured(36, 36, 1);
        let template = GrayImage32::from_fn(36, 36, |x, y| {
            let v = base.values[y * 36 + x] - 0.5;
            0.5 + if x >= 18 && y >= 18 { v } else { v / 4.0 }
        });
        let pose = at(40.0 + 17.5, 30.0 + 17.5);
        let covered = measure(&template, &scene(&template, true), &pose).unwrap();
        assert!((covered.visible - 0.75).abs() < 0.05, "{covered:?}");
    }

    #[test]
    fn light_falling_across_the_part_leaves_every_cell_matching() {
        let template = textured(36, 36, 1);
        let pose = at(40.0 + 17.5, 30.0 + 17.5);
        let clean = scene(&template, false);
        // Gain 1.3 at the part's left edge, 0.4 at its right, as a lamp on one side.
        let lit = GrayImage32::from_fn(120, 100, |x, y| {
            let gain = 1.3 - 0.9 * ((x as f32 - 40.0) / 35.0).clamp(0.0, 1.0);
            clean.values[y * 120 + x] * gain
        });
        let whole = TemplatePoints::support(&template).score(&lit, &pose);
        let reading = measure(&template, &lit, &pose).unwrap();
        assert!(reading.visible > 0.999, "{reading:?}");
        assert!(reading.visible_similarity > 0.95, "{reading:?}");
        assert!(
            whole < reading.visible_similarity - 0.02,
            "one ZNCC over the part {whole}, the cells' {reading:?}"
        );
    }

    #[test]
    fn an_unrelated_patch_is_mostly_not_visible() {
        let template = textured(36, 36, 1);
        let elsewhere = textured(120, 100, 99);
        let reading = measure(&template, &elsewhere, &at(60.0, 50.0)).unwrap();
        assert!(reading.visible < 0.3, "{reading:?}");
    }

    #[test]
    fn a_flat_template_has_no_coverage() {
        let flat = GrayImage32::from_fn(20, 20, |_, _| 0.5);
        assert!(measure(&flat, &textured(50, 50, 3), &at(25.0, 25.0)).is_none());
    }
}
