//! Standing a tall, thin object (an upright book) into a tight region (a caddy compartment barely wider than it).
//!
//! The generic placement carries the object at the yaw it was picked at and lets its root go over the region's
//! centre: an upright book then meets the compartment's walls crosswise or off-centre, and a fast carry swings it
//! out of a pinch 5 cm below its top. For an `In` placement whose region only takes the object's footprint when the
//! two are aligned, this turns the hand so the footprint lines up with the region, centres the footprint (not the
//! root) over the region, carries it high enough to clear the region owner's walls, and slowly. Any other placement
//! is left exactly as the generic expert plans it (the identity [`Tuning`]).
use libero_sim::Simulation;
use nalgebra::{Matrix3, Rotation3, Vector3};

use crate::expert::motion::{mat3, rotate_world, vec3};
use crate::expert::skills::{extent, pos};
use crate::judge::predicates::{IN_BOX_LOWER_Z_MARGIN_M, SceneIndex};

/// Taller than this (m) an object is carried by a pinch well below its top, which it can swing out of.
const TALL_M: f64 = 0.08;
/// A footprint is thin when its narrow side is under this fraction of its wide side (a book: 2.9 of 11 cm).
const THIN_RATIO: f64 = 0.5;
/// A region is tight when its narrow half side exceeds the object's wide half side by less than this (m).
const FIT_SLACK_M: f64 = 0.01;
/// A region box starting this far (m) above its owner's bottom (after LIBERO's 1 cm lowering of its floor) has a
/// raised floor: the object is perched off-centre.
const RAISED_FLOOR_M: f64 = 0.01;
/// How far along the region's wide axis a perched object is let down (m).
const PERCH_OFFSET_M: f64 = 0.012;
/// The object's bottom is carried this far (m) above the top of the region's owner (the caddy's walls).
const CLEAR_OWNER_M: f64 = 0.03;
/// Carry speed (max action) of a tight fit, against the generic 0.7.
const TIGHT_CARRY_SPEED: f64 = 0.35;
/// The hand's turn must be within this (rad) before the object is let down into the region.
const TIGHT_TURN_TOL_RAD: f64 = 0.05;

/// How a placement is carried and let down; [`Tuning::generic`] is the generic expert's plan unchanged.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Tuning {
    /// Where the object's root is let go (world, m).
    pub to_m: Vector3<f64>,
    /// Hand orientation while carrying and lowering.
    pub rot: Matrix3<f64>,
    /// Height the root is carried at (world z, m).
    pub carry_z_m: f64,
    /// Max action of the carry.
    pub carry_speed: f64,
    /// The carry ends only once the hand is within this of `rot` (rad; infinite: not checked).
    pub turn_tol_rad: f64,
    /// Let down off-centre onto a raised floor's ledge (the caddy's back compartment).
    pub perched: bool,
}

impl Tuning {
    pub fn generic(to_m: Vector3<f64>, rot: Matrix3<f64>, carry_z_m: f64) -> Self {
        Self { to_m, rot, carry_z_m, carry_speed: 0.7, turn_tol_rad: f64::INFINITY, perched: false }
    }
}

/// Horizontal half extents (m) of an upright object's footprint and of a region, and the object's height.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FitGeometry {
    pub object_narrow_half_m: f64,
    pub object_wide_half_m: f64,
    pub object_height_m: f64,
    pub region_narrow_half_m: f64,
    pub region_wide_half_m: f64,
}

impl FitGeometry {
    /// A tight fit: the object is tall, thin and standing (taller than its footprint is wide), and the region is
    /// barely larger than its footprint (its wide side within the region's wide side but not shorter than the
    /// region's narrow side by more than [`FIT_SLACK_M`]; its narrow side within the region's narrow side).
    pub fn is_tight(&self) -> bool {
        let upright_thin = self.object_height_m > TALL_M
            && self.object_narrow_half_m < THIN_RATIO * self.object_wide_half_m
            && self.object_height_m > 2.0 * self.object_wide_half_m;
        let barely = self.object_wide_half_m + FIT_SLACK_M > self.region_narrow_half_m
            && self.object_wide_half_m <= self.region_wide_half_m
            && self.object_narrow_half_m < self.region_narrow_half_m;
        upright_thin && barely
    }
}

/// The region's box, lowered as LIBERO's `In` lowers it, still starts above the owner's floor.
fn raised_floor(region_bottom_m: f64, owner_bottom_m: f64) -> bool {
    region_bottom_m - IN_BOX_LOWER_Z_MARGIN_M > owner_bottom_m + RAISED_FLOOR_M
}

