//! The logger of `libero-agent serve`: a line when an episode is prepared, started and ended (with its id, task and
//! labels), the `log` crate's lines bridged in, a line when the server stops, none of the third-party noise
//! (OpenH264's encoder warning, libwayland's `XDG_RUNTIME_DIR` complaint) on stderr, and `--log-format json` as
//! one JSON object a line.
mod common;

use std::io::{BufRead, BufReader};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use common::{bin, first_json_line, http};
use serde_json::{Value, json};

/// A `libero-agent serve` whose stderr lines arrive on `lines` (and are echoed for the test's own log).
struct Serve {
    child: Child,
    url: String,
    token: String,
    lines: mpsc::Receiver<String>,
    seen: Vec<String>,
    reader: Option<JoinHandle<()>>,
}

impl Serve {
    /// Without `XDG_RUNTIME_DIR` and `RUST_LOG`, as on a server started by hand or by a service manager.
    fn start(data: &Path, extra: &[&str]) -> Self {
        let mut child = Command::new(bin())
            .args(["serve", "--addr", "127.0.0.1:0", "--data"])
            .arg(data)
            .args(extra)
            .env_remove("XDG_RUNTIME_DIR")
            .env_remove("RUST_LOG")
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("start libero-agent serve");
        let stderr = child.stderr.take().expect("stderr");
        let (tx, lines) = mpsc::channel();
        let reader = std::thread::spawn(move || {
            for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                eprintln!("serve: {line}");
                let _ = tx.send(line);
            }
        });
        let url = first_json_line(&mut child)["url"].as_str().expect("url").to_owned();
        let token = std::fs::read_to_string(data.join("operator_token")).expect("the operator token").trim().to_owned();
        Self { child, url, token, lines, seen: Vec::new(), reader: Some(reader) }
    }

    fn post(&self, path: &str, body: &Value) -> Value {
        let auth = format!("Bearer {}", self.token);
        let (status, _, body) = http("POST", &format!("{}{path}", self.url), &[("Authorization", &auth)], body.to_string().as_bytes());
        let v: Value = serde_json::from_slice(&body).unwrap_or_else(|e| panic!("POST {path}: {e}: {}", String::from_utf8_lossy(&body)));
        assert!(status == 200 || status == 201, "POST {path}: {status} {v}");
        v
    }

    fn prepare(&self, body: Value) -> (String, String) {
        let p = self.post("/api/episodes", &body);
        (p["episode_id"].as_str().expect("episode_id").to_owned(), p["workspace"].as_str().expect("workspace").to_owned())
    }

    /// Waits (at most `limit`) for a stderr line that `want` accepts.
    fn wait_for(&mut self, what: &str, limit: Duration, want: impl Fn(&str) -> bool) -> String {
        let deadline = Instant::now() + limit;
        if let Some(l) = self.seen.iter().find(|l| want(l)) {
            return l.clone();
        }
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.lines.recv_timeout(left) {
                Ok(l) => {
                    self.seen.push(l.clone());
                    if want(&l) {
                        return l;
                    }
                }
                Err(_) => panic!("no {what} on stderr within {limit:?}; it said:\n{}", self.seen.join("\n")),
            }
        }
    }

    /// SIGTERM, as a service manager stops it; every stderr line it wrote.
    fn stop(mut self) -> Vec<String> {
        // SAFETY: kill(2) on our own child's pid.
        assert_eq!(unsafe { libc::kill(self.child.id() as libc::pid_t, libc::SIGTERM) }, 0);
        let t = Instant::now();
        let status = loop {
            if let Some(s) = self.child.try_wait().unwrap() {
                break s;
            }
            assert!(t.elapsed() < Duration::from_secs(60), "serve did not stop within 60 s of SIGTERM");
            std::thread::sleep(Duration::from_millis(100));
        };
        assert!(status.success(), "serve exited with {status}");
        self.reader.take().expect("reader").join().unwrap();
        self.seen.extend(self.lines.try_iter());
        std::mem::take(&mut self.seen)
    }
}

