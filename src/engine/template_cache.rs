//! The bounded cache of encoded templates, kept coherent with the template store.
//!
//! Matching a cached template needs nothing from the store (so it keeps working while a
//! database is down); what makes that safe is that every change reaches the cache:
//! - a write or delete through this replica updates or drops its own entry;
//! - a change announced by the store (another replica's write) drops the entry unless it
//!   already holds the announced content; a lost announcement channel drops everything.
//!
//! An encoding from the store is slow to produce (read, decode, encode on the model thread),
//! and a change may be announced meanwhile. Every change therefore advances a counter, and a
//! read may only insert what it read if the counter has not moved since it began ([`ReadTicket`]):
//! a slow read can never put back what a change removed.

use std::sync::{Arc, Mutex};

use crate::matcher::EncodedTemplate;

#[derive(Clone)]
struct CachedTemplate {
    content_sha256: String,
    encoded: Arc<EncodedTemplate>,
}

/// When a read from the store began, in changes seen (see the module docs).
#[derive(Debug, Clone, Copy)]
pub struct ReadTicket(u64);

pub struct TemplateCache {
    cache: moka::sync::Cache<String, CachedTemplate>,
    /// Changes seen so far; held while the cache changes, so a check and an insert are one step.
    changes: Mutex<u64>,
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
            changes: Mutex::new(0),
        }
    }

    pub fn get(&self, template_id: &str) -> Option<Arc<EncodedTemplate>> {
        self.cache.get(template_id).map(|c| c.encoded)
    }

    /// Taken before reading a template from the store.
    pub fn ticket(&self) -> ReadTicket {
        ReadTicket(*self.changes.lock().expect("cache lock"))
    }

    /// Caches an encoding of a template read from the store, unless a change was seen since `ticket`.
    pub fn insert_read(
        &self,
        template_id: &str,
        content_sha256: &str,
        encoded: Arc<EncodedTemplate>,
        ticket: ReadTicket,
    ) -> bool {
        let changes = self.changes.lock().expect("cache lock");
        if *changes != ticket.0 {
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
    /// before the write. Cached unless another change was seen in between (then it is only
    /// dropped: the order of the two is unknown here, the store knows).
    pub fn insert_written(
        &self,
        template_id: &str,
        content_sha256: &str,
        encoded: Arc<EncodedTemplate>,
        ticket: ReadTicket,
    ) {
        let mut changes = self.changes.lock().expect("cache lock");
        let unchanged = *changes == ticket.0;
        *changes += 1;
        if unchanged {
            self.cache.insert(
                template_id.to_owned(),
                CachedTemplate {
                    content_sha256: content_sha256.to_owned(),
                    encoded,
                },
            );
        } else {
            self.cache.invalidate(template_id);
        }
    }

    /// `template_id` changed: now holds `content_sha256`, or is deleted (`None`). An entry that
    /// already holds that content stays.
    pub fn changed(&self, template_id: &str, content_sha256: Option<&str>) {
        let mut changes = self.changes.lock().expect("cache lock");
        *changes += 1;
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
        *changes += 1;
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
