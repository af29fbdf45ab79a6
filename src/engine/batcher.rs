//! Dynamic batching: one model thread owns the [`Matcher`] and serves a queue.
//!
//! Why a dedicated OS thread and not tokio tasks: a forward pass keeps both cores busy for tens
//! of milliseconds (rayon inside burn and our CPU kernels); on the async runtime it would stall
//! every connection. The thread blocks on the queue; when the model is free it takes whatever
//! is waiting (up to `max_batch_size` searches), drops requests whose client has gone or whose
//! deadline has passed, runs them as one [`Matcher::match_many`] call and routes each answer
//! back through its oneshot channel. Template encodings share the thread (they need the model)
//! and never wait behind the bound: registration must not fail because the line is busy.

use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Instant;

use tokio::sync::{mpsc, oneshot};

use super::metrics::Metrics;
use crate::imaging::RgbImage32;
use crate::matcher::{EncodedTemplate, MatchError, MatchJob, MatchOutcome, Matcher, ValidOptions};

/// One search waiting for the model.
pub struct MatchWork {
    pub template: Arc<EncodedTemplate>,
    pub image: RgbImage32,
    pub options: ValidOptions,
    /// Dropped unanswered once this has passed.
    pub deadline: Option<Instant>,
    pub reply: oneshot::Sender<Result<BatchAnswer, BatchError>>,
}

/// What the model thread sends back for one search.
#[derive(Debug)]
pub struct BatchAnswer {
    pub outcome: MatchOutcome,
    /// Time between submission and the start of its batch.
    pub queue_ms: f64,
    /// Searches in the same forward pass.
    pub batch_size: usize,
}

#[derive(Debug, thiserror::Error)]
pub enum BatchError {
    #[error(transparent)]
    Match(#[from] MatchError),
    #[error("the request's deadline passed while it waited for the model")]
    DeadlineExceeded,
}

enum Work {
    Match(MatchWork, Instant),
    Encode(
        RgbImage32,
        oneshot::Sender<Result<EncodedTemplate, MatchError>>,
    ),
}

/// The queue is full: the caller should retry later (`RESOURCE_EXHAUSTED`).
#[derive(Debug, thiserror::Error)]
#[error("the match queue is full ({0} requests waiting); retry later or add replicas")]
pub struct QueueFull(pub usize);

/// The model thread stopped (the process is shutting down).
#[derive(Debug, thiserror::Error)]
#[error("the model is shutting down")]
pub struct ModelGone;

/// Handle to the model thread; cheap to share. The thread ends when every handle is dropped.
#[derive(Clone)]
pub struct Batcher {
    sender: mpsc::UnboundedSender<Work>,
    waiting: Arc<AtomicUsize>,
    queue_size: usize,
    metrics: Metrics,
}

impl Batcher {
    /// Starts the model thread.
    pub fn spawn(
        matcher: Matcher,
        max_batch_size: usize,
        queue_size: usize,
        metrics: Metrics,
    ) -> Self {
        let (sender, receiver) = mpsc::unbounded_channel();
        let waiting = Arc::new(AtomicUsize::new(0));
        let thread_waiting = waiting.clone();
        let thread_metrics = metrics.clone();
        std::thread::Builder::new()
            .name("posematch-model".into())
            .spawn(move || {
                model_loop(
                    matcher,
                    max_batch_size.max(1),
                    receiver,
                    thread_waiting,
                    thread_metrics,
                )
            })
            .expect("spawning the model thread");
        Self {
            sender,
            waiting,
            queue_size,
            metrics,
        }
    }

    /// Queues a search, or refuses at once when `queue_size` searches already wait.
    pub fn submit(&self, work: MatchWork) -> Result<(), SubmitError> {
        let before = self.waiting.fetch_add(1, Ordering::SeqCst);
        if before >= self.queue_size {
            self.waiting.fetch_sub(1, Ordering::SeqCst);
            self.metrics
                .dropped
                .with_label_values(&["queue_full"])
                .inc();
            return Err(SubmitError::Full(QueueFull(before)));
        }
        self.metrics.queue_depth.set((before + 1) as i64);
        self.sender
            .send(Work::Match(work, Instant::now()))
            .map_err(|_| {
                self.waiting.fetch_sub(1, Ordering::SeqCst);
                SubmitError::Gone(ModelGone)
            })
    }

