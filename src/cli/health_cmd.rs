//! `posematch health`: asks a running server's standard gRPC health service whether it is
//! SERVING; exit 0 if so. The container's HEALTHCHECK, with no extra probe binary in the image.

use std::time::Duration;

use clap::Args;
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
}

pub fn run(args: HealthArgs) -> Result<(), CliError> {
    if !(args.timeout > 0.0 && args.timeout <= 3600.0) {
        return Err(CliError::Usage(format!(
            "--timeout {} is invalid: give seconds in (0, 3600]",
            args.timeout
        )));
    }
    let timeout = Duration::from_secs_f64(args.timeout);
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map_err(|e| CliError::Runtime(format!("cannot start the async runtime: {e}")))?;
    let unhealthy = |m: String| CliError::Unhealthy(format!("{}: {m}", args.addr));
    let status = runtime.block_on(async {
        let endpoint = tonic::transport::Endpoint::from_shared(format!("http://{}", args.addr))
            .map_err(|e| CliError::Usage(format!("--addr {}: {e}", args.addr)))?
            .connect_timeout(timeout)
            .timeout(timeout);
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
