//! The client against a policy server written on the real openpi-client package (PyPI, 0.1.2): the LIBERO
//! contract checked by openpi's own preprocessing, scripted chunks, bit-exact round trips of every dtype, the
//! policy's traceback and close 1011, a server that never answers, `/healthz`, the API key, and the bytes of a
//! request as openpi's packer writes them.
mod common;

use std::time::Duration;

use common::{FixtureServer, fixture_script, venv_python, write_published_frame};
use libero_policy::codec::{self, Dtype, NdArray, map_get};
use libero_policy::libero::{LiberoContract, PublishedFrame, RobotBaseInWorld, observation_request, policy_state};
use libero_policy::{ChunkExecutor, ClientLimits, Endpoint, PolicyClient, PolicyError, healthz};
use rmpv::Value;

const PROMPT: &str = "put both the alphabet soup and the tomato sauce in the basket";

fn base() -> RobotBaseInWorld {
    RobotBaseInWorld { p_base_in_world_m: [-0.66, 0.0, 0.912], q_world_from_base_wxyz: [1.0, 0.0, 0.0, 0.0] }
}

fn connect(server: &FixtureServer) -> PolicyClient {
    PolicyClient::connect(&Endpoint::parse(&server.url()).unwrap(), None, ClientLimits::default()).unwrap()
}

/// Scripted chunks: `n` chunks of 10 actions, float32 as π0 answers.
fn chunks(n: usize) -> Vec<Vec<Vec<f32>>> {
    (0..n).map(|c| (0..10).map(|t| (0..7).map(|k| (c * 100 + t * 10 + k) as f32 / 1000.0 - 0.25).collect()).collect()).collect()
}

#[test]
fn the_libero_contract_matches_openpis_preprocessing_and_chunks_execute_five_at_a_time() {
    let dir = tempfile::tempdir().unwrap();
    write_published_frame(dir.path(), 7);
    let frame = PublishedFrame::read(dir.path()).unwrap();
    let expect = dir.path().join("expect.json");
    let state = policy_state(&frame, &base());
    std::fs::write(
        &expect,
        serde_json::to_vec(&serde_json::json!({
            "head_png": dir.path().join("head/rgb.png"), "wrist_png": dir.path().join("wrist/rgb.png"),
            "state": state, "prompt": PROMPT,
        }))
        .unwrap(),
    )
    .unwrap();
    let scripted = chunks(2);
    let chunk_file = dir.path().join("chunks.json");
    let doc: Vec<_> = scripted.iter().map(|c| serde_json::json!({"actions": c, "dtype": "<f4"})).collect();
    std::fs::write(&chunk_file, serde_json::to_vec(&doc).unwrap()).unwrap();
    let server = FixtureServer::start(&["--mode", "contract", "--expect", expect.to_str().unwrap(), "--chunks", chunk_file.to_str().unwrap()]);

    let mut client = connect(&server);
    let Value::Map(meta) = client.metadata() else { panic!("metadata") };
    assert_eq!(map_get(meta, "mode").and_then(Value::as_str), Some("contract"));
    let array = NdArray::from_value(map_get(meta, "array").unwrap()).unwrap().unwrap();
    assert_eq!((array.dtype, array.shape.clone(), array.to_f64()), (Dtype::I64, vec![3], vec![0.0, 1.0, 2.0]));

    let contract = LiberoContract::default().with_metadata(client.metadata()).unwrap();
    let mut executor = ChunkExecutor::new(contract.replan_steps);
    let mut executed = Vec::new();
    let mut requests = 0;
    for _ in 0..10 {
        if executor.needs_chunk() {
            let obs = observation_request(&frame, &base(), PROMPT, &contract).unwrap();
            let chunk = client.infer(&obs).unwrap_or_else(|e| panic!("{e}"));
            assert_eq!(chunk.actions_dtype, "<f4");
            assert!(chunk.server_timing.contains_key("infer_ms"), "{:?}", chunk.server_timing);
            assert_eq!(chunk.policy_timing.get("infer_ms"), Some(&1.25));
            executor.push_chunk(&chunk.actions).unwrap();
            requests += 1;
        }
        executed.push(executor.next_action().unwrap());
    }
    assert_eq!(requests, 2);
    for (i, a) in executed.iter().enumerate() {
        let want: Vec<f64> = scripted[i / 5][i % 5].iter().map(|&v| f64::from(v)).collect();
        assert_eq!(a.to_vec(), want, "action {i}: the first five of each chunk, bit for bit");
    }
    client.close();
}

