//! `posematch eval`: generate pairs with exact truth from a folder of photos, match them, and
//! print the paper's metrics (coarse network pose and refined pose side by side).

use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

use clap::Args;
use serde_json::json;

use super::{CliError, ModelArgs, load_model};
use crate::evaluation::{
    DetectionCounts, PairError, Summary, match_detections, match_pair, pair_error, summarise,
};
use crate::geometry::Pose;
use crate::matcher::MatchOptions;
use crate::refine::GrayImage32;
use crate::synth::{Level, PairSpec, PhotoSet, SyntheticPair, make_multi_instance, make_pair};

#[derive(Args, Debug)]
pub struct EvalArgs {
    /// Folder of ordinary photos (searched recursively) to cut pairs from.
    #[arg(long)]
    pub images: PathBuf,
    /// Transformation level: S1, S1.5, S2 or S2.5.
    #[arg(long, default_value = "S1.5", value_parser = |s: &str| s.parse::<Level>())]
    pub level: Level,
    /// Number of pairs (or multi-instance images).
    #[arg(long, default_value_t = 100)]
    pub count: u64,
    /// Registered template size WxH (the paper: 12x12, 28x52, 36x36, 124x124).
    #[arg(long, default_value = "36x36", value_parser = parse_size)]
    pub template_size: (u32, u32),
    /// Least structure of a template (mean grey-level gradient per pixel, 0–255): flatter
    /// boxes, such as sky, are drawn again, as the paper's object boxes never are flat.
    /// 0 accepts any box.
    #[arg(long, default_value_t = crate::synth::DEFAULT_MIN_STRUCTURE)]
    pub min_structure: f32,
    /// Seed of the pair generator; the same seed gives the same pairs.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Only the coarse network pose (no refinement row).
    #[arg(long)]
    pub no_refine: bool,
    /// Multi-instance images (320x320, 2–8 instances) with precision/recall instead of pairs.
    #[arg(long)]
    pub multi_instance: bool,
    /// Matcher: `tdcm` (the network; rows without and with refinement) or `ncc` (the classical
    /// baseline, always refined; needs no weights).
    #[arg(long, value_enum, default_value = "tdcm")]
    pub method: super::Method,
    /// Print JSON instead of the table.
    #[arg(long)]
    pub json: bool,
    /// Also write the generated pairs here as PNG files plus `pairs.jsonl` (with the truth),
    /// which `posematch match --pairs` reads.
    #[arg(long)]
    pub save: Option<PathBuf>,
    #[command(flatten)]
    pub model: ModelArgs,
}

fn parse_size(s: &str) -> Result<(u32, u32), String> {
    let (w, h) = s
        .split_once(['x', 'X'])
        .ok_or_else(|| format!("size `{s}`: expected WxH, e.g. 36x36"))?;
    let parse = |v: &str| {
        v.trim()
            .parse::<u32>()
            .map_err(|_| format!("size `{s}`: expected WxH"))
    };
    let (w, h) = (parse(w)?, parse(h)?);
    if !(8..=512).contains(&w) || !(8..=512).contains(&h) {
        return Err(format!("size `{s}`: each side must be 8..=512"));
    }
    Ok((w, h))
}

