//! LIBERO's reset-time placement, reproduced draw for draw from NumPy's legacy global RNG.
//!
//! `env.seed(s); env.reset()` in LIBERO (hf-libero 0.1.4 `BDDLBaseDomain._reset_internal` on robosuite 1.4.0)
//! consumes the stream in this order:
//! 1. robot `initialization_noise`: `randn(7)` (magnitude 0 in `ControlEnv`, but drawn);
//! 2. `object_property_initializers` (Open/Close/TurnOn/TurnOff atoms of `:init`, in order): one `uniform` each;
//!    the list is appended to on every model load, so after the `n`-th reset it holds `n + 1` copies;
//! 3. `mj_step1`, then the table samplers in `:init` order — fixtures (`MultiRegionRandomSampler`: no boundary
//!    shrink, no collision check, yaw about z) and objects (`TableRegionSampler`/`Libero100TableRegionSampler`:
//!    `randint(#ranges)`, x, y, rejection against everything placed so far, then the rotation draws);
//! 4. objects on object/fixture sites (`SiteRegionRandomSampler`, then `InSiteRegionRandomSampler`), then objects
//!    on objects (`ObjectBasedSampler`).
//!
//! Fixture poses are model parameters (`body_pos`/`body_quat`), not part of the state vector, so they are not in the
//! init files; [`Placement::apply`] writes them (and the site-alpha changes of `visualize(False)`) into a compiled
//! model exactly as robosuite does, without recomputing derived constants.
use mujoco_rs::prelude::*;

use crate::compose::registry::Rotation;
use crate::compose::{ComposedScene, InstanceInfo};
use crate::numpy_rng::NumpyRandomState;
use crate::SimError;

/// Panda arm `init_qpos` of LIBERO's MountedPanda / OnTheGroundPanda (rad).
pub const PANDA_INIT_QPOS: [f64; 7] = crate::robot::ARM_INIT_QPOS_RAD;
/// Panda gripper `init_qpos` (m).
pub const GRIPPER_INIT_QPOS: [f64; 2] = [0.020833, -0.020833];

/// A fixture's sampled pose (world frame; quaternion w, x, y, z).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct FixturePose {
    pub name: String,
    pub root_body: String,
    pub pos: [f64; 3],
    pub quat_wxyz: [f64; 4],
}

/// A movable object's sampled placement: the 7 values LIBERO writes into its free joint's qpos.
/// (LIBERO writes the samplers' x, y, z, w quaternion into MuJoCo's w, x, y, z slots — reproduced as is.)
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ObjectPose {
    pub name: String,
    pub joint: String,
    pub qpos: [f64; 7],
}

/// Result of one seeded reset.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Placement {
    pub seed: u32,
    pub fixtures: Vec<FixturePose>,
    /// Objects in the order LIBERO writes them.
    pub objects: Vec<ObjectPose>,
    /// Articulation joints set at reset (`set_joint`), last write per joint.
    pub joint_qpos: Vec<(String, f64)>,
    /// Site alphas after `visualize(False)`: every robot, gripper, object and fixture site with alpha > 0 negated.
    pub site_alpha: Vec<(String, f32)>,
}

/// What a sampler has placed so far (`placed_objects`): pos, the quaternion array as the sampler built it, offsets.
#[derive(Debug, Clone)]
struct Placed {
    name: String,
    pos: [f64; 3],
    quat: [f64; 4],
    top_z: f64,
    radius: f64,
}

