//! Helpers shared by the integration tests: where the reference files are, and how to turn the
//! parity fixture's stored pictures into image files a user would pass to `posematch`.

#![allow(dead_code)]

use std::path::{Path, PathBuf};

use safetensors::SafeTensors;

/// `../shared/reference`, or None (with a printed reason) when it is absent.
pub fn reference_dir() -> Option<PathBuf> {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/reference");
    if dir.join("tdcm-parity.safetensors").is_file() && dir.join("tdcm-official.pth").is_file() {
        Some(dir)
    } else {
        eprintln!(
            "SKIPPED: {} is absent, so tests against the official checkpoint cannot run",
            dir.display()
        );
        None
    }
}

pub fn read_fixture(dir: &Path) -> Vec<u8> {
    std::fs::read(dir.join("tdcm-parity.safetensors")).expect("fixture file readable")
}

/// Writes the fixture's `{pair}.{name}` BGR u8 `[h, w, 3]` array as an RGB PNG.
pub fn write_bgr_png(st: &SafeTensors, name: &str, out: &Path) {
    let view = st.tensor(name).unwrap_or_else(|e| panic!("{name}: {e}"));
    let shape = view.shape();
    let (h, w) = (shape[0] as u32, shape[1] as u32);
    let rgb: Vec<u8> = view
        .data()
        .chunks_exact(3)
        .flat_map(|p| [p[2], p[1], p[0]])
        .collect();
    image::RgbImage::from_raw(w, h, rgb)
        .expect("size matches")
        .save(out)
        .expect("png written");
}

/// The decode the official code produced for `pair` (fixture metadata `decode_no_refine`).
pub fn official_decode(st_bytes: &[u8], pair: &str) -> serde_json::Value {
    let (_, metadata) = SafeTensors::read_metadata(st_bytes).expect("fixture header");
    let text = metadata
        .metadata()
        .as_ref()
        .and_then(|m| m.get("decode_no_refine"))
        .expect("decode_no_refine metadata")
        .clone();
    let all: serde_json::Value = serde_json::from_str(&text).expect("JSON metadata");
    all[pair].clone()
}

/// Runs the `posematch` binary; returns (exit code, stdout, stderr).
pub fn posematch(args: &[&str]) -> (i32, String, String) {
    let output = std::process::Command::new(env!("CARGO_BIN_EXE_posematch"))
        .args(args)
        .output()
        .expect("posematch runs");
    (
        output.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&output.stdout).into_owned(),
        String::from_utf8_lossy(&output.stderr).into_owned(),
    )
}
