//! The episode actor: one thread owns one episode's world (simulation + renderer + evaluator), receives
//! tool calls over a channel, enforces the protocol's order of checks and budgets (§2.11, §4.4), publishes
//! observations and writes the private records. A fault or panic ends this episode only (INVALID, reason
//! recorded); other episodes' threads are untouched. What the agent does to its own workspace is never a
//! fault: an observation its workspace cannot take is an error of that tool call, and the episode goes on.
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::PathBuf;
use std::sync::mpsc::{self, RecvTimeoutError};
use std::sync::{Arc, Condvar, Mutex, OnceLock};
use std::time::{Duration, Instant};

use serde::Deserialize;
use serde_json::{Map, Value, json};

use crate::EpisodeError;
use crate::call::{MicroAction, ToolCall, ToolError, validate_actions};
use libero_records::json::{compact_sorted, utc_now_iso};
use crate::live::{LiveEvent, LiveSink, unix_now_s};
use crate::observation::{EncodedObservation, Frame, Level, encode_observation};
use crate::publish::{ObservationPublisher, write_private_copy};
use libero_records::records::{
    ActionLog, Outcome, RESULT_SCHEMA, RunDir, RunResult, ToolReply, aborted_result, classify, write_result,
};
use crate::tools::{MAX_AGENT_STEPS_CAP, ToolName};
use crate::workspace::OBSERVATION_FILE;

/// The part of an answer the live view shows beyond [`ToolReply`]: the observation a call published.
#[derive(Deserialize, Default)]
struct Answered {
    #[serde(default)]
    observation_id: Option<String>,
}

/// How often an idle active episode checks its wall clock (the original polled every 0.5 s).
pub const IDLE_POLL: Duration = Duration::from_millis(500);
const BUDGET_SCOPE: &str = libero_records::records::WALL_TIME_BUDGET_SCOPE;
const EXPIRY_REASON: &str = libero_records::records::WALL_TIME_EXHAUSTED;
/// `termination_reason` of an episode whose agent ended without `finish_episode` (docs/protocol.md §4.8).
pub const FORFEIT_REASON: &str = "agent_ended_without_finish_episode";
const FINISHED_TEXT: &str = "the episode is already finished; finish_episode was called and no further commands are accepted";
const ABORTED_TEXT: &str = "the episode was stopped by the server and accepts no further commands";
const START_TWICE_TEXT: &str = "start may be called exactly once";
/// How the agent's error begins when its workspace could not take an observation.
pub const PUBLICATION_FAILED: &str = "observation publication failed";
const CURRENT_OBSERVATION_DIR: &str = "benchmark_inputs/current_observation/";

/// The official verdict at finish (or the evaluator snapshot at expiry).
#[derive(Debug, Clone, PartialEq)]
pub struct Verdict {
    pub success: bool,
    /// Evaluator output, private (goes to `result.json` only).
    pub private_evaluation: Value,
    /// Ordered-stage events for `private_stage_events.jsonl`, if the evaluator has stages.
    pub stage_events: Vec<Value>,
}

/// What an episode runs on. Implemented by the LIBERO world (real MuJoCo simulation + renderer).
pub trait World {
    /// §4.2: reset, restore the init state, settle, capture the evaluator baseline.
    fn start(&mut self) -> Result<(), EpisodeError>;
    /// One 20 Hz control interval (§4.3).
    fn step(&mut self, action: &MicroAction) -> Result<(), EpisodeError>;
    /// The public frame of the current state (renders both cameras).
    fn frame(&mut self, frame_index: u64) -> Result<Frame, EpisodeError>;
    /// The official checker on the current state.
    fn verdict(&mut self) -> Result<Verdict, EpisodeError>;
}

/// Everything fixed when an episode is prepared.
#[derive(Debug, Clone)]
pub struct EpisodeConfig {
    pub episode_id: String,
    /// Shown to the agent (prompt and start payload).
    pub instruction: String,
    pub level: Level,
    pub max_agent_steps: u64,
    pub max_wall_time_s: f64,
    pub workspace: PathBuf,
    pub run_dir: PathBuf,
}

impl EpisodeConfig {
    /// `min(max_agent_steps, 1,000,000)`.
    pub fn agent_step_limit(&self) -> u64 {
        self.max_agent_steps.min(MAX_AGENT_STEPS_CAP)
    }
}

/// Lifecycle state visible to the server (never to the agent beyond the tool results): one definition with the
/// operator API's episode view, which carries it.
pub use libero_records::episode_view::EpisodeState;

/// A snapshot for the server's API and store.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct EpisodeStatus {
    pub state: EpisodeState,
    pub accepted_agent_steps: u64,
    pub latest_observation_id: Option<String>,
    /// Set once the episode has ended.
    pub outcome: Option<Outcome>,
    /// Why an aborted episode ended.
    pub reason: Option<String>,
}

enum Command {
    Call { name: String, arguments: Option<Map<String, Value>>, reply: mpsc::Sender<Value> },
    Stop { reason: String, done: mpsc::Sender<()> },
    /// The agent's harness ended without `finish_episode`: the agent's own FAIL, never INVALID.
    Forfeit { reason: String, done: mpsc::Sender<()> },
}

/// How an episode ended, kept after its thread and world are gone: enough to answer any later call exactly as
/// the actor would have.
#[derive(Debug, Clone, PartialEq)]
pub enum Ended {
    Finished,
    /// Every later call gets the expiry payload (§2.10).
    Expired { payload: Value },
    Aborted,
}

impl Ended {
    /// The answer to `call` after the end (the same order of checks as the actor's dispatch).
    fn answer(&self, call: &ToolCall) -> Value {
        match self {
            Self::Expired { payload } => payload.clone(),
            _ if matches!(call, ToolCall::Start) => ToolError::runtime_error(START_TWICE_TEXT).payload(),
            Self::Finished => ToolError::runtime_error(FINISHED_TEXT).payload(),
            Self::Aborted => ToolError::runtime_error(ABORTED_TEXT).payload(),
        }
    }
}

