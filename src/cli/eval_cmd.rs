//! `posematch eval`: generate pairs with exact truth from a folder of photos, match them, and
//! print the paper's metrics for three paths side by side: the network's best peak, that peak
//! refined (the path before verification), and verified candidates (the default); for
//! multi-instance scenes precision and recall; and how the verified score relates to being
//! right (the calibration table).

use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

use clap::Args;
use serde_json::json;

use super::{CliError, ModelArgs, load_model};
use crate::evaluation::{
    ANY_PEAK, Calibration, DetectionCounts, PairError, Paths, SUCCESS_IOU, Summary,
    match_detections, match_pair, matched_predictions, pair_error, path_changes, summarise,
};
use crate::geometry::Pose;
use crate::imaging::GrayImage32;
use crate::matcher::{MatchOptions, Method, TemplateMask};
use crate::synth::conditions::{self, Condition};
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
    /// Only the network's poses (no refined and verified rows).
    #[arg(long)]
    pub no_refine: bool,
    /// The verified path's options, as `posematch match`'s.
    #[command(flatten)]
    pub verification: super::VerificationArgs,
    /// What the line and the camera do to the part: `clean`, `reversed` (search image 255 −
    /// pixel), `occluded-quarter` (a quadrant of every instance covered by a plain patch),
    /// `cluttered-quarter` (covered by texture from elsewhere), `jpeg-30`, `defocus-2`
    /// (Gaussian, sigma 2 px), `noise-15` (Gaussian, sigma 15 grey levels), `dark-gamma`
    /// (gamma 2.2, gain 0.6, offset 10) or `uneven-light` (gain 1.3 → 0.4 across the frame).
    /// Several, comma-separated, apply in order: `absent,defocus-2` is a defocused scene
    /// without the part.
    #[arg(long, default_value = "clean", value_delimiter = ',', value_parser = str::parse::<Condition>)]
    pub condition: Vec<Condition>,
    /// With `--condition occluded-quarter`: register each template with the covered quadrant
    /// masked out (what `--template-mask` does), as an engineer who knows where a clamp sits.
    #[arg(long)]
    pub mask_covered: bool,
    /// Multi-instance images (320x320, 2–8 instances) with precision/recall instead of pairs.
    #[arg(long)]
    pub multi_instance: bool,
    /// Matcher: `tdcm` (the network; rows without and with refinement) or `ncc` (the classical
    /// baseline, always refined; needs no weights).
    #[arg(long, default_value = "tdcm", value_parser = str::parse::<Method>)]
    pub method: Method,
    /// Also print each path's Succ per source photo (single-instance pairs): which photos the
    /// misses come from.
    #[arg(long)]
    pub by_photo: bool,
    /// Objects' size on the network grid relative to the scale plan's (1, what `match` and the
    /// service run): a measurement knob for choosing the plan, 0.25..=2 (docs/speed.md).
    #[arg(long, default_value_t = crate::matcher::plan::DEFAULT_GRID_SCALE)]
    pub grid_scale: f32,
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
    if !(0.25..=2.0).contains(&args.grid_scale) {
        return Err(CliError::Usage(format!(
            "--grid-scale {} is out of range 0.25..=2 (1 = the scale plan's size)",
            args.grid_scale
        )));
    }
    let search_side = if args.multi_instance { 320 } else { 224 };
    let photos =
        PhotoSet::load(&args.images, search_side).map_err(|e| CliError::Input(e.to_string()))?;
    let matcher = match args.method {
        Method::Tdcm => {
            let mut matcher = load_model(&args.model)?;
            matcher.set_grid_scale(args.grid_scale);
            Some(matcher)
        }
        Method::Ncc => None,
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
    // Single-instance pairs always hold the object, so the network path takes its best peak
    // whatever its value (as in the paper and the official peak reading); multi-instance scenes keep
    // the heatmap threshold of the network path before verification. The verified path runs
    // with the CLI's options.
    let options = MatchOptions {
        max_instances: if args.multi_instance {
            MatchOptions::default().max_instances
        } else {
            1
        },
        min_score: args.verification.min_score,
        candidate_threshold: args.verification.candidate_threshold,
        max_candidates: args.verification.max_candidates,
        method: args.method,
        classical_fallback: !args.verification.no_classical_fallback,
        polarity: args.verification.polarity,
        ..MatchOptions::default()
    }
    .validate()
    .map_err(|e| CliError::Usage(e.as_flag()))?;
    let network_min_score = if args.multi_instance {
        NETWORK_MIN_SCORE
    } else {
        ANY_PEAK
    };
    let mut saver = args.save.as_deref().map(PairSaver::new).transpose()?;
    let mut rows: [Vec<(Option<PairError>, f64)>; 3] = Default::default();
    let mut counts = [DetectionCounts::default(); 3];
    let mut calibration = Calibration::default();
    // Source photo -> (pairs, successes per row).
    let mut by_photo: std::collections::BTreeMap<usize, (usize, [usize; 3])> = Default::default();
    for index in 0..args.count {
        let pair = if args.multi_instance {
            make_multi_instance(
                &photos,
                args.level,
                (tw, th),
                args.min_structure,
                args.seed,
                index,
            )
        } else {
            make_pair(&photos, &spec, args.seed, index)
        }
        .map_err(|e| CliError::Input(e.to_string()))?;
        let (pair, covered) = conditions::apply_all(pair, &args.condition, args.seed, index);
        let mask = covered.filter(|_| args.mask_covered).map(|quadrant| {
            let (w, h) = (pair.template.width, pair.template.height);
            TemplateMask::new(w, h, quadrant.mask_out(w, h))
                .expect("three quadrants of a template are enough pixels")
        });
        if let Some(saver) = saver.as_mut() {
            saver.save(index, &pair, mask.as_ref())?;
        }
        let (ptw, pth) = (pair.template.width as f32, pair.template.height as f32);
        let runs: Vec<(Vec<Pose>, f64)> = match &matcher {
            Some(matcher) => {
                let run = match_pair(
                    matcher,
                    &pair,
                    mask.as_ref(),
                    &options,
                    network_min_score,
                    Paths {
                        refined: !args.no_refine,
                        verified: !args.no_refine,
                    },
                )?;
                let flags = matched_predictions(&run.verified, &pair.truth, ptw, pth);
                for (pose, &true_positive) in run.verified.iter().zip(&flags) {
                    calibration.add(pose.score, true_positive);
                }
                let answered: Vec<Pose> = run
                    .verified
                    .into_iter()
                    .filter(|p| p.score >= options.effective_min_score())
                    .collect();
                vec![
                    (run.network, run.network_ms),
                    (run.refined, run.refined_ms),
                    (answered, run.verified_ms),
                ]
            }
            None => vec![run_ncc(
                &pair,
                mask.as_ref(),
                &options,
                args.level,
                !args.no_refine,
                args.multi_instance,
            )],
        };
        let photo = by_photo.entry(pair.photo).or_default();
        photo.0 += 1;
        for (row, (poses, ms)) in runs.into_iter().enumerate() {
            if args.multi_instance {
                counts[row].add(match_detections(&poses, &pair.truth, ptw, pth));
            } else {
                let truth = &pair.truth[0];
                let error = poses.first().map(|p| pair_error(p, truth, ptw, pth));
                photo.1[row] += usize::from(error.is_some_and(|e| e.iou >= SUCCESS_IOU));
                rows[row].push((error, ms));
            }
        }
    }
    let label = format!(
        "{} polarity={} {} {}x{} n={} seed={} min-structure={}",
        args.condition
            .iter()
            .map(|c| c.name())
            .collect::<Vec<_>>()
            .join("+"),
        options.polarity.name(),
        args.level.name(),
        tw,
        th,
        args.count,
        args.seed,
        args.min_structure
    );
    let names: Vec<&str> = match (&matcher, args.no_refine) {
        (Some(_), false) => vec![
            "tdcm network top-1",
            "tdcm top-1 refined",
            "tdcm verified (default)",
        ],
        (Some(_), true) => vec!["tdcm network top-1"],
        (None, false) => vec!["ncc + refinement"],
        (None, true) => vec!["ncc"],
    };
    let calibration = (matcher.is_some() && !args.no_refine).then_some(&calibration);
    if args.multi_instance {
        let mut shown: Vec<(&str, &DetectionCounts)> = names.iter().copied().zip(&counts).collect();
        if matcher.is_some() && !args.no_refine {
            shown.remove(1); // the refined network poses are the network's detections, moved
        }
        print_detection(&label, &shown, calibration, args.json);
    } else {
        let summaries: Vec<(&str, Summary)> = names
            .iter()
            .zip(&rows)
            .map(|(name, results)| (*name, summarise(results)))
            .collect();
        let changes = (matcher.is_some() && !args.no_refine).then(|| {
            (
                path_changes(&rows[0], &rows[1]),
                path_changes(&rows[0], &rows[2]),
            )
        });
        print_table(&label, &summaries, changes, calibration, args.json);
        if args.by_photo {
            print_by_photo(&photos, &names, &by_photo, &args.images, args.json);
        }
    }
    Ok(())
}

