//! Generic staged evaluator driven by manifest parameters (task catalog §1.4, §1.4a, §2.4): a list of stages, each a
//! conjunction of atoms, evaluated at control rate in one of three order modes, plus terminal checks at finish.
//!
//! * `ordered` — the RoboMemArena ordered evaluator: only the current stage is tested each control step (at most one
//!   stage per step); a later stage that already holds completes as soon as it becomes current (T23, T26, T27).
//! * `strict` — `_StrictPredicateSequence`: before the current stage every later stage is tested; one that already
//!   holds latches an ordering violation (permanent failure).
//! * `unordered` — the cooking goal evaluator (T21, T22): K goals, completed = goals true on the final state; the
//!   initial and maximum goal counts and every change of the satisfied set are recorded.
//!
//! Atoms: a LIBERO predicate (`{"bddl": ["on", "moka_pot_1", "flat_stove_2_cook_region"]}`), or one of the
//! RoboMemArena checks: `near` (object root within `xy_max_m` horizontally of an anchor body or site, height
//! difference inside `dz_range_m`), `drawer_open` / `drawer_closed` (world-y displacement of a drawer's region site
//! from its value at reset above / below a threshold, catalog §2.2), `in_box` (RoboMemArena box rule: site box with
//! half-extent |R·size|, lower z extended by `lower_z_m`, upper by `upper_z_m`), `released` (not grasped by
//! robosuite's two-pad test), `lifted` (root z − z at reset > `above_m`), `joint` (a joint's position, or its
//! magnitude, strictly inside `(min, max)`: rad for hinges, m for slides — T28's latch), `not`, and `any` (a
//! disjunction).
//!
//! Completed stages are re-tested every control step: a completed stage whose conjunction stops holding is recorded
//! as a regression (event + count), and stays completed. For stages naming a `contact_body` (opening operations), the
//! sustained-contact ratio is recorded as a diagnostic: over the control steps the stage was current, the share of
//! steps inside gripper–handle contact runs of ≥ 5 steps (paper_results: SCR = N_sustained / N_exec).
use std::sync::Arc;

use libero_bddl::{Atom as BddlAtom, Pos};
use libero_sim::mujoco_rs::prelude::{MjModel, MjtJoint, MjtObjBase};
use libero_sim::simulation::SimData;
use serde::{Deserialize, Serialize};
use serde_json::json;

use crate::TasksError;
use crate::commitment::CommitmentTracker;
use crate::evaluator::{
    EvaluationRecord, EventKind, Evaluator, FailureReason, PrivateEvent, StageRegressions, StageSpec, StageTracker,
    TerminalCheck, Tick, score_percent,
};
use crate::goal::GoalChecker;
use crate::predicates::{CompiledAtom, EntityRef, SceneIndex, in_subtree};

pub const CHECKER_ORDERED: &str = "private_ordered_stages";
pub const CHECKER_UNORDERED: &str = "private_unordered_goal_predicates";

/// Minimum contact run (control steps) that counts as sustained.
pub const SUSTAINED_RUN_STEPS: u32 = 5;

#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum OrderMode {
    #[default]
    Ordered,
    Strict,
    Unordered,
}

/// One atom of a stage or terminal conjunction.
#[derive(Debug, Clone, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AtomSpec {
    /// `[predicate, arg…]`, a LIBERO predicate.
    Bddl(Vec<String>),
    Near { object: String, anchor: String, xy_max_m: f64, dz_range_m: [f64; 2] },
    DrawerOpen { site: String, min_displacement_m: f64 },
    DrawerClosed { site: String, max_displacement_m: f64 },
    InBox { object: String, site: String, lower_z_m: f64, upper_z_m: f64 },
    Released(String),
    Lifted { object: String, above_m: f64 },
    /// A joint's position (rad for hinges, m for slides) strictly above `min` and below `max` where given; with
    /// `abs`, its magnitude (a handle that unlatches turned either way).
    Joint {
        name: String,
        #[serde(default)]
        min: Option<f64>,
        #[serde(default)]
        max: Option<f64>,
        #[serde(default)]
        abs: bool,
    },
    Not(Box<AtomSpec>),
    /// True when at least one inner atom holds.
    Any(Vec<AtomSpec>),
}

#[derive(Debug, Clone, Deserialize)]
pub struct StageParams {
    pub name: String,
    pub all: Vec<AtomSpec>,
    /// Body (subtree) whose contact with the gripper is monitored while this stage is current (opening operations).
    #[serde(default)]
    pub contact_body: Option<String>,
}

