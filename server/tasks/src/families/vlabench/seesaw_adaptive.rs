//! `private_ordered_physical_seesaw`, variant `adaptive_mass_selection`: the pool's `vlabench_physical/1`
//! adaptive_seesaw_usage (task catalog §7; the original's `VLABenchAdaptiveSeesawEvaluator`). Three weights that look
//! the same but weigh differently (private masses, written into the model per episode) lie on the table; the agent
//! must choose two whose mass clears a threshold tied to the total, put them on the seesaw, and when the board has
//! tilted and raised the payload, put the payload in the basket.
//!
//! Sampled at control steps only. Per sample, in this order (as the original):
//! * contact: a weight whose body subtree touches the moving board (anywhere on it, held or not; [`SeesawRig`]) is
//!   *seen*; the order in which weights are first seen is kept;
//! * maxima since reset: hinge delta = qpos(hinge) − qpos at reset, payload lift = z(payload root) − z at reset (both
//!   start at 0);
//! * the current stage, at most one per sample.
//!
//! Stages, in order ([`AdaptiveProgress`]):
//! 1. `01_Place_First_Mass_Probe` — exactly one weight in the far-end box (position only) and it has been seen
//!    touching the board;
//! 2. `02_Select_Two_Counterweights` — exactly two weights have ever touched the board. Completing it fixes the
//!    *selection*: the first two weights seen;
//! 3. `03_Observed_Mass_Threshold_Tilt_And_Payload_Lift` — the selection's mass ≥ max(`required_mass_floor_kg`,
//!    `required_mass_fraction` × the three weights' total) AND max hinge delta ≥ `hinge_lift_rad` AND max payload lift
//!    ≥ `payload_lift_m` AND still exactly two weights ever seen;
//! 4. `04_Place_Probed_Payload_In_Basket` — BDDL `In(payload, basket region)`.
//!
//! Success at finish ⇔ all stages AND the payload In the basket region AND stage 3 seen AND max payload lift ≥
//! `payload_lift_m` AND exactly two selected AND the selection's mass clears the threshold AND both selected weights
//! were seen touching the board.
//!
//! As in the original: the maxima run from the reset, not from the selection (stage 3 can only complete after stage
//! 2, so the order is kept, but a tilt seen earlier counts); a weight counts as seen whether or not the hand still
//! holds it; a third weight touching the board before stage 3 blocks it for good; nothing at finish asks that the
//! weights still lie on the board. Completed stages are not re-tested (their conditions are transient by design:
//! stage 1's single probe stops holding when the second weight goes on).
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
pub const VARIANT: &str = "adaptive_mass_selection";
pub const STAGES: [&str; 4] = [
    "01_Place_First_Mass_Probe",
    "02_Select_Two_Counterweights",
    "03_Observed_Mass_Threshold_Tilt_And_Payload_Lift",
    "04_Place_Probed_Payload_In_Basket",
];

/// The seesaw kind's row for this variant: the private masses are written into the model before the episode.
pub const EVALUATOR: EvaluatorKind = EvaluatorKind {
    variant: Some(VARIANT),
    model_edits: Some(|checker, model| {
        let p: AdaptiveParams = checker.parse()?;
        set_instance_masses(CHECKER, &p.masses_kg, model)
    }),
    ..EvaluatorKind::plain(CHECKER, check::<AdaptiveParams>, |checker, scene, model| {
        build(checker, scene, model, |h| AdaptiveSeesaw::new(checker.parse()?, h, model))
    })
};

/// How many weights the selection takes.
const SELECTION: usize = 2;

/// The checker's params (every field from the pool entry's definition, `masses_kg` the private part).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AdaptiveParams {
    pub variant: String,
    pub seesaw: String,
    pub hinge_joint: String,
    pub far_end_site: String,
    pub payload: String,
    /// The weights in the order the original iterates them (a tie in first contact goes to the earlier one).
    pub weights: Vec<String>,
    /// Private: weight instance → mass (kg), written into the compiled model before the episode starts.
    pub masses_kg: BTreeMap<String, f64>,
    pub basket_region: String,
    pub weight_xy_max_m: f64,
    pub weight_dz_range_m: [f64; 2],
    pub required_mass_floor_kg: f64,
    pub required_mass_fraction: f64,
    pub hinge_lift_rad: f64,
    pub payload_lift_m: f64,
    #[serde(deserialize_with = "crate::judge::stage_types::stage_names")]
    pub stages: Vec<String>,
}

