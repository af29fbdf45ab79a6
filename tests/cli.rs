//! `posematch match` as a user runs it: the official checkpoint reproduces the official decode,
//! batch mode keeps going past bad lines, and malformed input ends with one clear line.

mod common;

use std::path::Path;

use common::{
    official_decode, posematch, read_fixture, reference_dir, reference_files, write_bgr_png,
};
use posematch::geometry::angle_distance_deg;
use safetensors::SafeTensors;
use serde_json::Value;

fn angle_diff(a: f64, b: f64) -> f64 {
    f64::from(angle_distance_deg(a as f32, b as f32))
}

/// Writes pair `p`'s template and search image as PNGs into `dir`.
fn write_pair(st: &SafeTensors, p: &str, dir: &Path) -> (String, String) {
    let t = dir.join(format!("{p}-template.png"));
    let s = dir.join(format!("{p}-search.png"));
    write_bgr_png(st, &format!("{p}.template_src_bgr_u8"), &t);
    write_bgr_png(st, &format!("{p}.search_src_bgr_u8"), &s);
    (t.display().to_string(), s.display().to_string())
}

fn best_pose(stdout: &str) -> Value {
    let answer: Value = serde_json::from_str(stdout).expect("JSON on stdout");
    answer["poses"][0].clone()
}

#[test]
fn official_checkpoint_reproduces_the_official_decode() {
    let Some(dir) = reference_dir() else { return };
    let bytes = read_fixture(&dir);
    let st = SafeTensors::deserialize(&bytes).unwrap();
    let tmp = tempfile::tempdir().unwrap();
    let weights = dir.join("tdcm-official.pth").display().to_string();
    // (pair, template width, height, centre tolerance px, angle tolerance deg)
    for (pair, tw, th, max_px, max_deg) in
        [("b1", 36.0, 36.0, 0.5, 1.0), ("a", 34.0, 30.0, 2.0, 5.0)]
    {
        let (template, image) = write_pair(&st, pair, tmp.path());
        let (code, stdout, stderr) = posematch(&[
            "match",
            "--template",
            &template,
            "--image",
            &image,
            "--weights",
            &weights,
            "--convention",
            "gray",
            "--max-instances",
            "1",
            "--no-refine",
        ]);
        assert_eq!(code, 0, "{stderr}");
        let pose = best_pose(&stdout);
        let official = official_decode(&bytes, pair);
        let (ox, oy) = (
            official["center_xy"][0].as_f64().unwrap(),
            official["center_xy"][1].as_f64().unwrap(),
        );
        let (x, y) = (pose["x"].as_f64().unwrap(), pose["y"].as_f64().unwrap());
        let distance = ((x - ox).powi(2) + (y - oy).powi(2)).sqrt();
        let angle = angle_diff(
            pose["angle_deg"].as_f64().unwrap(),
            official["angle_deg"].as_f64().unwrap(),
        );
        // Official scales are relative to the 36-pixel grid; ours to the registered template.
        let osx = official["sx"].as_f64().unwrap() * 36.0 / tw;
        let osy = official["sy"].as_f64().unwrap() * 36.0 / th;
        println!(
            "{pair}: ours ({x:.2}, {y:.2}) {:.2}° sx {:.3} sy {:.3}; official ({ox:.2}, {oy:.2}) {:.2}° sx {osx:.3} sy {osy:.3}; \
             centre off by {distance:.2} px, angle by {angle:.2}°",
            pose["angle_deg"].as_f64().unwrap(),
            pose["scale_x"].as_f64().unwrap(),
            pose["scale_y"].as_f64().unwrap(),
            official["angle_deg"].as_f64().unwrap()
        );
        assert!(
            distance <= max_px,
            "{pair}: centre {distance} px from the official decode"
        );
        assert!(
            angle <= max_deg,
            "{pair}: angle {angle}° from the official decode"
        );
    }
}

