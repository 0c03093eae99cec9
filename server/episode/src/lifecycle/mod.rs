//! The episodes of one server process, from preparation to release: ids and tokens, the private run directory,
//! the workspace and the actor thread (`prepare`), stopping, forfeiting and the shutdown (`stop_all`), the records'
//! life across restarts (`recover_interrupted`), releasing ended episodes, the private videos (`videos`) and the
//! demonstration library (`demos`). No HTTP and no store here: the server serves each episode over MCP and keeps
//! the store from the [`EpisodeEvent`]s it is sent; in-process tools (the CLI's expert) use this alone.
mod demos;
mod log;
mod moments;
mod prepare;
mod request;
mod videos;

use std::collections::HashMap;
use std::fs;
use std::io::Read;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, RwLock};
use std::time::{Duration, Instant};

use anyhow::Context;
use libero_render::Renderer;
use libero_sim::AssetPaths;

pub use moments::{MAX_CACHED_MOMENTS, Moment, MomentError, SCENE_IDLE};
pub use request::{BranchError, BranchRequest, MAX_WALL_TIME_S, PrepareRequest, Prepared, valid_episode_id};

use self::log::EpisodeLog;
use crate::live::{LiveEvent, LiveSink, LiveViewers};
use libero_records::records::{aborted_result, read_episode_record, read_result, write_result};
use crate::tools::DEFAULT_WALL_TIME_S;
use crate::video_queue::VideoQueue;
use crate::{EpisodeHandle, EpisodeStatus, RunDir};

/// How long an ended episode is kept whole (its MCP sessions, its live view) after its thread exited: long enough
/// for its last reply to reach the client.
pub const RELEASE_GRACE: Duration = Duration::from_secs(2);

/// Where episodes' live views go (the server's fan-out to the console). A trait, so this crate needs no channel
/// or HTTP type to feed them.
pub trait LiveViews: Send + Sync {
    /// Opens `id`'s view; the sink the episode reports to and its viewer count (frames render only while watched).
    fn open(&self, id: &str, max_agent_steps: u64, max_wall_time_s: f64) -> (LiveSink, LiveViewers);
    /// Marks `id` as a branch of `parent` at control step `step`, before its first viewer connects.
    fn mark_branch(&self, id: &str, parent: &str, step: u64);
    /// Drops `id`'s view: the episode ended, or will never be served.
    fn close(&self, id: &str);
}

/// What the lifecycle tells its owner about an episode, so that the store is written when something happened
/// rather than polled. Sent from the episode's thread: the receiver must not block.
#[derive(Debug, Clone, PartialEq)]
pub enum EpisodeEvent {
    /// A tool call was answered: the accepted agent steps and the stage progress (completed, required K) after it,
    /// so the receiver needs no other view of the episode to record them.
    Called { id: String, accepted_agent_steps: u64, stages: Option<(usize, usize)> },
    /// The episode ended (finished, expired, aborted or forfeited): its result as written (`None` if its
    /// `result.json` could not be read back).
    Ended { id: String, result: Option<Box<libero_records::records::RunResult>> },
}

/// Receives [`EpisodeEvent`]s; returns at once.
pub type EventSink = Arc<dyn Fn(EpisodeEvent) + Send + Sync>;

/// An episode this process prepared. Once it has ended and was released, only a tombstone is left: the handle,
/// whose thread and world are gone (about a kilobyte), and its log.
struct Entry {
    handle: EpisodeHandle,
    released: bool,
    /// What the episode's log lines name, and how far they have followed it (kept by the tombstone).
    log: Arc<EpisodeLog>,
}

/// The episodes of this process (see the module's doc).
pub struct EpisodeSet {
    data: PathBuf,
    base_url: String,
    paths: Option<AssetPaths>,
    map: RwLock<HashMap<String, Arc<Entry>>>,
    /// One GPU device shared by every episode (opened at the first prepare).
    renderer: Mutex<Option<Renderer>>,
    /// Each episode's live view for the dashboard.
    live: Option<Arc<dyn LiveViews>>,
    /// Where episode events go (the server's store writer).
    events: Option<EventSink>,
    /// Serialises recording missing demonstrations, so concurrent rollouts of one task record one bundle.
    demo_recording: Mutex<()>,
    /// When each ended episode was first seen with its thread gone, until it is released (see [`RELEASE_GRACE`]).
    ending: Mutex<HashMap<String, Instant>>,
    /// The background worker that renders private videos from state records (started with the renderer).
    videos: Mutex<Option<VideoQueue>>,
    /// The review's moments rendered from recorded state (`moments`).
    moments: Arc<moments::MomentCache>,
}

