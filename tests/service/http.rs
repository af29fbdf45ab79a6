//! The HTTP port as a client sees it: the JSON API against the gRPC answers (same messages,
//! same poses), every documented error status with its JSON body, bad bodies (4xx, never 5xx),
//! bearer tokens, TLS, the page's files, and the OpenAPI document against what the server
//! answers.

use std::time::Duration;

use posematch::grpc::RunningServer;
use posematch::grpc::proto;
use serde_json::{Value, json};
use tonic::transport::Channel;

use crate::common::http::{Answer, HttpClient, base64};
use crate::common::service::*;

fn http_of(server: &RunningServer) -> HttpClient {
    HttpClient::new(server.http_addr.expect("the HTTP port is on"))
}

fn register_body(id: &str, image: &[u8]) -> Value {
    json!({"templateId": id, "image": {"encoded": base64(image)}, "labels": {"line": "4"}})
}

/// The classical matcher finds a crop of the frame exactly, whatever the weights: a real pose
/// to compare between the two transports.
fn ncc_match(template_ids: &[&str], frame: &[u8]) -> proto::MatchRequest {
    proto::MatchRequest {
        template_ids: template_ids.iter().map(|id| id.to_string()).collect(),
        image: encoded(frame.to_vec()),
        options: Some(proto::MatchOptions {
            method: proto::Method::Ncc as i32,
            max_instances: 2,
            ..Default::default()
        }),
        request_id: "frame-7".into(),
        ..Default::default()
    }
}

/// The same requests over HTTP and gRPC: the same messages back (registration, listing, the
/// stored image, deletion, calibrations) and the same poses, for the network and the classical
/// matcher; the proto's own field names are accepted as well as lowerCamelCase.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_http_api_answers_as_grpc_does() {
    let dir = tempfile::tempdir().unwrap();
    let (server, mut grpc) = start(&settings(dir.path(), &[]), untrained_model()).await;
    let http = http_of(&server);

    let registered = http
        .post("/v1/templates", &register_body("part-a", &template_png(1)))
        .await;
    assert_eq!(registered.status, 200, "{registered:?}");
    assert_eq!(registered.body["width"], 36);
    assert_eq!(registered.body["version"], "1", "int64 as a JSON string");
    let info = grpc
        .get_template(proto::GetTemplateRequest {
            template_id: "part-a".into(),
            include_image: true,
        })
        .await
        .unwrap()
        .into_inner();
    let from_http: proto::TemplateInfo = serde_json::from_value(registered.body).unwrap();
    assert_eq!(
        from_http,
        proto::TemplateInfo {
            image: None,
            ..info.clone()
        }
    );
    // The proto's own names work too.
    let snake = json!({"template_id": "part-b", "image": {"encoded": base64(&template_png(2))}});
    assert_eq!(http.post("/v1/templates", &snake).await.status, 200);

    let with_image = http.get("/v1/templates/part-a?includeImage=true").await;
    let with_image: proto::TemplateInfo = serde_json::from_value(with_image.body).unwrap();
    assert_eq!(with_image, info, "the stored image, as gRPC returns it");
    let first = http.get("/v1/templates?pageSize=1").await;
    assert_eq!(first.body["templates"][0]["templateId"], "part-a");
    let token = first.body["nextPageToken"].as_str().expect("a second page");
    let second = http
        .get(&format!("/v1/templates?page_size=1&page_token={token}"))
        .await;
    assert_eq!(second.body["templates"][0]["templateId"], "part-b");
    assert!(second.body.get("nextPageToken").is_none(), "{second:?}");

    let frame = png(&scene(200, 200, 1));
    for request in [
        ncc_match(&["part-a"], &frame),
        ncc_match(&["part-a", "part-b"], &frame),
        proto::MatchRequest {
            options: Some(proto::MatchOptions {
                no_refine: true,
                min_score: 0.01,
                max_instances: 3,
                ..Default::default()
            }),
            ..match_request("part-a", frame.clone(), "network")
        },
    ] {
        let over_grpc = grpc.r#match(request.clone()).await.unwrap().into_inner();
        let body = serde_json::to_value(&request).unwrap();
        let over_http = http.post("/v1/match", &body).await;
        assert_eq!(over_http.status, 200, "{over_http:?}");
        let over_http: proto::MatchResponse = serde_json::from_value(over_http.body).unwrap();
        assert!(!over_grpc.poses.is_empty(), "{over_grpc:?}");
        assert_same_poses(&over_http.poses, &over_grpc.poses);
        assert_eq!(over_http.request_id, request.request_id);
        assert_eq!(over_http.template_ids, request.template_ids);
        assert_eq!((over_http.image_width, over_http.image_height), (200, 200));
    }
    // The crop at (60, 70), 36x40, found where it was cut.
    let found = http
        .post(
            "/v1/match",
            &serde_json::to_value(ncc_match(&["part-a"], &frame)).unwrap(),
        )
        .await;
    let pose = &found.body["poses"][0];
    assert!((pose["x"].as_f64().unwrap() - 77.5).abs() < 0.5, "{pose}");
    assert!((pose["y"].as_f64().unwrap() - 89.5).abs() < 0.5, "{pose}");
    assert_eq!(pose["templateId"], "part-a");

    let calibration = json!({"calibrationId": "belt", "unit": "mm", "points": [
        {"imageX": 0, "imageY": 0, "worldX": 0, "worldY": 0},
        {"imageX": 100, "imageY": 0, "worldX": 10, "worldY": 0},
        {"imageX": 0, "imageY": 100, "worldX": 0, "worldY": 10}]});
    let registered = http.post("/v1/calibrations", &calibration).await;
    assert_eq!(registered.status, 200, "{registered:?}");
    assert_eq!(registered.body["model"], "MODEL_AFFINE", "enums by name");
    let over_grpc = grpc
        .get_calibration(proto::GetCalibrationRequest {
            calibration_id: "belt".into(),
        })
        .await
        .unwrap()
        .into_inner();
    let over_http = http.get("/v1/calibrations/belt").await;
    assert_eq!(
        serde_json::from_value::<proto::CalibrationInfo>(over_http.body).unwrap(),
        over_grpc
    );
    assert_eq!(http.get("/v1/calibrations").await.status, 200);
    assert_eq!(
        http.delete("/v1/calibrations/belt").await.body["deleted"],
        true
    );

    let deleted = http.delete("/v1/templates/part-a").await;
    assert_eq!(deleted.body, json!({"deleted": true}));
    let again = http.delete("/v1/templates/part-a").await;
    assert_eq!(
        (again.status, again.body.clone()),
        (200, json!({})),
        "false is left out"
    );
    let gone = grpc
        .get_template(proto::GetTemplateRequest {
            template_id: "part-a".into(),
            include_image: false,
        })
        .await
        .unwrap_err();
    assert_eq!(gone.code(), tonic::Code::NotFound);
    server.shutdown(Duration::from_secs(5)).await;
}

