//! The agent's transcript: what its CLI printed, normalised by the runner into one event schema and kept in the
//! episode's private run directory as `agent_events.jsonl` (docs/agent_transcript.md). The bytes behind it are
//! the agent's, so every field is bounded here ([`MAX_FIELD_BYTES`]) and the whole file is bounded by the writer
//! ([`TranscriptFile`], [`MAX_TRANSCRIPT_BYTES`]); the runner scrubs secrets before an event gets here. The server
//! reads this file and never opens anything the agent named in it.
use std::fs::File;
use std::io::Write;
use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::json::open_jsonl_for_append;

/// The file's name in the run directory (or, when the server is on another machine, the rollout directory).
pub const AGENT_EVENTS_FILE: &str = "agent_events.jsonl";
/// Most bytes of one text field (`text`, `arguments`, `command`, `output`, `path`); longer ones are cut and the
/// event says `truncated` (the same order of size as the action log's 16 KiB per field).
pub const MAX_FIELD_BYTES: usize = 8 * 1024;
/// Most bytes of a name-like field (`tool`, `call_id`, `observation_id`, `workspace_path`'s parts are paths).
pub const MAX_NAME_BYTES: usize = 256;
/// Most bytes of a transcript (the scrubbed logs keep 16 MiB of each stream, 8 MiB head and 8 MiB tail).
pub const MAX_TRANSCRIPT_BYTES: u64 = 16 << 20;
/// Kept free below [`MAX_TRANSCRIPT_BYTES`] for the events that say what was left out.
const CLOSING_RESERVE: u64 = 16 << 10;

/// What an event is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Kind {
    /// Text the agent said (a command agent's stdout line, a CLI's assistant message).
    Message,
    /// A reasoning summary or thinking block, as far as the CLI prints one.
    Reasoning,
    /// A shell command with its exit code (where the CLI reports one) and bounded output.
    Shell,
    /// A file the agent read through its CLI's read tool.
    FileRead,
    /// An image the agent looked at through its CLI's image or read tool.
    ImageView,
    /// Any other tool call, MCP robot calls included (`robot_tool`, `observation_id`).
    ToolCall,
    /// The result of a tool call (not of a shell command, which is one `shell` event).
    ToolResult,
    /// Token counts, from the CLI's stdout or from the runner's model-API gateway (`source`).
    Usage,
    /// A line of the CLI's stderr.
    Stderr,
    /// Anything else, never an error: unknown lines, notices, what was left out.
    #[default]
    Other,
}

/// Where an event's bytes came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Source {
    /// The CLI's stdout (the agent can write there too: its commands run as the CLI's user).
    Stdout,
    /// The CLI's stderr.
    Stderr,
    /// The runner's model-API gateway records, which the agent cannot write.
    ModelApiGateway,
    /// The runner itself (limits reached, bytes skipped).
    Runner,
}

/// Token counts of a `usage` event (each as the source reported it; see the schema document for conventions).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Tokens {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub input_tokens: Option<u64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub output_tokens: Option<u64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cached_input_tokens: Option<u64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reasoning_tokens: Option<u64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub total_tokens: Option<u64>,
}

/// One line of `agent_events.jsonl`. Fields a kind does not use are left out.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct AgentEvent {
    /// When the runner captured it (UTC, ISO-8601): the CLI's own timestamps are the agent's to forge.
    pub t: String,
    /// 0, 1, 2, … in capture order; a gap means events were left out.
    pub seq: u64,
    pub kind: Kind,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub source: Option<Source>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub text: Option<String>,
    /// The tool as the CLI named it (`mcp__libero__osc_sequence`, `Bash`, `read_file`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tool: Option<String>,
    /// `start_episode`, `osc_sequence` or `finish_episode` when the call is one of the episode's MCP tools.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub robot_tool: Option<String>,
    /// The CLI's id tying a call to its result.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub call_id: Option<String>,
    /// The call's arguments as compact JSON, bounded.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub arguments: Option<String>,
    /// Robot calls: the observation the call acted on (the newest one the agent had been given); robot results:
    /// the observation the call returned.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub observation_id: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub is_error: Option<bool>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub command: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub exit_code: Option<i64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub output: Option<String>,
    /// The path as the agent gave it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub path: Option<String>,
    /// The path relative to the workspace, when it lies inside it (resolved lexically, nothing opened).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub workspace_path: Option<String>,
    /// The file relative to `benchmark_inputs/current_observation/` when the path names a published observation
    /// file: the review shows the episode's own private copy of it, never the agent's file.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub observation_file: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tokens: Option<Tokens>,
    /// A field was cut to its bound.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub truncated: bool,
    /// One of the last events of a stream that went over its share of the transcript, written when the agent
    /// had finished: `t` and `seq` are still when it was captured, so it stands after events captured later.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub tail: bool,
}

