//! `private_ordered_coffee_brewing` (pool entry `long_horizon_v2/2` place_mug_and_brew_coffee; task catalog §6.2, §7;
//! the original's CoffeeBrewingEvaluator): put the mug under the dispenser, press the brew button while it stands
//! there, leave it there.
//!
//! Sampled at every control step **and** every physics substep (the same rule at both rates). Reset captures the
//! button slide's position q₀ and hides the coffee (the brown capsule `coffee_liquid_visual` is drawn transparent).
//! At each tick, in this order (so several stages may complete at one tick, as in the source):
//! 1. `01_Place_Mug_Under_Dispenser` completes, while current, when `In(mug, mug_region)` holds (the BDDL predicate:
//!    the mug's root inside the machine's `mug_region` box).
//! 2. While stage 2 is current and the mug is placed, a button displacement q − q₀ ≤ 0.003 m **arms** the button. An
//!    armed button pushed to q − q₀ ≥ 0.015 m with the mug placed **brews** (latched; the coffee becomes visible).
//!    `02_Press_Button_While_Mug_Is_Placed` completes, while current, once brewed. A press before the mug stands
//!    there counts for nothing: the button must be seen released with the mug placed, then pressed again.
//! 3. `03_Release_Mug_Under_Dispenser` completes, while current, when brewed, the mug placed, and the mug released
//!    and clear (not grasped, its root ≥ 5.5 cm from the grip site).
//!
//! Success at finish ⇔ all 3 stages completed AND brewed AND, on the final state, the mug placed and released and
//! clear. Regressions (diagnostic, control steps only) are recorded for the two state stages: stage 1 when the mug
//! leaves the region, stage 3 when it leaves or is grasped again; stage 2 is an event and cannot regress.
use libero_bddl::{Atom as BddlAtom, Pos};
use libero_sim::mujoco_rs::prelude::{MjModel, MjtJoint, MjtObjBase};
use libero_sim::simulation::SimData;
use serde::Deserialize;
use serde_json::json;

use crate::TasksError;
use crate::judge::evaluator::{EvaluationRecord, StageSpec, StageTracker, Tick};
use crate::judge::family::{History, StagedFamily, build, judge_checks, terminal_check};
use crate::judge::kind::{EvaluatorKind, check};
use crate::judge::predicates::CompiledAtom;
use crate::judge::support::missing_in_model;

pub const CHECKER: &str = "private_ordered_coffee_brewing";
pub const STAGES: [&str; 3] =
    ["01_Place_Mug_Under_Dispenser", "02_Press_Button_While_Mug_Is_Placed", "03_Release_Mug_Under_Dispenser"];

/// The pool definition's `checker_params` (every field from there: the original's values).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CoffeeParams {
    pub mug: String,
    /// The machine's region site the mug must be `In`.
    pub mug_region: String,
    /// The brew button's slide joint (m, + into the machine).
    pub button_joint: String,
    /// A press: displacement from the reset position ≥ this (m).
    pub press_threshold_m: f64,
    /// Released (re-armed): displacement ≤ this (m).
    pub release_threshold_m: f64,
    /// Released-and-clear: the mug's root at least this far from the grip site (m).
    pub clearance_m: f64,
    /// Geoms whose name ends with this are the coffee, drawn transparent until brewed.
    pub liquid_geom_suffix: String,
    #[serde(deserialize_with = "crate::judge::stage_types::stage_names")]
    pub stages: Vec<String>,
}

/// The kind's table row.
pub const EVALUATOR: EvaluatorKind = EvaluatorKind::plain(CHECKER, check::<CoffeeParams>, |checker, scene, model| {
    build(checker, scene, model, |h| CoffeeBrewing::new(checker.parse()?, h, model))
});

/// What one tick reads from the simulation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CoffeeSample {
    /// `In(mug, mug_region)`.
    pub mug_placed: bool,
    /// Button slide position (m).
    pub button_q_m: f64,
    /// The mug not grasped and its root ≥ the clearance from the grip site.
    pub released: bool,
}

