//! Operations on articulated mechanisms and their sustained-contact ratio (paper Figure 3). For each control step `t`
//! of an operation, `l_t` is the length of the gripper–handle contact run containing `t` (0 without contact);
//! `N_sustained = #{t : l_t ≥ 5}` and `SCR = N_sustained / N_exec × 100 %`.
//!
//! **The contact body** of a mechanism is found from the task's own goal, with no per-task list: the subtree of the
//! body that carries each articulation joint the goal tests (a microwave's door, a drawer's box, a door's leaf with its
//! handle), so any gripper contact with the moving part — handle, edge or face — counts. A drawer named by its region
//! site (`drawer_open`) moves the site's body. A stage may name a narrower `contact_body` (T28's latch handle), which
//! then wins.
//!
//! **An operation's steps** (`N_exec`): where the order of stages says when the agent turned to the operation (ordered
//! stages), the control steps its stage was current; where every goal is available at once (the unordered cooking
//! goals, a single-goal task), from the first step the gripper touches the mechanism while the opening is pending to
//! the step it first holds, or the episode's end. A pending opening never touched spans every step it was pending, with
//! SCR 0; one already open at reset is no operation.
use libero_sim::mujoco_rs::prelude::{MjModel, MjtObjBase};
use libero_sim::simulation::SimData;
use serde::Serialize;
use serde_json::{Value, json};

use crate::judge::predicates::{EntityRef, JointRef, JointTest, SceneIndex, in_subtree};

/// Minimum contact run (control steps) that counts as sustained.
pub const SUSTAINED_RUN_STEPS: u32 = 5;

/// Which way an operation moves its mechanism.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum OperationKind {
    Open,
    Close,
    /// A monitored stage whose atoms move no articulation the catalog classifies.
    Operate,
}

/// How an operation's control steps were delimited (see the module documentation).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Window {
    StageCurrent,
    FirstContact,
}

/// Gripper–mechanism contact over one operation.
#[derive(Debug, Clone, Default, Serialize)]
pub struct ContactMonitor {
    pub stage_name: String,
    pub exec_steps: u32,
    /// Lengths of the contact runs, in order.
    pub runs: Vec<u32>,
    #[serde(skip)]
    current_run: u32,
}

impl ContactMonitor {
    pub fn new(stage_name: impl Into<String>) -> Self {
        Self { stage_name: stage_name.into(), ..Default::default() }
    }

    pub fn step(&mut self, contact: bool) {
        self.exec_steps += 1;
        if contact {
            self.current_run += 1;
        } else if self.current_run > 0 {
            self.runs.push(self.current_run);
            self.current_run = 0;
        }
    }

    pub fn close(&mut self) {
        if self.current_run > 0 {
            self.runs.push(self.current_run);
            self.current_run = 0;
        }
    }

    /// Steps inside runs of ≥ [`SUSTAINED_RUN_STEPS`].
    pub fn sustained_steps(&self) -> u32 {
        self.runs.iter().chain((self.current_run > 0).then_some(&self.current_run)).filter(|&&r| r >= SUSTAINED_RUN_STEPS).sum()
    }

    pub fn ratio_percent(&self) -> f64 {
        if self.exec_steps == 0 { 0.0 } else { 100.0 * f64::from(self.sustained_steps()) / f64::from(self.exec_steps) }
    }

    /// One entry of `details.opening_operations`.
    pub fn to_json(&self, kind: OperationKind, window: Window, bodies: &[String], completed: bool) -> Value {
        let mut runs = self.runs.clone();
        runs.extend((self.current_run > 0).then_some(self.current_run));
        json!({"stage_name": self.stage_name, "operation": kind, "window": window, "mechanism_bodies": bodies,
            "exec_steps": self.exec_steps, "contact_runs": runs, "sustained_steps": self.sustained_steps(),
            "sustained_contact_ratio_percent": self.ratio_percent(), "completed": completed})
    }
}

/// Contact between the gripper (robosuite's `gripper0_*` bodies) and a body subtree.
#[derive(Debug, Clone)]
pub struct GripperContact {
    gripper_bodies: Vec<bool>,
    body_parent: Vec<i32>,
    geom_body: Vec<usize>,
}

