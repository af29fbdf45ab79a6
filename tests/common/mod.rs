//! Helpers shared by the integration tests: where the reference files are, how a test that
//! cannot run here says so ([`unavailable`]), the generated photos and pairs with known truth,
//! and how to turn the parity fixture's stored pictures into image files a user would pass to
//! `posematch`.

#![allow(dead_code)]

pub mod http;
pub mod postgres;
pub mod service;

use std::path::{Path, PathBuf};

use posematch::imaging::InputConvention;
use posematch::matcher::Matcher;
use posematch::model::load_weights;
use posematch::synth::{DEFAULT_MIN_STRUCTURE, Level, PairSpec};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use safetensors::SafeTensors;

/// The reference files beside the checkout: the parity fixture and the official checkpoint.
pub const REFERENCE: &str = "../shared/reference";
/// The real `grpcurl` binary, for the debugging workflow through reflection.
pub const GRPCURL: &str = "grpcurl";
/// `initdb` and `pg_ctl`, for throw-away database clusters.
pub const POSTGRESQL: &str = "PostgreSQL";
/// Debian's `chromium` and `chromium-driver`, for the setup page in a real browser.
pub const CHROMIUM: &str = "Chromium and chromedriver";

/// The variables that made one dependency's absence a failure before [`unavailable`] looked at
/// `CI`; still honoured for anyone who sets them by hand.
const REQUIRED_BY: [(&str, &str); 3] = [
    (REFERENCE, "POSEMATCH_REQUIRE_REFERENCE"),
    (GRPCURL, "POSEMATCH_REQUIRE_GRPCURL"),
    (POSTGRESQL, "POSEMATCH_REQUIRE_POSTGRES"),
];

/// The one way a test skips: `dependency` is missing here, and `why` says what needs it or what
/// would provide it. In CI (the variable `CI` set to anything but "", "0" or "false"), or where
/// the dependency's `POSEMATCH_REQUIRE_*` variable is set, absence is a failure: this panics.
/// Elsewhere it writes `SKIPPED <test>: <dependency> is absent (<why>)` and the caller returns.
pub fn unavailable(dependency: &str, why: &str) {
    let ci = std::env::var_os("CI")
        .map(|v| v.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    let in_ci = !matches!(ci.as_str(), "" | "0" | "false");
    assert!(
        !in_ci,
        "{dependency} is required in CI (CI={ci}) but absent: {why}"
    );
    for (required, variable) in REQUIRED_BY {
        assert!(
            required != dependency || std::env::var_os(variable).is_none(),
            "{dependency} is required here ({variable} is set) but absent: {why}"
        );
    }
    report_skip(dependency, why);
}

/// A test that cannot run on this machine because it lacks `feature` (a CPU capability, not
/// something to install): the same `SKIPPED` line as [`unavailable`], never a failure.
pub fn not_on_this_machine(feature: &str, why: &str) {
    report_skip(feature, why);
}

/// One line naming the skipped test (libtest names each test's thread after it), written to
/// the process's stderr itself: libtest captures only `print!`/`eprint!`, so `cargo test` shows
/// the line even for a test that passes.
fn report_skip(what: &str, why: &str) {
    use std::io::Write;
    let thread = std::thread::current();
    let test = thread.name().unwrap_or("an unnamed test");
    let _ = writeln!(
        std::io::stderr().lock(),
        "SKIPPED {test}: {what} is absent ({why})"
    );
}

/// `../shared/reference` when it holds the fixture and the official checkpoint; None, silently,
/// when it does not (for tests that use the files only when present).
pub fn reference_files() -> Option<PathBuf> {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join(REFERENCE);
    let present =
        dir.join("tdcm-parity.safetensors").is_file() && dir.join("tdcm-official.pth").is_file();
    present.then_some(dir)
}

/// `../shared/reference`, or None after [`unavailable`] (a failure in CI, which always has the
/// files: `.ci/run`).
pub fn reference_dir() -> Option<PathBuf> {
    let dir = reference_files();
    if dir.is_none() {
        unavailable(
            REFERENCE,
            "tests against the official checkpoint need tdcm-parity.safetensors and tdcm-official.pth there",
        );
    }
    dir
}

/// A throw-away PostgreSQL cluster, or None after [`unavailable`] when PostgreSQL is not
/// installed (a failure in CI: `.ci/run` installs it).
pub fn postgres_cluster() -> Option<postgres::PgCluster> {
    let cluster = postgres::PgCluster::start();
    if cluster.is_none() {
        unavailable(
            POSTGRESQL,
            "initdb and pg_ctl are not installed: apt-get install postgresql",
        );
    }
    cluster
}

/// The official checkpoint of `reference` (from [`reference_dir`]) as a matcher on the CPU,
/// with the ImageNet RGB input convention.
pub fn official_matcher(reference: &Path) -> Matcher {
    let device = burn::prelude::Device::flex();
    let model = load_weights(&reference.join("tdcm-official.pth"), &device).unwrap();
    Matcher::new(model, device, InputConvention::ImagenetRgb)
}

/// The paper's S1.5 pairs at the paper's sizes: 36x36 templates in 224x224 search windows, with
/// the default least structure of a template.
pub fn s1_5_spec() -> PairSpec {
    PairSpec {
        level: Level::S1_5,
        template_width: 36,
        template_height: 36,
        search_side: 224,
        min_structure: DEFAULT_MIN_STRUCTURE,
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

/// The fixture's `{pair}.{name}` BGR u8 `[h, w, 3]` array as an RGB image.
pub fn fixture_rgb(st: &SafeTensors, name: &str) -> image::RgbImage {
    let view = st.tensor(name).unwrap_or_else(|e| panic!("{name}: {e}"));
    let shape = view.shape();
    let (h, w) = (shape[0] as u32, shape[1] as u32);
    let rgb: Vec<u8> = view
        .data()
        .chunks_exact(3)
        .flat_map(|p| [p[2], p[1], p[0]])
        .collect();
    image::RgbImage::from_raw(w, h, rgb).expect("size matches")
}

/// Writes the fixture's `{pair}.{name}` BGR u8 `[h, w, 3]` array as an RGB PNG.
pub fn write_bgr_png(st: &SafeTensors, name: &str, out: &Path) {
    fixture_rgb(st, name).save(out).expect("png written");
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
