"""Drives one prepared LIBERO-Agent episode with the official MCP Python SDK (PyPI `mcp`) and checks the
protocol field by field. Run by `server/app/tests/mcp_python_client.rs`; prints one JSON report line and
exits non-zero on the first failed check.

    python episode_client.py --url URL --token TOKEN --workspace WS --tools-fixture F [--stdio BIN] [--mode auto|legacy]
"""
import argparse
import asyncio
import json
import math
import sys
from pathlib import Path

import numpy as np
from PIL import Image
from mcp import Client, StdioServerParameters
from mcp.client.streamable_http import streamable_http_client
from mcp.shared._httpx_utils import create_mcp_http_client

OBS_FILE = "benchmark_inputs/current_observation/observation.json"
CHECKS = []


def check(cond, what):
    if not cond:
        raise AssertionError(what)
    CHECKS.append(what)


def payload(result):
    sc = result.structured_content
    text = json.loads(result.content[0].text)
    check(sc == text, "text content is the structured payload")
    check(result.is_error == (sc.get("ok") is not True), "isError unless ok")
    return sc


def expect_error(result, error_type, message):
    p = payload(result)
    check(result.is_error, f"isError for {message!r}")
    check(p == {"ok": False, "error_type": error_type, "error": message}, f"error {p} == {message!r}")


def observation(ws):
    return json.loads((ws / OBS_FILE).read_text())


def check_observation(ws, obs_id, level=3):
    d = ws / "benchmark_inputs/current_observation"
    o = observation(ws)
    check(o["schema_version"] == "libero.agent_observation.v2", "schema")
    check(o["observation_id"] == obs_id, f"observation id {obs_id}")
    check(o["frame_index"] == int(obs_id[4:]), "frame index")
    check(o["profile"] == f"level{level}", "profile")
    check(o["capabilities"] == {"head_rgb": True, "wrist_rgb": True, "kinematic_state": True,
                                "dynamic_proprioception": level >= 2, "metric_depth": level >= 3,
                                "camera_calibration": level >= 3}, "capabilities")
    check(o["coordinate_conventions"]["camera_extrinsic"] == "T_robot_base_from_camera", "conventions")
    s = o["state"]
    check(len(s["arm_joint_position_rad_7d"]) == 7 and len(s["gripper_finger_joint_position_m_2d"]) == 2, "state")
    g = s["gripper_finger_joint_position_m_2d"]
    check(abs(s["gripper_width_m"] - (g[0] - g[1])) < 1e-12, "gripper width = q0 - q1")
    pose = s["eef_pose_robot_base_xyzw_7d"]
    check(len(pose) == 7 and pose[6] >= 0 and abs(sum(q * q for q in pose[3:]) - 1) < 1e-9, "eef pose unit quat, w>=0")
    check(("proprioception" in o) == (level >= 2), "proprioception only at level >= 2")
    if level >= 2:
        p = o["proprioception"]
        check(len(p["eef_twist_robot_base_6d"]) == 6 and p["force_torque_frame"] == "eef_ft_sensor", "proprio")
    check(set(o["cameras"]) == {"head", "wrist"}, "cameras head, wrist")
    for cam in ("head", "wrist"):
        c = o["cameras"][cam]
        rgb = Image.open(d / c["rgb"]["file"])
        check(rgb.mode == "RGB" and list(rgb.size)[::-1] + [3] == c["rgb"]["shape"], f"{cam} rgb png")
        arr = np.asarray(rgb)
        check(arr.std() > 0, f"{cam} image is not blank")
        if level < 3:
            check(set(c) == {"rgb"}, f"{cam} rgb only below level 3")
            continue
        dep = c["depth"]
        z = np.load(d / dep["metric_file"], allow_pickle=False)
        check(z.dtype == np.float32 and list(z.shape) == dep["shape"] and dep["dtype"] == "float32", f"{cam} depth")
        mask = np.asarray(Image.open(d / dep["valid_mask_file"]))
        check(mask.dtype == np.uint8 and mask.shape == z.shape and set(np.unique(mask)) <= {0, 255}, f"{cam} mask")
        valid = mask == 255
        check(valid.any() and np.isfinite(z[valid]).all() and (z[valid] > 0).all(), f"{cam} valid depth positive")
        check(0.01 < float(np.median(z[valid])) < 10.0, f"{cam} depth in metres")
        prev = np.asarray(Image.open(d / dep["preview_file"]))
        check(prev.shape == z.shape and (prev[~valid] == 0).all(), f"{cam} preview black where invalid")
        check(dep["preview_mapping"] == "inverse_depth_linear_near_white", "preview mapping")
        K = np.array(c["intrinsic_matrix_3x3"])
        h, w = z.shape
        check(K.shape == (3, 3) and K[0, 2] == w / 2 and K[1, 2] == h / 2 and K[0, 0] == K[1, 1], f"{cam} K")
        T = np.array(c["matrix_T_robot_base_from_camera_opencv_4x4"])
        R = T[:3, :3]
        check(np.allclose(R @ R.T, np.eye(3), atol=1e-9) and np.allclose(T[3], [0, 0, 0, 1]), f"{cam} T rigid")
    return o


