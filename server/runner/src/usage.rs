//! Token usage from harness logs (protocol §6.6–§6.7): every JSON line is walked recursively and each mapping
//! with a `usage` mapping yields a record (aliases normalised across providers); when some records come from
//! `result`-type lines only those count; consecutive identical records (the same message streamed in parts)
//! collapse; the rest are summed. Codex (`exec --json`) reports one `turn.completed` usage per turn.
use serde_json::{Map, Value};

use libero_records::agent_events::Tokens;
use libero_report::usage::{SOURCE_GATEWAY, SOURCE_NONE, SOURCE_STDOUT, StdoutFigures, Usage};

use crate::lines::{Line, LineSplitter};

/// The rollout's token figures from what the gateway saw ([`libero_sandbox::netgate::UsageSummary`]), for harnesses whose
/// stdout lacks them.
pub fn from_gateway(g: &libero_sandbox::netgate::UsageSummary) -> Usage {
    let available = g.responses_with_usage > 0;
    let some = |x: u64| available.then_some(x);
    Usage {
        available,
        requests_with_usage: g.responses_with_usage,
        lines_scanned: g.requests + g.unreadable_lines,
        input_tokens: some(g.input_tokens),
        output_tokens: some(g.output_tokens),
        cache_read_input_tokens: some(g.cached_input_tokens),
        reasoning_tokens: some(g.reasoning_tokens),
        total_tokens: some(g.total_tokens),
        ..Usage::default()
    }
}

/// The rollout's usage: the gateway's records when they hold any usage (every model request of a sandboxed
/// agent passes the gateway, and the agent cannot write its records), else what the harness printed on stdout
/// (runs without the sandbox), else nothing. Lines the agent prints into its CLI's stdout thus never count
/// when the gateway saw the traffic.
pub fn choose(stdout: Usage, gateway: Option<&libero_sandbox::netgate::UsageSummary>) -> Usage {
    let mut u = choose_source(stdout, gateway);
    if let Some(g) = gateway.filter(|g| !g.complete) {
        u.incomplete = Some(format!(
            "the gateway could not meter all model traffic: {} bytes through tunnels or forwards, {} responses without readable usage, {} unreadable record lines",
            g.tunnel_bytes, g.unmetered, g.unreadable_lines
        ));
    }
    u
}

fn choose_source(stdout: Usage, gateway: Option<&libero_sandbox::netgate::UsageSummary>) -> Usage {
    match gateway {
        Some(g) if g.responses_with_usage > 0 => {
            let mut u = from_gateway(g);
            if stdout.available {
                let agrees = (stdout.input_tokens, stdout.output_tokens, stdout.total_tokens) == (u.input_tokens, u.output_tokens, u.total_tokens);
                u.harness_stdout = Some(StdoutFigures {
                    input_tokens: stdout.input_tokens,
                    output_tokens: stdout.output_tokens,
                    total_tokens: stdout.total_tokens,
                    agrees,
                });
            }
            u.source = Some(SOURCE_GATEWAY.into());
            u
        }
        _ if stdout.available => Usage { source: Some(SOURCE_STDOUT.into()), ..stdout },
        _ => Usage { source: Some(SOURCE_NONE.into()), ..stdout },
    }
}

/// The token counts of a `usage` mapping, for a transcript's `usage` event.
pub(crate) fn tokens_of(usage: &Map<String, Value>) -> Option<Tokens> {
    record_of(usage).map(Record::tokens)
}

/// A Codex `turn.completed` event's counts.
pub(crate) fn codex_turn_tokens(v: &Value) -> Option<Tokens> {
    codex_turn_record(v).map(Record::tokens)
}

#[derive(Debug, Clone, Copy, Default, PartialEq)]
struct Record {
    input: Option<u64>,
    output: Option<u64>,
    cache_read: Option<u64>,
    reasoning: Option<u64>,
    total: Option<u64>,
}

impl Record {
    fn tokens(self) -> Tokens {
        Tokens { input_tokens: self.input, output_tokens: self.output, cached_input_tokens: self.cache_read, reasoning_tokens: self.reasoning, total_tokens: self.total }
    }
}

