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
//! robosuite's two-pad test), `released_and_clear` (not grasped and the object's root at least `min_distance_m` from
//! the grip site, catalog §2.4), `lifted` (root z − z at reset > `above_m`), and `not`.
//!
//! Optional guards and rates (T25): `forbidden_contacts` latches a permanent failure the first tick any listed
//! object's body subtree touches a forbidden body's subtree (contact distance ≤ `max_distance_m`), recorded as
//! `<object>_touched_<label>`; it is checked first at every tick and stops all further tracking. With
//! `sample_substeps` the stage logic also runs after every physics substep (same rules at both rates).
//!
//! Completed stages are re-tested every control step: a completed stage whose conjunction stops holding is recorded
//! as a regression (event + count), and stays completed. For stages naming a `contact_body` (opening operations), the
//! sustained-contact ratio is recorded as a diagnostic: over the control steps the stage was current, the share of
//! steps inside gripper–handle contact runs of ≥ 5 steps (paper_results: SCR = N_sustained / N_exec).
use std::sync::Arc;

use libero_bddl::{Atom as BddlAtom, Pos};
use libero_sim::mujoco_rs::prelude::{MjModel, MjtObjBase};
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
/// T25's checker: strict stages, substep sampling and the bowl–table contact guard, all from the manifest params.
pub const CHECKER_BUFFER_ROTATION: &str = "private_ordered_buffer_rotation_and_tabletop_avoidance";

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
    ReleasedAndClear { object: String, min_distance_m: f64 },
    Lifted { object: String, above_m: f64 },
    Not(Box<AtomSpec>),
}

#[derive(Debug, Clone, Deserialize)]
pub struct StageParams {
    pub name: String,
    pub all: Vec<AtomSpec>,
    /// Body (subtree) whose contact with the gripper is monitored while this stage is current (opening operations).
    #[serde(default)]
    pub contact_body: Option<String>,
}

/// A contact that fails the run for good the first time it is seen (T25: a bowl touching the tabletop).
#[derive(Debug, Clone, Deserialize)]
pub struct ForbiddenContactParams {
    /// Instances none of whose body subtrees may touch `body`.
    pub objects: Vec<String>,
    /// MuJoCo body whose subtree is forbidden (e.g. the kitchen table's `table`).
    pub body: String,
    /// Names the latch `<object>_touched_<label>`.
    pub label: String,
    /// A contact counts when its distance (negative = penetration) is at most this.
    pub max_distance_m: f64,
}

#[derive(Debug, Clone, Deserialize)]
pub struct StagedParams {
    #[serde(default)]
    pub order: OrderMode,
    /// Also sample after every physics substep (not only at control steps).
    #[serde(default)]
    pub sample_substeps: bool,
    #[serde(default)]
    pub forbidden_contacts: Vec<ForbiddenContactParams>,
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
    ReleasedAndClear { instance: usize, min_distance_m: f64 },
    Lifted { body: usize, above_m: f64 },
    Not(Box<Check>),
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
            Check::ReleasedAndClear { instance, min_distance_m } => {
                c.commitment.released_and_clear(c.index, d, *instance, *min_distance_m)
            }
            Check::Lifted { body, above_m } => d.xpos()[*body][2] - c.base.body0.get(*body).map_or(0.0, |p| p[2]) > *above_m,
            Check::Not(inner) => !inner.holds(c),
        }
    }
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
        AtomSpec::ReleasedAndClear { object, min_distance_m } => Check::ReleasedAndClear {
            instance: index.instance(object).ok_or_else(|| scene_err("object", object))?,
            min_distance_m: *min_distance_m,
        },
        AtomSpec::Lifted { object, above_m } => Check::Lifted { body: instance_body(object)?, above_m: *above_m },
        AtomSpec::Not(inner) => Check::Not(Box::new(compile(inner, index, model)?)),
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

/// Which side of a forbidden-contact guard a geom is on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum GuardSide {
    Neither,
    /// In the body subtree of the guard's `objects[k]`.
    Object(usize),
    Forbidden,
}

/// A compiled [`ForbiddenContactParams`].
#[derive(Debug, Clone)]
struct ForbiddenContactGuard {
    objects: Vec<String>,
    label: String,
    max_distance_m: f64,
    /// geom id → side
    side: Vec<GuardSide>,
}

