//! Operations on articulated mechanisms and their sustained-contact ratio (paper Figure 3). For each control step `t`
//! of an operation, `l_t` is the length of the gripper–**handle** contact run containing `t` (0 without contact);
//! `N_sustained = #{t : l_t ≥ 5}` and `SCR = N_sustained / N_exec × 100 %` (the definition lives in
//! [`libero_metrics::sustained_contact_ratio_percent`], which the report uses too).
//!
//! **The mechanism** of an operation is found from the task's own goal, with no per-task list: the subtree of the
//! body that carries each articulation joint the goal tests (a microwave's door, a drawer's box, a door's leaf). A
//! drawer named by its region site (`drawer_open`) moves the site's body. A stage may name a narrower `contact_body`
//! (T28's latch), which then wins.
//!
//! **The handle** of a mechanism is declared per fixture class in `tasks/mechanism_handles.json` (compiled in): its
//! collision geoms by name. Two contact runs are recorded per operation: `contact_runs`, gripper contact with any part
//! of the mechanism (what says the agent engaged it: the stage diagnostics' and Table 4's evidence), and
//! `handle_contact_runs`, gripper contact with a declared handle geom of the mechanism — the runs the SCR counts. A push
//! on a door's panel or a drawer's front is contact with the mechanism, not with its handle. An evaluator that
//! monitors an opening refuses to build when a declared handle is missing from the model or the mechanism it opens
//! has none declared.
//!
//! **An operation's steps** (`N_exec`): where the order of stages says when the agent turned to the operation (ordered
//! stages), the control steps its stage was current; where every goal is available at once (the unordered cooking
//! goals, a single-goal task), from the first step the gripper touches the mechanism (anywhere) while the opening is
//! pending to the step it first holds, or the episode's end. A pending opening never touched spans every step it was
//! pending, with no contact (the report counts it as not entered); one already open at reset is no operation.
use std::sync::OnceLock;

pub use libero_metrics::SUSTAINED_RUN_STEPS;
use libero_metrics::{sustained_contact_ratio_percent, sustained_steps};
use libero_sim::mujoco_rs::prelude::{MjModel, MjtObjBase};
use libero_sim::simulation::SimData;
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};

use crate::TasksError;
use crate::judge::predicates::{EntityRef, JointRef, JointTest, SceneIndex, in_subtree};

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

/// What the gripper touches at one control step.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Touch {
    /// Any part of the mechanism (handle included).
    pub mechanism: bool,
    /// One of the mechanism's declared handle geoms.
    pub handle: bool,
}

/// Contact runs of one kind over an operation's control steps.
#[derive(Debug, Clone, Default)]
pub struct Runs {
    done: Vec<u64>,
    current: u64,
}

impl Runs {
    fn step(&mut self, contact: bool) {
        if contact {
            self.current += 1;
        } else if self.current > 0 {
            self.done.push(self.current);
            self.current = 0;
        }
    }

    fn close(&mut self) {
        if self.current > 0 {
            self.done.push(self.current);
            self.current = 0;
        }
    }

    /// The run lengths in order, an open run included.
    pub fn all(&self) -> Vec<u64> {
        let mut runs = self.done.clone();
        runs.extend((self.current > 0).then_some(self.current));
        runs
    }
}

/// The names of what an operation watches, for its record: the mechanism's bodies and its handle geoms.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Watched {
    pub bodies: Vec<String>,
    pub handle_geoms: Vec<String>,
}

/// Gripper contact over one operation: with the mechanism anywhere, and with its handle.
#[derive(Debug, Clone, Default)]
pub struct ContactMonitor {
    pub stage_name: String,
    pub exec_steps: u64,
    /// Runs of contact with any part of the mechanism.
    pub mechanism: Runs,
    /// Runs of contact with its handle (the SCR's).
    pub handle: Runs,
}

impl ContactMonitor {
    pub fn new(stage_name: impl Into<String>) -> Self {
        Self { stage_name: stage_name.into(), ..Default::default() }
    }

    pub fn step(&mut self, touch: Touch) {
        self.exec_steps += 1;
        self.mechanism.step(touch.mechanism);
        self.handle.step(touch.handle);
    }

    pub fn close(&mut self) {
        self.mechanism.close();
        self.handle.close();
    }

