//! The setup page in a real browser: headless Chromium (Debian's `chromium`), driven through
//! WebDriver (`chromedriver`, from `chromium-driver`) against a real server on the embedded
//! default weights. The whole flow an engineer follows by hand: open the page, load a camera
//! frame, drag a box around the part, register it, match, read the pose table, see the overlay
//! drawn, delete the template. Skips with a message where Chromium or chromedriver is absent
//! (a failure in CI). A screenshot of the page with its poses is kept in
//! `target/browser-test/setup-page.png`.

mod common;

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use fantoccini::actions::{InputSource, MouseActions, PointerAction};
use fantoccini::{Client, ClientBuilder, Locator};
use posematch::grpc::RunningServer;
use serde_json::{Value, json};

use common::service::{embedded_model, png, scene, settings};

/// How long the page may take to show what a step does (the first match in a debug build
/// includes the network's warm-up).
const STEP: Duration = Duration::from_secs(90);

fn installed(variable: &str, names: &[&str]) -> Option<PathBuf> {
    if let Some(path) = std::env::var_os(variable) {
        return Some(PathBuf::from(path));
    }
    let path = std::env::var_os("PATH")?;
    std::env::split_paths(&path)
        .flat_map(|dir| names.iter().map(move |name| dir.join(name)))
        .find(|candidate| candidate.is_file())
}

/// chromedriver on a free port, stopped when dropped.
struct Driver {
    child: Child,
    url: String,
}

impl Driver {
    fn start(binary: &Path) -> Self {
        let port = std::net::TcpListener::bind("127.0.0.1:0")
            .unwrap()
            .local_addr()
            .unwrap()
            .port();
        let child = Command::new(binary)
            .arg(format!("--port={port}"))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("chromedriver starts");
        let deadline = Instant::now() + Duration::from_secs(30);
        while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
            assert!(Instant::now() < deadline, "chromedriver did not listen");
            std::thread::sleep(Duration::from_millis(50));
        }
        Self {
            child,
            url: format!("http://127.0.0.1:{port}"),
        }
    }
}

