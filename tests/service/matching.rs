//! Match and MatchStream: answers, raw buffers, regions of interest and streams; the official
//! checkpoint over gRPC (accuracy on the fixture; skips without `../shared/reference`); the
//! classical matcher over gRPC.

use std::time::Duration;

use posematch::grpc::ModelLoader;
use posematch::grpc::proto::{self, image::Data, raw_image::Format};
use posematch::imaging::InputConvention;
use posematch::matcher::Matcher;
use posematch::model::{load_weights, select_device};
use tonic::Code;

use crate::common;
use crate::common::service::*;

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
        template_ids: Vec::new(),
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

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn several_templates_in_one_request_answer_each_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let (server, mut client) = start(&settings(dir.path(), &[]), untrained_model()).await;
    let frame = scene(200, 200, 3);
    // Two distinct crops of one frame, and a third template from another scene.
    let crop = |x, y| png(&image::imageops::crop_imm(&frame, x, y, 36, 40).to_image());
    for (id, bytes) in [("left", crop(30, 40)), ("right", crop(120, 110))] {
        client
            .register_template(register_request(id, bytes))
            .await
            .unwrap();
    }
    client
        .register_template(register_request("other", template_png(9)))
        .await
        .unwrap();
    let several = |ids: &[&str], method: proto::Method| proto::MatchRequest {
        template_ids: ids.iter().map(|id| id.to_string()).collect(),
        image: encoded(png(&frame)),
        options: Some(proto::MatchOptions {
            method: method as i32,
            max_instances: 1,
            min_score: 0.01,
            ..Default::default()
        }),
        request_id: "both".into(),
        ..Default::default()
    };

    // The classical matcher finds each crop where it was cut, and names it.
    let answer = client
        .r#match(several(&["left", "right"], proto::Method::Ncc))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(answer.template_ids, ["left", "right"]);
    assert!(answer.template_id.is_empty());
    let centre = |id: &str| {
        let pose = answer
            .poses
            .iter()
            .find(|p| p.template_id == id)
            .unwrap_or_else(|| panic!("no pose of {id}: {:?}", answer.poses));
        (pose.x, pose.y)
    };
    let (lx, ly) = centre("left");
    let (rx, ry) = centre("right");
    assert!(
        (lx - 47.5).abs() < 0.5 && (ly - 59.5).abs() < 0.5,
        "{lx} {ly}"
    );
    assert!(
        (rx - 137.5).abs() < 0.5 && (ry - 129.5).abs() < 0.5,
        "{rx} {ry}"
    );
    assert!(
        answer.poses.windows(2).all(|w| w[0].score >= w[1].score),
        "best score first"
    );

    // The network path answers each template as a request of its own would (same poses),
    // though the searches ran in one batch.
    let together = client
        .r#match(several(&["left", "other"], proto::Method::Tdcm))
        .await
        .unwrap()
        .into_inner();
    for id in ["left", "other"] {
        let alone = client
            .r#match(several(&[id], proto::Method::Tdcm))
            .await
            .unwrap()
            .into_inner();
        assert!(alone.poses.iter().all(|p| p.template_id == id));
        let mine: Vec<proto::Pose> = together
            .poses
            .iter()
            .filter(|p| p.template_id == id)
            .cloned()
            .collect();
        assert_same_poses(&mine, &alone.poses);
    }
    // A single template_id names its template in every pose too.
    let single = client
        .r#match(match_request("left", png(&frame), "one"))
        .await
        .unwrap()
        .into_inner();
    assert!(single.poses.iter().all(|p| p.template_id == "left"));

    // Wrong lists are refused before any search, saying what to fix.
    let refused = |request: proto::MatchRequest| {
        let mut client = client.clone();
        async move { client.r#match(request).await.unwrap_err() }
    };
    let unknown = refused(several(&["left", "nope"], proto::Method::Tdcm)).await;
    assert_eq!(unknown.code(), Code::NotFound, "{unknown:?}");
    let twice = refused(several(&["left", "left"], proto::Method::Tdcm)).await;
    assert_eq!(twice.code(), Code::InvalidArgument);
    assert!(twice.message().contains("twice"), "{}", twice.message());
    let names: Vec<String> = (0..17).map(|i| format!("t{i}")).collect();
    let names: Vec<&str> = names.iter().map(String::as_str).collect();
    let many = refused(several(&names, proto::Method::Tdcm)).await;
    assert_eq!(many.code(), Code::InvalidArgument);
    assert!(many.message().contains("at most 16"), "{}", many.message());
    let mut both = several(&["left"], proto::Method::Tdcm);
    both.template_id = "right".into();
    let both = refused(both).await;
    assert_eq!(both.code(), Code::InvalidArgument);
    assert!(both.message().contains("both"), "{}", both.message());
    server.shutdown(Duration::from_secs(5)).await;
}

/// `suppress_across_templates`: two templates cut from one part (a crop and a slightly larger
/// crop around it) both find that part; asked to, the answer keeps only the better-scoring of
/// the two, and a third template's part elsewhere stays.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn overlapping_answers_of_different_templates_can_be_one_object() {
    let dir = tempfile::tempdir().unwrap();
    let (server, mut client) = start(&settings(dir.path(), &[]), untrained_model()).await;
    let frame = scene(200, 200, 3);
    let crop = |x, y, w, h| png(&image::imageops::crop_imm(&frame, x, y, w, h).to_image());
    for (id, bytes) in [
        ("part", crop(30, 40, 36, 40)),
        ("part-wider", crop(26, 38, 44, 44)),
        ("elsewhere", crop(120, 110, 36, 40)),
    ] {
        client
            .register_template(register_request(id, bytes))
            .await
            .unwrap();
    }
    let request = |suppress: bool| proto::MatchRequest {
        template_ids: vec!["part".into(), "part-wider".into(), "elsewhere".into()],
        image: encoded(png(&frame)),
        options: Some(proto::MatchOptions {
            method: proto::Method::Ncc as i32,
            max_instances: 1,
            min_score: 0.5,
            suppress_across_templates: suppress,
            ..Default::default()
        }),
        ..Default::default()
    };
    let ids = |answer: &proto::MatchResponse| -> Vec<String> {
        answer.poses.iter().map(|p| p.template_id.clone()).collect()
    };
    let each = client.r#match(request(false)).await.unwrap().into_inner();
    let mut found = ids(&each);
    found.sort();
    assert_eq!(found, ["elsewhere", "part", "part-wider"], "{each:?}");
    let score_of = |id: &str| {
        each.poses
            .iter()
            .find(|p| p.template_id == id)
            .unwrap()
            .score
    };
    let better = if score_of("part") >= score_of("part-wider") {
        "part"
    } else {
        "part-wider"
    };

    let one_each = client.r#match(request(true)).await.unwrap().into_inner();
    let mut found = ids(&one_each);
    found.sort();
    let mut expected = vec![better, "elsewhere"];
    expected.sort();
    assert_eq!(found, expected, "{one_each:?}");
    server.shutdown(Duration::from_secs(5)).await;
}
