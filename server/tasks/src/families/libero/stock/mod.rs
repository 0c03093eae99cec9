//! The generic scripted expert of the 130 stock LIBERO tasks (`libero_spatial`, `_object`, `_goal`, `_10`, `_90`,
//! addressed as `suite/NAME`): it reads the scene's own BDDL goal and plans every atom into a skill:
//!
//! - `In(obj, region)` / `On(obj, region | object)`: grasp from above and place (a rim pinch for bowls and mugs,
//!   fingers across the narrow side for everything else), the grasp and the drop height taken from the object's
//!   collision geometry (world bounding box of its contact geoms at the start of the step);
//! - `Open` / `Close` of a cabinet drawer region: pull or push its handle (the bottom drawer's, too low for a hand
//!   that pinches it, dragged and pushed with the fingertips); `Open` / `Close` of a microwave: swing the door by its
//!   handle, push it shut;
//! - `TurnOn` / `TurnOff` of a flat stove: pinch and turn the knob.
//!
//! Steps run in an order that works rather than the BDDL's: articulations first, a placement into a closed drawer
//! after an implicit opening and before the drawer's `Close`, a support object before what stands on it. A step
//! whose atom already holds when it would start is skipped. Each step's script is built when the step starts, from
//! the state then (so grasps follow objects moved by earlier steps).
//!
//! Behaviours: `solve`, and `stop_short` (every step but the last done; the last placement released 10 cm beyond its
//! target toward the robot, the last articulation stopped halfway), which must fail.
use std::sync::Arc;

use libero_sim::Simulation;
use nalgebra::{Matrix3, Vector3};

use crate::TasksError;
use crate::expert::fixtures::{microwave_door_phases, stove_knob_phases_toward};
use crate::expert::motion::{
    GRIPPER_CLOSED, GRIPPER_OPEN, Goal, Phase, PhaseCtx, Script, body_dir, body_point, grip_pose, mat3, open_along, rotate_world,
    rotation_error, vec3,
};
use crate::expert::skills::{
    BOTTOM_HANDLE_LOCAL_M, MIDDLE_HANDLE_LOCAL_M, TOP_HANDLE_LOCAL_M, BOTTOM_DRAWER_PITCH_RAD, carry, drag_drawer_open, extent, pos, pull_drawer, push_drawer, tip_push_drawer, xy_dist,
};
use crate::expert::{Expert, SOLVE, SceneRefs, SuiteExpert};
use crate::judge::goal::GoalChecker;
use crate::judge::predicates::{CompiledAtom, EntityRef, PredicateKind, SceneIndex};

mod clear;
mod fit;
mod grasp;
mod pan;
mod tilt;
mod topple;

/// Near miss: the last step stops short.
pub const STOP_SHORT: &str = "stop_short";
const BEHAVIOURS: &[&str] = &[STOP_SHORT];

/// Stock LIBERO suites: their entries run the stock BDDL and init file of the same name (the pool re-exports this).
pub const STOCK_SUITES: [&str; 5] = ["libero_spatial", "libero_object", "libero_goal", "libero_10", "libero_90"];

/// The generic expert of every stock task (`suite/NAME`): planned from the scene's goal, so no per-task rows.
pub const SUITE_EXPERT: SuiteExpert = SuiteExpert { suites: &STOCK_SUITES, behaviours: BEHAVIOURS, build: |refs, b, _| build(b, refs) };

/// Drawer slide targets (m): open needs q < −0.14 (range −0.16…0.01), closed q > 0.
const DRAWER_OPEN_Q_M: f64 = -0.152;
const DRAWER_CLOSED_Q_M: f64 = 0.001;
const DRAWER_HALF_Q_M: f64 = -0.07;
/// Microwave door hinge targets (rad): open needs q < −1.3, closed q > −0.005.
const DOOR_OPEN_Q_RAD: f64 = -1.45;
const DOOR_HALF_Q_RAD: f64 = -0.7;
/// Stove knob targets (rad): on needs q ≥ 0.5, off q < 0 (range −0.005…2.1).
const KNOB_ON_Q_RAD: f64 = 0.9;
const KNOB_OFF_Q_RAD: f64 = -0.004;
const KNOB_SHORT_ON_Q_RAD: f64 = 0.2;
const KNOB_SHORT_OFF_Q_RAD: f64 = 0.35;
/// Objects sharing a region stand this fraction of its half size from its centre, either side.
const SLOT_SPREAD: f64 = 0.6;
/// A footprint whose narrow side is at least this fraction of its wide side counts as round.
const ROUND_RATIO: f64 = 0.8;
/// How far toward an open drawer's front an object is put in (the region is ±7.6 cm deep).
const DRAWER_FRONT_SHIFT_M: f64 = 0.055;
/// A region whose surface normal leans this much from the vertical (its horizontal part; sin ≈ 17°) is tilted; a
/// placement on it aims this far downhill of its centre (m).
const TILTED_REGION_MIN_SIN: f64 = 0.3;
const TILTED_REGION_DOWNHILL_M: f64 = 0.012;
/// A tall object (over 8 cm) is grasped this far below its top: deep enough that a heavy book does not slip out.
const TALL_GRASP_BELOW_TOP_M: f64 = 0.05;
/// Control steps the hand waits at the end (1 s).
const SETTLE_STEPS: u32 = 20;
/// How far beyond its target `stop_short` lets the last object go (plus the region's half extent).
pub(super) const SHORT_OFFSET_M: f64 = 0.10;

/// What a placement aims at.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) enum Target {
    /// `In` (inside the box) or `On` (on top of the box) a region site.
    Region { region: usize, inside: bool },
    /// On another object (its root within 3 cm horizontally, in contact).
    Object(usize),
    /// On the table clear of a drawer region's open drawer (`clear`: the object stands under it).
    Aside { region: usize },
    /// On the table clear of the way `mover` (the plate) is pushed to `region` (`clear`: the object stands in it).
    OffPath { mover: usize, region: usize },
}

