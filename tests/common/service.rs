//! Helpers for tests of the gRPC service: servers in this process (an untrained network, for
//! the contract) or as child processes (the real binary, to kill or measure; ready once their
//! health service says SERVING), images, requests, poses and metrics.
//!
//! `benches/store.rs` includes this file on its own (`#[path]`), so it uses nothing from the
//! other files of `tests/common`.

use std::collections::HashMap;
use std::path::Path;
use std::time::{Duration, Instant};

use posematch::config::{Overrides, Settings};
use posematch::grpc::proto::pose_matcher_client::PoseMatcherClient;
use posematch::grpc::proto::{self, image::Data};
use posematch::grpc::{ModelLoader, RunningServer};
use posematch::imaging::InputConvention;
use posematch::matcher::Matcher;
use posematch::model::{TdcmConfig, WeightsSource, select_device};
use tonic::transport::Channel;

/// The default weights compiled into the binary: for answers that must find the part.
pub fn embedded_model() -> ModelLoader {
    Box::new(|| {
        let device = select_device().map_err(|e| e.to_string())?;
        let model = WeightsSource::Embedded
            .load(&device)
            .map_err(|e| e.to_string())?;
        Ok(Matcher::new(model, device, InputConvention::ImagenetRgb))
    })
}

/// Random weights: for tests of the service around the network, whose poses are arbitrary.
pub fn untrained_model() -> ModelLoader {
    Box::new(|| {
        let device = select_device().map_err(|e| e.to_string())?;
        let model = TdcmConfig::new().init(&device);
        Ok(Matcher::new(model, device, InputConvention::ImagenetRgb))
    })
}

pub fn settings(template_dir: &Path, tweak: &[(&str, &str)]) -> Settings {
    let mut environment: Vec<(String, String)> = vec![
        ("POSEMATCH__LISTEN".into(), "127.0.0.1:0".into()),
        ("POSEMATCH__HTTP_LISTEN".into(), "127.0.0.1:0".into()),
    ];
    environment.extend(
        tweak
            .iter()
            .map(|(k, v)| (format!("POSEMATCH__{}", k.to_uppercase()), v.to_string())),
    );
    let overrides = Overrides {
        template_dir: Some(template_dir.to_owned()),
        ..Overrides::default()
    };
    Settings::load(None, environment, &overrides).expect("valid test settings")
}

pub async fn start(
    settings: &Settings,
    loader: ModelLoader,
) -> (RunningServer, PoseMatcherClient<Channel>) {
    let mut server = RunningServer::start(settings, loader)
        .await
        .expect("server starts");
    server.ready().await.expect("model loads");
    let client = PoseMatcherClient::connect(format!("http://{}", server.grpc_addr))
        .await
        .expect("client connects");
    (server, client)
}

/// A textured RGB scene (smooth blobs and stripes, so crops of it are distinctive).
pub fn scene(width: u32, height: u32, seed: u32) -> image::RgbImage {
    image::RgbImage::from_fn(width, height, |x, y| {
        let (fx, fy, s) = (x as f32, y as f32, seed as f32);
        let a = ((fx * 0.11 + s).sin() * (fy * 0.07 - s).cos() * 0.5 + 0.5) * 255.0;
        let b = ((fx * 0.031 + fy * 0.053 + s * 2.0).sin() * 0.5 + 0.5) * 255.0;
        let c = (((x / 17 + y / 13 + seed) % 3) * 100) as f32;
        image::Rgb([a as u8, b as u8, c as u8])
    })
}

/// `image` as the bytes of a `format` file (PNG, JPEG...).
pub fn encode_image<P>(
    image: &image::ImageBuffer<P, Vec<P::Subpixel>>,
    format: image::ImageFormat,
) -> Vec<u8>
where
    P: image::PixelWithColorType,
    [P::Subpixel]: image::EncodableLayout,
{
    let mut bytes = Vec::new();
    image
        .write_to(&mut std::io::Cursor::new(&mut bytes), format)
        .unwrap();
    bytes
}

pub fn png(image: &image::RgbImage) -> Vec<u8> {
    encode_image(image, image::ImageFormat::Png)
}

