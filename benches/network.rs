//! Network and pipeline speed: template encode, search forward at 224x224 with a 36x36 template
//! for batch 1/4/8 (criterion reports time per call and pairs/s as elem/s; ms per pair is the
//! time divided by the batch), peak reading (up to 56 peaks from random-input maps, min_score 0.05),
//! and 224², 1024² and 2048² frames through the whole matcher.
//!
//! Uses the official checkpoint from `../shared/reference` when present (so peak reading sees real
//! maps), random weights otherwise (speed does not depend on the values). Before the timings it
//! prints the network's multiply-adds per pair and this machine's single-precision matmul rate
//! measured through the same backend, to put GFLOP/s in context.

use std::path::PathBuf;

/// The same allocator as the `posematch` binary, so the figures match what users get.
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;
use std::time::{Duration, Instant};

use burn::prelude::*;
use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};
use posematch::imaging::GrayImage32;
use posematch::imaging::{InputConvention, RgbImage32};
use posematch::matcher::peaks::{MapPlanes, find_peaks, peak_at};
use posematch::matcher::{MatchOptions, Matcher};
use posematch::model::cpu::{bf16, ops::matmul_bias};
use posematch::model::{Precision, Tdcm, TdcmConfig, load_weights, multiply_adds, select_device};
use posematch::refine::refine_pose;

/// Single-thread GFLOP/s of an `[m, k] x [k, n]` product (bias included) with the f32 gemm of
/// the CPU implementation, and with this process's bf16 instructions (`None` without one), printed beside
/// the machine's peak.
fn product_gflops(m: usize, k: usize, n: usize) -> (f64, Option<f64>) {
    let input: Vec<f32> = (0..m * k).map(|i| (i % 7) as f32 * 0.1).collect();
    let matrix: Vec<f32> = (0..k * n).map(|i| (i % 5) as f32 * 0.1).collect();
    let bias = vec![0.5f32; n];
    let mut out = vec![0f32; m * n];
    let flops = 2.0 * (m * k * n) as f64;
    let mut rate = |product: &mut dyn FnMut(&mut [f32])| {
        product(&mut out);
        let runs = (2e9 / flops).clamp(3.0, 10_000.0) as usize;
        let start = std::time::Instant::now();
        for _ in 0..runs {
            product(&mut out);
        }
        flops * runs as f64 / start.elapsed().as_secs_f64() / 1e9
    };
    let f32_rate = rate(&mut |out| matmul_bias(&input, m, k, &matrix, n, &bias, out));
    let bf16_rate = bf16::available().then(|| {
        let weights = bf16::Bf16Weights::new(&matrix, k, n, &bias);
        let stride = weights.lhs_stride();
        let mut lhs = vec![0u16; bf16::padded_rows(m) * stride];
        for (row, values) in lhs.chunks_exact_mut(stride).zip(input.chunks_exact(k)) {
            bf16::round_into(values, &mut row[..k]);
        }
        rate(&mut |out| bf16::multiply(&lhs, m, &weights, out))
    });
    (f32_rate, bf16_rate)
}

fn model(device: &Device) -> (Tdcm, &'static str) {
    let official =
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/reference/tdcm-official.pth");
    match load_weights(&official, device) {
        Ok(m) => (m, "official checkpoint"),
        Err(_) => (TdcmConfig::new().init(device), "random weights"),
    }
}

/// A textured test frame (smooth pseudo-random pattern) of the given size.
fn frame(width: u32, height: u32) -> RgbImage32 {
    let mut pixels = Vec::with_capacity((width * height * 3) as usize);
    for y in 0..height {
        for x in 0..width {
            let (fx, fy) = (x as f32, y as f32);
            let v = 0.5
                + 0.25 * (fx * 0.07).sin() * (fy * 0.05).cos()
                + 0.2 * ((fx * 0.013 + fy * 0.021).sin() * 3.0).sin();
            pixels.extend_from_slice(&[v, v * 0.9, v * 0.8]);
        }
    }
    RgbImage32::new(width, height, pixels)
}

