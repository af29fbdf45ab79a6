//! The system of record for registered templates. Two stores answer the same operations:
//! - [`directory`]: files in a local directory, owned by one replica (the default);
//! - [`postgres`]: a PostgreSQL table shared by any number of replicas, which hear of each
//!   other's changes through `LISTEN`/`NOTIFY` ([`StoreEvent`]) to keep their template caches
//!   coherent.
//!
//! Both promise what the registry relies on: a write is acknowledged only once it is committed;
//! the stored image always hashes to its metadata's `content_sha256` (checked again on load);
//! checking an ID and writing it happen atomically, so two writers never both create one ID.
//! Every operation is timed and its failures counted here, once for both stores.

pub mod directory;
pub mod postgres;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use tokio::sync::mpsc;

use super::Metrics;
use crate::geometry::TemplateOrigin;
use crate::imaging::{RgbImage32, decode_image_and_opacity};
use crate::matcher::{TEMPLATE_LIMITS, TemplateMask};
use crate::world::CalibrationSpec;
use directory::DirectoryStore;
use postgres::{PostgresStore, PostgresUrl};

/// What we keep about a registered template besides its pixels.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TemplateMeta {
    pub template_id: String,
    pub width: u32,
    pub height: u32,
    #[serde(default)]
    pub labels: BTreeMap<String, String>,
    /// Hex SHA-256 of the pixels as stored (16-bit RGB, big-endian, row-major) and the size.
    pub content_sha256: String,
    /// When the ID was first registered (Unix milliseconds).
    pub created_unix_ms: i64,
    /// When its image was last written (Unix milliseconds); 0 in metadata written before
    /// replacements were tracked.
    #[serde(default)]
    pub updated_unix_ms: i64,
    /// 1 at registration, +1 on every replacement: lets a client tell two images of one ID
    /// apart without comparing hashes. 0 in metadata written before versions were kept.
    #[serde(default)]
    pub version: i64,
    /// The reference point registered with the template ([`TemplateOrigin`]); `None`: its
    /// centre. Part of the content hash.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub origin: Option<TemplateOrigin>,
}

/// A template to write: its metadata as the client gave it and its image, encoded once by the
/// registry as the stored 16-bit PNG.
#[derive(Debug, Clone)]
pub struct NewTemplate {
    pub template_id: String,
    pub width: u32,
    pub height: u32,
    pub labels: BTreeMap<String, String>,
    pub content_sha256: String,
    pub origin: Option<TemplateOrigin>,
    pub png: Vec<u8>,
}

/// A registered calibration ([`crate::world`]): the points and unit as the client gave them
/// (the map is fitted again from them when used), and its bookkeeping.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CalibrationRecord {
    pub calibration_id: String,
    pub spec: CalibrationSpec,
    pub created_unix_ms: i64,
    pub updated_unix_ms: i64,
    pub version: i64,
}

/// What a `put` did, for templates ([`TemplateMeta`]) and calibrations ([`CalibrationRecord`]).
#[derive(Debug, Clone, PartialEq)]
pub enum PutOutcome<Meta = TemplateMeta> {
    /// The ID already holds exactly this content: nothing was written.
    Unchanged(Meta),
    /// The ID holds other content and `replace` was not given: nothing was written.
    Conflict(Meta),
    /// Committed; `created` is false for a replacement.
    Written { meta: Meta, created: bool },
}

/// A change another replica committed, announced by the store so cached kernels can follow.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum StoreEvent {
    /// `template_id` was written (its new `content_sha256`; `created` unless it replaced one)
    /// or deleted (`None`).
    Changed {
        template_id: String,
        content_sha256: Option<String>,
        created: bool,
    },
    /// Announcements may have been missed (the connection to the database was lost and is
    /// back): nothing cached can be trusted.
    Resynchronise,
}

#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("template directory {path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("stored template {origin} is unreadable: {message}")]
    Corrupt { origin: String, message: String },
    /// The database cannot be reached now (down, restarting, network): worth retrying.
    #[error(
        "the template database is unreachable ({0}); templates already cached keep matching, registrations and uncached templates work again once it is back"
    )]
    Unavailable(String),
    /// The database answered with an error that retrying will not fix (schema, permissions).
    #[error("template database: {0}")]
    Database(String),
    /// No room left for a template (disk or quota full, the database out of disk): the request
    /// may succeed once an operator frees space; no partial file is left behind.
    #[error(
        "template store is full ({0}); delete templates you no longer need or ask the operator to free space"
    )]
    Full(String),
}

