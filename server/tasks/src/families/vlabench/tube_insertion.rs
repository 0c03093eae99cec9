//! `private_tube_insertion` (T18; ChemistryTubePrecisionEvaluator, task catalog §4 T18). Terminal only: success ⇔
//! all five checks hold on the final state at finish, with
//! * p = world position of the tube's root body, s = the slot site, r = the rack's root body;
//! * a = the long axis of the tube: the local y axis (second column of the rotation) of `<tube>_tube_axis`;
//! * v = MuJoCo `cvel` of the tube's root body (angular part first, linear part last).
//!
//! | check | rule |
//! |---|---|
//! | `lateral_error` | ‖p_xy − s_xy‖ ≤ 0.018 m |
//! | `insertion_depth` | p_z − r_z ∈ [0.032, 0.085] m (from the rack root, not the tabletop) |
//! | `verticality` | \|a · ẑ\| ≥ 0.97 (≈ 14°) |
//! | `stability` | ‖v_lin‖ ≤ 0.08 m/s and ‖v_ang‖ ≤ 0.60 rad/s |
//! | `tube_rack_contact` | a contact between the tube's and the rack's body subtrees with distance ≤ 1e-3 m |
//!
//! Control-rate observe only counts how many control steps satisfied all five (a diagnostic). The BDDL goal
//! (`In(tube, slot)`) is reported as a diagnostic. Names are resolved when the evaluator is built, so a lookup
//! error fails the episode before it starts rather than at finish.
//!
//! `tubes` instead of `tube`/`slot_site` (pool `vlabench_tube_precision/1`, the original's
//! ChemistryTubeRearrangementEvaluator): every listed tube must pass all five checks in its own slot against the one
//! rack. Each tube is one stage (K = number of tubes; a stage is complete when that tube passes at finish, in any
//! order) and its checks are named `<tube>.<check>`.
use libero_sim::compose::ComposedScene;
use libero_sim::mujoco_rs::prelude::{MjModel, MjtObjBase};
use libero_sim::simulation::SimData;
use serde::{Deserialize, Serialize};

use crate::TasksError;
use crate::judge::evaluator::{
    EvaluationRecord, Evaluator, FailureReason, PrivateEvent, StageSpec, StageTracker, TerminalCheck, Tick,
};
use crate::judge::family::History;
use crate::judge::kind::{EvaluatorKind, check};
use crate::judge::support::missing_in_model;

pub const CHECKER: &str = "private_tube_insertion";

/// The kind's table row.
pub const EVALUATOR: EvaluatorKind = EvaluatorKind::plain(CHECKER, check::<TubeInsertionParams>, |checker, scene, model| {
    Ok(Box::new(TubeInsertion::new(checker.parse()?, scene, model, checker.task_id_owned())?))
});
pub const STAGE_NAME: &str = "01_Tube_Inserted_At_Finish";

/// One tube and the slot site it belongs in.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TubeSlot {
    pub tube: String,
    pub slot_site: String,
}

/// The manifest's `checker.params`: one tube (`tube` + `slot_site`, T18) or several (`tubes`), never both.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TubeInsertionParams {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tube: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub slot_site: Option<String>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub tubes: Vec<TubeSlot>,
    pub rack_root: String,
    pub lateral_max_m: f64,
    pub depth_range_m: [f64; 2],
    pub verticality_min: f64,
    pub linear_speed_max_m_s: f64,
    pub angular_speed_max_rad_s: f64,
    pub contact_distance_max_m: f64,
}

/// What the checks measured on one state.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct TubeMeasures {
    pub lateral_error_m: f64,
    pub insertion_depth_m: f64,
    /// |a · ẑ|
    pub verticality: f64,
    pub linear_speed_m_s: f64,
    pub angular_speed_rad_s: f64,
    pub tube_rack_contact: bool,
}

impl TubeInsertionParams {
    /// The (tube, slot) pairs to judge, in order; an error unless exactly one of the two forms is given.
    pub fn pairs(&self) -> Result<Vec<TubeSlot>, TasksError> {
        let bad = |message: &str| TasksError::Scene(format!("{CHECKER}: {message}"));
        match (&self.tube, &self.slot_site, self.tubes.is_empty()) {
            (Some(tube), Some(slot_site), true) => Ok(vec![TubeSlot { tube: tube.clone(), slot_site: slot_site.clone() }]),
            (None, None, false) => Ok(self.tubes.clone()),
            _ => Err(bad("give either `tube` and `slot_site` or a non-empty `tubes` list")),
        }
    }
}

