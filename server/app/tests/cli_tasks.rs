//! `libero-agent tasks list|show` print the release catalog: a table by default, the manifest entries with --json.
use std::process::Command;

fn run(args: &[&str]) -> (bool, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_libero-agent")).args(args).env("RUST_BACKTRACE", "0").output().expect("binary runs");
    (out.status.success(), String::from_utf8_lossy(&out.stdout).into_owned(), String::from_utf8_lossy(&out.stderr).into_owned())
}

#[test]
fn tasks_list_prints_all_30_as_a_table_or_json() {
    let (ok, table, _) = run(&["tasks", "list"]);
    assert!(ok);
    assert!(table.starts_with("ID "), "{table}");
    assert_eq!(table.lines().filter(|l| l.starts_with('T')).count(), 30, "{table}");
    assert!(table.contains("30 of 30 tasks implemented"), "{table}");
    let (ok, json, _) = run(&["tasks", "list", "--json"]);
    assert!(ok);
    let tasks: serde_json::Value = serde_json::from_str(&json).unwrap();
    assert_eq!(tasks.as_array().map(Vec::len), Some(30));
}

#[test]
fn tasks_show_prints_one_task_and_rejects_unknown_ids() {
    let (ok, text, _) = run(&["tasks", "show", "T16"]);
    assert!(ok && text.starts_with("T16 open_microwave") && text.contains("agent instruction     open the microwave"), "{text}");
    let (ok, json, _) = run(&["tasks", "show", "t19", "--json"]);
    assert!(ok);
    let t: serde_json::Value = serde_json::from_str(&json).unwrap();
    assert_eq!((t["id"].as_str(), t["implemented"].as_bool(), t["stage_count"].as_u64()), (Some("T19"), Some(true), Some(3)));
    let (ok, _, err) = run(&["tasks", "show", "T99"]);
    assert!(!ok && err.contains("no release task \"T99\""), "{err}");
}
