//! The bounded cache of encoded templates, kept coherent with the template store.
//!
//! Matching a cached template needs nothing from the store (so it keeps working while a
//! database is down); what makes that safe is that every change reaches the cache:
//! - a write or delete through this replica updates or drops its own entry;
//! - a change announced by the store (another replica's write) drops the entry unless it
//!   already holds the announced content; a lost announcement channel drops everything.
//!
//! An encoding from the store is slow to produce (read, decode, encode on the model thread),
//! and a change may be announced meanwhile. Every change is therefore numbered, and a read may
//! only insert what it read if no change to *that* template was seen since it began
//! ([`ReadTicket`]), or the latest one announced exactly the content it read: a slow read can
//! never put back what a change removed, and a change to another template (the usual case with
//! several replicas registering) does not stop this one from being cached.

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use crate::matcher::EncodedTemplate;

/// How many templates' latest changes are remembered before they are forgotten together
/// (reads then in flight are simply not cached: safe, and rare).
const REMEMBERED_CHANGES: usize = 4096;

#[derive(Clone)]
struct CachedTemplate {
    content_sha256: String,
    encoded: Arc<EncodedTemplate>,
}

/// When a read from the store began, in changes seen (see the module docs).
#[derive(Debug, Clone, Copy)]
pub struct ReadTicket(u64);

/// The changes seen, numbered in the order they were seen.
#[derive(Default)]
struct Changes {
    /// The number of the latest change.
    seen: u64,
    /// Reads that began before this change number may not insert: everything was dropped
    /// (a lost announcement channel) or the per-template record was forgotten.
    forgotten_before: u64,
    /// Per template: the number of its latest change and the content it then held
    /// (`None`: deleted or unknown).
    latest: HashMap<String, (u64, Option<String>)>,
}

impl Changes {
    fn record(&mut self, template_id: &str, content_sha256: Option<&str>) {
        self.seen += 1;
        if self.latest.len() >= REMEMBERED_CHANGES && !self.latest.contains_key(template_id) {
            self.latest.clear();
            self.forgotten_before = self.seen;
        }
        self.latest.insert(
            template_id.to_owned(),
            (self.seen, content_sha256.map(str::to_owned)),
        );
    }

    /// Whether content `content_sha256` of `template_id`, read or written after `ticket`, is
    /// still current as far as the changes seen tell.
    fn still_current(&self, template_id: &str, content_sha256: &str, ticket: ReadTicket) -> bool {
        if ticket.0 < self.forgotten_before {
            return false;
        }
        match self.latest.get(template_id) {
            Some((number, announced)) if *number > ticket.0 => {
                announced.as_deref() == Some(content_sha256)
            }
            _ => true,
        }
    }
}

pub struct TemplateCache {
    cache: moka::sync::Cache<String, CachedTemplate>,
    /// Held while the cache changes, so a check and an insert are one step.
    changes: Mutex<Changes>,
}

impl TemplateCache {
    /// At most `capacity` templates; `evictions` counts the ones pushed out by size.
    pub fn new(capacity: u64, evictions: prometheus::IntCounter) -> Self {
        let cache = moka::sync::Cache::builder()
            .max_capacity(capacity.max(1))
            .eviction_listener(move |_key, _value, cause| {
                if cause.was_evicted() {
                    evictions.inc();
                }
            })
            .build();
        Self {
            cache,
            changes: Mutex::new(Changes::default()),
        }
    }

    pub fn get(&self, template_id: &str) -> Option<Arc<EncodedTemplate>> {
        self.cache.get(template_id).map(|c| c.encoded)
    }

    /// Taken before reading a template from the store.
    pub fn ticket(&self) -> ReadTicket {
        ReadTicket(self.changes.lock().expect("cache lock").seen)
    }

    /// Caches an encoding of a template read from the store, unless a change to it that
    /// announced other content was seen since `ticket`.
    pub fn insert_read(
        &self,
        template_id: &str,
        content_sha256: &str,
        encoded: Arc<EncodedTemplate>,
        ticket: ReadTicket,
    ) -> bool {
        let changes = self.changes.lock().expect("cache lock");
        if !changes.still_current(template_id, content_sha256, ticket) {
            return false;
        }
        self.cache.insert(
            template_id.to_owned(),
            CachedTemplate {
                content_sha256: content_sha256.to_owned(),
                encoded,
            },
        );
        true
    }

    /// This replica committed `encoded` as `template_id`'s new content; `ticket` was taken
    /// before the write. Cached unless a change to it announcing other content was seen in
    /// between (then it is only dropped: the order of the two is unknown here, the store knows).
    pub fn insert_written(
        &self,
        template_id: &str,
        content_sha256: &str,
        encoded: Arc<EncodedTemplate>,
        ticket: ReadTicket,
    ) {
        let mut changes = self.changes.lock().expect("cache lock");
        let unchanged = changes.still_current(template_id, content_sha256, ticket);
        if unchanged {
            changes.record(template_id, Some(content_sha256));
            self.cache.insert(
                template_id.to_owned(),
                CachedTemplate {
                    content_sha256: content_sha256.to_owned(),
                    encoded,
                },
            );
        } else {
            changes.record(template_id, None);
            self.cache.invalidate(template_id);
        }
    }

