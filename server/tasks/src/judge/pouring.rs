//! The pour counter shared by T20's evaluator and the staged evaluator's `pour_count` atom (RoboMemArena
//! `PourCounterConfig`: lift 0.03 m, radius 0.20 m, tilt enter 0.70 rad, return 0.20 rad, enter dwell 3, return
//! dwell 5 control steps). It runs at control rate only. Per control step:
//! 1. lifted ⇔ bottle root z − z(reset) > 0.03 (strict);
//! 2. the first lifted step stores the bottle's rotation as the upright reference R_ref;
//! 3. tilt = geodesic angle between R_ref and the current rotation (undefined before R_ref);
//! 4. in_pour ⇔ lifted AND tilt ≥ 0.70 AND xy distance (bottle root, target site) ≤ 0.20;
//! 5. armed: a run of 3 consecutive in_pour steps registers one pour (start = current − 2) and disarms;
//! 6. disarmed: 5 consecutive steps with lifted AND tilt ≤ 0.20 re-arm. One long continuous pour counts once.
use libero_sim::simulation::SimData;
use nalgebra::Matrix3;
use serde::Deserialize;

/// The pour counter's thresholds (RoboMemArena `PourCounterConfig`; every one from the task's params), shared by
/// T20's evaluator and the staged evaluator's `pour_count` atom (T24). Flattened into those params, so it cannot
/// refuse unknown fields itself: the params that contain it do.
#[derive(Debug, Clone, Deserialize)]
pub struct PourCounterConfig {
    pub lift_delta_m: f64,
    pub target_radius_m: f64,
    pub tilt_enter_rad: f64,
    pub tilt_return_rad: f64,
    pub enter_dwell_steps: u32,
    pub return_dwell_steps: u32,
}

/// A registered pour: the control step its in-pour run began and the step it was counted.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Pour {
    pub start_step: u64,
    pub counted_step: u64,
}

/// The arm/disarm pour counter (steps 4–6 above) on already computed per-step quantities.
#[derive(Debug, Clone)]
pub struct PourCounter {
    radius_m: f64,
    tilt_enter_rad: f64,
    tilt_return_rad: f64,
    enter_dwell: u32,
    return_dwell: u32,
    armed: bool,
    enter_run: u32,
    return_run: u32,
    pours: Vec<Pour>,
}

impl PourCounter {
    pub fn new(p: &PourCounterConfig) -> Self {
        Self {
            radius_m: p.target_radius_m,
            tilt_enter_rad: p.tilt_enter_rad,
            tilt_return_rad: p.tilt_return_rad,
            enter_dwell: p.enter_dwell_steps.max(1),
            return_dwell: p.return_dwell_steps.max(1),
            armed: true,
            enter_run: 0,
            return_run: 0,
            pours: Vec::new(),
        }
    }

    /// One control step: `tilt_rad` is `None` before the upright reference exists; `distance_m` is the bottle's xy
    /// distance to the target. Returns the pour registered at this step, if any.
    pub fn update(&mut self, step: u64, lifted: bool, tilt_rad: Option<f64>, distance_m: f64) -> Option<Pour> {
        if self.armed {
            let in_pour = lifted && tilt_rad.is_some_and(|t| t >= self.tilt_enter_rad) && distance_m <= self.radius_m;
            self.enter_run = if in_pour { self.enter_run + 1 } else { 0 };
            if self.enter_run >= self.enter_dwell {
                let pour = Pour { start_step: step + 1 - u64::from(self.enter_dwell), counted_step: step };
                self.pours.push(pour);
                self.armed = false;
                self.enter_run = 0;
                self.return_run = 0;
                return Some(pour);
            }
        } else {
            let upright = lifted && tilt_rad.is_some_and(|t| t <= self.tilt_return_rad);
            self.return_run = if upright { self.return_run + 1 } else { 0 };
            if self.return_run >= self.return_dwell {
                self.armed = true;
                self.return_run = 0;
                self.enter_run = 0;
            }
        }
        None
    }

    pub fn pours(&self) -> &[Pour] {
        &self.pours
    }

    pub fn armed(&self) -> bool {
        self.armed
    }
}

/// Steps 1–3 of the algorithm on the simulator state, feeding a [`PourCounter`]: one bottle, one target site.
#[derive(Debug, Clone)]
pub struct PourTracker {
    config: PourCounterConfig,
    bottle_body: usize,
    target_site: usize,
    /// bottle root z at the evaluator reset
    z0_m: f64,
    r_ref: Option<Matrix3<f64>>,
    lift_seen: bool,
    max_tilt_rad: f64,
    counter: PourCounter,
}

impl PourTracker {
    /// A tracker whose lift baseline is `z0_m` (the bottle root height at the evaluator reset).
    pub fn new(config: &PourCounterConfig, bottle_body: usize, target_site: usize, z0_m: f64) -> Self {
        Self {
            counter: PourCounter::new(config),
            config: config.clone(),
            bottle_body,
            target_site,
            z0_m,
            r_ref: None,
            lift_seen: false,
            max_tilt_rad: 0.0,
        }
    }

