//! Generic staged evaluator driven by manifest parameters (task catalog §1.4, §1.4a, §2.4): a list of stages, each a
//! conjunction of atoms, evaluated at control rate in one of three order modes, plus terminal checks at finish.
//!
//! * `ordered` — the RoboMemArena ordered evaluator: only the current stage is tested each control step (at most one
//!   stage per step); a later stage that already holds completes as soon as it becomes current (T23, T26, T27).
//! * `strict` — `_StrictPredicateSequence`: before the current stage every later stage is tested; one that already
//!   holds latches an ordering violation (permanent failure).
//! * `unordered` — the cooking goal evaluator (T21, T22): K goals, completed = goals true on the final state; the
//!   initial and maximum goal counts and every change of the satisfied set are recorded.
//!
//! Atoms: a LIBERO predicate (`{"bddl": ["on", "moka_pot_1", "flat_stove_2_cook_region"]}`), or one of the
//! RoboMemArena checks: `near` (object root within `xy_max_m` horizontally of an anchor body or site, height
//! difference inside `dz_range_m`), `window` (object root minus an anchor body's or site's current position, in world
//! axes, strictly inside `x_m`, `y_m`, `z_m`: RoboMemArena's in-drawer window around a drawer's moving region site),
//! `drawer_open` / `drawer_closed` (world-y displacement of a drawer's region site
//! from its value at reset above / below a threshold, catalog §2.2), `in_box` (RoboMemArena box rule: site box with
//! half-extent |R·size|, lower z extended by `lower_z_m`, upper by `upper_z_m`), `released` (not grasped by
//! robosuite's two-pad test), `released_and_clear` (not grasped and the object's root at least `min_distance_m` from
//! the grip site, catalog §2.4), `lifted` (root z − z at reset > `above_m`), `joint` (a joint's position, or its
//! magnitude, strictly inside `(min, max)`: rad for hinges, m for slides — T28's latch), `pour_count` (a named pour
//! counter has registered ≥ `at_least` pours), `displaced_since` (the object's root at least `min_xy_m` horizontally from
//! where it was when a named earlier stage completed: VLABench find_unseen_object's "taken out after the drawer opened"),
//! `touching` (a live contact between two instances' body subtrees, distance ≤ `max_distance_m`: VLABench's "on the
//! real container", not hovering inside its region), `moved_xy` (root moved ≥ `min_m` horizontally from its pose at
//! reset), `any` (disjunction), `all` (conjunction, for use inside `any`) and `not`.
//!
//! Bindings (T23's "occupied drawer"): a name `$<binding>` usable wherever an atom names a site (drawer sites, `near`
//! anchors); at reset it is bound to the candidate site nearest (3-D) to an object's root, and stays bound for the
//! episode.
//!
//! Pour counters (T24): named RoboMemArena pour counters ([`crate::judge::pouring::PourTracker`], the T20 algorithm). A counter is
//! created the first control step a stage naming it is current (RoboMemArena creates it when the pour stage is first
//! evaluated) and from then on updated once per control step, before the stages are tested; `pour_count` atoms read it
//! (0 before creation). Failure monitors latch a permanent failure (e.g. `extra_pour`) at the first control step at or
//! after a given stage's completion where their atom holds.
//!
//! Optional guards and rates (T25): `forbidden_contacts` latches a permanent failure the first tick any listed
//! object's body subtree touches a forbidden body's subtree (contact distance ≤ `max_distance_m`), recorded as
//! `<object>_touched_<label>`; it is checked first at every tick and stops all further tracking. With
//! `sample_substeps` the stage logic also runs after every physics substep (same rules at both rates).
//!
//! Completed stages are re-tested every control step: a completed stage whose conjunction stops holding is recorded
//! as a regression (event + count), and stays completed. Mechanism operations record the sustained-contact ratio as a
//! diagnostic (paper Figure 3: SCR = N_sustained / N_exec over gripper contact with the mechanism's declared handle,
//! [`crate::judge::mechanism`]; an opening whose mechanism has no declared handle is refused): every stage whose atoms
//! open an articulation (`bddl open`, `drawer_open`, a `joint` bound toward its class's open test) is an opening
//! operation on the moving bodies of the articulations it tests, and a stage naming a `contact_body` is an operation
//! on that body whatever its direction (T23's closings, T28's latch). Ordered modes count the control steps the stage
//! was current; the unordered mode, where every goal is available at once, counts from the first gripper contact with
//! the mechanism while the opening is pending. Each stage's catalog `type` (object_manipulation /
//! mechanism_interaction) is checked here and reported by the stage diagnostics.
use std::sync::Arc;

use libero_bddl::{Atom as BddlAtom, Pos};
use libero_sim::mujoco_rs::prelude::{MjModel, MjtJoint, MjtObjBase};
use libero_sim::simulation::SimData;
use serde::{Deserialize, Serialize};
use serde_json::json;

use crate::TasksError;
use crate::judge::commitment::CommitmentTracker;
use crate::judge::evaluator::{
    EvaluationRecord, EventKind, Evaluator, FailureReason, PrivateEvent, StageRegressions, StageSpec, StageTracker,
    TerminalCheck, Tick, score_percent,
};
use crate::judge::goal::GoalChecker;
pub use crate::judge::mechanism::{ContactMonitor, SUSTAINED_RUN_STEPS};
use crate::judge::mechanism::{
    GripperContact, OperationKind, PendingOpening, Watched, Window, body_names, joint_operation, moving_bodies,
};
use crate::judge::predicates::{CompiledAtom, EntityRef, PredicateKind, SceneIndex, SubtreeContact, in_subtree};
use crate::judge::kind::{EvaluatorKind, check};
use crate::judge::stage_types::StageType;
use crate::judge::support::scene_goal_and_commitment;
use crate::judge::pouring::{PourCounterConfig, PourTracker};

pub const CHECKER_ORDERED: &str = "private_ordered_stages";
pub const CHECKER_UNORDERED: &str = "private_unordered_goal_predicates";
/// T25's checker: strict stages, substep sampling and the bowl–table contact guard, all from the manifest params.
pub const CHECKER_BUFFER_ROTATION: &str = "private_ordered_buffer_rotation_and_tabletop_avoidance";

/// The three staged kinds' table rows (one builder: the params say how the stages are judged). They delimit
/// operations by their own stages.
pub const EVALUATORS: &[EvaluatorKind] = &[staged(CHECKER_ORDERED), staged(CHECKER_UNORDERED), staged(CHECKER_BUFFER_ROTATION)];

const fn staged(name: &'static str) -> EvaluatorKind {
    EvaluatorKind {
        stages_delimit_operations: true,
        ..EvaluatorKind::plain(name, check::<StagedParams>, |checker, scene, model| {
            let (goal, commitment) = scene_goal_and_commitment(scene, model)?;
            let p = checker.parse()?;
            Ok(Box::new(StagedEvaluator::new(checker.kind, p, goal, commitment, model, checker.task_id_owned())?))
        })
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Deserialize, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum OrderMode {
    #[default]
    Ordered,
    Strict,
    Unordered,
}

/// One atom of a stage or terminal conjunction.
#[derive(Debug, Clone, Deserialize)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum AtomSpec {
    /// `[predicate, arg…]`, a LIBERO predicate.
    Bddl(Vec<String>),
    /// `object`'s root within `xy_max_m` of `anchor` (an instance's root or a site) horizontally and `dz_range_m` above
    /// it; with `square`, |dx| and |dy| each below `xy_max_m` (RoboMemArena's microwave rule) instead of the distance.
    Near {
        object: String,
        anchor: String,
        xy_max_m: f64,
        dz_range_m: [f64; 2],
        #[serde(default)]
        square: bool,
    },
    /// Object root minus the anchor's current position (instance root body, else site), world axes, strictly inside each range.
    Window { object: String, anchor: String, x_m: [f64; 2], y_m: [f64; 2], z_m: [f64; 2] },
    DrawerOpen { site: String, min_displacement_m: f64 },
    DrawerClosed { site: String, max_displacement_m: f64 },
    InBox { object: String, site: String, lower_z_m: f64, upper_z_m: f64 },
    Released(String),
    ReleasedAndClear { object: String, min_distance_m: f64 },
    Lifted { object: String, above_m: f64 },
    /// A joint's position (rad for hinges, m for slides) strictly above `min` and below `max` where given; with
    /// `abs`, its magnitude (a handle that unlatches turned either way).
    Joint {
        name: String,
        #[serde(default)]
        min: Option<f64>,
        #[serde(default)]
        max: Option<f64>,
        #[serde(default)]
        abs: bool,
    },
    /// The named pour counter (`pour_counters`) has registered at least `at_least` pours.
    PourCount { counter: String, at_least: usize },
    /// `object`'s root at least `min_xy_m` (horizontal) from its position when stage `stage` completed; false while
    /// that stage has not completed.
    DisplacedSince { object: String, stage: String, min_xy_m: f64 },
    /// A contact between `object`'s and `other`'s body subtrees with distance ≤ `max_distance_m` (a live support,
    /// not a hover inside a region).
    Touching { object: String, other: String, max_distance_m: f64 },
    /// `object`'s root is at least `min_m` from its reset position horizontally (it was really moved).
    MovedXy { object: String, min_m: f64 },
    /// At least one of the atoms holds.
    Any(Vec<AtomSpec>),
    /// Every one of the atoms holds (inside an `any`: RoboMemArena task 14's "the drawer holding the object is closed").
    All(Vec<AtomSpec>),
    Not(Box<AtomSpec>),
}

/// A site chosen per episode: among `sites`, the one whose world position at reset is nearest (3-D) to the root of
/// `nearest_to`. Atoms name it `$<name>`.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BindingParams {
    pub name: String,
    pub nearest_to: String,
    pub sites: Vec<String>,
}

