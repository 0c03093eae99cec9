"""LIBERO's own policy-step rate: the real `env.step` (robosuite 1.4.0 OSC_POSE + LIBERO env code, mujoco 3.17.0)
with no cameras, on a stock task after `set_init_state`, as the peer of `libero-agent bench sim`.
Reference tooling only (run with the refstack venv, see setup.sh).

    python bench_env_step.py [--suite libero_90] [--task KITCHEN_SCENE10_close_the_top_drawer_of_the_cabinet]
                             [--steps 200] [--rounds 3]

Prints one JSON line: env_step_per_s (best round), us_per_env_step, and the 25-raw-mj_step rate of the same
compiled model (so the two Python figures share a machine moment).
"""
import argparse, json, os, sys, time

HERE = os.path.dirname(os.path.abspath(__file__))
VENV = os.path.dirname(os.path.dirname(sys.executable))
os.environ.setdefault("LIBERO_CONFIG_PATH", os.path.join(VENV, "libero_config"))
sys.path.insert(0, HERE)

import numpy as np
import mujoco
import rs14_mj3_shim  # noqa: F401  (robosuite 1.4 on mujoco 3.x)
from libero.libero.envs import *  # noqa: F401,F403  (registers the problem classes)
from libero.libero.envs.env_wrapper import ControlEnv
from libero_env import load_init_states  # noqa: E402


def action(t):
    """`libero_sim::benchmark::sequence_a_action`, so both sides step the same motions."""
    if t < 5:
        return np.zeros(7)
    k = float(t - 5)
    grip = 1.0 if ((t - 5) // 15) % 2 == 0 else -1.0
    return np.array([0.6 * np.sin(k / 5.0), 0.5 * np.cos(k / 7.0), -0.4 + 0.3 * np.sin(k / 11.0),
                     0.3 * np.sin(k / 9.0), 0.2 * np.cos(k / 6.0), -0.25 * np.sin(k / 4.0), grip])


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--suite", default="libero_90")
    ap.add_argument("--task", default="KITCHEN_SCENE10_close_the_top_drawer_of_the_cabinet")
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--rounds", type=int, default=3)
    a = ap.parse_args()
    cache = os.environ.get("LIBERO_AGENT_CACHE", os.path.expanduser("~/.cache/libero-agent"))
    root = os.path.join(cache, "hf-libero-0.1.4")
    bddl = os.path.join(root, "bddl_files", a.suite, a.task + ".bddl")
    states = load_init_states(os.path.join(root, "init_files", a.suite, a.task + ".pruned_init"))
    env = ControlEnv(bddl_file_name=bddl, has_renderer=False, has_offscreen_renderer=False, use_camera_obs=False,
                     camera_depths=False, control_freq=20)
    env.seed(0)
    env.reset()
    # Thread CPU time, as `libero_sim::benchmark` uses: other jobs on a shared machine do not count against either.
    clock = time.thread_time
    best = wall_best = None
    for _ in range(a.rounds):
        env.set_init_state(states[0])
        t0, w0 = clock(), time.perf_counter()
        for i in range(a.steps):
            env.step(action(i))
        dt, wall = clock() - t0, time.perf_counter() - w0
        best = dt if best is None else min(best, dt)
        wall_best = wall if wall_best is None else min(wall_best, wall)
    # raw mj_step of the same compiled model, 25 per control step, ctrl held
    m, d = env.sim.model._model, env.sim.data._data
    raw_best = None
    for _ in range(a.rounds):
        env.set_init_state(states[0])
        t0 = clock()
        for _ in range(a.steps * 25):
            mujoco.mj_step(m, d)
        dt = clock() - t0
        raw_best = dt if raw_best is None else min(raw_best, dt)
    print(json.dumps(dict(
        scene=f"{a.suite}/{a.task}", steps=a.steps, rounds=a.rounds, clock="thread_cpu",
        env_step_per_s=a.steps / best, us_per_env_step=1e6 * best / a.steps,
        env_step_per_s_wall=a.steps / wall_best,
        python_raw_control_equiv_per_s=a.steps / raw_best,
        versions=dict(mujoco=mujoco.__version__, numpy=np.__version__),
    )))


if __name__ == "__main__":
    main()