/// The stage logic on samples, independent of MuJoCo (unit-tested below).
#[derive(Debug, Clone)]
pub struct CoffeeProgress {
    press_m: f64,
    release_m: f64,
    q0_m: f64,
    armed_at: Option<Tick>,
    brewed_at: Option<Tick>,
    max_displacement_m: f64,
    stages: StageTracker,
}

impl CoffeeProgress {
    /// Starts from the button's reset position.
    pub fn new(params: &CoffeeParams, q0_m: f64) -> Self {
        Self {
            press_m: params.press_threshold_m,
            release_m: params.release_threshold_m,
            q0_m,
            armed_at: None,
            brewed_at: None,
            max_displacement_m: 0.0,
            stages: StageTracker::new(params.stages.iter().map(StageSpec::required).collect()),
        }
    }

    pub fn displacement_m(&self, button_q_m: f64) -> f64 {
        button_q_m - self.q0_m
    }

    pub fn brewed(&self) -> bool {
        self.brewed_at.is_some()
    }

    pub fn armed(&self) -> bool {
        self.armed_at.is_some()
    }

    /// One sampling tick (control step or substep).
    pub fn observe(&mut self, tick: Tick, s: CoffeeSample) {
        let d = self.displacement_m(s.button_q_m);
        self.max_displacement_m = self.max_displacement_m.max(d);
        self.stages.advance(tick, |i| i == 0 && s.mug_placed);
        let pressing = self.stages.current() == Some(1);
        if pressing && s.mug_placed && d <= self.release_m && self.armed_at.is_none() {
            self.armed_at = Some(tick);
        }
        if self.armed() && s.mug_placed && d >= self.press_m && self.brewed_at.is_none() {
            self.brewed_at = Some(tick);
        }
        let brewed = self.brewed();
        self.stages.advance(tick, |i| i == 1 && brewed);
        self.stages.advance(tick, |i| i == 2 && brewed && s.mug_placed && s.released);
    }

    /// Re-tests the completed state stages (control steps only: a diagnostic).
    pub fn track_regressions(&mut self, tick: Tick, s: CoffeeSample) {
        let brewed = self.brewed();
        self.stages.track_regressions(tick, |i| match i {
            0 => s.mug_placed,
            1 => true,
            _ => brewed && s.mug_placed && s.released,
        });
    }

    pub fn stages(&self) -> &StageTracker {
        &self.stages
    }

    /// Success on the final state.
    pub fn success(&self, last: CoffeeSample) -> bool {
        self.stages.all_required_completed() && self.brewed() && last.mug_placed && last.released
    }

    fn details(&self, last: CoffeeSample, params: &CoffeeParams) -> serde_json::Value {
        json!({
            "button_q0_m": self.q0_m,
            "max_button_displacement_m": self.max_displacement_m,
            "final_button_displacement_m": self.displacement_m(last.button_q_m),
            "required_button_displacement_m": params.press_threshold_m,
            "release_button_displacement_m": params.release_threshold_m,
            "button_armed_after_mug_placement": self.armed(),
            "armed_at": self.armed_at,
            "brewed_at": self.brewed_at,
        })
    }
}

/// The kind's stage logic on the simulation (the shared skeleton: [`crate::judge::family`]).
pub struct CoffeeBrewing {
    params: CoffeeParams,
    mug: usize,
    placed: CompiledAtom,
    button_qpos_adr: usize,
    /// The coffee's geoms and their model colour.
    liquid: Vec<(usize, [f32; 4])>,
    progress: CoffeeProgress,
}

