//! What a caller may ask of one match, with defaults and validation shared by the CLI and the
//! service. Options are checked once, where they enter (CLI arguments, settings, a gRPC
//! request): [`MatchOptions::validate`] turns them into [`ValidOptions`], the only form the
//! engine and the matcher accept, so nothing below the boundary checks them again.

use super::verification::Heads;
use crate::imaging::GrayImage32;
use std::ops::Deref;

/// Restricts answers to angles in `[start, start + extent]` (degrees, counter-clockwise).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AngleRange {
    pub start_deg: f32,
    /// In (0, 360]; 360 means every angle.
    pub extent_deg: f32,
}

impl AngleRange {
    /// From the inclusive bounds `a..=b` in degrees, `a <= b`, `b - a <= 360`.
    pub fn from_bounds(a: f32, b: f32) -> Result<Self, String> {
        let bounded = |v: f32| (-720.0..=720.0).contains(&v);
        if !(bounded(a) && bounded(b)) || b < a || b - a > 360.0 {
            return Err(format!(
                "angle range {a},{b} is invalid: give START,END in degrees within [-720, 720] with START <= END and END - START <= 360"
            ));
        }
        Ok(Self {
            start_deg: a,
            extent_deg: b - a,
        })
    }

    pub fn contains(&self, angle_deg: f32) -> bool {
        if self.extent_deg >= 360.0 {
            return true;
        }
        let offset = (angle_deg - self.start_deg).rem_euclid(360.0);
        offset <= self.extent_deg + 1e-4
    }

    /// Whether `angle_deg` lies in the range widened by `margin_deg` on both sides.
    pub fn contains_within(&self, angle_deg: f32, margin_deg: f32) -> bool {
        if self.extent_deg + 2.0 * margin_deg >= 360.0 {
            return true;
        }
        let offset = (angle_deg - self.start_deg + margin_deg).rem_euclid(360.0);
        offset <= self.extent_deg + 2.0 * margin_deg + 1e-4
    }
}

/// Both scales of an answer must lie in `[min, max]` (relative to the registered template).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScaleRange {
    pub min: f32,
    pub max: f32,
}

/// Relative slack of [`ScaleRange::contains`] (2 %).
pub const SCALE_TOLERANCE: f32 = 0.02;

/// Smallest and largest scale we accept in a range: beyond these the search image would be
/// resampled by more than 100x.
pub const SCALE_LIMITS: (f32, f32) = (0.05, 20.0);

impl ScaleRange {
    pub fn new(min: f32, max: f32) -> Result<Self, String> {
        if !(min.is_finite() && max.is_finite())
            || min <= 0.0
            || max < min
            || min < SCALE_LIMITS.0
            || max > SCALE_LIMITS.1
        {
            return Err(format!(
                "scale range {min},{max} is invalid: give LO,HI with {} <= LO <= HI <= {}",
                SCALE_LIMITS.0, SCALE_LIMITS.1
            ));
        }
        Ok(Self { min, max })
    }

    /// Whether an answer's scale lies in the range, within [`SCALE_TOLERANCE`]: the range
    /// steers the search, and a refined scale of an object right at a bound can come out a
    /// fraction of a percent beyond it.
    pub fn contains(&self, scale: f32) -> bool {
        scale >= self.min / (1.0 + SCALE_TOLERANCE) && scale <= self.max * (1.0 + SCALE_TOLERANCE)
    }
}

/// Which matcher answers a request.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Method {
    /// The TDCM network proposes, verification and refinement on the image decide.
    #[default]
    Tdcm,
    /// The classical matcher: exhaustive rotation x scale NCC over a pyramid, then the same
    /// refinement (no weights; seconds per image, see `classical.rs`).
    Ncc,
}

impl std::str::FromStr for Method {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s.trim().to_ascii_lowercase().as_str() {
            "tdcm" => Ok(Self::Tdcm),
            "ncc" => Ok(Self::Ncc),
            other => Err(format!(
                "method `{}` is unknown: use `tdcm` (the network) or `ncc` (classical)",
                other.chars().take(40).collect::<String>().escape_debug()
            )),
        }
    }
}

/// Which contrast a part may show against its registered template (Halcon `use_polarity` /
/// `ignore_global_polarity`, Matrox `M_POLARITY`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Polarity {
    /// As registered: bright where the template is bright.
    #[default]
    Same,
    /// Reversed: dark where the template is bright (a backlight, another coating).
    Reversed,
    /// Either; each answer says which ([`crate::geometry::Pose`] has no field for it: the
    /// answers' [`Contrast`] travels beside them). About twice the work of one.
    Either,
}

/// One of the two contrasts a search looks for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Contrast {
    Same,
    Reversed,
}

