//! The gRPC service (`posematch.v1.PoseMatcher`) plus standard health and reflection, and the
//! Prometheus endpoint. This layer converts messages ([`convert`]) and records metrics and
//! traces; the work itself is the [`Engine`]'s.
//!
//! Start-up order matters to orchestrators: the ports are bound first and health reports
//! NOT_SERVING while the model loads; it turns SERVING only once the engine can answer.

mod api;
pub mod convert;
pub mod security;

use std::net::SocketAddr;
use std::sync::{Arc, OnceLock};
use std::time::Duration;

use tokio::net::TcpListener;
use tokio::sync::watch;
use tokio_stream::wrappers::TcpListenerStream;

use crate::config::Settings;
use crate::engine::store::{StoreError, StoreLocation, TemplateStore};
use crate::engine::{Engine, EngineConfig, Metrics};
use crate::matcher::Matcher;
pub use security::AccessTokens;

/// Generated messages and service traits of `proto/posematch/v1/posematch.proto`.
pub mod proto {
    #![allow(clippy::all, missing_docs)]
    tonic::include_proto!("posematch.v1");
    /// Encoded descriptors of the API, served by reflection.
    pub const FILE_DESCRIPTOR_SET: &[u8] =
        tonic::include_file_descriptor_set!("posematch_descriptor");
}

/// The health service name a liveness probe asks: SERVING while the process makes progress
/// (from the start; NOT_SERVING only once the model thread has ended), where the whole server's
/// status (`""`, for readiness) also needs the model loaded and the template store working. A
/// database outage takes replicas out of rotation without restarting them.
pub const LIVENESS_SERVICE: &str = "liveness";

/// Builds the model; runs on a blocking thread after the ports are bound.
pub type ModelLoader = Box<dyn FnOnce() -> Result<Matcher, String> + Send>;

