//! Large frames and small templates (issue 13): ms, recall and precision per case, with 1 and 2
//! threads, for the embedded default weights and, when `../shared/reference` is present, the
//! authors' checkpoint; then the classical matcher on the same large frame.
//!
//! Cases, all generated with exact truth (`posematch::synth::parts_frame`, procedural parts on a
//! procedural background, so no photo folder is needed):
//! - `frame2048`: 2048x2048, 144 parts of 28x52 at any angle, scale 1 (the paper's industrial
//!   case), `max_instances` 200, otherwise CLI defaults;
//! - `pair224`: 224x224 with one 36x36 part;
//! - `tiny12`: 224x224 with one 12x12 part;
//! - `frame2048board`: `frame2048`'s parts laid on a procedural circuit board
//!   (`posematch::synth::circuit_board`: traces, pads, chips, silkscreen), man-made clutter;
//! - `frame2048photo`, when `POSEMATCH_BENCH_PHOTOS=DIR` names a folder of photos: `frame2048`'s
//!   parts laid on a photo (one per frame in turn, stretched to 2048x2048) instead of the plain
//!   procedural background. Give held-out photos (`/usr/share/backgrounds/mate`).
//!
//! A detection counts when its centre is within 30 % of the part's short side of a true centre
//! and its angle within 15° (one detection per truth). `cargo bench --bench frames`;
//! `POSEMATCH_BENCH_FRAMES` sets frames per case (default 2), `POSEMATCH_BENCH_THREADS` the
//! thread counts (default `1,2`), `POSEMATCH_BENCH_GRID_SCALES` the objects' sizes on the
//! network grid to compare (default `1`; see `plan::scale_passes`), `POSEMATCH_BENCH_PRECISION`
//! the arithmetic of the network's products (default `auto`, as the CLI; `f32,bf16` compares
//! both where the CPU has bf16 instructions, AMX tiles or AVX-512 BF16; the table names the one
//! that ran);
//! `POSEMATCH_BENCH_CLASSICAL=0` skips the classical matcher (24 s, 14 GB);
//! `POSEMATCH_BENCH_WEIGHTS=FILE` adds a candidate weights file (`candidate` in the table), to
//! compare a training run with the default before it replaces it.

use std::path::PathBuf;
use std::time::Instant;

/// The same allocator as the `posematch` binary, so the figures match what users get.
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

use posematch::geometry::{Pose, angle_distance_deg};
use posematch::imaging::{GrayImage32, InputConvention, RgbImage32};
use posematch::imaging::{ImageLimits, decode_image_file, resize_rgb};
use posematch::matcher::{MatchOptions, Matcher, classical};
use posematch::model::{Precision, WeightsSource, load_weights, select_device};
use posematch::synth::{circuit_board, parts_frame, parts_frame_on, procedural_part};

struct Case {
    name: &'static str,
    part: RgbImage32,
    side: u32,
    grid: u32,
    max_instances: usize,
    /// What the parts are laid on.
    background: Background,
}

enum Background {
    /// The plain procedural background of `parts_frame`.
    Plain,
    /// A procedural circuit board, one per frame (`circuit_board`).
    Board,
    /// Photos, one per frame in turn, stretched to the frame.
    Photos(Vec<RgbImage32>),
}

impl Case {
    /// The frame of `seed` and its truth.
    fn scene(&self, seed: u64) -> (RgbImage32, Vec<Pose>) {
        match &self.background {
            Background::Plain => parts_frame(&self.part, self.side, self.grid, self.grid, seed),
            Background::Board => parts_frame_on(
                circuit_board(self.side, seed),
                &self.part,
                self.grid,
                self.grid,
                seed,
            ),
            Background::Photos(photos) => {
                let photo = &photos[seed as usize % photos.len()];
                let background = resize_rgb(photo, self.side, self.side);
                parts_frame_on(background, &self.part, self.grid, self.grid, seed)
            }
        }
    }
}

/// The photos of `POSEMATCH_BENCH_PHOTOS` (a folder and its subfolders; files in path order,
/// what does not decode skipped), for the `frame2048photo` case. Held-out photos only
/// (mate-backgrounds): never tune on them.
fn photo_backgrounds() -> Vec<RgbImage32> {
    let Ok(dir) = std::env::var("POSEMATCH_BENCH_PHOTOS") else {
        return Vec::new();
    };
    fn files_under(dir: &std::path::Path, out: &mut Vec<PathBuf>) {
        let Ok(entries) = std::fs::read_dir(dir) else {
            return;
        };
        for path in entries.filter_map(|e| e.ok().map(|e| e.path())) {
            if path.is_dir() {
                files_under(&path, out);
            } else {
                out.push(path);
            }
        }
    }
    let mut paths = Vec::new();
    files_under(std::path::Path::new(&dir), &mut paths);
    assert!(!paths.is_empty(), "POSEMATCH_BENCH_PHOTOS={dir}: no files");
    paths.sort();
    paths
        .iter()
        .filter_map(|p| decode_image_file(p, ImageLimits::default()).ok())
        .collect()
}

