//! Where the 2048 frame of `cargo bench --bench frames` loses its parts: for each of the 144
//! 28x52 parts of a generated frame, whether the network put a candidate near it (within 30 %
//! of the short side, as the bench counts), what angle and scales that candidate carried,
//! whether the screen kept it, and whether the verified answer found it. Procedural frames
//! only (no photos).
//!
//! `cargo run --release --example frame_diagnose -- [--seeds 0,1] [--photos DIR | --board]
//! [--max-candidates N] [--verbose] [--save FRAME.png] [--weights W]`

use clap::Parser;
use posematch::cli::{ModelArgs, load_model};
use posematch::geometry::{Pose, angle_distance_deg};
use posematch::imaging::GrayImage32;
use posematch::imaging::{ImageLimits, decode_image_file, resize_rgb};
use posematch::matcher::verification::{SCREEN_MIN, Verifier};
use posematch::matcher::{MatchJob, MatchOptions, ValidOptions};
use posematch::synth::{circuit_board, parts_frame, parts_frame_on, procedural_part};

#[derive(Parser)]
struct Args {
    #[arg(long, value_delimiter = ',', default_value = "0,1")]
    seeds: Vec<u64>,
    /// Lay the parts on these photos (files in name order, one per seed in turn; held-out
    /// photos only) instead of the procedural background.
    #[arg(long)]
    photos: Option<std::path::PathBuf>,
    /// Lay the parts on a procedural circuit board (`synth::circuit_board`), one per seed.
    #[arg(long, conflicts_with = "photos")]
    board: bool,
    /// Write the first seed's frame here (PNG), to look at.
    #[arg(long)]
    save: Option<std::path::PathBuf>,
    /// Candidates verified per frame (0: the matcher's automatic budget).
    #[arg(long, default_value_t = 0)]
    max_candidates: usize,
    /// Print every lost part that had a candidate near it: where the screen took it.
    #[arg(long)]
    verbose: bool,
    #[command(flatten)]
    model: ModelArgs,
}