    /// `N_sustained`: steps inside handle-contact runs of ≥ [`SUSTAINED_RUN_STEPS`].
    pub fn sustained_steps(&self) -> u64 {
        sustained_steps(&self.handle.all())
    }

    pub fn ratio_percent(&self) -> f64 {
        sustained_contact_ratio_percent(&self.handle.all(), self.exec_steps)
    }

    /// One entry of `details.opening_operations`.
    pub fn to_json(&self, kind: OperationKind, window: Window, watched: &Watched, completed: bool) -> Value {
        json!({"stage_name": self.stage_name, "operation": kind, "window": window, "mechanism_bodies": watched.bodies,
            "handle_geoms": watched.handle_geoms, "exec_steps": self.exec_steps, "contact_runs": self.mechanism.all(),
            "handle_contact_runs": self.handle.all(), "sustained_steps": self.sustained_steps(),
            "sustained_contact_ratio_percent": self.ratio_percent(), "completed": completed})
    }
}

/// One handle of a fixture class: its body and collision geoms, without the instance prefix.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HandleSpec {
    pub body: String,
    pub geoms: Vec<String>,
}

/// The handles of one or more fixture classes with the same geometry.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ClassHandles {
    pub classes: Vec<String>,
    /// Where in the asset the geoms come from (documentation).
    pub source: String,
    pub handles: Vec<HandleSpec>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct HandleFile {
    #[allow(dead_code)]
    description: String,
    classes: Vec<ClassHandles>,
}

/// `tasks/mechanism_handles.json`, compiled in: the handles belong to the assets the composer names, not to a
/// deployment.
const HANDLES_JSON: &str = include_str!("../../../../tasks/mechanism_handles.json");

/// Every declared handle, by class group (`tasks/mechanism_handles.json`).
pub fn declared_handles() -> Result<&'static [ClassHandles], TasksError> {
    static FILE: OnceLock<Result<Vec<ClassHandles>, String>> = OnceLock::new();
    FILE.get_or_init(|| serde_json::from_str::<HandleFile>(HANDLES_JSON).map(|f| f.classes).map_err(|e| e.to_string()))
        .as_deref()
        .map_err(|e| TasksError::Scene(format!("tasks/mechanism_handles.json: {e}")))
}

/// The handles declared for fixture class `category` (empty when none is).
pub fn class_handles(category: &str) -> Result<&'static [HandleSpec], TasksError> {
    Ok(declared_handles()?.iter().find(|c| c.classes.iter().any(|k| k == category)).map_or(&[], |c| &c.handles))
}

/// Contact between the gripper (robosuite's `gripper0_*` bodies) and a mechanism's body subtree, and its handle.
#[derive(Debug, Clone)]
pub struct GripperContact {
    gripper_bodies: Vec<bool>,
    body_parent: Vec<i32>,
    geom_body: Vec<usize>,
    /// geom id → its name where it is a declared handle geom of the scene's fixtures
    handle_geom: Vec<Option<String>>,
}

impl GripperContact {
    /// The gripper of `model`, with the handle geoms declared for the fixtures of `index` (an error names a declared
    /// body or geom the model lacks, or a declared geom on another body).
    pub fn new(index: &SceneIndex, model: &MjModel) -> Result<Self, TasksError> {
        let nbody = model.ffi().nbody as usize;
        let geom_body: Vec<usize> = model.geom_bodyid().iter().map(|&b| b as usize).collect();
        let mut handle_geom = vec![None; geom_body.len()];
        for inst in &index.instances {
            for h in class_handles(&inst.category)? {
                let missing = |what: String| {
                    TasksError::Scene(format!(
                        "the handle of {} (class {}, tasks/mechanism_handles.json): {what}",
                        inst.name, inst.category
                    ))
                };
                let body_name = format!("{}_{}", inst.name, h.body);
                let body = model
                    .name_to_id(MjtObjBase::mjOBJ_BODY, &body_name)
                    .ok_or_else(|| missing(format!("the model has no body {body_name:?}")))?;
                for g in &h.geoms {
                    let name = format!("{}_{g}", inst.name);
                    let id = model
                        .name_to_id(MjtObjBase::mjOBJ_GEOM, &name)
                        .ok_or_else(|| missing(format!("the model has no geom {name:?}")))?;
                    if geom_body[id] != body {
                        return Err(missing(format!("geom {name:?} is not on body {body_name:?}")));
                    }
                    handle_geom[id] = Some(name);
                }
            }
        }
        Ok(Self {
            gripper_bodies: (0..nbody)
                .map(|b| model.id_to_name(MjtObjBase::mjOBJ_BODY, b).is_some_and(|n| n.starts_with("gripper0_")))
                .collect(),
            body_parent: model.body_parentid().to_vec(),
            geom_body,
            handle_geom,
        })
    }

