//! The service's domain layer, independent of gRPC: a registry of templates (durable on disk,
//! their encoded kernels in a bounded cache; [`registry`]) and matching through the batching
//! model thread ([`matching`]). This file holds what both share: the engine, its start-up and
//! its errors.
//!
//! The gRPC layer ([`crate::grpc`]) only converts messages and maps [`EngineError`] to status
//! codes; every rule about templates, limits and options lives here or below.

pub mod batcher;
mod matching;
pub mod metrics;
mod registry;
pub mod store;

use std::path::PathBuf;
use std::sync::{Arc, RwLock};

use tokio::sync::Mutex;

use crate::matcher::{EncodedTemplate, MatchError, Matcher};
use batcher::{Batcher, EncodeError};
pub use matching::{MatchAnswer, Roi};
pub use metrics::Metrics;
pub use registry::{
    DEFAULT_PAGE_SIZE, MAX_LABEL_KEY_BYTES, MAX_LABEL_VALUE_BYTES, MAX_LABELS, MAX_PAGE_SIZE,
    MAX_TEMPLATE_ID_BYTES,
};
use store::{StoreError, TemplateIndex, TemplateStore};

/// How the engine is sized.
#[derive(Debug, Clone)]
pub struct EngineConfig {
    /// Most search images in one forward pass.
    pub max_batch_size: usize,
    /// Most match requests waiting for the model; more are refused.
    pub queue_size: usize,
    /// Most encoded template kernels kept in memory.
    pub cache_size: u64,
    /// Where registered templates are persisted.
    pub template_dir: PathBuf,
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
        "template `{0}` is not registered; register it first (RegisterTemplate) or check the ID with ListTemplates"
    )]
    NotFound(String),
    #[error(
        "template `{0}` is already registered with a different image; pass replace=true to overwrite it or choose another template_id"
    )]
    AlreadyExists(String),
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
    store: Arc<TemplateStore>,
    index: RwLock<TemplateIndex>,
    /// Serialises registrations and deletions (the index and the disk change together).
    writes: Mutex<()>,
    kernels: moka::sync::Cache<String, Arc<EncodedTemplate>>,
    batcher: Batcher,
    /// One classical (NCC) search at a time: each keeps the cores busy for about a second.
    classical: tokio::sync::Semaphore,
    /// Compute budget of one network search, checked before it queues.
    max_network_pixels: u64,
    metrics: Metrics,
}

impl Engine {
    /// Opens the template directory (reading only metadata) and starts the model thread.
    pub fn start(
        config: &EngineConfig,
        matcher: Matcher,
        metrics: Metrics,
    ) -> Result<Self, EngineError> {
        let (store, opened) = TemplateStore::open(&config.template_dir)?;
        metrics.templates.set(opened.metas.len() as i64);
        metrics
            .store_files_set_aside
            .inc_by(opened.set_aside.len() as u64);
        let index: TemplateIndex = opened
            .metas
            .into_iter()
            .map(|m| (m.template_id.clone(), m))
            .collect();
        let evictions = metrics.cache_evictions.clone();
        let kernels = moka::sync::Cache::builder()
            .max_capacity(config.cache_size.max(1))
            .eviction_listener(move |_key, _value, cause| {
                if cause.was_evicted() {
                    evictions.inc();
                }
            })
            .build();
        let batcher = Batcher::spawn(
            matcher,
            config.max_batch_size,
            config.queue_size.max(1),
            metrics.clone(),
        );
        tracing::info!(
            templates = index.len(),
            dir = %config.template_dir.display(),
            "template registry opened"
        );
        Ok(Self {
            store: Arc::new(store),
            index: RwLock::new(index),
            writes: Mutex::new(()),
            kernels,
            batcher,
            classical: tokio::sync::Semaphore::new(1),
            max_network_pixels: config.max_network_pixels,
            metrics,
        })
    }

    pub fn metrics(&self) -> &Metrics {
        &self.metrics
    }

    /// Whether a registration could be written now (see [`TemplateStore::check_writable`]);
    /// the service reports NOT_SERVING while it cannot.
    pub async fn store_writable(&self) -> Result<(), EngineError> {
        let store = self.store.clone();
        Ok(blocking(move || store.check_writable()).await??)
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