/// An error answer: the documented status, a JSON body with the gRPC code's name and a message.
fn assert_error(answer: &Answer, status: u16, code: &str, mentions: &str) {
    assert_eq!(answer.status, status, "{answer:?}");
    assert_eq!(answer.code(), code, "{answer:?}");
    assert!(
        answer.message().contains(mentions),
        "{mentions:?} not in {answer:?}"
    );
    assert_eq!(
        answer.headers["content-type"], "application/json",
        "{answer:?}"
    );
}

/// Every status the document lists is reachable, each with its JSON body; malformed, mistyped,
/// incomplete and oversize bodies are 4xx with a message, never 5xx.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_documented_status_is_reachable_with_a_json_error() {
    let dir = tempfile::tempdir().unwrap();
    let tweaks = [("queue_size", "1"), ("max_batch_size", "1")];
    let (server, _) = start(&settings(dir.path(), &tweaks), untrained_model()).await;
    let http = http_of(&server);
    let send = |path: &'static str, body: &'static [u8]| {
        let http = http.clone();
        async move { http.send("POST", path, body.to_vec(), &[]).await }
    };
    assert_error(
        &send("/v1/templates", b"{").await,
        400,
        "INVALID_ARGUMENT",
        "not a valid RegisterTemplate request",
    );
    assert_error(
        &send("/v1/match", b"").await,
        400,
        "INVALID_ARGUMENT",
        "not a valid Match request",
    );
    for bad in [
        json!({"templateId": 5}),
        json!({"templateId": "x", "bogus": 1}),
        json!({"templateId": "x", "image": {"encoded": "not base64!"}}),
        json!({"templateId": "x", "image": {"encoded": 7}}),
        json!([1, 2]),
    ] {
        let answer = http.post("/v1/templates", &bad).await;
        assert_error(&answer, 400, "INVALID_ARGUMENT", "not a valid");
    }
    // Well-formed, but not what the service takes: its own message.
    assert_error(
        &http
            .post("/v1/templates", &json!({"templateId": "x"}))
            .await,
        400,
        "INVALID_ARGUMENT",
        "image",
    );
    let options = json!({"templateId": "t", "image": {"encoded": base64(&png(&scene(64, 64, 1)))},
        "options": {"minScore": 7}});
    assert_error(
        &http.post("/v1/match", &options).await,
        400,
        "INVALID_ARGUMENT",
        "min_score",
    );
    // Only JSON bodies: a cross-site form or text/plain POST never reaches the service.
    for content_type in ["text/plain", "application/x-www-form-urlencoded"] {
        let body = serde_json::to_vec(&register_body("t", &template_png(1))).unwrap();
        let answer = http
            .send(
                "POST",
                "/v1/templates",
                body,
                &[("content-type", content_type)],
            )
            .await;
        assert_error(&answer, 415, "INVALID_ARGUMENT", "application/json");
    }
    assert_error(
        &http.get("/v1/templates?pageSize=many").await,
        400,
        "INVALID_ARGUMENT",
        "query",
    );

    let registered = http
        .post("/v1/templates", &register_body("t", &template_png(1)))
        .await;
    assert_eq!(registered.status, 200, "{registered:?}");
    assert_error(
        &http
            .post("/v1/templates", &register_body("t", &template_png(2)))
            .await,
        409,
        "ALREADY_EXISTS",
        "replace",
    );
    assert_error(
        &http.get("/v1/templates/nope").await,
        404,
        "NOT_FOUND",
        "nope",
    );
    let unknown =
        json!({"templateId": "nope", "image": {"encoded": base64(&png(&scene(64, 64, 1)))}});
    assert_error(
        &http.post("/v1/match", &unknown).await,
        404,
        "NOT_FOUND",
        "nope",
    );
    assert_error(&http.get("/v2/anything").await, 404, "NOT_FOUND", "/v1");
    assert_error(
        &http.send("PUT", "/v1/match", Vec::new(), &[]).await,
        405,
        "UNIMPLEMENTED",
        "method",
    );
    let frame = json!({"templateId": "t", "image": {"encoded": base64(&png(&scene(160, 160, 2)))},
        "options": {"noRefine": true}});
    let late = http
        .send(
            "POST",
            "/v1/match",
            serde_json::to_vec(&frame).unwrap(),
            &[("grpc-timeout", "1n")],
        )
        .await;
    assert_error(&late, 504, "DEADLINE_EXCEEDED", "deadline");
    // One waiting place: of eight large frames at once, some are turned away.
    let big = json!({"templateId": "t", "image": {"encoded": base64(&png(&scene(768, 768, 5)))},
        "options": {"noRefine": true}});
    let calls: Vec<_> = (0..8)
        .map(|_| {
            let (http, big) = (http.clone(), big.clone());
            tokio::spawn(async move { http.post("/v1/match", &big).await })
        })
        .collect();
    let mut statuses = Vec::new();
    for call in calls {
        let answer = call.await.unwrap();
        if answer.status == 429 {
            assert_error(&answer, 429, "RESOURCE_EXHAUSTED", "queue is full");
        }
        statuses.push(answer.status);
    }
    assert!(
        statuses.contains(&200) && statuses.contains(&429),
        "{statuses:?}"
    );
    assert!(
        statuses.iter().all(|s| [200, 429].contains(s)),
        "{statuses:?}"
    );
    server.shutdown(Duration::from_secs(30)).await;

    // While the model loads: 503 for the API; the page and the document are already there.
    let (gate, gate_rx) = std::sync::mpsc::channel::<()>();
    let slow: posematch::grpc::ModelLoader = Box::new(move || {
        let _ = gate_rx.recv();
        untrained_model()()
    });
    let small = [("max_message_bytes", "65536")];
    let mut server = RunningServer::start(&settings(dir.path(), &small), slow)
        .await
        .unwrap();
    let http = http_of(&server);
    // 65536-byte messages: a JSON body may be about 150 kB.
    let oversize = json!({"templateId": "t", "image": {"encoded": base64(&vec![7u8; 200_000])}});
    assert_error(
        &http.post("/v1/match", &oversize).await,
        413,
        "OUT_OF_RANGE",
        "larger",
    );

    assert_error(
        &http.get("/v1/templates").await,
        503,
        "UNAVAILABLE",
        "loading",
    );
    assert_eq!(http.get("/openapi.json").await.status, 200);
    assert_eq!(http.get("/").await.status, 200);
    gate.send(()).unwrap();
    server.ready().await.unwrap();
    assert_eq!(http.get("/v1/templates").await.status, 200);
    server.shutdown(Duration::from_secs(5)).await;
}

