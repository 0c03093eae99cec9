//! Issue 49, items 3 and 4: a teleop branch keeps what the robot holds and a demonstration saved from a branch
//! records its parent, step and replayed prefix (its trajectory only its own actions, replayed after the prefix);
//! a teleop episode is made on the first input, ended as abandoned when its page is gone, and the live and
//! teleop pages finish (judged) and abort episodes. Real `serve` processes, chromium, the records on disk.
mod common;

use std::path::{Path, PathBuf};
use std::process::Command;

use libero_episode::RunDir;
use libero_episode::demo::record::{SourceEpisode, bundle_source};
use libero_episode::physics::WorldPhysics;
use libero_server::client::McpClient;
use libero_sim::mujoco_rs::prelude::MjtObjBase;
use common::call_ok;
use serde_json::{Value, json};

fn artifacts_dir() -> PathBuf {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("../test-artifacts/teleop_lifecycle");
    std::fs::create_dir_all(&dir).expect("artifacts dir");
    dir
}

/// `POST` of a JSON body with the operator token: (status, JSON answer).
fn post(server: &common::Server, path: &str, body: &Value) -> (u16, Value) {
    common::post_json(server, path, body, Some(&server.token))
}

fn mcp(prepared: &Value) -> McpClient {
    common::mcp_session(prepared, "teleop-lifecycle-test")
}

/// A started T14 agent episode (its MCP session kept open) for the live page's buttons.
fn started_agent_episode(server: &common::Server, workspace: &Path) -> (String, McpClient) {
    let (status, prepared) = post(server, "/api/episodes", &json!({"task": "T14", "level": 1, "workspace": workspace}));
    assert_eq!(status, 201, "{prepared}");
    let mut client = mcp(&prepared);
    call_ok(&mut client, "start_episode", json!({}));
    (prepared["episode_id"].as_str().expect("id").to_owned(), client)
}

/// Chromium on a server whose teleop episodes are abandoned after 5 s without a page: a page opened and left
/// makes no episode; the first key makes one; Finish and judge shows the verdict and Reset clears every message;
/// Abort ends one; one driven and left ends as abandoned and its live page says why; the live page of an agent's
/// episode finishes (judged) and aborts it.
#[test]
fn teleop_episodes_start_on_the_first_key_end_as_abandoned_when_left_and_are_finished_or_aborted_from_both_pages() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let data = tmp.path().join("data");
    let server = common::Server::start_with(&data, &["--teleop-abandon-s", "5"]);
    let (finish_id, _finish_client) = started_agent_episode(&server, &tmp.path().join("finish"));
    let (abort_id, _abort_client) = started_agent_episode(&server, &tmp.path().join("abort"));
    let artifacts = artifacts_dir();
    let report = common::browser_script(
        "teleop_lifecycle_check.cjs",
        &[&server.url, "T14", "5", &finish_id, &abort_id, artifacts.to_str().expect("utf-8")],
        &server.token,
    );
    assert_eq!(report["ok"], true, "{report}");
    for shot in ["teleop-ready", "teleop-judged", "teleop-reset", "teleop-aborted", "live-abandoned", "live-judged", "live-aborted"] {
        assert!(artifacts.join(format!("{shot}.png")).is_file(), "screenshot {shot}.png");
    }
    // The records say the same as the pages: the abandoned episode's result names why.
    let abandoned = report["abandoned_episode"].as_str().expect("abandoned id");
    let result: Value = serde_json::from_slice(&std::fs::read(data.join("runs").join(abandoned).join("result.json")).expect("result.json")).expect("JSON");
    assert_eq!(result["status"], "aborted", "{result}");
    assert!(result["reason"].as_str().unwrap_or("").starts_with("abandoned: no teleop page was connected to it for 5 s"), "{result}");
    let judged: Value = serde_json::from_slice(&std::fs::read(data.join("runs").join(&finish_id).join("result.json")).expect("result.json")).expect("JSON");
    assert_eq!(judged["status"], "finished", "the live page's Finish and judge ended the agent's episode with finish_episode: {judged}");
}

/// `drink_2`'s height (m) after replaying `actions` in `source`'s world from its start.
fn object_height_after(source: &SourceEpisode, actions: &[[f64; 7]]) -> f64 {
    let paths = libero_sim::AssetPaths::discover().expect("assets");
    let mut world = WorldPhysics::build(&source.spec(&paths).expect("spec"), |_, _, _| Ok(())).expect("world");
    world.start(|_| {}).expect("start");
    for a in actions {
        world.step(a).expect("step");
    }
    let body = ["drink_2", "drink_2_main"]
        .iter()
        .find_map(|n| world.model().name_to_id(MjtObjBase::mjOBJ_BODY, n))
        .expect("T07's cola is drink_2");
    world.sim.observation().body_pos_in_world_m[body][2]
}

fn run(args: &[&str]) -> (bool, String) {
    let out = Command::new(common::bin()).args(args).output().expect("libero-agent");
    (out.status.success(), format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr)))
}

