//! `libero-agent bench teleop`: key-to-frame latency of teleoperation over the real WebSocket path. An
//! in-process server creates an operator episode (`POST /api/teleop`), and the bench opens the teleop
//! control socket and the live frame socket exactly as the teleop page does, sends action batches at the
//! 20 Hz control rate (at most two in flight, as the page), and measures from each send to the first frame
//! whose control step covers that batch. Beside it, `ack_ms` (send to the control socket's answer: the
//! episode executed the batch) says how much of that latency is the simulation and how much the live view.
use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{Context, bail};
use futures_util::{SinkExt, StreamExt};
use serde::Deserialize;
use serde_json::{Value, json};
use tokio::net::TcpStream;
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::tungstenite::client::IntoClientRequest;
use tokio_tungstenite::{MaybeTlsStream, WebSocketStream};

use crate::bench_mcp::percentile_ms;
use libero_server::client::{InProcessServer, post_json};
use libero_server::credential::operator_headers;

/// The control period: one action per 50 ms, as the teleop page generates them.
const CONTROL_PERIOD: Duration = Duration::from_millis(50);
/// Batches in flight at most, as the page (beyond that it stops generating).
const MAX_IN_FLIGHT: usize = 2;
/// How long to wait for the frame of the last batch after sending stops.
const DRAIN_LIMIT: Duration = Duration::from_secs(30);

/// Arguments of `bench teleop`.
#[derive(Debug, Clone, clap::Args)]
pub struct BenchTeleopArgs {
    /// Print only the JSON result.
    #[arg(long)]
    pub json: bool,
    /// Catalog task of the operator episode.
    #[arg(long, default_value = "T14")]
    pub task: String,
    /// Seconds of driving.
    #[arg(long, default_value_t = 10.0)]
    pub seconds: f64,
    /// Actions per batch (the page's default is 2: one batch, hence one live frame, every 100 ms).
    #[arg(long, default_value_t = 2)]
    pub batch: usize,
    /// Data directory of the in-process server (default: a new temporary directory, removed afterwards).
    #[arg(long)]
    pub data: Option<PathBuf>,
}

type Socket = WebSocketStream<MaybeTlsStream<TcpStream>>;

/// A frame as it arrived: when, and the control step it shows (`None`: a settle state).
#[derive(Debug, Clone, Copy)]
struct FrameSeen {
    at: Instant,
    control_step: Option<u64>,
}

/// A batch as it left: its sequence number, when, and the control step its last action reaches.
#[derive(Debug, Clone, Copy)]
struct BatchSent {
    seq: u64,
    at: Instant,
    last_step: u64,
}

/// What the drive saw: batches sent, frames received, answers `(seq, when)` and the actions executed.
struct Drive {
    sent: Vec<BatchSent>,
    frames: Vec<FrameSeen>,
    acks: Vec<(u64, Instant)>,
    acked_actions: usize,
}

pub fn run(args: &BenchTeleopArgs) -> anyhow::Result<()> {
    if args.batch == 0 || args.batch > 50 || !(args.seconds > 0.0) {
        bail!("--batch must be 1 to 50 and --seconds positive");
    }
    with_console_server("teleop", args.data.as_ref(), args.json, |url| drive(url, args))
}

/// Runs `bench` against an in-process server with the console on `data` (default: a new temporary directory,
/// removed afterwards), stops the server and prints the report as JSON (pretty unless `json`).
pub(crate) fn with_console_server(name: &str, data: Option<&PathBuf>, json: bool, bench: impl FnOnce(&str) -> anyhow::Result<Value>) -> anyhow::Result<()> {
    let (data, remove_data) = match data {
        Some(d) => (d.clone(), false),
        None => (std::env::temp_dir().join(format!("libero-agent-bench-{name}-{}", std::process::id())), true),
    };
    let server = InProcessServer::start_with(data.clone(), None, Some(libero_dashboard::console()), &format!("bench_{name}_over"))?;
    let result = bench(&server.url);
    let stopped = server.stop();
    if remove_data {
        let _ = std::fs::remove_dir_all(&data);
    }
    let report = result?;
    stopped?;
    if json {
        println!("{report}");
    } else {
        println!("{}", serde_json::to_string_pretty(&report)?);
    }
    Ok(())
}