#[derive(Debug, Clone, Deserialize)]
pub struct StagedParams {
    #[serde(default)]
    pub order: OrderMode,
    pub stages: Vec<StageParams>,
    /// Reported but not counted toward K nor required for success.
    #[serde(default)]
    pub optional_stages: Vec<StageParams>,
    /// Checks on the final state, all required for success.
    #[serde(default)]
    pub terminal: Vec<StageParams>,
}

/// A compiled atom.
#[derive(Debug, Clone)]
enum Check {
    Bddl(CompiledAtom),
    Near { body: usize, anchor: Anchor, xy_max_m: f64, dz: [f64; 2] },
    Drawer { site: usize, open: bool, threshold_m: f64 },
    InBox { body: usize, site: usize, half_m: [f64; 3], lower_z_m: f64, upper_z_m: f64 },
    Released(usize),
    Lifted { body: usize, above_m: f64 },
    Joint { qpos_adr: usize, min: Option<f64>, max: Option<f64>, abs: bool },
    Not(Box<Check>),
    Any(Vec<Check>),
}

#[derive(Debug, Clone, Copy)]
enum Anchor {
    Body(usize),
    Site(usize),
}

/// Per-episode baselines the atoms read.
#[derive(Debug, Clone, Default)]
struct Baseline {
    /// site id → world position at reset
    site0: Vec<[f64; 3]>,
    /// body id → world position at reset
    body0: Vec<[f64; 3]>,
}

struct Ctx<'a> {
    index: &'a SceneIndex,
    commitment: &'a CommitmentTracker,
    base: &'a Baseline,
    data: &'a SimData,
}

impl Check {
    fn holds(&self, c: &Ctx) -> bool {
        let d = c.data;
        match self {
            Check::Bddl(a) => a.evaluate(c.index, d),
            Check::Near { body, anchor, xy_max_m, dz } => {
                let p = d.xpos()[*body];
                let q = match anchor {
                    Anchor::Body(b) => d.xpos()[*b],
                    Anchor::Site(s) => d.site_xpos()[*s],
                };
                let dz_now = p[2] - q[2];
                (p[0] - q[0]).hypot(p[1] - q[1]) < *xy_max_m && dz_now > dz[0] && dz_now < dz[1]
            }
            Check::Drawer { site, open, threshold_m } => {
                let dy = (d.site_xpos()[*site][1] - c.base.site0.get(*site).map_or(0.0, |p| p[1])).abs();
                if *open { dy > *threshold_m } else { dy < *threshold_m }
            }
            Check::InBox { body, site, half_m, lower_z_m, upper_z_m } => {
                let p = d.xpos()[*body];
                let ctr = d.site_xpos()[*site];
                let m = d.site_xmat()[*site];
                (0..3).all(|k| {
                    let h = (m[3 * k] * half_m[0] + m[3 * k + 1] * half_m[1] + m[3 * k + 2] * half_m[2]).abs();
                    let (lo, hi) = if k == 2 { (ctr[k] - h - lower_z_m, ctr[k] + h + upper_z_m) } else { (ctr[k] - h, ctr[k] + h) };
                    p[k] > lo && p[k] < hi
                })
            }
            Check::Released(i) => !c.commitment.grasped(c.index, d, *i),
            Check::Lifted { body, above_m } => d.xpos()[*body][2] - c.base.body0.get(*body).map_or(0.0, |p| p[2]) > *above_m,
            Check::Joint { qpos_adr, min, max, abs } => {
                let q = d.qpos()[*qpos_adr];
                joint_inside(if *abs { q.abs() } else { q }, *min, *max)
            }
            Check::Not(inner) => !inner.holds(c),
            Check::Any(inner) => inner.iter().any(|a| a.holds(c)),
        }
    }
}

/// `min < q < max`, each bound only where given.
fn joint_inside(q: f64, min: Option<f64>, max: Option<f64>) -> bool {
    min.is_none_or(|m| q > m) && max.is_none_or(|m| q < m)
}

