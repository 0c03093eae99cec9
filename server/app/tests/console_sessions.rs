//! The console as its users live in it (issue 33): the operator token stays the same across restarts of a data
//! directory and open browser sessions survive them, until `serve --rotate-token`; the login link `serve` prints
//! works exactly once, also across a restart; the login page of a loopback server says where it listens and
//! where the token is (asked in process); `expert --pace realtime` sends 20 actions per second of wall time. (Error pages with the
//! navigation, `/api/` keeping JSON and the icon are checked in process: `routes_in_process`.)
//! Chromium (`tests/dashboard/console_errors.cjs`) looks at the login and error pages; screenshots go to
//! `target/test-artifacts/console/`.
mod common;

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::Duration;

use common::{Server, bin, browser_script, first_json_line, http};
use libero_testkit::server::{Method, TestServer};
use serde_json::Value;

/// The session cookie (`libero_session=…`) a login answer sets.
fn session_cookie(head: &str) -> String {
    let line = head.lines().find(|l| l.to_ascii_lowercase().starts_with("set-cookie:")).unwrap_or_else(|| panic!("no cookie in {head}"));
    line.split_once(':').unwrap().1.split(';').next().unwrap().trim().to_owned()
}

/// Opens a browser session with the operator token as a login URL; returns its cookie.
fn sign_in(base: &str, token: &str) -> String {
    let (status, head, _) = http("GET", &format!("{base}/?token={token}"), &[], b"");
    assert_eq!(status, 303, "the token opens a session: {head}");
    session_cookie(&head)
}

fn get_with(url: &str, headers: &[(&str, &str)]) -> (u16, String, String) {
    let (status, head, body) = http("GET", url, headers, b"");
    (status, head, String::from_utf8_lossy(&body).into_owned())
}

/// A `serve` whose stderr is read: its URL and the one-time login link it printed. Stderr keeps being drained.
struct LinkServer {
    child: Child,
    url: String,
    link: String,
}

impl LinkServer {
    fn start(data: &Path, addr: &str) -> Self {
        let mut child = Command::new(bin())
            .args(["serve", "--addr", addr, "--data"])
            .arg(data)
            .env("LIBERO_AGENT_THUMBNAILS_AHEAD", "off")
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("start libero-agent serve");
        let stderr = BufReader::new(child.stderr.take().expect("stderr"));
        let (tx, rx) = mpsc::channel();
        std::thread::spawn(move || {
            for line in stderr.lines().map_while(Result::ok) {
                eprintln!("serve: {line}");
                if let Some(i) = line.find("http://").filter(|_| line.contains("?token=")) {
                    let _ = tx.send(line[i..].trim().to_owned());
                }
            }
        });
        let url = first_json_line(&mut child)["url"].as_str().expect("url").to_owned();
        let link = rx.recv_timeout(Duration::from_secs(60)).expect("the login link on stderr");
        Self { child, url, link }
    }
}

impl Drop for LinkServer {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

#[test]
fn the_token_and_browser_sessions_survive_a_restart_until_the_token_is_rotated() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let mut first = Server::start(&data);
    let token = first.token.clone();
    let cookie = sign_in(&first.url, &token);
    let (status, _, _) = get_with(&format!("{}/api/episodes", first.url), &[("Cookie", &cookie)]);
    assert_eq!(status, 200, "the session works");
    first.kill();

    let mut second = Server::start(&data);
    assert_eq!(second.token, token, "a restart keeps the operator token");
    use std::os::unix::fs::PermissionsExt;
    let mode = std::fs::metadata(data.join("operator_token")).unwrap().permissions().mode() & 0o777;
    assert_eq!(mode, 0o600, "the token file stays private");
    let (status, _, body) = get_with(&format!("{}/", second.url), &[("Cookie", &cookie)]);
    assert_eq!(status, 200, "a session cookie from before the restart still opens the console");
    assert!(body.contains("header class=\"top\""), "the episodes page itself");
    let (status, _, _) = get_with(&format!("{}/api/episodes", second.url), &[("Cookie", &cookie)]);
    assert_eq!(status, 200);
    let sessions = std::fs::read_to_string(data.join("operator_sessions")).unwrap();
    assert!(!sessions.contains(cookie.split('=').nth(1).unwrap()) && !sessions.contains(&token), "only hashes are kept");
    second.kill();