fn sample_rotation(rng: &mut NumpyRandomState, rot: &Rotation) -> [f64; 4] {
    // TableRegionSampler._sample_quat: (x, y, z, w) arrays
    match rot {
        Rotation::Range { range, axis } => {
            let lo = range[0].min(range[1]);
            let hi = range[0].max(range[1]);
            let a = rng.uniform(lo, hi);
            let (s, c) = ((a / 2.0).sin(), (a / 2.0).cos());
            match axis {
                'x' => [s, 0.0, 0.0, c],
                'y' => [0.0, s, 0.0, c],
                _ => [0.0, 0.0, s, c],
            }
        }
        Rotation::Composed(axes) => {
            let mut q = [0.0, 0.0, 0.0, 1.0];
            for (axis, range) in axes {
                let a = rng.uniform(range[0].min(range[1]), range[0].max(range[1]));
                let (s, c) = ((a / 2.0).sin(), (a / 2.0).cos());
                let cur = match axis {
                    'x' => [s, 0.0, 0.0, c],
                    'y' => [0.0, s, 0.0, c],
                    _ => [0.0, 0.0, s, c],
                };
                q = quat_multiply_xyzw(cur, q);
            }
            q
        }
    }
}

/// robosuite `quat_multiply(q1, q0)` on (x, y, z, w) arrays, same operation order.
fn quat_multiply_xyzw(q1: [f64; 4], q0: [f64; 4]) -> [f64; 4] {
    let [x0, y0, z0, w0] = q0;
    let [x1, y1, z1, w1] = q1;
    [
        x1 * w0 + y1 * z0 - z1 * y0 + w1 * x0,
        -x1 * z0 + y1 * w0 + z1 * x0 + w1 * y0,
        x1 * y0 - y1 * x0 + z1 * w0 + w1 * z0,
        -x1 * x0 - y1 * y0 - z1 * z0 + w1 * w0,
    ]
}

/// robosuite `quat2mat` under numba: (x, y, z, w) → 3×3, computed in float32 as robosuite does.
fn quat2mat_f32(q_xyzw: [f64; 4]) -> [[f64; 3]; 3] {
    let q: [f32; 4] = [q_xyzw[3] as f32, q_xyzw[0] as f32, q_xyzw[1] as f32, q_xyzw[2] as f32];
    let n: f32 = q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3];
    if (n as f64) < f64::EPSILON * 4.0 {
        return [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    }
    let s = (2.0 / n as f64).sqrt();
    let q: Vec<f32> = q.iter().map(|v| (*v as f64 * s) as f32).collect();
    let o = |i: usize, j: usize| (q[i] * q[j]) as f64;
    [
        [1.0 - o(2, 2) - o(3, 3), o(1, 2) - o(3, 0), o(1, 3) + o(2, 0)],
        [o(1, 2) + o(3, 0), 1.0 - o(1, 1) - o(3, 3), o(2, 3) - o(1, 0)],
        [o(1, 3) - o(2, 0), o(2, 3) + o(1, 0), 1.0 - o(1, 1) - o(2, 2)],
    ]
}

/// One `MultiRegionRandomSampler`-family draw loop. Returns (pos, quat) or an error after 5000 tries.
#[allow(clippy::too_many_arguments)]
fn region_sample(
    rng: &mut NumpyRandomState,
    obj: &InstanceInfo,
    x_ranges: &[[f64; 2]],
    y_ranges: &[[f64; 2]],
    base: [f64; 3],
    z_offset: f64,
    shrink: bool,
    check: bool,
    placed: &[Placed],
    mut quat: impl FnMut(&mut NumpyRandomState) -> [f64; 4],
) -> Result<([f64; 3], [f64; 4]), SimError> {
    let r = obj.horizontal_radius;
    let bottom = obj.bottom_offset[2];
    for _ in 0..5000 {
        let idx = rng.randint(x_ranges.len() as i64) as usize;
        let (mut xmin, mut xmax) = (x_ranges[idx][0], x_ranges[idx][1]);
        if shrink {
            xmin += r;
            xmax -= r;
        }
        let x = rng.uniform(xmin, xmax) + base[0];
        let (mut ymin, mut ymax) = (y_ranges[idx][0], y_ranges[idx][1]);
        if shrink {
            ymin += r;
            ymax -= r;
        }
        let y = rng.uniform(ymin, ymax) + base[1];
        let z = z_offset + base[2] - bottom;
        let valid = !check
            || placed.iter().all(|p| {
                let (dx, dy) = (x - p.pos[0], y - p.pos[1]);
                !((dx * dx + dy * dy).sqrt() <= p.radius + r && z - p.pos[2] <= p.top_z - bottom)
            });
        if valid {
            return Ok(([x, y, z], quat(rng)));
        }
    }
    Err(SimError::Input(format!("placement of `{}` failed after 5000 tries (LIBERO raises RandomizationError)", obj.name)))
}