#[derive(Debug, thiserror::Error)]
pub enum ServeError {
    #[error("cannot listen on {addr}: {source}")]
    Bind {
        addr: String,
        #[source]
        source: std::io::Error,
    },
    /// A TLS or token file cannot be used.
    #[error(transparent)]
    Security(#[from] security::SecurityFileError),
    #[error("{0}")]
    Setup(String),
}

/// A started server: its bound addresses and the way to stop it.
pub struct RunningServer {
    pub grpc_addr: SocketAddr,
    /// `None` when the metrics endpoint is disabled.
    pub metrics_addr: Option<SocketAddr>,
    shutdown: watch::Sender<bool>,
    grpc: tokio::task::JoinHandle<Result<(), tonic::transport::Error>>,
    ready: watch::Receiver<Option<Result<(), String>>>,
    tokens: Option<AccessTokens>,
}

impl RunningServer {
    /// Binds the ports, starts serving (NOT_SERVING until the model is loaded) and loads the
    /// model in the background.
    pub async fn start(settings: &Settings, loader: ModelLoader) -> Result<Self, ServeError> {
        // Security files first: a wrong path fails the start, not the first client.
        let security = &settings.security;
        let tls = security
            .tls
            .as_ref()
            .map(security::tls_config)
            .transpose()?;
        let tokens = security
            .auth_tokens_file
            .as_deref()
            .map(AccessTokens::load)
            .transpose()?;
        let server = &settings.server;
        let bind_error = |addr: SocketAddr| {
            move |source| ServeError::Bind {
                addr: addr.to_string(),
                source,
            }
        };
        let listener = TcpListener::bind(server.listen)
            .await
            .map_err(bind_error(server.listen))?;
        let grpc_addr = listener.local_addr().map_err(bind_error(server.listen))?;
        let metrics = Metrics::new();
        let (shutdown, shutdown_rx) = watch::channel(false);

        let metrics_addr = if let Some(address) = server.metrics_listen {
            let listener = TcpListener::bind(address)
                .await
                .map_err(bind_error(address))?;
            let addr = listener.local_addr().ok();
            tokio::spawn(serve_metrics(
                listener,
                metrics.clone(),
                shutdown_rx.clone(),
            ));
            addr
        } else {
            None
        };

        let (health, health_service) = tonic_health::server::health_reporter();
        health
            .set_service_status("", tonic_health::ServingStatus::NotServing)
            .await;
        health
            .set_service_status(LIVENESS_SERVICE, tonic_health::ServingStatus::Serving)
            .await;
        health
            .set_not_serving::<proto::pose_matcher_server::PoseMatcherServer<api::Api>>()
            .await;
        let reflection_v1 = tonic_reflection::server::Builder::configure()
            .register_encoded_file_descriptor_set(proto::FILE_DESCRIPTOR_SET)
            .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
            .build_v1()
            .map_err(|e| ServeError::Setup(e.to_string()))?;
        let reflection_v1alpha = tonic_reflection::server::Builder::configure()
            .register_encoded_file_descriptor_set(proto::FILE_DESCRIPTOR_SET)
            .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
            .build_v1alpha()
            .map_err(|e| ServeError::Setup(e.to_string()))?;

        let engine: Arc<OnceLock<Arc<Engine>>> = Arc::new(OnceLock::new());
        let api = api::Api::new(
            engine.clone(),
            metrics.clone(),
            api::ImageDecoder::new(server.max_image_pixels, server.max_concurrent_decodes),
            settings.match_defaults.clone(),
        );
        let pose_matcher = proto::pose_matcher_server::PoseMatcherServer::new(api)
            .max_decoding_message_size(server.max_message_bytes)
            .max_encoding_message_size(server.max_message_bytes);

        let mut builder = tonic::transport::Server::builder();
        let tls_on = tls.is_some();
        if let Some(tls) = tls {
            builder = builder
                .tls_config(tls)
                .map_err(|e| ServeError::Setup(format!("TLS (tls_cert, tls_key): {e}")))?;
        }
        let reflection = server.reflection;
        let router = builder
            .layer(security::GateLayer {
                tokens: tokens.clone(),
                metrics: metrics.clone(),
            })
            .add_service(health_service)
            .add_optional_service(reflection.then_some(reflection_v1))
            .add_optional_service(reflection.then_some(reflection_v1alpha))
            .add_service(pose_matcher);
        let mut stop = shutdown_rx.clone();
        let grpc = tokio::spawn(router.serve_with_incoming_shutdown(
            TcpListenerStream::new(listener),
            async move {
                let _ = stop.wait_for(|s| *s).await;
            },
        ));

        let (ready_tx, ready) = watch::channel(None);
        let config = EngineConfig {
            max_batch_size: settings.engine.max_batch_size,
            queue_size: settings.engine.queue_size,
            cache_size: settings.engine.cache_size,
            database_grace: settings.store.database_grace,
            max_network_pixels: settings.engine.max_network_pixels,
        };
        let location = settings.store.location.clone();
        tokio::spawn(async move {
            let (opened, loaded) = tokio::join!(
                open_store(&location, &metrics),
                tokio::task::spawn_blocking(loader)
            );
            let loaded = loaded
                .map_err(|e| format!("model loading failed: {e}"))
                .and_then(|r| r);
            match (opened, loaded) {
                (Ok((store, templates)), Ok(matcher)) => {
                    let precision = matcher.network().precision();
                    let built =
                        Arc::new(Engine::start(&config, store, templates, matcher, metrics));
                    let _ = engine.set(built.clone());
                    // Logged once requests can be answered.
                    let arithmetic = precision.arithmetic();
                    tracing::info!(%precision, %arithmetic, "model loaded");
                    report_health(built, health, move || {
                        let _ = ready_tx.send(Some(Ok(())));
                    })
                    .await;
                }
                (Err(message), _) => {
                    tracing::error!(%message, "the template store could not be opened");
                    let _ = ready_tx.send(Some(Err(message)));
                }
                (_, Err(message)) => {
                    tracing::error!(%message, "the model could not be loaded");
                    let _ = ready_tx.send(Some(Err(message)));
                }
            }
        });
        tracing::info!(
            %grpc_addr,
            metrics_addr = ?metrics_addr,
            tls = tls_on,
            client_certificates = security.tls.as_ref().is_some_and(|t| t.client_ca.is_some()),
            bearer_tokens = tokens.is_some(),
            reflection,
            "listening"
        );
        Ok(Self {
            grpc_addr,
            metrics_addr,
            shutdown,
            grpc,
            ready,
            tokens,
        })
    }

    /// The bearer tokens in force (`None` when `auth_tokens_file` is not set), for reloading.
    pub fn access_tokens(&self) -> Option<AccessTokens> {
        self.tokens.clone()
    }

    /// Waits until the model is loaded (or failed to load).
    pub async fn ready(&mut self) -> Result<(), String> {
        let state = self
            .ready
            .wait_for(Option::is_some)
            .await
            .map_err(|_| "the loader stopped".to_string())?;
        state.clone().expect("checked is_some")
    }

