//! Issue 33: the live view's first frame is the settled start state, and an episode can be continued from any
//! control step of another one (a branch): real `serve` processes, the operator API, MCP clients, the live and
//! teleop sockets, the records on disk and chromium on the review page. An episode without a video is reviewed from
//! moments rendered from its recorded state, and continued from the step shown (issue 49, item 1).
mod common;

use std::io::{BufReader, Read, Write};
use std::path::{Path, PathBuf};
use std::time::Duration;

use libero_episode::state_record::StateRecordReader;
use libero_server::client::McpClient;
use serde_json::{Value, json};

use common::{call_ok, post_json as post};

fn mcp(prepared: &Value) -> McpClient {
    common::mcp_session(prepared, "branches-test")
}

fn actions(a: [f64; 7], n: usize) -> Value {
    json!({"actions": vec![a; n]})
}

/// The private copy of observation `obs` of episode `id`: its `observation.json` without the fields that name the
/// observation (its id and index), and the bytes of its two images.
fn observation(data: &Path, id: &str, obs: &str) -> (Value, Vec<u8>, Vec<u8>) {
    let dir = data.join("runs").join(id).join("private_observations").join(obs);
    let mut doc: Value = serde_json::from_slice(&std::fs::read(dir.join("observation.json")).expect("observation.json")).expect("JSON");
    for k in ["observation_id", "frame_index"] {
        doc.as_object_mut().expect("object").remove(k);
    }
    let read = |p: &str| std::fs::read(dir.join(p)).unwrap_or_else(|e| panic!("{p}: {e}"));
    (doc, read("head/rgb.png"), read("wrist/rgb.png"))
}

fn decode_png(bytes: &[u8]) -> (u32, u32, Vec<u8>) {
    let mut reader = png::Decoder::new(std::io::Cursor::new(bytes)).read_info().expect("png");
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).expect("png frame");
    buf.truncate(info.buffer_size());
    (info.width, info.height, buf)
}

/// A WebSocket to `path` of `server` with the operator token, past the handshake.
fn websocket(server: &common::Server, path: &str) -> BufReader<std::net::TcpStream> {
    let rest = server.url.strip_prefix("http://").expect("http url");
    let mut stream = std::net::TcpStream::connect(rest).expect("connect");
    stream.set_read_timeout(Some(Duration::from_secs(300))).expect("timeout");
    write!(
        stream,
        "GET {path} HTTP/1.1\r\nHost: {rest}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\nSec-WebSocket-Version: 13\r\n\
         Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nAuthorization: Bearer {}\r\n\r\n",
        server.token
    )
    .expect("handshake");
    let mut r = BufReader::new(stream);
    let mut head = Vec::new();
    while !head.ends_with(b"\r\n\r\n") {
        let mut b = [0u8; 1];
        r.read_exact(&mut b).expect("handshake answer");
        head.push(b[0]);
    }
    assert!(head.starts_with(b"HTTP/1.1 101"), "{}", String::from_utf8_lossy(&head));
    r
}

/// The next message: (opcode, payload).
fn next_message(r: &mut BufReader<std::net::TcpStream>) -> (u8, Vec<u8>) {
    let mut h = [0u8; 2];
    r.read_exact(&mut h).expect("frame header");
    let mut len = u64::from(h[1] & 0x7f);
    if len == 126 {
        let mut l = [0u8; 2];
        r.read_exact(&mut l).expect("length");
        len = u64::from(u16::from_be_bytes(l));
    } else if len == 127 {
        let mut l = [0u8; 8];
        r.read_exact(&mut l).expect("length");
        len = u64::from_be_bytes(l);
    }
    let mut payload = vec![0u8; len as usize];
    r.read_exact(&mut payload).expect("payload");
    (h[0] & 0x0f, payload)
}

/// Sends one masked text message (a client must mask).
fn send_text(r: &mut BufReader<std::net::TcpStream>, text: &str) {
    let bytes = text.as_bytes();
    let mask = [0x12u8, 0x34, 0x56, 0x78];
    let mut frame = vec![0x81u8];
    match bytes.len() {
        n if n < 126 => frame.push(0x80 | n as u8),
        n if n < 65536 => {
            frame.push(0x80 | 126);
            frame.extend_from_slice(&(n as u16).to_be_bytes());
        }
        n => {
            frame.push(0x80 | 127);
            frame.extend_from_slice(&(n as u64).to_be_bytes());
        }
    }
    frame.extend_from_slice(&mask);
    frame.extend(bytes.iter().enumerate().map(|(i, b)| b ^ mask[i % 4]));
    r.get_mut().write_all(&frame).expect("send");
}

