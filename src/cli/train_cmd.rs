//! `posematch train`: self-supervised training or fine-tuning from folders of unlabeled photos,
//! with a progress bar (loss, throughput), periodic checkpoints and validation tables.

use std::path::PathBuf;
use std::time::Duration;

use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};

use super::CliError;
use crate::evaluation::Summary;
use crate::model::WeightsSource;
use crate::model::select_device;
use crate::synth::Level;
use crate::train::{TrainError, TrainEvent, TrainOptions, train};

#[derive(Args, Debug)]
pub struct TrainArgs {
    /// Folder of training photos (searched recursively); repeat for several folders.
    #[arg(long, required = true)]
    images: Vec<PathBuf>,
    /// Held-out photos for the validation table (never trained on).
    #[arg(long)]
    validation_images: Option<PathBuf>,
    /// Transformation level of the training pairs: S1, S1.5, S2 or S2.5.
    #[arg(long, default_value = "S1.5", value_parser = |s: &str| s.parse::<Level>())]
    level: Level,
    /// Optimizer steps in the whole run.
    #[arg(long)]
    steps: u64,
    /// Pairs per step.
    #[arg(long, default_value_t = 8)]
    batch: usize,
    /// Side of the training search crops (the network is fully convolutional; the paper: 224).
    #[arg(long, default_value_t = 128)]
    search_size: u32,
    /// Peak learning rate (Adam, linear warm-up, cosine decay to 5 %).
    #[arg(long, default_value_t = 1e-3)]
    lr: f64,
    /// Seed of the pair sequence.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Start from these weights (.bpk, .pth or .safetensors) instead of random initialisation;
    /// `default` fine-tunes the weights embedded in this binary (`./default` for a file of
    /// that name).
    #[arg(long)]
    init: Option<PathBuf>,
    /// Continue the run checkpointed at --out.
    #[arg(long)]
    resume: bool,
    /// Weights file to write (burnpack); its optimizer state and progress go beside it.
    #[arg(long)]
    out: PathBuf,
    /// Minutes between checkpoints.
    #[arg(long, default_value_t = 5.0)]
    checkpoint_minutes: f64,
    /// Steps between validation tables (0: only at the end).
    #[arg(long, default_value_t = 500)]
    validate_every: u64,
    /// Held-out pairs per validation table.
    #[arg(long, default_value_t = 100)]
    validation_pairs: u64,
}

pub fn run(args: TrainArgs) -> Result<(), CliError> {
    if !(args.checkpoint_minutes > 0.0 && args.checkpoint_minutes <= 1440.0) {
        return Err(CliError::Usage(format!(
            "--checkpoint-minutes {} must be in (0, 1440]",
            args.checkpoint_minutes
        )));
    }
    let options = TrainOptions {
        images: args.images,
        validation_images: args.validation_images,
        level: args.level,
        steps: args.steps,
        batch: args.batch,
        search_side: args.search_size,
        learning_rate: args.lr,
        seed: args.seed,
        init: args
            .init
            .as_deref()
            .map(|path| WeightsSource::from_path(Some(path))),
        resume: args.resume,
        out: args.out,
        checkpoint_every: Duration::from_secs_f64(args.checkpoint_minutes * 60.0),
        validate_every: args.validate_every,
        validation_pairs: args.validation_pairs,
    };
    let starting_point = match (&options.init, options.resume) {
        (_, true) => format!("resuming {}", options.out.display()),
        (Some(WeightsSource::File(path)), _) => format!("from {}", path.display()),
        (Some(source @ WeightsSource::Embedded), _) => format!("from the {source}"),
        (None, _) => format!("from random weights (seed {})", options.seed),
    };
    let device = select_device()?;
    // Without a terminal (a log file, a container) the bar is hidden; plain lines instead.
    let terminal = std::io::IsTerminal::is_terminal(&std::io::stderr());
    let say = |bar: &ProgressBar, line: String| {
        if terminal {
            bar.println(line);
        } else {
            eprintln!("{line}");
        }
    };
    let bar = ProgressBar::new(options.steps);
    bar.set_style(
        ProgressStyle::with_template(
            "{elapsed_precise} [{bar:30}] {pos}/{len} steps  {msg}  eta {eta}",
        )
        .expect("valid template")
        .progress_chars("=> "),
    );
    let outcome = train(&options, &device, |event| match event {
        TrainEvent::Started {
            first_step, photos, ..
        } => {
            bar.set_position(first_step);
            say(
                &bar,
                format!(
                    "training on {photos} photos from step {first_step} (level {}, batch {}, {}x{} crops), {}",
                    options.level.name(),
                    options.batch,
                    options.search_side,
                    options.search_side,
                    starting_point
                ),
            );
        }
        TrainEvent::Step {
            step,
            loss,
            centre,
            parameters,
            learning_rate,
            pairs_per_s,
        } => {
            bar.set_position(step);
            let status = format!(
                "loss {loss:.3} (centre {centre:.3}, parameters {parameters:.3})  lr {learning_rate:.1e}  {pairs_per_s:.1} pairs/s"
            );
            if !terminal && (step % 50 == 0 || step == options.steps) {
                eprintln!("step {step}/{}: {status}", options.steps);
            }
            bar.set_message(status);
        }
        TrainEvent::Checkpoint { step, path } => {
            say(&bar, format!("step {step}: checkpoint {}", path.display()));
        }
        TrainEvent::Validation {
            step,
            network,
            refined,
        } => {
            say(
                &bar,
                format!("step {step}: validation\n{}", table(&network, &refined)),
            );
        }
    });
    bar.finish();
    let outcome = outcome.map_err(|e| match e {
        TrainError::Options(m) => CliError::Usage(m),
        e @ (TrainError::Photos(_) | TrainError::Weights(_)) => CliError::Input(e.to_string()),
        e @ (TrainError::Checkpoint { .. } | TrainError::Validation(_)) => {
            CliError::Runtime(e.to_string())
        }
    })?;
    eprintln!(
        "{} steps in {:.1} min; loss {:.3} -> {:.3}; weights in {}",
        outcome.steps_done,
        outcome.wall.as_secs_f64() / 60.0,
        outcome.first_loss.unwrap_or(f32::NAN),
        outcome.last_loss.unwrap_or(f32::NAN),
        options.out.display()
    );
    Ok(())
}

fn table(network: &Summary, refined: &Summary) -> String {
    super::eval_cmd::summary_table(&[
        ("network only", network.clone()),
        ("network + refinement", refined.clone()),
    ])
}
