//! The agent's transcript (docs/agent_transcript.md): what the harness's CLI prints, normalised into one event
//! schema ([`libero_records::agent_events`]) while the agent runs, so that a reviewer sees what the agent read,
//! thought and ran beside the robot's calls, and a person watching the live page sees it as it happens.
//!
//! Every byte read here is the agent's (its commands run as its CLI's user and can write to the CLI's stdout),
//! so parsing never fails: a line that is not what the harness prints becomes an `other` event; lines longer
//! than [`MAX_LINE_BYTES`] are counted, not parsed; text is scrubbed of secrets with the logs' matcher and bounded
//! per field; paths are only placed lexically against the workspace, never opened. Token counts shown here are
//! for reading the timeline; the rollout's usage comes from [`crate::usage::choose`].
//!
//! [`Follower`] tails the CLI's stdout and stderr (files in the rollout directory, outside the sandbox) and the
//! gateway's `model_api.jsonl`, every [`POLL`], and writes the events to the episode's run directory when this
//! machine has it (`run`, a local `run --server`, workers), otherwise posts them to the server's operator API
//! (`POST /api/episodes/{id}/agent/events`) and keeps a copy in the rollout directory.
//!
//! A flood from one stream never hides the others (`QUOTAS`): each stream has a byte quota of its own in the
//! transcript (stdout 10 MiB, stderr 1 MiB, the gateway's records 2 MiB) and the runner's notes another (1 MiB,
//! 64 KiB of it kept for the end). Once a stream's quota is spent its events are no longer written as they come:
//! they are counted by label (the gateway's by HTTP status, the others by kind) and summarised in a note at most
//! every 5 s (`model-API gateway: 12,345 more requests not shown (403: 12,000, 200: 345); …`), while the last 200
//! of them (at most 1 MiB for stdout, 256 KiB for the others) are kept and written when the follower finishes,
//! after a closing note and marked `tail`. Altogether at most 15.5 MiB, under the writer's own hard limit
//! ([`MAX_TRANSCRIPT_BYTES`]), which stays as a backstop. The gateway's counters line (`{"kind": "overflow",
//! …}`: what it only counted past its record cap, appended when it stops) becomes one note, as do skips, from the
//! notes' quota.
use std::collections::{HashMap, VecDeque};
use std::fs::File;
use std::os::unix::fs::{FileExt, OpenOptionsExt};
use std::path::{Component, Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use libero_records::agent_events::{AgentEvent, Kind, MAX_FIELD_BYTES, MAX_TRANSCRIPT_BYTES, Source, Tokens, TranscriptFile, Written, bound_str};
use libero_records::json::utc_now_iso;
use libero_episode::tools::ToolName;
use serde::Serialize;
use serde_json::{Map, Value, json};

use crate::harness::{Harness, TranscriptFormat};
use crate::lines::{Line, LineSplitter};
use libero_sandbox::logs::scrub_text;

/// Lines longer than this are counted, not parsed (a CLI's line carrying an image is a few hundred KiB).
pub const MAX_LINE_BYTES: usize = 1 << 20;
/// How often the follower looks for new output.
pub const POLL: Duration = Duration::from_millis(50);
/// Fields longer than this are cut before they are scrubbed (four times the stored bound).
const PRE_SCRUB_BYTES: usize = 4 * MAX_FIELD_BYTES;
/// Calls whose result has not been printed yet, kept at most (the oldest are forgotten).
const MAX_PENDING: usize = 256;
/// Bytes read from one stream per poll.
const READ_PER_POLL: usize = 1 << 20;
/// A stream that grew by more than this since the last read (a flood, or a sparse file) is skipped to its last
/// [`READ_PER_POLL`] bytes; the skip is an `other` event.
const SKIP_BEYOND: u64 = 32 << 20;
/// Events posted to a remote server per request, and their bytes (the server takes at most 1000 and 2 MiB).
const POST_BATCH: usize = 200;
const POST_BYTES: usize = 1 << 20;
/// A remote server that does not answer within this is left (the local copy stays).
const POST_TIMEOUT: Duration = Duration::from_secs(30);

/// Which of the agent's streams a line came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stream {
    Stdout,
    Stderr,
    /// The runner's gateway records (`sandbox/model_api.jsonl`).
    Gateway,
}

impl Stream {
    const ALL: [Stream; 3] = [Stream::Stdout, Stream::Stderr, Stream::Gateway];

    fn name(self) -> &'static str {
        match self {
            Stream::Stdout => "stdout",
            Stream::Stderr => "stderr",
            Stream::Gateway => "model-API gateway records",
        }
    }

    /// The stream in the notes about its quota, and what its events are called there.
    fn title(self) -> (&'static str, &'static str) {
        match self {
            Stream::Stdout => ("the agent's stdout", "events"),
            Stream::Stderr => ("the agent's stderr", "lines"),
            Stream::Gateway => ("model-API gateway", "requests"),
        }
    }

    /// The key in [`Summary::over_quota`].
    fn key(self) -> &'static str {
        match self {
            Stream::Stdout => "stdout",
            Stream::Stderr => "stderr",
            Stream::Gateway => "gateway",
        }
    }
}

// ---------------------------------------------------------------------------------------------- quotas

/// What one stream may take of the transcript.
#[derive(Debug, Clone, Copy)]
struct Quota {
    /// Bytes of its events written as they come.
    bytes: u64,
    /// Once those are spent, its last events are kept and written at the end (`tail: true`): at most this many
    tail_events: usize,
    /// and at most this many bytes of them.
    tail_bytes: u64,
}

/// How the transcript's bytes are shared among the streams and the runner's notes, so that a flood from one
/// stream (the agent's stdout, its stderr, its requests through the gateway) never hides the others.
#[derive(Debug, Clone, Copy)]
struct Quotas {
    stdout: Quota,
    stderr: Quota,
    gateway: Quota,
    /// The runner's notes: skips, the gateway's counters, what went over a quota.
    notes: u64,
    /// Of `notes`, kept for the notes written at the end.
    closing: u64,
    /// An over-quota stream's left-out events are summarised at most this often.
    summary_every: Duration,
}

impl Quotas {
    fn of(&self, stream: Stream) -> Quota {
        match stream {
            Stream::Stdout => self.stdout,
            Stream::Stderr => self.stderr,
            Stream::Gateway => self.gateway,
        }
    }

    /// The most bytes the follower writes.
    const fn total(&self) -> u64 {
        let q = [self.stdout, self.stderr, self.gateway];
        q[0].bytes + q[0].tail_bytes + q[1].bytes + q[1].tail_bytes + q[2].bytes + q[2].tail_bytes + self.notes
    }
}

/// The quotas of a rollout's transcript: most of it for stdout (what the CLI says the agent read, thought and
/// ran), a little for stderr and for the gateway's records (one event per model request), 200 events of each
/// stream's tail, the notes; together 15.5 MiB, under [`MAX_TRANSCRIPT_BYTES`] with room to spare.
const QUOTAS: Quotas = Quotas {
    stdout: Quota { bytes: 10 << 20, tail_events: 200, tail_bytes: 1 << 20 },
    stderr: Quota { bytes: 1 << 20, tail_events: 200, tail_bytes: 256 << 10 },
    gateway: Quota { bytes: 2 << 20, tail_events: 200, tail_bytes: 256 << 10 },
    notes: 1 << 20,
    closing: 64 << 10,
    summary_every: Duration::from_secs(5),
};
const _: () = assert!(QUOTAS.total() + (64 << 10) <= MAX_TRANSCRIPT_BYTES, "the quotas stay under the transcript's hard limit");

/// What an event counts as in the note about its stream's left-out events: an HTTP status (gateway records) or
/// the event's kind.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
enum Label {
    Status(u16),
    Name(&'static str),
}

impl std::fmt::Display for Label {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Label::Status(s) => write!(f, "{s}"),
            Label::Name(n) => f.write_str(n),
        }
    }
}

fn kind_name(kind: Kind) -> &'static str {
    match kind {
        Kind::Message => "message",
        Kind::Reasoning => "reasoning",
        Kind::Shell => "shell",
        Kind::FileRead => "file_read",
        Kind::ImageView => "image_view",
        Kind::ToolCall => "tool_call",
        Kind::ToolResult => "tool_result",
        Kind::Usage => "usage",
        Kind::Stderr => "stderr",
        Kind::Other => "other",
    }
}

/// An event on its way to the transcript.
#[derive(Debug)]
struct Captured {
    ev: AgentEvent,
    /// What it counts as when its stream is over its quota.
    label: Label,
    /// The runner's notice about the stream (bytes skipped, the gateway's counters): written from the notes'
    /// quota while that lasts, whatever the stream's.
    notice: bool,
}

impl Captured {
    fn new(ev: AgentEvent, label: Label) -> Self {
        Self { ev, label, notice: false }
    }

    fn of_kind(ev: AgentEvent) -> Self {
        let label = Label::Name(kind_name(ev.kind));
        Self::new(ev, label)
    }

    fn skip(ev: AgentEvent) -> Self {
        Self { notice: true, ..Self::new(ev, Label::Name("skipped")) }
    }
}

/// Distinct labels counted per stream; later ones count as `other labels`.
const MAX_LABELS: usize = 32;

/// One stream's share of the transcript.
struct Lane {
    stream: Stream,
    quota: Quota,
    summary_every: Duration,
    /// Bytes of its events written as they came.
    used: u64,
    /// The quota is spent: events are counted and the last ones kept.
    over: bool,
    /// Counted since the last note about them, and in all.
    since: Counts,
    all: Counts,
    /// The last counted events (already bounded and marked `tail`) with their line's bytes.
    tail: VecDeque<(AgentEvent, u64)>,
    tail_bytes: u64,
}

#[derive(Default)]
struct Counts {
    events: u64,
    by_label: std::collections::BTreeMap<Label, u64>,
}

impl Counts {
    fn add(&mut self, label: Label) {
        self.events += 1;
        let label = if self.by_label.len() < MAX_LABELS || self.by_label.contains_key(&label) { label } else { Label::Name("other labels") };
        *self.by_label.entry(label).or_default() += 1;
    }

