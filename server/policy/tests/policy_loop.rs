//! openpi's LIBERO loop (`episode::run_loop`) against the fixture server on the real openpi-client: the warm-up,
//! chunks cut to `replan_steps` and sent as one `osc_sequence` each, the control-step cap, a policy failure. The
//! episode side here is a recorder that republishes one folder: the episode service's own run of this loop is
//! issue 51's harness work, not this test's.
mod common;

use std::path::PathBuf;

use common::{FixtureServer, write_published_frame};
use libero_policy::episode::{EpisodeSteps, LoopEnd, run_loop};
use libero_policy::libero::{LIBERO_DUMMY_ACTION, LiberoContract, PublishedFrame, RobotBaseInWorld, policy_state};
use libero_policy::{ClientLimits, Endpoint, PolicyClient, PolicyError};

const PROMPT: &str = "open the top drawer of the cabinet";
const BASE: RobotBaseInWorld = RobotBaseInWorld { p_base_in_world_m: [-0.66, 0.0, 0.912], q_world_from_base_wxyz: [1.0, 0.0, 0.0, 0.0] };

/// Records each `osc_sequence` and answers with the same published folder.
struct Recorder {
    dir: PathBuf,
    calls: Vec<Vec<[f64; 7]>>,
}

impl EpisodeSteps for Recorder {
    fn osc_sequence(&mut self, actions: &[[f64; 7]]) -> Result<Option<PathBuf>, String> {
        assert!((1..=50).contains(&actions.len()));
        assert!(actions.iter().flatten().all(|v| v.abs() <= 1.0));
        self.calls.push(actions.to_vec());
        Ok(Some(self.dir.clone()))
    }
}

fn setup(mode: &str) -> (tempfile::TempDir, FixtureServer, Vec<Vec<Vec<f32>>>) {
    let dir = tempfile::tempdir().unwrap();
    write_published_frame(dir.path(), 3);
    let frame = PublishedFrame::read(dir.path()).unwrap();
    let expect = dir.path().join("expect.json");
    let spec = serde_json::json!({
        "head_png": dir.path().join("head/rgb.png"), "wrist_png": dir.path().join("wrist/rgb.png"),
        "state": policy_state(&frame, &BASE), "prompt": PROMPT,
    });
    std::fs::write(&expect, spec.to_string()).unwrap();
    // Three chunks of 8 actions; the first action of the second chunk asks for 1.5 (clipped to 1).
    let chunks: Vec<Vec<Vec<f32>>> =
        (0..3).map(|c| (0..8).map(|t| (0..7).map(|k| if c == 1 && t == 0 && k == 0 { 1.5 } else { (c * 10 + t + k) as f32 / 100.0 }).collect()).collect()).collect();
    let chunk_file = dir.path().join("chunks.json");
    let doc: Vec<_> = chunks.iter().map(|c| serde_json::json!({"actions": c, "dtype": "<f4"})).collect();
    std::fs::write(&chunk_file, serde_json::to_vec(&doc).unwrap()).unwrap();
    let server = FixtureServer::start(&["--mode", mode, "--expect", expect.to_str().unwrap(), "--chunks", chunk_file.to_str().unwrap()]);
    (dir, server, chunks)
}

#[test]
fn the_loop_warms_up_then_executes_five_of_each_chunk_up_to_the_cap() {
    let (dir, server, chunks) = setup("contract");
    let mut client = PolicyClient::connect(&Endpoint::parse(&server.url()).unwrap(), None, ClientLimits::default()).unwrap();
    let mut episode = Recorder { dir: dir.path().to_path_buf(), calls: Vec::new() };
    let contract = LiberoContract::default();
    let report = run_loop(&mut episode, &mut client, &contract, &BASE, PROMPT, dir.path().to_path_buf(), 12);
    assert!(matches!(report.end, LoopEnd::StepCap), "{:?}", report.end);
    assert_eq!((report.warmup_steps, report.control_steps, report.timings.len(), report.clipped_components), (10, 12, 3, 1));
    assert!(report.timings.iter().all(|t| t.contains_key("infer_ms") && t.contains_key("client_round_trip_ms")));
    let sizes: Vec<usize> = episode.calls.iter().map(Vec::len).collect();
    assert_eq!(sizes, [10, 5, 5, 2]);
    assert!(episode.calls[0].iter().all(|a| *a == LIBERO_DUMMY_ACTION));
    for (call, chunk) in episode.calls[1..].iter().zip(&chunks) {
        for (a, want) in call.iter().zip(chunk) {
            let want: Vec<f64> = want.iter().map(|&v| f64::from(v).clamp(-1.0, 1.0)).collect();
            assert_eq!(a.to_vec(), want);
        }
    }
}

#[test]
fn a_raising_policy_ends_the_loop_with_its_traceback_after_the_warm_up() {
    let (dir, server, _) = setup("raise");
    let mut client = PolicyClient::connect(&Endpoint::parse(&server.url()).unwrap(), None, ClientLimits::default()).unwrap();
    let mut episode = Recorder { dir: dir.path().to_path_buf(), calls: Vec::new() };
    let report = run_loop(&mut episode, &mut client, &LiberoContract::default(), &BASE, PROMPT, dir.path().to_path_buf(), 100);
    match report.end {
        LoopEnd::Policy(PolicyError::Policy { traceback, close_code: Some(1011) }) => assert!(traceback.contains("ValueError"), "{traceback}"),
        other => panic!("{other:?}"),
    }
    assert_eq!((episode.calls.len(), report.control_steps), (1, 0));
}