/// One planned step.
#[derive(Debug, Clone, PartialEq)]
pub(super) enum Step {
    Place { object: usize, target: Target },
    Drawer { region: usize, open: bool },
    Door { instance: usize, open: bool },
    Knob { instance: usize, on: bool },
}

/// A step and the goal atom it makes true (`None` for an implicit step: its own test is used).
pub(super) struct Planned {
    pub(super) step: Step,
    pub(super) atom: Option<CompiledAtom>,
}

/// The scene's goal as steps, or why one atom cannot be planned.
fn plan(index: &SceneIndex, goal: &GoalChecker) -> Result<Vec<Planned>, TasksError> {
    let cannot = |a: &CompiledAtom, why: &str| TasksError::goal(&a.text, format!("the generic expert cannot plan it: {why}"));
    let mut steps = Vec::new();
    for a in goal.atoms() {
        let step = match (a.kind, &a.args[..]) {
            (PredicateKind::In, [EntityRef::Instance(o), EntityRef::Region(r)]) => {
                Step::Place { object: *o, target: Target::Region { region: *r, inside: true } }
            }
            (PredicateKind::On, [EntityRef::Instance(o), EntityRef::Region(r)]) => {
                Step::Place { object: *o, target: Target::Region { region: *r, inside: false } }
            }
            (PredicateKind::On, [EntityRef::Instance(o), EntityRef::Instance(b)]) => Step::Place { object: *o, target: Target::Object(*b) },
            (PredicateKind::Open | PredicateKind::Close, [EntityRef::Region(r)]) => {
                let reg = &index.regions[*r];
                let cabinet = reg.parent.map(|p| index.instances[p].category.as_str());
                if reg.joints.len() != 1 || !cabinet.is_some_and(|c| c.ends_with("cabinet")) {
                    return Err(cannot(a, "only cabinet drawers open and close by region"));
                }
                Step::Drawer { region: *r, open: a.kind == PredicateKind::Open }
            }
            (PredicateKind::Open | PredicateKind::Close, [EntityRef::Instance(i)]) if index.instances[*i].category == "microwave" => {
                Step::Door { instance: *i, open: a.kind == PredicateKind::Open }
            }
            (PredicateKind::TurnOn | PredicateKind::TurnOff, [EntityRef::Instance(i)]) if index.instances[*i].category == "flat_stove" => {
                Step::Knob { instance: *i, on: a.kind == PredicateKind::TurnOn }
            }
            _ => return Err(cannot(a, "no skill for this predicate and argument kind")),
        };
        if let Step::Place { object, .. } = step
            && index.instances[object].is_fixture
        {
            return Err(cannot(a, "the object to move is a fixture"));
        }
        steps.push(Planned { step, atom: Some(a.clone()) });
    }
    Ok(order(index, steps))
}

/// The container a placement target lies in, if it must be open: a drawer region (its slide) or a microwave.
pub(super) fn container_of(index: &SceneIndex, target: Target) -> Option<Step> {
    let Target::Region { region, inside: true } = target else { return None };
    let reg = &index.regions[region];
    let parent = reg.parent?;
    if reg.joints.len() == 1 && index.instances[parent].category.ends_with("cabinet") {
        return Some(Step::Drawer { region, open: true });
    }
    (index.instances[parent].category == "microwave").then_some(Step::Door { instance: parent, open: true })
}

/// Whether `a` and `b` work the same articulation (a drawer's slide, a door, a knob).
pub(super) fn same_articulation(index: &SceneIndex, a: &Step, b: &Step) -> bool {
    match (a, b) {
        (Step::Drawer { region: r1, .. }, Step::Drawer { region: r2, .. }) => {
            index.regions[*r1].joints.first().map(|j| j.qpos_adr) == index.regions[*r2].joints.first().map(|j| j.qpos_adr)
        }
        (Step::Door { instance: i1, .. }, Step::Door { instance: i2, .. }) => i1 == i2,
        _ => false,
    }
}

/// Articulations first (in BDDL order), except the closing of a container something must go into; before each
/// placement into a container its opening (implicit unless the goal has it); placements with their support first;
/// the deferred closings last.
fn order(index: &SceneIndex, steps: Vec<Planned>) -> Vec<Planned> {
    let containers: Vec<Step> = steps
        .iter()
        .filter_map(|p| match p.step {
            Step::Place { target, .. } => container_of(index, target),
            _ => None,
        })
        .collect();
    let (mut places, others): (Vec<Planned>, Vec<Planned>) = steps.into_iter().partition(|p| matches!(p.step, Step::Place { .. }));
    let (late, early): (Vec<Planned>, Vec<Planned>) = others.into_iter().partition(|p| {
        let closing = matches!(p.step, Step::Drawer { open: false, .. } | Step::Door { open: false, .. });
        closing && containers.iter().any(|c| same_articulation(index, c, &p.step))
    });
    // a placement whose support object is itself placed goes after it
    let moved: Vec<usize> = places.iter().filter_map(|p| if let Step::Place { object, .. } = p.step { Some(object) } else { None }).collect();
    places.sort_by_key(|p| match p.step {
        Step::Place { target: Target::Object(b), .. } => usize::from(moved.contains(&b)),
        _ => 0,
    });
    let mut out = early;
    for p in places {
        if let Step::Place { target, .. } = p.step
            && let Some(open) = container_of(index, target)
            && !out.iter().any(|q| q.step == open)
        {
            out.push(Planned { step: open, atom: None });
        }
        out.push(p);
    }
    out.extend(late);
    clear::insert_clears(index, &mut out);
    clear::insert_path_clears(index, &mut out);
    out
}