    /// Stops accepting connections and waits up to `grace` for in-flight requests to finish.
    pub async fn shutdown(self, grace: Duration) {
        let _ = self.shutdown.send(true);
        match tokio::time::timeout(grace, self.grpc).await {
            Ok(Ok(Ok(()))) => tracing::info!("drained; stopped"),
            Ok(Ok(Err(e))) => tracing::warn!(error = %e, "server ended with an error"),
            Ok(Err(e)) => tracing::warn!(error = %e, "server task failed"),
            Err(_) => tracing::warn!(?grace, "in-flight requests did not finish in time"),
        }
    }
}

/// How often the template store is probed (writability of a directory, reachability of a
/// database), and how often while it fails.
const STORE_RECHECK: Duration = Duration::from_secs(5);
const STORE_RECHECK_FAILING: Duration = Duration::from_secs(1);
/// Backoff between attempts to reach the database at start.
const STORE_RETRY_MOST: Duration = Duration::from_secs(5);

/// Opens the template store; a database that cannot be reached yet is retried (health stays
/// NOT_SERVING meanwhile, as while the model loads), anything else fails the start.
async fn open_store(
    location: &StoreLocation,
    metrics: &Metrics,
) -> Result<(TemplateStore, usize), String> {
    let mut wait = Duration::from_millis(250);
    loop {
        match TemplateStore::open(location, metrics).await {
            Ok((store, opened)) => {
                metrics
                    .store_files_set_aside
                    .inc_by(opened.set_aside as u64);
                tracing::info!(
                    templates = opened.templates,
                    store = %location,
                    "template registry opened"
                );
                return Ok((store, opened.templates));
            }
            Err(e @ StoreError::Unavailable(_)) => {
                tracing::warn!(error = %e, store = %location, retry_in = ?wait, "template store not reachable yet");
                tokio::time::sleep(wait).await;
                wait = (wait * 2).min(STORE_RETRY_MOST);
            }
            Err(e) => return Err(format!("{location}: {e}")),
        }
    }
}

/// Keeps health true to what the service can do: SERVING while the model thread runs and the
/// template store works (probed every [`STORE_RECHECK`]: a read-only template directory would
/// fail every registration and is reported at once; a database gets `database_grace_seconds`
/// to come back, since cached templates keep matching), NOT_SERVING otherwise, each change
/// logged with its reason. Ends when the model thread ends (for good). `reported` runs once the
/// first status is set.
async fn report_health(
    engine: Arc<Engine>,
    health: tonic_health::server::HealthReporter,
    reported: impl FnOnce(),
) {
    let mut reported = Some(reported);
    let mut model_alive = engine.model_alive();
    let mut last: Option<bool> = None;
    let grace = engine.store_grace();
    let mut failing_since: Option<std::time::Instant> = None;
    loop {
        let alive = *model_alive.borrow_and_update();
        let store = engine.check_store().await;
        let store_ok = match &store {
            Ok(()) => {
                if failing_since.take().is_some() && !grace.is_zero() {
                    tracing::info!("the template store is reachable again");
                }
                true
            }
            Err(e) => {
                if failing_since.is_none() && !grace.is_zero() {
                    tracing::warn!(error = %e, ?grace, "the template store is unreachable; cached templates keep matching");
                }
                failing_since
                    .get_or_insert_with(std::time::Instant::now)
                    .elapsed()
                    < grace
            }
        };
        let serving = alive && store_ok;
        if last != Some(serving) {
            if serving {
                tracing::info!("serving");
                health
                    .set_service_status("", tonic_health::ServingStatus::Serving)
                    .await;
                health
                    .set_serving::<proto::pose_matcher_server::PoseMatcherServer<api::Api>>()
                    .await;
            } else {
                if !alive {
                    tracing::error!("the model thread ended; health reports NOT_SERVING");
                }
                match &store {
                    Err(e @ StoreError::Full(_)) => tracing::error!(
                        error = %e,
                        "the template store is full; health reports NOT_SERVING until there is space"
                    ),
                    Err(e @ StoreError::Io { .. }) => tracing::error!(
                        error = %e,
                        "the template directory is not writable (check the volume's mount and permissions); health reports NOT_SERVING until it is"
                    ),
                    Err(e) => tracing::error!(
                        error = %e,
                        "the template store has been unreachable for longer than database_grace_seconds; health reports NOT_SERVING until it is back"
                    ),
                    Ok(()) => {}
                }
                health
                    .set_service_status("", tonic_health::ServingStatus::NotServing)
                    .await;
                health
                    .set_not_serving::<proto::pose_matcher_server::PoseMatcherServer<api::Api>>()
                    .await;
            }
            last = Some(serving);
        }
        if let Some(reported) = reported.take() {
            reported();
        }
        if !alive {
            health
                .set_service_status(LIVENESS_SERVICE, tonic_health::ServingStatus::NotServing)
                .await;
            return;
        }
        let recheck = if failing_since.is_some() {
            STORE_RECHECK_FAILING
        } else {
            STORE_RECHECK
        };
        tokio::select! {
            _ = model_alive.changed() => {}
            _ = tokio::time::sleep(recheck) => {}
        }
    }
}

async fn serve_metrics(listener: TcpListener, metrics: Metrics, mut stop: watch::Receiver<bool>) {
    use axum::routing::get;
    let router = axum::Router::new().route(
        "/metrics",
        get(move || {
            let metrics = metrics.clone();
            async move {
                (
                    [(
                        axum::http::header::CONTENT_TYPE,
                        "text/plain; version=0.0.4; charset=utf-8",
                    )],
                    metrics.render(),
                )
            }
        }),
    );
    let result = axum::serve(listener, router)
        .with_graceful_shutdown(async move {
            let _ = stop.wait_for(|s| *s).await;
        })
        .await;
    if let Err(e) = result {
        tracing::warn!(error = %e, "metrics endpoint stopped");
    }
}
