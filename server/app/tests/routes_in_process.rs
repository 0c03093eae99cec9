//! Every route of `libero-agent serve` (the operator API, MCP, login and the browser console), called in process
//! through the full router (`libero_testkit::server::TestServer`: the same `router` and console `serve` runs, over a
//! throwaway data directory, no child process and no socket). Each route is exercised for its answer to a valid
//! request where that is cheap (pages render with the navigation, JSON carries its fields), its refusal without the
//! operator token where it is operator-only (401 for the API and sockets, a redirect to the login form for pages),
//! and a clear 4xx for bad input whose body says why.
//!
//! [`ROUTES`] names, for every `.route("…")` of `server/server/src` and `server/dashboard/src`, the test here that
//! covers it; `every_route_of_the_sources_has_an_in_process_test` fails on a route missing from it, so a new route
//! comes with its test. What needs a real connection (WebSocket sessions, connection limits, restarts, signals)
//! stays with the tests that spawn the binary.
use libero_testkit::server::{Answer, Method, TestServer};
use serde_json::json;

/// Each route of the sources and the test of this file that covers it.
const ROUTES: &[(&str, &str)] = &[
    ("/api/health", "health_login_static_files_and_the_icon_are_open_to_anyone"),
    ("/login", "health_login_static_files_and_the_icon_are_open_to_anyone"),
    ("/static/{file}", "health_login_static_files_and_the_icon_are_open_to_anyone"),
    ("/favicon.ico", "health_login_static_files_and_the_icon_are_open_to_anyone"),
    ("/mcp/{id}", "an_episode_is_prepared_read_reviewed_and_aborted_through_its_routes"),
    ("/api/episodes", "an_episode_is_prepared_read_reviewed_and_aborted_through_its_routes"),
    ("/api/episodes/{id}", "an_episode_is_prepared_read_reviewed_and_aborted_through_its_routes"),
    ("/api/episodes/{id}/video", "an_episode_is_prepared_read_reviewed_and_aborted_through_its_routes"),
    ("/api/episodes/{id}/result", "an_episode_is_prepared_read_reviewed_and_aborted_through_its_routes"),
    ("/api/episodes/{id}/abort", "an_episode_is_prepared_read_reviewed_and_aborted_through_its_routes"),
    ("/api/episodes/{id}/forfeit", "an_episode_is_prepared_read_reviewed_and_aborted_through_its_routes"),
    ("/api/episodes/{id}/agent/events", "an_episode_is_prepared_read_reviewed_and_aborted_through_its_routes"),
    ("/api/episodes/{id}/review", "an_episode_is_prepared_read_reviewed_and_aborted_through_its_routes"),
    ("/api/episodes/{id}/agent", "an_episode_is_prepared_read_reviewed_and_aborted_through_its_routes"),
    ("/api/episodes/{id}/moment", "an_episode_is_prepared_read_reviewed_and_aborted_through_its_routes"),
    ("/api/episodes/{id}/stages", "an_episode_is_prepared_read_reviewed_and_aborted_through_its_routes"),
    ("/api/episodes/{id}/finish", "a_teleop_episode_starts_and_is_finished_and_judged"),
    ("/episodes/{id}", "an_episode_is_prepared_read_reviewed_and_aborted_through_its_routes"),
    ("/episodes/{id}/review", "an_episode_is_prepared_read_reviewed_and_aborted_through_its_routes"),
    ("/episodes/{id}/video.mp4", "an_episode_is_prepared_read_reviewed_and_aborted_through_its_routes"),
    ("/episodes/{id}/observations/{*path}", "an_episode_is_prepared_read_reviewed_and_aborted_through_its_routes"),
    ("/api/thumbnails", "the_apis_lists_answer_json_with_their_fields"),
    ("/api/tasks", "the_apis_lists_answer_json_with_their_fields"),
    ("/api/demos", "the_apis_lists_answer_json_with_their_fields"),
    ("/api/results", "a_registered_batch_is_listed_by_the_results_routes"),
    ("/api/batches", "a_registered_batch_is_listed_by_the_results_routes"),
    ("/results", "a_registered_batch_is_listed_by_the_results_routes"),
    ("/results/report/{format}", "a_registered_batch_is_listed_by_the_results_routes"),
    ("/results/logs/{batch}/{rollout}", "a_registered_batch_is_listed_by_the_results_routes"),
    ("/results/logs/{batch}/{rollout}/{file}", "a_registered_batch_is_listed_by_the_results_routes"),
    ("/", "the_console_pages_render_with_the_navigation"),
    ("/tasks", "the_console_pages_render_with_the_navigation"),
    ("/tasks/{id}", "the_console_pages_render_with_the_navigation"),
    ("/tasks/{suite}/{task_id}", "the_console_pages_render_with_the_navigation"),
    ("/teleop/{task}", "the_console_pages_render_with_the_navigation"),
    ("/teleop/{suite}/{task_id}", "the_console_pages_render_with_the_navigation"),
    ("/demos", "the_console_pages_render_with_the_navigation"),
    ("/tasks/{id}/thumbnail.png", "thumbnails_refuse_unknown_tasks_and_cameras"),
    ("/tasks/{suite}/{task_id}/thumbnail.png", "thumbnails_refuse_unknown_tasks_and_cameras"),
    ("/api/teleop", "a_teleop_episode_starts_and_is_finished_and_judged"),
    ("/api/teleop/{id}/save", "teleop_and_demo_routes_refuse_bad_bodies_and_unknown_bundles"),
    ("/api/demos/export", "teleop_and_demo_routes_refuse_bad_bodies_and_unknown_bundles"),
    ("/api/demos/{task}/{bundle}/verify", "teleop_and_demo_routes_refuse_bad_bodies_and_unknown_bundles"),
    ("/api/demos/{task}/{bundle}/delete", "teleop_and_demo_routes_refuse_bad_bodies_and_unknown_bundles"),
    ("/demos/{task}/{bundle}/video.mp4", "teleop_and_demo_routes_refuse_bad_bodies_and_unknown_bundles"),
    ("/ws/episodes", "sockets_refuse_a_request_that_is_no_upgrade"),
    ("/ws/episodes/{id}", "sockets_refuse_a_request_that_is_no_upgrade"),
    ("/ws/teleop/{id}", "sockets_refuse_a_request_that_is_no_upgrade"),
];

