//! `private_ordered_hammer_contact` (T29 drive_nail_with_hammer; task catalog §5 T29, §6.2): lift the hammer, touch
//! the nail with it, drive the nail ≥ 7.5 cm into the block.
//!
//! Sampled at every control step **and** every physics substep (the same rule at both rates: a hammer blow can last
//! less than one control step). Reset captures the hammer root height z₀ and the nail slide q₀. Stages, in order
//! (only the current stage is tested; at most one completes per tick; completed stages stay completed):
//! 1. `01_Lift_Hammer` — hammer root z ≥ z₀ + 0.045.
//! 2. `02_Hammer_Contacts_Nail` — Body contact(hammer, nail link): a contact between the two body subtrees with
//!    distance ≤ 1 mm, at a tick where this stage is current.
//! 3. `03_Drive_Nail` — a hammer–nail contact has been seen at any time since reset (latched, also before the lift)
//!    AND q − q₀ ≥ 0.075.
//!
//! Success at finish ⇔ all 3 stages completed AND contact seen AND q − q₀ ≥ 0.075 on the final state. As in the
//! source, the displacement need not be caused by the hammer: only the order lift → contact → displacement counts.
//! Regressions are recorded for the two state stages (stage 1: the hammer back below z₀ + 0.045; stage 3: the nail
//! back below the threshold); stage 2 is an event and cannot regress.
use libero_sim::mujoco_rs::prelude::{MjModel, MjtObjBase};
use libero_sim::simulation::SimData;
use serde::Deserialize;
use serde_json::json;

use crate::TasksError;
use crate::judge::evaluator::{EvaluationRecord, StageSpec, StageTracker, Tick};
use crate::judge::family::{History, StagedFamily, build, judge_checks, terminal_check};
use crate::judge::kind::{EvaluatorKind, check};
use crate::judge::predicates::SubtreeContact;
use crate::judge::support::missing_in_model;

pub const CHECKER: &str = "private_ordered_hammer_contact";
pub const STAGES: [&str; 3] = ["01_Lift_Hammer", "02_Hammer_Contacts_Nail", "03_Drive_Nail"];

/// The manifest's `checker.params` (every field from the manifest: it is the one source of the thresholds).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HammerParams {
    pub hammer: String,
    pub nail_body: String,
    pub nail_joint: String,
    pub hammer_lift_m: f64,
    pub nail_drive_m: f64,
    pub contact_distance_max_m: f64,
    #[serde(deserialize_with = "crate::judge::stage_types::stage_names")]
    pub stages: Vec<String>,
}

/// The kind's table row.
pub const EVALUATOR: EvaluatorKind = EvaluatorKind::plain(CHECKER, check::<HammerParams>, |checker, scene, model| {
    build(checker, scene, model, |h| HammerContact::new(checker.parse()?, h, model))
});

/// What one tick reads from the simulation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HammerSample {
    pub hammer_z_m: f64,
    pub nail_q_m: f64,
    /// Body contact(hammer, nail) with distance ≤ the threshold at this tick.
    pub contact: bool,
}

/// The stage logic on samples, independent of MuJoCo (unit-tested below).
#[derive(Debug, Clone)]
pub struct HammerProgress {
    lift_m: f64,
    drive_m: f64,
    z0_m: f64,
    q0_m: f64,
    contact_seen: bool,
    first_contact: Option<Tick>,
    contact_ticks: u64,
    max_lift_m: f64,
    max_drive_m: f64,
    stages: StageTracker,
}

impl HammerProgress {
    /// Starts from the reset baselines (hammer root height, nail slide position).
    pub fn new(params: &HammerParams, z0_m: f64, q0_m: f64) -> Self {
        Self {
            lift_m: params.hammer_lift_m,
            drive_m: params.nail_drive_m,
            z0_m,
            q0_m,
            contact_seen: false,
            first_contact: None,
            contact_ticks: 0,
            max_lift_m: 0.0,
            max_drive_m: 0.0,
            stages: StageTracker::new(params.stages.iter().map(StageSpec::required).collect()),
        }
    }

    pub fn lifted(&self, hammer_z_m: f64) -> bool {
        hammer_z_m - self.z0_m >= self.lift_m
    }

    pub fn drive_m(&self, nail_q_m: f64) -> f64 {
        nail_q_m - self.q0_m
    }

    pub fn driven(&self, nail_q_m: f64) -> bool {
        self.drive_m(nail_q_m) >= self.drive_m
    }

    /// One sampling tick (control step or substep).
    pub fn observe(&mut self, tick: Tick, s: HammerSample) {
        if s.contact {
            self.contact_ticks += 1;
            if !self.contact_seen {
                self.contact_seen = true;
                self.first_contact = Some(tick);
            }
        }
        self.max_lift_m = self.max_lift_m.max(s.hammer_z_m - self.z0_m);
        self.max_drive_m = self.max_drive_m.max(self.drive_m(s.nail_q_m));
        let lifted = self.lifted(s.hammer_z_m);
        let driven = self.driven(s.nail_q_m);
        let contact_seen = self.contact_seen;
        // stage 2 is tested only while current: `advance` tests nothing else
        self.stages.advance(tick, |i| match i {
            0 => lifted,
            1 => s.contact,
            _ => contact_seen && driven,
        });
        self.stages.track_regressions(tick, |i| match i {
            0 => lifted,
            1 => true,
            _ => driven,
        });
    }

