//! Helpers for tests of the gRPC service: servers in this process (an untrained network, for
//! the contract) or as child processes (the real binary, to kill or measure), images, requests
//! and metrics.

use std::collections::HashMap;
use std::path::Path;

use posematch::grpc::proto::pose_matcher_client::PoseMatcherClient;
use posematch::grpc::proto::{self, image::Data};
use posematch::grpc::{ModelLoader, Overrides, RunningServer, Settings};
use posematch::imaging::InputConvention;
use posematch::matcher::Matcher;
use posematch::model::{TdcmConfig, select_device};
use tonic::transport::Channel;

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
        ("POSEMATCH__METRICS_LISTEN".into(), "127.0.0.1:0".into()),
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

pub fn png(image: &image::RgbImage) -> Vec<u8> {
    let mut bytes = Vec::new();
    image
        .write_to(
            &mut std::io::Cursor::new(&mut bytes),
            image::ImageFormat::Png,
        )
        .unwrap();
    bytes
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
    }
}

/// Equal up to float summation order (the network's reductions run in parallel).
pub fn assert_same_poses(a: &[proto::Pose], b: &[proto::Pose]) {
    assert_eq!(a.len(), b.len(), "{a:?} vs {b:?}");
    for (p, q) in a.iter().zip(b) {
        let close = (p.x - q.x).abs() < 0.01
            && (p.y - q.y).abs() < 0.01
            && (p.angle_deg - q.angle_deg).abs() < 0.01
            && (p.scale_x - q.scale_x).abs() < 1e-3
            && (p.scale_y - q.scale_y).abs() < 1e-3
            && (p.score - q.score).abs() < 1e-4;
        assert!(close, "{p:?} vs {q:?}");
    }
}

pub async fn metrics_text(server: &RunningServer) -> String {
    let addr = server.metrics_addr.expect("metrics enabled");
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
    pub fn start() -> Self {
        let dir = tempfile::tempdir().unwrap();
        let mut server = Self::start_in(&dir.path().join("templates"), |_| {});
        server._dir = Some(dir);
        server
    }

    /// A server on `template_dir`; `configure` may add arguments or change the user.
    pub fn start_in(
        template_dir: &Path,
        configure: impl FnOnce(&mut std::process::Command),
    ) -> Self {
        Self::start_with(|command| {
            command.arg("--template-dir").arg(template_dir);
            configure(command);
        })
    }

    /// A server whose store (and anything else) `configure` sets.
    pub fn start_with(configure: impl FnOnce(&mut std::process::Command)) -> Self {
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
        let (mut addr, mut loaded) = (None, false);
        for line in lines.by_ref() {
            let line = line.expect("server log readable");
            if let Some(rest) = line.split("grpc_addr=").nth(1) {
                addr = rest.split_whitespace().next().map(str::to_owned);
            }
            loaded |= line.contains("model loaded");
            let failed =
                line.contains("could not be loaded") || line.contains("could not be opened");
            log.lock().unwrap().push(line);
            if (addr.is_some() && loaded) || failed {
                break;
            }
        }
        // Keep draining the log so the server never blocks on a full pipe.
        let kept = log.clone();
        std::thread::spawn(move || {
            for line in lines.map_while(Result::ok) {
                kept.lock().unwrap().push(line);
            }
        });
        let addr = addr.expect("the server logs its address");
        Self {
            child,
            addr,
            log,
            _dir: None,
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
