//! Dynamic batching: one model thread owns the network and runs the match pipeline on it (the
//! [`Matcher`]; anything that is a [`MatchPipeline`]), serving two queues.
//!
//! Why a dedicated OS thread and not tokio tasks: a forward pass keeps both cores busy for tens
//! of milliseconds (rayon inside burn and our CPU implementation); on the async runtime it would stall
//! every connection. The thread blocks on the queue; when the model is free it takes whatever
//! is waiting (up to `max_batch_size` searches), drops requests whose client has gone or whose
//! deadline has passed, runs them as one [`Matcher::match_many`] call and routes each answer
//! back through its oneshot channel. Template encodings share the thread (they need the model)
//! and never wait behind the bound: registration must not fail because the line is busy.
//!
//! The thread is an actor that cannot die silently (TEI's queue is the model): a panic inside a
//! batch or an encoding answers that work's callers with an internal error, is logged and
//! counted, and the thread takes the next work; should the thread end anyway, [`Batcher::alive`]
//! turns false and the service reports NOT_SERVING. Each search carries its request's tracing
//! span, so the batch that ran it is linked to the request in traces and logs.

use std::panic::{AssertUnwindSafe, catch_unwind};
use std::sync::Arc;
use std::time::{Duration, Instant};

use crossbeam_channel::{Receiver, Sender, TrySendError, select};
use tokio::sync::{oneshot, watch};

use super::metrics::Metrics;
use crate::imaging::RgbImage32;
use crate::matcher::{
    EncodedTemplate, MatchError, MatchJob, MatchOutcome, Matcher, TemplateMask, ValidOptions,
};

/// What the model thread runs: the [`Matcher`] in production, a fake in the unit tests (which
/// gate it to see exactly how work is batched).
pub trait MatchPipeline: Send + 'static {
    fn encode_template(
        &self,
        image: &RgbImage32,
        mask: Option<&TemplateMask>,
    ) -> Result<EncodedTemplate, MatchError>;
    /// Runs `jobs` as one batch. `still_wanted(i)` tells whether job `i`'s caller still waits;
    /// a pipeline may skip the rest of an unwanted job's work and answer `None` for it.
    fn match_many(
        &self,
        jobs: &[MatchJob],
        still_wanted: &dyn Fn(usize) -> bool,
    ) -> Vec<Option<Result<MatchOutcome, MatchError>>>;
    /// No work has come for a while ([`IDLE_RELEASE`]): a pipeline may free what it keeps
    /// between batches.
    fn idle(&self) {}
}

/// How long the model thread waits without work before the model frees the activation buffers
/// it keeps between batches (so a line sending frames back to back reuses them, and an idle
/// replica holds no activations).
pub const IDLE_RELEASE: Duration = Duration::from_secs(1);

/// How the model thread batches its work.
#[derive(Debug, Clone, Copy)]
pub struct BatchLimits {
    /// Most searches in one batch.
    pub max_batch_size: usize,
    /// Most searches waiting; more are refused at once.
    pub queue_size: usize,
    /// Quiet time after which the pipeline hears that it is idle ([`IDLE_RELEASE`]).
    pub idle_release: Duration,
}

impl MatchPipeline for Matcher {
    fn encode_template(
        &self,
        image: &RgbImage32,
        mask: Option<&TemplateMask>,
    ) -> Result<EncodedTemplate, MatchError> {
        Matcher::encode_masked_template(self, image, mask)
    }

    fn match_many(
        &self,
        jobs: &[MatchJob],
        still_wanted: &dyn Fn(usize) -> bool,
    ) -> Vec<Option<Result<MatchOutcome, MatchError>>> {
        Matcher::match_many_wanted(self, jobs, still_wanted)
    }

    fn idle(&self) {
        self.network().release_buffers();
    }
}