fn int(m: &Map<String, Value>, keys: &[&str]) -> Option<u64> {
    keys.iter().find_map(|k| match m.get(*k) {
        Some(Value::Number(n)) => n.as_u64().or_else(|| n.as_f64().filter(|f| f.is_finite() && *f >= 0.0).map(|f| f as u64)),
        _ => None,
    })
}

fn record_of(u: &Map<String, Value>) -> Option<Record> {
    let cache_read = int(u, &["cache_read_input_tokens", "cache_read_tokens", "cached_tokens", "cached_input_tokens", "cacheReadInputTokens", "inputCacheRead"]);
    let mut input = int(u, &["input_tokens", "prompt_tokens", "inputTokens"]);
    if input.is_none() {
        // Kimi: `inputOther` excludes the cached part.
        input = int(u, &["inputOther"]).map(|o| o + cache_read.unwrap_or(0));
    }
    let output = int(u, &["output_tokens", "completion_tokens", "outputTokens", "output"]);
    let reasoning = int(u, &["reasoning_tokens", "reasoningTokens"]);
    let total = int(u, &["total_tokens", "totalTokens"]).or_else(|| match (input, output) {
        (None, None) => None,
        (i, o) => Some(i.unwrap_or(0) + o.unwrap_or(0)),
    });
    let r = Record { input, output, cache_read, reasoning, total };
    (r != Record::default()).then_some(r)
}

fn walk(v: &Value, out: &mut Vec<Record>) {
    match v {
        Value::Object(m) => {
            if let Some(Value::Object(u)) = m.get("usage")
                && let Some(r) = record_of(u)
            {
                out.push(r);
            }
            for (k, child) in m {
                if k != "usage" {
                    walk(child, out);
                }
            }
        }
        Value::Array(xs) => xs.iter().for_each(|x| walk(x, out)),
        _ => {}
    }
}

/// Usage of JSON-lines texts (harness stdout in stream-json mode, archived session files).
pub fn usage_from_jsonl<'a>(texts: impl IntoIterator<Item = &'a str>) -> Usage {
    let mut scanner = UsageScanner::new(UsageFormat::Jsonl);
    for text in texts {
        scanner.push(text.as_bytes());
        scanner.gap();
    }
    scanner.finish()
}

/// Codex `exec --json` on stdout: each turn ends with a `turn.completed` event carrying that turn's usage summed
/// over its model requests (`input_tokens` includes `cached_input_tokens`; `reasoning_output_tokens` is part of
/// `output_tokens`); the turns of a run add up.
pub fn usage_from_codex_exec(text: &str) -> Usage {
    let mut scanner = UsageScanner::new(UsageFormat::CodexExec);
    scanner.push(text.as_bytes());
    scanner.finish()
}

/// Lines longer than this are counted but not parsed (a harness's usage lines are a few hundred bytes; parsing a
/// line costs many times its size in memory).
pub const MAX_USAGE_LINE_BYTES: usize = 1 << 20;

/// What a harness prints on stdout.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum UsageFormat {
    /// Nothing to read (the `command` harness).
    None,
    /// JSON lines with `usage` mappings anywhere (Claude Code, Qwen Code, Kimi Code, DeepSeek).
    Jsonl,
    /// Codex `exec --json` events.
    CodexExec,
}

/// The sum of a sequence of records, consecutive repeats collapsed.
#[derive(Debug, Default)]
struct Sum {
    count: u64,
    last: Option<Record>,
    input: Option<u64>,
    output: Option<u64>,
    cache_read: Option<u64>,
    reasoning: Option<u64>,
    total: Option<u64>,
}

impl Sum {
    fn add(&mut self, r: Record, dedup: bool) {
        if dedup && self.last == Some(r) {
            return;
        }
        self.last = Some(r);
        self.count += 1;
        for (acc, v) in [
            (&mut self.input, r.input),
            (&mut self.output, r.output),
            (&mut self.cache_read, r.cache_read),
            (&mut self.reasoning, r.reasoning),
            (&mut self.total, r.total),
        ] {
            if let Some(v) = v {
                *acc = Some(acc.unwrap_or(0).saturating_add(v));
            }
        }
    }