pub fn run(args: EvalArgs) -> Result<(), CliError> {
    if !(0.0..=255.0).contains(&args.min_structure) {
        return Err(CliError::Usage(format!(
            "--min-structure {} is out of range: give grey levels per pixel in 0..=255 (default {})",
            args.min_structure,
            crate::synth::DEFAULT_MIN_STRUCTURE
        )));
    }
    let search_side = if args.multi_instance { 320 } else { 224 };
    let photos =
        PhotoSet::load(&args.images, search_side).map_err(|e| CliError::Usage(e.to_string()))?;
    let matcher = match args.method {
        super::Method::Tdcm => Some(load_model(&args.model)?),
        super::Method::Ncc => None,
    };
    let (tw, th) = args.template_size;
    let spec = PairSpec {
        level: args.level,
        template_width: tw,
        template_height: th,
        search_side,
        min_structure: args.min_structure,
    };
    // No scale range: the network sees objects at the template's size, as it was trained.
    // Single-instance pairs always hold the object, so the best peak is the answer whatever its
    // score (as in the paper and the official decode); multi-instance keeps the default 0.5.
    let options = MatchOptions {
        max_instances: if args.multi_instance { 16 } else { 1 },
        min_score: if args.multi_instance { 0.5 } else { 0.01 },
        refine: false,
        ..MatchOptions::default()
    };
    let mut saver = args.save.as_deref().map(PairSaver::new).transpose()?;
    let mut coarse: Vec<(Option<PairError>, f64)> = Vec::new();
    let mut refined: Vec<(Option<PairError>, f64)> = Vec::new();
    let (mut coarse_counts, mut refined_counts) =
        (DetectionCounts::default(), DetectionCounts::default());
    for index in 0..args.count {
        let pair = if args.multi_instance {
            make_multi_instance(
                &photos,
                args.level,
                tw,
                args.min_structure,
                args.seed,
                index,
            )
        } else {
            make_pair(&photos, &spec, args.seed, index)
        }
        .map_err(|e| CliError::Usage(e.to_string()))?;
        if let Some(saver) = saver.as_mut() {
            saver.save(index, &pair)?;
        }
        let (coarse_poses, coarse_ms, refined_poses, refine_ms) = match &matcher {
            Some(matcher) => {
                let run = match_pair(matcher, &pair, &options, !args.no_refine)?;
                (run.coarse, run.coarse_ms, run.refined, run.refine_ms)
            }
            None => run_ncc(
                &pair,
                &options,
                args.level,
                !args.no_refine,
                args.multi_instance,
            ),
        };
        let (ptw, pth) = (pair.template.width as f32, pair.template.height as f32);
        if args.multi_instance {
            coarse_counts.add(match_detections(&coarse_poses, &pair.truth, ptw, pth));
            refined_counts.add(match_detections(&refined_poses, &pair.truth, ptw, pth));
        } else {
            let truth = &pair.truth[0];
            coarse.push((
                coarse_poses.first().map(|p| pair_error(p, truth, ptw, pth)),
                coarse_ms,
            ));
            refined.push((
                refined_poses
                    .first()
                    .map(|p| pair_error(p, truth, ptw, pth)),
                coarse_ms + refine_ms,
            ));
        }
    }
    let label = format!(
        "{} {}x{} n={} seed={} min-structure={}",
        args.level.name(),
        tw,
        th,
        args.count,
        args.seed,
        args.min_structure
    );
    if args.multi_instance {
        print_detection(
            &label,
            &coarse_counts,
            (!args.no_refine).then_some(&refined_counts),
            args.json,
        );
    } else {
        let rows = if matcher.is_some() {
            [("tdcm (network only)", summarise(&coarse))]
                .into_iter()
                .chain((!args.no_refine).then(|| ("tdcm + refinement", summarise(&refined))))
                .collect::<Vec<_>>()
        } else {
            let name = if args.no_refine {
                "ncc"
            } else {
                "ncc + refinement"
            };
            vec![(name, summarise(&coarse))]
        };
        let changes =
            (matcher.is_some() && !args.no_refine).then(|| refinement_changes(&coarse, &refined));
        print_table(&label, &rows, changes, args.json);
    }
    Ok(())
}

/// The classical baseline on one pair (refined inside); same return shape as [`run_pair`].
fn run_ncc(
    pair: &SyntheticPair,
    options: &MatchOptions,
    level: Level,
    refine: bool,
    multi_instance: bool,
) -> (Vec<Pose>, f64, Vec<Pose>, f64) {
    let start = Instant::now();
    let (lo, hi) = level.scale_range();
    let ncc_options = MatchOptions {
        refine,
        // Single pairs always hold the object: take the best candidate whatever its score.
        min_score: if multi_instance { 0.5 } else { -1.0 },
        scale_range: (hi > lo).then_some(crate::matcher::ScaleRange { min: lo, max: hi }),
        ..options.clone()
    };
    let poses = crate::matcher::ncc::ncc_match(
        &GrayImage32::from_rgb(&pair.template),
        &GrayImage32::from_rgb(&pair.search),
        &ncc_options,
    );
    (
        poses.clone(),
        start.elapsed().as_secs_f64() * 1e3,
        poses,
        0.0,
    )
}

/// How many of the network's successes refinement lost, and how many failures it turned into
/// successes (IoU >= 0.5), pair by pair.
fn refinement_changes(
    coarse: &[(Option<PairError>, f64)],
    refined: &[(Option<PairError>, f64)],
) -> (usize, usize) {
    let success = |e: &Option<PairError>| e.as_ref().is_some_and(|e| e.iou >= 0.5);
    coarse
        .iter()
        .zip(refined)
        .fold((0, 0), |(lost, gained), ((c, _), (r, _))| {
            (
                lost + usize::from(success(c) && !success(r)),
                gained + usize::from(!success(c) && success(r)),
            )
        })
}