/// The live socket's `hello` and its first frame (header, JPEG).
fn hello_and_first_frame(server: &common::Server, id: &str) -> (Value, Value, Vec<u8>) {
    let mut ws = websocket(server, &format!("/ws/episodes/{id}"));
    let (op, hello) = next_message(&mut ws);
    assert_eq!(op, 1, "the socket begins with its hello");
    let hello: Value = serde_json::from_slice(&hello).expect("hello JSON");
    loop {
        let (op, payload) = next_message(&mut ws);
        if op == 2 {
            let n = u32::from_le_bytes(payload[..4].try_into().expect("header length")) as usize;
            let header: Value = serde_json::from_slice(&payload[4..4 + n]).expect("frame header");
            return (hello, header, payload[4 + n..].to_vec());
        }
    }
}

fn artifacts_dir() -> PathBuf {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("../test-artifacts/branches");
    std::fs::create_dir_all(&dir).expect("artifacts dir");
    dir
}

fn state_record_frames(data: &Path, id: &str) -> Vec<Vec<f64>> {
    let mut r = StateRecordReader::open(&data.join("runs").join(id).join("state_record.bin")).expect("state record");
    let mut out = Vec::new();
    while let Some((qpos, _)) = r.next_frame().expect("a frame") {
        out.push(qpos);
    }
    out
}

fn wait_for_video(server: &common::Server, id: &str) {
    for _ in 0..1200 {
        let (_, v) = common::http_get_json(&format!("{}/api/episodes/{id}/review?part=video", server.url));
        if v["video"] == true {
            return;
        }
        assert_ne!(v["video_status"]["state"], "failed", "{v}");
        std::thread::sleep(Duration::from_millis(500));
    }
    panic!("the video of {id} was not rendered in 10 minutes");
}

/// Item 1: before `start_episode`, a viewer of the live page sees the settled start state: the frame the socket
/// sends first is the JPEG of exactly the images the agent's initial observation then holds (T14: bowl, boxes,
/// open drawer; before the fix it was the composed scene without its placed objects).
#[test]
fn the_live_sockets_first_frame_is_the_settled_start_state_the_agent_then_receives() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let data = tmp.path().join("data");
    let server = common::Server::start(&data);
    let req = json!({"task": "T14", "level": 1, "video": false, "workspace": tmp.path().join("ws")});
    let (status, prepared) = post(&server, "/api/episodes", &req, Some(&server.token));
    assert_eq!(status, 201, "{prepared}");
    let id = prepared["episode_id"].as_str().expect("id");
    let (_, header, jpeg) = hello_and_first_frame(&server, id);
    assert_eq!(header["control_step"], Value::Null, "the frame before the start: {header}");
    let start = call_ok(&mut mcp(&prepared), "start_episode", json!({}));
    let (_, head, wrist) = observation(&data, id, start["observation_id"].as_str().expect("observation id"));
    let ((w, h, head), (_, _, wrist)) = (decode_png(&head), decode_png(&wrist));
    let side = libero_episode::video::side_by_side(&head, &wrist, w as usize, h as usize).expect("side by side");
    let expected = libero_episode::live::encode_jpeg(&side, 2 * w, h).expect("jpeg");
    std::fs::write(artifacts_dir().join("first-live-frame.jpg"), &jpeg).expect("artifact");
    std::fs::write(artifacts_dir().join("first-observation-as-live.jpg"), &expected).expect("artifact");
    assert!(
        jpeg == expected,
        "the first live frame ({} bytes) is not the JPEG of the initial observation's images ({} bytes)",
        jpeg.len(),
        expected.len()
    );
}

