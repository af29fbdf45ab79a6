//! Pose accuracy on generated pairs with exact ground truth (the paper's Algorithm 1): refinement
//! recovers the true pose from a rough start, and with the official checkpoint it sharpens the
//! network's poses without ever losing an object the network found.

mod common;

use burn::prelude::*;
use common::{official_matcher, reference_dir, s1_5_spec, structured_photo_dir};
use posematch::evaluation::{ANY_PEAK, Paths, match_pair, pair_error};
use posematch::geometry::Pose;
use posematch::imaging::GrayImage32;
use posematch::imaging::InputConvention;
use posematch::matcher::{MatchOptions, Matcher};
use posematch::refine::refine_pose;
use posematch::synth::{PhotoSet, make_pair};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

#[test]
fn refinement_recovers_the_true_pose_from_a_rough_start() {
    let dir = structured_photo_dir();
    let photos = PhotoSet::load(dir.path(), 224).unwrap();
    let mut rng = StdRng::seed_from_u64(5);
    let (mut centre, mut angle, mut scale) = (Vec::new(), Vec::new(), Vec::new());
    for index in 0..20 {
        let pair = make_pair(&photos, &s1_5_spec(), 1, index).unwrap();
        let truth = pair.truth[0];
        // A start like the network's: pixels, degrees and tens of percent off.
        let rough = Pose {
            x: truth.x + rng.random_range(-3.0..3.0),
            y: truth.y + rng.random_range(-3.0..3.0),
            angle_deg: truth.angle_deg + rng.random_range(-12.0..12.0),
            scale_x: truth.scale_x * rng.random_range(0.85..1.15),
            scale_y: truth.scale_y * rng.random_range(0.85..1.15),
            score: 0.7,
            network_score: 0.0,
        };
        let refined = refine_pose(
            &GrayImage32::from_rgb(&pair.template),
            &GrayImage32::from_rgb(&pair.search),
            &rough,
        );
        let error = pair_error(&refined, &truth, 36.0, 36.0);
        centre.push(error.centre_px);
        angle.push(error.rotation_deg);
        scale.push(error.scale);
    }
    let mean = |v: &[f32]| v.iter().sum::<f32>() / v.len() as f32;
    let (c, a, s) = (mean(&centre), mean(&angle), mean(&scale));
    println!("refined from rough starts: centre {c:.3} px, angle {a:.3}°, scale {s:.4}");
    assert!(c < 0.2, "mean centre error {c} px: {centre:?}");
    assert!(a < 0.3, "mean angle error {a}°: {angle:?}");
    assert!(s < 0.01, "mean scale error {s}: {scale:?}");
}

#[test]
fn refinement_sharpens_the_official_network_and_never_loses_an_object() {
    let Some(dir) = reference_dir() else { return };
    let matcher = official_matcher(&dir);
    let photos_dir = structured_photo_dir();
    let photos = PhotoSet::load(photos_dir.path(), 224).unwrap();
    let options = MatchOptions {
        max_instances: 1,
        min_score: Some(0.01),
        verify: false,
        ..MatchOptions::default()
    }
    .validate()
    .unwrap();
    let (mut coarse_hits, mut refined_hits, mut lost) = (0, 0, 0);
    let (mut coarse_angle, mut refined_angle) = (0.0, 0.0);
    let pairs = 16;
    for index in 0..pairs {
        let pair = make_pair(&photos, &s1_5_spec(), 2, index).unwrap();
        let truth = pair.truth[0];
        let encoded = matcher.encode_template(&pair.template).unwrap();
        let outcome = matcher.match_one(&encoded, &pair.search, &options).unwrap();
        let Some(coarse) = outcome.poses.first() else {
            continue;
        };
        let refined = refine_pose(&encoded.gray, &GrayImage32::from_rgb(&pair.search), coarse);
        let (c, r) = (
            pair_error(coarse, &truth, 36.0, 36.0),
            pair_error(&refined, &truth, 36.0, 36.0),
        );
        if c.iou >= 0.5 {
            coarse_hits += 1;
            coarse_angle += c.rotation_deg;
            if r.iou < 0.5 {
                lost += 1;
            } else {
                refined_angle += r.rotation_deg;
            }
        }
        if r.iou >= 0.5 {
            refined_hits += 1;
        }
    }
    println!(
        "{pairs} pairs: network found {coarse_hits} (mean angle error {:.2}°), refined {refined_hits} (on the network's hits {:.3}°), lost {lost}",
        coarse_angle / coarse_hits.max(1) as f32,
        refined_angle / coarse_hits.max(1) as f32,
    );
    assert!(
        coarse_hits >= pairs / 2,
        "the network found only {coarse_hits}"
    );
    assert_eq!(lost, 0, "refinement lost an object the network had found");
    assert!(refined_hits >= coarse_hits);
    assert!(
        refined_angle / (coarse_hits as f32) < 0.5,
        "refined angle error {}° on the network's hits",
        refined_angle / coarse_hits as f32
    );
}