    /// `template_id` changed: now holds `content_sha256`, or is deleted (`None`). An entry that
    /// already holds that content stays.
    pub fn changed(&self, template_id: &str, content_sha256: Option<&str>) {
        let mut changes = self.changes.lock().expect("cache lock");
        changes.record(template_id, content_sha256);
        let current = self
            .cache
            .get(template_id)
            .is_some_and(|c| Some(c.content_sha256.as_str()) == content_sha256);
        if !current {
            self.cache.invalidate(template_id);
        }
    }

    /// Anything may have changed: drop every entry.
    pub fn clear(&self) {
        let mut changes = self.changes.lock().expect("cache lock");
        changes.seen += 1;
        changes.forgotten_before = changes.seen;
        changes.latest.clear();
        self.cache.invalidate_all();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::imaging::GrayImage32;

    fn encoded(width: u32) -> Arc<EncodedTemplate> {
        let device = Default::default();
        Arc::new(EncodedTemplate {
            width,
            height: 8,
            kernel: burn::prelude::Tensor::zeros([1, 1, 1, 1], &device),
            gray: Arc::new(GrayImage32::from_fn(width as usize, 8, |_, _| 0.0)),
            reversed_kernel: burn::prelude::Tensor::zeros([1, 1, 1, 1], &device),
            reversed_gray: Arc::new(GrayImage32::from_fn(width as usize, 8, |_, _| 1.0)),
            origin: None,
        })
    }

    fn cache() -> TemplateCache {
        TemplateCache::new(10, prometheus::IntCounter::new("e", "e").unwrap())
    }

    #[test]
    fn a_read_that_overlaps_a_change_is_not_cached() {
        let cache = cache();
        let ticket = cache.ticket();
        // Another replica replaces `t` while this one reads and encodes the old content.
        cache.changed("t", Some("new"));
        assert!(!cache.insert_read("t", "old", encoded(8), ticket));
        assert!(cache.get("t").is_none());
        let ticket = cache.ticket();
        assert!(cache.insert_read("t", "new", encoded(9), ticket));
        assert_eq!(cache.get("t").unwrap().width, 9);
    }

    #[test]
    fn a_read_is_cached_when_only_other_templates_changed_meanwhile() {
        let cache = cache();
        let ticket = cache.ticket();
        // Another replica registers `u` while this one reads `t`.
        cache.changed("u", Some("u1"));
        assert!(cache.insert_read("t", "t1", encoded(8), ticket));
        assert!(cache.get("t").is_some());
    }

    #[test]
    fn a_read_is_cached_when_the_change_meanwhile_announced_what_it_read() {
        let cache = cache();
        let ticket = cache.ticket();
        // The announcement of the registration this read found arrives while it encodes.
        cache.changed("t", Some("new"));
        assert!(cache.insert_read("t", "new", encoded(8), ticket));
        // Deleted, then re-registered with other content, both during one read: not cached.
        let ticket = cache.ticket();
        cache.changed("t", None);
        cache.changed("t", Some("newer"));
        assert!(!cache.insert_read("t", "new", encoded(8), ticket));
        assert!(cache.get("t").is_none());
    }

    #[test]
    fn a_read_overlapping_a_resynchronisation_or_forgotten_changes_is_not_cached() {
        let cache = cache();
        let ticket = cache.ticket();
        cache.clear();
        assert!(!cache.insert_read("t", "t1", encoded(8), ticket));
        let ticket = cache.ticket();
        for i in 0..=REMEMBERED_CHANGES {
            cache.changed(&format!("other{i}"), Some("x"));
        }
        // The record of what changed was forgotten to stay bounded: `t` may have been in it.
        assert!(!cache.insert_read("t", "t1", encoded(8), ticket));
        assert!(cache.insert_read("t", "t1", encoded(8), cache.ticket()));
    }

    #[test]
    fn announcements_drop_stale_entries_and_keep_current_ones() {
        let cache = cache();
        cache.insert_written("t", "a", encoded(8), cache.ticket());
        cache.changed("t", Some("a")); // our own write, announced back
        assert!(cache.get("t").is_some());
        cache.changed("t", Some("b"));
        assert!(cache.get("t").is_none());
        cache.insert_written("t", "b", encoded(8), cache.ticket());
        cache.changed("t", None);
        assert!(cache.get("t").is_none());
        cache.insert_written("u", "u", encoded(8), cache.ticket());
        cache.clear();
        assert!(cache.get("u").is_none());
    }

    #[test]
    fn a_local_write_overtaken_by_an_announcement_is_dropped() {
        let cache = cache();
        cache.insert_written("t", "a", encoded(8), cache.ticket());
        let ticket = cache.ticket();
        cache.changed("t", Some("c")); // committed elsewhere, after or before ours: unknown
        cache.insert_written("t", "b", encoded(9), ticket);
        assert!(cache.get("t").is_none());
    }
}