/// What one sample measured, per weight in `weights` order.
#[derive(Debug, Clone, PartialEq)]
pub struct AdaptiveSample {
    pub on_far_end: Vec<bool>,
    pub touching_board: Vec<bool>,
    pub hinge_delta_rad: f64,
    pub payload_lift_m: f64,
    pub payload_in_basket: bool,
}

/// The stage logic on measured samples (no simulator).
#[derive(Debug, Clone)]
pub struct AdaptiveProgress {
    masses_kg: Vec<f64>,
    required_mass_kg: f64,
    hinge_lift_rad: f64,
    payload_lift_m: f64,
    pub stages: StageTracker,
    seen: Vec<bool>,
    /// Weights in the order they first touched the board.
    order: Vec<usize>,
    max_hinge_delta_rad: f64,
    max_payload_lift_m: f64,
    selected: Vec<usize>,
}

impl AdaptiveProgress {
    /// `masses_kg` per weight; the threshold is max(`floor_kg`, `fraction` × their total).
    pub fn new(names: &[String], masses_kg: Vec<f64>, (floor_kg, fraction): (f64, f64), hinge_lift_rad: f64, payload_lift_m: f64) -> Self {
        let total: f64 = masses_kg.iter().sum();
        Self {
            seen: vec![false; masses_kg.len()],
            required_mass_kg: floor_kg.max(fraction * total),
            masses_kg,
            hinge_lift_rad,
            payload_lift_m,
            stages: StageTracker::new(names.iter().map(StageSpec::required).collect()),
            order: Vec::new(),
            max_hinge_delta_rad: 0.0,
            max_payload_lift_m: 0.0,
            selected: Vec::new(),
        }
    }

    pub fn required_mass_kg(&self) -> f64 {
        self.required_mass_kg
    }

    pub fn selected(&self) -> &[usize] {
        &self.selected
    }

    pub fn contact_order(&self) -> &[usize] {
        &self.order
    }

    pub fn selected_mass_kg(&self) -> f64 {
        self.selected.iter().map(|&k| self.masses_kg[k]).sum()
    }

    pub fn maxima(&self) -> (f64, f64) {
        (self.max_hinge_delta_rad, self.max_payload_lift_m)
    }

    fn threshold_met(&self) -> bool {
        self.selected_mass_kg() >= self.required_mass_kg
    }

    fn selected_seen(&self) -> bool {
        self.selected.iter().all(|&k| self.seen[k])
    }

    fn holds(&self, s: &AdaptiveSample, i: usize) -> bool {
        match i {
            0 => {
                let on: Vec<usize> = (0..s.on_far_end.len()).filter(|&k| s.on_far_end[k]).collect();
                on.len() == 1 && on.iter().any(|&k| self.seen[k])
            }
            1 => self.order.len() == SELECTION,
            2 => {
                self.threshold_met()
                    && self.max_hinge_delta_rad >= self.hinge_lift_rad
                    && self.max_payload_lift_m >= self.payload_lift_m
                    && self.order.len() == SELECTION
                    && self.selected_seen()
            }
            _ => s.payload_in_basket,
        }
    }

    /// One sample: contacts, maxima, then the current stage.
    pub fn observe(&mut self, s: &AdaptiveSample, tick: Tick) {
        for (k, &touching) in s.touching_board.iter().enumerate() {
            if touching && !self.seen[k] {
                self.seen[k] = true;
                self.order.push(k);
            }
        }
        self.max_hinge_delta_rad = self.max_hinge_delta_rad.max(s.hinge_delta_rad);
        self.max_payload_lift_m = self.max_payload_lift_m.max(s.payload_lift_m);
        let this = &*self;
        let Some(i) = this.stages.current() else { return };
        let holds = this.holds(s, i);
        if self.stages.advance(tick, |_| holds) == Some(1) {
            self.selected = self.order.iter().take(SELECTION).copied().collect();
        }
    }