/// One search waiting for the model.
pub struct MatchWork {
    pub template: Arc<EncodedTemplate>,
    /// Shared by the searches of one request for several templates.
    pub image: Arc<RgbImage32>,
    pub options: ValidOptions,
    /// Dropped unanswered once this has passed.
    pub deadline: Option<Instant>,
    /// Answered with what the search has by then ([`MatchJob::answer_by`]).
    pub answer_by: Option<Instant>,
    pub reply: oneshot::Sender<Result<BatchAnswer, BatchError>>,
    /// The request's span: the batch that runs this search follows from it.
    pub span: tracing::Span,
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
    /// The model panicked on this search's batch (a bug of ours, logged on the server).
    #[error(
        "the model failed on this request's batch (an internal error, logged on the server); retrying may succeed"
    )]
    ModelFailed,
}

/// A template to encode and where its encoding goes.
type EncodeWork = (
    RgbImage32,
    Option<TemplateMask>,
    oneshot::Sender<Result<EncodedTemplate, EncodeError>>,
);

/// The queue is full: the caller should retry later (`RESOURCE_EXHAUSTED`).
#[derive(Debug, thiserror::Error)]
#[error("the match queue is full ({0} requests waiting); retry later or add replicas")]
pub struct QueueFull(pub usize);

/// The model thread stopped (the process is shutting down).
#[derive(Debug, thiserror::Error)]
#[error("the model is shutting down")]
pub struct ModelGone;

/// Handle to the model thread; cheap to share. The thread ends when every handle is dropped.
///
/// Two queues: searches wait in a bounded one (a full queue refuses at once), template
/// encodings in an unbounded one, so that a registration never fails because the line is busy
/// (encodings come one per registration or cache miss, and each caller waits for its own). The
/// thread takes from both fairly ([`Queues::next`]).
#[derive(Clone)]
pub struct Batcher {
    searches: Sender<(MatchWork, Instant)>,
    encodings: Sender<EncodeWork>,
    queue_size: usize,
    metrics: Metrics,
    alive: watch::Receiver<bool>,
}

impl Batcher {
    /// Starts the model thread.
    pub fn spawn(pipeline: impl MatchPipeline, limits: BatchLimits, metrics: Metrics) -> Self {
        let queue_size = limits.queue_size.max(1);
        let (searches, search_queue) = crossbeam_channel::bounded(queue_size);
        let (encodings, encode_queue) = crossbeam_channel::unbounded();
        let thread_metrics = metrics.clone();
        let (alive_tx, alive) = watch::channel(true);
        std::thread::Builder::new()
            .name("posematch-model".into())
            .spawn(move || {
                // Whichever way the thread ends, its watchers learn of it.
                let _alive = AliveWhileHeld(alive_tx);
                run_model_thread(
                    pipeline,
                    limits,
                    Queues {
                        searches: search_queue,
                        encodings: encode_queue,
                    },
                    thread_metrics,
                )
            })
            .expect("spawning the model thread");
        Self {
            searches,
            encodings,
            queue_size,
            metrics,
            alive,
        }
    }

    /// True while the model thread runs; false once it has ended (shutdown, or a failure
    /// outside any batch), after which no work is answered.
    pub fn alive(&self) -> watch::Receiver<bool> {
        self.alive.clone()
    }

    /// Refuses at once when `queue_size` searches already wait, before the caller spends
    /// memory on decoding a request that [`Batcher::submit`] would refuse anyway.
    pub fn check_room(&self) -> Result<(), QueueFull> {
        let waiting = self.searches.len();
        if waiting >= self.queue_size {
            self.metrics
                .dropped
                .with_label_values(&["queue_full"])
                .inc();
            return Err(QueueFull(waiting));
        }
        Ok(())
    }

    /// Queues a search, or refuses at once when `queue_size` searches already wait.
    pub fn submit(&self, work: MatchWork) -> Result<(), SubmitError> {
        match self.searches.try_send((work, Instant::now())) {
            Ok(()) => {
                self.metrics.queue_depth.set(self.searches.len() as i64);
                Ok(())
            }
            Err(TrySendError::Full(_)) => {
                self.metrics
                    .dropped
                    .with_label_values(&["queue_full"])
                    .inc();
                Err(SubmitError::Full(QueueFull(self.queue_size)))
            }
            Err(TrySendError::Disconnected(_)) => Err(SubmitError::Gone(ModelGone)),
        }
    }