    pub fn contact_seen(&self) -> bool {
        self.contact_seen
    }

    pub fn stages(&self) -> &StageTracker {
        &self.stages
    }

    /// Success on the final nail position: all stages, contact seen, nail still driven.
    pub fn success(&self, final_nail_q_m: f64) -> bool {
        self.stages.all_required_completed() && self.contact_seen && self.driven(final_nail_q_m)
    }

    fn details(&self, final_nail_q_m: f64) -> serde_json::Value {
        json!({
            "hammer_z0_m": self.z0_m,
            "nail_q0_m": self.q0_m,
            "max_hammer_lift_m": self.max_lift_m,
            "max_nail_displacement_m": self.max_drive_m,
            "final_nail_displacement_m": self.drive_m(final_nail_q_m),
            "hammer_nail_contact_seen": self.contact_seen,
            "first_contact": self.first_contact,
            "contact_ticks": self.contact_ticks,
        })
    }
}

/// The kind's stage logic on the simulation (the shared skeleton: [`crate::judge::family`]).
pub struct HammerContact {
    params: HammerParams,
    hammer_body: usize,
    nail_qpos_adr: usize,
    /// Body contact(hammer, nail link).
    touching: SubtreeContact,
    progress: HammerProgress,
}

impl HammerContact {
    pub fn new(params: HammerParams, history: &History, model: &MjModel) -> Result<Self, TasksError> {
        let hammer = history.index.instance(&params.hammer).ok_or_else(|| missing_in_model(CHECKER, "object", &params.hammer))?;
        let hammer_body = history.index.instances[hammer].body;
        let nail_body = model
            .name_to_id(MjtObjBase::mjOBJ_BODY, &params.nail_body)
            .ok_or_else(|| missing_in_model(CHECKER, "body", &params.nail_body))?;
        let joint = model
            .name_to_id(MjtObjBase::mjOBJ_JOINT, &params.nail_joint)
            .ok_or_else(|| missing_in_model(CHECKER, "joint", &params.nail_joint))?;
        let nail_qpos_adr = model.jnt_qposadr()[joint] as usize;
        let touching = SubtreeContact::new(model, hammer_body, nail_body, params.contact_distance_max_m);
        let progress = HammerProgress::new(&params, 0.0, 0.0);
        Ok(Self { params, hammer_body, nail_qpos_adr, touching, progress })
    }

    fn nail_q(&self, data: &SimData) -> f64 {
        data.qpos()[self.nail_qpos_adr]
    }
}

impl StagedFamily for HammerContact {
    fn checker(&self) -> &str {
        CHECKER
    }

    fn samples_substeps(&self) -> bool {
        true
    }

    fn reset(&mut self, _history: &History, data: &SimData) {
        self.progress = HammerProgress::new(&self.params, data.xpos()[self.hammer_body][2], self.nail_q(data));
    }

    fn sample(&mut self, _history: &mut History, data: &SimData, tick: Tick, _control: bool) {
        let s = HammerSample { hammer_z_m: data.xpos()[self.hammer_body][2], nail_q_m: self.nail_q(data), contact: self.touching.holds(data) };
        self.progress.observe(tick, s);
    }

    fn stages(&self) -> &StageTracker {
        self.progress.stages()
    }

