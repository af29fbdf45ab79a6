//! `posematch match`: one pair on the command line, or many from a JSONL file.

use std::collections::HashMap;
use std::fs::File;
use std::io::{BufRead, BufReader, BufWriter, Write};
use std::path::{Path, PathBuf};
use std::time::Instant;

use clap::Args;
use serde_json::{Value, json};

use super::{CliError, ModelArgs, load_model, read_image, read_template};
use crate::geometry::{Pose, TemplateFrame, TemplateOrigin};
use crate::imaging::{GrayImage32, RgbImage32};
use crate::matcher::classical::ClassicalOutcome;
use crate::matcher::selection::suppress_across_templates;
use crate::matcher::{
    AngleRange, EncodedTemplate, MatchOptions, Matcher, Method, ScaleRange, TemplateMask,
    ValidOptions,
};
use crate::world::WorldCalibration;

#[derive(Args, Debug)]
pub struct MatchArgs {
    /// Template image (PNG, JPEG, BMP, TIFF, PNM). Transparent pixels of a template with an
    /// alpha channel are ignored, as with --template-mask. Repeat it to find several templates
    /// in one call (the image is read once; each pose names its template; --max-instances
    /// applies per template).
    #[arg(long, required_unless_present = "pairs", conflicts_with = "pairs")]
    pub template: Vec<PathBuf>,
    /// Mask of the template's size: black (0) pixels are ignored by every score and the
    /// refinement (a date code, a serial number), any other value is used.
    #[arg(long, requires = "template")]
    pub template_mask: Option<PathBuf>,
    /// The template's reference point X,Y in template pixels (column, row; the top-left
    /// pixel's centre is 0,0): each pose reports where it lands (`origin_x`, `origin_y`).
    /// Default: the template centre.
    #[arg(long, requires = "template", value_parser = parse_origin, allow_hyphen_values = true)]
    pub template_origin: Option<(f32, f32)>,
    /// Image-to-world calibration, JSON `{"points": [{"image": [x, y], "world": [X, Y]}, ...],
    /// "unit": "mm"}` (3 points: affine; 4 or more: homography): each pose then also carries
    /// `world_x`, `world_y` (its reference point) and `world_angle_deg`.
    #[arg(long)]
    pub calibration: Option<PathBuf>,
    /// Search image.
    #[arg(long, required_unless_present = "pairs", conflicts_with = "pairs")]
    pub image: Option<PathBuf>,
    /// Batch mode: JSONL with one `{"id", "template", "image"[, "template_mask",
    /// "template_origin": [x, y], "max_instances"]}` per line, or `"templates": [paths]` (1 to
    /// 16) instead of `"template"` to find several in the image (each pose then names its
    /// `"template"`); relative paths are relative to this file's folder.
    #[arg(long, requires = "out")]
    pub pairs: Option<PathBuf>,
    /// Batch mode output: one `{"id", "poses", "timed_out", "ms"}` (or `{"id", "error"}`) per
    /// input line;
    /// `ms` is the matching alone (files read and decoded before; a new template is encoded
    /// before).
    #[arg(long, requires = "pairs")]
    pub out: Option<PathBuf>,
    #[command(flatten)]
    pub model: ModelArgs,
    /// Report at most this many instances, best first.
    #[arg(long, default_value_t = MatchOptions::default().max_instances)]
    pub max_instances: usize,
    #[command(flatten)]
    pub verification: super::VerificationArgs,
    /// Suppress an instance whose rotated box overlaps a better one by more than this IoU.
    #[arg(long, default_value_t = MatchOptions::default().max_overlap)]
    pub max_overlap: f32,
    /// With several templates (repeated --template, a batch line's `"templates"`): of two
    /// instances of different templates whose boxes overlap by more than --max-overlap, report
    /// only the better-scoring one (one answer per object when similar parts may be mistaken
    /// for one another).
    #[arg(long)]
    pub suppress_across_templates: bool,
    /// Only report angles in START,END (degrees, counter-clockwise, e.g. -45,45).
    #[arg(long, value_parser = parse_angle_range, allow_hyphen_values = true)]
    pub angle_range: Option<AngleRange>,
    /// Expected object scale LO,HI relative to the template (also steers the search).
    #[arg(long, value_parser = parse_scale_range)]
    pub scale_range: Option<ScaleRange>,
    /// Network only: no verification or refinement; scores are heatmap values (faster, finds
    /// fewer objects, coarser poses).
    #[arg(long)]
    pub no_refine: bool,
    /// Matcher: `tdcm` (the network) or `ncc` (classical exhaustive search, no weights needed;
    /// slow), for single pairs and `--pairs` alike.
    #[arg(long, default_value = "tdcm", value_parser = str::parse::<Method>)]
    pub method: Method,
    /// Answer within this many milliseconds (from the start of matching, after the files are
    /// read) with what was verified by then, and `"timed_out": true`, instead of finishing the
    /// search (with `--method ncc` too, whose image pyramid is not interruptible).
    #[arg(long)]
    pub timeout_ms: Option<u32>,
    /// Draw the poses on the search image and save it here (PNG).
    #[arg(long, conflicts_with = "pairs")]
    pub overlay: Option<PathBuf>,
}

