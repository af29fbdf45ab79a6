//! The time limit of one search (`timeout_ms`): work not started by then is left out, and the
//! search says so.
//!
//! Why a type: both searches (the verification of the network's candidates and the classical
//! matcher) check the limit from parallel workers, before each unit of work, and must report
//! afterwards whether any unit was left out.

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

/// When a search must answer (`None`: no limit) and whether it has had to leave work out.
#[derive(Debug)]
pub struct TimeLimit {
    answer_by: Option<Instant>,
    missed: AtomicBool,
}

impl TimeLimit {
    pub fn new(answer_by: Option<Instant>) -> Self {
        Self {
            answer_by,
            missed: AtomicBool::new(false),
        }
    }

    /// Whether there is still time to start a unit of work; a "no" is remembered
    /// ([`TimeLimit::missed`]).
    pub fn in_time(&self) -> bool {
        let on_time = self.answer_by.is_none_or(|due| Instant::now() < due);
        if !on_time {
            self.missed.store(true, Ordering::Relaxed);
        }
        on_time
    }

    /// Whether any unit of work was left out because the time had come.
    pub fn missed(&self) -> bool {
        self.missed.load(Ordering::Relaxed)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn a_passed_limit_is_remembered_and_no_limit_never_passes() {
        let unlimited = TimeLimit::new(None);
        assert!(unlimited.in_time() && !unlimited.missed());
        let future = TimeLimit::new(Some(Instant::now() + Duration::from_secs(60)));
        assert!(future.in_time() && !future.missed());
        let past = TimeLimit::new(Some(Instant::now() - Duration::from_millis(1)));
        assert!(!past.missed(), "nothing was left out before anyone asked");
        assert!(!past.in_time());
        assert!(past.missed());
    }
}
