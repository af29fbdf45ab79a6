//! Durable template storage: what makes "a restart or a crash loses nothing that was
//! acknowledged" true.
//!
//! Each template is two files in the template directory, named by the SHA-256 of its ID (any
//! UTF-8 ID is safe as a file name that way):
//! - `<key>.png`: the registered pixels as 16-bit RGB PNG (lossless for 8- and 16-bit inputs);
//! - `<key>.json`: the metadata ([`TemplateMeta`]); its presence is the commit point.
//!
//! Every file is written to a temporary name, flushed to disk, renamed over the final name and
//! the directory is synced, so a crash leaves either the old state or the new one. Registration
//! writes the image first and the metadata last; deletion removes the metadata first. At start
//! only the metadata is read; images are read when a template's kernel is first needed.

use std::collections::HashMap;
use std::fs::{self, File};
use std::io::Write;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::imaging::{RgbImage32, decode_image};
use crate::matcher::TEMPLATE_LIMITS;

/// What we keep about a registered template besides its pixels.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct TemplateMeta {
    pub template_id: String,
    pub width: u32,
    pub height: u32,
    #[serde(default)]
    pub labels: std::collections::BTreeMap<String, String>,
    /// Hex SHA-256 of the pixels as stored (16-bit RGB, big-endian, row-major) and the size.
    pub content_sha256: String,
    pub created_unix_ms: i64,
}

#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    #[error("template directory {path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("stored template {path} is unreadable: {message}")]
    Corrupt { path: PathBuf, message: String },
}

fn io_error(path: &Path) -> impl FnOnce(std::io::Error) -> StoreError + '_ {
    move |source| StoreError::Io {
        path: path.to_owned(),
        source,
    }
}

/// The template directory on disk.
#[derive(Debug)]
pub struct TemplateStore {
    dir: PathBuf,
}

impl TemplateStore {
    /// Opens (creating if needed) the directory and reads every committed template's metadata.
    /// Leftover temporary files of an interrupted write are removed; an image without metadata
    /// was never acknowledged and is removed too.
    pub fn open(dir: &Path) -> Result<(Self, Vec<TemplateMeta>), StoreError> {
        fs::create_dir_all(dir).map_err(io_error(dir))?;
        let mut metas = Vec::new();
        let mut images = Vec::new();
        // Images beside unreadable metadata: not proven unacknowledged, so never removed.
        let mut kept = std::collections::HashSet::new();
        for entry in fs::read_dir(dir).map_err(io_error(dir))? {
            let path = entry.map_err(io_error(dir))?.path();
            let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("");
            if name.starts_with(".tmp-") {
                let _ = fs::remove_file(&path);
            } else if name.ends_with(".json") {
                // A foreign or damaged file (a `notes.json`, a zero-byte file) must not stop
                // the service: it is skipped with a warning and left alone, and so is the image
                // beside it, in case an operator can repair it.
                let parsed = fs::read_to_string(&path)
                    .map_err(|e| e.to_string())
                    .and_then(|text| {
                        serde_json::from_str::<TemplateMeta>(&text).map_err(|e| e.to_string())
                    });
                match parsed {
                    Ok(meta) => metas.push(meta),
                    Err(message) => {
                        tracing::warn!(
                            path = %path.display(),
                            %message,
                            "skipping a file in the template directory that is not template metadata"
                        );
                        kept.insert(path.with_extension("png"));
                    }
                }
            } else if name.ends_with(".png") {
                images.push(path);
            }
        }
        let store = Self {
            dir: dir.to_owned(),
        };
        let committed: std::collections::HashSet<PathBuf> = metas
            .iter()
            .map(|m| store.image_path(&m.template_id))
            .collect();
        for image in images {
            if !committed.contains(&image) && !kept.contains(&image) {
                let _ = fs::remove_file(&image);
            }
        }
        metas.sort_by(|a, b| a.template_id.cmp(&b.template_id));
        Ok((store, metas))
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }

    fn key(template_id: &str) -> String {
        hex::encode(Sha256::digest(template_id.as_bytes()))
    }

    fn image_path(&self, template_id: &str) -> PathBuf {
        self.dir.join(format!("{}.png", Self::key(template_id)))
    }

    fn meta_path(&self, template_id: &str) -> PathBuf {
        self.dir.join(format!("{}.json", Self::key(template_id)))
    }

    /// Durably writes (or replaces) one template. Returns only once both files are on disk.
    pub fn save(&self, meta: &TemplateMeta, image: &RgbImage32) -> Result<(), StoreError> {
        let png = encode_png16(image);
        let image_path = self.image_path(&meta.template_id);
        self.write_atomically(&image_path, &png)?;
        let json = serde_json::to_vec_pretty(meta).expect("metadata serialises");
        self.write_atomically(&self.meta_path(&meta.template_id), &json)
    }

    /// Reads a template's pixels back.
    pub fn load_image(&self, template_id: &str) -> Result<RgbImage32, StoreError> {
        let path = self.image_path(template_id);
        let bytes = fs::read(&path).map_err(io_error(&path))?;
        decode_image(&bytes, &path.display().to_string(), TEMPLATE_LIMITS).map_err(|e| {
            StoreError::Corrupt {
                path: path.clone(),
                message: e.to_string(),
            }
        })
    }

    /// Removes a template; metadata first, so a crash in between leaves an orphan image that the
    /// next [`TemplateStore::open`] cleans up.
    pub fn remove(&self, template_id: &str) -> Result<(), StoreError> {
        let meta = self.meta_path(template_id);
        match fs::remove_file(&meta) {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(e) => return Err(io_error(&meta)(e)),
        }
        self.sync_dir()?;
        let _ = fs::remove_file(self.image_path(template_id));
        Ok(())
    }

