//! The `posematch` binary: parse flags, set up logging, run, and turn errors into one line and
//! an exit status.

use clap::Parser;

/// mimalloc keeps the large activation buffers of one forward pass mapped for the next; with
/// glibc's allocator every pass page-faults them back in (measured: ~25 ms of a ~60 ms search).
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() {
    let cli = posematch::cli::Cli::parse();
    // `serve` sets up its own logging (format and level from its settings).
    if !matches!(cli.command, posematch::cli::Command::Serve(_)) {
        tracing_subscriber::fmt()
            .with_env_filter(
                tracing_subscriber::EnvFilter::try_from_default_env()
                    .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn")),
            )
            .with_writer(std::io::stderr)
            .init();
    }
    if let Err(error) = posematch::cli::run(cli) {
        eprintln!("error: {error}");
        std::process::exit(error.exit_code());
    }
}
