//! One line of `actions.jsonl` (protocol §4.9), typed for its readers. The request and the response stay JSON:
//! they are the tool call as the server received it and the payload it answered, whatever they held.
use serde_json::Value;

use crate::typed::record;

pub const ACTION_EVENT_SCHEMA: &str = "libero.agent_action_event.v1";

record! {
    /// A request to the episode and its response, errors included.
    pub struct ActionEvent {
        pub schema_version: Option<String>,
        /// 0-based position in the log, every event counted.
        pub event_index: Option<u64>,
        pub recorded_at: Option<String>,
        pub attempt_index: Option<u64>,
        /// The request as received (null when it did not parse); oversized fields recorded truncated.
        pub request: Option<Value>,
        /// The payload or error object returned.
        pub response: Option<Value>,
    }
}

impl ActionEvent {
    /// The request's field `key` (null when the request or the field is missing).
    fn request_field(&self, key: &str) -> &Value {
        self.request.as_ref().and_then(|r| r.get(key)).unwrap_or(&Value::Null)
    }

    /// The response, null when there is none.
    pub fn response(&self) -> &Value {
        self.response.as_ref().unwrap_or(&Value::Null)
    }

    /// The MCP tool the request named (`tool`).
    pub fn tool(&self) -> Option<&str> {
        self.request_field("tool").as_str()
    }

    /// The socket protocol's command (`command`): also set for requests that are no tool call (the wall-time
    /// expiry, a forfeit, a branch point).
    pub fn command(&self) -> Option<&str> {
        self.request_field("command").as_str()
    }

    /// The tool call's `arguments.actions` (an `osc_sequence`'s micro-actions), when it is a list.
    pub fn actions(&self) -> Option<&Vec<Value>> {
        self.request_field("arguments").get("actions").and_then(Value::as_array)
    }

    /// The response read as a tool's reply.
    pub fn reply(&self) -> ToolReply {
        ToolReply::of(self.response())
    }

    /// Whether the response is `ok: true`.
    pub fn ok(&self) -> bool {
        self.reply().is_ok()
    }

    /// Whether the call's actions ran (see [`actions_executed`]).
    pub fn actions_executed(&self) -> bool {
        self.reply().actions_executed()
    }

    /// Control steps the response says ran (`execution.control_steps`), 0 when it says none.
    pub fn control_steps(&self) -> u64 {
        self.reply().control_steps()
    }
}

record! {
    /// What a tool of the episode answers (protocol §2.9; an event's `response` in the action log): `ok`, and for
    /// a refusal its `error_type` and `error`, for an `osc_sequence` what ran, for `finish_episode` the verdict.
    /// Typed here for the server's own clients (experts, replays, teleop, benches); other fields kept in `rest`.
    pub struct ToolReply {
        pub ok: Option<bool>,
        /// The error's class (`ValueError`, `RuntimeError`, `EnvironmentCommandError`).
        pub error_type: Option<String>,
        /// The error's message, kept as JSON so that messages quote it as it came.
        pub error: Option<Value>,
        pub execution: Option<Execution>,
        /// `finish_episode`'s verdict.
        pub success: Option<bool>,
        /// `finish_episode`'s `finished`.
        pub status: Option<String>,
    }
}

record! {
    /// An `osc_sequence` reply's `execution`.
    pub struct Execution {
        pub control_steps: Option<u64>,
        /// The actions ran, even where the answer is an error (the observation could not be published).
        pub command_completed: Option<bool>,
    }
}

impl ToolReply {
    /// The reply in `value`; a value that is no object reads as an empty reply, one that is not `ok`.
    pub fn of(value: &Value) -> Self {
        <Self as serde::Deserialize>::deserialize(value).unwrap_or_default()
    }

    /// Whether it is `ok: true`.
    pub fn is_ok(&self) -> bool {
        self.ok == Some(true)
    }

    /// Whether the call's actions ran (see [`actions_executed`]).
    pub fn actions_executed(&self) -> bool {
        self.is_ok() || self.execution.as_ref().and_then(|e| e.command_completed) == Some(true)
    }

