//! `private_ordered_physical_seesaw` (T30 basic_seesaw_usage; task catalog §5 T30, §6.1, VLABenchSeesawEvaluator):
//! put both counterweights on the seesaw's far end, let the board tilt and raise the hidden target out of its guard
//! cage, then put the target in the basket.
//!
//! Sampled at control steps only. Per sample:
//! * far-end anchor f = world position of the site `far_end_site` (fallbacks `<seesaw>_horizontal_radius_site`,
//!   `<seesaw>_top_site`, then the body carrying the hinge);
//! * weight w *on the far end* ⇔ ‖w_xy − f_xy‖ ≤ `weight_xy_max_m` AND `weight_dz_range_m` holds for w_z − f_z;
//!   *supported* ⇔ on the far end AND some contact between w's body subtree and the subtree of the body that carries
//!   the hinge (the moving board: the static rest block and base do not count; no distance filter, as in the
//!   release's seesaw helper); *released* ⇔ supported AND not Grasped(w);
//! * hinge delta = qpos(hinge) − qpos at reset; target lift = z(target root) − z at reset.
//!
//! Stages, in order, at most one per sample ([`SeesawProgress`]): `01_Place_First_Counterweight` (≥ 1 weight
//! released), `02_Place_Second_Counterweight` (all weights released at once; completing it resets the post-placement
//! maxima to max(0, current value)), `03_Physical_Lift_Of_Target` (no premature lift AND all weights released AND
//! post-placement max hinge delta ≥ `hinge_lift_rad` AND max target lift ≥ `target_lift_m`),
//! `04_Place_Target_In_Basket` (BDDL `In(target, basket region)`).
//!
//! Premature-lift guard: while stage 2 is not complete, a sample with hinge delta ≥ `hinge_lift_rad` AND target lift
//! ≥ `target_lift_m` latches `premature_lift_detected` (failure): the target must not be pulled out by hand or the
//! board pressed down before both weights are on.
//!
//! Success at finish ⇔ all stages completed AND target In the basket region AND the lift event (stage 3) seen AND
//! every weight still released on the far end AND no premature lift.
use libero_sim::mujoco_rs::prelude::{MjModel, MjtObjBase};
use libero_sim::simulation::SimData;
use serde::Deserialize;

use crate::TasksError;
use crate::judge::evaluator::{EvaluationRecord, FailureReason, StageSpec, StageTracker, Tick};
use crate::judge::family::{History, StagedFamily, build, judge_checks, terminal_check};
use crate::judge::kind::{EvaluatorKind, check};
use crate::judge::predicates::{CompiledAtom, in_subtree};
use crate::judge::support::missing_in_model;

pub const CHECKER: &str = "private_ordered_physical_seesaw";

/// T30's basic seesaw: the kind's row without a variant.
pub const EVALUATOR: EvaluatorKind = EvaluatorKind::plain(CHECKER, check::<SeesawParams>, |checker, scene, model| {
    build(checker, scene, model, |h| PhysicalSeesaw::new(checker.parse()?, h, model))
});
pub const STAGES: [&str; 4] = [
    "01_Place_First_Counterweight",
    "02_Place_Second_Counterweight",
    "03_Physical_Lift_Of_Target",
    "04_Place_Target_In_Basket",
];

/// The manifest's `checker.params` (every field from the manifest).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SeesawParams {
    pub seesaw: String,
    pub hinge_joint: String,
    pub far_end_site: String,
    pub target: String,
    pub weights: Vec<String>,
    pub basket_region: String,
    pub weight_xy_max_m: f64,
    pub weight_dz_range_m: [f64; 2],
    pub hinge_lift_rad: f64,
    pub target_lift_m: f64,
    #[serde(deserialize_with = "crate::judge::stage_types::stage_names")]
    pub stages: Vec<String>,
}

/// What one sample measured.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SeesawSample {
    /// Weights released (supported on the far end and not grasped).
    pub released: usize,
    pub weights: usize,
    pub hinge_delta_rad: f64,
    pub target_lift_m: f64,
    pub target_in_basket: bool,
}

impl SeesawSample {
    fn all_released(&self) -> bool {
        self.weights > 0 && self.released == self.weights
    }
}

