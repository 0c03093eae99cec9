//! LIBERO's goal predicates (hf-libero 0.1.4 `predicates/base_predicates.py`, `object_states/base_object_states.py`,
//! `objects/articulated_objects.py`, `objects/site_object.py`) on a scene composed by `libero-sim`.
//!
//! Names resolve as LIBERO's `object_states_dict` does: every object and fixture instance (except the arena
//! pseudo-fixtures `main_table`, `floor`, `countertop`, `coffee_table`) by its root body `<name>_main`, and every
//! BDDL region by its MuJoCo site `<target>_<region>`. Contact tests use robosuite's `contact_geoms` of an instance:
//! every geom of its body subtree whose group is not 1, matched against MuJoCo's current contact list.
//!
//! Positions are read from `xpos`/`site_xpos` as they are in the data: after a physics step these lag `qpos` by the
//! integration of that step, exactly as robosuite's `_check_success` sees them.
use std::collections::HashMap;

use libero_bddl::Atom;
use libero_sim::compose::ComposedScene;
use libero_sim::mujoco_rs::prelude::{MjModel, MjtJoint, MjtObjBase};
use libero_sim::simulation::SimData;
use serde::Serialize;

use crate::TasksError;

/// Fixtures LIBERO never wraps in an object state (`_generate_object_state_wrapper`'s skip list).
pub const UNWRAPPED_FIXTURES: [&str; 4] = ["main_table", "floor", "countertop", "coffee_table"];

/// `In(A, region)`: LIBERO lowers the box's bottom face by this much (`SiteObject.in_box`).
pub const IN_BOX_LOWER_Z_MARGIN_M: f64 = 0.01;
/// `On(A, region)`: A's origin must lie within (size_z − 0.005, size_z + 0.10) along the site's z (`SiteObject.under`).
pub const ON_SITE_BELOW_TOP_M: f64 = 0.005;
pub const ON_SITE_ABOVE_TOP_M: f64 = 0.10;
/// `On(A, B)` for an object B: horizontal distance between the two root origins must be below this.
pub const ON_OBJECT_MAX_XY_DISTANCE_M: f64 = 0.03;
/// `Up(A)`: origin height threshold.
pub const UP_MIN_Z_M: f64 = 1.0;

/// One side of an articulation test on a joint position (metres for slides, radians for hinges).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
#[serde(tag = "test", content = "value")]
pub enum JointTest {
    /// `q < value`
    Below(f64),
    /// `q > value`
    Above(f64),
    /// `q >= value`
    AtLeast(f64),
    /// `q <= value`
    AtMost(f64),
}

impl JointTest {
    pub fn holds(self, q: f64) -> bool {
        match self {
            JointTest::Below(v) => q < v,
            JointTest::Above(v) => q > v,
            JointTest::AtLeast(v) => q >= v,
            JointTest::AtMost(v) => q <= v,
        }
    }
}

/// An articulated class's `is_open`/`is_close`/`turn_on`/`turn_off` (absent where LIBERO's class has no such
/// method or raises `NotImplementedError`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct ArticulationRule {
    pub open: Option<JointTest>,
    pub close: Option<JointTest>,
    pub turn_on: Option<JointTest>,
    pub turn_off: Option<JointTest>,
}

