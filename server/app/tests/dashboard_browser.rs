//! The browser console, proven with a real browser: `libero-agent serve` runs a T14 episode that a scripted agent
//! drives over MCP (official Python SDK) while Debian's chromium, driven headless by playwright-core
//! (`tests/dashboard/browser_check.cjs`), watches the live page, then reviews the finished episode and opens the
//! tasks page. Screenshots land in `target/test-artifacts/dashboard/`. Also without a browser: range requests on
//! the private video, no private file reachable by path tricks, nothing of the live view in the agent's
//! workspace, and the operator guard beyond loopback (agent tokens never open the dashboard).
//!
//! Needs `python3 scripts/setup.py --test` (chromium, the MCP venv, playwright-core); fails saying so otherwise.
use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::Duration;

use libero_testkit::{cache_dir as cache, repo_root};
use serde_json::{Value, json};

mod common;
use common::http;

fn bin() -> &'static str {
    env!("CARGO_BIN_EXE_libero-agent")
}

const SETUP_HINT: &str = "run `python3 scripts/setup.py --test` (as root for the Debian packages)";

/// Every prerequisite of the browser test, or a clear failure naming how to get it.
fn browser_prerequisites() -> (PathBuf, PathBuf, PathBuf) {
    let chromium = std::env::var_os("LIBERO_AGENT_CHROMIUM").map(PathBuf::from).unwrap_or_else(|| "/usr/bin/chromium".into());
    assert!(chromium.is_file(), "{} missing: the dashboard test needs Debian's chromium; {SETUP_HINT}", chromium.display());
    let node_modules = cache().join("node/node_modules");
    assert!(
        node_modules.join("playwright-core/package.json").is_file(),
        "playwright-core missing under {}; {SETUP_HINT}",
        node_modules.display()
    );
    let python = cache().join("pyenv/bin/python");
    assert!(python.is_file(), "{} missing; {SETUP_HINT}", python.display());
    let node = Command::new("node").arg("--version").output();
    assert!(node.is_ok_and(|o| o.status.success()), "node missing (Debian: apt-get install nodejs); {SETUP_HINT}");
    (chromium, node_modules, python)
}

/// A running `libero-agent serve`; killed on drop. `stderr` is captured for the operator-token test.
struct Server {
    child: Child,
    url: String,
    port: u16,
    /// The operator token `serve` keeps in `<data>/operator_token`.
    token: String,
}

impl Server {
    fn start(data: &Path, addr: &str, extra: &[&str]) -> (Self, Option<std::process::ChildStderr>) {
        let mut child = Command::new(bin())
            .args(["serve", "--addr", addr, "--data"])
            .arg(data)
            .args(extra)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("start libero-agent serve");
        let v = common::first_json_line(&mut child);
        let url = v["url"].as_str().expect("url").to_owned();
        let port = url.rsplit(':').next().and_then(|p| p.parse().ok()).expect("port");
        let stderr = child.stderr.take();
        let token = std::fs::read_to_string(data.join("operator_token")).expect("serve keeps its operator token").trim().to_owned();
        (Self { child, url, port, token }, stderr)
    }

    /// `Authorization: Bearer <operator token>`.
    fn op(&self) -> String {
        format!("Bearer {}", self.token)
    }

    /// Loopback URL of the server (it may listen on 0.0.0.0).
    fn local(&self) -> String {
        format!("http://127.0.0.1:{}", self.port)
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn prepare(base: &str, extra_headers: &[(&str, &str)], workspace: &Path) -> Value {
    let body = json!({"task": "T14", "level": 3, "harness": "scripted", "model": "sinusoid", "batch": "dash-test",
        "workspace": workspace});
    let mut headers = vec![("Content-Type", "application/json")];
    headers.extend_from_slice(extra_headers);
    let (status, _, body) = http("POST", &format!("{base}/api/episodes"), &headers, body.to_string().as_bytes());
    assert_eq!(status, 201, "prepare: {}", String::from_utf8_lossy(&body));
    serde_json::from_slice(&body).expect("prepare JSON")
}

fn agent_token(prepared: &Value) -> String {
    prepared["mcp_headers"]["Authorization"].as_str().expect("auth").trim_start_matches("Bearer ").to_owned()
}

fn artifacts_dir() -> PathBuf {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("../test-artifacts/dashboard");
    std::fs::create_dir_all(&dir).expect("artifacts dir");
    dir
}

fn files_under(dir: &Path) -> Vec<String> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).into_iter().flatten().flatten() {
            let p = e.path();
            out.push(p.strip_prefix(dir).unwrap().to_string_lossy().into_owned());
            if p.is_dir() {
                stack.push(p);
            }
        }
    }
    out
}