impl Polarity {
    /// The contrasts a search with this polarity looks for.
    pub fn contrasts(self) -> &'static [Contrast] {
        match self {
            Self::Same => &[Contrast::Same],
            Self::Reversed => &[Contrast::Reversed],
            Self::Either => &[Contrast::Same, Contrast::Reversed],
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Self::Same => "same",
            Self::Reversed => "reversed",
            Self::Either => "either",
        }
    }
}

impl std::str::FromStr for Polarity {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s.trim().to_ascii_lowercase().as_str() {
            "same" => Ok(Self::Same),
            "reversed" => Ok(Self::Reversed),
            "either" => Ok(Self::Either),
            other => Err(format!(
                "polarity `{}` is unknown: use same, reversed or either",
                other.chars().take(40).collect::<String>().escape_debug()
            )),
        }
    }
}

/// Options of one match request.
#[derive(Debug, Clone, PartialEq)]
pub struct MatchOptions {
    /// At most this many poses, best first.
    pub max_instances: usize,
    /// Answers scoring below this are not reported. With verification the score is the verified
    /// similarity of the template at the refined pose (`verification.rs`); with
    /// `verify` off it is the network's heatmap value. `None`: [`DEFAULT_MIN_SCORE`], or
    /// [`NETWORK_MIN_SCORE`] without verification ([`MatchOptions::effective_min_score`]).
    pub min_score: Option<f32>,
    /// Peaks of the network's heatmap at or above this are candidates for verification
    /// (ignored with `verify` off, where `min_score` selects the peaks).
    pub candidate_threshold: f32,
    /// Most candidates verified per search (each network tile proposes at most this many and
    /// the best of them all are kept); 0 means [`MatchOptions::candidate_budget`]'s automatic
    /// budget.
    pub max_candidates: usize,
    /// Two answers whose rotated boxes overlap more than this (IoU) are one object.
    pub max_overlap: f32,
    pub angle_range: Option<AngleRange>,
    /// Also steers how the search image is rescaled (see [`crate::matcher`]).
    pub scale_range: Option<ScaleRange>,
    /// Verify every candidate on the image (screen, then confirm the survivors with refinement),
    /// score them by similarity, and let the classical fallback search when nothing verifies.
    /// Off: the network's poses and heatmap values as they come (faster, less accurate; CLI
    /// `--no-refine`, proto `no_refine`).
    pub verify: bool,
    /// The network, or the classical NCC matcher.
    pub method: Method,
    /// With verification: when no candidate of the network verifies at `min_score` (a template
    /// with a mask: always), search the image with the classical matcher around the template's
    /// expected scale: four scale pairs, ÷ and × 1.2 on each axis (a masked template three
    /// scales 1.25 apart), where they fit its budget, else the expected scale alone
    /// (`classical::fallback_candidates`; small searches only). Off: the network's candidates
    /// alone (a frame without the part costs no more than one with it).
    pub classical_fallback: bool,
    /// Which contrast the part may show ([`Polarity`]); the network and the verification
    /// search each contrast asked for.
    pub polarity: Polarity,
    /// Answer within this many milliseconds of the request's arrival with what was verified
    /// by then, flagged as timed out, instead of finishing the search (Halcon `timeout`,
    /// Matrox `M_TIMEOUT`). The answer may come later by one unit of work: one network piece
    /// (a tile of a large frame) or one candidate's confirmation (docs/service.md). `None`:
    /// no limit.
    pub timeout_ms: Option<u32>,
    /// Whether the verification also tries the template without each quarter, for parts a
    /// clamp or a cable partly covers (`matcher/verification.rs`, docs/industrial.md).
    /// `None`: when `min_score` is below [`COVERED_PARTS_BELOW`] (a quarter covered scores
    /// about 0.75), and for a template with a mask: the network is shown the ignored pixels
    /// too, where the part looks different, so its candidates are weak and the quarter
    /// variants' own screens find what the masked template's alone miss (docs/industrial.md,
    /// "Masks"). Set by callers that lower `min_score` for their own reasons (the
    /// evaluation keeps every answer) to keep the caller's choice.
    pub covered_parts: Option<bool>,
    /// With several templates in one call: two answers of different templates whose boxes
    /// overlap more than `max_overlap` are one object, and only the better-scoring one is
    /// reported ([`super::selection::suppress_across_templates`]; Halcon's `find_shape_models`
    /// does this across models). Off: each template answers as a call of its own would.
    pub suppress_across_templates: bool,
}

/// A `min_score` below this says the caller expects partly covered parts
/// ([`MatchOptions::covered_parts`]).
pub const COVERED_PARTS_BELOW: f32 = 0.85;

/// Upper bound on `max_instances`: beyond this a request is almost certainly a mistake.
pub const MAX_INSTANCES_LIMIT: usize = 1000;

/// Upper bound on `timeout_ms`: ten minutes.
pub const MAX_TIMEOUT_MS: u32 = 600_000;

