#!/usr/bin/env bash
# Issue 34, item 4: `bench render`, `bench mcp` and `bench scale` on a lent GPU machine (NVIDIA Vulkan driver, not
# lavapipe), or here on the CPU with the same arguments (`--cpu`), each JSON written to $OUT.
#
# On the GPU machine (no network) everything comes from the carried folders, which `.git/info/exclude` ignores:
#   .gl/            the Vulkan/GL loader debs (unpacked into /), see the device notes of the tool library
#   .devicebench/   libero-agent.xz (the stripped release binary), cache.tar.xz (a LIBERO_AGENT_CACHE holding
#                   libmujoco and only the asset files these benches load: T14, T16, T15 and bench render's scene)
#                   and project.tar.xz (the tree's tasks/ and assets/ the binary was built with)
# Prepare them with `scripts/device_bench.sh --pack BIN [SRC]` (BIN: a release build of libero-agent, SRC: the tree
# it was built from, default this one), check the subset
# here with `scripts/device_bench.sh --cpu`, and run on the machine as
#   bash scripts/device_bench.sh            (writes $OUT/{render,mcp,scale}.json, device.log, gpu_memory.csv)
#
# Here: `OUT=target/tmp/device_bench/cpu scripts/device_bench.sh --cpu [BIN]` runs the same benches on the CPU
# (lavapipe) with the carried cache subset, so the subset is proven to be enough.
set -uo pipefail

ROOT=$(cd "$(dirname "$0")/.." && pwd)
DB=$ROOT/.devicebench
OUT=${OUT:-$ROOT/target/tmp/device_bench/run}
MODE=gpu
# The asset files the benches below load (traced with strace on the full cache), relative to the cache.
ASSET_LIST=$DB/assets.txt

# The benches and their arguments: the same on the CPU and on the GPU.
RENDER_ARGS=(bench render --no-mujoco --json)
MCP_ARGS=(bench mcp --json)
SCALE_ARGS=(bench scale --episodes 8 --scenes 3 --tasks T14,T16,T15 --json)
# On the GPU machine only, when time allows: three times the episodes (about 20 GB; too much beside other work on a
# 24 GB machine).
SCALE_LARGE_ARGS=(bench scale --episodes 24 --scenes 3 --tasks T14,T16,T15 --settle-ms 1000 --json)

case "${1:-}" in
--pack)
    # Builds .devicebench/ from a release binary and the local cache (~/.cache/libero-agent or $LIBERO_AGENT_CACHE).
    BIN=${2:?usage: device_bench.sh --pack BIN [SRC]}
    SRC=${3:-$ROOT}
    CACHE=${LIBERO_AGENT_CACHE:-$HOME/.cache/libero-agent}
    test -s "$ASSET_LIST" || { echo "$ASSET_LIST missing (one cache-relative path a line)" >&2; exit 2; }
    strip -o "$DB/libero-agent" "$BIN" && xz -9e -T0 -f "$DB/libero-agent" || exit 1
    (cd "$CACHE" && { cat "$ASSET_LIST"; echo mujoco-3.17.0/lib/libmujoco.so.3.17.0; echo mujoco-3.17.0/lib/libmujoco.so; } \
        | tar -cf - --no-recursion -T - | xz -9e -T0 >"$DB/cache.tar.xz") || exit 1
    tar -C "$SRC" -cf - tasks assets | xz -9 -T0 >"$DB/project.tar.xz" || exit 1
    ls -la "$DB"
    exit 0
    ;;
--cpu)
    MODE=cpu
    BIN_ARG=${2:-}
    ;;
esac

mkdir -p "$OUT"
LOG=$OUT/device.log
# serve prints a one-time dashboard login link; it stays out of the log.
exec > >(grep --line-buffered -v 'token=' | tee -a "$LOG") 2>&1
echo "== device_bench.sh ($MODE) $(date -u +%FT%TZ) on $(hostname), $(nproc) cores, $(awk '/MemTotal/ {printf "%.0f GB", $2/1048576}' /proc/meminfo)"