/// With tokens, every `/v1` route needs one (401 with `WWW-Authenticate: Bearer` otherwise,
/// counted like gRPC's refusals); the page, the document and the metrics do not.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bearer_tokens_guard_the_api_but_not_the_page() {
    let dir = tempfile::tempdir().unwrap();
    let tokens = dir.path().join("tokens");
    std::fs::write(&tokens, "alpha\n").unwrap();
    let tokens = tokens.display().to_string();
    let templates = dir.path().join("templates");
    let (server, _) = start(
        &settings(
            &templates,
            &[
                ("auth_tokens_file", &tokens),
                ("max_message_bytes", "65536"),
            ],
        ),
        untrained_model(),
    )
    .await;
    let mut http = http_of(&server);
    // Refused before its body is read: a caller without a token costs no memory (a body over
    // the limit would otherwise be 413).
    // The refusal may reach the client, or the connection close under the body still being
    // written (a broken pipe): either way the server did not take the body.
    let oversize = json!({"templateId": "t", "image": {"encoded": base64(&vec![7u8; 200_000])}});
    match http
        .try_send(
            "POST",
            "/v1/templates",
            serde_json::to_vec(&oversize).unwrap(),
            &[],
        )
        .await
    {
        Ok(refused) => assert_error(&refused, 401, "UNAUTHENTICATED", "Bearer"),
        Err(e) => assert!(
            format!("{e:?}").contains("BrokenPipe") || format!("{e:?}").contains("reset"),
            "{e:?}"
        ),
    }
    let refused = http.get("/v1/templates").await;
    assert_error(&refused, 401, "UNAUTHENTICATED", "Bearer");
    assert_eq!(refused.headers["www-authenticate"], "Bearer");
    let refused = http
        .post("/v1/templates", &register_body("t", &template_png(1)))
        .await;
    assert_error(&refused, 401, "UNAUTHENTICATED", "Bearer");
    http.token = Some("beta".into());
    assert_eq!(http.get("/v1/templates/t").await.status, 401);
    http.token = Some("alpha".into());
    let registered = http
        .post("/v1/templates", &register_body("t", &template_png(1)))
        .await;
    assert_eq!(registered.status, 200, "{registered:?}");
    http.token = None;
    for path in ["/", "/app.js", "/style.css", "/openapi.json", "/metrics"] {
        assert_eq!(http.get(path).await.status, 200, "{path}");
    }
    let metrics = metrics_text(&server).await;
    assert_eq!(
        counter(
            &metrics,
            "posematch_requests_total",
            "code=\"UNAUTHENTICATED\",rpc=\"ListTemplates\""
        ),
        1.0,
        "{metrics}"
    );
    server.shutdown(Duration::from_secs(5)).await;
}

