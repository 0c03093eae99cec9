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