fn cases() -> Vec<Case> {
    let photos = photo_backgrounds();
    let mut cases = vec![
        Case {
            name: "frame2048",
            part: procedural_part(28, 52),
            side: 2048,
            grid: 12,
            max_instances: 200,
            background: Background::Plain,
        },
        Case {
            name: "pair224",
            part: procedural_part(36, 36),
            side: 224,
            grid: 1,
            max_instances: 1,
            background: Background::Plain,
        },
        Case {
            name: "tiny12",
            part: procedural_part(12, 12),
            side: 224,
            grid: 1,
            max_instances: 1,
            background: Background::Plain,
        },
    ];
    cases.push(Case {
        name: "frame2048board",
        part: procedural_part(28, 52),
        side: 2048,
        grid: 12,
        max_instances: 200,
        background: Background::Board,
    });
    if !photos.is_empty() {
        cases.push(Case {
            name: "frame2048photo",
            part: procedural_part(28, 52),
            side: 2048,
            grid: 12,
            max_instances: 200,
            background: Background::Photos(photos),
        });
    }
    cases
}

/// (true positives, detections, truths), one detection per truth, best score first.
fn count(poses: &[Pose], truth: &[Pose], part: &RgbImage32) -> (usize, usize, usize) {
    let radius = 0.3 * part.width.min(part.height) as f32;
    let mut taken = vec![false; truth.len()];
    let mut hits = 0;
    for pose in poses {
        let found = truth.iter().enumerate().position(|(i, t)| {
            !taken[i]
                && (pose.x - t.x).hypot(pose.y - t.y) <= radius
                && angle_distance_deg(pose.angle_deg, t.angle_deg) <= 15.0
        });
        if let Some(i) = found {
            taken[i] = true;
            hits += 1;
        }
    }
    (hits, poses.len(), truth.len())
}

fn peak_rss_mib() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1)?.parse::<f64>().ok())
        })
        .map_or(f64::NAN, |kib| kib / 1024.0)
}

/// Starts a new peak for [`peak_rss_mib`] from the memory in use now (Linux `clear_refs`).
fn reset_peak_rss() {
    let _ = std::fs::write("/proc/self/clear_refs", "5");
}

