//! The service's domain layer, independent of gRPC: a registry of templates (durable in a
//! [`store`], a directory or a database shared by replicas; their encodings in a bounded,
//! coherent cache, [`template_cache`]; [`registry`]) and matching through the batching model thread
//! ([`matching`]). This file holds what they share: the engine, its start-up and its errors.
//!
//! The gRPC layer (`grpc/`) only converts messages and maps [`EngineError`] to status
//! codes; every rule about templates, limits and options lives here or below.

pub mod batcher;
mod calibrations;
mod matching;
pub mod metrics;
mod registry;
pub mod store;
mod template_cache;

use std::sync::Arc;
use std::time::Duration;

use crate::matcher::{MatchError, Matcher};
use batcher::{BatchLimits, Batcher, EncodeError, IDLE_RELEASE};
pub use matching::{MAX_TEMPLATES_PER_MATCH, MatchAnswer, Roi};
pub use metrics::Metrics;
pub use registry::{
    DEFAULT_PAGE_SIZE, MAX_LABEL_KEY_BYTES, MAX_LABEL_VALUE_BYTES, MAX_LABELS, MAX_PAGE_SIZE,
    MAX_TEMPLATE_ID_BYTES, RegisteredTemplate,
};
use store::{StoreError, StoreEvent, TemplateStore};
use template_cache::TemplateCache;

/// How the engine is sized.
#[derive(Debug, Clone)]
pub struct EngineConfig {
    /// Most search images in one forward pass.
    pub max_batch_size: usize,
    /// Most match requests waiting for the model; more are refused.
    pub queue_size: usize,
    /// Most encoded templates kept in memory.
    pub cache_size: u64,
    /// How long a database store may be unreachable before health reports NOT_SERVING.
    pub database_grace: Duration,
    /// Most network pixels one network search may need (its compute budget; see
    /// [`crate::matcher::check_network_budget`]).
    pub max_network_pixels: u64,
}