/// `GET /openapi.json` over HTTPS, trusting `ca`, presenting `identity` (certificate and key
/// PEM) when given: the answer's text, or why there was none.
async fn https_get(
    addr: std::net::SocketAddr,
    ca: &str,
    identity: Option<(&str, &str)>,
) -> Result<String, String> {
    use rustls::pki_types::pem::PemObject;
    use rustls::pki_types::{CertificateDer, PrivateKeyDer, ServerName};
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut roots = rustls::RootCertStore::empty();
    roots
        .add(CertificateDer::from_pem_slice(ca.as_bytes()).unwrap())
        .unwrap();
    let builder = rustls::ClientConfig::builder_with_provider(std::sync::Arc::new(
        rustls::crypto::ring::default_provider(),
    ))
    .with_safe_default_protocol_versions()
    .unwrap()
    .with_root_certificates(roots);
    let config = match identity {
        Some((cert, key)) => builder
            .with_client_auth_cert(
                vec![CertificateDer::from_pem_slice(cert.as_bytes()).unwrap()],
                PrivateKeyDer::from_pem_slice(key.as_bytes()).unwrap(),
            )
            .unwrap(),
        None => builder.with_no_client_auth(),
    };
    let connector = tokio_rustls::TlsConnector::from(std::sync::Arc::new(config));
    let exchange = async {
        let tcp = tokio::net::TcpStream::connect(addr)
            .await
            .map_err(|e| e.to_string())?;
        let name = ServerName::try_from("localhost").unwrap();
        let mut stream = connector
            .connect(name, tcp)
            .await
            .map_err(|e| e.to_string())?;
        stream
            .write_all(
                b"GET /openapi.json HTTP/1.1\r\nHost: localhost\r\nConnection: close\r\n\r\n",
            )
            .await
            .map_err(|e| e.to_string())?;
        let mut answer = Vec::new();
        stream
            .read_to_end(&mut answer)
            .await
            .map_err(|e| e.to_string())?;
        Ok(String::from_utf8_lossy(&answer).into_owned())
    };
    tokio::time::timeout(Duration::from_secs(10), exchange)
        .await
        .map_err(|_| "no answer within 10 s".to_string())?
}

