//! `run --harness-version` and the version each rollout records, end to end through `libero-agent run`, `report` and
//! the Results page, with a stand-in `codex` on PATH (no model, no network, no sandbox): its `--version` prints the
//! version in a file beside it, and each launch moves that file on to 0.2.0 (an upgrade in the middle of a batch)
//! before it plays the episode with the built-in reference agent. A version that is not installed stops `run`
//! before anything is written, with the installed versions and the setup command. The real CLIs of the paper's
//! versions are run by `tests/real_clis.rs` and resolved by the runner's `cli_checks`.
mod common;

use std::os::unix::fs::PermissionsExt;
use std::path::Path;
use std::process::{Command, Output};

use common::{Server, bin, http_get_json, http_get_text};
use libero_records::batch_doc::HarnessVersion;
use libero_records::batch_doc::harness_manifest::HarnessManifest;
use serde_json::Value;

/// The stand-in CLI: `codex --version` prints `codex-cli <version file>`; any other call bumps the file to 0.2.0 and
/// runs the reference agent on the rollout's workspace.
fn fake_codex(dir: &Path, version: &str) {
    std::fs::create_dir_all(dir).unwrap();
    std::fs::write(dir.join("version"), version).unwrap();
    let script = "#!/bin/sh\nhere=$(dirname \"$0\")\nif [ \"$1\" = --version ]; then echo \"codex-cli $(cat \"$here/version\")\"; exit 0; fi\n\
                  echo 0.2.0 > \"$here/version\"\nexec libero-agent agent --workspace \"$LIBERO_AGENT_WORKSPACE\"\n";
    std::fs::write(dir.join("codex"), script).unwrap();
    std::fs::set_permissions(dir.join("codex"), std::fs::Permissions::from_mode(0o755)).unwrap();
}

/// `libero-agent run` of T14 by Codex without the sandbox, the stand-in and this build's `libero-agent` first on PATH.
fn run(tmp: &Path, batch: &Path, extra: &[&str]) -> Output {
    let creds = tmp.join("credentials");
    std::fs::write(&creds, "APIKEY=sk-fake-key-0123\n").unwrap();
    let path = format!("{}:{}:{}", tmp.join("cli").display(), Path::new(bin()).parent().unwrap().display(), std::env::var("PATH").unwrap());
    let out = Command::new(bin())
        .args(["run", "--experiment", "main_table", "--harness", "codex", "--model", "fake", "--tasks", "T14"])
        .args(["--wall-time-s", "300", "--no-sandbox", "--credentials-file"])
        .arg(&creds)
        .arg("--batch")
        .arg(batch)
        .arg("--workspace-root")
        .arg(tmp.join("workspaces"))
        .args(extra)
        .env("PATH", path)
        .output()
        .expect("run libero-agent run");
    eprintln!("{}", String::from_utf8_lossy(&out.stderr));
    out
}

fn json_file(path: &Path) -> Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))).unwrap()
}

#[test]
fn each_rollout_records_the_version_it_ran_and_a_mixed_batch_says_so() {
    let tmp = tempfile::tempdir().unwrap();
    let cli = tmp.path().join("cli");
    fake_codex(&cli, "0.1.0");
    let batch = tmp.path().join("batches/upgraded");

    // Not installed: nothing starts, and the error says what is and how to install the lock's versions.
    let out = run(tmp.path(), &batch, &["--reps", "1", "--harness-version", "0.0.9"]);
    let said = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success(), "{said}");
    assert!(said.contains("codex 0.0.9 is not installed on this machine; installed: "), "{said}");
    assert!(said.contains(&format!("0.1.0 (on PATH, {})", cli.join("codex").display())), "{said}");
    assert!(said.contains("python3 scripts/setup.py --harnesses") && said.contains("npm install --prefix"), "{said}");
    assert!(!batch.exists(), "nothing was written");

    // Installed (here on PATH): run, two rollouts, the CLI upgraded by the first.
    let out = run(tmp.path(), &batch, &["--reps", "2", "--harness-version", "0.1.0"]);
    assert!(out.status.success(), "run failed");
    let records: Vec<Value> =
        std::fs::read_to_string(batch.join("rollouts.jsonl")).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!(records.len(), 2);
    let observed: Vec<&str> = records.iter().map(|r| r["harness_version"]["observed"].as_str().unwrap_or("none")).collect();
    assert_eq!(observed, ["0.1.0", "0.2.0"], "each rollout probed the CLI it launched: {records:?}");
    for r in &records {
        assert_eq!(r["harness_version"]["executable"].as_str(), cli.join("codex").to_str(), "{r}");
        assert!(r["outcome"] == "SUCCESS" || r["outcome"] == "FAIL", "the stand-in played the episode: {r}");
        let manifest = HarnessManifest::read(&batch.join("rollouts").join(r["rollout_id"].as_str().unwrap())).unwrap().expect("the rollout's harness manifest");
        assert_eq!(manifest.command.as_ref().and_then(|c| c.first()).map(String::as_str), cli.join("codex").to_str(), "{manifest}");
        assert_eq!(manifest.harness_version.as_ref().map(HarnessVersion::to_value).as_ref(), Some(&r["harness_version"]), "the record's probe: {manifest}");
        assert!(manifest.rest.is_empty(), "every key the runner writes is a typed field of HarnessManifest: {:?}", manifest.rest.keys());
        assert!(manifest.outcome.is_some() && manifest.finished_at.is_some() && manifest.agent_events.is_some(), "the end's write: {manifest}");
    }
    let doc = json_file(&batch.join("batch.json"));
    assert_eq!(doc["settings"]["harness_version"], "0.1.0", "{doc}");
    assert_eq!(doc["harness"]["version"]["observed"], "0.1.0", "the batch's first look: {doc}");

    // `report`: the batch line and a warning under Table 1; its JSON flags the batch and the row.
    let report = Command::new(bin()).arg("report").arg(&batch).output().unwrap();
    let md = String::from_utf8_lossy(&report.stdout);
    assert!(report.status.success(), "{}", String::from_utf8_lossy(&report.stderr));
    assert!(md.contains("harness version 0.1.0 / 0.2.0 (mixed versions)"), "{md}");
    assert!(md.contains("**Warning: codex/fake (L3, demo none) pools rollouts of different harness versions: codex 0.1.0 / 0.2.0 (mixed versions).**"), "{md}");
    let report = Command::new(bin()).arg("report").arg(&batch).args(["--format", "json"]).output().unwrap();
    let json: Value = serde_json::from_slice(&report.stdout).unwrap();
    assert_eq!(json["batches"][0]["harness_versions"]["mixed"], true, "{json}");
    assert_eq!(json["rows"][0]["harness_versions"]["versions"], serde_json::json!([{"version": "0.1.0", "rollouts": 1}, {"version": "0.2.0", "rollouts": 1}]));

    // The Results page: the batch's progress line and its Table 1 row, as a warning.
    let server = Server::start_with(&tmp.path().join("data"), &["--batches", tmp.path().join("batches").to_str().unwrap()]);
    let (status, html) = http_get_text(&format!("{}/results", server.url));
    assert_eq!(status, 200);
    let warning = "class=\"harness-version warning\" title=\"0.1.0: 1 rollouts, 0.2.0: 1 rollouts\">codex 0.1.0 / 0.2.0 (mixed versions)<";
    assert_eq!(html.matches(warning).count(), 2, "progress and the main table: {html}");
    let (_, api) = http_get_json(&format!("{}/api/results", server.url));
    assert_eq!(api["batches"][0]["harness_versions"]["text"], "codex 0.1.0 / 0.2.0 (mixed versions)", "{api}");
}
