//! Self-supervised training of the TDCM network from unlabeled photos, as the paper does it:
//! pairs cut by Algorithm 1 (no pasting), structure-aware Gaussian pseudo labels, the paper's
//! losses with equal weights, Adam with warm-up and cosine decay.
//!
//! Why in the library and not only the CLI: a factory adapts the model to its own parts by
//! fine-tuning, and the same loop serves the shipped default weights, the tests' smoke run and
//! the command line. The loop reports through [`TrainEvent`]s; drawing progress is the caller's.
//!
//! Checkpoints are three files next to `out`: the weights (`out`, burnpack, loadable with
//! `--weights`), the optimizer state (`out.optim.bpk`) and the progress (`out.train.json`). Each
//! is written to a temporary name and renamed, so an interrupted run leaves the previous
//! checkpoint intact; `resume` continues from it with the same pair sequence.

mod jitter;
mod labels;
mod loss;

pub use jitter::jitter;
pub use labels::{LabelMaps, SIGMA_FRACTION, VALID_THRESHOLD};
pub use loss::{LabelTensors, Losses, losses};

use std::path::{Path, PathBuf};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use burn::module::Module;
use burn::optim::{AdamConfig, GradientsParams};
use burn::prelude::*;
use rand::SeedableRng;
use rand::rngs::StdRng;
use serde::{Deserialize, Serialize};

use crate::evaluation::{Summary, evaluate_pairs};
use crate::imaging::{InputConvention, RgbImage32, to_network_input};
use crate::matcher::Matcher;
use crate::model::{
    GridEnvelope, TEMPLATE_GRID, Tdcm, TdcmConfig, TrainedOn, WeightsSource, load_weights,
    save_weights,
};
use crate::synth::{
    DEFAULT_MIN_STRUCTURE, Level, PairSpec, PhotoSet, SynthError, SyntheticPair, make_pair,
};

/// Everything a run needs.
#[derive(Debug, Clone)]
pub struct TrainOptions {
    /// Training photos (any folders of ordinary images).
    pub images: Vec<PathBuf>,
    /// Held-out photos for the validation table; never used for training.
    pub validation_images: Option<PathBuf>,
    pub level: Level,
    pub steps: u64,
    pub batch: usize,
    /// Side of the square training search crops (multiple of 4; the paper: 224).
    pub search_side: u32,
    /// Peak learning rate (after warm-up).
    pub learning_rate: f64,
    pub seed: u64,
    /// Start from these weights (fine-tuning); random initialisation when `None`.
    pub init: Option<WeightsSource>,
    /// Continue the run whose checkpoint is at `out`.
    pub resume: bool,
    pub out: PathBuf,
    pub checkpoint_every: Duration,
    /// Validate every this many steps (and at the end); 0 = only at the end.
    pub validate_every: u64,
    pub validation_pairs: u64,
}

/// What the loop tells its caller.
#[derive(Debug, Clone)]
pub enum TrainEvent {
    Started {
        first_step: u64,
        steps: u64,
        photos: usize,
    },
    Step {
        step: u64,
        loss: f32,
        centre: f32,
        parameters: f32,
        learning_rate: f64,
        pairs_per_s: f64,
    },
    Checkpoint {
        step: u64,
        path: PathBuf,
    },
    Validation {
        step: u64,
        network: Summary,
        refined: Summary,
    },
}

/// How a run ended.
#[derive(Debug, Clone)]
pub struct TrainOutcome {
    pub steps_done: u64,
    pub first_loss: Option<f32>,
    pub last_loss: Option<f32>,
    pub validation: Option<(Summary, Summary)>,
    pub wall: Duration,
}

