//! The gateway's records: what each request became ([`Record`], [`Mode`], [`Cause`]), the records file with its
//! overflow counters past the cap ([`Overflow`], the sidecar), and reading a records file back ([`summarize`],
//! [`last_model_api_failure`]).
use super::*;

/// How the gateway handled a request.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Mode {
    /// Origin-form, to the configured upstream.
    Reverse,
    /// Absolute-form `http://…`, to an allowed host.
    Forward,
    /// A `CONNECT` tunnel to an allowed host.
    Connect,
    /// Not passed on: not allowed (403), not a request the gateway could read (malformed or oversized head or
    /// body), or no model API configured.
    Refused,
}

/// Who caused the answer a request got, or its end: only [`Cause::Upstream`] can make the model API's failure of
/// an agent ([`last_model_api_failure`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Cause {
    /// The host the request was passed on to: its response (whatever its status) and how its body ended, or no
    /// TCP connection, TLS handshake or HTTP exchange with it.
    Upstream,
    /// The gateway itself: a refusal, a bound (413, 431, 400), no model API configured, too many connections, the
    /// gateway stopping.
    Gateway,
    /// The client: its request body broke off, it went away before its answer was complete, it did not take its
    /// tunnel.
    Client,
    /// Records written before causes were recorded; never written now, never counted as the model API's failure.
    #[default]
    Unknown,
}

/// One line of the records file: one request (or one tunnel), written when it ended.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Record {
    /// When the request arrived, ISO-8601 UTC.
    pub time: String,
    /// The same, in milliseconds since the Unix epoch.
    pub unix_ms: u64,
    pub mode: Mode,
    pub method: String,
    /// `host:port` the request went (or would have gone) to; empty when the head could not be read.
    pub host: String,
    /// The request's path without query; empty for `CONNECT`.
    pub path: String,
    /// The status sent to the client (200 for an established tunnel).
    pub status: u16,
    /// Who caused the answer (or the end): [`Cause`].
    #[serde(default)]
    pub cause: Cause,
    /// Body bytes from the client (tunnels: every byte from the client).
    pub request_bytes: u64,
    /// Body bytes to the client (tunnels: every byte to the client).
    pub response_bytes: u64,
    pub duration_ms: u64,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub content_type: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub usage: Option<TokenUsage>,
    /// The request reached the upstream whole, but the tokens it cost could not be read: its response was
    /// encoded, ended early (cut by either side, or never came), or was a successful `POST` that reported no
    /// usage (`count_tokens` aside).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub unmetered: bool,
    /// Why the request failed or ended early (upstream unreachable, client gone, gateway stopped, …).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
}

/// A records file added up.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct UsageSummary {
    pub requests: u64,
    /// Requests in mode `refused`.
    pub refused: u64,
    /// Requests that recorded an error.
    pub failed: u64,
    /// Requests whose token cost could not be read ([`Record::unmetered`]).
    #[serde(default)]
    pub unmetered: u64,
    pub request_bytes: u64,
    pub response_bytes: u64,
    /// Of the bytes above, those through `CONNECT` tunnels and forwarded `http://` requests, both ways: traffic
    /// whose token usage the gateway cannot read.
    #[serde(default)]
    pub tunnel_bytes: u64,
    /// Responses that carried token usage; the token sums below are over these.
    pub responses_with_usage: u64,
    pub input_tokens: u64,
    pub output_tokens: u64,
    pub cached_input_tokens: u64,
    pub cache_creation_input_tokens: u64,
    pub reasoning_tokens: u64,
    pub total_tokens: u64,
    /// Lines that were not records (a line cut short when the runner died, a line over
    /// [`MAX_RECORD_LINE_BYTES`]).
    pub unreadable_lines: u64,
    /// Of the requests, those past the gateway's record cap: counted without a line of their own.
    #[serde(default)]
    pub overflowed: u64,
    /// The token sums are every token the agent's traffic cost: no bytes went through a tunnel or a forward
    /// (`tunnel_bytes` 0), no request was unmetered, every line was read, and the counters past the record cap
    /// are the gateway's final ones (not a crashed gateway's sidecar). False: the sums are a lower bound.
    /// Summaries written before this was recorded read false.
    #[serde(default)]
    pub complete: bool,
}

impl Default for UsageSummary {
    fn default() -> Self {
        Self {
            requests: 0,
            refused: 0,
            failed: 0,
            unmetered: 0,
            request_bytes: 0,
            response_bytes: 0,
            tunnel_bytes: 0,
            responses_with_usage: 0,
            input_tokens: 0,
            output_tokens: 0,
            cached_input_tokens: 0,
            cache_creation_input_tokens: 0,
            reasoning_tokens: 0,
            total_tokens: 0,
            unreadable_lines: 0,
            overflowed: 0,
            complete: true,
        }
    }
}

