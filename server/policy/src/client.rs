//! The blocking client of openpi's `WebsocketPolicyServer` (openpi `src/openpi/serving/websocket_policy_server.py`,
//! spoken by `openpi_client.websocket_client_policy` 0.1.2): connect (optionally with
//! `Authorization: Api-Key <key>`, the header openpi's client sends), read the server's metadata (the first
//! binary message), then one observation per request and one action dict back. A text frame instead of
//! the action is the policy's traceback; the server then closes with 1011. `GET /healthz` answers 200.
use std::collections::BTreeMap;
use std::io::{Read, Write};
use std::net::{TcpStream, ToSocketAddrs};
use std::time::{Duration, Instant};

use rmpv::Value;
use tungstenite::client::IntoClientRequest;
use tungstenite::protocol::WebSocketConfig;
use tungstenite::{Message, WebSocket};

use crate::codec::{self, NdArray, key_str, map_get};
use crate::PolicyError;

/// Bounds on what a policy server may send and how long it may take.
#[derive(Debug, Clone)]
pub struct ClientLimits {
    pub connect_timeout: Duration,
    /// How long one `infer` (and the metadata after connecting) may take.
    pub infer_timeout: Duration,
    /// Largest message accepted from the server.
    pub max_message_bytes: usize,
    /// Longest action chunk accepted.
    pub max_chunk_len: usize,
    /// Longest traceback kept from a failed policy.
    pub max_traceback_bytes: usize,
}

impl Default for ClientLimits {
    fn default() -> Self {
        Self {
            connect_timeout: Duration::from_secs(10),
            // A cold π0 on a busy GPU takes seconds for its first call (jit); a minute is a hung server.
            infer_timeout: Duration::from_secs(60),
            max_message_bytes: 16 << 20,
            max_chunk_len: 1024,
            max_traceback_bytes: 64 << 10,
        }
    }
}

/// A `ws://host:port[/path]` endpoint.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Endpoint {
    pub host: String,
    pub port: u16,
    pub path: String,
}

impl Endpoint {
    /// `ws://HOST:PORT[/path]`, or `HOST:PORT` as openpi's client accepts it. `wss://` is refused: serve
    /// the policy on a trusted network or through a tunnel.
    pub fn parse(url: &str) -> Result<Self, PolicyError> {
        let bad = |why: &str| PolicyError::Connection(format!("policy address {url:?}: {why}"));
        let rest = if let Some(r) = url.strip_prefix("ws://") {
            r
        } else if url.starts_with("wss://") {
            return Err(bad("wss:// is not supported; use ws:// (e.g. through an SSH tunnel)"));
        } else if url.contains("://") {
            return Err(bad("the scheme must be ws://"));
        } else {
            url
        };
        let (authority, path) = match rest.find('/') {
            Some(i) => (&rest[..i], rest[i..].to_string()),
            None => (rest, "/".to_string()),
        };
        let (host, port) = match authority.rsplit_once(':') {
            Some((h, p)) => (h, p.parse::<u16>().map_err(|_| bad("the port is not a number"))?),
            None => (authority, 80),
        };
        if host.is_empty() {
            return Err(bad("no host"));
        }
        Ok(Self { host: host.trim_matches(['[', ']']).to_string(), port, path })
    }

    pub fn url(&self) -> String {
        let host = if self.host.contains(':') { format!("[{}]", self.host) } else { self.host.clone() };
        format!("ws://{host}:{}{}", self.port, self.path)
    }

    fn connect_tcp(&self, timeout: Duration) -> Result<TcpStream, PolicyError> {
        let addrs = (self.host.as_str(), self.port)
            .to_socket_addrs()
            .map_err(|e| PolicyError::Connection(format!("{}: cannot resolve: {e}", self.url())))?;
        let mut last = None;
        for addr in addrs {
            match TcpStream::connect_timeout(&addr, timeout) {
                Ok(s) => return Ok(s),
                Err(e) => last = Some(e),
            }
        }
        Err(PolicyError::Connection(format!(
            "{}: {}",
            self.url(),
            last.map(|e| e.to_string()).unwrap_or_else(|| "no address".into())
        )))
    }
}

