#!/usr/bin/env python3
"""Reference images and timings from MuJoCo's own renderer (PyPI mujoco==3.17.0, software GL).

Used by libero-render's validation tests and by `libero-agent bench render`; run with the venv that
`python3 scripts/setup.py --test` creates (~/.cache/libero-agent/pyenv).

  render: mujoco_reference.py render --xml FILE --out DIR [--size 256] [--camera agentview ...]
          writes DIR/<camera>/{rgb.png, depth_m.npy, seg.npy} and DIR/meta.json
  bench:  mujoco_reference.py bench --xml FILE [--size 256] [--frames 100] [--camera ...]
          prints JSON with frames per second for all cameras x (RGB + depth)

Rendering follows robosuite's observation set-up (libero_port_notes.md §4.3): collision geoms
(group 0) hidden, robot/gripper/object sites with positive alpha hidden (alpha negated by robosuite;
set to 0 here so MuJoCo also drops them from segmentation), shadows and reflections off.
"""
import argparse
import json
import os
import sys
import time


def _setup_gl():
    os.environ.setdefault("MUJOCO_GL", "egl")
    if os.environ["MUJOCO_GL"] == "egl":
        os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
        os.environ.setdefault("EGL_PLATFORM", "surfaceless")


_setup_gl()
import numpy as np  # noqa: E402
import mujoco  # noqa: E402


def cache_dir():
    return os.environ.get("LIBERO_AGENT_CACHE") or os.path.join(os.path.expanduser("~"), ".cache", "libero-agent")


def load_model(xml_path):
    text = open(xml_path).read()
    c = cache_dir()
    text = text.replace("${ROBOSUITE_ASSETS}", os.path.join(c, "robosuite-1.4.0", "assets"))
    text = text.replace("${LIBERO_ASSETS}", os.path.join(c, "libero-assets-0.1.0", "assets"))
    model = mujoco.MjModel.from_xml_string(text)
    # robosuite visualize(False): hide robot/gripper/object sites (not world-body sites).
    for i in range(model.nsite):
        if model.site_bodyid[i] != 0 and model.site_rgba[i, 3] > 0:
            model.site_rgba[i, 3] = -model.site_rgba[i, 3]
    for i in range(model.nsite):
        if model.site_rgba[i, 3] < 0:
            model.site_rgba[i, 3] = 0.0
    return model


def make_data(model, keyframe):
    data = mujoco.MjData(model)
    if keyframe is not None:
        mujoco.mj_resetDataKeyframe(model, data, keyframe)
    mujoco.mj_forward(model, data)
    return data


def scene_option():
    opt = mujoco.MjvOption()
    opt.geomgroup[0] = 0
    opt.geomgroup[1] = 1
    return opt


def plain_flags(renderer):
    renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
    renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0


def write_png_rgb(path, rgb):
    from PIL import Image
    Image.fromarray(rgb).save(path)


def cmd_render(args):
    model = load_model(args.xml)
    data = make_data(model, args.keyframe)
    opt = scene_option()
    cams = args.camera or ["agentview", "robot0_eye_in_hand"]
    r = mujoco.Renderer(model, args.size, args.size)
    meta = {"znear_m": float(model.vis.map.znear * model.stat.extent),
            "zfar_m": float(model.vis.map.zfar * model.stat.extent), "cameras": {}}
    for cam in cams:
        d = os.path.join(args.out, cam)
        os.makedirs(d, exist_ok=True)
        r.disable_depth_rendering()
        r.disable_segmentation_rendering()
        r.update_scene(data, camera=cam, scene_option=opt)
        plain_flags(r)
        rgb = r.render().copy()
        r.enable_depth_rendering()
        r.update_scene(data, camera=cam, scene_option=opt)
        plain_flags(r)
        depth = r.render().astype(np.float32).copy()
        r.disable_depth_rendering()
        r.enable_segmentation_rendering()
        r.update_scene(data, camera=cam, scene_option=opt)
        plain_flags(r)
        seg_raw = r.render().copy()
        r.disable_segmentation_rendering()
        objid, objtype = seg_raw[..., 0].astype(np.int64), seg_raw[..., 1].astype(np.int64)
        seg = np.zeros(objid.shape, dtype=np.uint32)
        geom = (objtype == int(mujoco.mjtObj.mjOBJ_GEOM)) & (objid >= 0)
        site = (objtype == int(mujoco.mjtObj.mjOBJ_SITE)) & (objid >= 0)
        seg[geom] = (objid[geom] + 1).astype(np.uint32)
        seg[site] = ((objid[site] + 1) | (1 << 31)).astype(np.uint32)
        write_png_rgb(os.path.join(d, "rgb.png"), rgb)
        np.save(os.path.join(d, "depth_m.npy"), depth)
        np.save(os.path.join(d, "seg.npy"), seg)
        cid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, cam)
        meta["cameras"][cam] = {"id": int(cid), "cam_xpos": data.cam_xpos[cid].tolist(),
                                "cam_xmat": data.cam_xmat[cid].tolist(), "fovy": float(model.cam_fovy[cid])}
    r.close()
    with open(os.path.join(args.out, "meta.json"), "w") as f:
        json.dump(meta, f, indent=1)


def cmd_bench(args):
    model = load_model(args.xml)
    data = make_data(model, args.keyframe)
    opt = scene_option()
    cams = args.camera or ["agentview", "robot0_eye_in_hand"]
    r = mujoco.Renderer(model, args.size, args.size)
    rgb = np.empty((args.size, args.size, 3), dtype=np.uint8)
    depth = np.empty((args.size, args.size), dtype=np.float32)
    # One mjr_render per camera and one mjr_readPixels for RGB and depth together: the cheapest way
    # MuJoCo offers to get both images (mujoco.Renderer would render twice).
    ctx = r._mjr_context
    rect = r._rect

    def frame():
        for cam in cams:
            r.update_scene(data, camera=cam, scene_option=opt)
            plain_flags(r)
            r._gl_context.make_current()
            mujoco.mjr_render(rect, r.scene, ctx)
            mujoco.mjr_readPixels(rgb, depth, rect, ctx)

    for _ in range(args.warmup):
        frame()
    t0 = time.perf_counter()
    c0 = time.process_time()
    for _ in range(args.frames):
        frame()
    wall = time.perf_counter() - t0
    cpu = time.process_time() - c0
    r.close()
    print(json.dumps({
        "renderer": "mujoco " + mujoco.__version__ + " mjr_render (" + os.environ.get("MUJOCO_GL", "") + ")",
        "frames": args.frames, "cameras": cams, "size": args.size,
        "wall_s": wall, "cpu_s": cpu, "fps": args.frames / wall,
    }))


def main():
    p = argparse.ArgumentParser()
    sub = p.add_subparsers(dest="cmd", required=True)
    for name in ("render", "bench"):
        s = sub.add_parser(name)
        s.add_argument("--xml", required=True)
        s.add_argument("--size", type=int, default=256)
        s.add_argument("--camera", action="append")
        s.add_argument("--keyframe", type=int, default=None)
        if name == "render":
            s.add_argument("--out", required=True)
        else:
            s.add_argument("--frames", type=int, default=100)
            s.add_argument("--warmup", type=int, default=5)
    args = p.parse_args()
    {"render": cmd_render, "bench": cmd_bench}[args.cmd](args)


if __name__ == "__main__":
    sys.exit(main())
