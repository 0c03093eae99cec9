//! "First commitment": what the agent first physically committed to, used to judge target identification
//! (task catalog §1.5/§8.6: "judgment correct ⇔ the first candidate grasped and lifted ≥ 0.04 m is the target",
//! "the first button reaching a contact press is the target").
//!
//! Definition. The first commitment is the earliest control step t ≥ 1 after the evaluator reset at which either
//! * **object**: a movable object o is *grasped* — robosuite's grasp test: at least one MuJoCo contact between the
//!   left finger pad `gripper0_finger1_pad_collision` and a contact geom of o (group ≠ 1, o's body subtree) and at
//!   least one between the right pad `gripper0_finger2_pad_collision` and o — **and** o's root-body origin is at least
//!   [`LIFT_COMMIT_M`] (0.04 m) above its height at reset; or
//! * **fixture**: a hinge or slide joint of a fixture has moved from its value at reset by at least
//!   [`HINGE_COMMIT_RAD`] (0.10 rad) or [`SLIDE_COMMIT_M`] (0.02 m) — a door, drawer or knob was articulated; or
//! * **press**: an evaluator that knows about buttons reports a press through [`CommitmentTracker::commit_press`]
//!   (its own press rule, e.g. the 11-substep contact press).
//!
//! Sampled at control-step rate only (presses may arrive from substeps). Ties inside one step resolve objects
//! before fixtures, each in scene order (objects then fixtures as the BDDL lists them). Only the first one is kept.
use libero_sim::mujoco_rs::prelude::{MjModel, MjtObjBase};
use libero_sim::simulation::SimData;
use serde::Serialize;

use crate::TasksError;
use crate::judge::events::{EventKind, PrivateEvent, Tick};
use crate::judge::predicates::{JointKind, SceneIndex};

/// Lift (m) above the reset height that, with a grasp, commits to an object.
pub const LIFT_COMMIT_M: f64 = 0.04;
/// Fixture joint displacement from reset that commits to the fixture.
pub const HINGE_COMMIT_RAD: f64 = 0.10;
pub const SLIDE_COMMIT_M: f64 = 0.02;

pub const LEFT_PAD_GEOM: &str = "gripper0_finger1_pad_collision";
pub const RIGHT_PAD_GEOM: &str = "gripper0_finger2_pad_collision";

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum CommitmentKind {
    ObjectGraspedAndLifted,
    FixtureArticulated,
    ButtonPressed,
}

/// The first commitment of an episode.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Commitment {
    pub kind: CommitmentKind,
    /// Instance name (object, fixture or button).
    pub subject: String,
    #[serde(flatten)]
    pub tick: Tick,
    /// Lift (m) for objects, joint displacement (m or rad) for fixtures, 0 for presses.
    pub magnitude: f64,
}

impl Commitment {
    /// The `first_commitment` private event.
    pub fn event(&self) -> PrivateEvent {
        PrivateEvent { subject: Some(self.subject.clone()), ..PrivateEvent::new(EventKind::FirstCommitment, self.tick) }
    }
}

#[derive(Debug, Clone)]
struct ObjectWatch {
    instance: usize,
    z0_m: f64,
}

#[derive(Debug, Clone)]
struct JointWatch {
    instance: usize,
    qpos_adr: usize,
    threshold: f64,
    q0: f64,
}

/// Watches every movable object and articulated fixture joint of a scene for the first commitment.
#[derive(Debug, Clone)]
pub struct CommitmentTracker {
    left_pad: usize,
    right_pad: usize,
    /// `gripper0_grip_site`, for the released-and-clear test.
    grip_site: usize,
    objects: Vec<ObjectWatch>,
    joints: Vec<JointWatch>,
    first: Option<Commitment>,
}

