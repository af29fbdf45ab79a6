//! Where parts with a quarter covered are lost at a lowered `min_score` (default 0.7): for each
//! generated pair (S1.5, 36x36, `--condition`, default `occluded-quarter`) whether the part was
//! found, found under `min_score`, lost to a look-alike that scores at least as high as the
//! part's own pose (screened and confirmed from the truth, with the whole template and with
//! the covered quarter left out; scored with the whole template), lost to one that scores
//! lower (the search never reached the part), or whether the part's own pose scores under
//! `min_score`; with the visible-share reading at the part's pose and at the exact truth.
//! Use it on tuning photos,
//! never on evaluation photos:
//!
//! `cargo run --release --example covered_probe -- --images DIR [--count 200] [--min-score 0.7]`
use clap::Parser;
use posematch::cli::{ModelArgs, load_model};
use posematch::evaluation::pair_error;
use posematch::geometry::Pose;
use posematch::imaging::GrayImage32;
use posematch::matcher::verification::{Reading, ReadingKind, Verifier};
use posematch::matcher::{MatchOptions, ValidOptions};
use posematch::refine::Light;
use posematch::synth::conditions::{self, Condition};
use posematch::synth::{Level, PairSpec, PhotoSet, make_pair};

#[derive(Parser)]
struct Args {
    #[arg(long)]
    images: std::path::PathBuf,
    #[arg(long, default_value_t = 200)]
    count: u64,
    #[arg(long, default_value_t = 0.7)]
    min_score: f32,
    #[arg(long, default_value = "occluded-quarter", value_delimiter = ',', value_parser = str::parse::<Condition>)]
    condition: Vec<Condition>,
    #[command(flatten)]
    model: ModelArgs,
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
        min_score: Some(args.min_score),
        ..MatchOptions::default()
    }
    .validate()
    .unwrap();
    let mut tally = std::collections::BTreeMap::<String, usize>::new();
    for index in 0..args.count {
        let pair = make_pair(&photos, &spec, 0, index).unwrap();
        let (pair, quadrant) = conditions::apply_all(pair, &args.condition, 0, index);
        let truth = pair.truth[0];
        let encoded = matcher.encode_template(&pair.template).unwrap();
        let out = matcher.match_one(&encoded, &pair.search, &options).unwrap();
        let image = GrayImage32::from_rgb(&pair.search);
        let whole = Verifier::for_options(&encoded.gray, &image, &options);
        let oracle_whole = whole.confirm(&whole.screen(&truth), &truth, Light::Even);
        let mut oracle = whole.score_at(&oracle_whole.pose);
        let mut oracle_pose = oracle_whole.pose;
        if let Some(q) = quadrant {
            let mut partial = encoded.gray.as_ref().clone();
            let mask = q.mask_out(36, 36);
            for (v, keep) in partial.values.iter_mut().zip(mask) {
                if !keep {
                    *v = f32::NAN;
                }
            }
            let pv = Verifier::for_options(&partial, &image, &options);
            let c = pv.confirm(&pv.screen(&truth), &truth, Light::Even);
            let s = whole.score_at(&c.pose);
            if s > oracle {
                oracle = s;
                oracle_pose = c.pose;
            }
        }
        let oracle_ok = pair_error(&oracle_pose, &truth, 36.0, 36.0).iou >= 0.5;
        let best = out.poses.first();
        let ok = best.is_some_and(|p| pair_error(p, &truth, 36.0, 36.0).iou >= 0.5);
        let score = best.map_or(0.0, |p| p.score);
        let kind = if ok && score >= args.min_score {
            "found"
        } else if ok {
            "right, under min_score"
        } else if !oracle_ok || oracle < args.min_score {
            "truth itself scores under min_score"
        } else if best.is_some() && score >= oracle - 1e-3 {
            "decoy as good as truth"
        } else if best.is_some() {
            "decoy below truth: search lost truth"
        } else {
            "nothing answered; truth reaches min_score"
        };
        *tally.entry(kind.to_string()).or_default() += 1;
        let vis = visible_reading(&whole, &oracle_pose);
        let at_truth = whole.score_at(&truth);
        let vis_truth = visible_reading(&whole, &truth);
        if let (Some(r), Some(t)) = (vis, vis_truth) {
            println!(
                "      visible: share {:.3} sim {:.3} chance {:.3} -> {:.3}  at truth: share {:.3} sim {:.3} -> {:.3} (score {at_truth:.3}) [{kind}]",
                r.share,
                r.similarity,
                r.chance,
                r.score(),
                t.share,
                t.similarity,
                t.score()
            );
        }
        if kind != "found" {
            println!(
                "#{index:4} {kind:42} best {score:.3} oracle {oracle:.3} (ok {oracle_ok}) truth ({:.1},{:.1}) angle {:.0} s {:.2}/{:.2} q {:?} best {:?}",
                truth.x,
                truth.y,
                truth.angle_deg,
                truth.scale_x,
                truth.scale_y,
                quadrant.map(|q| (q.right, q.bottom)),
                best.map(|p| (p.x, p.y, p.angle_deg, p.scale_x, p.scale_y))
            );
        }
    }
    println!("{tally:#?}");
}

/// The visible-share reading of `verifier`'s template at `pose`.
fn visible_reading(verifier: &Verifier, pose: &Pose) -> Option<Reading> {
    verifier
        .readings_at(pose)
        .into_iter()
        .find(|r| matches!(r.kind, ReadingKind::Visible))
}