/// Where templates are kept, as configured (`template_store`, or the older `template_dir`).
#[derive(Debug, Clone)]
pub enum StoreLocation {
    Directory(PathBuf),
    Postgres(Box<PostgresUrl>),
}

impl StoreLocation {
    /// `postgres://…` or `postgresql://…` is a database; anything else a directory path.
    pub fn parse(setting: &str) -> Result<Self, String> {
        if setting.starts_with("postgres://") || setting.starts_with("postgresql://") {
            Ok(Self::Postgres(Box::new(PostgresUrl::parse(setting)?)))
        } else if setting.is_empty() {
            Err("an empty template store: give a directory or a postgres:// URL".into())
        } else {
            Ok(Self::Directory(PathBuf::from(setting)))
        }
    }
}

impl std::fmt::Display for StoreLocation {
    /// For logs: the database URL without its password.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Directory(dir) => write!(f, "{}", dir.display()),
            Self::Postgres(url) => write!(f, "{url}"),
        }
    }
}

/// How a store was opened, for the start-up log and metrics.
#[derive(Debug, Default)]
pub struct Opened {
    pub templates: usize,
    /// Directory store: files that were not valid templates, moved aside.
    pub set_aside: usize,
}

/// The configured store, with its operations timed and counted in [`Metrics`].
pub struct TemplateStore {
    backend: Backend,
    metrics: Metrics,
}

enum Backend {
    Directory(Arc<DirectoryStore>),
    Postgres(PostgresStore),
}

impl TemplateStore {
    /// Opens the store: a directory is created and scanned; a database is connected to, its
    /// schema migrated and its change channel listened to (fails if it cannot be reached: the
    /// caller decides whether to retry).
    pub async fn open(
        location: &StoreLocation,
        metrics: &Metrics,
    ) -> Result<(Self, Opened), StoreError> {
        let (backend, opened) = match location {
            StoreLocation::Directory(dir) => {
                let dir = dir.clone();
                let (store, opened) = blocking(move || DirectoryStore::open(&dir)).await??;
                (Backend::Directory(Arc::new(store)), opened)
            }
            StoreLocation::Postgres(url) => {
                let (store, opened) = PostgresStore::open(url, metrics.clone()).await?;
                (Backend::Postgres(store), opened)
            }
        };
        let store = Self {
            backend,
            metrics: metrics.clone(),
        };
        Ok((store, opened))
    }

    /// Announcements of other replicas' changes; `None` for a store no one else writes (a
    /// directory) and after the first call.
    pub fn take_events(&self) -> Option<mpsc::UnboundedReceiver<StoreEvent>> {
        match &self.backend {
            Backend::Directory(_) => None,
            Backend::Postgres(store) => store.take_events(),
        }
    }

    /// How long the store may fail [`TemplateStore::check`] before health reports NOT_SERVING:
    /// a database gets `database_grace` to come back (cached templates keep matching
    /// meanwhile); a directory that cannot be written is a fault of the deployment, reported
    /// at once.
    pub fn health_grace(&self, database_grace: Duration) -> Duration {
        match &self.backend {
            Backend::Directory(_) => Duration::ZERO,
            Backend::Postgres(_) => database_grace,
        }
    }

    /// Whether registrations could be written now, and how many templates there are.
    pub async fn check(&self) -> Result<usize, StoreError> {
        self.timed("check", async {
            match &self.backend {
                Backend::Directory(store) => {
                    let store = store.clone();
                    blocking(move || store.check_writable().map(|()| store.count())).await?
                }
                Backend::Postgres(store) => store.count().await,
            }
        })
        .await
    }

    pub async fn get(&self, template_id: &str) -> Result<Option<TemplateMeta>, StoreError> {
        self.timed("get", async {
            match &self.backend {
                Backend::Directory(store) => Ok(store.get(template_id)),
                Backend::Postgres(store) => store.get(template_id).await,
            }
        })
        .await
    }

    /// A template's metadata and stored image file (a 16-bit RGB PNG whose pixels hash to the
    /// metadata's `content_sha256`), read together so a concurrent replacement cannot pair one
    /// with the other's.
    pub async fn get_with_image(
        &self,
        template_id: &str,
    ) -> Result<Option<(TemplateMeta, Vec<u8>)>, StoreError> {
        self.timed("get_with_image", async {
            match &self.backend {
                Backend::Directory(store) => {
                    let (store, id) = (store.clone(), template_id.to_owned());
                    blocking(move || store.get_with_image(&id)).await?
                }
                Backend::Postgres(store) => store.get_with_image(template_id).await,
            }
        })
        .await
    }