/// `GET /healthz` of the policy server (200 = up).
pub fn healthz(endpoint: &Endpoint, timeout: Duration) -> Result<(), PolicyError> {
    let mut s = endpoint.connect_tcp(timeout)?;
    let io = |e: std::io::Error| PolicyError::Connection(format!("{}: healthz: {e}", endpoint.url()));
    s.set_read_timeout(Some(timeout)).map_err(io)?;
    s.set_write_timeout(Some(timeout)).map_err(io)?;
    write!(s, "GET /healthz HTTP/1.1\r\nHost: {}:{}\r\nConnection: close\r\n\r\n", endpoint.host, endpoint.port).map_err(io)?;
    let mut head = Vec::new();
    // Only the status line matters; read at most 4 KiB.
    s.take(4096).read_to_end(&mut head).map_err(|e| match e.kind() {
        std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut => PolicyError::Timeout(format!("healthz after {timeout:?}")),
        _ => io(e),
    })?;
    let line = String::from_utf8_lossy(&head);
    let status = line.lines().next().unwrap_or_default();
    if status.split_whitespace().nth(1) == Some("200") {
        Ok(())
    } else {
        Err(PolicyError::Connection(format!("{}: healthz answered {status:?}", endpoint.url())))
    }
}

/// One answer of the policy.
#[derive(Debug, Clone, PartialEq)]
pub struct ActionChunk {
    /// `actions`: `[chunk][action_dim]`, widened to f64 from the dtype the server sent.
    pub actions: Vec<Vec<f64>>,
    /// The dtype `actions` came in (numpy's `dtype.str`).
    pub actions_dtype: &'static str,
    /// `server_timing` (openpi: `infer_ms`, later `prev_total_ms`), numbers only.
    pub server_timing: BTreeMap<String, f64>,
    /// `policy_timing` when the policy reports it.
    pub policy_timing: BTreeMap<String, f64>,
    /// Round trip measured here, milliseconds.
    pub client_round_trip_ms: f64,
}

/// A connected policy.
pub struct PolicyClient {
    ws: WebSocket<TcpStream>,
    metadata: Value,
    limits: ClientLimits,
    /// Set after a timeout or a protocol failure: the stream's state is unknown, so nothing more is sent.
    broken: Option<String>,
}

impl PolicyClient {
    /// Connects, completes the websocket handshake and reads the metadata message.
    pub fn connect(endpoint: &Endpoint, api_key: Option<&str>, limits: ClientLimits) -> Result<Self, PolicyError> {
        let tcp = endpoint.connect_tcp(limits.connect_timeout)?;
        let conn = |e: &dyn std::fmt::Display| PolicyError::Connection(format!("{}: {e}", endpoint.url()));
        tcp.set_nodelay(true).map_err(|e| conn(&e))?;
        tcp.set_read_timeout(Some(limits.connect_timeout)).map_err(|e| conn(&e))?;
        tcp.set_write_timeout(Some(limits.connect_timeout)).map_err(|e| conn(&e))?;
        let mut request = endpoint.url().into_client_request().map_err(|e| conn(&e))?;
        if let Some(key) = api_key {
            let value = format!("Api-Key {key}").parse().map_err(|_| conn(&"the API key is not a valid header value"))?;
            request.headers_mut().insert("Authorization", value);
        }
        let config = WebSocketConfig::default()
            .max_message_size(Some(limits.max_message_bytes))
            .max_frame_size(Some(limits.max_message_bytes));
        let (ws, _response) = tungstenite::client::client_with_config(request, tcp, Some(config)).map_err(|e| match e {
            tungstenite::HandshakeError::Failure(e) => conn(&format!("websocket handshake: {e}")),
            tungstenite::HandshakeError::Interrupted(_) => PolicyError::Timeout(format!("{}: websocket handshake", endpoint.url())),
        })?;
        ws.get_ref().set_read_timeout(Some(limits.infer_timeout)).map_err(|e| conn(&e))?;
        let mut client = Self { ws, metadata: Value::Nil, limits, broken: None };
        let first = client.read_binary("the server's metadata")?;
        client.metadata = codec::unpack(&first)?;
        if !matches!(client.metadata, Value::Map(_)) {
            return Err(PolicyError::Protocol("the server's metadata is not a map".into()));
        }
        Ok(client)
    }

