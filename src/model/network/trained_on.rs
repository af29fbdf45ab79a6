//! What a set of weights was trained on, carried inside the weights file.
//!
//! Why: the heads' angle and scales are only as good as the pairs they learnt from. A part whose
//! shape on the network's grid lies outside them (a template more elongated than any training
//! part, objects smaller or larger than any training object) gets peaks whose angle and scales
//! the verification must not trust. The trainer knows what it drew; the matcher needs to know
//! it at run time, for any weights file — so the record travels in the file (burnpack metadata,
//! key [`METADATA_KEY`], JSON), and `posematch weights show` prints it.
//!
//! Everything is on the network's template grid ([`super::TEMPLATE_GRID`], 36x36): the matcher
//! shows a `w x h` template squeezed onto the grid and resizes the frame isotropically by
//! `36 / sqrt(w·h)`, so a part at scale `s` lands on the grid at axis scales
//! `s·w / sqrt(w·h)` and `s·h / sqrt(w·h)` ([`GridShape::of_template`]).
//!
//! Weights without a record (the authors' checkpoint, a file written before records existed)
//! are trusted everywhere, as before.

use serde::{Deserialize, Serialize};

/// The burnpack metadata key that holds the record (JSON).
pub const METADATA_KEY: &str = "posematch.trained_on";

/// Shapes of parts on the template grid.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GridEnvelope {
    /// Axis scales of the parts on the template grid (object side over grid side), either
    /// axis; closed range.
    pub grid_scales: [f32; 2],
    /// The largest ratio between a part's two axis scales on the grid (1: square parts only).
    pub aspect_max: f32,
}

impl GridEnvelope {
    fn check(&self, name: &str) -> Result<(), TrainedOnError> {
        let [lo, hi] = self.grid_scales;
        if !(lo.is_finite() && hi.is_finite() && lo > 0.0 && lo <= hi) {
            return Err(TrainedOnError::Invalid(format!(
                "{name}.grid_scales must be 0 < low <= high, got [{lo}, {hi}]"
            )));
        }
        if !(self.aspect_max.is_finite() && self.aspect_max >= 1.0) {
            return Err(TrainedOnError::Invalid(format!(
                "{name}.aspect_max must be at least 1, got {}",
                self.aspect_max
            )));
        }
        Ok(())
    }

    fn union(&self, other: &Self) -> Self {
        Self {
            grid_scales: [
                self.grid_scales[0].min(other.grid_scales[0]),
                self.grid_scales[1].max(other.grid_scales[1]),
            ],
            aspect_max: self.aspect_max.max(other.aspect_max),
        }
    }

    /// What both envelopes hold; `None` when they share no scale.
    fn intersection(&self, other: &Self) -> Option<Self> {
        let lo = self.grid_scales[0].max(other.grid_scales[0]);
        let hi = self.grid_scales[1].min(other.grid_scales[1]);
        (lo <= hi).then_some(Self {
            grid_scales: [lo, hi],
            aspect_max: self.aspect_max.min(other.aspect_max),
        })
    }
}

/// What weights were trained on, all their runs together.
///
/// Two envelopes, because drawing a shape is not learning it: `seen` is everything any run
/// drew, some of it in a share of the pairs only; `throughout` is what every run drew in all
/// its pairs' ranges, where the heads were trained all along. The matcher trusts the heads
/// inside `throughout` only: the default weights saw 28x52 parts (axis scales 0.73 and 1.36
/// on the grid) in half the pairs of three fine-tunes, and their scale heads still read them
/// as nearly square (docs/verification.md, "Where the heads are not trusted").
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainedOn {
    /// Shapes every run trained on.
    pub throughout: GridEnvelope,
    /// Shapes any run drew.
    pub seen: GridEnvelope,
    /// Sides (width, height, pixels) of the templates the pairs were cut for, before the
    /// squeeze onto the grid.
    pub template_sides: Vec<[u32; 2]>,
    /// Most parts in one search window (1: one part per window).
    pub parts_per_window_max: u32,
    /// Sides of the square search windows (pixels).
    pub search_sides: Vec<u32>,
    /// Training pairs seen, all runs together (0 when not counted).
    #[serde(default)]
    pub pairs: u64,
    /// One line per run, oldest first: when, how long, on what.
    #[serde(default)]
    pub runs: Vec<String>,
}

/// Why a record could not be read or is not one.
#[derive(Debug, thiserror::Error)]
pub enum TrainedOnError {
    #[error(
        "not a training record ({0}); expected JSON with throughout, seen, template_sides, parts_per_window_max and search_sides"
    )]
    Json(#[from] serde_json::Error),
    #[error("training record: {0}")]
    Invalid(String),
}