/// What every step's script needs about the scene, owned (the expert outlives the scene references).
pub(super) struct Ctx {
    pub(super) index: Arc<SceneIndex>,
    /// Robot base (world, m): `stop_short` drops toward it.
    pub(super) base_m: Vector3<f64>,
}

/// A step ready to run: its phases, built when it starts.
pub(super) type Build = Box<dyn FnOnce(&Simulation, &Ctx, &Matrix3<f64>) -> Vec<Phase> + Send>;

struct ReadyStep {
    /// The step is skipped when this holds as it would start.
    done: Option<Done>,
    build: Build,
    /// The step's script turns the hand relative to the expert's start orientation, not to the hand's orientation
    /// as the step starts (the bottom drawer's fingertip skills: turned from a placement's grasp orientation, the
    /// hand would come at the bar with its last wrist joint on its limit).
    from_home: bool,
}

/// The generic expert: plays its steps one script at a time.
struct StockExpert {
    ctx: Ctx,
    steps: std::vec::IntoIter<ReadyStep>,
    script: Option<Script>,
    /// The hand's orientation at the start (pointing down): every grasp orientation is a turn of it.
    home_rot: Option<Matrix3<f64>>,
    /// Control steps waited so far for the scene to come to rest before the first step is planned.
    waited: u32,
}

/// Before planning, the expert holds still while any movable object moves faster than this (m/s), for at most
/// [`MAX_SETTLE_WAIT_STEPS`]: some stock init rows leave an object in the air (LIVING_ROOM_SCENE3's ketchup 0.5 m
/// over the table), and a grasp planned from that state comes down where the object no longer is.
const AT_REST_M_PER_S: f64 = 0.01;
const MAX_SETTLE_WAIT_STEPS: u32 = 60;

/// Whether every movable (non-fixture) object's root moves slower than [`AT_REST_M_PER_S`].
fn at_rest(sim: &Simulation, index: &SceneIndex) -> bool {
    let cvel = sim.data().cvel();
    index.instances.iter().filter(|i| !i.is_fixture).all(|i| Vector3::new(cvel[i.body][3], cvel[i.body][4], cvel[i.body][5]).norm() < AT_REST_M_PER_S)
}

impl Expert for StockExpert {
    fn act(&mut self, sim: &Simulation) -> Option<[f64; 7]> {
        let home = *self.home_rot.get_or_insert_with(|| grip_pose(sim).1);
        if self.script.is_none() && self.waited < MAX_SETTLE_WAIT_STEPS && !at_rest(sim, &self.ctx.index) {
            self.waited += 1;
            return Some([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, GRIPPER_OPEN]);
        }
        self.waited = MAX_SETTLE_WAIT_STEPS;
        loop {
            if let Some(script) = self.script.as_mut() {
                if let Some(a) = script.act(sim) {
                    return Some(a);
                }
                self.script = None;
            }
            let step = self.steps.next()?;
            if step.done.as_ref().is_some_and(|done| done(sim)) {
                continue;
            }
            let phases = (step.build)(sim, &self.ctx, &home);
            self.script = Some(if step.from_home { Script::with_home(phases, home) } else { Script::new(phases) });
        }
    }

    fn phase(&self) -> Option<&'static str> {
        self.script.as_ref().and_then(Script::phase_name)
    }
}

/// The plan of this scene's goal, one line per step (`open wooden_cabinet_1_top_region (implicit)`, `place butter_1
/// in wooden_cabinet_1_top_region`, …), or which atom cannot be planned (for `expert --all`'s "no expert" rows).
pub fn plan_check(refs: &SceneRefs) -> Result<Vec<String>, TasksError> {
    let index = &refs.index;
    let goal = GoalChecker::new(Arc::new(index.clone()), &refs.scene.problem)?;
    let describe = |p: &Planned| {
        let line = match p.step {
            Step::Place { object, target } => {
                let to = match target {
                    Target::Region { region, inside } => format!("{} {}", if inside { "in" } else { "on" }, index.regions[region].key),
                    Target::Object(b) => format!("on {}", index.instances[b].name),
                    Target::Aside { region } => format!("clear of {}", index.regions[region].key),
                    Target::OffPath { mover, region } => format!("clear of {}'s way to {}", index.instances[mover].name, index.regions[region].key),
                };
                format!("place {} {to}", index.instances[object].name)
            }
            Step::Drawer { region, open } => format!("{} {}", if open { "open" } else { "close" }, index.regions[region].key),
            Step::Door { instance, open } => format!("{} {}", if open { "open" } else { "close" }, index.instances[instance].name),
            Step::Knob { instance, on } => format!("turn {} {}", if on { "on" } else { "off" }, index.instances[instance].name),
        };
        if p.atom.is_none() { format!("{line} (implicit)") } else { line }
    };
    Ok(plan(index, &goal)?.iter().map(describe).collect())
}