/// A named pour counter: `bottle` poured over `target_site` (catalog §4 T20 algorithm and thresholds).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PourCounterParams {
    pub name: String,
    pub bottle: String,
    pub target_site: String,
    #[serde(flatten)]
    pub config: PourCounterConfig,
}

/// A permanent failure latched at the first control step, at or after `after_stage` completed, where `when` holds.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FailureMonitorParams {
    pub name: String,
    pub after_stage: String,
    pub when: AtomSpec,
    pub reason: FailureReason,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StageParams {
    pub name: String,
    /// The stage's type for the stage-level diagnosis (read from the catalog by [`crate::judge::stage_types`]).
    #[serde(default, rename = "type")]
    pub stage_type: Option<StageType>,
    pub all: Vec<AtomSpec>,
    /// Body (subtree) whose contact with the gripper is monitored while this stage is current, instead of the
    /// moving bodies its atoms imply (a handle narrower than the door, or a closing).
    #[serde(default)]
    pub contact_body: Option<String>,
}

/// A contact that fails the run for good the first time it is seen (T25: a bowl touching the tabletop).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ForbiddenContactParams {
    /// Instances none of whose body subtrees may touch `body`.
    pub objects: Vec<String>,
    /// MuJoCo body whose subtree is forbidden (e.g. the kitchen table's `table`).
    pub body: String,
    /// Names the latch `<object>_touched_<label>`.
    pub label: String,
    /// A contact counts when its distance (negative = penetration) is at most this.
    pub max_distance_m: f64,
}

/// The staged kinds' `checker.params`. The fields that may be left out are structural (no optional stages, no pour
/// counters, …; `order` is `ordered`); every threshold is in the atoms, which have no defaults.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StagedParams {
    #[serde(default)]
    pub order: OrderMode,
    /// Also sample after every physics substep (not only at control steps).
    #[serde(default)]
    pub sample_substeps: bool,
    #[serde(default)]
    pub forbidden_contacts: Vec<ForbiddenContactParams>,
    pub stages: Vec<StageParams>,
    /// Reported but not counted toward K nor required for success.
    #[serde(default)]
    pub optional_stages: Vec<StageParams>,
    /// Checks on the final state, all required for success.
    #[serde(default)]
    pub terminal: Vec<StageParams>,
    #[serde(default)]
    pub bindings: Vec<BindingParams>,
    #[serde(default)]
    pub pour_counters: Vec<PourCounterParams>,
    #[serde(default)]
    pub failures: Vec<FailureMonitorParams>,
}

/// A compiled atom.
#[derive(Debug, Clone)]
enum Check {
    Bddl(CompiledAtom),
    Near { body: usize, anchor: Anchor, xy_max_m: f64, dz: [f64; 2], square: bool },
    Window { body: usize, anchor: Anchor, ranges: [[f64; 2]; 3] },
    Drawer { site: SiteRef, open: bool, threshold_m: f64 },
    InBox { body: usize, site: usize, half_m: [f64; 3], lower_z_m: f64, upper_z_m: f64 },
    Released(usize),
    ReleasedAndClear { instance: usize, min_distance_m: f64 },
    Lifted { body: usize, above_m: f64 },
    Joint { qpos_adr: usize, min: Option<f64>, max: Option<f64>, abs: bool },
    PourCount { counter: usize, at_least: usize },
    DisplacedSince { body: usize, stage: usize, min_xy_m: f64 },
    Touching(SubtreeContact),
    MovedXy { body: usize, min_m: f64 },
    Any(Vec<Check>),
    All(Vec<Check>),
    Not(Box<Check>),
}

#[derive(Debug, Clone, Copy)]
enum Anchor {
    Body(usize),
    Site(SiteRef),
}

/// A site named directly, or through a binding resolved at reset.
#[derive(Debug, Clone, Copy)]
enum SiteRef {
    Fixed(usize),
    Bound(usize),
}

impl SiteRef {
    /// The site id (`None` for a binding before the first reset).
    fn id(self, base: &Baseline) -> Option<usize> {
        match self {
            SiteRef::Fixed(s) => Some(s),
            SiteRef::Bound(b) => base.bound.get(b).copied(),
        }
    }
}

/// Per-episode baselines the atoms read.
#[derive(Debug, Clone, Default)]
struct Baseline {
    /// site id → world position at reset
    site0: Vec<[f64; 3]>,
    /// body id → world position at reset
    body0: Vec<[f64; 3]>,
    /// binding → the site it was bound to at reset
    bound: Vec<usize>,
    /// stage → body id → world position when the stage completed (`displaced_since`)
    body_at_stage: Vec<Option<Vec<[f64; 3]>>>,
}

/// A compiled binding.
#[derive(Debug, Clone)]
struct Binding {
    name: String,
    probe_body: usize,
    sites: Vec<usize>,
}

impl Binding {
    /// The candidate nearest (3-D) to the probe's root in `data` (the first on ties).
    fn resolve(&self, data: &SimData) -> usize {
        let p = data.xpos()[self.probe_body];
        let d2 = |s: usize| {
            let q = data.site_xpos()[s];
            (0..3).map(|k| (p[k] - q[k]).powi(2)).sum::<f64>()
        };
        self.sites.iter().copied().min_by(|&a, &b| d2(a).total_cmp(&d2(b))).unwrap_or(self.sites[0])
    }
}

/// A named pour counter; `tracker` exists from the control step a stage naming it was first current.
#[derive(Debug, Clone)]
struct PourSlot {
    params: PourCounterParams,
    bottle_body: usize,
    target_site: usize,
    tracker: Option<PourTracker>,
}

impl PourSlot {
    fn count(&self) -> usize {
        self.tracker.as_ref().map_or(0, |t| t.pours().len())
    }
}

/// A compiled failure monitor.
#[derive(Debug, Clone)]
struct FailureMonitor {
    name: String,
    after_stage: usize,
    when: Check,
    reason: FailureReason,
    latched_at: Option<Tick>,
}

struct Ctx<'a> {
    index: &'a SceneIndex,
    commitment: &'a CommitmentTracker,
    base: &'a Baseline,
    pours: &'a [PourSlot],
    data: &'a SimData,
}

impl Check {
    fn holds(&self, c: &Ctx) -> bool {
        let d = c.data;
        match self {
            Check::Bddl(a) => a.evaluate(c.index, d),
            Check::Near { body, anchor, xy_max_m, dz, square } => {
                let p = d.xpos()[*body];
                let Some(q) = anchor.position(c) else { return false };
                let dz_now = p[2] - q[2];
                near_xy(p[0] - q[0], p[1] - q[1], *xy_max_m, *square) && dz_now > dz[0] && dz_now < dz[1]
            }
            Check::Window { body, anchor, ranges } => {
                let p = d.xpos()[*body];
                anchor.position(c).is_some_and(|q| inside_window([p[0] - q[0], p[1] - q[1], p[2] - q[2]], ranges))
            }
            Check::Drawer { site, open, threshold_m } => {
                let Some(site) = site.id(c.base) else { return false };
                let dy = (d.site_xpos()[site][1] - c.base.site0.get(site).map_or(0.0, |p| p[1])).abs();
                if *open { dy > *threshold_m } else { dy < *threshold_m }
            }
            Check::InBox { body, site, half_m, lower_z_m, upper_z_m } => {
                let p = d.xpos()[*body];
                let ctr = d.site_xpos()[*site];
                let m = d.site_xmat()[*site];
                (0..3).all(|k| {
                    let h = (m[3 * k] * half_m[0] + m[3 * k + 1] * half_m[1] + m[3 * k + 2] * half_m[2]).abs();
                    let (lo, hi) = if k == 2 { (ctr[k] - h - lower_z_m, ctr[k] + h + upper_z_m) } else { (ctr[k] - h, ctr[k] + h) };
                    p[k] > lo && p[k] < hi
                })
            }
            Check::Released(i) => !c.commitment.grasped(c.index, d, *i),
            Check::ReleasedAndClear { instance, min_distance_m } => {
                c.commitment.released_and_clear(c.index, d, *instance, *min_distance_m)
            }
            Check::Lifted { body, above_m } => d.xpos()[*body][2] - c.base.body0.get(*body).map_or(0.0, |p| p[2]) > *above_m,
            Check::Joint { qpos_adr, min, max, abs } => {
                let q = d.qpos()[*qpos_adr];
                joint_inside(if *abs { q.abs() } else { q }, *min, *max)
            }
            Check::PourCount { counter, at_least } => c.pours.get(*counter).is_some_and(|p| p.count() >= *at_least),
            Check::DisplacedSince { body, stage, min_xy_m } => {
                let Some(Some(then)) = c.base.body_at_stage.get(*stage) else { return false };
                let (p, q) = (d.xpos()[*body], then[*body]);
                (p[0] - q[0]).hypot(p[1] - q[1]) >= *min_xy_m
            }
            Check::Touching(contact) => contact.holds(d),
            Check::MovedXy { body, min_m } => {
                let (p, p0) = (d.xpos()[*body], c.base.body0.get(*body).copied().unwrap_or(d.xpos()[*body]));
                (p[0] - p0[0]).hypot(p[1] - p0[1]) >= *min_m
            }
            Check::Any(atoms) => atoms.iter().any(|a| a.holds(c)),
            Check::All(atoms) => atoms.iter().all(|a| a.holds(c)),
            Check::Not(inner) => !inner.holds(c),
        }
    }

