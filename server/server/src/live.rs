//! The dashboard's fan-out of each episode's live events (see `libero_episode::live`). The episode's sink
//! serialises an event once, appends it to the catch-up history and broadcasts it; frames go through a
//! `watch` channel that holds only the newest one. Neither call waits for a viewer: a slow viewer misses
//! frames (it always gets the newest) and, if it falls behind the event channel, is re-sent the history.
//! Each subscription counts as a viewer of the episode's [`LiveViewers`] while it lives: frames are rendered
//! only while someone watches.
use std::collections::HashMap;
use std::sync::{Arc, Mutex, RwLock};

use axum::body::Bytes;
use libero_episode::lifecycle::LiveViews;
use libero_episode::live::{LiveViewers, ViewerGuard};
use libero_episode::{LiveEvent, LiveFrame, LiveSink};
use serde_json::json;
use tokio::sync::{broadcast, watch};

/// Events buffered per viewer before it counts as lagging (then it gets the history again).
const EVENT_CHANNEL_CAPACITY: usize = 1024;
/// Most events kept for a viewer that connects late (step events are not kept, only the latest one).
const HISTORY_LIMIT: usize = 20_000;

/// One event as sent to browsers: JSON text, serialised once.
pub type EventText = Arc<str>;

/// What a viewer that connects now needs to catch up.
#[derive(Default)]
pub struct CatchUp {
    pub history: Vec<EventText>,
    pub latest_step: Option<EventText>,
    pub progress: Option<(usize, usize)>,
    pub accepted_agent_steps: u64,
    pub wall_time_s: Option<f64>,
    pub finished: bool,
}

/// A live episode's figures for the episode table, before its store row has them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LiveSummary {
    /// Required stages completed and required, once the evaluator reported them.
    pub completed_stage_count: Option<u64>,
    pub required_stage_count: Option<u64>,
    /// Agent steps accepted so far.
    pub accepted_agent_steps: u64,
    /// Seconds since `start_episode`, as of the last answered call.
    pub wall_time_s: Option<f64>,
    /// The episode has ended.
    pub finished: bool,
}

/// One episode's live channels.
pub struct Hub {
    pub max_agent_steps: u64,
    pub max_wall_time_s: f64,
    events: broadcast::Sender<EventText>,
    frames: watch::Sender<Option<Bytes>>,
    state: Mutex<CatchUp>,
    viewers: LiveViewers,
    /// Set when the server lets go of the hub (the episode ended): viewers still streaming it then close.
    closed: watch::Sender<bool>,
    /// A branch's parent episode and control step, told to every viewer in the socket's `hello`.
    branch: std::sync::OnceLock<(String, u64)>,
}

/// A viewer's subscription, taken together with the history so nothing is missed or sent twice.
pub struct Subscription {
    pub history: Vec<EventText>,
    pub latest_step: Option<EventText>,
    pub events: broadcast::Receiver<EventText>,
    pub frames: watch::Receiver<Option<Bytes>>,
    /// Keeps this subscriber counted as a viewer (the episode renders frames for it) until dropped; held for
    /// its drop, never read.
    #[allow(dead_code)]
    pub viewer: ViewerGuard,
    /// Changes to true when the hub is closed.
    pub closed: watch::Receiver<bool>,
}

impl Hub {
    fn publish(&self, event: LiveEvent, changes: &broadcast::Sender<()>) {
        match event {
            LiveEvent::Frame(frame) => {
                // Encoded once; every viewer's socket sends the same bytes.
                self.frames.send_replace(Some(frame_message(&frame)));
            }
            event => {
                let Ok(text) = serde_json::to_string(&event) else { return };
                let text: EventText = text.into();
                let list_changed = matches!(
                    event,
                    LiveEvent::CallAnswered { .. } | LiveEvent::Progress { .. } | LiveEvent::Finished { .. }
                );
                let Ok(mut state) = self.state.lock() else { return };
                match &event {
                    LiveEvent::Step { .. } => state.latest_step = Some(text.clone()),
                    _ if state.history.len() < HISTORY_LIMIT => state.history.push(text.clone()),
                    _ => {}
                }
                match &event {
                    LiveEvent::Progress { completed, required } => state.progress = Some((*completed, *required)),
                    LiveEvent::CallAnswered { accepted_agent_steps, wall_time_s, .. } => {
                        state.accepted_agent_steps = *accepted_agent_steps;
                        state.wall_time_s = *wall_time_s;
                    }
                    LiveEvent::Finished { .. } => state.finished = true,
                    _ => {}
                }
                // Sent under the lock, so a subscriber's history and its channel neither overlap nor leave a gap.
                let _ = self.events.send(text);
                drop(state);
                if list_changed {
                    let _ = changes.send(());
                }
            }
        }
    }

