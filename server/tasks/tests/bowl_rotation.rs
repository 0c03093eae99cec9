//! T25 rotate_three_bowls_using_empty_plate's evaluator (the staged evaluator with the manifest's strict stages,
//! substep sampling and bowl–table guard) on constructed states of its real scene: bowls moved by editing qpos.
use std::sync::Arc;

use libero_sim::mujoco_rs::prelude::MjtObjBase;
use libero_sim::scene_setup::PreparedScene;
use libero_sim::{AssetPaths, Simulation};
use libero_tasks::judge::evaluator::{EventKind, FailureReason};
use libero_tasks::{Catalog, EvaluationRecord, Evaluator, Tick, build_evaluator};

struct World {
    sim: Simulation,
    ev: Box<dyn Evaluator>,
    step: u64,
}

impl World {
    /// The T25 scene at its manifest seed, settled 10 steps, the evaluator reset.
    fn new() -> Self {
        let catalog = Catalog::discover().unwrap();
        let t = catalog.get("T25").unwrap();
        let paths = AssetPaths::discover().expect("assets cached by scripts/setup.py");
        // the task's start: LIBERO's reset placement for the manifest seed (no init file)
        let prepared = PreparedScene::prepare(&catalog.dir.join(&t.bddl.path), &paths, t.init.seed.unwrap(), None).unwrap();
        let ev = build_evaluator(Some(&t.checker), Some("T25"), &prepared.scene, &prepared.model).unwrap();
        let mut sim = Simulation::new(Arc::new(prepared.model)).unwrap();
        sim.set_init_state(&prepared.start_row).unwrap();
        for _ in 0..10 {
            sim.step([0.0; 7]).unwrap();
        }
        let mut w = Self { sim, ev, step: 0 };
        w.ev.reset(w.sim.data(), Tick::at_control_step(0, w.sim.time_s()));
        w
    }

    fn body_pos(&self, name: &str) -> [f64; 3] {
        let b = self.sim.model().name_to_id(MjtObjBase::mjOBJ_BODY, name).unwrap();
        self.sim.data().xpos()[b]
    }

    /// Puts `bowl` (free joint, upright as it is) at `pos` with zero velocity.
    fn place(&mut self, bowl: &str, pos: [f64; 3]) {
        let model = self.sim.model().clone();
        let j = model.name_to_id(MjtObjBase::mjOBJ_JOINT, &format!("{bowl}_joint0")).unwrap();
        let (qadr, vadr) = (model.jnt_qposadr()[j] as usize, model.jnt_dofadr()[j] as usize);
        let nq = model.ffi().nq as usize;
        let mut row = self.sim.state_row();
        row[1 + qadr..1 + qadr + 3].copy_from_slice(&pos);
        row[1 + nq + vadr..1 + nq + vadr + 6].fill(0.0);
        self.sim.set_init_state(&row).unwrap();
    }

    /// Control steps of the zero action, the evaluator sampling every substep and every control step.
    fn run(&mut self, steps: u64) {
        for _ in 0..steps {
            self.step += 1;
            let (step, ev) = (self.step, &mut self.ev);
            self.sim
                .step_with([0.0; 7], |k, data| {
                    ev.observe_substep(data, Tick { control_step: step, substep: Some(k as u32), sim_time_s: data.ffi().time })
                })
                .unwrap();
            self.ev.observe_control_step(self.sim.data(), Tick::at_control_step(step, self.sim.time_s()));
        }
    }

    fn finish(&mut self) -> EvaluationRecord {
        self.ev.finish(self.sim.data(), Tick::at_control_step(self.step, self.sim.time_s()))
    }

    /// Where `bowl` rests on `plate` (the plate's origin plus the height bowl_1 rests at above plate_1 now).
    fn on_plate(&self, plate: &str) -> [f64; 3] {
        let dz = self.body_pos("akita_black_bowl_1_main")[2] - self.body_pos("plate_1_main")[2];
        let p = self.body_pos(&format!("{plate}_main"));
        [p[0], p[1], p[2] + dz + 0.002]
    }
}

#[test]
fn the_settled_start_has_no_stage_no_table_contact_and_is_sampled_at_substeps() {
    let mut w = World::new();
    assert!(w.ev.samples_substeps());
    w.run(20);
    let r = w.finish();
    assert!(!r.success);
    assert_eq!(r.completed_required_stage_count, 0, "{r:?}");
    assert_eq!(r.failure_reason, Some(FailureReason::IncompleteStage), "the bowls rest on their plates without touching the table");
    assert_eq!(r.substeps_observed, 25 * 20);
}

#[test]
fn a_bowl_set_on_the_tabletop_latches_a_permanent_table_contact_failure() {
    let mut w = World::new();
    // beside the plate row, on the bare table (top at z = 0.90)
    w.place("akita_black_bowl_1", [-0.33, 0.05, 0.905]);
    w.run(10);
    // then the first move done properly: tracking has stopped, the stage does not count
    let target = w.on_plate("plate_4");
    w.place("akita_black_bowl_1", target);
    w.run(20);
    let r = w.finish();
    assert!(!r.success);
    assert_eq!(r.failure_reason, Some(FailureReason::ForbiddenContact), "{r:?}");
    assert_eq!(r.completed_required_stage_count, 0, "no progress after the latch: {r:?}");
    let details = r.details.as_ref().unwrap();
    assert_eq!(details["forbidden_contact"]["name"], "akita_black_bowl_1_touched_tabletop", "{details}");
    assert!(r.events.iter().any(|e| e.kind == EventKind::ForbiddenContact));
}

#[test]
fn the_first_move_completes_stage_one_and_skipping_the_buffer_is_an_ordering_violation() {
    let mut w = World::new();
    let target = w.on_plate("plate_4");
    w.place("akita_black_bowl_1", target);
    w.run(20);
    let r = w.finish();
    assert_eq!(r.completed_required_stage_count, 1, "{r:?}");
    assert_eq!(r.failure_reason, Some(FailureReason::IncompleteStage));

    // bowl_3 onto the buffer plate, then bowl_1 straight onto plate_3: stage 4 holds while stage 1 is current
    let mut w = World::new();
    let buffer = w.on_plate("plate_4");
    w.place("akita_black_bowl_3", buffer);
    w.run(10);
    let right = w.on_plate("plate_3");
    w.place("akita_black_bowl_1", right);
    w.run(20);
    let r = w.finish();
    assert!(!r.success);
    assert_eq!(r.failure_reason, Some(FailureReason::OrderViolation), "{r:?}");
    assert_eq!(r.completed_required_stage_count, 0);
    let details = r.details.as_ref().unwrap();
    assert_eq!(
        details["order_violation_latch"], "04_Move_Buffered_Bowl_To_Right_Plate_before_01_Move_Left_Bowl_To_Empty_Plate",
        "{details}"
    );
}