/// An episode id of the right form that no server has.
const NOBODY: &str = "ep-20990101T000000Z-none";

/// One request of each operator-only route, with whether it is a page (a redirect to the login form without the
/// token) or an API or socket (401).
const OPERATOR_ONLY: &[(&str, &str)] = &[
    ("GET", "/"),
    ("GET", "/tasks"),
    ("GET", "/tasks/T14"),
    ("GET", "/tasks/libero_90/35"),
    ("GET", "/tasks/T14/thumbnail.png"),
    ("GET", "/tasks/libero_90/35/thumbnail.png"),
    ("GET", "/teleop/T14"),
    ("GET", "/teleop/libero_90/35"),
    ("GET", "/demos"),
    ("GET", "/demos/T14/ep-x/video.mp4"),
    ("GET", "/results"),
    ("GET", "/results/report/csv"),
    ("GET", "/results/logs/b/r"),
    ("GET", "/results/logs/b/r/stdout"),
    ("GET", "/episodes/ep-20990101T000000Z-none"),
    ("GET", "/episodes/ep-20990101T000000Z-none/review"),
    ("GET", "/episodes/ep-20990101T000000Z-none/video.mp4"),
    ("GET", "/episodes/ep-20990101T000000Z-none/observations/a/b.jpg"),
    ("GET", "/api/episodes"),
    ("POST", "/api/episodes"),
    ("GET", "/api/episodes/ep-20990101T000000Z-none"),
    ("GET", "/api/episodes/ep-20990101T000000Z-none/video"),
    ("GET", "/api/episodes/ep-20990101T000000Z-none/result"),
    ("POST", "/api/episodes/ep-20990101T000000Z-none/abort"),
    ("POST", "/api/episodes/ep-20990101T000000Z-none/forfeit"),
    ("POST", "/api/episodes/ep-20990101T000000Z-none/finish"),
    ("POST", "/api/episodes/ep-20990101T000000Z-none/agent/events"),
    ("GET", "/api/episodes/ep-20990101T000000Z-none/review"),
    ("GET", "/api/episodes/ep-20990101T000000Z-none/agent"),
    ("GET", "/api/episodes/ep-20990101T000000Z-none/moment?step=0"),
    ("GET", "/api/episodes/ep-20990101T000000Z-none/stages"),
    ("POST", "/api/episodes/ep-20990101T000000Z-none/stages"),
    ("GET", "/api/thumbnails"),
    ("GET", "/api/tasks"),
    ("GET", "/api/results"),
    ("POST", "/api/batches"),
    ("POST", "/api/teleop"),
    ("POST", "/api/teleop/ep-20990101T000000Z-none/save"),
    ("GET", "/api/demos"),
    ("POST", "/api/demos/export"),
    ("POST", "/api/demos/T14/ep-x/verify"),
    ("POST", "/api/demos/T14/ep-x/delete"),
    ("GET", "/ws/episodes"),
    ("GET", "/ws/episodes/ep-20990101T000000Z-none"),
    ("GET", "/ws/teleop/ep-20990101T000000Z-none"),
];

/// A page of the console: 200, HTML, the navigation.
fn assert_page(a: &Answer, path: &str) -> String {
    let body = a.text();
    assert_eq!(a.status, 200, "{path}: {body}");
    assert!(a.header("content-type").is_some_and(|t| t.starts_with("text/html")), "{path} is a page: {:?}", a.headers);
    assert!(has_navigation(&body), "{path} carries the navigation: {body}");
    body
}

fn has_navigation(body: &str) -> bool {
    body.contains("<nav>") && ["/", "/tasks", "/results", "/demos"].iter().all(|href| body.contains(&format!("href=\"{href}\"")))
}

/// An error page of the console: `status`, HTML with the navigation, the message saying `words`.
fn assert_error_page(a: &Answer, status: u16, words: &str, path: &str) {
    let body = a.text();
    assert_eq!(a.status, status, "{path}: {body}");
    assert!(a.header("content-type").is_some_and(|t| t.starts_with("text/html")), "{path} answers a page: {:?}", a.headers);
    assert!(has_navigation(&body), "{path}'s error page carries the navigation: {body}");
    assert!(body.contains("id=\"error-message\"") && body.contains(words), "{path} says why ({words}): {body}");
}

/// An error answer of the API: `status`, `{"ok": false, "error": "…words…"}`.
fn assert_refused(a: &Answer, status: u16, words: &str, what: &str) {
    assert_eq!(a.status, status, "{what}: {}", a.text());
    let v = a.json();
    assert_eq!(v["ok"], false, "{what}: {v}");
    let error = v["error"].as_str().unwrap_or_else(|| panic!("{what}: no error message: {v}"));
    assert!(error.contains(words), "{what} says why ({words}): {error}");
}

/// A query the route's extractor cannot read: 400 as every bad request, `{"ok": false, "error": …}` with axum's
/// words naming the field (not axum's plain text, which scripts reading `error` could not read).
fn assert_rejected(a: &Answer, words: &str, what: &str) {
    assert_refused(a, 400, "Failed to deserialize query string", what);
    assert!(a.json()["error"].as_str().is_some_and(|e| e.contains(words)), "{what} says why ({words}): {}", a.text());
}

