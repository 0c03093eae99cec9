//! A minimal HTTP/1.1 client for loopback `http://` URLs (the CLI talking to its own server); avoids a
//! TLS-capable client stack for two POST requests.
use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::time::Duration;

use anyhow::{Context, bail};

/// `http://host:port/path` split into its parts.
#[derive(Debug, Clone, PartialEq)]
pub struct HttpUrl {
    pub host_port: String,
    pub path: String,
}

impl HttpUrl {
    pub fn parse(url: &str) -> anyhow::Result<Self> {
        let rest = url.strip_prefix("http://").with_context(|| format!("only http:// URLs are supported: {url}"))?;
        let (host_port, path) = match rest.find('/') {
            Some(i) => (&rest[..i], &rest[i..]),
            None => (rest, "/"),
        };
        if host_port.is_empty() {
            bail!("URL has no host: {url}");
        }
        let host_port = if host_port.contains(':') { host_port.to_owned() } else { format!("{host_port}:80") };
        Ok(Self { host_port, path: path.to_owned() })
    }
}

#[derive(Debug)]
pub struct HttpResponse {
    pub status: u16,
    /// Header names lower-cased.
    pub headers: Vec<(String, String)>,
    pub body: Vec<u8>,
}

impl HttpResponse {
    pub fn header(&self, name: &str) -> Option<&str> {
        self.headers.iter().find(|(k, _)| k == name).map(|(_, v)| v.as_str())
    }
}

/// Sends one request with `Connection: close` and reads the whole response (plain or chunked body).
pub fn request(
    method: &str,
    url: &HttpUrl,
    headers: &[(String, String)],
    body: &[u8],
    timeout: Duration,
) -> anyhow::Result<HttpResponse> {
    let mut stream =
        TcpStream::connect(&url.host_port).with_context(|| format!("cannot connect to {}", url.host_port))?;
    stream.set_read_timeout(Some(timeout))?;
    let mut head = format!(
        "{method} {} HTTP/1.1\r\nHost: {}\r\nContent-Length: {}\r\nConnection: close\r\n",
        url.path,
        url.host_port,
        body.len()
    );
    for (k, v) in headers {
        if k.contains(['\r', '\n']) || v.contains(['\r', '\n']) {
            bail!("header {k:?} contains a line break");
        }
        head.push_str(&format!("{k}: {v}\r\n"));
    }
    head.push_str("\r\n");
    stream.write_all(head.as_bytes())?;
    stream.write_all(body)?;
    let mut reader = BufReader::new(stream);
    let mut status_line = String::new();
    reader.read_line(&mut status_line)?;
    let status: u16 = status_line
        .split_whitespace()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .with_context(|| format!("malformed HTTP status line {status_line:?}"))?;
    let mut headers = Vec::new();
    loop {
        let mut line = String::new();
        if reader.read_line(&mut line)? == 0 {
            break;
        }
        let line = line.trim_end();
        if line.is_empty() {
            break;
        }
        if let Some((k, v)) = line.split_once(':') {
            headers.push((k.trim().to_ascii_lowercase(), v.trim().to_owned()));
        }
    }
    let chunked = headers.iter().any(|(k, v)| k == "transfer-encoding" && v.eq_ignore_ascii_case("chunked"));
    let mut body = Vec::new();
    if chunked {
        loop {
            let mut size_line = String::new();
            reader.read_line(&mut size_line)?;
            let size = usize::from_str_radix(size_line.trim().split(';').next().unwrap_or("0"), 16)
                .with_context(|| format!("malformed chunk size {size_line:?}"))?;
            if size == 0 {
                break;
            }
            let start = body.len();
            body.resize(start + size, 0);
            reader.read_exact(&mut body[start..])?;
            let mut crlf = [0u8; 2];
            reader.read_exact(&mut crlf)?;
        }
    } else {
        reader.read_to_end(&mut body)?;
    }
    Ok(HttpResponse { status, headers, body })
}

/// JSON-RPC messages of one HTTP reply: a JSON body, or the `data:` events of an SSE stream.
pub fn messages_of(resp: &HttpResponse) -> Vec<serde_json::Value> {
    let body = String::from_utf8_lossy(&resp.body);
    let is_sse = resp.header("content-type").is_some_and(|c| c.starts_with("text/event-stream"));
    if !is_sse {
        return serde_json::from_str::<serde_json::Value>(body.trim()).map(|v| vec![v]).unwrap_or_default();
    }
    let mut out = Vec::new();
    for event in body.split("\n\n") {
        let data: Vec<&str> =
            event.lines().filter_map(|l| l.strip_prefix("data:")).map(|d| d.strip_prefix(' ').unwrap_or(d)).collect();
        if data.is_empty() {
            continue;
        }
        if let Ok(v) = serde_json::from_str::<serde_json::Value>(&data.join("\n")) {
            out.push(v);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn urls_split_into_authority_and_path() {
        let u = HttpUrl::parse("http://127.0.0.1:8080/mcp/ep-1").unwrap();
        assert_eq!((u.host_port.as_str(), u.path.as_str()), ("127.0.0.1:8080", "/mcp/ep-1"));
        assert_eq!(HttpUrl::parse("http://localhost").unwrap().host_port, "localhost:80");
        assert!(HttpUrl::parse("https://x").is_err());
    }

    #[test]
    fn sse_and_json_bodies_yield_their_messages() {
        let sse = HttpResponse {
            status: 200,
            headers: vec![("content-type".into(), "text/event-stream".into())],
            body: b"data: \n\nid: 0\nretry: 3000\ndata: {\"jsonrpc\":\"2.0\",\"id\":1,\"result\":{}}\n\n".to_vec(),
        };
        assert_eq!(messages_of(&sse), vec![serde_json::json!({"jsonrpc": "2.0", "id": 1, "result": {}})]);
        let plain = HttpResponse {
            status: 200,
            headers: vec![("content-type".into(), "application/json".into())],
            body: br#"{"jsonrpc":"2.0","id":2,"result":{}}"#.to_vec(),
        };
        assert_eq!(messages_of(&plain).len(), 1);
    }
}
