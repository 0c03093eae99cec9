//! The staged evaluator: compiles the params, samples the stages in their order mode with the monitors, and judges.
use libero_sim::mujoco_rs::prelude::{MjModel, MjtObjBase};
use libero_sim::simulation::SimData;
use serde_json::json;

use crate::TasksError;
use crate::judge::commitment::CommitmentTracker;
use crate::judge::evaluator::{
    EvaluationRecord, EventKind, Evaluator, FailureReason, PrivateEvent, StageSpec, StageTracker, TerminalCheck, Tick,
};
use crate::judge::family::History;
use crate::judge::goal::GoalChecker;
use crate::judge::mechanism::{ContactMonitor, GripperContact, OperationKind, PendingOpening, Watched, Window, body_names};
use crate::judge::pouring::PourTracker;
use crate::judge::staged::CHECKER_UNORDERED;
use crate::judge::staged::compile::{
    Baseline, Binding, BodySource, Ctx, Names, PourSlot, Stage, compile, instance_body, require_opening_handles, scene_err,
    site_id, stages_names,
};
use crate::judge::staged::lang::{OrderMode, StagedParams};
use crate::judge::staged::monitor::{FailureMonitor, ForbiddenContactGuard, ForbiddenContactLatch, GoalSetTracker};

pub struct StagedEvaluator {
    checker: String,
    order: OrderMode,
    /// The bookkeeping every evaluator shares ([`crate::judge::family::History`]).
    history: History,
    /// required stages, then optional ones
    stages: Vec<Stage>,
    n_required: usize,
    terminal: Vec<Stage>,
    gripper: GripperContact,
    site_names: Vec<String>,
    /// site id → the body carrying it (a drawer's region site moves with the drawer)
    site_body: Vec<usize>,
    /// body id → name, for the operations' records
    body_name: Vec<String>,
    /// stage → the bodies of its operation, resolved at reset (bindings are bound then)
    operation_bodies: Vec<Vec<usize>>,
    base: Baseline,
    bindings: Vec<Binding>,
    pours: Vec<PourSlot>,
    failures: Vec<FailureMonitor>,
    tracker: StageTracker,
    /// unordered mode: the satisfied-goal set over the episode
    goals: GoalSetTracker,
    /// (stage, monitor) of every ordered-mode operation so far
    monitors: Vec<(usize, ContactMonitor)>,
    monitor_open: Option<(usize, usize)>,
    /// unordered mode: (stage, its opening) for every stage that opens a mechanism
    pending_openings: Vec<(usize, PendingOpening)>,
    sample_substeps: bool,
    guards: Vec<ForbiddenContactGuard>,
    forbidden: Option<ForbiddenContactLatch>,
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
        let bindings = params
            .bindings
            .iter()
            .map(|b| {
                let sites = b.sites.iter().map(|s| site_id(model, s)).collect::<Result<Vec<_>, _>>()?;
                if sites.is_empty() {
                    return Err(scene_err("candidate site in binding", &b.name));
                }
                Ok(Binding { name: b.name.clone(), probe_body: instance_body(&index, &b.nearest_to)?, sites })
            })
            .collect::<Result<Vec<_>, TasksError>>()?;
        let pours = params
            .pour_counters
            .iter()
            .map(|p| {
                Ok(PourSlot {
                    params: p.clone(),
                    bottle_body: instance_body(&index, &p.bottle)?,
                    target_site: site_id(model, &p.target_site)?,
                    tracker: None,
                })
            })
            .collect::<Result<Vec<_>, TasksError>>()?;
        let binding_names: Vec<String> = params.bindings.iter().map(|b| b.name.clone()).collect();
        let counter_names: Vec<String> = params.pour_counters.iter().map(|p| p.name.clone()).collect();
        let stage_names: Vec<String> = params.stages.iter().chain(&params.optional_stages).map(|s| s.name.clone()).collect();
        let names = Names { index: &index, model, bindings: &binding_names, counters: &counter_names, stages: &stage_names };
        let mut stages = params.stages.iter().map(|s| Stage::compile(s, &names)).collect::<Result<Vec<_>, _>>()?;
        let n_required = stages.len();
        for s in &params.optional_stages {
            stages.push(Stage::compile(s, &names)?);
        }
        let terminal = params.terminal.iter().map(|s| Stage::compile(s, &names)).collect::<Result<Vec<_>, _>>()?;
        let failures = params
            .failures
            .iter()
            .map(|f| {
                Ok(FailureMonitor {
                    name: f.name.clone(),
                    after_stage: stages.iter().position(|s| s.name == f.after_stage).ok_or_else(|| scene_err("stage", &f.after_stage))?,
                    when: compile(&f.when, &names)?,
                    reason: f.reason,
                    latched_at: None,
                })
            })
            .collect::<Result<Vec<_>, TasksError>>()?;
        let guards =
            params.forbidden_contacts.iter().map(|g| ForbiddenContactGuard::compile(g, &index, model)).collect::<Result<Vec<_>, _>>()?;
        let gripper = GripperContact::new(&index, model)?;
        require_opening_handles(&stages, &bindings, &gripper, model)?;
        let nbody = model.ffi().nbody as usize;
        let specs = Self::specs(&stages, n_required);
        let goals = GoalSetTracker::new(stages_names(&stages), n_required);
        Ok(Self {
            checker: checker.to_owned(),
            order: if checker == CHECKER_UNORDERED { OrderMode::Unordered } else { params.order },
            history: History::new(goal, commitment, task_id),
            stages,
            n_required,
            terminal,
            gripper,
            site_names: (0..model.ffi().nsite as usize).map(|s| model.id_to_name(MjtObjBase::mjOBJ_SITE, s).unwrap_or_default().to_owned()).collect(),
            site_body: model.site_bodyid().iter().map(|&b| b as usize).collect(),
            body_name: body_names(model, &(0..nbody).collect::<Vec<_>>()),
            operation_bodies: Vec::new(),
            base: Baseline::default(),
            bindings,
            pours,
            failures,
            tracker: StageTracker::new(specs),
            goals,
            monitors: Vec::new(),
            monitor_open: None,
            pending_openings: Vec::new(),
            sample_substeps: params.sample_substeps,
            guards,
            forbidden: None,
        })
    }

    fn specs(stages: &[Stage], n_required: usize) -> Vec<StageSpec> {
        stages.iter().enumerate().map(|(i, s)| StageSpec { name: s.name.clone(), required: i < n_required }).collect()
    }

    /// The bodies of every stage's operation on this episode (a bound site is bound at reset).
    fn resolve_operation_bodies(&self) -> Vec<Vec<usize>> {
        self.stages
            .iter()
            .map(|s| {
                let sources = s.operation.iter().flat_map(|o| &o.bodies);
                let mut bodies: Vec<usize> = sources
                    .filter_map(|&b| match b {
                        BodySource::Body(b) => Some(b),
                        BodySource::BoundSite(k) => self.base.bound.get(k).and_then(|&site| self.site_body.get(site).copied()),
                    })
                    .collect();
                bodies.dedup();
                bodies
            })
            .collect()
    }

    /// The names of stage `stage`'s mechanism bodies and handle geoms on this episode.
    fn watched(&self, stage: usize) -> Watched {
        let bodies = self.operation_bodies.get(stage).map_or(&[][..], Vec::as_slice);
        Watched {
            bodies: bodies.iter().map(|&b| self.body_name.get(b).cloned().unwrap_or_default()).collect(),
            handle_geoms: self.gripper.handle_names(bodies),
        }
    }

    /// The record of an operation: which way, on which bodies and handle, and whether its stage completed.
    fn operation_json(&self, stage: usize, monitor: &ContactMonitor, window: Window, completed: bool) -> serde_json::Value {
        let kind = self.stages[stage].operation.as_ref().map_or(OperationKind::Operate, |o| o.kind);
        monitor.to_json(kind, window, &self.watched(stage), completed)
    }

    fn site_name(&self, site: usize) -> String {
        self.site_names.get(site).cloned().unwrap_or_default()
    }

    /// Creates the pour counters the stages `evaluated` name (first time only), then updates every existing counter
    /// once for this control step.
    fn feed_pours(&mut self, evaluated: &[usize], data: &SimData, tick: Tick) {
        for &i in evaluated {
            for &c in &self.stages[i].counters {
                let slot = &mut self.pours[c];
                if slot.tracker.is_none() {
                    let z0_m = self.base.body0.get(slot.bottle_body).map_or(0.0, |p| p[2]);
                    slot.tracker = Some(PourTracker::new(&slot.params.config, slot.bottle_body, slot.target_site, z0_m));
                }
            }
        }
        for slot in &mut self.pours {
            if let Some(t) = slot.tracker.as_mut()
                && t.update(data, tick.control_step).is_some()
            {
                self.history.events.push(PrivateEvent { subject: Some(slot.params.bottle.clone()), ..PrivateEvent::new(EventKind::PourDetected, tick) });
            }
        }
    }

    /// Latches every armed failure monitor whose atom holds now (armed once its stage has completed).
    fn check_failures(&mut self, data: &SimData, tick: Tick) {
        let ctx = Ctx { index: &self.history.index, commitment: &self.history.commitment, base: &self.base, pours: &self.pours, data };
        for m in &mut self.failures {
            if m.latched_at.is_none() && self.tracker.is_completed(m.after_stage) && m.when.holds(&ctx) {
                m.latched_at = Some(tick);
                self.history.events.push(PrivateEvent { subject: Some(m.name.clone()), ..PrivateEvent::new(EventKind::FailureLatched, tick) });
            }
        }
    }

    fn holding_now(&self, data: &SimData) -> Vec<bool> {
        let ctx = Ctx { index: &self.history.index, commitment: &self.history.commitment, base: &self.base, pours: &self.pours, data };
        self.stages.iter().map(|s| s.holds(&ctx)).collect()
    }

    /// Every goal is evaluated each tick, so every pour counter a goal names is live; counters update at control
    /// steps only (`control`), like the ordered mode's.
    fn observe_unordered(&mut self, data: &SimData, tick: Tick, control: bool) {
        if control && !self.pours.is_empty() {
            let all: Vec<usize> = (0..self.stages.len()).collect();
            self.feed_pours(&all, data, tick);
        }
        let now = self.holding_now(data);
        self.goals.observe(&now, tick);
    }

    /// The contact monitor of the current operation (control steps only: its ratio counts control steps).
    fn observe_monitor(&mut self, data: &SimData) {
        let current = self.tracker.current();
        if let Some((stage, _)) = self.monitor_open
            && current != Some(stage)
            && let Some((_, m)) = self.monitor_open.take()
        {
            self.monitors[m].1.close();
        }
        if let Some(i) = current
            && self.stages[i].operation.is_some()
        {
            if self.monitor_open.is_none() {
                self.monitors.push((i, ContactMonitor::new(self.stages[i].name.clone())));
                self.monitor_open = Some((i, self.monitors.len() - 1));
            }
            let touch = self.operation_bodies.get(i).map(|b| self.gripper.touches(data, b)).unwrap_or_default();
            if let Some((_, m)) = self.monitor_open {
                self.monitors[m].1.step(touch);
            }
        }
    }

    /// Unordered mode: each pending opening, after the goals were sampled on this control step.
    fn observe_pending_openings(&mut self, data: &SimData) {
        for (i, opening) in &mut self.pending_openings {
            let touch = self.gripper.touches(data, &opening.bodies);
            opening.step(touch, self.goals.holding.get(*i).copied().unwrap_or(false));
        }
    }

    /// Advances the stages; at control steps (`control`) also feeds the pour counters, re-tests the completed stages
    /// for regressions (a diagnostic: at substep rate it would count every substep of contact chatter while a released
    /// object settles) and polls the failure monitors.
    fn observe_ordered(&mut self, data: &SimData, tick: Tick, control: bool) {
        if control {
            let current = self.tracker.current();
            self.feed_pours(current.as_slice(), data, tick);
        }
        let ctx = Ctx { index: &self.history.index, commitment: &self.history.commitment, base: &self.base, pours: &self.pours, data };
        let stages = &self.stages;
        let completed = match self.order {
            OrderMode::Strict => self.tracker.advance_strict(tick, |i| stages[i].holds(&ctx)),
            _ => self.tracker.advance(tick, |i| stages[i].holds(&ctx)),
        };
        if let Some(i) = completed
            && let Some(slot) = self.base.body_at_stage.get_mut(i)
        {
            *slot = Some(data.xpos().to_vec());
        }
        let ctx = Ctx { index: &self.history.index, commitment: &self.history.commitment, base: &self.base, pours: &self.pours, data };
        let stages = &self.stages;
        if control {
            self.tracker.track_regressions(tick, |i| stages[i].holds(&ctx));
            self.check_failures(data, tick);
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
        self.history.events.push(PrivateEvent { subject: Some(name.clone()), ..PrivateEvent::new(EventKind::ForbiddenContact, tick) });
        self.forbidden = Some(ForbiddenContactLatch { name, object, tick });
        true
    }

    /// One sample of the stage logic (control step or substep).
    fn sample(&mut self, data: &SimData, tick: Tick, control: bool) {
        if self.forbidden_contact_latched(data, tick) {
            return;
        }
        if self.order == OrderMode::Unordered {
            self.observe_unordered(data, tick, control);
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
        let bound = self.bindings.iter().map(|b| b.resolve(data)).collect();
        self.base = Baseline {
            site0: data.site_xpos().to_vec(),
            body0: data.xpos().to_vec(),
            bound,
            body_at_stage: vec![None; self.stages.len()],
        };
        self.pours.iter_mut().for_each(|p| p.tracker = None);
        self.failures.iter_mut().for_each(|f| f.latched_at = None);
        self.tracker = StageTracker::new(Self::specs(&self.stages, self.n_required));
        self.monitors.clear();
        self.monitor_open = None;
        self.operation_bodies = self.resolve_operation_bodies();
        self.forbidden = None;
        self.history.reset(data);
        let now = self.holding_now(data);
        self.pending_openings = if self.order == OrderMode::Unordered {
            self.stages
                .iter()
                .enumerate()
                .filter(|(_, s)| s.operation.as_ref().is_some_and(|o| o.kind == OperationKind::Open))
                .map(|(i, s)| {
                    let mut opening = PendingOpening::new(s.name.clone(), self.operation_bodies[i].clone(), self.watched(i));
                    opening.reset(now[i]);
                    (i, opening)
                })
                .collect()
        } else {
            Vec::new()
        };
        self.goals.reset(now, tick);
    }

    fn observe_substep(&mut self, data: &SimData, tick: Tick) {
        if self.sample_substeps {
            self.history.substeps += 1;
            self.sample(data, tick, false);
        }
    }

    fn observe_control_step(&mut self, data: &SimData, tick: Tick) {
        self.history.control_steps += 1;
        if self.forbidden.is_none() && self.order != OrderMode::Unordered {
            self.observe_monitor(data);
        }
        self.sample(data, tick, true);
        if self.forbidden.is_none() && self.order == OrderMode::Unordered {
            self.observe_pending_openings(data);
        }
        self.history.observe_commitment(data, tick);
    }

    /// The stage events of the mode's tracker (the goal set's changes, or the ordered stages' completions,
    /// regressions and order violation) merged with the other events (pours, failures, forbidden contact,
    /// commitment): the record's `stage_events` and `events`, as they happen.
    fn private_events(&self) -> Vec<PrivateEvent> {
        let stage_events = if self.order == OrderMode::Unordered { self.goals.events() } else { self.tracker.events() };
        crate::judge::evaluator::merge_events(stage_events, &self.history.events)
    }

    /// Unordered: the required goals holding now (they may drop again); ordered: the latched required stages.
    fn stage_progress(&self) -> (usize, usize) {
        if self.order == OrderMode::Unordered {
            (self.goals.current_count(), self.n_required)
        } else {
            (self.tracker.completed_required_count(), self.tracker.required_count())
        }
    }

    fn finish(&mut self, data: &SimData, _tick: Tick) -> EvaluationRecord {
        let mut record = EvaluationRecord::new(self.checker.clone());
        record.stages_unordered = self.order == OrderMode::Unordered;
        let ctx = Ctx { index: &self.history.index, commitment: &self.history.commitment, base: &self.base, pours: &self.pours, data };
        record.terminal_state_checks =
            self.terminal.iter().map(|t| TerminalCheck { name: t.name.clone(), passed: t.holds(&ctx) }).collect();
        record.terminal_state_success = record.terminal_state_checks.iter().all(|c| c.passed);
        let mut details = serde_json::Map::new();
        details.insert("order".into(), json!(self.order));
        let stages_ok;
        if self.order == OrderMode::Unordered {
            let now: Vec<bool> = self.stages.iter().map(|s| s.holds(&ctx)).collect();
            stages_ok = self.goals.write_into(&now, &mut record, &mut details);
        } else {
            self.tracker.write_into(&mut record);
            stages_ok = self.tracker.all_required_completed() && !self.tracker.order_violated();
            details.insert("order_violation".into(), json!(self.tracker.order_violated()));
            if let Some(label) = self.tracker.order_violation_label() {
                details.insert("order_violation_latch".into(), json!(label));
            }
        }
        if let Some((_, m)) = self.monitor_open.take() {
            self.monitors[m].1.close();
        }
        let mut ops: Vec<serde_json::Value> = self
            .monitors
            .iter()
            .map(|(i, m)| self.operation_json(*i, m, Window::StageCurrent, self.tracker.is_completed(*i)))
            .collect();
        ops.extend(self.pending_openings.iter().filter_map(|(_, o)| o.to_json(None)));
        if !ops.is_empty() {
            details.insert("opening_operations".into(), json!(ops));
        }
        if !self.bindings.is_empty() {
            let bound: serde_json::Map<String, serde_json::Value> = self
                .bindings
                .iter()
                .zip(&self.base.bound)
                .map(|(b, &s)| (b.name.clone(), json!(self.site_name(s))))
                .collect();
            details.insert("bindings".into(), serde_json::Value::Object(bound));
        }
        if !self.pours.is_empty() {
            let counters: Vec<_> = self
                .pours
                .iter()
                .map(|p| {
                    let pours: Vec<_> = p.tracker.iter().flat_map(|t| t.pours()).map(|q| json!({"start_step": q.start_step, "counted_step": q.counted_step})).collect();
                    json!({"name": p.params.name, "created": p.tracker.is_some(), "count": p.count(), "pours": pours,
                        "max_tilt_rad": p.tracker.as_ref().map(PourTracker::max_tilt_rad)})
                })
                .collect();
            details.insert("pour_counters".into(), json!(counters));
        }
        let latched: Vec<&FailureMonitor> = self.failures.iter().filter(|f| f.latched_at.is_some()).collect();
        if !self.failures.is_empty() {
            let list: Vec<_> = latched
                .iter()
                .map(|f| json!({"name": f.name, "reason": f.reason, "control_step": f.latched_at.map(|t| t.control_step)}))
                .collect();
            details.insert("latched_failures".into(), json!(list));
        }
        if !self.guards.is_empty() {
            details.insert("forbidden_contact".into(), json!(self.forbidden));
        }
        record.details = Some(serde_json::Value::Object(details));
        record.success = stages_ok && record.terminal_state_success && latched.is_empty() && self.forbidden.is_none();
        record.failure_reason = if record.success {
            None
        } else if self.forbidden.is_some() {
            Some(FailureReason::ForbiddenContact)
        } else if let Some(f) = latched.first() {
            Some(f.reason)
        } else if self.tracker.order_violated() {
            Some(FailureReason::OrderViolation)
        } else if !stages_ok {
            Some(FailureReason::IncompleteStage)
        } else {
            Some(FailureReason::TerminalStateInvalid)
        };
        self.history.write_into(&mut record, data);
        record
    }
}

