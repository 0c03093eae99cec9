//! The MCP tool contract agents see (protocol spec §2.3–§2.5): server identity, instructions and the three
//! tool definitions as data, so the HTTP layer, the golden fixture and the tests share one source.
use serde_json::{Value, json};

/// `serverInfo.name` of the original adapter; agents' configs and logs key on it.
pub const SERVER_NAME: &str = "libero-agent-control";
pub const SERVER_VERSION: &str = "0.1.0";
/// The protocol version the original adapter always reports.
pub const PROTOCOL_VERSION: &str = "2025-06-18";
/// Name under which clients register the server (tools appear as `mcp__libero__osc_sequence`).
pub const MCP_SERVER_KEY: &str = "libero";
/// Most micro-actions one `osc_sequence` call may carry.
pub const MAX_MICRO_ACTIONS_PER_CALL: usize = 50;
/// Hard cap on accepted `osc_sequence` calls per episode (`MAX_NATIVE_OSC_SEQUENCE_SUBMISSIONS`).
pub const MAX_AGENT_STEPS_CAP: u64 = 1_000_000;
/// Release wall-clock budget per episode.
pub const DEFAULT_WALL_TIME_S: f64 = 1800.0;

/// The three tools, in `tools/list` order.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ToolName {
    StartEpisode,
    OscSequence,
    FinishEpisode,
}

impl ToolName {
    pub const ALL: [ToolName; 3] = [ToolName::StartEpisode, ToolName::OscSequence, ToolName::FinishEpisode];

    pub fn as_str(self) -> &'static str {
        match self {
            ToolName::StartEpisode => "start_episode",
            ToolName::OscSequence => "osc_sequence",
            ToolName::FinishEpisode => "finish_episode",
        }
    }

    pub fn parse(name: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|t| t.as_str() == name)
    }

    /// The command name of the original Unix-socket protocol, kept in `actions.jsonl` for replay tools.
    pub fn command(self) -> &'static str {
        match self {
            ToolName::StartEpisode => "start",
            ToolName::OscSequence => "osc_sequence",
            ToolName::FinishEpisode => "finish",
        }
    }
}

/// Server `instructions` (§2.4, no-reset variant, single episode).
pub const SERVER_INSTRUCTIONS: &str = "Control the prepared LIBERO episode only through the start_episode, osc_sequence and \
finish_episode tools. Call start_episode exactly once to begin the episode; its result reports the task instruction, \
the episode's max_agent_steps and max_wall_time_seconds. Each osc_sequence call accepts 1 to 50 normalized OSC_POSE \
actions. After every successful action, inspect the current observation in \
benchmark_inputs/current_observation/, which is replaced atomically before the tool returns. Call finish_episode \
exactly once, when the task is done, to get the official checker result.";

const ANNOTATIONS: fn() -> Value = || {
    json!({"readOnlyHint": false, "destructiveHint": false, "idempotentHint": false, "openWorldHint": false})
};

fn empty_schema() -> Value {
    json!({"type": "object", "properties": {}, "additionalProperties": false})
}

/// The inner-vector description of `osc_sequence` (units stated so the agent can plan metric motions).
pub const ACTION_VECTOR_DESCRIPTION: &str = "One normalized OSC_POSE micro action [dx, dy, dz, rx, ry, rz, gripper], \
each component in [-1, 1]. Translation 1.0 = 0.05 m; rotation 1.0 = a 0.5 rad rotation-vector component; \
gripper -1 opens and +1 closes, for one policy interval.";

/// One tool definition as it appears in `tools/list`.
pub fn tool_definition(tool: ToolName) -> Value {
    match tool {
        ToolName::StartEpisode => json!({
            "name": "start_episode",
            "title": "Start LIBERO episode",
            "description": "Start the prepared LIBERO episode (callable once). Publishes the initial current \
observation to benchmark_inputs/current_observation/ and returns the task instruction and the agent-step and \
wall-clock budgets.",
            "inputSchema": empty_schema(),
            "annotations": ANNOTATIONS(),
        }),
        ToolName::OscSequence => json!({
            "name": "osc_sequence",
            "title": "Execute LIBERO OSC sequence",
            "description": "Execute 1 to 50 exact normalized LIBERO OSC_POSE micro actions as one agent action, then \
atomically publish the resulting current observation to benchmark_inputs/current_observation/.",
            "inputSchema": {
                "type": "object",
                "properties": {
                    "actions": {
                        "type": "array",
                        "minItems": 1,
                        "maxItems": MAX_MICRO_ACTIONS_PER_CALL,
                        "items": {
                            "type": "array",
                            "minItems": 7,
                            "maxItems": 7,
                            "items": {"type": "number", "minimum": -1.0, "maximum": 1.0},
                            "description": ACTION_VECTOR_DESCRIPTION,
                        },
                    },
                },
                "required": ["actions"],
                "additionalProperties": false,
            },
            "annotations": ANNOTATIONS(),
        }),
        ToolName::FinishEpisode => json!({
            "name": "finish_episode",
            "title": "Finish LIBERO episode",
            "description": "Finish the active LIBERO episode (callable once) and return the official task-success \
result.",
            "inputSchema": empty_schema(),
            "annotations": ANNOTATIONS(),
        }),
    }
}

/// The `tools/list` result: `{"tools": [...]}`, no pagination cursor.
pub fn tools_list() -> Value {
    json!({"tools": ToolName::ALL.iter().map(|t| tool_definition(*t)).collect::<Vec<_>>()})
}

/// Whether the actions of a recorded `osc_sequence` response were executed: an accepted call, or one whose
/// actions ran but whose observation the agent's own workspace could not take (`ok: false` with
/// `execution.command_completed`). Replays and timelines count both.
pub use libero_records::records::actions_executed;

#[cfg(test)]
mod executed_tests {
    use super::*;

    #[test]
    fn a_call_whose_observation_the_workspace_refused_still_counts_as_executed() {
        assert!(actions_executed(&json!({"ok": true, "execution": {"command_completed": true}})));
        assert!(actions_executed(&json!({"ok": false, "error": "observation publication failed: …", "execution": {"command_completed": true}})));
        assert!(!actions_executed(&json!({"ok": false, "error_type": "InvalidAction"})));
    }
}