/// The stage logic on measured samples (no simulator): ordered stages, post-placement maxima and the premature-lift
/// latch.
#[derive(Debug, Clone)]
pub struct SeesawProgress {
    hinge_lift_rad: f64,
    target_lift_m: f64,
    pub stages: StageTracker,
    /// Largest hinge delta / target lift since stage 2 completed (`None` before).
    post_max: Option<(f64, f64)>,
    premature_lift: Option<Tick>,
    lift_event: Option<Tick>,
}

impl SeesawProgress {
    pub fn new(names: &[String], hinge_lift_rad: f64, target_lift_m: f64) -> Self {
        Self {
            hinge_lift_rad,
            target_lift_m,
            stages: StageTracker::new(names.iter().map(StageSpec::required).collect()),
            post_max: None,
            premature_lift: None,
            lift_event: None,
        }
    }

    fn lifted(&self, hinge_delta_rad: f64, target_lift_m: f64) -> bool {
        hinge_delta_rad >= self.hinge_lift_rad && target_lift_m >= self.target_lift_m
    }

    fn holds(&self, s: &SeesawSample, i: usize) -> bool {
        match i {
            0 => s.released >= 1,
            1 => s.all_released(),
            2 => {
                self.premature_lift.is_none()
                    && s.all_released()
                    && self.post_max.is_some_and(|(h, l)| self.lifted(h, l))
            }
            _ => s.target_in_basket,
        }
    }

    /// One sample: guard (before the stages, so a lift seen at the step that completes stage 2 is premature), maxima,
    /// then the current stage.
    pub fn observe(&mut self, s: &SeesawSample, tick: Tick) {
        let second_done = self.post_max.is_some();
        if !second_done && self.premature_lift.is_none() && self.lifted(s.hinge_delta_rad, s.target_lift_m) {
            self.premature_lift = Some(tick);
        }
        if let Some((h, l)) = &mut self.post_max {
            *h = h.max(s.hinge_delta_rad);
            *l = l.max(s.target_lift_m);
        }
        let completed = {
            let this = &*self;
            let holds: [bool; STAGES.len()] = std::array::from_fn(|i| this.holds(s, i));
            let done = self.stages.advance(tick, |i| holds.get(i).copied().unwrap_or(false));
            self.stages.track_regressions(tick, |i| holds.get(i).copied().unwrap_or(false));
            done
        };
        match completed {
            Some(1) => self.post_max = Some((s.hinge_delta_rad.max(0.0), s.target_lift_m.max(0.0))),
            Some(2) => self.lift_event = Some(tick),
            _ => {}
        }
    }

    pub fn premature_lift(&self) -> Option<Tick> {
        self.premature_lift
    }

    pub fn lift_event(&self) -> Option<Tick> {
        self.lift_event
    }

    pub fn post_max(&self) -> Option<(f64, f64)> {
        self.post_max
    }
}

/// T30's stage logic on the simulation (the shared skeleton: [`crate::judge::family`]).
pub struct PhysicalSeesaw {
    params: SeesawParams,
    target: usize,
    weights: Vec<usize>,
    rig: SeesawRig,
    /// Per weight: its subtree's geoms.
    weight_geoms: Vec<GeomMask>,
    in_basket: CompiledAtom,
    hinge0_rad: f64,
    target_z0_m: f64,
    progress: SeesawProgress,
}

#[derive(Debug, Clone, Copy)]
enum Anchor {
    Site(usize),
    Body(usize),
}

/// Per geom of the model: whether it belongs to one body subtree.
#[derive(Debug, Clone)]
pub(crate) struct GeomMask(Vec<bool>);

impl GeomMask {
    /// The geoms of `root`'s body subtree.
    pub(crate) fn subtree(model: &MjModel, root: usize) -> Self {
        let (parents, geom_body) = (model.body_parentid(), model.geom_bodyid());
        Self((0..model.ffi().ngeom as usize).map(|g| in_subtree(parents, geom_body[g] as usize, root)).collect())
    }

    fn has(&self, geom: i32) -> bool {
        self.0.get(geom as usize).copied().unwrap_or(false)
    }
}