fn parse_pair(s: &str, what: &str) -> Result<(f32, f32), String> {
    let parts: Vec<&str> = s.split(',').map(str::trim).collect();
    match parts.as_slice() {
        [a, b] => match (a.parse(), b.parse()) {
            (Ok(a), Ok(b)) => Ok((a, b)),
            _ => Err(format!("{what} `{s}`: expected two numbers A,B")),
        },
        _ => Err(format!("{what} `{s}`: expected two numbers A,B")),
    }
}

fn parse_origin(s: &str) -> Result<(f32, f32), String> {
    parse_pair(s, "template origin")
}

fn parse_angle_range(s: &str) -> Result<AngleRange, String> {
    let (a, b) = parse_pair(s, "angle range")?;
    AngleRange::from_bounds(a, b)
}

fn parse_scale_range(s: &str) -> Result<ScaleRange, String> {
    let (a, b) = parse_pair(s, "scale range")?;
    ScaleRange::new(a, b)
}

impl MatchArgs {
    fn options(&self) -> Result<ValidOptions, CliError> {
        MatchOptions {
            max_instances: self.max_instances,
            min_score: self.verification.min_score,
            candidate_threshold: self.verification.candidate_threshold,
            max_candidates: self.verification.max_candidates,
            max_overlap: self.max_overlap,
            angle_range: self.angle_range,
            scale_range: self.scale_range,
            verify: !self.no_refine,
            method: self.method,
            classical_fallback: !self.verification.no_classical_fallback,
            polarity: self.verification.polarity,
            timeout_ms: self.timeout_ms,
            covered_parts: None,
            suppress_across_templates: self.suppress_across_templates,
        }
        .validate()
        .map_err(|e| CliError::Usage(e.as_flag()))
    }
}

/// Reads and fits `--calibration`.
fn read_calibration(path: &Path) -> Result<WorldCalibration, CliError> {
    let text = std::fs::read_to_string(path).map_err(|e| CliError::io(path, e))?;
    WorldCalibration::from_json(&text)
        .map_err(|e| CliError::Usage(format!("--calibration {}: {e}", path.display())))
}

/// What the answer says about the calibration used: its model, unit and how well the points
/// agreed.
fn calibration_json(calibration: &WorldCalibration) -> Value {
    json!({
        "model": calibration.model(),
        "unit": calibration.unit(),
        "rms_residual": calibration.rms_residual(),
    })
}

fn origin_of(
    template: &RgbImage32,
    origin: Option<(f32, f32)>,
) -> Result<Option<TemplateOrigin>, String> {
    origin
        .map(|(x, y)| TemplateOrigin::new(x, y, template.width, template.height))
        .transpose()
}

