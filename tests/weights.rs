//! Weights: the one-time conversion round-trips exactly, and checkpoints that do not fit the
//! architecture fail with the name of the first offending tensor.

mod common;

use std::collections::HashMap;

use burn::prelude::*;
use common::{posematch, reference_dir};
use posematch::model::{LoadError, load_weights};
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
