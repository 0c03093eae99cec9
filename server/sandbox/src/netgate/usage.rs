//! Token accounting: the model's token usage read from each response the gateway passes on ([`TokenUsage`]),
//! from a bounded head and tail of it ([`Capture`]), for JSON bodies and server-sent events of the OpenAI chat,
//! OpenAI Responses and Anthropic Messages APIs.
use super::*;

/// Token usage a model API reported in a response, normalised. `api` says whose convention the counts follow:
/// `openai_chat` and `openai_responses` count cached tokens inside `input_tokens` and reasoning tokens inside
/// `output_tokens`; `anthropic_messages` counts cache reads (`cached_input_tokens`) and cache writes
/// (`cache_creation_input_tokens`) beside `input_tokens`, and its `total_tokens` is input + output (as in
/// the runner's `usage`).
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct TokenUsage {
    pub api: String,
    /// Input, output, cached input, reasoning and total tokens, the transcript's counts (same JSON fields).
    #[serde(flatten)]
    pub counts: Tokens,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cache_creation_input_tokens: Option<u64>,
}

/// The part of a response kept for reading token usage: its first [`HEAD_KEEP`] and last [`TAIL_KEEP`] bytes.
#[derive(Default)]
pub(super) struct Capture {
    pub(super) head: Vec<u8>,
    pub(super) tail: Vec<u8>,
    pub(super) total: u64,
    pub(super) sse: bool,
    /// Compressed despite `Accept-Encoding: identity`: not read.
    pub(super) encoded: bool,
}

impl Capture {
    pub(super) fn push(&mut self, d: &[u8]) {
        self.total += d.len() as u64;
        let room = HEAD_KEEP.saturating_sub(self.head.len()).min(d.len());
        self.head.extend_from_slice(&d[..room]);
        let rest = &d[room..];
        if !rest.is_empty() {
            self.tail.extend_from_slice(rest);
            if self.tail.len() > 2 * TAIL_KEEP {
                let cut = self.tail.len() - TAIL_KEEP;
                self.tail.drain(..cut);
            }
        }
    }

    pub(super) fn usage(&self) -> Option<TokenUsage> {
        if self.encoded || self.total == 0 {
            return None;
        }
        let whole = self.total == (self.head.len() + self.tail.len()) as u64;
        let sse = self.sse || self.head.starts_with(b"data:") || self.head.starts_with(b"event:");
        let mut acc = UsageAcc::default();
        match (sse, whole) {
            (true, true) => sse_events(&[&self.head[..], &self.tail[..]].concat(), &mut acc),
            (true, false) => {
                sse_events(&self.head, &mut acc);
                // The tail starts inside some line: from the next one.
                let from = self.tail.iter().position(|b| *b == b'\n').map_or(self.tail.len(), |i| i + 1);
                sse_events(&self.tail[from..], &mut acc);
            }
            (false, true) => {
                if let Ok(v) = serde_json::from_slice::<Value>(&[&self.head[..], &self.tail[..]].concat()) {
                    acc.feed(&v);
                }
            }
            (false, false) => {
                if let Some(u) = last_usage_object(&self.tail) {
                    acc.feed(&Value::Object(Map::from_iter([("usage".to_owned(), u)])));
                }
            }
        }
        acc.result()
    }
}

/// Feeds the JSON `data` of each server-sent event in `text` to `acc`.
pub(super) fn sse_events(text: &[u8], acc: &mut UsageAcc) {
    let text = String::from_utf8_lossy(text);
    let mut data = String::new();
    let mut dispatch = |data: &mut String| {
        if !data.is_empty() {
            if let Ok(v) = serde_json::from_str::<Value>(data) {
                acc.feed(&v);
            }
            data.clear();
        }
    };
    for line in text.split('\n').map(|l| l.strip_suffix('\r').unwrap_or(l)) {
        if line.is_empty() {
            dispatch(&mut data);
        } else if let Some(d) = line.strip_prefix("data:") {
            if !data.is_empty() {
                data.push('\n');
            }
            data.push_str(d.strip_prefix(' ').unwrap_or(d));
        }
    }
    dispatch(&mut data);
}

/// The value of the last `"usage"` key in a piece of JSON (the end of a body too large to keep whole).
pub(super) fn last_usage_object(text: &[u8]) -> Option<Value> {
    let key = b"\"usage\"";
    let mut end = text.len();
    while let Some(i) = text[..end].windows(key.len()).rposition(|w| w == key) {
        end = i;
        if i > 0 && text[i - 1] == b'\\' {
            continue; // inside a string
        }
        let rest = &text[i + key.len()..];
        let colon = rest.iter().position(|b| !b.is_ascii_whitespace())?;
        if rest[colon] != b':' {
            continue;
        }
        let mut values = serde_json::Deserializer::from_slice(&rest[colon + 1..]).into_iter::<Value>();
        if let Some(Ok(v @ Value::Object(_))) = values.next() {
            return Some(v);
        }
    }
    None
}

