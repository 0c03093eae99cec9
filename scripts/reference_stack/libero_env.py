"""Build a real LIBERO env (robosuite 1.4.0 + hf-libero 0.1.4 env code on mujoco 3.17.0) for a BDDL file and dump
what our Rust composer/placement must reproduce. Reference tooling only (run with the refstack venv, see setup.sh).

Flow (the golden flow): ControlEnv(bddl, has_offscreen_renderer=False, use_camera_obs=False); env.seed(SEED);
env.reset()  [; env.set_init_state(states[INDEX])]

    python libero_env.py --bddl FILE [--seed 0] [--out scene.json] [--mjcf input.xml] [--trace-rng]
                         [--init-file F.pruned_init --init-index 0]

JSON: model counts and element names in id order, bodies (pos/quat/mass/inertia), joints, geoms (size), sites,
cameras, fixture/object poses (body_pos/body_quat, xpos), runtime_model_overrides (model fields that differ from a
fresh compile of the input MJCF, as in golden80.py), and with --trace-rng every NumPy legacy-RNG draw made during
env.reset() (function, arguments, result).
"""
import argparse, json, os, sys, zipfile, pickle

HERE = os.path.dirname(os.path.abspath(__file__))
VENV = os.path.dirname(os.path.dirname(sys.executable))
os.environ.setdefault("LIBERO_CONFIG_PATH", os.path.join(VENV, "libero_config"))
sys.path.insert(0, HERE)

import numpy as np
import mujoco
import rs14_mj3_shim  # noqa: F401  (robosuite 1.4 on mujoco 3.x)
from libero.libero.envs import *  # noqa: F401,F403  (registers the problem classes)
from libero.libero.envs.env_wrapper import ControlEnv

L = lambda x: np.asarray(x).tolist()
OBJ = mujoco.mjtObj


def names(m, objtype, n):
    return [mujoco.mj_id2name(m, objtype, i) for i in range(n)]


def model_dump(m):
    return dict(
        nq=int(m.nq), nv=int(m.nv), nu=int(m.nu), nbody=int(m.nbody), njnt=int(m.njnt), ngeom=int(m.ngeom),
        nsite=int(m.nsite), ncam=int(m.ncam), nlight=int(m.nlight), nmesh=int(m.nmesh), ntex=int(m.ntex),
        nmat=int(m.nmat), nsensor=int(m.nsensor),
        body_names=names(m, OBJ.mjOBJ_BODY, m.nbody), joint_names=names(m, OBJ.mjOBJ_JOINT, m.njnt),
        geom_names=names(m, OBJ.mjOBJ_GEOM, m.ngeom), site_names=names(m, OBJ.mjOBJ_SITE, m.nsite),
        camera_names=names(m, OBJ.mjOBJ_CAMERA, m.ncam), actuator_names=names(m, OBJ.mjOBJ_ACTUATOR, m.nu),
        mesh_names=names(m, OBJ.mjOBJ_MESH, m.nmesh), material_names=names(m, OBJ.mjOBJ_MATERIAL, m.nmat),
        texture_names=names(m, OBJ.mjOBJ_TEXTURE, m.ntex),
        body_pos=L(m.body_pos), body_quat=L(m.body_quat), body_mass=L(m.body_mass), body_inertia=L(m.body_inertia),
        body_parentid=L(m.body_parentid), qpos0=L(m.qpos0), jnt_type=L(m.jnt_type), jnt_qposadr=L(m.jnt_qposadr),
        jnt_range=L(m.jnt_range), dof_damping=L(m.dof_damping), dof_armature=L(m.dof_armature),
        dof_frictionloss=L(m.dof_frictionloss), geom_size=L(m.geom_size), geom_type=L(m.geom_type),
        geom_bodyid=L(m.geom_bodyid), site_pos=L(m.site_pos), site_size=L(m.site_size), site_rgba=L(m.site_rgba),
        site_bodyid=L(m.site_bodyid), cam_pos=L(m.cam_pos), cam_quat=L(m.cam_quat), cam_fovy=L(m.cam_fovy),
        cam_bodyid=L(m.cam_bodyid),
    )