fn xy_ranges(ranges: &[[f64; 4]]) -> (Vec<[f64; 2]>, Vec<[f64; 2]>) {
    (ranges.iter().map(|r| [r[0], r[2]]).collect(), ranges.iter().map(|r| [r[1], r[3]]).collect())
}

impl Placement {
    /// The golden flow `ControlEnv(bddl); env.seed(seed); env.reset()` (first reset: two initializer copies).
    /// `model` is needed only for objects placed on object/fixture sites (their site positions come from MuJoCo);
    /// without it those objects are left out (fixture poses and table placements do not depend on them).
    pub fn sample(scene: &ComposedScene, seed: u32, model: Option<&MjModel>) -> Result<Self, SimError> {
        let mut rng = NumpyRandomState::new(seed);
        Self::sample_reset(scene, &mut rng, 1, model, seed)
    }

    /// One reset drawing from `rng` (continue the same `rng` for later resets); `reset_number` counts resets of
    /// the env since construction (1 for the first), which sets how many initializer copies draw.
    pub fn sample_reset(
        scene: &ComposedScene,
        rng: &mut NumpyRandomState,
        reset_number: usize,
        model: Option<&MjModel>,
        seed: u32,
    ) -> Result<Self, SimError> {
        let problem = &scene.problem;
        let find = |name: &str| scene.instance(name);
        // 1. robot initialization noise
        rng.randn(PANDA_INIT_QPOS.len());
        // 2. articulation initializers
        let mut initializers: Vec<(Vec<String>, [f64; 2])> = Vec::new();
        for atom in &problem.init {
            let Some(target) = atom.args.first() else { continue };
            if !matches!(atom.predicate.as_str(), "open" | "close" | "turnon" | "turnoff") {
                continue;
            }
            // object_states_dict holds objects, fixtures and regions
            let (joints, owner) = if let Some(inst) = find(target) {
                (inst.joints.clone(), inst)
            } else if let Some(region) = scene.regions.iter().find(|r| r.key == *target) {
                match region.parent.as_deref().and_then(find) {
                    Some(owner) => (region.joints.clone(), owner),
                    None => {
                        return Err(SimError::Input(format!("`({} {target})`: workspace regions have no joints", atom.predicate)));
                    }
                }
            } else {
                continue;
            };
            let art = owner.articulation.as_ref().ok_or_else(|| {
                SimError::Input(format!("`({} {target})`: `{}` is not articulated", atom.predicate, owner.category))
            })?;
            let range = match atom.predicate.as_str() {
                "open" => art.open,
                "close" => art.close,
                "turnon" => art.turn_on,
                _ => art.turn_off,
            }
            .ok_or_else(|| SimError::Input(format!("`({} {target})`: `{}` has no such range", atom.predicate, owner.category)))?;
            initializers.push((joints, range));
        }
        let mut joint_qpos: Vec<(String, f64)> = Vec::new();
        for _ in 0..=reset_number {
            for (joints, range) in &initializers {
                let v = rng.uniform(range[0], range[1]);
                for j in joints {
                    match joint_qpos.iter_mut().find(|(n, _)| n == j) {
                        Some(slot) => slot.1 = v,
                        None => joint_qpos.push((j.clone(), v)),
                    }
                }
            }
        }
        // 3. table samplers in :init order
        let ws = scene.problem_class.workspace_name();
        let wo = scene.workspace_offset;
        let mut placed: Vec<Placed> = Vec::new();
        let mut fixtures = Vec::new();
        let mut objects = Vec::new();
        let mut on_sites = Vec::new();
        let mut in_sites = Vec::new();
        let mut on_objects = Vec::new();
        for atom in &problem.init {
            if atom.args.len() < 2 {
                continue;
            }
            let (what, where_) = (&atom.args[0], &atom.args[1]);
            if atom.predicate == "on" && problem.is_object(where_) {
                on_objects.push((what.clone(), where_.clone()));
                continue;
            }
            let Some(region) = problem.region(where_) else { continue };
            if atom.predicate == "in" {
                in_sites.push((what.clone(), where_.clone()));
                continue;
            }
            if atom.predicate != "on" {
                continue;
            }
            if problem.is_object(&region.target) || problem.is_fixture(&region.target) && region.target != ws {
                if find(&region.target).is_some() {
                    on_sites.push((what.clone(), where_.clone()));
                    continue;
                }
            }
            let Some(obj) = find(what) else { continue };
            let (xr, yr) = xy_ranges(&region.ranges);
            if xr.is_empty() {
                return Err(SimError::Input(format!("region `{}` has no ranges to sample from", region.key)));
            }
            if obj.is_fixture {
                let yaw = region.yaw_rotation;
                let (pos, quat) = region_sample(rng, obj, &xr, &yr, wo, scene.fixture_z_offset, false, false, &placed, |rng| {
                    let a = rng.uniform(yaw[0].min(yaw[1]), yaw[0].max(yaw[1]));
                    [(a / 2.0).cos(), 0.0, 0.0, (a / 2.0).sin()]
                })?;
                placed.push(Placed { name: obj.name.clone(), pos, quat, top_z: obj.top_offset[2], radius: obj.horizontal_radius });
                fixtures.push(FixturePose { name: obj.name.clone(), root_body: obj.root_body.clone(), pos, quat_wxyz: quat });
            } else {
                let shrink = !scene.problem_class.uses_libero100_sampler();
                let (pos, quat) =
                    region_sample(rng, obj, &xr, &yr, wo, 0.01, shrink, true, &placed, |rng| sample_rotation(rng, &obj.rotation))?;
                placed.push(Placed { name: obj.name.clone(), pos, quat, top_z: obj.top_offset[2], radius: obj.horizontal_radius });
                objects.push(object_pose(obj, pos, quat)?);
            }
        }
        // 4. conditional samplers (need MuJoCo's site positions)
        if let Some(model) = model {
            let site_world = site_positions_at_reset(scene, model, &joint_qpos)?;
            for (what, region_key, inside) in
                on_sites.iter().map(|(a, b)| (a, b, false)).chain(in_sites.iter().map(|(a, b)| (a, b, true)))
            {
                let Some(obj) = find(what) else { continue };
                let Some(region) = scene.regions.iter().find(|r| r.key == *region_key) else { continue };
                let Some(reference) = placed.iter().find(|p| p.name == region.target).cloned() else {
                    return Err(SimError::Input(format!("`{what}` is placed on `{region_key}` but `{}` was not placed", region.target)));
                };
                let site = site_world
                    .iter()
                    .find(|(n, _)| n == region_key)
                    .map(|(_, p)| *p)
                    .ok_or_else(|| SimError::Input(format!("no site `{region_key}` in the model")))?;
                let ref_q = reference.quat;
                let xyzw = [ref_q[1], ref_q[2], ref_q[3], ref_q[0]]; // convert_quat(ref_quat, to="xyzw")
                let r = quat2mat_f32(xyzw);
                let s = [0, 1, 2].map(|i| r[i][0] * site[0] + r[i][1] * site[1] + r[i][2] * site[2]);
                let (pos, quat) = if inside {
                    in_site_sample(rng, obj, reference.pos, s, &placed)?
                } else {
                    let half = [region.size.first().copied().unwrap_or(0.0), region.size.get(1).copied().unwrap_or(0.0)];
                    // Project extension (no stock BDDL gives an object-owned region ranges): explicit `:ranges`
                    // replace LIBERO's `±size/2`, as offsets from the site, so several objects fit on one surface.
                    let (xr, yr) = if region.ranges.is_empty() {
                        (vec![[-half[0] / 2.0, half[0] / 2.0]], vec![[-half[1] / 2.0, half[1] / 2.0]])
                    } else {
                        xy_ranges(&region.ranges)
                    };
                    let base = [reference.pos[0], reference.pos[1], reference.pos[2] + reference.top_z];
                    site_region_sample(rng, obj, &xr, &yr, base, s, &placed)?
                };
                placed.push(Placed { name: obj.name.clone(), pos, quat, top_z: obj.top_offset[2], radius: obj.horizontal_radius });
                objects.push(object_pose(obj, pos, quat)?);
            }
            for (what, other) in &on_objects {
                let (Some(obj), Some(reference)) = (find(what), placed.iter().find(|p| p.name == *other).cloned()) else {
                    continue;
                };
                // ObjectBasedSampler: ranges [0, 0], no checks, z_offset 0.01 on top of the reference
                let base = [reference.pos[0], reference.pos[1], reference.pos[2] + reference.top_z];
                let (pos, quat) = region_sample(rng, obj, &[[0.0, 0.0]], &[[0.0, 0.0]], base, 0.01, false, false, &placed, |rng| {
                    sample_rotation(rng, &obj.rotation)
                })?;
                placed.push(Placed { name: obj.name.clone(), pos, quat, top_z: obj.top_offset[2], radius: obj.horizontal_radius });
                objects.push(object_pose(obj, pos, quat)?);
            }
        }
        let mut site_alpha = Vec::new();
        if let Some(model) = model {
            let sites: Vec<&String> = scene
                .robot_sites
                .iter()
                .chain(scene.objects.iter().chain(&scene.fixtures).flat_map(|i| i.sites.iter()))
                .collect();
            for s in sites {
                if let Some(id) = model.name_to_id(MjtObjBase::mjOBJ_SITE, s) {
                    let a = model.site_rgba()[id][3];
                    if a > 0.0 {
                        site_alpha.push((s.clone(), -a));
                    }
                }
            }
        }
        Ok(Self { seed, fixtures, objects, joint_qpos, site_alpha })
    }