#[test]
fn batch_mode_reports_each_line_and_survives_bad_ones() {
    let Some(dir) = reference_dir() else { return };
    let bytes = read_fixture(&dir);
    let st = SafeTensors::deserialize(&bytes).unwrap();
    let tmp = tempfile::tempdir().unwrap();
    write_pair(&st, "b1", tmp.path());
    std::fs::write(tmp.path().join("empty.png"), b"").unwrap();
    let pairs = tmp.path().join("pairs.jsonl");
    std::fs::write(
        &pairs,
        [
            r#"{"id": 1, "template": "b1-template.png", "image": "b1-search.png"}"#,
            r#"{"id": "two", "template": "b1-template.png", "image": "empty.png"}"#,
            r#"this is not json"#,
            r#"{"id": 4, "template": "b1-template.png", "image": "b1-search.png", "max_instances": 2}"#,
        ]
        .join("\n"),
    )
    .unwrap();
    let out = tmp.path().join("results.jsonl");
    let weights = dir.join("tdcm-official.pth").display().to_string();
    let (code, _, stderr) = posematch(&[
        "match",
        "--pairs",
        pairs.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--weights",
        &weights,
    ]);
    assert_eq!(code, 0, "{stderr}");
    let lines: Vec<Value> = std::fs::read_to_string(&out)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(lines.len(), 4);
    assert_eq!(lines[0]["id"], 1);
    let pose = &lines[0]["poses"][0];
    for key in [
        "x",
        "y",
        "angle_deg",
        "scale_x",
        "scale_y",
        "score",
        "network_score",
    ] {
        assert!(pose[key].is_number(), "{key} missing in {pose}");
    }
    assert!(lines[0]["ms"].as_f64().unwrap() > 0.0);
    // The true object: centre ≈ (119.5, 99.5), rotated +30°.
    assert!((pose["x"].as_f64().unwrap() - 119.5).abs() < 3.0, "{pose}");
    assert!((pose["y"].as_f64().unwrap() - 99.5).abs() < 3.0, "{pose}");
    assert_eq!(lines[1]["id"], "two");
    assert!(
        lines[1]["error"].as_str().unwrap().contains("empty"),
        "{}",
        lines[1]
    );
    assert!(lines[2]["error"].as_str().unwrap().contains("JSON"));
    assert!(lines[3]["poses"].as_array().unwrap().len() <= 2);
}

