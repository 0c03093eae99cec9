//! What an agent that only replays its demonstration would earn (issue 48): the trajectory replayed action by
//! action in the target episode, and again after moving the end effector by a constant offset first (the
//! displacement of one object between the source's and the target's start, which an agent that compares the
//! demonstration's video with its own cameras could find). A bundle may be shown in the target only if none of
//! these replays succeeds and none earns more than half the target's stages, nor more than the target's own
//! idle start earns plus one.
use std::collections::BTreeSet;

use libero_sim::mujoco_rs::prelude::MjtObjBase;
use libero_sim::controller::ACTION_SCALE;
use serde::Serialize;

use super::DemoError;
use crate::physics::{WorldPhysics, WorldSpec};

pub use libero_records::demo_manifest::REPLAY_CHECK_METHOD;
/// At most this many offsets are tried (the task's objects of interest first).
pub const MAX_OFFSET_REPLAYS: usize = 6;
/// Displacements shorter than this are not offsets (the same place), longer ones leave the reachable table.
const MIN_OFFSET_M: f64 = 0.01;
const MAX_OFFSET_M: f64 = 0.30;
/// Two displacements closer than this are one offset.
const SAME_OFFSET_M: f64 = 0.01;
/// Control steps allowed to move the end effector by an offset, and how close it must get.
const SHIFT_STEPS: usize = 80;
const SHIFT_TOLERANCE_M: f64 = 0.002;

/// Which replays a bundle must pass: all of them where some source layout does, the direct one where none does.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ReplayRule {
    WithOffsets,
    DirectOnly,
}

/// One replay's outcome.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct ReplayOutcome {
    pub success: bool,
    pub completed_required_stage_count: usize,
}

/// A replay after moving the end effector by `offset_m`, the start displacement of `instance`.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct OffsetReplay {
    pub instance: String,
    pub offset_m: [f64; 3],
    #[serde(flatten)]
    pub outcome: ReplayOutcome,
}

/// Every replay of one bundle in one target, and the verdict.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ReplayAttack {
    pub direct: ReplayOutcome,
    pub offsets: Vec<OffsetReplay>,
    pub required_stage_count: usize,
    /// Stages the target earns when the robot holds still for as long as the demonstration lasts.
    pub idle_completed_stage_count: usize,
}

impl ReplayAttack {
    /// The most stages a replay may earn: half the target's (rounded down), and the idle start's plus one.
    pub fn allowed_stage_count(&self) -> usize {
        (self.required_stage_count / 2).min(self.idle_completed_stage_count + 1)
    }

    /// Every replay with what it was, in words.
    fn labelled(&self) -> impl Iterator<Item = (String, &ReplayOutcome)> {
        let offsets = self.offsets.iter().map(|r| {
            let mm = r.offset_m.map(|d| (d * 1000.0).round());
            (format!("after moving the end effector by {mm:?} mm, {}'s displacement", r.instance), &r.outcome)
        });
        std::iter::once(("direct replay".to_owned(), &self.direct)).chain(offsets)
    }

    pub fn any_success(&self) -> bool {
        self.labelled().any(|(_, o)| o.success)
    }

    /// The most stages any replay earned.
    pub fn best_completed_stage_count(&self) -> usize {
        self.labelled().map(|(_, o)| o.completed_required_stage_count).max().unwrap_or(0)
    }

    /// Whether the bundle may be shown in the target: no replay, direct or offset, succeeds or earns more than
    /// [`Self::allowed_stage_count`].
    pub fn accepted(&self) -> bool {
        !self.any_success() && self.best_completed_stage_count() <= self.allowed_stage_count()
    }

    /// Whether the direct replay alone stays within the rule (what the paper states, and what is required when no
    /// source layout passes the offset replays too, as for a single door any offset lines up again).
    pub fn direct_accepted(&self) -> bool {
        !self.direct.success && self.direct.completed_required_stage_count <= self.allowed_stage_count()
    }

    pub fn passes(&self, rule: ReplayRule) -> bool {
        match rule {
            ReplayRule::WithOffsets => self.accepted(),
            ReplayRule::DirectOnly => self.direct_accepted(),
        }
    }