/// With TLS, the HTTP port speaks it too (the same files as gRPC): an HTTPS client that trusts
/// the CA is served, plain HTTP is not; with `tls_client_ca`, only clients that present a
/// certificate of that CA.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_http_port_serves_tls_when_grpc_does() {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let dir = tempfile::tempdir().unwrap();
    let pki = crate::security::test_pki();
    let file = |name: &str, pem: &str| {
        let path = dir.path().join(name);
        std::fs::write(&path, pem).unwrap();
        path.display().to_string()
    };
    let (cert, key, ca) = (
        file("server.pem", &pki.server_cert),
        file("server.key", &pki.server_key),
        file("ca.pem", &pki.ca),
    );
    let templates = dir.path().join("templates");
    let tls = [("tls_cert", cert.as_str()), ("tls_key", key.as_str())];
    let mut server = RunningServer::start(&settings(&templates, &tls), untrained_model())
        .await
        .unwrap();
    server.ready().await.unwrap();
    let addr = server.http_addr.unwrap();
    let answer = https_get(addr, &pki.ca, None).await.unwrap();
    assert!(answer.starts_with("HTTP/1.1 200"), "{answer:.200}");
    assert!(answer.contains("\"openapi\""), "{answer:.200}");
    let plain = tokio::time::timeout(Duration::from_secs(10), async {
        let mut tcp = tokio::net::TcpStream::connect(addr).await.unwrap();
        tcp.write_all(b"GET /openapi.json HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
            .await
            .unwrap();
        let mut answer = Vec::new();
        let _ = tcp.read_to_end(&mut answer).await;
        answer
    })
    .await
    .expect("a plain-HTTP client is answered or dropped, not left hanging");
    assert!(
        !String::from_utf8_lossy(&plain).contains("200 OK"),
        "plain HTTP was served on a TLS port"
    );
    server.shutdown(Duration::from_secs(5)).await;

    let mutual = [tls[0], tls[1], ("tls_client_ca", ca.as_str())];
    let mut server = RunningServer::start(&settings(&templates, &mutual), untrained_model())
        .await
        .unwrap();
    server.ready().await.unwrap();
    let addr = server.http_addr.unwrap();
    let anonymous = https_get(addr, &pki.ca, None).await;
    assert!(
        !anonymous
            .as_deref()
            .unwrap_or("")
            .starts_with("HTTP/1.1 200"),
        "a client without a certificate was served: {anonymous:?}"
    );
    let identity = Some((pki.client_cert.as_str(), pki.client_key.as_str()));
    let answer = https_get(addr, &pki.ca, identity).await.unwrap();
    assert!(answer.starts_with("HTTP/1.1 200"), "{answer:.200}");
    server.shutdown(Duration::from_secs(5)).await;
}