/// The thresholds of every LIBERO articulated class that implements them. The comparisons take `max`/`min` of
/// the class's default ranges exactly as the Python methods do (e.g. a cabinet drawer is "closed" only when
/// pushed strictly past 0 toward its +0.01 m limit).
pub fn articulation_rule(category: &str) -> Option<ArticulationRule> {
    let r = |open, close| ArticulationRule { open: Some(open), close: Some(close), ..Default::default() };
    match category {
        // door hinge about z, range [-2.094, 0] rad
        "microwave" => Some(r(JointTest::Below(-1.3), JointTest::Above(-0.005))),
        // drawer slides along local +y, range [-0.16, 0.01] m
        "wooden_cabinet" | "white_cabinet" | "wooden_cabinet_tall_bottom" => Some(r(JointTest::Below(-0.14), JointTest::Above(0.0))),
        "short_cabinet" => Some(r(JointTest::Above(0.10), JointTest::Below(0.0))),
        "short_fridge" => Some(r(JointTest::Above(2.0), JointTest::Below(0.0))),
        // T28's latched door hinge, range [0, 0.4] rad (catalog §2.2: open > 0.3, close ≤ 0.01)
        "robosuite_latched_door" => Some(r(JointTest::Above(0.3), JointTest::AtMost(0.01))),
        // knob hinge, range [-0.005, 2.1] rad
        "flat_stove" => Some(ArticulationRule {
            turn_on: Some(JointTest::AtLeast(0.5)),
            turn_off: Some(JointTest::Below(0.0)),
            ..Default::default()
        }),
        // slide_cabinet, window, faucet, basin_faucet: LIBERO raises NotImplementedError
        _ => None,
    }
}

/// The registered LIBERO predicate names (lower-case), in `VALIDATE_PREDICATE_FN_DICT` order.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum PredicateKind {
    True,
    False,
    In,
    On,
    Up,
    PrintJointState,
    Open,
    Close,
    TurnOn,
    TurnOff,
}

impl PredicateKind {
    pub fn parse(name: &str) -> Option<Self> {
        Some(match name.to_ascii_lowercase().as_str() {
            "true" => Self::True,
            "false" => Self::False,
            "in" => Self::In,
            "on" => Self::On,
            "up" => Self::Up,
            "printjointstate" => Self::PrintJointState,
            "open" => Self::Open,
            "close" => Self::Close,
            "turnon" => Self::TurnOn,
            "turnoff" => Self::TurnOff,
            _ => return None,
        })
    }

    /// Number of arguments the Python callable takes (`None` = any, the multi-ary constants).
    fn arity(self) -> Option<usize> {
        match self {
            Self::True | Self::False => None,
            Self::In | Self::On => Some(2),
            // `Up` is declared binary but called with one argument
            Self::Up | Self::PrintJointState | Self::Open | Self::Close | Self::TurnOn | Self::TurnOff => Some(1),
        }
    }
}

/// MuJoCo joint types, as far as the evaluators care.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum JointKind {
    /// 7-wide qpos; LIBERO's articulation tests cannot read it.
    Free,
    Ball,
    /// qpos in metres.
    Slide,
    /// qpos in radians.
    Hinge,
}

/// A joint as the predicates read it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct JointRef {
    pub name: String,
    pub qpos_adr: usize,
    pub kind: JointKind,
}

/// An object or fixture instance (LIBERO `ObjectState`).
#[derive(Debug, Clone, Serialize)]
pub struct InstanceEntity {
    pub name: String,
    pub category: String,
    pub is_fixture: bool,
    /// Root body `<name>_main`.
    pub body: usize,
    /// All joints of the instance in document order.
    pub joints: Vec<JointRef>,
    pub rule: Option<ArticulationRule>,
}

/// A BDDL region site (LIBERO `SiteObjectState`).
#[derive(Debug, Clone, Serialize)]
pub struct RegionEntity {
    pub key: String,
    pub site: usize,
    /// Half sizes as declared in the XML / TargetZone (not the compiled, possibly shrunk, site size).
    pub half_size_m: [f64; 3],
    /// Index of the owning instance; `None` for workspace (table/floor) zones.
    pub parent: Option<usize>,
    /// Joints of the body carrying the site (drawer slides).
    pub joints: Vec<JointRef>,
}

/// What a BDDL name denotes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub enum EntityRef {
    Instance(usize),
    Region(usize),
}

/// Name resolution and contact sets of one composed scene, built once per compiled model.
#[derive(Debug, Clone)]
pub struct SceneIndex {
    pub instances: Vec<InstanceEntity>,
    pub regions: Vec<RegionEntity>,
    by_name: HashMap<String, EntityRef>,
    /// geom id → instance whose `contact_geoms` contain it.
    geom_owner: Vec<Option<usize>>,
}