    /// Why it may not be shown under `rule` (None when it may), in words a user reads.
    pub fn rejection(&self, rule: ReplayRule) -> Option<String> {
        if self.passes(rule) {
            return None;
        }
        let considered = self.labelled().take(if rule == ReplayRule::DirectOnly { 1 } else { usize::MAX });
        let (how, worst) = considered.max_by_key(|(_, o)| (o.success, o.completed_required_stage_count))?;
        Some(if worst.success {
            format!("replaying its trajectory solves the target episode ({how})")
        } else {
            format!(
                "replaying its trajectory earns {} of {} stages ({how}); at most {} allowed (the idle start earns {})",
                worst.completed_required_stage_count,
                self.required_stage_count,
                self.allowed_stage_count(),
                self.idle_completed_stage_count
            )
        })
    }
}

/// Replays `actions` in `target`: directly, after each candidate offset, and the idle start for comparison.
/// `source` is the world the demonstration was recorded in (where the offsets come from).
pub fn attack(actions: &[[f64; 7]], source: &WorldSpec, target: &WorldSpec) -> Result<ReplayAttack, DemoError> {
    let mut world = WorldPhysics::build(target, |_, _, _| Ok(()))?;
    let fresh = |w: &WorldPhysics| -> Result<WorldPhysics, DemoError> {
        let mut f = w.fork(target)?;
        f.start(|_| {})?;
        Ok(f)
    };
    world.start(|_| {})?;
    let target_start = start_positions(&world);
    let mut source_world = WorldPhysics::build(source, |_, _, _| Ok(()))?;
    source_world.start(|_| {})?;
    let offsets = candidate_offsets(&start_positions(&source_world), &target_start, &interest(&world));
    drop(source_world);
    let idle_action = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0];
    let idle = replay(fresh(&world)?, std::iter::repeat_n(&idle_action, actions.len()))?;
    let gripper = actions.first().map_or(-1.0, |a| a[6]);
    let mut offset_replays = Vec::with_capacity(offsets.len());
    for (instance, offset_m) in offsets {
        let mut w = fresh(&world)?;
        shift_end_effector(&mut w, offset_m, gripper)?;
        offset_replays.push(OffsetReplay { instance, offset_m, outcome: replay(w, actions.iter())? });
    }
    let direct = replay(fresh(&world)?, actions.iter())?;
    let required_stage_count = world.evaluate().required_stage_count;
    Ok(ReplayAttack { direct, offsets: offset_replays, required_stage_count, idle_completed_stage_count: idle.completed_required_stage_count })
}

fn replay<'a>(mut world: WorldPhysics, actions: impl Iterator<Item = &'a [f64; 7]>) -> Result<ReplayOutcome, DemoError> {
    for a in actions {
        world.step(a)?;
    }
    let record = world.evaluate();
    Ok(ReplayOutcome { success: record.success, completed_required_stage_count: record.completed_required_stage_count })
}

/// Moves the end effector by `offset_m` (closed loop on its position, orientation held), as an agent would
/// before replaying a path it wants shifted.
fn shift_end_effector(world: &mut WorldPhysics, offset_m: [f64; 3], gripper: f64) -> Result<(), DemoError> {
    let start = world.sim.robot_state().eef_pos_in_world_m;
    let goal: [f64; 3] = std::array::from_fn(|i| start[i] + offset_m[i]);
    for _ in 0..SHIFT_STEPS {
        let now = world.sim.robot_state().eef_pos_in_world_m;
        let error: [f64; 3] = std::array::from_fn(|i| goal[i] - now[i]);
        if error.iter().map(|e| e * e).sum::<f64>().sqrt() < SHIFT_TOLERANCE_M {
            break;
        }
        let mut action = [0.0; 7];
        for i in 0..3 {
            action[i] = (error[i] / ACTION_SCALE[i]).clamp(-1.0, 1.0);
        }
        action[6] = gripper;
        world.step(&action)?;
    }
    Ok(())
}

