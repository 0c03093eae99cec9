//! The staged evaluator's monitors besides the stages: failure monitors, forbidden-contact guards and the unordered
//! mode's satisfied-goal set.
use libero_sim::mujoco_rs::prelude::{MjModel, MjtObjBase};
use serde::Serialize;
use serde_json::json;

use crate::TasksError;
use crate::judge::evaluator::{EvaluationRecord, EventKind, FailureReason, PrivateEvent, StageRegressions, Tick, score_percent};
use crate::judge::predicates::{SceneIndex, in_subtree};
use crate::judge::staged::compile::Check;
use crate::judge::staged::lang::ForbiddenContactParams;

/// A compiled failure monitor.
#[derive(Debug, Clone)]
pub(super) struct FailureMonitor {
    pub(super) name: String,
    pub(super) after_stage: usize,
    pub(super) when: Check,
    pub(super) reason: FailureReason,
    pub(super) latched_at: Option<Tick>,
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
pub(super) struct ForbiddenContactGuard {
    pub(super) objects: Vec<String>,
    label: String,
    max_distance_m: f64,
    /// geom id → side
    side: Vec<GuardSide>,
}

impl ForbiddenContactGuard {
    pub(super) fn compile(p: &ForbiddenContactParams, index: &SceneIndex, model: &MjModel) -> Result<Self, TasksError> {
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
    pub(super) fn touching(&self, contacts: impl IntoIterator<Item = ([usize; 2], f64)>) -> Option<usize> {
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

    pub(super) fn latch_name(&self, object: usize) -> String {
        format!("{}_touched_{}", self.objects[object], self.label)
    }
}

/// The latched forbidden contact of a run.
#[derive(Debug, Clone, Serialize)]
pub(super) struct ForbiddenContactLatch {
    pub(super) name: String,
    pub(super) object: String,
    pub(super) tick: Tick,
}

/// One change of the satisfied-goal set (unordered mode): when, and which goals hold afterwards.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct GoalSetChange {
    pub control_step: u64,
    pub sim_time_s: f64,
    pub satisfied: Vec<String>,
    /// Required goals among `satisfied`.
    pub count: usize,
}

/// The cooking goal evaluator's bookkeeping (task catalog §5.0): no order and no latch — which goals hold on the
/// final state decides — but the goal count at reset, the largest count seen, and every change of the satisfied
/// set (events, per-goal drop counts, the sets themselves) are kept as diagnostics. Goals `n_required..` are
/// optional: tracked but never counted.
#[derive(Debug, Clone)]
pub struct GoalSetTracker {
    names: Vec<String>,
    n_required: usize,
    pub(super) holding: Vec<bool>,
    drops: Vec<u32>,
    initial_count: usize,
    max_count: usize,
    events: Vec<PrivateEvent>,
    changes: Vec<GoalSetChange>,
}

impl GoalSetTracker {
    pub fn new(names: Vec<String>, n_required: usize) -> Self {
        let n = names.len();
        Self {
            names,
            n_required: n_required.min(n),
            holding: vec![false; n],
            drops: vec![0; n],
            initial_count: 0,
            max_count: 0,
            events: Vec::new(),
            changes: Vec::new(),
        }
    }

    fn count(&self, holding: &[bool]) -> usize {
        holding[..self.n_required].iter().filter(|&&h| h).count()
    }

    fn satisfied(&self) -> Vec<String> {
        self.names.iter().zip(&self.holding).filter(|(_, h)| **h).map(|(n, _)| n.clone()).collect()
    }

    /// The evaluator reset: `holding` is the set at the reset state (counted as the initial count, not a change).
    pub fn reset(&mut self, holding: Vec<bool>, tick: Tick) {
        self.holding = holding;
        self.drops.iter_mut().for_each(|d| *d = 0);
        self.events.clear();
        self.initial_count = self.count(&self.holding);
        self.max_count = self.initial_count;
        self.changes = vec![GoalSetChange {
            control_step: tick.control_step,
            sim_time_s: tick.sim_time_s,
            satisfied: self.satisfied(),
            count: self.initial_count,
        }];
    }

    /// One control step: every goal that became true or false is an event; a goal that stopped holding is a drop.
    pub fn observe(&mut self, now: &[bool], tick: Tick) {
        let mut changed = false;
        for (i, (&h, was)) in now.iter().zip(self.holding.iter_mut()).enumerate() {
            if h == *was {
                continue;
            }
            *was = h;
            changed = true;
            if !h {
                self.drops[i] += 1;
            }
            let kind = if h { EventKind::StageCompleted } else { EventKind::StageRegressed };
            self.events.push(PrivateEvent { stage_index: Some(i), stage_name: Some(self.names[i].clone()), ..PrivateEvent::new(kind, tick) });
        }
        if changed {
            let count = self.count(&self.holding);
            self.max_count = self.max_count.max(count);
            self.changes.push(GoalSetChange {
                control_step: tick.control_step,
                sim_time_s: tick.sim_time_s,
                satisfied: self.satisfied(),
                count,
            });
        }
    }

    pub fn initial_count(&self) -> usize {
        self.initial_count
    }

    pub fn max_count(&self) -> usize {
        self.max_count
    }

    /// Required goals holding at the latest sample: what [`Self::write_into`] counts completed on that state.
    pub fn current_count(&self) -> usize {
        self.count(&self.holding)
    }

    /// Every goal that became true (`stage_completed`) or false (`stage_regressed`) since the reset, in order.
    pub fn events(&self) -> &[PrivateEvent] {
        &self.events
    }

