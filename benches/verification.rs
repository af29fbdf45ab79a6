//! What verified candidates cost per 224x224 pair against the path before them (README
//! "Verified candidates"): network top-1 alone, network top-1 refined (the default before
//! verification), and the verified default path (`max_instances` 1), on the same generated
//! pairs, for the embedded default weights and, when `../shared/reference` is present, the
//! authors' checkpoint, in the default arithmetic (`--precision auto`). Before the timings it
//! prints where the verified path's time goes (network, screen, confirmation, classical
//! fallback) and each path's success on these pairs.
//!
//! Pairs: 24 held-out pairs cut from `POSEMATCH_BENCH_PHOTOS` (default
//! `/usr/share/backgrounds/mate`, Debian's mate-backgrounds) at S1.5 with 36x36 templates.
//! `cargo bench --bench verification`

use std::path::PathBuf;
use std::time::{Duration, Instant};

/// The same allocator as the `posematch` binary, so the figures match what users get.
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use posematch::evaluation::{SUCCESS_IOU, pair_error};
use posematch::geometry::Pose;
use posematch::imaging::GrayImage32;
use posematch::imaging::InputConvention;
use posematch::matcher::selection::select;
use posematch::matcher::{EncodedTemplate, MatchOptions, MatchTimings, Matcher};
use posematch::model::{Precision, WeightsSource, load_weights, select_device};
use posematch::refine::refine_pose;
use posematch::synth::{Level, PairSpec, PhotoSet, SyntheticPair, make_pair};

const PAIRS: u64 = 24;

fn pairs() -> Option<Vec<SyntheticPair>> {
    let dir = std::env::var_os("POSEMATCH_BENCH_PHOTOS")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from("/usr/share/backgrounds/mate"));
    let photos = match PhotoSet::load(&dir, 224) {
        Ok(photos) => photos,
        Err(e) => {
            eprintln!(
                "SKIPPED: {e} (install mate-backgrounds or set POSEMATCH_BENCH_PHOTOS to a folder of photos)"
            );
            return None;
        }
    };
    let spec = PairSpec {
        level: Level::S1_5,
        template_width: 36,
        template_height: 36,
        search_side: 224,
        min_structure: posematch::synth::DEFAULT_MIN_STRUCTURE,
    };
    Some(
        (0..PAIRS)
            .map(|i| make_pair(&photos, &spec, 0, i).expect("pairs from the bench photos"))
            .collect(),
    )
}

/// The network's best peak, whatever its value (as `posematch eval`'s network row).
fn network_top1(matcher: &Matcher, pair: &SyntheticPair) -> Option<Pose> {
    let encoded = matcher.encode_template(&pair.template).unwrap();
    best_peak(matcher, &encoded, pair)
}

fn best_peak(matcher: &Matcher, encoded: &EncodedTemplate, pair: &SyntheticPair) -> Option<Pose> {
    let options = MatchOptions {
        max_instances: 1,
        min_score: Some(posematch::evaluation::ANY_PEAK),
        verify: false,
        ..MatchOptions::default()
    }
    .validate()
    .unwrap();
    let outcome = matcher.match_one(encoded, &pair.search, &options).unwrap();
    let (tw, th) = (pair.template.width as f32, pair.template.height as f32);
    select(outcome.poses, &options, tw, th).into_iter().next()
}

/// The path before verification: the best peak, refined.
fn refined_top1(matcher: &Matcher, pair: &SyntheticPair) -> Option<Pose> {
    let encoded = matcher.encode_template(&pair.template).unwrap();
    best_peak(matcher, &encoded, pair)
        .map(|p| refine_pose(&encoded.gray, &GrayImage32::from_rgb(&pair.search), &p))
}

/// The default path (`max_instances` 1, every other option at its default).
fn verified(matcher: &Matcher, pair: &SyntheticPair) -> (Option<Pose>, MatchTimings) {
    let options = MatchOptions {
        max_instances: 1,
        ..MatchOptions::default()
    }
    .validate()
    .unwrap();
    let encoded = matcher.encode_template(&pair.template).unwrap();
    let outcome = matcher.match_one(&encoded, &pair.search, &options).unwrap();
    (outcome.poses.into_iter().next(), outcome.timings)
}

