//! The template registry: durable templates by ID (the [`super::store`] on disk, an index in
//! memory, encoded kernels in a bounded cache). Registrations and deletions are serialised so the
//! index and the disk change together; reads never wait for them.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::{SystemTime, UNIX_EPOCH};

use super::store::{TemplateMeta, content_sha256};
use super::{Engine, EngineError, blocking};
use crate::imaging::RgbImage32;
use crate::matcher::EncodedTemplate;

/// Longest accepted template ID, in bytes.
pub const MAX_TEMPLATE_ID_BYTES: usize = 256;
/// Most labels per template, and the longest key and value.
pub const MAX_LABELS: usize = 64;
pub const MAX_LABEL_KEY_BYTES: usize = 128;
pub const MAX_LABEL_VALUE_BYTES: usize = 1024;
/// `ListTemplates` page size when none is given, and the largest allowed.
pub const DEFAULT_PAGE_SIZE: usize = 100;
pub const MAX_PAGE_SIZE: usize = 1000;

impl Engine {
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
        let previous = self.lookup(&template_id);
        if let Some(existing) = &previous {
            if existing.content_sha256 == content {
                return Ok(existing.clone());
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
        blocking(move || store.save(&saved_meta, &image, previous.as_ref())).await??;
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

    /// A template's metadata and its stored image file (a 16-bit RGB PNG whose pixels hash to
    /// the metadata's `content_sha256`), read together under the write lock so a concurrent
    /// replacement cannot pair one with the other's.
    pub async fn get_with_image(
        &self,
        template_id: &str,
    ) -> Result<(TemplateMeta, Vec<u8>), EngineError> {
        let _writing = self.writes.lock().await;
        let meta = self.get(template_id)?;
        let (store, read) = (self.store.clone(), meta.clone());
        let png = blocking(move || store.image_bytes(&read)).await??;
        Ok((meta, png))
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
        let Some(meta) = self.lookup(template_id) else {
            return Ok(false);
        };
        let store = self.store.clone();
        blocking(move || store.remove(&meta)).await??;
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
    pub(super) async fn kernel(
        &self,
        template_id: &str,
    ) -> Result<Arc<EncodedTemplate>, EngineError> {
        if let Some(kernel) = self.kernels.get(template_id) {
            self.metrics.cache_hits.inc();
            return Ok(kernel);
        }
        self.metrics.cache_misses.inc();
        let meta = self.get(template_id)?;
        let (store, read) = (self.store.clone(), meta.clone());
        let image = blocking(move || store.load_image(&read)).await??;
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
