//! Issue 18's first piece: `serve --store postgres://…` keeps its episodes in a real PostgreSQL (a throwaway
//! cluster of Debian's package), so two servers with their own data directories see one table. A server that
//! starts while another's episode is open leaves that episode open (its start-up reconcile closes only its own
//! orphans), and a store URL that names no supported engine, or a server it cannot reach, is refused with a
//! clear message that never shows the password.
mod common;

use common::postgres::TestPostgres;
use common::{Server, bin, http};
use serde_json::{Value, json};

fn episodes(server: &Server) -> Vec<Value> {
    let (status, _, body) = http("GET", &format!("{}/api/episodes", server.url), &[("Authorization", &format!("Bearer {}", server.token))], b"");
    assert_eq!(status, 200, "{}", String::from_utf8_lossy(&body));
    let v: Value = serde_json::from_slice(&body).unwrap();
    v["episodes"].as_array().cloned().unwrap_or_default()
}

#[test]
fn two_servers_share_one_postgres_store_and_neither_closes_the_others_episodes() {
    let pg = TestPostgres::start();
    let dir = tempfile::tempdir().unwrap();
    let a = Server::start_with(&dir.path().join("a"), &["--store", &pg.url]);
    let body = json!({"task": "T14", "level": 3, "harness": "scripted", "model": "m", "batch": "shared",
        "workspace": dir.path().join("ws-a")});
    let (status, _, out) = http(
        "POST",
        &format!("{}/api/episodes", a.url),
        &[("Content-Type", "application/json"), ("Authorization", &format!("Bearer {}", a.token))],
        body.to_string().as_bytes(),
    );
    assert_eq!(status, 201, "{}", String::from_utf8_lossy(&out));
    let id = serde_json::from_slice::<Value>(&out).unwrap()["episode_id"].as_str().unwrap().to_owned();

    // A second server on its own data directory starts (and reconciles) while A's episode is open.
    let b = Server::start_with(&dir.path().join("b"), &["--store", &pg.url]);
    let seen = episodes(&b);
    let row = seen.iter().find(|e| e["id"] == id.as_str()).unwrap_or_else(|| panic!("B lists A's episode: {seen:?}"));
    assert_eq!((row["task_ref"].as_str(), row["batch"].as_str()), (Some("T14"), Some("shared")));
    assert!(row["outcome"].is_null(), "B's start-up left A's open episode open: {row}");
    assert!(row.get("run_dir").is_none(), "paths stay out of the API");
    assert_eq!(episodes(&a).len(), 1);
}

#[test]
fn a_store_url_that_cannot_be_used_is_refused_without_showing_its_password() {
    let dir = tempfile::tempdir().unwrap();
    for (url, why) in [
        ("mysql://u:hunter2@127.0.0.1/db", "expected sqlite://PATH or postgres://"),
        // nothing listens on port 1
        ("postgres://u:hunter2@127.0.0.1:1/db", "cannot open the episode store"),
    ] {
        let out = std::process::Command::new(bin())
            .args(["serve", "--addr", "127.0.0.1:0", "--data"])
            .arg(dir.path().join("data"))
            .args(["--store", url])
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success() && err.contains(why), "{url}: {err}");
        assert!(!err.contains("hunter2"), "the password stays out of messages: {err}");
    }
}

/// One text message from a dashboard's WebSocket, or `None` once it closed; panics after `timeout`.
fn next_text(
    runtime: &tokio::runtime::Runtime,
    socket: &mut tokio_tungstenite::WebSocketStream<tokio_tungstenite::MaybeTlsStream<tokio::net::TcpStream>>,
    timeout: std::time::Duration,
) -> Option<Value> {
    use futures_util::StreamExt;
    use tokio_tungstenite::tungstenite::Message;
    runtime.block_on(async {
        loop {
            match tokio::time::timeout(timeout, socket.next()).await.expect("the dashboard pushes within the timeout") {
                Some(Ok(Message::Text(t))) => return Some(serde_json::from_str(&t).unwrap()),
                Some(Ok(Message::Close(_))) | None => return None,
                Some(Ok(_)) => continue,
                Some(Err(e)) => panic!("socket: {e}"),
            }
        }
    })
}