pub fn build(behaviour: &str, refs: &SceneRefs) -> Result<Box<dyn Expert>, TasksError> {
    let index = Arc::new(refs.index.clone());
    let goal = GoalChecker::new(index.clone(), &refs.scene.problem)?;
    let planned = plan(&index, &goal)?;
    let short = behaviour != SOLVE;
    let last = planned.len().saturating_sub(1);
    let mut steps = Vec::with_capacity(planned.len());
    let targets: Vec<Option<Target>> = planned.iter().map(|p| if let Step::Place { target, .. } = p.step { Some(target) } else { None }).collect();
    let mut after_clear = false;
    let mut cleared: Vec<usize> = Vec::new();
    for (k, p) in planned.into_iter().enumerate() {
        let short = short && k == last;
        // a bowl or mug: grasp tries checked and repeated as steps of their own, then the carry (into a drawer, or
        // set aside from under one, the drawer's own pinch and straight rise instead)
        if let Step::Place { object, target } = p.step
            && grasp::rim_grasped(&index.instances[object].category)
            && clear::drawer_target(&index, target).is_none()
            && !matches!(target, Target::Aside { .. } | Target::OffPath { .. })
        {
            let atom_test = |a: &CompiledAtom| atom_done(&index, a.clone());
            let split = grasp::place_steps(object, &index.instances[object].category, target, slot_of(&targets, k), short, || p.atom.as_ref().filter(|_| !short).map(atom_test));
            steps.extend(split.into_iter().map(|(done, build)| ReadyStep { done, build, from_home: false }));
            continue;
        }
        // the near miss's last step always runs (it must act even where its atom holds already)
        let done = match (short, p.atom) {
            (true, _) => None,
            (false, Some(atom)) => Some(atom_done(&index, atom)),
            (false, None) => clear::clear_done(&index, &p.step).or_else(|| implicit_done(&index, &p.step)),
        };
        let slot = slot_of(&targets, k);
        // (a drawer opened after a clearing step: turned from the start, not from the clearing's rim grasp)
        let from_home = matches!(p.step, Step::Drawer { region, .. } if drawer_handle(&index, region) == Some(BOTTOM_HANDLE_LOCAL_M) || after_clear);
        after_clear = matches!(p.step, Step::Place { target: Target::Aside { .. }, .. });
        let mut build = step_builder(refs, &index, p.step.clone(), slot, short)?;
        // the placement into a drawer reopened after its object was set clear: from the pull's pose the reach
        // back for the object stretches the elbow onto its limit (KITCHEN_SCENE5's bowl), so from the start pose
        if let Step::Place { object, target } = p.step
            && cleared.contains(&object)
            && clear::drawer_target(&index, target).is_some()
        {
            build = Box::new(move |sim, ctx, home| {
                let mut phases = vec![rise(), clear::back_to_start(ctx, home)];
                phases.extend(build(sim, ctx, home));
                phases
            });
        }
        if let Step::Place { object, target: Target::Aside { .. } } = p.step {
            cleared.push(object);
        }
        steps.push(ReadyStep { done, build, from_home });
    }
    // the hand waits, open and still, until what it let go comes to rest: the goal is judged on the final state
    let settle: Build = Box::new(|_, _, _| vec![Phase::new("settle", |sim, ctx| Goal::at(ctx.start_pos_m, GRIPPER_OPEN).rotated(grip_pose(sim).1)).for_steps(SETTLE_STEPS)]);
    steps.push(ReadyStep { done: None, build: settle, from_home: false });
    let base = refs.scene.robot_base_pos;
    Ok(Box::new(StockExpert {
        ctx: Ctx { index, base_m: Vector3::new(base[0], base[1], base[2]) },
        steps: steps.into_iter(),
        script: None,
        home_rot: None,
        waited: 0,
    }))
}

/// Whether a step's work is done already (then it is skipped).
pub(super) type Done = Box<dyn Fn(&Simulation) -> bool + Send>;

/// A step's goal atom holds.
fn atom_done(index: &Arc<SceneIndex>, atom: CompiledAtom) -> Done {
    let index = index.clone();
    Box::new(move |sim| atom.evaluate(&index, sim.data()))
}

/// An implicit opening is done when its container already reads open.
fn implicit_done(index: &SceneIndex, step: &Step) -> Option<Done> {
    let (joints, owner) = match step {
        Step::Drawer { region, .. } => (index.regions[*region].joints.clone(), index.regions[*region].parent?),
        Step::Door { instance, .. } => (index.instances[*instance].joints.clone(), *instance),
        _ => return None,
    };
    let test = index.instances[owner].rule?.open?;
    Some(Box::new(move |sim| joints.iter().any(|j| test.holds(sim.data().qpos()[j.qpos_adr]))))
}

/// The `k`-th of `n` placements onto the same target.
#[derive(Debug, Clone, Copy)]
pub(super) struct Slot {
    pub(super) k: usize,
    pub(super) n: usize,
}

fn slot_of(targets: &[Option<Target>], step: usize) -> Slot {
    let same = |t: &Option<Target>| t.is_some() && *t == targets[step];
    Slot { k: targets[..step].iter().filter(|t| same(t)).count(), n: targets.iter().filter(|t| same(t)).count() }
}

/// The handle bar (in the drawer body's frame) of a drawer region's slide, by the slide's name.
pub(super) fn drawer_handle(index: &SceneIndex, region: usize) -> Option<[f64; 3]> {
    let joint = index.regions[region].joints.first()?;
    Some(if joint.name.ends_with("top_level") {
        TOP_HANDLE_LOCAL_M
    } else if joint.name.ends_with("middle_level") {
        MIDDLE_HANDLE_LOCAL_M
    } else {
        BOTTOM_HANDLE_LOCAL_M
    })
}