    /// Control steps it says ran (`execution.control_steps`), 0 when it says none.
    pub fn control_steps(&self) -> u64 {
        self.execution.as_ref().and_then(|e| e.control_steps).unwrap_or(0)
    }

    /// The error as JSON text (`null` when there is none), as messages quote it.
    pub fn error_text(&self) -> String {
        self.error.as_ref().unwrap_or(&Value::Null).to_string()
    }
}

/// Whether the actions of a call whose answer is `response` ran: an `ok` answer, or an error that reports its
/// execution completed (the observation could not be published into the workspace, but the robot moved).
pub fn actions_executed(response: &Value) -> bool {
    ToolReply::of(response).actions_executed()
}

#[cfg(test)]
mod tests {
    use serde_json::json;

    use super::*;

    #[test]
    fn an_action_log_line_parses() {
        let line = r#"{"attempt_index":1,"event_index":4,"recorded_at":"2026-01-01T00:00:00.000001+00:00","request":{"arguments":{"actions":[[0,0,0,0,0,0,-1],[0,0,0,0,0,0,1]]},"command":"osc_sequence","tool":"osc_sequence"},"response":{"execution":{"command_completed":true,"control_steps":2},"observation_id":"obs_000004","ok":true},"schema_version":"libero.agent_action_event.v1"}"#;
        let e: ActionEvent = serde_json::from_str(line).unwrap();
        assert_eq!((e.event_index, e.attempt_index, e.schema_version.as_deref()), (Some(4), Some(1), Some(ACTION_EVENT_SCHEMA)));
        assert_eq!((e.tool(), e.command(), e.actions().map(Vec::len)), (Some("osc_sequence"), Some("osc_sequence"), Some(2)));
        assert!(e.ok() && e.actions_executed());
        assert_eq!(e.control_steps(), 2);
        assert_eq!(serde_json::to_string(&e).unwrap(), line, "written back as read");
    }

    #[test]
    fn a_request_that_did_not_parse_is_null() {
        let e = ActionEvent::from_value(json!({"event_index": 0, "request": null, "response": {"ok": false, "error": "x"}})).unwrap();
        assert_eq!(e.request, Some(Value::Null));
        assert_eq!((e.tool(), e.command(), e.actions()), (None, None, None));
        assert!(!e.ok() && !e.actions_executed());
        assert_eq!(e.control_steps(), 0);
        assert_eq!(e.to_value()["request"], Value::Null, "the null is kept");
    }

    #[test]
    fn an_unpublished_observation_still_executed_its_actions() {
        assert!(actions_executed(&json!({"ok": true})));
        assert!(actions_executed(&json!({"ok": false, "execution": {"command_completed": true}})));
        assert!(!actions_executed(&json!({"ok": false, "error_type": "InvalidAction"})));
        assert!(!actions_executed(&json!("ok")));
    }

    #[test]
    fn a_reply_reads_its_fields_and_keeps_the_rest() {
        let v = json!({"ok": false, "error_type": "ValueError", "error": "no", "observation_id": "obs_000001"});
        let r = ToolReply::of(&v);
        assert_eq!((r.is_ok(), r.error_type.as_deref(), r.error_text()), (false, Some("ValueError"), "\"no\"".to_owned()));
        assert_eq!(r.to_value(), v, "written back as read");
        let f = ToolReply::of(&json!({"ok": true, "status": "finished", "success": true}));
        assert_eq!((f.is_ok(), f.status.as_deref(), f.success), (true, Some("finished"), Some(true)));
        assert_eq!(ToolReply::of(&json!({"ok": "yes", "execution": 3})), ToolReply { rest: json!({"ok": "yes", "execution": 3}).as_object().cloned().unwrap(), ..ToolReply::default() }, "ill-typed values are kept, not read");
        assert_eq!((ToolReply::of(&Value::Null).is_ok(), ToolReply::of(&Value::Null).error_text()), (false, "null".to_owned()));
    }
}
