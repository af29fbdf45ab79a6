//! Load benchmark of the service: N concurrent clients on loopback, each sending 224x224 PNG
//! frames with one registered 36x36 template back to back, against servers with different
//! `max_batch_size`, over gRPC and over the HTTP/JSON API (the same request as JSON, the image
//! in base64). Reports pairs/s, p50/p99 latency and the mean batch the model thread formed.
//!
//! `cargo bench --bench load` — bounded in time (POSEMATCH_LOAD_SECONDS per configuration,
//! default 10) and in requests (POSEMATCH_LOAD_MAX_REQUESTS per configuration, default 2000).
//! POSEMATCH_LOAD_BATCHES (default "1,2,4") and POSEMATCH_LOAD_CLIENTS (default "1,8") choose the
//! grid; POSEMATCH_LOAD_TRANSPORTS (default "grpc,http") the transports. Uses the official checkpoint when `../shared/reference` is present (realistic peak
//! counts for refinement), an untrained network otherwise (refinement then sees random peaks;
//! the network's cost does not depend on the weights).

#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

#[allow(dead_code)]
#[path = "../tests/common/service.rs"]
mod service;

#[allow(dead_code)]
#[path = "../tests/common/http.rs"]
mod http;

use std::path::PathBuf;
use std::time::{Duration, Instant};

use posematch::grpc::proto::{self, image::Data};
use posematch::grpc::{ModelLoader, RunningServer};
use posematch::imaging::InputConvention;
use posematch::matcher::Matcher;
use posematch::model::{load_weights, select_device};
use service::{counter, metrics_text, png, scene, settings, start, untrained_model};

fn env_list(name: &str, default: &str) -> Vec<usize> {
    std::env::var(name)
        .unwrap_or_else(|_| default.into())
        .split(',')
        .map(|s| s.trim().parse().expect("comma-separated numbers"))
        .collect()
}

fn env_number(name: &str, default: u64) -> u64 {
    std::env::var(name)
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(default)
}

fn loader() -> (ModelLoader, &'static str) {
    let official =
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/reference/tdcm-official.pth");
    if official.is_file() {
        let loader: ModelLoader = Box::new(move || {
            let device = select_device().map_err(|e| e.to_string())?;
            let model = load_weights(&official, &device).map_err(|e| e.to_string())?;
            Ok(Matcher::new(model, device, InputConvention::Gray))
        });
        (loader, "official checkpoint")
    } else {
        (untrained_model(), "untrained network")
    }
}

/// A 224x224 textured frame and a 36x36 crop of it (the template, present once, unrotated).
fn frame_and_template() -> (Vec<u8>, Vec<u8>) {
    let frame = scene(224, 224, 0);
    let template = image::imageops::crop_imm(&frame, 94, 80, 36, 36).to_image();
    (png(&frame), png(&template))
}

struct Run {
    pairs_per_s: f64,
    p50_ms: f64,
    p99_ms: f64,
    mean_batch: f64,
    requests: usize,
}

/// How the clients reach the service.
#[derive(Clone, Copy, PartialEq)]
enum Transport {
    Grpc,
    Http,
}

impl Transport {
    fn parse(name: &str) -> Self {
        match name.trim() {
            "grpc" => Self::Grpc,
            "http" => Self::Http,
            other => panic!("POSEMATCH_LOAD_TRANSPORTS: {other:?} is neither grpc nor http"),
        }
    }

    fn name(self) -> &'static str {
        match self {
            Self::Grpc => "gRPC",
            Self::Http => "HTTP",
        }
    }
}

