//! A page per task and thumbnails made ahead, on real servers and in real chromium: `serve --thumbnails-ahead`
//! renders T14's and a pool entry's thumbnails (both cameras) into `<data>/thumbnails/` with no page asked for, a
//! restart on the same data directory reuses those files (the server reports nothing rendered; their mtimes do not
//! change); an expert plays one T14 episode on the restarted server and a hand-written batch records it; then
//! chromium (`tests/dashboard/task_pages_check.cjs`) checks the Tasks page's cards fit at 1280 and 1920 px, follows a
//! card to `/tasks/T14` (instruction, K, stages, both images loaded, teleop and back links, the episode, its batch
//! cell), opens a pool entry's page, the review page's task link and Stages table at 1400 px, the Results page's
//! task link, and times the warm Tasks page. (Unknown tasks' 404 is routes_in_process's.) Screenshots go to
//! `target/test-artifacts/task_pages/`. The expert sweep's notes and a thumbnail asked while its scene renders are
//! checked in process (`TestServer`); a thumbnail request whose connection closes needs a real socket.
mod common;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant, SystemTime};

use common::{Server, http_get_json, http_get_text};
use libero_testkit::server::TestServer;
use serde_json::Value;

/// The pool entry whose page is checked besides T14's (a stock LIBERO scene, K = 1).
const POOL_TASK: &str = "libero_90/35";
const POOL_INSTRUCTION: &str = "open the microwave";
/// What the server renders ahead in this test (two scenes; `all` would be ~200 on a software renderer).
const AHEAD: &str = "T14,libero_90/35";

/// The thumbnail files and their modification times.
fn cached(data: &Path) -> BTreeMap<String, SystemTime> {
    std::fs::read_dir(data.join("thumbnails"))
        .into_iter()
        .flatten()
        .flatten()
        .filter(|e| e.file_name().to_string_lossy().ends_with(".png"))
        .map(|e| (e.file_name().to_string_lossy().into_owned(), e.metadata().unwrap().modified().unwrap()))
        .collect()
}

/// `/api/thumbnails` once the background pass is done (fails after `limit`).
fn ahead_done(server: &Server, limit: Duration) -> Value {
    let start = Instant::now();
    loop {
        let (status, v) = http_get_json(&format!("{}/api/thumbnails", server.url));
        assert_eq!(status, 200, "{v}");
        if v["thumbnails"]["ahead_done"] == true {
            return v["thumbnails"].clone();
        }
        assert!(start.elapsed() < limit, "thumbnails not rendered ahead within {limit:?}: {v}");
        std::thread::sleep(Duration::from_millis(500));
    }
}

/// One T14 episode played by the scripted expert on `server`; its episode id.
fn play_t14(server: &Server) -> String {
    let v = common::expert_on_server(&server.url, "T14");
    v["episode_id"].as_str().map(str::to_owned).unwrap_or_else(|| panic!("no episode_id in {v}"))
}

/// A finished one-rollout T14 batch whose rollout is `episode`, under `<data>/batches/`.
fn write_batch(data: &Path, episode: &str) {
    let dir = data.join("batches/task-page");
    std::fs::create_dir_all(&dir).unwrap();
    let batch = serde_json::json!({
        "schema_version": "libero_agent.batch.v1", "status": "finished",
        "settings": {"experiment": "main", "harness": "command", "model": "expert", "effort": "high", "reps": 1,
            "tasks": [14], "seed": 100, "wall_time_s": 300.0, "max_agent_steps": 100, "agent_cmd": "true", "sandbox": false},
        "rollout_count": 1, "counts": {"done": 1, "running": 0, "left": 0}, "running": [], "outcomes": {"SUCCESS": 1},
    });
    std::fs::write(dir.join("batch.json"), batch.to_string()).unwrap();
    let r = serde_json::json!({
        "schema_version": "libero_agent.rollout.v1", "rollout_id": "w1_t14_level3", "task": "T14", "task_number": 14,
        "split": "short_horizon_easy", "stage_count": 1, "repetition": 1, "level": 3, "demo": "none",
        "outcome": "SUCCESS", "episode_id": episode, "completed_stages": 1, "wall_time_s": 30.0,
        "started_at": "2025-01-01T00:00:00Z", "finished_at": "2025-01-01T00:00:30Z",
    });
    std::fs::write(dir.join("rollouts.jsonl"), format!("{r}\n")).unwrap();
}