    /// Write fixture poses and the reset-time site alphas into a compiled model (robosuite assigns
    /// `model.body_pos`/`body_quat`/`site_rgba` directly; derived quantities are not recomputed).
    pub fn apply(&self, model: &mut MjModel) -> Result<(), SimError> {
        for f in &self.fixtures {
            let id = model
                .name_to_id(MjtObjBase::mjOBJ_BODY, &f.root_body)
                .ok_or_else(|| SimError::Input(format!("model has no body `{}`", f.root_body)))?;
            model.body_pos_mut()[id] = f.pos;
            model.body_quat_mut()[id] = f.quat_wxyz;
        }
        for (name, alpha) in &self.site_alpha {
            let id = model
                .name_to_id(MjtObjBase::mjOBJ_SITE, name)
                .ok_or_else(|| SimError::Input(format!("model has no site `{name}`")))?;
            model.site_rgba_mut()[id][3] = *alpha;
        }
        Ok(())
    }

    /// Write the sampled object and articulation qpos (the state LIBERO has after `reset()`, before any
    /// `set_init_state`) into `qpos`.
    pub fn write_qpos(&self, model: &MjModel, qpos: &mut [f64]) -> Result<(), SimError> {
        let adr = |j: &str| -> Result<usize, SimError> {
            let id = model.name_to_id(MjtObjBase::mjOBJ_JOINT, j).ok_or_else(|| SimError::Input(format!("model has no joint `{j}`")))?;
            Ok(model.jnt_qposadr()[id] as usize)
        };
        for (j, v) in &self.joint_qpos {
            qpos[adr(j)?] = *v;
        }
        for o in &self.objects {
            let a = adr(&o.joint)?;
            qpos[a..a + 7].copy_from_slice(&o.qpos);
        }
        Ok(())
    }
}