#[test]
fn arrays_of_every_dtype_round_trip_bit_exactly() {
    let server = FixtureServer::start(&["--mode", "echo"]);
    let mut client = connect(&server);
    let sent = vec![
        ("u8", NdArray::from_u8(vec![2, 3, 4], (0..24).map(|i| (i * 11) as u8).collect()).unwrap()),
        ("f32", NdArray::from_f32(vec![5], &[0.1, -0.0, f32::MAX, f32::MIN_POSITIVE, 1e-45]).unwrap()),
        ("f64", NdArray::from_f64(vec![2, 2], &[std::f64::consts::PI, -1e300, 5e-324, 0.0]).unwrap()),
        ("i64", NdArray::new(Dtype::I64, vec![3], [i64::MIN, -1, i64::MAX].iter().flat_map(|v| v.to_le_bytes()).collect()).unwrap()),
        ("i32", NdArray::new(Dtype::I32, vec![2], [-7i32, 123456].iter().flat_map(|v| v.to_le_bytes()).collect()).unwrap()),
        ("bool", NdArray::new(Dtype::Bool, vec![2], vec![1, 0]).unwrap()),
        ("empty", NdArray::from_f32(vec![0, 7], &[]).unwrap()),
    ];
    let mut obs: Vec<(Value, Value)> = sent.iter().map(|(k, a)| (Value::from(*k), a.to_value())).collect();
    obs.push((Value::from("prompt"), Value::from("ünïcode prompt")));
    let obs = Value::Map(obs);
    // `infer` keeps only the typed chunk; the echo is read from the raw answer through the same codec.
    let chunk = client.infer(&obs).unwrap();
    assert_eq!(chunk.actions.len(), 10);
    drop(client);

    // The raw answer: connect again and read it whole.
    let mut raw = RawClient::connect(server.port);
    let answer = raw.round_trip(&codec::pack(&obs));
    let Value::Map(entries) = codec::unpack(&answer).unwrap() else { panic!("answer") };
    let Some(Value::Map(echo)) = map_get(&entries, "echo") else { panic!("no echo") };
    for (key, array) in &sent {
        let back = NdArray::from_value(map_get(echo, key).unwrap()).unwrap().unwrap();
        assert_eq!(&back, array, "{key}");
    }
    assert_eq!(map_get(echo, "prompt").and_then(Value::as_str), Some("ünïcode prompt"));
    assert_eq!(codec::to_json(map_get(&entries, "scalar").unwrap()), serde_json::json!(0.5));
}

#[test]
fn a_policy_that_raises_is_reported_with_its_traceback_and_close_1011() {
    let server = FixtureServer::start(&["--mode", "raise"]);
    let mut client = connect(&server);
    let obs = Value::Map(vec![(Value::from("prompt"), Value::from("x"))]);
    match client.infer(&obs) {
        Err(PolicyError::Policy { traceback, close_code }) => {
            assert!(traceback.contains("Traceback (most recent call last)"), "{traceback}");
            assert!(traceback.contains("ValueError: the scripted policy failed on purpose"), "{traceback}");
            assert_eq!(close_code, Some(1011));
        }
        other => panic!("expected the policy's error, got {other:?}"),
    }
    assert!(matches!(client.infer(&obs), Err(PolicyError::Connection(_))), "nothing more is sent after a failure");
}

#[test]
fn a_server_that_never_answers_times_out() {
    let server = FixtureServer::start(&["--mode", "hang"]);
    let limits = ClientLimits { infer_timeout: Duration::from_millis(800), ..ClientLimits::default() };
    let mut client = PolicyClient::connect(&Endpoint::parse(&server.url()).unwrap(), None, limits).unwrap();
    let started = std::time::Instant::now();
    let err = client.infer(&Value::Map(vec![])).unwrap_err();
    assert!(matches!(err, PolicyError::Timeout(_)), "{err}");
    assert!(started.elapsed() < Duration::from_secs(5));
    assert!(err.to_string().contains("800ms"), "{err}");
}

#[test]
fn healthz_and_the_api_key() {
    let server = FixtureServer::start(&["--mode", "echo", "--api-key", "s3cret"]);
    let endpoint = Endpoint::parse(&server.url()).unwrap();
    healthz(&endpoint, Duration::from_secs(5)).unwrap();
    let refused = PolicyClient::connect(&endpoint, None, ClientLimits::default()).err().expect("no key is refused");
    assert!(matches!(refused, PolicyError::Connection(_)), "{refused}");
    assert!(PolicyClient::connect(&endpoint, Some("wrong"), ClientLimits::default()).is_err());
    PolicyClient::connect(&endpoint, Some("s3cret"), ClientLimits::default()).unwrap().close();
    drop(server);
    assert!(healthz(&endpoint, Duration::from_secs(2)).is_err(), "nobody listens any more");
}