/// Item 2 on T14: a branch at step k starts bit-identical to its parent at k (state record, observation state and
/// images), says so everywhere (API, action log, live socket, home list), continues over MCP (judged) and by
/// teleop; bad requests get clear 4xx; chromium continues a review by teleop from the step it shows.
#[test]
fn a_t14_branch_starts_where_its_parent_was_and_continues_over_mcp_and_teleop() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let data = tmp.path().join("data");
    let server = common::Server::start(&data);
    let token = server.token.clone();
    // The parent: three 5-action calls, then finished.
    let req = json!({"task": "T14", "level": 2, "workspace": tmp.path().join("parent")});
    let (status, parent) = post(&server, "/api/episodes", &req, Some(&token));
    assert_eq!(status, 201, "{parent}");
    let parent_id = parent["episode_id"].as_str().expect("id").to_owned();
    let mut client = mcp(&parent);
    call_ok(&mut client, "start_episode", json!({}));
    call_ok(&mut client, "osc_sequence", actions([0.6, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0], 5));
    let at_10 = call_ok(&mut client, "osc_sequence", actions([0.0, 0.5, -0.4, 0.0, 0.2, 0.0, -1.0], 5));
    call_ok(&mut client, "osc_sequence", actions([0.0, 0.0, 0.0, 0.0, 0.0, 0.3, 1.0], 5));
    call_ok(&mut client, "finish_episode", json!({}));
    let k = 10u64;

    // Errors first: unknown parent, step beyond the log, no operator token.
    let (status, e) = post(&server, "/api/episodes", &json!({"branch": {"parent": "ep-nobody", "step": 1}}), Some(&token));
    assert_eq!(status, 404, "{e}");
    assert!(e["error"].as_str().unwrap_or("").contains("ep-nobody"), "{e}");
    let (status, e) = post(&server, "/api/episodes", &json!({"branch": {"parent": parent_id, "step": 16}}), Some(&token));
    assert_eq!(status, 400, "{e}");
    assert!(e["error"].as_str().unwrap_or("").contains("15 control steps"), "{e}");
    let (status, e) = post(&server, "/api/episodes", &json!({"branch": {"parent": parent_id, "step": 1}}), None);
    assert_eq!(status, 401, "{e}");
    let (status, e) = post(&server, "/api/teleop", &json!({"branch": {"parent": "ep-nobody", "step": 1}}), Some(&token));
    assert_eq!(status, 404, "teleop: {e}");
    let (status, e) = post(&server, "/api/episodes", &json!({"task": "T21", "branch": {"parent": parent_id, "step": 1}}), Some(&token));
    assert_eq!(status, 400, "another task: {e}");

    // The branch for an agent: its own endpoint and workspace.
    let req = json!({"branch": {"parent": parent_id, "step": k}, "level": 2, "workspace": tmp.path().join("branch")});
    let (status, branch) = post(&server, "/api/episodes", &req, Some(&token));
    assert_eq!(status, 201, "{branch}");
    let branch_id = branch["episode_id"].as_str().expect("id").to_owned();
    assert_eq!(branch["branch"], json!({"parent": parent_id, "step": k}), "{branch}");
    assert_eq!(branch["task"], "T14");
    assert!(Path::new(branch["prompt_file"].as_str().expect("prompt file")).is_file(), "the branch has its own workspace: {branch}");
    let (hello, first, _) = hello_and_first_frame(&server, &branch_id);
    assert_eq!(hello["branch"], json!({"parent_episode_id": parent_id, "parent_control_step": k}), "the live socket says it is a branch");
    assert_eq!(first["control_step"], Value::Null);
    let (_, row) = common::http_get_json(&format!("{}/api/episodes/{branch_id}", server.url));
    assert_eq!((row["branch_parent"].as_str(), row["branch_step"].as_u64()), (Some(parent_id.as_str()), Some(k)), "{row}");

    // A normal fresh start whose observation is the parent's after step k, bit for bit.
    let mut bclient = mcp(&branch);
    let start = call_ok(&mut bclient, "start_episode", json!({}));
    assert_eq!(start["max_agent_steps"].as_u64(), Some(libero_episode::tools::MAX_AGENT_STEPS_CAP), "the replay takes nothing of the budget");
    let theirs = observation(&data, &parent_id, at_10["observation_id"].as_str().expect("obs"));
    let ours = observation(&data, &branch_id, start["observation_id"].as_str().expect("obs"));
    assert_eq!(ours.0, theirs.0, "observation.json (state, sim time) at step {k}");
    assert!(ours.1 == theirs.1 && ours.2 == theirs.2, "head and wrist PNGs at step {k} are byte-identical");
    call_ok(&mut bclient, "osc_sequence", actions([0.0, -0.5, 0.3, 0.0, 0.0, 0.0, 1.0], 4));
    let finished = call_ok(&mut bclient, "finish_episode", json!({}));
    assert_eq!(finished["status"], "finished");
    assert_eq!(finished["accepted_agent_steps"], 1, "only the branch's own call counts");
    // The action log says where it branched; the state record holds the parent's states up to k bit for bit.
    let log = std::fs::read_to_string(data.join("runs").join(&branch_id).join("actions.jsonl")).expect("actions.jsonl");
    let first_line: Value = serde_json::from_str(log.lines().next().expect("a line")).expect("JSON");
    assert_eq!(first_line["request"]["command"], "branch_from");
    assert_eq!(first_line["request"]["parent_episode_id"], parent_id.as_str());
    assert_eq!(first_line["request"]["parent_control_step"], k);
    wait_for_video(&server, &parent_id);
    wait_for_video(&server, &branch_id);
    let (p, b) = (state_record_frames(&data, &parent_id), state_record_frames(&data, &branch_id));
    let settle = libero_episode::world::SETTLE_STEPS;
    let shared = settle + k as usize;
    assert_eq!(b.len(), shared + 4, "settle, the replayed prefix and the branch's own 4 steps");
    let bits = |f: &Vec<f64>| f.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    for i in 0..shared {
        assert_eq!(bits(&b[i]), bits(&p[i]), "state record frame {i} (qpos) differs from the parent's");
    }
    assert_ne!(bits(&b[shared]), bits(&p[shared]), "after the branch point the branch goes its own way");
    let (_, review) = common::http_get_json(&format!("{}/api/episodes/{branch_id}/review", server.url));
    let calls = review["calls"].as_array().expect("calls");
    assert_eq!((calls[0]["tool"].as_str(), calls[0]["control_step_end"].as_u64()), (Some("branch_from"), Some(k)), "{}", calls[0]);

    // By teleop: the teleop API makes the branch, the teleop socket drives it.
    let (status, teleop) = post(&server, "/api/teleop", &json!({"branch": {"parent": parent_id, "step": 5}}), Some(&token));
    assert_eq!(status, 200, "{teleop}");
    let teleop_id = teleop["episode_id"].as_str().expect("id").to_owned();
    assert_eq!(teleop["task"], "T14");
    let mut control = websocket(&server, &format!("/ws/teleop/{teleop_id}"));
    send_text(&mut control, &json!({"seq": 1, "actions": [[0.0, 0.0, 0.5, 0.0, 0.0, 0.0, -1.0], [0.0, 0.0, 0.5, 0.0, 0.0, 0.0, -1.0]]}).to_string());
    let (op, ack) = next_message(&mut control);
    let ack: Value = serde_json::from_slice(&ack).expect("ack JSON");
    assert_eq!(op, 1);
    assert_eq!(ack["seq"], 1, "{ack}");
    assert_ne!(ack["ok"], false, "{ack}");
    let tlog = std::fs::read_to_string(data.join("runs").join(&teleop_id).join("actions.jsonl")).expect("actions.jsonl");
    assert!(tlog.lines().next().is_some_and(|l| l.contains("branch_from")), "{tlog}");

    // The home list names the parent of each branch.
    let (_, home) = common::http_get_text(&format!("{}/", server.url));
    assert!(home.contains(&format!("branch of <a href=\"/episodes/{parent_id}/review\">{parent_id}</a> at step {k}")), "home list");
    let (_, page) = common::http_get_text(&format!("{}/episodes/{branch_id}/review", server.url));
    assert!(page.contains("branch of") && page.contains("id=\"continue-teleop\""), "review page");
    // A teleop branch the page could not start is an error page saying why (issue 49), not a page with dead controls.
    for (query, status, says) in [
        ("/teleop/T14?branch=ep-20990101T000000Z-deadbeef&step=1".to_owned(), 404, "no episode ep-20990101T000000Z-deadbeef".to_owned()),
        (format!("/teleop/T14?branch={parent_id}&step=99999"), 400, "step 99999 is beyond".to_owned()),
        (format!("/teleop/T21?branch={parent_id}&step=1"), 400, format!("episode {parent_id} is an episode of T14, not T21")),
    ] {
        let (got, body) = common::http_get_text(&format!("{}{query}", server.url));
        assert_eq!(got, status, "{query}: {body}");
        assert!(body.contains(&says) && body.contains("error-message"), "{query}: {body}");
    }

    // Chromium: the parent's review, three control steps in, "Continue from here" by teleop.
    let artifacts = artifacts_dir();
    let report = common::browser_script("branch_check.cjs", &[&server.url, &parent_id, "3", artifacts.to_str().expect("utf-8")], &token);
    assert_eq!(report["ok"], true, "{report}");
    // Teleop steps on in real time once the page is open, so the frame read is at step 3 or later, never before.
    let frame_step: u64 = report["frame_step"].as_str().and_then(|s| s.parse().ok()).expect("the frame's control step");
    assert!(frame_step >= 3, "the teleop branch starts at control step 3: {report}");
    let made = report["episode_id"].as_str().expect("the branch's id");
    let (_, row) = common::http_get_json(&format!("{}/api/episodes/{made}", server.url));
    assert_eq!((row["branch_parent"].as_str(), row["branch_step"].as_u64()), (Some(parent_id.as_str()), Some(3)), "{row}");
}