async fn run(
    transport: Transport,
    batch: usize,
    clients: usize,
    seconds: u64,
    max_requests: u64,
) -> Run {
    let dir = tempfile::tempdir().unwrap();
    let batch_setting = batch.to_string();
    let settings = settings(
        dir.path(),
        &[
            ("max_batch_size", batch_setting.as_str()),
            ("queue_size", "256"),
        ],
    );
    let (loader, _) = loader();
    let (server, mut client) = start(&settings, loader).await;
    let (frame, template) = frame_and_template();
    client
        .register_template(proto::RegisterTemplateRequest {
            template_id: "bench".into(),
            image: Some(proto::Image {
                data: Some(Data::Encoded(template)),
            }),
            ..Default::default()
        })
        .await
        .unwrap();
    let request = proto::MatchRequest {
        template_id: "bench".into(),
        image: Some(proto::Image {
            data: Some(Data::Encoded(frame)),
        }),
        ..Default::default()
    };
    // Warm-up: first passes allocate the activation buffers.
    for _ in 0..3 {
        client.r#match(request.clone()).await.unwrap();
    }
    let json = serde_json::to_value(&request).unwrap();
    let http_client = http::HttpClient::new(server.http_addr.expect("the HTTP port is on"));
    let start = Instant::now();
    let until = start + Duration::from_secs(seconds);
    let budget = std::sync::Arc::new(std::sync::atomic::AtomicU64::new(max_requests));
    let workers: Vec<_> = (0..clients)
        .map(|_| {
            let mut client = client.clone();
            let request = request.clone();
            let (http_client, json) = (http_client.clone(), json.clone());
            let budget = budget.clone();
            tokio::spawn(async move {
                let mut latencies = Vec::new();
                while Instant::now() < until
                    && budget
                        .fetch_update(
                            std::sync::atomic::Ordering::SeqCst,
                            std::sync::atomic::Ordering::SeqCst,
                            |b| b.checked_sub(1),
                        )
                        .is_ok()
                {
                    let t = Instant::now();
                    match transport {
                        Transport::Grpc => drop(client.r#match(request.clone()).await.unwrap()),
                        Transport::Http => {
                            let answer = http_client.post("/v1/match", &json).await;
                            assert_eq!(answer.status, 200, "{answer:?}");
                        }
                    }
                    latencies.push(t.elapsed().as_secs_f64() * 1e3);
                }
                latencies
            })
        })
        .collect();
    let batches_before = batch_stats(&server).await;
    let mut latencies = Vec::new();
    for worker in workers {
        latencies.extend(worker.await.unwrap());
    }
    let elapsed = start.elapsed().as_secs_f64();
    latencies.sort_by(f64::total_cmp);
    let pct = |p: f64| latencies[((latencies.len() - 1) as f64 * p).round() as usize];
    let batches_after = batch_stats(&server).await;
    let mean_batch =
        (batches_after.0 - batches_before.0) / (batches_after.1 - batches_before.1).max(1.0);
    server.shutdown(Duration::from_secs(30)).await;
    Run {
        pairs_per_s: latencies.len() as f64 / elapsed,
        p50_ms: pct(0.5),
        p99_ms: pct(0.99),
        mean_batch,
        requests: latencies.len(),
    }
}

/// (sum, count) of the model thread's batch sizes so far, from `/metrics`.
async fn batch_stats(server: &RunningServer) -> (f64, f64) {
    let metrics = metrics_text(server).await;
    (
        counter(&metrics, "posematch_batch_size_sum", ""),
        counter(&metrics, "posematch_batch_size_count", ""),
    )
}

fn main() {
    // `cargo bench` passes `--bench`; nothing else to parse.
    let batches = env_list("POSEMATCH_LOAD_BATCHES", "1,2,4");
    let clients = env_list("POSEMATCH_LOAD_CLIENTS", "1,8");
    let seconds = env_number("POSEMATCH_LOAD_SECONDS", 10);
    let max_requests = env_number("POSEMATCH_LOAD_MAX_REQUESTS", 2000);
    let transports: Vec<Transport> = std::env::var("POSEMATCH_LOAD_TRANSPORTS")
        .unwrap_or_else(|_| "grpc,http".into())
        .split(',')
        .map(Transport::parse)
        .collect();
    let (_, source) = loader();
    println!(
        "load: 224x224 PNG frames, 36x36 template, refinement on, {source}, {seconds} s or {max_requests} requests per row"
    );
    println!("transport  max_batch_size  clients  requests  pairs/s   p50 ms   p99 ms  mean batch");
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .unwrap();
    for &batch in &batches {
        for &n in &clients {
            for &transport in &transports {
                let r = runtime.block_on(run(transport, batch, n, seconds, max_requests));
                println!(
                    "{:<9}  {batch:>14}  {n:>7}  {:>8}  {:>7.2}  {:>7.1}  {:>7.1}  {:>10.2}",
                    transport.name(),
                    r.requests,
                    r.pairs_per_s,
                    r.p50_ms,
                    r.p99_ms,
                    r.mean_batch
                );
            }
        }
    }
}