    fn write_atomically(&self, path: &Path, bytes: &[u8]) -> Result<(), StoreError> {
        let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("file");
        let tmp = self.dir.join(format!(".tmp-{name}-{}", std::process::id()));
        let mut file = File::create(&tmp).map_err(io_error(&tmp))?;
        file.write_all(bytes).map_err(io_error(&tmp))?;
        file.sync_all().map_err(io_error(&tmp))?;
        drop(file);
        fs::rename(&tmp, path).map_err(io_error(path))?;
        self.sync_dir()
    }

    fn sync_dir(&self) -> Result<(), StoreError> {
        File::open(&self.dir)
            .and_then(|d| d.sync_all())
            .map_err(io_error(&self.dir))
    }
}

/// The pixels as 16-bit RGB samples: the stored form and what the content hash covers.
fn to_rgb16(image: &RgbImage32) -> Vec<u16> {
    image
        .pixels
        .iter()
        .map(|&v| (v.clamp(0.0, 1.0) * 65535.0).round() as u16)
        .collect()
}

fn encode_png16(image: &RgbImage32) -> Vec<u8> {
    let samples = to_rgb16(image);
    let buffer: image::ImageBuffer<image::Rgb<u16>, Vec<u16>> =
        image::ImageBuffer::from_raw(image.width, image.height, samples).expect("sizes agree");
    let mut png = Vec::new();
    image::DynamicImage::ImageRgb16(buffer)
        .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .expect("PNG encoding into memory cannot fail");
    png
}

/// Hex SHA-256 of an image's content (size and 16-bit samples): equal images, equal hashes,
/// whatever format they arrived in.
pub fn content_sha256(image: &RgbImage32) -> String {
    let mut hasher = Sha256::new();
    hasher.update(image.width.to_be_bytes());
    hasher.update(image.height.to_be_bytes());
    for sample in to_rgb16(image) {
        hasher.update(sample.to_be_bytes());
    }
    hex::encode(hasher.finalize())
}

/// The metadata of every registered template, by ID; the in-memory index the service answers
/// `GetTemplate`/`ListTemplates` from.
pub type TemplateIndex = HashMap<String, TemplateMeta>;

#[cfg(test)]
mod tests {
    use super::*;

    fn image(seed: u32) -> RgbImage32 {
        let pixels = (0..20 * 12 * 3)
            .map(|i| ((i as u32 * 37 + seed * 11) % 256) as f32 / 255.0)
            .collect();
        RgbImage32::new(20, 12, pixels)
    }

    fn meta(id: &str, img: &RgbImage32) -> TemplateMeta {
        TemplateMeta {
            template_id: id.into(),
            width: img.width,
            height: img.height,
            labels: [("line".to_string(), "3".to_string())].into(),
            content_sha256: content_sha256(img),
            created_unix_ms: 1,
        }
    }

    #[test]
    fn saved_templates_survive_a_reopen_bit_exactly() {
        let dir = tempfile::tempdir().unwrap();
        let (store, metas) = TemplateStore::open(dir.path()).unwrap();
        assert!(metas.is_empty());
        let img = image(1);
        store.save(&meta("part/7 ü", &img), &img).unwrap();
        let (store, metas) = TemplateStore::open(dir.path()).unwrap();
        assert_eq!(metas, vec![meta("part/7 ü", &img)]);
        let back = store.load_image("part/7 ü").unwrap();
        assert_eq!(content_sha256(&back), content_sha256(&img));
        assert_eq!(back.pixels, img.pixels);
    }

    #[test]
    fn removal_and_interrupted_writes_leave_a_clean_directory() {
        let dir = tempfile::tempdir().unwrap();
        let (store, _) = TemplateStore::open(dir.path()).unwrap();
        let img = image(2);
        store.save(&meta("a", &img), &img).unwrap();
        store.save(&meta("b", &img), &img).unwrap();
        store.remove("a").unwrap();
        // A crash after the image was written but before the metadata, and a torn temp file.
        fs::write(store.image_path("never-acknowledged"), b"x").unwrap();
        fs::write(dir.path().join(".tmp-x.json-1"), b"{").unwrap();
        let (_, metas) = TemplateStore::open(dir.path()).unwrap();
        assert_eq!(metas.len(), 1);
        assert_eq!(metas[0].template_id, "b");
        assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 2);
    }

    #[test]
    fn foreign_or_damaged_metadata_is_skipped_and_kept() {
        let dir = tempfile::tempdir().unwrap();
        let (store, _) = TemplateStore::open(dir.path()).unwrap();
        let img = image(3);
        store.save(&meta("good", &img), &img).unwrap();
        fs::write(dir.path().join("notes.json"), br#"{"owner": "line 4"}"#).unwrap();
        fs::write(dir.path().join("damaged.json"), b"").unwrap();
        fs::write(
            dir.path().join("damaged.png"),
            b"pixels an operator may want back",
        )
        .unwrap();
        let (_, metas) = TemplateStore::open(dir.path()).unwrap();
        assert_eq!(metas.len(), 1);
        assert_eq!(metas[0].template_id, "good");
        for name in ["notes.json", "damaged.json", "damaged.png"] {
            assert!(dir.path().join(name).exists(), "{name} was removed");
        }
    }

    #[test]
    fn content_hash_depends_on_pixels_and_size() {
        assert_eq!(content_sha256(&image(1)), content_sha256(&image(1)));
        assert_ne!(content_sha256(&image(1)), content_sha256(&image(2)));
    }
}