    /// `403: 12,000, 200: 345`, the most frequent first (at most 12).
    fn labels(&self) -> String {
        let mut v: Vec<(&Label, &u64)> = self.by_label.iter().collect();
        v.sort_by(|a, b| b.1.cmp(a.1).then(a.0.cmp(b.0)));
        let mut parts: Vec<String> = v.iter().take(12).map(|(l, n)| format!("{l}: {}", thousands(**n))).collect();
        if v.len() > 12 {
            parts.push("…".into());
        }
        parts.join(", ")
    }
}

fn mib(bytes: u64) -> String {
    if bytes.is_multiple_of(1 << 20) { format!("{} MiB", bytes >> 20) } else { format!("{} KiB", bytes >> 10) }
}

impl Lane {
    fn new(stream: Stream, quota: Quota, summary_every: Duration) -> Self {
        Self { stream, quota, summary_every, used: 0, over: false, since: Counts::default(), all: Counts::default(), tail: VecDeque::new(), tail_bytes: 0 }
    }

    /// Takes `ev` (of `bytes` as a line) for writing now, or counts and keeps it in the tail; the note to write
    /// when the quota is spent by it.
    fn take(&mut self, mut ev: AgentEvent, bytes: u64, label: Label) -> (Option<AgentEvent>, Option<String>) {
        if !self.over && self.used + bytes <= self.quota.bytes {
            self.used += bytes;
            return (Some(ev), None);
        }
        let mut note = None;
        if !self.over {
            self.over = true;
            let (title, noun) = self.stream.title();
            note = Some(format!(
                "{title} reached its quota of {} of this transcript: its later {noun} are counted and summarised at most every {} s, \
                 and the last {} of them are written when the agent has finished (marked tail)",
                mib(self.quota.bytes),
                self.summary_every.as_secs_f64(),
                self.quota.tail_events
            ));
        }
        self.since.add(label);
        self.all.add(label);
        ev.tail = true;
        let bytes = bytes + ",\"tail\":true".len() as u64;
        self.tail.push_back((ev, bytes));
        self.tail_bytes += bytes;
        while self.tail.len() > self.quota.tail_events || self.tail_bytes > self.quota.tail_bytes {
            let Some((_, b)) = self.tail.pop_front() else { break };
            self.tail_bytes -= b;
        }
        (None, note)
    }

    /// The periodic note about what was counted since the last one.
    fn since_note(&mut self) -> Option<String> {
        if self.since.events == 0 {
            return None;
        }
        let since = std::mem::take(&mut self.since);
        let (title, noun) = self.stream.title();
        Some(format!(
            "{title}: {} more {noun} not shown ({}); {} in all since it reached its quota, the last of them are written at the end",
            thousands(since.events),
            since.labels(),
            thousands(self.all.events)
        ))
    }

    /// At the end: the note about all that was counted, and the kept tail to write after it.
    fn closing(&mut self) -> Option<(String, Vec<AgentEvent>)> {
        if !self.over || self.all.events == 0 {
            return None;
        }
        let (title, noun) = self.stream.title();
        let tail: Vec<AgentEvent> = std::mem::take(&mut self.tail).into_iter().map(|(ev, _)| ev).collect();
        self.tail_bytes = 0;
        let left_out = self.all.events - tail.len() as u64;
        let note = format!(
            "{title}: {} {noun} in all over its quota of {} ({}); the last {} follow (marked tail, with the time and seq they were \
             captured at), {} are left out",
            thousands(self.all.events),
            mib(self.quota.bytes),
            self.all.labels(),
            thousands(tail.len() as u64),
            thousands(left_out)
        );
        Some((note, tail))
    }
}

/// What a call's result needs from the call.
#[derive(Debug, Clone)]
struct Pending {
    tool: String,
    robot_tool: Option<String>,
    /// A shell command: its result makes one `shell` event.
    command: Option<String>,
    /// The call was already shown (Codex's `item.started`).
    shown: bool,
}

/// Turns one harness's lines into transcript events.
pub struct Normalizer {
    /// How the harness's stdout reads ([`crate::harness::HarnessSpec::transcript`]).
    format: TranscriptFormat,
    workspace: PathBuf,
    secrets: Vec<String>,
    seq: u64,
    pending: HashMap<String, Pending>,
    pending_order: VecDeque<String>,
    /// The newest observation a robot tool's result carried: what the next robot call acts on.
    observation: Option<String>,
}

fn text_of(bytes: &[u8]) -> String {
    String::from_utf8_lossy(bytes).trim_end_matches('\r').to_owned()
}

fn event(kind: Kind, source: Source) -> AgentEvent {
    AgentEvent::new(kind, source)
}

fn say(kind: Kind, source: Source, text: impl Into<String>) -> AgentEvent {
    AgentEvent { text: Some(text.into()), ..event(kind, source) }
}

fn str_of<'a>(m: &'a Map<String, Value>, keys: &[&str]) -> Option<&'a str> {
    keys.iter().find_map(|k| m.get(*k).and_then(Value::as_str))
}

/// The episode's tool a CLI's tool name stands for (`mcp__libero__osc_sequence`, `osc_sequence`, `libero.…`).
fn robot_tool(name: &str) -> Option<&'static str> {
    ToolName::ALL.iter().map(|t| t.as_str()).find(|t| {
        name == *t || name.strip_suffix(t).is_some_and(|p| p.ends_with("__") || p.ends_with('.') || p.ends_with('/'))
    })
}

/// Tools that run a shell command, by the names the CLIs give them (compared without case).
const SHELL_TOOLS: [&str; 8] = ["bash", "shell", "run_shell_command", "exec_command", "execute_command", "run_command", "terminal", "local_shell"];
/// Tools that read a file (an image through them is an image view).
const READ_TOOLS: [&str; 6] = ["read", "read_file", "readfile", "read_many_files", "view", "cat"];
/// Tools that show the model an image.
const IMAGE_TOOLS: [&str; 5] = ["readmediafile", "read_media_file", "view_image", "zoom_image", "image_view"];
const IMAGE_EXTENSIONS: [&str; 7] = ["png", "jpg", "jpeg", "gif", "webp", "bmp", "tiff"];

fn is_one_of(name: &str, set: &[&str]) -> bool {
    set.iter().any(|s| name.eq_ignore_ascii_case(s))
}

fn is_image_path(path: &str) -> bool {
    Path::new(path).extension().and_then(|e| e.to_str()).is_some_and(|e| is_one_of(e, &IMAGE_EXTENSIONS))
}

/// The first well-formed `"observation_id": "…"` in a tool result's text.
fn observation_id_in(text: &str) -> Option<String> {
    let key = "\"observation_id\"";
    let mut rest = text;
    while let Some(i) = rest.find(key) {
        rest = &rest[i + key.len()..];
        let after = rest.trim_start().strip_prefix(':').map(str::trim_start).and_then(|r| r.strip_prefix('"'));
        if let Some(value) = after.and_then(|r| r.split_once('"')).map(|(v, _)| v)
            && !value.is_empty()
            && value.len() <= 64
            && value.chars().all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
        {
            return Some(value.to_owned());
        }
    }
    None
}

/// `text` with long base64 runs after `base64,` (images inlined into tool results) cut to a marker.
fn without_inline_data(text: &str) -> String {
    const MARK: &str = "base64,";
    let mut out = String::with_capacity(text.len().min(1 << 16));
    let mut rest = text;
    while let Some(i) = rest.find(MARK) {
        let (head, tail) = rest.split_at(i + MARK.len());
        out.push_str(head);
        let run = tail.bytes().take_while(|b| b.is_ascii_alphanumeric() || matches!(b, b'+' | b'/' | b'=')).count();
        if run >= 64 {
            out.push_str(&format!("<{run} bytes of base64>"));
        } else {
            out.push_str(&tail[..run]);
        }
        rest = &tail[run..];
    }
    out.push_str(rest);
    out
}

/// The text of a message or tool result's content: a string, or the texts of its parts (images as `[image]`).
fn content_text(v: &Value) -> String {
    match v {
        Value::String(s) => s.clone(),
        Value::Array(parts) => parts
            .iter()
            .map(|p| match p {
                Value::String(s) => s.clone(),
                Value::Object(m) => match m.get("type").and_then(Value::as_str) {
                    Some("text" | "output_text" | "input_text") => str_of(m, &["text"]).unwrap_or_default().to_owned(),
                    Some("image" | "image_url" | "input_image") => "[image]".to_owned(),
                    _ => str_of(m, &["text"]).map(str::to_owned).unwrap_or_else(|| compact(p)),
                },
                other => compact(other),
            })
            .collect::<Vec<_>>()
            .join("\n"),
        Value::Null => String::new(),
        other => compact(other),
    }
}

fn compact(v: &Value) -> String {
    serde_json::to_string(v).unwrap_or_default()
}

/// `path` without `.` and `..` (lexically; nothing is opened).
fn normalize(path: &Path) -> Option<PathBuf> {
    let mut out = PathBuf::new();
    for c in path.components() {
        match c {
            Component::RootDir => out.push("/"),
            Component::CurDir => {}
            Component::ParentDir => {
                if !out.pop() {
                    return None;
                }
            }
            Component::Normal(n) => out.push(n),
            Component::Prefix(_) => return None,
        }
    }
    Some(out)
}

impl Normalizer {
    pub fn new(harness: Harness, workspace: &Path, secrets: &[&str]) -> Self {
        Self {
            format: harness.spec().transcript,
            workspace: normalize(workspace).unwrap_or_else(|| workspace.to_path_buf()),
            secrets: secrets.iter().map(|s| (*s).to_owned()).collect(),
            seq: 0,
            pending: HashMap::new(),
            pending_order: VecDeque::new(),
            observation: None,
        }
    }

    /// Stamps, scrubs and bounds an event.
    fn finish_event(&mut self, mut ev: AgentEvent, t: &str) -> AgentEvent {
        ev.t = t.to_owned();
        ev.seq = self.seq;
        self.seq += 1;
        let secrets: Vec<&str> = self.secrets.iter().map(String::as_str).collect();
        let mut cut = false;
        for field in ev.texts_mut() {
            // Scrubbing copies the text: a huge field is cut first (well beyond its bound, so a secret at the cut is
            // left out by the bound below rather than shown in part).
            if field.len() > PRE_SCRUB_BYTES {
                *field = bound_str(field, PRE_SCRUB_BYTES).0;
                cut = true;
            }
            *field = scrub_text(field, &secrets);
        }
        ev.truncated |= cut;
        ev.bounded()
    }

