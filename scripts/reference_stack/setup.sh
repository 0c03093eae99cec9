#!/usr/bin/env bash
# Reference stack: the real robosuite 1.4.0 + LIBERO (hf-libero 0.1.4 env code) on mujoco 3.17.0, in a throwaway
# venv, used to diff our Rust composer/placement against the original for any BDDL and to benchmark LIBERO's
# env.step. Reference tooling only; the product never imports it.
#
#   scripts/reference_stack/setup.sh [VENV]      (default ~/.cache/libero-agent/refstack)
#   VENV/bin/python scripts/reference_stack/libero_env.py --bddl FILE --seed 0 --out scene.json [--mjcf scene.xml]
#
# Needs the cache that scripts/setup.py fills (wheels/, libero-assets-0.1.0/, hf-libero-0.1.4/). Installs from
# PyPI with pinned versions; robosuite and hf-libero go in with --no-deps (their declared deps pull in torch,
# wandb, transformers, opencv ... none of which the env code needs).
set -euo pipefail
CACHE="${LIBERO_AGENT_CACHE:-$HOME/.cache/libero-agent}"
VENV="${1:-$CACHE/refstack}"
WHEELS="$CACHE/wheels"
HERE="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"

python3 -m venv "$VENV"
PY="$VENV/bin/python"
"$PY" -m pip install --quiet --upgrade pip
# mujoco from the cached, sha256-locked wheel when present (same file as on PyPI)
MJ_WHEEL="$(ls "$WHEELS"/mujoco-3.17.0-*.whl 2>/dev/null | head -1 || true)"
"$PY" -m pip install --quiet "numpy==1.26.4" ${MJ_WHEEL:-"mujoco==3.17.0"}
# what the env code imports: robosuite (numba, scipy, PIL, cv2 via utils/opencv_renderer), libero envs (yaml, easydict, matplotlib.cm in
# env_wrapper, bddl.s scan_tokens, gymnasium/cloudpickle via envs/venv.py)
"$PY" -m pip install --quiet "scipy==1.13.1" "numba==0.60.0" "pillow" "pyyaml" "easydict" "matplotlib" \
    "gymnasium" "cloudpickle" "opencv-python-headless==4.10.0.84" "termcolor" "future"
"$PY" -m pip install --quiet --no-deps "bddl==1.0.1"
"$PY" -m pip install --quiet --no-deps "$WHEELS/robosuite-1.4.0-py3-none-any.whl"
"$PY" -m pip install --quiet --no-deps "$WHEELS/hf_libero-0.1.4-py3-none-any.whl"

SITE="$("$PY" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')"
# LIBERO looks for libero/libero/assets next to its code before trying a download: link the cached asset set.
ln -sfn "$CACHE/libero-assets-0.1.0/assets" "$SITE/libero/libero/assets"
# The config file LIBERO reads (it prompts on stdin when missing).
CFG="$VENV/libero_config"
mkdir -p "$CFG"
cat > "$CFG/config.yaml" <<YAML
benchmark_root: $SITE/libero/libero
bddl_files: $CACHE/hf-libero-0.1.4/bddl_files
init_states: $CACHE/hf-libero-0.1.4/init_files
datasets: $VENV/datasets
assets: $CACHE/libero-assets-0.1.0/assets
YAML
# robosuite prints a warning without macros_private; harmless. The shim makes robosuite 1.4 run on mujoco 3.x.
cp "$HERE/rs14_mj3_shim.py" "$SITE/rs14_mj3_shim.py"
echo "export LIBERO_CONFIG_PATH=$CFG" > "$VENV/env.sh"
LIBERO_CONFIG_PATH="$CFG" "$PY" -c 'import rs14_mj3_shim, libero.libero.envs; print("reference stack OK")'
echo "venv: $VENV   (source $VENV/env.sh, or let libero_env.py set LIBERO_CONFIG_PATH)"