    /// The pour counters this atom reads (so a stage naming one creates it when current).
    fn counters(&self, out: &mut Vec<usize>) {
        match self {
            Check::PourCount { counter, .. } => out.push(*counter),
            Check::Any(atoms) | Check::All(atoms) => atoms.iter().for_each(|a| a.counters(out)),
            Check::Not(inner) => inner.counters(out),
            _ => {}
        }
    }
}

impl Anchor {
    /// The anchor's current world position (`None` for a binding before the first reset).
    fn position(&self, c: &Ctx) -> Option<[f64; 3]> {
        match self {
            Anchor::Body(b) => Some(c.data.xpos()[*b]),
            Anchor::Site(s) => s.id(c.base).map(|s| c.data.site_xpos()[s]),
        }
    }
}

/// Each component of `offset` strictly inside its `(lo, hi)`.
fn inside_window(offset: [f64; 3], ranges: &[[f64; 2]; 3]) -> bool {
    offset.iter().zip(ranges).all(|(v, [lo, hi])| v > lo && v < hi)
}

/// `min < q < max`, each bound only where given.
fn joint_inside(q: f64, min: Option<f64>, max: Option<f64>) -> bool {
    min.is_none_or(|m| q > m) && max.is_none_or(|m| q < m)
}

/// What atoms may name besides the scene: bindings and pour counters, by name.
struct Names<'a> {
    index: &'a SceneIndex,
    model: &'a MjModel,
    bindings: &'a [String],
    counters: &'a [String],
    /// every stage's name (required, then optional), for `displaced_since`
    stages: &'a [String],
}

fn scene_err(what: &str, name: &str) -> TasksError {
    TasksError::Scene(format!("{CHECKER_ORDERED}: no {what} {name:?}"))
}

fn site_id(model: &MjModel, name: &str) -> Result<usize, TasksError> {
    model.name_to_id(MjtObjBase::mjOBJ_SITE, name).ok_or_else(|| scene_err("site", name))
}

fn instance_body(index: &SceneIndex, name: &str) -> Result<usize, TasksError> {
    index.instance(name).map(|i| index.instances[i].body).ok_or_else(|| scene_err("object or fixture", name))
}

fn compile(spec: &AtomSpec, names: &Names) -> Result<Check, TasksError> {
    let (index, model) = (names.index, names.model);
    let instance_body = |name: &str| instance_body(index, name);
    let site = |name: &str| site_id(model, name);
    let site_ref = |name: &str| -> Result<SiteRef, TasksError> {
        match name.strip_prefix('$') {
            Some(b) => names.bindings.iter().position(|n| n == b).map(SiteRef::Bound).ok_or_else(|| scene_err("binding", b)),
            None => site(name).map(SiteRef::Fixed),
        }
    };
    // an instance's root body, else a site (or binding)
    let anchor_of = |name: &str| -> Result<Anchor, TasksError> {
        match index.instance(name) {
            Some(i) => Ok(Anchor::Body(index.instances[i].body)),
            None => site_ref(name).map(Anchor::Site),
        }
    };
    Ok(match spec {
        AtomSpec::Bddl(words) => {
            let (predicate, args) = words.split_first().ok_or_else(|| scene_err("predicate in", "[]"))?;
            let atom = BddlAtom { predicate: predicate.to_ascii_lowercase(), args: args.to_vec(), pos: Pos::default() };
            Check::Bddl(CompiledAtom::compile(index, &atom)?)
        }
        AtomSpec::Near { object, anchor, xy_max_m, dz_range_m, square } => Check::Near {
            body: instance_body(object)?,
            anchor: anchor_of(anchor)?,
            xy_max_m: *xy_max_m,
            dz: *dz_range_m,
            square: *square,
        },
        AtomSpec::Window { object, anchor, x_m, y_m, z_m } => {
            Check::Window { body: instance_body(object)?, anchor: anchor_of(anchor)?, ranges: [*x_m, *y_m, *z_m] }
        }
        AtomSpec::DrawerOpen { site: s, min_displacement_m } => {
            Check::Drawer { site: site_ref(s)?, open: true, threshold_m: *min_displacement_m }
        }
        AtomSpec::DrawerClosed { site: s, max_displacement_m } => {
            Check::Drawer { site: site_ref(s)?, open: false, threshold_m: *max_displacement_m }
        }
        AtomSpec::InBox { object, site: s, lower_z_m, upper_z_m } => {
            let half_m = match index.resolve(s) {
                Some(EntityRef::Region(r)) => index.regions[r].half_size_m,
                _ => return Err(scene_err("BDDL region site (declared size needed)", s)),
            };
            Check::InBox { body: instance_body(object)?, site: site(s)?, half_m, lower_z_m: *lower_z_m, upper_z_m: *upper_z_m }
        }
        AtomSpec::Released(object) => Check::Released(index.instance(object).ok_or_else(|| scene_err("object", object))?),
        AtomSpec::ReleasedAndClear { object, min_distance_m } => Check::ReleasedAndClear {
            instance: index.instance(object).ok_or_else(|| scene_err("object", object))?,
            min_distance_m: *min_distance_m,
        },
        AtomSpec::Lifted { object, above_m } => Check::Lifted { body: instance_body(object)?, above_m: *above_m },
        AtomSpec::Joint { name, min, max, abs } => {
            let j = model.name_to_id(MjtObjBase::mjOBJ_JOINT, name).ok_or_else(|| scene_err("joint", name))?;
            if !matches!(model.jnt_type()[j], MjtJoint::mjJNT_HINGE | MjtJoint::mjJNT_SLIDE) {
                return Err(scene_err("hinge or slide joint", name));
            }
            Check::Joint { qpos_adr: model.jnt_qposadr()[j] as usize, min: *min, max: *max, abs: *abs }
        }
        AtomSpec::PourCount { counter, at_least } => Check::PourCount {
            counter: names.counters.iter().position(|n| n == counter).ok_or_else(|| scene_err("pour counter", counter))?,
            at_least: *at_least,
        },
        AtomSpec::DisplacedSince { object, stage, min_xy_m } => Check::DisplacedSince {
            body: instance_body(object)?,
            stage: names.stages.iter().position(|n| n == stage).ok_or_else(|| scene_err("stage", stage))?,
            min_xy_m: *min_xy_m,
        },
        AtomSpec::Touching { object, other, max_distance_m } => {
            Check::Touching(SubtreeContact::new(model, instance_body(object)?, instance_body(other)?, *max_distance_m))
        }
        AtomSpec::MovedXy { object, min_m } => Check::MovedXy { body: instance_body(object)?, min_m: *min_m },
        AtomSpec::Any(atoms) => Check::Any(atoms.iter().map(|a| compile(a, names)).collect::<Result<_, _>>()?),
        AtomSpec::All(atoms) => Check::All(atoms.iter().map(|a| compile(a, names)).collect::<Result<_, _>>()?),
        AtomSpec::Not(inner) => Check::Not(Box::new(compile(inner, names)?)),
    })
}

/// A body of a mechanism operation: fixed, or a bound drawer site's body (known at reset).
#[derive(Debug, Clone, Copy, PartialEq)]
enum BodySource {
    Body(usize),
    BoundSite(usize),
}