fn matmul_gflops(device: &Device) -> f64 {
    let n = 1024;
    let a: Tensor<2> = Tensor::ones([n, n], device);
    let b: Tensor<2> = Tensor::ones([n, n], device);
    let _ = a.clone().matmul(b.clone()).into_data();
    let runs = 10;
    let t = Instant::now();
    for _ in 0..runs {
        let _ = a.clone().matmul(b.clone()).into_data();
    }
    2.0 * (n * n * n) as f64 * runs as f64 / t.elapsed().as_secs_f64() / 1e9
}

fn benches(c: &mut Criterion) {
    let device = select_device().expect("BURN_DEVICE names a compiled backend");
    let (model, source) = model(&device);
    let macs = multiply_adds(224, 224, 36);
    println!(
        "network: {source}; {:.3} G multiply-adds per 224x224/36 pair ({:.2} GFLOP); \
         single-precision 1024^3 matmul on this backend: {:.1} GFLOP/s",
        macs as f64 / 1e9,
        2.0 * macs as f64 / 1e9,
        matmul_gflops(&device)
    );
    // The CPU implementation' products on one thread, at the shapes of a backbone block's fc1 and
    // fc2 and of the upsampler's conv1 (a 256-pixel chunk), in f32 and with the bf16 instructions.
    for (m, k, n) in [(256, 96, 384), (256, 384, 96), (256, 864, 192)] {
        let (f32_rate, bf16_rate) = product_gflops(m, k, n);
        println!(
            "product [{m}x{k}]x[{k}x{n}], one thread: f32 {f32_rate:.0} GFLOP/s, bf16 {}",
            match (bf16_rate, bf16::instructions()) {
                (Some(rate), Some(kernel)) => format!("{rate:.0} GFLOP/s ({kernel})"),
                _ => "not available on this CPU".into(),
            }
        );
    }
    let matcher = Matcher::new(model, device.clone(), InputConvention::ImagenetRgb);
    let template = frame(36, 36);
    let encoded = matcher.encode_template(&template).unwrap();

    let mut group = c.benchmark_group("network");
    group
        .sample_size(10)
        .measurement_time(Duration::from_secs(8));
    let template_input = Tensor::<4>::random(
        [1, 3, 36, 36],
        burn::tensor::Distribution::Normal(0.0, 1.0),
        &device,
    );
    group.bench_function("template_encode_36", |b| {
        b.iter(|| {
            matcher
                .network()
                .encode_templates(template_input.clone())
                .into_data()
        })
    });
    for batch in [1usize, 4, 8] {
        let images = Tensor::<4>::random(
            [batch, 3, 224, 224],
            burn::tensor::Distribution::Normal(0.0, 1.0),
            &device,
        );
        let kernels = Tensor::cat(vec![encoded.kernel.clone(); batch], 0);
        group.throughput(Throughput::Elements(batch as u64));
        group.bench_with_input(
            BenchmarkId::new("search_224_batch", batch),
            &batch,
            |b, _| {
                b.iter(|| {
                    let maps = matcher.network().forward(images.clone(), kernels.clone());
                    maps.stacked.into_data()
                })
            },
        );
    }
    // What a search runs: the pose heads only where the score reaches the default candidate
    // threshold's half (see `Matcher::run_network`).
    {
        let images = Tensor::<4>::random(
            [1, 3, 224, 224],
            burn::tensor::Distribution::Normal(0.0, 1.0),
            &device,
        );
        let planar: Vec<f32> = images.into_data().try_into_vec().unwrap();
        let least = 0.5 * posematch::matcher::MatchOptions::default().candidate_threshold;
        group.throughput(Throughput::Elements(1));
        // The same search with the products in bf16, where this CPU has bf16 instructions.
        let bf16 = match Precision::Bf16.check_machine() {
            Ok(()) => Some(
                Matcher::new(
                    matcher.network().model().clone(),
                    device.clone(),
                    InputConvention::ImagenetRgb,
                )
                .with_precision(Precision::Bf16)
                .unwrap(),
            ),
            Err(e) => {
                println!("bf16 search not measured: {e}");
                None
            }
        };
        let searches = [("", Some(&matcher)), ("_bf16", bf16.as_ref())];
        for (suffix, searcher) in searches {
            let Some(searcher) = searcher else { continue };
            let name = format!("search_224_batch_1_pose_heads_at_peaks{suffix}");
            group.bench_function(name, |b| {
                b.iter(|| {
                    let maps = searcher.network().search_maps(
                        planar.clone(),
                        [1, 224, 224],
                        encoded.kernel.clone(),
                        posematch::model::PoseHeads::WhereScoreAtLeast(least),
                    );
                    searcher.network().recycle(maps);
                })
            });
        }
    }
    // Peak reading alone: peaks, sub-pixel centres and parameters from one 224x224 set of maps.
    let images = Tensor::<4>::random(
        [1, 3, 224, 224],
        burn::tensor::Distribution::Normal(0.0, 1.0),
        &device,
    );
    let maps: Vec<f32> = matcher
        .network()
        .forward(images, encoded.kernel.clone())
        .stacked
        .into_data()
        .try_into_vec()
        .unwrap();
    let n = 224 * 224;
    let planes = MapPlanes {
        width: 224,
        height: 224,
        score: &maps[..n],
        sign: &maps[n..2 * n],
        cos: &maps[2 * n..3 * n],
        scale_x: &maps[3 * n..4 * n],
        scale_y: &maps[4 * n..5 * n],
    };
    group.throughput(Throughput::Elements(1));
    group.bench_function("peaks_224", |b| {
        b.iter(|| {
            find_peaks(&planes, 0.05, 56)
                .into_iter()
                .map(|(r, c)| peak_at(&planes, r, c))
                .collect::<Vec<_>>()
        })
    });
    // Refinement of one instance at 36x36 from a pose a few degrees, pixels and percent off.
    let search_image = frame(224, 224);
    let gray_search = GrayImage32::from_rgb(&search_image);
    let truth = posematch::geometry::Pose {
        x: 110.3,
        y: 97.8,
        angle_deg: 25.0,
        scale_x: 1.1,
        scale_y: 0.9,
        score: 1.0,
        network_score: 0.0,
    };
    let mut values = Vec::new();
    for b in 0..36 {
        for a in 0..36 {
            let (x, y) = truth.map_point(a as f32 - 17.5, b as f32 - 17.5);
            let i = (y.round() as usize * 224 + x.round() as usize).min(224 * 224 - 1);
            values.push(gray_search.values[i]);
        }
    }
    let gray_template = GrayImage32 {
        width: 36,
        height: 36,
        values,
    };
    let rough = posematch::geometry::Pose {
        x: 111.5,
        y: 96.9,
        angle_deg: 33.0,
        scale_x: 1.25,
        scale_y: 0.85,
        score: 0.8,
        network_score: 0.0,
    };
    group.bench_function("refine_instance_36", |b| {
        b.iter(|| refine_pose(&gray_template, &gray_search, &rough))
    });
    group.finish();

    let mut group = c.benchmark_group("pipeline");
    group
        .sample_size(10)
        .measurement_time(Duration::from_secs(10));
    let options = MatchOptions {
        verify: false,
        ..MatchOptions::default()
    }
    .validate()
    .unwrap();
    for side in [224u32, 1024, 2048] {
        let image = frame(side, side);
        if side > 224 {
            group
                .sample_size(10)
                .measurement_time(Duration::from_secs(30));
        }
        group.bench_function(format!("match_{side}x{side}"), |b| {
            b.iter(|| matcher.match_one(&encoded, &image, &options).unwrap())
        });
    }
    group.finish();
}

criterion_group!(network, benches);
criterion_main!(network);