impl UsageSummary {
    pub(super) fn add(&mut self, r: &Record) {
        self.requests += 1;
        self.refused += u64::from(r.mode == Mode::Refused);
        self.failed += u64::from(r.error.is_some());
        self.unmetered += u64::from(r.unmetered);
        self.request_bytes += r.request_bytes;
        self.response_bytes += r.response_bytes;
        if matches!(r.mode, Mode::Connect | Mode::Forward) {
            self.tunnel_bytes += r.request_bytes + r.response_bytes;
        }
        if let Some(u) = &r.usage {
            self.responses_with_usage += 1;
            self.input_tokens += u.counts.input_tokens.unwrap_or(0);
            self.output_tokens += u.counts.output_tokens.unwrap_or(0);
            self.cached_input_tokens += u.counts.cached_input_tokens.unwrap_or(0);
            self.cache_creation_input_tokens += u.cache_creation_input_tokens.unwrap_or(0);
            self.reasoning_tokens += u.counts.reasoning_tokens.unwrap_or(0);
            self.total_tokens += u.counts.total_tokens.unwrap_or(0);
        }
    }

    pub(super) fn merge(&mut self, o: &UsageSummary) {
        self.requests += o.requests;
        self.refused += o.refused;
        self.failed += o.failed;
        self.unmetered += o.unmetered;
        self.request_bytes += o.request_bytes;
        self.response_bytes += o.response_bytes;
        self.tunnel_bytes += o.tunnel_bytes;
        self.responses_with_usage += o.responses_with_usage;
        self.input_tokens += o.input_tokens;
        self.output_tokens += o.output_tokens;
        self.cached_input_tokens += o.cached_input_tokens;
        self.cache_creation_input_tokens += o.cache_creation_input_tokens;
        self.reasoning_tokens += o.reasoning_tokens;
        self.total_tokens += o.total_tokens;
        self.unreadable_lines += o.unreadable_lines;
        self.overflowed += o.overflowed;
    }
}

/// The tag of an [`Overflow`] line: `"kind": "overflow"`, which no [`Record`] has.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum OverflowKind {
    #[default]
    Overflow,
}

/// What the gateway counted of the requests past its record cap: the records file's last line once it stopped
/// (`{"kind":"overflow","requests":…,"by_status":{"403":…},…}`), and meanwhile its sidecar file
/// ([`overflow_sidecar`]).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Overflow {
    pub kind: OverflowKind,
    /// The requests' sums, as [`summarize`] makes them (`overflowed` = `requests`).
    #[serde(flatten)]
    pub summary: UsageSummary,
    /// Requests per status sent.
    pub by_status: BTreeMap<u16, u64>,
    /// Of the requests passed on (modes `reverse` and `forward`), the one that arrived last, whole.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub last_passed_on: Option<Record>,
}

impl Overflow {
    pub(super) fn add(&mut self, r: Record) {
        self.summary.add(&r);
        self.summary.overflowed += 1;
        self.summary.complete = self.summary.tunnel_bytes == 0 && self.summary.unmetered == 0;
        *self.by_status.entry(r.status).or_default() += 1;
        keep_if_last_passed_on(&mut self.last_passed_on, &r);
    }
}

/// `r` becomes `last` when it was passed on (modes `reverse` and `forward`) and arrived no earlier.
pub(super) fn keep_if_last_passed_on(last: &mut Option<Record>, r: &Record) {
    if matches!(r.mode, Mode::Reverse | Mode::Forward) && last.as_ref().is_none_or(|l| r.unix_ms >= l.unix_ms) {
        *last = Some(r.clone());
    }
}

/// Where a gateway keeps its overflow counters while it runs: beside `records`, `model_api.jsonl` →
/// `model_api.overflow.json`.
pub fn overflow_sidecar(records: &Path) -> PathBuf {
    records.with_extension("overflow.json")
}

/// A records file read once: its sums, and the last request passed on.
#[derive(Default)]
pub(super) struct Scan {
    pub(super) summary: UsageSummary,
    pub(super) last_passed_on: Option<Record>,
}

impl Scan {
    pub(super) fn passed_on(&mut self, r: &Record) {
        keep_if_last_passed_on(&mut self.last_passed_on, r);
    }

    pub(super) fn overflow(&mut self, o: &Overflow) {
        self.summary.merge(&o.summary);
        if let Some(r) = &o.last_passed_on {
            self.passed_on(r);
        }
    }
}

/// Reads a records file in one streamed pass (never whole: it is bounded by the gateway, but not by what a
/// crashed gateway left), with the overflow line or, without one, the sidecar a crashed gateway left.
pub(super) fn scan(records: &Path) -> std::io::Result<Scan> {
    let mut reader = BufReader::new(std::fs::File::open(records)?);
    let mut s = Scan::default();
    let (mut line, mut final_counters) = (Vec::new(), false);
    while let Some(whole) = next_line(&mut reader, &mut line, MAX_RECORD_LINE_BYTES)? {
        if !whole {
            s.summary.unreadable_lines += 1;
            continue;
        }
        if line.iter().all(u8::is_ascii_whitespace) {
            continue;
        }
        if let Ok(r) = serde_json::from_slice::<Record>(&line) {
            s.summary.add(&r);
            s.passed_on(&r);
        } else if let Ok(o) = serde_json::from_slice::<Overflow>(&line) {
            s.overflow(&o);
            final_counters = true;
        } else {
            s.summary.unreadable_lines += 1;
        }
    }
    let mut stale = false;
    if !final_counters {
        let mut text = String::new();
        let read = std::fs::File::open(overflow_sidecar(records)).and_then(|f| f.take(1 << 20).read_to_string(&mut text));
        if read.is_ok() {
            match serde_json::from_str::<Overflow>(&text) {
                Ok(o) => s.overflow(&o),
                Err(_) => s.summary.unreadable_lines += 1,
            }
            stale = true;
        }
    }
    let t = &s.summary;
    s.summary.complete = t.tunnel_bytes == 0 && t.unmetered == 0 && t.unreadable_lines == 0 && !stale;
    Ok(s)
}

