//! Durable template storage: what makes "a restart or a crash loses nothing that was
//! acknowledged, and what GetTemplate reports is exactly what Match uses" true.
//!
//! Each template is two files in the template directory, named by the SHA-256 of its ID (any
//! UTF-8 ID is safe as a file name that way):
//! - `<key>.<content>.png`: the registered pixels as 16-bit RGB PNG (lossless for 8- and 16-bit
//!   inputs), `<content>` being their content hash ([`content_sha256`]);
//! - `<key>.json`: the metadata ([`TemplateMeta`]); its presence is the commit point, and its
//!   `content_sha256` names the one image file that belongs to it.
//!
//! Every file is written to a temporary name, flushed to disk, renamed over the final name and
//! the directory is synced. A replacement writes the new image under its own (new) name, commits
//! the metadata, and only then removes the old image: whenever a process dies, the committed
//! metadata names an image file that holds exactly its pixels. Loading checks the hash again.
//! Deletion removes the metadata first. At start only the metadata is read; images that no
//! metadata names (an interrupted registration) are removed, and files that are not ours (a
//! `notes.json`, a damaged or zero-byte file) are moved aside into [`SET_ASIDE_DIR`] so that the
//! service starts and an operator can look at them.

use std::collections::{HashMap, HashSet};
use std::fs::{self, File};
use std::io::Write;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::imaging::{RgbImage32, decode_image};
use crate::matcher::TEMPLATE_LIMITS;

/// Sub-directory of the template directory where files that are not valid templates are moved
/// at start.
pub const SET_ASIDE_DIR: &str = "set-aside";

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

/// What [`TemplateStore::open`] found.
#[derive(Debug, Default)]
pub struct OpenedStore {
    /// Every committed template, by ID order.
    pub metas: Vec<TemplateMeta>,
    /// Files that were not valid templates, moved into [`SET_ASIDE_DIR`] (or left in place
    /// when the directory is not writable), by name.
    pub set_aside: Vec<String>,
    /// Images of interrupted registrations or replacements, removed.
    pub orphans_removed: usize,
}

/// The template directory on disk.
#[derive(Debug)]
pub struct TemplateStore {
    dir: PathBuf,
}

/// How a file in the template directory is named.
enum Entry {
    /// `.tmp-*`: an interrupted write of ours.
    Temporary,
    /// `<key>.json`.
    Meta { key: String },
    /// `<key>.<content>.png`, or `<key>.png` as written before images were content-addressed.
    Image { key: String },
    /// Anything else.
    Foreign,
}

fn is_hex_digest(s: &str) -> bool {
    s.len() == 64
        && s.bytes()
            .all(|b| b.is_ascii_digit() || (b'a'..=b'f').contains(&b))
}

fn classify(name: &str) -> Entry {
    if name.starts_with(".tmp-") {
        return Entry::Temporary;
    }
    if let Some(key) = name.strip_suffix(".json").filter(|k| is_hex_digest(k)) {
        return Entry::Meta { key: key.into() };
    }
    if let Some(stem) = name.strip_suffix(".png") {
        let key = stem.split_once('.').map_or(
            stem,
            |(key, content)| {
                if is_hex_digest(content) { key } else { "" }
            },
        );
        if is_hex_digest(key) {
            return Entry::Image { key: key.into() };
        }
    }
    Entry::Foreign
}