/// Creates the operator episode and drives it; the JSON report.
fn drive(base_url: &str, args: &BenchTeleopArgs) -> anyhow::Result<Value> {
    let (status, created) = post_json(base_url, "/api/teleop", &json!({"task": args.task}))?;
    let episode = TeleopCreated::deserialize(&created).ok().and_then(|c| c.episode_id).filter(|_| status == 200);
    let Some(id) = episode.as_deref() else {
        bail!("POST /api/teleop answered HTTP {status}: {created}");
    };
    let runtime = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    let Drive { sent, frames, acks, acked_actions } = runtime.block_on(drive_sockets(base_url, id, args))?;
    let summary = |mut ms: Vec<f64>| {
        let n = ms.len();
        json!({"p50": percentile_ms(&mut ms, 50.0), "p95": percentile_ms(&mut ms, 95.0), "n": n})
    };
    let ack_ms: Vec<f64> = sent
        .iter()
        .filter_map(|b| acks.iter().find(|(seq, _)| *seq == b.seq).map(|(_, at)| at.duration_since(b.at).as_secs_f64() * 1000.0))
        .collect();
    Ok(json!({
        "bench": "teleop",
        "task": args.task,
        "episode_id": id,
        "seconds": args.seconds,
        "batch_actions": args.batch,
        "batches_sent": sent.len(),
        "actions_acked": acked_actions,
        "achieved_actions_per_s": acked_actions as f64 / args.seconds,
        "frames_received": frames.len(),
        "frames_per_s": frames.len() as f64 / args.seconds,
        "key_to_frame_ms": summary(key_to_frame_ms(&sent, &frames)),
        "ack_ms": summary(ack_ms),
        "build": if cfg!(debug_assertions) { "debug" } else { "release" },
    }))
}

/// For each batch, the time from its send to the first frame at or after it whose control step reaches the
/// batch's last action. Batches never covered (the run ended first) are left out.
fn key_to_frame_ms(sent: &[BatchSent], frames: &[FrameSeen]) -> Vec<f64> {
    sent.iter()
        .filter_map(|b| {
            frames
                .iter()
                .find(|f| f.at >= b.at && f.control_step.is_some_and(|c| c >= b.last_step))
                .map(|f| f.at.duration_since(b.at).as_secs_f64() * 1000.0)
        })
        .collect()
}

/// Opens `path` on the server as the browser would, with the operator's credential.
pub(crate) async fn open_socket(base_url: &str, path: &str) -> anyhow::Result<Socket> {
    let ws_base = base_url.replacen("http://", "ws://", 1);
    let mut request = format!("{}{path}", ws_base.trim_end_matches('/')).into_client_request()?;
    for (name, value) in operator_headers(base_url)? {
        request.headers_mut().insert(tokio_tungstenite::tungstenite::http::HeaderName::from_bytes(name.as_bytes())?, value.parse()?);
    }
    let (socket, _) = tokio_tungstenite::connect_async(request).await.with_context(|| format!("WebSocket {path}"))?;
    Ok(socket)
}

/// `POST /api/teleop`'s answer, as far as the bench reads it.
#[derive(Deserialize)]
struct TeleopCreated {
    episode_id: Option<String>,
}

/// The JSON header of a live frame (the dashboard's live socket): its control step, null for a settle step.
#[derive(Deserialize)]
struct FrameHeader {
    #[serde(default)]
    control_step: Option<u64>,
}

/// The teleop socket's `ack` of an action batch, as far as the bench reads it.
#[derive(Deserialize, Default)]
struct Ack {
    seq: Option<u64>,
    ok: Option<bool>,
    /// Actions the batch held.
    actions: Option<u64>,
}

/// The control step of a binary frame message (4-byte LE header length, JSON header, JPEG).
pub(crate) fn frame_step(bytes: &[u8]) -> Option<Option<u64>> {
    let len = u32::from_le_bytes(bytes.get(..4)?.try_into().ok()?) as usize;
    let header: FrameHeader = serde_json::from_slice(bytes.get(4..4 + len)?).ok()?;
    Some(header.control_step)
}

/// The action of tick `tick`: back and forth along x once a second, gripper open.
fn action(tick: u64) -> [f64; 7] {
    let sign = if (tick / 20) % 2 == 0 { 1.0 } else { -1.0 };
    [0.3 * sign, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0]
}