#[test]
fn overlay_is_written() {
    let Some(dir) = reference_dir() else { return };
    let bytes = read_fixture(&dir);
    let st = SafeTensors::deserialize(&bytes).unwrap();
    let tmp = tempfile::tempdir().unwrap();
    let (template, image) = write_pair(&st, "a", tmp.path());
    let overlay = tmp.path().join("overlay.png");
    let weights = dir.join("tdcm-official.pth").display().to_string();
    let (code, _, stderr) = posematch(&[
        "match",
        "--template",
        &template,
        "--image",
        &image,
        "--weights",
        &weights,
        "--overlay",
        overlay.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{stderr}");
    let drawn = image::open(&overlay).unwrap().to_rgb8();
    let original = image::open(&image).unwrap().to_rgb8();
    assert_eq!(drawn.dimensions(), original.dimensions());
    let changed = drawn
        .pixels()
        .zip(original.pixels())
        .filter(|(a, b)| a != b)
        .count();
    assert!(changed > 100, "overlay drew only {changed} pixels");
}

/// Every malformed input: non-zero exit, one line on stderr that names the problem, no panic.
#[test]
fn malformed_input_fails_with_one_clear_line() {
    let tmp = tempfile::tempdir().unwrap();
    let p = |name: &str| tmp.path().join(name);
    let good_template = p("template.png");
    image::RgbImage::from_fn(36, 36, |x, y| {
        image::Rgb([(x * 7) as u8, (y * 7) as u8, 90])
    })
    .save(&good_template)
    .unwrap();
    let good_image = p("image.png");
    image::RgbImage::from_fn(120, 100, |x, y| {
        image::Rgb([(x * 2) as u8, (y * 2) as u8, 30])
    })
    .save(&good_image)
    .unwrap();
    std::fs::write(p("empty.png"), b"").unwrap();
    let png = std::fs::read(&good_image).unwrap();
    std::fs::write(p("truncated.png"), &png[..png.len() / 2]).unwrap();
    std::fs::write(p("text.png"), b"this is a text file, not an image\n").unwrap();
    image::RgbImage::new(1, 1).save(p("tiny.png")).unwrap();
    image::RgbImage::new(200, 200)
        .save(p("big_template.png"))
        .unwrap();
    std::fs::write(
        p("huge_header.png"),
        common::png_claiming(100_000, 100_000, &[]),
    )
    .unwrap();

    // A weights file is not needed to reject bad images, but give one when available so the
    // checks run in the order a real call does.
    let weights = reference_files().map(|d| d.join("tdcm-official.pth").display().to_string());
    let cases: [(&str, &str, &str); 6] = [
        ("template.png", "empty.png", "empty"),
        ("template.png", "truncated.png", "corrupt or truncated"),
        ("text.png", "image.png", "not a supported image"),
        ("tiny.png", "image.png", "1x1"),
        (
            "big_template.png",
            "image.png",
            "larger than the search image",
        ),
        ("template.png", "huge_header.png", "100000x100000"),
    ];
    for (template, image, expected) in cases {
        let (t, i) = (p(template), p(image));
        let mut args = vec![
            "match",
            "--template",
            t.to_str().unwrap(),
            "--image",
            i.to_str().unwrap(),
        ];
        if let Some(w) = &weights {
            args.extend(["--weights", w.as_str()]);
        }
        let (code, stdout, stderr) = posematch(&args);
        assert_eq!(code, 1, "{template} / {image}: bad input exits 1: {stderr}");
        assert!(stdout.is_empty(), "{stdout}");
        assert!(
            !stderr.contains("panicked"),
            "{template} / {image}: {stderr}"
        );
        assert_eq!(
            stderr.trim().lines().count(),
            1,
            "{template} / {image}: {stderr}"
        );
        assert!(
            stderr.contains(expected),
            "{template} / {image}: expected `{expected}` in: {stderr}"
        );
    }

    // Missing weights are bad input (exit 1), bad options wrong usage (exit 2).
    let (t, i) = (
        good_template.to_str().unwrap(),
        good_image.to_str().unwrap(),
    );
    let (code, _, stderr) = posematch(&[
        "match",
        "--template",
        t,
        "--image",
        i,
        "--weights",
        "/nonexistent.pth",
    ]);
    assert_eq!(code, 1, "{stderr}");
    assert!(stderr.contains("no such file"), "{stderr}");
    let (code, _, stderr) =
        posematch(&["match", "--template", t, "--image", i, "--min-score", "7"]);
    assert_eq!(code, 2, "{stderr}");
    assert!(stderr.contains("--min-score 7"), "{stderr}");
    let (code, _, stderr) = posematch(&[
        "match",
        "--template",
        t,
        "--image",
        i,
        "--scale-range",
        "3,1",
    ]);
    assert_eq!(code, 2, "{stderr}");
    assert!(stderr.contains("scale range"), "{stderr}");
}

/// `posematch serve` fails with the documented exit status: 2 for an invalid setting, 1 for
/// missing weights, 3 when it cannot bind its address.
#[test]
fn serve_failures_exit_with_the_documented_status() {
    let dir = tempfile::tempdir().unwrap();
    let templates = dir.path().join("templates");
    let templates = templates.to_str().unwrap();
    let serve = |extra: &[&str]| {
        let mut args = vec![
            "serve",
            "--template-dir",
            templates,
            "--metrics-listen",
            "127.0.0.1:0",
        ];
        args.extend_from_slice(extra);
        posematch(&args)
    };
    let (code, _, stderr) = serve(&["--listen", "nowhere"]);
    assert_eq!(code, 2, "{stderr}");
    assert!(stderr.contains("listen"), "{stderr}");
    let (code, _, stderr) = serve(&["--listen", "127.0.0.1:0", "--weights", "/nonexistent.bpk"]);
    assert_eq!(code, 1, "{stderr}");
    assert!(stderr.contains("/nonexistent.bpk"), "{stderr}");
    let taken = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let address = taken.local_addr().unwrap().to_string();
    let (code, _, stderr) = serve(&["--listen", &address]);
    assert_eq!(code, 3, "{stderr}");
    assert!(!stderr.contains("panicked"), "{stderr}");
}

/// A 96x96 image of random discs (`image.png`) and its 24x24 crop at (40, 30)
/// (`template.png`) in `dir`.
fn write_blob_pair(dir: &Path) {
    use rand::{Rng, SeedableRng};
    let mut rng = rand::rngs::StdRng::seed_from_u64(3);
    let mut image = image::RgbImage::from_pixel(96, 96, image::Rgb([120, 100, 80]));
    for _ in 0..60 {
        let (cx, cy, r) = (
            rng.random_range(0..96i32),
            rng.random_range(0..96i32),
            rng.random_range(2..9i32),
        );
        let colour = image::Rgb([rng.random(), rng.random(), rng.random()]);
        for y in (cy - r).max(0)..(cy + r).min(96) {
            for x in (cx - r).max(0)..(cx + r).min(96) {
                if (x - cx).pow(2) + (y - cy).pow(2) <= r * r {
                    image.put_pixel(x as u32, y as u32, colour);
                }
            }
        }
    }
    image.save(dir.join("image.png")).unwrap();
    image::imageops::crop_imm(&image, 40, 30, 24, 24)
        .to_image()
        .save(dir.join("template.png"))
        .unwrap();
}

/// `--template-origin` and `--calibration`: where the reference point lands, in pixels and in
/// world units (equal to the calibration applied to it), and bad input named by its flag.
#[test]
fn origins_and_calibrations_from_the_command_line() {
    let tmp = tempfile::tempdir().unwrap();
    write_blob_pair(tmp.path());
    let path = |name: &str| tmp.path().join(name).display().to_string();
    // An exact homography: a camera looking at the plane at an angle, in millimetres.
    let view = |x: f64, y: f64| {
        let w = 0.001 * x - 0.0005 * y + 1.0;
        (
            (0.25 * x + 0.02 * y + 3.0) / w,
            (-0.01 * x + 0.24 * y - 7.0) / w,
        )
    };
    let points: Vec<Value> = [
        (0.0, 0.0),
        (95.0, 0.0),
        (95.0, 95.0),
        (0.0, 95.0),
        (30.0, 60.0),
    ]
    .iter()
    .map(|&(x, y)| {
        let (wx, wy) = view(x, y);
        serde_json::json!({"image": [x, y], "world": [wx, wy]})
    })
    .collect();
    std::fs::write(
        path("cal.json"),
        serde_json::json!({"points": points, "unit": "mm"}).to_string(),
    )
    .unwrap();
    let (template, image, calibration) =
        (path("template.png"), path("image.png"), path("cal.json"));
    let base = [
        "match",
        "--method",
        "ncc",
        "--template",
        &template,
        "--image",
        &image,
        "--max-instances",
        "1",
    ];
    let with = |extra: &[&str]| {
        let args: Vec<&str> = base.iter().chain(extra).copied().collect();
        posematch(&args)
    };
    let (code, stdout, stderr) = with(&["--template-origin", "0,0", "--calibration", &calibration]);
    assert_eq!(code, 0, "{stderr}");
    let answer: Value = serde_json::from_str(&stdout).unwrap();
    assert_eq!(answer["calibration"]["model"], "homography");
    assert!(answer["calibration"]["rms_residual"].as_f64().unwrap() < 1e-6);
    let pose = &answer["poses"][0];
    let number = |key: &str| {
        pose[key]
            .as_f64()
            .unwrap_or_else(|| panic!("{key}: {pose}"))
    };
    // Template pixel (0, 0) is the crop's corner (40, 30); the centre stays (51.5, 41.5).
    assert!((number("origin_x") - 40.0).abs() < 0.5 && (number("origin_y") - 30.0).abs() < 0.5);
    assert!((number("x") - 51.5).abs() < 0.5, "{pose}");
    let (wx, wy) = view(number("origin_x"), number("origin_y"));
    assert!(
        (number("world_x") - wx).abs() < 1e-3 && (number("world_y") - wy).abs() < 1e-3,
        "{pose}"
    );

    // Points on one line, duplicated points and an origin far off: exit 2, naming the flag.
    std::fs::write(
        path("line.json"),
        r#"{"points": [{"image": [0, 0], "world": [0, 0]}, {"image": [10, 10], "world": [1, 1]},
           {"image": [20, 20], "world": [2, 2]}], "unit": "mm"}"#,
    )
    .unwrap();
    std::fs::write(
        path("twice.json"),
        r#"{"points": [{"image": [0, 0], "world": [0, 0]}, {"image": [10, 0], "world": [1, 0]},
           {"image": [0, 10], "world": [0, 1]}, {"image": [10, 0], "world": [2, 2]}], "unit": "mm"}"#,
    )
    .unwrap();
    for (extra, needle) in [
        (
            vec!["--calibration".to_string(), path("line.json")],
            "one line",
        ),
        (
            vec!["--calibration".to_string(), path("twice.json")],
            "same image position",
        ),
        (
            vec!["--template-origin".to_string(), "500,0".to_string()],
            "--template-origin",
        ),
    ] {
        let extra: Vec<&str> = extra.iter().map(String::as_str).collect();
        let (code, _, stderr) = with(&extra);
        assert_eq!(code, 2, "{extra:?}: {stderr}");
        assert!(stderr.contains(needle), "{extra:?}: {stderr}");
    }

    // Batch mode: an origin per line, the calibration for the batch.
    std::fs::write(
        path("pairs.jsonl"),
        r#"{"id": 1, "template": "template.png", "image": "image.png", "template_origin": [23, 23]}"#,
    )
    .unwrap();
    let (code, _, stderr) = posematch(&[
        "match",
        "--method",
        "ncc",
        "--pairs",
        &path("pairs.jsonl"),
        "--out",
        &path("out.jsonl"),
        "--calibration",
        &calibration,
    ]);
    assert_eq!(code, 0, "{stderr}");
    let line: Value =
        serde_json::from_str(&std::fs::read_to_string(path("out.jsonl")).unwrap()).unwrap();
    let pose = &line["poses"][0];
    assert!(
        (pose["origin_x"].as_f64().unwrap() - 63.0).abs() < 0.5,
        "{pose}"
    );
    assert!(pose["world_x"].is_number(), "{pose}");
}

