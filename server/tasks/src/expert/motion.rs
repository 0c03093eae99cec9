//! The motion layer of the scripted experts: a servo law that turns an end-effector goal into one normalized
//! `OSC_POSE` action (exactly what an agent sends), and scripts of phases (reach, grasp, pull …) whose goals
//! are recomputed from the privileged simulator state at every control step.
use libero_sim::Simulation;
use libero_sim::controller::ACTION_SCALE;
use nalgebra::{Matrix3, Rotation3, Unit, Vector3};

/// Gripper command: robosuite's −1 opens, +1 closes.
pub const GRIPPER_OPEN: f64 = -1.0;
pub const GRIPPER_CLOSED: f64 = 1.0;

/// Row-major 3×3 (MuJoCo `xmat`) to a matrix.
pub fn mat3(m: &[f64; 9]) -> Matrix3<f64> {
    Matrix3::from_row_slice(m)
}

pub fn vec3(v: &[f64; 3]) -> Vector3<f64> {
    Vector3::new(v[0], v[1], v[2])
}

/// The grip site: position (world, m) and R_world_from_site.
pub fn grip_pose(sim: &Simulation) -> (Vector3<f64>, Matrix3<f64>) {
    let site = sim.ids().grip_site;
    (vec3(&sim.data().site_xpos()[site]), mat3(&sim.data().site_xmat()[site]))
}

/// Finger opening (m): sum of the two finger slide joints' distances from closed.
pub fn gripper_width_m(sim: &Simulation) -> f64 {
    let q = sim.data().qpos();
    let [l, r] = sim.ids().finger_qpos_adr;
    q[l] - q[r]
}

/// World position of `local_m` in body `body`'s frame.
pub fn body_point(sim: &Simulation, body: usize, local_m: [f64; 3]) -> Vector3<f64> {
    let d = sim.data();
    vec3(&d.xpos()[body]) + mat3(&d.xmat()[body]) * Vector3::from(local_m)
}

/// World direction of `local` in body `body`'s frame.
pub fn body_dir(sim: &Simulation, body: usize, local: [f64; 3]) -> Vector3<f64> {
    mat3(&sim.data().xmat()[body]) * Vector3::from(local)
}

/// Where the end effector should be and how the gripper should be commanded.
#[derive(Debug, Clone, Copy)]
pub struct Goal {
    pub pos_m: Vector3<f64>,
    /// `None`: keep the orientation the script started with (gripper pointing down at home).
    pub rot: Option<Matrix3<f64>>,
    pub gripper: f64,
    /// Largest translation action norm (1 = 5 cm of goal offset per step, robosuite's clip).
    pub max_action: f64,
}

impl Goal {
    pub fn at(pos_m: Vector3<f64>, gripper: f64) -> Self {
        Self { pos_m, rot: None, gripper, max_action: 1.0 }
    }

    pub fn rotated(mut self, rot: Matrix3<f64>) -> Self {
        self.rot = Some(rot);
        self
    }

    pub fn slow(mut self, max_action: f64) -> Self {
        self.max_action = max_action;
        self
    }
}

/// One action toward `goal`: translation proportional to the position error (an action of 1 asks for 5 cm), capped
/// at `goal.max_action` in norm; rotation the axis-angle from the current to the wanted orientation (an action of 1
/// asks for 0.5 rad), each component clipped.
pub fn servo(sim: &Simulation, goal: &Goal, home_rot: &Matrix3<f64>) -> [f64; 7] {
    let (pos, rot) = grip_pose(sim);
    let mut a_pos = (goal.pos_m - pos) / ACTION_SCALE[0];
    let n = a_pos.norm();
    if n > goal.max_action && n > 0.0 {
        a_pos *= goal.max_action / n;
    }
    let wanted = goal.rot.unwrap_or(*home_rot);
    let r_err = Rotation3::from_matrix_unchecked(wanted * rot.transpose());
    let aa = r_err.scaled_axis() / ACTION_SCALE[3];
    let clip = |x: f64| x.clamp(-1.0, 1.0);
    [clip(a_pos.x), clip(a_pos.y), clip(a_pos.z), clip(aa.x), clip(aa.y), clip(aa.z), goal.gripper]
}

/// R rotated by `angle_rad` about the world axis `axis`.
pub fn rotate_world(rot: &Matrix3<f64>, axis: Vector3<f64>, angle_rad: f64) -> Matrix3<f64> {
    Rotation3::from_axis_angle(&Unit::new_normalize(axis), angle_rad).matrix() * rot
}

/// What a phase knows when it computes its goal.
#[derive(Debug, Clone, Copy)]
pub struct PhaseCtx {
    /// Grip-site position when the phase began.
    pub start_pos_m: Vector3<f64>,
    /// Control steps spent in this phase so far.
    pub steps: u32,
    /// Orientation when the script began.
    pub home_rot: Matrix3<f64>,
}

type GoalFn = Box<dyn FnMut(&Simulation, &PhaseCtx) -> Goal + Send>;
type CondFn = Box<dyn Fn(&Simulation, &PhaseCtx) -> bool + Send>;