#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    #[error("{0}")]
    Options(String),
    #[error(transparent)]
    Photos(#[from] SynthError),
    #[error("weights: {0}")]
    Weights(#[from] crate::model::LoadError),
    #[error("checkpoint {path}: {message}")]
    Checkpoint { path: PathBuf, message: String },
    #[error("validation: {0}")]
    Validation(#[from] crate::matcher::MatchError),
}

/// Progress stored beside the weights.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
struct Progress {
    step: u64,
    steps: u64,
    seed: u64,
    level: String,
    batch: usize,
    search_side: u32,
    learning_rate: f64,
    /// What the `--init` weights had been trained on (their record), which the weights this
    /// run writes have seen too.
    #[serde(default)]
    inherited: Option<TrainedOn>,
}

impl TrainOptions {
    /// What the weights have seen after `step` steps of this run: its own pairs (square
    /// templates of the grid's size at the level's scales, one part per window) and whatever
    /// the weights it started from had seen.
    fn trained_on(&self, step: u64, inherited: Option<&TrainedOn>) -> TrainedOn {
        let (lo, hi) = self.level.scale_range();
        let level = GridEnvelope {
            grid_scales: [lo, hi],
            aspect_max: hi / lo,
        };
        let this_run = TrainedOn::run(
            level,
            level,
            [TEMPLATE_GRID as u32; 2],
            1,
            self.search_side,
            step * self.batch as u64,
            format!(
                "posematch train: {}, {} of {} steps of {} pairs, search {} px, {}",
                self.level.name(),
                step,
                self.steps,
                self.batch,
                self.search_side,
                match &self.init {
                    Some(init) => format!("from {init}"),
                    None => "from random initialisation".into(),
                }
            ),
        );
        match inherited {
            Some(before) => before.then(&this_run),
            None => this_run,
        }
    }
}

fn checkpoint_paths(out: &Path) -> (PathBuf, PathBuf) {
    let with = |suffix: &str| {
        let mut name = out.as_os_str().to_owned();
        name.push(suffix);
        PathBuf::from(name)
    };
    (with(".optim.bpk"), with(".train.json"))
}

/// Linear warm-up over the first 5 % of the steps (at most 500), then cosine decay to 5 %.
pub fn learning_rate_at(step: u64, steps: u64, peak: f64) -> f64 {
    let warmup = (steps / 20).clamp(1, 500);
    if step < warmup {
        return peak * (step + 1) as f64 / warmup as f64;
    }
    let progress = (step - warmup) as f64 / (steps - warmup).max(1) as f64;
    peak * (0.05 + 0.95 * 0.5 * (1.0 + (std::f64::consts::PI * progress.min(1.0)).cos()))
}

/// One generated batch, ready to become tensors.
struct Batch {
    templates: Vec<RgbImage32>,
    searches: Vec<RgbImage32>,
    labels: Vec<LabelMaps>,
}

/// Pair `index` of the training sequence with jitter applied; depends only on `(seed, index)`.
fn training_example(
    photos: &PhotoSet,
    spec: &PairSpec,
    seed: u64,
    index: u64,
) -> Result<(RgbImage32, RgbImage32, LabelMaps), SynthError> {
    let SyntheticPair {
        template,
        mut search,
        truth,
        ..
    } = make_pair(photos, spec, seed, index)?;
    let mut rng = StdRng::seed_from_u64(seed ^ 0x7A11 ^ index.rotate_left(17));
    jitter(&mut search, &mut rng);
    let labels = LabelMaps::render(
        search.width as usize,
        search.height as usize,
        &truth,
        template.width as f32,
        template.height as f32,
    );
    Ok((template, search, labels))
}

impl TrainOptions {
    fn check(&self) -> Result<(), TrainError> {
        let bad = |m: String| Err(TrainError::Options(m));
        if self.images.is_empty() {
            return bad("give at least one --images folder".into());
        }
        if self.steps == 0 || self.steps > 10_000_000 {
            return bad(format!("--steps {} must be in 1..=10000000", self.steps));
        }
        if !(1..=256).contains(&self.batch) {
            return bad(format!("--batch {} must be in 1..=256", self.batch));
        }
        if !(64..=1024).contains(&self.search_side) || !self.search_side.is_multiple_of(4) {
            return bad(format!(
                "--search-size {} must be a multiple of 4 in 64..=1024",
                self.search_side
            ));
        }
        if !(self.learning_rate > 0.0 && self.learning_rate < 1.0) {
            return bad(format!("--lr {} must be in (0, 1)", self.learning_rate));
        }
        if self.resume && self.init.is_some() {
            return bad("--resume continues from --out; it cannot be combined with --init".into());
        }
        Ok(())
    }
}

/// Runs training; `on_event` sees progress, checkpoints and validation tables.
pub fn train(
    options: &TrainOptions,
    device: &Device,
    mut on_event: impl FnMut(TrainEvent),
) -> Result<TrainOutcome, TrainError> {
    options.check()?;
    // Fail now, not at the first checkpoint, when the output folder cannot be written.
    if let Some(parent) = options.out.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).map_err(|e| TrainError::Checkpoint {
            path: parent.to_owned(),
            message: format!("cannot create the output folder: {e}"),
        })?;
    }
    let started = Instant::now();
    let (optim_path, progress_path) = checkpoint_paths(&options.out);
    let training_device = device.clone().autodiff();
    // Random initialisation follows --seed too, so a run is repeatable.
    training_device.seed(options.seed);

    // Model, optimizer and first step: fresh, fine-tuned from --init, or resumed.
    let mut optimizer = AdamConfig::new().init();
    let (mut model, first_step, inherited): (Tdcm, u64, Option<TrainedOn>) = if options.resume {
        let text = std::fs::read_to_string(&progress_path).map_err(|e| TrainError::Checkpoint {
            path: progress_path.clone(),
            message: format!("cannot resume: {e}"),
        })?;
        let progress: Progress =
            serde_json::from_str(&text).map_err(|e| TrainError::Checkpoint {
                path: progress_path.clone(),
                message: e.to_string(),
            })?;
        if progress.seed != options.seed || progress.level != options.level.name() {
            return Err(TrainError::Options(format!(
                "the checkpoint was trained with seed {} at {}; resume with the same --seed and --level",
                progress.seed, progress.level
            )));
        }
        let model = load_weights(&options.out, &training_device)?;
        optimizer = optimizer
            .load(&optim_path)
            .map_err(|e| TrainError::Checkpoint {
                path: optim_path.clone(),
                message: e.to_string(),
            })?;
        (model, progress.step, progress.inherited)
    } else if let Some(init) = &options.init {
        (init.load(&training_device)?, 0, init.trained_on()?)
    } else {
        (TdcmConfig::new().init(&training_device), 0, None)
    };

    let training_photos = load_photo_folders(&options.images, options.search_side)?;
    let validation = match &options.validation_images {
        Some(dir) => Some(validation_pairs(dir, options)?),
        None => None,
    };
    on_event(TrainEvent::Started {
        first_step,
        steps: options.steps,
        photos: training_photos.len(),
    });

    // Batches are cut on a worker thread while the network trains on the previous one.
    let spec = PairSpec {
        level: options.level,
        template_width: TEMPLATE_GRID as u32,
        template_height: TEMPLATE_GRID as u32,
        search_side: options.search_side,
        min_structure: DEFAULT_MIN_STRUCTURE,
    };
    let (sender, receiver) = mpsc::sync_channel::<Result<Batch, SynthError>>(2);
    let (seed, batch_size, steps) = (options.seed, options.batch, options.steps);
    let producer = std::thread::spawn(move || {
        for step in first_step..steps {
            let mut batch = Batch {
                templates: Vec::with_capacity(batch_size),
                searches: Vec::with_capacity(batch_size),
                labels: Vec::with_capacity(batch_size),
            };
            for k in 0..batch_size as u64 {
                match training_example(&training_photos, &spec, seed, step * batch_size as u64 + k)
                {
                    Ok((template, search, labels)) => {
                        batch.templates.push(template);
                        batch.searches.push(search);
                        batch.labels.push(labels);
                    }
                    Err(e) => {
                        let _ = sender.send(Err(e));
                        return;
                    }
                }
            }
            if sender.send(Ok(batch)).is_err() {
                return; // the trainer stopped
            }
        }
    });

    let convention = InputConvention::ImagenetRgb;
    let (mut first_loss, mut last_loss, mut last_validation) = (None, None, None);
    let mut last_checkpoint = Instant::now();
    let mut window = (Instant::now(), 0u64);
    for step in first_step..options.steps {
        let batch = receiver
            .recv()
            .map_err(|_| TrainError::Options("the pair generator stopped".into()))??;
        let templates = to_network_input(
            &batch.templates.iter().collect::<Vec<_>>(),
            convention,
            &training_device,
        );
        let searches = to_network_input(
            &batch.searches.iter().collect::<Vec<_>>(),
            convention,
            &training_device,
        );
        let labels = LabelTensors::stack(&batch.labels, &training_device);
        let kernels = model.template_encoder.forward(templates);
        let maps = model.search_matcher.forward(searches, kernels).stacked;
        let terms = losses(maps, &labels);
        let scalar = |t: &Tensor<1>| {
            t.clone()
                .into_data()
                .try_to_vec::<f32>()
                .ok()
                .and_then(|v| v.first().copied())
                .unwrap_or(f32::NAN)
        };
        let (loss, centre) = (scalar(&terms.total), scalar(&terms.centre));
        if !loss.is_finite() {
            return Err(TrainError::Options(format!(
                "the loss became {loss} at step {step}; lower --lr"
            )));
        }
        let gradients = GradientsParams::from_grads(terms.total.backward(), &model);
        let learning_rate = learning_rate_at(step, options.steps, options.learning_rate);
        model = optimizer.step(learning_rate, model, gradients);
        first_loss.get_or_insert(loss);
        last_loss = Some(loss);
        window.1 += batch.templates.len() as u64;
        on_event(TrainEvent::Step {
            step: step + 1,
            loss,
            centre,
            parameters: loss - centre,
            learning_rate,
            pairs_per_s: window.1 as f64 / window.0.elapsed().as_secs_f64().max(1e-9),
        });
        if window.0.elapsed() > Duration::from_secs(30) {
            window = (Instant::now(), 0);
        }
        let done = step + 1 == options.steps;
        if done || last_checkpoint.elapsed() >= options.checkpoint_every {
            save_checkpoint(&model, &optimizer, options, step + 1, inherited.as_ref())?;
            last_checkpoint = Instant::now();
            on_event(TrainEvent::Checkpoint {
                step: step + 1,
                path: options.out.clone(),
            });
        }
        let validate_now = options.validate_every > 0 && (step + 1) % options.validate_every == 0;
        if let Some(pairs) = &validation
            && (done || validate_now)
        {
            let (network, refined) = validate(&model, device, pairs)?;
            on_event(TrainEvent::Validation {
                step: step + 1,
                network: network.clone(),
                refined: refined.clone(),
            });
            last_validation = Some((network, refined));
        }
    }
    drop(receiver);
    let _ = producer.join();
    Ok(TrainOutcome {
        steps_done: options.steps - first_step,
        first_loss,
        last_loss,
        validation: last_validation,
        wall: started.elapsed(),
    })
}

