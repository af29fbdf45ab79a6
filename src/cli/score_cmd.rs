//! `posematch score`: the paper's metrics for answers that any matcher wrote — ours
//! (`posematch match --pairs`), the OpenCV reference (`scripts/opencv_ncc.py`), or a Halcon or
//! PatMax export in the same JSON lines — against the truth `posematch eval --save` stored with
//! the pairs. One scorer for every matcher, so their tables compare like for like.

use std::collections::HashMap;
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};

use clap::Args;
use serde::Deserialize;

use super::CliError;
use super::eval_cmd::{print_detection, print_table};
use crate::evaluation::{DetectionCounts, PairError, match_detections, pair_error, summarise};
use crate::geometry::Pose;

#[derive(Args, Debug)]
pub struct ScoreArgs {
    /// `pairs.jsonl` written by `posematch eval --save` (paths and the truth).
    #[arg(long)]
    pub pairs: PathBuf,
    /// Answers, one JSON line per pair: `{"id": .., "poses": [..], "ms": ..}` (the output of
    /// `posematch match --pairs`); a line with `"error"` or a missing id counts as a miss.
    #[arg(long)]
    pub results: PathBuf,
    /// Name of the matcher in the table.
    #[arg(long, default_value = "answers")]
    pub name: String,
    /// Multi-instance scenes: precision and recall of every answer instead of the first
    /// answer's errors.
    #[arg(long)]
    pub multi_instance: bool,
    /// Print JSON instead of the table.
    #[arg(long)]
    pub json: bool,
}

#[derive(Deserialize)]
struct PairLine {
    id: u64,
    template: String,
    truth: Vec<Pose>,
}

#[derive(Deserialize)]
struct ResultLine {
    id: u64,
    #[serde(default)]
    poses: Vec<Pose>,
    #[serde(default)]
    ms: f64,
}

fn json_lines<T: for<'de> Deserialize<'de>>(path: &Path) -> Result<Vec<T>, CliError> {
    let file = std::fs::File::open(path).map_err(|e| CliError::io(path, e))?;
    let mut lines = Vec::new();
    for (number, line) in BufReader::new(file).lines().enumerate() {
        let line = line.map_err(|e| CliError::io(path, e))?;
        if line.trim().is_empty() {
            continue;
        }
        lines.push(serde_json::from_str(&line).map_err(|e| {
            CliError::Input(format!("{} line {}: {e}", path.display(), number + 1))
        })?);
    }
    Ok(lines)
}

pub fn run(args: ScoreArgs) -> Result<(), CliError> {
    let pairs: Vec<PairLine> = json_lines(&args.pairs)?;
    let answers: HashMap<u64, ResultLine> = json_lines::<ResultLine>(&args.results)?
        .into_iter()
        .map(|r| (r.id, r))
        .collect();
    let base = args.pairs.parent().unwrap_or(Path::new("."));
    let mut results: Vec<(Option<PairError>, f64)> = Vec::new();
    let mut counts = DetectionCounts::default();
    let mut missing = 0usize;
    for pair in &pairs {
        let template = base.join(&pair.template);
        let (tw, th) = image::image_dimensions(&template)
            .map_err(|e| CliError::Input(format!("{}: {e}", template.display())))?;
        let (tw, th) = (tw as f32, th as f32);
        let answer = answers.get(&pair.id);
        missing += usize::from(answer.is_none());
        let (poses, ms) = answer.map_or((&[][..], 0.0), |a| (&a.poses[..], a.ms));
        if args.multi_instance {
            counts.add(match_detections(poses, &pair.truth, tw, th));
        } else {
            let truth = pair
                .truth
                .first()
                .ok_or_else(|| CliError::Input(format!("pair {} has no truth", pair.id)))?;
            results.push((poses.first().map(|p| pair_error(p, truth, tw, th)), ms));
        }
    }
    if missing > 0 {
        eprintln!(
            "{missing} of {} pairs have no line in {}; counted as misses",
            pairs.len(),
            args.results.display()
        );
    }
    let label = format!("{} ({} pairs)", args.pairs.display(), pairs.len());
    if args.multi_instance {
        print_detection(&label, &[(&args.name, &counts)], None, args.json);
    } else {
        print_table(
            &label,
            &[(&args.name, summarise(&results))],
            None,
            None,
            args.json,
        );
    }
    Ok(())
}