/// The server's side of an episode: cheap to clone, usable from any thread.
#[derive(Clone)]
pub struct EpisodeHandle {
    tx: mpsc::Sender<Command>,
    status: Arc<Mutex<EpisodeStatus>>,
    config: Arc<EpisodeConfig>,
    /// Set when the episode ends, before its thread lets go of the command channel; from then on calls are
    /// answered here, without the thread (which exits, releasing the world).
    ended: Arc<OnceLock<Ended>>,
    /// Set by the episode thread as it exits, after everything it owned was dropped.
    exited: Arc<ExitSignal>,
}

/// Sets its signal when dropped.
struct SetOnDrop(Arc<ExitSignal>);

impl Drop for SetOnDrop {
    fn drop(&mut self) {
        self.0.set();
    }
}

/// A flag that can be waited for: the episode thread has exited.
#[derive(Default)]
struct ExitSignal {
    exited: Mutex<bool>,
    changed: Condvar,
}

impl ExitSignal {
    fn set(&self) {
        let mut exited = self.exited.lock().unwrap_or_else(|p| p.into_inner());
        *exited = true;
        self.changed.notify_all();
    }

    fn is_set(&self) -> bool {
        *self.exited.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn wait(&self) {
        let mut exited = self.exited.lock().unwrap_or_else(|p| p.into_inner());
        while !*exited {
            exited = self.changed.wait(exited).unwrap_or_else(|p| p.into_inner());
        }
    }

    /// As [`Self::wait`], giving up at `deadline`; whether the thread exited.
    fn wait_until(&self, deadline: Instant) -> bool {
        let mut exited = self.exited.lock().unwrap_or_else(|p| p.into_inner());
        while !*exited {
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return false;
            }
            exited = self.changed.wait_timeout(exited, left).map(|(g, _)| g).unwrap_or_else(|p| p.into_inner().0);
        }
        true
    }
}

impl EpisodeHandle {
    pub fn config(&self) -> &EpisodeConfig {
        &self.config
    }

    /// Runs one tool call to completion and returns its payload (`ok` true or false). Blocks the calling
    /// thread (from async code, call it inside `spawn_blocking`).
    pub fn call(&self, name: &str, arguments: Option<Map<String, Value>>) -> Value {
        if let Some(answer) = self.answer_after_end(name, arguments.as_ref()) {
            return answer;
        }
        let (reply, rx) = mpsc::channel();
        let cmd = Command::Call { name: name.to_owned(), arguments: arguments.clone(), reply };
        if self.tx.send(cmd).is_err() {
            return self
                .answer_after_end(name, arguments.as_ref())
                .unwrap_or_else(|| ToolError::runtime_error("the episode is no longer being served").payload());
        }
        // A call queued just as the episode ended is dropped with the channel; it gets the after-end answer.
        rx.recv()
            .ok()
            .or_else(|| self.answer_after_end(name, arguments.as_ref()))
            .unwrap_or_else(|| ToolError::environment().payload())
    }

    /// How the episode ended, once it has.
    pub fn ended(&self) -> Option<&Ended> {
        self.ended.get()
    }

    /// Whether the episode thread has exited, having dropped its world (simulation, GPU model, video recorder
    /// and its thread), action log and live sink.
    pub fn is_released(&self) -> bool {
        self.exited.is_set()
    }

    /// The answer to a call after the end (argument errors first, as the actor checks them), if it has ended.
    fn answer_after_end(&self, name: &str, arguments: Option<&Map<String, Value>>) -> Option<Value> {
        let ended = self.ended.get()?;
        Some(match ToolCall::parse(name, arguments) {
            Err(e) => e.payload(),
            Ok(call) => ended.answer(&call),
        })
    }

    pub fn status(&self) -> EpisodeStatus {
        match self.status.lock() {
            Ok(s) => s.clone(),
            Err(poisoned) => poisoned.into_inner().clone(),
        }
    }

    /// Ends the episode: an unfinished one is recorded as aborted with `reason`. Waits for the records and until
    /// the episode thread has released its world (the private video is final then).
    pub fn stop(&self, reason: &str) {
        let (done, rx) = mpsc::channel();
        if self.tx.send(Command::Stop { reason: reason.to_owned(), done }).is_ok() {
            let _ = rx.recv();
        }
        self.exited.wait();
    }

    /// Ends an unfinished episode as its agent's FAIL: the agent (or its harness) ended without `finish_episode`.
    /// Judged not successful whatever the scene shows (the agent never declared it done), the verdict's
    /// diagnostics kept; waits like [`EpisodeHandle::stop`]. An episode that already ended is left as it is.
    pub fn forfeit(&self, reason: &str) {
        let (done, rx) = mpsc::channel();
        if self.tx.send(Command::Forfeit { reason: reason.to_owned(), done }).is_ok() {
            let _ = rx.recv();
        }
    }

    /// Asks the episode to end as [`EpisodeHandle::stop`] does, without waiting: what a shutdown sends to every
    /// episode at once before waiting for all of them against one deadline.
    pub fn request_stop(&self, reason: &str) -> PendingStop {
        let (done, rx) = mpsc::channel();
        let sent = self.tx.send(Command::Stop { reason: reason.to_owned(), done }).is_ok();
        PendingStop { rx: sent.then_some(rx), exited: self.exited.clone() }
    }
}

/// A stop that was asked for; the episode thread answers once its records are written, then exits once its
/// world (and the private video) is released.
pub struct PendingStop {
    rx: Option<mpsc::Receiver<()>>,
    exited: Arc<ExitSignal>,
}