#[test]
fn chromium_watches_a_live_t14_episode_then_reviews_it() {
    let (chromium, node_modules, python) = browser_prerequisites();
    let tmp = tempfile::tempdir().unwrap();
    let (server, _stderr) = Server::start(&tmp.path().join("data"), "127.0.0.1:0", &[]);
    let ws = tmp.path().join("ws");
    let op = server.op();
    let prepared = prepare(&server.url, &[("Authorization", &op)], &ws);
    let episode = prepared["episode_id"].as_str().unwrap().to_owned();
    let artifacts = artifacts_dir();

    // The browser opens the live page first; the agent starts once it is connected.
    let mut browser = Command::new("node")
        .arg(repo_root().join("tests/dashboard/browser_check.cjs"))
        .args([&server.url, &episode])
        .arg(&artifacts)
        .arg(first_unimplemented_task())
        .env("NODE_PATH", &node_modules)
        .env("LIBERO_AGENT_CHROMIUM", &chromium)
        .env("LIBERO_OPERATOR_TOKEN", &server.token)
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .expect("start node");
    let (tx, rx) = mpsc::channel::<Value>();
    let stdout = browser.stdout.take().expect("node stdout");
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines().map_while(Result::ok) {
            match serde_json::from_str(&line) {
                Ok(v) => {
                    let _ = tx.send(v);
                }
                Err(_) => eprintln!("node: {line}"),
            }
        }
    });
    let first = rx.recv_timeout(Duration::from_secs(120)).expect("the browser script reports");
    assert_eq!(first["event"], "live-ready", "browser before the agent started: {first}");

    let agent = Command::new(&python)
        .arg(repo_root().join("tests/dashboard/drive_episode.py"))
        .args(["--url", prepared["mcp_url"].as_str().unwrap(), "--token", &agent_token(&prepared)])
        .args(["--calls", "4", "--actions", "20", "--pause-s", "1.5"])
        .output()
        .expect("run the scripted agent");
    let agent_out = String::from_utf8_lossy(&agent.stdout);
    assert!(agent.status.success(), "scripted agent failed:\n{agent_out}\n{}", String::from_utf8_lossy(&agent.stderr));

    let report = rx.recv_timeout(Duration::from_secs(540)).expect("the browser script finishes");
    let status = browser.wait().expect("node exit");
    assert!(status.success() && report["ok"] == true, "browser checks failed: {report}");
    eprintln!("browser report: {report}");
    for shot in ["live-running", "live-finished", "home", "review", "review-deeplink", "tasks", "tasks-pool"] {
        assert!(artifacts.join(format!("{shot}.png")).is_file(), "screenshot {shot}.png");
    }

    // The private video answers range requests (the browser's seeking relies on them).
    let video = format!("{}/episodes/{episode}/video.mp4", server.url);
    let (status, head, body) = http("GET", &video, &[("Range", "bytes=0-99"), ("Authorization", &op)], b"");
    assert_eq!((status, body.len()), (206, 100), "{head}");
    assert!(head.to_ascii_lowercase().contains("content-range: bytes 0-99/"), "{head}");
    // Telemetry was recorded per control step: 80 accepted actions after step 0.
    let (status, _, body) = http("GET", &format!("{}/api/episodes/{episode}/review", server.url), &[("Authorization", &op)], b"");
    assert_eq!(status, 200);
    let review: Value = serde_json::from_slice(&body).unwrap();
    let telemetry = review["telemetry"].as_array().unwrap();
    assert_eq!(telemetry.len(), 81, "control steps 0..=80");
    assert_eq!(telemetry[0]["video_frame"], 9, "control step 0 is the last of 10 settle frames");
    assert_eq!(review["calls"].as_array().unwrap().len(), 7, "start, 4 sequences, 1 rejected, finish");
    // No path tricks into the run directory.
    for bad in ["..%2Fresult.json", "obs_000001/..%2F..%2Fresult.json", "%2Fetc%2Fpasswd"] {
        let (status, _, _) = http("GET", &format!("{}/episodes/{episode}/observations/{bad}", server.url), &[("Authorization", &op)], b"");
        assert_eq!(status, 404, "{bad}");
    }
    let (status, _, _) = http("GET", &format!("{}/episodes/{episode}/observations/obs_000001/head/rgb.png", server.url), &[("Authorization", &op)], b"");
    assert_eq!(status, 200);
    // The agent's workspace holds nothing of the live view or the private records.
    let files = files_under(&ws);
    for private in ["telemetry", "continuous_video", "private_stage_events", "result.json", "actions.jsonl"] {
        assert!(!files.iter().any(|f| f.contains(private)), "{private} leaked into the workspace: {files:?}");
    }
    // Another site's page in the operator's browser can neither read the live streams nor prepare episodes.
    let upgrade = [("Connection", "Upgrade"), ("Upgrade", "websocket"), ("Sec-WebSocket-Version", "13"),
        ("Sec-WebSocket-Key", "dGhlIHNhbXBsZSBub25jZQ==")];
    let local_origin = format!("http://127.0.0.1:{}", server.port);
    let (status, _, _) = http("GET", &format!("{}/ws/episodes", server.url), &[&upgrade[..], &[("Origin", local_origin.as_str()), ("Authorization", op.as_str())]].concat(), b"");
    assert_eq!(status, 101, "the dashboard's own pages connect");
    let (status, _, _) = http("GET", &format!("{}/ws/episodes", server.url), &[&upgrade[..], &[("Origin", "http://evil.example")]].concat(), b"");
    assert_eq!(status, 403, "cross-site WebSocket refused");
    let (status, _, _) = http("POST", &format!("{}/api/episodes", server.url),
        &[("Origin", "http://evil.example"), ("Content-Type", "text/plain")], br#"{"task":"T14"}"#);
    assert_eq!(status, 403, "cross-site prepare refused");
    // Pages never show the agent's token.
    let token = agent_token(&prepared);
    for page in ["/", &format!("/episodes/{episode}/review"), &format!("/api/episodes/{episode}/review"), "/api/episodes"] {
        let (status, _, body) = http("GET", &format!("{}{page}", server.url), &[("Authorization", &op)], b"");
        assert_eq!(status, 200, "{page}");
        assert!(!String::from_utf8_lossy(&body).contains(&token), "{page} shows the agent token");
    }
}

