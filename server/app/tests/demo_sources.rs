//! Issue 49, item 5: a demonstration links to its source episode's review when this server's store knows that
//! episode. One T28 expert episode runs on the served server and is recorded into its library (`demo record`);
//! another runs in-process on another data directory and records into the same library. Chromium
//! (`tests/dashboard/demo_sources_check.cjs`) finds the first linked on the Demonstrations page and on the T28 page
//! (and follows both links to the review), the second shown by id without a link. Needs `python3 scripts/setup.py
//! --test` (chromium, node, playwright-core); fails saying so otherwise.
use std::path::PathBuf;
use std::process::{Command, Output};

use serde_json::Value;

mod common;
use common::Server;

fn libero(args: &[&str]) -> Output {
    let out = Command::new(common::bin()).args(args).output().expect("run libero-agent");
    assert!(out.status.success(), "{args:?}: {}", String::from_utf8_lossy(&out.stderr));
    out
}

fn episode_of(out: &Output) -> String {
    let v: Value = serde_json::from_slice(&out.stdout).expect("the expert's JSON line");
    v["episode_id"].as_str().expect("episode_id").to_owned()
}

#[test]
fn a_demonstration_links_to_its_source_episodes_review_when_the_store_knows_it() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let server = Server::start(&data);
    let known = episode_of(&libero(&["expert", "--task", "T28", "--runs", "1", "--no-video", "--server", &server.url]));
    let (run_dir, library) = (data.join("runs").join(&known), data.join("demos"));
    let bundle = library.join("T28").join(&known);
    libero(&["demo", "record", "--run-dir", &run_dir.to_string_lossy(), "--out", &bundle.to_string_lossy(), "--source-type", "scripted_expert"]);
    let other = dir.path().join("other");
    let unknown = episode_of(&libero(&[
        "expert", "--task", "T28", "--runs", "1", "--no-video", "--data", &other.to_string_lossy(), "--demo-out", &library.to_string_lossy(),
    ]));
    assert!(library.join("T28").join(&unknown).is_dir(), "the second bundle is in the served library");

    let artifacts = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("../test-artifacts/demo_sources");
    std::fs::create_dir_all(&artifacts).unwrap();
    let last = common::browser_script("demo_sources_check.cjs", &[&server.url, "T28", &known, &unknown, &artifacts.to_string_lossy()], &server.token);
    assert_eq!(last["ok"], true, "{last}");
}
