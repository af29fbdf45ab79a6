//! The `posematch` command line: flag parsing and file handling around [`crate::matcher`].
//! Thin on purpose; every rule about images and poses lives below this layer.

mod eval_cmd;
mod health_cmd;
mod match_cmd;
mod overlay;
mod score_cmd;
mod serve_cmd;
mod train_cmd;

use std::path::{Path, PathBuf};

use clap::{Args, Parser, Subcommand};

use crate::imaging::{DecodeError, ImageLimits, InputConvention, decode_image_file};
use crate::matcher::{MatchError, Matcher, Polarity, TemplateMask};
use crate::model::{
    DeviceError, LoadError, Precision, TrainedOn, WeightsSource, save_weights, select_device,
};

pub use match_cmd::MatchArgs;

#[derive(Parser, Debug)]
#[command(
    name = "posematch",
    version,
    about = "Find a template in images and report every instance's pose (x, y, angle, scale_x, scale_y)"
)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Match a template in an image (or a JSONL list of pairs) and print the poses as JSON.
    Match(MatchArgs),
    /// Measure accuracy on generated pairs with exact ground truth (the paper's metrics).
    Eval(eval_cmd::EvalArgs),
    /// Score answers any matcher wrote for saved pairs (`eval --save`) against their truth.
    Score(score_cmd::ScoreArgs),
    /// Train the network (or fine-tune it) on pairs cut from folders of unlabeled photos.
    Train(train_cmd::TrainArgs),
    /// Run the gRPC service (template registry, batching, health, reflection, metrics).
    Serve(serve_cmd::ServeArgs),
    /// Ask a running server whether it is SERVING (exit 0) — for container health checks.
    Health(health_cmd::HealthArgs),
    /// Manage network weights.
    #[command(subcommand)]
    Weights(WeightsCommand),
}

#[derive(Subcommand, Debug)]
pub enum WeightsCommand {
    /// Convert a PyTorch checkpoint of the official model (.pth or .safetensors) into
    /// PoseMatch's own format (.bpk), checking it against the architecture.
    Import {
        /// A .pth/.pt, .safetensors or .bpk file (`default`: the embedded weights, e.g. to
        /// give them another record).
        #[arg(long = "from")]
        from: PathBuf,
        #[arg(long)]
        out: PathBuf,
        /// What the weights were trained on, kept in the written file (models/README.md): a
        /// training record (`trained_on.json`, which `training/train.py` writes beside
        /// `weights.pth`), or weights whose record they inherit (`default`, a .bpk: the weights
        /// a fine-tune started from or was mixed with). Repeat to combine, oldest first: the
        /// file records everything any of them saw, and as trained throughout what all did.
        #[arg(long = "trained-on", value_name = "RECORD")]
        trained_on: Vec<PathBuf>,
    },
    /// Print what weights (default: the embedded ones) were trained on, as the file records it
    /// (JSON; nothing recorded: the weights are trusted everywhere).
    Show {
        /// `default` (embedded), or a .bpk/.pth/.safetensors file.
        #[arg(default_value = "default")]
        weights: String,
    },
    /// Write weights (default: the embedded ones) as a .safetensors file with the official
    /// checkpoint's tensor names and layouts, which `training/train.py --init-weights` starts a
    /// GPU run from and `weights import` reads back.
    Export {
        /// `default` (embedded), or a .bpk/.pth/.safetensors file.
        #[arg(long = "from", default_value = "default")]
        from: String,
        #[arg(long)]
        out: PathBuf,
    },
}