/// Item 2 on a two-stage task: T28's expert opens the door (unlatch, then open); a branch after the first stage
/// and before the second starts with the first reached, and its record at once equals the parent's up to there.
#[test]
fn a_t28_branch_after_the_first_stage_keeps_it_reached() {
    use libero_episode::expert_run::{ToolPort, run_expert};
    struct Port(McpClient);
    impl ToolPort for Port {
        fn call_tool(&mut self, tool: &str, arguments: Value) -> Result<Value, libero_episode::EpisodeError> {
            self.0.call_tool_payload(tool, arguments).map_err(|e| libero_episode::EpisodeError::Task(format!("{e:#}")))
        }
    }
    let tmp = tempfile::tempdir().expect("tempdir");
    let data = tmp.path().join("data");
    let server = common::Server::start(&data);
    let req = json!({"task": "T28", "level": 1, "seed": 100, "video": false, "workspace": tmp.path().join("parent")});
    let (status, parent) = post(&server, "/api/episodes", &req, Some(&server.token));
    assert_eq!(status, 201, "{parent}");
    let parent_id = parent["episode_id"].as_str().expect("id").to_owned();
    let paths = libero_sim::AssetPaths::discover().expect("assets: run scripts/setup.py");
    let spec = libero_episode::physics::WorldSpec {
        task: libero_episode::task::resolve_task("T28", &paths).expect("T28"),
        level: libero_episode::Level::L1,
        seed: 100,
        init_index: 0,
        paths,
    };
    let played = run_expert(&mut Port(mcp(&parent)), &spec, "T28", "solve", 3000, |_| {}).expect("the T28 expert");
    assert_eq!(played.finish["success"], true, "{}", played.finish);
    let events = std::fs::read_to_string(data.join("runs").join(&parent_id).join("private_stage_events.jsonl")).expect("stage events");
    let events: Vec<Value> = events.lines().map(|l| serde_json::from_str(l).expect("JSON")).collect();
    let completed: Vec<u64> =
        events.iter().filter(|e| e["kind"] == "stage_completed").filter_map(|e| e["control_step"].as_u64()).collect();
    assert_eq!(completed.len(), 2, "{events:?}");
    let k = (completed[0] + completed[1]) / 2;
    assert!(completed[0] <= k && k < completed[1]);
    let req = json!({"branch": {"parent": parent_id, "step": k}, "level": 1, "video": false, "workspace": tmp.path().join("branch")});
    let (status, branch) = post(&server, "/api/episodes", &req, Some(&server.token));
    assert_eq!(status, 201, "{branch}");
    let branch_id = branch["episode_id"].as_str().expect("id").to_owned();
    let mut client = mcp(&branch);
    call_ok(&mut client, "start_episode", json!({}));
    let finished = call_ok(&mut client, "finish_episode", json!({}));
    assert_eq!(finished["success"], false, "only the first stage is reached at step {k}");
    let result: Value =
        serde_json::from_slice(&std::fs::read(data.join("runs").join(&branch_id).join("result.json")).expect("result")).expect("JSON");
    assert_eq!(result["private_evaluation"]["completed_required_stage_count"], 1, "{}", result["private_evaluation"]);
    let ours = std::fs::read_to_string(data.join("runs").join(&branch_id).join("private_stage_events.jsonl")).unwrap_or_default();
    let ours: Vec<Value> = ours.lines().map(|l| serde_json::from_str(l).expect("JSON")).collect();
    let theirs: Vec<Value> = events.into_iter().filter(|e| e["control_step"].as_u64().is_some_and(|c| c <= k)).collect();
    assert_eq!(ours, theirs, "the branch's stage record is the parent's up to step {k}");
}

