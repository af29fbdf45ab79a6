//! The template registry: templates by ID in the configured [`super::store`] (the system of
//! record, a directory or a database), their encodings in the [`super::template_cache`].
//! The store makes each write atomic and announces other replicas' changes; this layer checks
//! what clients send, encodes templates on the model thread and keeps the cache in step.

use std::collections::BTreeMap;
use std::sync::Arc;

use super::store::{
    NewTemplate, PutOutcome, TemplateMeta, content_sha256, decode_stored, encode_png16,
};
use super::{Engine, EngineError, blocking, quoted};
use crate::geometry::TemplateOrigin;
use crate::imaging::RgbImage32;
use crate::matcher::{EncodedTemplate, TemplateMask};

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
    /// Registers `image` under `template_id` (derived from the content when empty), with the
    /// `mask` of the pixels it ignores and its reference point `origin`, if any. The same
    /// image, mask and origin under the same ID is a no-op; a different one needs `replace`.
    /// Returns once the template is committed to the store.
    pub async fn register(
        &self,
        template_id: &str,
        template: RegisteredTemplate,
        replace: bool,
        labels: BTreeMap<String, String>,
    ) -> Result<TemplateMeta, EngineError> {
        let RegisteredTemplate {
            image,
            mask,
            origin,
        } = template;
        check_labels(&labels)?;
        if let Some(mask) = &mask {
            mask.check_fits(image.width, image.height)
                .map_err(|e| EngineError::InvalidArgument(e.to_string()))?;
        }
        // A mask that uses every pixel is no mask: the template hashes as without one.
        let mask = mask.filter(|m| !m.uses_everything());
        let image = Arc::new(image);
        let (hashed, hashed_mask) = (image.clone(), mask.clone());
        let content =
            blocking(move || content_sha256(&hashed, hashed_mask.as_ref(), origin)).await?;
        let template_id = if template_id.is_empty() {
            format!("tpl-{}", &content[..16])
        } else {
            check_template_id(template_id)?;
            template_id.to_owned()
        };
        // Answer the common no-op and conflict without encoding; the store checks again
        // atomically with the write.
        if let Some(existing) = self.store.get(&template_id).await? {
            if existing.content_sha256 == content {
                return Ok(existing);
            }
            if !replace {
                return Err(EngineError::AlreadyExists(template_id));
            }
        }
        // Encoding validates the template (size limits) before anything is written.
        let mut encoded = self.batcher.encode((*image).clone(), mask.clone()).await?;
        encoded.origin = origin;
        let encoded = Arc::new(encoded);
        let stored = image.clone();
        let png = blocking(move || encode_png16(&stored, mask.as_ref())).await?;
        let new = NewTemplate {
            template_id: template_id.clone(),
            width: image.width,
            height: image.height,
            labels,
            content_sha256: content.clone(),
            origin,
            png,
        };
        let ticket = self.template_cache.ticket();
        match self.store.put(new, replace).await? {
            PutOutcome::Unchanged(meta) => Ok(meta),
            PutOutcome::Conflict(_) => Err(EngineError::AlreadyExists(template_id)),
            PutOutcome::Written { meta, created } => {
                if created && self.counts_own_writes {
                    self.metrics.templates.inc();
                }
                self.template_cache
                    .insert_written(&template_id, &content, encoded, ticket);
                Ok(meta)
            }
        }
    }

    pub async fn get(&self, template_id: &str) -> Result<TemplateMeta, EngineError> {
        refuse_impossible_id(template_id)?;
        self.store
            .get(template_id)
            .await?
            .ok_or_else(|| EngineError::NotFound(template_id.to_owned()))
    }

    /// A template's metadata, its stored image file (a 16-bit PNG whose pixels hash to the
    /// metadata's `content_sha256`; RGBA with the mask as alpha when it has one) and its mask,
    /// read together.
    pub async fn get_with_image(
        &self,
        template_id: &str,
    ) -> Result<(TemplateMeta, Vec<u8>, Option<TemplateMask>), EngineError> {
        refuse_impossible_id(template_id)?;
        let (meta, png) = self
            .store
            .get_with_image(template_id)
            .await?
            .ok_or_else(|| EngineError::NotFound(template_id.to_owned()))?;
        let (checked, source, sha, origin) = (
            png.clone(),
            quoted(template_id),
            meta.content_sha256.clone(),
            meta.origin,
        );
        let (_, mask) = blocking(move || decode_stored(&checked, &source, &sha, origin)).await??;
        Ok((meta, png, mask))
    }

    /// One page of templates in ID order; the token is where the next page starts.
    pub async fn list(
        &self,
        asked_page_size: usize,
        page_token: &str,
    ) -> Result<(Vec<TemplateMeta>, String), EngineError> {
        let page_size = page_size(asked_page_size)?;
        let after = page_after(page_token)?;
        // One more than the page: whether a next page exists.
        let page = self.store.list(after.as_deref(), page_size + 1).await?;
        Ok(into_page(page, page_size, |meta| &meta.template_id))
    }

    /// Removes a template from the store and the cache. `false` when it was not registered.
    pub async fn delete(&self, template_id: &str) -> Result<bool, EngineError> {
        if template_id.len() > MAX_TEMPLATE_ID_BYTES {
            return Ok(false);
        }
        let removed = self.store.remove(template_id).await?;
        // Dropped even when this replica found nothing: another may have deleted it first.
        self.template_cache.changed(template_id, None);
        if removed && self.counts_own_writes {
            self.metrics.templates.dec();
        }
        Ok(removed)
    }

    /// The template's encoding: from the cache (no store access, so cached templates match while
    /// a database is down), or read from the store and encoded on the model thread.
    pub(super) async fn encoded_template(
        &self,
        template_id: &str,
    ) -> Result<Arc<EncodedTemplate>, EngineError> {
        if let Some(encoded) = self.template_cache.get(template_id) {
            self.metrics.cache_hits.inc();
            return Ok(encoded);
        }
        self.metrics.cache_misses.inc();
        refuse_impossible_id(template_id)?;
        let ticket = self.template_cache.ticket();
        let (meta, image, mask) = self
            .store
            .load(template_id)
            .await?
            .ok_or_else(|| EngineError::NotFound(template_id.to_owned()))?;
        let mut encoded = self.batcher.encode(image, mask).await?;
        encoded.origin = meta.origin;
        let encoded = Arc::new(encoded);
        self.template_cache
            .insert_read(template_id, &meta.content_sha256, encoded.clone(), ticket);
        Ok(encoded)
    }
}

