//! Replicas sharing templates through a real PostgreSQL (a throw-away cluster per test, see
//! `common::postgres`): what one replica registers, replaces or deletes the others see within a
//! second, cached kernels included; a replica killed with SIGKILL mid-registration loses nothing
//! it acknowledged and leaves nothing half-written; a database restart is survived without
//! restarting the replicas.
//!
//! Which kernel a replica used is read from its answers: with the same (untrained, in-process)
//! network, a template gives the same poses every time, and two different templates different
//! ones. So "replica B now matches the replaced image" is "B's answer for `part` equals B's answer
//! for a reference ID holding the new image".

mod common;

use std::time::{Duration, Instant};

use common::postgres::PgCluster;
use common::service::*;
use posematch::grpc::RunningServer;
use posematch::grpc::proto;
use posematch::grpc::proto::pose_matcher_client::PoseMatcherClient;
use tonic::Code;
use tonic::transport::Channel;

/// A replica in this process on the cluster's database.
async fn replica(
    cluster: &PgCluster,
    tweak: &[(&str, &str)],
) -> (RunningServer, PoseMatcherClient<Channel>) {
    let unused = tempfile::tempdir().unwrap();
    let url = cluster.url();
    let mut all = vec![("template_store", url.as_str())];
    all.extend_from_slice(tweak);
    start(&settings(unused.path(), &all), untrained_model()).await
}

/// A match whose answer identifies the kernel used: network only, every peak kept.
fn probe(id: &str, frame: &[u8]) -> proto::MatchRequest {
    proto::MatchRequest {
        template_id: id.into(),
        image: encoded(frame.to_vec()),
        options: Some(proto::MatchOptions {
            no_refine: true,
            min_score: 1e-6,
            max_instances: 5,
            ..Default::default()
        }),
        request_id: String::new(),
        template_ids: Vec::new(),
    }
}

async fn poses(
    client: &mut PoseMatcherClient<Channel>,
    id: &str,
    frame: &[u8],
) -> Result<Vec<proto::Pose>, tonic::Status> {
    client
        .r#match(probe(id, frame))
        .await
        .map(|r| r.into_inner().poses)
}

fn replace_request(id: &str, image: Vec<u8>) -> proto::RegisterTemplateRequest {
    proto::RegisterTemplateRequest {
        replace: true,
        ..register_request(id, image)
    }
}