/// Upper bound on `max_candidates` (per search).
pub const MAX_CANDIDATES_LIMIT: usize = 4000;

/// Default `min_score` on the verified score: at most about 1 % of the answers on
/// multi-instance scenes of the tuning photos are not objects (docs/accuracy.md, "What a score means").
pub const DEFAULT_MIN_SCORE: f32 = 0.9;

/// Default `min_score` on the heatmap value when verification is off (the network-only path's
/// threshold before verification existed).
pub const NETWORK_MIN_SCORE: f32 = 0.5;

/// Default `candidate_threshold` (heatmap value; docs/verification.md).
pub const DEFAULT_CANDIDATE_THRESHOLD: f32 = 1e-5;

/// Fewest candidates verified per search by default: a weakly trained network's object is often
/// among its first few dozen peaks, not first (docs/verification.md).
pub const MIN_CANDIDATE_BUDGET: usize = 100;

impl Default for MatchOptions {
    fn default() -> Self {
        Self {
            max_instances: 10,
            min_score: None,
            candidate_threshold: DEFAULT_CANDIDATE_THRESHOLD,
            max_candidates: 0,
            max_overlap: 0.5,
            angle_range: None,
            scale_range: None,
            verify: true,
            method: Method::Tdcm,
            classical_fallback: true,
            polarity: Polarity::Same,
            timeout_ms: None,
            covered_parts: None,
            suppress_across_templates: false,
        }
    }
}

/// Automatic candidates per wanted instance where the heads are not trusted
/// ([`MatchOptions::candidate_budget_for`]). The 2048 frame of `cargo bench --bench frames`
/// (144 28x52 parts, `max_instances` 200, default weights, 4 frames): 3 per instance left 24
/// parts without a candidate within 16 px (recall 0.958), 4.5 left 2 (0.997), 6 none (1.000),
/// the screen 250 → 350 → 450 ms of a frame. Single 28x52 pairs (tuning photos, 200) gain
/// nothing from 200 candidates instead of 100 (92.5 % both); with one instance the budget stays
/// [`MIN_CANDIDATE_BUDGET`].
pub const UNTRUSTED_CANDIDATES_PER_INSTANCE: usize = 6;

impl MatchOptions {
    /// Whether partly covered parts are searched for with `template`
    /// ([`MatchOptions::covered_parts`]).
    pub fn expects_covered_parts(&self, template: &GrayImage32) -> bool {
        self.covered_parts.unwrap_or(
            self.effective_min_score() < COVERED_PARTS_BELOW || template.ignores_pixels(),
        )
    }

    /// Most candidates verified per search where the network's heads are trusted:
    /// `max_candidates`, or by default three per wanted instance and at least
    /// [`MIN_CANDIDATE_BUDGET`].
    pub fn candidate_budget(&self) -> usize {
        self.candidate_budget_for(Heads::Trusted)
    }

    /// [`MatchOptions::candidate_budget`] for heads trusted or not: where they are not, the
    /// heatmap's ranking is no better than its angle and scales, and the automatic budget is
    /// [`UNTRUSTED_CANDIDATES_PER_INSTANCE`] per wanted instance.
    pub fn candidate_budget_for(&self, heads: Heads) -> usize {
        let per_instance = match heads {
            Heads::Trusted => 3,
            Heads::Untrusted => UNTRUSTED_CANDIDATES_PER_INSTANCE,
        };
        match self.max_candidates {
            0 => (per_instance * self.max_instances).max(MIN_CANDIDATE_BUDGET),
            n => n,
        }
    }

    /// When a search that started at `start` must answer: `timeout_ms` later (`None`: no
    /// limit).
    pub fn answer_by(&self, start: std::time::Instant) -> Option<std::time::Instant> {
        self.timeout_ms
            .map(|ms| start + std::time::Duration::from_millis(u64::from(ms)))
    }

    /// The `min_score` in force: the one given, or the default for the path.
    pub fn effective_min_score(&self) -> f32 {
        self.min_score.unwrap_or(if self.verify {
            DEFAULT_MIN_SCORE
        } else {
            NETWORK_MIN_SCORE
        })
    }

    /// Checks every field; the message says what to change.
    pub fn validate(self) -> Result<ValidOptions, OptionsError> {
        self.check()?;
        Ok(ValidOptions(self))
    }

