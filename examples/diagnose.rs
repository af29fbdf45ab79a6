//! Why verified answers miss: for each generated pair (S1.5, 36x36) whose verified answer is
//! wrong, where the true object was lost — no candidate at all above the candidate threshold, no
//! candidate near it, screened below the survivors, confirmed lower than a decoy, or a decoy
//! that genuinely matches at least as well as the truth — with the rank and heatmap value of
//! the object's peak among all peaks; with `--readings`, what each reading made of the right
//! answers that scored under 0.9 and of the wrong ones that reached it. Mirrors `verify_candidates` (the second screen on the
//! light-evened level, and for a fine texture at full resolution as well, where no first
//! screen reaches 0.97, the best 20 screens ranked by their
//! score, `RANKED_BEYOND_SURVIVORS`, the best two confirmed).
//! Use it on tuning photos, never on evaluation photos:
//!
//! `cargo run --release --example diagnose -- --images DIR --count 500 [--condition C] [--weights W]`

use clap::Parser;
use posematch::cli::{ModelArgs, load_model};
use posematch::evaluation::pair_error;
use posematch::geometry::Pose;
use posematch::imaging::GrayImage32;
use posematch::matcher::verification::{RANKED_BEYOND_SURVIVORS, Verifier, wants_second_screen};
use posematch::matcher::{MatchJob, MatchOptions, ValidOptions};
use posematch::refine::Light;
use posematch::synth::conditions::{self, Condition};
use posematch::synth::{Level, PairSpec, PhotoSet, make_pair};

#[derive(Parser)]
struct Args {
    #[arg(long)]
    images: std::path::PathBuf,
    #[arg(long, default_value_t = 300)]
    count: u64,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Camera conditions applied to each pair, in order, as `posematch eval --condition`.
    #[arg(long, default_value = "clean", value_delimiter = ',', value_parser = str::parse::<Condition>)]
    condition: Vec<Condition>,
    /// Print every reading of the answers that are right but score under 0.9, and of the wrong
    /// ones that reach it (in scenes without the part, `--condition absent`: false answers).
    #[arg(long)]
    readings: bool,
    #[command(flatten)]
    model: ModelArgs,
}

/// One line per reading of an answer: `what` it was (right under the default `min_score`, or
/// wrong above it).
fn print_readings(
    index: u64,
    what: &str,
    verifier: &Verifier,
    pose: &Pose,
    template: &GrayImage32,
) {
    let chance = posematch::matcher::verification::chance_similarity(template);
    let length = posematch::matcher::verification::correlation_length(template).unwrap_or(0.0);
    println!(
        "#{index:4} {what}, score {:.3}, template chance {chance:.3} correlation length {length:.2}, angle {:.0} s {:.2}/{:.2}",
        verifier.score_at(pose),
        pose.angle_deg,
        pose.scale_x,
        pose.scale_y,
    );
    for reading in verifier.readings_at(pose) {
        println!(
            "        {:50} similarity {:.3} chance {:.3} share {:.2} -> {:.3}",
            format!("{:?}", reading.kind),
            reading.similarity,
            reading.chance,
            reading.share,
            reading.score()
        );
    }
}