    /// A template's metadata, pixels and mask, checked against its content hash: what a
    /// kernel is encoded from.
    pub async fn load(
        &self,
        template_id: &str,
    ) -> Result<Option<(TemplateMeta, RgbImage32, Option<TemplateMask>)>, StoreError> {
        let found = self.get_with_image(template_id).await?;
        let Some((meta, png)) = found else {
            return Ok(None);
        };
        let origin = format!("`{}`", meta.template_id.escape_debug());
        let image = blocking(move || {
            decode_stored(&png, &origin, &meta.content_sha256, meta.origin)
                .map(|(image, mask)| (meta, image, mask))
        })
        .await??;
        Ok(Some(image))
    }

    /// Up to `limit` templates with IDs after `after`, in byte order of the ID.
    pub async fn list(
        &self,
        after: Option<&str>,
        limit: usize,
    ) -> Result<Vec<TemplateMeta>, StoreError> {
        self.timed("list", async {
            match &self.backend {
                Backend::Directory(store) => Ok(store.list(after, limit)),
                Backend::Postgres(store) => store.list(after, limit).await,
            }
        })
        .await
    }

    /// Writes a template unless the ID holds the same image, or another one and `replace` is
    /// false; the check and the write are one atomic step.
    pub async fn put(&self, new: NewTemplate, replace: bool) -> Result<PutOutcome, StoreError> {
        self.timed("put", async {
            match &self.backend {
                Backend::Directory(store) => {
                    let store = store.clone();
                    blocking(move || store.put(&new, replace, now_unix_ms())).await?
                }
                Backend::Postgres(store) => store.put(&new, replace).await,
            }
        })
        .await
    }

    /// Removes a template; `false` when it was not registered.
    pub async fn remove(&self, template_id: &str) -> Result<bool, StoreError> {
        self.timed("remove", async {
            match &self.backend {
                Backend::Directory(store) => {
                    let (store, id) = (store.clone(), template_id.to_owned());
                    blocking(move || store.remove(&id)).await?
                }
                Backend::Postgres(store) => store.remove(template_id).await,
            }
        })
        .await
    }

    pub async fn get_calibration(
        &self,
        calibration_id: &str,
    ) -> Result<Option<CalibrationRecord>, StoreError> {
        self.timed("get_calibration", async {
            match &self.backend {
                Backend::Directory(store) => {
                    let (store, id) = (store.clone(), calibration_id.to_owned());
                    blocking(move || store.get_calibration(&id)).await?
                }
                Backend::Postgres(store) => store.get_calibration(calibration_id).await,
            }
        })
        .await
    }

    /// Up to `limit` calibrations with IDs after `after`, in byte order of the ID.
    pub async fn list_calibrations(
        &self,
        after: Option<&str>,
        limit: usize,
    ) -> Result<Vec<CalibrationRecord>, StoreError> {
        self.timed("list_calibrations", async {
            match &self.backend {
                Backend::Directory(store) => {
                    let (store, after) = (store.clone(), after.map(str::to_owned));
                    blocking(move || store.list_calibrations(after.as_deref(), limit)).await?
                }
                Backend::Postgres(store) => store.list_calibrations(after, limit).await,
            }
        })
        .await
    }

    /// Writes a calibration unless the ID holds the same points and unit, or other ones and
    /// `replace` is false; the check and the write are one atomic step.
    pub async fn put_calibration(
        &self,
        calibration_id: &str,
        spec: CalibrationSpec,
        replace: bool,
    ) -> Result<PutOutcome<CalibrationRecord>, StoreError> {
        self.timed("put_calibration", async {
            match &self.backend {
                Backend::Directory(store) => {
                    let (store, id) = (store.clone(), calibration_id.to_owned());
                    blocking(move || store.put_calibration(&id, &spec, replace, now_unix_ms()))
                        .await?
                }
                Backend::Postgres(store) => {
                    store.put_calibration(calibration_id, &spec, replace).await
                }
            }
        })
        .await
    }