/// Whether `value` has the shape `schema` gives it (the subset of JSON Schema the document
/// uses: `$ref`, `allOf`, objects with or without extra properties, arrays, enums and scalar
/// types); the error names the path.
fn conforms(document: &Value, schema: &Value, value: &Value, at: &str) -> Result<(), String> {
    if let Some(reference) = schema["$ref"].as_str() {
        let name = reference.rsplit('/').next().unwrap();
        let target = &document["components"]["schemas"][name];
        assert!(target.is_object(), "{reference} is not in the document");
        return conforms(document, target, value, at);
    }
    if let Some(all) = schema["allOf"].as_array() {
        return all
            .iter()
            .try_for_each(|s| conforms(document, s, value, at));
    }
    if let Some(names) = schema["enum"].as_array()
        && !names.contains(value)
    {
        return Err(format!("{at}: {value} is not one of {names:?}"));
    }
    let fits = match schema["type"].as_str() {
        Some("object") => {
            let Some(object) = value.as_object() else {
                return Err(format!("{at}: {value} is not an object"));
            };
            for (key, item) in object {
                let path = format!("{at}.{key}");
                match (&schema["properties"][key], &schema["additionalProperties"]) {
                    (Value::Null, Value::Bool(false)) => {
                        return Err(format!("{path}: not in the schema"));
                    }
                    (Value::Null, Value::Bool(true) | Value::Null) => {}
                    (Value::Null, extra) => conforms(document, extra, item, &path)?,
                    (property, _) => conforms(document, property, item, &path)?,
                }
            }
            for required in schema["required"].as_array().into_iter().flatten() {
                if !object.contains_key(required.as_str().unwrap()) {
                    return Err(format!("{at}: {required} is missing"));
                }
            }
            true
        }
        Some("array") => {
            let Some(items) = value.as_array() else {
                return Err(format!("{at}: {value} is not an array"));
            };
            for (index, item) in items.iter().enumerate() {
                conforms(document, &schema["items"], item, &format!("{at}[{index}]"))?;
            }
            true
        }
        Some("string") => value.is_string(),
        Some("number") => value.is_number(),
        Some("integer") => value.is_u64() || value.is_i64(),
        Some("boolean") => value.is_boolean(),
        _ => true,
    };
    if fits {
        Ok(())
    } else {
        Err(format!("{at}: {value} is not a {}", schema["type"]))
    }
}