/// Why a request failed; each maps to one gRPC status code.
#[derive(Debug, thiserror::Error)]
pub enum EngineError {
    #[error("{0}")]
    InvalidArgument(String),
    #[error(
        "template {} is not registered; register it first (RegisterTemplate) or check the ID with ListTemplates",
        quoted(.0)
    )]
    NotFound(String),
    #[error(
        "template {} is already registered with a different image; pass replace=true to overwrite it or choose another template_id",
        quoted(.0)
    )]
    AlreadyExists(String),
    #[error(
        "calibration {} is not registered; register it first (RegisterCalibration) or check the ID with ListCalibrations",
        quoted(.0)
    )]
    CalibrationNotFound(String),
    #[error(
        "calibration {} is already registered with other points or another unit; pass replace=true to overwrite it or choose another calibration_id",
        quoted(.0)
    )]
    CalibrationExists(String),
    #[error("{0}")]
    ResourceExhausted(String),
    #[error("{0}")]
    DeadlineExceeded(String),
    #[error("{0}")]
    Unavailable(String),
    /// A failure of ours, not the request's (a background task died).
    #[error("{0}")]
    Internal(String),
    /// The matcher refused the request (sizes, options, too much work).
    #[error(transparent)]
    Match(#[from] MatchError),
    /// The template store failed (disk, permissions); never the request's fault.
    #[error(transparent)]
    Store(#[from] StoreError),
}

/// Most characters of a client's text (a template ID, a label) quoted in an error message: a
/// status message travels in a header, and clients refuse a header of a megabyte.
pub const MAX_QUOTED_CHARS: usize = 100;

/// `text` in backquotes for an error message: control characters escaped, at most
/// [`MAX_QUOTED_CHARS`] characters of it, and its length in bytes when cut.
pub fn quoted(text: &str) -> String {
    let escaped: String = text.escape_debug().take(MAX_QUOTED_CHARS).collect();
    if text.escape_debug().nth(MAX_QUOTED_CHARS).is_some() {
        format!("`{escaped}…` ({} bytes)", text.len())
    } else {
        format!("`{escaped}`")
    }
}

impl From<EncodeError> for EngineError {
    /// Encoding a template: the template's own problem, or the model thread is gone.
    fn from(e: EncodeError) -> Self {
        match e {
            EncodeError::Match(e) => Self::InvalidArgument(format!("template: {e}")),
            EncodeError::Gone(e) => Self::Unavailable(e.to_string()),
            EncodeError::ModelFailed => Self::Internal(e.to_string()),
        }
    }
}

/// Templates plus the model.
pub struct Engine {
    store: TemplateStore,
    /// Whether this replica counts its own writes in the `templates` gauge (a directory); a
    /// shared store announces every write, this replica's included, and the count follows
    /// the announcements.
    counts_own_writes: bool,
    template_cache: Arc<TemplateCache>,
    batcher: Batcher,
    /// One classical (NCC) search at a time: each keeps the cores busy for about a second.
    classical: tokio::sync::Semaphore,
    /// Compute budget of one network search, checked before it queues.
    max_network_pixels: u64,
    database_grace: Duration,
    metrics: Metrics,
}

impl Engine {
    /// Starts the model thread over an opened store, and follows the store's announcements of
    /// other replicas' changes. Runs inside the async runtime.
    pub fn start(
        config: &EngineConfig,
        store: TemplateStore,
        templates: usize,
        matcher: Matcher,
        metrics: Metrics,
    ) -> Self {
        metrics.templates.set(templates as i64);
        let template_cache = Arc::new(TemplateCache::new(
            config.cache_size,
            metrics.cache_evictions.clone(),
        ));
        let events = store.take_events();
        let counts_own_writes = events.is_none();
        if let Some(mut events) = events {
            let (template_cache, templates) = (template_cache.clone(), metrics.templates.clone());
            tokio::spawn(async move {
                while let Some(event) = events.recv().await {
                    match event {
                        StoreEvent::Changed {
                            template_id,
                            content_sha256,
                            created,
                        } => {
                            template_cache.changed(&template_id, content_sha256.as_deref());
                            // Every write is announced, this replica's own included: the
                            // count follows announcements (store checks set it exactly).
                            if created {
                                templates.inc();
                            } else if content_sha256.is_none() {
                                templates.dec();
                            }
                        }
                        StoreEvent::Resynchronise => template_cache.clear(),
                    }
                }
            });
        }
        let batcher = Batcher::spawn(
            matcher,
            BatchLimits {
                max_batch_size: config.max_batch_size,
                queue_size: config.queue_size,
                idle_release: IDLE_RELEASE,
            },
            metrics.clone(),
        );
        Self {
            store,
            counts_own_writes,
            template_cache,
            batcher,
            classical: tokio::sync::Semaphore::new(1),
            max_network_pixels: config.max_network_pixels,
            database_grace: config.database_grace,
            metrics,
        }
    }

    pub fn metrics(&self) -> &Metrics {
        &self.metrics
    }

    /// Whether registrations could be written now ([`TemplateStore::check`]); refreshes the
    /// template count, which other replicas may have changed.
    pub async fn check_store(&self) -> Result<(), StoreError> {
        let count = self.store.check().await?;
        self.metrics.templates.set(count as i64);
        Ok(())
    }

    /// How long [`Engine::check_store`] may fail before health reports NOT_SERVING.
    pub fn store_grace(&self) -> Duration {
        self.store.health_grace(self.database_grace)
    }

    /// True while the model thread runs (see [`Batcher::alive`]): the service's health.
    pub fn model_alive(&self) -> tokio::sync::watch::Receiver<bool> {
        self.batcher.alive()
    }

    /// Whether a match request may go on to decode its image: RESOURCE_EXHAUSTED at once, with
    /// nothing allocated, when the model's queue is already full.
    pub fn admit_match(&self) -> Result<(), EngineError> {
        self.batcher
            .check_room()
            .map_err(|full| EngineError::ResourceExhausted(full.to_string()))
    }
}

/// Runs file and hashing work off the async runtime's threads.
async fn blocking<T: Send + 'static>(
    work: impl FnOnce() -> T + Send + 'static,
) -> Result<T, EngineError> {
    tokio::task::spawn_blocking(work)
        .await
        .map_err(|e| EngineError::Internal(format!("background task failed: {e}")))
}