    /// Events for one line of `stream`, stamped with the capture time `t`.
    pub fn line(&mut self, stream: Stream, line: Line<'_>, t: &str) -> Vec<AgentEvent> {
        self.capture(stream, line, t).into_iter().map(|c| c.ev).collect()
    }

    /// [`Normalizer::line`] with what each event counts as when its stream is over its quota.
    fn capture(&mut self, stream: Stream, line: Line<'_>, t: &str) -> Vec<Captured> {
        let raw = match (stream, line) {
            (_, Line::Overlong(n)) => {
                let kind = if stream == Stream::Stderr { Kind::Stderr } else { Kind::Other };
                let ev = say(kind, Source::Runner, format!("a {} line of {n} bytes (more than {MAX_LINE_BYTES}) was not parsed", stream.name()));
                vec![Captured::new(ev, Label::Name("overlong line"))]
            }
            (_, Line::Complete(b)) if b.iter().all(u8::is_ascii_whitespace) => Vec::new(),
            (Stream::Stderr, Line::Complete(b)) => vec![Captured::of_kind(say(Kind::Stderr, Source::Stderr, text_of(b)))],
            (Stream::Gateway, Line::Complete(b)) => self.gateway(b).into_iter().collect(),
            (Stream::Stdout, Line::Complete(b)) => self.stdout(b).into_iter().map(Captured::of_kind).collect(),
        };
        raw.into_iter().map(|c| Captured { ev: self.finish_event(c.ev, t), ..c }).collect()
    }

    /// `bytes` of `stream` were not read (a flood, or a sparse file).
    pub fn skipped(&mut self, stream: Stream, bytes: u64, t: &str) -> AgentEvent {
        let ev = say(Kind::Other, Source::Runner, format!("{bytes} bytes of the agent's {} were skipped (written faster than they are read)", stream.name()));
        self.finish_event(ev, t)
    }

    /// The runner's own note (what went over a quota and was left out).
    fn note(&mut self, text: String, t: &str) -> AgentEvent {
        self.finish_event(say(Kind::Other, Source::Runner, text), t)
    }

    /// At the end: shell commands whose result never came.
    pub fn finish(&mut self, t: &str) -> Vec<AgentEvent> {
        let mut out = Vec::new();
        for id in std::mem::take(&mut self.pending_order) {
            if let Some(p) = self.pending.remove(&id)
                && let Some(command) = p.command
            {
                out.push(AgentEvent {
                    tool: Some(p.tool),
                    call_id: Some(id),
                    command: Some(command),
                    text: Some("no result was printed".into()),
                    ..event(Kind::Shell, Source::Stdout)
                });
            }
        }
        out.into_iter().map(|ev| self.finish_event(ev, t)).collect()
    }

    fn stdout(&mut self, b: &[u8]) -> Vec<AgentEvent> {
        if self.format == TranscriptFormat::Text {
            return vec![say(Kind::Message, Source::Stdout, text_of(b))];
        }
        match serde_json::from_slice::<Value>(b) {
            Ok(Value::Object(m)) => self.json_line(&m).unwrap_or_else(|| vec![say(Kind::Other, Source::Stdout, text_of(b))]),
            // DeepSeek's headless profile prints its final answer as plain text.
            _ if self.format == TranscriptFormat::JsonLinesOrText => vec![say(Kind::Message, Source::Stdout, text_of(b))],
            _ => vec![say(Kind::Other, Source::Stdout, text_of(b))],
        }
    }

    /// A JSON line of any of the CLIs' shapes; None when it is none of them.
    fn json_line(&mut self, m: &Map<String, Value>) -> Option<Vec<AgentEvent>> {
        if let Some(ty) = m.get("type").and_then(Value::as_str) {
            return match ty {
                // Codex `exec --json`.
                "thread.started" | "turn.started" | "item.updated" => Some(Vec::new()),
                "turn.completed" => Some(
                    crate::usage::codex_turn_tokens(&Value::Object(m.clone()))
                        .map(|t| usage_event(Source::Stdout, t, "turn completed"))
                        .into_iter()
                        .collect(),
                ),
                "turn.failed" => Some(vec![say(Kind::Other, Source::Stdout, format!("turn failed: {}", m.get("error").map(content_or_message).unwrap_or_default()))]),
                "error" => Some(vec![say(Kind::Other, Source::Stdout, str_of(m, &["message"]).unwrap_or("error").to_owned())]),
                "item.started" | "item.completed" => Some(m.get("item").and_then(Value::as_object).map(|item| self.codex_item(item, ty == "item.completed")).unwrap_or_default()),
                // Claude Code and Qwen Code `stream-json`.
                "system" => Some(self.system(m)),
                "assistant" => Some(m.get("message").and_then(Value::as_object).map(|msg| self.assistant(msg.get("content"))).unwrap_or_default()),
                "user" => Some(m.get("message").and_then(Value::as_object).map(|msg| self.user(msg.get("content"))).unwrap_or_default()),
                "result" => Some(self.result(m)),
                "stream_event" => Some(Vec::new()),
                _ if m.contains_key("role") => Some(self.role_message(m)),
                _ => None,
            };
        }
        // Kimi Code `stream-json` (OpenAI-style messages).
        m.contains_key("role").then(|| self.role_message(m))
    }

    fn system(&mut self, m: &Map<String, Value>) -> Vec<AgentEvent> {
        match str_of(m, &["subtype"]) {
            Some("init") => {
                let tools = m.get("tools").and_then(Value::as_array).map_or(0, Vec::len);
                let servers: Vec<String> = m
                    .get("mcp_servers")
                    .and_then(Value::as_array)
                    .map(|s| s.iter().map(|x| format!("{} {}", x["name"].as_str().unwrap_or("?"), x["status"].as_str().unwrap_or("?"))).collect())
                    .unwrap_or_default();
                let model = str_of(m, &["model"]).unwrap_or("?");
                vec![say(Kind::Other, Source::Stdout, format!("session started: model {model}, {tools} tools, MCP servers: {}", servers.join(", ")))]
            }
            // Progress notices of the UI.
            Some("thinking_tokens" | "ui_invalidate" | "status") => Vec::new(),
            other => vec![say(Kind::Other, Source::Stdout, format!("system: {}", other.unwrap_or("?")))],
        }
    }

    fn assistant(&mut self, content: Option<&Value>) -> Vec<AgentEvent> {
        let Some(content) = content else { return Vec::new() };
        let Some(blocks) = content.as_array() else {
            return vec![say(Kind::Message, Source::Stdout, content_text(content))];
        };
        let mut out = Vec::new();
        for b in blocks {
            let Some(block) = b.as_object() else { continue };
            match str_of(block, &["type"]) {
                Some("text") => out.push(say(Kind::Message, Source::Stdout, str_of(block, &["text"]).unwrap_or_default())),
                Some("thinking") => out.push(say(Kind::Reasoning, Source::Stdout, str_of(block, &["thinking", "text"]).unwrap_or_default())),
                Some("redacted_thinking") => out.push(say(Kind::Reasoning, Source::Stdout, "[redacted thinking]")),
                Some("tool_use" | "server_tool_use") => {
                    let name = str_of(block, &["name"]).unwrap_or("?");
                    let id = str_of(block, &["id"]).map(str::to_owned);
                    out.extend(self.tool_use(name, id, block.get("input").unwrap_or(&Value::Null)));
                }
                other => out.push(say(Kind::Other, Source::Stdout, format!("assistant {} block", other.unwrap_or("?")))),
            }
        }
        out
    }

    fn user(&mut self, content: Option<&Value>) -> Vec<AgentEvent> {
        let Some(blocks) = content.and_then(Value::as_array) else { return Vec::new() };
        let mut out = Vec::new();
        for b in blocks {
            let Some(block) = b.as_object() else { continue };
            if str_of(block, &["type"]) == Some("tool_result") {
                let id = str_of(block, &["tool_use_id"]).map(str::to_owned);
                let is_error = block.get("is_error").and_then(Value::as_bool);
                out.push(self.tool_result(id, &content_text(block.get("content").unwrap_or(&Value::Null)), is_error, None));
            }
        }
        out
    }

    fn result(&mut self, m: &Map<String, Value>) -> Vec<AgentEvent> {
        let mut out = Vec::new();
        if let Some(t) = m.get("usage").and_then(Value::as_object).and_then(crate::usage::tokens_of) {
            out.push(usage_event(Source::Stdout, t, "session total"));
        }
        if m.get("is_error").and_then(Value::as_bool) == Some(true) {
            out.push(say(Kind::Other, Source::Stdout, format!("the session ended with an error: {}", str_of(m, &["result", "subtype"]).unwrap_or("?"))));
        }
        out
    }

    /// Kimi Code's (and any OpenAI-style) message lines.
    fn role_message(&mut self, m: &Map<String, Value>) -> Vec<AgentEvent> {
        match str_of(m, &["role"]) {
            Some("assistant") => {
                let mut out = Vec::new();
                if let Some(r) = str_of(m, &["reasoning_content", "reasoning"]).filter(|r| !r.is_empty()) {
                    out.push(say(Kind::Reasoning, Source::Stdout, r));
                }
                match m.get("content") {
                    Some(Value::Array(parts)) => {
                        for p in parts {
                            match p.get("type").and_then(Value::as_str) {
                                Some("think" | "thinking" | "reasoning") => {
                                    let text = p.get("think").or(p.get("thinking")).or(p.get("text")).map(content_text).unwrap_or_default();
                                    out.push(say(Kind::Reasoning, Source::Stdout, text));
                                }
                                _ => out.push(say(Kind::Message, Source::Stdout, content_text(&Value::Array(vec![p.clone()])))),
                            }
                        }
                    }
                    Some(Value::String(s)) if !s.is_empty() => out.push(say(Kind::Message, Source::Stdout, s.clone())),
                    _ => {}
                }
                for call in m.get("tool_calls").and_then(Value::as_array).into_iter().flatten() {
                    let f = &call["function"];
                    let name = f["name"].as_str().unwrap_or("?");
                    let args = match &f["arguments"] {
                        Value::String(s) => serde_json::from_str(s).unwrap_or_else(|_| Value::String(s.clone())),
                        other => other.clone(),
                    };
                    out.extend(self.tool_use(name, call["id"].as_str().map(str::to_owned), &args));
                }
                out
            }
            Some("tool") => {
                let id = str_of(m, &["tool_call_id"]).map(str::to_owned);
                vec![self.tool_result(id, &content_text(m.get("content").unwrap_or(&Value::Null)), None, None)]
            }
            Some("user") => vec![say(Kind::Other, Source::Stdout, format!("user: {}", content_text(m.get("content").unwrap_or(&Value::Null))))],
            // The CLI's own notices (version, resume hints).
            _ => Vec::new(),
        }
    }