/// The visual sites of fixtures that can be turned on (the stove's red burner ring) and LIBERO's rule for them
/// (`_post_process` after every step, and `set_init_state`): `alpha ← 1 − alpha` whenever the alpha's sign
/// disagrees with the fixture's on-state (q ≥ the lower `turn_on` bound of its last non-free joint).
#[derive(Debug, Clone)]
pub struct TurnOnSites {
    fixtures: Vec<TurnOnFixture>,
}

#[derive(Debug, Clone)]
struct TurnOnFixture {
    /// `qpos` address of the last hinge/slide joint (LIBERO's loop over joints keeps the last evaluation).
    qpos_adr: Option<usize>,
    on_at: f64,
    site_ids: Vec<usize>,
}

impl TurnOnSites {
    pub fn new(scene: &ComposedScene, model: &MjModel) -> Result<Self, SimError> {
        let mut fixtures = Vec::new();
        for inst in scene.objects.iter().chain(&scene.fixtures) {
            let Some(art) = &inst.articulation else { continue };
            let (Some(on), false) = (art.turn_on, inst.vis_sites.is_empty()) else { continue };
            let qpos_adr = inst
                .joints
                .iter()
                .filter_map(|j| model.name_to_id(MjtObjBase::mjOBJ_JOINT, j))
                .filter(|&id| model.jnt_type()[id] != MjtJoint::mjJNT_FREE)
                .map(|id| model.jnt_qposadr()[id] as usize)
                .last();
            let site_ids = inst
                .vis_sites
                .iter()
                .map(|s| model.name_to_id(MjtObjBase::mjOBJ_SITE, s).ok_or_else(|| SimError::Input(format!("model has no site `{s}`"))))
                .collect::<Result<_, _>>()?;
            fixtures.push(TurnOnFixture { qpos_adr, on_at: on[0].min(on[1]), site_ids });
        }
        Ok(Self { fixtures })
    }

