"""What the paper's agents ran (Appendix F): the published head depth back-projected through the published
calibration into the robot base frame, with numpy, scipy, Pillow and OpenCV, then a move computed from it.

The scripted model (tests/clis/scripted_model.py, `--script perception`) sends this program as the shell command
of the CLI under test (Codex's `exec_command`, Claude Code's `Bash`) in a heredoc; the CLI runs it in the sandbox.
Its last line, `LIBERO_PERCEPTION …`, is what the model reads back from the command's output to choose the next
`osc_sequence`: the action moves the gripper a bounded step toward the point 10 cm above the highest surface
under it. `python=` and `numpy=` say which interpreter and numpy ran (the toolbox's, at /opt/libero-toolbox).
"""
import json
import sys

import cv2
import numpy as np
import scipy
from PIL import Image
from scipy.spatial.transform import Rotation

OBS = "benchmark_inputs/current_observation"
obs = json.load(open(f"{OBS}/observation.json"))
head = obs["cameras"]["head"]
depth_m = np.load(f"{OBS}/{head['depth']['metric_file']}")
valid = np.asarray(Image.open(f"{OBS}/{head['depth']['valid_mask_file']}")) > 0
bgr = cv2.imread(f"{OBS}/{head['rgb']['file']}", cv2.IMREAD_COLOR)
rgb = np.asarray(Image.open(f"{OBS}/{head['rgb']['file']}").convert("RGB"))
assert bgr is not None and bgr.shape == rgb.shape and (bgr[..., ::-1] == rgb).all(), "OpenCV and Pillow disagree"

K = np.array(head["intrinsic_matrix_3x3"], dtype=float)
T_robot_base_from_camera = np.array(head["matrix_T_robot_base_from_camera_opencv_4x4"], dtype=float)
h, w = depth_m.shape
v, u = np.mgrid[0:h, 0:w]
ok = valid & np.isfinite(depth_m) & (depth_m > 0) & (depth_m < 5.0)
z = depth_m[ok]
points_camera = np.stack([(u[ok] - K[0, 2]) * z / K[0, 0], (v[ok] - K[1, 2]) * z / K[1, 1], z], axis=1)
points_base_m = points_camera @ T_robot_base_from_camera[:3, :3].T + T_robot_base_from_camera[:3, 3]

eef = obs["state"]["eef_pose_robot_base_xyzw_7d"]
eef_pos_m = np.array(eef[:3])
R_base_from_eef = Rotation.from_quat(eef[3:]).as_matrix()
# The highest surface within 5 cm (in x, y) of the gripper, and a target 10 cm above it.
near = np.linalg.norm(points_base_m[:, :2] - eef_pos_m[:2], axis=1) < 0.05
surface_z_m = float(np.percentile(points_base_m[near, 2], 95)) if near.any() else float(np.median(points_base_m[:, 2]))
target_m = np.array([eef_pos_m[0], eef_pos_m[1], surface_z_m + 0.10])
# Native OSC: an action of 1 moves 5 cm per step (robosuite's output_max 0.05 m); a bounded step toward the target.
delta_m = np.clip((target_m - eef_pos_m) / 0.05, -0.5, 0.5)
action = [round(float(x), 4) for x in delta_m] + [0.0, 0.0, 0.0, -1.0]

print(f"head {w}x{h}: {ok.sum()} valid depth pixels back-projected; gripper z {eef_pos_m[2]:.3f} m, "
      f"surface below {surface_z_m:.3f} m; gripper x axis {np.round(R_base_from_eef[:, 0], 3).tolist()}")
print(f"python={sys.executable} numpy={np.__file__} scipy={scipy.__version__} cv2={cv2.__version__}")
print("LIBERO_PERCEPTION action=" + ",".join(str(a) for a in action))