    /// The metadata the server sent after connecting.
    pub fn metadata(&self) -> &Value {
        &self.metadata
    }

    /// Sends one observation (a msgpack map) and reads the action dict.
    pub fn infer(&mut self, observation: &Value) -> Result<ActionChunk, PolicyError> {
        if let Some(why) = &self.broken {
            return Err(PolicyError::Connection(format!("the connection is unusable after: {why}")));
        }
        let started = Instant::now();
        let bytes = codec::pack(observation);
        if let Err(e) = self.ws.send(Message::Binary(bytes.into())) {
            return Err(self.fail(PolicyError::Connection(format!("sending the observation: {e}"))));
        }
        let answer = self.read_binary("the action")?;
        let value = codec::unpack(&answer).map_err(|e| self.fail(e))?;
        let mut chunk = action_chunk(&value, self.limits.max_chunk_len).map_err(|e| self.fail(e))?;
        chunk.client_round_trip_ms = started.elapsed().as_secs_f64() * 1e3;
        Ok(chunk)
    }

    /// Closes politely (best effort).
    pub fn close(mut self) {
        let _ = self.ws.close(None);
        let _ = self.ws.flush();
    }

    fn fail(&mut self, e: PolicyError) -> PolicyError {
        self.broken = Some(e.to_string());
        e
    }

    /// The next binary message; pings are answered, a text frame is the policy's traceback.
    fn read_binary(&mut self, what: &str) -> Result<Vec<u8>, PolicyError> {
        loop {
            match self.ws.read() {
                Ok(Message::Binary(b)) => return Ok(b.to_vec()),
                Ok(Message::Text(t)) => {
                    let mut traceback = t.as_str().to_string();
                    if traceback.len() > self.limits.max_traceback_bytes {
                        let mut end = self.limits.max_traceback_bytes;
                        while !traceback.is_char_boundary(end) {
                            end -= 1;
                        }
                        traceback.truncate(end);
                        traceback.push_str("\n[truncated]");
                    }
                    let close_code = self.read_close_code();
                    let e = PolicyError::Policy { traceback, close_code };
                    return Err(self.fail(e));
                }
                Ok(Message::Close(frame)) => {
                    let why = frame.map(|f| format!("{} {}", u16::from(f.code), f.reason)).unwrap_or_else(|| "no close frame".into());
                    return Err(self.fail(PolicyError::Connection(format!("the server closed the connection ({why}) instead of sending {what}"))));
                }
                Ok(Message::Ping(_) | Message::Pong(_) | Message::Frame(_)) => continue,
                Err(tungstenite::Error::Io(e)) if matches!(e.kind(), std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut) => {
                    let limit = self.limits.infer_timeout;
                    return Err(self.fail(PolicyError::Timeout(format!("no answer with {what} within {limit:?}"))));
                }
                Err(tungstenite::Error::Capacity(e)) => {
                    return Err(self.fail(PolicyError::Protocol(format!("{what}: {e} (limit {} bytes)", self.limits.max_message_bytes))));
                }
                Err(e) => return Err(self.fail(PolicyError::Connection(format!("reading {what}: {e}")))),
            }
        }
    }

    /// The close code that follows a traceback (openpi: 1011), waiting briefly.
    fn read_close_code(&mut self) -> Option<u16> {
        let _ = self.ws.get_ref().set_read_timeout(Some(Duration::from_secs(2)));
        let code = loop {
            match self.ws.read() {
                Ok(Message::Close(frame)) => break frame.map(|f| u16::from(f.code)),
                Ok(_) => continue,
                Err(_) => break None,
            }
        };
        let _ = self.ws.get_ref().set_read_timeout(Some(self.limits.infer_timeout));
        code
    }
}

