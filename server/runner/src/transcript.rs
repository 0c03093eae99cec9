//! The agent's transcript (docs/agent_transcript.md): what the harness's CLI prints, normalised into one event
//! schema ([`libero_episode::agent_events`]) while the agent runs, so that a reviewer sees what the agent read,
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
use std::collections::{HashMap, VecDeque};
use std::fs::File;
use std::os::unix::fs::{FileExt, OpenOptionsExt};
use std::path::{Component, Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::thread::JoinHandle;
use std::time::Duration;

use libero_episode::agent_events::{AgentEvent, Kind, MAX_FIELD_BYTES, Source, Tokens, TranscriptFile, Written, bound_str};
use libero_episode::json::utc_now_iso;
use libero_episode::tools::ToolName;
use serde::Serialize;
use serde_json::{Map, Value, json};

use crate::harness::Harness;
use crate::lines::{Line, LineSplitter};
use crate::logs::scrub_text;

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
    fn name(self) -> &'static str {
        match self {
            Stream::Stdout => "stdout",
            Stream::Stderr => "stderr",
            Stream::Gateway => "model-API gateway records",
        }
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
    harness: Harness,
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
            harness,
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
        let raw = match (stream, line) {
            (_, Line::Overlong(n)) => {
                let kind = if stream == Stream::Stderr { Kind::Stderr } else { Kind::Other };
                vec![say(kind, Source::Runner, format!("a {} line of {n} bytes (more than {MAX_LINE_BYTES}) was not parsed", stream.name()))]
            }
            (_, Line::Complete(b)) if b.iter().all(u8::is_ascii_whitespace) => Vec::new(),
            (Stream::Stderr, Line::Complete(b)) => vec![say(Kind::Stderr, Source::Stderr, text_of(b))],
            (Stream::Gateway, Line::Complete(b)) => self.gateway(b).into_iter().collect(),
            (Stream::Stdout, Line::Complete(b)) => self.stdout(b),
        };
        raw.into_iter().map(|ev| self.finish_event(ev, t)).collect()
    }

    /// `bytes` of `stream` were not read (a flood, or a sparse file).
    pub fn skipped(&mut self, stream: Stream, bytes: u64, t: &str) -> AgentEvent {
        let ev = say(Kind::Other, Source::Runner, format!("{bytes} bytes of the agent's {} were skipped (written faster than they are read)", stream.name()));
        self.finish_event(ev, t)
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
        if self.harness == Harness::Command {
            return vec![say(Kind::Message, Source::Stdout, text_of(b))];
        }
        match serde_json::from_slice::<Value>(b) {
            Ok(Value::Object(m)) => self.json_line(&m).unwrap_or_else(|| vec![say(Kind::Other, Source::Stdout, text_of(b))]),
            // DeepSeek's headless profile prints its final answer as plain text.
            _ if self.harness == Harness::Deepseek => vec![say(Kind::Message, Source::Stdout, text_of(b))],
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
    /// when the request was refused or failed.
    fn gateway(&mut self, b: &[u8]) -> Option<AgentEvent> {
        let Ok(r) = serde_json::from_slice::<crate::netgate::Record>(b) else {
            return Some(say(Kind::Other, Source::ModelApiGateway, "a gateway record that does not parse"));
        };
        let what = format!("{} {}{} → {} in {} ms", r.method, r.host, r.path, r.status, r.duration_ms);
        if let Some(u) = &r.usage {
            return Some(usage_event(Source::ModelApiGateway, u.counts, &format!("model request {what}")));
        }
        let refused = r.mode == crate::netgate::Mode::Refused;
        (refused || r.error.is_some() || r.status >= 400).then(|| {
            let why = r.error.as_deref().map(|e| format!(": {e}")).unwrap_or_default();
            say(Kind::Other, Source::ModelApiGateway, format!("{} {what}{why}", if refused { "refused" } else { "failed" }))
        })
    }
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
    fn poll(&mut self, n: &mut Normalizer, budget: usize, buf: &mut [u8], out: &mut Vec<AgentEvent>) -> std::io::Result<usize> {
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
            self.lines.end(|l| out.extend(n.line(self.stream, l, &t)));
            out.push(n.skipped(self.stream, 0, &t));
            return Ok(0);
        }
        if size - self.offset > SKIP_BEYOND {
            let to = size - budget as u64;
            self.lines.end(|l| out.extend(n.line(self.stream, l, &t)));
            out.push(n.skipped(self.stream, to - self.offset, &t));
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
            self.lines.push(&buf[..k], |l| out.extend(n.line(stream, l, &t)));
        }
        Ok(read)
    }

    /// The stream ended: its last line without a newline counts.
    fn end(&mut self, n: &mut Normalizer, out: &mut Vec<AgentEvent>) {
        let t = utc_now_iso();
        let stream = self.stream;
        self.lines.end(|l| out.extend(n.line(stream, l, &t)));
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
}

impl Sink {
    fn open(target: Target) -> anyhow::Result<Self> {
        let (path, remote) = match target {
            Target::RunDir(dir) => (dir.join(libero_episode::agent_events::AGENT_EVENTS_FILE), None),
            Target::Remote { server_url, episode_id, local } => (local, Some((server_url, episode_id))),
        };
        let file = TranscriptFile::open(&path).map_err(|e| anyhow::anyhow!("cannot write the transcript {}: {e}", path.display()))?;
        Ok(Self { file, remote, summary: Summary { path: Some(path), posted: None, ..Summary::default() } })
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
        let stop = Arc::new(AtomicBool::new(false));
        let stopping = stop.clone();
        let thread = Sink::open(target).map_err(|e| format!("{e:#}")).and_then(|sink| {
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
            local: r.rollout_dir.join(libero_episode::agent_events::AGENT_EVENTS_FILE),
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
        let mut events = Vec::new();
        // After the agent is gone, each stream is read to its end (a flood beyond the skip bound is skipped).
        let budget = if last { SKIP_BEYOND as usize } else { READ_PER_POLL };
        for (i, tail) in tails.iter_mut().enumerate() {
            if failed[i] || sink.file.is_full() {
                continue;
            }
            if let Err(e) = tail.poll(&mut n, budget, &mut buf, &mut events) {
                failed[i] = true;
                sink.error(format!("reading the agent's {}: {e}", tail.stream.name()));
            }
        }
        if last {
            for tail in &mut tails {
                tail.end(&mut n, &mut events);
            }
            events.extend(n.finish(&utc_now_iso()));
            sink.write(events);
            return sink.close();
        }
        sink.write(events);
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

    #[test]
    fn inline_images_are_cut_from_results() {
        let data = "A".repeat(5000);
        assert_eq!(without_inline_data(&format!("x data:image/png;base64,{data}\" y")), "x data:image/png;base64,<5000 bytes of base64>\" y");
        assert_eq!(without_inline_data("base64,abc"), "base64,abc");
    }
}