    /// Fills the stage fields of `record` from the goals holding on the final state (`now`) and the diagnostics
    /// into `details`; returns whether every required goal holds.
    pub fn write_into(&self, now: &[bool], record: &mut EvaluationRecord, details: &mut serde_json::Map<String, serde_json::Value>) -> bool {
        let names = |f: &dyn Fn(usize) -> bool| -> Vec<String> {
            (0..self.names.len()).filter(|&i| f(i)).map(|i| self.names[i].clone()).collect()
        };
        let completed = self.count(now);
        record.required_stage_count = self.n_required;
        record.completed_required_stage_count = completed;
        record.stage_score_percent = score_percent(completed, self.n_required);
        record.ordered_stage_names = names(&|i| i < self.n_required);
        record.optional_stage_names = names(&|i| i >= self.n_required);
        record.completed_stage_names = names(&|i| now.get(i).copied().unwrap_or(false));
        record.stage_regressions = (0..self.names.len())
            .filter(|&i| self.drops[i] > 0)
            .map(|i| StageRegressions { stage_name: self.names[i].clone(), count: self.drops[i] })
            .collect();
        record.stage_events = self.events.clone();
        // the final state is one more sample: a change since the last control step still counts toward the maximum
        let max_count = self.max_count.max(completed);
        details.insert("initial_goal_count".into(), json!(self.initial_count));
        details.insert("max_goal_count".into(), json!(max_count));
        details.insert("final_goal_count".into(), json!(completed));
        details.insert("regressed_from_max".into(), json!(completed < max_count));
        details.insert("goal_set_changes".into(), json!(self.changes));
        completed == self.n_required
    }
}


#[cfg(test)]
mod tests {
    use super::*;

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

    fn tick(step: u64) -> Tick {
        Tick::at_control_step(step, step as f64 * 0.05)
    }

    fn tracker() -> GoalSetTracker {
        GoalSetTracker::new(["a", "b", "c", "opt"].map(String::from).to_vec(), 3)
    }

    #[test]
    fn goal_set_counts_goals_on_the_final_state_and_keeps_initial_and_max() {
        let mut g = tracker();
        g.reset(vec![true, false, false, true], tick(0));
        assert_eq!(g.initial_count(), 1, "the optional goal is not counted");
        g.observe(&[true, true, false, true], tick(1));
        g.observe(&[true, true, true, true], tick(2));
        g.observe(&[true, false, true, false], tick(3));
        assert_eq!(g.max_count(), 3);
        let (mut record, mut details) = (EvaluationRecord::new("x"), serde_json::Map::new());
        let all = g.write_into(&[true, false, true, false], &mut record, &mut details);
        assert!(!all);
        assert_eq!((record.required_stage_count, record.completed_required_stage_count), (3, 2));
        assert_eq!(record.completed_stage_names, ["a", "c"]);
        assert_eq!(record.optional_stage_names, ["opt"]);
        assert_eq!(details["initial_goal_count"], 1);
        assert_eq!(details["max_goal_count"], 3);
        assert_eq!(details["regressed_from_max"], true);
        let drops: Vec<_> = record.stage_regressions.iter().map(|r| (r.stage_name.as_str(), r.count)).collect();
        assert_eq!(drops, [("b", 1), ("opt", 1)]);
    }

    #[test]
    fn goal_set_logs_every_change_and_nothing_else() {
        let mut g = tracker();
        g.reset(vec![false; 4], tick(0));
        g.observe(&[false; 4], tick(1));
        g.observe(&[true, false, false, false], tick(2));
        g.observe(&[true, false, false, false], tick(3));
        g.observe(&[false, false, false, false], tick(4));
        g.observe(&[true, false, false, false], tick(5));
        let (mut record, mut details) = (EvaluationRecord::new("x"), serde_json::Map::new());
        g.write_into(&[true, false, false, false], &mut record, &mut details);
        let steps: Vec<u64> = details["goal_set_changes"].as_array().unwrap().iter().map(|c| c["control_step"].as_u64().unwrap()).collect();
        assert_eq!(steps, [0, 2, 4, 5], "the reset set, then one entry per change");
        let kinds: Vec<_> = record.stage_events.iter().map(|e| (e.kind, e.tick.control_step)).collect();
        assert_eq!(kinds, [(EventKind::StageCompleted, 2), (EventKind::StageRegressed, 4), (EventKind::StageCompleted, 5)]);
        assert_eq!(record.stage_regressions[0].count, 1);
        assert_eq!(details["regressed_from_max"], false, "back at the maximum");
    }

    #[test]
    fn goal_set_reset_forgets_the_previous_episode() {
        let mut g = tracker();
        g.reset(vec![false; 4], tick(0));
        g.observe(&[true, true, true, false], tick(1));
        g.observe(&[false; 4], tick(2));
        g.reset(vec![false; 4], tick(0));
        let (mut record, mut details) = (EvaluationRecord::new("x"), serde_json::Map::new());
        assert!(!g.write_into(&[false; 4], &mut record, &mut details));
        assert_eq!(details["max_goal_count"], 0);
        assert!(record.stage_regressions.is_empty() && record.stage_events.is_empty());
        let mut all = tracker();
        all.reset(vec![true, true, true, false], tick(0));
        assert!(all.write_into(&[true, true, true, false], &mut record, &mut details), "optional goals are not required");
        assert_eq!(record.stage_score_percent, 100.0);
    }

}