pub fn run(args: MatchArgs) -> Result<(), CliError> {
    let options = args.options()?;
    let calibration = args
        .calibration
        .as_deref()
        .map(read_calibration)
        .transpose()?;
    // Read inputs before loading the model so that bad files fail fast.
    if let (Some(pairs), Some(out)) = (&args.pairs, &args.out) {
        let matcher = match args.method {
            Method::Tdcm => Some(load_model(&args.model)?),
            Method::Ncc => None,
        };
        if let Some(calibration) = &calibration {
            eprintln!("calibration: {}", calibration_json(calibration));
        }
        return run_pairs(matcher.as_ref(), pairs, out, &options, calibration.as_ref());
    }
    let (false, Some(image_path)) = (args.template.is_empty(), &args.image) else {
        return Err(CliError::Usage(
            "give --template and --image, or --pairs and --out".into(),
        ));
    };
    if args.template.len() > 1 && (args.template_mask.is_some() || args.template_origin.is_some()) {
        return Err(CliError::Usage(
            "--template-mask and --template-origin describe one template: give a single --template with them (or an alpha channel for each template's mask)".into(),
        ));
    }
    let mut templates = Vec::with_capacity(args.template.len());
    for path in &args.template {
        let (template, mask) = read_template(path, args.template_mask.as_deref())?;
        let origin = origin_of(&template, args.template_origin)
            .map_err(|m| CliError::Usage(format!("--template-origin: {m}")))?;
        let frame = TemplateFrame::new(template.width, template.height, origin);
        templates.push((template, mask, frame));
    }
    let image = read_image(image_path)?;
    // Every pose with the index of its template.
    let (mut poses, timed_out, ms): (Vec<(usize, Pose)>, bool, f64) = if args.method == Method::Ncc
    {
        let start = Instant::now();
        let (poses, timed_out) = ncc_all(&templates, &image, &options)?;
        (poses, timed_out, start.elapsed().as_secs_f64() * 1e3)
    } else {
        let matcher = load_model(&args.model)?;
        let start = Instant::now();
        let mut encoded = Vec::with_capacity(templates.len());
        for (template, mask, frame) in &templates {
            let mut one = matcher.encode_masked_template(template, mask.as_ref())?;
            one.origin = frame.origin;
            encoded.push(one);
        }
        let refs: Vec<&EncodedTemplate> = encoded.iter().collect();
        let (poses, timed_out) = network_all(&matcher, &refs, &image, &options)?;
        (poses, timed_out, start.elapsed().as_secs_f64() * 1e3)
    };
    poses.sort_by(|a, b| b.1.score.total_cmp(&a.1.score));
    if let Some(overlay) = &args.overlay {
        let drawn: Vec<_> = poses
            .iter()
            .map(|(index, pose)| {
                let frame = &templates[*index].2;
                (*pose, (frame.width, frame.height))
            })
            .collect();
        super::overlay::save_overlay(&image, &drawn, overlay)?;
    }
    let poses: Vec<Value> = poses
        .iter()
        .map(|(index, pose)| {
            let mut value = pose_json(pose, &templates[*index].2, calibration.as_ref());
            value["template"] = json!(args.template[*index]);
            value
        })
        .collect();
    let mut answer = json!({
        "image": image_path,
        "image_width": image.width,
        "image_height": image.height,
        "poses": poses,
        "timed_out": timed_out,
        "ms": round3(ms),
    });
    match args.template.as_slice() {
        [one] => answer["template"] = json!(one),
        several => answer["templates"] = json!(several),
    }
    if let Some(calibration) = &calibration {
        answer["calibration"] = calibration_json(calibration);
    }
    println!(
        "{}",
        serde_json::to_string_pretty(&answer).expect("JSON of plain values")
    );
    Ok(())
}

/// The classical matcher's answer (`--method ncc`): sizes checked as the network path checks
/// them, and its cost bounded.
fn ncc_answer(
    template: &RgbImage32,
    mask: Option<&TemplateMask>,
    image: &RgbImage32,
    options: &MatchOptions,
    answer_by: Option<Instant>,
) -> Result<ClassicalOutcome, crate::matcher::MatchError> {
    crate::matcher::check_pair_sizes(template.width, template.height, image.width, image.height)?;
    let gray = GrayImage32::from_rgb(template);
    let gray = match mask {
        Some(mask) => {
            mask.check_fits(template.width, template.height)?;
            mask.applied_to(&gray)
        }
        None => gray,
    };
    crate::matcher::classical::check_work(
        template.width,
        template.height,
        image.width,
        image.height,
        options,
    )?;
    Ok(crate::matcher::classical::ncc_match_until(
        &gray,
        &GrayImage32::from_rgb(image),
        options,
        answer_by,
    ))
}