    fn remember(&mut self, id: String, p: Pending) {
        if self.pending.insert(id.clone(), p).is_none() {
            self.pending_order.push_back(id);
        }
        while self.pending_order.len() > MAX_PENDING {
            if let Some(old) = self.pending_order.pop_front() {
                self.pending.remove(&old);
            }
        }
    }

    fn forget(&mut self, id: &str) -> Option<Pending> {
        let p = self.pending.remove(id)?;
        self.pending_order.retain(|x| x != id);
        Some(p)
    }

    /// Where `path` lies: relative to the workspace, and relative to the published observation.
    fn place(&self, path: &str) -> (Option<String>, Option<String>) {
        let p = Path::new(path);
        let Some(abs) = normalize(&if p.is_absolute() { p.to_path_buf() } else { self.workspace.join(p) }) else { return (None, None) };
        let Some(rel) = abs.strip_prefix(&self.workspace).ok().and_then(Path::to_str).map(str::to_owned) else { return (None, None) };
        let file = rel.strip_prefix("benchmark_inputs/current_observation/").filter(|f| !f.is_empty()).map(str::to_owned);
        (Some(rel), file)
    }

    /// A tool call: a shell command (shown with its result), a file read, an image view, or another call.
    fn tool_use(&mut self, name: &str, id: Option<String>, input: &Value) -> Vec<AgentEvent> {
        let args = input.as_object();
        let path = args.and_then(|a| str_of(a, &["file_path", "path", "absolute_path", "filename", "file"])).map(str::to_owned);
        let robot = robot_tool(name);
        let pending = |command: Option<String>| Pending { tool: name.to_owned(), robot_tool: robot.map(str::to_owned), command, shown: true };
        if robot.is_none() && is_one_of(name, &SHELL_TOOLS) {
            let command = match args.and_then(|a| a.get("command").or(a.get("cmd"))) {
                Some(Value::String(s)) => s.clone(),
                Some(Value::Array(words)) => words.iter().map(|w| w.as_str().map(str::to_owned).unwrap_or_else(|| compact(w))).collect::<Vec<_>>().join(" "),
                _ => compact(input),
            };
            return match id {
                Some(id) => {
                    self.remember(id, pending(Some(command)));
                    Vec::new()
                }
                None => vec![AgentEvent { tool: Some(name.to_owned()), command: Some(command), ..event(Kind::Shell, Source::Stdout) }],
            };
        }
        let kind = match &path {
            Some(p) if robot.is_none() && (is_one_of(name, &IMAGE_TOOLS) || (is_one_of(name, &READ_TOOLS) && is_image_path(p))) => Kind::ImageView,
            Some(_) if robot.is_none() && is_one_of(name, &READ_TOOLS) => Kind::FileRead,
            _ => Kind::ToolCall,
        };
        let mut ev = AgentEvent { tool: Some(name.to_owned()), call_id: id.clone(), ..event(kind, Source::Stdout) };
        if kind == Kind::ToolCall {
            ev.arguments = Some(compact(input));
            ev.robot_tool = robot.map(str::to_owned);
            if robot.is_some() {
                ev.observation_id = self.observation.clone();
            }
        } else if let Some(p) = path {
            let (ws, file) = self.place(&p);
            (ev.path, ev.workspace_path, ev.observation_file) = (Some(p), ws, file);
        }
        if let Some(id) = id {
            self.remember(id, pending(None));
        }
        vec![ev]
    }

    /// A call's result; `observation` when the CLI gives the structured payload's id.
    fn tool_result(&mut self, id: Option<String>, text: &str, is_error: Option<bool>, observation: Option<String>) -> AgentEvent {
        let call = id.as_deref().and_then(|i| self.forget(i));
        let text = without_inline_data(text);
        match call {
            Some(Pending { tool, command: Some(command), .. }) => AgentEvent {
                tool: Some(tool),
                call_id: id,
                command: Some(command),
                exit_code: exit_code_in(&text),
                output: Some(text),
                is_error,
                ..event(Kind::Shell, Source::Stdout)
            },
            call => {
                let robot = call.as_ref().and_then(|c| c.robot_tool.clone());
                let observation_id = if robot.is_some() { observation.or_else(|| observation_id_in(&text)) } else { None };
                if observation_id.is_some() {
                    self.observation.clone_from(&observation_id);
                }
                AgentEvent {
                    tool: call.map(|c| c.tool),
                    robot_tool: robot,
                    call_id: id,
                    observation_id,
                    is_error,
                    text: Some(text),
                    ..event(Kind::ToolResult, Source::Stdout)
                }
            }
        }
    }

    /// One Codex `exec --json` item, started or completed.
    fn codex_item(&mut self, item: &Map<String, Value>, completed: bool) -> Vec<AgentEvent> {
        let id = str_of(item, &["id"]).map(str::to_owned);
        match (str_of(item, &["type"]), completed) {
            (Some("agent_message"), true) => vec![say(Kind::Message, Source::Stdout, str_of(item, &["text"]).unwrap_or_default())],
            (Some("reasoning"), true) => vec![say(Kind::Reasoning, Source::Stdout, str_of(item, &["text"]).unwrap_or_default())],
            (Some("command_execution"), true) => {
                let exit_code = item.get("exit_code").and_then(Value::as_i64);
                vec![AgentEvent {
                    tool: Some("command_execution".into()),
                    call_id: id,
                    command: str_of(item, &["command"]).map(str::to_owned),
                    output: str_of(item, &["aggregated_output"]).map(without_inline_data),
                    exit_code,
                    is_error: Some(exit_code != Some(0) || str_of(item, &["status"]) == Some("failed")),
                    ..event(Kind::Shell, Source::Stdout)
                }]
            }
            (Some("mcp_tool_call"), _) => {
                let server = str_of(item, &["server"]).unwrap_or("?");
                let tool = str_of(item, &["tool"]).unwrap_or("?");
                let name = format!("mcp__{server}__{tool}");
                let shown = id.as_deref().and_then(|i| self.pending.get(i)).is_some_and(|p| p.shown);
                let mut out = Vec::new();
                if !shown {
                    out.extend(self.tool_use(&name, id.clone(), item.get("arguments").unwrap_or(&Value::Null)));
                }
                if completed {
                    let error = item.get("error").filter(|e| !e.is_null());
                    let text = match error {
                        Some(e) => content_or_message(e),
                        None => content_text(item.get("result").and_then(|r| r.get("content")).unwrap_or(&Value::Null)),
                    };
                    let observation = item.get("result").and_then(|r| r.pointer("/structured_content/observation_id")).and_then(Value::as_str).map(str::to_owned);
                    let failed = error.is_some() || str_of(item, &["status"]) == Some("failed");
                    out.push(self.tool_result(id, &text, Some(failed), observation));
                }
                out
            }
            (Some("web_search"), true) => {
                vec![AgentEvent { tool: Some("web_search".into()), arguments: str_of(item, &["query"]).map(str::to_owned), call_id: id, ..event(Kind::ToolCall, Source::Stdout) }]
            }
            (Some("file_change"), true) => {
                let changes: Vec<String> = item
                    .get("changes")
                    .and_then(Value::as_array)
                    .map(|c| c.iter().map(|x| format!("{} {}", x["kind"].as_str().unwrap_or("?"), x["path"].as_str().unwrap_or("?"))).collect())
                    .unwrap_or_default();
                vec![say(Kind::Other, Source::Stdout, format!("file change: {}", changes.join(", ")))]
            }
            (Some("error"), true) => vec![say(Kind::Other, Source::Stdout, str_of(item, &["message"]).unwrap_or("error").to_owned())],
            (Some("todo_list"), true) => vec![say(Kind::Other, Source::Stdout, format!("todo list: {}", compact(item.get("items").unwrap_or(&Value::Null))))],
            (_, false) => Vec::new(),
            (other, true) => vec![say(Kind::Other, Source::Stdout, format!("{} item", other.unwrap_or("?")))],
        }
    }

    /// One record of the gateway: a `usage` event when the response carried token counts, an `other` event
    /// when the request was refused or failed; its counters line (`{"kind": "overflow", …}`: the requests past its
    /// record cap, appended when it stops) is one note of the runner's.
    fn gateway(&mut self, b: &[u8]) -> Option<Captured> {
        let Ok(r) = serde_json::from_slice::<libero_sandbox::netgate::Record>(b) else {
            return Some(match serde_json::from_slice::<Value>(b) {
                Ok(Value::Object(m)) if m.get("kind").and_then(Value::as_str) == Some("overflow") => {
                    Captured { notice: true, ..Captured::new(say(Kind::Other, Source::Runner, overflow_text(&m)), Label::Name("overflow")) }
                }
                _ => Captured::new(say(Kind::Other, Source::ModelApiGateway, "a gateway record that does not parse"), Label::Name("unparsed")),
            });
        };
        let what = format!("{} {}{} → {} in {} ms", r.method, r.host, r.path, r.status, r.duration_ms);
        let label = Label::Status(r.status);
        if let Some(u) = &r.usage {
            return Some(Captured::new(usage_event(Source::ModelApiGateway, u.counts, &format!("model request {what}")), label));
        }
        let refused = r.mode == libero_sandbox::netgate::Mode::Refused;
        (refused || r.error.is_some() || r.status >= 400).then(|| {
            let why = r.error.as_deref().map(|e| format!(": {e}")).unwrap_or_default();
            Captured::new(say(Kind::Other, Source::ModelApiGateway, format!("{} {what}{why}", if refused { "refused" } else { "failed" })), label)
        })
    }
}