impl TrainedOn {
    /// A run that drew every pair from `throughout`, some from as far as `seen`.
    pub fn run(
        throughout: GridEnvelope,
        seen: GridEnvelope,
        template_sides: [u32; 2],
        parts_per_window_max: u32,
        search_side: u32,
        pairs: u64,
        run: String,
    ) -> Self {
        Self {
            throughout,
            seen: seen.union(&throughout),
            template_sides: vec![template_sides],
            parts_per_window_max,
            search_sides: vec![search_side],
            pairs,
            runs: vec![run],
        }
    }

    /// Parses and checks a record (JSON).
    pub fn from_json(text: &str) -> Result<Self, TrainedOnError> {
        let record: Self = serde_json::from_str(text)?;
        record.check()?;
        Ok(record)
    }

    /// The record as JSON (what the weights file keeps).
    pub fn to_json(&self) -> String {
        serde_json::to_string(self).expect("a record of numbers and strings serialises")
    }

    fn check(&self) -> Result<(), TrainedOnError> {
        self.throughout.check("throughout")?;
        self.seen.check("seen")?;
        let invalid = |what: &str| Err(TrainedOnError::Invalid(what.into()));
        if self.template_sides.is_empty() || self.template_sides.iter().any(|s| s.contains(&0)) {
            return invalid("template_sides must list at least one non-zero width and height");
        }
        if self.parts_per_window_max == 0 {
            return invalid("parts_per_window_max must be at least 1");
        }
        if self.search_sides.is_empty() || self.search_sides.contains(&0) {
            return invalid("search_sides must list at least one non-zero side");
        }
        Ok(())
    }

    /// What weights trained on `self`'s pairs and then on `later`'s saw (a fine-tune, or a
    /// mix of two weights): `seen` everything either drew, `throughout` what both drew (the
    /// later one's alone when they share no scale).
    pub fn then(&self, later: &Self) -> Self {
        let mut template_sides: Vec<[u32; 2]> = self
            .template_sides
            .iter()
            .chain(&later.template_sides)
            .copied()
            .collect();
        template_sides.sort_unstable();
        template_sides.dedup();
        let mut search_sides: Vec<u32> = self
            .search_sides
            .iter()
            .chain(&later.search_sides)
            .copied()
            .collect();
        search_sides.sort_unstable();
        search_sides.dedup();
        Self {
            throughout: self
                .throughout
                .intersection(&later.throughout)
                .unwrap_or(later.throughout),
            seen: self.seen.union(&later.seen),
            template_sides,
            parts_per_window_max: self.parts_per_window_max.max(later.parts_per_window_max),
            search_sides,
            pairs: self.pairs + later.pairs,
            runs: self.runs.iter().chain(&later.runs).cloned().collect(),
        }
    }

    /// Where `shape` lies outside the shapes every run trained the heads on (`None`: inside,
    /// their angle and scales can be trusted).
    pub fn outside(&self, shape: &GridShape) -> Option<Outside> {
        // A hair of slack: a range's own bound is inside.
        const SLACK: f32 = 1.001;
        let GridEnvelope {
            grid_scales: [lo, hi],
            aspect_max,
        } = self.throughout;
        if shape.aspect > aspect_max * SLACK {
            Some(Outside::Aspect {
                aspect: shape.aspect,
                trained: aspect_max,
            })
        } else if shape.smallest < lo / SLACK || shape.largest > hi * SLACK {
            Some(Outside::Scales {
                smallest: shape.smallest,
                largest: shape.largest,
                trained: [lo, hi],
            })
        } else {
            None
        }
    }
}

/// How the parts of one search land on the network's grid.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GridShape {
    /// The smallest and largest axis scale a part may have there.
    pub smallest: f32,
    pub largest: f32,
    /// The ratio of the longer axis to the shorter.
    pub aspect: f32,
}

impl GridShape {
    /// The parts of a `width x height` template at scales `lo..=hi` (relative to the template),
    /// shown on the grid as the matcher shows them: frame resized by
    /// `grid / sqrt(width·height·lo·hi)` (`plan::scale_factor`), so the geometric mean of the
    /// range lands on the grid.
    pub fn of_template(width: u32, height: u32, (lo, hi): (f32, f32)) -> Self {
        let (w, h) = (width as f32, height as f32);
        let mean_side = (w * h).sqrt();
        let middle = (lo * hi).sqrt();
        let short = w.min(h) / mean_side;
        let long = w.max(h) / mean_side;
        Self {
            smallest: short * lo / middle,
            largest: long * hi / middle,
            aspect: long / short,
        }
    }
}

/// Where a search lies outside what the weights saw.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Outside {
    /// The part is more elongated than any training part.
    Aspect { aspect: f32, trained: f32 },
    /// The part's axis scales on the grid reach beyond the training range.
    Scales {
        smallest: f32,
        largest: f32,
        trained: [f32; 2],
    },
}