impl CoffeeBrewing {
    pub fn new(params: CoffeeParams, history: &History, model: &MjModel) -> Result<Self, TasksError> {
        let index = &history.index;
        let mug = index.instance(&params.mug).ok_or_else(|| missing_in_model(CHECKER, "object", &params.mug))?;
        let atom = BddlAtom { predicate: "in".into(), args: vec![params.mug.clone(), params.mug_region.clone()], pos: Pos::default() };
        let placed = CompiledAtom::compile(index, &atom)?;
        let joint = model
            .name_to_id(MjtObjBase::mjOBJ_JOINT, &params.button_joint)
            .filter(|&j| model.jnt_type()[j] == MjtJoint::mjJNT_SLIDE)
            .ok_or_else(|| missing_in_model(CHECKER, "slide joint", &params.button_joint))?;
        let button_qpos_adr = model.jnt_qposadr()[joint] as usize;
        let liquid: Vec<(usize, [f32; 4])> = (0..model.ffi().ngeom as usize)
            .filter(|&g| model.id_to_name(MjtObjBase::mjOBJ_GEOM, g).is_some_and(|n| n.ends_with(&params.liquid_geom_suffix)))
            .map(|g| (g, model.geom_rgba()[g]))
            .collect();
        if liquid.is_empty() {
            return Err(missing_in_model(CHECKER, "geom ending in", &params.liquid_geom_suffix));
        }
        let progress = CoffeeProgress::new(&params, 0.0);
        Ok(Self { params, mug, placed, button_qpos_adr, liquid, progress })
    }

    fn read(&self, h: &History, data: &SimData) -> CoffeeSample {
        CoffeeSample {
            mug_placed: self.placed.evaluate(&h.index, data),
            button_q_m: data.qpos()[self.button_qpos_adr],
            released: h.commitment.released_and_clear(&h.index, data, self.mug, self.params.clearance_m),
        }
    }
}

impl StagedFamily for CoffeeBrewing {
    fn checker(&self) -> &str {
        CHECKER
    }

    fn samples_substeps(&self) -> bool {
        true
    }

    fn reset(&mut self, _history: &History, data: &SimData) {
        self.progress = CoffeeProgress::new(&self.params, data.qpos()[self.button_qpos_adr]);
    }

    fn sample(&mut self, h: &mut History, data: &SimData, tick: Tick, control: bool) {
        let s = self.read(h, data);
        self.progress.observe(tick, s);
        if control {
            self.progress.track_regressions(tick, s);
        }
    }

    fn stages(&self) -> &StageTracker {
        self.progress.stages()
    }

    fn judge(&self, h: &History, data: &SimData, record: &mut EvaluationRecord) {
        let (last, p) = (self.read(h, data), &self.progress);
        let checks = vec![
            terminal_check(format!("(in {} {})", self.params.mug, self.params.mug_region), last.mug_placed),
            terminal_check("button_pressed_after_mug_placement", p.brewed()),
            terminal_check(format!("released_and_clear {}", self.params.mug), last.released),
        ];
        judge_checks(record, p.stages(), checks);
        record.details = Some(p.details(last, &self.params));
    }

