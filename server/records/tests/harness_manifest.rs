//! The wire format of a rollout's `harness_manifest.json`, pinned by golden files: a manifest the runner fills
//! (every write's fields) serialises to `tests/fixtures/harness_manifest/filled.json` byte for byte, and a manifest an
//! older runner wrote (fields missing, an integer budget, keys this build does not name) still reads and is written
//! back unchanged.
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use libero_records::batch_doc::harness_manifest::{
    AgentEventsDoc, CREDENTIAL_MATERIAL_NEVER_RECORDED, HARNESS_MANIFEST_FILE, HARNESS_MANIFEST_SCHEMA, HarnessManifest, LogRecordDoc,
    ModelApiDoc, ResourcesUsedDoc,
};
use libero_records::batch_doc::ToolboxDoc;
use libero_records::json::pretty_sorted;
use libero_records::records::Outcome;
use serde_json::{Value, json};

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/fixtures/harness_manifest").join(name)
}

/// A typed record from JSON, as the runner makes one from what the sandbox crate describes.
fn doc<T: serde::de::DeserializeOwned>(v: Value) -> T {
    serde_json::from_value(v).unwrap()
}

/// What the runner writes for a sandboxed rollout that ended: the launch's fields, the sandbox's report, and the
/// end's, as `rollout.rs` sets them.
fn filled() -> HarnessManifest {
    HarnessManifest {
        schema_version: Some(HARNESS_MANIFEST_SCHEMA.into()),
        rollout_id: Some("w1_t14_level3".into()),
        created_at: Some("2026-01-01T00:00:00.000001+00:00".into()),
        harness: Some("codex".into()),
        model_requested: Some("gpt-5".into()),
        effort: Some("high".into()),
        harness_version: Some(doc(json!({"requested": "codex", "observed": "0.154.0", "probe_output": "codex-cli 0.154.0",
            "executable": "/usr/local/bin/codex"}))),
        api_protocol: Some("openai_chat".into()),
        credential_source: Some(Some("/home/researcher/.config/libero/credentials.json".into())),
        credential_material: Some(CREDENTIAL_MATERIAL_NEVER_RECORDED.into()),
        sandbox: Some(Some(doc(json!({
            "bubblewrap": "0.9.0", "namespaces": ["mount", "pid", "ipc", "uts", "net", "cgroup"],
            "identity": {"runner": "root", "agent_uid": 200000, "agent_gid": 200000, "uid_per_rollout": true, "how": "bubblewrap as root"},
            "seccomp": {"kind": "allow-list", "allowed_calls": 350, "default": "EPERM"},
            "resources": {"max_processes": 1024, "memory_bytes": 4294967296u64, "cpus": null, "cpu_weight": {"cpu.weight": 50},
                "disk_bytes": 2147483648u64, "enforced_by": "cgroup v2", "agent_uids": "200000-200999"},
            "network": "own namespace with only lo",
        })))),
        toolbox: Some(Some(doc::<ToolboxDoc>(json!({"name": "libero-toolbox", "source": "the project's lock (assets/third_party.lock.json)",
            "python": "3.12.3", "interpreter": "/opt/toolbox/bin/python3", "packages": [{"name": "numpy", "version": "2.2.0"}],
            "size_bytes": 1000, "host_path": "/opt/toolbox", "inside": "/opt/toolbox", "mount": "read-only", "agent_site": "PYTHONUSERBASE"})))),
        network: Some(Some(doc(json!({
            "mcp": {"inside": ["127.0.0.1:8765", "[::1]:8765"], "to": "http://127.0.0.1:8000/mcp", "host_name_on_loopback": null},
            "model_api": {"inside": "127.0.0.1:8766", "upstream": "https://api.openai.com/v1", "agent_base": "http://127.0.0.1:8766/v1",
                "routes": ["POST /v1/responses", "GET /v1/models"]},
            "proxy_allow_list": [], "everything_else": "unreachable (the namespace has only lo)",
        })))),
        episode_id: Some("ep-20260101T000000Z-0000abcd".into()),
        workspace: Some("/var/lib/libero/ws/w1_t14_level3".into()),
        private_run: Some("/var/lib/libero/runs/ep-20260101T000000Z-0000abcd".into()),
        session_home: Some("/var/lib/libero/ws/home".into()),
        command: Some(vec!["codex".into(), "exec".into(), "--json".into(), "<task-prompt>".into()]),
        task: Some("T14".into()),
        level: Some(3),
        demo: Some("video_traj".into()),
        seed: Some(0),
        max_wall_time_seconds: Some(1800.0),
        max_agent_steps: Some(400),
        sandbox_report: Some(Some(doc(json!({
            "schema_version": "libero.sandbox_report.v1", "uid": ["200000", "200000", "200000", "200000"], "gid": ["200000", "200000", "200000", "200000"],
            "groups": [], "uid_map": "0 0 4294967295", "gid_map": "0 0 4294967295",
            "capabilities": {"inheritable": "0000000000000000", "permitted": "0000000000000000", "effective": "0000000000000000",
                "bounding": "0000000000000000", "ambient": "0000000000000000"},
            "no_new_privs": true, "seccomp": "2", "namespaces": {"user": "user:[4026531837]", "net": "net:[4026532000]", "pid": null, "mnt": null},
            "network_interfaces": ["lo"], "relays": [{"listen": "127.0.0.1:8765", "to": "/run/relay/mcp.sock"}],
            "mounts": [{"mountpoint": "/usr", "root": "/usr", "options": "ro,nosuid", "fstype": "ext4"}],
        })))),
        relay_dir: Some(Some("/run/libero/r1".into())),
        finished_at: Some("2026-01-01T00:10:00.000001+00:00".into()),
        elapsed_seconds: Some(598.25),
        agent_exit_code: Some(Some(0)),
        infrastructure_error: Some(None),
        result_status: Some(Some("finished".into())),
        task_success: Some(Some(true)),
        outcome: Some(Outcome::Success),
        logs: Some(BTreeMap::from([
            ("codex_stderr.log".into(), doc::<LogRecordDoc>(json!({"size_bytes": 10, "kept_bytes": 10, "redactions": 0, "omitted": null}))),
            ("codex_stdout.jsonl".into(), doc(json!({"size_bytes": 20000000, "kept_bytes": 16777300, "redactions": 2,
                "omitted": {"from": 8388608, "to": 11611392, "sha256": "00ff", "sha256_bytes": 3222784}}))),
        ])),
        usage_source: Some(Some("model_api_gateway".into())),
        agent_events: Some(doc::<AgentEventsDoc>(json!({"path": "/var/lib/libero/runs/ep-20260101T000000Z-0000abcd/agent_events.jsonl",
            "events": 42, "bytes": 9000, "omitted_events": 0}))),
        model_api: Some(Some(doc::<ModelApiDoc>(json!({"requests": 12, "refused": 1, "failed": 0, "unmetered": 0, "request_bytes": 5000,
            "response_bytes": 7000, "tunnel_bytes": 0, "responses_with_usage": 11, "input_tokens": 1000, "output_tokens": 200,
            "cached_input_tokens": 0, "cache_creation_input_tokens": 0, "reasoning_tokens": 50, "total_tokens": 1200,
            "unreadable_lines": 0, "overflowed": 0, "complete": true})))),
        resources_used: Some(Some(doc::<ResourcesUsedDoc>(json!({"memory_peak_bytes": 104857600, "oom_kills": 0, "processes_peak": 12,
            "forks_refused": 0, "disk_used_bytes": null})))),
        ..HarnessManifest::default()
    }
}