/// The script builder of one step (fixture ids resolved now, geometry read when it starts).
fn step_builder(refs: &SceneRefs, index: &SceneIndex, step: Step, slot: Slot, short: bool) -> Result<Build, TasksError> {
    Ok(match step {
        Step::Place { object, target } => {
            let body = index.instances[object].body;
            let category = index.instances[object].category.clone();
            if category == "plate"
                && let Target::Region { region, .. } = target
            {
                let zone = index.regions[region].site;
                // done once the dish is well inside its region (half way from the centre to the nearest side): nudged
                // on toward the exact centre, a plate stalled 1.5 cm off it is dragged back and forth past it
                let half = &index.regions[region].half_size_m;
                let stop_m = if short { 0.09 } else { (0.5 * half[0].abs().min(half[1].abs())).max(0.012) };
                let phases = super::objects::push_plate_phases(body, zone, stop_m);
                return Ok(Box::new(move |_, _, _| phases));
            }
            if let Target::Aside { region } = target {
                return clear::aside_builder(refs, index, object, region);
            }
            Box::new(move |sim, ctx, home| place_phases(sim, ctx, home, object, &category, target, slot, short))
        }
        Step::Drawer { region, open } => {
            let joint = index.regions[region].joints.first().ok_or_else(|| TasksError::Scene("drawer region without a joint".into()))?;
            let (q_adr, j) = refs.joint(&joint.name)?;
            let drawer = refs.model.jnt_bodyid()[j] as usize;
            let handle = drawer_handle(index, region).unwrap_or(BOTTOM_HANDLE_LOCAL_M);
            let q_goal = match (open, short) {
                (true, false) => DRAWER_OPEN_Q_M,
                (false, false) => DRAWER_CLOSED_Q_M,
                (_, true) => DRAWER_HALF_Q_M,
            };
            let mut phases = Vec::new();
            match (open, handle == BOTTOM_HANDLE_LOCAL_M) {
                (true, false) => pull_drawer(&mut phases, drawer, handle, q_adr, q_goal),
                (false, false) => push_drawer(&mut phases, drawer, handle, q_adr, q_goal),
                // the bottom drawer's bar is out of reach of a hand that pinches it: work it with the fingertips
                (true, true) => drag_drawer_open(&mut phases, drawer, handle, q_adr, q_goal, BOTTOM_DRAWER_PITCH_RAD),
                (false, true) => tip_push_drawer(&mut phases, drawer, handle, q_adr, q_goal, BOTTOM_DRAWER_PITCH_RAD),
            }
            let phases = with_rise(phases);
            Box::new(move |_, _, _| phases)
        }
        Step::Door { instance, open } => {
            let name = index.instances[instance].name.clone();
            let phases = if open {
                microwave_door_phases(refs, &name, if short { DOOR_HALF_Q_RAD } else { DOOR_OPEN_Q_RAD })?
            } else {
                close_door_phases(refs, &name, if short { DOOR_HALF_Q_RAD } else { -0.002 })?
            };
            let phases = with_rise(phases);
            Box::new(move |_, _, _| phases)
        }
        Step::Knob { instance, on } => {
            let name = index.instances[instance].name.clone();
            let q_goal = match (on, short) {
                (true, false) => KNOB_ON_Q_RAD,
                (false, false) => KNOB_OFF_Q_RAD,
                (true, true) => KNOB_SHORT_ON_Q_RAD,
                (false, true) => KNOB_SHORT_OFF_Q_RAD,
            };
            let phases = with_rise(stove_knob_phases_toward(refs, &name, q_goal)?);
            Box::new(move |_, _, _| phases)
        }
    })
}

/// How far the open hand first rises between steps: clear of whatever it just worked on (scenes' tables stand at
/// different heights, so relative to where it is).
const RISE_M: f64 = 0.08;

/// `phases` after a straight rise of the hand (it may end a step low in a drawer or at a knob).
pub(super) fn with_rise(phases: Vec<Phase>) -> Vec<Phase> {
    let mut out = vec![rise()];
    out.extend(phases);
    out
}

pub(super) fn rise() -> Phase {
    let up = |ctx: &PhaseCtx| Vector3::new(ctx.start_pos_m.x, ctx.start_pos_m.y, ctx.start_pos_m.z + RISE_M);
    Phase::new("rise", move |sim, ctx| Goal::at(up(ctx), GRIPPER_OPEN).rotated(grip_pose(sim).1))
        .until(move |sim, ctx| (grip_pose(sim).0 - up(ctx)).norm() < 0.03)
        .max_steps(60)
}


/// The horizontal direction along which the largest contact geom of `instance` is narrowest (fingers close across
/// it); world y (the hand's home opening, no wrist turn) for a round or square footprint, where any direction fits.
pub(super) fn narrow_dir(sim: &Simulation, index: &SceneIndex, instance: usize) -> Vector3<f64> {
    let (model, data) = (sim.model(), sim.data());
    let aabb = model.geom_aabb();
    let Some(g) = index.contact_geoms(instance).max_by(|&a, &b| {
        let v = |g: usize| aabb[g][3] * aabb[g][4] * aabb[g][5];
        v(a).total_cmp(&v(b))
    }) else {
        return Vector3::y();
    };
    let r = mat3(&data.geom_xmat()[g]);
    let mut horizontal: Vec<usize> = (0..3).filter(|&k| r[(2, k)].abs() < 0.7).collect();
    horizontal.sort_by(|&a, &b| aabb[g][3 + a].total_cmp(&aabb[g][3 + b]));
    match horizontal[..] {
        [narrow, wide] if aabb[g][3 + narrow] < ROUND_RATIO * aabb[g][3 + wide] => {
            Vector3::new(r[(0, narrow)], r[(1, narrow)], 0.0).normalize()
        }
        _ => Vector3::y(),
    }
}

/// How a placement holds its object: the grasp point's offset from the root (world) and the hand's orientation.
pub(super) struct Grasp {
    pub(super) offset_m: Vector3<f64>,
    pub(super) rot: Matrix3<f64>,
}

/// Objects whose shape the bounding box does not tell well enough, grasped at a point of their own frame.
struct Handle {
    /// Grasp point in the object's body frame (m).
    local_m: [f64; 3],
    /// Body-frame direction the fingers open along.
    fingers_local: [f64; 3],
    /// The hand pitched forward of straight down (about world y) by this much: the wrist comes back toward the base.
    pitch_rad: f64,
}

