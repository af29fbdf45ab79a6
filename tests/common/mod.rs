//! Helpers shared by the integration tests: where the reference files are, and how to turn the
//! parity fixture's stored pictures into image files a user would pass to `posematch`.

#![allow(dead_code)]

pub mod postgres;
pub mod service;

use std::path::{Path, PathBuf};

use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use safetensors::SafeTensors;

/// `../shared/reference`, or None (with a printed reason) when it is absent. Where
/// `POSEMATCH_REQUIRE_REFERENCE` is set (CI, which always has the files: `.ci/run`), absence is
/// a failure, not a skip.
pub fn reference_dir() -> Option<PathBuf> {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/reference");
    if dir.join("tdcm-parity.safetensors").is_file() && dir.join("tdcm-official.pth").is_file() {
        Some(dir)
    } else {
        assert!(
            std::env::var_os("POSEMATCH_REQUIRE_REFERENCE").is_none(),
            "{} is required here (POSEMATCH_REQUIRE_REFERENCE is set): put the reference files beside the checkout",
            dir.display()
        );
        eprintln!(
            "SKIPPED: {} is absent, so tests against the official checkpoint cannot run",
            dir.display()
        );
        None
    }
}

/// A float32 tensor of a safetensors fixture: values and shape.
pub fn read_f32(st: &SafeTensors, name: &str) -> (Vec<f32>, Vec<usize>) {
    let view = st
        .tensor(name)
        .unwrap_or_else(|e| panic!("fixture {name}: {e}"));
    assert_eq!(view.dtype(), safetensors::Dtype::F32, "{name}");
    let values = view
        .data()
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    (values, view.shape().to_vec())
}

/// A 4-d float32 fixture tensor on `device`.
pub fn tensor(
    st: &SafeTensors,
    name: &str,
    device: &burn::prelude::Device,
) -> burn::prelude::Tensor<4> {
    let (values, shape) = read_f32(st, name);
    burn::prelude::Tensor::from_data(burn::prelude::TensorData::new(values, shape), device)
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

/// Two 640x480 "photos" with object-like structure: overlapping filled shapes of random grey
/// levels and colours on a smooth background.
pub fn structured_photo_dir() -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    let mut rng = StdRng::seed_from_u64(11);
    for k in 0..2 {
        let (w, h) = (640u32, 480u32);
        let mut photo = image::RgbImage::from_fn(w, h, |x, y| {
            let v = (100.0
                + 40.0 * ((x as f32) * 0.013 + k as f32).sin()
                + 30.0 * ((y as f32) * 0.021).cos()) as u8;
            image::Rgb([v, v / 2 + 40, 255 - v])
        });
        for _ in 0..220 {
            let (cx, cy) = (rng.random_range(0..w) as i32, rng.random_range(0..h) as i32);
            let (rx, ry) = (rng.random_range(3..28), rng.random_range(3..28));
            let colour = image::Rgb([rng.random(), rng.random(), rng.random()]);
            let ellipse = rng.random_bool(0.5);
            for y in (cy - ry).max(0)..(cy + ry).min(h as i32) {
                for x in (cx - rx).max(0)..(cx + rx).min(w as i32) {
                    let (dx, dy) = ((x - cx) as f32 / rx as f32, (y - cy) as f32 / ry as f32);
                    if !ellipse || dx * dx + dy * dy <= 1.0 {
                        photo.put_pixel(x as u32, y as u32, colour);
                    }
                }
            }
        }
        photo
            .save(dir.path().join(format!("photo{k}.png")))
            .unwrap();
    }
    dir
}

/// Largest absolute difference between two equally long tensors, and where (NaN counts as
/// worst).
pub fn worst(expected: &[f32], actual: &[f32]) -> (usize, f32) {
    assert_eq!(expected.len(), actual.len());
    expected
        .iter()
        .zip(actual)
        .map(|(e, a)| (e - a).abs())
        .enumerate()
        .fold((0, 0f32), |best, (i, d)| {
            if d > best.1 || d.is_nan() {
                (i, d)
            } else {
                best
            }
        })
}

/// A small PNG file whose IHDR announces `w x h` RGB, with `extra` chunks (kind, data) before
/// one tiny IDAT (an empty zlib stream) and IEND. Decoding it for real would need w*h*3 bytes.
pub fn png_claiming(w: u32, h: u32, extra: &[(&[u8; 4], Vec<u8>)]) -> Vec<u8> {
    let mut ihdr = Vec::new();
    ihdr.extend_from_slice(&w.to_be_bytes());
    ihdr.extend_from_slice(&h.to_be_bytes());
    ihdr.extend_from_slice(&[8, 2, 0, 0, 0]);
    let mut chunks: Vec<(&[u8], Vec<u8>)> = vec![(&b"IHDR"[..], ihdr)];
    chunks.extend(extra.iter().map(|(kind, data)| (&kind[..], data.clone())));
    chunks.push((
        &b"IDAT"[..],
        vec![0x78, 0x9c, 0x03, 0x00, 0x00, 0x00, 0x00, 0x01],
    ));
    chunks.push((&b"IEND"[..], Vec::new()));
    let mut png = b"\x89PNG\r\n\x1a\n".to_vec();
    for (kind, data) in chunks {
        png.extend(png_chunk(kind, &data));
    }
    png
}

/// One PNG chunk: length, kind, data, CRC.
pub fn png_chunk(kind: &[u8], data: &[u8]) -> Vec<u8> {
    let mut chunk = kind.to_vec();
    chunk.extend_from_slice(data);
    let mut bytes = (data.len() as u32).to_be_bytes().to_vec();
    bytes.extend_from_slice(&chunk);
    bytes.extend_from_slice(&crc32(&chunk).to_be_bytes());
    bytes
}

fn crc32(data: &[u8]) -> u32 {
    let mut crc = 0xFFFF_FFFFu32;
    for &byte in data {
        crc ^= byte as u32;
        for _ in 0..8 {
            crc = if crc & 1 != 0 {
                (crc >> 1) ^ 0xEDB8_8320
            } else {
                crc >> 1
            };
        }
    }
    !crc
}