/// Each path's Succ per source photo, most pairs first.
fn print_by_photo(
    photos: &PhotoSet,
    names: &[&str],
    by_photo: &std::collections::BTreeMap<usize, (usize, [usize; 3])>,
    root: &Path,
    as_json: bool,
) {
    let mut entries: Vec<(String, usize, &[usize])> = by_photo
        .iter()
        .map(|(&photo, (pairs, successes))| {
            let path = &photos.paths[photo];
            let name = path
                .strip_prefix(root)
                .unwrap_or(path)
                .display()
                .to_string();
            (name, *pairs, &successes[..names.len()])
        })
        .collect();
    entries.sort_by(|a, b| b.1.cmp(&a.1).then_with(|| a.0.cmp(&b.0)));
    if as_json {
        let rows: Vec<_> = entries
            .iter()
            .map(|(name, pairs, successes)| {
                json!({"photo": name, "pairs": pairs, "successes": successes})
            })
            .collect();
        println!("{}", json!({"paths": names, "by_photo": rows}));
        return;
    }
    println!("Succ per source photo ({}):", names.join(" | "));
    for (name, pairs, successes) in entries {
        let shares: Vec<String> = successes
            .iter()
            .map(|&s| format!("{:5.1}%", 100.0 * s as f32 / pairs as f32))
            .collect();
        println!("{pairs:5} pairs  {}  {name}", shares.join(" "));
    }
}

