//! `private_ordered_physical_pour` (T20 pour_wine_into_mug; task catalog §4 T20): lift the wine bottle, then tilt it
//! over the mug. Stages `01_Lift_Wine_Bottle` (lift seen) then `02_Pour_Wine_Into_Mug` (≥ 1 pour event), counted by
//! the shared pour counter ([`crate::judge::pouring`]); substeps are counted but ignored.
//!
//! Success ⇔ both stages completed AND a lift observed AND ≥ 1 pour. Nothing is required of the final state.
use libero_sim::mujoco_rs::prelude::{MjModel, MjtObjBase};
use libero_sim::simulation::SimData;
use serde::Deserialize;

use crate::TasksError;
use crate::judge::evaluator::{EvaluationRecord, EventKind, PrivateEvent, StageSpec, StageTracker, Tick};
use crate::judge::family::{History, StagedFamily, build, judge_history, terminal_check};
use crate::judge::kind::{EvaluatorKind, check};
use crate::judge::pouring::{PourCounterConfig, PourTracker};

pub const CHECKER: &str = "private_ordered_physical_pour";
pub const STAGES: [&str; 2] = ["01_Lift_Wine_Bottle", "02_Pour_Wine_Into_Mug"];

/// T20's parameters (manifest `checker.params`, every field from there).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PourParams {
    pub bottle: String,
    pub target_site: String,
    #[serde(flatten)]
    pub counter: PourCounterConfig,
    #[serde(deserialize_with = "crate::judge::stage_types::stage_names")]
    pub stages: Vec<String>,
}

/// The kind's table row.
pub const EVALUATOR: EvaluatorKind = EvaluatorKind::plain(CHECKER, check::<PourParams>, |checker, scene, model| {
    build(checker, scene, model, |h| PourWine::new(checker.parse()?, h, model))
});

/// The kind's stage logic on the simulation (the shared skeleton: [`crate::judge::family`]).
pub struct PourWine {
    params: PourParams,
    bottle_body: usize,
    target_site: usize,
    tracker: PourTracker,
    stages: StageTracker,
}

impl PourWine {
    pub fn new(params: PourParams, history: &History, model: &MjModel) -> Result<Self, TasksError> {
        let index = &history.index;
        let bottle = index.instance(&params.bottle).ok_or_else(|| TasksError::Scene(format!("no object {}", params.bottle)))?;
        let target_site = model
            .name_to_id(MjtObjBase::mjOBJ_SITE, &params.target_site)
            .ok_or_else(|| TasksError::Scene(format!("model has no site {:?}", params.target_site)))?;
        let bottle_body = index.instances[bottle].body;
        let tracker = PourTracker::new(&params.counter, bottle_body, target_site, 0.0);
        let stages = StageTracker::new(params.stages.iter().map(StageSpec::required).collect());
        Ok(Self { bottle_body, params, target_site, tracker, stages })
    }
}

impl StagedFamily for PourWine {
    fn checker(&self) -> &str {
        CHECKER
    }

    /// Substeps are counted but not sampled.
    fn samples_substeps(&self) -> bool {
        true
    }

    fn reset(&mut self, _history: &History, data: &SimData) {
        let z0_m = data.xpos()[self.bottle_body][2];
        self.tracker = PourTracker::new(&self.params.counter, self.bottle_body, self.target_site, z0_m);
        self.stages = StageTracker::new(self.params.stages.iter().map(StageSpec::required).collect());
    }

    fn sample(&mut self, h: &mut History, data: &SimData, tick: Tick, control: bool) {
        if !control {
            return;
        }
        if self.tracker.update(data, tick.control_step).is_some() {
            let event = PrivateEvent { subject: Some(self.params.bottle.clone()), ..PrivateEvent::new(EventKind::PourDetected, tick) };
            h.events.push(event);
        }
        let (lift_seen, pours) = (self.tracker.lift_seen(), self.tracker.pours().len());
        self.stages.advance(tick, |i| if i == 0 { lift_seen } else { pours >= 1 });
    }

    fn stages(&self) -> &StageTracker {
        &self.stages
    }

    fn judge(&self, _history: &History, _data: &SimData, record: &mut EvaluationRecord) {
        let (lift, pours) = (self.tracker.lift_seen(), self.tracker.pours().len());
        // nothing beyond the latched events is checked on the final state (catalog §1.4a); reported for the trace
        let checks = vec![
            terminal_check("lift_observed", lift),
            terminal_check(format!("pour_events >= 1 (count {pours}, max tilt {:.3} rad)", self.tracker.max_tilt_rad()), pours >= 1),
        ];
        judge_history(record, self.stages.all_required_completed() && lift && pours >= 1, checks);
    }
}