impl ForbiddenContactGuard {
    fn compile(p: &ForbiddenContactParams, index: &SceneIndex, model: &MjModel) -> Result<Self, TasksError> {
        let body_id = |name: &str| {
            model.name_to_id(MjtObjBase::mjOBJ_BODY, name).ok_or_else(|| TasksError::Scene(format!("forbidden contact: no body {name:?}")))
        };
        let forbidden = body_id(&p.body)?;
        let roots = p
            .objects
            .iter()
            .map(|o| {
                index.instance(o).map(|i| index.instances[i].body).ok_or_else(|| TasksError::Scene(format!("forbidden contact: no object {o:?}")))
            })
            .collect::<Result<Vec<_>, _>>()?;
        let (parents, geom_body) = (model.body_parentid(), model.geom_bodyid());
        let side = geom_body
            .iter()
            .map(|&b| {
                let b = b as usize;
                if in_subtree(parents, b, forbidden) {
                    GuardSide::Forbidden
                } else {
                    roots.iter().position(|&r| in_subtree(parents, b, r)).map_or(GuardSide::Neither, GuardSide::Object)
                }
            })
            .collect();
        Ok(Self { objects: p.objects.clone(), label: p.label.clone(), max_distance_m: p.max_distance_m, side })
    }

    /// The first listed object touching the forbidden body now, by contact order.
    fn touching(&self, contacts: impl IntoIterator<Item = ([usize; 2], f64)>) -> Option<usize> {
        contacts.into_iter().find_map(|([g1, g2], dist)| {
            if dist > self.max_distance_m {
                return None;
            }
            let side = |g: usize| self.side.get(g).copied().unwrap_or(GuardSide::Neither);
            match (side(g1), side(g2)) {
                (GuardSide::Object(k), GuardSide::Forbidden) | (GuardSide::Forbidden, GuardSide::Object(k)) => Some(k),
                _ => None,
            }
        })
    }

    fn latch_name(&self, object: usize) -> String {
        format!("{}_touched_{}", self.objects[object], self.label)
    }
}

/// The latched forbidden contact of a run.
#[derive(Debug, Clone, Serialize)]
struct ForbiddenContactLatch {
    name: String,
    object: String,
    tick: Tick,
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
    sample_substeps: bool,
    guards: Vec<ForbiddenContactGuard>,
    forbidden: Option<ForbiddenContactLatch>,
    control_steps: u64,
    substeps: u64,
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
        let guards =
            params.forbidden_contacts.iter().map(|g| ForbiddenContactGuard::compile(g, &index, model)).collect::<Result<Vec<_>, _>>()?;
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
            sample_substeps: params.sample_substeps,
            guards,
            forbidden: None,
            control_steps: 0,
            substeps: 0,
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

    /// The contact monitor of the current operation (control steps only: its ratio counts control steps).
    fn observe_monitor(&mut self, data: &SimData) {
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
    }

    /// Advances the stages; at control steps (`control`) also re-tests the completed ones for regressions (a
    /// diagnostic: at substep rate it would count every substep of contact chatter while a released object settles).
    fn observe_ordered(&mut self, data: &SimData, tick: Tick, control: bool) {
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
        if control {
            self.tracker.track_regressions(tick, |i| stages[i].holds(&ctx));
        }
    }

    /// Latches the first forbidden contact (checked before anything else at every tick); true once latched, when
    /// all further tracking stops.
    fn forbidden_contact_latched(&mut self, data: &SimData, tick: Tick) -> bool {
        if self.forbidden.is_some() {
            return true;
        }
        let contacts = || data.contact().iter().map(|c| ([c.geom[0] as usize, c.geom[1] as usize], c.dist));
        let Some((name, object)) =
            self.guards.iter().find_map(|g| g.touching(contacts()).map(|k| (g.latch_name(k), g.objects[k].clone())))
        else {
            return false;
        };
        self.events.push(PrivateEvent { subject: Some(name.clone()), ..PrivateEvent::new(EventKind::ForbiddenContact, tick) });
        self.forbidden = Some(ForbiddenContactLatch { name, object, tick });
        true
    }

    /// One sample of the stage logic (control step or substep).
    fn sample(&mut self, data: &SimData, tick: Tick, control: bool) {
        if self.forbidden_contact_latched(data, tick) {
            return;
        }
        if self.order == OrderMode::Unordered {
            self.observe_unordered(data, tick);
        } else {
            self.observe_ordered(data, tick, control);
        }
    }
}

