//! `private_ordered_physical_wipe` (T19 wipe_spill_from_table; task catalog §4 T19, §6.6): pick up the sponge, wipe
//! every brown spill marker while pressing the sponge on the tabletop, release it on the blue rest pad.
//!
//! Sampled at every control step **and** every physics substep (the same rule at both rates). Stages, in order
//! (only the current stage is tested; at most one completes per tick; completed stages stay completed):
//! 1. `01_Grasp_Sponge` — Grasped(sponge): both finger pads touch the sponge's contact geoms.
//! 2. `02_Wipe_All_Spill_Markers` — all 7 markers covered.
//! 3. `03_Release_Sponge_On_Blue_Rest_Area` — `On(sponge, spill_patch_1_sponge_rest_region)` (site rule plus contact
//!    with the spill patch's collision geoms, i.e. the rest pad) AND Released-and-clear(sponge): not grasped and the
//!    sponge origin ≥ 0.055 m from the grip site.
//!
//! Coverage (latched, independent of the stage index): at any tick where the sponge is grasped AND in body contact
//! with the `table` body (a contact between the two body subtrees with distance ≤ 1 mm — touching the blue pad does
//! not count), every marker whose world centre is within 0.052 m (xy) of the sponge origin becomes covered. Covered
//! markers vanish from the agent's images ([`crate::judge::evaluator::Evaluator::geom_rgba_overrides`]: alpha 0;
//! uncovered markers are drawn at alpha 0.92, as the original evaluator set them at reset).
//!
//! Success at finish ⇔ all 3 stages completed AND all markers covered AND the rest predicate and Released-and-clear
//! both hold on the final state.
use libero_sim::mujoco_rs::prelude::{MjModel, MjtObjBase};
use libero_sim::simulation::SimData;
use serde::Deserialize;

use crate::TasksError;
use crate::judge::evaluator::{EvaluationRecord, EventKind, PrivateEvent, StageSpec, StageTracker, Tick};
use crate::judge::family::{History, StagedFamily, build, judge_checks, terminal_check};
use crate::judge::kind::{EvaluatorKind, check};
use crate::judge::predicates::{CompiledAtom, SubtreeContact};

pub const CHECKER: &str = "private_ordered_physical_wipe";
pub const STAGES: [&str; 3] = ["01_Grasp_Sponge", "02_Wipe_All_Spill_Markers", "03_Release_Sponge_On_Blue_Rest_Area"];
/// Alpha of an uncovered marker (set at reset) and of a covered one.
pub const MARKER_ALPHA_UNCOVERED: f32 = 0.92;
pub const MARKER_ALPHA_COVERED: f32 = 0.0;
/// Body contact counts only with a penetration/gap distance at most this (catalog §0 "Body contact").
pub const BODY_CONTACT_MAX_DIST_M: f64 = 1e-3;

/// The manifest's `checker.params` (every field from the manifest: it is the one source of the thresholds).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WipeParams {
    pub sponge: String,
    pub spill_patch: String,
    pub markers: usize,
    pub cover_radius_m: f64,
    pub rest_region: String,
    pub release_clear_distance_m: f64,
    pub table_body: String,
    #[serde(deserialize_with = "crate::judge::stage_types::stage_names")]
    pub stages: Vec<String>,
}

/// The kind's table row.
pub const EVALUATOR: EvaluatorKind = EvaluatorKind::plain(CHECKER, check::<WipeParams>, |checker, scene, model| {
    build(checker, scene, model, |h| SpillWipe::new(checker.parse()?, h, model))
});

/// Which markers a sponge at `sponge_xy` covers: those whose centre is within `radius` (xy).
pub fn markers_under(sponge_xy: [f64; 2], markers_xy: &[[f64; 2]], radius: f64) -> impl Iterator<Item = usize> + '_ {
    markers_xy
        .iter()
        .enumerate()
        .filter(move |(_, m)| (m[0] - sponge_xy[0]).hypot(m[1] - sponge_xy[1]) <= radius)
        .map(|(i, _)| i)
}