fn successes(pairs: &[SyntheticPair], answers: &[Option<Pose>]) -> usize {
    pairs
        .iter()
        .zip(answers)
        .filter(|(pair, answer)| {
            answer.is_some_and(|p| pair_error(&p, &pair.truth[0], 36.0, 36.0).iou >= SUCCESS_IOU)
        })
        .count()
}

fn benches(c: &mut Criterion) {
    let Some(pairs) = pairs() else { return };
    let device = select_device().expect("BURN_DEVICE names a compiled backend");
    let mut models = vec![("default", WeightsSource::Embedded.load(&device).unwrap())];
    let official =
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/reference/tdcm-official.pth");
    if let Ok(model) = load_weights(&official, &device) {
        models.push(("official", model));
    }
    for (name, model) in models {
        // The CLI's and the service's default arithmetic (`auto`: bf16 where the CPU has it).
        let matcher = Matcher::new(model, device.clone(), InputConvention::ImagenetRgb)
            .with_precision(Precision::Auto)
            .unwrap_or_else(|e| panic!("{e}"));
        let arithmetic = matcher.network().precision().arithmetic();
        // Where the verified path's time goes, and what each path finds on these pairs.
        let start = Instant::now();
        let runs: Vec<(Option<Pose>, MatchTimings)> =
            pairs.iter().map(|p| verified(&matcher, p)).collect();
        let total_ms = start.elapsed().as_secs_f64() * 1e3 / pairs.len() as f64;
        let mean = |f: fn(&MatchTimings) -> f64| {
            runs.iter().map(|(_, t)| f(t)).sum::<f64>() / runs.len() as f64
        };
        let answers: Vec<Option<Pose>> = runs.iter().map(|(p, _)| *p).collect();
        let network: Vec<Option<Pose>> = pairs.iter().map(|p| network_top1(&matcher, p)).collect();
        let refined: Vec<Option<Pose>> = pairs.iter().map(|p| refined_top1(&matcher, p)).collect();
        println!(
            "{name} weights ({arithmetic}), {} pairs: verified {total_ms:.1} ms/pair = prepare {:.1} + network {:.1} + peaks {:.1} + screen {:.1} + confirm {:.1} + classical fallback {:.1} (ran on {} pairs) (+ template encode); Succ network {} / refined {} / verified {}",
            pairs.len(),
            mean(|t| t.prepare_ms),
            mean(|t| t.network_ms),
            mean(|t| t.peaks_ms),
            mean(|t| t.screen_ms),
            mean(|t| t.refine_ms),
            mean(|t| t.fallback_ms),
            runs.iter().filter(|(_, t)| t.fallback_ms > 0.0).count(),
            successes(&pairs, &network),
            successes(&pairs, &refined),
            successes(&pairs, &answers),
        );
        let mut group = c.benchmark_group(format!("verification_224/{name}"));
        group
            .sample_size(10)
            .measurement_time(Duration::from_secs(15))
            .throughput(Throughput::Elements(pairs.len() as u64));
        group.bench_function("network_top1", |b| {
            b.iter(|| {
                pairs
                    .iter()
                    .map(|p| network_top1(&matcher, p))
                    .collect::<Vec<_>>()
            })
        });
        group.bench_function("refined_top1_before", |b| {
            b.iter(|| {
                pairs
                    .iter()
                    .map(|p| refined_top1(&matcher, p))
                    .collect::<Vec<_>>()
            })
        });
        group.bench_function("verified_default", |b| {
            b.iter(|| {
                pairs
                    .iter()
                    .map(|p| verified(&matcher, p))
                    .collect::<Vec<_>>()
            })
        });
        group.finish();
    }
}

criterion_group!(verification, benches);
criterion_main!(verification);