/// The classical matcher's poses of each template (read templates with their masks), each with
/// its template's index, within one time limit for them all (`timeout_ms` from now); and
/// whether any search ran out of time.
fn ncc_all(
    templates: &[(RgbImage32, Option<TemplateMask>, TemplateFrame)],
    image: &RgbImage32,
    options: &MatchOptions,
) -> Result<(Vec<(usize, Pose)>, bool), crate::matcher::MatchError> {
    let answer_by = options.answer_by(Instant::now());
    let mut found = Vec::new();
    let mut timed_out = false;
    for (index, (template, mask, _)) in templates.iter().enumerate() {
        let outcome = ncc_answer(template, mask.as_ref(), image, options, answer_by)?;
        timed_out |= outcome.timed_out;
        found.extend(outcome.poses.into_iter().map(|pose| (index, pose)));
    }
    let sizes: Vec<(f32, f32)> = templates
        .iter()
        .map(|(template, ..)| (template.width as f32, template.height as f32))
        .collect();
    Ok((across_templates(found, &sizes, options), timed_out))
}

/// The network's poses of each template, found in one batch ([`Matcher::match_templates`]),
/// each with its template's index; and whether any search ran out of time.
fn network_all(
    matcher: &Matcher,
    templates: &[&EncodedTemplate],
    image: &RgbImage32,
    options: &ValidOptions,
) -> Result<(Vec<(usize, Pose)>, bool), crate::matcher::MatchError> {
    let mut found = Vec::new();
    let mut timed_out = false;
    for (index, outcome) in matcher
        .match_templates(templates, image, options)
        .into_iter()
        .enumerate()
    {
        let outcome = outcome?;
        timed_out |= outcome.timed_out;
        found.extend(outcome.poses.into_iter().map(|pose| (index, pose)));
    }
    let sizes: Vec<(f32, f32)> = templates
        .iter()
        .map(|template| (template.width as f32, template.height as f32))
        .collect();
    Ok((across_templates(found, &sizes, options), timed_out))
}

/// Every template's poses, with those that another template's better answer explains removed
/// where the options ask for it ([`suppress_across_templates`]).
fn across_templates(
    found: Vec<(usize, Pose)>,
    sizes: &[(f32, f32)],
    options: &MatchOptions,
) -> Vec<(usize, Pose)> {
    if options.suppress_across_templates && sizes.len() > 1 {
        suppress_across_templates(found, sizes, options.max_overlap)
    } else {
        found
    }
}

/// A pose as the CLI prints it: the pose's fields, its `transform` (the 2x3 matrix from
/// template pixels to image pixels, [`Pose::transform`]), where the template's reference point
/// lands (`origin_x`, `origin_y`) and, with a calibration, where that lies in the world
/// (`world_x`, `world_y`, `world_angle_deg`).
fn pose_json(
    pose: &Pose,
    template: &TemplateFrame,
    calibration: Option<&WorldCalibration>,
) -> Value {
    let mut value = serde_json::to_value(pose).expect("a pose is plain numbers");
    value["transform"] = json!(template.transform(pose));
    let (origin_x, origin_y) = template.origin_in_image(pose);
    value["origin_x"] = json!(origin_x);
    value["origin_y"] = json!(origin_y);
    if let Some(calibration) = calibration {
        let world = calibration.place(pose, template);
        value["world_x"] = json!(world.x);
        value["world_y"] = json!(world.y);
        value["world_angle_deg"] = json!(world.angle_deg);
    }
    value
}

fn ms_since(start: Instant) -> f64 {
    start.elapsed().as_secs_f64() * 1e3
}

fn round3(v: f64) -> f64 {
    (v * 1000.0).round() / 1000.0
}