impl TemplateStore {
    /// Opens (creating if needed) the directory and reads every committed template's metadata.
    /// Leftover temporary files and images no metadata names are removed; files that are not
    /// valid templates are logged and moved aside (never removed: an operator may want them).
    /// Fails only when the directory itself cannot be created or listed.
    pub fn open(dir: &Path) -> Result<(Self, OpenedStore), StoreError> {
        fs::create_dir_all(dir).map_err(io_error(dir))?;
        let store = Self {
            dir: dir.to_owned(),
        };
        let mut metas: HashMap<String, TemplateMeta> = HashMap::new();
        let mut images: Vec<(String, String)> = Vec::new();
        let mut foreign: Vec<(String, String)> = Vec::new();
        for entry in fs::read_dir(dir).map_err(io_error(dir))? {
            let entry = entry.map_err(io_error(dir))?;
            if entry.file_type().is_ok_and(|t| t.is_dir()) {
                continue;
            }
            let name = entry.file_name().to_string_lossy().into_owned();
            match classify(&name) {
                Entry::Temporary => {
                    let _ = fs::remove_file(entry.path());
                }
                Entry::Meta { key } => match read_meta(&entry.path(), &key) {
                    Ok(meta) => {
                        metas.insert(key, meta);
                    }
                    Err(why) => foreign.push((name, why)),
                },
                Entry::Image { key } => images.push((name, key)),
                Entry::Foreign => {
                    foreign.push((name, "not a file the template store writes".into()))
                }
            }
        }
        let mut opened = OpenedStore::default();
        // Images of set-aside metadata go with it; an image written before content addressing
        // is renamed to the name its metadata expects (its hash is checked when it is loaded).
        let set_aside_keys: HashSet<String> = foreign
            .iter()
            .filter_map(|(name, _)| name.strip_suffix(".json").map(str::to_owned))
            .collect();
        for (name, key) in images {
            let expected = metas.get(&key).map(|m| image_name(&key, &m.content_sha256));
            if expected.as_deref() == Some(name.as_str()) {
                continue;
            }
            let path = dir.join(&name);
            let legacy = name == format!("{key}.png");
            if let Some(expected) = expected.filter(|e| legacy && !dir.join(e).exists()) {
                if let Err(e) = fs::rename(&path, dir.join(&expected)) {
                    tracing::warn!(file = %name, error = %e, "could not rename a template image to its content-addressed name");
                }
                continue;
            }
            if set_aside_keys.contains(&key) {
                foreign.push((name, "the image of set-aside metadata".into()));
            } else if fs::remove_file(&path).is_ok() {
                opened.orphans_removed += 1;
            }
        }
        if opened.orphans_removed > 0 {
            tracing::info!(
                count = opened.orphans_removed,
                "removed template images of interrupted registrations"
            );
        }
        // Metadata whose image is gone cannot be matched: set aside rather than listed.
        metas.retain(|key, meta| {
            let image = image_name(key, &meta.content_sha256);
            let present = dir.join(&image).is_file();
            if !present {
                foreign.push((
                    format!("{key}.json"),
                    format!("its image {image} is missing"),
                ));
            }
            present
        });
        for (name, why) in foreign {
            store.set_aside(&name, &why);
            opened.set_aside.push(name);
        }
        let _ = store.sync_dir();
        opened.metas = metas.into_values().collect();
        opened
            .metas
            .sort_by(|a, b| a.template_id.cmp(&b.template_id));
        Ok((store, opened))
    }

    /// Moves one file into [`SET_ASIDE_DIR`] under a fresh name, with a warning saying why.
    fn set_aside(&self, name: &str, why: &str) {
        let aside = self.dir.join(SET_ASIDE_DIR);
        let moved = fs::create_dir_all(&aside).and_then(|()| {
            let mut target = aside.join(name);
            let mut n = 1;
            while target.exists() {
                target = aside.join(format!("{name}.{n}"));
                n += 1;
            }
            fs::rename(self.dir.join(name), &target)
        });
        match moved {
            Ok(()) => tracing::warn!(
                file = name,
                reason = why,
                "moved a file that is not a valid template to {SET_ASIDE_DIR}/ in the template directory"
            ),
            Err(e) => tracing::warn!(
                file = name,
                reason = why,
                error = %e,
                "skipping a file that is not a valid template (could not move it aside)"
            ),
        }
    }

    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Whether a template can be written now: creates, syncs and removes a probe file. A
    /// read-only directory (or a full disk) fails here before any registration does.
    pub fn check_writable(&self) -> Result<(), StoreError> {
        let probe = self.dir.join(format!(".tmp-probe-{}", std::process::id()));
        let written = File::create(&probe)
            .and_then(|mut f| f.write_all(b"probe").and_then(|()| f.sync_all()));
        let removed = fs::remove_file(&probe);
        written.and(removed).map_err(io_error(&self.dir))
    }

    fn key(template_id: &str) -> String {
        hex::encode(Sha256::digest(template_id.as_bytes()))
    }

    fn image_path(&self, meta: &TemplateMeta) -> PathBuf {
        self.dir.join(image_name(
            &Self::key(&meta.template_id),
            &meta.content_sha256,
        ))
    }

    fn meta_path(&self, template_id: &str) -> PathBuf {
        self.dir.join(format!("{}.json", Self::key(template_id)))
    }