async def run(args):
    ws = Path(args.workspace)
    fixture = json.loads(Path(args.tools_fixture).read_text())["tools"]
    header = {"Authorization": f"Bearer {args.token}"}
    if args.stdio:
        server = StdioServerParameters(command=args.stdio,
                                       args=["mcp-stdio", "--url", args.url, "--header", f"Authorization: Bearer {args.token}"])
    else:
        # Without the token the endpoint answers nothing but 401.
        async with create_mcp_http_client() as http:
            init = {"jsonrpc": "2.0", "id": 1, "method": "initialize",
                    "params": {"protocolVersion": "2025-06-18", "capabilities": {}, "clientInfo": {"name": "t", "version": "0"}}}
            hdr = {"Accept": "application/json, text/event-stream"}
            for h in (hdr, {**hdr, "Authorization": "Bearer wrong"}):
                r = await http.post(args.url, json=init, headers=h)
                check(r.status_code == 401, "no token, no access")
        server = streamable_http_client(args.url, http_client=create_mcp_http_client(headers=header))
    async with Client(server, mode=args.mode) as c:
        check(c.server_info.name == "libero-agent-control" and c.server_info.version == "0.1.0", "server info")
        check("start_episode" in (c.instructions or ""), "server instructions")
        tools = (await c.list_tools()).tools
        listed = [t.model_dump(by_alias=True, exclude_none=True, mode="json") for t in tools]
        check(listed == fixture, f"tools/list equals the golden fixture: {listed}")

        # Before start: designed errors, nothing published.
        expect_error(await c.call_tool("osc_sequence", {"actions": [[0] * 7]}), "RuntimeError",
                     "osc_sequence requires one active episode; call start_episode first")
        expect_error(await c.call_tool("finish_episode", {}), "RuntimeError",
                     "finish requires one active episode; call start_episode first")
        check(not (ws / OBS_FILE).exists(), "no observation before start")
        expect_error(await c.call_tool("start_episode", {"x": 1}), "ValueError", "start_episode accepts no arguments")
        expect_error(await c.call_tool("reset_episode", {}), "ValueError",
                     "unknown or disabled LIBERO MCP tool: reset_episode")

        r = await c.call_tool("start_episode", {})
        p = payload(r)
        check(not r.is_error, f"start ok: {p}")
        prompt = (ws / "TASK_PROMPT.txt").read_text()
        check(p["task_instruction"] == prompt.splitlines()[0], "start returns the instruction of the prompt")
        for k, v in {"observation_id": "obs_000000", "observation_file": OBS_FILE, "attempt_index": 1,
                     "reset_count": 0, "remaining_resets": 0, "wall_time_budget_scope": "per_episode_across_resets",
                     "execution": {}}.items():
            check(p[k] == v, f"start {k}")
        check(isinstance(p["max_wall_time_seconds"], float) and p["max_agent_steps"] == args.max_agent_steps, "budgets")
        o0 = check_observation(ws, "obs_000000", args.level)
        expect_error(await c.call_tool("start_episode", {}), "RuntimeError", "start may be called exactly once")

        # The error catalogue: each rejected without touching the simulation.
        bad = [
            ({"actions": [[0] * 7, [0] * 6]}, "actions must be a rectangular numeric array"),
            ({"actions": [["a"] * 7]}, "actions must be a rectangular numeric array"),
            ({"actions": []}, "actions must contain between 1 and 50 micro steps"),
            ({"actions": [[0] * 7] * 51}, "actions must contain between 1 and 50 micro steps"),
            ({"actions": [[0] * 6]}, "actions must have shape [N, 7]"),
            ({"actions": [[[0] * 7]]}, "actions must have shape [N, 7]"),
            ({"actions": [[0, 0, 0, 0, 0, 0, 1.0001]]}, "native OSC action components must be within [-1, 1]"),
            ({"actions": [[0] * 7], "speed": 2}, "osc_sequence requires only the actions argument"),
            ({}, "osc_sequence requires only the actions argument"),
        ]
        for arguments, message in bad:
            expect_error(await c.call_tool("osc_sequence", arguments), "ValueError", message)
        o = observation(ws)
        check(o["observation_id"] == "obs_000000" and o["sim_time_s"] == o0["sim_time_s"], "rejections change nothing")

        n = 5
        r = await c.call_tool("osc_sequence", {"actions": [[0.5, 0, -0.2, 0, 0, 0.1, -1]] * n})
        p = payload(r)
        check(not r.is_error and p["observation_id"] == "obs_000001", f"action accepted: {p}")
        check(p["execution"] == {"command_completed": True, "termination_reason": "sequence_executed",
                                 "micro_step_count": n, "control_steps": n}, "execution report")
        o1 = check_observation(ws, "obs_000001", args.level)
        check(math.isclose(o1["sim_time_s"] - o0["sim_time_s"], 0.05 * n, abs_tol=1e-9), "0.05 s per micro-action")
        dx = o1["state"]["eef_pose_robot_base_xyzw_7d"][0] - o0["state"]["eef_pose_robot_base_xyzw_7d"][0]
        check(dx > 0.005, f"+x actions move the end effector along +x ({dx:.4f} m)")

        r = await c.call_tool("finish_episode", {})
        p = payload(r)
        report_finish = p
        if p.get("ok"):
            check(p["status"] == "finished" and isinstance(p["success"], bool), "verdict")
            check(p["accepted_agent_steps"] == 1, "one accepted step")
            expect_error(await c.call_tool("osc_sequence", {"actions": [[0] * 7]}), "RuntimeError",
                         "the episode is already finished; finish_episode was called and no further commands are accepted")
        else:
            # No evaluator in this build: the server reports it as a server-side failure, never as a verdict.
            check(p["error_type"] == "EnvironmentCommandError", f"finish failure is a server error: {p}")
    # Nothing private in the workspace.
    names = [str(x.relative_to(ws)) for x in ws.rglob("*")]
    for bad_name in ("actions.jsonl", "result.json", "private_observations", "episode_record.json", ".bddl", "segmentation"):
        check(not any(bad_name in n for n in names), f"workspace holds no {bad_name}")
    print(json.dumps({"ok": True, "checks": len(CHECKS), "finish": report_finish}))


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--url", required=True)
    ap.add_argument("--token", required=True)
    ap.add_argument("--workspace", required=True)
    ap.add_argument("--tools-fixture", required=True)
    ap.add_argument("--stdio")
    ap.add_argument("--mode", default="auto")
    ap.add_argument("--level", type=int, default=3)
    ap.add_argument("--max-agent-steps", type=int, default=1000000)
    args = ap.parse_args()
    try:
        asyncio.run(run(args))
    except AssertionError as e:
        print(json.dumps({"ok": False, "failed": str(e), "passed": len(CHECKS)}))
        sys.exit(1)


if __name__ == "__main__":
    main()