/// Polls `until` every 10 ms for at most `limit`; the time it took.
async fn within<F: Future<Output = bool>>(
    limit: Duration,
    mut until: impl FnMut() -> F,
) -> Option<Duration> {
    let started = Instant::now();
    while started.elapsed() < limit {
        if until().await {
            return Some(started.elapsed());
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    None
}

async fn health(addr: std::net::SocketAddr) -> i32 {
    health_of(&addr.to_string(), "").await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn replicas_share_templates_and_follow_each_others_changes() {
    let Some(cluster) = common::postgres_cluster() else {
        return;
    };
    let (a, mut on_a) = replica(&cluster, &[]).await;
    let (b, mut on_b) = replica(&cluster, &[]).await;
    let frame = png(&scene(128, 128, 1));
    let (x, y) = (template_png(1), template_png(2));

    // Registered on A, matched on B (read through from the database, then cached on B).
    let registered = Instant::now();
    let info = on_a
        .register_template(register_request("part", x.clone()))
        .await
        .unwrap()
        .into_inner();
    println!(
        "registration on A: {:.1} ms",
        registered.elapsed().as_secs_f64() * 1e3
    );
    assert_eq!(info.version, 1);
    let with_x = poses(&mut on_b, "part", &frame)
        .await
        .expect("B matches A's template");
    assert!(!with_x.is_empty());
    on_a.register_template(register_request("reference-y", y.clone()))
        .await
        .unwrap();
    let with_y = poses(&mut on_b, "reference-y", &frame).await.unwrap();
    assert!(
        !same_poses(&with_x, &with_y),
        "the two templates must answer differently"
    );
    assert!(same_poses(
        &poses(&mut on_b, "part", &frame).await.unwrap(),
        &with_x
    ));

    // Replaced on A: B's cached kernel follows within a second.
    let replaced = on_a
        .register_template(replace_request("part", y.clone()))
        .await
        .unwrap()
        .into_inner();
    assert_eq!(
        (replaced.version, replaced.created_unix_ms),
        (2, info.created_unix_ms)
    );
    let mut b_probe = on_b.clone();
    let (frame_b, with_y_b) = (frame.clone(), with_y.clone());
    let seen = within(Duration::from_secs(1), || {
        let (mut client, frame, want) = (b_probe.clone(), frame_b.clone(), with_y_b.clone());
        async move {
            poses(&mut client, "part", &frame)
                .await
                .is_ok_and(|p| same_poses(&p, &want))
        }
    })
    .await;
    let seen = seen.expect("B matches the replaced image within 1 s");
    println!(
        "replace on A seen by B's cache after {:.0} ms",
        seen.as_secs_f64() * 1e3
    );

    // Deleted on B: A (which cached it when it registered) answers NOT_FOUND within a second.
    assert!(poses(&mut on_a, "part", &frame).await.is_ok());
    assert!(
        on_b.delete_template(proto::DeleteTemplateRequest {
            template_id: "part".into()
        })
        .await
        .unwrap()
        .into_inner()
        .deleted
    );
    let a_probe = on_a.clone();
    let frame_a = frame.clone();
    let gone = within(Duration::from_secs(1), || {
        let (mut client, frame) = (a_probe.clone(), frame_a.clone());
        async move {
            poses(&mut client, "part", &frame)
                .await
                .is_err_and(|s| s.code() == Code::NotFound)
        }
    })
    .await
    .expect("A forgets the template B deleted within 1 s");
    println!(
        "delete on B seen by A after {:.0} ms",
        gone.as_secs_f64() * 1e3
    );

    // One ID registered at once on both with different images: exactly one wins.
    let (first, second) = tokio::join!(
        on_a.register_template(register_request("race", template_png(3))),
        b_probe.register_template(register_request("race", template_png(4)))
    );
    let outcomes = [first.map(|_| ()), second.map(|_| ())];
    let won = outcomes.iter().filter(|o| o.is_ok()).count();
    assert_eq!(won, 1, "{outcomes:?}");
    assert!(
        outcomes
            .iter()
            .any(|o| o.as_ref().is_err_and(|s| s.code() == Code::AlreadyExists))
    );

    // Listing pages from the database, the same on both replicas.
    let ids = |templates: Vec<proto::TemplateInfo>| -> Vec<String> {
        templates.into_iter().map(|t| t.template_id).collect()
    };
    let listed = ids(list_all(&mut on_a, 1).await);
    assert_eq!(listed, vec!["race".to_string(), "reference-y".to_string()]);
    assert_eq!(ids(list_all(&mut on_b, 1).await), listed);

    let metrics = metrics_text(&b).await;
    assert!(
        counter(&metrics, "posematch_store_notifications_total", "") >= 3.0,
        "{metrics}"
    );
    assert_eq!(
        counter(&metrics, "posematch_templates ", ""),
        2.0,
        "{metrics}"
    );
    a.shutdown(Duration::from_secs(5)).await;
    b.shutdown(Duration::from_secs(5)).await;
}

/// SIGKILL of a replica while it registers templates one after another, several times: every
/// template it acknowledged is in the database, and every row there (acknowledged or cut short)
/// is whole: its image hashes to its `content_sha256` and Match can use it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn kill_9_during_registrations_loses_no_acknowledged_template() {
    let Some(cluster) = common::postgres_cluster() else {
        return;
    };
    let url = cluster.url();
    let mut acknowledged: Vec<(String, String)> = Vec::new();
    let mut next = 0u32;
    const ROUNDS: u64 = 4;
    for round in 0..ROUNDS {
        let server = ChildServer::start_with(|c| {
            c.arg("--template-store").arg(&url);
        });
        let client = server.client().await;
        let (acknowledge, mut acknowledgements) = tokio::sync::mpsc::unbounded_channel::<()>();
        let registering = {
            let mut client = client.clone();
            let first = next;
            tokio::spawn(async move {
                let mut done = Vec::new();
                for k in first.. {
                    let id = format!("t-{k:04}");
                    match client
                        .register_template(register_request(&id, template_png(k)))
                        .await
                    {
                        Ok(reply) => {
                            done.push((id, reply.into_inner().content_sha256));
                            let _ = acknowledge.send(());
                        }
                        Err(_) => break,
                    }
                }
                done
            })
        };
        // The kill comes after the first acknowledged registration, so every round has some.
        let first_acknowledged =
            tokio::time::timeout(Duration::from_secs(60), acknowledgements.recv()).await;
        assert!(
            matches!(first_acknowledged, Ok(Some(()))),
            "round {round}: no registration was acknowledged"
        );
        // Deliberate, not a wait for anything: each round's kill lands at another point of the
        // registrations.
        tokio::time::sleep(Duration::from_millis(100 + round * 170)).await;
        server.kill9();
        let done = registering.await.unwrap();
        assert!(
            !done.is_empty(),
            "round {round}: nothing registered before the kill"
        );
        next += done.len() as u32 + 1; // the one in flight may or may not have committed
        acknowledged.extend(done);
    }
    let (checker, mut client) = replica(&cluster, &[]).await;
    let stored = list_all(&mut client, 1000).await;
    for (id, sha) in &acknowledged {
        let row = stored.iter().find(|t| &t.template_id == id);
        assert_eq!(
            row.map(|t| &t.content_sha256),
            Some(sha),
            "acknowledged {id} lost"
        );
    }
    let frame = png(&scene(128, 128, 1));
    for info in &stored {
        let full = get_with_image(&mut client, &info.template_id).await;
        assert_eq!(
            audited_content_sha256(&full),
            info.content_sha256,
            "{}",
            info.template_id
        );
        poses(&mut client, &info.template_id, &frame)
            .await
            .unwrap_or_else(|s| panic!("{} cannot be matched: {s:?}", info.template_id));
    }
    println!(
        "{ROUNDS} kills during registration: {} acknowledged, {} stored, all whole",
        acknowledged.len(),
        stored.len()
    );
    checker.shutdown(Duration::from_secs(5)).await;
}

/// The database stops and comes back: cached templates keep matching, registrations and
/// uncached templates answer UNAVAILABLE, health turns NOT_SERVING only after the grace period,
/// and everything recovers (registrations, read-through, change notifications) without
/// restarting the replicas.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_database_restart_is_survived() {
    let Some(cluster) = common::postgres_cluster() else {
        return;
    };
    let (a, mut on_a) = replica(&cluster, &[("database_grace_seconds", "600")]).await;
    let (b, mut on_b) = replica(&cluster, &[("database_grace_seconds", "1")]).await;
    let frame = png(&scene(128, 128, 1));
    let (x, y) = (template_png(1), template_png(2));
    on_a.register_template(register_request("part", x))
        .await
        .unwrap();
    on_a.register_template(register_request("uncached", y.clone()))
        .await
        .unwrap();
    let with_x = poses(&mut on_b, "part", &frame).await.unwrap();

    cluster.stop();
    let cached = poses(&mut on_b, "part", &frame)
        .await
        .expect("a cached template matches while the database is down");
    assert!(same_poses(&cached, &with_x));
    let refused = on_a
        .register_template(register_request("new", template_png(5)))
        .await
        .unwrap_err();
    assert_eq!(refused.code(), Code::Unavailable, "{refused:?}");
    assert!(
        refused.message().contains("unreachable"),
        "{}",
        refused.message()
    );
    let uncached = poses(&mut on_b, "uncached", &frame).await.unwrap_err();
    assert_eq!(uncached.code(), Code::Unavailable, "{uncached:?}");
    let (b_addr, a_addr) = (b.grpc_addr, a.grpc_addr);
    within(Duration::from_secs(10), || async move {
        health(b_addr).await == NOT_SERVING
    })
    .await
    .expect("B (grace 1 s) reports NOT_SERVING");
    assert_eq!(
        health(a_addr).await,
        SERVING,
        "A is within its grace period"
    );

    cluster.start_again();
    let mut registering = on_a.clone();
    let recovered = within(Duration::from_secs(30), || {
        let mut client = registering.clone();
        async move {
            client
                .register_template(register_request("new", template_png(5)))
                .await
                .is_ok()
        }
    })
    .await
    .expect("registrations work again after the restart");
    println!(
        "registration recovered {:.1} s after the database restarted",
        recovered.as_secs_f64()
    );
    within(Duration::from_secs(10), || async move {
        health(b_addr).await == SERVING
    })
    .await
    .expect("B reports SERVING again");
    let with_y = poses(&mut on_b, "uncached", &frame)
        .await
        .expect("read-through works again");
    let again = poses(&mut on_b, "part", &frame).await.unwrap();
    assert!(same_poses(&again, &with_x));
    // B listens again: a replacement on A reaches B's cache.
    registering
        .register_template(replace_request("part", y))
        .await
        .unwrap();
    let (b_probe, frame_b) = (on_b.clone(), frame.clone());
    within(Duration::from_secs(1), || {
        let (mut client, frame, want) = (b_probe.clone(), frame_b.clone(), with_y.clone());
        async move {
            poses(&mut client, "part", &frame)
                .await
                .is_ok_and(|p| same_poses(&p, &want))
        }
    })
    .await
    .expect("after the restart B still follows A's replacements within 1 s");
    let metrics = metrics_text(&b).await;
    assert!(
        counter(&metrics, "posematch_store_reconnects_total", "") >= 1.0,
        "{metrics}"
    );
    assert!(
        counter(&metrics, "posematch_store_errors_total", "") >= 1.0,
        "{metrics}"
    );
    a.shutdown(Duration::from_secs(5)).await;
    b.shutdown(Duration::from_secs(5)).await;
}

/// A database that refuses us for good (here: it does not exist) fails the start with the
/// database's own words; one that is merely down is waited for (`a_database_restart_is_survived`
/// covers an outage while serving).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_database_that_refuses_fails_the_start_with_its_message() {
    let Some(cluster) = common::postgres_cluster() else {
        return;
    };
    let unused = tempfile::tempdir().unwrap();
    let url = format!(
        "{}/no_such_database",
        cluster.url().rsplit_once('/').unwrap().0
    );
    let settings = settings(unused.path(), &[("template_store", url.as_str())]);
    let mut server = RunningServer::start(&settings, untrained_model())
        .await
        .expect("the ports bind before the store is opened");
    let message = tokio::time::timeout(Duration::from_secs(30), server.ready())
        .await
        .expect("the start fails, not waits")
        .unwrap_err();
    assert!(message.contains("no_such_database"), "{message}");
    assert!(!message.contains("unreachable"), "{message}");
    println!("{message}");
}