/// One judged tube, resolved in the model.
struct JudgedTube {
    name: String,
    tube_body: usize,
    axis_body: usize,
    slot_site: usize,
    /// `in_tube[b]`: body b belongs to the tube's subtree.
    in_tube: Vec<bool>,
}

pub struct TubeInsertion {
    params: TubeInsertionParams,
    /// The shared bookkeeping ([`crate::judge::family`]); terminal judging keeps no stages during the episode.
    history: History,
    tubes: Vec<JudgedTube>,
    /// Several tubes (`tubes`): stages and check names carry the tube's name.
    several: bool,
    rack_body: usize,
    /// `in_rack[b]`: body b belongs to the rack's subtree.
    in_rack: Vec<bool>,
    geom_body: Vec<usize>,
    steps_all_checks_passed: u64,
    /// Tubes passing all their checks on the latest observed state: the stages finish would complete there.
    passing_now: usize,
}

/// `<name>`, `<name>_main`, `<name>_object`, in that order (catalog §2.4).
fn lookup_body(model: &MjModel, name: &str) -> Option<usize> {
    [name.to_owned(), format!("{name}_main"), format!("{name}_object")]
        .iter()
        .find_map(|n| model.name_to_id(MjtObjBase::mjOBJ_BODY, n))
}

fn subtree(model: &MjModel, root: usize) -> Vec<bool> {
    let parent = model.body_parentid();
    let nbody = model.ffi().nbody as usize;
    // parents precede children in MuJoCo's body order
    let mut inside = vec![false; nbody];
    for b in 0..nbody {
        inside[b] = b == root || (b != 0 && inside[parent[b] as usize]);
    }
    inside
}

fn norm3(v: &[f64]) -> f64 {
    v.iter().map(|x| x * x).sum::<f64>().sqrt()
}

impl TubeInsertion {
    pub fn new(
        params: TubeInsertionParams,
        scene: &ComposedScene,
        model: &MjModel,
        task_id: Option<String>,
    ) -> Result<Self, TasksError> {
        let history = History::for_scene(scene, model, task_id)?;
        let missing = |kind: &str, name: &str| missing_in_model(CHECKER, kind, name);
        let pairs = params.pairs()?;
        let tubes = pairs
            .iter()
            .map(|p| {
                let tube_body = lookup_body(model, &p.tube).ok_or_else(|| missing("body", &p.tube))?;
                let axis_name = format!("{}_tube_axis", p.tube);
                let axis_body = model.name_to_id(MjtObjBase::mjOBJ_BODY, &axis_name).ok_or_else(|| missing("body", &axis_name))?;
                let slot_site =
                    model.name_to_id(MjtObjBase::mjOBJ_SITE, &p.slot_site).ok_or_else(|| missing("site", &p.slot_site))?;
                Ok(JudgedTube { name: p.tube.clone(), tube_body, axis_body, slot_site, in_tube: subtree(model, tube_body) })
            })
            .collect::<Result<Vec<_>, TasksError>>()?;
        let rack_body = lookup_body(model, &params.rack_root).ok_or_else(|| missing("body", &params.rack_root))?;
        Ok(Self {
            several: !params.tubes.is_empty(),
            tubes,
            in_rack: subtree(model, rack_body),
            geom_body: model.geom_bodyid().iter().map(|&b| b as usize).collect(),
            params,
            history,
            rack_body,
            steps_all_checks_passed: 0,
            passing_now: 0,
        })
    }

    fn measure_tube(&self, t: &JudgedTube, data: &SimData) -> TubeMeasures {
        let p = data.xpos()[t.tube_body];
        let s = data.site_xpos()[t.slot_site];
        let r = data.xpos()[self.rack_body];
        // xmat is row-major: the second column's z component (the world z of local y) is element [2][1]
        let verticality = data.xmat()[t.axis_body][7].abs();
        let v = data.cvel()[t.tube_body];
        let body = |g: i32| self.geom_body[g as usize];
        let contact = data.contact().iter().any(|c| {
            let (b1, b2) = (body(c.geom[0]), body(c.geom[1]));
            c.dist <= self.params.contact_distance_max_m
                && ((t.in_tube[b1] && self.in_rack[b2]) || (t.in_tube[b2] && self.in_rack[b1]))
        });
        TubeMeasures {
            lateral_error_m: ((p[0] - s[0]).powi(2) + (p[1] - s[1]).powi(2)).sqrt(),
            insertion_depth_m: p[2] - r[2],
            verticality,
            angular_speed_rad_s: norm3(&v[0..3]),
            linear_speed_m_s: norm3(&v[3..6]),
            tube_rack_contact: contact,
        }
    }