    fn usage(&self, lines_scanned: u64) -> Usage {
        Usage {
            available: self.count > 0,
            requests_with_usage: self.count,
            lines_scanned,
            input_tokens: self.input,
            output_tokens: self.output,
            cache_read_input_tokens: self.cache_read,
            reasoning_tokens: self.reasoning,
            total_tokens: self.total,
            ..Usage::default()
        }
    }
}

/// Token usage from a harness's stdout fed in pieces of any size (the log is never held whole): lines are
/// split as bytes arrive, each kept only up to [`MAX_USAGE_LINE_BYTES`], and the records summed as they are
/// found, in constant memory. JSON lines: when some records come from `result`-type lines only those count;
/// consecutive identical records collapse. Codex: the `turn.completed` events add up.
#[derive(Debug)]
pub struct UsageScanner {
    lines: LineSplitter,
    sums: Sums,
}

/// What the lines of one log added up to so far.
#[derive(Debug)]
struct Sums {
    format: UsageFormat,
    lines: u64,
    all: Sum,
    results: Sum,
}

impl UsageScanner {
    pub fn new(format: UsageFormat) -> Self {
        Self { lines: LineSplitter::new(MAX_USAGE_LINE_BYTES), sums: Sums { format, lines: 0, all: Sum::default(), results: Sum::default() } }
    }

    /// The next bytes of the log.
    pub fn push(&mut self, bytes: &[u8]) {
        if self.sums.format == UsageFormat::None {
            return;
        }
        self.lines.push(bytes, |l| self.sums.line(l));
    }

    /// Bytes of the log were skipped here: the line under way ends.
    pub fn gap(&mut self) {
        self.lines.end(|l| self.sums.line(l));
    }

    pub fn finish(mut self) -> Usage {
        self.gap();
        let s = self.sums;
        match s.format {
            UsageFormat::None => Usage::default(),
            UsageFormat::CodexExec => s.all.usage(s.lines),
            UsageFormat::Jsonl if s.results.count > 0 => s.results.usage(s.lines),
            UsageFormat::Jsonl => s.all.usage(s.lines),
        }
    }
}

impl Sums {
    fn line(&mut self, line: Line<'_>) {
        let line = match line {
            Line::Overlong(_) => {
                self.lines += 1;
                return;
            }
            Line::Complete(l) => l,
        };
        if line.iter().all(u8::is_ascii_whitespace) {
            return;
        }
        self.lines += 1;
        // Only lines that can hold a usage record are parsed.
        let needle: &[u8] = if self.format == UsageFormat::CodexExec { b"turn.completed" } else { b"usage" };
        if !line.windows(needle.len()).any(|w| w == needle) {
            return;
        }
        let Ok(v) = serde_json::from_slice::<Value>(line) else { return };
        match self.format {
            UsageFormat::None => {}
            UsageFormat::CodexExec => {
                if let Some(r) = codex_turn_record(&v) {
                    self.all.add(r, false);
                }
            }
            UsageFormat::Jsonl => {
                let mut rs = Vec::new();
                walk(&v, &mut rs);
                let is_result = matches!(v.get("type").and_then(Value::as_str), Some("result" | "turn.result" | "session.result"));
                for r in rs {
                    if is_result {
                        self.results.add(r, true);
                    }
                    self.all.add(r, true);
                }
            }
        }
    }
}

/// A Codex `turn.completed` event's usage (its `reasoning_output_tokens` are reasoning tokens).
fn codex_turn_record(v: &Value) -> Option<Record> {
    if v["type"] != "turn.completed" {
        return None;
    }
    let mut u = v.get("usage")?.as_object()?.clone();
    if let Some(r) = u.get("reasoning_output_tokens").cloned() {
        u.insert("reasoning_tokens".into(), r);
    }
    record_of(&u)
}

#[cfg(test)]
mod tests {

