//! The network computes the official checkpoint's function: every tensor stored in
//! `../shared/reference/tdcm-parity.safetensors` is reproduced from the fixture's inputs.
//!
//! Tolerances (issue #2): every element within max(1e-4, 1e-5 × the tensor's largest magnitude);
//! the five heads within 1e-4 absolute. Skips, saying why, when `../shared/reference` is absent.

mod common;

use burn::prelude::*;
use common::{read_f32, reference_dir, tensor, worst};
use posematch::model::{InferenceNetwork, MatchMaps, available_backends, load_weights};
use safetensors::SafeTensors;

/// Compares, returns a failure description or None.
fn compare(st: &SafeTensors, name: &str, actual: Tensor<4>, absolute_only: bool) -> Option<String> {
    let (expected, shape) = read_f32(st, name);
    assert_eq!(actual.dims().to_vec(), shape, "{name}: shape");
    let actual: Vec<f32> = actual.into_data().try_to_vec().unwrap();
    let magnitude = expected.iter().fold(0f32, |m, v| m.max(v.abs()));
    let tolerance = if absolute_only {
        1e-4
    } else {
        (1e-5 * magnitude).max(1e-4)
    };
    let (worst_index, worst) = worst(&expected, &actual);
    println!(
        "{name:24} max|diff| {worst:.3e} (tolerance {tolerance:.1e}, max|value| {magnitude:.1})"
    );
    (worst > tolerance || worst.is_nan()).then(|| {
        format!(
            "{name}: element {worst_index} differs by {worst:e} (expected {}, got {}), tolerance {tolerance:e}",
            expected[worst_index], actual[worst_index]
        )
    })
}

fn check_backend(device: &Device, network: &InferenceNetwork, st: &SafeTensors) -> Vec<String> {
    let mut failures = Vec::new();
    for pair in ["a", "b1", "b2"] {
        let n = |s: &str| format!("{pair}.{s}");
        let template = tensor(st, &n("template"), device);
        let search = tensor(st, &n("search"), device);
        let (kernels, template_trace) = network.encode_templates_traced(template);
        let (maps, trace) = network.forward_traced(search, kernels.clone());
        let checks: Vec<(&str, Tensor<4>, bool)> = vec![
            ("backbone_T_stem", template_trace.stem, false),
            ("backbone_T", kernels, false),
            ("backbone_O_stem", trace.backbone.stem, false),
            ("backbone_O_stage1", trace.backbone.stage1, false),
            ("backbone_O", trace.features, false),
            ("dwcorr", trace.correlation, false),
            ("pointwise", trace.fusion, false),
            ("bn1", trace.bn1, false),
            ("bn2", trace.bn2, false),
        ];
        let heads = MatchMaps::CHANNELS
            .iter()
            .enumerate()
            .map(|(i, name)| (*name, maps.channel(i), true));
        let checks = checks.into_iter().chain(heads);
        for (name, actual, absolute_only) in checks {
            failures.extend(compare(st, &n(name), actual, absolute_only));
        }
    }
    failures
}

#[test]
fn network_reproduces_every_fixture_tensor_on_every_backend() {
    let Some(dir) = reference_dir() else { return };
    let bytes = std::fs::read(dir.join("tdcm-parity.safetensors")).unwrap();
    let st = SafeTensors::deserialize(&bytes).unwrap();
    let mut failures = Vec::new();
    for backend in available_backends() {
        let device = match backend {
            #[cfg(feature = "ndarray")]
            "ndarray" => Device::ndarray(),
            _ => Device::flex(),
        };
        // Both weight files, and both inference paths, each chosen explicitly: the host CPU
        // kernels (what the matcher runs on the CPU) and burn's modules (what training and GPUs
        // run).
        for (weights, host) in [
            ("tdcm-official.pth", true),
            ("tdcm-official.safetensors", true),
            ("tdcm-official.pth", false),
        ] {
            let model = load_weights(&dir.join(weights), &device).expect("official weights load");
            let (network, path) = if host {
                (InferenceNetwork::host(model), "host CPU kernels")
            } else {
                (InferenceNetwork::modules(model), "burn modules")
            };
            assert_eq!(network.runs_host_kernels(), host);
            println!("--- backend {backend}, weights {weights}, {path}");
            failures.extend(
                check_backend(&device, &network, &st)
                    .into_iter()
                    .map(|f| format!("[{backend}, {weights}, {path}] {f}")),
            );
        }
    }
    assert!(
        failures.is_empty(),
        "parity failures:\n{}",
        failures.join("\n")
    );
}