fn load_photo_folders(dirs: &[PathBuf], min_side: u32) -> Result<PhotoSet, TrainError> {
    let mut sets = dirs
        .iter()
        .map(|dir| PhotoSet::load(dir, min_side))
        .collect::<Result<Vec<_>, _>>()?;
    let mut all = sets.remove(0);
    for set in sets {
        all.extend(set);
    }
    Ok(all)
}

/// The fixed held-out set: paper-sized pairs (224x224, 36x36) from the validation photos.
fn validation_pairs(dir: &Path, options: &TrainOptions) -> Result<Vec<SyntheticPair>, TrainError> {
    let photos = PhotoSet::load(dir, 224)?;
    let spec = PairSpec {
        level: options.level,
        template_width: 36,
        template_height: 36,
        search_side: 224,
        min_structure: DEFAULT_MIN_STRUCTURE,
    };
    (0..options.validation_pairs)
        .map(|i| make_pair(&photos, &spec, 0x5EED_0FF5, i).map_err(TrainError::from))
        .collect()
}

/// The paper's table for the current weights on the validation pairs.
fn validate(
    model: &Tdcm,
    device: &Device,
    pairs: &[SyntheticPair],
) -> Result<(Summary, Summary), TrainError> {
    let matcher = Matcher::new(model.valid(), device.clone(), InputConvention::ImagenetRgb);
    Ok(evaluate_pairs(&matcher, pairs)?)
}