    /// Tokens that went through a tunnel were never counted: the chosen usage says it is a lower bound.
    #[test]
    fn usage_is_marked_incomplete_when_a_tunnel_carried_bytes() {
        let g = libero_sandbox::netgate::UsageSummary { requests: 2, responses_with_usage: 1, input_tokens: 10, output_tokens: 5, total_tokens: 15, ..Default::default() };
        assert_eq!(choose(Usage::default(), Some(&g)).incomplete, None, "a complete summary");
        let tunnelled = libero_sandbox::netgate::UsageSummary { tunnel_bytes: 4096, complete: false, ..g };
        let u = choose(Usage::default(), Some(&tunnelled));
        assert_eq!(u.total_tokens, Some(15));
        assert!(u.incomplete.as_deref().is_some_and(|w| w.contains("4096 bytes through tunnels")), "{u:?}");
    }

    use super::*;

    #[test]
    fn the_gateways_summary_gives_the_rollouts_figures_only_when_it_saw_usage() {
        let g = libero_sandbox::netgate::UsageSummary {
            requests: 5,
            responses_with_usage: 4,
            input_tokens: 101,
            output_tokens: 36,
            total_tokens: 137,
            ..Default::default()
        };
        let u = from_gateway(&g);
        assert!(u.available);
        assert_eq!((u.requests_with_usage, u.input_tokens, u.total_tokens), (4, Some(101), Some(137)));
        let none = from_gateway(&libero_sandbox::netgate::UsageSummary { requests: 3, ..Default::default() });
        assert!(!none.available && none.input_tokens.is_none() && none.total_tokens.is_none());
    }

    #[test]
    fn claude_code_stream_json_counts_the_result_line_only() {
        // Captured shape of `claude --print --output-format stream-json --verbose` (values shortened).
        let log = r#"{"type":"system","subtype":"init","cwd":"/tmp/ws","session_id":"5b1c","tools":["mcp__libero__start_episode"],"model":"claude-opus-5"}
{"type":"assistant","message":{"id":"msg_01","type":"message","role":"assistant","content":[{"type":"text","text":"Starting."}],"usage":{"input_tokens":4,"cache_creation_input_tokens":6120,"cache_read_input_tokens":11873,"output_tokens":8}},"session_id":"5b1c"}
{"type":"assistant","message":{"id":"msg_01","type":"message","role":"assistant","content":[{"type":"tool_use","id":"toolu_1","name":"mcp__libero__start_episode","input":{}}],"usage":{"input_tokens":4,"cache_creation_input_tokens":6120,"cache_read_input_tokens":11873,"output_tokens":8}},"session_id":"5b1c"}
{"type":"user","message":{"role":"user","content":[{"tool_use_id":"toolu_1","type":"tool_result","content":[{"type":"text","text":"{\"ok\": true}"}]}]},"session_id":"5b1c"}
{"type":"result","subtype":"success","is_error":false,"duration_ms":91234,"num_turns":12,"result":"Done.","session_id":"5b1c","total_cost_usd":0.91,"usage":{"input_tokens":120,"cache_creation_input_tokens":30211,"cache_read_input_tokens":402113,"output_tokens":5120,"server_tool_use":{"web_search_requests":0}}}
"#;
        let u = usage_from_jsonl([log]);
        assert!(u.available);
        assert_eq!((u.requests_with_usage, u.lines_scanned), (1, 5));
        assert_eq!((u.input_tokens, u.output_tokens, u.cache_read_input_tokens), (Some(120), Some(5120), Some(402113)));
        assert_eq!(u.total_tokens, Some(5240));
    }

    #[test]
    fn claude_without_a_result_line_sums_messages_and_collapses_repeats() {
        let log = r#"{"type":"assistant","message":{"usage":{"input_tokens":10,"output_tokens":5}}}
{"type":"assistant","message":{"usage":{"input_tokens":10,"output_tokens":5}}}
{"type":"assistant","message":{"usage":{"input_tokens":20,"output_tokens":7}}}"#;
        let u = usage_from_jsonl([log]);
        assert_eq!((u.requests_with_usage, u.total_tokens), (2, Some(42)));
    }