    /// Removes a calibration; `false` when it was not registered.
    pub async fn remove_calibration(&self, calibration_id: &str) -> Result<bool, StoreError> {
        self.timed("remove_calibration", async {
            match &self.backend {
                Backend::Directory(store) => {
                    let (store, id) = (store.clone(), calibration_id.to_owned());
                    blocking(move || store.remove_calibration(&id)).await?
                }
                Backend::Postgres(store) => store.remove_calibration(calibration_id).await,
            }
        })
        .await
    }

    async fn timed<T>(
        &self,
        operation: &str,
        work: impl Future<Output = Result<T, StoreError>>,
    ) -> Result<T, StoreError> {
        let started = Instant::now();
        let result = work.await;
        self.metrics
            .store_seconds
            .with_label_values(&[operation])
            .observe(started.elapsed().as_secs_f64());
        if result.is_err() {
            self.metrics
                .store_errors
                .with_label_values(&[operation])
                .inc();
        }
        result
    }
}

/// Runs file and hashing work off the async runtime's threads.
async fn blocking<T: Send + 'static>(
    work: impl FnOnce() -> T + Send + 'static,
) -> Result<T, StoreError> {
    tokio::task::spawn_blocking(work)
        .await
        .map_err(|e| StoreError::Database(format!("background task failed: {e}")))
}

pub(crate) fn now_unix_ms() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as i64)
}

/// Decodes a stored image and its mask (the PNG's alpha channel, see [`encode_png16`]) and
/// checks them, with the registered `template_origin`, against the hash they were registered
/// with; `source` names it in errors (a file, or a template ID in the database).
pub fn decode_stored(
    png: &[u8],
    source: &str,
    content_sha256: &str,
    template_origin: Option<TemplateOrigin>,
) -> Result<(RgbImage32, Option<TemplateMask>), StoreError> {
    let corrupt = |message: String| StoreError::Corrupt {
        origin: source.to_owned(),
        message,
    };
    let (image, opaque) = decode_image_and_opacity(png, source, TEMPLATE_LIMITS)
        .map_err(|e| corrupt(e.to_string()))?;
    let mask = opaque
        .map(|used| TemplateMask::new(image.width, image.height, used))
        .transpose()
        .map_err(|e| corrupt(e.to_string()))?;
    let found = self::content_sha256(&image, mask.as_ref(), template_origin);
    if found != content_sha256 {
        return Err(corrupt(format!(
            "its pixels hash to {found}, not to the registered {content_sha256}"
        )));
    }
    Ok((image, mask))
}

/// The pixels as 16-bit RGB samples: the stored form and what the content hash covers.
fn to_rgb16(image: &RgbImage32) -> Vec<u16> {
    image
        .pixels
        .iter()
        .map(|&v| (v.clamp(0.0, 1.0) * 65535.0).round() as u16)
        .collect()
}

/// The stored form of a template: a 16-bit RGB PNG, lossless for 8- and 16-bit inputs; with a
/// mask, a 16-bit RGBA PNG whose alpha is 0 where the mask ignores a pixel and opaque
/// elsewhere (one file, so both stores keep image and mask together, written atomically).
pub fn encode_png16(image: &RgbImage32, mask: Option<&TemplateMask>) -> Vec<u8> {
    let samples = to_rgb16(image);
    let dynamic = match mask {
        None => image::DynamicImage::ImageRgb16(
            image::ImageBuffer::from_raw(image.width, image.height, samples).expect("sizes agree"),
        ),
        Some(mask) => {
            let rgba: Vec<u16> = samples
                .chunks_exact(3)
                .zip(mask.used())
                .flat_map(|(rgb, &used)| [rgb[0], rgb[1], rgb[2], if used { u16::MAX } else { 0 }])
                .collect();
            image::DynamicImage::ImageRgba16(
                image::ImageBuffer::from_raw(image.width, image.height, rgba).expect("sizes agree"),
            )
        }
    };
    let mut png = Vec::new();
    dynamic
        .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .expect("PNG encoding into memory cannot fail");
    png
}