    /// Encodes a template (and its mask) on the model thread.
    pub async fn encode(
        &self,
        image: RgbImage32,
        mask: Option<TemplateMask>,
    ) -> Result<EncodedTemplate, EncodeError> {
        let (reply, answer) = oneshot::channel();
        self.encodings
            .send((image, mask, reply))
            .map_err(|_| EncodeError::Gone(ModelGone))?;
        answer.await.map_err(|_| EncodeError::Gone(ModelGone))?
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
    /// The model panicked while encoding (a bug of ours, logged on the server).
    #[error(
        "the model failed to encode the template (an internal error, logged on the server); retrying may succeed"
    )]
    ModelFailed,
}

/// Sends `false` when dropped: held by the model thread for its whole life.
struct AliveWhileHeld(watch::Sender<bool>);

impl Drop for AliveWhileHeld {
    fn drop(&mut self) {
        self.0.send_replace(false);
    }
}

/// Runs `work` on the model thread; a panic becomes `None`, logged (its message; the panic
/// hook prints where) and counted, so that the thread goes on with the next work.
fn unless_panicked<T>(what: &str, metrics: &Metrics, work: impl FnOnce() -> T) -> Option<T> {
    match catch_unwind(AssertUnwindSafe(work)) {
        Ok(value) => Some(value),
        Err(payload) => {
            let message = payload
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| payload.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "a non-text panic payload".into());
            metrics.model_panics.inc();
            tracing::error!(%message, "the model panicked on {what}; answering INTERNAL and going on");
            None
        }
    }
}

/// The model thread's ends of the two queues.
struct Queues {
    searches: Receiver<(MatchWork, Instant)>,
    encodings: Receiver<EncodeWork>,
}

/// The next work; `None` once every [`Batcher`] handle is gone.
enum Next {
    Search(MatchWork, Instant),
    Encode(EncodeWork),
}

impl Queues {
    /// Blocks for the next work, telling the pipeline once when it has been idle for
    /// `idle_release`. When both queues hold work either may come first (`select!` picks at
    /// random), so a stream of registrations cannot starve the searches, nor the reverse.
    fn next(&self, pipeline: &impl MatchPipeline, idle_release: Duration) -> Option<Next> {
        let waited = select! {
            recv(self.encodings) -> work => Some(work.ok().map(Next::Encode)),
            recv(self.searches) -> work => Some(work.ok().map(|(w, t)| Next::Search(w, t))),
            default(idle_release) => None,
        };
        if let Some(next) = waited {
            return next.or_else(|| self.next_when_one_closed());
        }
        pipeline.idle();
        select! {
            recv(self.encodings) -> work => work.ok().map(Next::Encode),
            recv(self.searches) -> work => work.ok().map(|(w, t)| Next::Search(w, t)),
        }
        .or_else(|| self.next_when_one_closed())
    }

    /// Both senders live in every [`Batcher`] and drop together, so one closed queue means the
    /// other is closing too; whatever it still holds is answered first.
    fn next_when_one_closed(&self) -> Option<Next> {
        self.encodings
            .try_recv()
            .map(Next::Encode)
            .or_else(|_| self.searches.try_recv().map(|(w, t)| Next::Search(w, t)))
            .ok()
    }

    /// Work already waiting, without blocking: encodings first while no search has joined the
    /// batch, then searches only (a batch that has begun does not wait behind encodings).
    fn waiting(&self, batch_started: bool) -> Option<Next> {
        let search = || self.searches.try_recv().map(|(w, t)| Next::Search(w, t));
        if batch_started {
            search().ok()
        } else {
            self.encodings
                .try_recv()
                .map(Next::Encode)
                .or_else(|_| search())
                .ok()
        }
    }
}