#[test]
fn a_dashboard_on_the_shared_store_pushes_another_servers_episode_progress_until_it_ends() {
    use libero_server::client::{McpClient, prepare_episode};
    use libero_server::episodes::PrepareRequest;
    use tokio_tungstenite::tungstenite::client::IntoClientRequest;
    let pg = TestPostgres::start();
    let dir = tempfile::tempdir().unwrap();
    let runner = Server::start_with(&dir.path().join("runner"), &["--store", &pg.url]);
    let watcher = Server::start_with(&dir.path().join("watcher"), &["--store", &pg.url]);
    let req = PrepareRequest { level: 3, workspace: Some(dir.path().join("ws")), wall_time_s: 300.0, max_agent_steps: 10, video: false, ..PrepareRequest::new("T14") };
    let prepared = prepare_episode(&runner.url, &req).unwrap();
    let id = prepared.episode_id.clone();

    // The watcher's page is the episode-elsewhere page, which follows the socket below.
    let (status, page) = common::http_get_text(&format!("{}/episodes/{id}", watcher.url));
    assert_eq!(status, 200, "{page}");
    assert!(page.contains(&format!("href=\"{}/episodes/{id}\"", runner.url)), "links to the running server: {page}");
    assert!(page.contains("/static/elsewhere.js") && page.contains(&format!("data-episode=\"{id}\"")), "{page}");
    let (status, script) = common::http_get_text(&format!("{}/static/elsewhere.js", watcher.url));
    assert!(status == 200 && script.contains("/ws/episodes/"), "{script}");

    let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build().unwrap();
    let ws_url = format!("{}/ws/episodes/{id}", watcher.url.replacen("http://", "ws://", 1));
    let mut request = ws_url.into_client_request().unwrap();
    request.headers_mut().insert("Authorization", format!("Bearer {}", watcher.token).parse().unwrap());
    let (mut socket, _) = runtime.block_on(tokio_tungstenite::connect_async(request)).unwrap();
    let wait = std::time::Duration::from_secs(30);
    let first = next_text(&runtime, &mut socket, wait).unwrap();
    assert_eq!((first["type"].as_str(), first["state"].as_str()), (Some("elsewhere"), Some("prepared")), "{first}");

    // The agent plays on the running server; the watcher's one socket is told each step, pushed by the store.
    let headers: Vec<(String, String)> = prepared.mcp_headers.clone().into_iter().collect();
    let mut client = McpClient::connect(&prepared.mcp_url, &headers, "watched").unwrap();
    client.call_tool("start_episode", json!({})).unwrap();
    let mut seen = vec![first];
    for step in 1..=2 {
        client.call_tool("osc_sequence", json!({"actions": [[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0]]})).unwrap();
        loop {
            let m = next_text(&runtime, &mut socket, wait).unwrap_or_else(|| panic!("the socket stays open while the episode runs: {seen:?}"));
            assert_eq!(m["type"], "elsewhere", "{m}");
            let done = m["accepted_agent_steps"] == step;
            seen.push(m);
            if done {
                break;
            }
        }
    }
    let last = seen.last().unwrap();
    assert_eq!(last["state"], "running", "{last}");
    assert!(last["required_stage_count"].as_i64().is_some_and(|r| r > 0), "the evaluator's stage count reaches the watcher: {last}");
    assert_eq!(last["steps"], "2");

    // The end: an `ended` message that names the review, then the socket closes.
    client.call_tool("finish_episode", json!({})).unwrap();
    let ended = loop {
        let m = next_text(&runtime, &mut socket, wait).expect("an ended message before the close");
        if m["type"] == "ended" {
            break m;
        }
        assert_eq!(m["type"], "elsewhere", "{m}");
    };
    assert!(ended["outcome"].is_string(), "{ended}");
    assert_eq!(ended["review_url"], format!("/episodes/{id}/review"));
    assert!(next_text(&runtime, &mut socket, wait).is_none(), "the socket closes after the end");
}

#[test]
fn an_episode_on_a_server_without_a_console_is_followed_from_the_store_without_a_dead_link() {
    use libero_server::client::{InProcessServer, prepare_episode};
    use libero_server::episodes::PrepareRequest;
    let pg = TestPostgres::start();
    let dir = tempfile::tempdir().unwrap();
    // What `libero-worker` and `run`'s own server are: MCP and the operator API, no pages.
    let slim = InProcessServer::start_with(dir.path().join("slim"), Some(pg.url.clone()), None, "test_finished").unwrap();
    let watcher = Server::start_with(&dir.path().join("watcher"), &["--store", &pg.url]);
    let req = PrepareRequest { level: 3, workspace: Some(dir.path().join("ws")), video: false, ..PrepareRequest::new("T14") };
    let id = prepare_episode(&slim.url, &req).unwrap().episode_id;
    let (status, page) = common::http_get_text(&format!("{}/episodes/{id}", watcher.url));
    assert_eq!(status, 200, "{page}");
    assert!(page.contains("id=\"no-live-view\"") && page.contains("/static/elsewhere.js"), "{page}");
    assert!(!page.contains(&slim.url), "no link to a server that has no pages: {page}");
    slim.stop_now().unwrap();
}
