//! The standard gRPC health service: NOT_SERVING while the model loads (liveness SERVING
//! meanwhile), SERVING once it is loaded.

use std::time::Duration;

use posematch::grpc::proto;
use posematch::grpc::proto::pose_matcher_client::PoseMatcherClient;
use posematch::grpc::{ModelLoader, RunningServer};
use tonic::Code;
use tonic::transport::Channel;

use crate::common::service::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn health_turns_serving_once_the_model_is_loaded() {
    use tonic_health::pb::health_check_response::ServingStatus;
    use tonic_health::pb::{HealthCheckRequest, health_client::HealthClient};
    let dir = tempfile::tempdir().unwrap();
    let (gate_tx, gate_rx) = std::sync::mpsc::channel::<()>();
    let slow_loader: ModelLoader = Box::new(move || {
        let _ = gate_rx.recv();
        untrained_model()()
    });
    let mut server = RunningServer::start(&settings(dir.path(), &[]), slow_loader)
        .await
        .unwrap();
    let channel = Channel::from_shared(format!("http://{}", server.grpc_addr))
        .unwrap()
        .connect()
        .await
        .unwrap();
    let mut health = HealthClient::new(channel.clone());
    let check = |service: &str| HealthCheckRequest {
        service: service.into(),
    };
    let status = health.check(check("")).await.unwrap().into_inner().status;
    assert_eq!(status, ServingStatus::NotServing as i32);
    // Loading is progress: a liveness probe must not restart a replica for it.
    let liveness = posematch::grpc::LIVENESS_SERVICE;
    let status = health
        .check(check(liveness))
        .await
        .unwrap()
        .into_inner()
        .status;
    assert_eq!(status, ServingStatus::Serving as i32);
    let early = PoseMatcherClient::new(channel.clone())
        .get_template(proto::GetTemplateRequest {
            template_id: "x".into(),
            ..Default::default()
        })
        .await
        .unwrap_err();
    assert_eq!(early.code(), Code::Unavailable);
    gate_tx.send(()).unwrap();
    server.ready().await.unwrap();
    for service in ["", "posematch.v1.PoseMatcher"] {
        let status = health
            .check(check(service))
            .await
            .unwrap()
            .into_inner()
            .status;
        assert_eq!(status, ServingStatus::Serving as i32, "{service}");
    }
    server.shutdown(Duration::from_secs(5)).await;
}