fn compile(spec: &AtomSpec, index: &SceneIndex, model: &MjModel) -> Result<Check, TasksError> {
    let scene_err = |what: &str, name: &str| TasksError::Scene(format!("{CHECKER_ORDERED}: no {what} {name:?}"));
    let instance_body = |name: &str| -> Result<usize, TasksError> {
        index.instance(name).map(|i| index.instances[i].body).ok_or_else(|| scene_err("object or fixture", name))
    };
    let site = |name: &str| model.name_to_id(MjtObjBase::mjOBJ_SITE, name).ok_or_else(|| scene_err("site", name));
    Ok(match spec {
        AtomSpec::Bddl(words) => {
            let (predicate, args) = words.split_first().ok_or_else(|| scene_err("predicate in", "[]"))?;
            let atom = BddlAtom { predicate: predicate.to_ascii_lowercase(), args: args.to_vec(), pos: Pos::default() };
            Check::Bddl(CompiledAtom::compile(index, &atom)?)
        }
        AtomSpec::Near { object, anchor, xy_max_m, dz_range_m } => {
            let anchor = match index.instance(anchor) {
                Some(i) => Anchor::Body(index.instances[i].body),
                None => Anchor::Site(site(anchor)?),
            };
            Check::Near { body: instance_body(object)?, anchor, xy_max_m: *xy_max_m, dz: *dz_range_m }
        }
        AtomSpec::DrawerOpen { site: s, min_displacement_m } => {
            Check::Drawer { site: site(s)?, open: true, threshold_m: *min_displacement_m }
        }
        AtomSpec::DrawerClosed { site: s, max_displacement_m } => {
            Check::Drawer { site: site(s)?, open: false, threshold_m: *max_displacement_m }
        }
        AtomSpec::InBox { object, site: s, lower_z_m, upper_z_m } => {
            let half_m = match index.resolve(s) {
                Some(EntityRef::Region(r)) => index.regions[r].half_size_m,
                _ => return Err(scene_err("BDDL region site (declared size needed)", s)),
            };
            Check::InBox { body: instance_body(object)?, site: site(s)?, half_m, lower_z_m: *lower_z_m, upper_z_m: *upper_z_m }
        }
        AtomSpec::Released(object) => Check::Released(index.instance(object).ok_or_else(|| scene_err("object", object))?),
        AtomSpec::Lifted { object, above_m } => Check::Lifted { body: instance_body(object)?, above_m: *above_m },
        AtomSpec::Joint { name, min, max, abs } => {
            let j = model.name_to_id(MjtObjBase::mjOBJ_JOINT, name).ok_or_else(|| scene_err("joint", name))?;
            if !matches!(model.jnt_type()[j], MjtJoint::mjJNT_HINGE | MjtJoint::mjJNT_SLIDE) {
                return Err(scene_err("hinge or slide joint", name));
            }
            Check::Joint { qpos_adr: model.jnt_qposadr()[j] as usize, min: *min, max: *max, abs: *abs }
        }
        AtomSpec::Not(inner) => Check::Not(Box::new(compile(inner, index, model)?)),
        AtomSpec::Any(inner) => Check::Any(inner.iter().map(|a| compile(a, index, model)).collect::<Result<_, _>>()?),
    })
}

#[derive(Debug, Clone)]
struct Stage {
    name: String,
    all: Vec<Check>,
    contact_body: Option<usize>,
}

impl Stage {
    fn compile(p: &StageParams, index: &SceneIndex, model: &MjModel) -> Result<Self, TasksError> {
        let all = p.all.iter().map(|a| compile(a, index, model)).collect::<Result<Vec<_>, _>>()?;
        let contact_body = match &p.contact_body {
            Some(b) => Some(
                model
                    .name_to_id(MjtObjBase::mjOBJ_BODY, b)
                    .ok_or_else(|| TasksError::Scene(format!("{CHECKER_ORDERED}: no body {b:?}")))?,
            ),
            None => None,
        };
        Ok(Self { name: p.name.clone(), all, contact_body })
    }

    fn holds(&self, c: &Ctx) -> bool {
        self.all.iter().all(|a| a.holds(c))
    }
}

/// Gripper–handle contact over one operation (the control steps a monitored stage was current).
#[derive(Debug, Clone, Default, Serialize)]
pub struct ContactMonitor {
    pub stage_name: String,
    pub exec_steps: u32,
    /// Lengths of the contact runs, in order.
    pub runs: Vec<u32>,
    #[serde(skip)]
    current_run: u32,
}

impl ContactMonitor {
    fn step(&mut self, contact: bool) {
        self.exec_steps += 1;
        if contact {
            self.current_run += 1;
        } else if self.current_run > 0 {
            self.runs.push(self.current_run);
            self.current_run = 0;
        }
    }

    fn close(&mut self) {
        if self.current_run > 0 {
            self.runs.push(self.current_run);
            self.current_run = 0;
        }
    }