    fn in_roots(&self, roots: &[usize], geom: usize) -> bool {
        roots.iter().any(|&r| in_subtree(&self.body_parent, self.geom_body[geom], r))
    }

    /// What of the subtrees of `roots` (a mechanism) a gripper geom touches in the current contacts.
    pub fn touches(&self, data: &SimData, roots: &[usize]) -> Touch {
        let mut touch = Touch::default();
        for c in data.contact() {
            let (g1, g2) = (c.geom[0] as usize, c.geom[1] as usize);
            let other = if self.gripper_bodies[self.geom_body[g1]] {
                g2
            } else if self.gripper_bodies[self.geom_body[g2]] {
                g1
            } else {
                continue;
            };
            if self.in_roots(roots, other) {
                touch.mechanism = true;
                touch.handle |= self.handle_geom[other].is_some();
            }
        }
        touch
    }

    /// The names of the declared handle geoms in the subtrees of `roots`.
    pub fn handle_names(&self, roots: &[usize]) -> Vec<String> {
        self.handle_geom.iter().enumerate().filter(|(g, _)| self.in_roots(roots, *g)).filter_map(|(_, n)| n.clone()).collect()
    }

    /// The handle geoms of an opening's mechanism (`roots`); an error when none is declared there, as the opening's
    /// sustained-contact ratio could count nothing.
    pub fn require_handle(&self, roots: &[usize], model: &MjModel, what: &str) -> Result<Vec<String>, TasksError> {
        let names = self.handle_names(roots);
        if names.is_empty() {
            let bodies = body_names(model, roots).join(", ");
            return Err(TasksError::Scene(format!(
                "{what} opens {bodies}, which carries no handle declared in tasks/mechanism_handles.json (Figure 3 counts gripper-handle contact)"
            )));
        }
        Ok(names)
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
    Waiting(u64),
    Engaged(ContactMonitor),
    Opened(ContactMonitor),
    /// Open at reset: nothing to operate.
    OpenAtReset,
}

/// An opening available from the start (an unordered goal, a single-goal task), delimited by first contact with its
/// mechanism.
#[derive(Debug, Clone)]
pub struct PendingOpening {
    stage_name: String,
    pub bodies: Vec<usize>,
    watched: Watched,
    state: Pending,
}

impl PendingOpening {
    /// `stage_name`: the stage (or goal atom) the opening completes; `bodies`: its mechanism, whose names and handle
    /// geoms `watched` gives for the record.
    pub fn new(stage_name: impl Into<String>, bodies: Vec<usize>, watched: Watched) -> Self {
        Self { stage_name: stage_name.into(), bodies, watched, state: Pending::Waiting(0) }
    }

    pub fn reset(&mut self, open_now: bool) {
        self.state = if open_now { Pending::OpenAtReset } else { Pending::Waiting(0) };
    }