    let rotated = Server::start_with(&data, &["--rotate-token"]);
    assert_ne!(rotated.token, token, "--rotate-token replaces the token");
    assert_eq!(std::fs::read_to_string(data.join("operator_token")).unwrap().trim(), rotated.token);
    let (status, head, _) = get_with(&format!("{}/api/episodes", rotated.url), &[("Cookie", &cookie)]);
    assert_eq!(status, 401, "an old session is refused after rotation: {head}");
    let (status, head, _) = get_with(&format!("{}/", rotated.url), &[("Cookie", &cookie)]);
    assert!(status == 303 && head.to_ascii_lowercase().contains("location: /login"), "an old session's page visit goes to the login form: {head}");
    let (status, _, _) = get_with(&format!("{}/api/episodes", rotated.url), &[("Authorization", &format!("Bearer {token}"))]);
    assert_eq!(status, 401, "the old token is refused");
    let (status, _, _) = get_with(&format!("{}/api/episodes", rotated.url), &[("Authorization", &format!("Bearer {}", rotated.token))]);
    assert_eq!(status, 200, "the new token works");
    let fresh = sign_in(&rotated.url, &rotated.token);
    let (status, _, _) = get_with(&format!("{}/api/episodes", rotated.url), &[("Cookie", &fresh)]);
    assert_eq!(status, 200);

    // --rotate-token and --operator-token-file contradict each other.
    let both = Command::new(bin())
        .args(["serve", "--addr", "127.0.0.1:0", "--rotate-token", "--operator-token-file", "/dev/null", "--data"])
        .arg(tmp.path().join("other"))
        .output()
        .unwrap();
    assert!(!both.status.success(), "conflicting flags are refused");
}

#[test]
fn the_printed_login_link_works_once_even_across_a_restart() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let first = LinkServer::start(&data, "127.0.0.1:0");
    let token = std::fs::read_to_string(data.join("operator_token")).unwrap().trim().to_owned();
    assert!(first.link.starts_with(&format!("{}/?token=", first.url)), "{}", first.link);
    assert!(!first.link.contains(&token), "the printed link holds a one-time code, not the operator token");
    let (status, head, _) = get_with(&first.link, &[]);
    assert_eq!(status, 303, "the link opens a session: {head}");
    assert!(head.lines().any(|l| l.trim().eq_ignore_ascii_case("location: /")), "{head}");
    let cookie = session_cookie(&head);
    let (status, _, _) = get_with(&format!("{}/api/episodes", first.url), &[("Cookie", &cookie)]);
    assert_eq!(status, 200);
    let (status, _, body) = get_with(&first.link, &[]);
    assert_eq!(status, 401, "the link works only once");
    assert!(body.contains("not the operator token"), "the login form says so: {body}");
    let used = first.link.clone();
    drop(first);

    let second = LinkServer::start(&data, "127.0.0.1:0");
    let used_here = used.replace(&used[..used.find("/?").unwrap()], &second.url);
    let (status, _, _) = get_with(&used_here, &[]);
    assert_eq!(status, 401, "a used link stays used after a restart");
    assert_ne!(second.link, used_here, "every start prints a new link");
    let unused = second.link.clone();
    let second_url = second.url.clone();
    drop(second);

    let third = LinkServer::start(&data, "127.0.0.1:0");
    let unused_here = unused.replace(&second_url, &third.url);
    let (status, head, _) = get_with(&unused_here, &[]);
    assert_eq!(status, 303, "a link not used before the restart works after it, once: {head}");
    let (status, _, _) = get_with(&unused_here, &[]);
    assert_eq!(status, 401, "and only once");
    let (status, _, _) = get_with(&third.link, &[]);
    assert_eq!(status, 303, "this start's own link");
}