    /// Durably writes one template, replacing `previous` (the committed metadata of the same
    /// ID, if any). Returns only once both files are on disk; the previous image is removed
    /// after the new metadata is committed.
    pub fn save(
        &self,
        meta: &TemplateMeta,
        image: &RgbImage32,
        previous: Option<&TemplateMeta>,
    ) -> Result<(), StoreError> {
        let png = encode_png16(image);
        let image_path = self.image_path(meta);
        self.write_atomically(&image_path, &png)?;
        let json = serde_json::to_vec_pretty(meta).expect("metadata serialises");
        self.write_atomically(&self.meta_path(&meta.template_id), &json)?;
        if let Some(previous) = previous {
            let old = self.image_path(previous);
            if old != image_path {
                let _ = fs::remove_file(old);
            }
        }
        Ok(())
    }

    /// The stored image file of a template, as it is on disk (a 16-bit RGB PNG).
    pub fn image_bytes(&self, meta: &TemplateMeta) -> Result<Vec<u8>, StoreError> {
        let path = self.image_path(meta);
        fs::read(&path).map_err(io_error(&path))
    }

    /// Reads a template's pixels back, checked against the metadata's content hash.
    pub fn load_image(&self, meta: &TemplateMeta) -> Result<RgbImage32, StoreError> {
        let path = self.image_path(meta);
        let corrupt = |message: String| StoreError::Corrupt {
            path: path.clone(),
            message,
        };
        let bytes = self.image_bytes(meta)?;
        let image = decode_image(&bytes, &path.display().to_string(), TEMPLATE_LIMITS)
            .map_err(|e| corrupt(e.to_string()))?;
        let found = content_sha256(&image);
        if found != meta.content_sha256 {
            return Err(corrupt(format!(
                "its pixels hash to {found}, not to the registered {}",
                meta.content_sha256
            )));
        }
        Ok(image)
    }