    /// Encodes a template on the model thread.
    pub async fn encode(&self, image: RgbImage32) -> Result<EncodedTemplate, EncodeError> {
        let (reply, answer) = oneshot::channel();
        self.sender
            .send(Work::Encode(image, reply))
            .map_err(|_| EncodeError::Gone(ModelGone))?;
        answer
            .await
            .map_err(|_| EncodeError::Gone(ModelGone))?
            .map_err(EncodeError::Match)
    }
}

#[derive(Debug, thiserror::Error)]
pub enum SubmitError {
    #[error(transparent)]
    Full(QueueFull),
    #[error(transparent)]
    Gone(ModelGone),
}

#[derive(Debug, thiserror::Error)]
pub enum EncodeError {
    #[error(transparent)]
    Match(MatchError),
    #[error(transparent)]
    Gone(ModelGone),
}

fn model_loop(
    matcher: Matcher,
    max_batch_size: usize,
    mut receiver: mpsc::UnboundedReceiver<Work>,
    waiting: Arc<AtomicUsize>,
    metrics: Metrics,
) {
    let mut batch: Vec<(MatchWork, Instant)> = Vec::with_capacity(max_batch_size);
    while let Some(first) = receiver.blocking_recv() {
        let mut next = Some(first);
        // Take what is already waiting, without waiting for more: a lone request never pays
        // for batching.
        while let Some(work) = next.take() {
            match work {
                Work::Encode(image, reply) => {
                    let _ = reply.send(matcher.encode_template(&image));
                }
                Work::Match(work, queued_at) => {
                    waiting.fetch_sub(1, Ordering::SeqCst);
                    batch.push((work, queued_at));
                }
            }
            if batch.len() < max_batch_size {
                next = receiver.try_recv().ok();
            }
        }
        metrics
            .queue_depth
            .set(waiting.load(Ordering::SeqCst) as i64);
        if batch.is_empty() {
            continue;
        }
        let now = Instant::now();
        let mut live = Vec::with_capacity(batch.len());
        for (work, queued_at) in batch.drain(..) {
            // The deadline first: a client whose deadline passed has usually hung up too, and
            // the reason to count is the deadline.
            if work.deadline.is_some_and(|d| d <= now) {
                metrics.dropped.with_label_values(&["deadline"]).inc();
                let _ = work.reply.send(Err(BatchError::DeadlineExceeded));
            } else if work.reply.is_closed() {
                metrics.dropped.with_label_values(&["client_gone"]).inc();
            } else {
                live.push((work, queued_at));
            }
        }
        if live.is_empty() {
            continue;
        }
        run_batch(&matcher, live, &metrics);
    }
}

fn run_batch(matcher: &Matcher, live: Vec<(MatchWork, Instant)>, metrics: &Metrics) {
    let start = Instant::now();
    let jobs: Vec<MatchJob> = live
        .iter()
        .map(|(work, _)| MatchJob {
            template: &work.template,
            image: &work.image,
            options: &work.options,
        })
        .collect();
    let results = matcher.match_many(&jobs);
    drop(jobs);
    let batch_size = live.len();
    metrics.batch_size.observe(batch_size as f64);
    metrics.batch_seconds.observe(start.elapsed().as_secs_f64());
    tracing::debug!(
        batch_size,
        ms = start.elapsed().as_secs_f64() * 1e3,
        "batch done"
    );
    for ((work, queued_at), result) in live.into_iter().zip(results) {
        let queue_ms = start.duration_since(queued_at).as_secs_f64() * 1e3;
        let answer = result
            .map(|outcome| BatchAnswer {
                outcome,
                queue_ms,
                batch_size,
            })
            .map_err(BatchError::from);
        let _ = work.reply.send(answer);
    }
}