/// Single-instance pairs through the three paths of `posematch eval` (one network pass each):
/// objects found by the network's best peak, by that peak refined and by verified candidates.
fn three_paths(matcher: &Matcher, pairs: u64) -> [usize; 3] {
    let photos_dir = structured_photo_dir();
    let photos = PhotoSet::load(photos_dir.path(), 224).unwrap();
    let options = MatchOptions {
        max_instances: 1,
        ..MatchOptions::default()
    }
    .validate()
    .unwrap();
    let mut found = [0; 3];
    for index in 0..pairs {
        let pair = make_pair(&photos, &s1_5_spec(), 3, index).unwrap();
        let truth = pair.truth[0];
        let run = match_pair(
            matcher,
            &pair,
            None,
            &options,
            ANY_PEAK,
            Paths {
                refined: true,
                verified: true,
            },
        )
        .unwrap();
        let answered: Vec<Pose> = run
            .verified
            .iter()
            .filter(|p| p.score >= options.effective_min_score())
            .copied()
            .collect();
        for (path, poses) in [run.network, run.refined, answered].iter().enumerate() {
            if let Some(p) = poses.first() {
                let error = pair_error(p, &truth, 36.0, 36.0);
                if error.iou >= 0.5 {
                    found[path] += 1;
                    if path == 2 {
                        // A verified answer is a refined one: precise, and scored by similarity.
                        assert!(error.centre_px < 0.5, "{error:?}");
                        assert!(p.score > 0.8 && p.network_score > 0.0, "{p:?}");
                    }
                }
            }
        }
    }
    found
}

#[test]
fn verified_candidates_find_what_the_best_peak_misses_with_the_embedded_weights() {
    let device = Device::flex();
    let model = posematch::model::WeightsSource::Embedded
        .load(&device)
        .unwrap();
    let matcher = Matcher::new(model, device, InputConvention::ImagenetRgb);
    let pairs = 24;
    let [network, refined, verified] = three_paths(&matcher, pairs);
    println!(
        "{pairs} pairs, embedded weights: network {network}, refined {refined}, verified {verified}"
    );
    // Verification keeps what the refined best peak finds and recovers at least half of what it
    // misses (the weights of 2026-11-26: the best peak misses 2 of 24, verification none).
    let missed = pairs as usize - refined;
    assert!(
        verified >= refined + missed.div_ceil(2),
        "verification found {verified}, the refined best peak {refined} of {pairs}"
    );
}

#[test]
fn verified_candidates_keep_what_the_official_network_finds() {
    let Some(dir) = reference_dir() else { return };
    let matcher = official_matcher(&dir);
    let pairs = 16;
    let [network, refined, verified] = three_paths(&matcher, pairs);
    println!(
        "{pairs} pairs, official weights: network {network}, refined {refined}, verified {verified}"
    );
    assert!(
        verified >= refined,
        "verification found {verified}, the refined best peak {refined}"
    );
}