    /// Removes a template; metadata first, so a crash in between leaves an orphan image that the
    /// next [`TemplateStore::open`] cleans up.
    pub fn remove(&self, meta: &TemplateMeta) -> Result<(), StoreError> {
        let path = self.meta_path(&meta.template_id);
        match fs::remove_file(&path) {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(e) => return Err(io_error(&path)(e)),
        }
        self.sync_dir()?;
        let _ = fs::remove_file(self.image_path(meta));
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

/// `<key>.<content>.png`.
fn image_name(key: &str, content_sha256: &str) -> String {
    format!("{key}.{content_sha256}.png")
}

/// Committed metadata whose file name is the key of its ID; why not otherwise.
fn read_meta(path: &Path, key: &str) -> Result<TemplateMeta, String> {
    let text = fs::read_to_string(path).map_err(|e| e.to_string())?;
    let meta: TemplateMeta = serde_json::from_str(&text).map_err(|e| e.to_string())?;
    if TemplateStore::key(&meta.template_id) != key {
        return Err(format!(
            "names template `{}`, whose metadata file has another name",
            meta.template_id.escape_debug()
        ));
    }
    if !is_hex_digest(&meta.content_sha256) {
        return Err("content_sha256 is not a SHA-256 in lowercase hex".into());
    }
    Ok(meta)
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

    fn names(dir: &Path) -> Vec<String> {
        let mut names: Vec<String> = fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        names
    }

    #[test]
    fn saved_templates_survive_a_reopen_bit_exactly() {
        let dir = tempfile::tempdir().unwrap();
        let (store, opened) = TemplateStore::open(dir.path()).unwrap();
        assert!(opened.metas.is_empty());
        let img = image(1);
        store.save(&meta("part/7 ü", &img), &img, None).unwrap();
        let (store, opened) = TemplateStore::open(dir.path()).unwrap();
        assert_eq!(opened.metas, vec![meta("part/7 ü", &img)]);
        let back = store.load_image(&opened.metas[0]).unwrap();
        assert_eq!(content_sha256(&back), content_sha256(&img));
        assert_eq!(back.pixels, img.pixels);
    }

    #[test]
    fn a_replacement_writes_a_new_image_and_removes_the_old_one_after_the_commit() {
        let dir = tempfile::tempdir().unwrap();
        let (store, _) = TemplateStore::open(dir.path()).unwrap();
        let (old, new) = (image(1), image(2));
        store.save(&meta("t", &old), &old, None).unwrap();
        let old_file = store.image_path(&meta("t", &old));
        store
            .save(&meta("t", &new), &new, Some(&meta("t", &old)))
            .unwrap();
        assert!(!old_file.exists());
        assert_eq!(names(dir.path()).len(), 2);
        // A crash between the new image and the commit: the old metadata still names the old
        // image, which is still there; the new one is an orphan, removed at start.
        let (store, _) = TemplateStore::open(dir.path()).unwrap();
        store.save(&meta("u", &old), &old, None).unwrap();
        store
            .write_atomically(&store.image_path(&meta("u", &new)), &encode_png16(&new))
            .unwrap();
        let (store, opened) = TemplateStore::open(dir.path()).unwrap();
        assert_eq!(opened.orphans_removed, 1);
        let u = opened.metas.iter().find(|m| m.template_id == "u").unwrap();
        assert_eq!(store.load_image(u).unwrap().pixels, old.pixels);
    }

    #[test]
    fn pixels_that_do_not_match_the_metadata_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let (store, _) = TemplateStore::open(dir.path()).unwrap();
        let (a, b) = (image(1), image(2));
        store.save(&meta("t", &a), &a, None).unwrap();
        fs::write(store.image_path(&meta("t", &a)), encode_png16(&b)).unwrap();
        let err = store.load_image(&meta("t", &a)).unwrap_err();
        assert!(err.to_string().contains("hash to"), "{err}");
    }

    #[test]
    fn images_stored_before_content_addressing_are_renamed() {
        let dir = tempfile::tempdir().unwrap();
        let (store, _) = TemplateStore::open(dir.path()).unwrap();
        let img = image(4);
        store.save(&meta("old", &img), &img, None).unwrap();
        let key = TemplateStore::key("old");
        fs::rename(
            store.image_path(&meta("old", &img)),
            dir.path().join(format!("{key}.png")),
        )
        .unwrap();
        let (store, opened) = TemplateStore::open(dir.path()).unwrap();
        assert_eq!(
            store.load_image(&opened.metas[0]).unwrap().pixels,
            img.pixels
        );
        assert!(opened.set_aside.is_empty());
    }

    #[test]
    fn removal_and_interrupted_writes_leave_a_clean_directory() {
        let dir = tempfile::tempdir().unwrap();
        let (store, _) = TemplateStore::open(dir.path()).unwrap();
        let img = image(2);
        store.save(&meta("a", &img), &img, None).unwrap();
        store.save(&meta("b", &img), &img, None).unwrap();
        store.remove(&meta("a", &img)).unwrap();
        // A crash after the image was written but before the metadata, and a torn temp file.
        fs::write(store.image_path(&meta("never-acknowledged", &img)), b"x").unwrap();
        fs::write(dir.path().join(".tmp-x.json-1"), b"{").unwrap();
        let (_, opened) = TemplateStore::open(dir.path()).unwrap();
        assert_eq!(opened.metas.len(), 1);
        assert_eq!(opened.metas[0].template_id, "b");
        assert_eq!(names(dir.path()).len(), 2);
    }

    #[test]
    fn files_that_are_not_templates_are_moved_aside_not_removed() {
        let dir = tempfile::tempdir().unwrap();
        let (store, _) = TemplateStore::open(dir.path()).unwrap();
        let img = image(3);
        store.save(&meta("good", &img), &img, None).unwrap();
        store.save(&meta("damaged", &img), &img, None).unwrap();
        store.save(&meta("imageless", &img), &img, None).unwrap();
        let damaged = store.meta_path("damaged");
        fs::write(&damaged, b"").unwrap();
        fs::remove_file(store.image_path(&meta("imageless", &img))).unwrap();
        fs::write(dir.path().join("notes.json"), br#"{"owner": "line 4"}"#).unwrap();
        fs::write(dir.path().join("photo.png"), b"not ours").unwrap();
        let (_, opened) = TemplateStore::open(dir.path()).unwrap();
        assert_eq!(opened.metas.len(), 1);
        assert_eq!(opened.metas[0].template_id, "good");
        assert_eq!(opened.set_aside.len(), 5, "{:?}", opened.set_aside);
        let aside = names(&dir.path().join(SET_ASIDE_DIR));
        for name in ["notes.json", "photo.png"] {
            assert!(aside.contains(&name.to_string()), "{name} not in {aside:?}");
        }
        let damaged_name = damaged.file_name().unwrap().to_string_lossy().into_owned();
        assert!(aside.contains(&damaged_name), "{aside:?}");
        // What stays is exactly the good template, plus the set-aside folder.
        assert_eq!(names(dir.path()).len(), 3, "{:?}", names(dir.path()));
        // A second start finds nothing more to do.
        let (_, again) = TemplateStore::open(dir.path()).unwrap();
        assert_eq!((again.metas.len(), again.set_aside.len()), (1, 0));
    }

    #[test]
    fn content_hash_depends_on_pixels_and_size() {
        assert_eq!(content_sha256(&image(1)), content_sha256(&image(1)));
        assert_ne!(content_sha256(&image(1)), content_sha256(&image(2)));
    }
}
