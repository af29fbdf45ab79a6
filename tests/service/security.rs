//! Who may call: TLS (and client certificates), bearer tokens, and their reload on SIGHUP;
//! request IDs cannot forge log lines.

use std::time::Duration;

use posematch::grpc::RunningServer;
use posematch::grpc::proto;
use posematch::grpc::proto::pose_matcher_client::PoseMatcherClient;
use tonic::transport::Channel;
use tonic::{Code, Status};

use crate::common::service::*;

/// PEM files of a test CA, a server certificate for `localhost` and a client certificate, all
/// generated here.
pub(crate) struct TestPki {
    pub ca: String,
    pub server_cert: String,
    pub server_key: String,
    pub client_cert: String,
    pub client_key: String,
}

pub(crate) fn test_pki() -> TestPki {
    use rcgen::{BasicConstraints, CertificateParams, DnType, IsCa, Issuer, KeyPair};
    let ca_key = KeyPair::generate().unwrap();
    let mut ca_params = CertificateParams::new(Vec::<String>::new()).unwrap();
    ca_params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    ca_params
        .distinguished_name
        .push(DnType::CommonName, "PoseMatch test CA");
    let ca = ca_params.self_signed(&ca_key).unwrap().pem();
    let issuer = Issuer::new(ca_params, ca_key);
    let leaf = |name: &str| {
        let key = KeyPair::generate().unwrap();
        let cert = CertificateParams::new(vec![name.to_string()])
            .unwrap()
            .signed_by(&key, &issuer)
            .unwrap();
        (cert.pem(), key.serialize_pem())
    };
    let (server_cert, server_key) = leaf("localhost");
    let (client_cert, client_key) = leaf("line-4-plc");
    TestPki {
        ca,
        server_cert,
        server_key,
        client_cert,
        client_key,
    }
}

/// A TLS client for `addr`, trusting `ca`, optionally presenting a client certificate.
async fn tls_client(
    addr: std::net::SocketAddr,
    ca: &str,
    identity: Option<(&str, &str)>,
) -> Result<PoseMatcherClient<Channel>, tonic::transport::Error> {
    use tonic::transport::{Certificate, ClientTlsConfig, Identity};
    let mut tls = ClientTlsConfig::new()
        .ca_certificate(Certificate::from_pem(ca))
        .domain_name("localhost");
    if let Some((cert, key)) = identity {
        tls = tls.identity(Identity::from_pem(cert, key));
    }
    let channel = Channel::from_shared(format!("https://{addr}"))
        .unwrap()
        .tls_config(tls)?
        .connect()
        .await?;
    Ok(PoseMatcherClient::new(channel))
}

async fn lists(client: &mut PoseMatcherClient<Channel>) -> Result<(), Status> {
    client
        .list_templates(proto::ListTemplatesRequest::default())
        .await
        .map(drop)
}

/// TLS with a certificate generated here: a client that trusts its CA is served, a plaintext
/// client is not; with `tls_client_ca`, only clients that present a certificate of that CA.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tls_serves_trusting_clients_and_refuses_plaintext() {
    let dir = tempfile::tempdir().unwrap();
    let pki = test_pki();
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
    let mut client = tls_client(server.grpc_addr, &pki.ca, None).await.unwrap();
    lists(&mut client).await.expect("a TLS client is served");
    let plaintext = async {
        let mut client = PoseMatcherClient::connect(format!("http://{}", server.grpc_addr))
            .await
            .map_err(|e| e.to_string())?;
        lists(&mut client).await.map_err(|e| e.to_string())
    };
    let refused = tokio::time::timeout(Duration::from_secs(10), plaintext)
        .await
        .expect("a plaintext client is answered, not left hanging");
    assert!(refused.is_err(), "a plaintext client was served");
    server.shutdown(Duration::from_secs(5)).await;

    let mutual = [tls[0], tls[1], ("tls_client_ca", ca.as_str())];
    let mut server = RunningServer::start(&settings(&templates, &mutual), untrained_model())
        .await
        .unwrap();
    server.ready().await.unwrap();
    let anonymous = match tls_client(server.grpc_addr, &pki.ca, None).await {
        Ok(mut client) => lists(&mut client).await.is_ok(),
        Err(_) => false,
    };
    assert!(!anonymous, "a client without a certificate was served");
    let identity = Some((pki.client_cert.as_str(), pki.client_key.as_str()));
    let mut client = tls_client(server.grpc_addr, &pki.ca, identity)
        .await
        .unwrap();
    lists(&mut client)
        .await
        .expect("a client with a certificate of the CA is served");
    server.shutdown(Duration::from_secs(5)).await;
}

fn with_token<T>(message: T, token: &str) -> tonic::Request<T> {
    let mut request = tonic::Request::new(message);
    request
        .metadata_mut()
        .insert("authorization", format!("Bearer {token}").parse().unwrap());
    request
}

