//! A rollout's token figures as its record keeps them (`usage` in `rollouts.jsonl`, `harness_usage.json`). The runner
//! measures them (its `usage` module: harness logs, the model-API gateway); the report reads them with their source.
use serde::{Deserialize, Serialize};

/// A rollout's token figures (the record's `usage`, `harness_usage.json`).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Usage {
    pub available: bool,
    pub requests_with_usage: u64,
    pub lines_scanned: u64,
    pub input_tokens: Option<u64>,
    pub output_tokens: Option<u64>,
    pub cache_read_input_tokens: Option<u64>,
    pub reasoning_tokens: Option<u64>,
    pub total_tokens: Option<u64>,
    /// Where the figures come from ([`SOURCE_GATEWAY`], [`SOURCE_STDOUT`] or [`SOURCE_NONE`]); absent in records
    /// written before sources were recorded (those took stdout first).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub source: Option<String>,
    /// What the harness printed on stdout when the gateway's figures were taken instead, for comparison.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub harness_stdout: Option<StdoutFigures>,
    /// Set when the gateway saw model traffic it could not meter (bytes through a tunnel or a forward, a response
    /// whose usage could not be read): the figures are then a lower bound. Absent: complete, or not known.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub incomplete: Option<String>,
}

/// The runner's model-API gateway records (`sandbox/model_api.jsonl`), which the agent cannot write.
pub const SOURCE_GATEWAY: &str = "model_api_gateway";
/// The usage the harness printed on its stdout, which the agent's own commands can write to as well.
pub const SOURCE_STDOUT: &str = "harness_stdout";
/// Neither reported any.
pub const SOURCE_NONE: &str = "unavailable";

/// The harness's own stdout figures beside the gateway's.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct StdoutFigures {
    pub input_tokens: Option<u64>,
    pub output_tokens: Option<u64>,
    pub total_tokens: Option<u64>,
    /// Input, output and total equal the gateway's.
    pub agrees: bool,
}