/// Batch mode. A bad line gets an `"error"` for its id and the batch goes on; templates are
/// encoded once per path. `matcher` None: the classical matcher (`--method ncc`).
fn run_pairs(
    matcher: Option<&Matcher>,
    pairs: &Path,
    out: &Path,
    options: &ValidOptions,
    calibration: Option<&WorldCalibration>,
) -> Result<(), CliError> {
    let input = File::open(pairs).map_err(|e| CliError::io(pairs, e))?;
    let base = pairs.parent().unwrap_or(Path::new(".")).to_owned();
    let output = File::create(out).map_err(|e| CliError::io(out, e))?;
    let mut output = BufWriter::new(output);
    // Encoded once per (template, mask) pair.
    let mut templates: HashMap<TemplateKey, EncodedTemplate> = HashMap::new();
    let (mut ok, mut failed) = (0usize, 0usize);
    for (number, line) in BufReader::new(input).lines().enumerate() {
        let line = line.map_err(|e| CliError::io(pairs, e))?;
        if line.trim().is_empty() {
            continue;
        }
        let (id, result) = match_line(matcher, &line, &base, options, calibration, &mut templates);
        let record = match result {
            Ok((poses, timed_out, ms)) => {
                ok += 1;
                json!({"id": id, "poses": poses, "timed_out": timed_out, "ms": round3(ms)})
            }
            Err(message) => {
                failed += 1;
                json!({"id": id, "error": format!("line {}: {message}", number + 1)})
            }
        };
        writeln!(output, "{record}").map_err(|e| CliError::io(out, e))?;
    }
    output.flush().map_err(|e| CliError::io(out, e))?;
    eprintln!(
        "{ok} pairs matched, {failed} failed; results in {}",
        out.display()
    );
    Ok(())
}

/// A batch line's `template`, or its `templates` (1 to [`MAX_TEMPLATES_PER_LINE`]), as paths.
fn template_paths(record: &Value, base: &Path) -> Result<Vec<PathBuf>, String> {
    match (record.get("template"), record.get("templates")) {
        (Some(Value::String(one)), None) => Ok(vec![base.join(one)]),
        (None, Some(Value::Array(list))) if (1..=MAX_TEMPLATES_PER_LINE).contains(&list.len()) => {
            let paths: Option<Vec<PathBuf>> = list
                .iter()
                .map(|p| p.as_str().map(|p| base.join(p)))
                .collect();
            paths.ok_or_else(|| "`templates` must list template paths (strings)".into())
        }
        (None, Some(_)) => Err(format!(
            "`templates` must be a list of 1 to {MAX_TEMPLATES_PER_LINE} template paths"
        )),
        (Some(_), Some(_)) => Err("give `template` or `templates`, not both".into()),
        (Some(_), None) => Err("`template` must be a path (a string)".into()),
        (None, None) => Err("missing string field `template` (or a list `templates`)".into()),
    }
}

/// The most templates one batch line may name: as many as one service request may.
const MAX_TEMPLATES_PER_LINE: usize = crate::engine::MAX_TEMPLATES_PER_MATCH;

/// One batch line's answer: its poses as printed, whether it timed out, and the milliseconds.
type LineAnswer = (Vec<Value>, bool, f64);

/// A batch's templates are encoded once per path, mask path and origin (as its bits).
type TemplateKey = (PathBuf, Option<PathBuf>, Option<(u32, u32)>);