    pub fn subscribe(&self) -> Option<Subscription> {
        let state = self.state.lock().ok()?;
        Some(Subscription {
            history: state.history.clone(),
            latest_step: state.latest_step.clone(),
            events: self.events.subscribe(),
            frames: self.frames.subscribe(),
            viewer: self.viewers.watch(),
            closed: self.closed.subscribe(),
        })
    }

    /// The history again (for a viewer that lagged), with a fresh receiver.
    pub fn resubscribe(&self) -> Option<(Vec<EventText>, broadcast::Receiver<EventText>)> {
        let state = self.state.lock().ok()?;
        Some((state.history.clone(), self.events.subscribe()))
    }

    /// The parent episode and control step of a branch (None for an ordinary episode).
    pub fn branch(&self) -> Option<&(String, u64)> {
        self.branch.get()
    }

    /// Agent steps accepted so far and (completed, required) stages once the evaluator reported them.
    pub fn progress(&self) -> Option<(u64, Option<(usize, usize)>)> {
        let s = self.state.lock().ok()?;
        Some((s.accepted_agent_steps, s.progress))
    }

    /// Live figures for the episode table: progress, submissions, wall time, ended (None if the hub's lock is
    /// poisoned).
    pub fn summary(&self) -> Option<LiveSummary> {
        let s = self.state.lock().ok()?;
        Some(LiveSummary {
            completed_stage_count: s.progress.map(|p| p.0 as u64),
            required_stage_count: s.progress.map(|p| p.1 as u64),
            accepted_agent_steps: s.accepted_agent_steps,
            wall_time_s: s.wall_time_s,
            finished: s.finished,
        })
    }
}