/// A horizontal footprint: half extents along its narrow and wide horizontal axes and the narrow axis (world, unit).
pub(super) struct Footprint {
    pub(super) narrow_half_m: f64,
    pub(super) wide_half_m: f64,
    pub(super) narrow_dir: Vector3<f64>,
}

/// The footprint of a box with world orientation `r` and half sizes `half_m` whose horizontal axes are two of its
/// own (`None` when it stands tilted).
fn footprint(r: &Matrix3<f64>, half_m: [f64; 3]) -> Option<Footprint> {
    let horizontal: Vec<usize> = (0..3).filter(|&k| r[(2, k)].abs() < 0.3).collect();
    let [a, b] = horizontal[..] else { return None };
    let (narrow, wide) = if half_m[a].abs() <= half_m[b].abs() { (a, b) } else { (b, a) };
    let narrow_dir = Vector3::new(r[(0, narrow)], r[(1, narrow)], 0.0).try_normalize(1e-9)?;
    Some(Footprint { narrow_half_m: half_m[narrow].abs(), wide_half_m: half_m[wide].abs(), narrow_dir })
}

/// The largest contact geom of `object` as a footprint (the book's one collision box), if it is a box-like geom
/// standing on one of its faces.
pub(super) fn object_footprint(sim: &Simulation, index: &SceneIndex, object: usize) -> Option<Footprint> {
    let (model, data) = (sim.model(), sim.data());
    let aabb = model.geom_aabb();
    let g = index.contact_geoms(object).max_by(|&a, &b| {
        let v = |g: usize| aabb[g][3] * aabb[g][4] * aabb[g][5];
        v(a).total_cmp(&v(b))
    })?;
    footprint(&mat3(&data.geom_xmat()[g]), [aabb[g][3], aabb[g][4], aabb[g][5]])
}

/// A turn up to this much longer is not taken to keep the wrist nearer home (rad).
const WRIST_SLACK_RAD: f64 = 0.5;

/// Angle (rad) of a horizontal direction about world z.
fn yaw(dir: Vector3<f64>) -> f64 {
    dir.y.atan2(dir.x)
}

/// The turn about world z (rad) that lines up `from` with `to` (both horizontal, sign-free), of the candidates
/// `k·π` apart the one that leaves the hand's yaw from home (`hand_yaw_rad`) smallest (the wrist's range).
fn align_turn(from: Vector3<f64>, to: Vector3<f64>, hand_yaw_rad: f64) -> f64 {
    use std::f64::consts::PI;
    let d = yaw(to) - yaw(from);
    let d = d - PI * (d / PI).round();
    // of the two smallest turns (either way round), the one leaving the wrist nearer home, unless both do alike
    let other = d - PI * d.signum();
    if (other + hand_yaw_rad).abs() + WRIST_SLACK_RAD < (d + hand_yaw_rad).abs() { other } else { d }
}