impl GripperContact {
    pub fn new(model: &MjModel) -> Self {
        let nbody = model.ffi().nbody as usize;
        Self {
            gripper_bodies: (0..nbody)
                .map(|b| model.id_to_name(MjtObjBase::mjOBJ_BODY, b).is_some_and(|n| n.starts_with("gripper0_")))
                .collect(),
            body_parent: model.body_parentid().to_vec(),
            geom_body: model.geom_bodyid().iter().map(|&b| b as usize).collect(),
        }
    }

    /// Some current contact pairs a gripper geom with a geom in the subtree of any of `roots`.
    pub fn touches(&self, data: &SimData, roots: &[usize]) -> bool {
        let in_roots = |b: usize| roots.iter().any(|&r| in_subtree(&self.body_parent, b, r));
        data.contact().iter().any(|c| {
            let (b1, b2) = (self.geom_body[c.geom[0] as usize], self.geom_body[c.geom[1] as usize]);
            (self.gripper_bodies[b1] && in_roots(b2)) || (self.gripper_bodies[b2] && in_roots(b1))
        })
    }
}

/// The bodies of `model` by name (for the record).
pub fn body_names(model: &MjModel, bodies: &[usize]) -> Vec<String> {
    bodies.iter().map(|&b| model.id_to_name(MjtObjBase::mjOBJ_BODY, b).unwrap_or_default().to_owned()).collect()
}

/// The body a joint moves.
pub fn joint_body(model: &MjModel, joint: &str) -> Option<usize> {
    let j = model.name_to_id(MjtObjBase::mjOBJ_JOINT, joint)?;
    Some(model.jnt_bodyid()[j] as usize)
}

/// The bodies an articulated instance's or region's joints move (empty for an entity without joints).
pub fn moving_bodies(index: &SceneIndex, model: &MjModel, e: EntityRef) -> Vec<usize> {
    let joints: &[JointRef] = match e {
        EntityRef::Instance(i) => &index.instances[i].joints,
        EntityRef::Region(r) => &index.regions[r].joints,
    };
    let mut out: Vec<usize> = joints.iter().filter_map(|j| joint_body(model, &j.name)).collect();
    out.dedup();
    out
}

fn points_up(t: JointTest) -> bool {
    matches!(t, JointTest::Above(_) | JointTest::AtLeast(_))
}

/// Which way a bound on a joint (`min < q`, `q < max`; with `abs`, on |q|) moves the articulated class that owns the
/// joint: toward its `open` test → open, toward its `close` test → close. A magnitude bound from below moves a
/// mechanism away from rest, i.e. opens it. `None` when no articulated class owns the joint or the bound is two-sided.
pub fn joint_operation(index: &SceneIndex, joint: &str, min: Option<f64>, max: Option<f64>, abs: bool) -> Option<OperationKind> {
    let owns = |joints: &[JointRef]| joints.iter().any(|j| j.name == joint);
    let rule = index
        .instances
        .iter()
        .find(|i| owns(&i.joints))
        .and_then(|i| i.rule)
        .or_else(|| index.regions.iter().find(|r| owns(&r.joints)).and_then(|r| r.parent).and_then(|p| index.instances[p].rule))?;
    let up = match (min, max) {
        (Some(_), None) => true,
        (None, Some(_)) => false,
        _ => return None,
    };
    if abs {
        return rule.open.map(|_| if up { OperationKind::Open } else { OperationKind::Close });
    }
    if rule.open.is_some_and(|t| points_up(t) == up) {
        Some(OperationKind::Open)
    } else if rule.close.is_some_and(|t| points_up(t) == up) {
        Some(OperationKind::Close)
    } else {
        None
    }
}

/// Where a pending opening stands.
#[derive(Debug, Clone)]
enum Pending {
    /// Not touched and not open yet; counts the steps it was pending.
    Waiting(u32),
    Engaged(ContactMonitor),
    Opened(ContactMonitor),
    /// Open at reset: nothing to operate.
    OpenAtReset,
}

/// An opening available from the start (an unordered goal, a single-goal task), delimited by first contact.
#[derive(Debug, Clone)]
pub struct PendingOpening {
    stage_name: String,
    pub bodies: Vec<usize>,
    body_names: Vec<String>,
    state: Pending,
}

impl PendingOpening {
    /// `stage_name`: the stage (or goal atom) the opening completes.
    pub fn new(stage_name: impl Into<String>, bodies: Vec<usize>, model: &MjModel) -> Self {
        let names = body_names(model, &bodies);
        Self::named(stage_name, bodies, names)
    }

