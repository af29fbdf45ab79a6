//! Weights: the one-time conversion round-trips exactly, and checkpoints that do not fit the
//! architecture fail with the name of the first offending tensor.

mod common;

use std::collections::HashMap;

use burn::prelude::*;
use common::{posematch, reference_dir};
use posematch::model::{GridShape, LoadError, TrainedOn, WeightsSource, load_weights};
use safetensors::{Dtype, SafeTensors, tensor::TensorView};

fn forward(model: &posematch::model::Tdcm, device: &Device) -> Vec<f32> {
    let images = Tensor::<4>::from_data(
        TensorData::new(
            (0..3 * 64 * 64)
                .map(|i| ((i % 97) as f32 - 48.0) / 30.0)
                .collect(),
            [1, 3, 64, 64],
        ),
        device,
    );
    let template = Tensor::<4>::from_data(
        TensorData::new(
            (0..3 * 36 * 36)
                .map(|i| ((i % 31) as f32 - 15.0) / 10.0)
                .collect(),
            [1, 3, 36, 36],
        ),
        device,
    );
    let kernels = model.template_encoder.forward(template);
    model
        .search_matcher
        .forward(images, kernels)
        .stacked
        .into_data()
        .try_into_vec()
        .unwrap()
}

#[test]
fn import_round_trips_exactly() {
    let Some(dir) = reference_dir() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("official.bpk");
    let pth = dir.join("tdcm-official.pth");
    let (code, _, stderr) = posematch(&[
        "weights",
        "import",
        "--from",
        pth.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{stderr}");
    let device = Device::flex();
    let original = load_weights(&pth, &device).unwrap();
    let converted = load_weights(&out, &device).unwrap();
    assert_eq!(forward(&original, &device), forward(&converted, &device));
}

/// The embedded default records what it was trained on, and by that record the heads are not
/// trusted for 28x52 parts (their short axis lands on the grid at 0.73, below the 0.8 every run
/// trained on) but are for square ones.
#[test]
fn the_default_weights_record_what_they_were_trained_on() {
    let record = WeightsSource::Embedded
        .trained_on()
        .unwrap()
        .expect("the embedded default carries a training record");
    assert!(record.seen.grid_scales[0] <= record.throughout.grid_scales[0]);
    assert!(record.seen.grid_scales[1] >= record.throughout.grid_scales[1]);
    assert!(record.seen.aspect_max >= record.throughout.aspect_max);
    assert!(!record.runs.is_empty());
    assert!(
        record
            .outside(&GridShape::of_template(28, 52, (1.0, 1.0)))
            .is_some()
    );
    assert_eq!(
        record.outside(&GridShape::of_template(36, 36, (1.0, 1.0))),
        None
    );
}

/// `weights import --trained-on` keeps a record in the file (combined oldest first with the
/// record of weights it inherits from), `weights show` prints it, and a record that is not one
/// is refused with what to fix.
#[test]
fn import_keeps_the_training_record_and_show_prints_it() {
    let tmp = tempfile::tempdir().unwrap();
    let run = tmp.path().join("trained_on.json");
    std::fs::write(
        &run,
        r#"{"throughout": {"grid_scales": [0.6, 2.0], "aspect_max": 3.3},
            "seen": {"grid_scales": [0.5, 2.5], "aspect_max": 5.0},
            "template_sides": [[36, 36]], "parts_per_window_max": 3, "search_sides": [224],
            "pairs": 1000, "runs": ["a test run"]}"#,
    )
    .unwrap();
    // `weights import --from default --out OUT --trained-on R…`: exit code and stderr.
    let import = |out: &std::path::Path, records: &[&str]| {
        let mut args = vec!["weights", "import", "--from", "default", "--out"];
        args.push(out.to_str().unwrap());
        for record in records {
            args.extend(["--trained-on", record]);
        }
        let (code, _, stderr) = posematch(&args);
        (code, stderr)
    };
    let out = tmp.path().join("tuned.bpk");
    let (code, stderr) = import(&out, &["default", run.to_str().unwrap()]);
    assert_eq!(code, 0, "{stderr}");
    let default = WeightsSource::Embedded.trained_on().unwrap().unwrap();
    let written = WeightsSource::File(out.clone())
        .trained_on()
        .unwrap()
        .unwrap();
    let expected =
        default.then(&TrainedOn::from_json(&std::fs::read_to_string(&run).unwrap()).unwrap());
    assert_eq!(written, expected);
    assert_eq!(written.runs.last().map(String::as_str), Some("a test run"));
    let (code, stdout, stderr) = posematch(&["weights", "show", out.to_str().unwrap()]);
    assert_eq!(code, 0, "{stderr}");
    let shown: TrainedOn = serde_json::from_str(&stdout).unwrap();
    assert_eq!(shown, written);
    // Without --trained-on: no record, and show says the heads are trusted everywhere.
    let bare = tmp.path().join("bare.bpk");
    let (code, stderr) = import(&bare, &[]);
    assert_eq!(code, 0, "{stderr}");
    assert_eq!(
        WeightsSource::File(bare.clone()).trained_on().unwrap(),
        None
    );
    let (code, _, stderr) = posematch(&["weights", "show", bare.to_str().unwrap()]);
    assert_eq!(code, 0, "{stderr}");
    assert!(stderr.contains("no training record"), "{stderr}");
    // Not a record; weights with nothing to inherit.
    let junk = tmp.path().join("junk.json");
    std::fs::write(&junk, r#"{"grid_scales": [1, 2]}"#).unwrap();
    for record in [junk.to_str().unwrap(), bare.to_str().unwrap()] {
        let (code, stderr) = import(&out, &[record]);
        assert_eq!(code, 1, "{stderr}");
        assert!(
            stderr.contains("--trained-on") || stderr.contains("not a training record"),
            "{stderr}"
        );
    }
}

/// `weights export` writes our weights under the official checkpoint's names and shapes (what
/// `training/train.py --init-weights` loads into the PyTorch model), and reading that file back
/// gives the same network to the bit.
#[test]
fn export_writes_the_official_layout_and_reads_back_exactly() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("default.safetensors");
    let (code, _, stderr) = posematch(&["weights", "export", "--out", out.to_str().unwrap()]);
    assert_eq!(code, 0, "{stderr}");
    let device = Device::flex();
    let embedded = posematch::model::WeightsSource::Embedded
        .load(&device)
        .unwrap();
    let exported = load_weights(&out, &device).unwrap();
    assert_eq!(forward(&embedded, &device), forward(&exported, &device));
    let Some(dir) = reference_dir() else { return };
    let shapes = |bytes: &[u8]| -> Vec<(String, Vec<usize>)> {
        let st = SafeTensors::deserialize(bytes).unwrap();
        let mut shapes: Vec<(String, Vec<usize>)> = st
            .tensors()
            .into_iter()
            .filter(|(name, _)| !name.ends_with("num_batches_tracked"))
            .map(|(name, view)| (name, view.shape().to_vec()))
            .collect();
        shapes.sort();
        shapes
    };
    let official = std::fs::read(dir.join("tdcm-official.safetensors")).unwrap();
    let ours = std::fs::read(&out).unwrap();
    assert_eq!(shapes(&ours), shapes(&official));
}

/// Writes the official tensors to a new safetensors file after `edit` changed the set.
fn edited_checkpoint(
    dir: &std::path::Path,
    out: &std::path::Path,
    edit: impl FnOnce(&mut HashMap<String, (Dtype, Vec<usize>, Vec<u8>)>),
) {
    let bytes = std::fs::read(dir.join("tdcm-official.safetensors")).unwrap();
    let st = SafeTensors::deserialize(&bytes).unwrap();
    let mut tensors: HashMap<String, (Dtype, Vec<usize>, Vec<u8>)> = st
        .tensors()
        .into_iter()
        .map(|(name, view)| {
            (
                name,
                (view.dtype(), view.shape().to_vec(), view.data().to_vec()),
            )
        })
        .collect();
    edit(&mut tensors);
    let views: Vec<(String, TensorView)> = tensors
        .iter()
        .map(|(name, (dtype, shape, data))| {
            (
                name.clone(),
                TensorView::new(*dtype, shape.clone(), data).unwrap(),
            )
        })
        .collect();
    safetensors::serialize_to_file(views, None, out).unwrap();
}

#[test]
fn a_checkpoint_that_does_not_fit_names_the_first_bad_tensor() {
    let Some(dir) = reference_dir() else { return };
    let tmp = tempfile::tempdir().unwrap();
    let device = Device::flex();

    let missing = tmp.path().join("missing.safetensors");
    edited_checkpoint(&dir, &missing, |t| {
        t.remove("conv_cos.2.bias");
    });
    let error = load_weights(&missing, &device).unwrap_err();
    assert!(matches!(error, LoadError::Mismatch { .. }), "{error}");
    assert!(
        error
            .to_string()
            .contains("search_matcher.heads.cos.conv1x1.bias")
            && error.to_string().contains("missing"),
        "{error}"
    );

    let misshapen = tmp.path().join("misshapen.safetensors");
    edited_checkpoint(&dir, &misshapen, |t| {
        t.insert(
            "conv1.weight".into(),
            (Dtype::F32, vec![192, 96, 1, 1], vec![0u8; 192 * 96 * 4]),
        );
    });
    let error = load_weights(&misshapen, &device).unwrap_err().to_string();
    assert!(
        error.contains("search_matcher.decoder.conv1.weight") && error.contains("shape"),
        "{error}"
    );

    let extra = tmp.path().join("extra.safetensors");
    edited_checkpoint(&dir, &extra, |t| {
        t.insert(
            "conv_angle.0.weight".into(),
            (Dtype::F32, vec![4], vec![0u8; 16]),
        );
    });
    let error = load_weights(&extra, &device).unwrap_err().to_string();
    assert!(error.contains("conv_angle.0.weight"), "{error}");

    let garbage = tmp.path().join("garbage.pth");
    std::fs::write(&garbage, b"not a checkpoint").unwrap();
    let (code, _, stderr) = posematch(&[
        "weights",
        "import",
        "--from",
        garbage.to_str().unwrap(),
        "--out",
        tmp.path().join("x.bpk").to_str().unwrap(),
    ]);
    assert_ne!(code, 0);
    assert!(
        stderr.starts_with("error: weights file") && !stderr.contains("panicked"),
        "{stderr}"
    );
    assert_eq!(stderr.trim().lines().count(), 1, "{stderr}");
}

/// A mounted weights file often loses its name (a container's `/models/weights`): each format
/// is then recognised by its first bytes and loads exactly as under its own extension, and a
/// file that is none of them says which formats it takes.
#[test]
fn a_weights_file_without_an_extension_is_recognised_by_its_content() {
    let tmp = tempfile::tempdir().unwrap();
    let device = Device::flex();
    let nameless = tmp.path().join("weights");
    let same_network = |named: &std::path::Path| {
        std::fs::copy(named, &nameless).unwrap();
        let expected = forward(&load_weights(named, &device).unwrap(), &device);
        let loaded = load_weights(&nameless, &device).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(forward(&loaded, &device), expected, "{}", named.display());
    };
    same_network(
        &std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("models/posematch-default.bpk"),
    );
    let exported = tmp.path().join("default.safetensors");
    let (code, _, stderr) = posematch(&["weights", "export", "--out", exported.to_str().unwrap()]);
    assert_eq!(code, 0, "{stderr}");
    same_network(&exported);

    std::fs::write(&nameless, b"<html>not weights</html>").unwrap();
    let error = load_weights(&nameless, &device).unwrap_err();
    assert!(matches!(error, LoadError::UnknownFormat { .. }), "{error}");
    assert!(
        error.to_string().contains(".pth/.pt, .safetensors or .bpk"),
        "{error}"
    );

    let Some(dir) = reference_dir() else { return };
    same_network(&dir.join("tdcm-official.pth"));
}