/// The gateway's counters line (`netgate::Overflow`) as text, whatever its exact shape: `requests` and
/// `by_status` first, then its other fields but `kind` that are not zero, empty or false; numbers with thousands
/// separators, objects one level deep (`requests: 177,188; by_status: (200: 188, 403: 177,000); refused: …`), at
/// most 32 fields of each.
fn overflow_text(m: &Map<String, Value>) -> String {
    fn value(v: &Value, depth: usize) -> String {
        match v {
            Value::Number(n) => n.as_u64().map(thousands).unwrap_or_else(|| n.to_string()),
            Value::Object(o) if depth < 2 => {
                let parts: Vec<String> = o.iter().take(32).map(|(k, v)| format!("{}: {}", bound_str(k, 64).0, value(v, depth + 1))).collect();
                format!("({})", parts.join(", "))
            }
            other => bound_str(&compact(other), 256).0,
        }
    }
    let nothing = |v: &Value| match v {
        Value::Null | Value::Bool(false) => true,
        Value::Number(n) => n.as_u64() == Some(0),
        Value::String(s) => s.is_empty(),
        Value::Array(a) => a.is_empty(),
        Value::Object(o) => o.is_empty(),
        Value::Bool(true) => false,
    };
    const FIRST: [&str; 2] = ["requests", "by_status"];
    let first = FIRST.iter().filter_map(|k| m.get_key_value(*k));
    let rest = m.iter().filter(|(k, v)| k.as_str() != "kind" && !FIRST.contains(&k.as_str()) && !nothing(v));
    let fields: Vec<String> = first.chain(rest).take(32).map(|(k, v)| format!("{}: {}", bound_str(k, 64).0, value(v, 1))).collect();
    format!(
        "model-API gateway: past its record cap it only counts requests; its counters: {}",
        if fields.is_empty() { "none".to_owned() } else { fields.join("; ") }
    )
}

/// `n` with a comma every three digits.
fn thousands(n: u64) -> String {
    let digits = n.to_string();
    let mut out = String::with_capacity(digits.len() + digits.len() / 3);
    for (i, c) in digits.chars().enumerate() {
        if i > 0 && (digits.len() - i).is_multiple_of(3) {
            out.push(',');
        }
        out.push(c);
    }
    out
}

/// `Exit code N` at the start of a shell tool's result (Claude Code's way of saying a command failed).
fn exit_code_in(text: &str) -> Option<i64> {
    text.trim_start().strip_prefix("Exit code ")?.split(|c: char| !c.is_ascii_digit() && c != '-').next()?.parse().ok()
}

/// An error object's message, or its JSON.
fn content_or_message(v: &Value) -> String {
    v.get("message").and_then(Value::as_str).map(str::to_owned).unwrap_or_else(|| content_text(v))
}

fn usage_event(source: Source, tokens: Tokens, text: &str) -> AgentEvent {
    AgentEvent { tokens: Some(tokens), text: Some(text.to_owned()), ..event(Kind::Usage, source) }
}

/// Normalises a whole captured stdout (and stderr) at once: what [`Follower`] does piece by piece (golden tests).
pub fn normalize_logs(harness: Harness, workspace: &Path, secrets: &[&str], stdout: &[u8], stderr: &[u8]) -> Vec<AgentEvent> {
    let mut n = Normalizer::new(harness, workspace, secrets);
    let mut out = Vec::new();
    for (stream, bytes) in [(Stream::Stdout, stdout), (Stream::Stderr, stderr)] {
        let mut lines = LineSplitter::new(MAX_LINE_BYTES);
        let t = "1970-01-01T00:00:00+00:00";
        lines.push(bytes, |l| out.extend(n.line(stream, l, t)));
        lines.end(|l| out.extend(n.line(stream, l, t)));
    }
    out.extend(n.finish("1970-01-01T00:00:00+00:00"));
    out
}

// ---------------------------------------------------------------------------------------------- following

/// One stream the follower reads as it grows.
struct Tail {
    stream: Stream,
    path: PathBuf,
    file: Option<File>,
    offset: u64,
    lines: LineSplitter,
}

impl Tail {
    fn new(stream: Stream, path: PathBuf) -> Self {
        Self { stream, path, file: None, offset: 0, lines: LineSplitter::new(MAX_LINE_BYTES) }
    }

    /// Reads what is new, at most `budget` bytes, into events.
    fn poll(&mut self, n: &mut Normalizer, budget: usize, buf: &mut [u8], out: &mut Vec<Captured>) -> std::io::Result<usize> {
        if self.file.is_none() {
            match std::fs::OpenOptions::new().read(true).custom_flags(libc::O_NOFOLLOW | libc::O_NONBLOCK | libc::O_CLOEXEC).open(&self.path) {
                Ok(f) if f.metadata()?.is_file() => self.file = Some(f),
                Ok(_) => return Err(std::io::Error::other(format!("{} is not a regular file", self.path.display()))),
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(0),
                Err(e) => return Err(e),
            }
        }
        let Some(file) = self.file.as_ref() else { return Ok(0) };
        let size = file.metadata()?.len();
        let t = utc_now_iso();
        if size < self.offset {
            // Truncated under us (the agent can reopen its CLI's stdout): go on from its new end.
            self.offset = size;
            self.lines.end(|l| out.extend(n.capture(self.stream, l, &t)));
            out.push(Captured::skip(n.skipped(self.stream, 0, &t)));
            return Ok(0);
        }
        if size - self.offset > SKIP_BEYOND {
            let to = size - budget as u64;
            self.lines.end(|l| out.extend(n.capture(self.stream, l, &t)));
            out.push(Captured::skip(n.skipped(self.stream, to - self.offset, &t)));
            self.offset = to;
        }
        let mut read = 0;
        while read < budget && self.offset < size {
            let want = buf.len().min(budget - read).min((size - self.offset) as usize);
            let k = file.read_at(&mut buf[..want], self.offset)?;
            if k == 0 {
                break;
            }
            self.offset += k as u64;
            read += k;
            let stream = self.stream;
            self.lines.push(&buf[..k], |l| out.extend(n.capture(stream, l, &t)));
        }
        Ok(read)
    }

    /// The stream ended: its last line without a newline counts.
    fn end(&mut self, n: &mut Normalizer, out: &mut Vec<Captured>) {
        let t = utc_now_iso();
        let stream = self.stream;
        self.lines.end(|l| out.extend(n.capture(stream, l, &t)));
    }
}

/// Where the events go.
pub enum Target {
    /// The episode's run directory is on this machine: `<run_dir>/agent_events.jsonl`.
    RunDir(PathBuf),
    /// It is not: posted to `server_url`'s operator API, and kept in `local` (the rollout directory).
    Remote { server_url: String, episode_id: String, local: PathBuf },
}

/// What the follower wrote (in the rollout's `harness_manifest.json` under `agent_events`).
#[derive(Debug, Clone, Default, Serialize)]
pub struct Summary {
    pub path: Option<PathBuf>,
    #[serde(flatten)]
    pub written: Written,
    /// Events of each stream (`stdout`, `stderr`, `gateway`) that went over its quota and were left out (counted
    /// in the notes; the tail that was written is not among them).
    #[serde(skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub over_quota: std::collections::BTreeMap<String, u64>,
    /// Events the remote server accepted, when posting.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub posted: Option<u64>,
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub errors: Vec<String>,
}

struct Sink {
    file: TranscriptFile,
    remote: Option<(String, String)>,
    summary: Summary,
    quotas: Quotas,
    /// One per [`Stream::ALL`].
    lanes: Vec<Lane>,
    /// Bytes of the runner's notes written.
    notes_used: u64,
    /// When the over-quota streams were last summarised.
    last_summary: Instant,
    /// Events to write at the next [`Sink::flush`], in capture order, and notes to write after them.
    batch: Vec<AgentEvent>,
    notes: Vec<String>,
}

impl Sink {
    fn open_with(target: Target, quotas: Quotas) -> anyhow::Result<Self> {
        let (path, remote) = match target {
            Target::RunDir(dir) => (dir.join(libero_records::agent_events::AGENT_EVENTS_FILE), None),
            Target::Remote { server_url, episode_id, local } => (local, Some((server_url, episode_id))),
        };
        let file = TranscriptFile::open(&path).map_err(|e| anyhow::anyhow!("cannot write the transcript {}: {e}", path.display()))?;
        Ok(Self {
            file,
            remote,
            summary: Summary { path: Some(path), posted: None, ..Summary::default() },
            quotas,
            lanes: Stream::ALL.iter().map(|&s| Lane::new(s, quotas.of(s), quotas.summary_every)).collect(),
            notes_used: 0,
            last_summary: Instant::now(),
            batch: Vec::new(),
            notes: Vec::new(),
        })
    }

    /// Whether a note of `bytes` fits the notes' quota (`closing`: the part kept for the end included).
    fn note_fits(&self, bytes: u64, closing: bool) -> bool {
        let limit = if closing { self.quotas.notes } else { self.quotas.notes.saturating_sub(self.quotas.closing) };
        self.notes_used + bytes <= limit
    }

    /// Takes what `stream` gave: written at the next flush while the stream's quota lasts, else counted and the
    /// last kept.
    fn admit(&mut self, stream: Stream, got: Vec<Captured>) {
        let lane = Stream::ALL.iter().position(|&s| s == stream).unwrap_or(0);
        for Captured { ev, label, notice } in got {
            let bytes = ev.to_line().len() as u64 + 1;
            if notice && self.note_fits(bytes, false) {
                self.notes_used += bytes;
                self.batch.push(ev);
                continue;
            }
            let (now, note) = self.lanes[lane].take(ev, bytes, label);
            self.batch.extend(now);
            self.notes.extend(note);
        }
    }

    /// Writes what was admitted, then the notes (with a summary of each over-quota stream when one is due).
    fn flush(&mut self, n: &mut Normalizer) {
        if self.last_summary.elapsed() >= self.quotas.summary_every {
            self.last_summary = Instant::now();
            let due: Vec<String> = self.lanes.iter_mut().filter_map(Lane::since_note).collect();
            self.notes.extend(due);
        }
        let t = utc_now_iso();
        for text in std::mem::take(&mut self.notes) {
            self.push_note(n, text, &t, false);
        }
        let batch = std::mem::take(&mut self.batch);
        self.write(batch);
    }

    /// Stamps a note and queues it if it fits the notes' quota (a note that does not is dropped; its stream's
    /// counts go on to the closing note).
    fn push_note(&mut self, n: &mut Normalizer, text: String, t: &str, closing: bool) {
        // The stamped line is the text, escaped, and some 120 bytes: checked before a seq is spent on it.
        let estimate = 2 * text.len() as u64 + 256;
        if !self.note_fits(estimate, closing) {
            return;
        }
        let ev = n.note(text, t);
        self.notes_used += ev.to_line().len() as u64 + 1;
        self.batch.push(ev);
    }