/// Issue 8's browser part: chromium teleoperates T14 from the tasks page's link with the robosuite keys, sees frames
/// and the latency label, saves the demonstration; the bundle then passes `demo validate`, the Demos page lists,
/// plays and exports it, and only same-site requests may delete it.
#[test]
fn chromium_teleoperates_t14_and_saves_a_bundle_that_validates() {
    let (chromium, node_modules, _python) = browser_prerequisites();
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let (server, _stderr) = Server::start(&data, "127.0.0.1:0", &[]);
    let artifacts = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("../test-artifacts/teleop");
    std::fs::create_dir_all(&artifacts).expect("artifacts dir");
    let report = browser_script("teleop_check.cjs", &[server.url.as_ref(), "T14".as_ref(), artifacts.as_os_str()], &server, &chromium, &node_modules);
    eprintln!("teleop report: {report}");
    for shot in ["teleop-driving", "teleop-saved", "demos"] {
        assert!(artifacts.join(format!("{shot}.png")).is_file(), "screenshot {shot}.png");
    }
    let key = report["bundle"].as_str().expect("bundle key");
    let dir = data.join("demos").join(key);
    let validate = Command::new(bin()).args(["demo", "validate"]).arg(&dir).output().expect("demo validate");
    assert!(validate.status.success(), "demo validate {}: {}", dir.display(), String::from_utf8_lossy(&validate.stderr));
    let manifest: Value = serde_json::from_slice(&std::fs::read(dir.join("manifest.json")).unwrap()).unwrap();
    assert_eq!(manifest["source"]["source_type"], "human_teleop");
    assert!(manifest["transition_count"].as_u64().unwrap() >= 20, "at least a second of driving: {manifest}");
    assert_eq!(manifest["verification"]["verified"], report["verified"], "the page shows the manifest's verdict");
    // Deleting is operator-only and same-site: another site's page cannot, the dashboard can.
    let delete = format!("{}/api/demos/{key}/delete", server.url);
    let (status, _, _) = http("POST", &delete, &[("Origin", "http://evil.example")], b"");
    assert_eq!(status, 403, "cross-site delete refused");
    assert!(dir.is_dir());
    let op = server.op();
    let (status, _, _) = http("POST", &format!("{}/api/demos/T14/..%2F..%2Fruns/delete", server.url), &[("Authorization", &op)], b"");
    assert_eq!(status, 404, "no path tricks");
    let (status, _, _) = http("POST", &delete, &[], b"");
    assert_eq!(status, 401, "deleting needs the operator credential");
    let (status, _, body) = http("POST", &delete, &[("Authorization", &op)], b"");
    assert_eq!(status, 200, "{}", String::from_utf8_lossy(&body));
    assert!(!dir.exists(), "deleted");
}

