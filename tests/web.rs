//! `gaitscope live --web` in a real browser: Debian's headless Chromium driven through
//! chromedriver (WebDriver), against the binary serving the bundled LSTM checkpoint.
//! Needs `chromium` and `chromium-driver` (scripts/setup.sh --test installs them).
#![cfg(feature = "web")]

use fantoccini::{Client, ClientBuilder, Locator};
use re_chunk::Chunk;
use serde_json::{Value, json};
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

mod common;

const WAIT: Duration = Duration::from_secs(60);

fn free_ports<const N: usize>() -> [u16; N] {
    // Held together so that they differ, released before the servers bind them.
    let listeners: Vec<TcpListener> = (0..N)
        .map(|_| TcpListener::bind("127.0.0.1:0").unwrap())
        .collect();
    std::array::from_fn(|i| listeners[i].local_addr().unwrap().port())
}

fn wait_for_port(port: u16, child: &mut Child) {
    let deadline = Instant::now() + WAIT;
    while std::net::TcpStream::connect(("127.0.0.1", port)).is_err() {
        if let Ok(Some(status)) = child.try_wait() {
            panic!("exited before listening on {port}: {status}");
        }
        assert!(Instant::now() < deadline, "nothing listens on {port}");
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// Kills the process when the test ends, however it ends.
struct Killed(Child);

impl Drop for Killed {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// The inodes of the sockets `pid` holds open (its fds' `socket:[N]` links; none if it is gone).
fn socket_inodes(pid: u32) -> Vec<String> {
    let Ok(fds) = std::fs::read_dir(format!("/proc/{pid}/fd")) else {
        return Vec::new();
    };
    fds.filter_map(|e| std::fs::read_link(e.ok()?.path()).ok())
        .filter_map(|l| {
            let l = l.to_string_lossy().into_owned();
            Some(l.strip_prefix("socket:[")?.strip_suffix(']')?.to_string())
        })
        .collect()
}

/// The TCP sockets `pid` listens on, as (address, port), from /proc/net/tcp{,6} and its fds.
fn listening_sockets(pid: u32) -> Vec<(std::net::IpAddr, u16)> {
    let inodes = socket_inodes(pid);
    let mut out = Vec::new();
    for (file, v6) in [("/proc/net/tcp", false), ("/proc/net/tcp6", true)] {
        let Ok(text) = std::fs::read_to_string(file) else {
            continue;
        };
        for line in text.lines().skip(1) {
            let f: Vec<&str> = line.split_whitespace().collect();
            // local_address, st (0A = LISTEN), inode
            if f.len() < 10 || f[3] != "0A" || !inodes.iter().any(|i| i == f[9]) {
                continue;
            }
            let (addr, port) = f[1].split_once(':').unwrap();
            let port = u16::from_str_radix(port, 16).unwrap();
            let ip = if v6 {
                // Four little-endian 32-bit words.
                let mut bytes = [0u8; 16];
                for w in 0..4 {
                    let word = u32::from_str_radix(&addr[8 * w..8 * w + 8], 16).unwrap();
                    bytes[4 * w..4 * w + 4].copy_from_slice(&word.to_le_bytes());
                }
                std::net::IpAddr::from(bytes)
            } else {
                std::net::IpAddr::from(u32::from_str_radix(addr, 16).unwrap().to_le_bytes())
            };
            out.push((ip, port));
        }
    }
    out
}

/// The paths of the Unix sockets `pid` listens on (`/proc/net/unix`: flag `__SO_ACCEPTCON`).
fn listening_unix_sockets(pid: u32) -> Vec<PathBuf> {
    let inodes = socket_inodes(pid);
    let text = std::fs::read_to_string("/proc/net/unix").unwrap_or_default();
    text.lines()
        .skip(1)
        .filter_map(|line| {
            // Num RefCount Protocol Flags Type St Inode Path
            let f: Vec<&str> = line.split_whitespace().collect();
            let listening = u32::from_str_radix(f.get(3)?, 16).ok()? & 0x0001_0000 != 0;
            let inode = *f.get(6)?;
            if !listening || !inodes.iter().any(|i| i == inode) {
                return None;
            }
            Some(PathBuf::from(f.get(7)?))
        })
        .collect()
}

/// Processes whose parent chain reaches `ancestor`, running `exe`.
fn descendants_running(ancestor: u32, exe: &Path) -> Vec<u32> {
    let parent = |pid: u32| -> Option<u32> {
        let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
        // "pid (comm) state ppid …": comm may hold spaces, so split after its ')'.
        stat.rsplit_once(')')?
            .1
            .split_whitespace()
            .nth(1)?
            .parse()
            .ok()
    };
    let exe = exe.canonicalize().unwrap();
    std::fs::read_dir("/proc")
        .unwrap()
        .filter_map(|e| e.ok()?.file_name().to_str()?.parse::<u32>().ok())
        .filter(|&pid| std::fs::read_link(format!("/proc/{pid}/exe")).is_ok_and(|p| p == exe))
        .filter(|&pid| {
            let mut p = pid;
            while let Some(up) = parent(p) {
                if up == ancestor {
                    return true;
                }
                if up <= 1 {
                    break;
                }
                p = up;
            }
            false
        })
        .collect()
}

/// The process that listens on `port` (any address), if one does.
fn listener_of(port: u16) -> Option<u32> {
    let pids: Vec<u32> = std::fs::read_dir("/proc")
        .ok()?
        .filter_map(|e| e.ok()?.file_name().to_str()?.parse::<u32>().ok())
        .collect();
    pids.into_iter()
        .find(|&pid| listening_sockets(pid).iter().any(|(_, p)| *p == port))
}

fn chromedriver() -> (Killed, u16) {
    let [port] = free_ports::<1>();
    let mut child = Command::new("chromedriver")
        .arg(format!("--port={port}"))
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("chromedriver (Debian's chromium-driver: scripts/setup.sh --test installs it)");
    wait_for_port(port, &mut child);
    (Killed(child), port)
}

async fn browser(port: u16) -> Client {
    let profile = tempfile::tempdir().unwrap().keep();
    let mut caps = serde_json::Map::new();
    caps.insert(
        "goog:chromeOptions".into(),
        json!({
            "binary": "/usr/bin/chromium",
            "args": [
                "--headless=new", "--no-sandbox", "--no-first-run", "--disable-quic",
                "--disable-background-networking", "--disable-component-update", "--disable-sync",
                "--disable-dev-shm-usage", "--window-size=1400,1000",
                // WebGL on the CPU (SwiftShader), for Rerun's viewer on a machine with no GPU.
                "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                format!("--user-data-dir={}", profile.display()),
            ],
        }),
    );
    ClientBuilder::new(hyper_util::client::legacy::connect::HttpConnector::new())
        .capabilities(caps)
        .connect(&format!("http://127.0.0.1:{port}"))
        .await
        .expect("a chromium session through chromedriver")
}

/// Chromium on the control page at `port`: the driver (killed on drop), the runtime to drive the
/// client with, and the client.
fn control_page(port: u16) -> (Killed, tokio::runtime::Runtime, Client) {
    let (driver, driver_port) = chromedriver();
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let client = rt.block_on(async {
        let client = browser(driver_port).await;
        client
            .goto(&format!("http://127.0.0.1:{port}/"))
            .await
            .unwrap();
        client
    });
    (driver, rt, client)
}

/// Clicks the page's element `id`.
async fn click(client: &Client, id: &str) {
    client
        .find(Locator::Id(id))
        .await
        .unwrap()
        .click()
        .await
        .unwrap();
}

/// The text of the page's element `id`.
async fn text_of(client: &Client, id: &str) -> String {
    client
        .find(Locator::Id(id))
        .await
        .unwrap()
        .text()
        .await
        .unwrap()
}

/// Types `count` into the page's step field and presses Step.
async fn step_by(client: &Client, count: u32) {
    let field = client.find(Locator::Id("step-count")).await.unwrap();
    field.clear().await.unwrap();
    field.send_keys(&count.to_string()).await.unwrap();
    click(client, "step").await;
}

/// The page's own view of the sim: GET /state from inside the page.
async fn state(client: &Client) -> Value {
    client
        .execute_async(
            "const done = arguments[0]; fetch('/state').then(r => r.json()).then(done);",
            vec![],
        )
        .await
        .unwrap()
}

async fn wait_state(client: &Client, what: &str, ready: impl Fn(&Value) -> bool) -> Value {
    let deadline = Instant::now() + WAIT;
    loop {
        let s = state(client).await;
        if ready(&s) {
            return s;
        }
        assert!(
            Instant::now() < deadline,
            "timed out waiting for {what}: {s}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

fn lane_step(s: &Value) -> u64 {
    s["lanes"][0]["step"].as_u64().unwrap()
}

fn joint<'a>(s: &'a Value, name: &str) -> &'a Value {
    s["lanes"][0]["joints"]
        .as_array()
        .unwrap()
        .iter()
        .find(|j| j["name"] == name)
        .unwrap()
}

/// Sends a raw body from the page, as a buggy or hostile page would, and returns the reply.
async fn send_raw(client: &Client, body: &str) -> Value {
    client
        .execute_async(
            "const done = arguments[1]; window.gaitscopeSend(arguments[0]).then(done);",
            vec![json!(body)],
        )
        .await
        .unwrap()
}

/// Waits (up to WAIT) for `live --web` to exit after `what`; its status and stderr.
fn wait_exit(live: &mut Killed, what: &str) -> (std::process::ExitStatus, String) {
    let deadline = Instant::now() + WAIT;
    let status = loop {
        if let Some(status) = live.0.try_wait().unwrap() {
            break status;
        }
        assert!(
            Instant::now() < deadline,
            "live --web did not end after {what}"
        );
        std::thread::sleep(Duration::from_millis(100));
    };
    let mut stderr = String::new();
    std::io::Read::read_to_string(live.0.stderr.as_mut().unwrap(), &mut stderr).unwrap();
    (status, stderr)
}

fn read_rrd(path: &Path) -> Vec<Chunk> {
    common::recording_chunks(read_msgs(path))
}

fn read_msgs(path: &Path) -> Vec<rerun::log::LogMsg> {
    let file = std::io::BufReader::new(std::fs::File::open(path).unwrap());
    re_log_encoding::DecoderApp::decode_lazy(file)
        .map_while(Result::ok)
        .collect()
}

/// PNG → (width, height, variance of the grey level): a blank page has none.
fn png_variance(png: &[u8]) -> (u32, u32, f64) {
    let decoder = png::Decoder::new(std::io::Cursor::new(png));
    let mut reader = decoder.read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size().unwrap()];
    let info = reader.next_frame(&mut buf).unwrap();
    let channels = info.color_type.samples();
    let grey: Vec<f64> = buf[..info.buffer_size()]
        .chunks(channels)
        .map(|p| p[..3].iter().map(|&c| f64::from(c)).sum::<f64>() / 3.0)
        .collect();
    let mean = grey.iter().sum::<f64>() / grey.len() as f64;
    let var = grey.iter().map(|g| (g - mean).powi(2)).sum::<f64>() / grey.len() as f64;
    (info.width, info.height, var)
}

/// `gaitscope live --web` on the bundled LSTM with `args`, on three free ports (control page,
/// web viewer, gRPC), no display; returns once the control page answers.
fn live_web(args: &[&std::ffi::OsStr], stderr: Stdio) -> (Killed, [u16; 3]) {
    let ports = free_ports::<3>();
    let child = Command::new(env!("CARGO_BIN_EXE_gaitscope"))
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .args(["live", "--web", "--checkpoint", "checkpoints/encoder-lstm"])
        .args(["--exit-after", "300"])
        .args(["--port", &ports[0].to_string()])
        .args(["--viewer-port", &ports[1].to_string()])
        .args(["--grpc-port", &ports[2].to_string()])
        .args(args)
        .env_remove("DISPLAY")
        .env_remove("WAYLAND_DISPLAY")
        .stdout(Stdio::null())
        .stderr(stderr)
        .spawn()
        .unwrap();
    let mut live = Killed(child);
    wait_for_port(ports[0], &mut live.0);
    (live, ports)
}

/// Frames the page paints per second over `ms` (requestAnimationFrame).
async fn animation_fps(client: &Client, ms: u32) -> Value {
    client
        .execute_async(
            "const [ms, done] = arguments; let n = 0; const t0 = performance.now();
             function tick() { n++; if (performance.now() - t0 < ms) requestAnimationFrame(tick);
             else done(1000 * n / (performance.now() - t0)); }
             requestAnimationFrame(tick);",
            vec![json!(ms)],
        )
        .await
        .unwrap()
}

#[test]
fn the_control_page_drives_the_sim_and_the_web_viewer_renders() {
    let dir = tempfile::tempdir().unwrap();
    let save = dir.path().join("session.rrd");
    let args = ["--condition", "manual", "--paused", "--save"].map(std::ffi::OsStr::new);
    let (mut live, [port, viewer_port, grpc_port]) =
        live_web(&[&args[..], &[save.as_os_str()]].concat(), Stdio::piped());

    // Every socket it listens on is a loopback one, and it serves all three of ours.
    let sockets = listening_sockets(live.0.id());
    assert!(
        sockets.iter().all(|(ip, _)| ip.is_loopback()),
        "{sockets:?}"
    );
    for p in [port, viewer_port, grpc_port] {
        assert!(sockets.iter().any(|(_, q)| *q == p), "{p} in {sockets:?}");
    }

    let (_driver, rt, client) = control_page(port);
    rt.block_on(async move {
        // The joint rows appear with the first server-sent snapshot.
        let fail = client
            .wait()
            .at_most(WAIT)
            .for_element(Locator::Id("fail-ankle_3"))
            .await
            .unwrap();
        let s = state(&client).await;
        assert_eq!(s["paused"], true);
        // The joint table names the model it shows.
        let heading = text_of(&client, "joints-model").await;
        assert_eq!(heading, "encoder-lstm");
        assert_eq!(lane_step(&s), 0);
        // The page says what the condition means in the model's world (the bundled model's is
        // the paper's); each option says its own on hover.
        assert_eq!(s["world"], "paper");
        assert_eq!(
            s["condition_meanings"]["mild"],
            "a joint whose fatigue reaches 30 keeps 0.5× its torque"
        );
        let meaning = text_of(&client, "condition-meaning").await;
        assert_eq!(
            meaning,
            "world paper: manual = only what a hand does (fail now: 0.1× torque)"
        );
        // Manual: fatigue accumulates but triggers nothing, and the heading says so.
        assert_eq!(s["lanes"][0]["fatigue_triggers"], false);
        let tau = text_of(&client, "tau").await;
        assert_eq!(tau, "fatigue triggers nothing here");
        let severe_hint = client
            .find(Locator::Css("#condition option:nth-child(3)"))
            .await
            .unwrap()
            .attr("title")
            .await
            .unwrap();
        assert_eq!(
            severe_hint.as_deref(),
            Some("a joint whose fatigue reaches 30 keeps 0.1× its torque")
        );
        // The page says how the web viewer gets the stream (gaitscope::telemetry::WEB_STREAM_BATCH).
        let note = text_of(&client, "viewer-note").await;
        assert!(note.contains("500 ms batches"), "{note}");
        assert_eq!(s["session"]["viewer_batch_ms"], 500);

        // Pause is on: "Step" with 5 advances exactly 5 env steps.
        step_by(&client, 5).await;
        wait_state(&client, "5 steps", |s| lane_step(s) >= 5).await;
        tokio::time::sleep(Duration::from_millis(500)).await;
        assert_eq!(
            lane_step(&state(&client).await),
            5,
            "exactly 5, then paused"
        );

        // "fail" on ankle_3: the joint is failed before the next step (manual → severe 0.1).
        fail.click().await.unwrap();
        let s = wait_state(&client, "ankle_3 failed", |s| {
            joint(s, "ankle_3")["state"] == "triggered"
        })
        .await;
        assert_eq!(joint(&s, "ankle_3")["scale"], 0.1);
        assert_eq!(lane_step(&s), 5, "applied while paused, before step 6");
        // The page's own readout of the click (its next event may trail our /state read).
        let deadline = Instant::now() + WAIT;
        let latency = loop {
            let text = text_of(&client, "latency").await;
            if text.ends_with("(step 5)") {
                break text;
            }
            assert!(Instant::now() < deadline, "latency readout: {text}");
            tokio::time::sleep(Duration::from_millis(20)).await;
        };
        eprintln!("click → applied, seen by the page: {latency}");
        // The server's timing of it (its event may come one period after the applied state).
        let last = loop {
            let text = text_of(&client, "last-command").await;
            if text.contains("taken by") || Instant::now() > deadline {
                break text;
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        };
        assert!(
            last.starts_with("edit fail:ankle_3: taken by the simulation")
                && last.ends_with("ms after the server sent it"),
            "{last}"
        );
        step_by(&client, 1).await;
        let s = wait_state(&client, "step 6", |s| lane_step(s) == 6).await;
        let ankle = joint(&s, "ankle_3");
        assert_eq!(
            ankle["applied"].as_f64().unwrap(),
            0.1 * ankle["commanded"].as_f64().unwrap()
        );

        // Bad requests: refused with their reason, shown on the page, nothing changes.
        let handled = s["commands_handled"].as_u64().unwrap();
        let too_many_edits = format!(
            r#"{{"command":"edit","edit":"{}"}}"#,
            vec!["fail:all"; 65].join(",")
        );
        for (body, reason) in [
            ("{not json", "malformed request"),
            (
                r#"{"command":"edit","edit":"fail:ankle_9"}"#,
                "unknown joint 'ankle_9'",
            ),
            (r#"{"command":"edit","edit":"scale:ankle_3=1.5"}"#, "[0, 1]"),
            (
                r#"{"command":"speed","value":100}"#,
                "speed must be between",
            ),
            (r#"{"command":"self_destruct"}"#, "malformed request"),
            (
                too_many_edits.as_str(),
                "65 edits in one request; at most 64",
            ),
        ] {
            let reply = send_raw(&client, body).await;
            let error = reply["error"].as_str().unwrap_or_default();
            assert!(error.contains(reason), "{body}: {reply}");
            let shown = text_of(&client, "error").await;
            assert!(shown.contains(reason), "{shown}");
        }
        let s = state(&client).await;
        assert_eq!(s["commands_handled"].as_u64().unwrap(), handled);
        assert_eq!(lane_step(&s), 6);
        assert_eq!(joint(&s, "ankle_3")["scale"], 0.1);

        // Bad pushes are refused with their reason too.
        for (body, reason) in [
            (
                r#"{"command":"push","body":"tail","force":[0,40,0]}"#,
                "unknown body 'tail' to push",
            ),
            (
                r#"{"command":"push","body":"torso","force":[0,4000,0]}"#,
                "more than the 1000 N",
            ),
            (
                r#"{"command":"push","body":"torso","force":[0,40]}"#,
                "malformed request",
            ),
        ] {
            let reply = send_raw(&client, body).await;
            let error = reply["error"].as_str().unwrap_or_default();
            assert!(error.contains(reason), "{body}: {reply}");
        }
        // The attribution checkbox reaches the sim.
        click(&client, "attribution").await;
        wait_state(&client, "attribution on", |s| s["attribution"] == true).await;
        // "Push" with the page's defaults (torso, 40 N along +y, 5 steps), then two steps.
        click(&client, "push").await;
        wait_state(&client, "push taken", |s| {
            s["commands_handled"].as_u64().unwrap() > handled
        })
        .await;
        step_by(&client, 2).await;
        wait_state(&client, "step 8", |s| lane_step(s) == 8).await;
        // "Save state": the page fetches the state before step 9 (and offers it as a file).
        click(&client, "save-state").await;
        let deadline = Instant::now() + WAIT;
        let saved = loop {
            let v = client
                .execute("return window.gaitscopeSavedState || null", vec![])
                .await
                .unwrap();
            if let Some(text) = v.as_str() {
                break text.to_string();
            }
            assert!(Instant::now() < deadline, "no saved state");
            tokio::time::sleep(Duration::from_millis(20)).await;
        };
        let saved: Value = serde_json::from_str(&saved).unwrap();
        assert_eq!(saved["format"], "gaitscope-state/1");
        assert_eq!(saved["step"], 8);
        assert_eq!(
            saved["damage"]["scale"][7], 0.1,
            "ankle_3 failed by the page"
        );
        assert_eq!(saved["pushes"][0]["remaining"], 3, "5-step push, 2 taken");
        assert!(saved["mjcf_key"].as_str().unwrap().starts_with("<key "));

        // The Rerun web viewer loads in the same browser and draws the stream.
        client.new_window(true).await.unwrap();
        let handles = client.windows().await.unwrap();
        client.switch_to_window(handles[1].clone()).await.unwrap();
        let viewer_url = s["session"]["viewer_url"].as_str().unwrap().to_string();
        client.goto(&viewer_url).await.unwrap();
        client
            .wait()
            .at_most(WAIT)
            .for_element(Locator::Css("canvas"))
            .await
            .unwrap();
        // Frames the browser paints per second while the viewer runs (requestAnimationFrame).
        let fps = animation_fps(&client, 3000).await;
        eprintln!("web viewer tab: {fps} frames/s (requestAnimationFrame, headless SwiftShader)");
        tokio::time::sleep(Duration::from_secs(10)).await;
        let shot = client.screenshot().await.unwrap();
        let (w, h, var) = png_variance(&shot);
        let out = Path::new(env!("CARGO_TARGET_TMPDIR")).join("web-viewer.png");
        std::fs::write(&out, &shot).unwrap();
        eprintln!(
            "viewer screenshot {w}×{h}, grey variance {var:.0}: {}",
            out.display()
        );
        assert!(var > 100.0, "the viewer tab is blank (variance {var})");
        client.switch_to_window(handles[0].clone()).await.unwrap();
        let shot = client.screenshot().await.unwrap();
        std::fs::write(
            Path::new(env!("CARGO_TARGET_TMPDIR")).join("web-control.png"),
            &shot,
        )
        .unwrap();

        // Quit from the page ends the process, and the saved stream holds what the page did.
        click(&client, "quit").await;
        client.close().await.unwrap();
    });
    let (status, stderr) = wait_exit(&mut live, "Quit");
    assert!(status.success(), "{stderr}");
    assert!(stderr.contains("control page:"), "{stderr}");
    // Written as session.rrd.partial, renamed once flushed.
    assert!(!dir.path().join("session.rrd.partial").exists());
    let chunks = read_rrd(&save);
    // The legs: per-step colours only, ankle_3 red (scale 0.1) from the step after the page
    // failed it.
    common::assert_no_static_shadowing(&chunks);
    assert_eq!(
        common::check_leg_colors(&chunks, "/ant", &[]),
        3,
        "ankle_3 red at steps 6, 7 and 8"
    );
    // The 3-D view is titled by checkpoint, not by the lane's fixed root ("Ant: ant").
    let views = common::blueprint_view_names(&read_msgs(&save));
    assert!(
        views.contains(&"Ant: encoder-lstm".to_string()),
        "{views:?}"
    );
    assert!(!views.contains(&"Ant: ant".to_string()), "{views:?}");
    let commanded = common::joint_series(&chunks, "/ant/actions/commanded");
    let applied = common::joint_series(&chunks, "/ant/actions/applied");
    assert_eq!(applied.len(), 8, "8 env steps reached the file");
    // Env step t is recorded at global step t + 1; ankle_3 is actuator 7 in Ant-v4's order.
    let a = 7;
    for t in 0..8i64 {
        let scale = if t >= 5 { 0.1 } else { 1.0 };
        assert_eq!(
            applied[&(t + 1)][a],
            scale * commanded[&(t + 1)][a],
            "env step {t}"
        );
    }
    let events = common::text_log(&chunks, "/ant/events");
    assert_eq!(
        events,
        vec![
            (6, "step 6: ankle_3 failed by hand; scale → 0.1".to_string()),
            (
                7,
                "step 7: push torso by (0, 40, 0) N for 5 steps".to_string()
            )
        ]
    );
    // The push's arrow is drawn on the two steps it acted (and still acts).
    let vectors = rerun::Arrows3D::descriptor_vectors().component;
    let arrows: Vec<i64> = common::per_step(&chunks, "/ant/world/push", |c| {
        c.iter_slices::<[f32; 3]>(vectors)
            .map(|s| s.len())
            .collect::<Vec<usize>>()
    })
    .into_iter()
    .filter(|(_, n)| *n > 0)
    .map(|(t, _)| t)
    .collect();
    assert_eq!(arrows, [7, 8]);
}

#[test]
fn bad_web_flags_are_refused_before_anything_listens() {
    let run = |args: &[&str]| {
        Command::new(env!("CARGO_BIN_EXE_gaitscope"))
            .current_dir(env!("CARGO_MANIFEST_DIR"))
            .args(["live", "--web", "--exit-after", "5"])
            .args(args)
            .output()
            .unwrap()
    };
    // A port the OS hands out and this test holds, so no other test can take it meanwhile.
    let taken = TcpListener::bind(("127.0.0.1", 0)).unwrap();
    let port = taken.local_addr().unwrap().port();
    let out = run(&["--port", &port.to_string()]);
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("cannot listen for the control page"),
        "{stderr}"
    );
    drop(taken);
    let out = run(&["--port", "9999", "--viewer-port", "9999"]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("given twice"), "{stderr}");
    let out = run(&["--bind", "not-an-address"]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("--bind"), "{stderr}");
}

#[test]
fn native_live_and_the_viewer_it_spawns_listen_only_on_loopback() {
    // `live` as a person runs it: a display (a private Xvfb screen), the stock Rerun viewer it
    // spawns (Vulkan on the CPU), the egui panel.
    let runtime = tempfile::tempdir().unwrap();
    let bin = Path::new(env!("CARGO_BIN_EXE_gaitscope"));
    let child = Command::new("xvfb-run")
        .args(["-a", "-s", "-screen 0 1920x1080x24"])
        .arg(bin)
        .args([
            "live",
            "--checkpoint",
            "checkpoints/encoder-lstm",
            "--exit-after",
            "15",
        ])
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .env("WGPU_BACKEND", "vulkan")
        .env("XDG_RUNTIME_DIR", runtime.path())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("xvfb-run (Debian's xvfb: scripts/setup.sh --test installs it)");
    let mut live = Killed(child);
    // "streaming to the Rerun viewer (PATH) at rerun+http://127.0.0.1:PORT/proxy"
    let stderr = live.0.stderr.take().unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        use std::io::BufRead;
        for line in std::io::BufReader::new(stderr)
            .lines()
            .map_while(Result::ok)
        {
            let _ = tx.send(line);
        }
    });
    let deadline = Instant::now() + WAIT;
    let mut said = Vec::new();
    let port: u16 = loop {
        let line = rx
            .recv_timeout(deadline.saturating_duration_since(Instant::now()))
            .unwrap_or_else(|_| panic!("live never said where it streams: {said:?}"));
        if let Some(rest) = line.split("rerun+http://127.0.0.1:").nth(1) {
            break rest.split('/').next().unwrap().parse().unwrap();
        }
        said.push(line);
    };
    let viewer = loop {
        if let Some(pid) = listener_of(port) {
            break pid;
        }
        assert!(Instant::now() < deadline, "no viewer listens on {port}");
        std::thread::sleep(Duration::from_millis(200));
    };
    // Let the session run a few seconds (the panel up, the stream flowing) before looking.
    std::thread::sleep(Duration::from_secs(5));
    let ours = descendants_running(live.0.id(), bin);
    assert_eq!(ours.len(), 1, "one gaitscope under xvfb-run: {ours:?}");
    let mut sockets = listening_sockets(ours[0]);
    let viewer_sockets = listening_sockets(viewer);
    // --exit-after ends the session and the viewer it started: nothing is left running.
    let deadline = Instant::now() + WAIT;
    while live.0.try_wait().unwrap().is_none() {
        assert!(Instant::now() < deadline, "live outlived --exit-after");
        std::thread::sleep(Duration::from_millis(200));
    }
    let viewer_left = Path::new(&format!("/proc/{viewer}")).exists();
    if viewer_left {
        let _ = Command::new("kill").arg(viewer.to_string()).status();
    }
    let mut said = said.join("\n");
    while let Ok(line) = rx.try_recv() {
        said.push('\n');
        said.push_str(&line);
    }
    assert!(
        !viewer_left,
        "the viewer outlived live --exit-after: {said}"
    );
    assert!(
        said.contains("closed the Rerun viewer it started"),
        "{said}"
    );
    assert!(
        viewer_sockets.iter().any(|(_, p)| *p == port),
        "{viewer_sockets:?}"
    );
    sockets.extend(viewer_sockets);
    assert!(
        sockets.iter().all(|(ip, _)| ip.is_loopback()),
        "every listening socket of live and its viewer is loopback: {sockets:?}"
    );
}

/// The docs' pictures and numbers, of a running two-model session (not a check: run with
/// `cargo test --release --test web -- --ignored`, then look at docs/web-*.png).
#[test]
#[ignore]
fn docs_pictures_and_latency_of_a_running_session() {
    let args = ["--compare", "checkpoints/baseline", "--condition", "severe"];
    let (_live, [port, ..]) = live_web(&args.map(std::ffi::OsStr::new), Stdio::null());
    let docs = Path::new(env!("CARGO_MANIFEST_DIR")).join("docs");
    let (_driver, rt, client) = control_page(port);
    rt.block_on(async move {
        client
            .wait()
            .at_most(WAIT)
            .for_element(Locator::Id("fail-hip_1"))
            .await
            .unwrap();
        // Click → the page sees the applied state, on a sim running at 1×, five times.
        let mut latencies = Vec::new();
        for joint in ["hip_1", "ankle_1", "hip_2", "ankle_2", "hip_3"] {
            tokio::time::sleep(Duration::from_secs(2)).await;
            let t0 = Instant::now();
            client
                .find(Locator::Id(&format!("fail-{joint}")))
                .await
                .unwrap()
                .click()
                .await
                .unwrap();
            let text = loop {
                let t = text_of(&client, "latency").await;
                if t != "–" && !latencies.iter().any(|(_, l)| *l == t) {
                    break t;
                }
                assert!(
                    t0.elapsed() < Duration::from_secs(20),
                    "no latency shown after {joint}: {t}"
                );
                tokio::time::sleep(Duration::from_millis(5)).await;
            };
            latencies.push((t0.elapsed().as_millis(), text));
        }
        eprintln!(
            "click → applied, as the page shows it (and the driver's round trip): {latencies:?}"
        );
        let s = state(&client).await;
        let url = s["session"]["viewer_url"].as_str().unwrap().to_string();
        client.new_window(true).await.unwrap();
        let handles = client.windows().await.unwrap();
        client.switch_to_window(handles[1].clone()).await.unwrap();
        client.goto(&url).await.unwrap();
        tokio::time::sleep(Duration::from_secs(20)).await;
        let fps = animation_fps(&client, 5000).await;
        eprintln!("web viewer tab: {fps} frames/s");
        std::fs::write(
            docs.join("web-viewer.png"),
            client.screenshot().await.unwrap(),
        )
        .unwrap();
        client.switch_to_window(handles[0].clone()).await.unwrap();
        std::fs::write(
            docs.join("web-control.png"),
            client.screenshot().await.unwrap(),
        )
        .unwrap();
        let s = state(&client).await;
        eprintln!(
            "sim: {} of {} steps/s",
            s["steps_per_s"], s["target_steps_per_s"]
        );
        client.close().await.unwrap();
    });
}

/// SIGINT and SIGTERM end `live --web` as Quit does: exit 0, the session report, and a
/// `--save` file flushed to the last step.
#[test]
fn a_signal_ends_live_web_with_its_report_and_saved_file() {
    for signal in ["-INT", "-TERM"] {
        let dir = tempfile::tempdir().unwrap();
        let save = dir.path().join("session.rrd");
        let args = [std::ffi::OsStr::new("--save"), save.as_os_str()];
        let (mut live, _) = live_web(&args, Stdio::piped());
        // Let it run a few steps at 1×.
        std::thread::sleep(Duration::from_secs(2));
        let pid = live.0.id().to_string();
        assert!(
            Command::new("kill")
                .args([signal, &pid])
                .status()
                .unwrap()
                .success()
        );
        let (status, stderr) = wait_exit(&mut live, signal);
        assert!(status.success(), "{signal}: {stderr}");
        assert!(
            stderr.contains("web: ") && stderr.contains("requests"),
            "{stderr}"
        );
        let chunks = read_rrd(&save);
        let steps = common::joint_series(&chunks, "/ant/joints/fatigue").len();
        assert!(
            steps > 0,
            "{signal}: the saved file has the session's steps"
        );
    }
}

/// One HTTP request on its own connection; the whole answer (or what came within 20 s).
fn raw_http(port: u16, request: &str) -> String {
    use std::io::{Read, Write};
    let mut stream = std::net::TcpStream::connect(("127.0.0.1", port)).unwrap();
    stream
        .set_read_timeout(Some(Duration::from_secs(20)))
        .unwrap();
    stream.write_all(request.as_bytes()).unwrap();
    let mut answer = Vec::new();
    let _ = stream.read_to_end(&mut answer);
    String::from_utf8_lossy(&answer).into_owned()
}

fn post(port: u16, body: &str) -> String {
    raw_http(
        port,
        &format!(
            "POST /command HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nContent-Type: application/json\r\n\
             Content-Length: {}\r\nConnection: close\r\n\r\n{body}",
            body.len()
        ),
    )
}

/// A client that announces a body and stalls holds only its own request: the page's state, other
/// commands and Quit go on; a stalled body loses its slot after its time.
#[test]
fn a_stalled_request_does_not_freeze_the_page() {
    use std::io::Write;
    let (mut live, [port, _, _]) = live_web(&[std::ffi::OsStr::new("--paused")], Stdio::null());
    // Announces 5,000 bytes, sends one, keeps the connection open.
    let mut stalled = std::net::TcpStream::connect(("127.0.0.1", port)).unwrap();
    stalled
        .write_all(
            format!(
                "POST /command HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nContent-Type: application/json\r\n\
                 Content-Length: 5000\r\n\r\n{{"
            )
            .as_bytes(),
        )
        .unwrap();
    std::thread::sleep(Duration::from_millis(300));
    let state = raw_http(
        port,
        &format!("GET /state HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nConnection: close\r\n\r\n"),
    );
    assert!(state.starts_with("HTTP/1.1 200"), "{state}");
    assert!(state.contains("\"paused\":true"), "{state}");
    let stepped = post(port, r#"{"command":"step","count":3}"#);
    assert!(
        stepped.starts_with("HTTP/1.1 200") && stepped.contains("receipt"),
        "{stepped}"
    );
    // A command from outside the page is timed by the server, and the page shows it.
    let get = |path: &str| {
        raw_http(
            port,
            &format!("GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nConnection: close\r\n\r\n"),
        )
    };
    let body = |answer: &str| -> Value {
        serde_json::from_str(answer.split("\r\n\r\n").nth(1).unwrap()).unwrap()
    };
    let deadline = Instant::now() + WAIT;
    let timed = loop {
        let s = body(&get("/state"));
        if s["last_command"]["applied"] == true && s["lanes"][0]["step"] == 3 {
            break s;
        }
        assert!(Instant::now() < deadline, "the API's step never timed: {s}");
        std::thread::sleep(Duration::from_millis(20));
    };
    let last = &timed["last_command"];
    assert_eq!(last["command"], "step 3", "{last}");
    let ms = last["applied_in_ms"].as_f64().unwrap();
    assert!((0.0..WAIT.as_millis() as f64).contains(&ms), "{last}");
    // The page comes with that state inside it: never an empty "connecting…" page.
    let page = get("/");
    let start = page.find("const first = ").unwrap() + "const first = ".len();
    let line = &page[start..start + page[start..].find('\n').unwrap()];
    let first: Value = serde_json::from_str(line.trim_end_matches(';')).unwrap();
    assert_eq!(first["paused"], true);
    assert_eq!(first["lanes"][0]["step"], timed["lanes"][0]["step"]);
    assert_eq!(first["last_command"]["command"], "step 3");
    assert!(!page.contains("FIRST_SNAPSHOT"));
    let quit = post(port, r#"{"command":"quit"}"#);
    assert!(quit.starts_with("HTTP/1.1 200"), "{quit}");
    let deadline = Instant::now() + WAIT;
    while live.0.try_wait().unwrap().is_none() {
        assert!(
            Instant::now() < deadline,
            "Quit ended the session despite the stalled client"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    drop(stalled);
}

/// Every port `live --web` serves answers only loopback hosts (DNS rebinding reaches none of
/// them), caps its connections and times out slow headers: a flood of half-open connections
/// leaves the thread count bounded and the page answering once it passes.
#[test]
fn every_port_checks_host_and_bounds_connections() {
    let (mut live, [port, viewer_port, grpc_port]) =
        live_web(&[std::ffi::OsStr::new("--paused")], Stdio::null());
    for p in [port, viewer_port, grpc_port] {
        let evil = raw_http(
            p,
            "GET / HTTP/1.1\r\nHost: rebind.evil.example\r\nConnection: close\r\n\r\n",
        );
        assert!(evil.starts_with("HTTP/1.1 403"), "port {p}: {evil}");
    }
    let viewer = raw_http(
        viewer_port,
        &format!("GET / HTTP/1.1\r\nHost: 127.0.0.1:{viewer_port}\r\nConnection: close\r\n\r\n"),
    );
    assert!(
        viewer.starts_with("HTTP/1.1 200"),
        "{}",
        &viewer[..viewer.len().min(200)]
    );
    let threads = || {
        std::fs::read_dir(format!("/proc/{}/task", live.0.id()))
            .unwrap()
            .count()
    };
    let before = threads();
    // 300 connections that send half a header and wait.
    let flood: Vec<std::net::TcpStream> = (0..300)
        .filter_map(|_| {
            let mut s = std::net::TcpStream::connect(("127.0.0.1", port)).ok()?;
            use std::io::Write;
            s.write_all(b"GET /state HTTP/1.1\r\n").ok()?;
            Some(s)
        })
        .collect();
    std::thread::sleep(Duration::from_millis(500));
    let during = threads();
    eprintln!("threads: {before} before, {during} with 300 half-open connections");
    assert!(during <= before + 70, "{before} → {during} threads");
    // Even with every slot held, the page answers: a newcomer evicts the oldest slow head.
    let state = raw_http(
        port,
        &format!("GET /state HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nConnection: close\r\n\r\n"),
    );
    assert!(state.starts_with("HTTP/1.1 200"), "{state}");
    // Past the header timeout (5 s) the slots are free again and the page answers.
    std::thread::sleep(Duration::from_secs(6));
    let state = raw_http(
        port,
        &format!("GET /state HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nConnection: close\r\n\r\n"),
    );
    assert!(state.starts_with("HTTP/1.1 200"), "{state}");
    drop(flood);
    // The servers behind the guards listen on no TCP port: the process listens on the three
    // public ports only (the backends used to be loopback ports any local process could find
    // with `ss` and reach around the guard) ...
    let public = [port, viewer_port, grpc_port];
    let mut tcp: Vec<u16> = listening_sockets(live.0.id())
        .into_iter()
        .map(|(_, p)| p)
        .collect();
    tcp.sort_unstable();
    let mut expected = public.to_vec();
    expected.sort_unstable();
    assert_eq!(tcp, expected, "TCP ports beyond the public three");
    // ... and on three Unix sockets in one folder of its own that no other user may enter.
    let sockets = listening_unix_sockets(live.0.id());
    assert_eq!(sockets.len(), 3, "{sockets:?}");
    let folder = sockets[0].parent().unwrap().to_path_buf();
    assert!(sockets.iter().all(|s| s.parent() == Some(folder.as_path())));
    use std::os::unix::fs::MetadataExt;
    let meta = std::fs::metadata(&folder).unwrap();
    assert_eq!(meta.mode() & 0o777, 0o700, "{folder:?}");
    // Even this user's processes, reaching a socket without the guard, get neither the sim's
    // state nor the viewer's files: those servers answer only what their guard stamped.
    for socket in &sockets {
        for path in ["/state", "/index.html"] {
            let mut s = std::os::unix::net::UnixStream::connect(socket).unwrap();
            s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
            use std::io::{Read, Write};
            let _ = s.write_all(
                format!("GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n")
                    .as_bytes(),
            );
            let mut out = Vec::new();
            let _ = s.read_to_end(&mut out);
            let direct = String::from_utf8_lossy(&out);
            assert!(
                !direct.contains("global_step")
                    && !direct
                        .to_ascii_lowercase()
                        .contains("content-type: text/html"),
                "{socket:?} served {path} around the guard: {}",
                &direct[..direct.len().min(300)]
            );
        }
    }
    // Through its public port the viewer is served whole.
    let page = raw_http(
        viewer_port,
        &format!(
            "GET /index.html HTTP/1.1\r\nHost: 127.0.0.1:{viewer_port}\r\nConnection: close\r\n\r\n"
        ),
    );
    assert!(
        page.starts_with("HTTP/1.1 200"),
        "{}",
        &page[..page.len().min(300)]
    );
    assert!(
        page.to_ascii_lowercase()
            .contains("content-type: text/html")
    );
    // A flood of step commands: the queue is bounded (refused with a reason past it), memory
    // stays flat, and pause stops the steps still queued.
    let rss_mb = || {
        let status = std::fs::read_to_string(format!("/proc/{}/status", live.0.id())).unwrap();
        let kb: f64 = status
            .lines()
            .find_map(|l| l.strip_prefix("VmRSS:"))
            .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
            .unwrap();
        kb / 1024.0
    };
    let rss_before = rss_mb();
    for _ in 0..1_000 {
        let reply = post(port, r#"{"command":"step","count":1000}"#);
        assert!(reply.starts_with("HTTP/1.1 200"), "{reply}");
    }
    let rss_after = rss_mb();
    eprintln!("1,000 × step 1000: RSS {rss_before:.0} → {rss_after:.0} MB");
    assert!(
        rss_after - rss_before < 50.0,
        "{rss_before} → {rss_after} MB"
    );
    let paused = post(port, r#"{"command":"pause"}"#);
    assert!(paused.starts_with("HTTP/1.1 200"), "{paused}");
    std::thread::sleep(Duration::from_millis(300));
    let step = |s: &str| -> u64 {
        let body = &s[s.find("\r\n\r\n").unwrap() + 4..];
        let v: Value = serde_json::from_str(body.trim()).unwrap();
        v["global_step"].as_u64().unwrap()
    };
    let get_state = || {
        raw_http(
            port,
            &format!("GET /state HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nConnection: close\r\n\r\n"),
        )
    };
    let at = step(&get_state());
    // The million steps asked for were not all queued: at most 10,000 wait.
    assert!(at < 20_000, "{at} steps");
    std::thread::sleep(Duration::from_millis(500));
    assert_eq!(
        step(&get_state()),
        at,
        "paused: the queued steps were dropped"
    );
    let quit = post(port, r#"{"command":"quit"}"#);
    assert!(quit.starts_with("HTTP/1.1 200"), "{quit}");
    let deadline = Instant::now() + WAIT;
    while live.0.try_wait().unwrap().is_none() {
        assert!(Instant::now() < deadline, "Quit ended the session");
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// The web viewer's newest `step` on screen: the end of the `step` timeline in its active
/// recording, read from its Viewer Control state (`window._handle.viewer_state()`, protobuf).
async fn viewer_newest_step(client: &Client) -> Option<i64> {
    use prost::Message;
    use re_protos::viewer_control::v1alpha1::GetStateResponse;
    let bytes = client
        .execute(
            "return window._handle ? Array.from(window._handle.viewer_state()) : null;",
            vec![],
        )
        .await
        .ok()?;
    let bytes: Vec<u8> = serde_json::from_value(bytes).ok()?;
    let state = GetStateResponse::decode(bytes.as_slice()).ok()?;
    state
        .recordings
        .iter()
        .filter(|r| r.store_id.starts_with("Recording:"))
        .flat_map(|r| &r.timelines)
        .filter(|t| t.timeline.as_ref().is_some_and(|t| t.name == "step"))
        .filter_map(|t| t.time_range.map(|r| r.end))
        .max()
}

/// The sim's `global_step`, from the control port's `GET /state`.
fn sim_global_step(port: u16) -> i64 {
    let answer = raw_http(
        port,
        &format!("GET /state HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nConnection: close\r\n\r\n"),
    );
    let body = answer.split_once("\r\n\r\n").map_or("", |(_, b)| b);
    let state: Value = serde_json::from_str(body).unwrap_or_else(|e| panic!("{e}: {answer}"));
    state["global_step"].as_i64().unwrap()
}

/// How far behind the sim the web viewer in headless Chromium runs, over `secs` seconds of a
/// two-model session at 1×: (seconds since the viewer opened, sim step, viewer's newest step).
fn web_viewer_lag(extra: &[&str], secs: u64) -> Vec<(f64, i64, i64)> {
    let mut args = vec!["--compare", "checkpoints/baseline", "--condition", "severe"];
    args.extend_from_slice(extra);
    let os: Vec<_> = args.iter().map(std::ffi::OsStr::new).collect();
    let (_live, [port, ..]) = live_web(&os, Stdio::null());
    let (_driver, rt, client) = control_page(port);
    rt.block_on(async move {
        let s = state(&client).await;
        let url = s["session"]["viewer_url"].as_str().unwrap().to_string();
        client.new_window(true).await.unwrap();
        let handles = client.windows().await.unwrap();
        client.switch_to_window(handles[1].clone()).await.unwrap();
        client.goto(&url).await.unwrap();
        let t0 = Instant::now();
        let mut samples = Vec::new();
        while t0.elapsed() < Duration::from_secs(secs) {
            tokio::time::sleep(Duration::from_secs(5)).await;
            let shown = viewer_newest_step(&client).await;
            let sim = sim_global_step(port);
            let t = t0.elapsed().as_secs_f64();
            eprintln!("{t:6.1} s: sim step {sim}, viewer's newest step {shown:?}");
            samples.push((t, sim, shown.unwrap_or(-1)));
        }
        client.close().await.unwrap();
        samples
    })
}

/// Prints how far the web viewer falls behind the stream (docs/web.md's figure).
#[test]
#[ignore]
fn web_viewer_latency() {
    let secs = std::env::var("LAG_SECS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(90);
    let extra = std::env::var("LAG_ARGS").unwrap_or_default();
    let extra: Vec<&str> = extra.split_whitespace().collect();
    let samples = web_viewer_lag(&extra, secs);
    let last = samples.last().unwrap();
    eprintln!("after {:.0} s: {} steps behind", last.0, last.1 - last.2);
}

/// Sends Pause once the server behind the control port's guard is up (the guard answers 502
/// until then).
fn pause_when_up(port: u16) {
    let deadline = Instant::now() + WAIT;
    loop {
        let answer = post(port, r#"{"command": "pause"}"#);
        if !answer.starts_with("HTTP/1.1 502") {
            assert!(answer.starts_with("HTTP/1.1 200"), "{answer}");
            return;
        }
        assert!(
            Instant::now() < deadline,
            "the control server never came up"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// Layout changes (here the attribution view, on and off) leave no thread behind: each distinct
/// layout is built once (issue 49: 1,000 toggles had grown the process from 24 to 6,030
/// threads).
#[test]
fn toggling_views_leaves_no_threads_behind() {
    let (mut live, [port, _, _]) = live_web(&[std::ffi::OsStr::new("--paused")], Stdio::piped());
    let pid = live.0.id();
    let threads = || {
        std::fs::read_dir(format!("/proc/{pid}/task"))
            .unwrap()
            .count()
    };
    let toggle = |on: bool| {
        let answer = post(
            port,
            &format!(r#"{{"command": "attribution", "on": {on}}}"#),
        );
        assert!(answer.starts_with("HTTP/1.1 200"), "{answer}");
    };
    pause_when_up(port);
    // Both layouts built once, then counted.
    toggle(true);
    toggle(false);
    std::thread::sleep(Duration::from_millis(500));
    let before = threads();
    for i in 0..100 {
        toggle(i % 2 == 0);
    }
    std::thread::sleep(Duration::from_millis(500));
    let after = threads();
    eprintln!("threads {before} → {after} after 100 toggles");
    assert!(
        after <= before + 4,
        "threads {before} → {after} after 100 toggles"
    );
    let _ = post(port, r#"{"command": "quit"}"#);
    let (status, _) = wait_exit(&mut live, "quit");
    assert!(status.success());
}

/// Commands are JSON by media type (not by prefix), from this server's own page when a browser
/// names one, with exactly their fields; Host names are case-insensitive (issue 49 #10).
#[test]
fn commands_are_checked_by_type_origin_and_fields() {
    let (mut live, [port, _, _]) = live_web(&[std::ffi::OsStr::new("--paused")], Stdio::piped());
    let send = |headers: &str, body: &str| {
        raw_http(
            port,
            &format!(
                "POST /command HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n{headers}\
                 Content-Length: {}\r\nConnection: close\r\n\r\n{body}",
                body.len()
            ),
        )
    };
    let pause = r#"{"command": "pause"}"#;
    let json = "Content-Type: application/json\r\n";
    pause_when_up(port);
    let ok = send(json, pause);
    assert!(ok.starts_with("HTTP/1.1 200"), "{ok}");
    let ok = send("Content-Type: application/json; charset=utf-8\r\n", pause);
    assert!(ok.starts_with("HTTP/1.1 200"), "{ok}");
    let own = format!("{json}Origin: http://127.0.0.1:{port}\r\n");
    let ok = send(&own, pause);
    assert!(ok.starts_with("HTTP/1.1 200"), "{ok}");
    for (headers, body, says) in [
        (
            "Content-Type: application/jsonx\r\n".to_string(),
            pause,
            "commands must be sent as application/json",
        ),
        (
            format!("{json}Origin: http://evil.example\r\n"),
            pause,
            "not from 'http://evil.example'",
        ),
        (
            json.to_string(),
            r#"{"command": "pause", "now": true}"#,
            "unknown field `now`",
        ),
    ] {
        let answer = send(&headers, body);
        assert!(
            answer.starts_with("HTTP/1.1 4") && answer.contains(says),
            "{headers}{body}: {answer}"
        );
    }
    let state = raw_http(
        port,
        &format!("GET /state HTTP/1.1\r\nHost: LOCALHOST:{port}\r\nConnection: close\r\n\r\n"),
    );
    assert!(state.starts_with("HTTP/1.1 200"), "{state}");
    let _ = post(port, r#"{"command": "quit"}"#);
    let (status, _) = wait_exit(&mut live, "quit");
    assert!(status.success());
}

/// `live --web --search DIR`: the page gets the folder's findings, and "Next failure"'s three
/// commands (the finding's scenario, its seed, a reset) replay a held-out episode the search
/// saw fail — it fails here too, live, step for step the same world. The button itself, in
/// Chromium, steps to the same finding.
#[test]
fn the_page_steps_through_a_search_folders_failures() {
    let dir = tempfile::tempdir().unwrap();
    let found = dir.path().join("search");
    let o = Command::new(env!("CARGO_BIN_EXE_gaitscope"))
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .args([
            "search",
            "--checkpoint",
            "checkpoints/encoder-lstm",
            "--budget",
            "3",
        ])
        .args([
            "--evaluations",
            "6",
            "--episodes",
            "4",
            "--held-out",
            "8",
            "--top",
            "1",
        ])
        .args([
            "--shrink-evaluations",
            "0",
            "--max-steps",
            "150",
            "--latest-onset",
            "10",
        ])
        .arg("--out")
        .arg(&found)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let args = [
        "--paused".as_ref(),
        "--max-steps".as_ref(),
        "150".as_ref(),
        "--search".as_ref(),
        found.as_os_str(),
    ];
    let (mut live, [port, _, _]) = live_web(&args, Stdio::piped());
    let (_driver, rt, client) = control_page(port);
    let found = found.clone();
    rt.block_on(async move {
        client
            .wait()
            .at_most(WAIT)
            .for_element(Locator::Id("fail-hip_1"))
            .await
            .unwrap();
        let s = state(&client).await;
        let findings = s["session"]["findings"].as_array().unwrap().clone();
        // Deterministic: the same seeds always give this search a failing held-out episode.
        let first = findings
            .iter()
            .find(|f| !f["failing_seeds"].as_array().unwrap().is_empty())
            .expect("a finding with a failing held-out episode");
        let seed = first["failing_seeds"][0].as_u64().unwrap();
        click(&client, "next-failure").await;
        let s = wait_state(&client, "the finding's episode", |s| {
            s["episode_seed"].as_u64() == Some(seed) && lane_step(s) == 0
        })
        .await;
        assert_eq!(
            s["scenario"],
            format!("search-{}", first["name"].as_str().unwrap())
        );
        let shown = text_of(&client, "finding").await;
        assert!(shown.contains(&format!("seed {seed}")), "{shown}");
        // Run it out, exactly as many steps as the search's held-out run took (one more would
        // start the next episode): it ends there, and fails, as it did in the search.
        let log = std::fs::read_to_string(found.join("candidates.jsonl")).unwrap();
        let steps = log
            .lines()
            .map(|l| serde_json::from_str::<Value>(l).unwrap())
            .filter(|c| c["phase"] == "held-out")
            .flat_map(|c| c["outcomes"][0].as_array().unwrap().clone())
            .find(|e| e["seed"].as_u64() == Some(seed))
            .and_then(|e| e["steps"].as_u64())
            .unwrap();
        client
            .execute(
                "gaitscopeSend({command: 'step', count: arguments[0]});",
                vec![json!(steps)],
            )
            .await
            .unwrap();
        let s = wait_state(&client, "the episode's end", |s| {
            s["lanes"][0]["done"] == true
        })
        .await;
        assert_eq!(lane_step(&s), steps, "{}", s["lanes"][0]);
        assert_eq!(s["lanes"][0]["success"], false, "{}", s["lanes"][0]);
    });
    let _ = post(port, r#"{"command": "quit"}"#);
    let _ = wait_exit(&mut live, "quit");
}

/// Issue 49: `live --web --save` on a full disk (here: a file-size limit) renamed its cut-off
/// file into place — the file sink's failed flush looked like a closed viewer's. Now only a
/// file that reads back whole takes the name asked for; a cut-off one stays `.partial`, said so.
#[test]
fn live_save_on_a_full_disk_leaves_nothing_under_the_name() {
    let dir = tempfile::tempdir().unwrap();
    let save = dir.path().join("session.rrd");
    let [port, viewer_port, grpc_port] = free_ports::<3>();
    let out = Command::new("bash")
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .arg("-c")
        // 200 KB at most per file; SIGXFSZ ignored so the write fails with EFBIG instead.
        .arg(format!(
            "trap '' XFSZ; ulimit -f 200; exec {} live --web --checkpoint checkpoints/encoder-lstm \
             --exit-after 8 --speed 8 --port {port} --viewer-port {viewer_port} --grpc-port {grpc_port} \
             --save {}",
            env!("CARGO_BIN_EXE_gaitscope"),
            save.display()
        ))
        .env_remove("DISPLAY")
        .env_remove("WAYLAND_DISPLAY")
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{stderr}");
    assert!(
        stderr.contains("could not be written completely"),
        "{stderr}"
    );
    assert!(stderr.contains("session.rrd.partial"), "{stderr}");
    assert!(!stderr.contains("session saved to"), "{stderr}");
    assert!(!save.exists(), "a cut-off file took the name");
    assert!(dir.path().join("session.rrd.partial").exists());
}

/// A native viewer's way in: HTTP/2 gRPC (`ReadMessages`) on the public gRPC port, relayed by
/// its guard to the message proxy on its Unix socket, gets the session's recording — store info
/// (the recording's and its blueprint's) first, then data (what `rerun --connect
/// rerun+http://127.0.0.1:PORT/proxy` reads).
#[test]
fn a_native_grpc_client_reads_the_stream_through_the_guard() {
    use re_protos::log_msg::v1alpha1::log_msg::Msg;
    use re_protos::sdk_comms::v1alpha1::ReadMessagesRequest;
    use re_protos::sdk_comms::v1alpha1::message_proxy_service_client::MessageProxyServiceClient;
    let (_live, [port, _, grpc_port]) =
        live_web(&[std::ffi::OsStr::new("--paused")], Stdio::null());
    pause_when_up(port);
    let rt = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .unwrap();
    let kinds = rt.block_on(async {
        let channel =
            tonic::transport::Endpoint::from_shared(format!("http://127.0.0.1:{grpc_port}"))
                .unwrap()
                .connect()
                .await
                .expect("an HTTP/2 connection through the guard");
        let mut client =
            MessageProxyServiceClient::new(channel).max_decoding_message_size(usize::MAX);
        let mut stream = client
            .read_messages(ReadMessagesRequest {})
            .await
            .expect("ReadMessages through the guard")
            .into_inner();
        let mut kinds = Vec::new();
        while !kinds.contains(&"data") {
            let next = tokio::time::timeout(WAIT, stream.message()).await;
            let Ok(Ok(Some(response))) = next else {
                panic!("the stream ended or stalled after {kinds:?}: {next:?}");
            };
            let kind = match response.log_msg.and_then(|m| m.msg) {
                Some(Msg::SetStoreInfo(_)) => "store info",
                Some(Msg::ArrowMsg(_)) => "data",
                Some(Msg::BlueprintActivationCommand(_)) => "blueprint activation",
                None => "none",
            };
            kinds.push(kind);
        }
        kinds
    });
    assert_eq!(kinds[0], "store info", "{kinds:?}");
    assert!(kinds.contains(&"data"), "{kinds:?}");
}