    fn geom_rgba_overrides(&self) -> Vec<(usize, [f32; 4])> {
        let alpha = if self.progress.brewed() { 1.0 } else { 0.0 };
        self.liquid.iter().map(|&(g, c)| (g, [c[0], c[1], c[2], alpha])).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tick(step: u64) -> Tick {
        Tick::at_control_step(step, step as f64 * 0.05)
    }

    /// The pool entry's own params (the one source of the thresholds).
    fn params() -> CoffeeParams {
        crate::judge::test_params::parsed("long_horizon_v2/place_mug_and_brew_coffee")
    }

    fn progress() -> CoffeeProgress {
        CoffeeProgress::new(&params(), 0.0)
    }

    fn at(mug_placed: bool, button_q_m: f64, released: bool) -> CoffeeSample {
        CoffeeSample { mug_placed, button_q_m, released }
    }

    fn feed(p: &mut CoffeeProgress, samples: &[CoffeeSample]) {
        for (k, s) in samples.iter().enumerate() {
            p.observe(tick(k as u64 + 1), *s);
        }
    }

    fn completed(p: &CoffeeProgress) -> usize {
        p.stages().completed_required_count()
    }

    #[test]
    fn place_release_press_completes_all_three_and_brews() {
        let mut p = progress();
        // placed while still held, let go, then pressed: the press brews and the release stage follows at once
        feed(&mut p, &[at(true, 0.0, false), at(true, 0.0, true), at(true, 0.010, true), at(true, 0.016, true), at(true, 0.0, true)]);
        assert!(p.armed() && p.brewed());
        assert_eq!(completed(&p), 3);
        let steps: Vec<u64> = p.stages().events().iter().map(|e| e.tick.control_step).collect();
        assert_eq!(steps, [1, 4, 4], "the release stage completes at the brewing tick when the mug is already let go");
        assert!(p.success(at(true, 0.0, true)));
        assert!(!p.success(at(false, 0.0, true)), "the mug must still stand there");
        assert!(!p.success(at(true, 0.0, false)), "and be let go");
    }

    #[test]
    fn a_press_before_the_mug_is_placed_does_not_brew() {
        let mut p = progress();
        feed(&mut p, &[at(false, 0.0, true), at(false, 0.025, true), at(false, 0.025, true)]);
        assert!(!p.armed() && !p.brewed());
        // the mug arrives while the button is still held down: not armed until it comes back up
        feed(&mut p, &[at(true, 0.025, true), at(true, 0.020, true)]);
        assert_eq!(completed(&p), 1);
        assert!(!p.armed() && !p.brewed());
        // released with the mug there: armed; nothing more without a new press
        feed(&mut p, &[at(true, 0.002, true), at(true, 0.0, true)]);
        assert!(p.armed() && !p.brewed());
        assert_eq!(completed(&p), 1);
        assert!(!p.success(at(true, 0.0, true)));
    }

    #[test]
    fn thresholds_are_inclusive_at_3_mm_and_15_mm_from_the_reset_position() {
        let mut p = CoffeeProgress::new(&params(), 0.001);
        feed(&mut p, &[at(true, 0.0041, true)]);
        assert!(!p.armed(), "0.0041 − 0.001 > 0.003");
        feed(&mut p, &[at(true, 0.004, true)]);
        assert!(p.armed());
        feed(&mut p, &[at(true, 0.0159, true)]);
        assert!(!p.brewed(), "0.0159 − 0.001 < 0.015");
        feed(&mut p, &[at(true, 0.016, true)]);
        assert!(p.brewed());
    }

    #[test]
    fn pressing_after_the_mug_was_taken_away_again_does_not_brew_and_the_mug_leaving_regresses_stage_one() {
        let mut p = progress();
        feed(&mut p, &[at(true, 0.0, true), at(true, 0.0, true), at(false, 0.0, true), at(false, 0.02, true)]);
        assert!(p.armed() && !p.brewed(), "the press needs the mug in place");
        for (k, s) in [at(true, 0.0, true), at(false, 0.0, true), at(false, 0.0, true)].into_iter().enumerate() {
            p.track_regressions(tick(10 + k as u64), s);
        }
        let mut r = EvaluationRecord::new(CHECKER);
        p.stages().write_into(&mut r);
        assert_eq!(r.completed_required_stage_count, 1);
        assert_eq!(r.stage_regressions.len(), 1);
        assert_eq!((r.stage_regressions[0].stage_name.as_str(), r.stage_regressions[0].count), ("01_Place_Mug_Under_Dispenser", 1));
    }

    #[test]
    fn params_parse_from_pool_json_and_refuse_unknown_or_missing_fields() {
        let p = params();
        assert_eq!((p.press_threshold_m, p.release_threshold_m, p.clearance_m), (0.015, 0.003, 0.055));
        assert_eq!(p.button_joint, "coffee_machine_1_button_slide");
        assert!(serde_json::from_value::<CoffeeParams>(json!({"press_m": 0.02})).is_err());
        let partial = json!({"mug": "mug_1", "press_threshold_m": 0.015, "stages": STAGES});
        let e = serde_json::from_value::<CoffeeParams>(partial).err().map(|e| e.to_string()).unwrap_or_default();
        assert!(e.contains("missing field"), "{e}");
    }
}
