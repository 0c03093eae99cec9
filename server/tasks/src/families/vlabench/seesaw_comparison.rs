//! `private_ordered_physical_seesaw`, variant `active_weight_comparison`: the pool's `vlabench_physical/2`
//! active_weight_comparison (task catalog §7; the original's `VLABenchActiveWeightComparisonEvaluator`). Two weights
//! that look the same (private masses, written into the model per episode) must each be probed alone on the seesaw's
//! far end, with the board back at rest in between, and the heavier one then put in the basket.
//!
//! Sampled at control steps only. Per sample, in this order (as the original):
//! * on the far end: a candidate's root in the far-end box ([`SeesawRig::on_far_end`], position only: a candidate
//!   held over the far end counts); touching: its body subtree touches the moving board; a candidate seen touching is
//!   remembered;
//! * neutral reset, while the first probe is known and the second not yet: a sample with no candidate on the far end,
//!   none touching the board, |hinge − hinge at reset| ≤ `neutral_hinge_tolerance_rad` and |hinge velocity| ≤
//!   `neutral_hinge_velocity_max_rad_s` counts one; any other sample restarts the count until it has reached
//!   `neutral_steps`, which opens the reset gate for good;
//! * responses: for the first probe while it is on the far end, and the second while it is, the largest
//!   |hinge − hinge at reset| so far (both against the reset pose);
//! * the first probe is the one candidate alone on the far end (the first sample with exactly one); the second is the
//!   other candidate alone on the far end and touching the board once the gate is open;
//! * the current stage, at most one per sample.
//!
//! Stages, in order ([`ComparisonProgress`]):
//! 1. `01_Probe_First_Candidate` — the first probe on the far end, seen touching the board, response ≥
//!    `min_response_rad`;
//! 2. `02_Probe_Second_Candidate_After_Reset` — the first probe off the far end, the second on it, having touched the
//!    board after the gate opened, the gate open, response ≥ `min_response_rad`;
//! 3. `03_Mass_Response_Agrees_With_MuJoCo` — both responses recorded, both ≥ `min_response_rad`, and the heavier
//!    candidate's (by the model's masses) > the lighter's + `response_margin_rad`; testing it names the heavier one
//!    the *winner*;
//! 4. `04_Place_Dynamically_Heavier_Candidate` — the winner In the basket region AND in contact with the basket.
//!
//! Success at finish ⇔ all stages AND stage 3 seen AND both candidates seen touching the board AND the winner In the
//! basket region with basket contact. Completed stages are not re-tested (a probe leaves the far end by design).
use std::collections::BTreeMap;

use libero_sim::mujoco_rs::prelude::MjModel;
use libero_sim::simulation::SimData;
use serde::Deserialize;

use crate::TasksError;
use crate::families::vlabench::seesaw::{CHECKER, GeomMask, SeesawRig};
use crate::judge::evaluator::{EvaluationRecord, StageSpec, StageTracker, Tick};
use crate::judge::family::{History, StagedFamily, build, judge_checks, terminal_check};
use crate::judge::kind::{EvaluatorKind, check};
use crate::judge::predicates::CompiledAtom;
use crate::judge::support::{instance_mass, missing_in_model, set_instance_masses};

/// The `variant` of the checker's params that selects this evaluator.
pub const VARIANT: &str = "active_weight_comparison";
pub const STAGES: [&str; 4] = [
    "01_Probe_First_Candidate",
    "02_Probe_Second_Candidate_After_Reset",
    "03_Mass_Response_Agrees_With_MuJoCo",
    "04_Place_Dynamically_Heavier_Candidate",
];

/// The seesaw kind's row for this variant: the private masses are written into the model before the episode.
pub const EVALUATOR: EvaluatorKind = EvaluatorKind {
    variant: Some(VARIANT),
    model_edits: Some(|checker, model| {
        let p: ComparisonParams = checker.parse()?;
        set_instance_masses(CHECKER, &p.masses_kg, model)
    }),
    ..EvaluatorKind::plain(CHECKER, check::<ComparisonParams>, |checker, scene, model| {
        build(checker, scene, model, |h| WeightComparison::new(checker.parse()?, h, model))
    })
};