async fn drive_sockets(base_url: &str, id: &str, args: &BenchTeleopArgs) -> anyhow::Result<Drive> {
    let live = open_socket(base_url, &format!("/ws/episodes/{id}")).await?;
    let control = open_socket(base_url, &format!("/ws/teleop/{id}")).await?;
    let frames: Arc<Mutex<Vec<FrameSeen>>> = Arc::default();
    let reader = tokio::spawn(read_frames(live, frames.clone()));
    let (mut control_tx, mut control_rx) = control.split();
    let in_flight = Arc::new(AtomicUsize::new(0));
    let acked = Arc::new(AtomicUsize::new(0));
    let answers: Arc<Mutex<Vec<(u64, Instant)>>> = Arc::default();
    let acks = {
        let (in_flight, acked, answers) = (in_flight.clone(), acked.clone(), answers.clone());
        tokio::spawn(async move {
            while let Some(Ok(Message::Text(text))) = control_rx.next().await {
                let at = Instant::now();
                let ack: Ack = serde_json::from_str(&text).unwrap_or_default();
                if let (Some(seq), Ok(mut a)) = (ack.seq, answers.lock()) {
                    a.push((seq, at));
                }
                if ack.ok == Some(true) {
                    acked.fetch_add(ack.actions.unwrap_or(0) as usize, Ordering::AcqRel);
                } else {
                    log::warn!("teleop batch refused: {text}");
                }
                in_flight.fetch_sub(1, Ordering::AcqRel);
            }
        })
    };
    let period = CONTROL_PERIOD * args.batch as u32;
    let end = Instant::now() + Duration::from_secs_f64(args.seconds);
    let mut sent = Vec::new();
    let (mut tick, mut seq) = (0u64, 0u64);
    let mut ticker = tokio::time::interval(period);
    ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    while Instant::now() < end {
        ticker.tick().await;
        if in_flight.load(Ordering::Acquire) >= MAX_IN_FLIGHT {
            continue; // as the page: time stretches while the simulation is behind, never a backlog
        }
        let actions: Vec<[f64; 7]> = (0..args.batch).map(|k| action(tick + k as u64)).collect();
        tick += args.batch as u64;
        seq += 1;
        in_flight.fetch_add(1, Ordering::AcqRel);
        let at = Instant::now();
        control_tx.send(Message::Text(json!({"seq": seq, "actions": actions}).to_string().into())).await?;
        sent.push(BatchSent { seq, at, last_step: tick });
    }
    let drained = Instant::now();
    while drained.elapsed() < DRAIN_LIMIT {
        let covered = frames.lock().map(|f| f.iter().any(|x| x.control_step.is_some_and(|c| c >= tick))).unwrap_or(true);
        if covered {
            break;
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
    reader.abort();
    acks.abort();
    let frames = frames.lock().map(|f| f.clone()).unwrap_or_default();
    let acks = answers.lock().map(|a| a.clone()).unwrap_or_default();
    Ok(Drive { sent, frames, acks, acked_actions: acked.load(Ordering::Acquire) })
}

/// Records every frame's arrival on the live socket.
async fn read_frames(mut live: Socket, frames: Arc<Mutex<Vec<FrameSeen>>>) {
    while let Some(Ok(message)) = live.next().await {
        if let Message::Binary(bytes) = message {
            let at = Instant::now();
            if let (Some(control_step), Ok(mut f)) = (frame_step(&bytes), frames.lock()) {
                f.push(FrameSeen { at, control_step });
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_batch_is_covered_by_the_first_later_frame_that_reaches_its_last_step() {
        let t0 = Instant::now();
        let ms = |n| t0 + Duration::from_millis(n);
        let batch = |seq: u64, at| BatchSent { seq, at, last_step: 4 * seq };
        let sent = [batch(1, ms(0)), batch(2, ms(200)), batch(3, ms(400))];
        let frames = [
            FrameSeen { at: ms(100), control_step: Some(3) },
            FrameSeen { at: ms(250), control_step: Some(8) },
            FrameSeen { at: ms(300), control_step: None },
        ];
        assert_eq!(key_to_frame_ms(&sent, &frames), [250.0, 50.0], "the last batch was never shown");
        let mut header = br#"{"control_step":7}"#.to_vec();
        let mut message = (header.len() as u32).to_le_bytes().to_vec();
        message.append(&mut header);
        assert_eq!(frame_step(&message), Some(Some(7)));
        assert_eq!(frame_step(&[1, 0]), None);
    }
}
