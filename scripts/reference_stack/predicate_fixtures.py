"""Ground truth for our LIBERO goal predicates, from the real stack (robosuite 1.4.0 + hf-libero 0.1.4 env code on
mujoco 3.17.0). Reference tooling only; run with the refstack venv (see setup.sh):

    ~/.cache/libero-agent/refstack/bin/python scripts/reference_stack/predicate_fixtures.py [--out DIR] [--only SUBSTR]

For each task: ControlEnv(bddl); env.seed(0); env.reset()  (fixture placement = our Placement::sample(seed 0));
env.set_init_state(states[i]). Then states are produced by
  * the init state itself;
  * articulation perturbations: every joint an Open/Close/TurnOn/TurnOff atom reads is set to the class threshold,
    threshold -/+ 1e-4 and -/+ 0.01, and to both ends of its range;
  * object moves for In/On atoms: the object's free joint put at the region centre, just inside/outside each face of
    LIBERO's test box (1 mm), above an object support, and dropped onto the support and settled with zero actions;
each followed by env.sim.forward(). For every state the fixture stores time/qpos/qvel and LIBERO's own value of
every goal atom (`env._eval_predicate`) plus of extra atoms over the scene's articulated fixtures/regions and
objects, and `env._check_success()`.

Output: one JSON per task in tests/fixtures/predicates/<suite>__<task>.json.
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

CACHE = os.environ.get("LIBERO_AGENT_CACHE", os.path.expanduser("~/.cache/libero-agent"))
ROOT = os.path.join(CACHE, "hf-libero-0.1.4")

TASKS = [
    # the 8 golden tasks
    ("libero_object", "pick_up_the_alphabet_soup_and_place_it_in_the_basket", [0, 1]),
    ("libero_90", "KITCHEN_SCENE10_close_the_top_drawer_of_the_cabinet", [0, 1]),
    ("libero_90", "KITCHEN_SCENE1_open_the_top_drawer_of_the_cabinet", [0]),
    ("libero_90", "KITCHEN_SCENE7_open_the_microwave", [0]),
    ("libero_goal", "turn_on_the_stove", [0]),
    ("libero_goal", "push_the_plate_to_the_front_of_the_stove", [0]),
    ("libero_10", "LIVING_ROOM_SCENE2_put_both_the_alphabet_soup_and_the_tomato_sauce_in_the_basket", [0]),
    ("libero_10", "STUDY_SCENE1_pick_up_the_book_and_place_it_in_the_back_compartment_of_the_caddy", [0]),
    # more predicate kinds / fixture classes
    ("libero_90", "KITCHEN_SCENE6_close_the_microwave", [0]),
    ("libero_90", "KITCHEN_SCENE8_turn_off_the_stove", [0]),
    ("libero_90", "KITCHEN_SCENE4_close_the_bottom_drawer_of_the_cabinet_and_open_the_top_drawer", [0]),
    ("libero_90", "KITCHEN_SCENE9_put_the_frying_pan_on_top_of_the_cabinet", [0]),
    ("libero_90", "LIVING_ROOM_SCENE6_put_the_red_mug_on_the_plate", [0]),
    ("libero_goal", "open_the_middle_drawer_of_the_cabinet", [0]),
    ("libero_goal", "put_the_bowl_on_the_plate", [0]),
    ("libero_goal", "put_the_bowl_on_top_of_the_cabinet", [0]),
    ("libero_goal", "put_the_wine_bottle_on_the_rack", [0]),
    ("libero_goal", "open_the_top_drawer_and_put_the_bowl_inside", [0]),
    ("libero_10", "KITCHEN_SCENE3_turn_on_the_stove_and_put_the_moka_pot_on_it", [0]),
    ("libero_10", "KITCHEN_SCENE6_put_the_yellow_and_white_mug_in_the_microwave_and_close_it", [0]),
    ("libero_spatial", "pick_up_the_black_bowl_between_the_plate_and_the_ramekin_and_place_it_on_the_plate", [0]),
]

OBJ = mujoco.mjtObj
ARTICULATION = {"open", "close", "turnon", "turnoff"}


def load_init_states(path):
    z = zipfile.ZipFile(path)
    return pickle.loads(z.read([x for x in z.namelist() if x.endswith("data.pkl")][0]))


def class_threshold(obj, pred):
    """The joint value where LIBERO's test flips, from the class's default ranges (max/min as the methods use)."""
    a = obj.object_properties["articulation"]
    if pred == "open":
        r = a["default_open_ranges"]
        return max(r) if obj.is_open(max(r) - 1e-9) else min(r)
    if pred == "close":
        r = a["default_close_ranges"]
        return min(r) if obj.is_close(min(r) + 1e-9) else max(r)
    if pred == "turnon":
        return min(a["default_turnon_ranges"])
    return max(a["default_turnoff_ranges"])


def implements_open(obj):
    try:
        obj.is_open(0.0)
        return True
    except (NotImplementedError, AttributeError):
        return False


class Task:
    def __init__(self, suite, name):
        self.suite, self.name = suite, name
        bddl = os.path.join(ROOT, "bddl_files", suite, name + ".bddl")
        self.env = ControlEnv(bddl_file_name=bddl, has_offscreen_renderer=False, use_camera_obs=False)
        self.env.seed(0)
        self.env.reset()
        self.e = self.env.env
        self.m, self.d = self.env.sim.model._model, self.env.sim.data._data
        self.states = load_init_states(os.path.join(ROOT, "init_files", suite, name + ".pruned_init"))
        self.goal = [list(s) for s in self.e.parsed_problem["goal_state"]]
        self.atoms = self.goal + self.extra_atoms()

    def extra_atoms(self):
        """Atoms beyond the goal: both articulation tests on every articulated fixture and region with joints, and
        Up on every object (LIBERO evaluates these with the same machinery)."""
        out = []
        for name, obj in self.e.fixtures_dict.items():
            if name not in self.e.object_states_dict:
                continue
            if hasattr(obj, "turn_on"):
                out += [["turnon", name], ["turnoff", name]]
            elif implements_open(obj) and obj.joints:
                out += [["open", name], ["close", name]]
        for key, site in self.e.object_sites_dict.items():
            parent = self.e.get_object(site.parent_name)
            if site.joints and implements_open(parent):
                out += [["open", key], ["close", key]]
        for name in self.e.objects_dict:
            out.append(["up", name])
        seen, uniq = set(), []
        for a in out:
            if tuple(a) not in seen and a not in self.goal:
                seen.add(tuple(a))
                uniq.append(a)
        return uniq

    def evaluate(self, label):
        values = [bool(self.e._eval_predicate(a)) for a in self.atoms]
        return dict(label=label, time=float(self.d.time), qpos=self.d.qpos.tolist(), qvel=self.d.qvel.tolist(),
                    check_success=bool(self.e._check_success()), values=values)

    def restore(self, idx):
        self.env.set_init_state(self.states[idx])

    def joint_adr(self, joint):
        return int(self.m.jnt_qposadr[mujoco.mj_name2id(self.m, OBJ.mjOBJ_JOINT, joint)])

    def joint_range(self, joint):
        return self.m.jnt_range[mujoco.mj_name2id(self.m, OBJ.mjOBJ_JOINT, joint)].tolist()

    def free_joint(self, obj_name):
        body = mujoco.mj_name2id(self.m, OBJ.mjOBJ_BODY, self.e.get_object(obj_name).root_body)
        j = int(self.m.body_jntadr[body])
        assert j >= 0 and self.m.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE, obj_name
        return j

    def articulation_cases(self, idx, atom):
        pred, target = atom[0].lower(), atom[1]
        if target in self.e.object_sites_dict:
            joints = self.e.object_sites_dict[target].joints
            owner = self.e.get_object(self.e.object_sites_dict[target].parent_name)
        else:
            owner = self.e.get_object(target)
            joints = owner.joints
        t = class_threshold(owner, pred)
        rows = []
        lo, hi = self.joint_range(joints[0])
        for label, q in [("threshold", t), ("threshold-1e-4", t - 1e-4), ("threshold+1e-4", t + 1e-4),
                         ("threshold-0.01", t - 0.01), ("threshold+0.01", t + 0.01), ("range_min", lo),
                         ("range_max", hi)]:
            self.restore(idx)
            for j in joints:
                self.d.qpos[self.joint_adr(j)] = q
            self.env.sim.forward()
            rows.append(self.evaluate(f"init{idx}:{'/'.join(atom)}:{label}"))
        return rows

    def place(self, obj_name, pos):
        j = self.free_joint(obj_name)
        a, v = int(self.m.jnt_qposadr[j]), int(self.m.jnt_dofadr[j])
        self.d.qpos[a:a + 3] = pos
        self.d.qvel[v:v + 6] = 0

    def site_frame(self, key):
        sid = mujoco.mj_name2id(self.m, OBJ.mjOBJ_SITE, key)
        return self.d.site_xpos[sid].copy(), self.d.site_xmat[sid].reshape(3, 3).copy(), np.asarray(
            self.e.object_sites_dict[key].size, dtype=float)

    def settle(self, steps=15):
        for _ in range(steps):
            self.env.step([0.0] * 7)
        self.env.sim.forward()

    def move_cases(self, idx, atom):
        pred, a, b = atom[0].lower(), atom[1], atom[2]
        rows = []
        tag = lambda label: f"init{idx}:{'/'.join(atom)}:{label}"
        if b in self.e.object_sites_dict:
            self.restore(idx)
            c, R, s = self.site_frame(b)
            if pred == "in":
                h = np.abs(R @ s)
                lb = c - h
                lb[2] -= 0.01
                ub = c + h
                mid = (lb + ub) / 2
                cases = [("centre", mid)]
                for k, axis in enumerate("xyz"):
                    for side, edge, sign in (("min", lb, 1), ("max", ub, -1)):
                        for inside in (True, False):
                            p = mid.copy()
                            p[k] = edge[k] + sign * (0.001 if inside else -0.001)
                            cases.append((f"{axis}{side}_{'inside' if inside else 'outside'}_1mm", p))
            else:  # on a site: d = R (p - c)  =>  p = c + R^T d
                d0 = np.array([0.0, 0.0, s[2] + 0.05])
                cases = [("centre_5cm_above", c + R.T @ d0)]
                for label, d in [("dz_low_inside_1mm", [0, 0, s[2] - 0.005 + 0.001]),
                                 ("dz_low_outside_1mm", [0, 0, s[2] - 0.005 - 0.001]),
                                 ("dz_high_inside_1mm", [0, 0, s[2] + 0.10 - 0.001]),
                                 ("dz_high_outside_1mm", [0, 0, s[2] + 0.10 + 0.001]),
                                 ("dx_inside_1mm", [s[0] - 0.001, 0, s[2] + 0.02]),
                                 ("dx_outside_1mm", [s[0] + 0.001, 0, s[2] + 0.02]),
                                 ("dy_inside_1mm", [0, s[1] - 0.001, s[2] + 0.02]),
                                 ("dy_outside_1mm", [0, -s[1] - 0.001, s[2] + 0.02])]:
                    cases.append((label, c + R.T @ np.asarray(d, dtype=float)))
            for label, p in cases:
                self.restore(idx)
                self.place(a, p)
                self.env.sim.forward()
                rows.append(self.evaluate(tag(label)))
            # dropped from above the region centre and settled (real contacts with the support)
            self.restore(idx)
            drop = (c + R.T @ np.array([0.0, 0.0, s[2] + 0.06])) if pred == "on" else np.array([c[0], c[1], c[2] + 0.08])
            self.place(a, drop)
            self.env.sim.forward()
            self.settle()
            rows.append(self.evaluate(tag("dropped_and_settled")))
        else:  # on an object: B's root origin below A's, contact, xy distance < 0.03
            for label, offset in [("xy_0.02_above", [0.02, 0.0, 0.06]), ("xy_0.035_above", [0.035, 0.0, 0.06]),
                                  ("xy_0_below", [0.0, 0.0, -0.02])]:
                self.restore(idx)
                pb = self.d.xpos[mujoco.mj_name2id(self.m, OBJ.mjOBJ_BODY, self.e.get_object(b).root_body)].copy()
                self.place(a, pb + np.asarray(offset))
                self.env.sim.forward()
                rows.append(self.evaluate(tag(label)))
                if label != "xy_0_below":
                    self.settle()
                    rows.append(self.evaluate(tag(label + "_settled")))
        return rows

    def run(self, inits):
        cases = []
        for idx in inits:
            self.restore(idx)
            cases.append(self.evaluate(f"init{idx}"))
            self.settle(10)
            cases.append(self.evaluate(f"init{idx}:settled_10_zero_actions"))
            for atom in self.goal:
                if atom[0].lower() in ARTICULATION:
                    cases += self.articulation_cases(idx, atom)
                elif atom[0].lower() in ("in", "on") and atom[1] in self.e.objects_dict:
                    cases += self.move_cases(idx, atom)
        atoms = [f"({a[0].lower()} {' '.join(a[1:])})" for a in self.atoms]
        return dict(schema_version="libero_agent.predicate_fixture.v1", suite=self.suite, task=self.name,
                    placement_seed=0, generator="scripts/reference_stack/predicate_fixtures.py",
                    stack="robosuite 1.4.0 + hf-libero 0.1.4 + mujoco 3.17.0",
                    goal_atoms=atoms[:len(self.goal)], extra_atoms=atoms[len(self.goal):],
                    nq=int(self.m.nq), nv=int(self.m.nv), cases=cases)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default=os.path.join(HERE, "../../tests/fixtures/predicates"))
    ap.add_argument("--only")
    a = ap.parse_args()
    os.makedirs(a.out, exist_ok=True)
    for suite, name, inits in TASKS:
        if a.only and a.only not in name:
            continue
        t = Task(suite, name)
        fixture = t.run(inits)
        t.env.close()
        path = os.path.join(a.out, f"{suite}__{name}.json")
        with open(path, "w") as f:
            json.dump(fixture, f, separators=(",", ":"))
        n_true = sum(v for c in fixture["cases"] for v in c["values"])
        n_all = sum(len(c["values"]) for c in fixture["cases"])
        print(f"{suite}/{name}: {len(fixture['cases'])} states, {n_all} values ({n_true} true)", flush=True)


if __name__ == "__main__":
    main()