fn model_id(model: &MjModel, kind: MjtObjBase, name: &str) -> Result<usize, TasksError> {
    model.name_to_id(kind, name).ok_or_else(|| TasksError::Scene(format!("model has no {kind:?} named {name:?}")))
}

fn joint_ref(model: &MjModel, name: &str) -> Result<JointRef, TasksError> {
    let id = model_id(model, MjtObjBase::mjOBJ_JOINT, name)?;
    Ok(JointRef {
        name: name.to_owned(),
        qpos_adr: model.jnt_qposadr()[id] as usize,
        kind: match model.jnt_type()[id] {
            MjtJoint::mjJNT_FREE => JointKind::Free,
            MjtJoint::mjJNT_BALL => JointKind::Ball,
            MjtJoint::mjJNT_SLIDE => JointKind::Slide,
            _ => JointKind::Hinge,
        },
    })
}

/// Whether `body` is `root` or one of its descendants.
pub(crate) fn in_subtree(parent: &[i32], mut body: usize, root: usize) -> bool {
    loop {
        if body == root {
            return true;
        }
        if body == 0 {
            return false;
        }
        body = parent[body] as usize;
    }
}

/// "Body contact(A, B)" of the manipulation helpers (task catalog §0): some active contact between a geom of A's
/// body subtree and a geom of B's with contact distance ≤ `max_dist_m`. The geoms are sorted once per model.
#[derive(Debug, Clone)]
pub struct SubtreeContact {
    /// Per geom: 1 = in A's subtree, 2 = in B's (A wins where they nest), 0 = neither.
    geom_side: Vec<u8>,
    max_dist_m: f64,
}

impl SubtreeContact {
    pub fn new(model: &MjModel, body_a: usize, body_b: usize, max_dist_m: f64) -> Self {
        let parents = model.body_parentid();
        let geom_side = model
            .geom_bodyid()
            .iter()
            .map(|&b| {
                let b = b as usize;
                if in_subtree(parents, b, body_a) {
                    1
                } else if in_subtree(parents, b, body_b) {
                    2
                } else {
                    0
                }
            })
            .collect();
        Self { geom_side, max_dist_m }
    }

    pub fn holds(&self, data: &SimData) -> bool {
        data.contact().iter().any(|c| {
            let (a, b) = (self.geom_side[c.geom[0] as usize], self.geom_side[c.geom[1] as usize]);
            c.dist <= self.max_dist_m && ((a, b) == (1, 2) || (a, b) == (2, 1))
        })
    }
}

impl SceneIndex {
    pub fn new(scene: &ComposedScene, model: &MjModel) -> Result<Self, TasksError> {
        let mut instances = Vec::new();
        let mut by_name = HashMap::new();
        // objects_dict first, then fixtures_dict (a later key overwrites an earlier one, as in the Python dict)
        for info in scene.objects.iter().chain(&scene.fixtures) {
            if UNWRAPPED_FIXTURES.contains(&info.name.as_str()) {
                continue;
            }
            let joints = info.joints.iter().map(|j| joint_ref(model, j)).collect::<Result<Vec<_>, _>>()?;
            by_name.insert(info.name.clone(), EntityRef::Instance(instances.len()));
            instances.push(InstanceEntity {
                name: info.name.clone(),
                category: info.category.clone(),
                is_fixture: info.is_fixture,
                body: model_id(model, MjtObjBase::mjOBJ_BODY, &info.root_body)?,
                joints,
                rule: articulation_rule(&info.category),
            });
        }
        let mut regions = Vec::new();
        for r in &scene.regions {
            let half_size_m: [f64; 3] = r.size.as_slice().try_into().map_err(|_| {
                TasksError::Scene(format!("region {} has {} size values, predicates need 3", r.key, r.size.len()))
            })?;
            let parent = match &r.parent {
                Some(p) => match by_name.get(p) {
                    Some(EntityRef::Instance(i)) => Some(*i),
                    _ => return Err(TasksError::Scene(format!("region {} belongs to unknown instance {p}", r.key))),
                },
                None => None,
            };
            let joints = r.joints.iter().map(|j| joint_ref(model, j)).collect::<Result<Vec<_>, _>>()?;
            by_name.insert(r.key.clone(), EntityRef::Region(regions.len()));
            regions.push(RegionEntity {
                key: r.key.clone(),
                site: model_id(model, MjtObjBase::mjOBJ_SITE, &r.key)?,
                half_size_m,
                parent,
                joints,
            });
        }
        let parent = model.body_parentid();
        let ngeom = model.ffi().ngeom as usize;
        let (geom_body, geom_group) = (model.geom_bodyid(), model.geom_group());
        let mut geom_owner = vec![None; ngeom];
        for (g, owner) in geom_owner.iter_mut().enumerate() {
            if geom_group[g] == 1 {
                continue;
            }
            *owner = instances.iter().position(|inst| in_subtree(parent, geom_body[g] as usize, inst.body));
        }
        Ok(Self { instances, regions, by_name, geom_owner })
    }