/// Per-family tuning: the moka pot across its lid's knob, straight down (as the cooking task's expert grasps it);
/// the frying pan across its handle 15 cm from its centre, level (placed by [`pan`]).
fn handle_of(category: &str) -> Option<Handle> {
    match category {
        "moka_pot" => Some(Handle { local_m: [0.0, 0.0, 0.075], fingers_local: [1.0, 0.0, 0.0], pitch_rad: 0.0 }),
        c if pan::is_pan(c) => Some(Handle { local_m: [0.15, 0.0, 0.039], fingers_local: [0.0, 1.0, 0.0], pitch_rad: 0.0 }),
        _ => None,
    }
}

/// Bowls and mugs are too wide for the hand: pinch the wall a little below the rim on the side along the narrower
/// horizontal extent (a mug's handle sticks out along the wider one). Anything else: from above at the centre of its
/// box, the fingers across its narrow side, a little below its top (not lower than 1.5 cm above its bottom).
fn choose_grasp(sim: &Simulation, body: usize, category: &str, lo: Vector3<f64>, hi: Vector3<f64>, narrow: Vector3<f64>, home: &Matrix3<f64>) -> Grasp {
    let root = pos(sim, body);
    if let Some(h) = handle_of(category) {
        let point = body_point(sim, body, h.local_m);
        let rot = rotate_world(&open_along(home, body_dir(sim, body, h.fingers_local)), Vector3::y(), -h.pitch_rad);
        return Grasp { offset_m: point - root, rot };
    }
    let centre = (lo + hi) / 2.0;
    let half = (hi - lo) / 2.0;
    if category.contains("bowl") || category.contains("mug") || category.contains("cup") {
        let (axis, r) = if half.y <= half.x { (Vector3::y(), half.y) } else { (Vector3::x(), half.x) };
        let rim = Vector3::new(centre.x, centre.y, hi.z - 0.014) + axis * (r - 0.008);
        return Grasp { offset_m: rim - root, rot: open_along(home, axis) };
    }
    let z = (hi.z - 0.03).max(lo.z + 0.015).min(centre.z.max(lo.z + 0.015));
    let z = if hi.z - lo.z > 0.08 { hi.z - TALL_GRASP_BELOW_TOP_M } else { z };
    Grasp { offset_m: Vector3::new(centre.x, centre.y, z) - root, rot: open_along(home, narrow) }
}

/// The near miss's let-go point: `SHORT_OFFSET_M` plus the region's half extent short of `to`, toward the robot.
pub(super) fn short_of(ctx: &Ctx, to: Vector3<f64>, target: Target) -> Vector3<f64> {
    let away = Vector3::new(ctx.base_m.x - to.x, ctx.base_m.y - to.y, 0.0);
    let extra = match target {
        Target::Region { region, .. } => ctx.index.regions[region].half_size_m[0].abs().max(ctx.index.regions[region].half_size_m[1].abs()),
        Target::Object(_) | Target::Aside { .. } | Target::OffPath { .. } => 0.0,
    };
    to + away.try_normalize(1e-9).unwrap_or(-Vector3::x()) * (SHORT_OFFSET_M + extra)
}

/// The world bounding boxes (instance, min, max) of every instance with contact geoms but `object`, now.
pub(super) fn other_boxes(sim: &Simulation, index: &SceneIndex, object: usize) -> Vec<(usize, Vector3<f64>, Vector3<f64>)> {
    (0..index.instances.len())
        .filter(|&i| i != object && index.contact_geoms(i).next().is_some())
        .map(|i| {
            let (lo, hi) = extent(sim, index, i);
            (i, lo, hi)
        })
        .collect()
}

/// A region's box now: its centre (world), its orientation, and its half height along world z (m).
pub(super) fn region_box(sim: &Simulation, index: &SceneIndex, region: usize) -> (Vector3<f64>, Matrix3<f64>, f64) {
    let reg = &index.regions[region];
    let r = mat3(&sim.data().site_xmat()[reg.site]);
    let h_z = r.row(2).transpose().component_mul(&Vector3::from(reg.half_size_m)).abs().sum();
    (vec3(&sim.data().site_xpos()[reg.site]), r, h_z)
}

/// Where the object's root should be let go: above the region's floor (`In`) or top (`On`) or the support object's
/// top, by the root's height above the object's bottom; and the height the root is carried at.
pub(super) fn place_target(sim: &Simulation, ctx: &Ctx, object: usize, target: Target, slot: Slot, root_above_bottom_m: f64, half_width_m: f64) -> (Vector3<f64>, f64) {
    let index = &ctx.index;
    match target {
        Target::Region { region, inside } => {
            let reg = &index.regions[region];
            let (c, r, h_z) = region_box(sim, index, region);
            let surface = if inside { c.z - h_z } else { c.z + h_z };
            let top = c.z + h_z;
            // an open drawer's back part stays under the cabinet: aim at its front part (the site turns with the
            // drawer body, which slides out along its local −y)
            // (as far as the object's width leaves room before the drawer's front wall)
            let shift = (reg.half_size_m[1] - half_width_m - 0.01).clamp(0.0, DRAWER_FRONT_SHIFT_M);
            let front = if inside && !reg.joints.is_empty() { r * Vector3::new(0.0, -shift, 0.0) } else { Vector3::zeros() };
            // several objects on one region (two moka pots on one burner) side by side along its axis nearest world y
            let side = if slot.n > 1 && !inside {
                let k = if r[(1, 0)].abs() > r[(1, 1)].abs() { 0 } else { 1 };
                let f = 2.0 * (slot.k as f64 + 0.5) / slot.n as f64 - 1.0;
                Vector3::new(r[(0, k)], r[(1, k)], 0.0) * (f * SLOT_SPREAD * reg.half_size_m[k])
            } else {
                Vector3::zeros()
            };
            // a tilted surface (the wine rack's cradle, inclined 62°): a little downhill of its centre, where what stands
            // on it leans into the cradle instead of tipping out of it (the surface's normal: the region box's thin
            // axis, turned up)
            let thin = (0..3).min_by(|&a, &b| reg.half_size_m[a].abs().total_cmp(&reg.half_size_m[b].abs())).unwrap_or(2);
            let normal = r.column(thin) * r[(2, thin)].signum();
            let downhill = Vector3::new(normal.x, normal.y, 0.0);
            let downhill = if !inside && downhill.norm() > TILTED_REGION_MIN_SIN { downhill.normalize() * TILTED_REGION_DOWNHILL_M } else { Vector3::zeros() };
            let front = front + side + downhill;
            (Vector3::new(c.x + front.x, c.y + front.y, surface + root_above_bottom_m + 0.012), top + root_above_bottom_m + 0.05)
        }
        Target::Aside { region } => clear::aside_target(sim, ctx, object, region),
        Target::OffPath { mover, region } => clear::off_path_target(sim, ctx, object, mover, region),
        Target::Object(b) => {
            let (_, hi) = extent(sim, index, b);
            let p = pos(sim, index.instances[b].body);
            (Vector3::new(p.x, p.y, hi.z + root_above_bottom_m + 0.005), hi.z + root_above_bottom_m + 0.06)
        }
    }
}