    fn judge(&self, _history: &History, data: &SimData, record: &mut EvaluationRecord) {
        let (q, p) = (self.nail_q(data), &self.progress);
        let checks = vec![
            terminal_check("hammer_nail_contact_seen", p.contact_seen()),
            terminal_check(format!("nail_displacement_m {:.4} >= {}", p.drive_m(q), self.params.nail_drive_m), p.driven(q)),
        ];
        judge_checks(record, p.stages(), checks);
        record.details = Some(p.details(q));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::judge::evaluator::EventKind;

    const Z0: f64 = 0.934;
    const Q0: f64 = 0.0;

    fn tick(step: u64) -> Tick {
        Tick::at_control_step(step, step as f64 * 0.05)
    }

    fn progress() -> HammerProgress {
        HammerProgress::new(&crate::judge::test_params::parsed("T29"), Z0, Q0)
    }

    fn at(z_above_m: f64, q_m: f64, contact: bool) -> HammerSample {
        HammerSample { hammer_z_m: Z0 + z_above_m, nail_q_m: Q0 + q_m, contact }
    }

    fn feed(p: &mut HammerProgress, samples: &[HammerSample]) {
        for (k, s) in samples.iter().enumerate() {
            p.observe(tick(k as u64 + 1), *s);
        }
    }

    fn completed(p: &HammerProgress) -> usize {
        p.stages().completed_required_count()
    }

    #[test]
    fn lift_contact_drive_completes_one_stage_per_tick() {
        let mut p = progress();
        // everything holds at once: still one stage per tick
        feed(&mut p, &[at(0.05, 0.08, true), at(0.05, 0.08, true), at(0.05, 0.08, true)]);
        assert_eq!(completed(&p), 3);
        let steps: Vec<u64> = p.stages().events().iter().map(|e| e.tick.control_step).collect();
        assert_eq!(steps, [1, 2, 3]);
        assert!(p.success(Q0 + 0.08));
        assert!(!p.success(Q0 + 0.07), "the final displacement must still reach the threshold");
    }

    #[test]
    fn lift_threshold_is_inclusive_at_4_5_cm() {
        let mut p = progress();
        feed(&mut p, &[at(0.0449, 0.0, false)]);
        assert_eq!(completed(&p), 0);
        feed(&mut p, &[at(0.045, 0.0, false)]);
        assert_eq!(completed(&p), 1);
    }

    #[test]
    fn contact_before_the_lift_does_not_complete_stage_two_but_counts_for_the_drive() {
        let mut p = progress();
        // the hammer pushes the nail in without being lifted: contact seen, nail driven, stage 1 never holds
        feed(&mut p, &[at(0.0, 0.01, true), at(0.0, 0.08, true), at(0.0, 0.08, false)]);
        assert!(p.contact_seen());
        assert_eq!(completed(&p), 0);
        // lifted afterwards without touching again: stage 2 needs a contact while it is current
        feed(&mut p, &[at(0.06, 0.08, false), at(0.06, 0.08, false)]);
        assert_eq!(completed(&p), 1);
        assert!(!p.success(Q0 + 0.08));
        feed(&mut p, &[at(0.06, 0.08, true), at(0.06, 0.08, false)]);
        assert_eq!(completed(&p), 3, "the latched contact and the driven nail complete stage 3 at the next tick");
    }

    #[test]
    fn a_nail_driven_without_any_contact_never_completes_stage_three() {
        let mut p = progress();
        // e.g. pushed with the fingers: lift, then the nail moves but the hammer never touches it
        feed(&mut p, &[at(0.06, 0.0, false), at(0.06, 0.09, false), at(0.06, 0.10, false)]);
        assert_eq!(completed(&p), 1);
        assert!(!p.contact_seen());
        assert!(!p.success(Q0 + 0.10));
    }

    #[test]
    fn drive_needs_7_5_cm_from_the_reset_position() {
        let mut p = HammerProgress::new(&crate::judge::test_params::parsed("T29"), Z0, 0.01);
        feed(&mut p, &[at(0.05, 0.0, true), at(0.05, 0.0, true), at(0.05, 0.084, true)]);
        assert_eq!(completed(&p), 2, "0.084 − 0.01 < 0.075");
        feed(&mut p, &[at(0.05, 0.086, true)]);
        assert_eq!(completed(&p), 3);
    }

    #[test]
    fn setting_the_hammer_down_regresses_stage_one_once_per_drop() {
        let mut p = progress();
        feed(&mut p, &[at(0.05, 0.0, false), at(0.0, 0.0, false), at(0.0, 0.0, false), at(0.05, 0.0, false), at(0.01, 0.0, false)]);
        let mut r = EvaluationRecord::new(CHECKER);
        p.stages().write_into(&mut r);
        assert_eq!(r.completed_required_stage_count, 1, "a regressed stage stays completed");
        assert_eq!(r.stage_regressions.len(), 1);
        assert_eq!((r.stage_regressions[0].stage_name.as_str(), r.stage_regressions[0].count), ("01_Lift_Hammer", 2));
    }

    #[test]
    fn the_contact_stage_never_regresses_and_the_drive_stage_does_when_the_nail_backs_out() {
        let mut p = progress();
        feed(&mut p, &[at(0.05, 0.0, false), at(0.05, 0.0, true), at(0.05, 0.08, false), at(0.05, 0.08, false), at(0.05, 0.07, false)]);
        let mut r = EvaluationRecord::new(CHECKER);
        p.stages().write_into(&mut r);
        assert_eq!(r.completed_required_stage_count, 3);
        let names: Vec<&str> = r.stage_regressions.iter().map(|s| s.stage_name.as_str()).collect();
        assert_eq!(names, ["03_Drive_Nail"]);
        assert!(p.stages().events().iter().any(|e| e.kind == EventKind::StageRegressed));
        assert!(!p.success(Q0 + 0.07));
    }

    #[test]
    fn params_parse_from_manifest_json() {
        let p: HammerParams = serde_json::from_value(json!({
            "hammer_lift_m": 0.045, "nail_joint": "hammer_block_1_nail_slide", "nail_drive_m": 0.075,
            "contact_distance_max_m": 0.001, "stages": STAGES, "hammer": "hammer_1", "nail_body": "hammer_block_1_nail_link"
        }))
        .unwrap();
        assert_eq!((p.hammer_lift_m, p.nail_drive_m, p.contact_distance_max_m), (0.045, 0.075, 0.001));
        assert_eq!(p.stages, STAGES);
    }
}