    /// Steps inside runs of ≥ [`SUSTAINED_RUN_STEPS`].
    pub fn sustained_steps(&self) -> u32 {
        self.runs.iter().chain((self.current_run > 0).then_some(&self.current_run)).filter(|&&r| r >= SUSTAINED_RUN_STEPS).sum()
    }

    pub fn ratio_percent(&self) -> f64 {
        if self.exec_steps == 0 { 0.0 } else { 100.0 * f64::from(self.sustained_steps()) / f64::from(self.exec_steps) }
    }
}

pub struct StagedEvaluator {
    checker: String,
    order: OrderMode,
    index: Arc<SceneIndex>,
    goal: GoalChecker,
    commitment: CommitmentTracker,
    task_id: Option<String>,
    /// required stages, then optional ones
    stages: Vec<Stage>,
    n_required: usize,
    terminal: Vec<Stage>,
    gripper_bodies: Vec<bool>,
    body_parent: Vec<i32>,
    geom_body: Vec<usize>,
    base: Baseline,
    tracker: StageTracker,
    /// unordered mode: which goals hold now, and the log of changes
    holding: Vec<bool>,
    unordered_regressions: Vec<u32>,
    initial_goal_count: usize,
    max_goal_count: usize,
    unordered_events: Vec<PrivateEvent>,
    monitors: Vec<ContactMonitor>,
    monitor_open: Option<(usize, usize)>,
    events: Vec<PrivateEvent>,
    control_steps: u64,
}

impl StagedEvaluator {
    pub fn new(
        checker: &str,
        params: StagedParams,
        goal: GoalChecker,
        commitment: CommitmentTracker,
        model: &MjModel,
        task_id: Option<String>,
    ) -> Result<Self, TasksError> {
        let index = goal.index().clone();
        let mut stages = params.stages.iter().map(|s| Stage::compile(s, &index, model)).collect::<Result<Vec<_>, _>>()?;
        let n_required = stages.len();
        for s in &params.optional_stages {
            stages.push(Stage::compile(s, &index, model)?);
        }
        let terminal = params.terminal.iter().map(|s| Stage::compile(s, &index, model)).collect::<Result<Vec<_>, _>>()?;
        let nbody = model.ffi().nbody as usize;
        let gripper_bodies = (0..nbody)
            .map(|b| model.id_to_name(MjtObjBase::mjOBJ_BODY, b).is_some_and(|n| n.starts_with("gripper0_")))
            .collect();
        let n = stages.len();
        let specs = Self::specs(&stages, n_required);
        Ok(Self {
            checker: checker.to_owned(),
            order: if checker == CHECKER_UNORDERED { OrderMode::Unordered } else { params.order },
            index,
            goal,
            commitment,
            task_id,
            stages,
            n_required,
            terminal,
            gripper_bodies,
            body_parent: model.body_parentid().to_vec(),
            geom_body: model.geom_bodyid().iter().map(|&b| b as usize).collect(),
            base: Baseline::default(),
            tracker: StageTracker::new(specs),
            holding: vec![false; n],
            unordered_regressions: vec![0; n],
            initial_goal_count: 0,
            max_goal_count: 0,
            unordered_events: Vec::new(),
            monitors: Vec::new(),
            monitor_open: None,
            events: Vec::new(),
            control_steps: 0,
        })
    }

    fn specs(stages: &[Stage], n_required: usize) -> Vec<StageSpec> {
        stages.iter().enumerate().map(|(i, s)| StageSpec { name: s.name.clone(), required: i < n_required }).collect()
    }

    fn gripper_touches(&self, data: &SimData, body: usize) -> bool {
        data.contact().iter().any(|c| {
            let (b1, b2) = (self.geom_body[c.geom[0] as usize], self.geom_body[c.geom[1] as usize]);
            (self.gripper_bodies[b1] && in_subtree(&self.body_parent, b2, body))
                || (self.gripper_bodies[b2] && in_subtree(&self.body_parent, b1, body))
        })
    }

    fn stage_event(&self, kind: EventKind, tick: Tick, i: usize) -> PrivateEvent {
        PrivateEvent { stage_index: Some(i), stage_name: Some(self.stages[i].name.clone()), ..PrivateEvent::new(kind, tick) }
    }