/// The paper's table (header and one row per method), shared with `posematch train`.
pub(super) fn summary_table(rows: &[(&str, Summary)]) -> String {
    let mut lines = vec![
        format!(
            "| {:<22} | {:>11} | {:>8} | {:>11} | {:>6} | {:>6} | {:>8} |",
            "method", "Loc.Err(px)", "ScaleErr", "Rot.Err(°)", "mIoU", "Succ", "ms/pair"
        ),
        format!(
            "|{:-<24}|{:->13}|{:->10}|{:->13}|{:->8}|{:->8}|{:->10}|",
            "", "", "", "", "", "", ""
        ),
    ];
    for (name, s) in rows {
        lines.push(format!(
            "| {:<22} | {:>11.3} | {:>8.4} | {:>11.3} | {:>6.3} | {:>5.1}% | {:>8.1} |",
            name,
            s.loc_err_px,
            s.scale_err,
            s.rot_err_deg,
            s.miou,
            100.0 * s.success,
            s.ms_per_pair
        ));
    }
    lines.join("\n")
}

fn print_table(
    label: &str,
    rows: &[(&str, Summary)],
    refinement_changes: Option<(usize, usize)>,
    as_json: bool,
) {
    if as_json {
        let rows: Vec<_> = rows
            .iter()
            .map(|(name, s)| json!({"method": name, "summary": s}))
            .collect();
        let changes =
            refinement_changes.map(|(lost, gained)| json!({"lost": lost, "gained": gained}));
        println!(
            "{}",
            json!({"set": label, "rows": rows, "refinement": changes})
        );
        return;
    }
    println!("pairs: {label}");
    println!("{}", summary_table(rows));
    println!("(errors over successful pairs, IoU >= 0.5; mIoU and Succ over all pairs)");
    if let Some((lost, gained)) = refinement_changes {
        println!(
            "refinement lost {lost} of the network's successes and turned {gained} failures into successes"
        );
    }
}

fn print_detection(
    label: &str,
    coarse: &DetectionCounts,
    refined: Option<&DetectionCounts>,
    as_json: bool,
) {
    if as_json {
        println!(
            "{}",
            json!({"set": label, "coarse": coarse, "refined": refined})
        );
        return;
    }
    println!("multi-instance: {label}");
    println!(
        "| {:<22} | {:>9} | {:>7} | {:>7} | {:>6} |",
        "method", "precision", "recall", "objects", "found"
    );
    for (name, c) in [
        ("tdcm (network only)", Some(coarse)),
        ("tdcm + refinement", refined),
    ] {
        if let Some(c) = c {
            println!(
                "| {:<22} | {:>9.3} | {:>7.3} | {:>7} | {:>6} |",
                name,
                c.precision(),
                c.recall(),
                c.objects,
                c.true_positives
            );
        }
    }
}

/// Writes pairs as PNG files and a `pairs.jsonl` that `posematch match --pairs` reads.
struct PairSaver {
    dir: PathBuf,
    index: std::fs::File,
}

impl PairSaver {
    fn new(dir: &Path) -> Result<Self, CliError> {
        std::fs::create_dir_all(dir).map_err(|e| CliError::io(dir, e))?;
        let path = dir.join("pairs.jsonl");
        let index = std::fs::File::create(&path).map_err(|e| CliError::io(&path, e))?;
        Ok(Self {
            dir: dir.to_owned(),
            index,
        })
    }

    fn save(&mut self, id: u64, pair: &SyntheticPair) -> Result<(), CliError> {
        let template = format!("pair_{id:05}_template.png");
        let search = format!("pair_{id:05}_search.png");
        for (name, image) in [(&template, &pair.template), (&search, &pair.search)] {
            let path = self.dir.join(name);
            to_rgb8(image)
                .save(&path)
                .map_err(|e| CliError::io(&path, std::io::Error::other(e)))?;
        }
        let line = json!({"id": id, "template": template, "image": search, "truth": pair.truth});
        writeln!(self.index, "{line}").map_err(|e| CliError::io(&self.dir, e))
    }
}

fn to_rgb8(image: &crate::imaging::RgbImage32) -> image::RgbImage {
    let bytes = image
        .pixels
        .iter()
        .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
        .collect();
    image::RgbImage::from_raw(image.width, image.height, bytes).expect("size matches")
}