/// Runs `tests/dashboard/<script>` in node with an operator session for `server`; its last JSON line, which
/// must say `ok: true`.
fn browser_script(script: &str, args: &[&std::ffi::OsStr], server: &Server, chromium: &Path, node_modules: &Path) -> Value {
    let out = Command::new("node")
        .arg(repo_root().join("tests/dashboard").join(script))
        .args(args)
        .env("NODE_PATH", node_modules)
        .env("LIBERO_AGENT_CHROMIUM", chromium)
        .env("LIBERO_OPERATOR_TOKEN", &server.token)
        .stderr(Stdio::inherit())
        .output()
        .expect("run node");
    let stdout = String::from_utf8_lossy(&out.stdout);
    let report: Value = stdout.lines().rev().find_map(|l| serde_json::from_str(l).ok()).unwrap_or(Value::Null);
    assert!(out.status.success() && report["ok"] == true, "{script} checks failed: {stdout}");
    report
}

/// Issue 19's newcomer: a fresh server's home page says what to do next and prepares an episode whose MCP
/// configuration it shows, in Chromium with screenshots.
#[test]
fn a_fresh_console_guides_a_newcomer_and_prepares_an_episode_to_connect() {
    let (chromium, node_modules, _python) = browser_prerequisites();
    let tmp = tempfile::tempdir().unwrap();
    let (server, _stderr) = Server::start(&tmp.path().join("data"), "127.0.0.1:0", &[]);
    let artifacts = artifacts_dir();
    let report = browser_script("onboarding_check.cjs", &[server.url.as_ref(), artifacts.as_os_str()], &server, &chromium, &node_modules);
    for shot in ["onboarding-empty", "onboarding-prepared"] {
        assert!(artifacts.join(format!("{shot}.png")).is_file(), "screenshot {shot}.png");
    }
    let (status, _, body) = http("GET", &format!("{}/api/episodes", server.url), &[("Authorization", &server.op())], b"");
    assert_eq!(status, 200);
    let list: Value = serde_json::from_slice(&body).unwrap();
    let id = report["mcp_url"].as_str().unwrap().rsplit('/').next().unwrap().to_owned();
    assert!(list["episodes"].as_array().unwrap().iter().any(|e| e["id"] == id.as_str()), "the page's episode is in the store: {list}");
}