/// The coverage rule on one tick: returns the markers newly covered (and latches them in `covered`).
pub fn cover(
    covered: &mut [bool],
    grasped: bool,
    touching_table: bool,
    sponge_xy: [f64; 2],
    markers_xy: &[[f64; 2]],
    radius: f64,
) -> Vec<usize> {
    if !(grasped && touching_table) {
        return Vec::new();
    }
    let new: Vec<usize> = markers_under(sponge_xy, markers_xy, radius).filter(|&i| !covered[i]).collect();
    for &i in &new {
        covered[i] = true;
    }
    new
}

/// The kind's stage logic on the simulation (the shared skeleton: [`crate::judge::family`]).
pub struct SpillWipe {
    params: WipeParams,
    sponge: usize,
    /// Geom ids of the markers and their model colours.
    marker_geoms: Vec<(usize, [f32; 4])>,
    /// Body contact(sponge, table).
    sponge_on_table: SubtreeContact,
    rest_on: CompiledAtom,
    covered: Vec<bool>,
    grasp_seen: bool,
    stages: StageTracker,
}

impl SpillWipe {
    pub fn new(params: WipeParams, history: &History, model: &MjModel) -> Result<Self, TasksError> {
        let index = &history.index;
        let sponge = index.instance(&params.sponge).ok_or_else(|| TasksError::Scene(format!("no object {}", params.sponge)))?;
        let id = |kind, name: &str| {
            model.name_to_id(kind, name).ok_or_else(|| TasksError::Scene(format!("model has no {kind:?} {name:?}")))
        };
        let table = id(MjtObjBase::mjOBJ_BODY, &params.table_body)?;
        let ngeom = model.ffi().ngeom as usize;
        let mut marker_geoms = Vec::with_capacity(params.markers);
        for i in 0..params.markers {
            let suffix = format!("spill_marker_{i}");
            let g = (0..ngeom)
                .find(|&g| model.id_to_name(MjtObjBase::mjOBJ_GEOM, g).is_some_and(|n| n.ends_with(&suffix)))
                .ok_or_else(|| TasksError::Scene(format!("model has no geom named *{suffix}")))?;
            let c = model.geom_rgba()[g];
            marker_geoms.push((g, [c[0], c[1], c[2], c[3]]));
        }
        let sponge_on_table = SubtreeContact::new(model, index.instances[sponge].body, table, BODY_CONTACT_MAX_DIST_M);
        let atom = libero_bddl::Atom { predicate: "On".into(), args: vec![params.sponge.clone(), params.rest_region.clone()], pos: Default::default() };
        let rest_on = CompiledAtom::compile(index, &atom)?;
        let stages = StageTracker::new(params.stages.iter().map(StageSpec::required).collect());
        let covered = vec![false; params.markers];
        Ok(Self { params, sponge, marker_geoms, sponge_on_table, rest_on, covered, grasp_seen: false, stages })
    }

    fn grasped(&self, h: &History, data: &SimData) -> bool {
        h.commitment.grasped(&h.index, data, self.sponge)
    }

    fn released_and_clear(&self, h: &History, data: &SimData) -> bool {
        h.commitment.released_and_clear(&h.index, data, self.sponge, self.params.release_clear_distance_m)
    }

    fn rest_holds(&self, h: &History, data: &SimData) -> bool {
        self.rest_on.evaluate(&h.index, data)
    }

    fn markers_xy(&self, data: &SimData) -> Vec<[f64; 2]> {
        self.marker_geoms.iter().map(|(g, _)| {
            let p = data.geom_xpos()[*g];
            [p[0], p[1]]
        }).collect()
    }

    fn stage_holds(&self, h: &History, data: &SimData, i: usize) -> bool {
        match i {
            0 => self.grasped(h, data),
            1 => self.covered.iter().all(|c| *c),
            _ => self.rest_holds(h, data) && self.released_and_clear(h, data),
        }
    }
}

impl StagedFamily for SpillWipe {
    fn checker(&self) -> &str {
        CHECKER
    }

    fn samples_substeps(&self) -> bool {
        true
    }

    fn reset(&mut self, _history: &History, _data: &SimData) {
        self.covered.iter_mut().for_each(|c| *c = false);
        self.grasp_seen = false;
        self.stages = StageTracker::new(self.params.stages.iter().map(StageSpec::required).collect());
    }