    /// Ids of every site the rule may toggle.
    pub fn site_ids(&self) -> impl Iterator<Item = usize> + '_ {
        self.fixtures.iter().flat_map(|f| f.site_ids.iter().copied())
    }

    /// Applies the rule for `qpos` to `site_rgba` (indexed by site id, as `MjModel::site_rgba`).
    pub fn toggle(&self, qpos: &[f64], site_rgba: &mut [[f32; 4]]) {
        for f in &self.fixtures {
            let on = f.qpos_adr.is_some_and(|a| qpos[a] >= f.on_at);
            for &id in &f.site_ids {
                let a = site_rgba[id][3];
                if (a <= 0.0 && on) || (a > 0.0 && !on) {
                    site_rgba[id][3] = 1.0 - a;
                }
            }
        }
    }
}

/// LIBERO `set_visualization` after a state change: a visual-state site (flat_stove burner) shows iff its
/// stove is on (knob angle ≥ min turn-on range), toggling alpha ← 1 − alpha when sign and state disagree.
pub fn update_visual_sites(scene: &ComposedScene, model: &mut MjModel, qpos: &[f64]) -> Result<(), SimError> {
    let sites = TurnOnSites::new(scene, model)?;
    sites.toggle(qpos, model.site_rgba_mut());
    Ok(())
}

fn object_pose(obj: &InstanceInfo, pos: [f64; 3], quat: [f64; 4]) -> Result<ObjectPose, SimError> {
    let joint = obj
        .joints
        .last()
        .cloned()
        .ok_or_else(|| SimError::Input(format!("object `{}` has no joint to place it with", obj.name)))?;
    Ok(ObjectPose { name: obj.name.clone(), joint, qpos: [pos[0], pos[1], pos[2], quat[0], quat[1], quat[2], quat[3]] })
}