pub fn encoded(bytes: Vec<u8>) -> Option<proto::Image> {
    Some(proto::Image {
        data: Some(Data::Encoded(bytes)),
    })
}

pub fn template_png(seed: u32) -> Vec<u8> {
    png(&image::imageops::crop_imm(&scene(200, 200, seed), 60, 70, 36, 40).to_image())
}

pub fn register_request(id: &str, image: Vec<u8>) -> proto::RegisterTemplateRequest {
    proto::RegisterTemplateRequest {
        template_id: id.into(),
        image: encoded(image),
        replace: false,
        labels: HashMap::from([("line".to_string(), "4".to_string())]),
        mask: None,
        origin_x: None,
        origin_y: None,
    }
}

pub fn match_request(id: &str, image: Vec<u8>, request_id: &str) -> proto::MatchRequest {
    proto::MatchRequest {
        template_id: id.into(),
        image: encoded(image),
        options: Some(proto::MatchOptions {
            no_refine: true,
            ..Default::default()
        }),
        request_id: request_id.into(),
        template_ids: Vec::new(),
    }
}

/// Equal up to float summation order (the network's reductions run in parallel).
pub fn same_pose(p: &proto::Pose, q: &proto::Pose) -> bool {
    (p.x - q.x).abs() < 0.01
        && (p.y - q.y).abs() < 0.01
        && (p.angle_deg - q.angle_deg).abs() < 0.01
        && (p.scale_x - q.scale_x).abs() < 1e-3
        && (p.scale_y - q.scale_y).abs() < 1e-3
        && (p.score - q.score).abs() < 1e-4
}

/// The same poses, in the same order ([`same_pose`]).
pub fn same_poses(a: &[proto::Pose], b: &[proto::Pose]) -> bool {
    a.len() == b.len() && a.iter().zip(b).all(|(p, q)| same_pose(p, q))
}

/// [`same_poses`], or a failure naming the first pair that differs.
pub fn assert_same_poses(a: &[proto::Pose], b: &[proto::Pose]) {
    assert_eq!(a.len(), b.len(), "{a:?} vs {b:?}");
    for (p, q) in a.iter().zip(b) {
        assert!(same_pose(p, q), "{p:?} vs {q:?}");
    }
}

pub async fn metrics_text(server: &RunningServer) -> String {
    let addr = server.http_addr.expect("the HTTP port enabled");
    tokio::task::spawn_blocking(move || {
        use std::io::{Read, Write};
        let mut stream = std::net::TcpStream::connect(addr).unwrap();
        write!(
            stream,
            "GET /metrics HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n"
        )
        .unwrap();
        let mut text = String::new();
        stream.read_to_string(&mut text).unwrap();
        text
    })
    .await
    .unwrap()
}

/// Sum of a counter over all its label sets (0 when absent).
pub fn counter(metrics: &str, name: &str, label_filter: &str) -> f64 {
    metrics
        .lines()
        .filter(|l| l.starts_with(name) && l.contains(label_filter))
        .filter_map(|l| l.rsplit(' ').next()?.parse::<f64>().ok())
        .sum()
}

/// Health status codes, as `Check` answers them.
pub const SERVING: i32 = tonic_health::pb::health_check_response::ServingStatus::Serving as i32;
pub const NOT_SERVING: i32 =
    tonic_health::pb::health_check_response::ServingStatus::NotServing as i32;

/// How long a child server may take to turn SERVING (it loads the model after binding).
const START_DEADLINE: Duration = Duration::from_secs(120);
/// Pause between two health checks of a starting child server.
const HEALTH_POLL: Duration = Duration::from_millis(20);

/// `posematch serve` as a child process (embedded weights, plaintext on 127.0.0.1, a port the
/// OS picks), so that its own peak memory can be read from `/proc` and it can be killed with
/// SIGKILL. Its log lines are kept for assertions.
pub struct ChildServer {
    pub child: std::process::Child,
    pub addr: String,
    pub log: std::sync::Arc<std::sync::Mutex<Vec<String>>>,
    _dir: Option<tempfile::TempDir>,
}

impl ChildServer {
    /// A SERVING server on a template directory of its own.
    pub fn start() -> Self {
        let dir = tempfile::tempdir().unwrap();
        let mut server = Self::start_in(&dir.path().join("templates"), |_| {});
        server._dir = Some(dir);
        server
    }