    fn observe_unordered(&mut self, data: &SimData, tick: Tick) {
        let ctx = Ctx { index: &self.index, commitment: &self.commitment, base: &self.base, data };
        let now: Vec<bool> = self.stages.iter().map(|s| s.holds(&ctx)).collect();
        for (i, &h) in now.iter().enumerate() {
            if h != self.holding[i] {
                let kind = if h { EventKind::StageCompleted } else { EventKind::StageRegressed };
                if !h {
                    self.unordered_regressions[i] += 1;
                }
                let e = self.stage_event(kind, tick, i);
                self.unordered_events.push(e);
            }
        }
        self.holding = now;
        let count = self.holding[..self.n_required].iter().filter(|&&h| h).count();
        self.max_goal_count = self.max_goal_count.max(count);
    }

    fn observe_ordered(&mut self, data: &SimData, tick: Tick) {
        // contact monitor of the current operation
        let current = self.tracker.current();
        if let Some((stage, _)) = self.monitor_open
            && current != Some(stage)
        {
            if let Some((_, m)) = self.monitor_open.take() {
                self.monitors[m].close();
            }
        }
        if let Some(i) = current
            && let Some(body) = self.stages[i].contact_body
        {
            if self.monitor_open.is_none() {
                self.monitors.push(ContactMonitor { stage_name: self.stages[i].name.clone(), ..Default::default() });
                self.monitor_open = Some((i, self.monitors.len() - 1));
            }
            let contact = self.gripper_touches(data, body);
            if let Some((_, m)) = self.monitor_open {
                self.monitors[m].step(contact);
            }
        }
        let ctx = Ctx { index: &self.index, commitment: &self.commitment, base: &self.base, data };
        let stages = &self.stages;
        match self.order {
            OrderMode::Strict => {
                self.tracker.advance_strict(tick, |i| stages[i].holds(&ctx));
            }
            _ => {
                self.tracker.advance(tick, |i| stages[i].holds(&ctx));
            }
        }
        self.tracker.track_regressions(tick, |i| stages[i].holds(&ctx));
    }
}

impl Evaluator for StagedEvaluator {
    fn checker(&self) -> &str {
        &self.checker
    }

    fn reset(&mut self, data: &SimData, tick: Tick) {
        self.base = Baseline { site0: data.site_xpos().to_vec(), body0: data.xpos().to_vec() };
        self.tracker = StageTracker::new(Self::specs(&self.stages, self.n_required));
        self.monitors.clear();
        self.monitor_open = None;
        self.events.clear();
        self.unordered_events.clear();
        self.unordered_regressions.iter_mut().for_each(|r| *r = 0);
        self.control_steps = 0;
        self.commitment.reset(&self.index, data);
        let ctx = Ctx { index: &self.index, commitment: &self.commitment, base: &self.base, data };
        self.holding = self.stages.iter().map(|s| s.holds(&ctx)).collect();
        self.initial_goal_count = self.holding[..self.n_required].iter().filter(|&&h| h).count();
        self.max_goal_count = self.initial_goal_count;
        let _ = tick;
    }

    fn observe_control_step(&mut self, data: &SimData, tick: Tick) {
        self.control_steps += 1;
        if self.order == OrderMode::Unordered {
            self.observe_unordered(data, tick);
        } else {
            self.observe_ordered(data, tick);
        }
        if let Some(e) = self.commitment.observe_event(&self.index, data, tick) {
            self.events.push(e);
        }
    }

