//! The `tools/list` wire format is a golden fixture: any change to names, titles, descriptions, schemas
//! or annotations must be deliberate (`UPDATE_GOLDEN=1 cargo test -p libero-episode --test tools_contract`).
use std::path::PathBuf;

use libero_episode::tools::{ToolName, tools_list};
use serde_json::{Value, json};

fn fixture() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/tools_list.json")
}

#[test]
fn tools_list_matches_the_golden_fixture() {
    let actual = tools_list();
    if std::env::var_os("UPDATE_GOLDEN").is_some() {
        let mut text = libero_records::json::pretty_sorted(&actual);
        text.push('\n');
        std::fs::write(fixture(), text).unwrap();
    }
    let golden: Value = serde_json::from_str(&std::fs::read_to_string(fixture()).unwrap()).unwrap();
    assert_eq!(actual, golden, "tools/list changed; update the fixture only if intended");
}

#[test]
fn tools_follow_the_original_contract() {
    let list = tools_list();
    let tools = list["tools"].as_array().unwrap();
    let names: Vec<&str> = tools.iter().map(|t| t["name"].as_str().unwrap()).collect();
    assert_eq!(names, ["start_episode", "osc_sequence", "finish_episode"], "order of §2.5, no reset tool");
    let annotations =
        json!({"readOnlyHint": false, "destructiveHint": false, "idempotentHint": false, "openWorldHint": false});
    for t in tools {
        assert_eq!(t["annotations"], annotations);
        assert!(t.get("outputSchema").is_none(), "no outputSchema is declared");
        assert!(!t["description"].as_str().unwrap().is_empty());
    }
    let empty = json!({"type": "object", "properties": {}, "additionalProperties": false});
    assert_eq!(tools[0]["inputSchema"], empty);
    assert_eq!(tools[2]["inputSchema"], empty);
    assert_eq!(tools[0]["title"], "Start LIBERO episode");
    assert_eq!(tools[1]["title"], "Execute LIBERO OSC sequence");
    assert_eq!(tools[2]["title"], "Finish LIBERO episode");
    let schema = &tools[1]["inputSchema"];
    assert_eq!(schema["required"], json!(["actions"]));
    assert_eq!(schema["additionalProperties"], false);
    let actions = &schema["properties"]["actions"];
    assert_eq!((actions["minItems"].as_u64(), actions["maxItems"].as_u64()), (Some(1), Some(50)));
    let vector = &actions["items"];
    assert_eq!((vector["minItems"].as_u64(), vector["maxItems"].as_u64()), (Some(7), Some(7)));
    assert_eq!(vector["items"], json!({"type": "number", "minimum": -1.0, "maximum": 1.0}));
    assert!(vector["description"].as_str().unwrap().contains("0.05 m"));
    assert_eq!(ToolName::parse("osc_sequence"), Some(ToolName::OscSequence));
}