pub(super) fn count(m: &Map<String, Value>, path: &[&str]) -> Option<u64> {
    let (last, parents) = path.split_last()?;
    let mut at = m;
    for p in parents {
        at = at.get(*p)?.as_object()?;
    }
    at.get(*last)?.as_u64()
}

/// Usage as the responses of one request report it: the last complete report wins; Anthropic's stream reports in
/// parts (`message_start`, then cumulative `message_delta`s), merged.
#[derive(Default)]
pub(super) struct UsageAcc {
    pub(super) last: Option<TokenUsage>,
    pub(super) anthropic: Option<TokenUsage>,
}

impl UsageAcc {
    pub(super) fn feed(&mut self, v: &Value) {
        let kind = v.get("type").and_then(Value::as_str).unwrap_or_default();
        match kind {
            "message_start" => {
                if let Some(u) = v.pointer("/message/usage").and_then(Value::as_object) {
                    self.merge_anthropic(u);
                }
            }
            "message_delta" => {
                if let Some(u) = v.get("usage").and_then(Value::as_object) {
                    self.merge_anthropic(u);
                }
            }
            k if k.starts_with("response.") => {
                if let Some(u) = v.pointer("/response/usage").and_then(Value::as_object) {
                    self.last = Some(responses_usage(u));
                }
            }
            _ => {
                let Some(u) = v.get("usage").and_then(Value::as_object) else { return };
                if u.contains_key("prompt_tokens") || u.contains_key("completion_tokens") {
                    self.last = Some(chat_usage(u));
                } else if kind == "message" || u.contains_key("cache_read_input_tokens") || u.contains_key("cache_creation_input_tokens") {
                    self.merge_anthropic(u);
                } else if u.contains_key("input_tokens") || u.contains_key("output_tokens") {
                    self.last = Some(responses_usage(u));
                }
            }
        }
    }

    pub(super) fn merge_anthropic(&mut self, u: &Map<String, Value>) {
        let a = self.anthropic.get_or_insert_with(|| TokenUsage { api: "anthropic_messages".into(), ..TokenUsage::default() });
        for (key, field) in [
            ("input_tokens", &mut a.counts.input_tokens),
            ("output_tokens", &mut a.counts.output_tokens),
            ("cache_read_input_tokens", &mut a.counts.cached_input_tokens),
            ("cache_creation_input_tokens", &mut a.cache_creation_input_tokens),
        ] {
            if let Some(n) = count(u, &[key]) {
                *field = Some(n);
            }
        }
    }

    pub(super) fn result(self) -> Option<TokenUsage> {
        let mut u = self.anthropic.or(self.last)?;
        let c = &mut u.counts;
        if c.total_tokens.is_none() && (c.input_tokens.is_some() || c.output_tokens.is_some()) {
            c.total_tokens = Some(c.input_tokens.unwrap_or(0) + c.output_tokens.unwrap_or(0));
        }
        Some(u)
    }
}

/// OpenAI chat completions (and the OpenAI-compatible APIs: DeepSeek's `prompt_cache_hit_tokens`, Moonshot's
/// top-level `cached_tokens`).
pub(super) fn chat_usage(u: &Map<String, Value>) -> TokenUsage {
    TokenUsage {
        api: "openai_chat".into(),
        counts: Tokens {
            input_tokens: count(u, &["prompt_tokens"]),
            output_tokens: count(u, &["completion_tokens"]),
            cached_input_tokens: count(u, &["prompt_tokens_details", "cached_tokens"])
                .or_else(|| count(u, &["prompt_cache_hit_tokens"]))
                .or_else(|| count(u, &["cached_tokens"])),
            reasoning_tokens: count(u, &["completion_tokens_details", "reasoning_tokens"]).or_else(|| count(u, &["reasoning_tokens"])),
            total_tokens: count(u, &["total_tokens"]),
        },
        cache_creation_input_tokens: None,
    }
}

/// OpenAI Responses API.
pub(super) fn responses_usage(u: &Map<String, Value>) -> TokenUsage {
    TokenUsage {
        api: "openai_responses".into(),
        counts: Tokens {
            input_tokens: count(u, &["input_tokens"]),
            output_tokens: count(u, &["output_tokens"]),
            cached_input_tokens: count(u, &["input_tokens_details", "cached_tokens"]),
            reasoning_tokens: count(u, &["output_tokens_details", "reasoning_tokens"]),
            total_tokens: count(u, &["total_tokens"]),
        },
        cache_creation_input_tokens: None,
    }
}