impl PendingStop {
    /// True once the episode thread has ended and released its world; false if it had not by `deadline`
    /// (stuck in the simulation, or still finishing its video).
    pub fn wait_until(&self, deadline: Instant) -> bool {
        if let Some(rx) = &self.rx
            && matches!(rx.recv_timeout(deadline.saturating_duration_since(Instant::now())), Err(RecvTimeoutError::Timeout))
        {
            return false;
        }
        self.exited.wait_until(deadline)
    }
}

enum Phase {
    Prepared,
    Active { started: Instant },
    Finished,
    Expired { payload: Value },
    Aborted,
}

struct Actor<W: World> {
    config: Arc<EpisodeConfig>,
    world: Option<W>,
    phase: Phase,
    accepted: u64,
    frame_index: u64,
    latest_id: Option<String>,
    log: ActionLog,
    run: RunDir,
    /// Holds the workspace root open for the episode's life.
    publisher: ObservationPublisher,
    /// The initial observation, reset done and archived, that a `start_episode` could not publish into the
    /// workspace (the agent wrecked it): the next `start_episode` publishes it without resetting again.
    unpublished_start: Option<EncodedObservation>,
    /// The call being served spent the agent-step budget: the episode ends once that call is logged.
    step_budget_spent: bool,
    status: Arc<Mutex<EpisodeStatus>>,
    /// The operator's live view (calls, the end); never the agent's.
    live: Option<LiveSink>,
    /// Whether the end was reported to `live` already.
    end_reported: bool,
    /// Shared with the handles: how the episode ended, for calls after this thread is gone.
    ended: Arc<OnceLock<Ended>>,
}

/// Starts an episode thread. `make_world` runs on that thread; if it fails, the episode is recorded as
/// aborted and the error returned (nothing is served).
pub fn spawn_episode<W, F>(config: EpisodeConfig, make_world: F) -> Result<EpisodeHandle, EpisodeError>
where
    W: World + 'static,
    F: FnOnce() -> Result<W, EpisodeError> + Send + 'static,
{
    spawn_episode_live(config, None, make_world)
}

/// As [`spawn_episode`], reporting calls and the episode's end to `live` (the operator's dashboard).
pub fn spawn_episode_live<W, F>(config: EpisodeConfig, live: Option<LiveSink>, make_world: F) -> Result<EpisodeHandle, EpisodeError>
where
    W: World + 'static,
    F: FnOnce() -> Result<W, EpisodeError> + Send + 'static,
{
    let run = RunDir::new(&config.run_dir);
    std::fs::create_dir_all(&run.root)?;
    let log = ActionLog::open(&run.actions_jsonl())?;
    // The server creates the workspace root (the app fills it after the episode exists) and keeps it open.
    std::fs::create_dir_all(&config.workspace)?;
    let publisher = ObservationPublisher::open(&config.workspace)?;
    let config = Arc::new(config);
    let status = Arc::new(Mutex::new(EpisodeStatus {
        state: EpisodeState::Prepared,
        accepted_agent_steps: 0,
        latest_observation_id: None,
        outcome: None,
        reason: None,
    }));
    let (tx, rx) = mpsc::channel();
    let (ready_tx, ready_rx) = mpsc::channel::<Result<(), EpisodeError>>();
    let actor_config = config.clone();
    let actor_status = status.clone();
    let ended: Arc<OnceLock<Ended>> = Arc::default();
    let actor_ended = ended.clone();
    let exited: Arc<ExitSignal> = Arc::default();
    let thread_exited = exited.clone();
    std::thread::Builder::new()
        .name(format!("episode-{}", config.episode_id))
        .spawn(move || {
            // Dropped last, on a panic too, so `stop` never waits for a thread that is gone.
            let _exited = SetOnDrop(thread_exited);
            let world = match catch_unwind(AssertUnwindSafe(make_world)) {
                Ok(Ok(w)) => w,
                Ok(Err(e)) => {
                    let _ = ready_tx.send(Err(e));
                    return;
                }
                Err(p) => {
                    let _ = ready_tx.send(Err(EpisodeError::Thread(panic_text(&p))));
                    return;
                }
            };
            let _ = ready_tx.send(Ok(()));
            let mut actor = Actor {
                publisher,
                unpublished_start: None,
                step_budget_spent: false,
                config: actor_config,
                world: Some(world),
                phase: Phase::Prepared,
                accepted: 0,
                frame_index: 0,
                latest_id: None,
                log,
                run,
                status: actor_status,
                live,
                end_reported: false,
                ended: actor_ended,
            };
            actor.run(rx);
            // The world (simulation, GPU model, video recorder), the action log and the live sink go first.
            drop(actor);
        })?;
    match ready_rx.recv() {
        Ok(Ok(())) => Ok(EpisodeHandle { tx, status, config, ended, exited }),
        Ok(Err(e)) => {
            let _ = write_result(&RunDir::new(&config.run_dir), &aborted_result(&format!("environment construction failed: {e}"), config.max_wall_time_s, None));
            Err(e)
        }
        Err(_) => Err(EpisodeError::Thread("episode thread exited during construction".into())),
    }
}

/// Tool calls being handled right now, by any episode of this process: background work (the private videos)
/// waits while there are some, so that on a CPU renderer it takes only cores the episodes leave idle.
static CALLS_IN_FLIGHT: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);

/// Whether any episode of this process is handling a tool call.
pub fn calls_in_flight() -> usize {
    CALLS_IN_FLIGHT.load(std::sync::atomic::Ordering::Acquire)
}

struct CallInFlight;

impl CallInFlight {
    fn enter() -> Self {
        CALLS_IN_FLIGHT.fetch_add(1, std::sync::atomic::Ordering::AcqRel);
        CallInFlight
    }
}

impl Drop for CallInFlight {
    fn drop(&mut self) {
        CALLS_IN_FLIGHT.fetch_sub(1, std::sync::atomic::Ordering::AcqRel);
    }
}

fn panic_text(p: &Box<dyn std::any::Any + Send>) -> String {
    p.downcast_ref::<&str>()
        .map(|s| (*s).to_owned())
        .or_else(|| p.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "panic".to_owned())
}