/// `GET /openapi.json` describes the server: every message of the proto has a schema, every
/// documented route is served (its answers among the statuses it lists), and what the server
/// answers — successes and errors — fits the schemas it names.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_openapi_document_matches_what_the_server_does() {
    let dir = tempfile::tempdir().unwrap();
    // Trained weights: the document's match example must find its part (random ones may not).
    let (server, _) = start(&settings(dir.path(), &[]), embedded_model()).await;
    let http = http_of(&server);
    let document = http.get("/openapi.json").await.body;
    assert_eq!(document["openapi"], "3.0.3");
    let schemas = &document["components"]["schemas"];
    for message in [
        "RegisterTemplateRequest",
        "TemplateInfo",
        "MatchRequest",
        "MatchOptions",
        "MatchResponse",
        "Pose",
        "Image",
        "RawImage",
        "RawImage.Format",
        "Polarity",
        "CalibrationInfo.Model",
        "Error",
    ] {
        assert!(schemas[message].is_object(), "{message} has no schema");
    }
    let pose = &schemas["Pose"]["properties"];
    assert!(pose["angleDeg"].is_object() && pose["scaleX"].is_object());
    assert!(
        pose["score"]["description"]
            .as_str()
            .unwrap()
            .contains("ZNCC"),
        "proto comments become descriptions"
    );

    // The document's own examples work as they stand: the crop at (30, 40), 24x24, is found.
    let example = |path: &str| {
        document["paths"][path]["post"]["requestBody"]["content"]["application/json"]["example"]
            .clone()
    };
    for path in ["/v1/templates", "/v1/calibrations", "/v1/match"] {
        let answer = http.post(path, &example(path)).await;
        assert_eq!(answer.status, 200, "the example of POST {path}: {answer:?}");
        if path == "/v1/match" {
            let pose = &answer.body["poses"][0];
            let at = (pose["x"].as_f64().unwrap(), pose["y"].as_f64().unwrap());
            assert!(
                (at.0 - 41.5).abs() < 1.0 && (at.1 - 51.5).abs() < 1.0,
                "{answer:?}"
            );
        }
    }

    let check = |answer: &Answer, path: &str, method: &str| {
        let operation = &document["paths"][path][method];
        assert!(operation.is_object(), "{method} {path} is not documented");
        let status = answer.status.to_string();
        let response = &operation["responses"][&status];
        assert!(
            response.is_object(),
            "{method} {path} answered {status}, which it does not document: {answer:?}"
        );
        let response = match response["$ref"].as_str() {
            Some(r) => &document["components"]["responses"][r.rsplit('/').next().unwrap()],
            None => response,
        };
        let schema = &response["content"]["application/json"]["schema"];
        if let Err(e) = conforms(&document, schema, &answer.body, "body") {
            panic!("{method} {path} ({status}): {e}");
        }
    };
    let frame = png(&scene(200, 200, 1));
    let flow = [
        (
            "post",
            "/v1/templates",
            "/v1/templates",
            register_body("part-a", &template_png(1)),
        ),
        (
            "post",
            "/v1/templates",
            "/v1/templates",
            register_body("part-a", &template_png(2)),
        ),
        ("get", "/v1/templates", "/v1/templates", Value::Null),
        (
            "get",
            "/v1/templates/{template_id}",
            "/v1/templates/part-a?includeImage=true",
            Value::Null,
        ),
        (
            "get",
            "/v1/templates/{template_id}",
            "/v1/templates/missing",
            Value::Null,
        ),
        (
            "post",
            "/v1/match",
            "/v1/match",
            serde_json::to_value(ncc_match(&["part-a"], &frame)).unwrap(),
        ),
        ("post", "/v1/match", "/v1/match", json!({"image": 3})),
        (
            "post",
            "/v1/calibrations",
            "/v1/calibrations",
            json!({"calibrationId": "c", "unit": "mm", "points": [
            {"imageX": 0, "imageY": 0, "worldX": 0, "worldY": 0},
            {"imageX": 10, "imageY": 0, "worldX": 1, "worldY": 0},
            {"imageX": 0, "imageY": 10, "worldX": 0, "worldY": 1},
            {"imageX": 10, "imageY": 10, "worldX": 1, "worldY": 1.1}]}),
        ),
        ("get", "/v1/calibrations", "/v1/calibrations", Value::Null),
        (
            "get",
            "/v1/calibrations/{calibration_id}",
            "/v1/calibrations/c",
            Value::Null,
        ),
        (
            "delete",
            "/v1/calibrations/{calibration_id}",
            "/v1/calibrations/c",
            Value::Null,
        ),
        (
            "delete",
            "/v1/templates/{template_id}",
            "/v1/templates/part-a",
            Value::Null,
        ),
    ];
    let mut answered = std::collections::HashSet::new();
    for (method, documented, path, body) in flow {
        let answer = match method {
            "post" => http.post(path, &body).await,
            "get" => http.get(path).await,
            _ => http.delete(path).await,
        };
        check(&answer, documented, method);
        answered.insert((documented, method));
    }
    // A body without `Content-Type: application/json` is refused as documented (415).
    for path in ["/v1/templates", "/v1/match", "/v1/calibrations"] {
        let answer = http
            .send(
                "POST",
                path,
                b"{}".to_vec(),
                &[("content-type", "text/plain")],
            )
            .await;
        assert_eq!(answer.status, 415, "{answer:?}");
        check(&answer, path, "post");
    }
    // Every documented operation was exercised.
    for (path, operations) in document["paths"].as_object().unwrap() {
        for method in operations.as_object().unwrap().keys() {
            assert!(
                answered.contains(&(path.as_str(), method.as_str())),
                "{method} {path} is documented but not exercised here"
            );
        }
    }
    server.shutdown(Duration::from_secs(5)).await;
}

/// The page's files carry their types and a content security policy.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_setup_page_is_served_with_its_policy() {
    let dir = tempfile::tempdir().unwrap();
    let (server, _): (
        RunningServer,
        proto::pose_matcher_client::PoseMatcherClient<Channel>,
    ) = start(&settings(dir.path(), &[]), untrained_model()).await;
    let http = http_of(&server);
    for (path, kind, contains) in [
        ("/", "text/html", "<title>PoseMatch setup</title>"),
        ("/app.js", "text/javascript", "/v1/match"),
        ("/style.css", "text/css", "{"),
    ] {
        let answer = http.get(path).await;
        assert_eq!(answer.status, 200, "{path}");
        let content_type = answer.headers["content-type"].to_str().unwrap();
        assert!(content_type.starts_with(kind), "{path}: {content_type}");
        assert!(
            answer.headers["content-security-policy"]
                .to_str()
                .unwrap()
                .contains("default-src 'self'"),
            "{path}"
        );
        assert!(
            answer.body.as_str().unwrap().contains(contains),
            "{path} lacks {contains:?}"
        );
    }
    server.shutdown(Duration::from_secs(5)).await;
}
