//! The directory store: templates as files in a local directory, owned by one replica. What
//! makes "a restart or a crash loses nothing that was acknowledged, and what GetTemplate reports
//! is exactly what Match uses" true without a database.
//!
//! Each template is two files in the template directory, named by the SHA-256 of its ID (any
//! UTF-8 ID is safe as a file name that way):
//! - `<key>.<content>.png`: the registered pixels as 16-bit RGB PNG, `<content>` being their
//!   content hash ([`super::content_sha256`]);
//! - `<key>.json`: the metadata ([`TemplateMeta`]); its presence is the commit point, and its
//!   `content_sha256` names the one image file that belongs to it.
//!
//! Every file is written to a temporary name, flushed to disk, renamed over the final name and
//! the directory is synced. A replacement writes the new image under its own (new) name, commits
//! the metadata, and only then removes the old image: whenever a process dies, the committed
//! metadata names an image file that holds exactly its pixels. Loading checks the hash again.
//! Deletion removes the metadata first. At start only the metadata is read (into an index in
//! memory); images that no metadata names (an interrupted registration) are removed, and files
//! that are not ours (a `notes.json`, a damaged or zero-byte file) are moved aside into
//! [`SET_ASIDE_DIR`] so that the service starts and an operator can look at them. Writes are
//! serialised, so the index and the disk change together; reads never wait for them.

use std::collections::{HashMap, HashSet};
use std::fs::{self, File};
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::{Mutex, RwLock};

use sha2::{Digest, Sha256};

use super::{
    CalibrationRecord, NewTemplate, Opened, PutOutcome, StoreError, TemplateMeta, io_error,
    is_hex_digest,
};
use crate::world::CalibrationSpec;

/// Sub-directory of the template directory where files that are not valid templates are moved
/// at start.
pub const SET_ASIDE_DIR: &str = "set-aside";
/// Sub-directory of the template directory holding calibrations ([`crate::world`]), one
/// `<key>.json` each (the key as for templates), written the same atomic way.
pub const CALIBRATION_DIR: &str = "calibrations";

/// What a scan of the directory at start found.
#[derive(Debug, Default)]
struct Scan {
    /// Every committed template, by ID order.
    metas: Vec<TemplateMeta>,
    /// Files that were not valid templates, moved into [`SET_ASIDE_DIR`] (or left in place
    /// when the directory is not writable), by name.
    set_aside: Vec<String>,
    /// Images of interrupted registrations or replacements, removed.
    orphans_removed: usize,
}

/// The template directory on disk, with the metadata of every template in memory.
#[derive(Debug)]
pub struct DirectoryStore {
    dir: PathBuf,
    index: RwLock<HashMap<String, TemplateMeta>>,
    /// Serialises writes: the index and the disk change together.
    writes: Mutex<()>,
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

impl DirectoryStore {
    /// Opens (creating if needed) the directory and reads every committed template's metadata.
    /// Leftover temporary files and images no metadata names are removed; files that are not
    /// valid templates are logged and moved aside (never removed: an operator may want them).
    /// Fails only when the directory itself cannot be created or listed.
    pub fn open(dir: &Path) -> Result<(Self, Opened), StoreError> {
        let (store, scan) = Self::scan(dir)?;
        let opened = Opened {
            templates: scan.metas.len(),
            set_aside: scan.set_aside.len(),
        };
        *store.index.write().expect("index lock") = scan
            .metas
            .into_iter()
            .map(|m| (m.template_id.clone(), m))
            .collect();
        Ok((store, opened))
    }