/// The checker's params (every field from the pool entry's definition, `masses_kg` the private part).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ComparisonParams {
    pub variant: String,
    pub seesaw: String,
    pub hinge_joint: String,
    pub far_end_site: String,
    /// The two candidates, in the order the original iterates them.
    pub candidates: Vec<String>,
    /// Private: candidate instance → mass (kg), written into the compiled model before the episode starts.
    pub masses_kg: BTreeMap<String, f64>,
    pub basket: String,
    pub basket_region: String,
    pub weight_xy_max_m: f64,
    pub weight_dz_range_m: [f64; 2],
    pub min_response_rad: f64,
    pub response_margin_rad: f64,
    pub neutral_steps: u32,
    pub neutral_hinge_tolerance_rad: f64,
    pub neutral_hinge_velocity_max_rad_s: f64,
    #[serde(deserialize_with = "crate::judge::stage_types::stage_names")]
    pub stages: Vec<String>,
}

/// What one sample measured, per candidate in `candidates` order.
#[derive(Debug, Clone, PartialEq)]
pub struct ComparisonSample {
    pub on_far_end: [bool; 2],
    pub touching_board: [bool; 2],
    /// qpos(hinge) − qpos at reset.
    pub hinge_delta_rad: f64,
    pub hinge_velocity_rad_s: f64,
    /// In the basket region AND touching the basket.
    pub in_basket: [bool; 2],
}

/// The thresholds of [`ComparisonProgress`].
#[derive(Debug, Clone, Copy)]
pub struct ComparisonGates {
    pub min_response_rad: f64,
    pub response_margin_rad: f64,
    pub neutral_steps: u32,
    pub neutral_hinge_tolerance_rad: f64,
    pub neutral_hinge_velocity_max_rad_s: f64,
}

impl From<&ComparisonParams> for ComparisonGates {
    fn from(p: &ComparisonParams) -> Self {
        Self {
            min_response_rad: p.min_response_rad,
            response_margin_rad: p.response_margin_rad,
            neutral_steps: p.neutral_steps,
            neutral_hinge_tolerance_rad: p.neutral_hinge_tolerance_rad,
            neutral_hinge_velocity_max_rad_s: p.neutral_hinge_velocity_max_rad_s,
        }
    }
}

/// The stage logic on measured samples (no simulator).
#[derive(Debug, Clone)]
pub struct ComparisonProgress {
    /// Candidate indices, lighter first (ties: the earlier candidate counts as the lighter, as Python's stable sort).
    by_mass: [usize; 2],
    gates: ComparisonGates,
    pub stages: StageTracker,
    seen: [bool; 2],
    response_rad: [Option<f64>; 2],
    first: Option<usize>,
    second: Option<usize>,
    winner: Option<usize>,
    neutral_steps: u32,
    gate_open: bool,
    second_contact_after_reset: bool,
}

impl ComparisonProgress {
    pub fn new(names: &[String], masses_kg: [f64; 2], gates: ComparisonGates) -> Self {
        Self {
            by_mass: if masses_kg[1] < masses_kg[0] { [1, 0] } else { [0, 1] },
            gates,
            stages: StageTracker::new(names.iter().map(StageSpec::required).collect()),
            seen: [false; 2],
            response_rad: [None; 2],
            first: None,
            second: None,
            winner: None,
            neutral_steps: 0,
            gate_open: false,
            second_contact_after_reset: false,
        }
    }

    pub fn first(&self) -> Option<usize> {
        self.first
    }

    pub fn second(&self) -> Option<usize> {
        self.second
    }

    pub fn winner(&self) -> Option<usize> {
        self.winner
    }

    pub fn responses_rad(&self) -> [Option<f64>; 2] {
        self.response_rad
    }

    pub fn neutral(&self) -> (u32, bool) {
        (self.neutral_steps, self.gate_open)
    }

    pub fn both_seen(&self) -> bool {
        self.seen.iter().all(|s| *s)
    }

    fn response(&self, k: Option<usize>) -> f64 {
        k.and_then(|k| self.response_rad[k]).unwrap_or(0.0)
    }

    fn neutral_reached(&self) -> bool {
        self.gate_open && self.neutral_steps >= self.gates.neutral_steps
    }

    /// Stage 3's test; names the winner whenever both responses exist.
    fn responses_agree_with_mass(&mut self) -> bool {
        let (Some(_), Some(_)) = (self.response_rad[0], self.response_rad[1]) else { return false };
        let [lighter, heavier] = self.by_mass;
        self.winner = Some(heavier);
        let (l, h) = (self.response(Some(lighter)), self.response(Some(heavier)));
        let min = self.gates.min_response_rad;
        l >= min && h >= min && h > l + self.gates.response_margin_rad
    }