/// The mechanism operation a stage performs: which way, on which bodies' subtrees.
#[derive(Debug, Clone)]
struct StageOperation {
    kind: OperationKind,
    bodies: Vec<BodySource>,
}

/// The first articulation direction `atoms` move (searching `any`/`all`, not `not`) with the bodies of every atom
/// moving that way.
fn operation_of(atoms: &[AtomSpec], names: &Names) -> Option<StageOperation> {
    fn walk(a: &AtomSpec, names: &Names, out: &mut Vec<(OperationKind, BodySource)>) {
        let (index, model) = (names.index, names.model);
        let site_body = |site: &str| match site.strip_prefix('$') {
            Some(b) => names.bindings.iter().position(|n| n == b).map(BodySource::BoundSite),
            None => model.name_to_id(MjtObjBase::mjOBJ_SITE, site).map(|s| BodySource::Body(model.site_bodyid()[s] as usize)),
        };
        match a {
            AtomSpec::Bddl(words) if words.len() == 2 => {
                let kind = match PredicateKind::parse(&words[0]) {
                    Some(PredicateKind::Open) => OperationKind::Open,
                    Some(PredicateKind::Close) => OperationKind::Close,
                    _ => return,
                };
                if let Some(e) = index.resolve(&words[1]) {
                    out.extend(moving_bodies(index, model, e).into_iter().map(|b| (kind, BodySource::Body(b))));
                }
            }
            AtomSpec::DrawerOpen { site, .. } => out.extend(site_body(site).map(|b| (OperationKind::Open, b))),
            AtomSpec::DrawerClosed { site, .. } => out.extend(site_body(site).map(|b| (OperationKind::Close, b))),
            AtomSpec::Joint { name, min, max, abs } => {
                if let (Some(kind), Some(body)) = (joint_operation(index, name, *min, *max, *abs), crate::judge::mechanism::joint_body(model, name)) {
                    out.push((kind, BodySource::Body(body)));
                }
            }
            AtomSpec::Any(items) | AtomSpec::All(items) => items.iter().for_each(|i| walk(i, names, out)),
            _ => {}
        }
    }
    let mut found = Vec::new();
    atoms.iter().for_each(|a| walk(a, names, &mut found));
    let kind = found.first()?.0;
    let mut bodies: Vec<BodySource> = found.into_iter().filter(|(k, _)| *k == kind).map(|(_, b)| b).collect();
    bodies.dedup();
    Some(StageOperation { kind, bodies })
}

#[derive(Debug, Clone)]
struct Stage {
    name: String,
    all: Vec<Check>,
    /// The mechanism operation monitored for its sustained-contact ratio: a named `contact_body` (any direction), else
    /// an opening the atoms imply.
    operation: Option<StageOperation>,
    /// pour counters its atoms read
    counters: Vec<usize>,
}

impl Stage {
    fn compile(p: &StageParams, names: &Names) -> Result<Self, TasksError> {
        let all = p.all.iter().map(|a| compile(a, names)).collect::<Result<Vec<_>, _>>()?;
        let implied = operation_of(&p.all, names);
        let operation = match &p.contact_body {
            Some(b) => {
                let body = names.model.name_to_id(MjtObjBase::mjOBJ_BODY, b).ok_or_else(|| scene_err("body", b))?;
                let kind = implied.map_or(OperationKind::Operate, |o| o.kind);
                Some(StageOperation { kind, bodies: vec![BodySource::Body(body)] })
            }
            None => implied.filter(|o| o.kind == OperationKind::Open && !o.bodies.is_empty()),
        };
        let mut counters = Vec::new();
        all.iter().for_each(|a| a.counters(&mut counters));
        Ok(Self { name: p.name.clone(), all, operation, counters })
    }

    fn holds(&self, c: &Ctx) -> bool {
        self.all.iter().all(|a| a.holds(c))
    }
}

/// Which side of a forbidden-contact guard a geom is on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum GuardSide {
    Neither,
    /// In the body subtree of the guard's `objects[k]`.
    Object(usize),
    Forbidden,
}

/// A compiled [`ForbiddenContactParams`].
#[derive(Debug, Clone)]
struct ForbiddenContactGuard {
    objects: Vec<String>,
    label: String,
    max_distance_m: f64,
    /// geom id → side
    side: Vec<GuardSide>,
}

impl ForbiddenContactGuard {
    fn compile(p: &ForbiddenContactParams, index: &SceneIndex, model: &MjModel) -> Result<Self, TasksError> {
        let body_id = |name: &str| {
            model.name_to_id(MjtObjBase::mjOBJ_BODY, name).ok_or_else(|| TasksError::Scene(format!("forbidden contact: no body {name:?}")))
        };
        let forbidden = body_id(&p.body)?;
        let roots = p
            .objects
            .iter()
            .map(|o| {
                index.instance(o).map(|i| index.instances[i].body).ok_or_else(|| TasksError::Scene(format!("forbidden contact: no object {o:?}")))
            })
            .collect::<Result<Vec<_>, _>>()?;
        let (parents, geom_body) = (model.body_parentid(), model.geom_bodyid());
        let side = geom_body
            .iter()
            .map(|&b| {
                let b = b as usize;
                if in_subtree(parents, b, forbidden) {
                    GuardSide::Forbidden
                } else {
                    roots.iter().position(|&r| in_subtree(parents, b, r)).map_or(GuardSide::Neither, GuardSide::Object)
                }
            })
            .collect();
        Ok(Self { objects: p.objects.clone(), label: p.label.clone(), max_distance_m: p.max_distance_m, side })
    }

    /// The first listed object touching the forbidden body now, by contact order.
    fn touching(&self, contacts: impl IntoIterator<Item = ([usize; 2], f64)>) -> Option<usize> {
        contacts.into_iter().find_map(|([g1, g2], dist)| {
            if dist > self.max_distance_m {
                return None;
            }
            let side = |g: usize| self.side.get(g).copied().unwrap_or(GuardSide::Neither);
            match (side(g1), side(g2)) {
                (GuardSide::Object(k), GuardSide::Forbidden) | (GuardSide::Forbidden, GuardSide::Object(k)) => Some(k),
                _ => None,
            }
        })
    }

    fn latch_name(&self, object: usize) -> String {
        format!("{}_touched_{}", self.objects[object], self.label)
    }
}

/// The latched forbidden contact of a run.
#[derive(Debug, Clone, Serialize)]
struct ForbiddenContactLatch {
    name: String,
    object: String,
    tick: Tick,
}

fn stages_names(stages: &[Stage]) -> Vec<String> {
    stages.iter().map(|s| s.name.clone()).collect()
}

/// One change of the satisfied-goal set (unordered mode): when, and which goals hold afterwards.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct GoalSetChange {
    pub control_step: u64,
    pub sim_time_s: f64,
    pub satisfied: Vec<String>,
    /// Required goals among `satisfied`.
    pub count: usize,
}

/// The cooking goal evaluator's bookkeeping (task catalog §5.0): no order and no latch — which goals hold on the
/// final state decides — but the goal count at reset, the largest count seen, and every change of the satisfied
/// set (events, per-goal drop counts, the sets themselves) are kept as diagnostics. Goals `n_required..` are
/// optional: tracked but never counted.
#[derive(Debug, Clone)]
pub struct GoalSetTracker {
    names: Vec<String>,
    n_required: usize,
    holding: Vec<bool>,
    drops: Vec<u32>,
    initial_count: usize,
    max_count: usize,
    events: Vec<PrivateEvent>,
    changes: Vec<GoalSetChange>,
}

impl GoalSetTracker {
    pub fn new(names: Vec<String>, n_required: usize) -> Self {
        let n = names.len();
        Self {
            names,
            n_required: n_required.min(n),
            holding: vec![false; n],
            drops: vec![0; n],
            initial_count: 0,
            max_count: 0,
            events: Vec::new(),
            changes: Vec::new(),
        }
    }

    fn count(&self, holding: &[bool]) -> usize {
        holding[..self.n_required].iter().filter(|&&h| h).count()
    }

    fn satisfied(&self) -> Vec<String> {
        self.names.iter().zip(&self.holding).filter(|(_, h)| **h).map(|(n, _)| n.clone()).collect()
    }

    /// The evaluator reset: `holding` is the set at the reset state (counted as the initial count, not a change).
    pub fn reset(&mut self, holding: Vec<bool>, tick: Tick) {
        self.holding = holding;
        self.drops.iter_mut().for_each(|d| *d = 0);
        self.events.clear();
        self.initial_count = self.count(&self.holding);
        self.max_count = self.initial_count;
        self.changes = vec![GoalSetChange {
            control_step: tick.control_step,
            sim_time_s: tick.sim_time_s,
            satisfied: self.satisfied(),
            count: self.initial_count,
        }];
    }