    /// A SERVING server on `template_dir`; `configure` may add arguments or change the user.
    pub fn start_in(
        template_dir: &Path,
        configure: impl FnOnce(&mut std::process::Command),
    ) -> Self {
        Self::start_with(|command| {
            command.arg("--template-dir").arg(template_dir);
            configure(command);
        })
    }

    /// A server whose store (and anything else) `configure` sets, once its health service
    /// answers SERVING for the whole server.
    pub fn start_with(configure: impl FnOnce(&mut std::process::Command)) -> Self {
        let mut server = Self::launch_with(configure);
        server.wait_until_serving();
        server
    }

    /// [`ChildServer::start_in`] without waiting for SERVING: for a server that is expected
    /// not to serve (ask [`ChildServer::health`]).
    pub fn launch_in(
        template_dir: &Path,
        configure: impl FnOnce(&mut std::process::Command),
    ) -> Self {
        Self::launch_with(|command| {
            command.arg("--template-dir").arg(template_dir);
            configure(command);
        })
    }

    /// The server as soon as it listens (its log names the port the OS gave it), serving or
    /// not.
    pub fn launch_with(configure: impl FnOnce(&mut std::process::Command)) -> Self {
        use std::io::BufRead;
        let mut command = std::process::Command::new(env!("CARGO_BIN_EXE_posematch"));
        command
            .args(["serve", "--listen", "127.0.0.1:0", "--metrics-listen", ""])
            .env("POSEMATCH__LOG_FORMAT", "text")
            .env("NO_COLOR", "1")
            .stderr(std::process::Stdio::piped());
        configure(&mut command);
        let mut child = command.spawn().expect("posematch serve starts");
        let mut lines = std::io::BufReader::new(child.stderr.take().unwrap()).lines();
        let log = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
        let mut addr = None;
        for line in lines.by_ref() {
            let line = line.expect("server log readable");
            addr = line
                .split("grpc_addr=")
                .nth(1)
                .and_then(|rest| rest.split_whitespace().next())
                .map(str::to_owned);
            log.lock().unwrap().push(line);
            if addr.is_some() {
                break;
            }
        }
        let Some(addr) = addr else {
            let _ = child.kill();
            let _ = child.wait();
            let log = log.lock().unwrap().clone();
            panic!("the server ended without logging its address: {log:?}");
        };
        // Keep draining the log so the server never blocks on a full pipe.
        let kept = log.clone();
        std::thread::spawn(move || {
            for line in lines.map_while(Result::ok) {
                kept.lock().unwrap().push(line);
            }
        });
        Self {
            child,
            addr,
            log,
            _dir: None,
        }
    }

    /// Polls the health service until the whole server is SERVING. Fails, with the log, when
    /// the server exits or reports a failed start first, or is not SERVING within
    /// [`START_DEADLINE`].
    fn wait_until_serving(&mut self) {
        let started = Instant::now();
        loop {
            let exited = self
                .child
                .try_wait()
                .expect("the server's state is readable");
            let failed = self.logged("could not be loaded") || self.logged("could not be opened");
            if exited.is_some() || failed {
                panic!(
                    "the server did not start (exit: {exited:?}): {:?}",
                    self.log_so_far()
                );
            }
            let status = health_blocking(&self.addr, "");
            if status == Ok(SERVING) {
                return;
            }
            if started.elapsed() > START_DEADLINE {
                panic!(
                    "the server is not SERVING after {START_DEADLINE:?} (health: {status:?}): {:?}",
                    self.log_so_far()
                );
            }
            // The interval between two checks, not a guess at how long loading takes.
            std::thread::sleep(HEALTH_POLL);
        }
    }

    pub async fn client(&self) -> PoseMatcherClient<Channel> {
        PoseMatcherClient::connect(format!("http://{}", self.addr))
            .await
            .expect("client connects")
    }

    /// The health of the whole server, as a probe sees it.
    pub async fn health(&self) -> i32 {
        health_of(&self.addr, "").await
    }

    /// Whether a log line contains `text` so far.
    pub fn logged(&self, text: &str) -> bool {
        self.log.lock().unwrap().iter().any(|l| l.contains(text))
    }