impl std::fmt::Display for Outside {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Aspect { aspect, trained } => write!(
                f,
                "the part's aspect {aspect:.2} exceeds the {trained:.2} the weights were trained on"
            ),
            Self::Scales {
                smallest,
                largest,
                trained,
            } => write!(
                f,
                "the part's axis scales on the network grid ({smallest:.2}–{largest:.2}) reach beyond the {:.2}–{:.2} the weights were trained on",
                trained[0], trained[1]
            ),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const S15: GridEnvelope = GridEnvelope {
        grid_scales: [0.8, 1.5],
        aspect_max: 1.875,
    };
    const WIDE: GridEnvelope = GridEnvelope {
        grid_scales: [0.5, 2.5],
        aspect_max: 3.5,
    };

    fn base() -> TrainedOn {
        TrainedOn::run(S15, S15, [36, 36], 1, 224, 1000, "base".into())
    }

    #[test]
    fn a_record_survives_json_and_refuses_nonsense() {
        let record = base();
        assert_eq!(TrainedOn::from_json(&record.to_json()).unwrap(), record);
        let mut bad = record.clone();
        bad.throughout.grid_scales = [1.5, 0.8];
        assert!(TrainedOn::from_json(&bad.to_json()).is_err());
        bad = record.clone();
        bad.seen.aspect_max = 0.5;
        assert!(TrainedOn::from_json(&bad.to_json()).is_err());
        bad = record.clone();
        bad.search_sides.clear();
        assert!(TrainedOn::from_json(&bad.to_json()).is_err());
        assert!(TrainedOn::from_json(r#"{"throughout": {"grid_scales": [1, 2]}}"#).is_err());
        assert!(TrainedOn::from_json("not json").is_err());
    }

    #[test]
    fn a_fine_tune_has_seen_what_either_run_saw_but_trained_throughout_only_on_what_both_did() {
        let wide = TrainedOn::run(S15, WIDE, [36, 36], 7, 160, 500, "wide".into());
        let both = base().then(&wide);
        assert_eq!(both.seen, WIDE);
        assert_eq!(both.throughout, S15);
        assert_eq!(both.template_sides, vec![[36, 36]]);
        assert_eq!(both.parts_per_window_max, 7);
        assert_eq!(both.search_sides, vec![160, 224]);
        assert_eq!(both.pairs, 1500);
        assert_eq!(both.runs, vec!["base".to_string(), "wide".into()]);
        let small_only = GridEnvelope {
            grid_scales: [0.3, 0.6],
            aspect_max: 1.2,
        };
        let later = TrainedOn::run(small_only, small_only, [12, 12], 1, 96, 10, "small".into());
        assert_eq!(
            base().then(&later).throughout,
            small_only,
            "no shared scale: the later run's"
        );
    }

    #[test]
    fn an_elongated_template_lands_on_the_grid_at_unequal_axis_scales() {
        // 28x52 at scale 1: sqrt(28·52) = 38.16, so 0.734 and 1.363 of the grid.
        let shape = GridShape::of_template(28, 52, (1.0, 1.0));
        assert!((shape.smallest - 0.734).abs() < 1e-3, "{shape:?}");
        assert!((shape.largest - 1.363).abs() < 1e-3, "{shape:?}");
        assert!((shape.aspect - 1.857).abs() < 1e-3, "{shape:?}");
        let record = base().then(&TrainedOn::run(
            S15,
            WIDE,
            [36, 36],
            7,
            160,
            500,
            "wide".into(),
        ));
        assert!(
            matches!(record.outside(&shape), Some(Outside::Scales { .. })),
            "0.73 is below the 0.8 that every run trained on, though one run drew it"
        );
        assert_eq!(
            record.outside(&GridShape::of_template(36, 36, (0.9, 1.1))),
            None
        );
        assert!(
            record
                .outside(&GridShape::of_template(36, 36, (0.8, 1.5)))
                .is_some(),
            "searched over 0.8–1.5, a square part lands at 0.73–1.37 of the grid"
        );
        assert_eq!(
            record.outside(&GridShape::of_template(12, 12, (1.0, 1.0))),
            None
        );
        let thin = GridShape::of_template(12, 60, (1.0, 1.0));
        assert!(matches!(
            record.outside(&thin),
            Some(Outside::Aspect { .. })
        ));
        let wide_throughout = TrainedOn::run(WIDE, WIDE, [36, 36], 1, 160, 1, "w".into());
        assert_eq!(wide_throughout.outside(&shape), None);
        assert!(
            wide_throughout.outside(&thin).is_some(),
            "aspect 5 is beyond 3.5"
        );
    }
}