/// World position of every object's and fixture's root body at the start, by instance name.
fn start_positions(world: &WorldPhysics) -> Vec<(String, [f64; 3])> {
    let model = world.model();
    let xpos = world.sim.data().xpos();
    world
        .scene
        .objects
        .iter()
        .chain(&world.scene.fixtures)
        .filter_map(|i| model.name_to_id(MjtObjBase::mjOBJ_BODY, &i.root_body).map(|b| (i.name.clone(), xpos[b])))
        .collect()
}

/// The BDDL's objects of interest (tried first).
fn interest(world: &WorldPhysics) -> BTreeSet<String> {
    world.scene.problem.obj_of_interest.iter().cloned().collect()
}

/// The distinct start displacements (target − source) of the instances both worlds have, objects of interest
/// first, at most [`MAX_OFFSET_REPLAYS`].
pub fn candidate_offsets(source: &[(String, [f64; 3])], target: &[(String, [f64; 3])], interest: &BTreeSet<String>) -> Vec<(String, [f64; 3])> {
    let mut moved: Vec<(bool, String, [f64; 3])> = target
        .iter()
        .filter_map(|(name, t)| {
            let (_, s) = source.iter().find(|(n, _)| n == name)?;
            let d: [f64; 3] = std::array::from_fn(|i| t[i] - s[i]);
            let norm = d.iter().map(|x| x * x).sum::<f64>().sqrt();
            (MIN_OFFSET_M..=MAX_OFFSET_M).contains(&norm).then(|| (!interest.contains(name), name.clone(), d))
        })
        .collect();
    moved.sort_by(|a, b| (a.0, &a.1).cmp(&(b.0, &b.1)));
    let mut out: Vec<(String, [f64; 3])> = Vec::new();
    for (_, name, d) in moved {
        let near = |o: &[f64; 3]| o.iter().zip(&d).map(|(a, b)| (a - b) * (a - b)).sum::<f64>().sqrt() < SAME_OFFSET_M;
        if out.len() < MAX_OFFSET_REPLAYS && !out.iter().any(|(_, o)| near(o)) {
            out.push((name, d));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn attack(direct: (bool, usize), offsets: &[(bool, usize)], k: usize, idle: usize) -> ReplayAttack {
        let o = |(success, c): (bool, usize)| ReplayOutcome { success, completed_required_stage_count: c };
        ReplayAttack {
            direct: o(direct),
            offsets: offsets.iter().map(|&x| OffsetReplay { instance: "bowl_1".into(), offset_m: [0.03, 0.0, 0.0], outcome: o(x) }).collect(),
            required_stage_count: k,
            idle_completed_stage_count: idle,
        }
    }

    #[test]
    fn a_replay_may_earn_at_most_half_the_stages_and_the_idle_starts_plus_one() {
        // T28 (K = 2): 1 stage allowed, 2 is full credit
        assert!(attack((false, 1), &[], 2, 0).accepted());
        assert!(!attack((false, 2), &[], 2, 0).accepted());
        // T27 (K = 4): half is 2, but an idle start of 0 allows only 1
        assert!(!attack((false, 2), &[], 4, 0).accepted());
        assert!(attack((false, 2), &[], 4, 1).accepted());
        assert_eq!(attack((false, 0), &[], 4, 3).allowed_stage_count(), 2, "half caps a generous idle start");
        // K = 1: nothing allowed
        assert_eq!(attack((false, 0), &[], 1, 0).allowed_stage_count(), 0);
        assert!(!attack((false, 1), &[], 1, 0).accepted());
        // success is never allowed, whatever the stages
        assert!(!attack((true, 0), &[], 5, 4).accepted());
    }

    #[test]
    fn the_best_offset_replay_counts_as_much_as_the_direct_one() {
        let a = attack((false, 0), &[(false, 0), (false, 3)], 4, 0);
        assert_eq!(a.best_completed_stage_count(), 3);
        assert!(a.direct_accepted() && a.passes(ReplayRule::DirectOnly) && !a.passes(ReplayRule::WithOffsets));
        assert_eq!(a.rejection(ReplayRule::DirectOnly), None);
        let why = a.rejection(ReplayRule::WithOffsets).unwrap();
        assert!(why.contains("3 of 4 stages") && why.contains("[30.0, 0.0, 0.0] mm") && why.contains("bowl_1"), "{why}");
        assert!(attack((false, 0), &[(true, 4)], 4, 0).rejection(ReplayRule::WithOffsets).unwrap().contains("solves"));
        assert!(attack((false, 2), &[(true, 4)], 4, 0).rejection(ReplayRule::DirectOnly).unwrap().contains("2 of 4 stages (direct replay)"));
        assert_eq!(attack((false, 1), &[(false, 0)], 4, 0).rejection(ReplayRule::WithOffsets), None);
    }

    #[test]
    fn offsets_are_distinct_start_displacements_objects_of_interest_first() {
        let p = |n: &str, x: f64, y: f64| (n.to_owned(), [x, y, 0.9]);
        let source = [p("plate_1", 0.0, 0.0), p("bowl_1", 0.1, 0.0), p("mug_1", 0.2, 0.0), p("cabinet_1", 0.0, 0.3), p("far_1", 0.0, 0.0)];
        let target = [p("plate_1", 0.04, 0.0), p("bowl_1", 0.1, 0.005), p("mug_1", 0.245, 0.0), p("cabinet_1", 0.0, 0.2), p("far_1", 0.5, 0.0)];
        let interest: BTreeSet<String> = ["mug_1".to_owned()].into();
        let got = candidate_offsets(&source, &target, &interest);
        let names: Vec<&str> = got.iter().map(|(n, _)| n.as_str()).collect();
        // mug (of interest) first; plate's 4 cm is within 1 cm of the mug's 4.5 cm; bowl moved 5 mm (no
        // offset); far_1 moved 50 cm (off the table)
        assert_eq!(names, ["mug_1", "cabinet_1"], "{got:?}");
        assert!((got[1].1[1] + 0.1).abs() < 1e-12);
    }

    fn spec(task: &str, layout: Option<crate::task::LayoutVariant>) -> WorldSpec {
        let paths = libero_sim::AssetPaths::discover().expect("assets cached by scripts/setup.py");
        let mut task = crate::task::resolve_task(task, &paths).unwrap();
        task.layout = layout;
        WorldSpec { task, level: crate::Level::L1, seed: 100, init_index: 0, paths }
    }

    #[test]
    fn a_rigidly_shifted_source_is_replayed_shifted_back_in_a_real_scene() {
        let target = spec("T28", None);
        let own = target.task.effective_layout(100, 0).unwrap();
        let shifted = crate::task::LayoutVariant { placement_seed: own.placement_seed, init_index: 0, region_margin_m: 0.0, scene_shift_m: [0.0, 0.04], yaw_margin_rad: 0.0 };
        let source = spec("T28", Some(shifted));
        // Holding still for 30 steps: the offset replay moves the end effector by the scene's displacement first.
        let actions = vec![[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0]; 30];
        let a = super::attack(&actions, &source, &target).unwrap();
        assert_eq!(a.required_stage_count, 2);
        assert!(!a.offsets.is_empty(), "the door moved with the scene: {a:?}");
        for o in &a.offsets {
            assert!((o.offset_m[1] + 0.04).abs() < 0.005 && o.offset_m[0].abs() < 0.005, "target − source is the shift back: {o:?}");
        }
        assert_eq!(a.direct, ReplayOutcome { success: false, completed_required_stage_count: a.idle_completed_stage_count });
        assert!(a.accepted(), "holding still earns nothing: {a:?}");
    }

    #[test]
    fn the_end_effector_moves_by_the_offset_before_the_replay() {
        let target = spec("T28", None);
        let mut world = WorldPhysics::build(&target, |_, _, _| Ok(())).unwrap();
        world.start(|_| {}).unwrap();
        let before = world.sim.robot_state().eef_pos_in_world_m;
        shift_end_effector(&mut world, [0.03, -0.04, 0.02], -1.0).unwrap();
        let after = world.sim.robot_state().eef_pos_in_world_m;
        let moved: Vec<f64> = (0..3).map(|i| after[i] - before[i]).collect();
        for (m, want) in moved.iter().zip([0.03, -0.04, 0.02]) {
            assert!((m - want).abs() < 0.004, "moved {moved:?}");
        }
    }
}