    pub fn resolve(&self, name: &str) -> Option<EntityRef> {
        self.by_name.get(name).copied()
    }

    /// Instance index by name (objects and wrapped fixtures only).
    pub fn instance(&self, name: &str) -> Option<usize> {
        match self.resolve(name) {
            Some(EntityRef::Instance(i)) => Some(i),
            _ => None,
        }
    }

    /// The contact geoms of instance `i` (robosuite `contact_geoms`).
    pub fn contact_geoms(&self, i: usize) -> impl Iterator<Item = usize> + '_ {
        self.geom_owner.iter().enumerate().filter(move |(_, o)| **o == Some(i)).map(|(g, _)| g)
    }

    /// robosuite `check_contact(A, B)`: some current contact pairs a contact geom of `a` with one of `b`.
    pub fn in_contact(&self, data: &SimData, a: usize, b: usize) -> bool {
        data.contact().iter().any(|c| {
            let (o1, o2) = (self.geom_owner(c.geom[0] as usize), self.geom_owner(c.geom[1] as usize));
            (o1 == Some(a) && o2 == Some(b)) || (o1 == Some(b) && o2 == Some(a))
        })
    }

    /// The instance whose contact geoms include `geom`.
    pub fn geom_owner(&self, geom: usize) -> Option<usize> {
        self.geom_owner.get(geom).copied().flatten()
    }

    /// World position of an instance's root body or a region's site.
    pub fn position(&self, data: &SimData, e: EntityRef) -> [f64; 3] {
        match e {
            EntityRef::Instance(i) => data.xpos()[self.instances[i].body],
            EntityRef::Region(r) => data.site_xpos()[self.regions[r].site],
        }
    }
}

/// A goal atom bound to the scene, ready to evaluate.
#[derive(Debug, Clone, Serialize)]
pub struct CompiledAtom {
    /// The atom as written, lower-cased, e.g. `(open microwave_1)`.
    pub text: String,
    pub kind: PredicateKind,
    pub args: Vec<EntityRef>,
    /// Set when LIBERO's `_eval_predicate` returns `None` (an atom with 0 or more than 2 arguments): always false.
    pub evaluates_to_none: bool,
}

fn atom_text(atom: &Atom) -> String {
    let mut s = format!("({}", atom.predicate.to_ascii_lowercase());
    for a in &atom.args {
        s.push(' ');
        s.push_str(a);
    }
    s.push(')');
    s
}

impl CompiledAtom {
    /// Binds `atom`; fails where LIBERO would raise (unknown name or predicate, wrong argument kind or arity,
    /// an articulation test on a class that does not implement it or on a free joint).
    pub fn compile(index: &SceneIndex, atom: &Atom) -> Result<Self, TasksError> {
        let text = atom_text(atom);
        let kind = PredicateKind::parse(&atom.predicate)
            .ok_or_else(|| TasksError::goal(&text, format!("unknown predicate {:?}", atom.predicate)))?;
        let args = atom
            .args
            .iter()
            .map(|a| index.resolve(a).ok_or_else(|| TasksError::goal(&text, format!("no object, fixture or region named {a:?}"))))
            .collect::<Result<Vec<_>, _>>()?;
        // `_eval_predicate` only dispatches 1- or 2-argument atoms; anything else returns None (falsy)
        let evaluates_to_none = !(1..=2).contains(&args.len());
        if !evaluates_to_none
            && let Some(n) = kind.arity()
            && n != args.len()
        {
            return Err(TasksError::goal(&text, format!("{kind:?} takes {n} argument(s)")));
        }
        let compiled = Self { text, kind, args, evaluates_to_none };
        if !evaluates_to_none {
            compiled.check_argument_kinds(index)?;
        }
        Ok(compiled)
    }

