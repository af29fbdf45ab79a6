//! The template registry over gRPC: the RPCs' contract, a restart that keeps every
//! acknowledged template, stray files in the template directory, SIGKILL during a replacement,
//! and a template directory the server cannot write.

use std::time::Duration;

use posematch::grpc::proto;
use tonic::Code;

use crate::common::service::*;

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
        // Deliberate, not a wait for anything: each round's kill lands at another point of the
        // replacements.
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
    // Launched, not started: this server never turns SERVING.
    let server = ChildServer::launch_in(&templates, |command| {
        if root {
            command.uid(65534).gid(65534);
        }
    });
    // Polled for up to 2 minutes: the server loads the model before it checks the directory.
    let mut said = false;
    for _ in 0..2400 {
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

/// A mask is checked before anything is stored, kept with the template (its content hash
/// covers it) and returned by GetTemplate; bad options of the new kinds name their field.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn masks_are_checked_stored_and_returned_and_new_options_are_validated() {
    let dir = tempfile::tempdir().unwrap();
    let (server, mut client) = start(&settings(dir.path(), &[]), untrained_model()).await;
    let mask_png = |w: u32, h: u32, used: fn(u32, u32) -> bool| {
        png(&image::RgbImage::from_fn(w, h, |x, y| {
            let v = if used(x, y) { 255 } else { 0 };
            image::Rgb([v, v, v])
        }))
    };
    let with_mask = |id: &str, mask: Vec<u8>| proto::RegisterTemplateRequest {
        mask: encoded(mask),
        ..register_request(id, template_png(1))
    };
    for (what, mask, needle) in [
        (
            "a mask of another size",
            mask_png(36, 36, |_, _| true),
            "36x40",
        ),
        (
            "a mask that uses nothing",
            mask_png(36, 40, |_, _| false),
            "0 pixels",
        ),
        ("an undecodable mask", b"not a png".to_vec(), "mask"),
    ] {
        let status = client
            .register_template(with_mask("masked", mask))
            .await
            .unwrap_err();
        assert_eq!(status.code(), Code::InvalidArgument, "{what}: {status:?}");
        assert!(
            status.message().contains("mask") && status.message().contains(needle),
            "{what}: {}",
            status.message()
        );
    }
    // Nothing was stored by the refused registrations.
    let missing = client
        .get_template(proto::GetTemplateRequest {
            template_id: "masked".into(),
            include_image: false,
        })
        .await
        .unwrap_err();
    assert_eq!(missing.code(), Code::NotFound);

    let left_half = mask_png(36, 40, |x, _| x < 18);
    let masked = client
        .register_template(with_mask("masked", left_half.clone()))
        .await
        .unwrap()
        .into_inner();
    let plain = client
        .register_template(register_request("plain", template_png(1)))
        .await
        .unwrap()
        .into_inner();
    assert_ne!(masked.content_sha256, plain.content_sha256);
    // The same pixels without the mask are another template under the ID.
    let clash = client
        .register_template(register_request("masked", template_png(1)))
        .await
        .unwrap_err();
    assert_eq!(clash.code(), Code::AlreadyExists, "{clash:?}");
    let full = client
        .get_template(proto::GetTemplateRequest {
            template_id: "masked".into(),
            include_image: true,
        })
        .await
        .unwrap()
        .into_inner();
    let Some(proto::image::Data::Encoded(returned)) = full.mask.and_then(|m| m.data) else {
        panic!("GetTemplate returned no mask");
    };
    let returned = image::load_from_memory(&returned).unwrap().to_luma8();
    assert_eq!(returned.dimensions(), (36, 40));
    assert!(
        returned
            .enumerate_pixels()
            .all(|(x, _, p)| (p.0[0] == 255) == (x < 18))
    );
    let unmasked = client
        .get_template(proto::GetTemplateRequest {
            template_id: "plain".into(),
            include_image: true,
        })
        .await
        .unwrap()
        .into_inner();
    assert!(unmasked.mask.is_none());

    // New match options are validated by name.
    for (options, field) in [
        (
            proto::MatchOptions {
                timeout_ms: Some(0),
                ..Default::default()
            },
            "timeout_ms",
        ),
        (
            proto::MatchOptions {
                polarity: 7,
                ..Default::default()
            },
            "polarity",
        ),
    ] {
        let mut request = match_request("masked", png(&scene(120, 120, 4)), "r");
        request.options = Some(options);
        let status = client.r#match(request).await.unwrap_err();
        assert_eq!(status.code(), Code::InvalidArgument, "{field}: {status:?}");
        assert!(status.message().contains(field), "{}", status.message());
    }
    drop(server);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn origins_and_calibrations_place_poses_in_pixels_and_the_world() {
    let dir = tempfile::tempdir().unwrap();
    let (server, mut client) = start(&settings(dir.path(), &[]), untrained_model()).await;
    let point = |image: [f64; 2], world: [f64; 2]| proto::CalibrationPoint {
        image_x: image[0],
        image_y: image[1],
        world_x: world[0],
        world_y: world[1],
    };
    // An exact synthetic calibration: a camera looking at the plane at an angle.
    let view = |p: [f64; 2]| {
        let w = 0.0004 * p[0] - 0.0002 * p[1] + 1.0;
        [
            (0.21 * p[0] + 0.03 * p[1] - 12.0) / w,
            (-0.02 * p[0] + 0.19 * p[1] + 40.0) / w,
        ]
    };
    let calibrate =
        |id: &str, image: &[[f64; 2]], replace: bool| proto::RegisterCalibrationRequest {
            calibration_id: id.into(),
            points: image.iter().map(|&p| point(p, view(p))).collect(),
            unit: "mm".into(),
            replace,
        };
    let corners = [
        [0.0, 0.0],
        [199.0, 0.0],
        [199.0, 199.0],
        [0.0, 199.0],
        [90.0, 120.0],
    ];

    // Points that determine no map, and unknown IDs: named, and nothing stored.
    for (what, points, needle) in [
        (
            "collinear",
            vec![[0.0, 0.0], [50.0, 50.0], [100.0, 100.0]],
            "one line",
        ),
        (
            "duplicated",
            vec![[0.0, 0.0], [100.0, 0.0], [0.0, 100.0], [100.0, 0.0]],
            "same image position",
        ),
        (
            "too few",
            vec![[0.0, 0.0], [100.0, 0.0]],
            "3 to 1000 points",
        ),
    ] {
        let status = client
            .register_calibration(calibrate("belt", &points, false))
            .await
            .unwrap_err();
        assert_eq!(status.code(), Code::InvalidArgument, "{what}: {status:?}");
        assert!(
            status.message().contains(needle),
            "{what}: {}",
            status.message()
        );
    }
    let unknown = client
        .get_calibration(proto::GetCalibrationRequest {
            calibration_id: "belt".into(),
        })
        .await
        .unwrap_err();
    assert_eq!(unknown.code(), Code::NotFound, "{unknown:?}");

    let belt = client
        .register_calibration(calibrate("belt", &corners, false))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(
        belt.model,
        proto::calibration_info::Model::Homography as i32
    );
    assert!(belt.rms_residual < 1e-6, "{}", belt.rms_residual);
    assert_eq!(
        (belt.points.len(), belt.unit.as_str(), belt.version),
        (5, "mm", 1)
    );
    // The same again is a no-op; other points need replace.
    let again = client
        .register_calibration(calibrate("belt", &corners, false))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(again, belt);
    let three = [[0.0, 0.0], [199.0, 0.0], [0.0, 199.0]];
    let clash = client
        .register_calibration(calibrate("belt", &three, false))
        .await
        .unwrap_err();
    assert_eq!(clash.code(), Code::AlreadyExists, "{clash:?}");
    let affine = client
        .register_calibration(calibrate("belt-affine", &three, false))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(affine.model, proto::calibration_info::Model::Affine as i32);
    let listed = client
        .list_calibrations(proto::ListCalibrationsRequest {
            page_size: 1,
            page_token: String::new(),
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(listed.calibrations.len(), 1);
    assert_eq!(listed.calibrations[0].calibration_id, "belt");
    let rest = client
        .list_calibrations(proto::ListCalibrationsRequest {
            page_size: 10,
            page_token: listed.next_page_token,
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(rest.calibrations.len(), 1);
    assert_eq!(rest.calibrations[0].calibration_id, "belt-affine");

    // A template with an origin at its top-left pixel; one coordinate alone is refused.
    let half = proto::RegisterTemplateRequest {
        origin_x: Some(0.0),
        ..register_request("placed", template_png(1))
    };
    let status = client.register_template(half).await.unwrap_err();
    assert_eq!(status.code(), Code::InvalidArgument, "{status:?}");
    assert!(
        status.message().contains("origin_x/origin_y"),
        "{}",
        status.message()
    );
    let far = proto::RegisterTemplateRequest {
        origin_x: Some(1e6),
        origin_y: Some(0.0),
        ..register_request("placed", template_png(1))
    };
    assert_eq!(
        client.register_template(far).await.unwrap_err().code(),
        Code::InvalidArgument
    );
    let placed = proto::RegisterTemplateRequest {
        origin_x: Some(0.0),
        origin_y: Some(0.0),
        ..register_request("placed", template_png(1))
    };
    let info = client.register_template(placed).await.unwrap().into_inner();
    assert_eq!((info.origin_x, info.origin_y), (Some(0.0), Some(0.0)));
    let plain = client
        .register_template(register_request("plain", template_png(1)))
        .await
        .unwrap()
        .into_inner();
    assert_ne!(
        plain.content_sha256, info.content_sha256,
        "the origin is content"
    );
    assert_eq!((plain.origin_x, plain.origin_y), (None, None));

    // The template is scene(200, 200, 1) cropped at (60, 70): found there, upright.
    let find = |template_id: &str, calibration_id: &str| {
        let mut request = match_request(template_id, png(&scene(200, 200, 1)), "w");
        request.options = Some(proto::MatchOptions {
            method: proto::Method::Ncc as i32,
            max_instances: 1,
            angle_start_deg: -10.0,
            angle_extent_deg: 20.0,
            scale_min: 0.9,
            scale_max: 1.1,
            calibration_id: calibration_id.into(),
            ..Default::default()
        });
        request
    };
    let answer = client
        .r#match(find("placed", "belt"))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(answer.world_unit, "mm");
    let pose = &answer.poses[0];
    assert!(
        (pose.x - 77.5).abs() < 0.5 && (pose.y - 89.5).abs() < 0.5,
        "{pose:?}"
    );
    // The origin is where the transform sends template pixel (0, 0), near (60, 70).
    let t = &pose.transform;
    assert_eq!((pose.origin_x, pose.origin_y), (t[2], t[5]));
    assert!((pose.origin_x - 60.0).abs() < 0.5 && (pose.origin_y - 70.0).abs() < 0.5);
    // World coordinates are the calibration applied to the origin.
    let [wx, wy] = view([pose.origin_x as f64, pose.origin_y as f64]);
    let (x, y) = (pose.world_x.unwrap(), pose.world_y.unwrap());
    assert!(
        (x - wx).abs() < 1e-3 && (y - wy).abs() < 1e-3,
        "{x} {y} vs {wx} {wy}"
    );
    assert!(pose.world_angle_deg.is_some());
    // Without a calibration: no world fields; without an origin: the origin is the centre.
    let answer = client
        .r#match(find("plain", ""))
        .await
        .unwrap()
        .into_inner();
    let pose = &answer.poses[0];
    assert_eq!(answer.world_unit, "");
    assert!(pose.world_x.is_none() && pose.world_angle_deg.is_none());
    assert!((pose.origin_x - pose.x).abs() < 1e-4 && (pose.origin_y - pose.y).abs() < 1e-4);
    // An unknown calibration is NOT_FOUND, naming it.
    let status = client.r#match(find("plain", "nope")).await.unwrap_err();
    assert_eq!(status.code(), Code::NotFound, "{status:?}");
    assert!(
        status.message().contains("calibration"),
        "{}",
        status.message()
    );

    // Deleted, and kept across a restart like templates.
    let deleted = client
        .delete_calibration(proto::DeleteCalibrationRequest {
            calibration_id: "belt-affine".into(),
        })
        .await
        .unwrap()
        .into_inner();
    assert!(deleted.deleted);
    drop(client);
    drop(server);
    let (_server, mut client) = start(&settings(dir.path(), &[]), untrained_model()).await;
    let kept = client
        .get_calibration(proto::GetCalibrationRequest {
            calibration_id: "belt".into(),
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(kept, belt);
    let gone = client
        .get_calibration(proto::GetCalibrationRequest {
            calibration_id: "belt-affine".into(),
        })
        .await
        .unwrap_err();
    assert_eq!(gone.code(), Code::NotFound);
    let template = client
        .get_template(proto::GetTemplateRequest {
            template_id: "placed".into(),
            include_image: false,
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(
        (template.origin_x, template.origin_y),
        (Some(0.0), Some(0.0))
    );
}