impl Drop for Driver {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Polls `probe` until it gives a value, or fails naming `what` after [`STEP`].
async fn eventually<T, F, Fut>(what: &str, mut probe: F) -> T
where
    F: FnMut() -> Fut,
    Fut: std::future::Future<Output = Option<T>>,
{
    let deadline = Instant::now() + STEP;
    loop {
        if let Some(value) = probe().await {
            return value;
        }
        assert!(Instant::now() < deadline, "the page never showed: {what}");
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

async fn script(browser: &Client, code: &str) -> Value {
    browser.execute(code, Vec::new()).await.expect(code)
}

/// Clicks a control as a user would: scrolled to the middle of the window first.
async fn click(browser: &Client, css: &str) -> Result<(), String> {
    let element = browser
        .find(Locator::Css(css))
        .await
        .map_err(|e| format!("{css}: {e}"))?;
    browser
        .execute(
            "arguments[0].scrollIntoView({block: 'center'})",
            vec![serde_json::to_value(&element).unwrap()],
        )
        .await
        .map_err(|e| e.to_string())?;
    element
        .click()
        .await
        .map_err(|e| format!("clicking {css}: {e}"))
}

async fn status_text(browser: &Client) -> String {
    script(
        browser,
        "return document.getElementById('status').textContent",
    )
    .await
    .as_str()
    .unwrap_or("")
    .to_owned()
}

/// A template ID that is markup: shown as text, never run.
const MARKUP_ID: &str = "<img src=x onerror=\"window.pwned = 1\">";

/// A camera frame with a distinctive part: a textured scene; the part is its crop at
/// `PART` (x, y, width, height) in image pixels.
const PART: (u32, u32, u32, u32) = (180, 120, 64, 48);

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_setup_flow_works_in_a_real_browser() {
    let chromium = installed(
        "CHROMIUM",
        &["chromium", "chromium-browser", "google-chrome"],
    );
    let chromedriver = installed("CHROMEDRIVER", &["chromedriver"]);
    let (Some(chromium), Some(chromedriver)) = (chromium, chromedriver) else {
        common::unavailable(
            common::CHROMIUM,
            "the setup page's browser test; install Debian's chromium and chromium-driver",
        );
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let mut server = RunningServer::start(
        &settings(&dir.path().join("templates"), &[]),
        embedded_model(),
    )
    .await
    .unwrap();
    server.ready().await.unwrap();
    let page = format!("http://{}/", server.http_addr.unwrap());
    // A template whose ID and labels are markup: the page must show them as text.
    let http = common::http::HttpClient::new(server.http_addr.unwrap());
    let markup = json!({
        "templateId": MARKUP_ID,
        "image": {"encoded": common::http::base64(&png(&image::imageops::crop_imm(&scene(480, 360, 3), 20, 20, 32, 32).to_image()))},
        "labels": {"<b>key</b>": "<img src=y onerror=\"window.pwned = 2\">"}
    });
    let registered = http.post("/v1/templates", &markup).await;
    assert_eq!(registered.status, 200, "{registered:?}");
    let frame_path = dir.path().join("frame.png");
    std::fs::write(&frame_path, png(&scene(480, 360, 3))).unwrap();

    let driver = Driver::start(&chromedriver);
    let capabilities = json!({
        "goog:chromeOptions": {
            "binary": chromium,
            "args": ["--headless=new", "--no-sandbox", "--disable-gpu",
                     "--disable-dev-shm-usage", "--window-size=1366,900"]
        }
    });
    let browser = ClientBuilder::new(hyper_util::client::legacy::connect::HttpConnector::new())
        .capabilities(capabilities.as_object().unwrap().clone())
        .connect(&driver.url)
        .await
        .expect("chromedriver starts a headless Chromium");
    let outcome = setup_flow(&browser, &page, &frame_path).await;
    let _ = browser.close().await;
    drop(driver);
    server.shutdown(Duration::from_secs(5)).await;
    if let Err(message) = outcome {
        panic!("{message}");
    }
}

/// The flow itself; an error names the step that failed.
async fn setup_flow(browser: &Client, page: &str, frame: &Path) -> Result<(), String> {
    browser.goto(page).await.map_err(|e| e.to_string())?;
    assert_eq!(browser.title().await.unwrap(), "PoseMatch setup");
    // Every control has a label (a <label for>, a wrapping label or an aria-label).
    let unlabelled = script(
        browser,
        "return [...document.querySelectorAll('input, select, button')].filter(e =>
            !(e.labels && e.labels.length) && !e.getAttribute('aria-label') && !e.textContent.trim()
        ).map(e => e.id || e.outerHTML.slice(0, 60))",
    )
    .await;
    assert_eq!(unlabelled, json!([]), "controls without a label");

    // Load the frame through the file picker.
    let picker = browser.find(Locator::Id("frame-file")).await.unwrap();
    picker
        .send_keys(frame.to_str().unwrap())
        .await
        .map_err(|e| format!("choosing the frame: {e}"))?;
    let canvas = browser.find(Locator::Id("frame-canvas")).await.unwrap();
    eventually("the frame drawn", || async {
        canvas
            .attr("data-frame-width")
            .await
            .ok()
            .flatten()
            .filter(|w| w == "480")
    })
    .await;

    // Drag a box around the part, in screen coordinates of the scaled canvas.
    let overlay = browser.find(Locator::Id("overlay-canvas")).await.unwrap();
    let geometry = browser
        .execute(
            "arguments[0].scrollIntoView({block: 'center'});
             const r = arguments[0].getBoundingClientRect();
             return [r.left, r.top, r.width / arguments[0].width, r.height / arguments[0].height];",
            vec![serde_json::to_value(&overlay).unwrap()],
        )
        .await
        .unwrap();
    let number = |i: usize| geometry[i].as_f64().unwrap();
    let (left, top, sx, sy) = (number(0), number(1), number(2), number(3));
    let (x, y, w, h) = PART;
    // Pointer positions aim at pixel centres so rounding lands on the intended pixels.
    let screen = |px: f64, py: f64| ((left + px * sx).floor(), (top + py * sy).floor());
    let (x0, y0) = screen(x as f64 + 0.5, y as f64 + 0.5);
    let (x1, y1) = screen((x + w) as f64 + 0.5, (y + h) as f64 + 0.5);
    let drag = MouseActions::new("mouse".into())
        .then(PointerAction::MoveTo {
            duration: None,
            x: x0,
            y: y0,
        })
        .then(PointerAction::Down {
            button: fantoccini::actions::MOUSE_BUTTON_LEFT,
        })
        .then(PointerAction::MoveTo {
            duration: Some(Duration::from_millis(200)),
            x: ((x0 + x1) / 2.0).floor(),
            y: ((y0 + y1) / 2.0).floor(),
        })
        .then(PointerAction::MoveTo {
            duration: Some(Duration::from_millis(200)),
            x: x1,
            y: y1,
        })
        .then(PointerAction::Up {
            button: fantoccini::actions::MOUSE_BUTTON_LEFT,
        });
    browser
        .perform_actions(drag)
        .await
        .map_err(|e| format!("dragging the box: {e}"))?;
    let selected = script(
        browser,
        "return ['sel-x', 'sel-y', 'sel-w', 'sel-h'].map(id => Number(document.getElementById(id).value))",
    )
    .await;
    let selected: Vec<i64> = serde_json::from_value(selected).unwrap();
    let expected = [x as i64, y as i64, w as i64, h as i64];
    let near = selected
        .iter()
        .zip(expected)
        .all(|(got, want)| (got - want).abs() <= 2);
    if !near {
        return Err(format!(
            "the dragged box is {selected:?}, not about {expected:?}"
        ));
    }
    // Keyboard users type the box; so does this test, to cut exactly the part.
    for (id, value) in ["sel-x", "sel-y", "sel-w", "sel-h"].iter().zip(expected) {
        let field = browser.find(Locator::Id(id)).await.unwrap();
        field.clear().await.unwrap();
        field.send_keys(&value.to_string()).await.unwrap();
    }

    // Register the box as a template.
    let id_field = browser.find(Locator::Id("template-id")).await.unwrap();
    id_field.send_keys("bracket-7").await.unwrap();
    browser
        .find(Locator::Id("template-labels"))
        .await
        .unwrap()
        .send_keys("line=4, station=2")
        .await
        .unwrap();
    click(browser, "#register-selection").await?;
    eventually("the registration confirmed", || async {
        let text = status_text(browser).await;
        text.contains("Registered bracket-7").then_some(())
    })
    .await;
    eventually("the template listed and checked", || async {
        let checked = script(
            browser,
            "const box = document.querySelector('#templates li[data-template-id=\"bracket-7\"] input[name=template]');
             return box ? box.checked : null",
        )
        .await;
        (checked == json!(true)).then_some(())
    })
    .await;
    let injected = script(
        browser,
        "return [window.pwned === undefined, document.querySelectorAll('img[src=x], img[src=y], #templates b').length,
                 [...document.querySelectorAll('#templates li')].some(li => li.textContent.includes('<img src=x'))]",
    )
    .await;
    assert_eq!(
        injected,
        json!([true, 0, true]),
        "markup in an ID or label must be shown as text, never run"
    );
    let thumbnail = eventually("the thumbnail loaded", || async {
        let loaded = script(
            browser,
            "const img = document.querySelector('#templates li[data-template-id=\"bracket-7\"] img');
             return img && img.complete && img.naturalWidth",
        )
        .await;
        loaded.as_u64().filter(|w| *w > 0)
    })
    .await;
    assert_eq!(thumbnail, w as u64, "the thumbnail is the registered crop");

    // Match and read the poses.
    click(browser, "#run-match").await?;
    let drawn = eventually("the poses drawn", || async {
        overlay
            .attr("data-drawn-poses")
            .await
            .ok()
            .flatten()
            .and_then(|n| n.parse::<u32>().ok())
    })
    .await;
    let status = status_text(browser).await;
    if drawn == 0 {
        return Err(format!("no pose was found (status: {status})"));
    }
    let rows = script(
        browser,
        "return [...document.querySelectorAll('#poses tbody tr')].map(r => [...r.cells].map(c => c.textContent.trim()))",
    )
    .await;
    let rows: Vec<Vec<String>> = serde_json::from_value(rows).unwrap();
    assert_eq!(rows.len(), drawn as usize, "one table row per drawn pose");
    let best = &rows[0];
    assert!(best.iter().any(|c| c == "bracket-7"), "{best:?}");
    let (cx, cy) = (
        x as f64 + (w as f64 - 1.0) / 2.0,
        y as f64 + (h as f64 - 1.0) / 2.0,
    );
    let numbers: Vec<f64> = best.iter().filter_map(|c| c.parse().ok()).collect();
    // Columns: #, (template), x, y, angle, scale x, scale y, score.
    let (px, py, score) = (numbers[1], numbers[2], numbers[numbers.len() - 1]);
    if (px - cx).abs() > 1.5 || (py - cy).abs() > 1.5 || score < 0.9 {
        return Err(format!(
            "the best pose {best:?} is not the part at ({cx}, {cy}) with a score of at least 0.9"
        ));
    }
    let timings = script(
        browser,
        "return document.getElementById('timings').textContent",
    )
    .await;
    assert!(timings.as_str().unwrap_or("").contains("ms"), "{timings}");
    let painted = script(
        browser,
        "const c = document.getElementById('overlay-canvas');
         const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
         let n = 0; for (let i = 3; i < d.length; i += 4) if (d[i] > 0) n++;
         return n",
    )
    .await;
    assert!(
        painted.as_u64().unwrap_or(0) > 100,
        "the overlay is blank: {painted}"
    );
    let screenshot = browser.screenshot().await.map_err(|e| e.to_string())?;
    let shots = PathBuf::from(env!("CARGO_TARGET_TMPDIR"))
        .parent()
        .map(|target| target.join("browser-test"))
        .unwrap();
    std::fs::create_dir_all(&shots).unwrap();
    std::fs::write(shots.join("setup-page.png"), screenshot).unwrap();

    // Delete it (the page asks first).
    click(
        browser,
        "#templates li[data-template-id=\"bracket-7\"] button.delete",
    )
    .await?;
    browser
        .accept_alert()
        .await
        .map_err(|e| format!("the deletion was not confirmed by a dialog: {e}"))?;
    eventually("the template gone from the list", || async {
        let gone = script(
            browser,
            "return !document.querySelector('#templates li[data-template-id=\"bracket-7\"]')",
        )
        .await;
        (gone == json!(true)).then_some(())
    })
    .await;
    Ok(())
}
