//! The staged evaluator's compiler: atoms resolved against the scene and the model into [`Check`]s, which evaluate on
//! a state with the episode's baselines ([`Ctx`]); the stages and the mechanism operations their atoms imply.
use libero_bddl::{Atom as BddlAtom, Pos};
use libero_sim::mujoco_rs::prelude::{MjModel, MjtJoint, MjtObjBase};
use libero_sim::simulation::SimData;

use crate::TasksError;
use crate::judge::commitment::CommitmentTracker;
use crate::judge::mechanism::{GripperContact, OperationKind, joint_operation, moving_bodies};
use crate::judge::pouring::PourTracker;
use crate::judge::predicates::{CompiledAtom, EntityRef, PredicateKind, SceneIndex, SubtreeContact};
use crate::judge::staged::CHECKER_ORDERED;
use crate::judge::staged::lang::{AtomSpec, PourCounterParams, StageParams};

/// A compiled atom.
#[derive(Debug, Clone)]
pub(super) enum Check {
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
pub(super) enum Anchor {
    Body(usize),
    Site(SiteRef),
}

/// A site named directly, or through a binding resolved at reset.
#[derive(Debug, Clone, Copy)]
pub(super) enum SiteRef {
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
pub(super) struct Baseline {
    /// site id → world position at reset
    pub(super) site0: Vec<[f64; 3]>,
    /// body id → world position at reset
    pub(super) body0: Vec<[f64; 3]>,
    /// binding → the site it was bound to at reset
    pub(super) bound: Vec<usize>,
    /// stage → body id → world position when the stage completed (`displaced_since`)
    pub(super) body_at_stage: Vec<Option<Vec<[f64; 3]>>>,
}

/// A compiled binding.
#[derive(Debug, Clone)]
pub(super) struct Binding {
    pub(super) name: String,
    pub(super) probe_body: usize,
    pub(super) sites: Vec<usize>,
}

impl Binding {
    /// The candidate nearest (3-D) to the probe's root in `data` (the first on ties).
    pub(super) fn resolve(&self, data: &SimData) -> usize {
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
pub(super) struct PourSlot {
    pub(super) params: PourCounterParams,
    pub(super) bottle_body: usize,
    pub(super) target_site: usize,
    pub(super) tracker: Option<PourTracker>,
}

impl PourSlot {
    pub(super) fn count(&self) -> usize {
        self.tracker.as_ref().map_or(0, |t| t.pours().len())
    }
}

pub(super) struct Ctx<'a> {
    pub(super) index: &'a SceneIndex,
    pub(super) commitment: &'a CommitmentTracker,
    pub(super) base: &'a Baseline,
    pub(super) pours: &'a [PourSlot],
    pub(super) data: &'a SimData,
}

impl Check {
    pub(super) fn holds(&self, c: &Ctx) -> bool {
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
    pub(super) fn counters(&self, out: &mut Vec<usize>) {
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
pub(super) struct Names<'a> {
    pub(super) index: &'a SceneIndex,
    pub(super) model: &'a MjModel,
    pub(super) bindings: &'a [String],
    pub(super) counters: &'a [String],
    /// every stage's name (required, then optional), for `displaced_since`
    pub(super) stages: &'a [String],
}

pub(super) fn scene_err(what: &str, name: &str) -> TasksError {
    TasksError::Scene(format!("{CHECKER_ORDERED}: no {what} {name:?}"))
}

pub(super) fn site_id(model: &MjModel, name: &str) -> Result<usize, TasksError> {
    model.name_to_id(MjtObjBase::mjOBJ_SITE, name).ok_or_else(|| scene_err("site", name))
}

pub(super) fn instance_body(index: &SceneIndex, name: &str) -> Result<usize, TasksError> {
    index.instance(name).map(|i| index.instances[i].body).ok_or_else(|| scene_err("object or fixture", name))
}

pub(super) fn compile(spec: &AtomSpec, names: &Names) -> Result<Check, TasksError> {
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
pub(super) enum BodySource {
    Body(usize),
    BoundSite(usize),
}

/// The mechanism operation a stage performs: which way, on which bodies' subtrees.
#[derive(Debug, Clone)]
pub(super) struct StageOperation {
    pub(super) kind: OperationKind,
    pub(super) bodies: Vec<BodySource>,
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
pub(super) struct Stage {
    pub(super) name: String,
    pub(super) all: Vec<Check>,
    /// The mechanism operation monitored for its sustained-contact ratio: a named `contact_body` (any direction), else
    /// an opening the atoms imply.
    pub(super) operation: Option<StageOperation>,
    /// pour counters its atoms read
    pub(super) counters: Vec<usize>,
}

impl Stage {
    pub(super) fn compile(p: &StageParams, names: &Names) -> Result<Self, TasksError> {
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

    pub(super) fn holds(&self, c: &Ctx) -> bool {
        self.all.iter().all(|a| a.holds(c))
    }
}

pub(super) fn stages_names(stages: &[Stage]) -> Vec<String> {
    stages.iter().map(|s| s.name.clone()).collect()
}

/// Every opening stage's mechanism carries a declared handle (each candidate drawer of a bound site too): an error
/// otherwise, as its sustained-contact ratio could count nothing.
pub(super) fn require_opening_handles(stages: &[Stage], bindings: &[Binding], gripper: &GripperContact, model: &MjModel) -> Result<(), TasksError> {
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

/// Horizontal part of the `near` atom: inside the circle of radius `max_m`, or with `square` the square of half side
/// `max_m` (strict bounds).
fn near_xy(dx: f64, dy: f64, max_m: f64, square: bool) -> bool {
    if square { dx.abs() < max_m && dy.abs() < max_m } else { dx.hypot(dy) < max_m }
}


#[cfg(test)]
mod tests {
    use super::*;
    use crate::judge::staged::lang::StagedParams;
    use serde_json::json;

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

}