/// The text the runner writes (sorted, pretty, one trailing newline).
fn written(m: &HarnessManifest) -> String {
    let dir = tempfile::tempdir().unwrap();
    m.write(dir.path()).unwrap();
    std::fs::read_to_string(dir.path().join(HARNESS_MANIFEST_FILE)).unwrap()
}

#[test]
fn a_filled_manifest_is_written_as_the_golden_file() {
    let text = written(&filled());
    assert_eq!(text, format!("{}\n", pretty_sorted(&filled().to_value())));
    let path = fixture("filled.json");
    if std::env::var_os("UPDATE_GOLDEN").is_some() {
        std::fs::write(&path, &text).unwrap();
    }
    let expected = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e} (UPDATE_GOLDEN=1 writes it)", path.display()));
    assert_eq!(text, expected, "the manifest's wire format changed: old batch directories would read differently");
}

#[test]
fn the_golden_file_reads_into_every_typed_field_and_writes_back_unchanged() {
    let text = std::fs::read_to_string(fixture("filled.json")).unwrap();
    let m: HarnessManifest = serde_json::from_str(&text).unwrap();
    assert_eq!(m, filled(), "every field reads back as written");
    assert_eq!(format!("{}\n", pretty_sorted(&m.to_value())), text);
    assert_eq!(m.outcome, Some(Outcome::Success));
    assert_eq!((m.model_requests_passed(), m.relay_dir(), m.usage_source.clone().flatten().as_deref()), (11, Some(Path::new("/run/libero/r1")), Some("model_api_gateway")));
    let sr = m.sandbox_report().unwrap();
    assert_eq!((sr.network_interfaces.clone(), sr.no_new_privs, sr.seccomp.clone().flatten().as_deref()), (Some(vec!["lo".to_owned()]), Some(Some(true)), Some("2")));
    assert!(sr.mounts.as_ref().unwrap().iter().any(|x| x.mountpoint.as_deref() == Some("/usr") && x.options.as_deref().is_some_and(|o| o.starts_with("ro"))));
    let route = m.network().and_then(|n| n.model_api.as_ref()).unwrap();
    assert_eq!(route.upstream.clone().flatten().as_deref(), Some("https://api.openai.com/v1"));
    let sandbox = m.sandbox().unwrap();
    assert_eq!(sandbox.identity.as_ref().and_then(|i| i.agent_uid), Some(200000));
    assert_eq!(sandbox.resources.clone().flatten().and_then(|r| r.max_processes), Some(1024));
    assert_eq!(m.resources_used().and_then(|u| u.memory_peak_bytes), Some(Some(104857600)));
    assert_eq!(m.agent_events.as_ref().and_then(|e| e.events), Some(42));
    assert_eq!(m.logs.as_ref().map(|l| l.keys().cloned().collect::<Vec<_>>()), Some(vec!["codex_stderr.log".into(), "codex_stdout.jsonl".into()]));
}