fn main() {
    let args = Args::parse();
    let matcher = load_model(&args.model).unwrap();
    let photos = PhotoSet::load(&args.images, 224).unwrap();
    let spec = PairSpec {
        level: "S1.5".parse::<Level>().unwrap(),
        template_width: 36,
        template_height: 36,
        search_side: 224,
        min_structure: posematch::synth::DEFAULT_MIN_STRUCTURE,
    };
    let options: ValidOptions = MatchOptions {
        max_instances: 1,
        ..MatchOptions::default()
    }
    .validate()
    .unwrap();
    let mut tally = std::collections::BTreeMap::<&str, usize>::new();
    for index in 0..args.count {
        let pair = make_pair(&photos, &spec, args.seed, index).unwrap();
        let (pair, _) = conditions::apply_all(pair, &args.condition, args.seed, index);
        let truth = pair.truth[0];
        let encoded = matcher.encode_template(&pair.template).unwrap();
        let wide_options: ValidOptions = MatchOptions {
            max_instances: 1,
            candidate_threshold: 1e-6,
            max_candidates: 2000,
            ..MatchOptions::default()
        }
        .validate()
        .unwrap();
        let job = MatchJob {
            template: &encoded,
            image: &pair.search,
            options: &wide_options,
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
            .filter(|p| p.network_score >= options.candidate_threshold)
            .take(options.candidate_budget())
            .copied()
            .collect();
        let image = GrayImage32::from_rgb(&pair.search);
        let template = &encoded.gray;
        let verifier = Verifier::new(template, &image, None, |_| true);
        let ok = |p: &Pose| pair_error(p, &truth, 36.0, 36.0).iou >= 0.5;
        // Screen every candidate, rank.
        let mut screened: Vec<(usize, Pose, posematch::matcher::verification::Screened)> =
            candidates
                .iter()
                .enumerate()
                .map(|(i, c)| (i, *c, verifier.screen(c)))
                .collect();
        // One instance wanted, as in `posematch eval`'s pairs.
        let light = if wants_second_screen(screened.iter().map(|s| &s.2), 1) {
            let twin = verifier.full_resolution_twin();
            for (_, candidate, screen) in &mut screened {
                *screen = verifier.screen_evened_also_at(twin.as_ref(), candidate, *screen);
            }
            Light::Planes
        } else {
            Light::Even
        };
        screened.sort_by(|a, b| b.2.score.total_cmp(&a.2.score));
        // The best screens by their score, as `verify_candidates` ranks them (two survivors).
        let ranked = screened.len().min(2 + RANKED_BEYOND_SURVIVORS);
        let mut head: Vec<(f32, _)> = screened
            .drain(..ranked)
            .map(|s| (verifier.score_at(&s.2.pose), s))
            .collect();
        head.sort_by(|a, b| b.0.total_cmp(&a.0));
        screened.splice(0..0, head.into_iter().map(|(_, s)| s));
        if screened.is_empty() {
            *tally.entry("no candidates at all").or_default() += 1;
            let near = proposal
                .candidates
                .iter()
                .enumerate()
                .find(|(_, c)| (c.x - truth.x).hypot(c.y - truth.y) < 8.0)
                .map(|(i, c)| (i, c.network_score));
            println!(
                "#{index:4} no candidates: {} wide peaks, top {:?}, near truth {:?}",
                proposal.candidates.len(),
                proposal.candidates.first().map(|c| c.network_score),
                near
            );
            continue;
        }
        let best = &screened[0];
        let winner = verifier.confirm(&best.2, &best.1, light);
        let second = screened.get(1).map(|s| verifier.confirm(&s.2, &s.1, light));
        let picked = match second {
            Some(s) if s.score > winner.score => s,
            _ => winner,
        };
        if ok(&picked.pose) && picked.score >= 0.9 {
            *tally.entry("right").or_default() += 1;
            continue;
        }
        if ok(&picked.pose) {
            *tally.entry("right pose, score < 0.9").or_default() += 1;
            if args.readings {
                print_readings(index, "right", &verifier, &picked.pose, template);
            }
            continue;
        }
        // Oracle: screen and confirm at the truth.
        let oracle_screen = verifier.screen(&truth);
        let oracle = verifier.confirm(&oracle_screen, &truth, light);
        let near: Vec<usize> = candidates
            .iter()
            .enumerate()
            .filter(|(_, c)| (c.x - truth.x).hypot(c.y - truth.y) < 8.0)
            .map(|(i, _)| i)
            .collect();
        let rank_of_true_screen = screened.iter().position(|s| ok(&s.2.pose));
        let wide_near = proposal
            .candidates
            .iter()
            .enumerate()
            .filter(|(_, c)| (c.x - truth.x).hypot(c.y - truth.y) < 8.0)
            .map(|(i, c)| (i, c.network_score))
            .next();
        let top_net = proposal.candidates.first().map(|c| c.network_score);
        let kind = match rank_of_true_screen {
            _ if oracle.score <= picked.score + 1e-3 => "decoy matches at least as well as truth",
            None if near.is_empty() => "no candidate near truth",
            None => "candidate near, screen did not reach truth",
            Some(rank) if rank >= 2 => "screen ranked truth below survivors",
            Some(_) => "confirm lost truth",
        };
        *tally.entry(kind).or_default() += 1;
        if args.readings && picked.score >= 0.9 {
            *tally.entry("wrong, score >= 0.9").or_default() += 1;
            print_readings(index, "wrong", &verifier, &picked.pose, template);
        }
        println!(
            "#{index:4} {kind:45} picked score {:.3} oracle {:.3} (screen {:.3}) net-rank {:?} of {} near, true screen rank {:?} best screen {:.3}, wide near {:?} top {:?}, truth angle {:.0} s {:.2}/{:.2}",
            picked.score,
            oracle.score,
            oracle_screen.score,
            near.first(),
            candidates.len(),
            rank_of_true_screen,
            best.2.score,
            wide_near,
            top_net,
            truth.angle_deg,
            truth.scale_x,
            truth.scale_y,
        );
        if let Some(rank) = rank_of_true_screen {
            let (i, candidate, screen) = &screened[rank];
            println!(
                "      its screen:  candidate {i} at angle {:.0} s {:.2}/{:.2} -> screened angle {:.0} s {:.2}/{:.2} score {:.3} (truth angle {:.0})",
                candidate.angle_deg,
                candidate.scale_x,
                candidate.scale_y,
                screen.pose.angle_deg,
                screen.pose.scale_x,
                screen.pose.scale_y,
                screen.score,
                truth.angle_deg
            );
        }
    }
    println!("{tally:#?}");
}