fn run_model_thread(
    pipeline: impl MatchPipeline,
    limits: BatchLimits,
    queues: Queues,
    metrics: Metrics,
) {
    let max_batch_size = limits.max_batch_size.max(1);
    let mut batch: Vec<(MatchWork, Instant)> = Vec::with_capacity(max_batch_size);
    while let Some(first) = queues.next(&pipeline, limits.idle_release) {
        let mut next = Some(first);
        // Take what is already waiting, without waiting for more: a lone request never pays
        // for batching.
        while let Some(work) = next.take() {
            match work {
                Next::Encode((image, mask, reply)) => {
                    let encoded = unless_panicked("a template", &metrics, || {
                        pipeline.encode_template(&image, mask.as_ref())
                    })
                    .ok_or(EncodeError::ModelFailed)
                    .and_then(|r| r.map_err(EncodeError::Match));
                    let _ = reply.send(encoded);
                }
                Next::Search(work, queued_at) => batch.push((work, queued_at)),
            }
            if batch.len() < max_batch_size {
                next = queues.waiting(!batch.is_empty());
            }
        }
        metrics.queue_depth.set(queues.searches.len() as i64);
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
        run_batch(&pipeline, live, &metrics);
    }
}

fn run_batch(pipeline: &impl MatchPipeline, live: Vec<(MatchWork, Instant)>, metrics: &Metrics) {
    let start = Instant::now();
    let batch_size = live.len();
    let span = tracing::info_span!("batch", batch_size);
    for (work, _) in &live {
        span.follows_from(&work.span);
    }
    let _in_batch = span.enter();
    let jobs: Vec<MatchJob> = live
        .iter()
        .map(|(work, _)| MatchJob {
            template: &work.template,
            image: work.image.as_ref(),
            options: &work.options,
            answer_by: work.answer_by,
        })
        .collect();
    // A client that leaves while the network runs spares its job's verification.
    let still_wanted = |i: usize| !live[i].0.reply.is_closed();
    let results = unless_panicked("a batch", metrics, || {
        pipeline.match_many(&jobs, &still_wanted)
    });
    drop(jobs);
    metrics.batch_size.observe(batch_size as f64);
    metrics.batch_seconds.observe(start.elapsed().as_secs_f64());
    tracing::debug!(ms = start.elapsed().as_secs_f64() * 1e3, "batch done");
    let Some(results) = results else {
        for (work, _) in live {
            let _ = work.reply.send(Err(BatchError::ModelFailed));
        }
        return;
    };
    for ((work, queued_at), result) in live.into_iter().zip(results) {
        let Some(result) = result else {
            metrics.dropped.with_label_values(&["client_gone"]).inc();
            continue;
        };
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

#[cfg(test)]
mod tests {
    //! The model runs on its own OS thread, so these tests hold it with a gate instead of a
    //! clock: the fake model announces each batch and waits for the test to release it, and
    //! the test queues work while it is held. No sleep stands in for synchronisation.

    use std::sync::Mutex;
    use std::sync::mpsc::{Receiver, Sender, channel};
    use std::time::Duration;

    use burn::prelude::*;

    use super::*;
    use crate::geometry::Pose;
    use crate::imaging::GrayImage32;

    /// Answers each job with one pose whose `x` is the job's image width, so a test can tell
    /// which answer went where.
    struct GatedPipeline {
        started: Sender<usize>,
        release: Mutex<Receiver<()>>,
        /// One message each time the model thread reports it idle.
        idles: Sender<()>,
    }

    /// An image this wide makes the fake model panic (a bug in the model).
    const PANICS: u32 = 13;

    impl MatchPipeline for GatedPipeline {
        fn encode_template(
            &self,
            image: &RgbImage32,
            _mask: Option<&TemplateMask>,
        ) -> Result<EncodedTemplate, MatchError> {
            assert_ne!(image.width, PANICS, "a bug in the encoder");
            Ok(template(image.width))
        }

        fn match_many(
            &self,
            jobs: &[MatchJob],
            still_wanted: &dyn Fn(usize) -> bool,
        ) -> Vec<Option<Result<MatchOutcome, MatchError>>> {
            self.started.send(jobs.len()).unwrap();
            self.release.lock().unwrap().recv().unwrap();
            assert!(
                jobs.iter().all(|job| job.image.width != PANICS),
                "a bug in the model"
            );
            jobs.iter()
                .enumerate()
                .map(|(i, job)| {
                    still_wanted(i).then(|| {
                        Ok(MatchOutcome {
                            poses: vec![Pose {
                                x: job.image.width as f32,
                                y: 0.0,
                                angle_deg: 0.0,
                                scale_x: 1.0,
                                scale_y: 1.0,
                                score: 1.0,
                                network_score: 1.0,
                            }],
                            timings: Default::default(),
                            timed_out: false,
                        })
                    })
                })
                .collect()
        }

        fn idle(&self) {
            let _ = self.idles.send(());
        }
    }

    fn template(width: u32) -> EncodedTemplate {
        EncodedTemplate {
            width,
            height: 8,
            kernel: Tensor::zeros([1, 96, 9, 9], &Device::flex()),
            gray: Arc::new(GrayImage32::from_rgb(&image(8))),
            reversed_kernel: Tensor::zeros([1, 96, 9, 9], &Device::flex()),
            reversed_gray: Arc::new(GrayImage32::from_rgb(&image(8))),
            origin: None,
        }
    }

    fn image(width: u32) -> RgbImage32 {
        RgbImage32::new(width, 8, vec![0.5; width as usize * 8 * 3])
    }

    struct Harness {
        batcher: Batcher,
        metrics: Metrics,
        /// Sizes of batches as the model starts them.
        started: Receiver<usize>,
        release: Sender<()>,
        template: Arc<EncodedTemplate>,
        idles: Receiver<()>,
    }

    /// The quiet time after which the test model hears it is idle: short, so that the test
    /// of idleness waits a fraction of a second, not [`IDLE_RELEASE`].
    const TEST_IDLE_RELEASE: Duration = Duration::from_millis(50);

    type Answer = oneshot::Receiver<Result<BatchAnswer, BatchError>>;

    impl Harness {
        fn new(max_batch_size: usize, queue_size: usize) -> Self {
            let (started_tx, started) = channel();
            let (release, release_rx) = channel();
            let metrics = Metrics::new();
            let (idles_tx, idles) = channel();
            let pipeline = GatedPipeline {
                started: started_tx,
                release: Mutex::new(release_rx),
                idles: idles_tx,
            };
            let limits = BatchLimits {
                max_batch_size,
                queue_size,
                idle_release: TEST_IDLE_RELEASE,
            };
            let batcher = Batcher::spawn(pipeline, limits, metrics.clone());
            Self {
                batcher,
                metrics,
                started,
                release,
                template: Arc::new(template(8)),
                idles,
            }
        }

        fn submit(&self, width: u32, deadline: Option<Instant>) -> Result<Answer, SubmitError> {
            let (reply, answer) = oneshot::channel();
            self.batcher
                .submit(MatchWork {
                    template: self.template.clone(),
                    image: Arc::new(image(width)),
                    options: ValidOptions::default(),
                    deadline,
                    answer_by: None,
                    reply,
                    span: tracing::Span::none(),
                })
                .map(|()| answer)
        }

        /// Waits until the model starts a batch; its size.
        fn next_batch(&self) -> usize {
            self.started
                .recv_timeout(Duration::from_secs(30))
                .expect("the model thread started a batch")
        }

        fn release_batch(&self) {
            self.release.send(()).unwrap();
        }

        fn dropped(&self, reason: &str) -> u64 {
            self.metrics.dropped.with_label_values(&[reason]).get()
        }
    }

    fn answer(answer: Answer) -> BatchAnswer {
        answer
            .blocking_recv()
            .expect("the model thread answered")
            .expect("a successful answer")
    }

    #[test]
    fn the_model_hears_of_idleness_once_per_quiet_period_and_never_while_busy() {
        let h = Harness::new(2, 10);
        // The thread starts idle: one report, then none until work has come and gone.
        h.idles
            .recv_timeout(Duration::from_secs(30))
            .expect("an idle report before any work");
        let first = h.submit(100, None).unwrap();
        assert_eq!(h.next_batch(), 1);
        // Busy for many idle periods: a batch in progress is not idleness. (This sleep lets
        // time pass on purpose; nothing waits for it.)
        std::thread::sleep(TEST_IDLE_RELEASE * 4);
        assert!(h.idles.try_recv().is_err(), "idle reported while busy");
        let released = Instant::now();
        h.release_batch();
        assert_eq!(answer(first).outcome.poses[0].x, 100.0);
        h.idles
            .recv_timeout(Duration::from_secs(30))
            .expect("an idle report after a quiet period");
        assert!(
            released.elapsed() >= TEST_IDLE_RELEASE,
            "idle reported {:?} after the work, before a quiet period",
            released.elapsed()
        );
        // One quiet stretch is reported once, however long it lasts.
        std::thread::sleep(TEST_IDLE_RELEASE * 4);
        assert!(
            h.idles.try_recv().is_err(),
            "a quiet stretch reported twice"
        );
        // Work after idleness is served as before.
        let second = h.submit(101, None).unwrap();
        assert_eq!(h.next_batch(), 1);
        h.release_batch();
        assert_eq!(answer(second).outcome.poses[0].x, 101.0);
    }

    #[test]
    fn waiting_work_is_batched_up_to_the_limit_and_each_answer_reaches_its_caller() {
        let h = Harness::new(3, 10);
        let first = h.submit(100, None).unwrap();
        assert_eq!(
            h.next_batch(),
            1,
            "a lone request does not wait for company"
        );
        let queued: Vec<Answer> = (101..105).map(|w| h.submit(w, None).unwrap()).collect();
        h.release_batch();
        assert_eq!(
            h.next_batch(),
            3,
            "what waits is taken, up to max_batch_size"
        );
        h.release_batch();
        assert_eq!(h.next_batch(), 1);
        h.release_batch();
        let first = answer(first);
        assert_eq!((first.batch_size, first.outcome.poses[0].x), (1, 100.0));
        let sizes_and_widths: Vec<(usize, f32)> = queued
            .into_iter()
            .map(|a| {
                let a = answer(a);
                (a.batch_size, a.outcome.poses[0].x)
            })
            .collect();
        assert_eq!(
            sizes_and_widths,
            vec![(3, 101.0), (3, 102.0), (3, 103.0), (1, 104.0)]
        );
    }

    #[test]
    fn a_full_queue_refuses_at_once_and_counts_it() {
        let h = Harness::new(1, 2);
        let running = h.submit(100, None).unwrap();
        assert_eq!(h.next_batch(), 1);
        // The running request has left the queue; two more fit, the third does not.
        let waiting = [h.submit(101, None).unwrap(), h.submit(102, None).unwrap()];
        match h.submit(103, None) {
            Err(SubmitError::Full(QueueFull(2))) => {}
            other => panic!("expected a full queue, got {:?}", other.map(|_| ())),
        }
        assert_eq!(h.dropped("queue_full"), 1);
        assert_eq!(h.metrics.queue_depth.get(), 2);
        for _ in 0..3 {
            h.release_batch();
        }
        assert_eq!((h.next_batch(), h.next_batch()), (1, 1));
        answer(running);
        for a in waiting {
            answer(a);
        }
    }

    #[test]
    fn expired_and_abandoned_work_never_reaches_the_model_and_is_counted_by_reason() {
        let h = Harness::new(8, 10);
        let running = h.submit(100, None).unwrap();
        assert_eq!(h.next_batch(), 1);
        let expired = h.submit(101, Some(Instant::now())).unwrap();
        let abandoned = h.submit(102, None).unwrap();
        drop(abandoned);
        let live = h.submit(103, None).unwrap();
        h.release_batch();
        assert_eq!(h.next_batch(), 1, "only the live request is run");
        h.release_batch();
        answer(running);
        assert_eq!(answer(live).outcome.poses[0].x, 103.0);
        assert!(matches!(
            expired.blocking_recv().unwrap(),
            Err(BatchError::DeadlineExceeded)
        ));
        assert_eq!((h.dropped("deadline"), h.dropped("client_gone")), (1, 1));
    }

    #[test]
    fn a_client_that_leaves_during_its_batch_is_not_answered_and_is_counted() {
        let h = Harness::new(8, 10);
        let leaving = h.submit(100, None).unwrap();
        assert_eq!(h.next_batch(), 1);
        drop(leaving);
        h.release_batch();
        let after = h.submit(101, None).unwrap();
        assert_eq!(h.next_batch(), 1);
        h.release_batch();
        answer(after);
        assert_eq!(h.dropped("client_gone"), 1);
    }

    #[test]
    fn template_encodings_are_not_refused_by_a_full_match_queue() {
        let h = Harness::new(1, 1);
        let running = h.submit(100, None).unwrap();
        assert_eq!(h.next_batch(), 1);
        let waiting = h.submit(101, None).unwrap();
        assert!(matches!(h.submit(102, None), Err(SubmitError::Full(_))));
        let batcher = h.batcher.clone();
        let encoding = std::thread::spawn(move || {
            tokio::runtime::Builder::new_current_thread()
                .build()
                .unwrap()
                .block_on(batcher.encode(image(77), None))
        });
        h.release_batch();
        h.release_batch();
        assert_eq!(h.next_batch(), 1);
        let encoded = encoding
            .join()
            .unwrap()
            .expect("encoded while the queue was full");
        assert_eq!(encoded.width, 77);
        answer(running);
        answer(waiting);
    }

    fn encode(batcher: &Batcher, width: u32) -> Result<EncodedTemplate, EncodeError> {
        tokio::runtime::Builder::new_current_thread()
            .build()
            .unwrap()
            .block_on(batcher.encode(image(width), None))
    }

    #[test]
    fn a_panic_answers_its_own_batch_with_an_internal_error_and_the_thread_goes_on() {
        let h = Harness::new(4, 10);
        let alive = h.batcher.alive();
        let doomed = h.submit(PANICS, None).unwrap();
        assert_eq!(h.next_batch(), 1);
        h.release_batch();
        assert!(matches!(
            doomed.blocking_recv().expect("answered, not dropped"),
            Err(BatchError::ModelFailed)
        ));
        assert!(matches!(
            encode(&h.batcher, PANICS),
            Err(EncodeError::ModelFailed)
        ));
        assert_eq!(h.metrics.model_panics.get(), 2);

        let next = h.submit(100, None).unwrap();
        assert_eq!(h.next_batch(), 1);
        h.release_batch();
        assert_eq!(answer(next).outcome.poses[0].x, 100.0);
        assert_eq!(encode(&h.batcher, 77).unwrap().width, 77);
        assert!(*alive.borrow(), "the model thread still runs");
    }

    #[test]
    fn watchers_learn_when_the_model_thread_ends() {
        let h = Harness::new(1, 1);
        let mut alive = h.batcher.alive();
        assert!(*alive.borrow());
        drop(h); // every handle gone: the thread ends
        let ended = tokio::runtime::Builder::new_current_thread()
            .enable_time()
            .build()
            .unwrap()
            .block_on(async {
                tokio::time::timeout(Duration::from_secs(30), alive.wait_for(|a| !*a))
                    .await
                    .map(|r| r.map(|a| *a))
            });
        assert!(matches!(ended, Ok(Ok(false))), "{ended:?}");
    }
}