    /// As [`Self::new`], with the bodies' names already known.
    pub fn named(stage_name: impl Into<String>, bodies: Vec<usize>, body_names: Vec<String>) -> Self {
        Self { stage_name: stage_name.into(), bodies, body_names, state: Pending::Waiting(0) }
    }

    pub fn reset(&mut self, open_now: bool) {
        self.state = if open_now { Pending::OpenAtReset } else { Pending::Waiting(0) };
    }

    /// One control step: whether the gripper touches the mechanism and whether the opening holds now.
    pub fn step(&mut self, touching: bool, open_now: bool) {
        let mut monitor = match &mut self.state {
            Pending::OpenAtReset | Pending::Opened(_) => return,
            Pending::Waiting(steps) if !touching && !open_now => {
                *steps += 1;
                return;
            }
            Pending::Waiting(_) => ContactMonitor::new(self.stage_name.clone()),
            Pending::Engaged(m) => std::mem::take(m),
        };
        monitor.step(touching);
        self.state = if open_now {
            monitor.close();
            Pending::Opened(monitor)
        } else {
            Pending::Engaged(monitor)
        };
    }

    /// Its entry of `details.opening_operations` (`None` when it was open at reset); `stage_name` overrides the
    /// name given at construction (a single-goal task's record names its one stage).
    pub fn to_json(&self, stage_name: Option<&str>) -> Option<Value> {
        let (monitor, completed) = match &self.state {
            Pending::OpenAtReset => return None,
            Pending::Waiting(steps) => (ContactMonitor { exec_steps: *steps, ..ContactMonitor::new("") }, false),
            Pending::Engaged(m) => (m.clone(), false),
            Pending::Opened(m) => (m.clone(), true),
        };
        let monitor = ContactMonitor { stage_name: stage_name.unwrap_or(&self.stage_name).to_owned(), ..monitor };
        let mut v = monitor.to_json(OperationKind::Open, Window::FirstContact, &self.body_names, completed);
        if stage_name.is_some() {
            v["goal"] = json!(self.stage_name);
        }
        Some(v)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sustained_contact_counts_only_runs_of_five_or_more() {
        let mut m = ContactMonitor::default();
        for c in [true, true, false, true, true, true, true, true, false, false, true] {
            m.step(c);
        }
        m.close();
        assert_eq!(m.runs, [2, 5, 1]);
        assert_eq!(m.sustained_steps(), 5);
        assert!((m.ratio_percent() - 100.0 * 5.0 / 11.0).abs() < 1e-12);
    }

    fn pending() -> PendingOpening {
        PendingOpening::named("Microwave_Open", vec![3], vec!["door".into()])
    }

    #[test]
    fn a_pending_opening_counts_from_first_contact_to_the_step_it_opens() {
        let mut p = pending();
        // 3 steps elsewhere, then 6 steps on the handle, 1 off, opened on the 2nd step back on it, then ignored.
        let steps = [(false, false); 3].into_iter().chain([(true, false); 6]).chain([(false, false), (true, false), (true, true)]);
        for (touch, open) in steps.chain([(false, false), (true, false)]) {
            p.step(touch, open);
        }
        let v = p.to_json(None).unwrap();
        assert_eq!((v["exec_steps"].as_u64(), v["completed"].as_bool()), (Some(9), Some(true)));
        assert_eq!(v["contact_runs"], json!([6, 2]));
        assert_eq!(v["sustained_steps"], 6);
        assert!((v["sustained_contact_ratio_percent"].as_f64().unwrap() - 600.0 / 9.0).abs() < 1e-9);
        assert_eq!((v["operation"].as_str(), v["window"].as_str()), (Some("open"), Some("first_contact")));
    }

    #[test]
    fn an_untouched_opening_spans_its_pending_steps_and_one_open_at_reset_is_none() {
        let mut p = pending();
        for _ in 0..4 {
            p.step(false, false);
        }
        let v = p.to_json(Some("01_BDDL_Goal_At_Finish")).unwrap();
        assert_eq!((v["exec_steps"].as_u64(), v["sustained_contact_ratio_percent"].as_f64()), (Some(4), Some(0.0)));
        assert_eq!((v["stage_name"].as_str(), v["goal"].as_str(), v["completed"].as_bool()), (Some("01_BDDL_Goal_At_Finish"), Some("Microwave_Open"), Some(false)));
        p.reset(true);
        p.step(true, true);
        assert!(p.to_json(None).is_none());
    }
}