/// Several `--template`s in one call: each pose names its template, the present one is found
/// where it was cut, and an absent one reports nothing at the default min_score.
#[test]
fn several_templates_are_found_in_one_call() {
    let tmp = tempfile::tempdir().unwrap();
    write_blob_pair(tmp.path());
    let path = |name: &str| tmp.path().join(name).display().to_string();
    // A template from elsewhere: stripes the disc image does not hold.
    image::RgbImage::from_fn(24, 24, |x, y| {
        let v = if (x / 3 + y / 5) % 2 == 0 { 30 } else { 220 };
        image::Rgb([v, 255 - v, v / 2])
    })
    .save(path("absent.png"))
    .unwrap();
    let (present, absent, search) = (path("template.png"), path("absent.png"), path("image.png"));
    let (code, stdout, stderr) = posematch(&[
        "match",
        "--template",
        &absent,
        "--template",
        &present,
        "--image",
        &search,
    ]);
    assert_eq!(code, 0, "{stderr}");
    let answer: Value = serde_json::from_str(&stdout).unwrap();
    assert_eq!(answer["templates"], serde_json::json!([absent, present]));
    let poses = answer["poses"].as_array().unwrap();
    assert!(!poses.is_empty(), "{stdout}");
    assert!(
        poses.iter().all(|p| p["template"] == present.as_str()),
        "{stdout}"
    );
    assert!(
        (poses[0]["x"].as_f64().unwrap() - 51.5).abs() < 0.5,
        "{stdout}"
    );
    // A mask or an origin belongs to one template.
    let (code, _, stderr) = posematch(&[
        "match",
        "--template",
        &absent,
        "--template",
        &present,
        "--image",
        &search,
        "--template-origin",
        "0,0",
    ]);
    assert_eq!(code, 2, "{stderr}");
    assert!(stderr.contains("single --template"), "{stderr}");

    // Batch lines name several templates with "templates"; each pose names its own.
    std::fs::write(
        tmp.path().join("pairs.jsonl"),
        [
            r#"{"id": "both", "templates": ["absent.png", "template.png"], "image": "image.png"}"#,
            r#"{"id": "one", "template": "template.png", "image": "image.png"}"#,
            r#"{"id": "masked", "templates": ["absent.png", "template.png"], "image": "image.png", "template_origin": [0, 0]}"#,
            r#"{"id": "none", "templates": [], "image": "image.png"}"#,
            r#"{"id": "twice", "template": "template.png", "templates": ["absent.png"], "image": "image.png"}"#,
        ]
        .join("\n"),
    )
    .unwrap();
    let results = path("results.jsonl");
    let (code, _, stderr) =
        posematch(&["match", "--pairs", &path("pairs.jsonl"), "--out", &results]);
    assert_eq!(code, 0, "{stderr}");
    let lines: Vec<Value> = std::fs::read_to_string(&results)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    let both = lines[0]["poses"].as_array().expect("poses");
    assert!(!both.is_empty(), "{:?}", lines[0]);
    assert!(
        both.iter().all(|p| p["template"] == "template.png"),
        "{both:?}"
    );
    let one = lines[1]["poses"].as_array().expect("poses");
    assert_eq!(
        (both[0]["x"].as_f64(), both[0]["y"].as_f64()),
        (one[0]["x"].as_f64(), one[0]["y"].as_f64()),
        "the same search whether alone or beside another template"
    );
    assert!(one[0].get("template").is_none(), "{:?}", one[0]);
    for (line, says) in [(2, "one template"), (3, "1 to 16"), (4, "not both")] {
        let error = lines[line]["error"].as_str().unwrap_or_default();
        assert!(error.contains(says), "line {line}: {:?}", lines[line]);
    }
}