/// T07's expert grasps and lifts the cola; a teleop branch a few steps after the lift starts with the gripper
/// closed (the parent's last command), so driving up keeps the cola lifted; its saved demonstration names the
/// parent, step and replayed prefix and holds only the branch's own actions. An agent's branch that finishes the
/// parent's remaining actions is recorded and verified by replay (the prefix first, or it could not succeed).
#[test]
fn a_teleop_branch_taken_while_holding_an_object_keeps_holding_it_and_its_demonstration_replays_the_prefix_first() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let data = tmp.path().join("data");
    let server = common::Server::start(&data);
    let out = Command::new(common::bin())
        .args(["expert", "--task", "T07", "--no-video", "--server", &server.url])
        .env("LIBERO_OPERATOR_TOKEN", &server.token)
        .output()
        .expect("expert");
    assert!(out.status.success(), "expert: {}", String::from_utf8_lossy(&out.stderr));
    let expert: Value = serde_json::from_slice(String::from_utf8_lossy(&out.stdout).lines().last().expect("a JSON line").as_bytes()).expect("JSON");
    assert_eq!(expert["success"], true, "{expert}");
    let parent_id = expert["episode_id"].as_str().expect("id").to_owned();
    let lifted_at = expert["first_commitment"]["control_step"].as_u64().expect("the lift's step");
    let step = lifted_at + 7;
    let parent = SourceEpisode::read(&RunDir::new(data.join("runs").join(&parent_id))).expect("parent");
    let parent_actions: Vec<[f64; 7]> = parent.actions.iter().map(|a| a.1).collect();
    assert_eq!(parent_actions[step as usize - 1][6], 1.0, "the parent's gripper is closed at step {step}");
    let start_height = object_height_after(&parent, &[]);
    let lifted = object_height_after(&parent, &parent_actions[..step as usize]) - start_height;
    assert!(lifted > 0.04, "the parent holds the cola {lifted:.3} m up at step {step}");

    // Chromium drives the branch up (no gripper key) and saves it.
    let artifacts = artifacts_dir();
    let report = common::browser_script(
        "teleop_branch_hold_check.cjs",
        &[&server.url, "T07", &parent_id, &step.to_string(), artifacts.to_str().expect("utf-8")],
        &server.token,
    );
    assert_eq!(report["ok"], true, "{report}");
    let branch_id = report["episode_id"].as_str().expect("the branch's id").to_owned();
    let branch = SourceEpisode::read(&RunDir::new(data.join("runs").join(&branch_id))).expect("branch");
    assert_eq!(branch.replayed(), step as usize);
    let own: Vec<[f64; 7]> = branch.own_actions().iter().map(|a| a.1).collect();
    assert!(own.len() >= 10, "the page drove the branch: {} actions", own.len());
    assert!(own.iter().all(|a| a[6] == 1.0), "every action of the branch keeps the gripper closed");
    let all: Vec<[f64; 7]> = branch.actions.iter().map(|a| a.1).collect();
    let held = object_height_after(&branch, &all) - start_height;
    assert!(held > lifted, "the cola is still held, and higher: {held:.3} m (was {lifted:.3} m at the branch point)");

    // The bundle: parent, step and prefix in the manifest; only the branch's own actions as its trajectory.
    let bundle = data.join("demos").join(report["bundle"].as_str().expect("bundle key"));
    let manifest: Value = serde_json::from_slice(&std::fs::read(bundle.join("manifest.json")).expect("manifest")).expect("JSON");
    assert_eq!(
        manifest["source"]["branch"],
        json!({"parent_episode_id": parent_id, "parent_control_step": step, "replayed_actions": step, "prefix_file": "branch_prefix.jsonl"}),
        "{manifest}"
    );
    assert_eq!(manifest["transition_count"].as_u64(), Some(own.len() as u64));
    let rows = std::fs::read_to_string(bundle.join("trajectory.jsonl")).expect("trajectory");
    assert_eq!(rows.lines().count(), own.len(), "the trajectory holds only the branch's own actions");
    let (valid, why) = run(&["demo", "validate", bundle.to_str().expect("utf-8")]);
    assert!(valid, "demo validate: {why}");
    let (_, read) = bundle_source(&bundle).expect("bundle source");
    assert_eq!(read.actions.iter().map(|a| a.1).collect::<Vec<_>>(), all, "read back, the prefix comes first");

    // An agent's branch at the same step that plays the parent's remaining actions succeeds; its bundle verifies
    // by replay only because the replay starts with the prefix.
    let (status, prepared) = post(&server, "/api/episodes", &json!({"branch": {"parent": parent_id, "step": step}, "level": 1, "workspace": tmp.path().join("agent")}));
    assert_eq!(status, 201, "{prepared}");
    let agent_id = prepared["episode_id"].as_str().expect("id").to_owned();
    let mut client = mcp(&prepared);
    call_ok(&mut client, "start_episode", json!({}));
    for chunk in parent_actions[step as usize..].chunks(50) {
        call_ok(&mut client, "osc_sequence", json!({"actions": chunk}));
    }
    call_ok(&mut client, "finish_episode", json!({}));
    let out_dir = tmp.path().join("agent_bundle");
    let run_dir = data.join("runs").join(&agent_id);
    let (recorded, why) = run(&["demo", "record", "--run-dir", run_dir.to_str().expect("utf-8"), "--out", out_dir.to_str().expect("utf-8")]);
    assert!(recorded, "demo record of a succeeding branch verifies: {why}");
    let (verified, why) = run(&["demo", "verify", out_dir.to_str().expect("utf-8")]);
    assert!(verified, "demo verify replays the prefix first: {why}");
    let manifest: Value = serde_json::from_slice(&std::fs::read(out_dir.join("manifest.json")).expect("manifest")).expect("JSON");
    assert_eq!(manifest["transition_count"].as_u64(), Some(parent_actions.len() as u64 - step), "{manifest}");
    assert_eq!(manifest["verification"]["verified"], true, "{manifest}");
}
