//! robosuite 1.4 `PandaGripper` command ramp (port notes §1.7).

/// Ramp increment per physics substep (`PandaGripper.speed`).
pub const GRIPPER_SPEED_PER_SUBSTEP: f64 = 0.01;

/// The gripper's internal command `current_action` ∈ [−1, 1]²: (+1, −1) open, (−1, +1) closed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GripperRamp {
    pub current_action: [f64; 2],
}

impl Default for GripperRamp {
    /// A new gripper object (every hard reset) starts at the half-open command [0, 0].
    fn default() -> Self {
        Self { current_action: [0.0, 0.0] }
    }
}

/// NumPy's `sign` (0 for ±0; NaN is rejected before actions reach here).
fn np_sign(x: f64) -> f64 {
    if x > 0.0 {
        1.0
    } else if x < 0.0 {
        -1.0
    } else {
        0.0
    }
}

impl GripperRamp {
    /// One substep of `format_action`: move 0.01 toward open (a < 0) or closed (a > 0).
    pub fn advance(&mut self, gripper_action: f64) {
        let s = np_sign(gripper_action);
        let step = [-1.0 * GRIPPER_SPEED_PER_SUBSTEP * s, 1.0 * GRIPPER_SPEED_PER_SUBSTEP * s];
        for (c, d) in self.current_action.iter_mut().zip(step) {
            *c = (*c + d).clamp(-1.0, 1.0);
        }
    }

    /// Position-servo targets (metres) for the two finger actuators with ctrlrange rows `[lo, hi]`:
    /// `bias + weight · current_action`.
    pub fn ctrl(&self, ctrlrange: &[[f64; 2]; 2]) -> [f64; 2] {
        let mut out = [0.0; 2];
        for i in 0..2 {
            let bias = 0.5 * (ctrlrange[i][1] + ctrlrange[i][0]);
            let weight = 0.5 * (ctrlrange[i][1] - ctrlrange[i][0]);
            out[i] = bias + weight * self.current_action[i];
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn full_close_takes_eight_control_steps_and_maps_to_closed_ctrl() {
        let mut g = GripperRamp::default();
        for _ in 0..4 * 25 {
            g.advance(1.0);
        }
        assert_eq!(g.current_action, [-1.0, 1.0]);
        let ranges = [[0.0, 0.04], [-0.04, 0.0]];
        assert_eq!(g.ctrl(&ranges), [0.0, 0.0]);
        for _ in 0..8 * 25 - 1 {
            g.advance(-0.3);
        }
        assert!(g.current_action[0] < 1.0, "one substep short of fully open");
        g.advance(-1.0);
        assert_eq!(g.current_action, [1.0, -1.0]);
        assert_eq!(g.ctrl(&ranges), [0.04, -0.04]);
        g.advance(0.0);
        assert_eq!(g.current_action, [1.0, -1.0], "zero holds");
    }
}