/// Asked of the full router in process: a loopback server's login page names its address and the token file, and
/// claims nothing beyond loopback; one bound to 0.0.0.0 says it listens beyond loopback.
#[tokio::test(flavor = "multi_thread")]
async fn the_login_page_says_where_the_server_listens_and_where_the_token_is() {
    let server = TestServer::start().await;
    let token_file = std::path::absolute(server.data().join("operator_token")).unwrap();
    let login = server.get("/login").await;
    let body = login.text();
    assert_eq!(login.status, 200, "{body}");
    assert!(login.header("content-type").is_some_and(|t| t.starts_with("text/html")), "{:?}", login.headers);
    assert!(body.contains(&token_file.display().to_string()), "the login page names {}: {body}", token_file.display());
    assert!(!body.contains("beyond loopback"), "a loopback server does not claim to listen beyond loopback: {body}");
    let addr = server.url().trim_start_matches("http://");
    assert!(body.contains(addr) && body.contains("loopback address"), "it says where it listens: {body}");
    drop(server);

    // Beyond loopback, it says so.
    let wide = TestServer::start_at("0.0.0.0:0", &[]).await;
    let port = wide.url().rsplit(':').next().unwrap().to_owned();
    let login = wide.send(Method::GET, "/login", &[("host", &format!("127.0.0.1:{port}"))], Vec::new()).await;
    let body = login.text();
    assert_eq!(login.status, 200, "{body}");
    assert!(body.contains("beyond loopback") && body.contains("0.0.0.0:"), "{body}");
}

fn artifacts_dir() -> PathBuf {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("../test-artifacts/console");
    std::fs::create_dir_all(&dir).expect("artifacts dir");
    dir
}

#[test]
fn chromium_sees_the_login_page_and_error_pages_with_the_navigation() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let server = Server::start(&data);
    let token_file = std::path::absolute(data.join("operator_token")).unwrap();
    let artifacts = artifacts_dir();
    for shot in ["console-login", "console-error-404", "console-error-episode"] {
        let _ = std::fs::remove_file(artifacts.join(format!("{shot}.png")));
    }
    let report = browser_script("console_errors.cjs", &[&server.url, artifacts.to_str().unwrap(), token_file.to_str().unwrap()], &server.token);
    assert_eq!(report["ok"], true, "{report}");
    for shot in ["console-login", "console-error-404", "console-error-episode"] {
        assert!(artifacts.join(format!("{shot}.png")).is_file(), "screenshot {shot}.png");
    }
}

#[test]
fn expert_pace_realtime_sends_at_most_twenty_actions_per_second() {
    let tmp = tempfile::tempdir().unwrap();
    let out = Command::new(bin())
        .args(["expert", "--task", "T14", "--no-video", "--pace", "realtime", "--max-actions", "100", "--data"])
        .arg(tmp.path().join("data"))
        .output()
        .expect("run expert");
    let stdout = String::from_utf8_lossy(&out.stdout);
    eprintln!("{stdout}{}", String::from_utf8_lossy(&out.stderr));
    let line: Value = stdout.lines().find_map(|l| serde_json::from_str(l).ok()).expect("the run's JSON line");
    assert_eq!(line["pace"], "realtime", "the pace is recorded with the run: {line}");
    let actions = line["actions"].as_u64().expect("actions");
    // T14's expert solves it in about 76 actions, more than one call's 50.
    assert!(actions > 50, "the run sent its actions: {line}");
    assert!(line["osc_sequence_calls"].as_u64().unwrap_or(0) >= 2, "more than one call: {line}");
    // A lower bound only (never an upper one): n actions at 20 per second keep the episode open at least n/20 s
    // from start to finish. Unpaced, they take well under that (60 actions about 1.1 s in a debug build).
    let wall = line["episode_wall_time_s"].as_f64().expect("the episode's wall time");
    let floor = actions as f64 / 20.0;
    assert!(wall >= floor, "{actions} actions in {wall:.2} s, less than {floor} s");

    // An unknown pace is refused with the choices.
    let bad = Command::new(bin()).args(["expert", "--task", "T14", "--pace", "slow"]).output().unwrap();
    assert!(!bad.status.success());
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(err.contains("realtime") && err.contains("fast"), "{err}");
}
