//! The service's domain layer, independent of gRPC: a registry of templates (durable on disk,
//! their encoded kernels in a bounded cache) and matching through the batching model thread.
//!
//! The gRPC layer ([`crate::service`]) only converts messages and maps [`EngineError`] to status
//! codes; every rule about templates, limits and options lives here or below.

pub mod batcher;
pub mod metrics;
pub mod store;

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::{Arc, RwLock};
use std::time::{Instant, SystemTime, UNIX_EPOCH};

use tokio::sync::{Mutex, oneshot};

use crate::geometry::Pose;
use crate::imaging::RgbImage32;
use crate::matcher::{EncodedTemplate, MatchError, MatchTimings, Matcher, ValidOptions};
use batcher::{BatchError, Batcher, EncodeError, MatchWork, SubmitError};
pub use metrics::Metrics;
use store::{StoreError, TemplateIndex, TemplateMeta, TemplateStore, content_sha256};

/// Longest accepted template ID, in bytes.
pub const MAX_TEMPLATE_ID_BYTES: usize = 256;
/// Most labels per template, and the longest key and value.
pub const MAX_LABELS: usize = 64;
pub const MAX_LABEL_KEY_BYTES: usize = 128;
pub const MAX_LABEL_VALUE_BYTES: usize = 1024;
/// `ListTemplates` page size when none is given, and the largest allowed.
pub const DEFAULT_PAGE_SIZE: usize = 100;
pub const MAX_PAGE_SIZE: usize = 1000;

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
        }
    }
}

/// A rectangle of the search image to restrict the search to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Roi {
    pub x: u32,
    pub y: u32,
    pub width: u32,
    pub height: u32,
}

/// The answer to one match.
#[derive(Debug, Clone)]
pub struct MatchAnswer {
    /// In the full image's coordinates, best first.
    pub poses: Vec<Pose>,
    pub timings: MatchTimings,
    pub queue_ms: f64,
    pub batch_size: usize,
}

/// Templates plus the model.
pub struct Engine {
    store: Arc<TemplateStore>,
    index: RwLock<TemplateIndex>,
    /// Serialises registrations and deletions (the index and the disk change together).
    writes: Mutex<()>,
    kernels: moka::sync::Cache<String, Arc<EncodedTemplate>>,
    batcher: Batcher,
    metrics: Metrics,
}