    /// At the end: what is left, then for each stream over its quota the note about all it left out and its
    /// kept tail.
    fn finish(&mut self, n: &mut Normalizer) {
        let t = utc_now_iso();
        for text in std::mem::take(&mut self.notes) {
            self.push_note(n, text, &t, false);
        }
        for i in 0..self.lanes.len() {
            let Some((note, tail)) = self.lanes[i].closing() else { continue };
            let stream = self.lanes[i].stream;
            let left_out = self.lanes[i].all.events - tail.len() as u64;
            self.summary.over_quota.insert(stream.key().to_owned(), left_out);
            self.push_note(n, note, &t, true);
            self.batch.extend(tail);
        }
        let batch = std::mem::take(&mut self.batch);
        self.write(batch);
    }

    fn write(&mut self, events: Vec<AgentEvent>) {
        if events.is_empty() {
            return;
        }
        let before = self.file.written().events;
        let copy = self.remote.is_some().then(|| events.clone());
        if let Err(e) = self.file.append(events) {
            self.error(format!("writing the transcript: {e}"));
        }
        // The server gets what the local copy kept (both stop at the same bound).
        let kept = (self.file.written().events - before) as usize;
        if let (Some((url, id)), Some(copy)) = (self.remote.clone(), copy) {
            self.post(&url, &id, &copy[..kept.min(copy.len())]);
        }
    }

    /// Posts events to the remote server in batches of at most [`POST_BATCH`] events and [`POST_BYTES`]; a server
    /// that refuses or fails is not tried again.
    fn post(&mut self, url: &str, id: &str, events: &[AgentEvent]) {
        let mut batches: Vec<Vec<&AgentEvent>> = vec![Vec::new()];
        let mut bytes = 0;
        for ev in events {
            let size = ev.to_line().len() + 1;
            if let Some(last) = batches.last_mut()
                && (last.len() >= POST_BATCH || bytes + size > POST_BYTES)
                && !last.is_empty()
            {
                batches.push(Vec::new());
                bytes = 0;
            }
            bytes += size;
            if let Some(last) = batches.last_mut() {
                last.push(ev);
            }
        }
        for batch in batches.into_iter().filter(|b| !b.is_empty()) {
            let body = json!({"events": batch});
            match libero_server::client::post_json_within(url, &format!("/api/episodes/{id}/agent/events"), &body, POST_TIMEOUT) {
                Ok((200, v)) => *self.summary.posted.get_or_insert(0) += v["accepted"].as_u64().unwrap_or(0),
                Ok((status, v)) => {
                    self.error(format!("the server at {url} refused the transcript (HTTP {status}): {v}"));
                    self.remote = None;
                    return;
                }
                Err(e) => {
                    self.error(format!("cannot post the transcript to {url}: {e:#}"));
                    self.remote = None;
                    return;
                }
            }
        }
    }

    fn error(&mut self, e: String) {
        if self.summary.errors.len() < 8 {
            eprintln!("libero-agent: {e}");
            self.summary.errors.push(e);
        }
    }

    fn close(mut self) -> Summary {
        if let Err(e) = self.file.sync() {
            self.error(format!("syncing the transcript: {e}"));
        }
        self.summary.written = self.file.written();
        self.summary
    }
}

/// What the follower reads.
pub struct Streams {
    pub stdout: PathBuf,
    pub stderr: PathBuf,
    /// The gateway's records, when the agent is sandboxed.
    pub gateway: Option<PathBuf>,
}

/// Follows a running agent's output into its transcript, on a thread of its own. Dropped without
/// [`Follower::finish`] (a rollout that failed on the way), the thread still reads what is left and ends.
pub struct Follower {
    stop: Arc<AtomicBool>,
    thread: Option<JoinHandle<Summary>>,
    /// Why there is no thread.
    failed: Option<String>,
}

impl Follower {
    /// Starts following. A transcript that cannot be written (its file, the thread) is reported by
    /// [`Follower::finish`]; it never fails the rollout.
    pub fn start(normalizer: Normalizer, streams: Streams, target: Target) -> Self {
        Self::start_with(normalizer, streams, target, QUOTAS)
    }

    fn start_with(normalizer: Normalizer, streams: Streams, target: Target, quotas: Quotas) -> Self {
        let stop = Arc::new(AtomicBool::new(false));
        let stopping = stop.clone();
        let thread = Sink::open_with(target, quotas).map_err(|e| format!("{e:#}")).and_then(|sink| {
            std::thread::Builder::new()
                .name("transcript".into())
                .spawn(move || follow(normalizer, streams, sink, &stopping))
                .map_err(|e| format!("cannot start the transcript thread: {e}"))
        });
        match thread {
            Ok(t) => Self { stop, thread: Some(t), failed: None },
            Err(e) => {
                eprintln!("libero-agent: no transcript: {e}");
                Self { stop, thread: None, failed: Some(e) }
            }
        }
    }

    /// Reads what is left (the agent has exited), writes the last events and returns what was written.
    pub fn finish(mut self) -> Summary {
        self.stop.store(true, Ordering::SeqCst);
        match self.thread.take() {
            Some(t) => t.join().unwrap_or_else(|_| Summary { errors: vec!["the transcript thread panicked".into()], ..Summary::default() }),
            None => Summary { errors: self.failed.take().into_iter().collect(), ..Summary::default() },
        }
    }
}

impl Drop for Follower {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
    }
}

/// A rollout's transcript: what it follows and where it goes.
pub struct RolloutTranscript<'a> {
    pub harness: Harness,
    pub workspace: &'a Path,
    /// Scrubbed from every event (the API key, the episode token).
    pub secrets: &'a [&'a str],
    pub streams: Streams,
    pub server_url: &'a str,
    pub episode_id: &'a str,
    /// The episode's run directory as the server reported it.
    pub run_dir: &'a Path,
    /// The rollout directory, for the local copy when the run directory is on another machine.
    pub rollout_dir: &'a Path,
}

/// Follows a rollout's agent into `<run_dir>/agent_events.jsonl` when this machine has the run directory, else
/// to the server's operator API with a copy in the rollout directory.
pub fn follow_rollout(r: RolloutTranscript<'_>) -> Follower {
    let target = if r.run_dir.is_dir() {
        Target::RunDir(r.run_dir.to_path_buf())
    } else {
        Target::Remote {
            server_url: r.server_url.to_owned(),
            episode_id: r.episode_id.to_owned(),
            local: r.rollout_dir.join(libero_records::agent_events::AGENT_EVENTS_FILE),
        }
    };
    Follower::start(Normalizer::new(r.harness, r.workspace, r.secrets), r.streams, target)
}