    fn sample(&mut self, h: &mut History, data: &SimData, tick: Tick, _control: bool) {
        let grasped = self.grasped(h, data);
        self.grasp_seen |= grasped;
        if self.grasp_seen && grasped {
            let p = data.xpos()[h.index.instances[self.sponge].body];
            let markers = self.markers_xy(data);
            // Body contact(sponge, table): some contact between the two subtrees with distance ≤ 1 mm
            let touching = self.sponge_on_table.holds(data);
            for i in cover(&mut self.covered, grasped, touching, [p[0], p[1]], &markers, self.params.cover_radius_m) {
                let event = PrivateEvent {
                    subject: Some(format!("{}_spill_marker_{i}", self.params.spill_patch)),
                    ..PrivateEvent::new(EventKind::SpillMarkerCovered, tick)
                };
                h.events.push(event);
            }
        }
        // ordered: only the current stage is tested (the earlier stages' conditions are their prerequisites)
        let holds: [bool; STAGES.len()] = std::array::from_fn(|i| self.stage_holds(h, data, i));
        self.stages.advance(tick, |i| holds[i]);
        self.stages.track_regressions(tick, |i| holds[i]);
    }

    fn stages(&self) -> &StageTracker {
        &self.stages
    }

    fn judge(&self, h: &History, data: &SimData, record: &mut EvaluationRecord) {
        let all_covered = self.covered.iter().all(|c| *c);
        let covered_count = self.covered.iter().filter(|c| **c).count();
        let checks = vec![
            terminal_check(format!("all_spill_markers_covered ({covered_count}/{})", self.covered.len()), all_covered),
            terminal_check(format!("(on {} {})", self.params.sponge, self.params.rest_region), self.rest_holds(h, data)),
            terminal_check(format!("released_and_clear {}", self.params.sponge), self.released_and_clear(h, data)),
        ];
        judge_checks(record, &self.stages, checks);
    }

    fn geom_rgba_overrides(&self) -> Vec<(usize, [f32; 4])> {
        self.marker_geoms
            .iter()
            .zip(&self.covered)
            .map(|((g, c), covered)| {
                (*g, [c[0], c[1], c[2], if *covered { MARKER_ALPHA_COVERED } else { MARKER_ALPHA_UNCOVERED }])
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// World marker centres with the patch root at (0, 0.10) (catalog §4 T19).
    const MARKERS: [[f64; 2]; 7] = [
        [-0.080, 0.065],
        [-0.040, 0.115],
        [0.005, 0.075],
        [0.050, 0.125],
        [0.090, 0.080],
        [-0.095, 0.140],
        [0.105, 0.145],
    ];

    #[test]
    fn coverage_needs_grasp_and_table_contact_and_latches() {
        let mut covered = [false; 7];
        assert!(cover(&mut covered, false, true, [-0.08, 0.065], &MARKERS, 0.052).is_empty(), "not grasped");
        assert!(cover(&mut covered, true, false, [-0.08, 0.065], &MARKERS, 0.052).is_empty(), "lifted off the table");
        assert_eq!(cover(&mut covered, true, true, [-0.08, 0.065], &MARKERS, 0.052), [0]);
        assert!(cover(&mut covered, true, true, [-0.08, 0.065], &MARKERS, 0.052).is_empty(), "already covered");
        // leaving the marker does not uncover it
        assert!(cover(&mut covered, true, true, [0.5, 0.5], &MARKERS, 0.052).is_empty());
        assert!(covered[0]);
    }

    #[test]
    fn coverage_radius_is_0_052_from_the_sponge_origin() {
        let mut covered = [false; 7];
        // 0.051 m from marker 4, farther from all others
        let new = cover(&mut covered, true, true, [0.090 + 0.051, 0.080], &MARKERS, 0.052);
        assert_eq!(new, [4]);
        let mut covered = [false; 7];
        assert!(cover(&mut covered, true, true, [0.090 + 0.053, 0.080 - 0.001], &MARKERS, 0.052).iter().all(|&i| i != 4));
    }

    #[test]
    fn two_strokes_along_the_marker_rows_cover_everything() {
        let mut covered = [false; 7];
        for k in 0..=40 {
            let x = -0.10 + 0.21 * k as f64 / 40.0;
            cover(&mut covered, true, true, [x, 0.075], &MARKERS, 0.052);
            cover(&mut covered, true, true, [x, 0.135], &MARKERS, 0.052);
        }
        assert!(covered.iter().all(|c| *c), "{covered:?}");
    }
}