/// `--suppress-across-templates`: a template and a slightly larger crop around the same part
/// both find it; with the flag only the better-scoring answer is left, in single and batch
/// mode.
#[test]
fn overlapping_answers_of_different_templates_can_be_one_object() {
    let tmp = tempfile::tempdir().unwrap();
    write_blob_pair(tmp.path());
    let path = |name: &str| tmp.path().join(name).display().to_string();
    let image = image::open(path("image.png")).unwrap().to_rgb8();
    image::imageops::crop_imm(&image, 38, 28, 28, 28)
        .to_image()
        .save(path("wider.png"))
        .unwrap();
    let (template, wider, search) = (path("template.png"), path("wider.png"), path("image.png"));
    let templates_of = |stdout: &str| -> Vec<String> {
        let answer: Value = serde_json::from_str(stdout).unwrap();
        answer["poses"]
            .as_array()
            .unwrap()
            .iter()
            .map(|p| p["template"].as_str().unwrap().to_owned())
            .collect()
    };
    let run = |extra: &[&str]| {
        let mut args = vec![
            "match",
            "--method",
            "ncc",
            "--template",
            &template,
            "--template",
            &wider,
            "--image",
            &search,
            "--max-instances",
            "1",
        ];
        args.extend_from_slice(extra);
        let (code, stdout, stderr) = posematch(&args);
        assert_eq!(code, 0, "{stderr}");
        stdout
    };
    let each = run(&[]);
    let mut found = templates_of(&each);
    found.sort();
    assert_eq!(found, [template.clone(), wider.clone()], "{each}");
    let one = run(&["--suppress-across-templates"]);
    assert_eq!(templates_of(&one).len(), 1, "{one}");
    let answer: Value = serde_json::from_str(&each).unwrap();
    assert_eq!(
        templates_of(&one)[0],
        answer["poses"][0]["template"].as_str().unwrap(),
        "the better-scoring answer stays: {each} {one}"
    );

    // Batch mode (the network): the same flag applies to each line's templates.
    std::fs::write(
        path("pairs.jsonl"),
        r#"{"id": "both", "templates": ["template.png", "wider.png"], "image": "image.png"}"#,
    )
    .unwrap();
    let (pairs, results) = (path("pairs.jsonl"), path("results.jsonl"));
    for (flag, expected) in [(None, 2), (Some("--suppress-across-templates"), 1)] {
        let mut args = vec![
            "match",
            "--pairs",
            &pairs,
            "--out",
            &results,
            "--max-instances",
            "1",
            "--min-score",
            "0.5",
        ];
        args.extend(flag);
        let (code, _, stderr) = posematch(&args);
        assert_eq!(code, 0, "{stderr}");
        let line: Value =
            serde_json::from_str(std::fs::read_to_string(&results).unwrap().trim()).unwrap();
        assert_eq!(line["poses"].as_array().unwrap().len(), expected, "{line}");
    }
}