    /// One control step: every goal that became true or false is an event; a goal that stopped holding is a drop.
    pub fn observe(&mut self, now: &[bool], tick: Tick) {
        let mut changed = false;
        for (i, (&h, was)) in now.iter().zip(self.holding.iter_mut()).enumerate() {
            if h == *was {
                continue;
            }
            *was = h;
            changed = true;
            if !h {
                self.drops[i] += 1;
            }
            let kind = if h { EventKind::StageCompleted } else { EventKind::StageRegressed };
            self.events.push(PrivateEvent { stage_index: Some(i), stage_name: Some(self.names[i].clone()), ..PrivateEvent::new(kind, tick) });
        }
        if changed {
            let count = self.count(&self.holding);
            self.max_count = self.max_count.max(count);
            self.changes.push(GoalSetChange {
                control_step: tick.control_step,
                sim_time_s: tick.sim_time_s,
                satisfied: self.satisfied(),
                count,
            });
        }
    }

    pub fn initial_count(&self) -> usize {
        self.initial_count
    }

    pub fn max_count(&self) -> usize {
        self.max_count
    }

    /// Required goals holding at the latest sample: what [`Self::write_into`] counts completed on that state.
    pub fn current_count(&self) -> usize {
        self.count(&self.holding)
    }

    /// Every goal that became true (`stage_completed`) or false (`stage_regressed`) since the reset, in order.
    pub fn events(&self) -> &[PrivateEvent] {
        &self.events
    }

    /// Fills the stage fields of `record` from the goals holding on the final state (`now`) and the diagnostics
    /// into `details`; returns whether every required goal holds.
    pub fn write_into(&self, now: &[bool], record: &mut EvaluationRecord, details: &mut serde_json::Map<String, serde_json::Value>) -> bool {
        let names = |f: &dyn Fn(usize) -> bool| -> Vec<String> {
            (0..self.names.len()).filter(|&i| f(i)).map(|i| self.names[i].clone()).collect()
        };
        let completed = self.count(now);
        record.required_stage_count = self.n_required;
        record.completed_required_stage_count = completed;
        record.stage_score_percent = score_percent(completed, self.n_required);
        record.ordered_stage_names = names(&|i| i < self.n_required);
        record.optional_stage_names = names(&|i| i >= self.n_required);
        record.completed_stage_names = names(&|i| now.get(i).copied().unwrap_or(false));
        record.stage_regressions = (0..self.names.len())
            .filter(|&i| self.drops[i] > 0)
            .map(|i| StageRegressions { stage_name: self.names[i].clone(), count: self.drops[i] })
            .collect();
        record.stage_events = self.events.clone();
        // the final state is one more sample: a change since the last control step still counts toward the maximum
        let max_count = self.max_count.max(completed);
        details.insert("initial_goal_count".into(), json!(self.initial_count));
        details.insert("max_goal_count".into(), json!(max_count));
        details.insert("final_goal_count".into(), json!(completed));
        details.insert("regressed_from_max".into(), json!(completed < max_count));
        details.insert("goal_set_changes".into(), json!(self.changes));
        completed == self.n_required
    }
}

pub struct StagedEvaluator {
    checker: String,
    order: OrderMode,
    index: Arc<SceneIndex>,
    goal: GoalChecker,
    commitment: CommitmentTracker,
    task_id: Option<String>,
    /// required stages, then optional ones
    stages: Vec<Stage>,
    n_required: usize,
    terminal: Vec<Stage>,
    gripper: GripperContact,
    site_names: Vec<String>,
    /// site id → the body carrying it (a drawer's region site moves with the drawer)
    site_body: Vec<usize>,
    /// body id → name, for the operations' records
    body_name: Vec<String>,
    /// stage → the bodies of its operation, resolved at reset (bindings are bound then)
    operation_bodies: Vec<Vec<usize>>,
    base: Baseline,
    bindings: Vec<Binding>,
    pours: Vec<PourSlot>,
    failures: Vec<FailureMonitor>,
    tracker: StageTracker,
    /// unordered mode: the satisfied-goal set over the episode
    goals: GoalSetTracker,
    /// (stage, monitor) of every ordered-mode operation so far
    monitors: Vec<(usize, ContactMonitor)>,
    monitor_open: Option<(usize, usize)>,
    /// unordered mode: (stage, its opening) for every stage that opens a mechanism
    pending_openings: Vec<(usize, PendingOpening)>,
    events: Vec<PrivateEvent>,
    sample_substeps: bool,
    guards: Vec<ForbiddenContactGuard>,
    forbidden: Option<ForbiddenContactLatch>,
    control_steps: u64,
    substeps: u64,
}

impl StagedEvaluator {
    pub fn new(
        checker: &str,
        params: StagedParams,
        goal: GoalChecker,
        commitment: CommitmentTracker,
        model: &MjModel,
        task_id: Option<String>,
    ) -> Result<Self, TasksError> {
        let index = goal.index().clone();
        let bindings = params
            .bindings
            .iter()
            .map(|b| {
                let sites = b.sites.iter().map(|s| site_id(model, s)).collect::<Result<Vec<_>, _>>()?;
                if sites.is_empty() {
                    return Err(scene_err("candidate site in binding", &b.name));
                }
                Ok(Binding { name: b.name.clone(), probe_body: instance_body(&index, &b.nearest_to)?, sites })
            })
            .collect::<Result<Vec<_>, TasksError>>()?;
        let pours = params
            .pour_counters
            .iter()
            .map(|p| {
                Ok(PourSlot {
                    params: p.clone(),
                    bottle_body: instance_body(&index, &p.bottle)?,
                    target_site: site_id(model, &p.target_site)?,
                    tracker: None,
                })
            })
            .collect::<Result<Vec<_>, TasksError>>()?;
        let binding_names: Vec<String> = params.bindings.iter().map(|b| b.name.clone()).collect();
        let counter_names: Vec<String> = params.pour_counters.iter().map(|p| p.name.clone()).collect();
        let stage_names: Vec<String> = params.stages.iter().chain(&params.optional_stages).map(|s| s.name.clone()).collect();
        let names = Names { index: &index, model, bindings: &binding_names, counters: &counter_names, stages: &stage_names };
        let mut stages = params.stages.iter().map(|s| Stage::compile(s, &names)).collect::<Result<Vec<_>, _>>()?;
        let n_required = stages.len();
        for s in &params.optional_stages {
            stages.push(Stage::compile(s, &names)?);
        }
        let terminal = params.terminal.iter().map(|s| Stage::compile(s, &names)).collect::<Result<Vec<_>, _>>()?;
        let failures = params
            .failures
            .iter()
            .map(|f| {
                Ok(FailureMonitor {
                    name: f.name.clone(),
                    after_stage: stages.iter().position(|s| s.name == f.after_stage).ok_or_else(|| scene_err("stage", &f.after_stage))?,
                    when: compile(&f.when, &names)?,
                    reason: f.reason,
                    latched_at: None,
                })
            })
            .collect::<Result<Vec<_>, TasksError>>()?;
        let guards =
            params.forbidden_contacts.iter().map(|g| ForbiddenContactGuard::compile(g, &index, model)).collect::<Result<Vec<_>, _>>()?;
        let gripper = GripperContact::new(&index, model)?;
        require_opening_handles(&stages, &bindings, &gripper, model)?;
        let nbody = model.ffi().nbody as usize;
        let specs = Self::specs(&stages, n_required);
        let goals = GoalSetTracker::new(stages_names(&stages), n_required);
        Ok(Self {
            checker: checker.to_owned(),
            order: if checker == CHECKER_UNORDERED { OrderMode::Unordered } else { params.order },
            index,
            goal,
            commitment,
            task_id,
            stages,
            n_required,
            terminal,
            gripper,
            site_names: (0..model.ffi().nsite as usize).map(|s| model.id_to_name(MjtObjBase::mjOBJ_SITE, s).unwrap_or_default().to_owned()).collect(),
            site_body: model.site_bodyid().iter().map(|&b| b as usize).collect(),
            body_name: body_names(model, &(0..nbody).collect::<Vec<_>>()),
            operation_bodies: Vec::new(),
            base: Baseline::default(),
            bindings,
            pours,
            failures,
            tracker: StageTracker::new(specs),
            goals,
            monitors: Vec::new(),
            monitor_open: None,
            pending_openings: Vec::new(),
            events: Vec::new(),
            sample_substeps: params.sample_substeps,
            guards,
            forbidden: None,
            control_steps: 0,
            substeps: 0,
        })
    }

    fn specs(stages: &[Stage], n_required: usize) -> Vec<StageSpec> {
        stages.iter().enumerate().map(|(i, s)| StageSpec { name: s.name.clone(), required: i < n_required }).collect()
    }