#[test]
fn task_pages_show_a_task_and_its_episodes_and_thumbnails_are_rendered_ahead_and_reused() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let artifacts = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("../test-artifacts/task_pages");
    std::fs::create_dir_all(&artifacts).unwrap();

    // 1. Rendered ahead at start, before any page asks: both cameras of both scenes.
    let mut server = Server::start_with(&data, &["--thumbnails-ahead", AHEAD]);
    let first = ahead_done(&server, Duration::from_secs(600));
    assert_eq!(first["rendered"], 2, "two scenes rendered ahead: {first}");
    let files = cached(&data);
    assert_eq!(files.len(), 4, "head and wrist of each scene: {files:?}");
    assert_eq!(files.keys().filter(|f| f.ends_with("-head.png")).count(), 2, "{files:?}");
    assert_eq!(files.keys().filter(|f| f.ends_with("-wrist.png")).count(), 2, "{files:?}");
    server.kill();

    // 2. A restart reuses them: nothing rendered, the files untouched.
    let server = Server::start_with(&data, &["--thumbnails-ahead", AHEAD]);
    let second = ahead_done(&server, Duration::from_secs(120));
    assert_eq!(second["rendered"], 0, "a restart renders nothing again: {second}");
    assert_eq!(second["reused"], 2, "{second}");
    assert_eq!(cached(&data), files, "the cached files were not rewritten");

    // 3. (Unknown tasks' 404 pages and a bad camera's 400 are routes_in_process's.) A finished T14 episode and a batch that records it.
    let episode = play_t14(&server);
    write_batch(&data, &episode);
    let (status, page) = http_get_text(&format!("{}/tasks/T14", server.url));
    assert_eq!(status, 200);
    assert!(page.contains(&episode), "the T14 page lists {episode}");

    // 4. In chromium.
    let last = common::browser_script(
        "task_pages_check.cjs",
        &[&server.url, &episode, POOL_TASK, POOL_INSTRUCTION, &artifacts.to_string_lossy()],
        &server.token,
    );
    assert_eq!(last["ok"], true, "{last}");
    eprintln!("task pages: {last}");
    // the pages asked for nothing but cached thumbnails of these two scenes
    let (_, v) = http_get_json(&format!("{}/api/thumbnails", server.url));
    assert_eq!(v["thumbnails"]["rendered"], 0, "{v}");
}

/// Copies the repository's `tasks/` folder (catalog, pool, definitions; not its results) to `to`.
fn copy_tasks(from: &Path, to: &Path) {
    for e in std::fs::read_dir(from).unwrap().flatten() {
        let (src, dst) = (e.path(), to.join(e.file_name()));
        if e.file_type().unwrap().is_dir() {
            if e.file_name() != "results" {
                std::fs::create_dir_all(&dst).unwrap();
                copy_tasks(&src, &dst);
            }
        } else {
            std::fs::copy(&src, &dst).unwrap();
        }
    }
}

/// The `<article>` of the Tasks page whose opening tag names `marker` (its id or data-id).
fn card<'a>(page: &'a str, marker: &str) -> &'a str {
    page.split("<article").find(|a| a.split('>').next().is_some_and(|tag| tag.contains(marker))).unwrap_or_else(|| panic!("no card {marker}"))
}

/// A page of the in-process server, asked with the operator token: (status, HTML).
async fn operator_page(server: &TestServer, path: &str) -> (u16, String) {
    let a = server.get_as_operator(path).await;
    (a.status, a.text())
}

