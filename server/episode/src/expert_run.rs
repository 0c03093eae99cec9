//! Runs a scripted privileged expert as an episode's agent. The expert reads a replica of the episode's physics
//! (built from the same task, seed and init state, stepped with the same actions — bit-identical by the
//! determinism contract) and acts only through the episode's tools: `start_episode`, `osc_sequence` calls of at
//! most 50 actions, `finish_episode`. Whether the tools are served in-process or over MCP is the caller's port.
use serde_json::{Value, json};

use libero_records::records::ToolReply;
use libero_tasks::expert::Expert;

use crate::EpisodeError;
use crate::actor::EpisodeHandle;
use crate::physics::{WorldPhysics, WorldSpec};
use crate::tools::MAX_MICRO_ACTIONS_PER_CALL;

/// The behaviour of an agent that starts and finishes without acting.
pub const IDLE: &str = "idle";

/// Somewhere the three tools can be called.
pub trait ToolPort {
    /// Calls `tool` and returns its payload (with `ok` true or false); `Err` only when the call could not be made.
    fn call_tool(&mut self, tool: &str, arguments: Value) -> Result<Value, EpisodeError>;
}

impl ToolPort for EpisodeHandle {
    fn call_tool(&mut self, tool: &str, arguments: Value) -> Result<Value, EpisodeError> {
        let arguments = match arguments {
            Value::Object(m) => Some(m),
            _ => None,
        };
        Ok(self.call(tool, arguments))
    }
}

/// What an expert run did.
#[derive(Debug, Clone)]
pub struct ExpertRun {
    pub osc_calls: u64,
    pub actions: u64,
    /// The `finish_episode` payload (agent-visible: `success`, budgets).
    pub finish: Value,
    /// The replica's own evaluation record (its success must agree with the episode's verdict).
    pub replica_record: Value,
}

/// Actions travel as JSON: quantized to 1e-6 so that the decimal text parses back to exactly the value the
/// replica stepped with (a short decimal parses by one correctly rounded division).
fn quantize(a: [f64; 7]) -> [f64; 7] {
    a.map(|x| ((x * 1e6).round() / 1e6).clamp(-1.0, 1.0))
}

/// The payload of an `ok` answer; a refusal as an error quoting the reply's `error` (the whole reply without one).
fn tool_ok(tool: &str, payload: Value) -> Result<Value, EpisodeError> {
    let reply = ToolReply::of(&payload);
    if reply.is_ok() {
        Ok(payload)
    } else {
        let message = reply.error.as_ref().map_or_else(|| payload.to_string(), Value::to_string);
        Err(EpisodeError::Task(format!("{tool} failed: {message}")))
    }
}

/// Plays `behaviour` (an expert behaviour of the task, or [`IDLE`]) through `port` on the episode described by
/// `spec`, at most `max_actions` actions. `progress` hears one line per `osc_sequence` call.
pub fn run_expert(
    port: &mut dyn ToolPort,
    spec: &WorldSpec,
    task_id: &str,
    behaviour: &str,
    max_actions: u64,
    mut progress: impl FnMut(&str),
) -> Result<ExpertRun, EpisodeError> {
    let mut replica = WorldPhysics::build(spec, |_, _, _| Ok(()))?;
    let mut expert: Option<Box<dyn Expert>> = if behaviour == IDLE {
        None
    } else {
        Some(
            libero_tasks::expert_for(task_id, behaviour, &replica.scene, replica.model())
                .map_err(|e| EpisodeError::Task(e.to_string()))?,
        )
    };
    tool_ok("start_episode", port.call_tool("start_episode", json!({}))?)?;
    replica.start(|_| {})?;
    let (mut osc_calls, mut actions) = (0u64, 0u64);
    while let Some(expert) = expert.as_mut() {
        let mut chunk: Vec<[f64; 7]> = Vec::with_capacity(MAX_MICRO_ACTIONS_PER_CALL);
        while chunk.len() < MAX_MICRO_ACTIONS_PER_CALL && actions + (chunk.len() as u64) < max_actions {
            let Some(a) = expert.act(&replica.sim) else { break };
            let a = quantize(a);
            replica.step(&a)?;
            chunk.push(a);
        }
        if chunk.is_empty() {
            break;
        }
        let n = chunk.len() as u64;
        tool_ok("osc_sequence", port.call_tool("osc_sequence", json!({ "actions": chunk }))?)?;
        osc_calls += 1;
        actions += n;
        progress(&format!("osc_sequence #{osc_calls}: {n} actions ({actions} total), phase {}", expert.phase().unwrap_or("done")));
        if actions >= max_actions {
            break;
        }
    }
    let finish = tool_ok("finish_episode", port.call_tool("finish_episode", json!({}))?)?;
    let record = replica.evaluate();
    let replica_success = record.success;
    let verdict = ToolReply::of(&finish).success;
    if verdict != Some(replica_success) {
        return Err(EpisodeError::Task(format!(
            "the expert's replica diverged from the episode: replica success {replica_success}, episode {}",
            verdict.map_or("missing".into(), |s| s.to_string())
        )));
    }
    let replica_record = serde_json::to_value(&record).map_err(|e| EpisodeError::Evaluator(e.to_string()))?;
    Ok(ExpertRun { osc_calls, actions, finish, replica_record })
}

/// One control step of a replica-only run, for tuning scripts.
#[derive(Debug, Clone, serde::Serialize)]
pub struct TraceStep {
    pub step: u64,
    pub phase: Option<&'static str>,
    pub action: [f64; 7],
    pub eef_pos_in_world_m: [f64; 3],
    pub gripper_qpos_m: [f64; 2],
}

/// Plays `behaviour` on a replica alone (no episode, no rendering): fast, for developing and tuning experts.
/// `trace` sees every step; returns the evaluation record on the final state.
pub fn run_replica_only(
    spec: &WorldSpec,
    task_id: &str,
    behaviour: &str,
    max_actions: u64,
    mut trace: impl FnMut(&TraceStep, &libero_sim::Simulation),
) -> Result<Value, EpisodeError> {
    let mut replica = WorldPhysics::build(spec, |_, _, _| Ok(()))?;
    let mut expert =
        libero_tasks::expert_for(task_id, behaviour, &replica.scene, replica.model()).map_err(|e| EpisodeError::Task(e.to_string()))?;
    replica.start(|_| {})?;
    for step in 1..=max_actions {
        let phase = expert.phase();
        let Some(a) = expert.act(&replica.sim) else { break };
        let a = quantize(a);
        replica.step(&a)?;
        let r = replica.sim.robot_state();
        let t = TraceStep { step, phase, action: a, eef_pos_in_world_m: r.eef_pos_in_world_m, gripper_qpos_m: r.gripper_qpos_m };
        trace(&t, &replica.sim);
    }
    serde_json::to_value(replica.evaluate()).map_err(|e| EpisodeError::Evaluator(e.to_string()))
}