fn follow(mut n: Normalizer, streams: Streams, mut sink: Sink, stop: &AtomicBool) -> Summary {
    let mut tails: Vec<Tail> = [(Stream::Stdout, Some(streams.stdout)), (Stream::Stderr, Some(streams.stderr)), (Stream::Gateway, streams.gateway)]
        .into_iter()
        .filter_map(|(s, p)| p.map(|p| Tail::new(s, p)))
        .collect();
    let mut buf = vec![0u8; 256 << 10];
    let mut failed = vec![false; tails.len()];
    loop {
        let last = stop.load(Ordering::SeqCst);
        // After the agent is gone, each stream is read to its end (a flood beyond the skip bound is skipped).
        let budget = if last { SKIP_BEYOND as usize } else { READ_PER_POLL };
        for (i, tail) in tails.iter_mut().enumerate() {
            let mut got = Vec::new();
            if !failed[i]
                && !sink.file.is_full()
                && let Err(e) = tail.poll(&mut n, budget, &mut buf, &mut got)
            {
                failed[i] = true;
                sink.error(format!("reading the agent's {}: {e}", tail.stream.name()));
            }
            if last {
                tail.end(&mut n, &mut got);
            }
            sink.admit(tail.stream, got);
        }
        if last {
            let left = n.finish(&utc_now_iso()).into_iter().map(Captured::of_kind).collect();
            sink.admit(Stream::Stdout, left);
            sink.finish(&mut n);
            return sink.close();
        }
        sink.flush(&mut n);
        std::thread::sleep(POLL);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn robot_tools_are_recognised_under_every_prefix() {
        assert_eq!(robot_tool("mcp__libero__osc_sequence"), Some("osc_sequence"));
        assert_eq!(robot_tool("osc_sequence"), Some("osc_sequence"));
        assert_eq!(robot_tool("libero.finish_episode"), Some("finish_episode"));
        assert_eq!(robot_tool("my_osc_sequence"), None);
        assert_eq!(robot_tool("Bash"), None);
    }

    #[test]
    fn observation_ids_and_exit_codes_are_read_from_result_text() {
        assert_eq!(observation_id_in(r#"{"ok":true,"observation_id": "obs_000004"}"#).as_deref(), Some("obs_000004"));
        assert_eq!(observation_id_in(r#""observation_id": "../../x" and "observation_id":"obs_1""#).as_deref(), Some("obs_1"));
        assert_eq!(observation_id_in("nothing"), None);
        assert_eq!(exit_code_in("Exit code 2\nls: cannot access"), Some(2));
        assert_eq!(exit_code_in("fine"), None);
    }

    #[test]
    fn paths_are_placed_lexically_in_the_workspace() {
        let n = Normalizer::new(Harness::ClaudeCode, Path::new("/ws/w1"), &[]);
        assert_eq!(n.place("/ws/w1/benchmark_inputs/current_observation/head/rgb.png"), (Some("benchmark_inputs/current_observation/head/rgb.png".into()), Some("head/rgb.png".into())));
        assert_eq!(n.place("benchmark_inputs/./current_observation/wrist/../head/rgb.png").1.as_deref(), Some("head/rgb.png"));
        assert_eq!(n.place("/ws/w1/../w2/secret.png"), (None, None));
        assert_eq!(n.place("/etc/passwd"), (None, None));
        assert_eq!(n.place("scratch/plot.png"), (Some("scratch/plot.png".into()), None));
    }

    /// A refused request as the gateway records it; `i` is in its path and its duration.
    fn refused_record(i: usize) -> String {
        format!(
            r#"{{"time":"2026-01-01T00:00:00Z","unix_ms":0,"mode":"refused","method":"POST","host":"api.example:443","path":"/v1/{i:06}","status":403,"request_bytes":0,"response_bytes":0,"duration_ms":{i}}}"#
        )
    }

    /// A request that went through and carried token counts.
    fn usage_record(i: usize) -> String {
        format!(
            r#"{{"time":"2026-01-01T00:00:00Z","unix_ms":0,"mode":"reverse","method":"POST","host":"127.0.0.1:1","path":"/v1/messages","status":200,"request_bytes":10,"response_bytes":20,"duration_ms":{i},"usage":{{"api":"anthropic_messages","input_tokens":800,"output_tokens":30,"total_tokens":830}}}}"#
        )
    }

    fn claude_lines(lines: &[serde_json::Value]) -> String {
        lines.iter().map(|l| format!("{l}\n")).collect()
    }

    /// What the agent does after the flood, as Claude Code prints it: a robot call and its result, a shell
    /// command and its result, its last words.
    fn after_the_flood() -> String {
        claude_lines(&[
            json!({"type": "assistant", "message": {"content": [{"type": "tool_use", "id": "toolu_9", "name": "mcp__libero__osc_sequence", "input": {"steps": [[0.1, 0, 0]]}}]}}),
            json!({"type": "user", "message": {"content": [{"type": "tool_result", "tool_use_id": "toolu_9", "content": "{\"ok\":true,\"observation_id\":\"obs_000042\"}"}]}}),
            json!({"type": "assistant", "message": {"content": [{"type": "tool_use", "id": "toolu_10", "name": "Bash", "input": {"command": "echo after-the-flood"}}]}}),
            json!({"type": "user", "message": {"content": [{"type": "tool_result", "tool_use_id": "toolu_10", "content": "after-the-flood"}]}}),
            json!({"type": "assistant", "message": {"content": [{"type": "text", "text": "final words after the flood"}]}}),
        ])
    }

    fn read_events(path: &Path) -> (String, Vec<AgentEvent>) {
        let text = std::fs::read_to_string(path).unwrap();
        let events = text.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
        (text, events)
    }

    /// The number after `prefix` in `text` (with thousands separators).
    fn count_after(text: &str, prefix: &str) -> Option<u64> {
        let rest = &text[text.find(prefix)? + prefix.len()..];
        rest.chars().take_while(|c| c.is_ascii_digit() || *c == ',').filter(char::is_ascii_digit).collect::<String>().parse().ok()
    }

    fn notes(events: &[AgentEvent]) -> Vec<&str> {
        events.iter().filter(|e| e.source == Some(Source::Runner)).filter_map(|e| e.text.as_deref()).collect()
    }

    /// The red team's flood (177,188 refused requests in 45 s filled the whole transcript in 8 s), bigger and
    /// faster: 300,000 refused requests in about 3 s, then the agent's robot call, a command and its last words.
    /// The gateway's records keep to their quota, the later stdout events are written as they come, a note
    /// counts the requests not shown, and the flood's last 200 records are written at the end.
    #[test]
    fn a_flood_of_gateway_records_hides_neither_the_agents_later_events_nor_how_the_flood_ended() {
        use std::io::Write;
        const FLOOD: usize = 300_000;
        let dir = tempfile::tempdir().unwrap();
        let (stdout, stderr, gateway) = (dir.path().join("stdout.jsonl"), dir.path().join("stderr.log"), dir.path().join("model_api.jsonl"));
        std::fs::write(&stdout, claude_lines(&[json!({"type": "assistant", "message": {"content": [{"type": "text", "text": "before the flood"}]}})])).unwrap();
        std::fs::write(&stderr, b"").unwrap();
        let mut g = std::fs::File::create(&gateway).unwrap();
        let run = dir.path().join("run");
        std::fs::create_dir(&run).unwrap();
        let started = Instant::now();
        let follower = Follower::start(
            Normalizer::new(Harness::ClaudeCode, Path::new("/ws/w1"), &[]),
            Streams { stdout: stdout.clone(), stderr, gateway: Some(gateway.clone()) },
            Target::RunDir(run.clone()),
        );
        for chunk in 0..FLOOD / 10_000 {
            let lines: String = (chunk * 10_000..(chunk + 1) * 10_000).map(|i| refused_record(i) + "\n").collect();
            g.write_all(lines.as_bytes()).unwrap();
            std::thread::sleep(Duration::from_millis(100));
        }
        std::fs::OpenOptions::new().append(true).open(&stdout).unwrap().write_all(after_the_flood().as_bytes()).unwrap();
        std::thread::sleep(Duration::from_millis(300));
        let summary = follower.finish();
        let took = started.elapsed();
        assert!(took < Duration::from_secs(90), "the flood took {took:?}");
        assert!(summary.errors.is_empty(), "{:?}", summary.errors);

        let (text, events) = read_events(&run.join(libero_records::agent_events::AGENT_EVENTS_FILE));
        assert!((text.len() as u64) < MAX_TRANSCRIPT_BYTES && (text.len() as u64) <= QUOTAS.total(), "bounded: {} bytes", text.len());
        assert_eq!(summary.written.events, events.len() as u64);
        assert_eq!(summary.written.omitted_events, 0, "the hard limit was never reached");
        let texts: Vec<&str> = events.iter().filter(|e| !e.tail).filter_map(|e| e.text.as_deref()).collect();
        assert!(texts.contains(&"before the flood") && texts.contains(&"final words after the flood"), "{:?}", notes(&events));
        let robot = events.iter().find(|e| e.kind == Kind::ToolCall && e.robot_tool.as_deref() == Some("osc_sequence")).expect("the robot call after the flood");
        assert!(!robot.tail);
        assert!(events.iter().any(|e| e.kind == Kind::ToolResult && e.observation_id.as_deref() == Some("obs_000042")));
        assert!(events.iter().any(|e| e.kind == Kind::Shell && e.command.as_deref() == Some("echo after-the-flood") && e.output.as_deref() == Some("after-the-flood")));

        // The gateway's records as they came: within their quota.
        let shown: Vec<&AgentEvent> = events.iter().filter(|e| e.source == Some(Source::ModelApiGateway) && !e.tail).collect();
        let shown_bytes: usize = shown.iter().map(|e| e.to_line().len() + 1).sum();
        assert!(!shown.is_empty() && shown_bytes as u64 <= QUOTAS.gateway.bytes, "{} events, {shown_bytes} bytes", shown.len());
        // The notes: the quota reached, what was not shown, in all.
        let notes = notes(&events);
        assert!(notes.iter().any(|t| t.starts_with("model-API gateway reached its quota of 2 MiB")), "{notes:?}");
        let closing = notes.iter().find(|t| t.contains("in all over its quota")).expect("the closing note");
        assert!(closing.contains("403: "), "{closing}");
        let over = count_after(closing, "model-API gateway: ").unwrap();
        let skipped = notes.iter().any(|t| t.contains("model-API gateway records were skipped"));
        if skipped {
            assert!(over + (shown.len() as u64) < FLOOD as u64, "{closing}");
        } else {
            assert_eq!(over + shown.len() as u64, FLOOD as u64, "every request is shown or counted: {closing}");
        }
        assert_eq!(summary.over_quota.get("gateway"), Some(&(over - 200)), "{:?}", summary.over_quota);
        // The flood's tail: its last 200 records, in order, after the closing note.
        let tail: Vec<&AgentEvent> = events.iter().filter(|e| e.tail).collect();
        assert_eq!(tail.len(), 200);
        assert!(tail.iter().all(|e| e.source == Some(Source::ModelApiGateway)));
        assert!(tail.last().unwrap().text.as_deref().unwrap().contains(&format!("/v1/{:06}", FLOOD - 1)), "{:?}", tail.last());
        assert!(tail.windows(2).all(|w| w[0].seq < w[1].seq));
        let closing_at = events.iter().position(|e| e.text.as_deref() == Some(*closing)).unwrap();
        let first_tail = events.iter().position(|e| e.tail).unwrap();
        assert!(closing_at < first_tail, "the note stands before the tail");
        // The writer's own hard limit stays untouched; every seq but the tail's rises.
        let seqs: Vec<u64> = events.iter().filter(|e| !e.tail).map(|e| e.seq).collect();
        assert!(seqs.windows(2).all(|w| w[0] < w[1]));
    }

    fn small_quotas() -> Quotas {
        Quotas {
            stdout: Quota { bytes: 8 << 10, tail_events: 5, tail_bytes: 64 << 10 },
            stderr: Quota { bytes: 4 << 10, tail_events: 5, tail_bytes: 64 << 10 },
            gateway: Quota { bytes: 4 << 10, tail_events: 10, tail_bytes: 64 << 10 },
            notes: 8 << 10,
            closing: 3 << 10,
            summary_every: Duration::ZERO,
        }
    }

    fn feed(n: &mut Normalizer, sink: &mut Sink, stream: Stream, line: &str) {
        let got = n.capture(stream, Line::Complete(line.as_bytes()), "2026-01-01T00:00:00+00:00");
        sink.admit(stream, got);
    }

    /// Every gateway request is either written as it came, or counted in the notes by status; the notes keep
    /// to their own quota whatever their number, the closing note is written from what is kept for it, and the
    /// tail is the stream's last events.
    #[test]
    fn over_quota_events_are_counted_by_label_and_the_last_kept_while_other_streams_go_on() {
        let dir = tempfile::tempdir().unwrap();
        let q = small_quotas();
        let mut sink = Sink::open_with(Target::RunDir(dir.path().to_path_buf()), q).unwrap();
        let mut n = Normalizer::new(Harness::ClaudeCode, Path::new("/ws"), &[]);
        let (mut refused, mut usage) = (0u64, 0u64);
        for i in 0..3000 {
            if i % 7 == 0 {
                usage += 1;
                feed(&mut n, &mut sink, Stream::Gateway, &usage_record(i));
            } else {
                refused += 1;
                feed(&mut n, &mut sink, Stream::Gateway, &refused_record(i));
            }
            if i % 100 == 0 {
                feed(&mut n, &mut sink, Stream::Stderr, &format!("stderr line {i}"));
                // Each flush is a summary's chance (every 0 s here): the notes run out long before the flood.
                sink.flush(&mut n);
            }
        }
        feed(&mut n, &mut sink, Stream::Gateway, "not a record");
        sink.flush(&mut n);
        let stdout = after_the_flood();
        for line in stdout.lines() {
            feed(&mut n, &mut sink, Stream::Stdout, line);
        }
        sink.finish(&mut n);
        let summary = sink.close();
        let (text, events) = read_events(summary.path.as_ref().unwrap());
        assert!(text.len() as u64 <= q.total(), "{} bytes", text.len());

        // Stderr and stdout kept to their quotas and were written as they came.
        let stderr = events.iter().filter(|e| e.kind == Kind::Stderr).count();
        assert_eq!(stderr, 30);
        assert!(events.iter().any(|e| e.text.as_deref() == Some("final words after the flood") && !e.tail));
        assert!(events.iter().any(|e| e.robot_tool.as_deref() == Some("osc_sequence") && e.kind == Kind::ToolCall));

        let shown = events.iter().filter(|e| e.source == Some(Source::ModelApiGateway) && !e.tail).count() as u64;
        let notes = notes(&events);
        let notes_bytes: usize = events.iter().filter(|e| e.source == Some(Source::Runner)).map(|e| e.to_line().len() + 1).sum();
        assert!(notes_bytes as u64 <= q.notes, "{notes_bytes}");
        let periodic: Vec<&&str> = notes.iter().filter(|t| t.contains("more requests not shown")).collect();
        assert!(periodic.len() > 3, "{notes:?}");
        let closing = notes.iter().find(|t| t.contains("in all over its quota")).expect("the closing note, from its reserve");
        let over = count_after(closing, "model-API gateway: ").unwrap();
        assert_eq!(over + shown, 3001, "{closing}");
        let shown_refused = events.iter().filter(|e| e.source == Some(Source::ModelApiGateway) && !e.tail && e.kind == Kind::Other).count() as u64;
        let shown_usage = shown - shown_refused;
        assert_eq!(count_after(closing, "403: "), Some(refused - shown_refused), "{closing}");
        assert_eq!(count_after(closing, "200: "), Some(usage - shown_usage), "{closing}");
        assert_eq!(count_after(closing, "unparsed: "), Some(1), "{closing}");
        assert_eq!(summary.over_quota.get("gateway"), Some(&(over - 10)));
        assert!(!summary.over_quota.contains_key("stdout") && !summary.over_quota.contains_key("stderr"));
        // The tail: the last ten, the last of them the line that did not parse.
        let tail: Vec<&AgentEvent> = events.iter().filter(|e| e.tail).collect();
        assert_eq!(tail.len(), 10);
        assert_eq!(tail.last().unwrap().text.as_deref(), Some("a gateway record that does not parse"));
        assert!(tail[8].text.as_deref().unwrap().contains("in 2999 ms"), "{:?}", tail[8]);
    }

    /// A flood on the agent's stdout keeps the gateway's and stderr's events, and stdout's own last lines.
    #[test]
    fn a_stdout_flood_keeps_its_last_lines_and_hides_no_other_stream() {
        let dir = tempfile::tempdir().unwrap();
        let q = small_quotas();
        let mut sink = Sink::open_with(Target::RunDir(dir.path().to_path_buf()), q).unwrap();
        let mut n = Normalizer::new(Harness::Command, Path::new("/ws"), &[]);
        for i in 0..5000 {
            feed(&mut n, &mut sink, Stream::Stdout, &format!("flood line {i}"));
            if i % 1000 == 999 {
                feed(&mut n, &mut sink, Stream::Gateway, &usage_record(i));
                feed(&mut n, &mut sink, Stream::Stderr, &format!("warning {i}"));
                sink.flush(&mut n);
            }
        }
        // A line far longer than a tail's bytes is counted but cannot be kept.
        feed(&mut n, &mut sink, Stream::Stdout, &"y".repeat(200 << 10));
        feed(&mut n, &mut sink, Stream::Stdout, "the agent's last line");
        sink.finish(&mut n);
        let summary = sink.close();
        let (text, events) = read_events(summary.path.as_ref().unwrap());
        assert!(text.len() as u64 <= q.total());
        assert_eq!(events.iter().filter(|e| e.source == Some(Source::ModelApiGateway)).count(), 5);
        assert_eq!(events.iter().filter(|e| e.kind == Kind::Stderr).count(), 5);
        let tail: Vec<&str> = events.iter().filter(|e| e.tail).filter_map(|e| e.text.as_deref()).collect();
        assert_eq!(tail.len(), 5);
        assert_eq!(tail.last(), Some(&"the agent's last line"));
        assert!(tail.iter().all(|t| t.len() <= MAX_FIELD_BYTES));
        let closing = notes(&events).into_iter().find(|t| t.contains("in all over its quota")).unwrap().to_owned();
        assert!(closing.starts_with("the agent's stdout: ") && closing.contains("message: "), "{closing}");
        let written = events.iter().filter(|e| e.source == Some(Source::Stdout) && !e.tail).count() as u64;
        assert_eq!(count_after(&closing, "the agent's stdout: ").unwrap() + written, 5002);
    }

    #[test]
    fn a_tail_keeps_to_its_bytes_and_events() {
        let mut lane = Lane::new(Stream::Stderr, Quota { bytes: 0, tail_events: 3, tail_bytes: 1000 }, Duration::from_secs(5));
        for i in 0..10 {
            let ev = AgentEvent { seq: i, ..say(Kind::Stderr, Source::Stderr, "x") };
            let bytes = ev.to_line().len() as u64 + 1;
            let (now, note) = lane.take(ev, bytes, Label::Name("stderr"));
            assert!(now.is_none());
            assert_eq!(note.is_some(), i == 0, "the quota is said to be reached once");
        }
        assert_eq!(lane.tail.iter().map(|(e, _)| e.seq).collect::<Vec<_>>(), [7, 8, 9]);
        let big = say(Kind::Stderr, Source::Stderr, "z".repeat(600));
        let bytes = big.to_line().len() as u64 + 1;
        lane.take(big.clone(), bytes, Label::Name("stderr"));
        lane.take(big, bytes, Label::Name("stderr"));
        assert_eq!(lane.tail.len(), 1, "two of 600 bytes do not fit in 1000");
        assert!(lane.tail_bytes <= 1000 && lane.tail.iter().all(|(e, _)| e.tail));
        assert!(lane.since_note().unwrap().contains("12 more lines not shown (stderr: 12); 12 in all"));
        assert!(lane.since_note().is_none(), "nothing new since");
        let (note, tail) = lane.closing().unwrap();
        assert_eq!(tail.len(), 1);
        assert!(note.contains("12 lines in all over its quota") && note.contains("11 are left out"), "{note}");
    }

    /// The gateway's counters line (the requests past its record cap, appended when it stops) is one note; a line of
    /// an unknown shape stays what it was.
    #[test]
    fn the_gateways_overflow_line_is_one_note_and_unknown_lines_stay_unparsed() {
        let mut n = Normalizer::new(Harness::ClaudeCode, Path::new("/ws"), &[]);
        let t = "2026-01-01T00:00:00+00:00";
        let line = r#"{"kind":"overflow","requests":177188,"by_status":{"403":177000,"200":188},"first_unix_ms":1,"last_unix_ms":45000}"#;
        let got = n.capture(Stream::Gateway, Line::Complete(line.as_bytes()), t);
        assert_eq!(got.len(), 1);
        assert!(got[0].notice);
        let ev = &got[0].ev;
        assert_eq!((ev.kind, ev.source), (Kind::Other, Some(Source::Runner)));
        let text = ev.text.as_deref().unwrap();
        assert!(text.contains("requests: 177,188") && text.contains("by_status: (200: 188, 403: 177,000)"), "{text}");
        // The shape `netgate::Overflow` writes: its summary flattened, the statuses, the last request passed on.
        let real = json!({"kind": "overflow", "requests": 167188, "refused": 167000, "failed": 0, "unmetered": 0, "request_bytes": 0,
            "response_bytes": 0, "tunnel_bytes": 0, "responses_with_usage": 188, "input_tokens": 150400, "output_tokens": 0,
            "unreadable_lines": 0, "overflowed": 167188, "complete": true, "by_status": {"200": 188, "403": 167000},
            "last_passed_on": {"time": "2026-01-01T00:00:45Z", "method": "POST", "path": "/v1/messages", "status": 200, "usage": {"input_tokens": 800}}});
        let ev = n.line(Stream::Gateway, Line::Complete(real.to_string().as_bytes()), t);
        let text = ev[0].text.as_deref().unwrap();
        assert!(
            text.starts_with("model-API gateway: past its record cap it only counts requests; its counters: requests: 167,188; by_status: (200: 188, 403: 167,000); "),
            "{text}"
        );
        assert!(text.contains("refused: 167,000") && text.contains("complete: true") && text.contains("last_passed_on: (") && !text.contains("failed"), "{text}");
        for odd in [
            r#"{"kind":"overflow"}"#,
            r#"{"kind":"overflow","requests":"many","by_status":[1,2],"nested":{"a":{"b":{"c":1}}},"neg":-3,"f":1.5}"#,
        ] {
            let ev = n.line(Stream::Gateway, Line::Complete(odd.as_bytes()), t);
            assert_eq!(ev.len(), 1);
            assert_eq!(ev[0].source, Some(Source::Runner), "{odd}");
        }
        for unknown in [r#"{"kind":"other","requests":1}"#, "[1,2]", "{\"kind\":", r#""overflow""#] {
            let ev = n.line(Stream::Gateway, Line::Complete(unknown.as_bytes()), t);
            assert_eq!(ev.len(), 1);
            assert_eq!((ev[0].source, ev[0].text.as_deref()), (Some(Source::ModelApiGateway), Some("a gateway record that does not parse")), "{unknown}");
        }
        assert_eq!(thousands(0), "0");
        assert_eq!(thousands(999), "999");
        assert_eq!(thousands(1000), "1,000");
        assert_eq!(thousands(12_345_678), "12,345,678");
    }

    #[test]
    fn inline_images_are_cut_from_results() {
        let data = "A".repeat(5000);
        assert_eq!(without_inline_data(&format!("x data:image/png;base64,{data}\" y")), "x data:image/png;base64,<5000 bytes of base64>\" y");
        assert_eq!(without_inline_data("base64,abc"), "base64,abc");
    }
}