    #[test]
    fn qwen_code_stream_json_result() {
        let log = r#"{"type":"system","subtype":"init","session_id":"q1","model":"qwen3.8-max"}
{"type":"assistant","message":{"role":"assistant","content":[{"type":"text","text":"ok"}],"usage":{"input_tokens":900,"output_tokens":40,"cache_read_input_tokens":0}}}
{"type":"result","subtype":"success","is_error":false,"num_turns":3,"usage":{"input_tokens":15800,"output_tokens":910,"cache_read_input_tokens":7000,"total_tokens":16710}}"#;
        let u = usage_from_jsonl([log]);
        assert_eq!((u.input_tokens, u.output_tokens, u.total_tokens), (Some(15800), Some(910), Some(16710)));
    }

    #[test]
    fn kimi_code_counts_input_other_plus_cache_reads() {
        let log = r#"{"type":"assistant","content":"…","usage":{"inputOther":1200,"inputCacheRead":3000,"inputCacheCreation":0,"output":150}}
{"type":"assistant","content":"…","usage":{"inputOther":300,"inputCacheRead":4200,"output":90}}"#;
        let u = usage_from_jsonl([log]);
        assert_eq!(u.input_tokens, Some(1200 + 3000 + 300 + 4200));
        assert_eq!(u.output_tokens, Some(240));
        assert_eq!(u.total_tokens, Some(8700 + 240));
    }

    #[test]
    fn deepseek_session_openai_style_usage() {
        let log = r#"{"kind":"llm.response","data":{"model":"deepseek-v4-pro","usage":{"prompt_tokens":5000,"completion_tokens":700,"total_tokens":5700,"prompt_tokens_details":{"cached_tokens":4096},"completion_tokens_details":{"reasoning_tokens":300}}}}
{"kind":"tool.result","data":{"ok":true}}
not json at all
{"kind":"llm.response","data":{"usage":{"prompt_tokens":6000,"completion_tokens":100,"total_tokens":6100,"usage":true}}}"#;
        let u = usage_from_jsonl([log]);
        assert_eq!(u.lines_scanned, 4);
        assert_eq!((u.input_tokens, u.output_tokens, u.total_tokens), (Some(11000), Some(800), Some(11800)));
        // Nested details are not `usage` mappings: cached/reasoning come only from top-level aliases.
        assert_eq!(u.reasoning_tokens, None);
    }

    #[test]
    fn codex_exec_json_sums_its_turns() {
        // Captured from `codex exec --json` 0.169.0 against the scripted endpoint of tests/real_clis.rs (shortened).
        let log = r#"{"type":"thread.started","thread_id":"01a20be2-85c6-7dd1-925d-8c34d3b12771"}
{"type":"item.completed","item":{"id":"item_0","type":"error","message":"Model metadata for `scripted` not found."}}
{"type":"turn.started"}
{"type":"item.completed","item":{"id":"item_1","type":"mcp_tool_call","server":"libero","tool":"start_episode","arguments":{},"result":{"content":[{"type":"text","text":"{}"}]},"error":null,"status":"completed"}}
{"type":"item.completed","item":{"id":"item_5","type":"agent_message","text":"The episode is finished."}}
{"type":"turn.completed","usage":{"input_tokens":6000,"cached_input_tokens":2000,"cache_write_input_tokens":0,"output_tokens":150,"reasoning_output_tokens":40}}
{"type":"turn.started"}
{"type":"turn.completed","usage":{"input_tokens":1000,"cached_input_tokens":0,"output_tokens":10,"reasoning_output_tokens":0}}"#;
        let u = usage_from_codex_exec(log);
        assert!(u.available);
        assert_eq!((u.requests_with_usage, u.lines_scanned), (2, 8));
        assert_eq!((u.input_tokens, u.cache_read_input_tokens, u.output_tokens), (Some(7000), Some(2000), Some(160)));
        assert_eq!((u.reasoning_tokens, u.total_tokens), (Some(40), Some(7160)));
        assert!(!usage_from_codex_exec(r#"{"type":"turn.failed","error":{"message":"x"}}"#).available);
    }
}