fn match_line(
    matcher: Option<&Matcher>,
    line: &str,
    base: &Path,
    options: &ValidOptions,
    calibration: Option<&WorldCalibration>,
    templates: &mut HashMap<TemplateKey, EncodedTemplate>,
) -> (Value, Result<LineAnswer, String>) {
    let record: Value = match serde_json::from_str(line) {
        Ok(v) => v,
        Err(e) => return (Value::Null, Err(format!("not valid JSON: {e}"))),
    };
    let id = record.get("id").cloned().unwrap_or(Value::Null);
    let path = |key: &str| -> Result<PathBuf, String> {
        record
            .get(key)
            .and_then(Value::as_str)
            .map(|p| base.join(p))
            .ok_or_else(|| format!("missing string field `{key}`"))
    };
    let result = (|| {
        let template_paths = template_paths(&record, base)?;
        let image_path = path("image")?;
        let mask_path = match record.get("template_mask") {
            None | Some(Value::Null) => None,
            Some(_) => Some(path("template_mask")?),
        };
        let origin = match record.get("template_origin") {
            None | Some(Value::Null) => None,
            Some(value) => match value.as_array().map(|a| a.as_slice()) {
                Some([x, y]) => match (x.as_f64(), y.as_f64()) {
                    (Some(x), Some(y)) => Some((x as f32, y as f32)),
                    _ => return Err("`template_origin` must be two numbers [x, y]".into()),
                },
                _ => return Err("`template_origin` must be two numbers [x, y]".into()),
            },
        };
        if template_paths.len() > 1 && (mask_path.is_some() || origin.is_some()) {
            return Err(
                "`template_mask` and `template_origin` describe one template: use `template` with them"
                    .into(),
            );
        }
        let options = match record.get("max_instances") {
            None => options.clone(),
            Some(n) => MatchOptions {
                max_instances: n
                    .as_u64()
                    .ok_or("`max_instances` must be a positive integer")?
                    as usize,
                ..(**options).clone()
            }
            .validate()
            .map_err(|e| e.to_string())?,
        };
        // Every pose with the index of its template, and each template's frame.
        let (mut found, frames, timed_out, ms) = match matcher {
            None => {
                let mut read = Vec::with_capacity(template_paths.len());
                for template_path in &template_paths {
                    let (template, mask) = read_template(template_path, mask_path.as_deref())
                        .map_err(|e| e.to_string())?;
                    let origin = origin_of(&template, origin)
                        .map_err(|m| format!("template_origin: {m}"))?;
                    let frame = TemplateFrame::new(template.width, template.height, origin);
                    read.push((template, mask, frame));
                }
                let image = read_image(&image_path).map_err(|e| e.to_string())?;
                let start = Instant::now();
                let (found, timed_out) =
                    ncc_all(&read, &image, &options).map_err(|e| e.to_string())?;
                let frames: Vec<TemplateFrame> = read.iter().map(|(_, _, frame)| *frame).collect();
                (found, frames, timed_out, ms_since(start))
            }
            Some(matcher) => {
                let mut keys = Vec::with_capacity(template_paths.len());
                for template_path in &template_paths {
                    let key = (
                        template_path.clone(),
                        mask_path.clone(),
                        origin.map(|(x, y)| (x.to_bits(), y.to_bits())),
                    );
                    if !templates.contains_key(&key) {
                        let (template, mask) = read_template(template_path, mask_path.as_deref())
                            .map_err(|e| e.to_string())?;
                        let origin = origin_of(&template, origin)
                            .map_err(|m| format!("template_origin: {m}"))?;
                        let mut encoded = matcher
                            .encode_masked_template(&template, mask.as_ref())
                            .map_err(|e| format!("{}: {e}", template_path.display()))?;
                        encoded.origin = origin;
                        templates.insert(key.clone(), encoded);
                    }
                    keys.push(key);
                }
                let image = read_image(&image_path).map_err(|e| e.to_string())?;
                let encoded: Vec<&EncodedTemplate> = keys.iter().map(|k| &templates[k]).collect();
                let start = Instant::now();
                let (found, timed_out) =
                    network_all(matcher, &encoded, &image, &options).map_err(|e| e.to_string())?;
                let frames = encoded.iter().map(|template| template.frame()).collect();
                (found, frames, timed_out, ms_since(start))
            }
        };
        found.sort_by(|a, b| b.1.score.total_cmp(&a.1.score));
        let several = record.get("templates").is_some();
        let poses = found
            .iter()
            .map(|(index, pose)| {
                let mut value = pose_json(pose, &frames[*index], calibration);
                if several {
                    value["template"] = record["templates"][*index].clone();
                }
                value
            })
            .collect();
        Ok((poses, timed_out, ms))
    })();
    (id, result)
}