    /// The terminal checks on the final sample, by the original's names.
    pub fn terminal_checks(&self, s: &AdaptiveSample) -> Vec<(&'static str, bool)> {
        vec![
            ("payload_in_basket", s.payload_in_basket),
            ("physical_tilt_observed", self.stages.is_completed(2)),
            ("payload_lift_observed", self.max_payload_lift_m >= self.payload_lift_m),
            ("exactly_two_counterweights_selected", self.selected.len() == SELECTION),
            ("selected_mass_threshold_met", self.threshold_met()),
            ("selected_weights_contacted_seesaw", !self.selected.is_empty() && self.selected_seen()),
        ]
    }
}

/// The variant's stage logic on the simulation (the shared skeleton: [`crate::judge::family`]).
pub struct AdaptiveSeesaw {
    params: AdaptiveParams,
    payload: usize,
    /// Root body per weight.
    weight_bodies: Vec<usize>,
    weight_geoms: Vec<GeomMask>,
    masses_kg: Vec<f64>,
    rig: SeesawRig,
    in_basket: CompiledAtom,
    hinge0_rad: f64,
    payload_z0_m: f64,
    progress: AdaptiveProgress,
}

impl AdaptiveSeesaw {
    pub fn new(params: AdaptiveParams, history: &History, model: &MjModel) -> Result<Self, TasksError> {
        if params.variant != VARIANT || params.weights.len() < SELECTION || params.stages.len() != STAGES.len() {
            return Err(TasksError::Scene(format!(
                "{CHECKER} ({VARIANT}): needs variant {VARIANT:?}, at least {SELECTION} weights and {} stages",
                STAGES.len()
            )));
        }
        let index = &history.index;
        let instance = |n: &str| index.instance(n).ok_or_else(|| missing_in_model(CHECKER, "instance", n));
        let payload = instance(&params.payload)?;
        let weight_bodies =
            params.weights.iter().map(|w| instance(w).map(|i| index.instances[i].body)).collect::<Result<Vec<_>, _>>()?;
        let weight_geoms = weight_bodies.iter().map(|&b| GeomMask::subtree(model, b)).collect();
        // the live model's masses, as the original reads `body_mass` (the private params have been written there)
        let masses_kg = params.weights.iter().map(|w| instance_mass(CHECKER, model, w)).collect::<Result<Vec<_>, _>>()?;
        let rig = SeesawRig::new(
            CHECKER,
            model,
            &params.seesaw,
            &params.hinge_joint,
            &params.far_end_site,
            params.weight_xy_max_m,
            params.weight_dz_range_m,
        )?;
        let atom = libero_bddl::Atom {
            predicate: "In".into(),
            args: vec![params.payload.clone(), params.basket_region.clone()],
            pos: Default::default(),
        };
        let in_basket = CompiledAtom::compile(index, &atom)?;
        let progress = Self::fresh_progress(&params, &masses_kg);
        Ok(Self {
            params,
            payload,
            weight_bodies,
            weight_geoms,
            masses_kg,
            rig,
            in_basket,
            hinge0_rad: 0.0,
            payload_z0_m: 0.0,
            progress,
        })
    }

    fn fresh_progress(p: &AdaptiveParams, masses_kg: &[f64]) -> AdaptiveProgress {
        AdaptiveProgress::new(
            &p.stages,
            masses_kg.to_vec(),
            (p.required_mass_floor_kg, p.required_mass_fraction),
            p.hinge_lift_rad,
            p.payload_lift_m,
        )
    }

    fn measure(&self, h: &History, data: &SimData) -> AdaptiveSample {
        AdaptiveSample {
            on_far_end: self.weight_bodies.iter().map(|&b| self.rig.on_far_end(data, b)).collect(),
            touching_board: self.weight_geoms.iter().map(|g| self.rig.touches_board(data, g)).collect(),
            hinge_delta_rad: self.rig.hinge_rad(data) - self.hinge0_rad,
            payload_lift_m: data.xpos()[h.index.instances[self.payload].body][2] - self.payload_z0_m,
            payload_in_basket: self.in_basket.evaluate(&h.index, data),
        }
    }