/// A frame as one binary WebSocket message: 4-byte little-endian header length, JSON header, JPEG bytes.
fn frame_message(frame: &LiveFrame) -> Bytes {
    let header = json!({
        "type": "frame",
        "control_step": frame.control_step,
        "sim_time_s": frame.sim_time_s,
        "video_frame": frame.video_frame,
        "width_px": frame.width_px,
        "height_px": frame.height_px,
    })
    .to_string();
    let mut out = Vec::with_capacity(4 + header.len() + frame.jpeg.len());
    out.extend_from_slice(&(header.len() as u32).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    out.extend_from_slice(&frame.jpeg);
    Bytes::from(out)
}

/// Every live episode's hub, plus a "the episode list changed" signal for the home page.
pub struct LiveHubs {
    map: RwLock<HashMap<String, Arc<Hub>>>,
    changes: broadcast::Sender<()>,
}

impl Default for LiveHubs {
    fn default() -> Self {
        Self { map: RwLock::new(HashMap::new()), changes: broadcast::channel(64).0 }
    }
}

impl LiveHubs {
    /// Creates `id`'s hub and returns the sink the episode reports to and its viewer count, for the world's
    /// live renderer.
    pub fn open(&self, id: &str, max_agent_steps: u64, max_wall_time_s: f64) -> (LiveSink, LiveViewers) {
        let viewers = LiveViewers::new();
        let hub = Arc::new(Hub {
            max_agent_steps,
            max_wall_time_s,
            events: broadcast::channel(EVENT_CHANNEL_CAPACITY).0,
            frames: watch::channel(None).0,
            state: Mutex::new(CatchUp::default()),
            viewers: viewers.clone(),
            closed: watch::channel(false).0,
            branch: std::sync::OnceLock::new(),
        });
        if let Ok(mut map) = self.map.write() {
            map.insert(id.to_owned(), hub.clone());
        }
        self.notify();
        let changes = self.changes.clone();
        (Arc::new(move |event| hub.publish(event, &changes)), viewers)
    }

    /// Marks `id` as a branch of `parent` at control step `step` (before its first viewer can connect).
    pub fn mark_branch(&self, id: &str, parent: &str, step: u64) {
        if let Some(hub) = self.get(id) {
            let _ = hub.branch.set((parent.to_owned(), step));
        }
    }

    pub fn get(&self, id: &str) -> Option<Arc<Hub>> {
        self.map.read().ok()?.get(id).cloned()
    }

    /// Drops `id`'s hub (history, newest frame) once its episode has ended; viewers still on it are told to close.
    /// Pages of the episode then read its records from the run directory and the store.
    pub fn close(&self, id: &str) {
        let hub = self.map.write().ok().and_then(|mut m| m.remove(id));
        if let Some(hub) = hub {
            hub.closed.send_replace(true);
        }
    }

    /// Tells home pages to refresh their list.
    pub fn notify(&self) {
        let _ = self.changes.send(());
    }

    pub fn changes(&self) -> broadcast::Receiver<()> {
        self.changes.subscribe()
    }
}

/// The lifecycle opens, marks and closes each episode's hub through this.
impl LiveViews for LiveHubs {
    fn open(&self, id: &str, max_agent_steps: u64, max_wall_time_s: f64) -> (LiveSink, LiveViewers) {
        LiveHubs::open(self, id, max_agent_steps, max_wall_time_s)
    }

    fn mark_branch(&self, id: &str, parent: &str, step: u64) {
        LiveHubs::mark_branch(self, id, parent, step);
    }

    fn close(&self, id: &str) {
        LiveHubs::close(self, id);
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Arc as StdArc;

    use serde_json::Value;

    use super::*;

    #[test]
    fn late_viewers_get_history_and_the_newest_frame_and_slow_ones_never_block_the_sender() {
        let hubs = StdArc::new(LiveHubs::default());
        let (sink, viewers) = hubs.open("ep", 10, 60.0);
        sink(LiveEvent::CallReceived { tool: "start_episode".into(), actions: None, at_unix_s: 0.0 });
        for c in 0..5000u64 {
            sink(LiveEvent::Step { control_step: c, sim_time_s: c as f64 * 0.05 });
        }
        let frame = |c| LiveFrame { control_step: Some(c), sim_time_s: 0.0, video_frame: Some(c), width_px: 2, height_px: 1, jpeg: vec![1, 2, 3].into() };
        sink(LiveEvent::Frame(frame(1)));
        sink(LiveEvent::Frame(frame(2)));
        let hub = hubs.get("ep").unwrap();
        let sub = hub.subscribe().unwrap();
        assert_eq!(viewers.count(), 1, "a subscriber is a viewer");
        assert_eq!(sub.history.len(), 1, "step events are not history");
        assert!(sub.latest_step.as_deref().unwrap().contains("\"control_step\":4999"));
        let newest = sub.frames.borrow().clone().unwrap();
        let header_len = u32::from_le_bytes(newest[..4].try_into().unwrap()) as usize;
        let header: Value = serde_json::from_slice(&newest[4..4 + header_len]).unwrap();
        assert_eq!((header["control_step"].as_u64(), &newest[4 + header_len..]), (Some(2), &[1u8, 2, 3][..]));
        // A viewer that never reads: the sender goes on; the viewer lags and is told so.
        let mut events = sub.events;
        for c in 0..(EVENT_CHANNEL_CAPACITY as u64 + 10) {
            sink(LiveEvent::Step { control_step: c, sim_time_s: 0.0 });
        }
        assert!(matches!(events.try_recv(), Err(broadcast::error::TryRecvError::Lagged(_))));
        drop(sub.viewer);
        assert_eq!(viewers.count(), 0, "a dropped subscription is no longer a viewer");
    }
}