/// The seesaw as every `private_ordered_physical_seesaw` variant reads it (T30 and the pool's `vlabench_physical` 1
/// and 2, all as the release's seesaw helpers): the hinge, the far-end anchor (`far_end_site`, falling back to
/// `<seesaw>_horizontal_radius_site`, `<seesaw>_top_site`, then the body carrying the hinge), the far-end box around
/// it and the moving board (the subtree of the body that carries the hinge: the static rest block and base do not
/// count).
pub(crate) struct SeesawRig {
    hinge_qpos_adr: usize,
    hinge_dof_adr: usize,
    anchor: Anchor,
    board: GeomMask,
    xy_max_m: f64,
    dz_range_m: [f64; 2],
}

impl SeesawRig {
    pub(crate) fn new(
        checker: &str,
        model: &MjModel,
        seesaw: &str,
        hinge_joint: &str,
        far_end_site: &str,
        xy_max_m: f64,
        dz_range_m: [f64; 2],
    ) -> Result<Self, TasksError> {
        let hinge = model
            .name_to_id(MjtObjBase::mjOBJ_JOINT, hinge_joint)
            .ok_or_else(|| missing_in_model(checker, "joint", hinge_joint))?;
        let board = model.jnt_bodyid()[hinge] as usize;
        let site = |n: &str| model.name_to_id(MjtObjBase::mjOBJ_SITE, n);
        let anchor = [far_end_site.to_owned(), format!("{seesaw}_horizontal_radius_site"), format!("{seesaw}_top_site")]
            .iter()
            .find_map(|n| site(n))
            .map_or(Anchor::Body(board), Anchor::Site);
        Ok(Self {
            hinge_qpos_adr: model.jnt_qposadr()[hinge] as usize,
            hinge_dof_adr: model.jnt_dofadr()[hinge] as usize,
            anchor,
            board: GeomMask::subtree(model, board),
            xy_max_m,
            dz_range_m,
        })
    }

    pub(crate) fn far_end(&self, data: &SimData) -> [f64; 3] {
        match self.anchor {
            Anchor::Site(s) => data.site_xpos()[s],
            Anchor::Body(b) => data.xpos()[b],
        }
    }

    /// Whether a body's origin is in the far-end box: ‖xy − f_xy‖ ≤ `xy_max_m` and z − f_z in `dz_range_m` (position
    /// only: held above the far end counts).
    pub(crate) fn on_far_end(&self, data: &SimData, body: usize) -> bool {
        let f = self.far_end(data);
        let w = data.xpos()[body];
        let [lo, hi] = self.dz_range_m;
        let dz = w[2] - f[2];
        (w[0] - f[0]).hypot(w[1] - f[1]) <= self.xy_max_m && (lo..=hi).contains(&dz)
    }

    /// Some current contact between a geom of `geoms` and a geom of the moving board (no distance filter).
    pub(crate) fn touches_board(&self, data: &SimData, geoms: &GeomMask) -> bool {
        data.contact().iter().any(|c| {
            let (a, b) = (c.geom[0], c.geom[1]);
            (geoms.has(a) && self.board.has(b)) || (self.board.has(a) && geoms.has(b))
        })
    }

    pub(crate) fn hinge_rad(&self, data: &SimData) -> f64 {
        data.qpos()[self.hinge_qpos_adr]
    }

    pub(crate) fn hinge_velocity(&self, data: &SimData) -> f64 {
        data.qvel()[self.hinge_dof_adr]
    }
}

impl PhysicalSeesaw {
    pub fn new(params: SeesawParams, history: &History, model: &MjModel) -> Result<Self, TasksError> {
        let index = &history.index;
        let instance = |n: &str| index.instance(n).ok_or_else(|| missing_in_model(CHECKER, "instance", n));
        let target = instance(&params.target)?;
        let weights = params.weights.iter().map(|w| instance(w)).collect::<Result<Vec<_>, _>>()?;
        let rig = SeesawRig::new(
            CHECKER,
            model,
            &params.seesaw,
            &params.hinge_joint,
            &params.far_end_site,
            params.weight_xy_max_m,
            params.weight_dz_range_m,
        )?;
        let weight_geoms = weights.iter().map(|&w| GeomMask::subtree(model, index.instances[w].body)).collect();
        let atom = libero_bddl::Atom {
            predicate: "In".into(),
            args: vec![params.target.clone(), params.basket_region.clone()],
            pos: Default::default(),
        };
        let in_basket = CompiledAtom::compile(index, &atom)?;
        let progress = SeesawProgress::new(&params.stages, params.hinge_lift_rad, params.target_lift_m);
        Ok(Self { params, target, weights, rig, weight_geoms, in_basket, hinge0_rad: 0.0, target_z0_m: 0.0, progress })
    }