    /// Per tube: its measures and its five checks (named `<tube>.<check>` when there are several tubes).
    fn judge_all(&self, data: &SimData) -> Vec<(TubeMeasures, Vec<TerminalCheck>)> {
        self.tubes
            .iter()
            .map(|t| {
                let m = self.measure_tube(t, data);
                let mut checks = self.checks(&m);
                if self.several {
                    checks.iter_mut().for_each(|c| c.name = format!("{}.{}", t.name, c.name));
                }
                (m, checks)
            })
            .collect()
    }

    /// How many tubes pass all their checks on `data`.
    fn passing(&self, data: &SimData) -> usize {
        self.judge_all(data).iter().filter(|(_, checks)| checks.iter().all(|c| c.passed)).count()
    }

    fn stage_names(&self) -> Vec<String> {
        if !self.several {
            return vec![STAGE_NAME.to_owned()];
        }
        self.tubes.iter().enumerate().map(|(i, t)| format!("{:02}_{}_Inserted_At_Finish", i + 1, t.name)).collect()
    }

    /// The five named checks on `m`.
    pub fn checks(&self, m: &TubeMeasures) -> Vec<TerminalCheck> {
        let p = &self.params;
        let check = |name: &str, passed: bool| TerminalCheck { name: name.to_owned(), passed };
        vec![
            check("lateral_error", m.lateral_error_m <= p.lateral_max_m),
            check("insertion_depth", (p.depth_range_m[0]..=p.depth_range_m[1]).contains(&m.insertion_depth_m)),
            check("verticality", m.verticality >= p.verticality_min),
            check("stability", m.linear_speed_m_s <= p.linear_speed_max_m_s && m.angular_speed_rad_s <= p.angular_speed_max_rad_s),
            check("tube_rack_contact", m.tube_rack_contact),
        ]
    }
}

impl Evaluator for TubeInsertion {
    fn private_events(&self) -> Vec<PrivateEvent> {
        self.history.events.clone()
    }

    fn checker(&self) -> &str {
        CHECKER
    }

    /// Terminal judging: the tubes that would pass if the episode finished now (the stages complete at finish).
    fn stage_progress(&self) -> (usize, usize) {
        (self.passing_now, self.tubes.len())
    }

    fn reset(&mut self, data: &SimData, _tick: Tick) {
        self.steps_all_checks_passed = 0;
        self.history.reset(data);
        self.passing_now = self.passing(data);
    }

    fn observe_control_step(&mut self, data: &SimData, tick: Tick) {
        self.history.control_steps += 1;
        self.passing_now = self.passing(data);
        if self.passing_now == self.tubes.len() {
            self.steps_all_checks_passed += 1;
        }
        self.history.observe_commitment(data, tick);
    }

    fn finish(&mut self, data: &SimData, tick: Tick) -> EvaluationRecord {
        let judged = self.judge_all(data);
        let passed: Vec<bool> = judged.iter().map(|(_, checks)| checks.iter().all(|c| c.passed)).collect();
        let success = passed.iter().all(|&p| p);
        let names = self.stage_names();
        let mut stages = StageTracker::new(names.iter().map(StageSpec::required).collect());
        // terminal judging has no order: a tube that passes completes its stage whatever the others do
        stages.complete_where(tick, |i| passed[i]);
        let checks: Vec<TerminalCheck> = judged.iter().flat_map(|(_, c)| c.iter().cloned()).collect();
        let mut record = EvaluationRecord::new(CHECKER);
        stages.write_into(&mut record);
        self.history.write_into(&mut record, data);
        record.success = success;
        record.terminal_state_success = success;
        record.terminal_state_checks = checks;
        record.failure_reason = (!success).then_some(FailureReason::TerminalStateInvalid);
        let finals: Vec<TubeMeasures> = judged.iter().map(|(m, _)| *m).collect();
        let per_tube: serde_json::Map<String, serde_json::Value> =
            self.tubes.iter().zip(&finals).map(|(t, m)| (t.name.clone(), serde_json::json!(m))).collect();
        record.details = Some(serde_json::json!({
            "final": match finals.as_slice() {
                [only] if !self.several => serde_json::json!(only),
                _ => serde_json::Value::Object(per_tube),
            },
            "control_steps_all_checks_passed": self.steps_all_checks_passed,
        }));
        record
    }
}