    fn check_argument_kinds(&self, index: &SceneIndex) -> Result<(), TasksError> {
        let err = |m: &str| Err(TasksError::goal(&self.text, m));
        match self.kind {
            PredicateKind::In => match self.args[..] {
                [EntityRef::Instance(_), EntityRef::Region(_)] => Ok(()),
                [EntityRef::Region(_), _] => err("the contained argument must be an object (LIBERO reads its root body)"),
                _ => err("the container must be a region site (LIBERO objects have no in_box)"),
            },
            PredicateKind::On => match self.args[0] {
                EntityRef::Instance(_) => Ok(()),
                EntityRef::Region(_) => err("the supported argument must be an object (LIBERO reads its root body)"),
            },
            PredicateKind::Open | PredicateKind::Close | PredicateKind::TurnOn | PredicateKind::TurnOff => {
                let (joints, rule) = match self.args[0] {
                    EntityRef::Instance(i) => (&index.instances[i].joints, index.instances[i].rule),
                    EntityRef::Region(r) => {
                        if matches!(self.kind, PredicateKind::TurnOn | PredicateKind::TurnOff) {
                            return err("regions have no turn_on/turn_off (SiteObjectState)");
                        }
                        let reg = &index.regions[r];
                        (&reg.joints, reg.parent.and_then(|p| index.instances[p].rule))
                    }
                };
                if joints.is_empty() {
                    return Ok(()); // no joint is tested: Open/TurnOn false, Close/TurnOff true
                }
                if joints.iter().any(|j| matches!(j.kind, JointKind::Free | JointKind::Ball)) {
                    return err("articulation tests on a free or ball joint fail in LIBERO (multi-value qpos)");
                }
                let test = rule.and_then(|r| self.test_of(&r));
                if test.is_none() {
                    return err("this class does not implement the articulation test");
                }
                Ok(())
            }
            PredicateKind::True | PredicateKind::False | PredicateKind::Up | PredicateKind::PrintJointState => Ok(()),
        }
    }

    fn test_of(&self, rule: &ArticulationRule) -> Option<JointTest> {
        match self.kind {
            PredicateKind::Open => rule.open,
            PredicateKind::Close => rule.close,
            PredicateKind::TurnOn => rule.turn_on,
            PredicateKind::TurnOff => rule.turn_off,
            _ => None,
        }
    }

    /// The truth value on the current data.
    pub fn evaluate(&self, index: &SceneIndex, data: &SimData) -> bool {
        if self.evaluates_to_none {
            return false;
        }
        match self.kind {
            PredicateKind::True | PredicateKind::PrintJointState => true,
            PredicateKind::False => false,
            PredicateKind::Up => index.position(data, self.args[0])[2] >= UP_MIN_Z_M,
            PredicateKind::In => match self.args[..] {
                [a @ EntityRef::Instance(_), EntityRef::Region(r)] => region_contains(index, data, r, index.position(data, a)),
                _ => false,
            },
            PredicateKind::On => match self.args[..] {
                [EntityRef::Instance(a), EntityRef::Instance(b)] => on_object(index, data, a, b),
                [EntityRef::Instance(a), EntityRef::Region(r)] => on_region(index, data, a, r),
                _ => false,
            },
            PredicateKind::Open | PredicateKind::TurnOn => self.joint_values(index, data).any(|(t, q)| t.holds(q)),
            PredicateKind::Close | PredicateKind::TurnOff => self.joint_values(index, data).all(|(t, q)| t.holds(q)),
        }
    }