def runtime_overrides(env):
    """Model fields that differ between the running model and a fresh compile of the input MJCF (golden80.py)."""
    m1 = env.sim.model._model
    m3 = mujoco.MjModel.from_xml_string(env.env.model.get_xml())
    out = {}
    for field in dir(m1):
        if field.startswith("_"):
            continue
        try:
            a = getattr(m1, field); b = getattr(m3, field)
        except Exception:
            continue
        if not (isinstance(a, np.ndarray) and a.dtype.kind in "fiub") or a.shape != b.shape or a.size == 0:
            continue
        rows = np.where(a != b)[0] if a.ndim == 1 else np.where(np.any((a != b).reshape(a.shape[0], -1), axis=1))[0]
        if len(rows):
            out[field] = [dict(id=int(i), value=L(a[i]), compiled_value=L(b[i])) for i in rows]
    return out


def instance_poses(env, dct):
    m, d = env.sim.model._model, env.sim.data._data
    out = {}
    for name, obj in dct.items():
        bid = mujoco.mj_name2id(m, OBJ.mjOBJ_BODY, obj.root_body)
        out[name] = dict(category=getattr(obj, "category_name", type(obj).__name__), root_body=obj.root_body,
                         body_pos=L(m.body_pos[bid]), body_quat_wxyz=L(m.body_quat[bid]), xpos=L(d.xpos[bid]),
                         xquat_wxyz=L(d.xquat[bid]), joints=list(getattr(obj, "joints", [])))
    return out


RNG_TRACE = []


def install_rng_trace():
    """Log every draw from NumPy's legacy global RandomState (what env.seed() seeds)."""
    import numpy.random as npr
    for fn in ["uniform", "randint", "choice", "random", "random_sample", "rand", "randn", "normal", "shuffle",
               "permutation"]:
        orig = getattr(npr, fn)

        def wrap(*a, _orig=orig, _fn=fn, **k):
            r = _orig(*a, **k)
            RNG_TRACE.append(dict(fn=_fn, args=[L(x) if hasattr(x, "__len__") else x for x in a],
                                  kwargs={kk: (L(v) if hasattr(v, "__len__") else v) for kk, v in k.items()},
                                  result=L(r) if r is not None else None))
            return r
        setattr(npr, fn, wrap)


def load_init_states(path):
    z = zipfile.ZipFile(path)
    return pickle.loads(z.read([x for x in z.namelist() if x.endswith("data.pkl")][0]))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--bddl", required=True)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out")
    ap.add_argument("--mjcf", help="write robosuite's input MJCF (env.env.model.get_xml()) here")
    ap.add_argument("--trace-rng", action="store_true")
    ap.add_argument("--init-file")
    ap.add_argument("--init-index", type=int, default=0)
    ap.add_argument("--no-model", action="store_true", help="omit the full model dump")
    a = ap.parse_args()
    env = ControlEnv(bddl_file_name=a.bddl, has_offscreen_renderer=False, use_camera_obs=False)
    if a.trace_rng:
        install_rng_trace()
    env.seed(a.seed)
    env.reset()
    if a.init_file:
        env.set_init_state(load_init_states(a.init_file)[a.init_index])
    xml = env.env.model.get_xml()
    if a.mjcf:
        with open(a.mjcf, "w") as f:
            f.write(xml)
    m, d = env.sim.model._model, env.sim.data._data
    e = env.env
    out = dict(
        bddl=os.path.abspath(a.bddl), bddl_relpath=os.path.relpath(os.path.abspath(a.bddl), os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(a.bddl))))),
        seed=a.seed, problem=e.parsed_problem["problem_name"],
        fixtures=instance_poses(env, e.fixtures_dict), objects=instance_poses(env, e.objects_dict),
        qpos=L(d.qpos), runtime_model_overrides=runtime_overrides(env),
        n_object_property_initializers=len(e.object_property_initializers),
        rng_trace=RNG_TRACE if a.trace_rng else None,
    )
    if not a.no_model:
        out["model"] = model_dump(m)
    env.close()
    if a.out:
        with open(a.out, "w") as f:
            json.dump(out, f)
    else:
        json.dump(out, sys.stdout)


if __name__ == "__main__":
    main()