impl<W: World> Actor<W> {
    /// Serves commands until the episode ends (finish, expiry, abort, stop); then hands later calls to the
    /// handles ([`Ended`]) and returns, so the thread and everything it owns are released.
    fn run(&mut self, rx: mpsc::Receiver<Command>) {
        while self.serve_one(&rx) {}
        if let Some(ended) = self.ended_phase() {
            let _ = self.ended.set(ended);
        }
    }

    /// How the episode ended, if it has.
    fn ended_phase(&self) -> Option<Ended> {
        match &self.phase {
            Phase::Prepared | Phase::Active { .. } => None,
            Phase::Finished => Some(Ended::Finished),
            Phase::Expired { payload } => Some(Ended::Expired { payload: payload.clone() }),
            Phase::Aborted => Some(Ended::Aborted),
        }
    }

    /// Handles one command or idle tick; false once the episode has ended (or nobody can call any more).
    fn serve_one(&mut self, rx: &mpsc::Receiver<Command>) -> bool {
        let msg = match self.phase {
            Phase::Active { started } => {
                let deadline = started + Duration::from_secs_f64(self.config.max_wall_time_s.max(0.0));
                let wait = deadline.saturating_duration_since(Instant::now()).min(IDLE_POLL);
                rx.recv_timeout(wait)
            }
            _ => rx.recv().map_err(|_| RecvTimeoutError::Disconnected),
        };
        match msg {
            // The reply goes out before the thread releases the world (which queues the private video).
            Ok(Command::Call { name, arguments, reply }) => {
                let payload = {
                    let _busy = CallInFlight::enter();
                    self.handle_call(&name, arguments)
                };
                let _ = reply.send(payload);
            }
            Ok(Command::Stop { reason, done }) => {
                self.abort_if_unfinished(&reason);
                let _ = done.send(());
                return false;
            }
            Ok(Command::Forfeit { reason, done }) => {
                self.forfeit(&reason);
                let _ = done.send(());
            }
            Err(RecvTimeoutError::Timeout) => {
                if self.deadline_passed() {
                    self.expire(EXPIRY_REASON, "wall_time_budget_expired");
                }
            }
            Err(RecvTimeoutError::Disconnected) => {
                self.abort_if_unfinished("server_stopped_before_finish");
                return false;
            }
        }
        self.ended_phase().is_none()
    }

    fn deadline_passed(&self) -> bool {
        match self.phase {
            Phase::Active { started } => started.elapsed().as_secs_f64() >= self.config.max_wall_time_s,
            _ => false,
        }
    }

    fn wall_time_s(&self) -> Option<f64> {
        match self.phase {
            Phase::Active { started } => Some(started.elapsed().as_secs_f64()),
            _ => None,
        }
    }

    fn handle_call(&mut self, name: &str, arguments: Option<Map<String, Value>>) -> Value {
        let actions = arguments.as_ref().and_then(|a| a.get("actions")).and_then(Value::as_array).map(Vec::len);
        if let Some(live) = &self.live {
            live(LiveEvent::CallReceived { tool: name.to_owned(), actions, at_unix_s: unix_now_s() });
        }
        let payload = self.handle_call_logged(name, arguments);
        if let Some(live) = &self.live {
            // The payload was built here: read back through its types (a reply, and a finish's result fields).
            let reply = ToolReply::of(&payload);
            let answered = Answered::deserialize(&payload).unwrap_or_default();
            let finished_wall = || RunResult::deserialize(&payload).ok().and_then(|r| r.wall_time_seconds.flatten());
            live(LiveEvent::CallAnswered {
                tool: name.to_owned(),
                actions,
                ok: reply.is_ok(),
                error_type: reply.error_type,
                error: reply.error.as_ref().and_then(Value::as_str).map(str::to_owned),
                observation_id: answered.observation_id,
                accepted_agent_steps: self.accepted,
                max_agent_steps: self.config.agent_step_limit(),
                wall_time_s: self.wall_time_s().or_else(finished_wall),
                max_wall_time_s: self.config.max_wall_time_s,
                at_unix_s: unix_now_s(),
            });
        }
        payload
    }

    fn handle_call_logged(&mut self, name: &str, arguments: Option<Map<String, Value>>) -> Value {
        let call = ToolCall::parse(name, arguments.as_ref());
        let request = json!({
            "tool": name,
            "command": call.as_ref().ok().map(|c| c.tool().command()),
            "arguments": arguments,
            "observation_id": self.latest_id,
        });
        let payload = match call {
            Err(e) => e.payload(),
            Ok(call) => match catch_unwind(AssertUnwindSafe(|| self.dispatch(call))) {
                Ok(Ok(payload)) => payload,
                Ok(Err(e)) => e.payload(),
                Err(p) => {
                    self.abort(&format!("internal error: {}", panic_text(&p)));
                    ToolError::environment().payload()
                }
            },
        };
        if let Err(e) = self.log.append(&request, &payload, 1) {
            log::error!("episode {}: cannot append to actions.jsonl: {e}", self.config.episode_id);
            self.abort(&format!("action log write failed: {e}"));
            return ToolError::environment().payload();
        }
        if std::mem::take(&mut self.step_budget_spent) && matches!(self.phase, Phase::Active { .. }) {
            self.expire(libero_records::records::STEP_BUDGET_EXHAUSTED, "agent_step_budget_exhausted");
        }
        payload
    }

