//! Prometheus metrics of one engine. Each engine owns its registry (no process-wide globals), so
//! several servers in one process — the integration tests — count separately.

use prometheus::{
    Encoder, Histogram, HistogramOpts, HistogramVec, IntCounter, IntCounterVec, IntGauge, Opts,
    Registry, TextEncoder,
};

/// Every metric the service exports on `/metrics`.
#[derive(Clone)]
pub struct Metrics {
    registry: Registry,
    /// Finished RPCs by method and gRPC status code name.
    pub requests: IntCounterVec,
    /// Wall time of each RPC, by method.
    pub latency_seconds: HistogramVec,
    /// Search images per forward pass.
    pub batch_size: Histogram,
    /// Wall time of each batch on the model thread (network, peak reading, verification).
    pub batch_seconds: Histogram,
    /// Match requests waiting for the model.
    pub queue_depth: IntGauge,
    /// Match requests dropped unanswered, by reason: `queue_full` (refused), `deadline` (expired
    /// before its batch), `client_gone` (the caller left before or during its batch).
    pub dropped: IntCounterVec,
    /// Model-thread work that panicked (answered INTERNAL; the thread goes on).
    pub model_panics: IntCounter,
    pub cache_hits: IntCounter,
    pub cache_misses: IntCounter,
    pub cache_evictions: IntCounter,
    /// Registered templates.
    pub templates: IntGauge,
    /// Files in the template directory that were not valid templates, moved aside at start.
    pub store_files_set_aside: IntCounter,
    /// Wall time of each template-store operation (`get`, `put`, `list`, …), and the ones that
    /// failed, by operation.
    pub store_seconds: HistogramVec,
    pub store_errors: IntCounterVec,
    /// Template changes announced by other replicas (database store).
    pub store_notifications: IntCounter,
    /// Times the database store's listening connection came back after being lost.
    pub store_reconnects: IntCounter,
    /// 1 while this replica hears other replicas' changes (database store; always 1 for a
    /// directory, which no one else writes).
    pub store_listening: IntGauge,
}

impl Default for Metrics {
    fn default() -> Self {
        Self::new()
    }
}

impl Metrics {
    pub fn new() -> Self {
        let registry = Registry::new();
        let latency_buckets = vec![
            0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.075, 0.1, 0.15, 0.25, 0.5, 1.0, 2.5, 5.0,
            10.0, 30.0,
        ];
        let requests = IntCounterVec::new(
            Opts::new(
                "posematch_requests_total",
                "Finished RPCs by method and status code",
            ),
            &["rpc", "code"],
        )
        .expect("valid metric");
        let latency_seconds = HistogramVec::new(
            HistogramOpts::new("posematch_request_duration_seconds", "RPC wall time")
                .buckets(latency_buckets.clone()),
            &["rpc"],
        )
        .expect("valid metric");
        let batch_size = Histogram::with_opts(
            HistogramOpts::new("posematch_batch_size", "Search images per forward pass")
                .buckets(vec![1.0, 2.0, 3.0, 4.0, 6.0, 8.0, 12.0, 16.0, 32.0]),
        )
        .expect("valid metric");
        let batch_seconds = Histogram::with_opts(
            HistogramOpts::new(
                "posematch_batch_duration_seconds",
                "Model-thread time per batch (network, peak reading, verification)",
            )
            .buckets(latency_buckets),
        )
        .expect("valid metric");
        let queue_depth = IntGauge::new(
            "posematch_queue_depth",
            "Match requests waiting for the model",
        )
        .expect("valid metric");
        let dropped = IntCounterVec::new(
            Opts::new(
                "posematch_dropped_total",
                "Match requests dropped unanswered, by reason (queue_full, deadline, client_gone)",
            ),
            &["reason"],
        )
        .expect("valid metric");
        let model_panics = IntCounter::new(
            "posematch_model_panics_total",
            "Batches or template encodings that panicked on the model thread (each request answered INTERNAL)",
        )
        .expect("valid metric");
        let cache_hits = IntCounter::new(
            "posematch_template_cache_hits_total",
            "Matches whose template kernel was cached",
        )
        .expect("valid metric");
        let cache_misses = IntCounter::new(
            "posematch_template_cache_misses_total",
            "Matches that had to encode their template first",
        )
        .expect("valid metric");
        let cache_evictions = IntCounter::new(
            "posematch_template_cache_evictions_total",
            "Template kernels evicted from the bounded cache (re-encoded from disk when needed)",
        )
        .expect("valid metric");
        let templates =
            IntGauge::new("posematch_templates", "Registered templates").expect("valid metric");
        let store_files_set_aside = IntCounter::new(
            "posematch_store_files_set_aside_total",
            "Files in the template directory that were not valid templates, moved aside at start",
        )
        .expect("valid metric");
        let store_seconds = HistogramVec::new(
            HistogramOpts::new(
                "posematch_store_duration_seconds",
                "Template store operation wall time, by operation",
            )
            .buckets(vec![
                0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 5.0, 10.0,
            ]),
            &["operation"],
        )
        .expect("valid metric");
        let store_errors = IntCounterVec::new(
            Opts::new(
                "posematch_store_errors_total",
                "Template store operations that failed, by operation",
            ),
            &["operation"],
        )
        .expect("valid metric");
        let store_notifications = IntCounter::new(
            "posematch_store_notifications_total",
            "Template changes announced by other replicas through the database",
        )
        .expect("valid metric");
        let store_reconnects = IntCounter::new(
            "posematch_store_reconnects_total",
            "Times the database's change notifications were listened to again after a lost connection (every cached kernel dropped)",
        )
        .expect("valid metric");
        let store_listening = IntGauge::new(
            "posematch_store_listening",
            "1 while this replica hears other replicas' template changes",
        )
        .expect("valid metric");
        store_listening.set(1);
        for collector in [
            Box::new(requests.clone()) as Box<dyn prometheus::core::Collector>,
            Box::new(latency_seconds.clone()),
            Box::new(batch_size.clone()),
            Box::new(batch_seconds.clone()),
            Box::new(queue_depth.clone()),
            Box::new(dropped.clone()),
            Box::new(model_panics.clone()),
            Box::new(cache_hits.clone()),
            Box::new(cache_misses.clone()),
            Box::new(cache_evictions.clone()),
            Box::new(templates.clone()),
            Box::new(store_files_set_aside.clone()),
            Box::new(store_seconds.clone()),
            Box::new(store_errors.clone()),
            Box::new(store_notifications.clone()),
            Box::new(store_reconnects.clone()),
            Box::new(store_listening.clone()),
        ] {
            registry.register(collector).expect("unique metric names");
        }
        Self {
            registry,
            requests,
            latency_seconds,
            batch_size,
            batch_seconds,
            queue_depth,
            dropped,
            model_panics,
            cache_hits,
            cache_misses,
            cache_evictions,
            templates,
            store_files_set_aside,
            store_seconds,
            store_errors,
            store_notifications,
            store_reconnects,
            store_listening,
        }
    }

    /// The Prometheus text exposition of every metric.
    pub fn render(&self) -> String {
        let mut out = Vec::new();
        TextEncoder::new()
            .encode(&self.registry.gather(), &mut out)
            .expect("text encoding into memory cannot fail");
        String::from_utf8(out).expect("the text format is UTF-8")
    }
}