    /// The bodies of every stage's operation on this episode (a bound site is bound at reset).
    fn resolve_operation_bodies(&self) -> Vec<Vec<usize>> {
        self.stages
            .iter()
            .map(|s| {
                let sources = s.operation.iter().flat_map(|o| &o.bodies);
                let mut bodies: Vec<usize> = sources
                    .filter_map(|&b| match b {
                        BodySource::Body(b) => Some(b),
                        BodySource::BoundSite(k) => self.base.bound.get(k).and_then(|&site| self.site_body.get(site).copied()),
                    })
                    .collect();
                bodies.dedup();
                bodies
            })
            .collect()
    }

    /// The names of stage `stage`'s mechanism bodies and handle geoms on this episode.
    fn watched(&self, stage: usize) -> Watched {
        let bodies = self.operation_bodies.get(stage).map_or(&[][..], Vec::as_slice);
        Watched {
            bodies: bodies.iter().map(|&b| self.body_name.get(b).cloned().unwrap_or_default()).collect(),
            handle_geoms: self.gripper.handle_names(bodies),
        }
    }

    /// The record of an operation: which way, on which bodies and handle, and whether its stage completed.
    fn operation_json(&self, stage: usize, monitor: &ContactMonitor, window: Window, completed: bool) -> serde_json::Value {
        let kind = self.stages[stage].operation.as_ref().map_or(OperationKind::Operate, |o| o.kind);
        monitor.to_json(kind, window, &self.watched(stage), completed)
    }

    fn site_name(&self, site: usize) -> String {
        self.site_names.get(site).cloned().unwrap_or_default()
    }

    /// Creates the pour counters the stages `evaluated` name (first time only), then updates every existing counter
    /// once for this control step.
    fn feed_pours(&mut self, evaluated: &[usize], data: &SimData, tick: Tick) {
        for &i in evaluated {
            for &c in &self.stages[i].counters {
                let slot = &mut self.pours[c];
                if slot.tracker.is_none() {
                    let z0_m = self.base.body0.get(slot.bottle_body).map_or(0.0, |p| p[2]);
                    slot.tracker = Some(PourTracker::new(&slot.params.config, slot.bottle_body, slot.target_site, z0_m));
                }
            }
        }
        for slot in &mut self.pours {
            if let Some(t) = slot.tracker.as_mut()
                && t.update(data, tick.control_step).is_some()
            {
                self.events.push(PrivateEvent { subject: Some(slot.params.bottle.clone()), ..PrivateEvent::new(EventKind::PourDetected, tick) });
            }
        }
    }

    /// Latches every armed failure monitor whose atom holds now (armed once its stage has completed).
    fn check_failures(&mut self, data: &SimData, tick: Tick) {
        let ctx = Ctx { index: &self.index, commitment: &self.commitment, base: &self.base, pours: &self.pours, data };
        for m in &mut self.failures {
            if m.latched_at.is_none() && self.tracker.is_completed(m.after_stage) && m.when.holds(&ctx) {
                m.latched_at = Some(tick);
                self.events.push(PrivateEvent { subject: Some(m.name.clone()), ..PrivateEvent::new(EventKind::FailureLatched, tick) });
            }
        }
    }

    fn holding_now(&self, data: &SimData) -> Vec<bool> {
        let ctx = Ctx { index: &self.index, commitment: &self.commitment, base: &self.base, pours: &self.pours, data };
        self.stages.iter().map(|s| s.holds(&ctx)).collect()
    }

    /// Every goal is evaluated each tick, so every pour counter a goal names is live; counters update at control
    /// steps only (`control`), like the ordered mode's.
    fn observe_unordered(&mut self, data: &SimData, tick: Tick, control: bool) {
        if control && !self.pours.is_empty() {
            let all: Vec<usize> = (0..self.stages.len()).collect();
            self.feed_pours(&all, data, tick);
        }
        let now = self.holding_now(data);
        self.goals.observe(&now, tick);
    }

    /// The contact monitor of the current operation (control steps only: its ratio counts control steps).
    fn observe_monitor(&mut self, data: &SimData) {
        let current = self.tracker.current();
        if let Some((stage, _)) = self.monitor_open
            && current != Some(stage)
            && let Some((_, m)) = self.monitor_open.take()
        {
            self.monitors[m].1.close();
        }
        if let Some(i) = current
            && self.stages[i].operation.is_some()
        {
            if self.monitor_open.is_none() {
                self.monitors.push((i, ContactMonitor::new(self.stages[i].name.clone())));
                self.monitor_open = Some((i, self.monitors.len() - 1));
            }
            let touch = self.operation_bodies.get(i).map(|b| self.gripper.touches(data, b)).unwrap_or_default();
            if let Some((_, m)) = self.monitor_open {
                self.monitors[m].1.step(touch);
            }
        }
    }

    /// Unordered mode: each pending opening, after the goals were sampled on this control step.
    fn observe_pending_openings(&mut self, data: &SimData) {
        for (i, opening) in &mut self.pending_openings {
            let touch = self.gripper.touches(data, &opening.bodies);
            opening.step(touch, self.goals.holding.get(*i).copied().unwrap_or(false));
        }
    }

    /// Advances the stages; at control steps (`control`) also feeds the pour counters, re-tests the completed stages
    /// for regressions (a diagnostic: at substep rate it would count every substep of contact chatter while a released
    /// object settles) and polls the failure monitors.
    fn observe_ordered(&mut self, data: &SimData, tick: Tick, control: bool) {
        if control {
            let current = self.tracker.current();
            self.feed_pours(current.as_slice(), data, tick);
        }
        let ctx = Ctx { index: &self.index, commitment: &self.commitment, base: &self.base, pours: &self.pours, data };
        let stages = &self.stages;
        let completed = match self.order {
            OrderMode::Strict => self.tracker.advance_strict(tick, |i| stages[i].holds(&ctx)),
            _ => self.tracker.advance(tick, |i| stages[i].holds(&ctx)),
        };
        if let Some(i) = completed
            && let Some(slot) = self.base.body_at_stage.get_mut(i)
        {
            *slot = Some(data.xpos().to_vec());
        }
        let ctx = Ctx { index: &self.index, commitment: &self.commitment, base: &self.base, pours: &self.pours, data };
        let stages = &self.stages;
        if control {
            self.tracker.track_regressions(tick, |i| stages[i].holds(&ctx));
            self.check_failures(data, tick);
        }
    }

    /// Latches the first forbidden contact (checked before anything else at every tick); true once latched, when
    /// all further tracking stops.
    fn forbidden_contact_latched(&mut self, data: &SimData, tick: Tick) -> bool {
        if self.forbidden.is_some() {
            return true;
        }
        let contacts = || data.contact().iter().map(|c| ([c.geom[0] as usize, c.geom[1] as usize], c.dist));
        let Some((name, object)) =
            self.guards.iter().find_map(|g| g.touching(contacts()).map(|k| (g.latch_name(k), g.objects[k].clone())))
        else {
            return false;
        };
        self.events.push(PrivateEvent { subject: Some(name.clone()), ..PrivateEvent::new(EventKind::ForbiddenContact, tick) });
        self.forbidden = Some(ForbiddenContactLatch { name, object, tick });
        true
    }

    /// One sample of the stage logic (control step or substep).
    fn sample(&mut self, data: &SimData, tick: Tick, control: bool) {
        if self.forbidden_contact_latched(data, tick) {
            return;
        }
        if self.order == OrderMode::Unordered {
            self.observe_unordered(data, tick, control);
        } else {
            self.observe_ordered(data, tick, control);
        }
    }
}

/// Every opening stage's mechanism carries a declared handle (each candidate drawer of a bound site too): an error
/// otherwise, as its sustained-contact ratio could count nothing.
fn require_opening_handles(stages: &[Stage], bindings: &[Binding], gripper: &GripperContact, model: &MjModel) -> Result<(), TasksError> {
    for s in stages {
        let Some(op) = s.operation.as_ref().filter(|o| o.kind == OperationKind::Open) else { continue };
        let what = format!("stage {}", s.name);
        let fixed: Vec<usize> = op.bodies.iter().filter_map(|b| if let BodySource::Body(b) = b { Some(*b) } else { None }).collect();
        if !fixed.is_empty() {
            gripper.require_handle(&fixed, model, &what)?;
        }
        for b in &op.bodies {
            if let BodySource::BoundSite(k) = b {
                for &site in bindings.get(*k).map_or(&[][..], |b| b.sites.as_slice()) {
                    gripper.require_handle(&[model.site_bodyid()[site] as usize], model, &what)?;
                }
            }
        }
    }
    Ok(())
}

impl Evaluator for StagedEvaluator {
    fn checker(&self) -> &str {
        &self.checker
    }

    fn samples_substeps(&self) -> bool {
        self.sample_substeps
    }

