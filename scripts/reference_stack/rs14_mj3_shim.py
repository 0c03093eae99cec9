# Reference tooling, NOT product code. Copied verbatim (below these two lines) from the shim the golden trajectories
# of tests/reference/golden/ were recorded with: lets robosuite 1.4.0 run on mujoco 3.17.0.
"""Minimal compatibility shim: robosuite 1.4.0 (as pinned by LIBERO) on MuJoCo >= 3.x (tested: 3.17.0).

Only two API incompatibilities break robosuite 1.4.0 + LIBERO on MuJoCo 3.17.0; nothing else is patched,
and no controller equation, physics option or model setting is changed. Import this module once, before
creating a LIBERO/robosuite env. On MuJoCo 2.3.x the shim detects that nothing is needed and does nothing.

1. robosuite.utils.binding_utils.MjModel.get_joint_qpos_addr / get_joint_qvel_addr end with
       assert joint_type in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE)
   where joint_type is a numpy.int32 from model.jnt_type. With the pybind enums of MuJoCo 3.17,
   `enum == numpy.int32` is False, so the tuple-membership test fails for every hinge/slide joint
   (AssertionError in Robot.setup_references). Fix: re-run the *original* method with a Python-int view of
   jnt_type (a read-only proxy of the model), so the same code executes with comparable values.

2. robosuite.controllers.base_controller.Controller.update calls
       mujoco.mj_fullM(model, mass_matrix, sim.data.qM)        # MuJoCo <= 3.3 signature (m, dst, M)
   MuJoCo 3.17 has no MjData.qM any more and the signature is mj_fullM(m, d, dst). Fix: in the
   base_controller module only, `mujoco` is replaced by a pass-through proxy whose mj_fullM accepts the old
   argument order, and robosuite's MjData wrapper gets a `qM` attribute that hands the MjData itself to
   that proxy. mj_fullM only copies the inertia entries into a dense matrix, so the result is the same matrix.
"""
import types
import mujoco
import numpy as np

APPLIED = []


def apply():
    if APPLIED:
        return APPLIED
    from robosuite.utils import binding_utils
    from robosuite.controllers import base_controller

    # ---- 1. joint-type enum comparison -------------------------------------------------------------
    if np.int32(int(mujoco.mjtJoint.mjJNT_HINGE)) not in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE):

        class _IntJntTypeView:
            """Delegates everything to the wrapped robosuite MjModel but returns jnt_type as Python ints."""
            def __init__(self, model):
                object.__setattr__(self, "_m", model)

            def __getattr__(self, name):
                if name == "jnt_type":
                    return [int(x) for x in self._m.jnt_type]
                return getattr(self._m, name)

        orig_qpos = binding_utils.MjModel.get_joint_qpos_addr
        orig_qvel = binding_utils.MjModel.get_joint_qvel_addr

        def get_joint_qpos_addr(self, name):
            return orig_qpos(_IntJntTypeView(self), name)

        def get_joint_qvel_addr(self, name):
            return orig_qvel(_IntJntTypeView(self), name)

        binding_utils.MjModel.get_joint_qpos_addr = get_joint_qpos_addr
        binding_utils.MjModel.get_joint_qvel_addr = get_joint_qvel_addr
        APPLIED.append("jnt_type enum comparison (get_joint_qpos_addr/get_joint_qvel_addr)")

    # ---- 2. mj_fullM signature / MjData.qM removal --------------------------------------------------
    if not hasattr(mujoco.MjData, "qM"):

        class _MujocoOldFullM(types.ModuleType):
            def __getattr__(self, name):          # everything else: the real mujoco module
                return getattr(mujoco, name)

            @staticmethod
            def mj_fullM(m, dst, data):           # old order (m, dst, M); `data` is the MjData (see qM below)
                mujoco.mj_fullM(m, data, dst)

        base_controller.mujoco = _MujocoOldFullM("mujoco")
        binding_utils.MjData.qM = property(lambda self: self._data)
        APPLIED.append("mj_fullM(m, dst, qM) -> mj_fullM(m, d, dst) in Controller.update")
    return APPLIED


apply()