impl Engine {
    /// Opens the template directory (reading only metadata) and starts the model thread.
    pub fn start(
        config: &EngineConfig,
        matcher: Matcher,
        metrics: Metrics,
    ) -> Result<Self, EngineError> {
        let (store, metas) = TemplateStore::open(&config.template_dir)?;
        metrics.templates.set(metas.len() as i64);
        let index: TemplateIndex = metas
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
            metrics,
        })
    }

    pub fn metrics(&self) -> &Metrics {
        &self.metrics
    }

    /// Registers `image` under `template_id` (derived from the content when empty). The same
    /// image under the same ID is a no-op; a different one needs `replace`. Returns once the
    /// template is on disk.
    pub async fn register(
        &self,
        template_id: &str,
        image: RgbImage32,
        replace: bool,
        labels: BTreeMap<String, String>,
    ) -> Result<TemplateMeta, EngineError> {
        check_labels(&labels)?;
        let image = Arc::new(image);
        let hashed = image.clone();
        let content = blocking(move || content_sha256(&hashed)).await?;
        let template_id = if template_id.is_empty() {
            format!("tpl-{}", &content[..16])
        } else {
            check_template_id(template_id)?;
            template_id.to_owned()
        };
        let _writing = self.writes.lock().await;
        if let Some(existing) = self.lookup(&template_id) {
            if existing.content_sha256 == content {
                return Ok(existing);
            }
            if !replace {
                return Err(EngineError::AlreadyExists(template_id));
            }
        }
        // Encoding validates the template (size limits) before anything is written.
        let encoded = self.batcher.encode((*image).clone()).await?;
        let meta = TemplateMeta {
            template_id: template_id.clone(),
            width: image.width,
            height: image.height,
            labels,
            content_sha256: content,
            created_unix_ms: SystemTime::now()
                .duration_since(UNIX_EPOCH)
                .map_or(0, |d| d.as_millis() as i64),
        };
        let (saved_meta, store) = (meta.clone(), self.store.clone());
        blocking(move || store.save(&saved_meta, &image)).await??;
        let count = {
            let mut index = self.index.write().expect("index lock");
            index.insert(template_id.clone(), meta.clone());
            index.len()
        };
        self.metrics.templates.set(count as i64);
        self.kernels.insert(template_id, Arc::new(encoded));
        Ok(meta)
    }

    fn lookup(&self, template_id: &str) -> Option<TemplateMeta> {
        self.index
            .read()
            .expect("index lock")
            .get(template_id)
            .cloned()
    }

    pub fn get(&self, template_id: &str) -> Result<TemplateMeta, EngineError> {
        self.lookup(template_id)
            .ok_or_else(|| EngineError::NotFound(template_id.to_owned()))
    }

    /// One page of templates in ID order; the token is where the next page starts.
    pub fn list(
        &self,
        page_size: usize,
        page_token: &str,
    ) -> Result<(Vec<TemplateMeta>, String), EngineError> {
        let page_size = match page_size {
            0 => DEFAULT_PAGE_SIZE,
            n if n > MAX_PAGE_SIZE => {
                return Err(EngineError::InvalidArgument(format!(
                    "page_size {n} is too large: use at most {MAX_PAGE_SIZE} (0 means {DEFAULT_PAGE_SIZE})"
                )));
            }
            n => n,
        };
        let after = if page_token.is_empty() {
            None
        } else {
            let bytes = hex::decode(page_token).map_err(|_| {
                EngineError::InvalidArgument(
                    "page_token is not one this server issued; pass next_page_token from the previous response, or empty for the first page".into(),
                )
            })?;
            Some(String::from_utf8(bytes).map_err(|_| {
                EngineError::InvalidArgument("page_token is not one this server issued".into())
            })?)
        };
        let index = self.index.read().expect("index lock");
        let mut ids: Vec<&String> = index
            .keys()
            .filter(|id| after.as_ref().is_none_or(|a| *id > a))
            .collect();
        ids.sort();
        let page: Vec<TemplateMeta> = ids
            .iter()
            .take(page_size)
            .map(|id| index[*id].clone())
            .collect();
        let next = if ids.len() > page_size {
            hex::encode(page.last().expect("non-empty page").template_id.as_bytes())
        } else {
            String::new()
        };
        Ok((page, next))
    }

    /// Removes a template from disk, index and cache. `false` when it was not registered.
    pub async fn delete(&self, template_id: &str) -> Result<bool, EngineError> {
        let _writing = self.writes.lock().await;
        if self.lookup(template_id).is_none() {
            return Ok(false);
        }
        let (store, id) = (self.store.clone(), template_id.to_owned());
        blocking(move || store.remove(&id)).await??;
        let count = {
            let mut index = self.index.write().expect("index lock");
            index.remove(template_id);
            index.len()
        };
        self.metrics.templates.set(count as i64);
        self.kernels.invalidate(template_id);
        Ok(true)
    }

    /// The template's kernel: from the cache, or read from disk and encoded on the model thread.
    async fn kernel(&self, template_id: &str) -> Result<Arc<EncodedTemplate>, EngineError> {
        if let Some(kernel) = self.kernels.get(template_id) {
            self.metrics.cache_hits.inc();
            return Ok(kernel);
        }
        self.metrics.cache_misses.inc();
        let meta = self.get(template_id)?;
        let (store, id) = (self.store.clone(), meta.template_id.clone());
        let image = blocking(move || store.load_image(&id)).await??;
        let encoded = Arc::new(self.batcher.encode(image).await?);
        // A concurrent delete or replace wins: only cache what is still registered as read.
        if self
            .lookup(template_id)
            .is_some_and(|m| m.content_sha256 == meta.content_sha256)
        {
            self.kernels.insert(template_id.to_owned(), encoded.clone());
        }
        Ok(encoded)
    }

    /// Finds the template in `image` (optionally only inside `roi`).
    pub async fn match_image(
        &self,
        template_id: &str,
        image: RgbImage32,
        options: ValidOptions,
        roi: Option<Roi>,
        deadline: Option<Instant>,
    ) -> Result<MatchAnswer, EngineError> {
        let template = self.kernel(template_id).await?;
        let (image, offset) = match roi {
            None => (image, (0.0, 0.0)),
            Some(roi) => {
                check_roi(&roi, image.width, image.height)?;
                let cropped = image.crop(roi.x, roi.y, roi.width, roi.height);
                (cropped, (roi.x as f32, roi.y as f32))
            }
        };
        crate::matcher::check_pair_sizes(
            template.width,
            template.height,
            image.width,
            image.height,
        )?;
        let (reply, answer) = oneshot::channel();
        self.batcher
            .submit(MatchWork {
                template,
                image,
                options,
                deadline,
                reply,
            })
            .map_err(|e| match e {
                SubmitError::Full(e) => EngineError::ResourceExhausted(e.to_string()),
                SubmitError::Gone(e) => EngineError::Unavailable(e.to_string()),
            })?;
        let answer = answer
            .await
            .map_err(|_| EngineError::Unavailable("the model thread stopped".into()))?
            .map_err(|e| match e {
                BatchError::Match(e) => EngineError::from(e),
                BatchError::DeadlineExceeded => EngineError::DeadlineExceeded(e.to_string()),
            })?;
        let mut poses = answer.outcome.poses;
        for pose in &mut poses {
            pose.x += offset.0;
            pose.y += offset.1;
        }
        Ok(MatchAnswer {
            poses,
            timings: answer.outcome.timings,
            queue_ms: answer.queue_ms,
            batch_size: answer.batch_size,
        })
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

fn check_template_id(id: &str) -> Result<(), EngineError> {
    if id.len() > MAX_TEMPLATE_ID_BYTES {
        return Err(EngineError::InvalidArgument(format!(
            "template_id is {} bytes long; use at most {MAX_TEMPLATE_ID_BYTES}",
            id.len()
        )));
    }
    if id.chars().any(char::is_control) {
        return Err(EngineError::InvalidArgument(
            "template_id contains control characters; use printable text".into(),
        ));
    }
    Ok(())
}

fn check_labels(labels: &BTreeMap<String, String>) -> Result<(), EngineError> {
    if labels.len() > MAX_LABELS {
        return Err(EngineError::InvalidArgument(format!(
            "{} labels given; use at most {MAX_LABELS}",
            labels.len()
        )));
    }
    for (key, value) in labels {
        if key.is_empty() || key.len() > MAX_LABEL_KEY_BYTES || value.len() > MAX_LABEL_VALUE_BYTES
        {
            return Err(EngineError::InvalidArgument(format!(
                "label `{key}`: keys must be 1..={MAX_LABEL_KEY_BYTES} bytes and values at most {MAX_LABEL_VALUE_BYTES} bytes"
            )));
        }
    }
    Ok(())
}

fn check_roi(roi: &Roi, width: u32, height: u32) -> Result<(), EngineError> {
    let inside = roi.width > 0
        && roi.height > 0
        && roi.x as u64 + roi.width as u64 <= width as u64
        && roi.y as u64 + roi.height as u64 <= height as u64;
    if inside {
        Ok(())
    } else {
        Err(EngineError::InvalidArgument(format!(
            "roi x={} y={} {}x{} does not lie inside the {width}x{height} image",
            roi.x, roi.y, roi.width, roi.height
        )))
    }
}
