//! `posematch serve`: the gRPC service and its HTTP port. Reads the layered settings, sets up logging in the
//! configured format, starts the server and drains it on SIGTERM or Ctrl-C.

use std::path::PathBuf;

use clap::Args;

use super::CliError;
use crate::config::{LogFormat, Overrides, Settings};
use crate::grpc::{ModelLoader, RunningServer};
use crate::matcher::Matcher;
use crate::model::{WeightsSource, select_device};

#[derive(Args, Debug)]
pub struct ServeArgs {
    /// TOML settings file (keys as in deploy/posematch.toml); POSEMATCH__<KEY> environment
    /// variables override it, and these flags override both.
    #[arg(long)]
    config: Option<PathBuf>,
    /// gRPC listen address (default 0.0.0.0:50051).
    #[arg(long)]
    listen: Option<String>,
    /// HTTP address: the JSON API (/v1), the setup page (/), /openapi.json and /metrics
    /// (default 0.0.0.0:9090; port 0 = any free port; "" = off). --metrics-listen is its older
    /// name.
    #[arg(long, alias = "metrics-listen")]
    http_listen: Option<String>,
    /// Weights file (.bpk, .pth, .safetensors); default: the weights embedded in the binary.
    #[arg(long)]
    weights: Option<PathBuf>,
    /// Arithmetic of the network's large products: auto (default: bf16 where the CPU has AMX
    /// tiles or AVX-512 BF16, else f32), f32 (exact) or bf16.
    #[arg(long)]
    precision: Option<String>,
    /// Where registered templates are kept: a directory, or postgres://USER@HOST/DATABASE for
    /// a database shared by replicas (default: --template-dir).
    #[arg(long)]
    template_store: Option<String>,
    /// Template directory when no --template-store is given (default ./data/templates).
    #[arg(long)]
    template_dir: Option<PathBuf>,
    /// PEM certificate chain: serve TLS only (with --tls-key).
    #[arg(long)]
    tls_cert: Option<PathBuf>,
    /// PEM private key of --tls-cert.
    #[arg(long)]
    tls_key: Option<PathBuf>,
    /// PEM CA certificates: require client certificates signed by one (mutual TLS).
    #[arg(long)]
    tls_client_ca: Option<PathBuf>,
    /// Bearer tokens, one per line: every call except health needs one (re-read on SIGHUP).
    #[arg(long)]
    auth_tokens_file: Option<PathBuf>,
}

pub fn run(args: ServeArgs) -> Result<(), CliError> {
    let overrides = Overrides {
        listen: args.listen,
        http_listen: args.http_listen,
        weights: args.weights,
        precision: args.precision,
        template_dir: args.template_dir,
        template_store: args.template_store,
        tls_cert: args.tls_cert,
        tls_key: args.tls_key,
        tls_client_ca: args.tls_client_ca,
        auth_tokens_file: args.auth_tokens_file,
    };
    let settings = Settings::load(args.config.as_deref(), std::env::vars(), &overrides)
        .map_err(|e| CliError::Usage(e.to_string()))?;
    init_logging(settings.server.log_format);
    let loader = model_loader(&settings)?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .thread_name("posematch-rpc")
        .build()
        .map_err(|e| CliError::Runtime(format!("cannot start the async runtime: {e}")))?;
    runtime.block_on(async {
        // Listen for SIGHUP before anything can send it (its default action ends the process).
        #[cfg(unix)]
        let hangups = tokio::signal::unix::signal(tokio::signal::unix::SignalKind::hangup()).ok();
        let mut server = RunningServer::start(&settings, loader)
            .await
            .map_err(|e| CliError::Runtime(e.to_string()))?;
        #[cfg(unix)]
        tokio::spawn(reload_tokens_on_sighup(hangups, server.access_tokens()));
        let outcome = tokio::select! {
            ready = server.ready() => match ready {
                Ok(()) => None,
                Err(message) => Some(Err(CliError::Runtime(message))),
            },
            _ = shutdown_signal() => Some(Ok(())),
        };
        let outcome = match outcome {
            Some(outcome) => outcome,
            None => {
                shutdown_signal().await;
                Ok(())
            }
        };
        tracing::info!("shutting down; draining in-flight requests");
        server.shutdown(settings.server.shutdown_grace).await;
        outcome
    })
}

/// Checks what can be checked before binding, then defers the (slow) load to the server.
fn model_loader(settings: &Settings) -> Result<ModelLoader, CliError> {
    let (convention, precision) = (settings.engine.convention, settings.engine.precision);
    let weights = settings.engine.weights.clone();
    if let WeightsSource::File(path) = &weights
        && !path.is_file()
    {
        return Err(CliError::Input(format!(
            "weights file {} does not exist",
            path.display()
        )));
    }
    Ok(Box::new(move || {
        let device = select_device().map_err(|e| e.to_string())?;
        let model = weights.load(&device).map_err(|e| e.to_string())?;
        let trained_on = weights.trained_on().map_err(|e| e.to_string())?;
        Matcher::new(model, device, convention)
            .with_trained_on(trained_on)
            .with_precision(precision)
            .map_err(|e| e.to_string())
    }))
}

fn init_logging(format: LogFormat) {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()));
    let _ = match format {
        LogFormat::Text => builder.try_init(),
        LogFormat::Json => builder.json().try_init(),
    };
}

/// Re-reads the token file on every SIGHUP; a file that cannot be read leaves the tokens in
/// force (logged).
#[cfg(unix)]
async fn reload_tokens_on_sighup(
    hangups: Option<tokio::signal::unix::Signal>,
    tokens: Option<crate::grpc::AccessTokens>,
) {
    let Some(mut hangups) = hangups else {
        tracing::warn!("cannot listen for SIGHUP; the token file is read only at start");
        return;
    };
    while hangups.recv().await.is_some() {
        let Some(tokens) = &tokens else {
            tracing::info!("SIGHUP: no auth_tokens_file is configured; nothing to reload");
            continue;
        };
        match tokens.reload() {
            Ok(count) => tracing::info!(count, "bearer tokens reloaded"),
            Err(message) => {
                tracing::error!(%message, "bearer tokens not reloaded; the previous ones stay")
            }
        }
    }
}

async fn shutdown_signal() {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let terminate = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut signal) => {
                signal.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let terminate = std::future::pending::<()>();
    tokio::select! {
        _ = ctrl_c => {},
        _ = terminate => {},
    }
}
