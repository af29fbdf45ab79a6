//! Training end to end on a few generated photos: the loss falls, checkpoints are written
//! atomically, a run resumes where it stopped, and the weights it wrote load and match.

mod common;

use std::time::Duration;

use burn::prelude::*;
use common::structured_photo_dir;
use posematch::imaging::{InputConvention, RgbImage32};
use posematch::matcher::{Matcher, ValidOptions};
use posematch::model::load_weights;
use posematch::synth::Level;
use posematch::train::{TrainEvent, TrainOptions, train};

fn options(photos: &std::path::Path, out: &std::path::Path, steps: u64) -> TrainOptions {
    TrainOptions {
        images: vec![photos.to_owned()],
        validation_images: Some(photos.to_owned()),
        level: Level::S1_5,
        steps,
        batch: 2,
        search_side: 96,
        learning_rate: 2e-3,
        seed: 3,
        init: None,
        resume: false,
        out: out.to_owned(),
        checkpoint_every: Duration::from_secs(3600),
        validate_every: 0,
        validation_pairs: 2,
    }
}

#[test]
fn training_lowers_the_loss_checkpoints_and_resumes() {
    let photos = structured_photo_dir();
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("smoke.bpk");
    let device = Device::flex();

    let mut losses = Vec::new();
    let mut validations = 0;
    let outcome = train(
        &options(photos.path(), &out, 12),
        &device,
        |event| match event {
            TrainEvent::Step { loss, .. } => losses.push(loss),
            TrainEvent::Validation { .. } => validations += 1,
            _ => {}
        },
    )
    .unwrap();
    println!("losses: {losses:?}");
    assert_eq!(outcome.steps_done, 12);
    assert_eq!(validations, 1, "a validation table at the end");
    let mean = |v: &[f32]| v.iter().sum::<f32>() / v.len() as f32;
    assert!(
        mean(&losses[9..]) < 0.7 * mean(&losses[..3]),
        "loss did not fall: {losses:?}"
    );
    for suffix in ["", ".optim.bpk", ".train.json"] {
        let mut name = out.as_os_str().to_owned();
        name.push(suffix);
        assert!(std::path::Path::new(&name).is_file(), "{name:?} missing");
    }
    let leftovers = std::fs::read_dir(dir.path())
        .unwrap()
        .filter(|e| {
            e.as_ref()
                .unwrap()
                .file_name()
                .to_string_lossy()
                .ends_with(".tmp")
        })
        .count();
    assert_eq!(leftovers, 0);

    // Resume: continues at step 12 and runs only the missing steps.
    let mut resumed = options(photos.path(), &out, 15);
    resumed.resume = true;
    resumed.validation_images = None;
    let mut first = None;
    let outcome = train(&resumed, &device, |event| {
        if let TrainEvent::Started { first_step, .. } = event {
            first = Some(first_step);
        }
    })
    .unwrap();
    assert_eq!(first, Some(12));
    assert_eq!(outcome.steps_done, 3);
    let progress: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(dir.path().join("smoke.bpk.train.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(progress["step"], 15);

    // A resume with another seed would replay different pairs: refused with a message.
    let mut wrong = resumed.clone();
    wrong.seed = 4;
    let error = train(&wrong, &device, |_| {}).unwrap_err().to_string();
    assert!(error.contains("seed"), "{error}");

    // The written weights load for inference and match.
    let model = load_weights(&out, &device).unwrap();
    let matcher = Matcher::new(model, device, InputConvention::ImagenetRgb);
    let template = RgbImage32::new(36, 36, vec![0.5; 36 * 36 * 3]);
    let image = RgbImage32::new(96, 96, vec![0.5; 96 * 96 * 3]);
    let encoded = matcher.encode_template(&template).unwrap();
    matcher
        .match_one(&encoded, &image, &ValidOptions::default())
        .unwrap();
}

#[test]
fn absurd_options_are_refused_with_the_flag_named() {
    let photos = structured_photo_dir();
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("w.bpk");
    let device = Device::flex();
    type Tweak = Box<dyn Fn(&mut TrainOptions)>;
    let cases: Vec<(Tweak, &str)> = vec![
        (Box::new(|o| o.steps = 0), "--steps"),
        (Box::new(|o| o.batch = 0), "--batch"),
        (Box::new(|o| o.search_side = 90), "--search-size"),
        (Box::new(|o| o.learning_rate = 5.0), "--lr"),
        (Box::new(|o| o.resume = true), "cannot resume"),
    ];
    for (tweak, expected) in cases {
        let mut o = options(photos.path(), &out, 5);
        tweak(&mut o);
        let error = train(&o, &device, |_| {}).unwrap_err().to_string();
        assert!(
            error.contains(expected),
            "{error} should mention {expected}"
        );
    }
}

/// The shipped binary runs on its embedded default weights, and `posematch train` is a real
/// command: a short fine-tuning run from them (`--init default`, all a user of the binary or the
/// container has) writes weights that `match` then loads.
#[test]
fn cli_matches_on_embedded_weights_and_fine_tunes_them() {
    use common::posematch;
    let photos = structured_photo_dir();
    let dir = tempfile::tempdir().unwrap();
    let photo = photos.path().join("photo0.png");
    let template = dir.path().join("template.png");
    image::open(&photo)
        .unwrap()
        .crop_imm(200, 150, 36, 36)
        .save(&template)
        .unwrap();
    let (code, stdout, stderr) = posematch(&[
        "match",
        "--template",
        template.to_str().unwrap(),
        "--image",
        photo.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{stderr}");
    let answer: serde_json::Value = serde_json::from_str(&stdout).unwrap();
    assert_eq!(answer["image_width"], 640);

    let out = dir.path().join("tuned.bpk");
    let (code, _, stderr) = posematch(&[
        "train",
        "--images",
        photos.path().to_str().unwrap(),
        "--init",
        "default",
        "--steps",
        "2",
        "--batch",
        "1",
        "--search-size",
        "64",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{stderr}");
    assert!(
        stderr.contains("from the embedded default weights"),
        "{stderr}"
    );
    let (code, _, stderr) = posematch(&[
        "match",
        "--template",
        template.to_str().unwrap(),
        "--image",
        photo.to_str().unwrap(),
        "--weights",
        out.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{stderr}");

    let (code, _, stderr) = posematch(&[
        "train",
        "--images",
        photos.path().to_str().unwrap(),
        "--steps",
        "0",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(code, 2, "{stderr}");
    assert!(stderr.contains("--steps"), "{stderr}");
    assert_eq!(stderr.trim().lines().count(), 1, "{stderr}");
}