#[tokio::test(flavor = "multi_thread")]
async fn every_operator_route_refuses_a_request_without_the_token() {
    let server = TestServer::start().await;
    for (method, path) in OPERATOR_ONLY {
        let a = match *method {
            "GET" => server.get(path).await,
            _ => server.post_json(path, &json!({})).await,
        };
        let api = path.starts_with("/api/") || path.starts_with("/ws/");
        if api || *method == "POST" {
            assert_refused(&a, 401, "operator token required", &format!("{method} {path} without the token"));
            assert_eq!(a.header("www-authenticate"), Some("Bearer"), "{method} {path}");
        } else {
            assert_eq!(a.status, 303, "{method} {path} without the token leads to the login form: {}", a.text());
            assert_eq!(a.header("location"), Some("/login"), "{method} {path}");
        }
        // A wrong token opens nothing either.
        let wrong = server.send(axum_method(method), path, &[("authorization", "Bearer not-the-operator-token-at-all")], Vec::new()).await;
        assert!(matches!(wrong.status, 303 | 401), "{method} {path} with a wrong token: {} {}", wrong.status, wrong.text());
    }
    // Another site's page cannot use the operator's credential.
    let a = server
        .send(axum_method("GET"), "/api/episodes", &[("authorization", &format!("Bearer {}", server.token())), ("origin", "http://evil.example")], Vec::new())
        .await;
    assert_refused(&a, 403, "cross-site", "a cross-site request");
    // And a request naming another host is refused before anything else.
    let a = server.send(axum_method("GET"), "/api/health", &[("host", "evil.example")], Vec::new()).await;
    assert_refused(&a, 421, "does not answer to Host", "a request for another host");
}

fn axum_method(m: &str) -> Method {
    m.parse().unwrap()
}

#[tokio::test(flavor = "multi_thread")]
async fn health_login_static_files_and_the_icon_are_open_to_anyone() {
    let server = TestServer::start().await;
    let health = server.get("/api/health").await.json();
    assert_eq!(health["ok"], true, "{health}");
    assert_eq!(health["episodes"], 0, "{health}");
    assert_eq!(health["version"], env!("CARGO_PKG_VERSION"), "{health}");

    let login = server.get("/login").await;
    assert_eq!(login.status, 200, "{}", login.text());
    assert!(login.text().contains("<form") && login.text().contains("name=\"token\""), "{}", login.text());
    // A wrong token: the form again, saying so; the right one: a session cookie and the home page.
    let form = |token: &str| format!("token={token}").into_bytes();
    let ctype = [("content-type", "application/x-www-form-urlencoded")];
    let wrong = server.send(axum_method("POST"), "/login", &ctype, form("wrong-token-wrong-token")).await;
    assert_eq!(wrong.status, 401, "{}", wrong.text());
    assert!(wrong.text().contains("<form"), "{}", wrong.text());
    let right = server.send(axum_method("POST"), "/login", &ctype, form(server.token())).await;
    assert_eq!(right.status, 303, "{}", right.text());
    assert_eq!(right.header("location"), Some("/"));
    let cookie = right.header("set-cookie").expect("a session cookie").split(';').next().unwrap().to_owned();
    assert!(cookie.contains('='), "{cookie}");
    let home = server.send(axum_method("GET"), "/", &[("cookie", &cookie)], Vec::new()).await;
    assert_page(&home, "/ with the session cookie");
    let bad = server.send(axum_method("POST"), "/login", &ctype, b"nothing=here".to_vec()).await;
    assert!(bad.status == 400 || bad.status == 422, "a form without the token is refused: {} {}", bad.status, bad.text());
    assert!(bad.text().contains("token"), "it says the token is missing: {}", bad.text());

    let css = server.get("/static/style.css").await;
    assert_eq!(css.status, 200);
    assert!(css.header("content-type").is_some_and(|t| t.starts_with("text/css")), "{:?}", css.headers);
    assert!(css.text().contains('{'), "a style sheet");
    let js = server.get("/static/common.js").await;
    assert!(js.status == 200 && js.header("content-type").is_some_and(|t| t.starts_with("text/javascript")), "{:?}", js.headers);
    assert_error_page(&server.get("/static/nothing.js").await, 404, "no such file", "/static/nothing.js");

    let icon = server.get("/favicon.ico").await;
    assert_eq!(icon.status, 200);
    assert_eq!(icon.header("content-type"), Some("image/x-icon"));
    assert_eq!(&icon.body[..4], &[0, 0, 1, 0], "an ICO file");

    // Unknown addresses: a page for browsers, JSON for scripts.
    assert_error_page(&server.get_as_operator("/no/such/page").await, 404, "no page at this address", "/no/such/page");
    assert_refused(&server.get_as_operator("/api/no-such-route").await, 404, "no route GET /api/no-such-route", "/api/no-such-route");
}