/// When a phase ends.
pub enum Until {
    /// The grip site is within this distance (m) of the goal.
    Reached(f64),
    /// After this many control steps.
    Steps(u32),
    /// A condition on the state.
    Holds(CondFn),
}

/// One phase of a script. A phase that has not ended after `max_steps` ends anyway: the expert moves on and the
/// evaluator judges the outcome (a stuck expert fails visibly instead of hanging).
pub struct Phase {
    pub name: &'static str,
    goal: GoalFn,
    until: Until,
    max_steps: u32,
}

impl Phase {
    pub fn new(name: &'static str, goal: impl FnMut(&Simulation, &PhaseCtx) -> Goal + Send + 'static) -> Self {
        Self { name, goal: Box::new(goal), until: Until::Steps(1), max_steps: 200 }
    }

    pub fn until_reached(mut self, tol_m: f64) -> Self {
        self.until = Until::Reached(tol_m);
        self
    }

    pub fn for_steps(mut self, steps: u32) -> Self {
        self.until = Until::Steps(steps);
        self.max_steps = self.max_steps.max(steps);
        self
    }

    pub fn until(mut self, cond: impl Fn(&Simulation, &PhaseCtx) -> bool + Send + 'static) -> Self {
        self.until = Until::Holds(Box::new(cond));
        self
    }

    pub fn max_steps(mut self, steps: u32) -> Self {
        self.max_steps = steps;
        self
    }
}

/// A sequence of phases played one control step at a time.
pub struct Script {
    phases: Vec<Phase>,
    current: usize,
    ctx: Option<PhaseCtx>,
    home_rot: Option<Matrix3<f64>>,
    /// (phase name, control steps it took, whether it ended on its own condition).
    pub log: Vec<(&'static str, u32, bool)>,
}

impl Script {
    pub fn new(phases: Vec<Phase>) -> Self {
        Self { phases, current: 0, ctx: None, home_rot: None, log: Vec::new() }
    }

    /// A script whose home orientation is `home_rot` rather than the hand's orientation when it starts.
    pub fn with_home(phases: Vec<Phase>, home_rot: Matrix3<f64>) -> Self {
        Self { home_rot: Some(home_rot), ..Self::new(phases) }
    }

    /// The next action, or `None` when every phase has ended.
    pub fn act(&mut self, sim: &Simulation) -> Option<[f64; 7]> {
        loop {
            let phase = self.phases.get_mut(self.current)?;
            let (pos, rot) = grip_pose(sim);
            let home_rot = *self.home_rot.get_or_insert(rot);
            let ctx = *self.ctx.get_or_insert(PhaseCtx { start_pos_m: pos, steps: 0, home_rot });
            let goal = (phase.goal)(sim, &ctx);
            let done = match &phase.until {
                Until::Reached(tol) => (goal.pos_m - pos).norm() <= *tol,
                Until::Steps(n) => ctx.steps >= *n,
                Until::Holds(cond) => cond(sim, &ctx),
            };
            if done || ctx.steps >= phase.max_steps {
                self.log.push((phase.name, ctx.steps, done));
                self.current += 1;
                self.ctx = None;
                continue;
            }
            if let Some(c) = self.ctx.as_mut() {
                c.steps += 1;
            }
            return Some(servo(sim, &goal, &home_rot));
        }
    }

    /// The phase being played, if any.
    pub fn phase_name(&self) -> Option<&'static str> {
        self.phases.get(self.current).map(|p| p.name)
    }
}

/// The home orientation turned about world z so that the fingers open along the horizontal direction `dir`
/// (at home they open along world y; the turn is the smaller of the two that fit, |angle| ≤ π/2).
pub fn open_along(home_rot: &Matrix3<f64>, dir: Vector3<f64>) -> Matrix3<f64> {
    open_along_near(home_rot, dir, 0.0)
}

/// As [`open_along`], choosing of the two turns that fit the one nearest `prefer_rad`: for a direction near the
/// ±π/2 tie a fixed preference keeps the choice from flipping by π with numerical noise.
pub fn open_along_near(home_rot: &Matrix3<f64>, dir: Vector3<f64>, prefer_rad: f64) -> Matrix3<f64> {
    use std::f64::consts::PI;
    let phi = dir.y.atan2(dir.x) - std::f64::consts::FRAC_PI_2;
    let phi = phi - PI * ((phi - prefer_rad) / PI).round();
    rotate_world(home_rot, Vector3::z(), phi)
}

/// Angle (rad) between the grip site's orientation and `wanted`.
pub fn rotation_error(sim: &Simulation, wanted: &Matrix3<f64>) -> f64 {
    Rotation3::from_matrix_unchecked(wanted * grip_pose(sim).1.transpose()).angle()
}

/// World position of a body's origin.
pub fn body_pos(sim: &Simulation, body: usize) -> Vector3<f64> {
    vec3(&sim.data().xpos()[body])
}