#[test]
fn an_older_runners_manifest_still_reads_and_writes_back_unchanged() {
    // An unsandboxed rollout of a runner before `relay_dir`, the transcript, the gateway, the caps and the probed
    // executable were recorded; its budget written as an integer, and a key this build does not name.
    let text = std::fs::read_to_string(fixture("older_unsandboxed.json")).unwrap();
    let m: HarnessManifest = serde_json::from_str(&text).unwrap();
    assert_eq!(format!("{}\n", pretty_sorted(&m.to_value())), text, "an older manifest is written back byte for byte");
    assert_eq!((m.rollout_id.as_deref(), m.harness.as_deref(), m.level, m.demo.as_deref()), (Some("w1_t03_level1"), Some("command"), Some(1), Some("none")));
    assert_eq!(m.max_wall_time_seconds, Some(1800.0), "an integer budget reads as seconds");
    assert_eq!((m.sandbox.clone(), m.sandbox(), m.network(), m.sandbox_report()), (Some(None), None, None, None), "null: no sandbox");
    assert_eq!((m.relay_dir.clone(), m.agent_events.clone(), m.usage_source.clone(), m.model_api.clone(), m.resources_used.clone()), (None, None, None, None, None));
    assert_eq!(m.harness_version.as_ref().map(|v| (v.observed.clone(), v.executable.clone())), Some((None, None)));
    assert_eq!((m.agent_exit_code, m.infrastructure_error.clone(), m.task_success, m.outcome), (Some(Some(1)), Some(Some("harness exited before finish_episode (exit code 1)".into())), Some(None), Some(Outcome::Invalid)));
    assert_eq!(m.model_requests_passed(), 0);
    assert!(m.rest.contains_key("operator_note"), "a key this build does not name is kept");
}

#[test]
fn a_launch_time_manifest_lacks_what_is_known_only_later() {
    let mut m = filled();
    (m.finished_at, m.elapsed_seconds, m.agent_exit_code, m.infrastructure_error, m.result_status, m.task_success, m.outcome) = (None, None, None, None, None, None, None);
    (m.logs, m.usage_source, m.agent_events, m.model_api, m.resources_used, m.sandbox_report, m.relay_dir) = (None, None, None, None, None, None, None);
    let v = m.to_value();
    for later in ["finished_at", "elapsed_seconds", "agent_exit_code", "outcome", "logs", "agent_events", "model_api", "sandbox_report", "relay_dir"] {
        assert!(v.get(later).is_none(), "{later} is absent before it is known, not null");
    }
    let back: HarnessManifest = serde_json::from_value(v).unwrap();
    assert_eq!((back.outcome, back.model_api(), back.relay_dir()), (None, None, None));
}

#[test]
fn a_rollout_directory_without_a_manifest_has_none() {
    let dir = tempfile::tempdir().unwrap();
    assert_eq!(HarnessManifest::read(dir.path()).unwrap(), None, "no manifest: a rollout that never launched");
    filled().write(dir.path()).unwrap();
    assert_eq!(HarnessManifest::read(dir.path()).unwrap(), Some(filled()));
    std::fs::write(dir.path().join(HARNESS_MANIFEST_FILE), "[]").unwrap();
    assert!(HarnessManifest::read(dir.path()).is_err(), "a manifest that is no object is an error, not an empty manifest");
}