fn main() {
    // `cargo bench` passes `--bench`; a filter argument selects cases by name.
    let filter: Option<String> = std::env::args().skip(1).find(|a| !a.starts_with("--"));
    let frames: u64 = std::env::var("POSEMATCH_BENCH_FRAMES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(2);
    let list = |name: &str, default: &str| -> Vec<f64> {
        std::env::var(name)
            .unwrap_or_else(|_| default.into())
            .split(',')
            .filter_map(|v| v.trim().parse().ok())
            .collect()
    };
    let thread_counts: Vec<usize> = list("POSEMATCH_BENCH_THREADS", "1,2")
        .into_iter()
        .map(|t| t.max(1.0) as usize)
        .collect();
    let grid_scales = list("POSEMATCH_BENCH_GRID_SCALES", "1");
    let precisions: Vec<Precision> = std::env::var("POSEMATCH_BENCH_PRECISION")
        .unwrap_or_else(|_| "auto".into())
        .split(',')
        .map(|p| {
            p.parse()
                .expect("POSEMATCH_BENCH_PRECISION: f32 and/or bf16")
        })
        .collect();
    let device = select_device().expect("BURN_DEVICE names a compiled backend");
    // Each model with its training record, as the CLI and the service load it.
    let with_record = |source: WeightsSource| {
        let model = source
            .load(&device)
            .unwrap_or_else(|e| panic!("{source}: {e}"));
        (model, source.trained_on().unwrap_or_else(|e| panic!("{e}")))
    };
    let mut models = vec![("default", with_record(WeightsSource::Embedded))];
    let official =
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/reference/tdcm-official.pth");
    if let Ok(model) = load_weights(&official, &device) {
        models.push(("official", (model, None)));
    }
    if let Ok(candidate) = std::env::var("POSEMATCH_BENCH_WEIGHTS") {
        models.push((
            "candidate",
            with_record(WeightsSource::File(PathBuf::from(candidate))),
        ));
    }
    // `classical` alone runs only the classical matcher on the large frame.
    let classical_only = filter.as_deref() == Some("classical");
    if classical_only {
        models.clear();
    }
    let cases: Vec<Case> = cases()
        .into_iter()
        .filter(|c| classical_only || filter.as_ref().is_none_or(|f| c.name.contains(f.as_str())))
        .collect();
    println!(
        "| weights | arithmetic | case | grid scale | threads | ms/frame (median) | prepare / network / peaks / screen / refine ms | recall | precision |"
    );
    println!("| --- | --- | --- | --- | --- | --- | --- | --- | --- |");
    let mut memory = Vec::new();
    let runs = models
        .iter()
        .flat_map(|(name, model)| precisions.iter().map(move |p| (*name, model, *p)));
    for (name, (model, trained_on), precision) in runs {
        // Each model's peak on its own (the previous matcher and its buffers are gone).
        reset_peak_rss();
        let mut matcher = Matcher::new(model.clone(), device.clone(), InputConvention::ImagenetRgb)
            .with_trained_on(trained_on.clone())
            .with_precision(precision)
            .unwrap_or_else(|e| panic!("{e}"));
        let precision = matcher.network().precision().arithmetic();
        for (case, &grid_scale) in cases
            .iter()
            .flat_map(|c| grid_scales.iter().map(move |g| (c, g)))
        {
            matcher.set_grid_scale(grid_scale as f32);
            let template = matcher.encode_template(&case.part).unwrap();
            let options = MatchOptions {
                max_instances: case.max_instances,
                ..MatchOptions::default()
            }
            .validate()
            .unwrap();
            // Frames are made one at a time (untimed), as a camera delivers them: the memory
            // figure is then that of a service holding one frame.
            let scene = |seed: u64| case.scene(seed);
            // One untimed search first: allocations and caches warm, as in a running service.
            matcher.match_one(&template, &scene(0).0, &options).unwrap();
            for &threads in &thread_counts {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .unwrap();
                let (mut ms, mut totals) = (Vec::new(), (0, 0, 0));
                let mut stages = Vec::new();
                for seed in 0..frames {
                    let (frame, truth) = scene(seed);
                    let start = Instant::now();
                    let outcome = pool
                        .install(|| matcher.match_one(&template, &frame, &options))
                        .unwrap();
                    ms.push(start.elapsed().as_secs_f64() * 1e3);
                    let t = &outcome.timings;
                    stages.push((
                        t.prepare_ms,
                        t.network_ms,
                        t.peaks_ms,
                        t.screen_ms,
                        t.refine_ms,
                    ));
                    let (h, d, t) = count(&outcome.poses, &truth, &case.part);
                    totals = (totals.0 + h, totals.1 + d, totals.2 + t);
                }
                let mut order: Vec<usize> = (0..ms.len()).collect();
                order.sort_by(|a, b| ms[*a].total_cmp(&ms[*b]));
                let median = order[ms.len() / 2];
                let (prepare, network, peaks, screen, refine) = stages[median];
                println!(
                    "| {name} | {precision} | {} | {grid_scale} | {threads} | {:.1} | {prepare:.0} / {network:.0} / {peaks:.0} / {screen:.0} / {refine:.0} | {:.3} | {:.3} |",
                    case.name,
                    ms[median],
                    totals.0 as f64 / totals.2.max(1) as f64,
                    totals.0 as f64 / totals.1.max(1) as f64,
                );
            }
        }
        memory.push(format!(
            "peak memory while matching with the {name} weights ({precision}): {:.0} MiB",
            peak_rss_mib()
        ));
    }
    for line in memory {
        println!("{line}");
    }
    // Before the classical matcher (which needs far more): the most any network case needed
    // since the last model's start.
    println!(
        "peak memory of the network cases: {:.0} MiB",
        peak_rss_mib()
    );
    // The classical matcher on the first large frame, two threads (POSEMATCH_BENCH_CLASSICAL=0
    // skips it).
    let classical = std::env::var("POSEMATCH_BENCH_CLASSICAL").map_or(true, |v| v != "0");
    if let Some(case) = cases
        .iter()
        .find(|c| c.name == "frame2048")
        .filter(|_| classical)
    {
        let (frame, truth) = parts_frame(&case.part, case.side, case.grid, case.grid, 0);
        let options = MatchOptions {
            max_instances: case.max_instances,
            ..MatchOptions::default()
        };
        let (tw, th) = (case.part.width, case.part.height);
        // The service and the CLI refuse this much classical work (about 2 s is their limit);
        // the benchmark runs it anyway, to compare.
        if let Err(e) = classical::check_work(tw, th, frame.width, frame.height, &options) {
            println!("classical (ncc) on frame2048 would be refused by the service: {e}");
        }
        let start = Instant::now();
        let poses = classical::ncc_match(
            &GrayImage32::from_rgb(&case.part),
            &GrayImage32::from_rgb(&frame),
            &options,
        );
        let ms = start.elapsed().as_secs_f64() * 1e3;
        let (h, d, t) = count(&poses, &truth, &case.part);
        println!(
            "classical (ncc) on frame2048, 2 threads: {ms:.1} ms, recall {:.3}, precision {:.3}",
            h as f64 / t.max(1) as f64,
            h as f64 / d.max(1) as f64
        );
    }
    println!("peak memory of this process: {:.0} MiB", peak_rss_mib());
}