#[tokio::test(flavor = "multi_thread")]
async fn the_console_pages_render_with_the_navigation() {
    let server = TestServer::start().await;
    let home = assert_page(&server.get_as_operator("/").await, "/");
    assert!(home.contains("T14"), "the home page offers the release tasks: {home}");
    let filtered = assert_page(&server.get_as_operator("/?outcome=RUNNING&task=T14").await, "/?outcome=RUNNING");
    assert!(filtered.contains("RUNNING"), "{filtered}");
    assert_error_page(&server.get_as_operator("/?outcome=WHATEVER").await, 400, "outcome must be one of", "/?outcome=WHATEVER");

    let tasks = assert_page(&server.get_as_operator("/tasks").await, "/tasks");
    assert!(tasks.contains("of the 30 release tasks"), "{tasks}");
    let suite = assert_page(&server.get_as_operator("/tasks?tasks=libero_90").await, "/tasks?tasks=libero_90");
    assert!(suite.contains("registered entries"), "{suite}");
    let bad = server.get_as_operator("/tasks?tasks=no_such_suite").await;
    assert_eq!(bad.status, 400, "{}", bad.text());
    assert!(has_navigation(&bad.text()) && bad.text().contains("no_such_suite"), "the page says which selection fails: {}", bad.text());

    let t14 = assert_page(&server.get_as_operator("/tasks/T14").await, "/tasks/T14");
    assert!(t14.contains("T14"), "{t14}");
    assert_page(&server.get_as_operator("/tasks/libero_90/35").await, "/tasks/libero_90/35");
    for unknown in ["/tasks/T99", "/tasks/libero_90/9999", "/tasks/no_such_suite/1"] {
        let a = server.get_as_operator(unknown).await;
        assert_eq!(a.status, 404, "{unknown}: {}", a.text());
        assert!(has_navigation(&a.text()) && a.text().contains("id=\"error-message\""), "{unknown}: {}", a.text());
    }

    let teleop = assert_page(&server.get_as_operator("/teleop/T14").await, "/teleop/T14");
    assert!(teleop.contains("T14"), "{teleop}");
    assert_page(&server.get_as_operator("/teleop/libero_90/35").await, "/teleop/libero_90/35");
    assert_error_page(&server.get_as_operator("/teleop/T999").await, 404, "T999", "/teleop/T999");
    assert_error_page(&server.get_as_operator("/teleop/libero_90/9999").await, 404, "libero_90/9999", "/teleop/libero_90/9999");
    assert_error_page(&server.get_as_operator("/teleop/T14?branch=x").await, 400, "a branch needs", "/teleop/T14?branch=x");
    // a query the page cannot read gets the error page too, naming the field (not axum's bare text)
    assert_error_page(&server.get_as_operator("/teleop/T14?step=soon").await, 400, "step: invalid digit", "/teleop/T14?step=soon");
    let branch = format!("/teleop/T14?branch={NOBODY}&step=3");
    assert_error_page(&server.get_as_operator(&branch).await, 404, "to branch from", &branch);

    assert_page(&server.get_as_operator("/demos").await, "/demos");
}

#[tokio::test(flavor = "multi_thread")]
async fn the_apis_lists_answer_json_with_their_fields() {
    let server = TestServer::start().await;
    let list = server.get_as_operator("/api/episodes").await.json();
    assert_eq!(list, json!({"ok": true, "episodes": []}));
    assert_rejected(&server.get_as_operator("/api/episodes?limit=many").await, "limit: invalid digit", "?limit=many");

    let tasks = server.get_as_operator("/api/tasks").await.json();
    assert_eq!(tasks["ok"], true, "{tasks}");
    let cards = tasks["tasks"].as_array().expect("tasks");
    assert_eq!(cards.len(), 30, "the 30 release tasks");
    assert!(cards.iter().any(|c| c["id"] == "T14"), "{tasks}");

    let thumbs = server.get_as_operator("/api/thumbnails").await.json();
    assert_eq!(thumbs["ok"], true, "{thumbs}");
    assert_eq!(thumbs["thumbnails"]["rendered"], 0, "nothing rendered ahead in process: {thumbs}");

    let demos = server.get_as_operator("/api/demos").await.json();
    assert_eq!(demos, json!({"ok": true, "bundles": []}));
}