    /// (test, qpos) of every joint an articulation predicate reads (empty when the target has no joints).
    fn joint_values<'a>(&'a self, index: &'a SceneIndex, data: &'a SimData) -> impl Iterator<Item = (JointTest, f64)> + 'a {
        let (joints, rule): (&[JointRef], Option<ArticulationRule>) = match self.args.first() {
            Some(EntityRef::Instance(i)) => (&index.instances[*i].joints, index.instances[*i].rule),
            Some(EntityRef::Region(r)) => {
                let reg = &index.regions[*r];
                (&reg.joints, reg.parent.and_then(|p| index.instances[p].rule))
            }
            None => (&[], None),
        };
        // compile() guarantees a test exists whenever there are joints
        let test = rule.and_then(|r| self.test_of(&r));
        let qpos = data.qpos();
        joints.iter().filter_map(move |j| test.map(|t| (t, qpos[j.qpos_adr])))
    }
}

/// `SiteObject.in_box`: `h = |R·s|` (element-wise, R the row-major `site_xmat`), `c − h − (0,0,0.01) < p < c + h`.
pub fn region_contains(index: &SceneIndex, data: &SimData, region: usize, p: [f64; 3]) -> bool {
    let reg = &index.regions[region];
    let c = data.site_xpos()[reg.site];
    let rs = mat_vec(&data.site_xmat()[reg.site], reg.half_size_m);
    (0..3).all(|k| {
        let h = rs[k].abs();
        let lb = c[k] - h - if k == 2 { IN_BOX_LOWER_Z_MARGIN_M } else { 0.0 };
        p[k] > lb && p[k] < c[k] + h
    })
}

/// `SiteObjectState.check_ontop`: `d = R·(p − c)` (R, not Rᵀ, as LIBERO writes it),
/// `s_z − 0.005 < d_z < s_z + 0.10`, `|d_x| < s_x`, `|d_y| < s_y`; plus contact with the site's owner, if any.
fn on_region(index: &SceneIndex, data: &SimData, a: usize, region: usize) -> bool {
    let reg = &index.regions[region];
    let c = data.site_xpos()[reg.site];
    let p = data.xpos()[index.instances[a].body];
    let d = mat_vec(&data.site_xmat()[reg.site], [p[0] - c[0], p[1] - c[1], p[2] - c[2]]);
    let s = reg.half_size_m;
    let under = s[2] - ON_SITE_BELOW_TOP_M < d[2] && d[2] < s[2] + ON_SITE_ABOVE_TOP_M && d[0].abs() < s[0] && d[1].abs() < s[1];
    under && reg.parent.is_none_or(|owner| index.in_contact(data, owner, a))
}

/// `ObjectState.check_ontop` with B the support: `z_B ≤ z_A`, contact(B, A), `‖xy_A − xy_B‖ < 0.03`.
fn on_object(index: &SceneIndex, data: &SimData, a: usize, b: usize) -> bool {
    let (pa, pb) = (data.xpos()[index.instances[a].body], data.xpos()[index.instances[b].body]);
    pb[2] <= pa[2] && index.in_contact(data, b, a) && (pa[0] - pb[0]).hypot(pa[1] - pb[1]) < ON_OBJECT_MAX_XY_DISTANCE_M
}

fn mat_vec(m: &[f64; 9], v: [f64; 3]) -> [f64; 3] {
    [
        m[0] * v[0] + m[1] * v[1] + m[2] * v[2],
        m[3] * v[0] + m[4] * v[1] + m[5] * v[2],
        m[6] * v[0] + m[7] * v[1] + m[8] * v[2],
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Catalog §2.2: the latched door is open strictly above 0.3 rad and closed at or below 0.01 rad.
    #[test]
    fn latched_door_thresholds() {
        let r = articulation_rule("robosuite_latched_door").unwrap();
        let (open, close) = (r.open.unwrap(), r.close.unwrap());
        assert!(open.holds(0.3001) && !open.holds(0.3));
        assert!(close.holds(0.01) && close.holds(0.0) && !close.holds(0.0101));
    }
}
