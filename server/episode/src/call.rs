//! Turning an MCP `tools/call` into an episode command, with the original adapter's argument checks
//! (§2.6) and the service's action validation (§2.11): exact messages, no clipping, no tolerance.
use serde_json::{Map, Value, json};

use crate::tools::{MAX_MICRO_ACTIONS_PER_CALL, ToolName};

/// An agent-facing failure: `{"ok": false, "error_type": ..., "error": ...}`, delivered with `isError: true`.
/// `error_type` keeps the original Python class names, which agents' prompts and logs already know.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{error_type}: {message}")]
pub struct ToolError {
    pub error_type: &'static str,
    pub message: String,
}

impl ToolError {
    pub fn value_error(message: impl Into<String>) -> Self {
        Self { error_type: "ValueError", message: message.into() }
    }
    pub fn runtime_error(message: impl Into<String>) -> Self {
        Self { error_type: "RuntimeError", message: message.into() }
    }
    /// An unexpected simulator or I/O failure; details go to the private log only.
    pub fn environment() -> Self {
        Self {
            error_type: "EnvironmentCommandError",
            message: "the LIBERO server could not execute this command".to_owned(),
        }
    }
    pub fn payload(&self) -> Value {
        json!({"ok": false, "error_type": self.error_type, "error": self.message})
    }
}

/// A checked tool call. `OscSequence` keeps the raw `actions` value: the service validates it only after
/// the wall-clock, activity and budget checks (§2.11 order).
#[derive(Debug, Clone, PartialEq)]
pub enum ToolCall {
    Start,
    OscSequence { actions: Value },
    Finish,
}

impl ToolCall {
    pub fn tool(&self) -> ToolName {
        match self {
            ToolCall::Start => ToolName::StartEpisode,
            ToolCall::OscSequence { .. } => ToolName::OscSequence,
            ToolCall::Finish => ToolName::FinishEpisode,
        }
    }

    /// The adapter-level checks: known tool, argument keys. `arguments: None` is an absent object.
    pub fn parse(name: &str, arguments: Option<&Map<String, Value>>) -> Result<Self, ToolError> {
        let tool = ToolName::parse(name)
            .ok_or_else(|| ToolError::value_error(format!("unknown or disabled LIBERO MCP tool: {name}")))?;
        let empty = Map::new();
        let args = arguments.unwrap_or(&empty);
        match tool {
            ToolName::StartEpisode | ToolName::FinishEpisode => {
                if !args.is_empty() {
                    return Err(ToolError::value_error(format!("{name} accepts no arguments")));
                }
                Ok(if tool == ToolName::StartEpisode { ToolCall::Start } else { ToolCall::Finish })
            }
            ToolName::OscSequence => match args.get("actions") {
                Some(actions) if args.len() == 1 => Ok(ToolCall::OscSequence { actions: actions.clone() }),
                _ => Err(ToolError::value_error("osc_sequence requires only the actions argument")),
            },
        }
    }

    /// `tools/call` params as sent on the wire: `{"name": ..., "arguments": {...}}`.
    pub fn parse_params(params: &Value) -> Result<Self, ToolError> {
        let params = params
            .as_object()
            .ok_or_else(|| ToolError::value_error("tools/call params must be an object"))?;
        let name = params.get("name").and_then(Value::as_str);
        let arguments = match params.get("arguments") {
            None | Some(Value::Null) => Ok(None),
            Some(Value::Object(m)) => Ok(Some(m)),
            Some(_) => Err(()),
        };
        match (name, arguments) {
            (Some(name), Ok(arguments)) => Self::parse(name, arguments),
            _ => Err(ToolError::value_error("tools/call requires a tool name and object arguments")),
        }
    }
}

/// One normalized OSC_POSE micro-action `[dx, dy, dz, rx, ry, rz, gripper]`.
pub type MicroAction = [f64; 7];

/// Shape of a JSON value read as a NumPy array (`np.asarray(x, dtype=float64)`): `None` when it is not
/// a rectangular numeric array. Booleans count as numbers (NumPy coerces them to 1/0).
fn numeric_shape(v: &Value) -> Option<Vec<usize>> {
    match v {
        Value::Number(_) | Value::Bool(_) => Some(Vec::new()),
        Value::Array(items) => {
            let mut inner: Option<Vec<usize>> = None;
            for item in items {
                let s = numeric_shape(item)?;
                match &inner {
                    None => inner = Some(s),
                    Some(prev) if *prev == s => {}
                    Some(_) => return None,
                }
            }
            let mut shape = vec![items.len()];
            shape.extend(inner.unwrap_or_default());
            Some(shape)
        }
        _ => None,
    }
}

fn as_f64(v: &Value) -> f64 {
    match v {
        Value::Bool(b) => f64::from(u8::from(*b)),
        Value::Number(n) => n.as_f64().unwrap_or(f64::NAN),
        _ => f64::NAN,
    }
}