impl Evaluator for StagedEvaluator {
    fn checker(&self) -> &str {
        &self.checker
    }

    fn samples_substeps(&self) -> bool {
        self.sample_substeps
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
        self.substeps = 0;
        self.forbidden = None;
        self.commitment.reset(&self.index, data);
        let ctx = Ctx { index: &self.index, commitment: &self.commitment, base: &self.base, data };
        self.holding = self.stages.iter().map(|s| s.holds(&ctx)).collect();
        self.initial_goal_count = self.holding[..self.n_required].iter().filter(|&&h| h).count();
        self.max_goal_count = self.initial_goal_count;
        let _ = tick;
    }

    fn observe_substep(&mut self, data: &SimData, tick: Tick) {
        if self.sample_substeps {
            self.substeps += 1;
            self.sample(data, tick, false);
        }
    }

    fn observe_control_step(&mut self, data: &SimData, tick: Tick) {
        self.control_steps += 1;
        if self.forbidden.is_none() && self.order != OrderMode::Unordered {
            self.observe_monitor(data);
        }
        self.sample(data, tick, true);
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
            if let Some(label) = self.tracker.order_violation_label() {
                details.insert("order_violation_latch".into(), json!(label));
            }
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
        if !self.guards.is_empty() {
            details.insert("forbidden_contact".into(), json!(self.forbidden));
        }
        record.details = Some(serde_json::Value::Object(details));
        record.success = stages_ok && record.terminal_state_success && self.forbidden.is_none();
        record.failure_reason = if record.success {
            None
        } else if self.forbidden.is_some() {
            Some(FailureReason::ForbiddenContact)
        } else if self.tracker.order_violated() {
            Some(FailureReason::OrderViolation)
        } else if !stages_ok {
            Some(FailureReason::IncompleteStage)
        } else {
            Some(FailureReason::TerminalStateInvalid)
        };
        crate::pour::fill_history(&mut record, (self.control_steps, self.substeps), &self.events, &self.commitment, &self.goal, data);
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

    fn guard() -> ForbiddenContactGuard {
        use GuardSide::*;
        ForbiddenContactGuard {
            objects: vec!["bowl_a".into(), "bowl_b".into()],
            label: "tabletop".into(),
            max_distance_m: 1e-3,
            side: vec![Neither, Object(0), Object(1), Forbidden, Forbidden],
        }
    }

    #[test]
    fn forbidden_contact_needs_a_listed_object_against_the_forbidden_body_within_the_distance() {
        let g = guard();
        assert_eq!(g.touching([([1, 2], -0.01), ([0, 3], -0.01), ([3, 4], -0.01)]), None, "bowl–bowl, other–table: allowed");
        assert_eq!(g.touching([([3, 2], 0.0011)]), None, "a contact farther than 1 mm does not count");
        assert_eq!(g.touching([([3, 2], 0.001)]), Some(1), "at the limit it counts, either geom order");
        assert_eq!(g.touching([([0, 4], -0.02), ([1, 4], -0.002)]), Some(0));
        assert_eq!(g.touching([([99, 3], -0.02)]), None, "unknown geoms are neither side");
        assert_eq!(g.latch_name(1), "bowl_b_touched_tabletop");
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
        assert!(!p.sample_substeps && p.forbidden_contacts.is_empty(), "both default off");
    }

    #[test]
    fn guard_rate_and_release_atom_parse_from_manifest_json() {
        let p: StagedParams = serde_json::from_value(json!({
            "order": "strict",
            "sample_substeps": true,
            "forbidden_contacts": [{"objects": ["a", "b"], "body": "table", "label": "tabletop", "max_distance_m": 0.001}],
            "stages": [{"name": "01", "all": [{"released_and_clear": {"object": "a", "min_distance_m": 0.055}}]}]
        }))
        .unwrap();
        assert!(p.sample_substeps);
        assert_eq!(p.forbidden_contacts[0].objects, ["a", "b"]);
        assert!(matches!(&p.stages[0].all[0], AtomSpec::ReleasedAndClear { object, min_distance_m } if object == "a" && *min_distance_m == 0.055));
    }
}