    fn dispatch(&mut self, call: ToolCall) -> Result<Value, ToolError> {
        if self.deadline_passed() {
            self.expire(EXPIRY_REASON, "wall_time_budget_expired");
        }
        if let Some(ended) = self.ended_phase() {
            return Ok(ended.answer(&call));
        }
        let prepared = matches!(self.phase, Phase::Prepared);
        match call {
            ToolCall::Start if prepared => self.start(),
            ToolCall::Start => Err(ToolError::runtime_error(START_TWICE_TEXT)),
            call if prepared => Err(ToolError::runtime_error(format!(
                "{} requires one active episode; call start_episode first",
                if call.tool() == ToolName::FinishEpisode { "finish" } else { "osc_sequence" }
            ))),
            ToolCall::OscSequence { actions } => {
                let limit = self.config.agent_step_limit();
                if self.accepted >= limit {
                    return Err(ToolError::runtime_error(format!("agent step limit reached ({limit})")));
                }
                let actions = validate_actions(&actions)?;
                let mut payload = self.execute(&actions)?;
                // The call that spends the step budget ends the episode (§3.1), judged as the wall time's end is;
                // the agent gets its observation and the word that the episode is over.
                if self.accepted >= limit && matches!(self.phase, Phase::Active { .. }) {
                    self.step_budget_spent = true;
                    if let Some(p) = payload.as_object_mut() {
                        p.insert("episode_ended".into(), json!(true));
                        p.insert("termination_reason".into(), json!(libero_records::records::STEP_BUDGET_EXHAUSTED));
                    }
                }
                Ok(payload)
            }
            ToolCall::Finish => self.finish(),
        }
    }

    /// A server-side failure: recorded privately, the episode ends INVALID, the agent gets the generic error.
    fn fault(&mut self, e: EpisodeError) -> ToolError {
        log::error!("episode {}: {e}", self.config.episode_id);
        self.abort(&e.to_string());
        ToolError::environment()
    }

    /// Runs `f` on the world; a failure aborts the episode and becomes the agent's generic error.
    fn with_world<T>(&mut self, f: impl FnOnce(&mut W) -> Result<T, EpisodeError>) -> Result<T, ToolError> {
        let result = match self.world.as_mut() {
            Some(w) => f(w),
            None => Err(EpisodeError::Thread("the world was already released".into())),
        };
        result.map_err(|e| self.fault(e))
    }

    /// Renders the current frame, encodes it and writes the evaluator-private archive copy. A failure here is the
    /// server's (simulator, renderer, run directory): the episode ends INVALID.
    fn archive_frame(&mut self) -> Result<EncodedObservation, ToolError> {
        let index = self.frame_index;
        let frame = self.with_world(|w| w.frame(index))?;
        let private = self.run.private_observations();
        let archived = encode_observation(&frame, self.config.level).and_then(|e| write_private_copy(&private, &e).map(|()| e));
        let encoded = archived.map_err(|e| self.fault(EpisodeError::Io(e)))?;
        self.latest_id = Some(encoded.observation_id.clone());
        Ok(encoded)
    }

    /// Publishes an archived observation into the agent's workspace. A failure there is the agent's doing (it
    /// changed its workspace under every attempt) or its workspace's (a full disk): never a fault of the
    /// episode, which goes on; the text tells the agent.
    fn publish_to_workspace(&mut self, encoded: &EncodedObservation) -> Result<(), String> {
        self.publisher.publish_encoded(encoded).map_err(|e| {
            log::warn!("episode {}: {} not published into the workspace: {e}", self.config.episode_id, encoded.observation_id);
            format!(
                "{PUBLICATION_FAILED}: {} could not be placed at {CURRENT_OBSERVATION_DIR} in your workspace: {e} (your workspace's benchmark_inputs was changed or cannot be written)",
                encoded.observation_id
            )
        })
    }

    fn start(&mut self) -> Result<Value, ToolError> {
        let encoded = match self.unpublished_start.take() {
            Some(encoded) => encoded,
            None => {
                self.with_world(|w| w.start())?;
                self.archive_frame()?
            }
        };
        if let Err(why) = self.publish_to_workspace(&encoded) {
            self.unpublished_start = Some(encoded);
            return Err(ToolError::runtime_error(format!(
                "{why}; the episode has not started and its wall clock is not running: call start_episode again"
            )));
        }
        // The wall clock starts after the initial observation is published (§2.7).
        self.phase = Phase::Active { started: Instant::now() };
        self.update_status();
        Ok(json!({
            "ok": true,
            "observation_id": encoded.observation_id,
            "observation_file": OBSERVATION_FILE,
            "max_agent_steps": self.config.agent_step_limit(),
            "attempt_index": 1,
            "reset_count": 0,
            "remaining_resets": 0,
            "max_wall_time_seconds": self.config.max_wall_time_s,
            "wall_time_budget_scope": BUDGET_SCOPE,
            "execution": {},
            "task_instruction": self.config.instruction,
        }))
    }

    fn execute(&mut self, actions: &[MicroAction]) -> Result<Value, ToolError> {
        self.with_world(|w| actions.iter().try_for_each(|a| w.step(a)))?;
        self.frame_index += 1;
        self.accepted += 1;
        let encoded = self.archive_frame()?;
        let published = self.publish_to_workspace(&encoded);
        self.update_status();
        let execution = json!({
            "command_completed": true,
            "termination_reason": "sequence_executed",
            "micro_step_count": actions.len(),
            "control_steps": actions.len(),
        });
        Ok(match published {
            Ok(()) => json!({
                "ok": true,
                "observation_id": encoded.observation_id,
                "observation_file": OBSERVATION_FILE,
                "execution": execution,
            }),
            // The robot moved and the call counts: the payload says so beside the error (`execution`).
            Err(why) => {
                let mut payload = ToolError::runtime_error(format!(
                    "{why}; the actions were executed and count as accepted agent step {}; the episode continues and the next successful osc_sequence publishes a new observation",
                    self.accepted
                ))
                .payload();
                payload["execution"] = execution;
                payload["accepted_agent_steps"] = json!(self.accepted);
                payload
            }
        })
    }

