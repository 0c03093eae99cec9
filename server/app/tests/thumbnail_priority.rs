//! Issue 49, item 9: a page asking for a thumbnail whose scene is being rendered right now gets it with that render,
//! not after the renders queued before it. Three page requests on a fresh data directory (no pass ahead): the head
//! view of libero_90/35, then T14's, then libero_90/35's wrist view while its scene still renders. The wrist view
//! comes with the first render, before T14's (which waits for its turn and renders after); the scene of
//! libero_90/35 is rendered once.
use std::time::{Duration, Instant};

mod common;
use common::{Server, http, http_get_json};

#[test]
fn a_thumbnail_of_a_scene_rendering_now_comes_with_that_render_not_after_the_queue() {
    let dir = tempfile::tempdir().unwrap();
    let server = Server::start(&dir.path().join("data"));
    let t0 = Instant::now();
    let ask = |path: &'static str, after_ms: u64| {
        let (url, auth) = (format!("{}{path}", server.url), format!("Bearer {}", server.token));
        std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(after_ms));
            let (status, _, body) = http("GET", &url, &[("Authorization", &auth)], b"");
            (status, body.len(), t0.elapsed())
        })
    };
    let head = ask("/tasks/libero_90/35/thumbnail.png", 0);
    let other = ask("/tasks/T14/thumbnail.png", 300);
    let wrist = ask("/tasks/libero_90/35/thumbnail.png?camera=wrist", 600);
    let (head, other, wrist) = (head.join().unwrap(), other.join().unwrap(), wrist.join().unwrap());
    for (what, (status, len, _)) in [("head", head), ("T14", other), ("wrist", wrist)] {
        assert!(status == 200 && len > 1000, "{what}: {status}, {len} bytes");
    }
    // T14's scene takes seconds to set up and render; the wrist view must not wait for any of it.
    assert!(wrist.2 + Duration::from_millis(500) < other.2, "the wrist view ({:?}) waited behind T14's render ({:?})", wrist.2, other.2);
    let (_, stats) = http_get_json(&format!("{}/api/thumbnails", server.url));
    assert_eq!(stats["thumbnails"]["rendered"], 2, "two scenes rendered, libero_90/35 once: {stats}");
}