    fn reset(&mut self, data: &SimData, tick: Tick) {
        let bound = self.bindings.iter().map(|b| b.resolve(data)).collect();
        self.base = Baseline {
            site0: data.site_xpos().to_vec(),
            body0: data.xpos().to_vec(),
            bound,
            body_at_stage: vec![None; self.stages.len()],
        };
        self.pours.iter_mut().for_each(|p| p.tracker = None);
        self.failures.iter_mut().for_each(|f| f.latched_at = None);
        self.tracker = StageTracker::new(Self::specs(&self.stages, self.n_required));
        self.monitors.clear();
        self.monitor_open = None;
        self.operation_bodies = self.resolve_operation_bodies();
        self.events.clear();
        self.control_steps = 0;
        self.substeps = 0;
        self.forbidden = None;
        self.commitment.reset(&self.index, data);
        let now = self.holding_now(data);
        self.pending_openings = if self.order == OrderMode::Unordered {
            self.stages
                .iter()
                .enumerate()
                .filter(|(_, s)| s.operation.as_ref().is_some_and(|o| o.kind == OperationKind::Open))
                .map(|(i, s)| {
                    let mut opening = PendingOpening::new(s.name.clone(), self.operation_bodies[i].clone(), self.watched(i));
                    opening.reset(now[i]);
                    (i, opening)
                })
                .collect()
        } else {
            Vec::new()
        };
        self.goals.reset(now, tick);
    }

    fn observe_substep(&mut self, data: &SimData, tick: Tick) {
        if self.sample_substeps {
            self.substeps += 1;
            self.sample(data, tick, false);
        }
    }

    fn observe_control_step(&mut self, data: &SimData, tick: Tick) {
        self.control_steps += 1;
        if self.forbidden.is_none() && self.order != OrderMode::Unordered {
            self.observe_monitor(data);
        }
        self.sample(data, tick, true);
        if self.forbidden.is_none() && self.order == OrderMode::Unordered {
            self.observe_pending_openings(data);
        }
        if let Some(e) = self.commitment.observe_event(&self.index, data, tick) {
            self.events.push(e);
        }
    }

    /// The stage events of the mode's tracker (the goal set's changes, or the ordered stages' completions,
    /// regressions and order violation) merged with the other events (pours, failures, forbidden contact,
    /// commitment): the record's `stage_events` and `events`, as they happen.
    fn private_events(&self) -> Vec<PrivateEvent> {
        let stage_events = if self.order == OrderMode::Unordered { self.goals.events() } else { self.tracker.events() };
        crate::judge::evaluator::merge_events(stage_events, &self.events)
    }

    /// Unordered: the required goals holding now (they may drop again); ordered: the latched required stages.
    fn stage_progress(&self) -> (usize, usize) {
        if self.order == OrderMode::Unordered {
            (self.goals.current_count(), self.n_required)
        } else {
            (self.tracker.completed_required_count(), self.tracker.required_count())
        }
    }

    fn finish(&mut self, data: &SimData, _tick: Tick) -> EvaluationRecord {
        let mut record = EvaluationRecord::new(self.checker.clone());
        record.task_id = self.task_id.clone();
        record.stages_unordered = self.order == OrderMode::Unordered;
        let ctx = Ctx { index: &self.index, commitment: &self.commitment, base: &self.base, pours: &self.pours, data };
        record.terminal_state_checks =
            self.terminal.iter().map(|t| TerminalCheck { name: t.name.clone(), passed: t.holds(&ctx) }).collect();
        record.terminal_state_success = record.terminal_state_checks.iter().all(|c| c.passed);
        let mut details = serde_json::Map::new();
        details.insert("order".into(), json!(self.order));
        let stages_ok;
        if self.order == OrderMode::Unordered {
            let now: Vec<bool> = self.stages.iter().map(|s| s.holds(&ctx)).collect();
            stages_ok = self.goals.write_into(&now, &mut record, &mut details);
        } else {
            self.tracker.write_into(&mut record);
            stages_ok = self.tracker.all_required_completed() && !self.tracker.order_violated();
            details.insert("order_violation".into(), json!(self.tracker.order_violated()));
            if let Some(label) = self.tracker.order_violation_label() {
                details.insert("order_violation_latch".into(), json!(label));
            }
        }
        if let Some((_, m)) = self.monitor_open.take() {
            self.monitors[m].1.close();
        }
        let mut ops: Vec<serde_json::Value> = self
            .monitors
            .iter()
            .map(|(i, m)| self.operation_json(*i, m, Window::StageCurrent, self.tracker.is_completed(*i)))
            .collect();
        ops.extend(self.pending_openings.iter().filter_map(|(_, o)| o.to_json(None)));
        if !ops.is_empty() {
            details.insert("opening_operations".into(), json!(ops));
        }
        if !self.bindings.is_empty() {
            let bound: serde_json::Map<String, serde_json::Value> = self
                .bindings
                .iter()
                .zip(&self.base.bound)
                .map(|(b, &s)| (b.name.clone(), json!(self.site_name(s))))
                .collect();
            details.insert("bindings".into(), serde_json::Value::Object(bound));
        }
        if !self.pours.is_empty() {
            let counters: Vec<_> = self
                .pours
                .iter()
                .map(|p| {
                    let pours: Vec<_> = p.tracker.iter().flat_map(|t| t.pours()).map(|q| json!({"start_step": q.start_step, "counted_step": q.counted_step})).collect();
                    json!({"name": p.params.name, "created": p.tracker.is_some(), "count": p.count(), "pours": pours,
                        "max_tilt_rad": p.tracker.as_ref().map(PourTracker::max_tilt_rad)})
                })
                .collect();
            details.insert("pour_counters".into(), json!(counters));
        }
        let latched: Vec<&FailureMonitor> = self.failures.iter().filter(|f| f.latched_at.is_some()).collect();
        if !self.failures.is_empty() {
            let list: Vec<_> = latched
                .iter()
                .map(|f| json!({"name": f.name, "reason": f.reason, "control_step": f.latched_at.map(|t| t.control_step)}))
                .collect();
            details.insert("latched_failures".into(), json!(list));
        }
        if !self.guards.is_empty() {
            details.insert("forbidden_contact".into(), json!(self.forbidden));
        }
        record.details = Some(serde_json::Value::Object(details));
        record.success = stages_ok && record.terminal_state_success && latched.is_empty() && self.forbidden.is_none();
        record.failure_reason = if record.success {
            None
        } else if self.forbidden.is_some() {
            Some(FailureReason::ForbiddenContact)
        } else if let Some(f) = latched.first() {
            Some(f.reason)
        } else if self.tracker.order_violated() {
            Some(FailureReason::OrderViolation)
        } else if !stages_ok {
            Some(FailureReason::IncompleteStage)
        } else {
            Some(FailureReason::TerminalStateInvalid)
        };
        crate::judge::support::fill_history(&mut record, (self.control_steps, self.substeps), &self.events, &self.commitment, &self.goal, data);
        record
    }
}

