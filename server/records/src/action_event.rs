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

    /// Whether the response is `ok: true`.
    pub fn ok(&self) -> bool {
        self.response().get("ok") == Some(&Value::Bool(true))
    }

    /// Whether the call's actions ran (see [`actions_executed`]).
    pub fn actions_executed(&self) -> bool {
        actions_executed(self.response())
    }

    /// Control steps the response says ran (`execution.control_steps`), 0 when it says none.
    pub fn control_steps(&self) -> u64 {
        self.response().get("execution").and_then(|e| e.get("control_steps")).and_then(Value::as_u64).unwrap_or(0)
    }
}

/// Whether the actions of a call whose answer is `response` ran: an `ok` answer, or an error that reports its
/// execution completed (the observation could not be published into the workspace, but the robot moved).
pub fn actions_executed(response: &Value) -> bool {
    response.get("ok") == Some(&Value::Bool(true))
        || response.get("execution").and_then(|e| e.get("command_completed")) == Some(&Value::Bool(true))
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
}