    fn finish(&mut self, data: &SimData, _tick: Tick) -> EvaluationRecord {
        let mut record = EvaluationRecord::new(self.checker.clone());
        record.task_id = self.task_id.clone();
        let ctx = Ctx { index: &self.index, commitment: &self.commitment, base: &self.base, data };
        record.terminal_state_checks =
            self.terminal.iter().map(|t| TerminalCheck { name: t.name.clone(), passed: t.holds(&ctx) }).collect();
        record.terminal_state_success = record.terminal_state_checks.iter().all(|c| c.passed);
        let mut details = serde_json::Map::new();
        details.insert("order".into(), json!(self.order));
        let stages_ok;
        if self.order == OrderMode::Unordered {
            let now: Vec<bool> = self.stages.iter().map(|s| s.holds(&ctx)).collect();
            let names = |f: &dyn Fn(usize) -> bool| -> Vec<String> {
                (0..self.stages.len()).filter(|&i| f(i)).map(|i| self.stages[i].name.clone()).collect()
            };
            record.required_stage_count = self.n_required;
            record.completed_required_stage_count = now[..self.n_required].iter().filter(|&&h| h).count();
            record.stage_score_percent = score_percent(record.completed_required_stage_count, self.n_required);
            record.ordered_stage_names = names(&|i| i < self.n_required);
            record.optional_stage_names = names(&|i| i >= self.n_required);
            record.completed_stage_names = names(&|i| now[i]);
            record.stage_regressions = (0..self.stages.len())
                .filter(|&i| self.unordered_regressions[i] > 0)
                .map(|i| StageRegressions { stage_name: self.stages[i].name.clone(), count: self.unordered_regressions[i] })
                .collect();
            record.stage_events = self.unordered_events.clone();
            stages_ok = record.completed_required_stage_count == self.n_required;
            details.insert("initial_goal_count".into(), json!(self.initial_goal_count));
            details.insert("max_goal_count".into(), json!(self.max_goal_count));
            details.insert("regressed_from_max".into(), json!(record.completed_required_stage_count < self.max_goal_count));
        } else {
            self.tracker.write_into(&mut record);
            stages_ok = self.tracker.all_required_completed() && !self.tracker.order_violated();
            details.insert("order_violation".into(), json!(self.tracker.order_violated()));
        }
        if let Some((_, m)) = self.monitor_open.take() {
            self.monitors[m].close();
        }
        if !self.monitors.is_empty() {
            let ops: Vec<_> = self
                .monitors
                .iter()
                .map(|m| {
                    json!({"stage_name": m.stage_name, "exec_steps": m.exec_steps, "contact_runs": m.runs,
                        "sustained_steps": m.sustained_steps(), "sustained_contact_ratio_percent": m.ratio_percent()})
                })
                .collect();
            details.insert("opening_operations".into(), json!(ops));
        }
        record.details = Some(serde_json::Value::Object(details));
        record.success = stages_ok && record.terminal_state_success;
        record.failure_reason = if record.success {
            None
        } else if self.tracker.order_violated() {
            Some(FailureReason::OrderViolation)
        } else if !stages_ok {
            Some(FailureReason::IncompleteStage)
        } else {
            Some(FailureReason::TerminalStateInvalid)
        };
        crate::pour::fill_history(&mut record, (self.control_steps, 0), &self.events, &self.commitment, &self.goal, data);
        record
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sustained_contact_counts_only_runs_of_five_or_more() {
        let mut m = ContactMonitor::default();
        for c in [true, true, false, true, true, true, true, true, false, false, true] {
            m.step(c);
        }
        m.close();
        assert_eq!(m.runs, [2, 5, 1]);
        assert_eq!(m.sustained_steps(), 5);
        assert!((m.ratio_percent() - 100.0 * 5.0 / 11.0).abs() < 1e-12);
    }

    #[test]
    fn joint_bounds_are_strict_and_optional() {
        assert!(joint_inside(0.31, Some(0.3), None));
        assert!(!joint_inside(0.3, Some(0.3), None));
        assert!(joint_inside(-5.0, None, Some(0.01)));
        assert!(!joint_inside(0.01, None, Some(0.01)));
        assert!(joint_inside(0.5, Some(0.4), Some(0.6)) && !joint_inside(0.7, Some(0.4), Some(0.6)));
        assert!(joint_inside(1.0, None, None));
    }

    #[test]
    fn joint_and_any_atoms_parse() {
        let p: StagedParams = serde_json::from_value(json!({
            "stages": [{"name": "01", "all": [{"any": [
                {"joint": {"name": "d_latch_joint", "min": 1.1, "abs": true}},
                {"joint": {"name": "d_hinge", "min": 0.05}}]}], "contact_body": "d_latch"}]
        }))
        .unwrap();
        let AtomSpec::Any(inner) = &p.stages[0].all[0] else { panic!("not an any atom") };
        assert!(matches!(&inner[0], AtomSpec::Joint { min: Some(m), max: None, abs: true, .. } if *m == 1.1));
        assert!(matches!(&inner[1], AtomSpec::Joint { abs: false, .. }));
    }

    #[test]
    fn params_parse_from_manifest_json() {
        let p: StagedParams = serde_json::from_value(json!({
            "order": "strict",
            "stages": [{"name": "01", "all": [{"bddl": ["on", "a", "b"]}, {"released": "a"}], "contact_body": "x"},
                       {"name": "02", "all": [{"not": {"drawer_open": {"site": "s", "min_displacement_m": 0.1}}}]}],
            "terminal": [{"name": "t", "all": [{"near": {"object": "a", "anchor": "c", "xy_max_m": 0.3, "dz_range_m": [0.1, 0.3]}}]}]
        }))
        .unwrap();
        assert_eq!(p.order, OrderMode::Strict);
        assert_eq!(p.stages.len(), 2);
        assert!(matches!(p.stages[1].all[0], AtomSpec::Not(_)));
    }
}