    fn finished_payload(&self, success: bool, wall_time_s: f64) -> Value {
        json!({
            "ok": true,
            "status": "finished",
            "success": success,
            "accepted_agent_steps": self.accepted,
            "accepted_agent_steps_current_attempt": self.accepted,
            "attempt_index": 1,
            "reset_count": 0,
            "remaining_resets": 0,
            "max_wall_time_seconds": self.config.max_wall_time_s,
            "wall_time_budget_scope": BUDGET_SCOPE,
            "wall_time_seconds": wall_time_s,
        })
    }

    /// `result.json`: the finish payload (§2.9) with the schema, the time and the evaluator's record (§4.9).
    fn write_final(&mut self, payload: &Value, verdict: Option<&Verdict>) -> std::io::Result<()> {
        let mut result = RunResult::from_value(payload.clone()).map_err(std::io::Error::other)?;
        result.schema_version = Some(RESULT_SCHEMA.to_owned());
        result.finished_at = Some(utc_now_iso());
        if let Some(v) = verdict {
            result.set_private_evaluation(v.private_evaluation.clone());
            if !v.stage_events.is_empty() {
                let mut text = String::new();
                for e in &v.stage_events {
                    text.push_str(&compact_sorted(e));
                    text.push('\n');
                }
                libero_records::json::write_atomic(&self.run.stage_events_jsonl(), text.as_bytes())?;
            }
        }
        write_result(&self.run, &result)
    }

    fn finish(&mut self) -> Result<Value, ToolError> {
        let wall = self.wall_time_s().unwrap_or(0.0);
        let verdict = self.with_world(|w| w.verdict())?;
        let payload = self.finished_payload(verdict.success, wall);
        if let Err(e) = self.write_final(&payload, Some(&verdict)) {
            self.abort(&format!("result.json write failed: {e}"));
            return Err(ToolError::environment());
        }
        self.phase = Phase::Finished;
        self.update_status();
        Ok(payload)
    }

    /// A budget's end — the wall clock (§4.6, recorded even if no call arrives) or the agent-step budget:
    /// finished, not successful, with `reason` as the termination reason and `command` in the action log.
    fn expire(&mut self, reason: &str, command: &str) {
        let wall = self.wall_time_s().unwrap_or(self.config.max_wall_time_s);
        let verdict = self.world.as_mut().and_then(|w| w.verdict().ok());
        let mut payload = self.finished_payload(false, wall);
        payload["termination_reason"] = json!(reason);
        if let Err(e) = self.write_final(&payload, verdict.as_ref()) {
            self.abort(&format!("result.json write failed: {e}"));
            return;
        }
        if let Err(e) = self.log.append(&json!({"command": command}), &payload, 1) {
            log::error!("episode {}: cannot log expiry: {e}", self.config.episode_id);
        }
        self.phase = Phase::Expired { payload };
        self.world = None;
        self.update_status();
    }

    /// The agent ended without `finish_episode`: finished, not successful, with the reason in the action log.
    fn forfeit(&mut self, reason: &str) {
        if !matches!(self.phase, Phase::Prepared | Phase::Active { .. }) {
            return;
        }
        let wall = self.wall_time_s().unwrap_or(0.0);
        let verdict = self.world.as_mut().and_then(|w| w.verdict().ok());
        let mut payload = self.finished_payload(false, wall);
        payload["termination_reason"] = json!(FORFEIT_REASON);
        if let Err(e) = self.write_final(&payload, verdict.as_ref()) {
            self.abort(&format!("result.json write failed: {e}"));
            return;
        }
        if let Err(e) = self.log.append(&json!({"command": FORFEIT_REASON, "reason": reason}), &payload, 1) {
            log::error!("episode {}: cannot log the forfeit: {e}", self.config.episode_id);
        }
        self.phase = Phase::Finished;
        self.world = None;
        self.update_status();
    }

    fn abort(&mut self, reason: &str) {
        if matches!(self.phase, Phase::Finished | Phase::Expired { .. } | Phase::Aborted) {
            return;
        }
        let result = aborted_result(reason, self.config.max_wall_time_s, self.wall_time_s());
        if let Err(e) = write_result(&self.run, &result) {
            log::error!("episode {}: cannot write aborted result: {e}", self.config.episode_id);
        }
        self.phase = Phase::Aborted;
        self.world = None;
        if let Ok(mut s) = self.status.lock() {
            s.reason = Some(reason.to_owned());
        }
        self.update_status();
    }

    fn abort_if_unfinished(&mut self, reason: &str) {
        self.abort(reason);
    }

    fn update_status(&mut self) {
        let state = match self.phase {
            Phase::Prepared => EpisodeState::Prepared,
            Phase::Active { .. } => EpisodeState::Active,
            Phase::Finished | Phase::Expired { .. } => EpisodeState::Finished,
            Phase::Aborted => EpisodeState::Aborted,
        };
        if matches!(state, EpisodeState::Finished | EpisodeState::Aborted) {
            self.publisher.release_staging();
        }
        let outcome = match state {
            EpisodeState::Finished | EpisodeState::Aborted => {
                Some(classify(libero_records::records::read_result(&self.run).as_ref()))
            }
            _ => None,
        };
        let reason = match self.status.lock() {
            Ok(mut s) => {
                s.state = state;
                s.accepted_agent_steps = self.accepted;
                s.latest_observation_id = self.latest_id.clone();
                s.outcome = outcome;
                s.reason.clone()
            }
            Err(_) => None,
        };
        self.report_end(state, outcome, reason);
    }

    /// Tells the live view once that the episode ended.
    fn report_end(&mut self, state: EpisodeState, outcome: Option<Outcome>, reason: Option<String>) {
        let (Some(live), Some(outcome)) = (&self.live, outcome) else { return };
        if self.end_reported {
            return;
        }
        self.end_reported = true;
        let state = serde_json::to_value(state).ok().and_then(|v| v.as_str().map(str::to_owned)).unwrap_or_default();
        live(LiveEvent::Finished { state, outcome: Some(outcome.as_str().to_owned()), reason });
    }
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::{AtomicBool, Ordering};