    fn holds(&mut self, s: &ComparisonSample, i: usize) -> bool {
        let on = |k: Option<usize>| k.is_some_and(|k| s.on_far_end[k]);
        match i {
            0 => on(self.first) && self.first.is_some_and(|k| self.seen[k]) && self.response(self.first) >= self.gates.min_response_rad,
            1 => {
                self.second.is_some()
                    && !on(self.first)
                    && on(self.second)
                    && self.second_contact_after_reset
                    && self.neutral_reached()
                    && self.response(self.second) >= self.gates.min_response_rad
            }
            2 => self.responses_agree_with_mass(),
            _ => self.winner.is_some_and(|k| s.in_basket[k]),
        }
    }

    pub fn observe(&mut self, s: &ComparisonSample, tick: Tick) {
        let on_board: Vec<usize> = (0..2).filter(|&k| s.on_far_end[k]).collect();
        for k in 0..2 {
            self.seen[k] |= s.touching_board[k];
        }
        if self.first.is_some() && self.second.is_none() {
            let neutral = on_board.is_empty()
                && !s.touching_board.iter().any(|t| *t)
                && s.hinge_delta_rad.abs() <= self.gates.neutral_hinge_tolerance_rad
                && s.hinge_velocity_rad_s.abs() <= self.gates.neutral_hinge_velocity_max_rad_s;
            if neutral {
                self.neutral_steps += 1;
                if self.neutral_steps >= self.gates.neutral_steps {
                    self.gate_open = true;
                }
            } else if !self.gate_open {
                self.neutral_steps = 0;
            }
        }
        for k in [self.first, self.second].into_iter().flatten() {
            if s.on_far_end[k] {
                let r = self.response_rad[k].get_or_insert(0.0);
                *r = r.max(s.hinge_delta_rad.abs());
            }
        }
        match (self.first, self.second) {
            (None, _) if on_board.len() == 1 => self.first = Some(on_board[0]),
            (Some(first), None)
                if self.neutral_reached() && on_board.len() == 1 && on_board[0] != first && s.touching_board[on_board[0]] =>
            {
                self.second = Some(on_board[0]);
                self.second_contact_after_reset = true;
            }
            _ => {}
        }
        let Some(i) = self.stages.current() else { return };
        let holds = self.holds(s, i);
        self.stages.advance(tick, |_| holds);
    }

    /// The terminal checks on the final sample, by the original's names.
    pub fn terminal_checks(&self, s: &ComparisonSample) -> Vec<(&'static str, bool)> {
        vec![
            ("mass_response_order_observed", self.stages.is_completed(2)),
            ("both_candidates_contacted_seesaw", self.both_seen()),
            ("dynamically_heavier_candidate_in_basket", self.winner.is_some_and(|k| s.in_basket[k])),
        ]
    }
}

/// The variant's stage logic on the simulation (the shared skeleton: [`crate::judge::family`]).
pub struct WeightComparison {
    params: ComparisonParams,
    candidates: [usize; 2],
    candidate_geoms: [GeomMask; 2],
    basket: usize,
    in_region: [CompiledAtom; 2],
    masses_kg: [f64; 2],
    rig: SeesawRig,
    hinge0_rad: f64,
    progress: ComparisonProgress,
}

impl WeightComparison {
    pub fn new(params: ComparisonParams, history: &History, model: &MjModel) -> Result<Self, TasksError> {
        if params.variant != VARIANT || params.candidates.len() != 2 || params.stages.len() != STAGES.len() {
            return Err(TasksError::Scene(format!(
                "{CHECKER} ({VARIANT}): needs variant {VARIANT:?}, exactly two candidates and {} stages",
                STAGES.len()
            )));
        }
        let index = &history.index;
        let instance = |n: &str| index.instance(n).ok_or_else(|| missing_in_model(CHECKER, "instance", n));
        let candidates = [instance(&params.candidates[0])?, instance(&params.candidates[1])?];
        let basket = instance(&params.basket)?;
        let candidate_geoms = candidates.map(|c| GeomMask::subtree(model, index.instances[c].body));
        let in_region = |name: &String| {
            let atom = libero_bddl::Atom {
                predicate: "In".into(),
                args: vec![name.clone(), params.basket_region.clone()],
                pos: Default::default(),
            };
            CompiledAtom::compile(index, &atom)
        };
        let in_region = [in_region(&params.candidates[0])?, in_region(&params.candidates[1])?];
        // the live model's masses, as the original reads `body_mass` (the private params have been written there)
        let masses_kg = [instance_mass(CHECKER, model, &params.candidates[0])?, instance_mass(CHECKER, model, &params.candidates[1])?];
        let rig = SeesawRig::new(
            CHECKER,
            model,
            &params.seesaw,
            &params.hinge_joint,
            &params.far_end_site,
            params.weight_xy_max_m,
            params.weight_dz_range_m,
        )?;
        let progress = ComparisonProgress::new(&params.stages, masses_kg, (&params).into());
        Ok(Self {
            params,
            candidates,
            candidate_geoms,
            basket,
            in_region,
            masses_kg,
            rig,
            hinge0_rad: 0.0,
            progress,
        })
    }

