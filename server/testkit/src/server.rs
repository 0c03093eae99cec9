//! The full router of `libero-agent serve` (the operator API, MCP, login and the console's pages), over a
//! throwaway data directory, answering requests in process: no child process, no socket, no HTTP parsing. Each
//! request goes through the same layers a real one does (host check, operator guard, compression, the console's
//! error pages), so a test of a route's answer needs no binary.
//!
//! ```ignore
//! let server = TestServer::start().await;
//! let page = server.get_as_operator("/tasks").await;
//! assert_eq!(page.status, 200, "{}", page.text());
//! ```
//!
//! What needs a real connection (WebSocket upgrades, the accept loop's limits, a process's signals and restart)
//! stays with the tests that spawn the binary.
use std::path::Path;

pub use axum::http::Method;

use axum::body::Body;
use axum::http::{HeaderMap, Request, header};
use clap::Parser;
use libero_server::{AppState, InProcess, ServeArgs};
use serde_json::Value;
use tower::ServiceExt;

/// Largest body a test reads (a page, a JSON list, a thumbnail).
const MAX_BODY: usize = 64 << 20;

#[derive(Parser)]
struct Serve {
    #[command(flatten)]
    args: ServeArgs,
}

/// A server answering in process (see the module doc); its data directory is removed when it drops.
pub struct TestServer {
    inner: InProcess,
    host: String,
    token: String,
    data: tempfile::TempDir,
}

/// One answer: its status, headers and body (decompressed: requests ask for no encoding).
#[derive(Debug)]
pub struct Answer {
    pub status: u16,
    pub headers: HeaderMap,
    pub body: Vec<u8>,
}

impl Answer {
    pub fn text(&self) -> String {
        String::from_utf8_lossy(&self.body).into_owned()
    }

    /// The body as JSON; fails the test, showing the body, where it is not.
    pub fn json(&self) -> Value {
        serde_json::from_slice(&self.body).unwrap_or_else(|e| panic!("status {}: body is not JSON ({e}): {}", self.status, self.text()))
    }

    /// A header's value as text.
    pub fn header(&self, name: &str) -> Option<&str> {
        self.headers.get(name).and_then(|v| v.to_str().ok())
    }
}

impl TestServer {
    /// `serve --addr 127.0.0.1:0 --thumbnails-ahead off` with the console, over a new temporary data directory.
    pub async fn start() -> Self {
        Self::start_with(&[]).await
    }

    /// With more `serve` arguments (e.g. `--batches DIR`).
    pub async fn start_with(extra: &[&str]) -> Self {
        Self::start_at("127.0.0.1:0", extra).await
    }

    /// Bound to `addr` (`0.0.0.0:0`: a server reachable beyond loopback, as its pages say), with more `serve`
    /// arguments. Requests name [`url`](Self::url)'s authority as their `Host`, which a server bound to an
    /// unspecified address does not answer to: send those with a `host` header of `127.0.0.1:PORT`.
    pub async fn start_at(addr: &str, extra: &[&str]) -> Self {
        let data = tempfile::tempdir().expect("a temporary data directory");
        let mut argv = vec!["serve", "--addr", addr, "--thumbnails-ahead", "off", "--data"];
        let dir = data.path().to_str().expect("a UTF-8 temporary path").to_owned();
        argv.push(&dir);
        argv.extend_from_slice(extra);
        let mut args = Serve::try_parse_from(argv).unwrap_or_else(|e| panic!("serve arguments: {e}")).args;
        args.console = Some(libero_dashboard::console());
        let bound = libero_server::start(&args).await.unwrap_or_else(|e| panic!("start the server: {e:#}"));
        let token = bound.operator_token().to_owned();
        let inner = bound.in_process();
        let host = inner.base_url.trim_start_matches("http://").to_owned();
        Self { inner, host, token, data }
    }

    /// The data directory (`--data`).
    pub fn data(&self) -> &Path {
        self.data.path()
    }

    /// The operator token.
    pub fn token(&self) -> &str {
        &self.token
    }

    /// The server's state (its episodes, store, operator).
    pub fn app(&self) -> &AppState {
        &self.inner.app
    }

    /// The URL the server would be reached at (`http://127.0.0.1:PORT`; nothing listens there).
    pub fn url(&self) -> &str {
        &self.inner.base_url
    }

    /// `GET path` without any credential.
    pub async fn get(&self, path: &str) -> Answer {
        self.send(Method::GET, path, &[], Vec::new()).await
    }

    /// `GET path` with the operator token (`Authorization: Bearer`, as the CLI and scripts send it).
    pub async fn get_as_operator(&self, path: &str) -> Answer {
        let auth = self.bearer();
        self.send(Method::GET, path, &[("authorization", &auth)], Vec::new()).await
    }

    /// `POST path` of a JSON body without any credential.
    pub async fn post_json(&self, path: &str, body: &Value) -> Answer {
        self.send(Method::POST, path, &[("content-type", "application/json")], body.to_string().into_bytes()).await
    }

    /// `POST path` of a JSON body with the operator token.
    pub async fn post_json_as_operator(&self, path: &str, body: &Value) -> Answer {
        let auth = self.bearer();
        self.send(Method::POST, path, &[("content-type", "application/json"), ("authorization", &auth)], body.to_string().into_bytes())
            .await
    }

    /// Any request: `Host` is this server's unless `headers` name one.
    pub async fn send(&self, method: Method, path: &str, headers: &[(&str, &str)], body: Vec<u8>) -> Answer {
        let mut req = Request::builder().method(method).uri(path);
        if !headers.iter().any(|(k, _)| k.eq_ignore_ascii_case("host")) {
            req = req.header(header::HOST, &self.host);
        }
        for (k, v) in headers {
            req = req.header(*k, *v);
        }
        let req = req.body(Body::from(body)).unwrap_or_else(|e| panic!("request {path}: {e}"));
        let resp = self.inner.router.clone().oneshot(req).await.unwrap_or_else(|e| match e {});
        let (parts, body) = resp.into_parts();
        let body = axum::body::to_bytes(body, MAX_BODY).await.unwrap_or_else(|e| panic!("read the body of {path}: {e}")).to_vec();
        Answer { status: parts.status.as_u16(), headers: parts.headers, body }
    }

    /// Stops every open episode (recorded as aborted) and writes their rows.
    pub async fn stop_episodes(&self) {
        self.inner.stop("the in-process test server stopped").await;
    }

    fn bearer(&self) -> String {
        format!("Bearer {}", self.token)
    }
}