impl Drop for Serve {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// No third-party noise: OpenH264's parameter warning, libwayland's runtime-directory error, wgpu's EGL probe.
fn assert_quiet(lines: &[String]) {
    for l in lines {
        assert!(!l.contains("OpenH264") && !l.contains("bEnableFrameSkip"), "OpenH264 noise: {l}");
        assert!(!l.contains("XDG_RUNTIME_DIR"), "libwayland noise: {l}");
        assert!(!l.contains("eglInitialize"), "EGL probe noise: {l}");
    }
}

/// Text lines: an episode played by the reference agent (with its private video, so OpenH264 encodes) and one
/// prepared and aborted, then SIGTERM.
#[test]
fn serve_logs_each_episode_start_and_end_and_its_stop_without_third_party_noise() {
    let tmp = tempfile::tempdir().unwrap();
    let mut serve = Serve::start(&tmp.path().join("data"), &[]);

    let (played, workspace) =
        serve.prepare(json!({"task": "T14", "level": 1, "harness": "command", "model": "reference", "batch": "logtest"}));
    let agent = Command::new(bin()).args(["agent", "--workspace", &workspace]).output().expect("run the reference agent");
    assert!(agent.status.success(), "the reference agent failed: {}", String::from_utf8_lossy(&agent.stderr));
    let ended = serve.wait_for("the played episode's end line", Duration::from_secs(30), |l| {
        l.contains("episode ended") && l.contains(&played)
    });
    for field in ["task=\"T14\"", "level=1", "harness=\"command\"", "model=\"reference\"", "batch=\"logtest\"", "state=\"finished\"", "steps=4"] {
        assert!(ended.contains(field), "{field} missing: {ended}");
    }
    assert!(ended.contains(" INFO ") && ended.contains("outcome="), "{ended}");
    // The video worker's own `log::info!` (bridged from the `log` crate) once the video is encoded.
    serve.wait_for("the private video's line", Duration::from_secs(120), |l| {
        l.contains("libero_episode::video_queue") && l.contains(&played) && l.contains("frames in")
    });

    let (aborted, _) = serve.prepare(json!({"task": "T14", "level": 1, "video": false}));
    let row = serve.post(&format!("/api/episodes/{aborted}/abort"), &json!({"reason": "logging test abort"}));
    assert_eq!(row["outcome"], "INVALID", "{row}");

    let lines = serve.stop();
    let text = lines.join("\n");
    let line_of = |what: &str, id: &str| {
        lines.iter().filter(|l| l.contains(what) && l.contains(id)).cloned().collect::<Vec<_>>()
    };
    for (id, events) in [(&played, &["episode prepared", "episode started", "episode ended"][..]), (&aborted, &["episode prepared", "episode ended"][..])] {
        for event in events {
            let found = line_of(event, id);
            assert_eq!(found.len(), 1, "one {event:?} line for {id}:\n{text}");
            assert!(found[0].contains("task=\"T14\""), "{found:?}");
        }
    }
    assert!(line_of("episode started", &aborted).is_empty(), "an episode never started has no start line:\n{text}");
    let abort_end = &line_of("episode ended", &aborted)[0];
    assert!(
        abort_end.contains("state=\"aborted\"") && abort_end.contains("outcome=\"INVALID\"") && abort_end.contains("reason=\"logging test abort\""),
        "{abort_end}"
    );
    assert!(lines.last().is_some_and(|l| l.ends_with("libero-agent serve: stopped")), "the last line says it stopped:\n{text}");
    assert!(lines.iter().any(|l| l.contains("?token=")), "the one-time login link is still printed as it was:\n{text}");
    assert!(!text.contains('\u{1b}'), "no colours on a pipe");
    assert_quiet(&lines);
}

/// `--log-format json`: every log line is one JSON object (`timestamp`, `level`, `target`, and `fields` with the
/// message and the event's fields). The episode is still open at SIGTERM: the stop ends it, and its line says so.
#[test]
fn serve_log_format_json_writes_one_json_object_a_line() {
    let tmp = tempfile::tempdir().unwrap();
    let serve = Serve::start(&tmp.path().join("data"), &["--log-format", "json"]);
    let (id, _) = serve.prepare(json!({"task": "T14", "level": 1, "video": false, "model": "m-json", "batch": "b-json"}));
    let lines = serve.stop();
    let text = lines.join("\n");
    // What is not a log line: the one-time login link `serve` prints as it always did (two lines).
    let records: Vec<Value> = lines
        .iter()
        .filter(|l| !l.starts_with("libero-agent serve: open the dashboard") && !l.contains("?token="))
        .map(|l| serde_json::from_str(l).unwrap_or_else(|e| panic!("not a JSON log line ({e}): {l}\n{text}")))
        .collect();
    for r in &records {
        assert!(r["timestamp"].is_string() && r["level"].is_string() && r["target"].is_string(), "{r}");
        assert!(r["fields"]["message"].is_string(), "{r}");
    }
    let event = |message: &str| {
        records
            .iter()
            .find(|r| r["fields"]["message"] == message && r["fields"]["episode_id"] == id.as_str())
            .map(|r| &r["fields"])
            .unwrap_or_else(|| panic!("no {message:?} line for {id}:\n{text}"))
    };
    let prepared = event("episode prepared");
    assert_eq!((prepared["task"].as_str(), prepared["level"].as_u64()), (Some("T14"), Some(1)), "{prepared}");
    assert_eq!((prepared["model"].as_str(), prepared["batch"].as_str()), (Some("m-json"), Some("b-json")), "{prepared}");
    assert!(prepared.get("harness").is_none(), "no harness given, none logged: {prepared}");
    let ended = event("episode ended");
    assert_eq!((ended["task"].as_str(), ended["level"].as_u64()), (Some("T14"), Some(1)), "{ended}");
    assert_eq!((ended["state"].as_str(), ended["outcome"].as_str()), (Some("aborted"), Some("INVALID")), "{ended}");
    assert_eq!((ended["steps"].as_u64(), ended["reason"].as_str()), (Some(0), Some("server_received_signal_15_before_finish")), "{ended}");
    assert!(ended["since_prepared_s"].is_f64(), "{ended}");
    let stopped = records.last().expect("log lines");
    assert_eq!((stopped["level"].as_str(), stopped["fields"]["message"].as_str()), (Some("INFO"), Some("libero-agent serve: stopped")), "{text}");
    assert_quiet(&lines);
}
