//! Template-store benchmark: the directory store against PostgreSQL, with the real binary
//! (`posematch serve`, embedded default weights) as child processes on loopback and a
//! throw-away PostgreSQL cluster (`tests/common/postgres.rs`; needs Debian's `postgresql`).
//!
//! `cargo bench --bench store` prints, per store:
//! - Match latency with a warm kernel cache (224x224 PNG frame, 36x36 template; client side);
//! - registration latency (distinct 36x36 templates, one client; encoding included);
//! - memory of a fresh replica over POSEMATCH_BENCH_TEMPLATES templates (default 10 000):
//!   after start, after listing them all, after matching 100 of them (0: skipped);
//!
//! and for two PostgreSQL replicas, how long a replacement on A takes to reach B: to a
//! `LISTEN`ing connection (the notification B's cache acts on) and until B's next Match
//! answers with the new image.

#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

#[allow(dead_code)]
#[path = "../tests/common/postgres.rs"]
mod postgres;
#[allow(dead_code)]
#[path = "../tests/common/service.rs"]
mod service;

use std::time::{Duration, Instant};

use posematch::grpc::proto;
use postgres::PgCluster;
use service::{ChildServer, encoded, png, register_request, scene, template_png};

fn env_number(name: &str, default: usize) -> usize {
    std::env::var(name)
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(default)
}

/// Median and 95th percentile, in milliseconds.
fn percentiles(mut samples: Vec<Duration>) -> (f64, f64) {
    samples.sort();
    let at =
        |q: f64| samples[((samples.len() - 1) as f64 * q).round() as usize].as_secs_f64() * 1e3;
    (at(0.5), at(0.95))
}

fn rss_mib(server: &ChildServer) -> f64 {
    let status = std::fs::read_to_string(format!("/proc/{}/status", server.child.id())).unwrap();
    let line = status.lines().find(|l| l.starts_with("VmRSS:")).unwrap();
    line.split_whitespace()
        .nth(1)
        .unwrap()
        .parse::<f64>()
        .unwrap()
        / 1024.0
}

fn match_request(id: &str, frame: &[u8]) -> proto::MatchRequest {
    proto::MatchRequest {
        template_id: id.into(),
        image: encoded(frame.to_vec()),
        options: None,
        request_id: String::new(),
        template_ids: Vec::new(),
    }
}

/// Registers `count` distinct templates `t-00000`… with four clients at once.
async fn register_many(server: &ChildServer, count: usize) {
    let started = Instant::now();
    let mut tasks = Vec::new();
    for lane in 0..4 {
        let mut client = server.client().await;
        tasks.push(tokio::spawn(async move {
            for k in (lane..count).step_by(4) {
                client
                    .register_template(register_request(
                        &format!("t-{k:05}"),
                        template_png(k as u32 + 100),
                    ))
                    .await
                    .unwrap();
            }
        }));
    }
    for task in tasks {
        task.await.unwrap();
    }
    println!(
        "  registered {count} templates with 4 clients in {:.1} s ({:.0}/s)",
        started.elapsed().as_secs_f64(),
        count as f64 / started.elapsed().as_secs_f64()
    );
}

async fn latencies(store: &str, server: &ChildServer) {
    let mut client = server.client().await;
    let frame = png(&scene(224, 224, 7));
    let template = png(&image::imageops::crop_imm(&scene(224, 224, 7), 94, 80, 36, 36).to_image());
    client
        .register_template(register_request("warm", template))
        .await
        .unwrap();
    for _ in 0..5 {
        client.r#match(match_request("warm", &frame)).await.unwrap();
    }
    let mut matches = Vec::new();
    for _ in 0..60 {
        let started = Instant::now();
        client.r#match(match_request("warm", &frame)).await.unwrap();
        matches.push(started.elapsed());
    }
    let mut registrations = Vec::new();
    for k in 0..100u32 {
        let started = Instant::now();
        client
            .register_template(register_request(
                &format!("latency-{k}"),
                template_png(50_000 + k),
            ))
            .await
            .unwrap();
        registrations.push(started.elapsed());
    }
    let (m50, m95) = percentiles(matches);
    let (r50, r95) = percentiles(registrations);
    println!("{store}: Match, warm cache, 224x224: median {m50:.1} ms, p95 {m95:.1} ms (60 calls)");
    println!("{store}: RegisterTemplate 36x36: median {r50:.1} ms, p95 {r95:.1} ms (100 calls)");
}