    use super::*;
    use crate::observation::{CameraFrame, RgbImage, RobotReadout};

    /// A world that does nothing and says when it is dropped.
    struct FakeWorld {
        dropped: Arc<AtomicBool>,
        fail_start: bool,
        /// `start` (reset) calls so far.
        starts: Arc<std::sync::atomic::AtomicUsize>,
    }

    impl Drop for FakeWorld {
        fn drop(&mut self) {
            self.dropped.store(true, Ordering::SeqCst);
        }
    }

    fn camera() -> CameraFrame {
        let identity = [[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]];
        CameraFrame {
            image: RgbImage { width: 2, height: 2, rgb: vec![0; 12] },
            depth_m: vec![1.0; 4],
            depth_valid: vec![true; 4],
            intrinsic_matrix_3x3: [[1.0, 0.0, 1.0], [0.0, 1.0, 1.0], [0.0, 0.0, 1.0]],
            t_robot_base_from_camera: identity,
        }
    }

    impl World for FakeWorld {
        fn start(&mut self) -> Result<(), EpisodeError> {
            self.starts.fetch_add(1, Ordering::SeqCst);
            if self.fail_start { Err(EpisodeError::Thread("start failed on purpose".into())) } else { Ok(()) }
        }
        fn step(&mut self, _: &MicroAction) -> Result<(), EpisodeError> {
            Ok(())
        }
        fn frame(&mut self, frame_index: u64) -> Result<Frame, EpisodeError> {
            Ok(Frame { frame_index, robot: RobotReadout::default(), head: camera(), wrist: camera(), task_reference: None })
        }
        fn verdict(&mut self) -> Result<Verdict, EpisodeError> {
            Ok(Verdict { success: false, private_evaluation: json!({}), stage_events: vec![] })
        }
    }

    fn spawn(dir: &std::path::Path, wall_s: f64, fail_start: bool) -> (EpisodeHandle, Arc<AtomicBool>) {
        let config = EpisodeConfig {
            episode_id: "fake".into(),
            instruction: "do nothing".into(),
            level: Level::L1,
            max_agent_steps: 10,
            max_wall_time_s: wall_s,
            workspace: dir.join("ws"),
            run_dir: dir.join("run"),
        };
        std::fs::create_dir_all(config.workspace.join("benchmark_inputs")).unwrap();
        let dropped = Arc::new(AtomicBool::new(false));
        let world = FakeWorld { dropped: dropped.clone(), fail_start, starts: Arc::default() };
        (spawn_episode(config, move || Ok(world)).unwrap(), dropped)
    }

    fn wait_released(h: &EpisodeHandle) {
        let t = Instant::now();
        while !h.is_released() {
            assert!(t.elapsed() < Duration::from_secs(10), "the episode thread did not exit");
            std::thread::sleep(Duration::from_millis(10));
        }
    }

    fn error_text(payload: &Value) -> &str {
        payload["error"].as_str().unwrap_or_default()
    }

    #[test]
    fn a_finished_episode_releases_its_thread_and_world_and_later_calls_get_the_same_answers() {
        let dir = tempfile::tempdir().unwrap();
        let (h, dropped) = spawn(dir.path(), 600.0, false);
        assert_eq!(h.call("start_episode", None)["ok"], true);
        assert!(!h.is_released() && h.ended().is_none());
        assert_eq!(h.call("finish_episode", None)["status"], "finished");
        wait_released(&h);
        assert!(dropped.load(Ordering::SeqCst), "the world is dropped with the thread");
        assert_eq!(h.ended(), Some(&Ended::Finished));
        assert_eq!(error_text(&h.call("finish_episode", None)), FINISHED_TEXT);
        assert_eq!(error_text(&h.call("start_episode", None)), START_TWICE_TEXT);
        let bad = h.call("osc_sequence", None);
        assert_eq!((bad["error_type"].as_str(), error_text(&bad)), (Some("ValueError"), "osc_sequence requires only the actions argument"));
        h.stop("too late"); // nobody is left to stop: returns once the thread is gone
        assert_eq!(h.status().state, EpisodeState::Finished);
    }

    #[test]
    fn stop_returns_once_the_world_is_gone_whether_the_episode_was_open_or_had_just_finished() {
        let dir = tempfile::tempdir().unwrap();
        let (open, dropped) = spawn(&dir.path().join("open"), 600.0, false);
        assert_eq!(open.call("start_episode", None)["ok"], true);
        open.stop("server_received_signal_15_before_finish");
        assert!(dropped.load(Ordering::SeqCst) && open.is_released());
        assert_eq!(open.ended(), Some(&Ended::Aborted));
        let (finished, dropped) = spawn(&dir.path().join("finished"), 600.0, false);
        assert_eq!(finished.call("start_episode", None)["ok"], true);
        assert_eq!(finished.call("finish_episode", None)["ok"], true);
        finished.stop("test over");
        assert!(dropped.load(Ordering::SeqCst) && finished.is_released());
    }

    #[test]
    fn a_faulted_episode_and_an_expired_one_release_theirs_too() {
        let dir = tempfile::tempdir().unwrap();
        let (faulted, dropped) = spawn(&dir.path().join("faulted"), 600.0, true);
        assert_eq!(faulted.call("start_episode", None)["error_type"], "EnvironmentCommandError");
        wait_released(&faulted);
        assert!(dropped.load(Ordering::SeqCst));
        assert_eq!(error_text(&faulted.call("finish_episode", None)), ABORTED_TEXT);
        let (expiring, dropped) = spawn(&dir.path().join("expiring"), 0.2, false);
        assert_eq!(expiring.call("start_episode", None)["ok"], true);
        wait_released(&expiring);
        assert!(dropped.load(Ordering::SeqCst));
        let late = expiring.call("finish_episode", None);
        assert_eq!((late["ok"].clone(), late["termination_reason"].clone()), (json!(true), json!(EXPIRY_REASON)));
    }

