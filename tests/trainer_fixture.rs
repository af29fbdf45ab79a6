//! The PyTorch trainer (`training/`) trains the network we serve: weights it exported
//! (`training/fixtures/trainer-weights.pth`, perturbed random initialisation) give our burn
//! network the same five maps as its own model on the stored inputs, directly and after
//! `posematch weights import`; and its labels equal `src/train/labels.rs`'s for the stored poses.
//! All within 1e-4. The fixture is written by `python3 training/export_fixture.py`; this test
//! needs no PyTorch.

mod common;

use std::path::PathBuf;

use burn::prelude::*;
use common::{read_f32, tensor, worst};
use posematch::geometry::Pose;
use posematch::model::{InferenceNetwork, load_weights};
use posematch::train::LabelMaps;
use safetensors::SafeTensors;

const TOLERANCE: f32 = 1e-4;

fn fixtures() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("training/fixtures")
}

fn check_maps(network: &InferenceNetwork, st: &SafeTensors, device: &Device, what: &str) {
    let kernels = network.encode_templates(tensor(st, "template", device));
    let maps = network
        .forward(tensor(st, "search", device), kernels)
        .stacked;
    let (expected, shape) = read_f32(st, "maps");
    assert_eq!(maps.dims().to_vec(), shape, "{what}: map shape");
    let actual: Vec<f32> = maps.into_data().try_to_vec().unwrap();
    let (at, diff) = worst(&expected, &actual);
    println!("{what}: max|diff| {diff:.2e}");
    assert!(
        diff <= TOLERANCE,
        "{what}: map element {at} differs by {diff:e} (trainer {}, ours {})",
        expected[at],
        actual[at]
    );
}

#[test]
fn trainer_weights_give_our_network_the_trainers_maps() {
    let bytes = std::fs::read(fixtures().join("trainer-fixture.safetensors")).unwrap();
    let st = SafeTensors::deserialize(&bytes).unwrap();
    let device = Device::flex();
    let weights = fixtures().join("trainer-weights.pth");
    let model = load_weights(&weights, &device).expect("the trainer's export loads");
    check_maps(
        &InferenceNetwork::host(model.clone()),
        &st,
        &device,
        "direct, CPU implementation",
    );
    check_maps(
        &InferenceNetwork::modules(model),
        &st,
        &device,
        "direct, burn modules",
    );

    // The documented import step: .pth -> our own format, then served from that.
    let dir = tempfile::tempdir().unwrap();
    let imported = dir.path().join("trainer.bpk");
    let (code, _, stderr) = common::posematch(&[
        "weights",
        "import",
        "--from",
        weights.to_str().unwrap(),
        "--out",
        imported.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "weights import failed: {stderr}");
    let model = load_weights(&imported, &device).expect("the imported weights load");
    check_maps(
        &InferenceNetwork::new(model, &device),
        &st,
        &device,
        "after `posematch weights import`",
    );
}

#[test]
fn trainer_labels_equal_ours() {
    let bytes = std::fs::read(fixtures().join("trainer-fixture.safetensors")).unwrap();
    let st = SafeTensors::deserialize(&bytes).unwrap();
    let (poses, pose_shape) = read_f32(&st, "label_poses");
    let (labels, shape) = read_f32(&st, "labels");
    let (count, channels, height, width) = (shape[0], shape[1], shape[2], shape[3]);
    assert_eq!((pose_shape[0], pose_shape[1], channels), (count, 5, 6));
    let plane = height * width;
    for (k, p) in poses.chunks_exact(5).enumerate() {
        let truth = Pose {
            x: p[0],
            y: p[1],
            angle_deg: p[2],
            scale_x: p[3],
            scale_y: p[4],
            score: 1.0,
            network_score: 0.0,
        };
        let ours = LabelMaps::render(width, height, &[truth], 36.0, 36.0);
        let fields = [
            ("heatmap", &ours.heatmap),
            ("valid", &ours.valid),
            ("sign", &ours.sign),
            ("cos", &ours.cos),
            ("scale_x", &ours.scale_x),
            ("scale_y", &ours.scale_y),
        ];
        for (c, (name, values)) in fields.iter().enumerate() {
            let start = (k * channels + c) * plane;
            let theirs = &labels[start..start + plane];
            let (at, diff) = worst(theirs, values);
            assert!(
                diff <= TOLERANCE,
                "pose {k} {name}: pixel {at} differs by {diff:e} (trainer {}, ours {})",
                theirs[at],
                values[at]
            );
        }
        let valid: f32 = ours.valid.iter().sum();
        assert!(valid > 0.0, "pose {k} supervises no pixel");
    }
}