/// Hex SHA-256 of a template's content (size and 16-bit samples, then one byte per pixel of
/// its mask, 1 = used, when it has one, then its origin's x and y as big-endian f32 when it has
/// one): equal templates, equal hashes, whatever format they arrived in; a template without a
/// mask or origin hashes as it did before they existed. The origin is in the hash so that a
/// new origin is a new version of the template, which every replica's cache notices.
pub fn content_sha256(
    image: &RgbImage32,
    mask: Option<&TemplateMask>,
    origin: Option<TemplateOrigin>,
) -> String {
    let mut hasher = Sha256::new();
    hasher.update(image.width.to_be_bytes());
    hasher.update(image.height.to_be_bytes());
    for sample in to_rgb16(image) {
        hasher.update(sample.to_be_bytes());
    }
    if let Some(mask) = mask {
        let flags: Vec<u8> = mask.used().iter().map(|&used| u8::from(used)).collect();
        hasher.update(&flags);
    }
    if let Some(origin) = origin {
        hasher.update(origin.x.to_be_bytes());
        hasher.update(origin.y.to_be_bytes());
    }
    hex::encode(hasher.finalize())
}

fn is_hex_digest(s: &str) -> bool {
    s.len() == 64
        && s.bytes()
            .all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b))
}

/// For error messages that name a directory.
/// A full disk or quota is [`StoreError::Full`] (the caller can act on it), anything else
/// [`StoreError::Io`].
fn io_error(path: &Path) -> impl FnOnce(std::io::Error) -> StoreError + '_ {
    use std::io::ErrorKind;
    move |source| match source.kind() {
        ErrorKind::StorageFull | ErrorKind::QuotaExceeded | ErrorKind::FileTooLarge => {
            tracing::warn!(path = %path.display(), error = %source, "the template directory is full");
            StoreError::Full("no space left on the template directory's disk".into())
        }
        _ => StoreError::Io {
            path: path.to_owned(),
            source,
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn locations_are_told_apart_by_scheme() {
        assert!(matches!(
            StoreLocation::parse("./data/templates"),
            Ok(StoreLocation::Directory(_))
        ));
        let url = StoreLocation::parse("postgres://app:s3cret@db:5433/posematch").unwrap();
        assert!(matches!(url, StoreLocation::Postgres(_)));
        let shown = url.to_string();
        assert!(!shown.contains("s3cret"), "{shown}");
        assert!(
            shown.contains("db:5433") && shown.contains("posematch"),
            "{shown}"
        );
        assert!(StoreLocation::parse("postgres://db/x?sslmode=nonsense").is_err());
        assert!(StoreLocation::parse("").is_err());
    }

    #[test]
    fn content_hash_depends_on_pixels_and_size() {
        let a = RgbImage32::new(2, 1, vec![0.0, 0.5, 1.0, 0.25, 0.75, 0.0]);
        let b = RgbImage32::new(1, 2, a.pixels.clone());
        assert_eq!(
            content_sha256(&a, None, None),
            content_sha256(&a.clone(), None, None)
        );
        assert_ne!(
            content_sha256(&a, None, None),
            content_sha256(&b, None, None)
        );
    }

    #[test]
    fn a_mask_is_stored_in_the_png_and_hashed_with_the_pixels() {
        let (w, h) = (12u32, 10u32);
        let image = RgbImage32::new(w, h, (0..w * h * 3).map(|i| (i % 7) as f32 / 7.0).collect());
        let mask = TemplateMask::new(w, h, (0..w * h).map(|i| i % w < 6).collect()).unwrap();
        let plain = content_sha256(&image, None, None);
        let masked = content_sha256(&image, Some(&mask), None);
        assert_ne!(plain, masked);
        let (back, no_mask) =
            decode_stored(&encode_png16(&image, None), "t", &plain, None).unwrap();
        assert!(no_mask.is_none());
        assert_eq!(content_sha256(&back, None, None), plain);
        let (back, back_mask) =
            decode_stored(&encode_png16(&image, Some(&mask)), "t", &masked, None).unwrap();
        assert_eq!(back_mask.as_ref(), Some(&mask));
        assert_eq!(content_sha256(&back, back_mask.as_ref(), None), masked);
        // The same pixels without their mask are not what was registered.
        assert!(decode_stored(&encode_png16(&image, None), "t", &masked, None).is_err());
        // An origin is part of what was registered: the same pixels without it, or with
        // another, are not that template.
        let origin = TemplateOrigin::new(1.5, 9.0, w, h).unwrap();
        let placed = content_sha256(&image, None, Some(origin));
        assert_ne!(placed, plain);
        let png = encode_png16(&image, None);
        assert!(decode_stored(&png, "t", &placed, Some(origin)).is_ok());
        assert!(decode_stored(&png, "t", &placed, None).is_err());
        let moved = TemplateOrigin::new(1.5, 8.0, w, h).unwrap();
        assert!(decode_stored(&png, "t", &placed, Some(moved)).is_err());
    }
}