fn main() {
    let args = Args::parse();
    let matcher = load_model(&args.model).unwrap();
    let photos: Option<Vec<posematch::imaging::RgbImage32>> = args.photos.as_ref().map(|dir| {
        let mut paths: Vec<_> = std::fs::read_dir(dir)
            .unwrap()
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.is_file())
            .collect();
        paths.sort();
        paths
            .iter()
            .filter_map(|p| decode_image_file(p, ImageLimits::default()).ok())
            .collect()
    });
    let part = procedural_part(28, 52);
    let options: ValidOptions = MatchOptions {
        max_instances: 200,
        max_candidates: args.max_candidates,
        ..MatchOptions::default()
    }
    .validate()
    .unwrap();
    let encoded = matcher.encode_template(&part).unwrap();
    let radius = 0.3 * 28.0;
    let mut tally = std::collections::BTreeMap::<String, usize>::new();
    let mut near_errors: Vec<(f32, f32, f32)> = Vec::new();
    for &seed in &args.seeds {
        let (frame, truth) = match &photos {
            Some(photos) => {
                let photo = &photos[seed as usize % photos.len()];
                parts_frame_on(resize_rgb(photo, 2048, 2048), &part, 12, 12, seed)
            }
            None if args.board => parts_frame_on(circuit_board(2048, seed), &part, 12, 12, seed),
            None => parts_frame(&part, 2048, 12, 12, seed),
        };
        if let Some(path) = args.save.as_ref().filter(|_| seed == args.seeds[0]) {
            let bytes: Vec<u8> = frame
                .pixels
                .iter()
                .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
                .collect();
            image::RgbImage::from_raw(frame.width, frame.height, bytes)
                .unwrap()
                .save(path)
                .unwrap();
        }
        let job = MatchJob {
            template: &encoded,
            image: &frame,
            options: &options,
            answer_by: None,
        };
        let proposal = matcher
            .propose(std::slice::from_ref(&job))
            .pop()
            .unwrap()
            .unwrap();
        let candidates: Vec<Pose> = proposal
            .candidates
            .iter()
            .take(options.candidate_budget_for(matcher.heads_for(&job)))
            .copied()
            .collect();
        let answer = matcher.match_one(&encoded, &frame, &options).unwrap();
        let image = GrayImage32::from_rgb(&frame);
        let verifier = Verifier::for_options(&encoded.gray, &image, &options);
        let hit = |p: &Pose, t: &Pose| {
            (p.x - t.x).hypot(p.y - t.y) <= radius
                && angle_distance_deg(p.angle_deg, t.angle_deg) <= 15.0
        };
        for t in &truth {
            let found = answer.poses.iter().any(|p| hit(p, t));
            let near = candidates
                .iter()
                .filter(|c| (c.x - t.x).hypot(c.y - t.y) <= radius)
                .max_by(|a, b| a.network_score.total_cmp(&b.network_score));
            let kind = match near {
                None => {
                    let nearest = candidates
                        .iter()
                        .map(|c| (c.x - t.x).hypot(c.y - t.y))
                        .fold(f32::INFINITY, f32::min);
                    format!(
                        "no candidate near (nearest {} px) ",
                        if nearest < 12.0 {
                            "8-12"
                        } else if nearest < 16.0 {
                            "12-16"
                        } else if nearest < 24.0 {
                            "16-24"
                        } else {
                            ">= 24"
                        }
                    )
                }
                Some(c) => {
                    let angle_error = angle_distance_deg(c.angle_deg, t.angle_deg);
                    near_errors.push((angle_error, c.scale_x, c.scale_y));
                    let screened = verifier.screen(c);
                    let screen_right = hit(&screened.pose, t);
                    if !found && args.verbose {
                        let oracle = verifier.screen(t);
                        println!(
                            "lost: candidate {:.1} px off, angle error {:.0}°, scales {:.2}/{:.2}; screened {:.1} px off, angle error {:.0}°, scales {:.2}/{:.2}, score {:.2}; at the truth the screen scores {:.2}",
                            (c.x - t.x).hypot(c.y - t.y),
                            angle_error,
                            c.scale_x,
                            c.scale_y,
                            (screened.pose.x - t.x).hypot(screened.pose.y - t.y),
                            angle_distance_deg(screened.pose.angle_deg, t.angle_deg),
                            screened.pose.scale_x,
                            screened.pose.scale_y,
                            screened.score,
                            oracle.score
                        );
                    }
                    format!(
                        "candidate near (angle {}), screen {} {}",
                        if angle_error <= 15.0 {
                            "right"
                        } else {
                            "wrong"
                        },
                        if screen_right { "right" } else { "wrong" },
                        if screened.score >= SCREEN_MIN {
                            ">= min"
                        } else {
                            "< min"
                        },
                    )
                }
            };
            *tally
                .entry(format!(
                    "{kind} -> {}",
                    if found { "found" } else { "lost" }
                ))
                .or_default() += 1;
        }
        println!(
            "seed {seed}: {} candidates, {} answers, screen {:.0} ms, confirm {:.0} ms, network {:.0} ms",
            candidates.len(),
            answer.poses.len(),
            answer.timings.screen_ms,
            answer.timings.refine_ms,
            answer.timings.network_ms,
        );
    }
    for (kind, n) in &tally {
        println!("{n:5}  {kind}");
    }
    let n = near_errors.len().max(1) as f32;
    let mean = |f: &dyn Fn(&(f32, f32, f32)) -> f32| near_errors.iter().map(f).sum::<f32>() / n;
    println!(
        "near candidates: mean angle error {:.1}°, mean scales {:.2} / {:.2}, share with scale_x > scale_y {:.2}",
        mean(&|e| e.0),
        mean(&|e| e.1),
        mean(&|e| e.2),
        mean(&|e| f32::from(e.1 > e.2)),
    );
}