/// What a client registers: the template's pixels, the mask of the pixels every score
/// ignores, and its reference point (checked against the image's size by
/// [`TemplateOrigin::new`]).
#[derive(Debug, Clone)]
pub struct RegisteredTemplate {
    pub image: RgbImage32,
    pub mask: Option<TemplateMask>,
    pub origin: Option<TemplateOrigin>,
}

impl RegisteredTemplate {
    /// A template with neither mask nor origin.
    pub fn plain(image: RgbImage32) -> Self {
        Self {
            image,
            mask: None,
            origin: None,
        }
    }
}

/// An ID longer than any registration accepts is answered NOT_FOUND before the store is asked
/// (a megabyte ID costs no database round trip).
fn refuse_impossible_id(id: &str) -> Result<(), EngineError> {
    if id.len() > MAX_TEMPLATE_ID_BYTES {
        return Err(EngineError::NotFound(id.to_owned()));
    }
    Ok(())
}

fn check_template_id(id: &str) -> Result<(), EngineError> {
    check_id("template_id", id)
}

/// An ID (of a template or a calibration, named `field`): at most [`MAX_TEMPLATE_ID_BYTES`]
/// bytes of printable text.
pub(super) fn check_id(field: &str, id: &str) -> Result<(), EngineError> {
    if id.len() > MAX_TEMPLATE_ID_BYTES {
        return Err(EngineError::InvalidArgument(format!(
            "{field} is {} bytes long; use at most {MAX_TEMPLATE_ID_BYTES}",
            id.len()
        )));
    }
    if id.chars().any(char::is_control) {
        return Err(EngineError::InvalidArgument(format!(
            "{field} contains control characters; use printable text"
        )));
    }
    Ok(())
}

/// A listing's page size: 0 means [`DEFAULT_PAGE_SIZE`], at most [`MAX_PAGE_SIZE`].
pub(super) fn page_size(asked: usize) -> Result<usize, EngineError> {
    match asked {
        0 => Ok(DEFAULT_PAGE_SIZE),
        n if n > MAX_PAGE_SIZE => Err(EngineError::InvalidArgument(format!(
            "page_size {n} is too large: use at most {MAX_PAGE_SIZE} (0 means {DEFAULT_PAGE_SIZE})"
        ))),
        n => Ok(n),
    }
}

/// A listing read with one item more than `size` → the page and the token of the next one
/// (hex of the page's last ID; empty when this is the last page).
pub(super) fn into_page<T>(
    mut items: Vec<T>,
    size: usize,
    id: impl Fn(&T) -> &str,
) -> (Vec<T>, String) {
    if items.len() <= size {
        return (items, String::new());
    }
    items.truncate(size);
    let next = hex::encode(id(items.last().expect("a non-empty page")).as_bytes());
    (items, next)
}

/// Where a listing's page starts: after the ID its token (hex of the last ID) names.
pub(super) fn page_after(page_token: &str) -> Result<Option<String>, EngineError> {
    if page_token.is_empty() {
        return Ok(None);
    }
    let bytes = hex::decode(page_token).map_err(|_| {
        EngineError::InvalidArgument(
            "page_token is not one this server issued; pass next_page_token from the previous response, or empty for the first page".into(),
        )
    })?;
    String::from_utf8(bytes).map(Some).map_err(|_| {
        EngineError::InvalidArgument("page_token is not one this server issued".into())
    })
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
                "label {}: keys must be 1..={MAX_LABEL_KEY_BYTES} bytes and values at most {MAX_LABEL_VALUE_BYTES} bytes",
                super::quoted(key)
            )));
        }
    }
    Ok(())
}