/// Answers of the multi-instance network path: heatmap peaks at or above the network path's
/// old default `min_score`.
const NETWORK_MIN_SCORE: f32 = 0.5;

/// The classical baseline on one pair (refined inside): its poses and time.
fn run_ncc(
    pair: &SyntheticPair,
    mask: Option<&TemplateMask>,
    options: &MatchOptions,
    level: Level,
    refine: bool,
    multi_instance: bool,
) -> (Vec<Pose>, f64) {
    let start = Instant::now();
    let (lo, hi) = level.scale_range();
    let ncc_options = MatchOptions {
        verify: refine,
        // Single pairs always hold the object: take the best candidate whatever its score.
        min_score: Some(if multi_instance {
            options.effective_min_score()
        } else {
            -1.0
        }),
        scale_range: (hi > lo).then_some(crate::matcher::ScaleRange { min: lo, max: hi }),
        ..options.clone()
    };
    let template = GrayImage32::from_rgb(&pair.template);
    let template = match mask {
        Some(mask) => mask.applied_to(&template),
        None => template,
    };
    let poses = crate::matcher::classical::ncc_match(
        &template,
        &GrayImage32::from_rgb(&pair.search),
        &ncc_options,
    );
    (poses, start.elapsed().as_secs_f64() * 1e3)
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

/// Lost/gained successes of the refined and of the verified path against the network's.
pub(super) type PathChanges = ((usize, usize), (usize, usize));

pub(super) fn print_table(
    label: &str,
    rows: &[(&str, Summary)],
    changes: Option<PathChanges>,
    calibration: Option<&Calibration>,
    as_json: bool,
) {
    if as_json {
        let rows: Vec<_> = rows
            .iter()
            .map(|(name, s)| json!({"method": name, "summary": s}))
            .collect();
        let changes = changes.map(|((rl, rg), (vl, vg))| {
            json!({"refined": {"lost": rl, "gained": rg}, "verified": {"lost": vl, "gained": vg}})
        });
        println!(
            "{}",
            json!({"set": label, "rows": rows, "changes": changes, "calibration": calibration})
        );
        return;
    }
    println!("pairs: {label}");
    println!("{}", summary_table(rows));
    println!("(errors over successful pairs, IoU >= 0.5; mIoU and Succ over all pairs)");
    if let Some(((rl, rg), (vl, vg))) = changes {
        println!(
            "against the network's top-1: refinement lost {rl} successes and gained {rg}; verification lost {vl} and gained {vg}"
        );
    }
    if let Some(c) = calibration {
        println!("{}", c.table());
    }
}

pub(super) fn print_detection(
    label: &str,
    rows: &[(&str, &DetectionCounts)],
    calibration: Option<&Calibration>,
    as_json: bool,
) {
    if as_json {
        let rows: Vec<_> = rows
            .iter()
            .map(|(name, c)| json!({"method": name, "counts": c, "precision": c.precision(), "recall": c.recall()}))
            .collect();
        println!(
            "{}",
            json!({"set": label, "rows": rows, "calibration": calibration})
        );
        return;
    }
    println!("multi-instance: {label}");
    println!(
        "| {:<24} | {:>9} | {:>7} | {:>7} | {:>6} | {:>7} |",
        "method", "precision", "recall", "objects", "found", "answers"
    );
    for (name, c) in rows {
        println!(
            "| {:<24} | {:>9.3} | {:>7.3} | {:>7} | {:>6} | {:>7} |",
            name,
            c.precision(),
            c.recall(),
            c.objects,
            c.true_positives,
            c.predictions
        );
    }
    if let Some(c) = calibration {
        println!("{}", c.table());
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

    /// Writes the pair's images (and its template's mask, with `--mask-covered`) and one line
    /// of `pairs.jsonl`, which `posematch match --pairs` reads as it is.
    fn save(
        &mut self,
        id: u64,
        pair: &SyntheticPair,
        mask: Option<&TemplateMask>,
    ) -> Result<(), CliError> {
        let template = format!("pair_{id:05}_template.png");
        let search = format!("pair_{id:05}_search.png");
        for (name, image) in [(&template, &pair.template), (&search, &pair.search)] {
            let path = self.dir.join(name);
            to_rgb8(image)
                .save(&path)
                .map_err(|e| CliError::io(&path, std::io::Error::other(e)))?;
        }
        let mut line =
            json!({"id": id, "template": template, "image": search, "truth": pair.truth});
        if let Some(mask) = mask {
            let name = format!("pair_{id:05}_mask.png");
            let path = self.dir.join(&name);
            std::fs::write(&path, mask.to_png()).map_err(|e| CliError::io(&path, e))?;
            line["template_mask"] = json!(name);
        }
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
