#!/usr/bin/env bash
# The checks on a GPU machine, in steps (docs/GPU.md says when to run each):
#   bash benchmarks/gpu_session.sh prepare   # HERE, on the development machine: wheels and data
#   bash benchmarks/gpu_session.sh check     # on the GPU machine: driver, ICD, OpenCL devices, limits
#   bash benchmarks/gpu_session.sh suite     # ... the kernel test suite through NVIDIA's OpenCL
#   bash benchmarks/gpu_session.sh raster    # ... benchmarks/raster.py (100k to 1M at 1008x567 and 1080p)
#   bash benchmarks/gpu_session.sh raster_direct  # ... the same without page-locked staging
#   bash benchmarks/gpu_session.sh gsplat    # ... gsplat (CUDA) on the same scenes (JIT build first)
#   bash benchmarks/gpu_session.sh warp      # ... benchmarks/warp.py --quick
#   bash benchmarks/gpu_session.sh train     # ... training throughput, SPIn-NeRF at 504x284
#   bash benchmarks/gpu_session.sh split     # ... where one rasterizer fwd+bwd's time goes
#   bash benchmarks/gpu_session.sh demo      # ... a small end-to-end `coin-cl run` on the GPU
#   bash benchmarks/gpu_session.sh session   # ... all of the above in one call of at most ~9 minutes
# Several steps may follow each other in one call: `... check suite`. Every step's log goes to
# $LOG/<step>.log ($OUT unless set; `session` packs its logs into $OUT/logs.tgz after every step,
# since the device tool brings back at most 8 files). The GPU machine has no network: everything it
# lacks (pyopencl and its needs, plyfile, gsplat) travels as wheels in .whl/, the data in .gpudata/.
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-/tmp/coin-cl-gpu-out}
LOG=${LOG:-$OUT}
mkdir -p "$OUT" "$LOG"
export PYTHONUNBUFFERED=1 OMP_WAIT_POLICY=PASSIVE

# The wheels the GPU machine lacks (its package list: the device tool's KINDS.md), pinned to the
# versions this project's CPU environment runs (pyopencl's needs included).
WHEELS="pyopencl==2026.1.4 pytools==2026.1.1 platformdirs==4.14.7 siphash24==1.9 plyfile==1.1.5 gsplat==1.5.3"
PLATFORMS="--platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64
  --platform manylinux2014_x86_64 --platform manylinux1_x86_64"

# NVIDIA's OpenCL library wherever the driver mount put it (the usual library folders only: fast).
nvidia_ocl_libs() {
  find -H /usr/lib /usr/lib64 /lib /lib64 /usr/local /opt -name 'libnvidia-opencl.so*' 2>/dev/null | sort -u
}

prepare() {
  local data=${COIN_DATA:-../shared/data}/spinnerf_scene1
  [ -d "$data" ] || { echo "prepare: $data not found; set COIN_DATA"; return 1; }
  local exclude
  exclude="$(git rev-parse --git-common-dir)/info/exclude"
  mkdir -p "$(dirname "$exclude")"
  for d in /.whl/ /.gpudata/; do grep -qx "$d" "$exclude" 2>/dev/null || echo "$d" >>"$exclude"; done
  # shellcheck disable=SC2086
  python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    $PLATFORMS -d .whl $WHEELS || return 1
  # raster.py and warp.py read the SfM cloud and the poses; train.py a half-size scene without the
  # inpainting priors (14 MB instead of 105: the device tool carries 64 MiB at most).
  mkdir -p .gpudata/spinnerf_scene1/sparse
  cp -r "$data/sparse/0" .gpudata/spinnerf_scene1/sparse/
  cp "$data/poses_bounds.npy" .gpudata/spinnerf_scene1/
  rm -rf .gpudata/scene_half
  python3 -c "
from coin_cl.scene import save_scene
from coin_cl.scene.loader import load_scene
save_scene(load_scene('$data', resolution=0.5, priors=False), '.gpudata/scene_half')" || return 1
  du -sh .whl .gpudata
  echo "prepared: name .whl and .gpudata in the device tool's carry"
}