/// `--method ncc` answers batch files too (no weights needed); bad lines get their error.
#[test]
fn classical_matcher_runs_in_batch_mode() {
    let tmp = tempfile::tempdir().unwrap();
    write_blob_pair(tmp.path());
    let pairs = tmp.path().join("pairs.jsonl");
    std::fs::write(
        &pairs,
        [
            r#"{"id": 1, "template": "template.png", "image": "image.png"}"#,
            r#"{"id": 2, "template": "template.png", "image": "missing.png"}"#,
        ]
        .join("\n"),
    )
    .unwrap();
    let out = tmp.path().join("results.jsonl");
    let (code, _, stderr) = posematch(&[
        "match",
        "--method",
        "ncc",
        "--pairs",
        pairs.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{stderr}");
    let lines: Vec<Value> = std::fs::read_to_string(&out)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    let pose = &lines[0]["poses"][0];
    // The template's centre in the image: (40 + 11.5, 30 + 11.5).
    assert!((pose["x"].as_f64().unwrap() - 51.5).abs() < 0.5, "{pose}");
    assert!((pose["y"].as_f64().unwrap() - 41.5).abs() < 0.5, "{pose}");
    assert!(pose["score"].as_f64().unwrap() > 0.9, "{pose}");
    assert!(lines[1]["error"].as_str().unwrap().contains("missing.png"));
}

/// The comparison workflow of the README: pairs with truth saved by `eval`, answered by any
/// matcher in batch mode, scored by `score` — here the classical matcher, which must find
/// the objects of generated S1.5 pairs (known truth) with its default search.
#[test]
fn saved_pairs_answered_in_batch_are_scored_against_their_truth() {
    let photos = common::structured_photo_dir();
    let tmp = tempfile::tempdir().unwrap();
    let saved = tmp.path().join("pairs");
    let (code, _, stderr) = posematch(&[
        "eval",
        "--images",
        photos.path().to_str().unwrap(),
        "--level",
        "S1.5",
        "--count",
        "6",
        "--no-refine",
        "--save",
        saved.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{stderr}");
    let pairs = saved.join("pairs.jsonl");
    let results = tmp.path().join("ncc.jsonl");
    let (code, _, stderr) = posematch(&[
        "match",
        "--method",
        "ncc",
        "--scale-range",
        "0.8,1.5",
        "--max-instances",
        "1",
        "--min-score",
        "0.01",
        "--pairs",
        pairs.to_str().unwrap(),
        "--out",
        results.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{stderr}");
    let (code, stdout, stderr) = posematch(&[
        "score",
        "--json",
        "--name",
        "ncc",
        "--pairs",
        pairs.to_str().unwrap(),
        "--results",
        results.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{stderr}");
    let table: Value = serde_json::from_str(stdout.trim()).unwrap();
    let summary = &table["rows"][0]["summary"];
    assert_eq!(summary["pairs"], 6, "{table}");
    assert!(summary["success"].as_f64().unwrap() >= 5.0 / 6.0, "{table}");
    assert!(summary["loc_err_px"].as_f64().unwrap() < 0.5, "{table}");

    // A results file that misses pairs counts them as misses, and says so.
    std::fs::write(&results, "").unwrap();
    let (code, stdout, stderr) = posematch(&[
        "score",
        "--json",
        "--pairs",
        pairs.to_str().unwrap(),
        "--results",
        results.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{stderr}");
    assert!(stderr.contains("6 of 6 pairs have no line"), "{stderr}");
    let table: Value = serde_json::from_str(stdout.trim()).unwrap();
    assert_eq!(table["rows"][0]["summary"]["success"], 0.0, "{table}");
}