#[test]
fn a_request_packs_to_the_bytes_openpis_packer_writes() {
    // The committed golden: openpi-client 0.1.2's `Packer().pack` of a small request (see the spec).
    let fixtures = fixture_script().parent().unwrap().to_path_buf();
    let spec: serde_json::Value = serde_json::from_slice(&std::fs::read(fixtures.join("request_spec.json")).unwrap()).unwrap();
    let golden = std::fs::read_to_string(fixtures.join("request_openpi_client_0.1.2.hex")).unwrap();
    assert_eq!(hex(&codec::pack(&spec_request(&spec))), golden.trim());

    // And live, the full LIBERO request of a published frame: openpi's images from its own preprocessing.
    let dir = tempfile::tempdir().unwrap();
    write_published_frame(dir.path(), 11);
    let frame = PublishedFrame::read(dir.path()).unwrap();
    let state = policy_state(&frame, &base());
    let live = serde_json::json!({"request": [
        ["observation/image", "png", dir.path().join("head/rgb.png")],
        ["observation/wrist_image", "png", dir.path().join("wrist/rgb.png")],
        ["observation/state", "<f8", {"data": state, "shape": [8]}],
        ["prompt", "str", PROMPT],
    ]});
    let ours = codec::pack(&observation_request(&frame, &base(), PROMPT, &LiberoContract::default()).unwrap());
    assert_eq!(hex(&ours), openpi_pack(&live, dir.path()), "our request differs from openpi's");
}

#[test]
fn resize_with_pad_matches_pillow_on_odd_shapes() {
    // Non-square and upscaled images go through Pillow's padding and filter paths too.
    for (w, h, size) in [(256u32, 200u32, 224usize), (100, 256, 224), (64, 64, 224), (300, 300, 97)] {
        let dir = tempfile::tempdir().unwrap();
        let rgb = common::noise(u64::from(w * h), (w * h * 3) as usize);
        common::write_png(&dir.path().join("img.png"), w, h, &rgb);
        let spec = serde_json::json!({"size": size, "request": [["observation/image", "png", dir.path().join("img.png")]]});
        let img = libero_policy::libero::read_rgb_png(&dir.path().join("img.png")).unwrap();
        let contract = LiberoContract { image_height: size, image_width: size, ..LiberoContract::default() };
        let out = libero_policy::libero::policy_image(&img, &contract);
        let ours = Value::Map(vec![(Value::from("observation/image"), NdArray::from_u8(vec![size, size, 3], out.data).unwrap().to_value())]);
        assert_eq!(hex(&codec::pack(&ours)), openpi_pack(&spec, dir.path()), "{w}×{h} → {size}");
    }
}

/// The request a spec describes, built with our codec.
fn spec_request(spec: &serde_json::Value) -> Value {
    let entries = spec["request"].as_array().unwrap().iter().map(|e| {
        let (key, kind, value) = (e[0].as_str().unwrap(), e[1].as_str().unwrap(), &e[2]);
        let v = match kind {
            "str" => Value::from(value.as_str().unwrap()),
            dtype => {
                let shape: Vec<usize> = value["shape"].as_array().unwrap().iter().map(|d| d.as_u64().unwrap() as usize).collect();
                let data: Vec<f64> = value["data"].as_array().unwrap().iter().map(|d| d.as_f64().unwrap()).collect();
                let a = match dtype {
                    "|u1" => NdArray::from_u8(shape, data.iter().map(|&d| d as u8).collect()),
                    "<f4" => NdArray::from_f32(shape, &data.iter().map(|&d| d as f32).collect::<Vec<_>>()),
                    "<f8" => NdArray::from_f64(shape, &data),
                    other => panic!("{other}"),
                };
                a.unwrap().to_value()
            }
        };
        (Value::from(key), v)
    });
    Value::Map(entries.collect())
}

fn openpi_pack(spec: &serde_json::Value, dir: &std::path::Path) -> String {
    let path = dir.join("pack_spec.json");
    std::fs::write(&path, serde_json::to_vec(spec).unwrap()).unwrap();
    let out = std::process::Command::new(venv_python())
        .arg(fixture_script())
        .args(["--mode", "pack", "--expect", path.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8(out.stdout).unwrap()
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// A bare websocket client that returns the server's answer bytes unparsed.
struct RawClient(tungstenite::WebSocket<std::net::TcpStream>);

impl RawClient {
    fn connect(port: u16) -> Self {
        let tcp = std::net::TcpStream::connect(("127.0.0.1", port)).unwrap();
        let (mut ws, _) = tungstenite::client::client(format!("ws://127.0.0.1:{port}/"), tcp).unwrap();
        ws.read().unwrap(); // metadata
        Self(ws)
    }

    fn round_trip(&mut self, bytes: &[u8]) -> Vec<u8> {
        self.0.send(tungstenite::Message::Binary(bytes.to_vec().into())).unwrap();
        self.0.read().unwrap().into_data().to_vec()
    }
}