    /// A copy of the log lines so far.
    pub fn log_so_far(&self) -> Vec<String> {
        self.log.lock().unwrap().clone()
    }

    /// SIGKILL, as an OOM killer or a power cut would: no destructor, no flush.
    pub fn kill9(mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }

    /// VmHWM: the most resident memory the server has had, in MiB.
    pub fn peak_mib(&self) -> f64 {
        let status = std::fs::read_to_string(format!("/proc/{}/status", self.child.id())).unwrap();
        let line = status
            .lines()
            .find(|l| l.starts_with("VmHWM:"))
            .expect("VmHWM in /proc/PID/status");
        let kib: f64 = line.split_whitespace().nth(1).unwrap().parse().unwrap();
        kib / 1024.0
    }
}

impl Drop for ChildServer {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The content hash a client computes from `GetTemplate(include_image)`: SHA-256 over width and
/// height (u32 big-endian) then every 16-bit sample (big-endian), as the proto documents.
pub fn audited_content_sha256(info: &proto::TemplateInfo) -> String {
    use sha2::Digest;
    let Some(Data::Encoded(png)) = info.image.as_ref().and_then(|i| i.data.clone()) else {
        panic!("GetTemplate(include_image) returned no encoded image: {info:?}");
    };
    let stored = image::load_from_memory_with_format(&png, image::ImageFormat::Png)
        .expect("the stored image is a PNG")
        .into_rgb16();
    let mut hasher = sha2::Sha256::new();
    hasher.update(stored.width().to_be_bytes());
    hasher.update(stored.height().to_be_bytes());
    for sample in stored.as_raw() {
        hasher.update(sample.to_be_bytes());
    }
    hex::encode(hasher.finalize())
}

pub async fn get_with_image(
    client: &mut PoseMatcherClient<Channel>,
    id: &str,
) -> proto::TemplateInfo {
    client
        .get_template(proto::GetTemplateRequest {
            template_id: id.into(),
            include_image: true,
        })
        .await
        .expect("the template is registered")
        .into_inner()
}

/// The health status of `service` ("" = the whole server) on the server at `addr`.
pub async fn health_of(addr: &str, service: &str) -> i32 {
    let channel = Channel::from_shared(format!("http://{addr}"))
        .unwrap()
        .connect()
        .await
        .expect("health client connects");
    tonic_health::pb::health_client::HealthClient::new(channel)
        .check(tonic_health::pb::HealthCheckRequest {
            service: service.into(),
        })
        .await
        .expect("health answers")
        .into_inner()
        .status
}

/// One health check of `service` ("" = the whole server) on the server at `addr`, from
/// synchronous code, a tokio worker's included: it runs on a thread of its own, with a runtime
/// of its own.
pub fn health_blocking(addr: &str, service: &str) -> Result<i32, String> {
    let (addr, service) = (addr.to_owned(), service.to_owned());
    std::thread::spawn(move || -> Result<i32, String> {
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .map_err(|e| e.to_string())?;
        runtime.block_on(async move {
            let channel = Channel::from_shared(format!("http://{addr}"))
                .map_err(|e| e.to_string())?
                .connect_timeout(Duration::from_secs(1))
                .timeout(Duration::from_secs(5))
                .connect()
                .await
                .map_err(|e| e.to_string())?;
            let answer = tonic_health::pb::health_client::HealthClient::new(channel)
                .check(tonic_health::pb::HealthCheckRequest { service })
                .await
                .map_err(|e| e.to_string())?;
            Ok::<i32, String>(answer.into_inner().status)
        })
    })
    .join()
    .expect("the health check's thread does not panic")
}

/// Every registered template, following `next_page_token` with pages of `page_size`.
pub async fn list_all(
    client: &mut PoseMatcherClient<Channel>,
    page_size: u32,
) -> Vec<proto::TemplateInfo> {
    let (mut all, mut token) = (Vec::new(), String::new());
    loop {
        let page = client
            .list_templates(proto::ListTemplatesRequest {
                page_size,
                page_token: token,
            })
            .await
            .expect("ListTemplates answers")
            .into_inner();
        all.extend(page.templates);
        if page.next_page_token.is_empty() {
            return all;
        }
        token = page.next_page_token;
    }
}