    fn released(&self, h: &History, data: &SimData, k: usize) -> bool {
        self.rig.on_far_end(data, h.index.instances[self.weights[k]].body)
            && self.rig.touches_board(data, &self.weight_geoms[k])
            && !h.commitment.grasped(&h.index, data, self.weights[k])
    }

    fn measure(&self, h: &History, data: &SimData) -> SeesawSample {
        SeesawSample {
            released: (0..self.weights.len()).filter(|&k| self.released(h, data, k)).count(),
            weights: self.weights.len(),
            hinge_delta_rad: self.rig.hinge_rad(data) - self.hinge0_rad,
            target_lift_m: data.xpos()[h.index.instances[self.target].body][2] - self.target_z0_m,
            target_in_basket: self.in_basket.evaluate(&h.index, data),
        }
    }
}

impl StagedFamily for PhysicalSeesaw {
    fn checker(&self) -> &str {
        CHECKER
    }

    fn reset(&mut self, h: &History, data: &SimData) {
        self.hinge0_rad = self.rig.hinge_rad(data);
        self.target_z0_m = data.xpos()[h.index.instances[self.target].body][2];
        self.progress = SeesawProgress::new(&self.params.stages, self.params.hinge_lift_rad, self.params.target_lift_m);
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
        let premature = self.progress.premature_lift();
        let checks = vec![
            terminal_check(format!("(in {} {})", self.params.target, self.params.basket_region), s.target_in_basket),
            terminal_check("lift_event_seen", self.progress.lift_event().is_some()),
            terminal_check(format!("counterweights_released_on_far_end ({}/{})", s.released, s.weights), s.all_released()),
            terminal_check("no_premature_lift", premature.is_none()),
        ];
        judge_checks(record, &self.progress.stages, checks);
        if !record.success && premature.is_some() {
            record.failure_reason = Some(FailureReason::PrematureLiftDetected);
        }
        record.details = Some(serde_json::json!({
            "hinge_delta_rad": s.hinge_delta_rad,
            "target_lift_m": s.target_lift_m,
            "post_placement_max_hinge_delta_rad": self.progress.post_max().map(|m| m.0),
            "post_placement_max_target_lift_m": self.progress.post_max().map(|m| m.1),
            "premature_lift_detected_at": premature,
            "lift_event_at": self.progress.lift_event(),
            "weights_released_at_finish": s.released,
        }));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tick(step: u64) -> Tick {
        Tick::at_control_step(step, step as f64 * 0.05)
    }

    fn progress() -> SeesawProgress {
        let names: Vec<String> = STAGES.iter().map(|s| s.to_string()).collect();
        SeesawProgress::new(&names, 0.12, 0.04)
    }

    fn sample(released: usize, hinge: f64, lift: f64, in_basket: bool) -> SeesawSample {
        SeesawSample { released, weights: 2, hinge_delta_rad: hinge, target_lift_m: lift, target_in_basket: in_basket }
    }

    fn completed(p: &SeesawProgress) -> usize {
        p.stages.completed_required_count()
    }

    #[test]
    fn full_run_completes_the_four_stages_one_per_step() {
        let mut p = progress();
        p.observe(&sample(1, 0.05, 0.01, false), tick(1));
        assert_eq!(completed(&p), 1);
        // both weights down and the target already in the basket: stage 2 only, at most one stage per step
        p.observe(&sample(2, 0.06, 0.015, true), tick(2));
        assert_eq!(completed(&p), 2);
        assert_eq!(p.post_max(), Some((0.06, 0.015)));
        p.observe(&sample(2, 0.40, 0.09, true), tick(3));
        assert_eq!(completed(&p), 3);
        assert_eq!(p.lift_event(), Some(tick(3)));
        p.observe(&sample(2, 0.40, 0.09, true), tick(4));
        assert_eq!(completed(&p), 4);
        assert!(p.premature_lift().is_none());
    }

    #[test]
    fn a_lift_at_the_step_that_places_the_second_weight_is_premature() {
        // the guard is tested before the stages: the lift must follow the placement
        let mut p = progress();
        p.observe(&sample(1, 0.05, 0.01, false), tick(1));
        p.observe(&sample(2, 0.40, 0.09, false), tick(2));
        assert_eq!(completed(&p), 2);
        assert_eq!(p.premature_lift(), Some(tick(2)));
    }

    #[test]
    fn lifting_before_both_weights_are_placed_latches_the_guard_and_blocks_stage_3() {
        let mut p = progress();
        p.observe(&sample(1, 0.05, 0.0, false), tick(1));
        // the board pressed down by hand while only one weight is on: both thresholds at once
        p.observe(&sample(1, 0.13, 0.05, false), tick(2));
        assert_eq!(p.premature_lift(), Some(tick(2)));
        p.observe(&sample(2, 0.40, 0.09, false), tick(3));
        assert_eq!(completed(&p), 2, "stages 1 and 2 still complete");
        for k in 4..10 {
            p.observe(&sample(2, 0.40, 0.09, true), tick(k));
        }
        assert_eq!(completed(&p), 2, "stage 3 never completes after a premature lift");
    }

    #[test]
    fn the_guard_needs_both_thresholds_and_is_off_after_stage_2() {
        let mut p = progress();
        p.observe(&sample(0, 0.20, 0.039, false), tick(1));
        p.observe(&sample(0, 0.119, 0.20, false), tick(2));
        assert!(p.premature_lift().is_none(), "one threshold alone is no lift");
        p.observe(&sample(1, 0.0, 0.0, false), tick(3));
        p.observe(&sample(2, 0.0, 0.0, false), tick(4));
        p.observe(&sample(2, 0.30, 0.08, false), tick(5));
        assert!(p.premature_lift().is_none(), "after stage 2 the lift is the intended one");
        assert_eq!(completed(&p), 3);
    }

    #[test]
    fn stage_2_resets_the_maxima_so_an_earlier_tilt_does_not_count() {
        let mut p = progress();
        p.observe(&sample(1, 0.0, 0.0, false), tick(1));
        // a tilt without lift before stage 2 (no premature lift: the target did not rise)
        p.observe(&sample(1, 0.50, 0.0, false), tick(2));
        // stage 2 completes while the board is back: maxima start from the current (negative → 0) values
        p.observe(&sample(2, -0.02, -0.01, false), tick(3));
        assert_eq!(completed(&p), 2);
        assert_eq!(p.post_max(), Some((0.0, 0.0)));
        p.observe(&sample(2, 0.10, 0.05, false), tick(4));
        assert_eq!(completed(&p), 2, "0.10 rad is below the hinge threshold");
        // the maxima are running maxima: the hinge peak and the lift peak may come at different steps
        p.observe(&sample(2, 0.13, 0.01, false), tick(5));
        assert_eq!(completed(&p), 3);
        assert_eq!(p.post_max(), Some((0.13, 0.05)));
    }

    #[test]
    fn stage_3_needs_both_weights_still_released() {
        let mut p = progress();
        p.observe(&sample(1, 0.0, 0.0, false), tick(1));
        p.observe(&sample(2, 0.0, 0.0, false), tick(2));
        p.observe(&sample(1, 0.40, 0.09, false), tick(3));
        assert_eq!(completed(&p), 2, "a weight was taken off again");
        p.observe(&sample(2, 0.30, 0.05, false), tick(4));
        assert_eq!(completed(&p), 3, "the maxima were kept while the weight was off");
    }

    #[test]
    fn taking_a_weight_off_records_a_regression() {
        let mut p = progress();
        p.observe(&sample(1, 0.0, 0.0, false), tick(1));
        p.observe(&sample(0, 0.0, 0.0, false), tick(2));
        let mut r = EvaluationRecord::new(CHECKER);
        p.stages.write_into(&mut r);
        assert_eq!(r.completed_required_stage_count, 1);
        assert_eq!(r.stage_regressions.len(), 1);
        assert_eq!(r.stage_regressions[0].stage_name, STAGES[0]);
    }
}