setup() {
  [ -n "${COIN_GPU_SETUP:-}" ] && return 0
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site \
    .whl/*.whl || { echo "setup: wheel install failed (was .whl carried?)"; return 1; }
  export PYTHONPATH=/tmp/site:$PWD COIN_DATA=$PWD/.gpudata COIN_GPU_SETUP=1
  # NVIDIA's OpenCL library must be named by an .icd file the loader reads; the driver mount may
  # hold the library without the file, so one is written in a folder of ours when none names it.
  if ! grep -qs nvidia /etc/OpenCL/vendors/*.icd; then
    local lib
    lib=$(nvidia_ocl_libs | head -n 1)
    if [ -z "$lib" ]; then
      echo "setup: NO NVIDIA OpenCL library (libnvidia-opencl.so*) on this machine;" \
        "/etc/OpenCL/vendors holds: $(ls /etc/OpenCL/vendors 2>&1)"
      return 3
    fi
    mkdir -p /tmp/coin-cl-icd
    echo "$lib" >/tmp/coin-cl-icd/nvidia.icd
    export OCL_ICD_VENDORS=/tmp/coin-cl-icd
    echo "setup: no system ICD file names NVIDIA's library; using $lib via OCL_ICD_VENDORS"
  fi
  export COIN_CL_DEVICE=${COIN_CL_DEVICE:-nvidia}
}

check() {
  nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv
  echo "== /etc/OpenCL/vendors"; ls -l /etc/OpenCL/vendors 2>&1; cat /etc/OpenCL/vendors/*.icd 2>&1
  echo "== NVIDIA OpenCL libraries"
  nvidia_ocl_libs
  echo "== OpenCL devices (rank: the default order; limits the kernels depend on)"
  python3 - <<'EOF'
from coin_cl.engine import devices
from coin_cl.engine.limits import query_limits
from coin_cl.engine.runtime import get_runtime

for p, d in devices.all_devices():
    pr = devices.probe_device(d)
    print(f"{devices.device_label(d)} | {d.version} | driver {d.driver_version} | rank {devices.default_rank(d)}"
          f" | probe {'ok' if pr.ok else 'FAILS: ' + pr.message} | host-unified {devices.host_unified(d)}"
          f" | {query_limits(d)} | float atomics {devices.probe_float_atomics(d)}"
          f" | CAS add {devices.probe_cas_atomics(d)}")
rt = get_runtime()
print(f"chosen: {rt.name}; discrete memory path: {rt.discrete}")
EOF
}

suite() {
  python3 -m pytest -q -p no:cacheprovider -m kernel tests/test_ops.py tests/test_rendering.py \
    tests/test_warp.py tests/test_decode.py tests/test_ssim.py tests/test_runtime.py tests/test_limits.py \
    tests/test_devices.py tests/test_transfers.py
}

# What the driver answers about each kernel the engine launches with a work-group size (the
# narrowing rule of Runtime._fit_local once read CL_KERNEL_LOCAL_MEM_SIZE / COMPILE_WORK_GROUP_SIZE).
kernel_info() {
  python3 - <<'EOF'
import pyopencl as cl
from coin_cl.engine.runtime import get_runtime

rt = get_runtime()
info = cl.kernel_work_group_info
for f, k, d in [("bin.cl", "bin_rects", None), ("project.cl", "project_fwd", None),
                ("project.cl", "project_bwd", None), ("reduce.cl", "reduce_grads", {"NUM_CHANNELS": 3}),
                ("rasterize_gpu.cl", "rasterize_fwd", {"NUM_CHANNELS": 3, "GROUP": 256})]:
    try:
        kern = rt.kernel(f, k, d)
        vals = {n: kern.get_work_group_info(getattr(info, n), rt.device) for n in
                ("WORK_GROUP_SIZE", "LOCAL_MEM_SIZE", "COMPILE_WORK_GROUP_SIZE", "PRIVATE_MEM_SIZE",
                 "PREFERRED_WORK_GROUP_SIZE_MULTIPLE")}
        print(f, k, vals)
    except Exception as e:  # a name or define this sketch got wrong: say so, go on
        print(f, k, "ERROR", type(e).__name__, str(e)[:200])
EOF
}

# shellcheck disable=SC2086
raster() { (cd benchmarks && python3 raster.py --device "$COIN_CL_DEVICE" ${RASTER_ARGS:-}); }

# The same without the page-locked staging (COIN_CL_PINNED=0): copies straight from torch's memory.
raster_direct() { COIN_CL_PINNED=0 RASTER_ARGS="--quick --scenes 100k,500k,1M-1080p --runs 5" raster; }

# The whole program on the GPU, once, small: the package installed as a user gets it (the
# coin_cl.diffusion and coin_cl.kernels mappings of setup.cfg, the `coin-cl` entry point), then
# `coin-cl run` on the half-size scene of `prepare` at half its size (252x142; a COLMAP-free
# scene, since pycolmap's 38 MB wheel does not fit the device tool's carry) with 30 steps per
# stage and stage 1's `--inpainter telea` (the machine's OpenCV lacks the contrib module whose FSR
# the embedded inpainter's structure pass uses); its log and report come back.
demo() {
  python3 -m pip install -q --no-deps --no-build-isolation --no-index --target /tmp/coin-site . ||
    { echo "demo: the package did not install"; return 1; }
  local t=$SECONDS
  # shellcheck disable=SC2086
  PYTHONPATH=/tmp/coin-site:$PYTHONPATH /tmp/coin-site/bin/coin-cl run "$COIN_DATA/scene_half" \
    --out /tmp/coin-cl-e2e --device "$COIN_CL_DEVICE" ${DEMO_ARGS:---iters 30 --resolution 0.5 --inpainter telea}
  local rc=$?
  echo "demo: exit $rc after $((SECONDS - t)) s"
  for f in log.json report.md eval/metrics.json; do
    [ -f "/tmp/coin-cl-e2e/$f" ] && cp "/tmp/coin-cl-e2e/$f" "$LOG/e2e_${f//\//_}"
  done
  return $rc
}

gsplat() {
  # gsplat's wheel compiles its CUDA code at its first call, the benchmark's first warm-up (minutes on
  # 16 cores; built for Hopper only, the card here).
  export TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0} MAX_JOBS=${MAX_JOBS:-16}
  # shellcheck disable=SC2086
  (cd benchmarks && python3 raster_gsplat.py ${GSPLAT_ARGS:-})
}

warp() { (cd benchmarks && python3 warp.py --quick); }

split() { (cd benchmarks && python3 raster.py --device "$COIN_CL_DEVICE" --split --scenes 100k,500k,1M-1080p --runs 3); }

train() {
  (cd benchmarks && python3 train.py --throughput --data "$COIN_DATA/scene_half" --resolution 1.0 \
    --steps "${STEPS:-50}" --warmup 5 --models scaffold,3dgs --paths new --out /tmp/coin-cl-train) &&
    cp /tmp/coin-cl-train/throughput.json "$LOG/train.json"
}

gsplat_build() {
  # Only the JIT build of gsplat's CUDA code (-O3, as its users get it), so that `session` can run it
  # beside the kernel suite and time gsplat afterwards on a quiet machine.
  export TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0} MAX_JOBS=${MAX_JOBS:-16}
  python3 -c "import time; t = time.time(); from gsplat.cuda._backend import _C; assert _C is not None, 'no CUDA toolkit'; print(f'gsplat built in {time.time() - t:.0f} s')"
}

# One device call of the whole GPU part, for a session lent ~15 minutes of device time in all:
# the build of gsplat runs in the background (14 of the 16 cores) beside `check` and the kernel
# suite (correctness only: no timing then); the timed steps run after the build has ended or been
# given up, each under a cap, and the logs are packed into $OUT/logs.tgz after every step, so a
# call cut short still brings back what it did. Caps in seconds: SUITE_S, RASTER_S, WARP_S,
# TRAIN_S, BUILD_S, GSPLAT_S, SPLIT_S, DEMO_S.
session() {
  local t0=$SECONDS
  export LOG=/tmp/coin-cl-gpu-logs
  mkdir -p "$LOG"
  pack() { tar czf "$OUT/logs.tgz" -C "$LOG" . 2>/dev/null; }
  MAX_JOBS=${MAX_JOBS:-14} timeout "${BUILD_S:-270}" bash "$0" gsplat_build >/dev/null 2>&1 &
  local build=$!
  if [ -n "${NO_OPENCL:-}" ]; then
    # No NVIDIA OpenCL here (setup said why): the CUDA peer alone, against the card's limits.
    wait "$build"; echo "== build exit $?: $(tail -n 1 "$LOG/gsplat_build.log")"
    GSPLAT_ARGS="--scenes 10k,100k,500k --runs 5 --no-compare" timeout "${GSPLAT_S:-60}" bash "$0" gsplat \
      >/dev/null 2>&1
    echo "== gsplat exit $? (+$((SECONDS - t0)) s)"
    pack
    return
  fi
  for step in check suite; do
    echo "== $step (+$((SECONDS - t0)) s)"
    timeout "${SUITE_S:-200}" bash "$0" "$step" >/dev/null 2>&1
    echo "   exit $?; tail: $(tail -n 1 "$LOG/$step.log")"
    pack
  done
  echo "== waiting for the gsplat build (+$((SECONDS - t0)) s)"
  wait "$build"; echo "   build exit $? (124: not done in ${BUILD_S:-270} s): $(tail -n 1 "$LOG/gsplat_build.log")"
  local scenes=100k,500k,1M,500k-1080p,1M-1080p
  RASTER_ARGS=${RASTER_ARGS:---scenes $scenes --runs 5} timeout "${RASTER_S:-150}" bash "$0" raster >/dev/null 2>&1
  echo "== raster exit $? (+$((SECONDS - t0)) s)"; pack
  timeout "${RASTER_S:-150}" bash "$0" raster_direct >/dev/null 2>&1
  echo "== raster_direct exit $? (+$((SECONDS - t0)) s)"; pack
  GSPLAT_ARGS=${GSPLAT_ARGS:---scenes $scenes --runs 5} timeout "${GSPLAT_S:-90}" bash "$0" gsplat >/dev/null 2>&1
  echo "== gsplat exit $? (+$((SECONDS - t0)) s)"; pack
  timeout "${SPLIT_S:-60}" bash "$0" split >/dev/null 2>&1; echo "== split exit $? (+$((SECONDS - t0)) s)"; pack
  timeout "${WARP_S:-40}" bash "$0" warp >/dev/null 2>&1; echo "== warp exit $? (+$((SECONDS - t0)) s)"; pack
  STEPS=${STEPS:-20} timeout "${TRAIN_S:-90}" bash "$0" train >/dev/null 2>&1
  echo "== train exit $? (+$((SECONDS - t0)) s)"; pack
  timeout "${DEMO_S:-120}" bash "$0" demo >/dev/null 2>&1; echo "== demo exit $? (+$((SECONDS - t0)) s)"; pack
}

[ $# -ge 1 ] || { sed -n 2,12p "$0"; exit 2; }
status=0
for step in "$@"; do
  case "$step" in
  prepare) prepare 2>&1 | tee "$OUT/prepare.log" || status=1 ;;
  session)
    setup
    case $? in 0) ;; 3) export NO_OPENCL=1 ;; *) exit 1 ;; esac
    session
    ;;
  check | suite | raster | raster_direct | gsplat | gsplat_build | warp | train | kernel_info | split | demo)
    setup || exit $?
    echo "== $step ($(date -u +%H:%M:%S))"
    "$step" 2>&1 | tee "$LOG/$step.log" || status=1
    ;;
  *) echo "unknown step $step"; exit 2 ;;
  esac
done
exit $status