#[tokio::test(flavor = "multi_thread")]
async fn thumbnails_refuse_unknown_tasks_and_cameras() {
    let server = TestServer::start().await;
    for path in ["/tasks/T14/thumbnail.png?camera=depth", "/tasks/libero_90/35/thumbnail.png?camera=top"] {
        assert_error_page(&server.get_as_operator(path).await, 400, "camera must be head or wrist", path);
    }
    for path in ["/tasks/T99/thumbnail.png", "/tasks/libero_90/9999/thumbnail.png"] {
        let a = server.get_as_operator(path).await;
        assert_eq!(a.status, 404, "{path}: {}", a.text());
        assert!(a.text().contains("id=\"error-message\""), "{path}: {}", a.text());
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn teleop_and_demo_routes_refuse_bad_bodies_and_unknown_bundles() {
    let server = TestServer::start().await;
    let bearer = format!("Bearer {}", server.token());
    let a = server.send(axum_method("POST"), "/api/teleop", &[("authorization", &bearer)], b"not json".to_vec()).await;
    assert_refused(&a, 400, "body must be", "POST /api/teleop with no JSON");
    assert_refused(&server.post_json_as_operator("/api/teleop", &json!({"task": "T99"})).await, 422, "T99", "a teleop of an unknown task");
    let save = format!("/api/teleop/{NOBODY}/save");
    assert_refused(&server.post_json_as_operator(&save, &json!({})).await, 404, "is not an operator episode", &save);

    assert_refused(&server.post_json_as_operator("/api/demos/export", &json!({"bundles": []})).await, 400, "choose at least one bundle", "an empty export");
    assert_refused(&server.post_json_as_operator("/api/demos/export", &json!({"nothing": 1})).await, 400, "body must be", "an export without bundles");
    assert_refused(&server.post_json_as_operator("/api/demos/export", &json!({"bundles": ["T14/ep-x"]})).await, 404, "no bundle T14/ep-x", "an unknown bundle's export");
    for action in ["verify", "delete"] {
        let path = format!("/api/demos/T14/ep-x/{action}");
        assert_refused(&server.post_json_as_operator(&path, &json!({})).await, 404, "no such bundle", &path);
    }
    assert_error_page(&server.get_as_operator("/demos/T14/ep-x/video.mp4").await, 404, "no such bundle", "a bundle's video");
}

#[tokio::test(flavor = "multi_thread")]
async fn sockets_refuse_a_request_that_is_no_upgrade() {
    let server = TestServer::start().await;
    for path in ["/ws/episodes".to_owned(), format!("/ws/episodes/{NOBODY}"), format!("/ws/teleop/{NOBODY}")] {
        let a = server.get_as_operator(&path).await;
        assert!((400..500).contains(&a.status), "{path} without an upgrade: {} {}", a.status, a.text());
        assert!(a.text().to_lowercase().contains("upgrade"), "{path} says it wants an upgrade: {}", a.text());
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn an_episode_is_prepared_read_reviewed_and_aborted_through_its_routes() {
    let server = TestServer::start().await;
    assert_refused(&server.post_json_as_operator("/api/episodes", &json!({"task": 14})).await, 400, "invalid prepare request", "a task that is no string");
    assert_refused(&server.post_json_as_operator("/api/episodes", &json!({"task": "T99", "video": false})).await, 422, "T99", "an unknown task");
    let prepared = server.post_json_as_operator("/api/episodes", &json!({"task": "T14", "video": false, "batch": "in-process"})).await;
    assert_eq!(prepared.status, 201, "{}", prepared.text());
    let prepared = prepared.json();
    let id = prepared["episode_id"].as_str().expect("episode_id").to_owned();
    assert_eq!(prepared["task"], "T14", "{prepared}");
    assert!(prepared["mcp_url"].as_str().is_some_and(|u| u.ends_with(&format!("/mcp/{id}"))), "{prepared}");
    let episode_bearer = prepared["mcp_headers"]["Authorization"].as_str().expect("the episode's bearer").to_owned();

    // The operator API: the list and the row, with the live state while the server runs it.
    let list = server.get_as_operator("/api/episodes?limit=5").await.json();
    assert!(list["episodes"].as_array().unwrap().iter().any(|e| e["id"] == id.as_str()), "{list}");
    let row = server.get_as_operator(&format!("/api/episodes/{id}")).await.json();
    assert_eq!((row["id"].as_str(), row["task_ref"].as_str(), row["batch"].as_str()), (Some(id.as_str()), Some("T14"), Some("in-process")), "{row}");
    assert!(row["state"].is_string() && row["outcome"].is_null(), "an open episode: {row}");
    assert!(row.get("run_dir").is_none() && row.get("workspace").is_none(), "no paths in the API: {row}");
    assert_refused(&server.get_as_operator(&format!("/api/episodes/{NOBODY}")).await, 404, NOBODY, "an unknown episode");
    let video = server.get_as_operator(&format!("/api/episodes/{id}/video")).await.json();
    assert_eq!(video, json!({"video": false, "video_status": null}), "an episode without a video");
    assert_refused(&server.get_as_operator(&format!("/api/episodes/{NOBODY}/video")).await, 404, NOBODY, "an unknown episode's video");
    // The result a runner on another machine classifies: none while the episode is open.
    let result = server.get_as_operator(&format!("/api/episodes/{id}/result")).await.json();
    assert_eq!(result, json!({"ok": true, "result": null}), "an open episode has no result");
    assert_refused(&server.get_as_operator(&format!("/api/episodes/{NOBODY}/result")).await, 404, NOBODY, "an unknown episode's result");

    // The live and review pages, and the review's data.
    let live = assert_page(&server.get_as_operator(&format!("/episodes/{id}")).await, "the live page");
    assert!(live.contains(&id) && live.contains("T14"), "{live}");
    assert_error_page(&server.get_as_operator(&format!("/episodes/{NOBODY}")).await, 404, NOBODY, "an unknown episode's live page");
    assert_error_page(&server.get_as_operator("/episodes/bad..id").await, 404, "no such episode", "a malformed id");
    let review = assert_page(&server.get_as_operator(&format!("/episodes/{id}/review")).await, "the review page");
    assert!(review.contains(&id), "{review}");
    assert_error_page(&server.get_as_operator(&format!("/episodes/{NOBODY}/review")).await, 404, NOBODY, "an unknown review");
    let undecodable = server.get_as_operator("/episodes/%FF/review").await;
    assert_eq!(undecodable.status, 400, "{}", undecodable.text());
    assert!(has_navigation(&undecodable.text()) && undecodable.text().contains("id=\"error-message\""), "{}", undecodable.text());
    // A gzip-accepting browser gets the error page too (error answers are not compressed before they become pages).
    let bearer = format!("Bearer {}", server.token());
    let gzip = server.send(axum_method("GET"), &format!("/episodes/{NOBODY}/review"), &[("authorization", &bearer), ("accept-encoding", "gzip")], Vec::new()).await;
    assert_error_page(&gzip, 404, NOBODY, "an unknown review asked with gzip");
    // And a page that succeeds is compressed for it.
    let gzipped = server.send(axum_method("GET"), &format!("/episodes/{id}/review"), &[("authorization", &bearer), ("accept-encoding", "gzip")], Vec::new()).await;
    assert_eq!((gzipped.status, gzipped.header("content-encoding")), (200, Some("gzip")), "{:?}", gzipped.headers);
    let data = server.get_as_operator(&format!("/api/episodes/{id}/review")).await.json();
    assert_eq!(data["ok"], true, "{data}");
    for key in ["stage_events", "calls", "telemetry", "video", "video_status", "result"] {
        assert!(data.get(key).is_some(), "the review data has {key}: {data}");
    }
    let calls = server.get_as_operator(&format!("/api/episodes/{id}/review?part=calls")).await.json();
    assert_eq!(calls["calls"], json!([]), "no call yet: {calls}");
    assert_refused(&server.get_as_operator(&format!("/api/episodes/{id}/review?part=everything")).await, 400, "part must be calls, telemetry or video", "a bad part");
    assert_rejected(&server.get_as_operator(&format!("/api/episodes/{id}/review?from=minus")).await, "from: invalid digit", "a bad line number");
    let agent = server.get_as_operator(&format!("/api/episodes/{id}/agent")).await.json();
    assert_eq!((agent["ok"].as_bool(), agent["timeline"].as_array().map(Vec::len)), (Some(true), Some(0)), "{agent}");
    assert_refused(&server.get_as_operator(&format!("/api/episodes/{NOBODY}/agent")).await, 404, NOBODY, "an unknown episode's transcript");

    // A transcript's events from a runner elsewhere.
    let events = format!("/api/episodes/{id}/agent/events");
    assert_refused(&server.post_json_as_operator(&events, &json!({"lines": []})).await, 400, "body must be {\"events\"", "events without events");
    let added = server.post_json_as_operator(&events, &json!({"events": []})).await;
    assert_eq!(added.status, 200, "{}", added.text());
    let nobody_events = format!("/api/episodes/{NOBODY}/agent/events");
    assert_refused(&server.post_json_as_operator(&nobody_events, &json!({"events": []})).await, 404, "episode", "an unknown episode's events");

    // Media of an episode without a video, observations, moments, stages.
    assert_error_page(&server.get_as_operator(&format!("/episodes/{id}/video.mp4")).await, 404, "this episode records no video", "the video");
    assert_error_page(&server.get_as_operator(&format!("/episodes/{NOBODY}/video.mp4")).await, 404, NOBODY, "an unknown episode's video");
    for path in [format!("/episodes/{id}/observations/nothing/head.jpg"), format!("/episodes/{id}/observations/..%2F..%2Fepisode.json")] {
        assert_error_page(&server.get_as_operator(&path).await, 404, "no such observation file", &path);
    }
    let moment = format!("/api/episodes/{id}/moment");
    assert_refused(&server.get_as_operator(&moment).await, 400, "step must be a control step number", "a moment without its step");
    assert_refused(&server.get_as_operator(&format!("{moment}?step=soon")).await, 400, "(got \"soon\")", "a moment at no step");
    assert_refused(&server.get_as_operator(&format!("/api/episodes/{NOBODY}/moment?step=0")).await, 404, NOBODY, "an unknown episode's moment");
    // The state before any action, rendered from the episode's record.
    let first = server.get_as_operator(&format!("{moment}?step=0")).await;
    assert_eq!(first.status, 200, "{}", first.text());
    assert_eq!((first.header("content-type"), first.header("x-control-step"), first.header("x-control-steps")), (Some("image/jpeg"), Some("0"), Some("0")));
    assert_eq!(&first.body[..2], &[0xff, 0xd8], "a JPEG");
    assert_refused(&server.get_as_operator(&format!("{moment}?step=7")).await, 400, "7", "a moment after the last step");
    let stages = format!("/api/episodes/{id}/stages");
    assert_refused(&server.get_as_operator(&stages).await, 404, "is no rollout of a batch", "the stages of an episode of no batch");
    assert_refused(&server.post_json_as_operator(&stages, &json!({"stage_name": "s"})).await, 400, "body must be", "an annotation without its fields");

    // MCP: its own token only, never the operator's.
    let mcp = format!("/mcp/{id}");
    assert_refused(&server.post_json(&mcp, &json!({})).await, 401, "missing or invalid episode token", "MCP without a token");
    assert_refused(&server.post_json_as_operator(&mcp, &json!({})).await, 401, "missing or invalid episode token", "MCP with the operator token");
    // And the episode's token opens nothing of the operator's.
    let sneaky = server.send(axum_method("GET"), "/api/episodes", &[("authorization", &episode_bearer)], Vec::new()).await;
    assert_refused(&sneaky, 401, "operator token required", "the operator API with an episode token");
    let batch = json!({"name": "sneaky", "dir": "/tmp/sneaky", "doc": {"schema_version": "libero_agent.batch.v1", "settings": {}}, "records": []});
    let sneaky = server.send(axum_method("POST"), "/api/batches", &[("authorization", &episode_bearer), ("content-type", "application/json")], batch.to_string().into_bytes()).await;
    assert_refused(&sneaky, 401, "operator token required", "a batch registered with an episode token");

    // Abort: a reason is required; the row then says INVALID, and a late forfeit leaves it so.
    let abort = format!("/api/episodes/{id}/abort");
    assert_refused(&server.post_json_as_operator(&abort, &json!({})).await, 400, "body must be {\"reason\"", "an abort without a reason");
    assert_refused(&server.post_json_as_operator(&abort, &json!({"reason": "  "})).await, 400, "body must be {\"reason\"", "an empty reason");
    assert_refused(&server.post_json_as_operator(&format!("/api/episodes/{NOBODY}/abort"), &json!({"reason": "x"})).await, 404, "no open episode", "an unknown abort");
    let aborted = server.post_json_as_operator(&abort, &json!({"reason": "the in-process route test"})).await;
    assert_eq!(aborted.status, 200, "{}", aborted.text());
    let aborted = aborted.json();
    assert_eq!(aborted["outcome"], "INVALID", "{aborted}");
    let result = server.get_as_operator(&format!("/api/episodes/{id}/result")).await.json();
    assert_eq!((result["result"]["status"].as_str(), result["result"]["reason"].as_str()), (Some("aborted"), Some("the in-process route test")), "{result}");
    let forfeit = format!("/api/episodes/{id}/forfeit");
    assert_refused(&server.post_json_as_operator(&forfeit, &json!({})).await, 400, "body must be {\"reason\"", "a forfeit without a reason");
    let late = server.post_json_as_operator(&forfeit, &json!({"reason": "late"})).await;
    assert_eq!(late.status, 200, "{}", late.text());
    let late = late.json();
    assert_eq!((late["outcome"].as_str(), late["reason"].as_str()), (Some("INVALID"), Some("the in-process route test")), "an ended episode is left as it is: {late}");
    assert_refused(&server.post_json_as_operator(&format!("/api/episodes/{NOBODY}/finish"), &json!({})).await, 404, "no open episode", "an unknown finish");

    // Its own token reaches the episode's MCP service, which says what a request lacks.
    let stream = server.send(axum_method("GET"), &mcp, &[("authorization", &episode_bearer)], Vec::new()).await;
    assert_eq!(stream.status, 406, "{}", stream.text());
    assert!(stream.text().contains("must accept text/event-stream"), "{}", stream.text());
    let home = assert_page(&server.get_as_operator("/?batch=in-process").await, "the home page's batch filter");
    assert!(home.contains(&id), "the batch filter finds the episode: {home}");
}

#[tokio::test(flavor = "multi_thread")]
async fn a_teleop_episode_starts_and_is_finished_and_judged() {
    let server = TestServer::start().await;
    let started = server.post_json_as_operator("/api/teleop", &json!({"task": "T14", "seed": 100})).await;
    assert_eq!(started.status, 200, "{}", started.text());
    let started = started.json();
    assert_eq!((started["ok"].as_bool(), started["task"].as_str(), started["seed"].as_u64()), (Some(true), Some("T14"), Some(100)), "{started}");
    let id = started["episode_id"].as_str().expect("episode_id").to_owned();
    let row = server.get_as_operator(&format!("/api/episodes/{id}")).await.json();
    assert_eq!((row["harness"].as_str(), row["model"].as_str(), row["batch"].as_str()), (Some("teleop"), Some("human"), Some("teleop")), "{row}");
    assert!(row["state"] == "active" && row["started_at"].is_string(), "started on creation: {row}");

    // Finish and judge: nothing was done, so the task is not solved; a second finish answers the verdict as it stands.
    let finish = format!("/api/episodes/{id}/finish");
    let judged = server.post_json_as_operator(&finish, &json!({})).await;
    assert_eq!(judged.status, 200, "{}", judged.text());
    let judged = judged.json();
    assert_eq!((judged["episode_id"].as_str(), judged["success"].as_bool()), (Some(id.as_str()), Some(false)), "{judged}");
    assert!(judged["required_stage_count"].as_u64().is_some_and(|k| k >= 1), "{judged}");
    assert_eq!(judged["outcome"], "FAIL", "{judged}");
    let again = server.post_json_as_operator(&finish, &json!({})).await;
    assert_eq!(again.status, 200, "{}", again.text());
    assert_eq!(again.json()["outcome"], "FAIL");
}

/// A finished batch of one T14 rollout of the `command` harness, with its stdout log, under `dir`.
fn write_batch(dir: &std::path::Path, marker: &str) {
    let rollout = dir.join("rollouts/w1_t14_level3");
    std::fs::create_dir_all(&rollout).unwrap();
    let batch = json!({
        "schema_version": "libero_agent.batch.v1", "status": "finished", "created_at": "2025-01-01T00:00:00Z",
        "settings": {"experiment": "main_table", "harness": "command", "model": "reference", "reps": 1, "tasks": [14], "seed": 100,
            "wall_time_s": 300.0, "max_agent_steps": 100, "agent_cmd": "true", "sandbox": false},
        "rollout_count": 1, "counts": {"done": 1, "running": 0, "left": 0}, "outcomes": {"SUCCESS": 1},
    });
    std::fs::write(dir.join("batch.json"), batch.to_string()).unwrap();
    let record = json!({
        "schema_version": "libero_agent.rollout.v1", "rollout_id": "w1_t14_level3", "task": "T14", "task_number": 14,
        "split": "short_horizon_easy", "stage_count": 1, "repetition": 1, "level": 3, "demo": "none", "outcome": "SUCCESS",
        "episode_id": "ep-20250101T000000Z-fixture", "completed_stages": 1, "wall_time_s": 60.0,
        "started_at": "2025-01-01T00:00:00Z", "finished_at": "2025-01-01T00:01:00Z",
    });
    std::fs::write(dir.join("rollouts.jsonl"), format!("{record}\n")).unwrap();
    std::fs::write(rollout.join("command_stdout.log"), format!("{marker}\n")).unwrap();
}

#[tokio::test(flavor = "multi_thread")]
async fn a_registered_batch_is_listed_by_the_results_routes() {
    let extra = tempfile::tempdir().unwrap();
    let marker = "stdout-marker-7d2e";
    write_batch(&extra.path().join("fixture_b"), marker);
    let server = TestServer::start_with(&["--batches", extra.path().to_str().unwrap()]).await;

    let all = server.get_as_operator("/api/results").await.json();
    assert_eq!(all["available"], json!(["fixture_b"]), "{all}");
    let one = server.get_as_operator("/api/results?batch=fixture_b&reps=1").await.json();
    let b = &one["batches"][0];
    assert_eq!((b["name"].as_str(), b["status"].as_str(), b["reps"].as_u64()), (Some("fixture_b"), Some("finished"), Some(1)), "{one}");
    assert_eq!(b["episodes"][0]["logs"], "/results/logs/fixture_b/w1_t14_level3", "{b}");
    assert_refused(&server.get_as_operator("/api/results?reps=0").await, 400, "reps must be a whole number from 1 to", "?reps=0");
    assert_refused(&server.get_as_operator("/api/results?batch=nope").await, 404, "no batch \"nope\"", "an unknown batch");

    let page = assert_page(&server.get_as_operator("/results?batch=fixture_b").await, "/results?batch=fixture_b");
    assert!(page.contains("command + reference") && page.contains("/episodes/ep-20250101T000000Z-fixture/review"), "{page}");
    assert_page(&server.get_as_operator("/results").await, "/results");
    assert_error_page(&server.get_as_operator("/results?reps=many").await, 400, "reps must be a whole number", "/results?reps=many");

    let csv = server.get_as_operator("/results/report/csv?batch=fixture_b").await;
    assert_eq!(csv.status, 200, "{}", csv.text());
    assert!(csv.header("content-type").is_some_and(|t| t.starts_with("text/csv")), "{:?}", csv.headers);
    assert!(csv.header("content-disposition").is_some_and(|d| d.contains("libero-agent-results.csv")), "{:?}", csv.headers);
    assert!(csv.text().contains("T14"), "{}", csv.text());
    let latex = server.get_as_operator("/results/report/latex?batch=fixture_b").await;
    assert!(latex.status == 200 && latex.text().contains("\\begin"), "{}", latex.text());
    assert_error_page(&server.get_as_operator("/results/report/pdf").await, 400, "csv, markdown or latex", "a report as PDF");

    // A rollout's logs: the page, a raw file, and only the runner's file names of known rollouts.
    let logs = assert_page(&server.get_as_operator("/results/logs/fixture_b/w1_t14_level3").await, "the rollout's logs");
    assert!(logs.contains(marker), "the page shows the stdout: {logs}");
    let raw = server.get_as_operator("/results/logs/fixture_b/w1_t14_level3/stdout").await;
    assert_eq!((raw.status, raw.text()), (200, format!("{marker}\n")));
    assert_error_page(&server.get_as_operator("/results/logs/fixture_b/w1_t14_level3/home").await, 404, "logs are stdout, stderr, transcript", "a file no runner writes");
    assert_error_page(&server.get_as_operator("/results/logs/fixture_b/w9_t14_level3").await, 404, "has no finished rollout", "an unknown rollout");
    assert_error_page(&server.get_as_operator("/results/logs/nope/w1_t14_level3/stdout").await, 404, "no batch", "an unknown batch's logs");

    // A runner elsewhere registers its batch; a bad one is refused saying why.
    let doc = json!({"schema_version": "libero_agent.batch.v1", "settings": {}, "created_at": "2025-01-02T00:00:00Z"});
    let bad = json!({"name": "../up", "dir": "/tmp/up", "doc": doc, "records": []});
    assert_refused(&server.post_json_as_operator("/api/batches", &bad).await, 400, "batch name must be", "a batch named ../up");
    let bad = json!({"name": "posted", "dir": "/tmp/other", "doc": doc, "records": []});
    assert_refused(&server.post_json_as_operator("/api/batches", &bad).await, 400, "is not the last component of dir", "a name that is not its dir's");
    assert_refused(&server.post_json_as_operator("/api/batches", &json!({"name": "x"})).await, 400, "body must be", "a body without dir and doc");
    let good = json!({"name": "posted", "dir": "/tmp/elsewhere/posted", "doc": doc, "records": []});
    let answer = server.post_json_as_operator("/api/batches", &good).await;
    assert_eq!(answer.status, 200, "{}", answer.text());
    assert_eq!(answer.json(), json!({"ok": true, "name": "posted", "have": 0, "results": "/results?batch=posted"}));
    let all = server.get_as_operator("/api/results").await.json();
    assert!(all["available"].as_array().unwrap().contains(&json!("posted")), "{all}");
    let moved = json!({"name": "posted", "dir": "/tmp/moved/posted", "doc": doc, "records": []});
    assert_refused(&server.post_json_as_operator("/api/batches", &moved).await, 409, "already has a batch named", "another batch of the same name");
}

/// The path of every `.route("…")` call in the router's sources (test modules left out).
fn routes_in_sources() -> std::collections::BTreeSet<String> {
    let server_dir = libero_testkit::server_dir();
    let mut found = std::collections::BTreeSet::new();
    for crate_dir in ["server/src", "dashboard/src"] {
        let mut files: Vec<_> = std::fs::read_dir(server_dir.join(crate_dir)).unwrap().map(|e| e.unwrap().path()).collect();
        files.sort();
        for file in files.iter().filter(|f| f.extension().is_some_and(|e| e == "rs")) {
            let text = std::fs::read_to_string(file).unwrap();
            let code = text.split("#[cfg(test)]").next().unwrap();
            for (i, _) in code.match_indices(".route(") {
                let rest = code[i + ".route(".len()..].trim_start();
                let path = rest.strip_prefix('"').and_then(|r| r.split('"').next());
                let path = path.unwrap_or_else(|| panic!("{}: a .route( whose path is not a literal: {}", file.display(), &rest[..rest.len().min(60)]));
                found.insert(path.to_owned());
            }
        }
    }
    found
}

#[test]
fn every_route_of_the_sources_has_an_in_process_test() {
    let sources = routes_in_sources();
    assert!(sources.contains("/api/episodes") && sources.contains("/tasks/{id}") && sources.len() > 40, "the scan found the routes: {sources:?}");
    let listed: std::collections::BTreeSet<String> = ROUTES.iter().map(|(p, _)| p.to_string()).collect();
    let untested: Vec<&String> = sources.difference(&listed).collect();
    assert!(untested.is_empty(), "routes without an in-process test (add one here and list it in ROUTES): {untested:?}");
    let gone: Vec<&String> = listed.difference(&sources).collect();
    assert!(gone.is_empty(), "ROUTES lists routes the sources no longer have: {gone:?}");
    let this = std::fs::read_to_string(file!()).or_else(|_| std::fs::read_to_string(libero_testkit::repo_root().join(file!()))).unwrap();
    for (path, test) in ROUTES {
        assert!(this.contains(&format!("async fn {test}(")), "{path}'s test {test} is not in this file");
    }
    // Every operator-only route is checked without the token.
    for path in &sources {
        let open = ["/api/health", "/login", "/static/{file}", "/favicon.ico", "/mcp/{id}"].contains(&path.as_str());
        let pattern: Vec<&str> = path.split('/').collect();
        let checked = OPERATOR_ONLY.iter().any(|(_, p)| {
            let p = p.split('?').next().unwrap();
            let parts: Vec<&str> = p.split('/').collect();
            parts.len() == pattern.len() && pattern.iter().zip(&parts).all(|(a, b)| a.starts_with('{') || a == b)
                || pattern.last().is_some_and(|l| l.starts_with("{*")) && parts.len() >= pattern.len() && pattern[..pattern.len() - 1].iter().zip(&parts).all(|(a, b)| a.starts_with('{') || a == b)
        });
        assert!(open || checked, "{path} is operator-only: add a request of it to OPERATOR_ONLY");
    }
}