    fn spawn_counting(dir: &std::path::Path) -> (EpisodeHandle, Arc<std::sync::atomic::AtomicUsize>) {
        let config = EpisodeConfig {
            episode_id: "sabotaged".into(),
            instruction: "do nothing".into(),
            level: Level::L3,
            max_agent_steps: 10,
            max_wall_time_s: 600.0,
            workspace: dir.join("ws"),
            run_dir: dir.join("run"),
        };
        std::fs::create_dir_all(config.workspace.join("benchmark_inputs")).unwrap();
        let starts = Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let world = FakeWorld { dropped: Arc::default(), fail_start: false, starts: starts.clone() };
        (spawn_episode(config, move || Ok(world)).unwrap(), starts)
    }

    fn observation_id_on_disk(ws: &std::path::Path) -> Value {
        let text = std::fs::read(ws.join(OBSERVATION_FILE)).unwrap();
        serde_json::from_slice::<Value>(&text).unwrap()["observation_id"].clone()
    }

    #[test]
    fn an_agent_that_wrecks_every_publication_gets_errors_and_its_episode_still_ends_with_a_verdict() {
        use crate::publish::{ATTEMPTS, Moment, install_hook};
        let dir = tempfile::tempdir().unwrap();
        let ws = dir.path().join("ws");
        // The agent deletes benchmark_inputs under every attempt of the first start_episode and of the first
        // osc_sequence (attempt counts 0..8 and 9..17), and leaves the others alone.
        let bi = ws.join("benchmark_inputs");
        let mut staged = 0usize;
        install_hook(&ws, move |moment, _| {
            if moment == Moment::Staged {
                if staged < ATTEMPTS || (ATTEMPTS + 1..2 * ATTEMPTS + 1).contains(&staged) {
                    let _ = std::fs::remove_dir_all(&bi);
                }
                staged += 1;
            }
        });
        let (h, starts) = spawn_counting(dir.path());
        let first = h.call("start_episode", None);
        assert_eq!(first["error_type"], "RuntimeError", "{first}");
        let text = error_text(&first);
        assert!(text.starts_with(PUBLICATION_FAILED) && text.contains("call start_episode again"), "{text}");
        assert_eq!(h.status().state, EpisodeState::Prepared, "not aborted, not started");
        let early = h.call("osc_sequence", Some(json!({"actions": [[0, 0, 0, 0, 0, 0, 0]]}).as_object().unwrap().clone()));
        assert!(error_text(&early).contains("call start_episode first"), "{early}");
        // The retry publishes the initial observation archived by the first call, without a second reset.
        let second = h.call("start_episode", None);
        assert_eq!((second["ok"].clone(), second["observation_id"].clone()), (json!(true), json!("obs_000000")), "{second}");
        assert_eq!(starts.load(Ordering::SeqCst), 1, "the world was reset once");
        assert_eq!(observation_id_on_disk(&ws), "obs_000000");
        let act = || Some(json!({"actions": [[0.1, 0, 0, 0, 0, 0, 1], [0.1, 0, 0, 0, 0, 0, 1]]}).as_object().unwrap().clone());
        // The step is executed and counted; only its observation is missing, and the payload says both.
        let spoiled = h.call("osc_sequence", act());
        assert_eq!((spoiled["ok"].clone(), spoiled["error_type"].clone()), (json!(false), json!("RuntimeError")), "{spoiled}");
        assert!(error_text(&spoiled).starts_with(PUBLICATION_FAILED) && error_text(&spoiled).contains("obs_000001"), "{spoiled}");
        assert_eq!(spoiled["execution"]["command_completed"], true);
        assert_eq!(spoiled["execution"]["control_steps"], 2);
        assert_eq!(spoiled["accepted_agent_steps"], 1);
        assert_eq!(h.status().state, EpisodeState::Active);
        assert_eq!(h.status().accepted_agent_steps, 1);
        let next = h.call("osc_sequence", act());
        assert_eq!((next["ok"].clone(), next["observation_id"].clone()), (json!(true), json!("obs_000002")), "{next}");
        assert_eq!(observation_id_on_disk(&ws), "obs_000002");
        let finished = h.call("finish_episode", None);
        assert_eq!((finished["status"].clone(), finished["accepted_agent_steps"].clone()), (json!("finished"), json!(2)), "{finished}");
        let status = h.status();
        assert_eq!((status.state, status.outcome), (EpisodeState::Finished, Some(Outcome::Fail)));
        let result = libero_records::records::read_result(&RunDir::new(dir.path().join("run"))).unwrap();
        assert_eq!(result.status.as_deref(), Some("finished"));
        // Every frame is in the private archive, the unpublished one included.
        for id in ["obs_000000", "obs_000001", "obs_000002"] {
            assert!(dir.path().join("run/private_observations").join(id).join("observation.json").is_file(), "{id}");
        }
    }

    #[test]
    fn an_agent_that_removes_its_whole_workspace_still_gets_a_verdict() {
        let dir = tempfile::tempdir().unwrap();
        let (h, _) = spawn_counting(dir.path());
        assert_eq!(h.call("start_episode", None)["ok"], true);
        std::fs::remove_dir_all(dir.path().join("ws")).unwrap();
        let spoiled = h.call("osc_sequence", Some(json!({"actions": [[0, 0, 0, 0, 0, 0, 1]]}).as_object().unwrap().clone()));
        assert!(error_text(&spoiled).contains("workspace directory itself was removed"), "{spoiled}");
        assert_eq!(spoiled["execution"]["command_completed"], true);
        let finished = h.call("finish_episode", None);
        assert_eq!((finished["status"].clone(), finished["accepted_agent_steps"].clone()), (json!("finished"), json!(1)));
        assert_eq!(h.status().outcome, Some(Outcome::Fail));
    }
}