/// Which answers count and which network peaks are verified: shared by `match` and `eval`.
#[derive(Args, Debug, Clone)]
pub struct VerificationArgs {
    /// Report only answers scoring at least this (0..1): the verified score of the template at
    /// the refined pose, or the heatmap value with --no-refine. Default 0.9 (0.5 on the
    /// heatmap with --no-refine).
    #[arg(long)]
    pub min_score: Option<f32>,
    /// Heatmap value (0..1) from which a network peak is a candidate for verification.
    #[arg(long, default_value_t = crate::matcher::options::DEFAULT_CANDIDATE_THRESHOLD)]
    pub candidate_threshold: f32,
    /// Most candidates verified per search (the best of every tile's peaks); 0 = automatic (3
    /// per --max-instances, 6 where the weights' heads are not trusted, at least 100).
    #[arg(long, default_value_t = 0)]
    pub max_candidates: usize,
    /// Do not search the image classically (around the template's expected scale) when none of
    /// the network's candidates verifies at --min-score; by default that search runs where it
    /// costs less than about 65 ms (e.g. up to about 650x650 pixels for a 36x36 template).
    #[arg(long)]
    pub no_classical_fallback: bool,
    /// Which contrast the part may show: `same` (as registered), `reversed` (dark where the
    /// template is bright: a backlight, another coating) or `either` (both searched, about
    /// twice the work).
    #[arg(long, default_value = "same", value_parser = str::parse::<Polarity>)]
    pub polarity: Polarity,
}

/// Model flags shared by every subcommand that runs the network.
#[derive(Args, Debug, Clone)]
pub struct ModelArgs {
    /// Weights file: .bpk (PoseMatch), .pth/.pt or .safetensors (official PyTorch checkpoint;
    /// a file named otherwise is recognised by its content); `default`: the weights embedded
    /// in this binary (models/README.md).
    #[arg(long, default_value = "default", value_parser = parse_weights_source)]
    pub weights: WeightsSource,
    /// Input convention: `imagenet` (RGB, ImageNet mean/std; how the official checkpoint was
    /// trained) or `gray` (the authors' test.py demo).
    #[arg(long, default_value = "imagenet", value_parser = str::parse::<InputConvention>)]
    pub convention: InputConvention,
    /// Arithmetic of the network's large products: `auto` (bf16 where the CPU has Intel AMX
    /// tiles or AVX-512 BF16, else f32), `f32` (exact, the same numbers on every machine) or
    /// `bf16` (about twice as fast; docs/speed.md shows its held-out accuracy).
    #[arg(long, default_value = "auto", value_parser = str::parse::<Precision>)]
    pub precision: Precision,
}

pub(crate) fn parse_weights_source(s: &str) -> Result<WeightsSource, String> {
    Ok(WeightsSource::from_path(Some(Path::new(s))))
}