impl CommitmentTracker {
    pub fn new(index: &SceneIndex, model: &MjModel) -> Result<Self, TasksError> {
        let geom = |name: &str| {
            model.name_to_id(MjtObjBase::mjOBJ_GEOM, name).ok_or_else(|| TasksError::Scene(format!("model has no geom {name}")))
        };
        let mut objects = Vec::new();
        let mut joints = Vec::new();
        for (i, inst) in index.instances.iter().enumerate() {
            if !inst.is_fixture {
                objects.push(ObjectWatch { instance: i, z0_m: 0.0 });
                continue;
            }
            for j in &inst.joints {
                let threshold = match j.kind {
                    JointKind::Hinge => HINGE_COMMIT_RAD,
                    JointKind::Slide => SLIDE_COMMIT_M,
                    JointKind::Free | JointKind::Ball => continue,
                };
                joints.push(JointWatch { instance: i, qpos_adr: j.qpos_adr, threshold, q0: 0.0 });
            }
        }
        let grip_site = model
            .name_to_id(MjtObjBase::mjOBJ_SITE, libero_sim::robot::GRIP_SITE)
            .ok_or_else(|| TasksError::Scene(format!("model has no site {}", libero_sim::robot::GRIP_SITE)))?;
        Ok(Self { left_pad: geom(LEFT_PAD_GEOM)?, right_pad: geom(RIGHT_PAD_GEOM)?, grip_site, objects, joints, first: None })
    }

    /// Captures reset heights and joint positions; forgets any earlier commitment.
    pub fn reset(&mut self, index: &SceneIndex, data: &SimData) {
        for o in &mut self.objects {
            o.z0_m = data.xpos()[index.instances[o.instance].body][2];
        }
        for j in &mut self.joints {
            j.q0 = data.qpos()[j.qpos_adr];
        }
        self.first = None;
    }

    /// robosuite's grasp test for instance `i`.
    pub fn grasped(&self, index: &SceneIndex, data: &SimData, i: usize) -> bool {
        let touches = |pad: usize| {
            data.contact().iter().any(|c| {
                let (g1, g2) = (c.geom[0] as usize, c.geom[1] as usize);
                (g1 == pad && index.geom_owner(g2) == Some(i)) || (g2 == pad && index.geom_owner(g1) == Some(i))
            })
        };
        touches(self.left_pad) && touches(self.right_pad)
    }

    /// Released-and-clear: instance `i` is not grasped and its root origin is at least `min_distance_m` from the grip
    /// site (the hand has let go and moved away).
    pub fn released_and_clear(&self, index: &SceneIndex, data: &SimData, i: usize, min_distance_m: f64) -> bool {
        let p = data.xpos()[index.instances[i].body];
        let g = data.site_xpos()[self.grip_site];
        let d = ((p[0] - g[0]).powi(2) + (p[1] - g[1]).powi(2) + (p[2] - g[2]).powi(2)).sqrt();
        !self.grasped(index, data, i) && d >= min_distance_m
    }

    /// Samples one control step; returns the commitment if it happened now.
    pub fn observe(&mut self, index: &SceneIndex, data: &SimData, tick: Tick) -> Option<&Commitment> {
        if self.first.is_some() {
            return None;
        }
        let object = self.objects.iter().find_map(|o| {
            let lift = data.xpos()[index.instances[o.instance].body][2] - o.z0_m;
            (lift >= LIFT_COMMIT_M && self.grasped(index, data, o.instance))
                .then_some((CommitmentKind::ObjectGraspedAndLifted, o.instance, lift))
        });
        let found = object.or_else(|| {
            self.joints.iter().find_map(|j| {
                let moved = (data.qpos()[j.qpos_adr] - j.q0).abs();
                (moved >= j.threshold).then_some((CommitmentKind::FixtureArticulated, j.instance, moved))
            })
        });
        let (kind, instance, magnitude) = found?;
        self.first = Some(Commitment { kind, subject: index.instances[instance].name.clone(), tick, magnitude });
        self.first.as_ref()
    }

    /// A press reported by a button-aware evaluator; kept only if nothing was committed before.
    pub fn commit_press(&mut self, button: &str, tick: Tick) -> Option<&Commitment> {
        if self.first.is_some() {
            return None;
        }
        self.first = Some(Commitment { kind: CommitmentKind::ButtonPressed, subject: button.to_owned(), tick, magnitude: 0.0 });
        self.first.as_ref()
    }

    /// [`observe`](Self::observe), as the private event that records the commitment.
    pub fn observe_event(&mut self, index: &SceneIndex, data: &SimData, tick: Tick) -> Option<PrivateEvent> {
        self.observe(index, data, tick).map(Commitment::event)
    }

    /// [`commit_press`](Self::commit_press), as the private event that records the commitment.
    pub fn commit_press_event(&mut self, button: &str, tick: Tick) -> Option<PrivateEvent> {
        self.commit_press(button, tick).map(Commitment::event)
    }

    pub fn first(&self) -> Option<&Commitment> {
        self.first.as_ref()
    }
}