/// `bytes` random bytes from the OS as lowercase hex (episode ids, tokens, login codes).
pub fn random_hex(bytes: usize) -> std::io::Result<String> {
    let mut buf = vec![0u8; bytes];
    fs::File::open("/dev/urandom")?.read_exact(&mut buf)?;
    Ok(buf.iter().map(|b| format!("{b:02x}")).collect())
}

/// Absolute, lexically normalised path (the workspace may not exist yet).
fn absolute(p: &Path) -> std::io::Result<PathBuf> {
    let p = if p.is_absolute() { p.to_path_buf() } else { std::env::current_dir()?.join(p) };
    let mut out = PathBuf::new();
    for c in p.components() {
        match c {
            std::path::Component::ParentDir => {
                out.pop();
            }
            std::path::Component::CurDir => {}
            other => out.push(other),
        }
    }
    Ok(out)
}

impl EpisodeSet {
    /// Episodes under `data` (`runs/`, `workspaces/`, `demos/`), reached by agents at `<base_url>/mcp/<id>`.
    pub fn new(data: PathBuf, base_url: String) -> anyhow::Result<Self> {
        crate::memory::tune_for_long_runs();
        let data = absolute(&data)?;
        fs::create_dir_all(data.join("runs"))?;
        fs::create_dir_all(data.join("workspaces"))?;
        let paths = match AssetPaths::discover() {
            Ok(p) => Some(p),
            Err(e) => {
                tracing::warn!("{e}; episodes cannot be prepared until the assets are set up");
                None
            }
        };
        Ok(Self {
            data,
            base_url,
            paths,
            map: RwLock::new(HashMap::new()),
            renderer: Mutex::new(None),
            live: None,
            events: None,
            demo_recording: Mutex::new(()),
            ending: Mutex::new(HashMap::new()),
            videos: Mutex::new(None),
            moments: Arc::default(),
        })
    }

    /// Feeds every later episode's live events to `views`.
    pub fn with_live(mut self, views: Arc<dyn LiveViews>) -> Self {
        self.live = Some(views);
        self
    }

    /// Sends every later episode's [`EpisodeEvent`]s to `events`.
    pub fn with_events(mut self, events: EventSink) -> Self {
        self.events = Some(events);
        self
    }

    /// The sink the episode's actor and its world report to: the live view's, if any, followed by the events its
    /// owner hears of ([`EpisodeEvent`], which carry the figures, so the owner reads no view).
    fn actor_sink(&self, id: &str, view: Option<LiveSink>) -> Option<LiveSink> {
        let Some(events) = self.events.clone() else { return view };
        let id = id.to_owned();
        let run = RunDir::new(self.runs_dir().join(&id));
        // the newest stage progress, told with the next answered call
        let stages: Mutex<Option<(usize, usize)>> = Mutex::new(None);
        Some(Arc::new(move |event: LiveEvent| {
            let told = match &event {
                LiveEvent::Progress { completed, required } => {
                    if let Ok(mut s) = stages.lock() {
                        *s = Some((*completed, *required));
                    }
                    None
                }
                LiveEvent::CallAnswered { accepted_agent_steps, .. } => Some(EpisodeEvent::Called {
                    id: id.clone(),
                    accepted_agent_steps: *accepted_agent_steps,
                    stages: stages.lock().ok().and_then(|s| *s),
                }),
                // the actor reports the end after writing result.json
                LiveEvent::Finished { .. } => Some(EpisodeEvent::Ended { id: id.clone(), result: read_result(&run).map(Box::new) }),
                _ => None,
            };
            if let Some(view) = &view {
                view(event);
            }
            if let Some(told) = told {
                events(told);
            }
        }))
    }

    pub fn data_dir(&self) -> &Path {
        &self.data
    }

    /// Ids of the episodes this process holds.
    pub fn ids(&self) -> Vec<String> {
        self.map.read().map(|m| m.keys().cloned().collect()).unwrap_or_default()
    }

    /// The asset set, when it is installed (thumbnails resolve tasks with it).
    pub fn asset_paths(&self) -> Option<&AssetPaths> {
        self.paths.as_ref()
    }

    /// The GPU device every episode (and the thumbnails) render with, opened at first use.
    pub fn renderer(&self) -> anyhow::Result<Renderer> {
        let mut slot = self.renderer.lock().map_err(|_| anyhow::anyhow!("renderer lock poisoned"))?;
        if let Some(r) = slot.as_ref() {
            return Ok(r.clone());
        }
        let r = Renderer::new().context("cannot open a GPU for rendering")?;
        *slot = Some(r.clone());
        Ok(r)
    }

