//! openpi's LIBERO evaluation loop over any episode that takes `osc_sequence` and publishes observation
//! folders, so that a runner harness or a single-episode command plugs its episode in through [`EpisodeSteps`]:
//! warm-up, then ask for a chunk, execute its first `replan_steps` actions as one `osc_sequence`, read the newly
//! published observation, repeat until the control-step cap, the episode's own end or a policy failure.
use std::collections::BTreeMap;
use std::path::PathBuf;

use crate::libero::{ChunkExecutor, LIBERO_DUMMY_ACTION, LiberoContract, PublishedFrame, RobotBaseInWorld, observation_request};
use crate::{PolicyClient, PolicyError};

/// The episode as the policy loop drives it (the episode service's tools, in process or over MCP).
pub trait EpisodeSteps {
    /// Executes `actions` (1 to 50, each 7 components in [-1, 1]) as one `osc_sequence` and returns the folder of
    /// the observation published after them, or `None` when the episode refused more (its budget or its end).
    fn osc_sequence(&mut self, actions: &[[f64; 7]]) -> Result<Option<PathBuf>, String>;
}

/// Why the loop stopped.
#[derive(Debug)]
pub enum LoopEnd {
    /// The control-step cap (after the warm-up) was reached.
    StepCap,
    /// The episode refused more actions.
    EpisodeEnded,
    /// The policy or its connection failed; the episode should be recorded as an infrastructure failure.
    Policy(PolicyError),
    /// The episode service failed a call.
    Episode(String),
}

/// What the loop did, for the rollout's record.
#[derive(Debug)]
pub struct LoopReport {
    pub end: LoopEnd,
    /// Control steps after the warm-up.
    pub control_steps: usize,
    pub warmup_steps: usize,
    /// One entry per request: `server_timing` plus `client_round_trip_ms`.
    pub timings: Vec<BTreeMap<String, f64>>,
    pub clipped_components: usize,
}

/// Runs openpi's LIBERO loop from the episode's first published observation `first` until `max_steps` control
/// steps (openpi's per-suite caps, `libero::suite_max_steps`) or an end.
pub fn run_loop(
    episode: &mut dyn EpisodeSteps,
    client: &mut PolicyClient,
    contract: &LiberoContract,
    base: &RobotBaseInWorld,
    prompt: &str,
    first: PathBuf,
    max_steps: usize,
) -> LoopReport {
    let mut report = LoopReport { end: LoopEnd::StepCap, control_steps: 0, warmup_steps: 0, timings: Vec::new(), clipped_components: 0 };
    let mut current = first;
    if contract.warmup_steps > 0 {
        // openpi steps the dummy action `num_steps_wait` times before its first observation.
        match send(episode, &vec![LIBERO_DUMMY_ACTION; contract.warmup_steps]) {
            Ok(Some(dir)) => current = dir,
            Ok(None) => return LoopReport { end: LoopEnd::EpisodeEnded, ..report },
            Err(e) => return LoopReport { end: LoopEnd::Episode(e), ..report },
        }
        report.warmup_steps = contract.warmup_steps;
    }
    let mut executor = ChunkExecutor::new(contract.replan_steps);
    while report.control_steps < max_steps {
        let frame = match PublishedFrame::read(&current) {
            Ok(f) => f,
            Err(e) => return LoopReport { end: LoopEnd::Episode(e.to_string()), ..report },
        };
        let answer = observation_request(&frame, base, prompt, contract).and_then(|obs| client.infer(&obs));
        let chunk = match answer.and_then(|c| executor.push_chunk(&c.actions).map(|()| c)) {
            Ok(c) => c,
            Err(e) => return LoopReport { end: LoopEnd::Policy(e), clipped_components: executor.clipped_components, ..report },
        };
        let mut timing = chunk.server_timing.clone();
        timing.insert("client_round_trip_ms".into(), chunk.client_round_trip_ms);
        report.timings.push(timing);
        let mut actions = Vec::new();
        while let Some(a) = executor.next_action() {
            if report.control_steps + actions.len() < max_steps {
                actions.push(a);
            }
        }
        report.clipped_components = executor.clipped_components;
        match send(episode, &actions) {
            Ok(Some(dir)) => current = dir,
            Ok(None) => return LoopReport { end: LoopEnd::EpisodeEnded, control_steps: report.control_steps + actions.len(), ..report },
            Err(e) => return LoopReport { end: LoopEnd::Episode(e), ..report },
        }
        report.control_steps += actions.len();
    }
    report
}

/// `osc_sequence` takes at most this many actions a call.
const MAX_ACTIONS_PER_CALL: usize = 50;

/// Sends `actions` in calls of at most [`MAX_ACTIONS_PER_CALL`]; the folder published after the last.
fn send(episode: &mut dyn EpisodeSteps, actions: &[[f64; 7]]) -> Result<Option<PathBuf>, String> {
    let mut last = None;
    for part in actions.chunks(MAX_ACTIONS_PER_CALL) {
        match episode.osc_sequence(part)? {
            Some(dir) => last = Some(dir),
            None => return Ok(None),
        }
    }
    Ok(last)
}
