//! Memory of the template registry with many templates: registers N distinct templates through
//! the real gRPC server (default 10 000), matches a spread of them so the kernel cache misses,
//! evicts and reloads from disk, restarts the server on the same directory and matches again.
//! Prints the process's resident memory (VmRSS, and the peak VmHWM) at each stage, the cache
//! counters from `/metrics`, and how long registration and the restart took.
//!
//! `cargo bench --bench templates` — POSEMATCH_TEMPLATES (default 10000) and
//! POSEMATCH_TEMPLATES_CACHE (the `cache_size` setting, default 1024) choose the run. The network
//! is untrained: memory and I/O do not depend on the weights.

#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

#[allow(dead_code)]
#[path = "../tests/common/service.rs"]
mod service;

use std::time::{Duration, Instant};

use posematch::grpc::RunningServer;
use posematch::grpc::proto::pose_matcher_client::PoseMatcherClient;
use posematch::grpc::proto::{self, image::Data};
use service::{counter, metrics_text, png, settings, start, untrained_model};
use tonic::transport::Channel;

fn env_number(name: &str, default: u64) -> u64 {
    std::env::var(name)
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(default)
}

/// (VmRSS, VmHWM) of this process in MiB.
fn memory_mib() -> (f64, f64) {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    let field = |name: &str| {
        status
            .lines()
            .find(|l| l.starts_with(name))
            .and_then(|l| l.split_whitespace().nth(1)?.parse::<f64>().ok())
            .map_or(f64::NAN, |kib| kib / 1024.0)
    };
    (field("VmRSS:"), field("VmHWM:"))
}

/// A distinct 36x36 template for every index (its content hash differs).
fn template(index: u64) -> Vec<u8> {
    let seed = index as u32;
    png(&image::RgbImage::from_fn(36, 36, |x, y| {
        let v = (x.wrapping_mul(2654435761) ^ y.wrapping_mul(40503) ^ seed.wrapping_mul(97))
            .wrapping_mul(2246822519);
        image::Rgb([
            (v >> 24) as u8,
            (v >> 16) as u8,
            (v >> 8) as u8 ^ seed as u8,
        ])
    }))
}

fn frame() -> Vec<u8> {
    png(&image::RgbImage::from_fn(96, 96, |x, y| {
        image::Rgb([
            (x * 5 % 256) as u8,
            (y * 3 % 256) as u8,
            ((x + y) % 256) as u8,
        ])
    }))
}

async fn report(stage: &str, server: &RunningServer) {
    let (rss, peak) = memory_mib();
    let metrics = metrics_text(server).await;
    let metric = |name: &str| counter(&metrics, name, "");
    println!(
        "{stage:<44} RSS {rss:>7.1} MiB  peak {peak:>7.1} MiB  templates {:>6}  cache hits {:>5} misses {:>5} evictions {:>5}",
        metric("posematch_templates "),
        metric("posematch_template_cache_hits_total"),
        metric("posematch_template_cache_misses_total"),
        metric("posematch_template_cache_evictions_total"),
    );
}

/// A server on `dir` with an untrained network and `cache` encoded templates in memory.
async fn start_server(
    dir: &std::path::Path,
    cache: u64,
) -> (RunningServer, PoseMatcherClient<Channel>) {
    let cache = cache.to_string();
    start(
        &settings(dir, &[("cache_size", cache.as_str())]),
        untrained_model(),
    )
    .await
}

/// Matches `count` templates spread evenly over all `total` IDs.
async fn match_spread(client: &mut PoseMatcherClient<Channel>, total: u64, count: u64) -> f64 {
    let frame = frame();
    let start = Instant::now();
    for i in 0..count {
        let id = i * total / count;
        client
            .r#match(proto::MatchRequest {
                template_id: format!("part-{id:05}"),
                image: Some(proto::Image {
                    data: Some(Data::Encoded(frame.clone())),
                }),
                options: Some(proto::MatchOptions {
                    no_refine: true,
                    ..Default::default()
                }),
                ..Default::default()
            })
            .await
            .unwrap();
    }
    start.elapsed().as_secs_f64() * 1e3 / count as f64
}

async fn run(total: u64, cache: u64) {
    let dir = tempfile::tempdir().unwrap();
    let (server, mut client) = start_server(dir.path(), cache).await;
    report("started, empty registry", &server).await;
    let start = Instant::now();
    for i in 0..total {
        client
            .register_template(proto::RegisterTemplateRequest {
                template_id: format!("part-{i:05}"),
                image: Some(proto::Image {
                    data: Some(Data::Encoded(template(i))),
                }),
                labels: [("line".to_string(), (i % 7).to_string())].into(),
                ..Default::default()
            })
            .await
            .unwrap();
        if (i + 1) % (total / 4).max(1) == 0 {
            report(&format!("registered {}", i + 1), &server).await;
        }
    }
    let per_template = start.elapsed().as_secs_f64() * 1e3 / total as f64;
    println!("registration: {per_template:.2} ms per template (encode + durable write)");
    let ms = match_spread(&mut client, total, 200).await;
    report("200 matches spread over all IDs", &server).await;
    println!("matching with cache misses: {ms:.1} ms per request (96x96 frame, no refinement)");
    server.shutdown(Duration::from_secs(5)).await;

    let restart = Instant::now();
    let (server, mut client) = start_server(dir.path(), cache).await;
    let restart_ms = restart.elapsed().as_secs_f64() * 1e3;
    report("restarted on the same directory", &server).await;
    println!("restart until SERVING: {restart_ms:.0} ms (metadata only; kernels load lazily)");
    let ms = match_spread(&mut client, total, 200).await;
    report("200 matches after the restart", &server).await;
    println!("matching after the restart: {ms:.1} ms per request");
    let listed = client
        .list_templates(proto::ListTemplatesRequest {
            page_size: 1000,
            ..Default::default()
        })
        .await
        .unwrap()
        .into_inner();
    println!(
        "first page after the restart: {} templates",
        listed.templates.len()
    );
    server.shutdown(Duration::from_secs(5)).await;
}

fn main() {
    let total = env_number("POSEMATCH_TEMPLATES", 10_000);
    let cache = env_number("POSEMATCH_TEMPLATES_CACHE", 1024);
    println!("templates: {total} distinct 36x36 templates, cache_size {cache}, untrained network");
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .unwrap()
        .block_on(run(total, cache));
}