    fn measure(&self, h: &History, data: &SimData) -> ComparisonSample {
        let body = |k: usize| h.index.instances[self.candidates[k]].body;
        ComparisonSample {
            on_far_end: [0, 1].map(|k| self.rig.on_far_end(data, body(k))),
            touching_board: [0, 1].map(|k| self.rig.touches_board(data, &self.candidate_geoms[k])),
            hinge_delta_rad: self.rig.hinge_rad(data) - self.hinge0_rad,
            hinge_velocity_rad_s: self.rig.hinge_velocity(data),
            in_basket: [0, 1].map(|k| {
                self.in_region[k].evaluate(&h.index, data) && h.index.in_contact(data, self.basket, self.candidates[k])
            }),
        }
    }

    fn name(&self, k: Option<usize>) -> Option<&str> {
        k.map(|k| self.params.candidates[k].as_str())
    }
}

impl StagedFamily for WeightComparison {
    fn checker(&self) -> &str {
        CHECKER
    }

    fn reset(&mut self, _history: &History, data: &SimData) {
        self.hinge0_rad = self.rig.hinge_rad(data);
        self.progress = ComparisonProgress::new(&self.params.stages, self.masses_kg, (&self.params).into());
    }

    fn sample(&mut self, h: &mut History, data: &SimData, tick: Tick, _control: bool) {
        let s = self.measure(h, data);
        self.progress.observe(&s, tick);
    }

    fn stages(&self) -> &StageTracker {
        &self.progress.stages
    }