/// Bearer tokens: calls without a valid one are refused (and counted), health stays open,
/// reflection can be switched off.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bearer_tokens_guard_every_call_but_health() {
    let dir = tempfile::tempdir().unwrap();
    let tokens = dir.path().join("tokens");
    std::fs::write(&tokens, "# line 4\nalpha\n").unwrap();
    let tokens = tokens.display().to_string();
    let (server, mut client) = start(
        &settings(
            &dir.path().join("templates"),
            &[
                ("auth_tokens_file", tokens.as_str()),
                ("reflection", "false"),
            ],
        ),
        untrained_model(),
    )
    .await;
    let refused = lists(&mut client).await.unwrap_err();
    assert_eq!(refused.code(), Code::Unauthenticated, "{refused:?}");
    assert!(refused.message().contains("Bearer"), "{refused:?}");
    let wrong = client
        .list_templates(with_token(proto::ListTemplatesRequest::default(), "beta"))
        .await
        .unwrap_err();
    assert_eq!(wrong.code(), Code::Unauthenticated, "{wrong:?}");
    client
        .list_templates(with_token(proto::ListTemplatesRequest::default(), "alpha"))
        .await
        .expect("a valid token is served");
    let channel = Channel::from_shared(format!("http://{}", server.grpc_addr))
        .unwrap()
        .connect()
        .await
        .unwrap();
    let health = tonic_health::pb::health_client::HealthClient::new(channel.clone())
        .check(tonic_health::pb::HealthCheckRequest::default())
        .await
        .expect("health needs no token")
        .into_inner();
    assert_eq!(
        health.status,
        tonic_health::pb::health_check_response::ServingStatus::Serving as i32
    );
    let reflection = tonic_reflection::pb::v1::server_reflection_client::ServerReflectionClient::new(channel)
        .server_reflection_info(with_token(
            tokio_stream::iter([tonic_reflection::pb::v1::ServerReflectionRequest {
                host: String::new(),
                message_request: Some(
                    tonic_reflection::pb::v1::server_reflection_request::MessageRequest::ListServices(
                        String::new(),
                    ),
                ),
            }]),
            "alpha",
        ))
        .await
        .unwrap_err();
    assert_eq!(
        reflection.code(),
        Code::Unimplemented,
        "reflection is off: {reflection:?}"
    );
    let metrics = metrics_text(&server).await;
    assert_eq!(
        counter(
            &metrics,
            "posematch_requests_total",
            "code=\"UNAUTHENTICATED\",rpc=\"ListTemplates\""
        ),
        2.0,
        "{metrics}"
    );
    server.shutdown(Duration::from_secs(5)).await;
}

/// `posematch serve --auth-tokens-file`: SIGHUP swaps the tokens without a restart; IDs with
/// newlines and terminal escapes cannot forge or colour log lines.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sighup_reloads_the_tokens_and_logs_escape_ids() {
    let dir = tempfile::tempdir().unwrap();
    let tokens = dir.path().join("tokens");
    std::fs::write(&tokens, "alpha\n").unwrap();
    let server = ChildServer::start_in(&dir.path().join("templates"), |command| {
        command.arg("--auth-tokens-file").arg(&tokens);
    });
    let mut client = server.client().await;
    let list = |token: &str| with_token(proto::ListTemplatesRequest::default(), token);
    client.list_templates(list("alpha")).await.unwrap();
    let mut register = register_request("t", template_png(1));
    register.labels.clear();
    client
        .register_template(with_token(register, "alpha"))
        .await
        .unwrap();
    let forged = "frame-1\nERROR FORGED a line\u{1b}[31m";
    client
        .r#match(with_token(
            match_request("t", png(&scene(96, 96, 1)), forged),
            "alpha",
        ))
        .await
        .unwrap();
    std::fs::write(&tokens, "beta\n").unwrap();
    let hup = std::process::Command::new("kill")
        .args(["-HUP", &server.child.id().to_string()])
        .status()
        .unwrap();
    assert!(hup.success());
    let mut swapped = false;
    for _ in 0..100 {
        let alpha = client.list_templates(list("alpha")).await;
        if alpha
            .as_ref()
            .is_err_and(|s| s.code() == Code::Unauthenticated)
        {
            swapped = true;
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert!(swapped, "the old token is still accepted after SIGHUP");
    client
        .list_templates(list("beta"))
        .await
        .expect("the new token");
    assert_eq!(
        server.health().await,
        tonic_health::pb::health_check_response::ServingStatus::Serving as i32
    );
    let log = server.log.lock().unwrap().clone();
    assert!(log.iter().any(|l| l.contains("frame-1")), "{log:?}");
    assert!(
        !log.iter()
            .any(|l| l.starts_with("ERROR FORGED") || l.contains('\u{1b}')),
        "a forged or coloured line: {log:?}"
    );
    assert!(
        log.iter().any(|l| l.contains("bearer tokens reloaded")),
        "{log:?}"
    );
}
