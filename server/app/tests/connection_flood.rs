//! Issue 30, item 4: a flood of loopback connections beside a running episode. A hostile agent shares the
//! server's loopback; before the connection limits it could open idle or half-sent connections until the server
//! had no file descriptor left, and the next step of every episode failed without a result.
//!
//! Here a real `libero-agent serve`, started with only 1000 file descriptors, plays one T14 episode
//! undisturbed, then a second one while threads of this test open 20,000+ connections to it on 127.0.0.1 and
//! [::1] (half of them idle, a quarter sending a request head one byte at a time, a quarter closed at once),
//! paced and bounded in count and time. The flooded episode's calls (each on a new connection, as a simple
//! client makes them) must stay within twice the undisturbed p95 or one second more, whichever is larger: this
//! 2-core machine is shared with other builds and tests, so the absolute floor keeps scheduling noise from
//! failing the test, while a server that let the flood in would fail calls outright or stall them for seconds
//! (SYN retries, refused connections). Both episodes end with `result.json` and a store row with an outcome;
//! the server stays up, answers `/api/health` and never runs out of descriptors; its open descriptors stay
//! within its connection cap (500 of its 1000) above the level before the flood, and every idle or half-sent
//! connection older than the header timeout has been closed by the server.
#![cfg(feature = "episode-serve")]