    /// Whether the shared GPU device has been opened (by an episode, a video, a review moment or teleop).
    pub fn renderer_is_open(&self) -> bool {
        self.renderer.lock().map(|slot| slot.is_some()).unwrap_or(true)
    }

    pub fn runs_dir(&self) -> PathBuf {
        self.data.join("runs")
    }

    /// Episodes this process holds that have not ended.
    pub fn count(&self) -> usize {
        self.map.read().map(|m| m.values().filter(|e| e.handle.ended().is_none()).count()).unwrap_or(0)
    }

    /// Releases what episodes that ended at least [`RELEASE_GRACE`] ago, and whose threads have exited, still hold
    /// here (their live views, the models only they read). Returns the ids released, for the owner to let go of its
    /// own part (the MCP sessions) and, when any were, to hand the freed memory back to the OS
    /// ([`crate::memory::return_freed_memory`], which blocks). Cheap and non-blocking when nothing is due, so it can
    /// be called periodically from async code without keeping a blocking thread busy.
    pub fn release_ended(&self) -> Vec<String> {
        let due = self.retire_due(Instant::now());
        for id in &due {
            self.close_live(id);
        }
        if !due.is_empty() {
            // Models other episodes' models read their large arrays from, now that no such episode is left.
            libero_sim::shared_model::release_unused();
        }
        due
    }

    /// Drops `id`'s live view (an episode that ended, or will never be served).
    fn close_live(&self, id: &str) {
        if let Some(live) = &self.live {
            live.close(id);
        }
    }

    /// Turns the entries of episodes ended for [`RELEASE_GRACE`] into tombstones; returns their ids.
    fn retire_due(&self, now: Instant) -> Vec<String> {
        let (Ok(mut map), Ok(mut ending)) = (self.map.write(), self.ending.lock()) else { return Vec::new() };
        let mut due = Vec::new();
        for (id, entry) in map.iter_mut() {
            if entry.released || entry.handle.ended().is_none() || !entry.handle.is_released() {
                continue;
            }
            let since = *ending.entry(id.clone()).or_insert(now);
            if now.duration_since(since) >= RELEASE_GRACE {
                due.push(id.clone());
                entry.log.follow(id, &entry.handle.status());
                *entry = Arc::new(Entry { handle: entry.handle.clone(), released: true, log: entry.log.clone() });
                ending.remove(id);
            }
        }
        due
    }

    /// The in-process handle of an episode (for the CLI's own agents and the operator's teleop, never for an
    /// agent's requests).
    pub fn handle(&self, id: &str) -> Option<EpisodeHandle> {
        let map = self.map.read().ok()?;
        map.get(id).map(|e| e.handle.clone())
    }

    pub fn status(&self, id: &str) -> Option<EpisodeStatus> {
        let map = self.map.read().ok()?;
        let entry = map.get(id)?;
        let status = entry.handle.status();
        entry.log.follow(id, &status);
        Some(status)
    }

    /// Ends one episode (aborted with `reason` unless it already ended); false if this process does not hold it.
    pub fn stop(&self, id: &str, reason: &str) -> bool {
        self.end_with(id, |h| h.stop(reason))
    }

    /// Ends one unfinished episode as its agent's FAIL (the agent ended without `finish_episode`); false if this
    /// process does not hold it.
    pub fn forfeit(&self, id: &str, reason: &str) -> bool {
        self.end_with(id, |h| h.forfeit(reason))
    }

    /// Runs `end` on `id`'s handle and records the state it leaves; false if this process does not hold it.
    fn end_with(&self, id: &str, end: impl FnOnce(&EpisodeHandle)) -> bool {
        let Some(e) = self.map.read().ok().and_then(|m| m.get(id).cloned()) else { return false };
        end(&e.handle);
        e.log.follow(id, &e.handle.status());
        true
    }

    /// Records every unfinished episode as aborted with `reason` (server shutdown), waiting at most `timeout`
    /// in all: an episode thread stuck in the simulation is left behind (the process is ending) rather than
    /// holding the shutdown. Returns how many did not answer in time.
    pub fn stop_all(&self, reason: &str, timeout: Duration) -> usize {
        let entries: Vec<(String, Arc<Entry>)> =
            self.map.read().map(|m| m.iter().map(|(id, e)| (id.clone(), e.clone())).collect()).unwrap_or_default();
        let deadline = Instant::now() + timeout;
        let pending: Vec<_> = entries.iter().map(|(_, e)| e.handle.request_stop(reason)).collect();
        let stuck = pending.into_iter().filter(|p| !p.wait_until(deadline)).count();
        for (id, e) in &entries {
            e.log.follow(id, &e.handle.status());
        }
        stuck
    }