/// `s` cut to at most `max` bytes on a character boundary, and whether it was cut.
pub fn bound_str(s: &str, max: usize) -> (String, bool) {
    if s.len() <= max {
        return (s.to_owned(), false);
    }
    let mut end = max;
    while !s.is_char_boundary(end) {
        end -= 1;
    }
    (s[..end].to_owned(), true)
}

impl AgentEvent {
    /// A bare event of `kind` from `source`.
    pub fn new(kind: Kind, source: Source) -> Self {
        Self { kind, source: Some(source), ..Self::default() }
    }

    /// Every free-text field, for a transformation such as secret scrubbing.
    pub fn texts_mut(&mut self) -> impl Iterator<Item = &mut String> {
        [
            &mut self.text,
            &mut self.tool,
            &mut self.robot_tool,
            &mut self.call_id,
            &mut self.arguments,
            &mut self.observation_id,
            &mut self.command,
            &mut self.output,
            &mut self.path,
            &mut self.workspace_path,
            &mut self.observation_file,
        ]
        .into_iter()
        .flatten()
    }

    /// Cuts every field to its bound (names to [`MAX_NAME_BYTES`], the rest to [`MAX_FIELD_BYTES`]) and sets
    /// `truncated` if any was cut; the time is kept only if it is short.
    pub fn bounded(mut self) -> Self {
        let mut cut = false;
        let mut bound = |field: &mut Option<String>, max: usize| {
            if let Some(v) = field.as_mut() {
                let (b, c) = bound_str(v, max);
                *v = b;
                cut |= c;
            }
        };
        for f in [&mut self.tool, &mut self.robot_tool, &mut self.call_id, &mut self.observation_id] {
            bound(f, MAX_NAME_BYTES);
        }
        for f in [
            &mut self.text,
            &mut self.arguments,
            &mut self.command,
            &mut self.output,
            &mut self.path,
            &mut self.workspace_path,
            &mut self.observation_file,
        ] {
            bound(f, MAX_FIELD_BYTES);
        }
        if self.t.len() > 64 {
            self.t = bound_str(&self.t, 64).0;
        }
        self.truncated |= cut;
        self
    }

    /// The event's JSON line (no newline).
    pub fn to_line(&self) -> String {
        serde_json::to_string(self).unwrap_or_else(|_| "{}".to_owned())
    }
}

/// What a writer kept and left out.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct Written {
    pub events: u64,
    pub bytes: u64,
    /// Events not written because the transcript reached [`MAX_TRANSCRIPT_BYTES`].
    pub omitted_events: u64,
}

/// An append-only transcript bounded at [`MAX_TRANSCRIPT_BYTES`]. Once an event would not fit, it and every
/// later one are counted instead of written, and one `other` event (from the reserve kept for it) says so.
pub struct TranscriptFile {
    file: File,
    size: u64,
    limit: u64,
    written: Written,
    /// The limit was reached (and said so).
    full: bool,
}

impl TranscriptFile {
    /// Opens (creating) `path` for appending, without following a link; an existing transcript goes on where it
    /// ends (a torn last line is ended first).
    pub fn open(path: &Path) -> std::io::Result<Self> {
        Self::open_with_limit(path, MAX_TRANSCRIPT_BYTES)
    }

    /// With another limit (tests).
    pub fn open_with_limit(path: &Path, limit: u64) -> std::io::Result<Self> {
        if std::fs::symlink_metadata(path).is_ok_and(|m| !m.is_file()) {
            return Err(std::io::Error::other(format!("{} is not a regular file", path.display())));
        }
        let (file, _) = open_jsonl_for_append(path)?;
        let size = file.metadata()?.len();
        Ok(Self { file, size, limit, written: Written::default(), full: size + CLOSING_RESERVE.min(limit / 2) >= limit })
    }