/// Pick `object` and place it on or in `target`.
#[allow(clippy::too_many_arguments)] // the step's plan (object, target, slot, short) plus the state it starts from
pub(super) fn place_phases(
    sim: &Simulation,
    ctx: &Ctx,
    home: &Matrix3<f64>,
    object: usize,
    category: &str,
    target: Target,
    slot: Slot,
    short: bool,
) -> Vec<Phase> {
    let body = ctx.index.instances[object].body;
    let root = pos(sim, body);
    let (lo, hi) = extent(sim, &ctx.index, object);
    let grasp = clear::drawer_pinch(sim, ctx, target, category, root, lo, hi, home)
        .unwrap_or_else(|| choose_grasp(sim, body, category, lo, hi, narrow_dir(sim, &ctx.index, object), home));
    let half_width_m = (hi.x - lo.x).max(hi.y - lo.y) / 2.0;
    let (mut to, carry_top) = place_target(sim, ctx, object, target, slot, root.z - lo.z, half_width_m);
    let generic = fit::Tuning::generic(to, grasp.rot, carry_top.max(root.z + 0.10).max(to.z + 0.08).min(1.30));
    let fit = match target {
        // the near miss keeps the generic plan: the tuned carry cannot reach a target short of the caddy toward the
        // robot, and would stand the book in the compartment anyway
        Target::Region { region, inside: true } if !short => fit::tune(sim, &ctx.index, object, region, home, generic),
        _ => generic,
    };
    to = fit.to_m;
    if short {
        to = short_of(ctx, to, target);
    }
    let (carry_z, place_rot) = (fit.carry_z_m, fit.rot);
    let (rot, off) = (grasp.rot, grasp.offset_m);
    if tilt::is_book(category)
        && !short
        && let Target::Region { region, inside: true } = target
        && let Some(e) = tilt::entry(sim, &ctx.index, object, region, ctx.base_m)
    {
        return with_rise(tilt::place_phases(sim, &ctx.index, object, region, &e, (off, rot), home));
    }
    if tilt::is_book(category)
        && let Target::Region { region, inside: true } = target
        && let Some(p) = topple::phases(sim, &ctx.index, object, region, (off, rot), ctx.base_m, home, short)
    {
        return with_rise(p);
    }
    if !short
        && !grasp::rim_grasped(category)
        && let Target::Region { region, inside: true } = target
        && clear::drawer_target(&ctx.index, target).is_some()
        && let Some(drop) = tilt::drawer_drop(sim, &ctx.index, object, region, (off, rot), home, (to, ctx.base_m))
    {
        return with_rise(drop);
    }
    if pan::is_pan(category) {
        let region = if let Target::Region { region, inside: true } = target { Some(region) } else { None };
        return with_rise(pan::place_phases(sim, &ctx.index, object, region, (off, rot), to, carry_z));
    }
    let target_now = move |_: &Simulation| to;
    let mut lift_rise: Option<f64> = None;
    let [above, down, close] = pick_phases(body, off, rot);
    let mut phases = vec![
        rise(),
        above,
        down,
        close,
        // the whole rise fixed as the lift starts: a goal re-read from the rising object stops half way, and the
        // carry then drags a tall object (a book) through the walls of what it goes into
        // (the perched book keeps the lift it was tuned with, re-read from the rising book, which lifts it half way
        // and leaves the carry to climb the rest: with the whole rise first it lands on the compartment's wall)
        Phase::new("lift", move |sim, ctx| {
            let rise = if fit.perched { carry_z - pos(sim, body).z } else { *lift_rise.get_or_insert_with(|| carry_z - pos(sim, body).z) };
            Goal::at(ctx.start_pos_m + Vector3::z() * rise, GRIPPER_CLOSED).slow(0.6).rotated(rot)
        })
        .until(move |sim, _| pos(sim, body).z > carry_z - 0.015)
        .max_steps(if fit.perched { 80 } else { 120 }),
        Phase::new("carry_over_target", move |sim, _| {
            let t = target_now(sim);
            Goal::at(carry(sim, body, Vector3::new(t.x, t.y, carry_z)), GRIPPER_CLOSED).slow(fit.carry_speed).rotated(place_rot)
        })
        .until(move |sim, _| xy_dist(pos(sim, body), target_now(sim)) < 0.008 && rotation_error(sim, &place_rot) < fit.turn_tol_rad)
        .max_steps(200),
        Phase::new("lower", move |sim, _| Goal::at(carry(sim, body, target_now(sim) - Vector3::z() * 0.01), GRIPPER_CLOSED).slow(0.35).rotated(place_rot))
            .until(move |sim, ctx| pos(sim, body).z < target_now(sim).z + 0.004 || stalled(sim, ctx))
            .max_steps(70),
        Phase::new("open", move |_, ctx| Goal::at(ctx.start_pos_m, GRIPPER_OPEN).rotated(place_rot)).for_steps(10),
        Phase::new("retreat", move |_, ctx| Goal::at(ctx.start_pos_m + Vector3::z() * 0.12, GRIPPER_OPEN).rotated(place_rot))
            .until_reached(0.02)
            .max_steps(40),
    ];
    clear::rise_before_carry(&ctx.index, target, body, carry_z, &mut phases);
    phases
}