fn save_checkpoint(
    model: &Tdcm,
    optimizer: &burn::optim::ModuleOptimizer,
    options: &TrainOptions,
    step: u64,
    inherited: Option<&TrainedOn>,
) -> Result<(), TrainError> {
    let (optim_path, progress_path) = checkpoint_paths(&options.out);
    let failed = |path: &Path, message: String| TrainError::Checkpoint {
        path: path.to_owned(),
        message,
    };
    let temporary = |path: &Path| {
        let mut name = path.as_os_str().to_owned();
        name.push(".tmp");
        PathBuf::from(name)
    };
    let weights_tmp = temporary(&options.out);
    save_weights(
        &model.valid(),
        Some(&options.trained_on(step, inherited)),
        &weights_tmp,
    )?;
    let optim_tmp = temporary(&optim_path);
    optimizer
        .save(&optim_tmp)
        .map_err(|e| failed(&optim_path, e.to_string()))?;
    let progress = Progress {
        step,
        steps: options.steps,
        seed: options.seed,
        level: options.level.name().into(),
        batch: options.batch,
        search_side: options.search_side,
        learning_rate: options.learning_rate,
        inherited: inherited.cloned(),
    };
    let progress_tmp = temporary(&progress_path);
    std::fs::write(
        &progress_tmp,
        serde_json::to_string_pretty(&progress).expect("progress serialises"),
    )
    .map_err(|e| failed(&progress_path, e.to_string()))?;
    // Weights and optimizer first, the progress file last: it names the step they belong to.
    for (from, to) in [
        (&weights_tmp, &options.out),
        (&optim_tmp, &optim_path),
        (&progress_tmp, &progress_path),
    ] {
        std::fs::rename(from, to).map_err(|e| failed(to, e.to_string()))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn learning_rate_warms_up_then_decays() {
        let peak = 1e-3;
        assert!(learning_rate_at(0, 1000, peak) < peak / 10.0);
        assert!((learning_rate_at(49, 1000, peak) - peak).abs() < 1e-12);
        assert!(learning_rate_at(500, 1000, peak) < peak);
        assert!((learning_rate_at(999, 1000, peak) - 0.05 * peak).abs() < 1e-5);
    }
}