async fn memory(store: &str, start: &dyn Fn() -> ChildServer, count: usize) {
    let filler = start();
    register_many(&filler, count).await;
    filler.kill9();
    let server = start();
    let mut client = server.client().await;
    tokio::time::sleep(Duration::from_millis(500)).await;
    let at_start = rss_mib(&server);
    let listed = service::list_all(&mut client, 1000).await.len();
    let after_list = rss_mib(&server);
    let frame = png(&scene(224, 224, 7));
    for k in 0..100 {
        client
            .r#match(match_request(&format!("t-{k:05}"), &frame))
            .await
            .unwrap();
    }
    let after_matches = rss_mib(&server);
    println!(
        "{store}: fresh replica over {listed} templates: RSS {at_start:.0} MiB at start, {after_list:.0} MiB after listing all, {after_matches:.0} MiB after matching 100"
    );
}

async fn propagation(cluster: &PgCluster) {
    let url = cluster.url();
    let a = ChildServer::start_with(|c| {
        c.arg("--template-store").arg(&url);
    });
    let b = ChildServer::start_with(|c| {
        c.arg("--template-store").arg(&url);
    });
    let (client, mut listener) = tokio_postgres::connect(&url, tokio_postgres::NoTls)
        .await
        .unwrap();
    let (sender, mut notifications) = tokio::sync::mpsc::unbounded_channel();
    tokio::spawn(async move {
        let mut messages = futures_util::stream::poll_fn(move |cx| listener.poll_message(cx));
        while let Some(Ok(message)) = futures_util::StreamExt::next(&mut messages).await {
            if let tokio_postgres::AsyncMessage::Notification(n) = message {
                let _ = sender.send((Instant::now(), n));
            }
        }
    });
    client
        .batch_execute("LISTEN posematch_templates")
        .await
        .unwrap();
    let (mut on_a, mut on_b) = (a.client().await, b.client().await);
    let frame = png(&scene(224, 224, 7));
    let images = [template_png(1), template_png(2)];
    on_a.register_template(register_request("moving", images[0].clone()))
        .await
        .unwrap();
    while notifications.try_recv().is_ok() {}
    let (mut to_listener, mut to_acknowledgement, mut to_match) =
        (Vec::new(), Vec::new(), Vec::new());
    for round in 1..=20 {
        let before = on_b
            .r#match(match_request("moving", &frame))
            .await
            .unwrap()
            .into_inner()
            .poses;
        let request = proto::RegisterTemplateRequest {
            replace: true,
            ..register_request("moving", images[round % 2].clone())
        };
        let sent = Instant::now();
        on_a.register_template(request).await.unwrap();
        let acknowledged = Instant::now();
        let (heard, _) = notifications.recv().await.unwrap();
        to_listener.push(heard.saturating_duration_since(sent));
        to_acknowledgement.push(acknowledged - sent);
        loop {
            let now = on_b
                .r#match(match_request("moving", &frame))
                .await
                .unwrap()
                .into_inner()
                .poses;
            if now.first().map(|p| (p.x, p.y, p.score))
                != before.first().map(|p| (p.x, p.y, p.score))
            {
                break;
            }
        }
        to_match.push(sent.elapsed());
    }
    let (a50, a95) = percentiles(to_acknowledgement);
    let (l50, l95) = percentiles(to_listener);
    let (m50, m95) = percentiles(to_match);
    println!(
        "replace sent to A -> acknowledged: median {a50:.1} ms, p95 {a95:.1} ms (20 replacements)"
    );
    println!(
        "replace sent to A -> notification at a listening connection: median {l50:.1} ms, p95 {l95:.1} ms"
    );
    println!(
        "replace sent to A -> B's next Match answers with the new image: median {m50:.1} ms, p95 {m95:.1} ms (B's Match itself included)"
    );
}

fn main() {
    let Some(cluster) = PgCluster::start() else {
        eprintln!("the store benchmark needs PostgreSQL (apt-get install postgresql)");
        return;
    };
    let runtime = tokio::runtime::Runtime::new().unwrap();
    let templates = env_number("POSEMATCH_BENCH_TEMPLATES", 10_000);
    runtime.block_on(async {
        let dir = tempfile::tempdir().unwrap();
        let url = cluster.url();
        let directory = || {
            let path = dir.path().join("templates");
            ChildServer::start_with(move |c| {
                c.arg("--template-dir").arg(&path);
            })
        };
        let database = || {
            let url = url.clone();
            ChildServer::start_with(move |c| {
                c.arg("--template-store").arg(&url);
            })
        };
        latencies("directory", &directory()).await;
        latencies("postgres", &database()).await;
        propagation(&cluster).await;
        // Fresh stores for the memory figures.
        let (client, connection) = tokio_postgres::connect(&url, tokio_postgres::NoTls)
            .await
            .unwrap();
        tokio::spawn(connection);
        client
            .batch_execute("TRUNCATE posematch_templates")
            .await
            .unwrap();
        let dir = tempfile::tempdir().unwrap();
        let directory = || {
            let path = dir.path().join("templates");
            ChildServer::start_with(move |c| {
                c.arg("--template-dir").arg(&path);
            })
        };
        if templates > 0 {
            memory("directory", &directory, templates).await;
            memory("postgres", &database, templates).await;
        }
    });
}