    /// One control step; returns the pour registered at this step, if any.
    pub fn update(&mut self, data: &SimData, control_step: u64) -> Option<Pour> {
        let p = data.xpos()[self.bottle_body];
        let rot = Matrix3::from_row_slice(&data.xmat()[self.bottle_body]);
        let lifted = p[2] - self.z0_m > self.config.lift_delta_m;
        if lifted && self.r_ref.is_none() {
            self.r_ref = Some(rot);
        }
        self.lift_seen |= lifted;
        let tilt = self.r_ref.as_ref().map(|r| geodesic_angle(r, &rot));
        if let Some(t) = tilt {
            self.max_tilt_rad = self.max_tilt_rad.max(t);
        }
        let target = data.site_xpos()[self.target_site];
        let distance = (p[0] - target[0]).hypot(p[1] - target[1]);
        self.counter.update(control_step, lifted, tilt, distance)
    }

    pub fn pours(&self) -> &[Pour] {
        self.counter.pours()
    }

    pub fn lift_seen(&self) -> bool {
        self.lift_seen
    }

    pub fn max_tilt_rad(&self) -> f64 {
        self.max_tilt_rad
    }
}

/// Geodesic angle between two rotations: `arccos((trace(AᵀB) − 1) / 2)`.
pub fn geodesic_angle(a: &Matrix3<f64>, b: &Matrix3<f64>) -> f64 {
    (((a.transpose() * b).trace() - 1.0) / 2.0).clamp(-1.0, 1.0).acos()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// T20's thresholds, as its manifest params give them.
    fn counter() -> PourCounter {
        PourCounter::new(&crate::judge::test_params::parsed("T20"))
    }

    /// Feeds `(lifted, tilt, distance)` per step from step 1; returns the counted steps.
    fn run(c: &mut PourCounter, seq: &[(bool, Option<f64>, f64)]) -> Vec<u64> {
        seq.iter().enumerate().filter_map(|(k, &(l, t, d))| c.update(k as u64 + 1, l, t, d).map(|p| p.counted_step)).collect()
    }

    #[test]
    fn one_continuous_pour_counts_once() {
        let mut c = counter();
        let mut seq = vec![(true, Some(0.0), 0.1); 3];
        seq.extend(vec![(true, Some(0.9), 0.1); 40]);
        let counted = run(&mut c, &seq);
        assert_eq!(counted, [6], "the third consecutive in-pour step counts, once");
        assert_eq!(c.pours()[0].start_step, 4);
        assert!(!c.armed());
    }

    #[test]
    fn two_tilted_steps_do_not_count() {
        let mut c = counter();
        let seq = [(true, Some(0.9), 0.1), (true, Some(0.9), 0.1), (true, Some(0.5), 0.1), (true, Some(0.9), 0.1), (true, Some(0.9), 0.1)];
        assert!(run(&mut c, &seq).is_empty());
    }

    #[test]
    fn rearms_after_five_upright_lifted_steps() {
        let mut c = counter();
        let pour = [(true, Some(0.9), 0.1); 3];
        let upright4 = [(true, Some(0.1), 0.1); 4];
        let mut seq: Vec<_> = pour.to_vec();
        seq.extend(upright4);
        seq.extend(pour); // only 4 upright steps: still disarmed
        assert_eq!(run(&mut c, &seq), [3]);
        let mut c = counter();
        let mut seq: Vec<_> = pour.to_vec();
        seq.extend([(true, Some(0.1), 0.1); 5]);
        seq.extend(pour);
        assert_eq!(run(&mut c, &seq), [3, 11], "re-armed after 5 upright steps, second pour counts");
        // an interrupted upright run restarts
        let mut c = counter();
        let mut seq: Vec<_> = pour.to_vec();
        seq.extend([(true, Some(0.1), 0.1); 3]);
        seq.push((true, Some(0.4), 0.1));
        seq.extend([(true, Some(0.1), 0.1); 3]);
        seq.extend(pour);
        assert_eq!(run(&mut c, &seq), [3]);
        // upright while set down (not lifted) does not re-arm
        let mut c = counter();
        let mut seq: Vec<_> = pour.to_vec();
        seq.extend([(false, Some(0.0), 0.1); 10]);
        seq.extend(pour);
        assert_eq!(run(&mut c, &seq), [3]);
    }

    #[test]
    fn tilting_outside_the_radius_or_unlifted_does_not_count() {
        let mut c = counter();
        assert!(run(&mut c, &[(true, Some(1.2), 0.2001); 10]).is_empty(), "outside 0.20 m");
        assert!(run(&mut c, &[(false, Some(1.2), 0.05); 10]).is_empty(), "not lifted");
        assert!(run(&mut c, &[(true, None, 0.05); 10]).is_empty(), "no upright reference yet");
        assert_eq!(run(&mut c, &[(true, Some(0.70), 0.20); 3]), [3], "the bounds are inclusive");
    }

    #[test]
    fn geodesic_tilt() {
        let r0 = Matrix3::identity();
        let r = *nalgebra::Rotation3::from_axis_angle(&nalgebra::Vector3::x_axis(), 0.8).matrix();
        assert!((geodesic_angle(&r0, &r) - 0.8).abs() < 1e-12);
        let yaw = *nalgebra::Rotation3::from_axis_angle(&nalgebra::Vector3::z_axis(), 0.3).matrix();
        assert!((geodesic_angle(&yaw, &(yaw * r)) - 0.8).abs() < 1e-12);
    }
}