WORK=$(mktemp -d /tmp/devicebench.XXXXXX)
trap 'rm -rf "$WORK"' EXIT
if [ "$MODE" = gpu ]; then
    for f in "$ROOT"/.gl/*.deb; do dpkg -x "$f" /; done
    ldconfig
    nvidia-smi -L
    # Only NVIDIA's ICD and EGL vendor, never a software rasteriser; wgpu on Vulkan alone (no GL fallback).
    for icd in /usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json /usr/share/vulkan/icd.d/nvidia_icd.json /etc/vulkan/icd.d/nvidia_icd.json; do
        if [ -f "$icd" ]; then export VK_DRIVER_FILES=$icd VK_ICD_FILENAMES=$icd; break; fi
    done
    if [ -z "${VK_DRIVER_FILES:-}" ]; then
        icd=$(find /usr /etc -name 'nvidia_icd*.json' 2>/dev/null | head -1)
        [ -n "$icd" ] && export VK_DRIVER_FILES=$icd VK_ICD_FILENAMES=$icd
    fi
    egl=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
    [ -f "$egl" ] && export __EGL_VENDOR_LIBRARY_FILENAMES=$egl
    echo "VK_DRIVER_FILES=${VK_DRIVER_FILES:-unset}"
    ldconfig -p | grep -E 'libvulkan|libGLX_nvidia|libnvidia-glcore' | head -5
fi
export WGPU_BACKEND=vulkan

# xz -dc, or Python's lzma where xz is missing.
unxz() {
    if command -v xz >/dev/null; then xz -dc "$1"; else python3 -c 'import lzma, shutil, sys; shutil.copyfileobj(lzma.open(sys.argv[1]), sys.stdout.buffer)' "$1"; fi
}
# The cache subset and the binary, unpacked outside the tree.
mkdir -p "$WORK/cache"
unxz "$DB/cache.tar.xz" | tar -xf - -C "$WORK/cache" || { echo "cannot unpack $DB/cache.tar.xz" >&2; exit 1; }
if [ -n "${BIN_ARG:-}" ]; then
    cp "$BIN_ARG" "$WORK/libero-agent"
else
    unxz "$DB/libero-agent.xz" >"$WORK/libero-agent" || exit 1
fi
chmod +x "$WORK/libero-agent"
# AssetPaths wants these folders even when nothing in them is read.
mkdir -p "$WORK/cache/hf-libero-0.1.4" "$WORK/cache/robosuite-1.4.0/assets" "$WORK/cache/libero-assets-0.1.0/assets" "$WORK/cache/mujoco-3.17.0/lib"
export LIBERO_AGENT_CACHE=$WORK/cache
mkdir -p "$WORK/project"
unxz "$DB/project.tar.xz" | tar -xf - -C "$WORK/project" || { echo "cannot unpack $DB/project.tar.xz" >&2; exit 1; }
export LIBERO_AGENT_ASSETS_DIR=$WORK/project/assets LIBERO_AGENT_TASKS_DIR=$WORK/project/tasks
export LD_LIBRARY_PATH=$WORK/cache/mujoco-3.17.0/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}
# No user registry or data directory of this machine's user: all of it under $WORK.
export HOME=$WORK/home LIBERO_AGENT_STATE=$WORK/state LIBERO_AGENT_DATA=$WORK/data TMPDIR=$WORK/tmp
mkdir -p "$HOME" "$TMPDIR"
BIN=$WORK/libero-agent
"$BIN" --version

GPU_MEM_PID=
if [ "$MODE" = gpu ]; then
    nvidia-smi --query-gpu=timestamp,memory.used,utilization.gpu --format=csv -lms 500 >"$OUT/gpu_memory.csv" 2>/dev/null &
    GPU_MEM_PID=$!
fi

status=0
# run_bench NAME LIMIT_S ARGS...: one bench, its JSON to $OUT/NAME.json, stopped after LIMIT_S seconds.
run_bench() {
    local name=$1 limit=$2
    shift 2
    echo "== $name: libero-agent $*"
    local t0=$SECONDS
    # The limits fit the GPU machine's 16 cores and its lease; two shared cores take several times longer.
    [ "$MODE" = cpu ] && limit=$((limit * 5))
    if timeout --kill-after=15 "$limit" "$BIN" "$@" >"$OUT/$name.json"; then
        echo "== $name: done in $((SECONDS - t0)) s"
    else
        echo "== $name: FAILED (exit $?) after $((SECONDS - t0)) s"
        status=1
    fi
}

run_bench render 90 "${RENDER_ARGS[@]}"
# The adapter wgpu picked (bench render names it); on the GPU machine it must not be a software rasteriser.
adapter=$(grep -o '"renderer":"[^"]*"' "$OUT/render.json" | head -1)
echo "== adapter: ${adapter:-unknown}"
if [ "$MODE" = gpu ] && ! grep -q NVIDIA <<<"$adapter"; then
    echo "== not the NVIDIA driver: stopping" >&2
    exit 1
fi
run_bench mcp 180 "${MCP_ARGS[@]}"
run_bench scale 150 "${SCALE_ARGS[@]}"
if [ "$MODE" = gpu ] && [ "$SECONDS" -lt 200 ]; then
    run_bench scale24 150 "${SCALE_LARGE_ARGS[@]}"
fi
[ "$MODE" = gpu ] && nvidia-smi --query-gpu=name,driver_version,memory.total,memory.used --format=csv
[ -n "$GPU_MEM_PID" ] && kill "$GPU_MEM_PID" 2>/dev/null
echo "== done: status $status"
sleep 1 # lets the log's tee write its last lines
exit $status