/// The next line of `r` into `line`, without its newline: `Some(true)`, or `Some(false)` for a line over `max`
/// bytes (skipped, `line` left empty); `None` at the end.
pub(super) fn next_line(r: &mut impl BufRead, line: &mut Vec<u8>, max: usize) -> std::io::Result<Option<bool>> {
    line.clear();
    let n = r.by_ref().take(max as u64 + 1).read_until(b'\n', line)?;
    if n == 0 {
        return Ok(None);
    }
    if line.last() == Some(&b'\n') {
        line.pop();
        return Ok(Some(true));
    }
    if line.len() <= max {
        return Ok(Some(true));
    }
    line.clear();
    loop {
        let buf = r.fill_buf()?;
        if buf.is_empty() {
            break;
        }
        if let Some(i) = buf.iter().position(|b| *b == b'\n') {
            r.consume(i + 1);
            break;
        }
        let n = buf.len();
        r.consume(n);
    }
    Ok(Some(false))
}

/// Adds up a gateway's records file (its overflow counters included).
pub fn summarize(records: &Path) -> std::io::Result<UsageSummary> {
    Ok(scan(records)?.summary)
}

/// Why the model API failed the agent, if it did: the last request the gateway passed on (to the upstream or an
/// allowed host; past the record cap too) was answered 429 or 5xx by that host, or its response broke off there,
/// or no connection or handshake with it succeeded ([`Cause::Upstream`]). What the agent's side or the gateway
/// does (a refused host or path, a client that went away, a request body cut short, an unreadable head, a 4xx,
/// no model API configured) is not a failure of the model API: only this may make an agent that quit without
/// `finish_episode` INVALID.
pub fn last_model_api_failure(records: &Path) -> Option<String> {
    let last = scan(records).ok()?.last_passed_on?;
    let failed = last.status == 429 || last.status >= 500 || last.error.is_some();
    (last.cause == Cause::Upstream && failed).then(|| {
        let why = last.error.as_deref().map(|e| format!(": {e}")).unwrap_or_default();
        format!("the model API answered {} to {} {}{why}", last.status, last.method, last.path)
    })
}

/// The records file: whole records up to the cap, counters past it.
pub(super) struct Log {
    pub(super) file: std::fs::File,
    pub(super) sidecar: PathBuf,
    pub(super) max_records: u64,
    pub(super) written: u64,
    pub(super) overflow: Option<Overflow>,
    /// The counters changed since the sidecar was last written.
    pub(super) dirty: bool,
    pub(super) sidecar_at: Option<Instant>,
    pub(super) closed: bool,
}

impl Log {
    /// Appends one record, or counts it past the cap (a write error loses that line; the proxying goes on).
    pub(super) fn add(&mut self, r: Record) {
        if self.written < self.max_records && self.overflow.is_none() {
            self.written += 1;
            if let Ok(mut line) = serde_json::to_vec(&r) {
                line.push(b'\n');
                let _ = self.file.write_all(&line);
            }
            return;
        }
        self.overflow.get_or_insert_with(Overflow::default).add(r);
        self.dirty = true;
        // The first time at once; then every [`SIDECAR_EVERY`], by the gateway's ticker.
        if self.sidecar_at.is_none() {
            self.flush_sidecar();
        }
    }

    /// Rewrites the sidecar (temporary file, then rename: never half a file) when the counters changed.
    pub(super) fn flush_sidecar(&mut self) {
        let Some(o) = &self.overflow else { return };
        if self.closed || !self.dirty {
            return;
        }
        let Ok(text) = serde_json::to_vec(o) else { return };
        let tmp = self.sidecar.with_extension("json.tmp");
        if std::fs::write(&tmp, text).and_then(|()| std::fs::rename(&tmp, &self.sidecar)).is_ok() {
            self.dirty = false;
        }
        self.sidecar_at = Some(Instant::now());
    }

    /// The counters as the file's last line, once; the sidecar then goes.
    pub(super) fn close(&mut self) {
        if self.closed {
            return;
        }
        if let Some(o) = &self.overflow
            && let Ok(mut line) = serde_json::to_vec(o)
        {
            line.push(b'\n');
            if self.file.write_all(&line).and_then(|()| self.file.sync_data()).is_ok() {
                let _ = std::fs::remove_file(&self.sidecar);
            } else {
                self.flush_sidecar();
            }
        }
        self.closed = true;
    }
}