/// Issue 17: on loopback too, every page, API and stream needs the operator credential; the login link `serve`
/// prints opens a browser session (a random id, not the token); a foreign `Host` is refused before any handler;
/// a second server on the same data directory refuses to start.
#[test]
fn on_loopback_every_route_needs_the_operator_credential_and_the_login_link_opens_a_session() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("gen");
    let (server, stderr) = Server::start(&data, "127.0.0.1:0", &[]);
    let (tx, rx) = mpsc::channel();
    let mut stderr = BufReader::new(stderr.expect("stderr"));
    std::thread::spawn(move || {
        let mut line = String::new();
        while stderr.read_line(&mut line).is_ok_and(|n| n > 0) {
            if line.contains("?token=") {
                let _ = tx.send(line.trim().to_owned());
            }
            line.clear();
        }
    });
    let link = rx.recv_timeout(Duration::from_secs(20)).expect("the login link on stderr");
    assert!(link.starts_with(&format!("{}/?token=", server.url)) && !link.contains(&server.token), "the link holds a one-time code, not the token: {link}");
    assert!(server.token.len() >= 32);
    use std::os::unix::fs::PermissionsExt;
    let mode = std::fs::metadata(data.join("operator_token")).unwrap().permissions().mode() & 0o777;
    assert_eq!(mode, 0o600, "the token file is private");
    let base = server.url.clone();
    let prepared = prepare(&base, &[("Authorization", &server.op())], &tmp.path().join("ws"));
    let episode = prepared["episode_id"].as_str().unwrap().to_owned();
    let agent = format!("Bearer {}", agent_token(&prepared));
    let pages = ["/", "/tasks", "/results", "/demos", &format!("/episodes/{episode}"), &format!("/episodes/{episode}/review"), "/teleop/T14", "/teleop/libero_90/35"];
    let apis = ["/api/episodes", &format!("/api/episodes/{episode}"), &format!("/api/episodes/{episode}/review"), "/api/results", "/api/tasks",
        "/api/demos", &format!("/episodes/{episode}/video.mp4"), &format!("/episodes/{episode}/observations/obs_000000/observation.json"),
        "/tasks/T14/thumbnail.png", "/tasks/libero_90/35/thumbnail.png", "/ws/episodes", &format!("/ws/episodes/{episode}"),
        &format!("/api/episodes/{episode}/stages"), "/results/report/csv",
        "/results/logs/b/w1_t14_level3", "/results/logs/b/w1_t14_level3/stdout"];
    for path in pages.iter().chain(apis.iter()) {
        for auth in [None, Some(agent.as_str())] {
            let headers: Vec<(&str, &str)> = auth.map(|a| vec![("Authorization", a)]).unwrap_or_default();
            let (status, head, _) = http("GET", &format!("{base}{path}"), &headers, b"");
            let refused = status == 401 || (status == 303 && head.to_ascii_lowercase().contains("location: /login"));
            assert!(refused, "{path} with {auth:?} answered {status}: {head}");
        }
    }
    for (path, body) in [("/api/episodes", r#"{"task":"T14"}"#.to_owned()), (&format!("/api/episodes/{episode}/abort"), r#"{"reason":"x"}"#.to_owned()),
        ("/api/teleop", r#"{"task":"T14"}"#.to_owned()),
        (&format!("/api/episodes/{episode}/stages"), r#"{"stage_name":"x","reached":true,"succeeded":false,"annotator":"a"}"#.to_owned())] {
        let (status, _, _) = http("POST", &format!("{base}{path}"), &[("Authorization", &agent), ("Content-Type", "application/json")], body.as_bytes());
        assert_eq!(status, 401, "POST {path} with the agent token");
    }
    // The login link: a session cookie that is not the token, and a redirect without the token.
    let (status, head, _) = http("GET", &format!("{base}/tasks?token={}", server.token), &[], b"");
    assert_eq!(status, 303, "{head}");
    assert!(head.lines().any(|l| l.trim().eq_ignore_ascii_case("location: /tasks")), "{head}");
    let cookie_line = head.lines().find(|l| l.to_ascii_lowercase().starts_with("set-cookie:")).expect("a cookie");
    assert!(cookie_line.contains("HttpOnly") && cookie_line.contains("SameSite=Strict") && !cookie_line.contains(&server.token), "{cookie_line}");
    let cookie = cookie_line.split_once(':').unwrap().1.split(';').next().unwrap().trim().to_owned();
    let (status, _, body) = http("GET", &format!("{base}/"), &[("Cookie", &cookie)], b"");
    assert_eq!(status, 200);
    assert!(String::from_utf8_lossy(&body).contains(&episode), "the home page lists the episode");
    let (status, _, _) = http("GET", &format!("{base}/?token={}", agent_token(&prepared)), &[], b"");
    assert_eq!(status, 401, "the agent token is no login link");
    let forged = format!("libero_session={}", server.token);
    let (status, _, _) = http("GET", &format!("{base}/api/episodes"), &[("Cookie", &forged)], b"");
    assert_eq!(status, 401, "the token itself is no session id");
    // Host allow-list, before any handler: DNS rebinding names and foreign hosts get 421.
    let port = server.port;
    for host in ["evil.example", &format!("evil.example:{port}"), &format!("127.0.0.1.nip.io:{port}"), &format!("127.0.0.1:{}", port.wrapping_add(1))] {
        for path in ["/api/health", "/", &format!("/mcp/{episode}")] {
            let (status, _, _) = http_host("GET", &format!("{base}{path}"), host, &[("Authorization", &server.op())]);
            assert_eq!(status, 421, "Host {host} {path}");
        }
    }
    let (status, _, _) = http_host("GET", &format!("{base}/api/health"), &format!("localhost:{port}"), &[]);
    assert_eq!(status, 200, "loopback names of the bound port are allowed");
    // A second server on the same data directory refuses instead of marking this one's episodes aborted.
    let second = Command::new(bin()).args(["serve", "--addr", "127.0.0.1:0", "--data"]).arg(&data).output().expect("second serve");
    assert!(!second.status.success());
    let err = String::from_utf8_lossy(&second.stderr);
    assert!(err.contains("another libero-agent server") && err.contains(&server.child.id().to_string()), "{err}");
    let (status, _, body) = http("GET", &format!("{base}/api/episodes/{episode}"), &[("Authorization", &server.op())], b"");
    assert_eq!(status, 200);
    let row: Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(row["state"], "prepared", "the first server's episode is untouched: {row}");
    // SIGTERM: the server records its open episode as aborted and exits within seconds.
    let mut server = server;
    // SAFETY: signalling the child this test started.
    unsafe { libc::kill(server.child.id() as i32, libc::SIGTERM) };
    let asked = std::time::Instant::now();
    let status = loop {
        if let Some(status) = server.child.try_wait().unwrap() {
            break status;
        }
        assert!(asked.elapsed() < Duration::from_secs(20), "serve ignored SIGTERM for 20 s");
        std::thread::sleep(Duration::from_millis(50));
    };
    assert!(status.success(), "serve exits cleanly on SIGTERM: {status}");
    let result: Value = serde_json::from_slice(&std::fs::read(data.join("runs").join(&episode).join("result.json")).unwrap()).unwrap();
    assert_eq!(result["status"], "aborted", "{result}");
    drop(server);

    // A token file and a public host name beyond loopback.
    let token = "0123456789abcdef-operator-secret";
    let file = tmp.path().join("operator.token");
    std::fs::write(&file, format!("{token}\n")).unwrap();
    let (server, _stderr) =
        Server::start(&tmp.path().join("file"), "0.0.0.0:0", &["--operator-token-file", file.to_str().unwrap(), "--public-host", "bench.lab"]);
    assert_eq!(server.token, token);
    let base = server.local();
    let (status, _, _) = http("GET", &format!("{base}/api/health"), &[], b"");
    assert_eq!(status, 200, "health stays open");
    let (status, _, _) = http_host("GET", &format!("{base}/api/episodes"), &format!("bench.lab:{}", server.port), &[("Authorization", &server.op())]);
    assert_eq!(status, 200, "the public host name is allowed");
    let (status, _, _) =
        http("POST", &format!("{base}/login"), &[("Content-Type", "application/x-www-form-urlencoded")], format!("token={token}").as_bytes());
    assert_eq!(status, 303, "the login form opens a session too");
}

/// As [`http`] with another `Host` header (what a DNS-rebinding page's requests carry).
fn http_host(method: &str, url: &str, host: &str, headers: &[(&str, &str)]) -> (u16, String, Vec<u8>) {
    use std::io::{Read, Write};
    let rest = url.strip_prefix("http://").expect("http url");
    let (addr, path) = rest.split_at(rest.find('/').unwrap_or(rest.len()));
    let mut stream = std::net::TcpStream::connect(addr).expect("connect");
    stream.set_read_timeout(Some(Duration::from_secs(60))).unwrap();
    let mut head = format!("{method} {path} HTTP/1.1\r\nHost: {host}\r\nConnection: close\r\nContent-Length: 0\r\n");
    for (k, v) in headers {
        head.push_str(&format!("{k}: {v}\r\n"));
    }
    head.push_str("\r\n");
    stream.write_all(head.as_bytes()).unwrap();
    let mut raw = Vec::new();
    stream.read_to_end(&mut raw).unwrap();
    let text = String::from_utf8_lossy(&raw).into_owned();
    let status = text.split_whitespace().nth(1).and_then(|s| s.parse().ok()).expect("status");
    (status, text, Vec::new())
}

/// A task the catalog lists as not implemented (the tasks page must say so), from `tasks list --json`; `-` when
/// every task is implemented (the page must then mark none as not implemented).
fn first_unimplemented_task() -> String {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_libero-agent")).args(["tasks", "list", "--json"]).output().expect("tasks list");
    let tasks: Value = serde_json::from_slice(&out.stdout).expect("tasks list --json");
    tasks
        .as_array()
        .and_then(|a| a.iter().find(|t| t["implemented"] == false))
        .and_then(|t| t["id"].as_str())
        .unwrap_or("-")
        .to_owned()
}

/// Issue 48: a person annotates the stages of a real batch's long-horizon rollouts in the review page by keyboard
/// (name, r, 3, n + note, Enter, c, ]), in Chromium. The annotations land in the batch's `stage_annotations.jsonl`
/// and the store, and the report's Table 4 counts them: reached moves from the automatic 0 of 4 to the annotated
/// 1 of 4, with 2 annotated and 2 automatic stage opportunities.
#[test]
fn stages_are_annotated_by_keyboard_in_the_review_and_table_4_counts_them() {
    let (chromium, node_modules, _python) = browser_prerequisites();
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let batch = data.join("batches/lh");
    let out = Command::new(bin())
        .args(["run", "--experiment", "main_table", "--harness", "command", "--model", "reference", "--tasks", "T28", "--reps", "2"])
        .args(["--concurrency", "2", "--agent-cmd", "exec {libero_agent} agent --workspace {workspace}", "--wall-time-s", "300", "--no-sandbox"])
        .arg("--batch")
        .arg(&batch)
        .arg("--workspace-root")
        .arg(tmp.path().join("ws"))
        .output()
        .expect("run");
    assert!(out.status.success(), "run: {}", String::from_utf8_lossy(&out.stderr));
    let table4 = || {
        let out = Command::new(bin()).args(["report", "--format", "json"]).arg(&batch).output().expect("report");
        assert!(out.status.success(), "report: {}", String::from_utf8_lossy(&out.stderr));
        let v: Value = serde_json::from_slice(&out.stdout).unwrap();
        v["stage_diagnosis"][0].clone()
    };
    let before = table4();
    assert_eq!((before["annotated"].as_u64(), before["automatic"].as_u64(), before["reached"]["successes"].as_u64()), (Some(0), Some(4), Some(0)), "{before}");
    let records = std::fs::read_to_string(batch.join("rollouts.jsonl")).unwrap();
    let first: Value = serde_json::from_str(records.lines().next().unwrap()).unwrap();
    let episode = first["episode_id"].as_str().unwrap();
    let (server, _stderr) = Server::start(&data, "127.0.0.1:0", &[]);
    let artifacts = artifacts_dir();
    let report = browser_script("annotate_check.cjs", &[server.url.as_ref(), episode.as_ref(), artifacts.as_os_str()], &server, &chromium, &node_modules);
    for shot in ["annotate-start", "annotate-done", "annotate-next-episode"] {
        assert!(artifacts.join(format!("{shot}.png")).is_file(), "screenshot {shot}.png");
    }
    assert_eq!(report["stages"], 2);
    let stages = report["saved"]["stages"].as_array().unwrap();
    assert_eq!(stages[0]["annotation"]["failure_modes"], json!(["geometric_error"]), "{report}");
    assert_eq!(stages[0]["annotation"]["note"], "gripper closed 2 cm short of the handle");
    assert_eq!(stages[0]["counted"]["source"], "annotated");
    assert!(stages.iter().all(|s| s["annotation"]["annotator"] == "Ada Annotator"), "{report}");
    // The batch's file holds both (the export), and Table 4 counts them.
    let lines = std::fs::read_to_string(batch.join("stage_annotations.jsonl")).unwrap();
    assert_eq!(lines.lines().count(), 2, "{lines}");
    let after = table4();
    assert_eq!((after["annotated"].as_u64(), after["automatic"].as_u64(), after["reached"]["successes"].as_u64()), (Some(2), Some(2), Some(1)), "{after}");
    assert_eq!(after["geometric_error"], 1, "{after}");
    // Bad input changes nothing: an unknown stage, and modes on a stage that succeeded.
    let url = format!("{}/api/episodes/{episode}/stages", server.url);
    for body in [
        json!({"stage_name": "99_nope", "reached": true, "succeeded": false, "annotator": "x"}),
        json!({"stage_name": "01_Unlatch_Door", "reached": true, "succeeded": true, "failure_modes": ["other"], "annotator": "x"}),
        json!({"stage_name": "01_Unlatch_Door", "reached": true, "succeeded": false, "annotator": ""}),
    ] {
        let (status, _, _) = http("POST", &url, &[("Authorization", &server.op()), ("Content-Type", "application/json")], body.to_string().as_bytes());
        assert_eq!(status, 422, "{body}");
    }
    assert_eq!(std::fs::read_to_string(batch.join("stage_annotations.jsonl")).unwrap(), lines, "refused input wrote nothing");
}
