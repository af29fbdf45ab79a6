//! `posematch health`: asks a running server's standard gRPC health service whether it is
//! SERVING; exit 0 if so. The container's HEALTHCHECK, with no extra probe binary in the image.

use std::path::PathBuf;
use std::time::Duration;

use clap::Args;
use tonic::transport::{Certificate, ClientTlsConfig, Identity};
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::{HealthCheckRequest, health_client::HealthClient};

use super::CliError;

#[derive(Args, Debug)]
pub struct HealthArgs {
    /// Server address.
    #[arg(long, default_value = "127.0.0.1:50051")]
    addr: String,
    /// Service to ask about; empty means the whole server.
    #[arg(long, default_value = "")]
    service: String,
    /// Give up after this many seconds.
    #[arg(long, default_value_t = 3.0)]
    timeout: f64,
    /// Connect with TLS, trusting the CA certificate(s) in this PEM file (for a server started
    /// with --tls-cert; its own certificate works when it is self-signed).
    #[arg(long)]
    tls_ca: Option<PathBuf>,
    /// Name the server's certificate must carry (with --tls-ca).
    #[arg(long, default_value = "localhost")]
    tls_domain: String,
    /// Client certificate and key (PEM), for a server that requires them (--tls-client-ca).
    #[arg(long, requires = "tls_key")]
    tls_cert: Option<PathBuf>,
    #[arg(long, requires = "tls_cert")]
    tls_key: Option<PathBuf>,
}

/// The client TLS settings of the arguments, or `None` for plaintext.
fn client_tls(args: &HealthArgs) -> Result<Option<ClientTlsConfig>, CliError> {
    let Some(ca) = &args.tls_ca else {
        if args.tls_cert.is_some() {
            return Err(CliError::Usage(
                "--tls-cert needs --tls-ca (the CA that signed the server's certificate)".into(),
            ));
        }
        return Ok(None);
    };
    let read = |flag: &str, path: &PathBuf| {
        std::fs::read(path).map_err(|e| CliError::Input(format!("{flag} {}: {e}", path.display())))
    };
    let mut config = ClientTlsConfig::new()
        .ca_certificate(Certificate::from_pem(read("--tls-ca", ca)?))
        .domain_name(args.tls_domain.clone());
    if let (Some(cert), Some(key)) = (&args.tls_cert, &args.tls_key) {
        config = config.identity(Identity::from_pem(
            read("--tls-cert", cert)?,
            read("--tls-key", key)?,
        ));
    }
    Ok(Some(config))
}

pub fn run(args: HealthArgs) -> Result<(), CliError> {
    if !(args.timeout > 0.0 && args.timeout <= 3600.0) {
        return Err(CliError::Usage(format!(
            "--timeout {} is invalid: give seconds in (0, 3600]",
            args.timeout
        )));
    }
    let timeout = Duration::from_secs_f64(args.timeout);
    let tls = client_tls(&args)?;
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map_err(|e| CliError::Runtime(format!("cannot start the async runtime: {e}")))?;
    let unhealthy = |m: String| CliError::Unhealthy(format!("{}: {m}", args.addr));
    let status = runtime.block_on(async {
        let scheme = if tls.is_some() { "https" } else { "http" };
        let mut endpoint =
            tonic::transport::Endpoint::from_shared(format!("{scheme}://{}", args.addr))
                .map_err(|e| CliError::Usage(format!("--addr {}: {e}", args.addr)))?
                .connect_timeout(timeout)
                .timeout(timeout);
        if let Some(tls) = tls {
            endpoint = endpoint
                .tls_config(tls)
                .map_err(|e| CliError::Usage(format!("TLS: {e}")))?;
        }
        let channel = endpoint
            .connect()
            .await
            .map_err(|e| unhealthy(format!("cannot connect: {e}")))?;
        let answer = HealthClient::new(channel)
            .check(HealthCheckRequest {
                service: args.service.clone(),
            })
            .await
            .map_err(|s| unhealthy(format!("{:?}: {}", s.code(), s.message())))?;
        Ok::<_, CliError>(answer.into_inner().status)
    })?;
    if status == ServingStatus::Serving as i32 {
        println!("SERVING");
        Ok(())
    } else {
        let name = ServingStatus::try_from(status)
            .map(|s| s.as_str_name())
            .unwrap_or("UNKNOWN");
        Err(unhealthy(format!("status {name}")))
    }
}