/// Everything that ends a command with a non-zero exit; the message says what to fix.
#[derive(Debug, thiserror::Error)]
pub enum CliError {
    #[error(transparent)]
    Decode(#[from] DecodeError),
    #[error(transparent)]
    Match(#[from] MatchError),
    #[error(transparent)]
    Weights(#[from] LoadError),
    #[error(transparent)]
    Device(#[from] DeviceError),
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    /// An option, flag, setting or environment value is invalid.
    #[error("{0}")]
    Usage(String),
    /// An input (image, weights, photos, pairs file) is missing, unreadable or invalid.
    #[error("{0}")]
    Input(String),
    /// The service or a training run failed while running (address in use, model thread,
    /// checkpoint write).
    #[error("{0}")]
    Runtime(String),
    #[error("unhealthy: {0}")]
    Unhealthy(String),
}

impl CliError {
    pub fn io(path: &Path, source: std::io::Error) -> Self {
        Self::Io {
            path: path.to_owned(),
            source,
        }
    }

    /// Exit status (README "Exit status"): 2 wrong usage (options, settings, `BURN_DEVICE`),
    /// 1 bad input (files, weights, photos) and "not serving" from `posematch health` (Docker
    /// reads 1 as unhealthy and reserves 2), 3 a failure while running.
    pub fn exit_code(&self) -> i32 {
        match self {
            Self::Usage(_) | Self::Device(_) => 2,
            Self::Decode(_)
            | Self::Match(_)
            | Self::Weights(_)
            | Self::Io { .. }
            | Self::Input(_)
            | Self::Unhealthy(_) => 1,
            Self::Runtime(_) => 3,
        }
    }
}

/// Loads the network from `--weights` or the embedded default.
pub fn load_model(args: &ModelArgs) -> Result<Matcher, CliError> {
    let device = select_device()?;
    let model = args.weights.load(&device)?;
    Matcher::new(model, device, args.convention)
        .with_trained_on(args.weights.trained_on()?)
        .with_precision(args.precision)
        .map_err(|e| CliError::Usage(e.to_string()))
}

/// Runs one parsed command line.
pub fn run(cli: Cli) -> Result<(), CliError> {
    match cli.command {
        Command::Match(args) => match_cmd::run(args),
        Command::Eval(args) => eval_cmd::run(args),
        Command::Score(args) => score_cmd::run(args),
        Command::Serve(args) => serve_cmd::run(args),
        Command::Train(args) => train_cmd::run(args),
        Command::Health(args) => health_cmd::run(args),
        Command::Weights(WeightsCommand::Import {
            from,
            out,
            trained_on,
        }) => {
            let device = select_device()?;
            let model = WeightsSource::from_path(Some(&from)).load(&device)?;
            let record = combined_records(&trained_on)?;
            save_weights(&model, record.as_ref(), &out)?;
            eprintln!("wrote {}", out.display());
            Ok(())
        }
        Command::Weights(WeightsCommand::Show { weights }) => {
            let source = WeightsSource::from_path(Some(Path::new(&weights)));
            match source.trained_on()? {
                Some(record) => println!(
                    "{}",
                    serde_json::to_string_pretty(&record).expect("a record serialises")
                ),
                None => {
                    eprintln!("{source}: no training record (its heads are trusted everywhere)")
                }
            }
            Ok(())
        }
        Command::Weights(WeightsCommand::Export { from, out }) => {
            let device = select_device()?;
            let model = WeightsSource::from_path(Some(Path::new(&from))).load(&device)?;
            crate::model::export_pytorch_safetensors(&model, &out)?;
            eprintln!("wrote {}", out.display());
            Ok(())
        }
    }
}

/// The union of the records `paths` name: a record's JSON, or weights (`default`, a file) whose
/// own record is taken.
fn combined_records(paths: &[PathBuf]) -> Result<Option<TrainedOn>, CliError> {
    let mut combined: Option<TrainedOn> = None;
    for path in paths {
        let is_json = path.extension().is_some_and(|e| e == "json");
        let record = if is_json {
            let text = std::fs::read_to_string(path).map_err(|e| CliError::io(path, e))?;
            TrainedOn::from_json(&text)
                .map_err(|e| CliError::Input(format!("{}: {e}", path.display())))?
        } else {
            let source = WeightsSource::from_path(Some(path));
            source.trained_on()?.ok_or_else(|| {
                CliError::Input(format!(
                    "--trained-on {source}: these weights record nothing to inherit; give their training record (JSON)"
                ))
            })?
        };
        combined = Some(match combined {
            Some(before) => before.then(&record),
            None => record,
        });
    }
    Ok(combined)
}

/// Decodes an image file with the default limits.
pub(crate) fn read_image(path: &Path) -> Result<crate::imaging::RgbImage32, CliError> {
    Ok(decode_image_file(path, ImageLimits::default())?)
}

/// Decodes a template and its mask: `mask_path` (0 = ignore, anything else = use), or else
/// the template's own alpha channel where it has transparent pixels (transparent = ignore).
pub(crate) fn read_template(
    path: &Path,
    mask_path: Option<&Path>,
) -> Result<(crate::imaging::RgbImage32, Option<TemplateMask>), CliError> {
    let bytes = std::fs::read(path).map_err(|e| CliError::io(path, e))?;
    let what = path.display().to_string();
    let (template, opacity) =
        crate::imaging::decode_image_and_opacity(&bytes, &what, ImageLimits::default())?;
    let mask = match (mask_path, opacity) {
        (Some(mask_path), _) => {
            let mask = TemplateMask::from_image(&read_image(mask_path)?)
                .map_err(|e| CliError::Input(format!("{}: {e}", mask_path.display())))?;
            mask.check_fits(template.width, template.height)
                .map_err(|e| CliError::Input(format!("{}: {e}", mask_path.display())))?;
            Some(mask)
        }
        (None, Some(opaque)) => Some(
            TemplateMask::new(template.width, template.height, opaque)
                .map_err(|e| CliError::Input(format!("{what} (its alpha channel): {e}")))?,
        ),
        (None, None) => None,
    };
    Ok((template, mask))
}