    /// After a crash or kill: every run directory with an episode record but no result becomes an aborted
    /// (INVALID) episode with its reason. Finished records are left untouched. Returns how many.
    pub fn recover_interrupted(&self) -> usize {
        let Ok(dirs) = fs::read_dir(self.runs_dir()) else { return 0 };
        let mut n = 0;
        for d in dirs.flatten() {
            let run = RunDir::new(d.path());
            if !run.episode_record().is_file() || read_result(&run).is_some() {
                continue;
            }
            let max_wall = read_episode_record(&run)
                .ok()
                .flatten()
                .and_then(|r| r.max_wall_time_seconds)
                .unwrap_or(DEFAULT_WALL_TIME_S);
            let result = aborted_result("server_stopped_before_finish: the server exited while the episode was open", max_wall, None);
            if write_result(&run, &result).is_ok() {
                n += 1;
            }
        }
        n
    }
}

impl Drop for EpisodeSet {
    /// The end lines of episodes nothing asked about since they ended (the in-process expert stops its episodes
    /// through their handles).
    fn drop(&mut self) {
        if let Ok(map) = self.map.read() {
            for (id, e) in map.iter() {
                e.log.follow(id, &e.handle.status());
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The owner hears of answered calls and the end, and nothing else, each carrying what happened: the accepted
    /// steps and the newest stage progress with a call, the written result with the end; so it needs no view of
    /// the episode (a live hub, the run directory) to record them. The view still hears everything, first.
    /// Without an event sink the view's sink is used as it is.
    #[test]
    fn the_owner_hears_calls_with_their_progress_and_the_end_with_its_result() {
        let dir = tempfile::tempdir().unwrap();
        let heard: Arc<Mutex<Vec<String>>> = Arc::default();
        let told: Arc<Mutex<Vec<EpisodeEvent>>> = Arc::default();
        let (h1, h2, t1) = (heard.clone(), heard.clone(), told.clone());
        let events: EventSink = Arc::new(move |e| {
            h1.lock().unwrap().push("owner".into());
            t1.lock().unwrap().push(e);
        });
        let view: LiveSink = Arc::new(move |_| h2.lock().unwrap().push("view".into()));
        let set = EpisodeSet::new(dir.path().join("data"), "http://127.0.0.1:0".into()).unwrap();
        assert!(set.actor_sink("ep", None).is_none(), "no view, no events: no sink");
        let set = set.with_events(events);
        let sink = set.actor_sink("ep", Some(view)).unwrap();
        let answered = |steps: u64| LiveEvent::CallAnswered {
            tool: "osc_sequence".into(),
            actions: Some(1),
            ok: true,
            error_type: None,
            error: None,
            observation_id: None,
            accepted_agent_steps: steps,
            max_agent_steps: 10,
            wall_time_s: None,
            max_wall_time_s: 60.0,
            at_unix_s: 0.0,
        };
        sink(answered(0));
        sink(LiveEvent::Step { control_step: 1, sim_time_s: 0.05 });
        sink(LiveEvent::Progress { completed: 1, required: 3 });
        sink(answered(1));
        let run = RunDir::new(set.runs_dir().join("ep"));
        fs::create_dir_all(&run.root).unwrap();
        let result = aborted_result("operator", 60.0, Some(1.5));
        write_result(&run, &result).unwrap();
        sink(LiveEvent::Finished { state: "aborted".into(), outcome: Some("INVALID".into()), reason: Some("operator".into()) });
        assert_eq!(*heard.lock().unwrap(), ["view", "owner", "view", "view", "view", "owner", "view", "owner"]);
        let told = told.lock().unwrap().clone();
        assert_eq!(
            told,
            [
                EpisodeEvent::Called { id: "ep".into(), accepted_agent_steps: 0, stages: None },
                EpisodeEvent::Called { id: "ep".into(), accepted_agent_steps: 1, stages: Some((1, 3)) },
                EpisodeEvent::Ended { id: "ep".into(), result: Some(Box::new(read_result(&run).unwrap())) },
            ]
        );
        assert_eq!(told[2], EpisodeEvent::Ended { id: "ep".into(), result: Some(Box::new(result)) }, "the result as written");
    }
}
