//! Golden output of the embedded default weights: the network's best candidates (no
//! refinement) on fixed generated pairs, compared with `tests/golden/embedded-default.json`.
//! It fails when the shipped weights, the network or the decoding change what users get; a
//! deliberate change (new default weights) rewrites the file with `POSEMATCH_BLESS=1 cargo test
//! --test golden` and says so in the commit.

mod common;

use std::path::PathBuf;

use burn::prelude::*;
use posematch::geometry::angle_distance_deg;
use posematch::imaging::InputConvention;
use posematch::matcher::{MatchJob, MatchOptions, Matcher};
use posematch::model::WeightsSource;
use posematch::synth::{PhotoSet, make_pair};
use serde_json::{Value, json};

/// Pixel and heatmap tolerances: the CPU implementation sum in a machine-dependent order.
const POSITION_TOLERANCE: f64 = 0.05;
const VALUE_TOLERANCE: f64 = 2e-3;
const ANGLE_TOLERANCE: f64 = 0.5;

fn golden_path() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/golden/embedded-default.json")
}

fn current_output() -> Value {
    let device = Device::flex();
    let model = WeightsSource::Embedded.load(&device).unwrap();
    let matcher = Matcher::new(model, device, InputConvention::ImagenetRgb);
    let photos_dir = common::structured_photo_dir();
    let photos = PhotoSet::load(photos_dir.path(), 224).unwrap();
    let spec = common::s1_5_spec();
    let options = MatchOptions {
        verify: false,
        min_score: Some(0.01),
        max_instances: 3,
        ..MatchOptions::default()
    }
    .validate()
    .unwrap();
    let pairs: Vec<Value> = (0..3)
        .map(|index| {
            let pair = make_pair(&photos, &spec, 5, index).unwrap();
            let encoded = matcher.encode_template(&pair.template).unwrap();
            let job = MatchJob {
                template: &encoded,
                image: &pair.search,
                options: &options,
                answer_by: None,
            };
            let proposal = matcher.propose(&[job]).pop().unwrap().unwrap();
            let top: Vec<Value> = proposal
                .candidates
                .iter()
                .take(3)
                .map(|p| {
                    json!({"x": p.x, "y": p.y, "angle_deg": p.angle_deg, "scale_x": p.scale_x,
                           "scale_y": p.scale_y, "network_score": p.network_score})
                })
                .collect();
            json!({"index": index, "candidates": top})
        })
        .collect();
    json!({"weights": "embedded default", "pairs": pairs})
}

fn close(name: &str, expected: f64, actual: f64) -> bool {
    let tolerance = match name {
        "x" | "y" => POSITION_TOLERANCE,
        "angle_deg" => ANGLE_TOLERANCE,
        _ => VALUE_TOLERANCE,
    };
    if name == "angle_deg" {
        return f64::from(angle_distance_deg(expected as f32, actual as f32)) <= tolerance;
    }
    (expected - actual).abs() <= tolerance
}

#[test]
fn embedded_default_weights_give_the_golden_candidates() {
    let actual = current_output();
    let path = golden_path();
    if std::env::var_os("POSEMATCH_BLESS").is_some() {
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        std::fs::write(&path, serde_json::to_string_pretty(&actual).unwrap() + "\n").unwrap();
        eprintln!("wrote {}", path.display());
        return;
    }
    let expected: Value = serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    let (expected, actual) = (&expected["pairs"], &actual["pairs"]);
    assert_eq!(expected.as_array().unwrap().len(), 3);
    for (e, a) in expected
        .as_array()
        .unwrap()
        .iter()
        .zip(actual.as_array().unwrap())
    {
        let (ec, ac) = (
            e["candidates"].as_array().unwrap(),
            a["candidates"].as_array().unwrap(),
        );
        assert_eq!(ec.len(), ac.len(), "pair {}: candidate count", e["index"]);
        for (k, (ep, ap)) in ec.iter().zip(ac).enumerate() {
            for (name, value) in ep.as_object().unwrap() {
                let (x, y) = (value.as_f64().unwrap(), ap[name].as_f64().unwrap());
                assert!(
                    close(name, x, y),
                    "pair {} candidate {k} {name}: golden {x}, now {y} (a deliberate change of the \
                     default weights or the network? rewrite with POSEMATCH_BLESS=1)",
                    e["index"]
                );
            }
        }
    }
}