use std::collections::VecDeque;
use std::io::{BufRead, BufReader, ErrorKind, Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use serde_json::{Value, json};

mod common;
use common::{Server, bin, first_json_line, http, http_get_json};

const TASK: &str = "T14";
/// Timed `osc_sequence` calls per episode, and micro-actions per call.
const CALLS: usize = 20;
const ACTIONS: usize = 10;
/// The server's defaults (`--max-connections-per-ip`, `--header-read-timeout-s`).
const PER_IP: usize = 256;
const HEADER_TIMEOUT: Duration = Duration::from_secs(10);
/// The server runs near its descriptor limit: with 1000 descriptors its connection cap is 500 (half the limit,
/// since the usual reserve of 1024 would leave nothing), below the two addresses' 2 x 256, so the total cap
/// binds as well as the per-address one, and 500 descriptors stay for the episodes' own files.
const SERVER_NOFILE: u64 = 1000;
const SERVER_CAP: usize = 500;
/// The flood: at least this many connections, at this pace, for at most this long.
const FLOOD_MIN: usize = 20_000;
const FLOOD_MAX: usize = 60_000;
const FLOOD_RATE_PER_S: f64 = 1000.0;
const FLOOD_MAX_TIME: Duration = Duration::from_secs(75);
const FLOOD_THREADS: usize = 4;
/// How long the flood holds an idle or half-sent connection before checking whether the server closed it.
const HOLD: Duration = Duration::from_secs(12);

/// Raises this process's soft descriptor limit to the hard one; returns it.
fn raise_nofile() -> u64 {
    let mut lim = libc::rlimit { rlim_cur: 0, rlim_max: 0 };
    // SAFETY: getrlimit/setrlimit with a pointer to a local struct.
    unsafe {
        assert_eq!(libc::getrlimit(libc::RLIMIT_NOFILE, &mut lim), 0);
        lim.rlim_cur = lim.rlim_max;
        assert_eq!(libc::setrlimit(libc::RLIMIT_NOFILE, &lim), 0);
    }
    lim.rlim_cur
}

fn open_fds(pid: u32) -> usize {
    std::fs::read_dir(format!("/proc/{pid}/fd")).map(|d| d.count()).unwrap_or(0)
}

/// Nearest-rank percentile in ms.
fn percentile(ms: &[f64], p: f64) -> f64 {
    let mut v = ms.to_vec();
    v.sort_by(f64::total_cmp);
    let rank = ((p / 100.0) * v.len() as f64).ceil() as usize;
    v[rank.clamp(1, v.len()) - 1]
}

/// The JSON-RPC message with `id` in a JSON or SSE body.
fn reply(body: &[u8], id: u64) -> Value {
    let text = String::from_utf8_lossy(body);
    let messages: Vec<Value> = match serde_json::from_str::<Value>(&text) {
        Ok(v) => vec![v],
        Err(_) => text.lines().filter_map(|l| l.strip_prefix("data:")).filter_map(|d| serde_json::from_str(d.trim()).ok()).collect(),
    };
    messages.into_iter().find(|m| m["id"] == id).unwrap_or_else(|| panic!("no reply with id {id} in {text:?}"))
}

/// One episode played over raw MCP JSON-RPC, every request on a new connection.
struct Episode {
    id: String,
    url: String,
    auth: String,
    run_dir: PathBuf,
    session: Option<String>,
    next_id: u64,
}

impl Episode {
    fn prepare(server: &Server, ws: &Path) -> Self {
        let req = json!({"task": TASK, "level": 1, "video": false, "workspace": ws});
        let op = format!("Bearer {}", server.token);
        let headers = [("Content-Type", "application/json"), ("Authorization", op.as_str())];
        let (status, _, body) = http("POST", &format!("{}/api/episodes", server.url), &headers, req.to_string().as_bytes());
        let p: Value = serde_json::from_slice(&body).unwrap();
        assert_eq!(status, 201, "{p}");
        Self {
            id: p["episode_id"].as_str().unwrap().to_owned(),
            url: p["mcp_url"].as_str().unwrap().to_owned(),
            auth: p["mcp_headers"]["Authorization"].as_str().unwrap().to_owned(),
            run_dir: PathBuf::from(p["run_dir"].as_str().unwrap()),
            session: None,
            next_id: 1,
        }
    }

    fn post(&mut self, message: &Value) -> (u16, String, Vec<u8>) {
        let mut headers = vec![
            ("Authorization", self.auth.as_str()),
            ("Content-Type", "application/json"),
            ("Accept", "application/json, text/event-stream"),
        ];
        if let Some(s) = &self.session {
            headers.extend([("Mcp-Session-Id", s.as_str()), ("Mcp-Protocol-Version", "2025-06-18")]);
        }
        http("POST", &self.url, &headers, message.to_string().as_bytes())
    }

    fn initialize(&mut self) {
        let init = json!({"jsonrpc": "2.0", "id": 0, "method": "initialize",
            "params": {"protocolVersion": "2025-06-18", "capabilities": {}, "clientInfo": {"name": "flood-test", "version": "0"}}});
        let (status, head, body) = self.post(&init);
        assert_eq!(status, 200, "{}", String::from_utf8_lossy(&body));
        self.session = head
            .lines()
            .find_map(|l| l.split_once(':').filter(|(k, _)| k.eq_ignore_ascii_case("mcp-session-id")))
            .map(|(_, v)| v.trim().to_owned());
        assert!(self.session.is_some(), "no session id: {head}");
        let (status, _, _) = self.post(&json!({"jsonrpc": "2.0", "method": "notifications/initialized"}));
        assert!(status < 300, "notifications/initialized: HTTP {status}");
    }

    /// A tool call; its payload, which must say `ok`.
    fn call(&mut self, tool: &str, arguments: Value) -> Value {
        let id = self.next_id;
        self.next_id += 1;
        let message = json!({"jsonrpc": "2.0", "id": id, "method": "tools/call", "params": {"name": tool, "arguments": arguments}});
        let (status, _, body) = self.post(&message);
        let r = reply(&body, id);
        assert_eq!((status, &r["result"]["structuredContent"]["ok"]), (200, &json!(true)), "{tool}: {r}");
        r["result"]["structuredContent"].clone()
    }

    /// Plays the episode: start, [`CALLS`] timed `osc_sequence` calls, finish; the calls' latencies in ms.
    fn play(&mut self) -> Vec<f64> {
        self.initialize();
        self.call("start_episode", json!({}));
        let mut ms = Vec::with_capacity(CALLS);
        for call in 0..CALLS {
            let sign = if call % 2 == 0 { 1.0 } else { -1.0 };
            let actions = vec![json!([0.1 * sign, 0.05 * sign, 0.0, 0.0, 0.0, 0.02 * sign, -1.0]); ACTIONS];
            let t = Instant::now();
            self.call("osc_sequence", json!({"actions": actions}));
            ms.push(t.elapsed().as_secs_f64() * 1e3);
        }
        self.call("finish_episode", json!({}));
        ms
    }

    /// The episode ended normally: its `result.json` is written and its store row has an outcome.
    fn assert_ended(&self, server: &Server) {
        let result = self.run_dir.join("result.json");
        let deadline = Instant::now() + Duration::from_secs(30);
        while !result.is_file() {
            assert!(Instant::now() < deadline, "{} was never written", result.display());
            std::thread::sleep(Duration::from_millis(100));
        }
        let r: Value = serde_json::from_slice(&std::fs::read(&result).unwrap()).unwrap();
        assert_eq!((&r["status"], r["accepted_agent_steps"].as_u64()), (&json!("finished"), Some(CALLS as u64)), "{r}");
        let op = format!("Bearer {}", server.token);
        let (status, _, body) = http("GET", &format!("{}/api/episodes/{}", server.url, self.id), &[("Authorization", op.as_str())], b"");
        let row: Value = serde_json::from_slice(&body).unwrap();
        assert_eq!(status, 200, "{row}");
        assert!(matches!(row["outcome"].as_str(), Some("SUCCESS" | "FAIL")), "{row}");
        assert_eq!(row["success"], r["success"], "{row}");
        assert!(row["finished_at"].is_string(), "{row}");
    }
}

/// What the flood saw.
#[derive(Debug, Default)]
struct FloodReport {
    opened: usize,
    connect_failed: usize,
    /// Idle or half-sent connections checked after [`HOLD`]: closed by the server (FIN, reset or an answer).
    closed_by_server: usize,
    /// ... and still open then: the server kept them past its header timeout.
    still_open: usize,
}

#[derive(Clone, Copy, PartialEq)]
enum Kind {
    Idle,
    Slow,
}

/// Whether the server closed `s` (nonblocking): end of stream, a reset, or any answer (a 503, a 408).
fn closed_by_server(s: &mut TcpStream) -> bool {
    let mut buf = [0u8; 256];
    match s.read(&mut buf) {
        Ok(_) => true,
        Err(e) if e.kind() == ErrorKind::WouldBlock => false,
        Err(_) => true,
    }
}

/// One flood thread: opens connections to `targets` in turn at its share of the pace until `done` says the
/// episode is over and [`FLOOD_MIN`] are open (or [`FLOOD_MAX`] / [`FLOOD_MAX_TIME`]), holding at most
/// `budget` descriptors.
fn flood_thread(
    targets: Vec<SocketAddr>,
    index: usize,
    done: Arc<AtomicBool>,
    opened_total: Arc<AtomicUsize>,
    budget: usize,
) -> FloodReport {
    const SLOW_HEAD: &[u8] = b"GET /api/health HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Slow: aaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaa";
    let interval = Duration::from_secs_f64(FLOOD_THREADS as f64 / FLOOD_RATE_PER_S);
    let start = Instant::now();
    let mut held: VecDeque<(TcpStream, Instant, Kind, usize)> = VecDeque::new();
    let mut report = FloodReport::default();
    let mut last_drip = Instant::now();
    let mut n = 0usize;
    loop {
        let total = opened_total.load(Ordering::Relaxed);
        let enough = done.load(Ordering::Relaxed) && total >= FLOOD_MIN;
        if enough || total >= FLOOD_MAX || start.elapsed() > FLOOD_MAX_TIME {
            break;
        }
        if let Some(wait) = (start + interval * n as u32).checked_duration_since(Instant::now()) {
            std::thread::sleep(wait);
        }
        let slot = n * FLOOD_THREADS + index;
        n += 1;
        let target = targets[slot % targets.len()];
        let kind = match slot % 4 {
            0 | 1 => Some(Kind::Idle),
            2 => Some(Kind::Slow),
            _ => None,
        };
        match TcpStream::connect_timeout(&target, Duration::from_secs(2)) {
            Ok(s) => {
                report.opened += 1;
                opened_total.fetch_add(1, Ordering::Relaxed);
                if let Some(kind) = kind {
                    s.set_nonblocking(true).unwrap();
                    held.push_back((s, Instant::now(), kind, 0));
                }
            }
            Err(_) => report.connect_failed += 1,
        }
        // Check and let go of what was held long enough (or crowds the descriptor budget).
        while let Some((_, at, _, _)) = held.front() {
            if at.elapsed() < HOLD && held.len() <= budget {
                break;
            }
            let (mut s, at, _, _) = held.pop_front().unwrap();
            if at.elapsed() >= HOLD {
                if closed_by_server(&mut s) {
                    report.closed_by_server += 1;
                } else {
                    report.still_open += 1;
                }
            }
        }
        // Half a request head, one byte per half second per connection.
        if last_drip.elapsed() > Duration::from_millis(500) {
            last_drip = Instant::now();
            for (s, _, kind, sent) in held.iter_mut() {
                if *kind == Kind::Slow && *sent < SLOW_HEAD.len() && s.write(&SLOW_HEAD[*sent..*sent + 1]).is_ok() {
                    *sent += 1;
                }
            }
        }
    }
    for (mut s, at, _, _) in held {
        if at.elapsed() >= HOLD {
            if closed_by_server(&mut s) {
                report.closed_by_server += 1;
            } else {
                report.still_open += 1;
            }
        }
    }
    report
}

/// `libero-agent serve` with at most [`SERVER_NOFILE`] descriptors (soft and hard); its stderr lines are
/// echoed and kept.
fn start_server(data: &Path) -> (Server, Arc<Mutex<Vec<String>>>) {
    let mut cmd = Command::new(bin());
    cmd.args(["serve", "--addr", "127.0.0.1:0", "--data"]).arg(data).stdout(Stdio::piped()).stderr(Stdio::piped());
    // SAFETY: only setrlimit, async-signal-safe, between fork and exec.
    unsafe {
        cmd.pre_exec(|| {
            let lim = libc::rlimit { rlim_cur: SERVER_NOFILE, rlim_max: SERVER_NOFILE };
            if libc::setrlimit(libc::RLIMIT_NOFILE, &lim) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
    let mut child = cmd.spawn().expect("start libero-agent serve");
    let lines = Arc::new(Mutex::new(Vec::new()));
    let stderr = child.stderr.take().unwrap();
    let kept = lines.clone();
    std::thread::spawn(move || {
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            eprintln!("{line}");
            kept.lock().unwrap().push(line);
        }
    });
    let url = first_json_line(&mut child)["url"].as_str().expect("url").to_owned();
    let token = std::fs::read_to_string(data.join("operator_token")).unwrap().trim().to_owned();
    (Server { child, url, token }, lines)
}

#[test]
fn a_connection_flood_beside_an_episode_neither_stalls_it_nor_exhausts_the_server() {
    let nofile = raise_nofile();
    let tmp = tempfile::tempdir().unwrap();
    let (mut server, server_log) = start_server(&tmp.path().join("data"));
    let pid = server.child.id();
    let port: u16 = server.url.rsplit(':').next().unwrap().parse().unwrap();

    // The server holds its port on both loopback addresses: nobody else can listen on [::1]:PORT.
    let v6 = std::net::TcpListener::bind("[::1]:0").is_ok();
    let mut targets: Vec<SocketAddr> = vec![SocketAddr::from(([127, 0, 0, 1], port))];
    if v6 {
        let twin = SocketAddr::from((std::net::Ipv6Addr::LOCALHOST, port));
        let err = std::net::TcpListener::bind(twin).expect_err("the server's port is free on [::1]");
        assert_eq!(err.kind(), ErrorKind::AddrInUse);
        let (status, body) = http_get_json(&format!("http://[::1]:{port}/api/health"));
        assert_eq!((status, &body["ok"]), (200, &json!(true)), "{body}");
        targets.push(twin);
    } else {
        eprintln!("no IPv6 loopback on this machine: the flood uses 127.0.0.1 only");
    }

    // Undisturbed.
    let mut calm = Episode::prepare(&server, &tmp.path().join("ws-calm"));
    let calm_ms = calm.play();
    calm.assert_ended(&server);
    std::thread::sleep(Duration::from_secs(1));
    let fds_before = open_fds(pid);

    // The flood, and a sampler of the server's open descriptors.
    let done = Arc::new(AtomicBool::new(false));
    let opened = Arc::new(AtomicUsize::new(0));
    let budget = (nofile as usize).saturating_sub(1000).min(16_000) / FLOOD_THREADS;
    let flood: Vec<_> = (0..FLOOD_THREADS)
        .map(|i| {
            let (targets, done, opened) = (targets.clone(), done.clone(), opened.clone());
            std::thread::spawn(move || flood_thread(targets, i, done, opened, budget))
        })
        .collect();
    let sampling = Arc::new(AtomicBool::new(true));
    let sampler = {
        let sampling = sampling.clone();
        std::thread::spawn(move || {
            let mut max = 0;
            while sampling.load(Ordering::Relaxed) {
                max = max.max(open_fds(pid));
                std::thread::sleep(Duration::from_millis(50));
            }
            max
        })
    };
    // Let the flood reach the caps before the episode starts.
    std::thread::sleep(Duration::from_secs(3));
    let flood_started = Instant::now();
    let mut flooded = Episode::prepare(&server, &tmp.path().join("ws-flooded"));
    let flooded_ms = flooded.play();
    let episode_s = flood_started.elapsed().as_secs_f64();
    flooded.assert_ended(&server);
    done.store(true, Ordering::Relaxed);
    let mut report = FloodReport::default();
    for t in flood {
        let r = t.join().expect("flood thread");
        report.opened += r.opened;
        report.connect_failed += r.connect_failed;
        report.closed_by_server += r.closed_by_server;
        report.still_open += r.still_open;
    }
    sampling.store(false, Ordering::Relaxed);
    let fds_max = sampler.join().unwrap();

    let (calm_p50, calm_p95) = (percentile(&calm_ms, 50.0), percentile(&calm_ms, 95.0));
    let (flood_p50, flood_p95) = (percentile(&flooded_ms, 50.0), percentile(&flooded_ms, 95.0));
    eprintln!(
        "osc_sequence ({ACTIONS} actions, new connection per call): calm p50 {calm_p50:.0} ms p95 {calm_p95:.0} ms; \
         flooded p50 {flood_p50:.0} ms p95 {flood_p95:.0} ms (episode {episode_s:.1} s under flood)\n\
         flood: {report:?}; server descriptors {fds_before} before, at most {fds_max} during"
    );

    // The flood happened, and the server dealt with it.
    assert!(report.opened >= FLOOD_MIN, "{report:?}");
    assert_eq!(server.child.try_wait().unwrap(), None, "the server died");
    let (status, health) = http_get_json(&format!("{}/api/health", server.url));
    assert_eq!((status, &health["ok"]), (200, &json!(true)), "{health}");
    let limit = fds_before + SERVER_CAP.min(targets.len() * PER_IP) + 60;
    assert!(fds_max <= limit, "the server held {fds_max} descriptors during the flood (limit {limit})");
    assert!(
        report.closed_by_server > 0 && report.still_open == 0,
        "idle connections outlived the {HEADER_TIMEOUT:?} header timeout: {report:?}"
    );
    // The episode beside it did not notice much.
    let allowed = (2.0 * calm_p95).max(calm_p95 + 1000.0);
    assert!(flood_p95 <= allowed, "flooded p95 {flood_p95:.0} ms > {allowed:.0} ms (calm p95 {calm_p95:.0} ms)");
    // Within a few header timeouts of the flood's end, the server is back to its own descriptors.
    let deadline = Instant::now() + 2 * HEADER_TIMEOUT;
    while open_fds(pid) > fds_before + 20 {
        assert!(Instant::now() < deadline, "the server still holds {} descriptors (had {fds_before})", open_fds(pid));
        std::thread::sleep(Duration::from_millis(200));
    }
    server.kill();
    // It said why connections were closed, and it never ran out of descriptors.
    let log = server_log.lock().unwrap().join("\n");
    assert!(log.contains(&format!("connection limits reached ({SERVER_CAP} in total, {PER_IP} per address")), "{log}");
    assert!(!log.contains("out of file descriptors"), "{log}");
}