/// The typed action dict: `actions` of shape `[chunk, dim]` (or `[dim]`, one action), finite.
pub fn action_chunk(value: &Value, max_chunk_len: usize) -> Result<ActionChunk, PolicyError> {
    let Value::Map(entries) = value else {
        return Err(PolicyError::Protocol("the answer is not a map".into()));
    };
    let actions = map_get(entries, "actions").ok_or_else(|| PolicyError::Protocol("the answer has no \"actions\"".into()))?;
    let array = NdArray::from_value(actions)?.ok_or_else(|| PolicyError::Protocol("\"actions\" is not a numpy array".into()))?;
    let (len, dim) = match array.shape.as_slice() {
        [len, dim] => (*len, *dim),
        [dim] => (1, *dim),
        other => return Err(PolicyError::Protocol(format!("\"actions\" has shape {other:?}, not [chunk, dim]"))),
    };
    if len == 0 || len > max_chunk_len {
        return Err(PolicyError::Protocol(format!("an action chunk of {len} steps (1 to {max_chunk_len} accepted)")));
    }
    if dim == 0 {
        return Err(PolicyError::Protocol("actions of dimension 0".into()));
    }
    let values = array.to_f64();
    if let Some(i) = values.iter().position(|v| !v.is_finite()) {
        return Err(PolicyError::Protocol(format!("action {} component {} is not finite", i / dim, i % dim)));
    }
    Ok(ActionChunk {
        actions: values.chunks_exact(dim).map(<[f64]>::to_vec).collect(),
        actions_dtype: array.dtype.numpy_str(),
        server_timing: number_map(map_get(entries, "server_timing")),
        policy_timing: number_map(map_get(entries, "policy_timing")),
        client_round_trip_ms: 0.0,
    })
}

/// The numeric entries of a `{name: number}` map; anything else is left out.
fn number_map(value: Option<&Value>) -> BTreeMap<String, f64> {
    let Some(Value::Map(entries)) = value else { return BTreeMap::new() };
    entries
        .iter()
        .filter_map(|(k, v)| {
            let n = match v {
                Value::F64(f) => *f,
                Value::F32(f) => f64::from(*f),
                Value::Integer(i) => i.as_f64()?,
                _ => return None,
            };
            Some((key_str(k)?.to_string(), n))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn endpoints_parse_as_openpi_writes_them() {
        assert_eq!(Endpoint::parse("ws://10.0.0.2:8000").unwrap(), Endpoint { host: "10.0.0.2".into(), port: 8000, path: "/".into() });
        assert_eq!(Endpoint::parse("localhost:8000").unwrap().url(), "ws://localhost:8000/");
        assert_eq!(Endpoint::parse("ws://[::1]:9/p").unwrap().url(), "ws://[::1]:9/p");
        assert!(Endpoint::parse("wss://h:1").is_err());
        assert!(Endpoint::parse("http://h:1").is_err());
        assert!(Endpoint::parse("ws://h:x").is_err());
    }

    #[test]
    fn an_action_dict_is_checked() {
        let actions = NdArray::from_f32(vec![2, 7], &[0.5; 14]).unwrap().to_value();
        let timing = Value::Map(vec![(Value::from("infer_ms"), Value::F64(3.5))]);
        let ok = Value::Map(vec![(Value::from("actions"), actions.clone()), (Value::from("server_timing"), timing)]);
        let chunk = action_chunk(&ok, 10).unwrap();
        assert_eq!(chunk.actions.len(), 2);
        assert_eq!(chunk.server_timing["infer_ms"], 3.5);
        assert!(action_chunk(&ok, 1).is_err(), "longer than the cap");
        let nan = NdArray::from_f64(vec![1, 7], &[0.0, 0.0, f64::NAN, 0.0, 0.0, 0.0, 0.0]).unwrap().to_value();
        assert!(action_chunk(&Value::Map(vec![(Value::from("actions"), nan)]), 10).is_err());
        assert!(action_chunk(&Value::Map(vec![]), 10).is_err());
    }
}