/// The placement of `object` into region `region` (an `In`), tuned when it is a tight fit; else `generic`.
/// `home` is the hand's orientation when the script began (the hand's yaw is kept near it).
pub fn tune(sim: &Simulation, index: &SceneIndex, object: usize, region: usize, home: &Matrix3<f64>, generic: Tuning) -> Tuning {
    let Some(obj) = object_footprint(sim, index, object) else { return generic };
    let reg = &index.regions[region];
    let data = sim.data();
    let Some(area) = footprint(&mat3(&data.site_xmat()[reg.site]), reg.half_size_m) else { return generic };
    let (lo, hi) = extent(sim, index, object);
    let geometry = FitGeometry {
        object_narrow_half_m: obj.narrow_half_m,
        object_wide_half_m: obj.wide_half_m,
        object_height_m: hi.z - lo.z,
        region_narrow_half_m: area.narrow_half_m,
        region_wide_half_m: area.wide_half_m,
    };
    if !geometry.is_tight() {
        return generic;
    }
    // the hand's yaw from home now (about world z)
    let now = generic.rot * home.transpose();
    let hand_yaw_rad = now[(1, 0)].atan2(now[(0, 0)]);
    let turn_rad = align_turn(obj.narrow_dir, area.narrow_dir, hand_yaw_rad);
    let spin = Rotation3::from_axis_angle(&Vector3::z_axis(), turn_rad);
    let root = pos(sim, index.instances[object].body);
    // the footprint's centre (not the root) over the region's centre, once turned
    let centre_from_root = spin * Vector3::new((lo.x + hi.x) / 2.0 - root.x, (lo.y + hi.y) / 2.0 - root.y, 0.0);
    let c = vec3(&data.site_xpos()[reg.site]);
    // a region whose box starts above its owner's floor (the caddy's back compartment, 1.1 cm up): an object
    // standing on the floor leaves its root under the box, so it is let down off-centre along the region, where
    // its end rests on the compartment's ledge (the site's own axes, so this turns with the owner)
    let r = mat3(&data.site_xmat()[reg.site]);
    let h_z = r.row(2).transpose().component_mul(&Vector3::from(reg.half_size_m)).abs().sum();
    let owner_bottom_m = reg.parent.map_or(f64::NEG_INFINITY, |p| extent(sim, index, p).0.z);
    let perch = if raised_floor(c.z - h_z, owner_bottom_m) { Vector3::new(-area.narrow_dir.y, area.narrow_dir.x, 0.0) * PERCH_OFFSET_M } else { Vector3::zeros() };
    let to_m = Vector3::new(c.x - centre_from_root.x + perch.x, c.y - centre_from_root.y + perch.y, generic.to_m.z);
    // the bottom carried clear of the owner's walls
    let owner_top_m = reg.parent.map_or(f64::NEG_INFINITY, |p| extent(sim, index, p).1.z);
    let carry_z_m = generic.carry_z_m.max(owner_top_m + (root.z - lo.z) + CLEAR_OWNER_M);
    Tuning {
        to_m,
        rot: rotate_world(&generic.rot, Vector3::z(), turn_rad),
        carry_z_m,
        carry_speed: TIGHT_CARRY_SPEED,
        turn_tol_rad: TIGHT_TURN_TOL_RAD,
        perched: perch != Vector3::zeros(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The stock book (2.9 × 11 cm, 13.4 cm tall) and the desk caddy's compartments.
    fn book_into(region_narrow_half_m: f64, region_wide_half_m: f64) -> FitGeometry {
        FitGeometry { object_narrow_half_m: 0.01434, object_wide_half_m: 0.05519, object_height_m: 0.1344, region_narrow_half_m, region_wide_half_m }
    }

    #[test]
    fn book_fits_tightly_only_in_the_narrow_compartments() {
        assert!(book_into(0.02775, 0.06216).is_tight(), "back / front compartment: only lengthwise");
        assert!(book_into(0.06196, 0.06216).is_tight(), "left / right compartment: the book's length barely fits");
        assert!(!book_into(0.08, 0.1).is_tight(), "a roomy region: any yaw fits");
        assert!(!book_into(0.02775, 0.05).is_tight(), "too short a region: not a fit at all");
        assert!(!book_into(0.012, 0.08).is_tight(), "narrower than the book");
    }

    #[test]
    fn round_squat_or_lying_objects_are_not_tight_fits() {
        // a wine bottle (round footprint) into a narrow drawer
        let bottle = FitGeometry { object_narrow_half_m: 0.035, object_wide_half_m: 0.036, object_height_m: 0.3, region_narrow_half_m: 0.03, region_wide_half_m: 0.1 };
        assert!(!bottle.is_tight());
        // a book lying flat (thin footprint but low)
        let flat = FitGeometry { object_narrow_half_m: 0.02, object_wide_half_m: 0.07, object_height_m: 0.03, region_narrow_half_m: 0.03, region_wide_half_m: 0.1 };
        assert!(!flat.is_tight());
        // a long thin box lying on its side (tall enough, but longer than high)
        let long = FitGeometry { object_narrow_half_m: 0.02, object_wide_half_m: 0.07, object_height_m: 0.09, region_narrow_half_m: 0.03, region_wide_half_m: 0.1 };
        assert!(!long.is_tight());
    }

    #[test]
    fn the_back_compartment_has_a_raised_floor() {
        // desk caddy 0.887 m up: back box from 0.912 m, front box from 0.8915 m
        assert!(raised_floor(0.912, 0.887));
        assert!(!raised_floor(0.8915, 0.887));
    }

    #[test]
    fn the_turn_is_sign_free_and_keeps_the_wrist_near_home() {
        use std::f64::consts::FRAC_PI_2;
        let turn = align_turn(Vector3::x(), Vector3::y(), 0.0);
        assert!((turn.abs() - FRAC_PI_2).abs() < 1e-9);
        // already lined up, either way round: no turn
        assert!(align_turn(Vector3::x(), -Vector3::x(), 0.0).abs() < 1e-9);
        // the shorter turn, unless it takes the wrist much further from home
        assert!((align_turn(Vector3::x(), Vector3::new(1.0, 1.0, 0.0).normalize(), 0.0) - FRAC_PI_2 / 2.0).abs() < 1e-9);
        let t = align_turn(Vector3::x(), Vector3::new(1.0, 1.0, 0.0).normalize(), 1.5);
        assert!(t < 0.0 && (t + 1.5).abs() <= FRAC_PI_2);
    }
}