    fn scan(dir: &Path) -> Result<(Self, Scan), StoreError> {
        fs::create_dir_all(dir).map_err(io_error(dir))?;
        let store = Self {
            dir: dir.to_owned(),
            index: RwLock::new(HashMap::new()),
            writes: Mutex::new(()),
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
        let mut opened = Scan::default();
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

    pub fn count(&self) -> usize {
        self.index.read().expect("index lock").len()
    }

    pub fn get(&self, template_id: &str) -> Option<TemplateMeta> {
        self.index
            .read()
            .expect("index lock")
            .get(template_id)
            .cloned()
    }

    /// Up to `limit` templates with IDs after `after`, in byte order.
    pub fn list(&self, after: Option<&str>, limit: usize) -> Vec<TemplateMeta> {
        let index = self.index.read().expect("index lock");
        let mut ids: Vec<&String> = index
            .keys()
            .filter(|id| after.is_none_or(|a| id.as_str() > a))
            .collect();
        ids.sort();
        ids.into_iter()
            .take(limit)
            .map(|id| index[id].clone())
            .collect()
    }

    /// Metadata and image file read under the write lock, so a concurrent replacement cannot
    /// remove the image between the two.
    pub fn get_with_image(
        &self,
        template_id: &str,
    ) -> Result<Option<(TemplateMeta, Vec<u8>)>, StoreError> {
        let _writing = self.writes.lock().expect("write lock");
        let Some(meta) = self.get(template_id) else {
            return Ok(None);
        };
        let png = self.image_bytes(&meta)?;
        Ok(Some((meta, png)))
    }

    /// Writes `new` unless its ID holds the same image, or another one and `replace` is false.
    pub fn put(
        &self,
        new: &NewTemplate,
        replace: bool,
        now_unix_ms: i64,
    ) -> Result<PutOutcome, StoreError> {
        let _writing = self.writes.lock().expect("write lock");
        let previous = self.get(&new.template_id);
        if let Some(existing) = &previous {
            if existing.content_sha256 == new.content_sha256 {
                return Ok(PutOutcome::Unchanged(existing.clone()));
            }
            if !replace {
                return Ok(PutOutcome::Conflict(existing.clone()));
            }
        }
        let meta = TemplateMeta {
            template_id: new.template_id.clone(),
            width: new.width,
            height: new.height,
            labels: new.labels.clone(),
            content_sha256: new.content_sha256.clone(),
            created_unix_ms: previous.as_ref().map_or(now_unix_ms, |p| p.created_unix_ms),
            updated_unix_ms: now_unix_ms,
            version: previous.as_ref().map_or(1, |p| p.version + 1),
            origin: new.origin,
        };
        self.save(&meta, &new.png, previous.as_ref())?;
        self.index
            .write()
            .expect("index lock")
            .insert(meta.template_id.clone(), meta.clone());
        Ok(PutOutcome::Written {
            meta,
            created: previous.is_none(),
        })
    }

    /// Removes a template; `false` when it was not registered.
    pub fn remove(&self, template_id: &str) -> Result<bool, StoreError> {
        let _writing = self.writes.lock().expect("write lock");
        let Some(meta) = self.get(template_id) else {
            return Ok(false);
        };
        self.remove_files(&meta)?;
        self.index.write().expect("index lock").remove(template_id);
        Ok(true)
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
    fn save(
        &self,
        meta: &TemplateMeta,
        png: &[u8],
        previous: Option<&TemplateMeta>,
    ) -> Result<(), StoreError> {
        let image_path = self.image_path(meta);
        self.write_atomically(&image_path, png)?;
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
    fn image_bytes(&self, meta: &TemplateMeta) -> Result<Vec<u8>, StoreError> {
        let path = self.image_path(meta);
        fs::read(&path).map_err(io_error(&path))
    }

    /// Reads a template's pixels back, checked against the metadata's content hash.
    #[cfg(test)]
    fn load_image(&self, meta: &TemplateMeta) -> Result<crate::imaging::RgbImage32, StoreError> {
        let path = self.image_path(meta);
        super::decode_stored(
            &self.image_bytes(meta)?,
            &path.display().to_string(),
            &meta.content_sha256,
            meta.origin,
        )
        .map(|(image, _mask)| image)
    }

    /// Removes a template's files; metadata first, so a crash in between leaves an orphan image
    /// that the next [`DirectoryStore::open`] cleans up.
    fn remove_files(&self, meta: &TemplateMeta) -> Result<(), StoreError> {
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

    /// Writes `path` (in the template directory or one of its sub-directories) by a
    /// temporary file, a rename and a sync of its directory.
    fn write_atomically(&self, path: &Path, bytes: &[u8]) -> Result<(), StoreError> {
        let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("file");
        let folder = path.parent().unwrap_or(&self.dir);
        let tmp = folder.join(format!(".tmp-{name}-{}", std::process::id()));
        let written = File::create(&tmp).and_then(|mut file| {
            file.write_all(bytes)?;
            file.sync_all()
        });
        if let Err(e) = written {
            // A full disk leaves no partial file behind to hold its space.
            let _ = fs::remove_file(&tmp);
            return Err(io_error(&tmp)(e));
        }
        fs::rename(&tmp, path).map_err(io_error(path))?;
        sync_folder(folder)
    }

    fn sync_dir(&self) -> Result<(), StoreError> {
        sync_folder(&self.dir)
    }

    fn calibration_path(&self, calibration_id: &str) -> PathBuf {
        self.dir
            .join(CALIBRATION_DIR)
            .join(format!("{}.json", Self::key(calibration_id)))
    }

    pub fn get_calibration(
        &self,
        calibration_id: &str,
    ) -> Result<Option<CalibrationRecord>, StoreError> {
        let path = self.calibration_path(calibration_id);
        let bytes = match fs::read(&path) {
            Ok(bytes) => bytes,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(io_error(&path)(e)),
        };
        let record: CalibrationRecord =
            serde_json::from_slice(&bytes).map_err(|e| StoreError::Corrupt {
                origin: path.display().to_string(),
                message: e.to_string(),
            })?;
        Ok((record.calibration_id == calibration_id).then_some(record))
    }

    /// Every calibration file is read (there are a handful per line, not thousands); one that
    /// cannot be read is logged and left out rather than failing the listing.
    pub fn list_calibrations(
        &self,
        after: Option<&str>,
        limit: usize,
    ) -> Result<Vec<CalibrationRecord>, StoreError> {
        let folder = self.dir.join(CALIBRATION_DIR);
        let entries = match fs::read_dir(&folder) {
            Ok(entries) => entries,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
            Err(e) => return Err(io_error(&folder)(e)),
        };
        let mut records = Vec::new();
        for entry in entries {
            let path = entry.map_err(io_error(&folder))?.path();
            let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("");
            if name.starts_with(".tmp-") || !name.ends_with(".json") {
                continue;
            }
            let read = fs::read(&path).map_err(|e| e.to_string()).and_then(|b| {
                serde_json::from_slice::<CalibrationRecord>(&b).map_err(|e| e.to_string())
            });
            match read {
                Ok(record) if after.is_none_or(|a| record.calibration_id.as_str() > a) => {
                    records.push(record)
                }
                Ok(_) => {}
                Err(error) => {
                    tracing::warn!(path = %path.display(), %error, "unreadable calibration file left out")
                }
            }
        }
        records.sort_by(|a, b| a.calibration_id.cmp(&b.calibration_id));
        records.truncate(limit);
        Ok(records)
    }

    pub fn put_calibration(
        &self,
        calibration_id: &str,
        spec: &CalibrationSpec,
        replace: bool,
        now_unix_ms: i64,
    ) -> Result<PutOutcome<CalibrationRecord>, StoreError> {
        let _writing = self.writes.lock().expect("write lock");
        let previous = self.get_calibration(calibration_id)?;
        if let Some(previous) = &previous {
            if &previous.spec == spec {
                return Ok(PutOutcome::Unchanged(previous.clone()));
            }
            if !replace {
                return Ok(PutOutcome::Conflict(previous.clone()));
            }
        }
        let record = CalibrationRecord {
            calibration_id: calibration_id.to_owned(),
            spec: spec.clone(),
            created_unix_ms: previous.as_ref().map_or(now_unix_ms, |p| p.created_unix_ms),
            updated_unix_ms: now_unix_ms,
            version: previous.as_ref().map_or(1, |p| p.version + 1),
        };
        let folder = self.dir.join(CALIBRATION_DIR);
        fs::create_dir_all(&folder).map_err(io_error(&folder))?;
        let json = serde_json::to_vec_pretty(&record).expect("a calibration is plain data");
        self.write_atomically(&self.calibration_path(calibration_id), &json)?;
        Ok(PutOutcome::Written {
            meta: record,
            created: previous.is_none(),
        })
    }

    pub fn remove_calibration(&self, calibration_id: &str) -> Result<bool, StoreError> {
        let _writing = self.writes.lock().expect("write lock");
        let path = self.calibration_path(calibration_id);
        match fs::remove_file(&path) {
            Ok(()) => {
                sync_folder(&self.dir.join(CALIBRATION_DIR))?;
                Ok(true)
            }
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(false),
            Err(e) => Err(io_error(&path)(e)),
        }
    }
}

fn sync_folder(folder: &Path) -> Result<(), StoreError> {
    File::open(folder)
        .and_then(|d| d.sync_all())
        .map_err(io_error(folder))
}

/// `<key>.<content>.png`.
fn image_name(key: &str, content_sha256: &str) -> String {
    format!("{key}.{content_sha256}.png")
}

/// Committed metadata whose file name is the key of its ID; why not otherwise.
fn read_meta(path: &Path, key: &str) -> Result<TemplateMeta, String> {
    let text = fs::read_to_string(path).map_err(|e| e.to_string())?;
    let meta: TemplateMeta = serde_json::from_str(&text).map_err(|e| e.to_string())?;
    if DirectoryStore::key(&meta.template_id) != key {
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::store::{content_sha256, encode_png16};
    use crate::imaging::RgbImage32;

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
            content_sha256: content_sha256(img, None, None),
            created_unix_ms: 1,
            updated_unix_ms: 1,
            version: 1,
            origin: None,
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
        let (store, opened) = DirectoryStore::scan(dir.path()).unwrap();
        assert!(opened.metas.is_empty());
        let img = image(1);
        store
            .save(&meta("part/7 ü", &img), &encode_png16(&img, None), None)
            .unwrap();
        let (store, opened) = DirectoryStore::scan(dir.path()).unwrap();
        assert_eq!(opened.metas, vec![meta("part/7 ü", &img)]);
        let back = store.load_image(&opened.metas[0]).unwrap();
        assert_eq!(
            content_sha256(&back, None, None),
            content_sha256(&img, None, None)
        );
        assert_eq!(back.pixels, img.pixels);
    }

    #[test]
    fn a_replacement_writes_a_new_image_and_removes_the_old_one_after_the_commit() {
        let dir = tempfile::tempdir().unwrap();
        let (store, _) = DirectoryStore::scan(dir.path()).unwrap();
        let (old, new) = (image(1), image(2));
        store
            .save(&meta("t", &old), &encode_png16(&old, None), None)
            .unwrap();
        let old_file = store.image_path(&meta("t", &old));
        store
            .save(
                &meta("t", &new),
                &encode_png16(&new, None),
                Some(&meta("t", &old)),
            )
            .unwrap();
        assert!(!old_file.exists());
        assert_eq!(names(dir.path()).len(), 2);
        // A crash between the new image and the commit: the old metadata still names the old
        // image, which is still there; the new one is an orphan, removed at start.
        let (store, _) = DirectoryStore::scan(dir.path()).unwrap();
        store
            .save(&meta("u", &old), &encode_png16(&old, None), None)
            .unwrap();
        store
            .write_atomically(
                &store.image_path(&meta("u", &new)),
                &encode_png16(&new, None),
            )
            .unwrap();
        let (store, opened) = DirectoryStore::scan(dir.path()).unwrap();
        assert_eq!(opened.orphans_removed, 1);
        let u = opened.metas.iter().find(|m| m.template_id == "u").unwrap();
        assert_eq!(store.load_image(u).unwrap().pixels, old.pixels);
    }

    #[test]
    fn pixels_that_do_not_match_the_metadata_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let (store, _) = DirectoryStore::scan(dir.path()).unwrap();
        let (a, b) = (image(1), image(2));
        store
            .save(&meta("t", &a), &encode_png16(&a, None), None)
            .unwrap();
        fs::write(store.image_path(&meta("t", &a)), encode_png16(&b, None)).unwrap();
        let err = store.load_image(&meta("t", &a)).unwrap_err();
        assert!(err.to_string().contains("hash to"), "{err}");
    }

    #[test]
    fn images_stored_before_content_addressing_are_renamed() {
        let dir = tempfile::tempdir().unwrap();
        let (store, _) = DirectoryStore::scan(dir.path()).unwrap();
        let img = image(4);
        store
            .save(&meta("old", &img), &encode_png16(&img, None), None)
            .unwrap();
        let key = DirectoryStore::key("old");
        fs::rename(
            store.image_path(&meta("old", &img)),
            dir.path().join(format!("{key}.png")),
        )
        .unwrap();
        let (store, opened) = DirectoryStore::scan(dir.path()).unwrap();
        assert_eq!(
            store.load_image(&opened.metas[0]).unwrap().pixels,
            img.pixels
        );
        assert!(opened.set_aside.is_empty());
    }

    #[test]
    fn removal_and_interrupted_writes_leave_a_clean_directory() {
        let dir = tempfile::tempdir().unwrap();
        let (store, _) = DirectoryStore::scan(dir.path()).unwrap();
        let img = image(2);
        store
            .save(&meta("a", &img), &encode_png16(&img, None), None)
            .unwrap();
        store
            .save(&meta("b", &img), &encode_png16(&img, None), None)
            .unwrap();
        store.remove_files(&meta("a", &img)).unwrap();
        // A crash after the image was written but before the metadata, and a torn temp file.
        fs::write(store.image_path(&meta("never-acknowledged", &img)), b"x").unwrap();
        fs::write(dir.path().join(".tmp-x.json-1"), b"{").unwrap();
        let (_, opened) = DirectoryStore::scan(dir.path()).unwrap();
        assert_eq!(opened.metas.len(), 1);
        assert_eq!(opened.metas[0].template_id, "b");
        assert_eq!(names(dir.path()).len(), 2);
    }

    #[test]
    fn files_that_are_not_templates_are_moved_aside_not_removed() {
        let dir = tempfile::tempdir().unwrap();
        let (store, _) = DirectoryStore::scan(dir.path()).unwrap();
        let img = image(3);
        store
            .save(&meta("good", &img), &encode_png16(&img, None), None)
            .unwrap();
        store
            .save(&meta("damaged", &img), &encode_png16(&img, None), None)
            .unwrap();
        store
            .save(&meta("imageless", &img), &encode_png16(&img, None), None)
            .unwrap();
        let damaged = store.meta_path("damaged");
        fs::write(&damaged, b"").unwrap();
        fs::remove_file(store.image_path(&meta("imageless", &img))).unwrap();
        fs::write(dir.path().join("notes.json"), br#"{"owner": "line 4"}"#).unwrap();
        fs::write(dir.path().join("photo.png"), b"not ours").unwrap();
        let (_, opened) = DirectoryStore::scan(dir.path()).unwrap();
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
        let (_, again) = DirectoryStore::scan(dir.path()).unwrap();
        assert_eq!((again.metas.len(), again.set_aside.len()), (1, 0));
    }

    #[test]
    fn put_creates_replaces_and_refuses_by_content() {
        let dir = tempfile::tempdir().unwrap();
        let (store, _) = DirectoryStore::open(dir.path()).unwrap();
        let new = |img: &RgbImage32| NewTemplate {
            template_id: "t".into(),
            width: img.width,
            height: img.height,
            labels: Default::default(),
            content_sha256: content_sha256(img, None, None),
            origin: None,
            png: encode_png16(img, None),
        };
        let (a, b) = (image(1), image(2));
        let PutOutcome::Written {
            meta: first,
            created: true,
        } = store.put(&new(&a), false, 10).unwrap()
        else {
            panic!("first put creates");
        };
        assert_eq!((first.version, first.created_unix_ms), (1, 10));
        assert!(
            matches!(store.put(&new(&a), false, 11).unwrap(), PutOutcome::Unchanged(m) if m == first)
        );
        assert!(
            matches!(store.put(&new(&b), false, 12).unwrap(), PutOutcome::Conflict(m) if m == first)
        );
        let PutOutcome::Written {
            meta: second,
            created: false,
        } = store.put(&new(&b), true, 13).unwrap()
        else {
            panic!("replace writes");
        };
        assert_eq!(
            (
                second.version,
                second.created_unix_ms,
                second.updated_unix_ms
            ),
            (2, 10, 13)
        );
        let (_, png) = store.get_with_image("t").unwrap().unwrap();
        assert_eq!(png, encode_png16(&b, None));
        assert!(store.remove("t").unwrap());
        assert!(!store.remove("t").unwrap());
        assert_eq!(store.count(), 0);
    }
}