    /// One control step: what the gripper touches and whether the opening holds now.
    pub fn step(&mut self, touch: Touch, open_now: bool) {
        let mut monitor = match &mut self.state {
            Pending::OpenAtReset | Pending::Opened(_) => return,
            Pending::Waiting(steps) if !touch.mechanism && !open_now => {
                *steps += 1;
                return;
            }
            Pending::Waiting(_) => ContactMonitor::new(self.stage_name.clone()),
            Pending::Engaged(m) => std::mem::take(m),
        };
        monitor.step(touch);
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
        let mut v = monitor.to_json(OperationKind::Open, Window::FirstContact, &self.watched, completed);
        if stage_name.is_some() {
            v["goal"] = json!(self.stage_name);
        }
        Some(v)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const HANDLE: Touch = Touch { mechanism: true, handle: true };
    const PANEL: Touch = Touch { mechanism: true, handle: false };
    const NONE: Touch = Touch { mechanism: false, handle: false };

    #[test]
    fn sustained_contact_counts_only_handle_runs_of_five_or_more() {
        let mut m = ContactMonitor::default();
        // handle 2, off, handle 5, panel 4 (the door's face: the mechanism, not its handle), off 2, handle 4
        let steps = [HANDLE, HANDLE, NONE].into_iter().chain([HANDLE; 5]).chain([PANEL; 4]).chain([NONE; 2]).chain([HANDLE; 4]);
        for t in steps {
            m.step(t);
        }
        m.close();
        assert_eq!(m.handle.all(), [2, 5, 4]);
        assert_eq!(m.mechanism.all(), [2, 9, 4], "the panel extends the mechanism run, not the handle run");
        assert_eq!(m.sustained_steps(), 5, "the run of 4 is not sustained, the run of 5 is; the panel never counts");
        assert_eq!(m.exec_steps, 18);
        assert!((m.ratio_percent() - 100.0 * 5.0 / 18.0).abs() < 1e-12);
    }

    fn pending() -> PendingOpening {
        PendingOpening::new("Microwave_Open", vec![3], Watched { bodies: vec!["door".into()], handle_geoms: vec!["door_g14".into()] })
    }

    #[test]
    fn a_pending_opening_counts_from_first_contact_with_the_mechanism_to_the_step_it_opens() {
        let mut p = pending();
        // 3 steps elsewhere, 2 on the panel, then 6 on the handle, 1 off, opened on the 2nd step back on it, then ignored.
        let steps = [(NONE, false); 3]
            .into_iter()
            .chain([(PANEL, false); 2])
            .chain([(HANDLE, false); 6])
            .chain([(NONE, false), (HANDLE, false), (HANDLE, true)]);
        for (touch, open) in steps.chain([(NONE, false), (HANDLE, false)]) {
            p.step(touch, open);
        }
        let v = p.to_json(None).unwrap();
        assert_eq!((v["exec_steps"].as_u64(), v["completed"].as_bool()), (Some(11), Some(true)));
        assert_eq!((&v["contact_runs"], &v["handle_contact_runs"]), (&json!([8, 2]), &json!([6, 2])));
        assert_eq!(v["sustained_steps"], 6);
        assert!((v["sustained_contact_ratio_percent"].as_f64().unwrap() - 600.0 / 11.0).abs() < 1e-9);
        assert_eq!((v["operation"].as_str(), v["window"].as_str()), (Some("open"), Some("first_contact")));
        assert_eq!((&v["mechanism_bodies"], &v["handle_geoms"]), (&json!(["door"]), &json!(["door_g14"])));
    }

    #[test]
    fn an_untouched_opening_spans_its_pending_steps_and_one_open_at_reset_is_none() {
        let mut p = pending();
        for _ in 0..4 {
            p.step(NONE, false);
        }
        let v = p.to_json(Some("01_BDDL_Goal_At_Finish")).unwrap();
        assert_eq!((v["exec_steps"].as_u64(), v["sustained_contact_ratio_percent"].as_f64()), (Some(4), Some(0.0)));
        assert_eq!((&v["contact_runs"], &v["handle_contact_runs"]), (&json!([]), &json!([])));
        assert_eq!((v["stage_name"].as_str(), v["goal"].as_str(), v["completed"].as_bool()), (Some("01_BDDL_Goal_At_Finish"), Some("Microwave_Open"), Some(false)));
        p.reset(true);
        p.step(HANDLE, true);
        assert!(p.to_json(None).is_none());
    }

    #[test]
    fn the_handle_declarations_parse_and_name_each_class_once() {
        let all = declared_handles().unwrap();
        let mut classes: Vec<&str> = all.iter().flat_map(|c| c.classes.iter().map(String::as_str)).collect();
        let n = classes.len();
        classes.sort_unstable();
        classes.dedup();
        assert_eq!(classes.len(), n, "a class declared twice");
        for c in ["microwave", "wooden_cabinet", "white_cabinet", "wooden_cabinet_tall_bottom", "short_cabinet", "robosuite_latched_door"] {
            assert!(!class_handles(c).unwrap().is_empty(), "{c}");
        }
        assert!(class_handles("short_fridge").unwrap().is_empty());
    }
}