/// Horizontal part of the `near` atom: inside the circle of radius `max_m`, or with `square` the square of half side
/// `max_m` (strict bounds).
fn near_xy(dx: f64, dy: f64, max_m: f64, square: bool) -> bool {
    if square { dx.abs() < max_m && dy.abs() < max_m } else { dx.hypot(dy) < max_m }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn guard() -> ForbiddenContactGuard {
        use GuardSide::*;
        ForbiddenContactGuard {
            objects: vec!["bowl_a".into(), "bowl_b".into()],
            label: "tabletop".into(),
            max_distance_m: 1e-3,
            side: vec![Neither, Object(0), Object(1), Forbidden, Forbidden],
        }
    }

    #[test]
    fn forbidden_contact_needs_a_listed_object_against_the_forbidden_body_within_the_distance() {
        let g = guard();
        assert_eq!(g.touching([([1, 2], -0.01), ([0, 3], -0.01), ([3, 4], -0.01)]), None, "bowl–bowl, other–table: allowed");
        assert_eq!(g.touching([([3, 2], 0.0011)]), None, "a contact farther than 1 mm does not count");
        assert_eq!(g.touching([([3, 2], 0.001)]), Some(1), "at the limit it counts, either geom order");
        assert_eq!(g.touching([([0, 4], -0.02), ([1, 4], -0.002)]), Some(0));
        assert_eq!(g.touching([([99, 3], -0.02)]), None, "unknown geoms are neither side");
        assert_eq!(g.latch_name(1), "bowl_b_touched_tabletop");
    }

    #[test]
    fn joint_bounds_are_strict_and_optional() {
        assert!(joint_inside(0.31, Some(0.3), None));
        assert!(!joint_inside(0.3, Some(0.3), None));
        assert!(joint_inside(-5.0, None, Some(0.01)));
        assert!(!joint_inside(0.01, None, Some(0.01)));
        assert!(joint_inside(0.5, Some(0.4), Some(0.6)) && !joint_inside(0.7, Some(0.4), Some(0.6)));
        assert!(joint_inside(1.0, None, None));
    }

    #[test]
    fn window_and_all_atoms_parse_and_window_bounds_are_strict_per_axis() {
        let p: StagedParams = serde_json::from_value(json!({
            "stages": [{"name": "02", "all": [{"window": {"object": "cookies_1", "anchor": "wooden_cabinet_1_middle_region",
                "x_m": [-0.15, 0.15], "y_m": [-0.2, 0.1], "z_m": [-0.1, 0.1]}}]}]
        }))
        .unwrap();
        let AtomSpec::Window { y_m, .. } = &p.stages[0].all[0] else { panic!("not a window atom") };
        let any_all: AtomSpec = serde_json::from_value(json!({"any": [{"all": [
            {"window": {"object": "o", "anchor": "s", "x_m": [0.0, 1.0], "y_m": [0.0, 1.0], "z_m": [0.0, 1.0]}},
            {"drawer_closed": {"site": "s", "max_displacement_m": 0.08}}]}]}))
        .unwrap();
        assert!(matches!(&any_all, AtomSpec::Any(v) if matches!(&v[0], AtomSpec::All(w) if w.len() == 2)));
        assert_eq!(*y_m, [-0.2, 0.1]);
        let w = [[-0.15, 0.15], [-0.2, 0.1], [-0.1, 0.1]];
        assert!(inside_window([0.0, -0.19, 0.05], &w), "inside the drawer, toward its front");
        assert!(!inside_window([0.0, 0.1, 0.0], &w) && !inside_window([0.0, -0.2, 0.0], &w), "strict at both ends");
        assert!(!inside_window([0.16, 0.0, 0.0], &w) && !inside_window([0.0, 0.0, -0.11], &w), "each axis counts");
    }

    #[test]
    fn near_is_a_circle_unless_square() {
        assert!(!near_xy(0.15, 0.15, 0.2, false), "≈ 0.21 m away: outside the circle");
        assert!(near_xy(0.15, 0.15, 0.2, true), "inside the square (RoboMemArena's microwave rule)");
        assert!(!near_xy(0.2, 0.0, 0.2, true) && !near_xy(0.0, -0.21, 0.2, true), "strict, either axis");
        let p: StagedParams = serde_json::from_value(json!({"stages": [{"name": "01", "all": [
            {"near": {"object": "a", "anchor": "s", "xy_max_m": 0.2, "dz_range_m": [-1.0, 1.0], "square": true}},
            {"near": {"object": "a", "anchor": "s", "xy_max_m": 0.2, "dz_range_m": [-1.0, 1.0]}}]}]}))
        .unwrap();
        assert!(matches!(p.stages[0].all[..], [AtomSpec::Near { square: true, .. }, AtomSpec::Near { square: false, .. }]));
    }

    #[test]
    fn joint_and_any_atoms_parse() {
        let p: StagedParams = serde_json::from_value(json!({
            "stages": [{"name": "01", "all": [{"any": [
                {"joint": {"name": "d_latch_joint", "min": 1.1, "abs": true}},
                {"joint": {"name": "d_hinge", "min": 0.05}}]}], "contact_body": "d_latch"}]
        }))
        .unwrap();
        let AtomSpec::Any(inner) = &p.stages[0].all[0] else { panic!("not an any atom") };
        assert!(matches!(&inner[0], AtomSpec::Joint { min: Some(m), max: None, abs: true, .. } if *m == 1.1));
        assert!(matches!(&inner[1], AtomSpec::Joint { abs: false, .. }));
    }

    fn tick(step: u64) -> Tick {
        Tick::at_control_step(step, step as f64 * 0.05)
    }

    fn tracker() -> GoalSetTracker {
        GoalSetTracker::new(["a", "b", "c", "opt"].map(String::from).to_vec(), 3)
    }

    #[test]
    fn goal_set_counts_goals_on_the_final_state_and_keeps_initial_and_max() {
        let mut g = tracker();
        g.reset(vec![true, false, false, true], tick(0));
        assert_eq!(g.initial_count(), 1, "the optional goal is not counted");
        g.observe(&[true, true, false, true], tick(1));
        g.observe(&[true, true, true, true], tick(2));
        g.observe(&[true, false, true, false], tick(3));
        assert_eq!(g.max_count(), 3);
        let (mut record, mut details) = (EvaluationRecord::new("x"), serde_json::Map::new());
        let all = g.write_into(&[true, false, true, false], &mut record, &mut details);
        assert!(!all);
        assert_eq!((record.required_stage_count, record.completed_required_stage_count), (3, 2));
        assert_eq!(record.completed_stage_names, ["a", "c"]);
        assert_eq!(record.optional_stage_names, ["opt"]);
        assert_eq!(details["initial_goal_count"], 1);
        assert_eq!(details["max_goal_count"], 3);
        assert_eq!(details["regressed_from_max"], true);
        let drops: Vec<_> = record.stage_regressions.iter().map(|r| (r.stage_name.as_str(), r.count)).collect();
        assert_eq!(drops, [("b", 1), ("opt", 1)]);
    }

    #[test]
    fn goal_set_logs_every_change_and_nothing_else() {
        let mut g = tracker();
        g.reset(vec![false; 4], tick(0));
        g.observe(&[false; 4], tick(1));
        g.observe(&[true, false, false, false], tick(2));
        g.observe(&[true, false, false, false], tick(3));
        g.observe(&[false, false, false, false], tick(4));
        g.observe(&[true, false, false, false], tick(5));
        let (mut record, mut details) = (EvaluationRecord::new("x"), serde_json::Map::new());
        g.write_into(&[true, false, false, false], &mut record, &mut details);
        let steps: Vec<u64> = details["goal_set_changes"].as_array().unwrap().iter().map(|c| c["control_step"].as_u64().unwrap()).collect();
        assert_eq!(steps, [0, 2, 4, 5], "the reset set, then one entry per change");
        let kinds: Vec<_> = record.stage_events.iter().map(|e| (e.kind, e.tick.control_step)).collect();
        assert_eq!(kinds, [(EventKind::StageCompleted, 2), (EventKind::StageRegressed, 4), (EventKind::StageCompleted, 5)]);
        assert_eq!(record.stage_regressions[0].count, 1);
        assert_eq!(details["regressed_from_max"], false, "back at the maximum");
    }

    #[test]
    fn goal_set_reset_forgets_the_previous_episode() {
        let mut g = tracker();
        g.reset(vec![false; 4], tick(0));
        g.observe(&[true, true, true, false], tick(1));
        g.observe(&[false; 4], tick(2));
        g.reset(vec![false; 4], tick(0));
        let (mut record, mut details) = (EvaluationRecord::new("x"), serde_json::Map::new());
        assert!(!g.write_into(&[false; 4], &mut record, &mut details));
        assert_eq!(details["max_goal_count"], 0);
        assert!(record.stage_regressions.is_empty() && record.stage_events.is_empty());
        let mut all = tracker();
        all.reset(vec![true, true, true, false], tick(0));
        assert!(all.write_into(&[true, true, true, false], &mut record, &mut details), "optional goals are not required");
        assert_eq!(record.stage_score_percent, 100.0);
    }

    #[test]
    fn params_parse_from_manifest_json() {
        let p: StagedParams = serde_json::from_value(json!({
            "order": "strict",
            "stages": [{"name": "01", "all": [{"bddl": ["on", "a", "b"]}, {"released": "a"}], "contact_body": "x"},
                       {"name": "02", "all": [{"not": {"drawer_open": {"site": "s", "min_displacement_m": 0.1}}}]}],
            "terminal": [{"name": "t", "all": [{"near": {"object": "a", "anchor": "c", "xy_max_m": 0.3, "dz_range_m": [0.1, 0.3]}}]}]
        }))
        .unwrap();
        assert_eq!(p.order, OrderMode::Strict);
        assert_eq!(p.stages.len(), 2);
        assert!(matches!(p.stages[1].all[0], AtomSpec::Not(_)));
        assert!(!p.sample_substeps && p.forbidden_contacts.is_empty(), "both default off");
    }

    #[test]
    fn guard_rate_and_release_atom_parse_from_manifest_json() {
        let p: StagedParams = serde_json::from_value(json!({
            "order": "strict",
            "sample_substeps": true,
            "forbidden_contacts": [{"objects": ["a", "b"], "body": "table", "label": "tabletop", "max_distance_m": 0.001}],
            "stages": [{"name": "01", "all": [{"released_and_clear": {"object": "a", "min_distance_m": 0.055}}]}]
        }))
        .unwrap();
        assert!(p.sample_substeps);
        assert_eq!(p.forbidden_contacts[0].objects, ["a", "b"]);
        assert!(matches!(&p.stages[0].all[0], AtomSpec::ReleasedAndClear { object, min_distance_m } if object == "a" && *min_distance_m == 0.055));
    }
}