// Issue 49, item 1: an episode without a private video is reviewed from its recorded state. A real `serve`, T28's
// expert run with `--no-video` through it, the moment route (`/api/episodes/{id}/moment?step=N`) and its errors,
// and chromium on the review page: moments per control step that match what the agent observed, plots, stepping,
// play and "Continue from here" at the step shown.

/// T28's expert on `server` without a video: (episode id, actions executed).
fn play_t28_without_video(server: &common::Server) -> (String, u64) {
    let v = common::expert_on_server(&server.url, "T28");
    (v["episode_id"].as_str().expect("episode id").to_owned(), v["actions"].as_u64().expect("actions"))
}

fn header<'a>(headers: &'a str, name: &str) -> Option<&'a str> {
    headers.lines().find_map(|l| l.split_once(':').filter(|(k, _)| k.trim().eq_ignore_ascii_case(name)).map(|(_, v)| v.trim()))
}

#[test]
fn an_episode_without_video_is_reviewed_from_moments_rendered_from_its_recorded_state() {
    let data = tempfile::tempdir().unwrap();
    let server = common::Server::start(data.path());
    let (id, actions) = play_t28_without_video(&server);
    assert!(!data.path().join("runs").join(&id).join("continuous_video.mp4").exists(), "the episode has no video");
    let auth = format!("Bearer {}", server.token);
    let get = |path: &str, auth: Option<&str>| {
        let headers: Vec<(&str, &str)> = auth.map(|a| vec![("Authorization", a)]).unwrap_or_default();
        common::http("GET", &format!("{}{path}", server.url), &headers, b"")
    };

    // Every control step from the settled start (0) to the last action has its moment: a JPEG naming its step.
    for step in [0, actions / 2, actions] {
        let (status, headers, body) = get(&format!("/api/episodes/{id}/moment?step={step}"), Some(&auth));
        assert_eq!(status, 200, "step {step}: {}", String::from_utf8_lossy(&body));
        assert_eq!(header(&headers, "content-type"), Some("image/jpeg"));
        assert_eq!(header(&headers, "x-control-step"), Some(step.to_string().as_str()));
        assert_eq!(header(&headers, "x-control-steps"), Some(actions.to_string().as_str()));
        assert!(body.starts_with(&[0xFF, 0xD8]) && body.len() > 5000, "a JPEG of a scene ({} bytes)", body.len());
    }
    // Bad input gets a clear error and renders nothing.
    for (query, status, says) in [
        ("step=abc".to_owned(), 400, "step must be a control step number".to_owned()),
        (String::new(), 400, "step must be a control step number".to_owned()),
        ("step=-1".to_owned(), 400, "step must be a control step number".to_owned()),
        (format!("step={}", actions + 1), 400, format!("control step {} is past the episode's last ({actions} control steps", actions + 1)),
    ] {
        let (got, _, body) = get(&format!("/api/episodes/{id}/moment?{query}"), Some(&auth));
        let body = String::from_utf8_lossy(&body);
        assert_eq!(got, status, "{query}: {body}");
        assert!(body.contains(&says), "{query}: {body}");
    }
    let (got, _, _) = get("/api/episodes/ep-20990101T000000Z-deadbeef/moment?step=0", Some(&auth));
    assert_eq!(got, 404, "an unknown episode");
    // Operator-only: without the operator's credential, or with an episode's token, nothing is rendered.
    let prepared = common::prepare_t14(&server.url, &data.path().join("agent-ws"));
    let agent = prepared["mcp_headers"]["Authorization"].as_str().expect("the episode's token").to_owned();
    for credential in [None, Some(agent.as_str())] {
        let (got, _, body) = get(&format!("/api/episodes/{id}/moment?step=0"), credential);
        assert!(got == 401 || got == 303, "{credential:?}: {got}");
        assert!(!body.starts_with(&[0xFF, 0xD8]));
    }

    // Chromium: the review opened at step 120 shows moments, plots, steps, plays and continues from the step shown.
    let artifacts = std::env::temp_dir().join("libero-agent-review-moments");
    std::fs::create_dir_all(&artifacts).unwrap();
    let report = common::browser_script("review_moments_check.cjs", &[&server.url, &id, "120", artifacts.to_str().expect("utf-8")], &server.token);
    assert_eq!(report["ok"], true, "{report}");
    let branch_step = report["branch_step"].as_u64().expect("the branch's step");
    assert!(branch_step > 120, "play moved past the opened moment before the branch: {report}");
    let (_, rows) = common::http_get_json(&format!("{}/api/episodes", server.url));
    let branch = rows["episodes"].as_array().expect("episodes").iter().find(|r| r["branch_parent"] == id.as_str()).cloned();
    let branch = branch.unwrap_or_else(|| panic!("a branch of {id}: {rows}"));
    assert_eq!(branch["branch_step"].as_u64(), Some(branch_step), "{branch}");
    assert_eq!((branch["harness"].as_str(), branch["model"].as_str(), branch["batch"].as_str()), (Some("expert"), Some("solve"), None), "{branch}");
}