    fn names(&self, ks: &[usize]) -> Vec<String> {
        ks.iter().map(|&k| self.params.weights[k].clone()).collect()
    }
}

impl StagedFamily for AdaptiveSeesaw {
    fn checker(&self) -> &str {
        CHECKER
    }

    fn reset(&mut self, h: &History, data: &SimData) {
        self.hinge0_rad = self.rig.hinge_rad(data);
        self.payload_z0_m = data.xpos()[h.index.instances[self.payload].body][2];
        self.progress = Self::fresh_progress(&self.params, &self.masses_kg);
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
        let (max_hinge, max_lift) = self.progress.maxima();
        let masses: BTreeMap<&str, f64> =
            self.params.weights.iter().map(String::as_str).zip(self.masses_kg.iter().copied()).collect();
        record.details = Some(serde_json::json!({
            "variant": VARIANT,
            "weight_masses_kg": masses,
            "required_mass_threshold_kg": self.progress.required_mass_kg(),
            "contact_order": self.names(self.progress.contact_order()),
            "selected_weights": self.names(self.progress.selected()),
            "selected_mass_kg": self.progress.selected_mass_kg(),
            "max_hinge_delta_rad": max_hinge,
            "max_payload_lift_m": max_lift,
            "hinge_delta_rad": s.hinge_delta_rad,
            "payload_lift_m": s.payload_lift_m,
            "weights_on_far_end_at_finish": self.names(&(0..s.on_far_end.len()).filter(|&k| s.on_far_end[k]).collect::<Vec<_>>()),
        }));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tick(step: u64) -> Tick {
        Tick::at_control_step(step, step as f64 * 0.05)
    }

    /// The catalog's masses: a = 0.60, b = 0.30, c = 1.20 (threshold max(0.80, 0.58 × 2.10) = 1.218 kg).
    fn progress() -> AdaptiveProgress {
        let names: Vec<String> = STAGES.iter().map(|s| s.to_string()).collect();
        AdaptiveProgress::new(&names, vec![0.60, 0.30, 1.20], (0.80, 0.58), 0.12, 0.04)
    }

    fn sample(on: [bool; 3], touching: [bool; 3], hinge: f64, lift: f64, in_basket: bool) -> AdaptiveSample {
        AdaptiveSample {
            on_far_end: on.to_vec(),
            touching_board: touching.to_vec(),
            hinge_delta_rad: hinge,
            payload_lift_m: lift,
            payload_in_basket: in_basket,
        }
    }

    fn completed(p: &AdaptiveProgress) -> usize {
        p.stages.completed_required_count()
    }

    const NONE: [bool; 3] = [false; 3];

    #[test]
    fn the_threshold_is_tied_to_the_total_mass() {
        let p = progress();
        assert!((p.required_mass_kg() - 1.218).abs() < 1e-12);
        let names: Vec<String> = STAGES.iter().map(|s| s.to_string()).collect();
        let light = AdaptiveProgress::new(&names, vec![0.2, 0.3, 0.4], (0.80, 0.58), 0.12, 0.04);
        assert_eq!(light.required_mass_kg(), 0.80, "the floor holds for light sets");
    }

    #[test]
    fn the_heavy_pair_completes_the_four_stages_one_per_sample() {
        let mut p = progress();
        // c held above the far end, not yet touching: no probe yet
        p.observe(&sample([false, false, true], NONE, 0.0, 0.0, false), tick(1));
        assert_eq!(completed(&p), 0);
        // c set down: the first probe; the board tilts at once
        p.observe(&sample([false, false, true], [false, false, true], 0.5, 0.08, false), tick(2));
        assert_eq!(completed(&p), 1);
        p.observe(&sample([true, false, true], [true, false, true], 0.6, 0.10, true), tick(3));
        assert_eq!((completed(&p), p.selected()), (2, &[2usize, 0][..]), "selected in contact order");
        p.observe(&sample([true, false, true], [true, false, true], 0.6, 0.10, true), tick(4));
        assert_eq!(completed(&p), 3);
        p.observe(&sample([true, false, true], [true, false, true], 0.6, 0.10, true), tick(5));
        assert_eq!(completed(&p), 4);
        assert!(p.terminal_checks(&sample(NONE, NONE, 0.0, 0.0, true)).iter().all(|(_, ok)| *ok));
    }

    #[test]
    fn the_light_pair_is_selected_tilts_the_board_and_still_fails_the_mass_gate() {
        let mut p = progress();
        p.observe(&sample([true, false, false], [true, false, false], 0.3, 0.05, false), tick(1));
        p.observe(&sample([true, true, false], [true, true, false], 0.6, 0.10, false), tick(2));
        assert_eq!(p.selected(), &[0usize, 1][..]);
        for k in 3..10 {
            p.observe(&sample([true, true, false], [true, true, false], 0.6, 0.10, true), tick(k));
        }
        assert_eq!(completed(&p), 2, "0.90 kg < 1.218 kg");
        let checks = p.terminal_checks(&sample(NONE, NONE, 0.0, 0.0, true));
        assert!(checks.contains(&("selected_mass_threshold_met", false)) && checks.contains(&("payload_in_basket", true)));
    }

    #[test]
    fn one_heavy_and_the_light_weight_clear_the_threshold_too() {
        // 0.30 + 1.20 = 1.50 kg ≥ 1.218: the gate is on the selection's mass, not on which pair
        let mut p = progress();
        p.observe(&sample([false, true, false], [false, true, false], 0.2, 0.0, false), tick(1));
        p.observe(&sample([false, true, true], [false, true, true], 0.6, 0.1, false), tick(2));
        p.observe(&sample([false, true, true], [false, true, true], 0.6, 0.1, false), tick(3));
        assert_eq!(completed(&p), 3);
    }

    #[test]
    fn a_third_weight_on_the_board_before_the_lift_stage_blocks_it() {
        let mut p = progress();
        p.observe(&sample([false, false, true], [false, false, true], 0.0, 0.0, false), tick(1));
        p.observe(&sample([true, false, true], [true, false, true], 0.0, 0.0, false), tick(2));
        assert_eq!(completed(&p), 2);
        // the light weight touches the board (even held) before stage 3 could complete
        p.observe(&sample([true, true, true], [true, true, true], 0.6, 0.1, false), tick(3));
        for k in 4..10 {
            p.observe(&sample([true, true, true], [true, true, true], 0.6, 0.1, true), tick(k));
        }
        assert_eq!(completed(&p), 2);
        assert_eq!(p.contact_order(), &[2usize, 0, 1][..]);
    }

    #[test]
    fn two_weights_touching_at_once_never_make_a_first_probe() {
        // stage 1 needs exactly one weight on the far end
        let mut p = progress();
        p.observe(&sample([true, false, true], [true, false, true], 0.6, 0.1, false), tick(1));
        p.observe(&sample([true, false, true], [true, false, true], 0.6, 0.1, false), tick(2));
        assert_eq!(completed(&p), 0);
        // the tie in first contact goes to the earlier name
        assert_eq!(p.contact_order(), &[0usize, 2][..]);
    }

    #[test]
    fn the_maxima_run_from_the_reset_as_the_original() {
        let mut p = progress();
        // the board pressed by hand before any weight: hinge and lift peaks
        p.observe(&sample(NONE, NONE, 0.4, 0.09, false), tick(1));
        p.observe(&sample(NONE, NONE, 0.0, 0.0, false), tick(2));
        p.observe(&sample([false, false, true], [false, false, true], 0.0, 0.0, false), tick(3));
        p.observe(&sample([true, false, true], [true, false, true], 0.0, 0.0, false), tick(4));
        p.observe(&sample([true, false, true], [true, false, true], 0.0, 0.0, false), tick(5));
        assert_eq!(completed(&p), 3, "the earlier peaks count once the heavy pair is selected");
    }
}