/// The last expert sweep of the tasks folder (`results/expert_sweep.jsonl` and its `.meta.json`, as `libero-agent
/// expert --all` writes them) shows on the Tasks page's cards and on the task pages of the entries it
/// has, release tasks and pool entries alike, as "solved k/n on DATE at COMMIT"; an entry it lacks shows none. Asked of
/// the full router in process, with `LIBERO_AGENT_TASKS_DIR` naming a copy of the tasks folder (set before any thread
/// starts; nextest runs each test in a process of its own).
#[test]
fn the_expert_sweep_shows_on_the_task_pages_of_the_entries_it_covers_only() {
    let tasks = tempfile::tempdir().unwrap();
    copy_tasks(&libero_testkit::tasks_dir(), tasks.path());
    let results = tasks.path().join("results");
    std::fs::create_dir_all(&results).unwrap();
    let rows = [
        r#"{"task":"T14","suite":"release","runs":3,"successes":3,"expert":true,"actions":[76,76,76],"seconds":9.1}"#,
        r#"{"task":"libero_90/KITCHEN_SCENE7_open_the_microwave","entry":"libero_90/35","suite":"libero_90","runs":3,"successes":2,"expert":true,"seconds":20.0}"#,
    ];
    std::fs::write(results.join("expert_sweep.jsonl"), rows.join("\n") + "\n").unwrap();
    std::fs::write(results.join("expert_sweep.meta.json"), r#"{"date_utc":"2026-11-27T10:00:00Z","commit":"abc1234"}"#).unwrap();
    // SAFETY: the test's only thread so far; nothing reads the environment concurrently.
    unsafe { std::env::set_var("LIBERO_AGENT_TASKS_DIR", tasks.path()) };
    let runtime = tokio::runtime::Builder::new_multi_thread().enable_all().build().unwrap();
    runtime.block_on(async {
        let server = TestServer::start().await;

        let (status, page) = operator_page(&server, "/tasks").await;
        assert_eq!(status, 200, "{page}");
        assert!(card(&page, "id=\"T14\"").contains("solved 3/3 on 2026-11-27 at abc1234"), "{}", card(&page, "id=\"T14\""));
        assert!(!card(&page, "id=\"T01\"").contains("expert-sweep"), "T01 is not in the sweep: {}", card(&page, "id=\"T01\""));
        let (status, page) = operator_page(&server, "/tasks?suite=libero_90").await;
        assert_eq!(status, 200, "{page}");
        assert!(card(&page, &format!("data-id=\"{POOL_TASK}\"")).contains("solved 2/3 on 2026-11-27 at abc1234"), "{page}");

        let (status, page) = operator_page(&server, "/tasks/T14").await;
        assert_eq!(status, 200, "{page}");
        assert!(page.contains(r#"<dd id="expert-sweep">solved 3/3 on 2026-11-27 at abc1234</dd>"#), "{page}");
        let (_, page) = operator_page(&server, &format!("/tasks/{POOL_TASK}")).await;
        assert!(page.contains(r#"<dd id="expert-sweep">solved 2/3 on 2026-11-27 at abc1234</dd>"#), "{page}");
        let (status, page) = operator_page(&server, "/tasks/T01").await;
        assert_eq!(status, 200, "{page}");
        assert!(!page.contains("expert-sweep"), "T01 is not in the sweep: {page}");
    });
}

/// Page renders are served one at a time, and a thumbnail request whose page went away (the browser closed its
/// connection when the person navigated on) leaves the queue unrendered: with T14 rendering, three more requests
/// wait; closing them counts three cancelled and renders nothing more, T14's request still gets its PNG, and a
/// cancelled one asked again later renders normally.
#[test]
fn thumbnail_requests_whose_page_went_away_are_never_rendered() {
    use std::io::{Read, Write};
    let dir = tempfile::tempdir().unwrap();
    let server = Server::start(&dir.path().join("data"));
    let host = server.url.strip_prefix("http://").unwrap().to_owned();
    let ask = |id: &str| {
        let mut stream = std::net::TcpStream::connect(&host).unwrap();
        stream.set_read_timeout(Some(Duration::from_secs(600))).unwrap();
        let head = format!(
            "GET /tasks/{id}/thumbnail.png HTTP/1.1\r\nHost: {host}\r\nConnection: close\r\nAuthorization: Bearer {}\r\n\r\n",
            server.token
        );
        stream.write_all(head.as_bytes()).unwrap();
        stream
    };
    let stats = || http_get_json(&format!("{}/api/thumbnails", server.url)).1["thumbnails"].clone();
    let wait_for = |what: &str, done: &dyn Fn(&Value) -> bool| {
        let start = Instant::now();
        loop {
            let s = stats();
            if done(&s) {
                return s;
            }
            assert!(start.elapsed() < Duration::from_secs(300), "{what} within 300 s: {s}");
            std::thread::sleep(Duration::from_millis(50));
        }
    };

    let mut first = ask("T14");
    wait_for("T14 rendering", &|s| s["on_demand_rendering"] == 1);
    let left: Vec<_> = ["T15", "T17", "T21"].into_iter().map(ask).collect();
    wait_for("three requests waiting behind T14", &|s| s["on_demand_waiting"] == 3);
    drop(left);
    let s = wait_for("the three closed requests cancelled", &|s| s["on_demand_cancelled"] == 3 && s["on_demand_waiting"] == 0);
    assert_eq!(s["on_demand_rendering"], 1, "T14 still rendering while the others leave: {s}");

    let mut reply = Vec::new();
    first.read_to_end(&mut reply).unwrap();
    assert!(reply.starts_with(b"HTTP/1.1 200"), "{}", String::from_utf8_lossy(&reply[..reply.len().min(200)]));
    assert!(reply.windows(4).any(|w| w == b"\x89PNG"), "T14's reply is a PNG");
    let s = wait_for("T14's render finished", &|s| s["on_demand_rendering"] == 0);
    assert_eq!(s["rendered"], 1, "only T14 was rendered: {s}");

    let bearer = format!("Bearer {}", server.token);
    let (status, _, png) = common::http("GET", &format!("{}/tasks/T15/thumbnail.png", server.url), &[("Authorization", &bearer)], &[]);
    assert_eq!(status, 200);
    assert!(png.starts_with(b"\x89PNG"));
    let s = stats();
    assert_eq!((s["rendered"].as_u64(), s["on_demand_cancelled"].as_u64()), (Some(2), Some(3)), "{s}");
}

/// Issue 49, item 9: a page asking for a thumbnail whose scene is being rendered right now gets it with that render,
/// not after the renders queued before it. Three page requests on a fresh data directory (no pass ahead), asked of
/// the full router in process at once: the head view of libero_90/35, then T14's, then libero_90/35's wrist view
/// while its scene still renders. The wrist view comes with the first render, before T14's (which waits for its turn
/// and renders after); the scene of libero_90/35 is rendered once.
#[tokio::test(flavor = "multi_thread")]
async fn a_thumbnail_of_a_scene_rendering_now_comes_with_that_render_not_after_the_queue() {
    let server = std::sync::Arc::new(TestServer::start().await);
    let t0 = Instant::now();
    let ask = |path: &'static str, after_ms: u64| {
        let server = server.clone();
        tokio::spawn(async move {
            tokio::time::sleep(Duration::from_millis(after_ms)).await;
            let a = server.get_as_operator(path).await;
            (a.status, a.body.len(), t0.elapsed())
        })
    };
    let head = ask("/tasks/libero_90/35/thumbnail.png", 0);
    let other = ask("/tasks/T14/thumbnail.png", 300);
    let wrist = ask("/tasks/libero_90/35/thumbnail.png?camera=wrist", 600);
    let (head, other, wrist) = (head.await.unwrap(), other.await.unwrap(), wrist.await.unwrap());
    for (what, (status, len, _)) in [("head", head), ("T14", other), ("wrist", wrist)] {
        assert!(status == 200 && len > 1000, "{what}: {status}, {len} bytes");
    }
    // T14's scene takes seconds to set up and render; the wrist view must not wait for any of it.
    assert!(wrist.2 + Duration::from_millis(500) < other.2, "the wrist view ({:?}) waited behind T14's render ({:?})", wrist.2, other.2);
    let stats = server.get_as_operator("/api/thumbnails").await.json();
    assert_eq!(stats["thumbnails"]["rendered"], 2, "two scenes rendered, libero_90/35 once: {stats}");
}