    fn judge(&self, h: &History, data: &SimData, record: &mut EvaluationRecord) {
        let s = self.measure(h, data);
        let checks = self.progress.terminal_checks(&s).into_iter().map(|(name, passed)| terminal_check(name, passed)).collect();
        judge_checks(record, &self.progress.stages, checks);
        let names = &self.params.candidates;
        let masses: BTreeMap<&str, f64> = names.iter().map(String::as_str).zip(self.masses_kg).collect();
        let responses: BTreeMap<&str, Option<f64>> =
            names.iter().map(String::as_str).zip(self.progress.responses_rad()).collect();
        let (neutral_steps, gate_open) = self.progress.neutral();
        record.details = Some(serde_json::json!({
            "variant": VARIANT,
            "candidate_masses_kg": masses,
            "trial_response_rad": responses,
            "first_candidate": self.name(self.progress.first()),
            "second_candidate": self.name(self.progress.second()),
            "winner": self.name(self.progress.winner()),
            "neutral_hinge_stable_steps": neutral_steps,
            "reset_gate_open": gate_open,
            "hinge_delta_rad": s.hinge_delta_rad,
            "candidates_in_basket_at_finish": names.iter().zip(s.in_basket).filter(|(_, b)| *b).map(|(n, _)| n).collect::<Vec<_>>(),
        }));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tick(step: u64) -> Tick {
        Tick::at_control_step(step, step as f64 * 0.05)
    }

    /// Candidate 0 is the heavier (1.20 kg against 0.30 kg), as the pool entry's.
    fn progress() -> ComparisonProgress {
        let names: Vec<String> = STAGES.iter().map(|s| s.to_string()).collect();
        ComparisonProgress::new(&names, [1.20, 0.30], (&crate::judge::test_params::parsed::<ComparisonParams>("vlabench_physical/active_weight_comparison")).into())
    }

    fn sample(on: [bool; 2], touching: [bool; 2], hinge: f64, velocity: f64, in_basket: [bool; 2]) -> ComparisonSample {
        ComparisonSample { on_far_end: on, touching_board: touching, hinge_delta_rad: hinge, hinge_velocity_rad_s: velocity, in_basket }
    }

    const NO: [bool; 2] = [false; 2];

    fn completed(p: &ComparisonProgress) -> usize {
        p.stages.completed_required_count()
    }

    /// Probe `k` alone: held over the far end, set down, the board answers `response`, taken off again.
    fn probe(p: &mut ComparisonProgress, k: usize, response: f64, step: &mut u64) {
        let mut on = NO;
        on[k] = true;
        for (touching, hinge) in [(false, 0.0), (true, 0.0), (true, response / 2.0), (true, response), (true, response), (false, response)] {
            let mut t = NO;
            t[k] = touching;
            *step += 1;
            p.observe(&sample(on, t, hinge, 0.0, NO), tick(*step));
        }
    }

    fn neutral(p: &mut ComparisonProgress, n: u64, step: &mut u64) {
        for _ in 0..n {
            *step += 1;
            p.observe(&sample(NO, NO, 0.01, 0.05, NO), tick(*step));
        }
    }

    #[test]
    fn probing_both_with_a_reset_between_and_placing_the_heavier_completes_the_four_stages() {
        let (mut p, mut step) = (progress(), 0);
        probe(&mut p, 1, 0.08, &mut step);
        assert_eq!((completed(&p), p.first()), (1, Some(1)), "the light one probed first");
        neutral(&mut p, 3, &mut step);
        assert_eq!(p.neutral(), (3, true));
        probe(&mut p, 0, 0.30, &mut step);
        // admitted at its first touch, stage 2 at its first response, stage 3 at the next sample
        assert_eq!((completed(&p), p.second(), p.winner()), (3, Some(0), Some(0)));
        step += 1;
        p.observe(&sample(NO, NO, 0.0, 0.0, [true, false]), tick(step));
        assert_eq!(completed(&p), 4);
        assert!(p.terminal_checks(&sample(NO, NO, 0.0, 0.0, [true, false])).iter().all(|(_, ok)| *ok));
        // the lighter one in the basket instead fails the last stage's terminal check
        assert!(!p.terminal_checks(&sample(NO, NO, 0.0, 0.0, [false, true]))[2].1);
    }

    #[test]
    fn without_the_neutral_reset_the_second_probe_is_not_admitted() {
        let (mut p, mut step) = (progress(), 0);
        probe(&mut p, 1, 0.08, &mut step);
        neutral(&mut p, 2, &mut step);
        // the board still moving: the count restarts
        step += 1;
        p.observe(&sample(NO, NO, 0.01, 0.5, NO), tick(step));
        assert_eq!(p.neutral(), (0, false));
        probe(&mut p, 0, 0.30, &mut step);
        assert_eq!((completed(&p), p.second()), (1, None));
    }

    #[test]
    fn a_hinge_left_away_from_its_reset_pose_keeps_the_gate_shut() {
        let (mut p, mut step) = (progress(), 0);
        probe(&mut p, 1, 0.08, &mut step);
        for _ in 0..10 {
            step += 1;
            p.observe(&sample(NO, NO, 0.051, 0.0, NO), tick(step));
        }
        assert_eq!(p.neutral(), (0, false));
    }

    #[test]
    fn responses_too_close_fail_the_comparison_and_name_the_winner_anyway() {
        let (mut p, mut step) = (progress(), 0);
        probe(&mut p, 1, 0.300, &mut step);
        neutral(&mut p, 3, &mut step);
        probe(&mut p, 0, 0.302, &mut step);
        assert_eq!(completed(&p), 2);
        for _ in 0..5 {
            step += 1;
            p.observe(&sample(NO, NO, 0.0, 0.0, [true, false]), tick(step));
        }
        assert_eq!((completed(&p), p.winner()), (2, Some(0)));
    }

    #[test]
    fn both_on_the_far_end_at_once_is_no_probe() {
        let (mut p, mut step) = (progress(), 0);
        for _ in 0..5 {
            step += 1;
            p.observe(&sample([true, true], [true, true], 0.4, 0.0, NO), tick(step));
        }
        assert_eq!((completed(&p), p.first()), (0, None));
    }

    #[test]
    fn the_heavier_straight_into_the_basket_completes_nothing() {
        let (mut p, mut step) = (progress(), 0);
        for _ in 0..5 {
            step += 1;
            p.observe(&sample(NO, NO, 0.0, 0.0, [true, false]), tick(step));
        }
        assert_eq!(completed(&p), 0);
        assert!(!p.terminal_checks(&sample(NO, NO, 0.0, 0.0, [true, false])).iter().any(|(_, ok)| *ok));
    }
}