/// Origins and calibrations live in the database like templates: what one replica registers,
/// the other reads, and a replaced origin reaches the other replica's cache (the origin is part
/// of the content hash the change notification carries).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn origins_and_calibrations_are_shared_by_replicas() {
    let Some(cluster) = common::postgres_cluster() else {
        return;
    };
    let (_a, mut on_a) = replica(&cluster, &[]).await;
    let (_b, mut on_b) = replica(&cluster, &[]).await;
    let placed = |x: f32, replace: bool| proto::RegisterTemplateRequest {
        origin_x: Some(x),
        origin_y: Some(0.0),
        replace,
        ..register_request("part", template_png(1))
    };
    let first = on_a
        .register_template(placed(0.0, false))
        .await
        .unwrap()
        .into_inner();
    let frame = png(&scene(128, 128, 1));
    // How far the reported origin lies from the image of template pixel (0, 0) (the
    // transform's translation). Both coordinates: the untrained network's pose has a random
    // angle, and at ±90° a shift of the origin along u moves only y.
    let origin_from_corner = |poses: &[proto::Pose]| {
        let pose = &poses[0];
        (pose.origin_x - pose.transform[2]).hypot(pose.origin_y - pose.transform[5])
    };
    let seen = poses(&mut on_b, "part", &frame).await.unwrap();
    assert!(
        origin_from_corner(&seen) < 1e-3,
        "origin at template pixel (0, 0)"
    );
    // A new origin alone is a replacement (ALREADY_EXISTS without replace) and B follows it.
    let clash = on_a
        .register_template(placed(35.0, false))
        .await
        .unwrap_err();
    assert_eq!(clash.code(), Code::AlreadyExists);
    let second = on_a
        .register_template(placed(35.0, true))
        .await
        .unwrap()
        .into_inner();
    assert_ne!(second.content_sha256, first.content_sha256);
    assert_eq!((second.origin_x, second.version), (Some(35.0), 2));
    let followed = within(Duration::from_secs(5), || {
        let mut on_b = on_b.clone();
        let frame = frame.clone();
        async move {
            let seen = poses(&mut on_b, "part", &frame).await.unwrap();
            origin_from_corner(&seen) > 1.0
        }
    })
    .await;
    assert!(followed.is_some(), "B still reports the old origin");

    let point = |image: [f64; 2], world: [f64; 2]| proto::CalibrationPoint {
        image_x: image[0],
        image_y: image[1],
        world_x: world[0],
        world_y: world[1],
    };
    let registered = on_a
        .register_calibration(proto::RegisterCalibrationRequest {
            calibration_id: "cam-1".into(),
            points: vec![
                point([0.0, 0.0], [0.0, 0.0]),
                point([100.0, 0.0], [10.0, 0.0]),
                point([0.0, 100.0], [0.0, 10.0]),
                point([100.0, 100.0], [10.0, 10.0]),
            ],
            unit: "mm".into(),
            replace: false,
        })
        .await
        .unwrap()
        .into_inner();
    let read = on_b
        .get_calibration(proto::GetCalibrationRequest {
            calibration_id: "cam-1".into(),
        })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(read, registered);
    let mut request = probe("part", &frame);
    request.options.as_mut().unwrap().calibration_id = "cam-1".into();
    let answer = on_b.r#match(request).await.unwrap().into_inner();
    let pose = &answer.poses[0];
    assert_eq!(answer.world_unit, "mm");
    assert!((pose.world_x.unwrap() - pose.origin_x as f64 / 10.0).abs() < 1e-3);
    let deleted = on_b
        .delete_calibration(proto::DeleteCalibrationRequest {
            calibration_id: "cam-1".into(),
        })
        .await
        .unwrap()
        .into_inner();
    assert!(deleted.deleted);
    let gone = on_a
        .get_calibration(proto::GetCalibrationRequest {
            calibration_id: "cam-1".into(),
        })
        .await
        .unwrap_err();
    assert_eq!(gone.code(), Code::NotFound);
}
