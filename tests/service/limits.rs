//! What the service refuses, and how: oversize messages, bad requests, a full queue, an
//! expired deadline, a search beyond the compute budget, and decompression bombs.

use std::time::Duration;

use posematch::grpc::proto::pose_matcher_client::PoseMatcherClient;
use posematch::grpc::proto::{self, image::Data, raw_image::Format};
use tonic::Code;

use crate::common;
use crate::common::service::*;

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

/// A 16x16 JPEG whose frame header is patched to announce `w x h` (about 700 bytes).
fn jpeg_claiming(w: u16, h: u16) -> Vec<u8> {
    let mut bytes = encode_image(
        &image::RgbImage::from_pixel(16, 16, image::Rgb([90, 120, 150])),
        image::ImageFormat::Jpeg,
    );
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
    encode_image(&image::GrayImage::new(side, side), image::ImageFormat::Png)
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

/// A client that sends a megabyte where an ID goes gets a status whose message quotes a
/// hundred characters of it at most: a status travels in a header, and clients refuse large
/// ones (they would report "metadata size exceeds hard limit" instead of the answer).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_megabyte_template_id_is_answered_with_a_short_message() {
    let dir = tempfile::tempdir().unwrap();
    let (_server, mut client) = start(&settings(dir.path(), &[]), untrained_model()).await;
    let huge = "x".repeat(1 << 20);
    let short = |status: &tonic::Status, code: Code| {
        assert_eq!(status.code(), code, "{:.300}", status.message());
        assert!(
            status.message().len() < 400,
            "a {} byte message",
            status.message().len()
        );
    };
    let status = client
        .register_template(register_request(&huge, template_png(1)))
        .await
        .unwrap_err();
    short(&status, Code::InvalidArgument);
    assert!(status.message().contains("template_id"), "{status:?}");
    let status = client
        .get_template(proto::GetTemplateRequest {
            template_id: huge.clone(),
            ..Default::default()
        })
        .await
        .unwrap_err();
    short(&status, Code::NotFound);
    assert!(status.message().contains("1048576 bytes"), "{status:?}");
    let status = client
        .r#match(match_request(&huge, png(&scene(96, 96, 1)), "r"))
        .await
        .unwrap_err();
    short(&status, Code::NotFound);
    let deleted = client
        .delete_template(proto::DeleteTemplateRequest {
            template_id: huge.clone(),
        })
        .await
        .unwrap()
        .into_inner();
    assert!(!deleted.deleted);
    // Through a stream, the request ID is quoted too.
    let mut request = match_request(&huge, png(&scene(96, 96, 1)), &huge);
    request.template_id = "missing".into();
    let mut stream = client
        .match_stream(tokio_stream::iter(vec![request]))
        .await
        .unwrap()
        .into_inner();
    let status = stream.message().await.unwrap_err();
    short(&status, Code::NotFound);
}

/// A template that does not fit on the disk answers RESOURCE_EXHAUSTED ("template store is
/// full"), which a client can act on, not INTERNAL; nothing half-written stays registered and
/// the server goes on serving. The disk is "full" for a server process whose files may not
/// grow beyond a few kilobytes (RLIMIT_FSIZE; writes past it fail with EFBIG, SIGXFSZ ignored).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_template_disk_answers_resource_exhausted() {
    use std::os::unix::process::CommandExt;
    let dir = tempfile::tempdir().unwrap();
    let server = ChildServer::start_in(&dir.path().join("templates"), |command| {
        // SAFETY: between fork and exec only async-signal-safe calls (signal, setrlimit).
        unsafe {
            command.pre_exec(|| {
                libc::signal(libc::SIGXFSZ, libc::SIG_IGN);
                let limit = libc::rlimit {
                    rlim_cur: 3000,
                    rlim_max: 3000,
                };
                if libc::setrlimit(libc::RLIMIT_FSIZE, &limit) != 0 {
                    return Err(std::io::Error::last_os_error());
                }
                Ok(())
            });
        }
    });
    let mut client = server.client().await;
    let large = png(&image::imageops::crop_imm(&scene(300, 300, 3), 20, 20, 160, 160).to_image());
    let status = client
        .register_template(register_request("big", large))
        .await
        .unwrap_err();
    assert_eq!(status.code(), Code::ResourceExhausted, "{status:?}");
    assert!(
        status.message().contains("template store is full"),
        "{status:?}"
    );
    let listed = client
        .list_templates(proto::ListTemplatesRequest::default())
        .await
        .unwrap()
        .into_inner();
    assert!(listed.templates.is_empty(), "{listed:?}");
    assert_eq!(server.health().await, SERVING);
}