    fn check(&self) -> Result<(), OptionsError> {
        let invalid = |field, value: &dyn std::fmt::Display, allowed: String| {
            Err(OptionsError {
                field,
                value: value.to_string(),
                allowed,
            })
        };
        if self.max_instances == 0 || self.max_instances > MAX_INSTANCES_LIMIT {
            return invalid(
                "max_instances",
                &self.max_instances,
                format!("1..={MAX_INSTANCES_LIMIT}"),
            );
        }
        if let Some(min_score) = self.min_score
            && !(min_score > 0.0 && min_score < 1.0)
        {
            return invalid("min_score", &min_score, "a value in (0, 1)".into());
        }
        if !(self.candidate_threshold > 0.0 && self.candidate_threshold < 1.0) {
            return invalid(
                "candidate_threshold",
                &self.candidate_threshold,
                "a value in (0, 1)".into(),
            );
        }
        if self.max_candidates > MAX_CANDIDATES_LIMIT {
            return invalid(
                "max_candidates",
                &self.max_candidates,
                format!("1..={MAX_CANDIDATES_LIMIT}, or 0 for the automatic budget"),
            );
        }
        if !(self.max_overlap >= 0.0 && self.max_overlap <= 1.0) {
            return invalid("max_overlap", &self.max_overlap, "a value in [0, 1]".into());
        }
        if let Some(timeout_ms) = self.timeout_ms
            && !(1..=MAX_TIMEOUT_MS).contains(&timeout_ms)
        {
            return invalid(
                "timeout_ms",
                &timeout_ms,
                format!("1..={MAX_TIMEOUT_MS} milliseconds, or leave it unset for no limit"),
            );
        }
        Ok(())
    }
}

/// An option out of its range: which one, its value and what is allowed. Each front door words
/// it its own way (a request's `options.min_score`, a setting's `min_score = …`).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{field} {value} is invalid: use {allowed}")]
pub struct OptionsError {
    /// The option's name, as in the proto, the settings and the CLI (without dashes).
    pub field: &'static str,
    pub value: String,
    pub allowed: String,
}

impl OptionsError {
    /// Worded for the command line: `--max-instances 0 is invalid: use 1..=1000`.
    pub fn as_flag(&self) -> String {
        format!(
            "--{} {} is invalid: use {}",
            self.field.replace('_', "-"),
            self.value,
            self.allowed
        )
    }
}

/// [`MatchOptions`] that passed [`MatchOptions::validate`]. Read-only (it dereferences to the
/// options); to change a field, take the options out ([`ValidOptions::into_inner`]) and validate
/// again.
#[derive(Debug, Clone, PartialEq)]
pub struct ValidOptions(MatchOptions);

impl ValidOptions {
    pub fn into_inner(self) -> MatchOptions {
        self.0
    }

    /// Options derived inside the crate from validated ones, with a field deliberately outside
    /// the public range (evaluation asks for every peak, however weak). Never for caller input.
    pub(crate) fn derived(options: MatchOptions) -> Self {
        Self(options)
    }
}

impl Default for ValidOptions {
    fn default() -> Self {
        MatchOptions::default()
            .validate()
            .expect("the default options are valid")
    }
}

impl Deref for ValidOptions {
    type Target = MatchOptions;

    fn deref(&self) -> &MatchOptions {
        &self.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn untrusted_heads_get_twice_the_automatic_candidates_above_the_floor() {
        let frame = MatchOptions {
            max_instances: 200,
            ..MatchOptions::default()
        };
        assert_eq!(frame.candidate_budget(), 600);
        assert_eq!(frame.candidate_budget_for(Heads::Untrusted), 1200);
        let single = MatchOptions {
            max_instances: 1,
            ..MatchOptions::default()
        };
        assert_eq!(
            single.candidate_budget_for(Heads::Untrusted),
            MIN_CANDIDATE_BUDGET
        );
        let chosen = MatchOptions {
            max_candidates: 50,
            ..frame
        };
        assert_eq!(chosen.candidate_budget_for(Heads::Untrusted), 50);
    }

    #[test]
    fn defaults_are_valid_and_each_absurd_field_is_refused_by_name() {
        assert_eq!(*ValidOptions::default(), MatchOptions::default());
        let refused = |options: MatchOptions, field: &str| {
            let error = options.validate().unwrap_err();
            assert_eq!(error.field, field, "{error}");
            assert!(error.to_string().starts_with(field), "{field}: {error}");
        };
        let d = MatchOptions::default;
        refused(
            MatchOptions {
                max_instances: 0,
                ..d()
            },
            "max_instances",
        );
        refused(
            MatchOptions {
                min_score: Some(1.5),
                ..d()
            },
            "min_score",
        );
        refused(
            MatchOptions {
                candidate_threshold: f32::NAN,
                ..d()
            },
            "candidate_threshold",
        );
        refused(
            MatchOptions {
                max_candidates: MAX_CANDIDATES_LIMIT + 1,
                ..d()
            },
            "max_candidates",
        );
        refused(
            MatchOptions {
                max_overlap: -0.1,
                ..d()
            },
            "max_overlap",
        );
        refused(
            MatchOptions {
                timeout_ms: Some(0),
                ..d()
            },
            "timeout_ms",
        );
    }
}