    /// Appends the events that fit (one write per call), bounded field by field.
    pub fn append(&mut self, events: Vec<AgentEvent>) -> std::io::Result<()> {
        let mut out = String::new();
        let reserve = CLOSING_RESERVE.min(self.limit / 2);
        for ev in events {
            if self.full {
                self.written.omitted_events += 1;
                continue;
            }
            let seq = ev.seq;
            let t = ev.t.clone();
            let line = ev.bounded().to_line();
            if self.size + out.len() as u64 + line.len() as u64 + 1 + reserve > self.limit {
                self.full = true;
                self.written.omitted_events += 1;
                let mut note = AgentEvent::new(Kind::Other, Source::Runner);
                note.t = t;
                note.seq = seq;
                note.text = Some(format!(
                    "the transcript reached its limit of {} bytes: this and later events are left out (the scrubbed logs keep the \
                     first and last 8 MiB of each stream)",
                    self.limit
                ));
                out.push_str(&note.to_line());
                out.push('\n');
                continue;
            }
            out.push_str(&line);
            out.push('\n');
            self.written.events += 1;
        }
        if !out.is_empty() {
            self.file.write_all(out.as_bytes())?;
            self.size += out.len() as u64;
            self.written.bytes += out.len() as u64;
        }
        Ok(())
    }

    /// Whether later events are only counted.
    pub fn is_full(&self) -> bool {
        self.full
    }

    pub fn written(&self) -> Written {
        self.written
    }

    /// Flushes to disk.
    pub fn sync(&mut self) -> std::io::Result<()> {
        self.file.sync_data()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fields_are_cut_on_character_boundaries_and_flagged() {
        let mut ev = AgentEvent::new(Kind::Message, Source::Stdout);
        ev.text = Some("é".repeat(MAX_FIELD_BYTES));
        ev.tool = Some("x".repeat(1000));
        let b = ev.bounded();
        assert!(b.truncated);
        assert!(b.text.as_ref().unwrap().len() <= MAX_FIELD_BYTES && b.text.as_ref().unwrap().chars().all(|c| c == 'é'));
        assert_eq!(b.tool.unwrap().len(), MAX_NAME_BYTES);
        let small = AgentEvent { text: Some("hi".into()), ..AgentEvent::new(Kind::Message, Source::Stdout) }.bounded();
        assert!(!small.truncated);
        assert!(!small.to_line().contains("truncated"), "an untruncated event does not carry the flag");
    }

    #[test]
    fn a_transcript_stops_at_its_limit_and_says_so_once() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join(AGENT_EVENTS_FILE);
        let mut f = TranscriptFile::open_with_limit(&path, 64 << 10).unwrap();
        let events: Vec<AgentEvent> = (0..100)
            .map(|i| AgentEvent { seq: i, t: "2026-01-01T00:00:00+00:00".into(), text: Some("y".repeat(4000)), ..AgentEvent::new(Kind::Message, Source::Stdout) })
            .collect();
        f.append(events).unwrap();
        assert!(f.is_full());
        let w = f.written();
        assert_eq!(w.events + w.omitted_events, 100);
        assert!(w.events >= 10 && w.omitted_events > 0, "{w:?}");
        let text = std::fs::read_to_string(&path).unwrap();
        assert!(text.len() as u64 <= 64 << 10);
        let lines: Vec<AgentEvent> = text.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
        assert_eq!(lines.len() as u64, w.events + 1);
        let last = lines.last().unwrap();
        assert_eq!((last.kind, last.source), (Kind::Other, Some(Source::Runner)));
        assert_eq!(last.seq, w.events, "the note takes the first left-out event's place");
        f.append(vec![AgentEvent::new(Kind::Message, Source::Stdout)]).unwrap();
        assert_eq!(std::fs::read_to_string(&path).unwrap(), text, "nothing more once full");
    }

    #[test]
    fn a_planted_link_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("elsewhere");
        std::fs::write(&target, "x").unwrap();
        let link = dir.path().join(AGENT_EVENTS_FILE);
        std::os::unix::fs::symlink(&target, &link).unwrap();
        assert!(TranscriptFile::open(&link).is_err());
        assert_eq!(std::fs::read_to_string(&target).unwrap(), "x");
    }
}
