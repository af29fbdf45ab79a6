//! What a caller may ask of one match, with defaults and validation shared by the CLI and the
//! service.

use crate::geometry::wrap_angle_deg;

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
        if !(a.is_finite() && b.is_finite()) || b < a || b - a > 360.0 {
            return Err(format!(
                "angle range {a},{b} is invalid: give START,END in degrees with START <= END and END - START <= 360"
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

    /// The middle of the range in (−180, 180].
    pub fn centre_deg(&self) -> f32 {
        wrap_angle_deg(self.start_deg + self.extent_deg / 2.0)
    }
}

/// Both scales of an answer must lie in `[min, max]` (relative to the registered template).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScaleRange {
    pub min: f32,
    pub max: f32,
}

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

    pub fn contains(&self, scale: f32) -> bool {
        scale >= self.min * 0.999 && scale <= self.max * 1.001
    }
}

/// Options of one match request.
#[derive(Debug, Clone, PartialEq)]
pub struct MatchOptions {
    /// At most this many poses, best first.
    pub max_instances: usize,
    /// Peaks of the score map below this are not objects.
    pub min_score: f32,
    /// Two answers whose rotated boxes overlap more than this (IoU) are one object.
    pub max_overlap: f32,
    pub angle_range: Option<AngleRange>,
    /// Also steers how the search image is rescaled (see [`crate::matcher`]).
    pub scale_range: Option<ScaleRange>,
    /// Geometric refinement of each pose (added by the precision work; the coarse network pose
    /// is returned either way).
    pub refine: bool,
}

/// Upper bound on `max_instances`: beyond this a request is almost certainly a mistake.
pub const MAX_INSTANCES_LIMIT: usize = 1000;

impl Default for MatchOptions {
    fn default() -> Self {
        Self {
            max_instances: 10,
            min_score: 0.5,
            max_overlap: 0.5,
            angle_range: None,
            scale_range: None,
            refine: true,
        }
    }
}

impl MatchOptions {
    /// Checks every field; the message says what to change.
    pub fn validate(&self) -> Result<(), String> {
        if self.max_instances == 0 || self.max_instances > MAX_INSTANCES_LIMIT {
            return Err(format!(
                "max_instances {} is invalid: use 1..={MAX_INSTANCES_LIMIT}",
                self.max_instances
            ));
        }
        if !(self.min_score > 0.0 && self.min_score < 1.0) {
            return Err(format!(
                "min_score {} is invalid: use a value in (0, 1)",
                self.min_score
            ));
        }
        if !(self.max_overlap >= 0.0 && self.max_overlap <= 1.0) {
            return Err(format!(
                "max_overlap {} is invalid: use a value in [0, 1]",
                self.max_overlap
            ));
        }
        Ok(())
    }
}
