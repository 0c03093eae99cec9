//! `libero-agent tasks list|show` print the release catalog (a table by default, the manifest entries with --json)
//! and, with `--tasks` (and `--group`) or a `suite/id`, the registered pool.
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

#[test]
fn tasks_list_suite_shows_the_registered_pool_with_status_and_counts() {
    let (ok, table, _) = run(&["tasks", "list", "--tasks", "all"]);
    assert!(ok, "{table}");
    let rows: Vec<&str> = table.lines().filter(|l| l.split_once('/').is_some_and(|(s, _)| !s.contains(' '))).collect();
    assert_eq!(rows.len(), 213, "{table}");
    assert!(table.contains("libero_90: 90 registered, 90 run, 0 excluded, 0 not implemented"), "{table}");
    assert!(table.contains("robomemarena: 26 registered, 26 run, 0 excluded, 0 not implemented"), "{table}");
    let microwave = rows.iter().find(|l| l.starts_with("libero_90/35 ")).expect("libero_90/35");
    assert!(microwave.contains("KITCHEN_SCENE7_open_the_microwave") && microwave.ends_with("runs"), "{microwave}");
    assert!(rows.iter().any(|l| l.starts_with("robomemarena/4 ") && l.ends_with("runs (as T23)")), "{table}");
    assert!(rows.iter().any(|l| l.starts_with("vlabench_world_knowledge/8 ") && l.ends_with("excluded")), "{table}");

    let (ok, json, _) = run(&["tasks", "list", "--tasks", "robomemarena", "--group", "long_horizon", "--json"]);
    assert!(ok, "{json}");
    let entries: Vec<serde_json::Value> = serde_json::from_str(&json).unwrap();
    assert_eq!(entries.len(), 26);
    assert_eq!(entries[0]["name"], "robomemarena_task_01");
    let (ok, json, _) = run(&["tasks", "list", "--group", "perception", "--json"]);
    let perception: Vec<serde_json::Value> = serde_json::from_str(&json).unwrap();
    assert!(ok && perception.iter().all(|e| e["group"] == "perception") && perception.len() > 30, "{}", perception.len());

    let (ok, _, err) = run(&["tasks", "list", "--tasks", "libero_100"]);
    assert!(!ok && err.contains("no pool suite \"libero_100\""), "{err}");
    let (ok, _, err) = run(&["tasks", "list", "--group", "medium_horizon"]);
    assert!(!ok && err.contains("no group"), "{err}");
}

#[test]
fn tasks_show_prints_a_pool_entry_by_id_or_name() {
    let (ok, text, _) = run(&["tasks", "show", "libero_goal/7"]);
    assert!(ok && text.starts_with("libero_goal/7 turn_on_the_stove") && text.contains("release task          T17"), "{text}");
    let (ok, same, _) = run(&["tasks", "show", "libero_goal/turn_on_the_stove"]);
    assert!(ok);
    assert_eq!(same, text);
    let (ok, text, _) = run(&["tasks", "show", "long_horizon_v2/2"]);
    assert!(ok && text.contains("press the front button to brew coffee") && !text.contains("not implemented"), "{text}");
    let (ok, text, _) = run(&["tasks", "show", "vlabench_perception/1"]);
    assert!(ok && text.contains("excluded"), "an entry that does not run says why: {text}");
    let (ok, _, err) = run(&["tasks", "show", "robomemarena/27"]);
    assert!(!ok && err.contains("robomemarena has task ids 1–26"), "{err}");
}

/// `--tasks` reads the one task-selection syntax (docs/commands.md, "Selecting tasks"): release tasks alone print
/// the release table, anything else the pool's entries (a release task as its pool twins), in the selection's order;
/// a typo is refused naming what is accepted.
#[test]
fn tasks_list_takes_any_task_selection() {
    let (ok, table, err) = run(&["tasks", "list", "--tasks", "release", "--group", "perception"]);
    assert!(ok, "{err}");
    let ids: Vec<&str> = table.lines().filter(|l| l.starts_with('T')).map(|l| &l[..3]).collect();
    assert_eq!(ids, ["T01", "T02", "T03", "T04", "T05", "T06", "T07", "T08", "T09", "T10"], "{table}");
    let (ok, table, _) = run(&["tasks", "list", "--tasks", "T16,T11"]);
    assert!(ok && table.lines().filter(|l| l.starts_with('T')).map(|l| &l[..3]).eq(["T16", "T11"]), "{table}");

    let (ok, json, err) = run(&["tasks", "list", "--tasks", "libero_goal/7,T16", "--tasks", "match:open_the_microwave", "--json"]);
    assert!(ok, "{err}");
    let entries: Vec<serde_json::Value> = serde_json::from_str(&json).unwrap();
    let ids: Vec<String> = entries.iter().map(|e| format!("{}/{}", e["suite"].as_str().unwrap(), e["task_id"])).collect();
    assert_eq!(ids[0], "libero_goal/7", "{ids:?}");
    assert!(ids.contains(&"libero_90/35".to_owned()), "T16's twin and a match for the microwave: {ids:?}");
    assert_eq!(ids.iter().filter(|i| *i == "libero_90/35").count(), 1, "each entry once: {ids:?}");

    for (bad, want) in [("kitchen", "no pool suite \"kitchen\""), ("group:medium", "no group"), ("T31", "no release task"), ("libero_90/999", "no pool entry")] {
        let (ok, _, err) = run(&["tasks", "list", "--tasks", bad]);
        assert!(!ok && err.contains(want), "{bad}: {err}");
    }
}