/// The service's action validation, in its order: rectangular numeric → 1..=50 vectors → shape [N, 7]
/// → finite → every component within [-1, 1] (no clipping, no tolerance).
pub fn validate_actions(actions: &Value) -> Result<Vec<MicroAction>, ToolError> {
    let shape = numeric_shape(actions)
        .ok_or_else(|| ToolError::value_error("actions must be a rectangular numeric array"))?;
    let Value::Array(rows) = actions else {
        return Err(ToolError::value_error("actions must have shape [N, 7]"));
    };
    if rows.is_empty() || rows.len() > MAX_MICRO_ACTIONS_PER_CALL {
        return Err(ToolError::value_error(format!(
            "actions must contain between 1 and {MAX_MICRO_ACTIONS_PER_CALL} micro steps"
        )));
    }
    if shape.len() != 2 || shape[1] != 7 {
        return Err(ToolError::value_error("actions must have shape [N, 7]"));
    }
    let mut out = Vec::with_capacity(rows.len());
    for row in rows {
        let Value::Array(cols) = row else {
            return Err(ToolError::value_error("actions must have shape [N, 7]"));
        };
        let mut a = [0.0; 7];
        for (slot, c) in a.iter_mut().zip(cols) {
            *slot = as_f64(c);
        }
        out.push(a);
    }
    if out.iter().flatten().any(|x| !x.is_finite()) {
        return Err(ToolError::value_error("actions must contain only finite numbers"));
    }
    if out.iter().flatten().any(|x| x.abs() > 1.0) {
        return Err(ToolError::value_error("native OSC action components must be within [-1, 1]"));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// (The action log lives in `libero-records`; this checks it against the call rules it must fit.)
    /// The longest valid `osc_sequence` arguments: 50 actions whose every component has the longest JSON
    /// form a number in [-1, 1] can take.
    fn maximal_valid_arguments() -> Value {
        let longest = -2.2250738585072014e-308_f64; // 24 characters
        assert_eq!(serde_json::to_string(&longest).unwrap().len(), 24);
        json!({"actions": vec![[longest; 7]; crate::tools::MAX_MICRO_ACTIONS_PER_CALL]})
    }

    #[test]
    fn the_largest_valid_call_is_logged_in_full() {
        let args = maximal_valid_arguments();
        assert!(validate_actions(&args["actions"]).is_ok());
        let size = libero_records::json::compact_sorted(&args).len();
        assert!(size * 3 / 2 < libero_records::records::MAX_LOGGED_FIELD_BYTES, "{size} bytes: the limit must stay well above a valid call");
        assert_eq!(libero_records::records::bounded_for_log(&args), args);
    }

    use serde_json::json;

    fn msg(v: Value) -> String {
        validate_actions(&v).unwrap_err().message
    }

    #[test]
    fn valid_sequences_pass_unchanged_with_booleans_as_numbers() {
        let a = validate_actions(&json!([[0.1, -0.2, 0, 1, -1, 0.5, true], [0, 0, 0, 0, 0, 0, false]])).unwrap();
        assert_eq!(a, vec![[0.1, -0.2, 0.0, 1.0, -1.0, 0.5, 1.0], [0.0; 7]]);
        assert_eq!(validate_actions(&json!(vec![[0.0; 7]; 50])).unwrap().len(), 50);
    }

    #[test]
    fn every_catalogue_row_gets_its_exact_message() {
        let rect = "actions must be a rectangular numeric array";
        assert_eq!(msg(json!([[0, 0, 0, 0, 0, 0, 0], [0, 0]])), rect, "ragged");
        assert_eq!(msg(json!([[0, 0, 0, 0, 0, 0, "x"]])), rect, "string");
        assert_eq!(msg(json!([[0, 0, 0, 0, 0, 0, {"a": 1}]])), rect, "object");
        assert_eq!(msg(json!([[0, 0, 0, 0, 0, 0, null]])), rect, "null");
        assert_eq!(msg(json!("0,0,0,0,0,0,0")), rect, "a string for the whole array");
        let count = "actions must contain between 1 and 50 micro steps";
        assert_eq!(msg(json!([])), count);
        assert_eq!(msg(json!(vec![[0.0; 7]; 51])), count);
        let shape = "actions must have shape [N, 7]";
        assert_eq!(msg(json!([[0, 0, 0, 0, 0, 0]])), shape, "6 components");
        assert_eq!(msg(json!([[0, 0, 0, 0, 0, 0, 0, 0]])), shape, "8 components");
        assert_eq!(msg(json!([0, 0, 0, 0, 0, 0, 0])), shape, "flat vector");
        assert_eq!(msg(json!([[[0, 0, 0, 0, 0, 0, 0]]])), shape, "3-D");
        assert_eq!(msg(json!(0.5)), shape, "scalar");
        let range = "native OSC action components must be within [-1, 1]";
        assert_eq!(msg(json!([[0, 0, 0, 0, 0, 0, 1.0000001]])), range);
        assert_eq!(msg(json!([[-1.5, 0, 0, 0, 0, 0, 0]])), range);
    }

    #[test]
    fn adapter_argument_checks_name_the_tool() {
        let args = |v: Value| v.as_object().cloned();
        assert_eq!(
            ToolCall::parse("reset_episode", None).unwrap_err().message,
            "unknown or disabled LIBERO MCP tool: reset_episode"
        );
        assert_eq!(
            ToolCall::parse("start_episode", args(json!({"x": 1})).as_ref()).unwrap_err().message,
            "start_episode accepts no arguments"
        );
        assert_eq!(
            ToolCall::parse("finish_episode", args(json!({"x": 1})).as_ref()).unwrap_err().message,
            "finish_episode accepts no arguments"
        );
        for bad in [json!({}), json!({"actions": [], "speed": 1})] {
            assert_eq!(
                ToolCall::parse("osc_sequence", args(bad).as_ref()).unwrap_err().message,
                "osc_sequence requires only the actions argument"
            );
        }
        assert_eq!(ToolCall::parse("start_episode", None).unwrap(), ToolCall::Start);
        assert_eq!(
            ToolCall::parse_params(&json!({"name": "osc_sequence", "arguments": {"actions": [[0]]}})).unwrap(),
            ToolCall::OscSequence { actions: json!([[0]]) }
        );
        assert_eq!(
            ToolCall::parse_params(&json!([1])).unwrap_err().message,
            "tools/call params must be an object"
        );
        assert_eq!(
            ToolCall::parse_params(&json!({"name": 3})).unwrap_err().message,
            "tools/call requires a tool name and object arguments"
        );
    }
}