/// Above the grip point (`offset_m` from `body`'s root, read as the object stands), down onto it, and close the
/// fingers (until they stop), the hand at `rot`.
pub(super) fn pick_phases(body: usize, offset_m: Vector3<f64>, rot: Matrix3<f64>) -> [Phase; 3] {
    let at_grasp = move |sim: &Simulation| pos(sim, body) + offset_m;
    [
        Phase::new("above_object", move |sim, _| Goal::at(at_grasp(sim) + Vector3::z() * 0.10, GRIPPER_OPEN).rotated(rot))
            .until(move |sim, _| (grip_pose(sim).0 - at_grasp(sim) - Vector3::z() * 0.10).norm() < 0.012 && rotation_error(sim, &rot) < 0.06)
            .max_steps(160),
        Phase::new("down_to_object", move |sim, _| Goal::at(at_grasp(sim), GRIPPER_OPEN).slow(0.5).rotated(rot))
            .until_reached(0.007)
            .max_steps(80),
        Phase::new("close", move |_, ctx| Goal::at(ctx.start_pos_m, GRIPPER_CLOSED).rotated(rot))
            .until(|sim, ctx| ctx.steps >= 20 || (ctx.steps >= 8 && sim.data().qvel()[sim.ids().finger_dof_adr[0]].abs() < 1e-3))
            .max_steps(20),
    ]
}

/// Lowering has stalled: the object rests on something (its support is higher than the target guessed). Read from
/// the object's vertical speed after the first steps of the phase.
pub(super) fn stalled(sim: &Simulation, ctx: &PhaseCtx) -> bool {
    const STILL_M_PER_S: f64 = 0.004;
    ctx.steps > 15 && grip_speed_z(sim).abs() < STILL_M_PER_S
}

/// The hand's vertical speed (m/s): the grip site's linear velocity along world z.
fn grip_speed_z(sim: &Simulation) -> f64 {
    let m = sim.model();
    let site = sim.ids().grip_site;
    let body = m.site_bodyid()[site] as usize;
    // cvel: [angular(3), linear(3)] at the subtree's centre of mass frame; the linear part suffices to tell still
    sim.data().cvel()[body][5]
}

/// LIBERO microwave door: a point on its outer face near the free edge, in the door body's frame (the handle side is
/// local +x, the outer face local −y).
const DOOR_PUSH_LOCAL_M: [f64; 3] = [0.20, -0.03, 0.05];

/// Push a microwave's door shut with the closed hand on its outer face near the free edge, the goal leading the door
/// along its arc, until the hinge reads at least `q_goal`.
fn close_door_phases(refs: &SceneRefs, microwave: &str, q_goal: f64) -> Result<Vec<Phase>, TasksError> {
    let door = refs.body(&format!("{microwave}_microdoorroot"))?;
    let (q_adr, joint) = refs.joint(&format!("{microwave}_microjoint"))?;
    let q = move |sim: &Simulation| sim.data().qpos()[q_adr];
    let anchor = move |sim: &Simulation| vec3(&sim.data().xanchor()[joint]);
    let axis = move |sim: &Simulation| vec3(&sim.data().xaxis()[joint]);
    let face = move |sim: &Simulation, out_m: f64| body_point(sim, door, [DOOR_PUSH_LOCAL_M[0], DOOR_PUSH_LOCAL_M[1] - out_m, DOOR_PUSH_LOCAL_M[2]]);
    let ahead = move |sim: &Simulation, lead: f64, out_m: f64| {
        let spin = nalgebra::Rotation3::from_axis_angle(&nalgebra::Unit::new_normalize(axis(sim)), lead);
        let a = anchor(sim);
        a + spin * (face(sim, out_m) - a)
    };
    Ok(vec![
        Phase::new("above_door_face", move |sim, _| Goal::at(face(sim, 0.08) + Vector3::z() * 0.10, GRIPPER_CLOSED))
            .until_reached(0.015)
            .max_steps(150),
        Phase::new("beside_door_face", move |sim, _| Goal::at(face(sim, 0.06), GRIPPER_CLOSED).slow(0.5)).until_reached(0.01).max_steps(80),
        Phase::new("push_door", move |sim, _| {
            let lead = (q_goal - q(sim) + 0.1).clamp(0.1, 0.3);
            Goal::at(ahead(sim, lead, 0.0), GRIPPER_CLOSED).slow(0.5)
        })
        .until(move |sim, _| q(sim) >= q_goal)
        .max_steps(300),
        Phase::new("back_off_door", move |sim, ctx| Goal::at(ctx.start_pos_m - (face(sim, 0.0) - face(sim, 0.1)) + Vector3::z() * 0.05, GRIPPER_CLOSED))
            .until_reached(0.02)
            .max_steps(40),
    ])
}