/// `SiteRegionRandomSampler.sample`: boundary shrink and collision checks on, offsets by the rotated site.
fn site_region_sample(
    rng: &mut NumpyRandomState,
    obj: &InstanceInfo,
    xr: &[[f64; 2]],
    yr: &[[f64; 2]],
    base: [f64; 3],
    site: [f64; 3],
    placed: &[Placed],
) -> Result<([f64; 3], [f64; 4]), SimError> {
    let r = obj.horizontal_radius;
    let bottom = obj.bottom_offset[2];
    for _ in 0..5000 {
        let idx = rng.randint(xr.len() as i64) as usize;
        let x = rng.uniform(xr[idx][0] + r, xr[idx][1] - r) + base[0] + site[0];
        let y = rng.uniform(yr[idx][0] + r, yr[idx][1] - r) + base[1] + site[1];
        let z = 0.0 + base[2] + site[2] - bottom;
        if clear_of(placed, [x, y, z], r, bottom) {
            return Ok(([x, y, z], sample_rotation(rng, &obj.rotation)));
        }
    }
    Err(SimError::Input(format!("placement of `{}` failed after 5000 tries (LIBERO raises RandomizationError)", obj.name)))
}

/// robosuite's sampler collision test: a candidate is rejected when it overlaps a placed object horizontally and
/// is not above it.
fn clear_of(placed: &[Placed], [x, y, z]: [f64; 3], radius: f64, bottom: f64) -> bool {
    placed.iter().all(|p| {
        let (dx, dy) = (x - p.pos[0], y - p.pos[1]);
        !((dx * dx + dy * dy).sqrt() <= p.radius + radius && z - p.pos[2] <= p.top_z - bottom)
    })
}

/// `InSiteRegionRandomSampler.sample`: ranges `[(0, 0)]` (still drawn), the object at the site's xy,
/// collision-checked; the reference's top offset is *not* added.
fn in_site_sample(
    rng: &mut NumpyRandomState,
    obj: &InstanceInfo,
    base: [f64; 3],
    site: [f64; 3],
    placed: &[Placed],
) -> Result<([f64; 3], [f64; 4]), SimError> {
    let r = obj.horizontal_radius;
    let bottom = obj.bottom_offset[2];
    for _ in 0..5000 {
        rng.randint(1);
        let x = rng.uniform(0.0, 0.0) + base[0] + site[0];
        let y = rng.uniform(0.0, 0.0) + base[1] + site[1];
        let z = 0.0 + base[2] + site[2] - bottom;
        if clear_of(placed, [x, y, z], r, bottom) {
            return Ok(([x, y, z], sample_rotation(rng, &obj.rotation)));
        }
    }
    Err(SimError::Input(format!("placement of `{}` inside its region failed (LIBERO raises RandomizationError)", obj.name)))
}

/// World site positions as `mj_step1` leaves them at reset: robot at `init_qpos`, articulations set, fixtures
/// and objects still where the MJCF puts them.
fn site_positions_at_reset(scene: &ComposedScene, model: &MjModel, joint_qpos: &[(String, f64)]) -> Result<Vec<(String, [f64; 3])>, SimError> {
    let mut data = MjData::new(model);
    let adr = |j: &str| model.name_to_id(MjtObjBase::mjOBJ_JOINT, j).map(|id| model.jnt_qposadr()[id] as usize);
    {
        let qpos = data.qpos_mut();
        for (k, v) in PANDA_INIT_QPOS.iter().enumerate() {
            if let Some(a) = adr(&format!("robot0_joint{}", k + 1)) {
                qpos[a] = *v;
            }
        }
        for (j, v) in joint_qpos {
            if let Some(a) = adr(j) {
                qpos[a] = *v;
            }
        }
    }
    data.kinematics();
    let mut out = Vec::new();
    for r in &scene.regions {
        if r.parent.is_none() {
            continue;
        }
        if let Some(id) = model.name_to_id(MjtObjBase::mjOBJ_SITE, &r.key) {
            out.push((r.key.clone(), data.site_xpos()[id]));
        }
    }
    Ok(out)
}
