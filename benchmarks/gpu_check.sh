#!/usr/bin/env bash
# The GPU measurements of the VCDGS speed work (issue 36), made in one call of a lent GPU machine
# (device tool: `run` with carry [".whl", ".gl", ".carry"] and timeout_s 600). The whole script keeps to
# $BUDGET seconds (default 540): each step gets at most what is left, the most wanted measurement first.
#
# Needs, beside the checkout (ignored folders carried to the machine):
#   .whl/          the Python wheels the machine lacks (roma, pytorch-msssim, pygltflib + deps, trimesh, moderngl,
#                  glcontext, gsplat 1.5.3 source wheel: built just in time for the GPU)
#   .gl/           Debian's libegl1/libgl1/libglvnd0/... (headless OpenGL for the mesh renderer)
#   .carry/assets/ facecap.glb (the shared asset)
# made here, in the repository root, in ~1 minute (session 21's commands; the machine has torch 2.11, numpy, scipy,
# opencv, imageio, typer, rich, tqdm, pillow, jaxtyping and ninja already):
#   printf '/.whl/\n/.gl/\n/.carry/\n' >> .git/info/exclude
#   python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
#     --platform manylinux_2_28_x86_64 --platform manylinux2014_x86_64 --platform manylinux1_x86_64 -d .whl \
#     roma pytorch-msssim pygltflib dataclasses-json deprecated 'marshmallow<4' trimesh moderngl glcontext gsplat==1.5.3
#   mkdir -p .gl /tmp/amd64/partial; o='-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/amd64'
#   apt-get $o update; (cd .gl && apt-get $o download libvulkan1 libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2)
#   mkdir -p .carry/assets && cp ../shared/assets/facecap.glb .carry/assets/
# and writes JSON and logs ($OUT/logs.txt) to $OUT. Results: docs/BENCHMARKS.md.
set -u
OUT=${OUT:-/tmp/gpu_check}
BUDGET=${BUDGET:-540}
END=$(( $(date +%s) + BUDGET ))
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD/src
for f in .gl/*.deb; do dpkg -x "$f" /; done
ldconfig
nv=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
[ -f $nv ] && export __EGL_VENDOR_LIBRARY_FILENAMES=$nv
export T2BS_SHARED_ASSETS=$PWD/.carry/assets
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee "$OUT/gpu.txt"
python3 -c "import torch; print('torch', torch.__version__)" | tee -a "$OUT/gpu.txt"

step() {  # name, most seconds, command...: runs under min(most, what is left), its log appended to $OUT/logs.txt
  local name=$1 most=$2; shift 2
  local left=$(( END - $(date +%s) ))
  local limit=$(( most < left ? most : left ))
  if [ "$limit" -lt 20 ]; then echo "== $name skipped: ${left} s left" | tee -a "$OUT/summary.txt"; return 1; fi
  local t0=$(date +%s)
  local log=/tmp/gpu_check_logs/$name.log  # all logs end in one file: the device tool returns at most 8 files
  mkdir -p /tmp/gpu_check_logs
  timeout "$limit" "$@" >"$log" 2>&1
  local rc=$?
  echo "== $name rc=$rc $(( $(date +%s) - t0 )) s (limit $limit)" | tee -a "$OUT/summary.txt"
  { echo "===== $name"; cat "$log"; } >>"$OUT/logs.txt"
  grep -E "^(quick|paper) |passed|failed|rows|full|error|Error" "$log" | grep -v Warning | tail -6
  return $rc
}

# gsplat compiles its CUDA kernels on first use; the mesh renderer must find EGL.
step setup 150 python3 -c "
from gsplat.cuda._backend import _C
print('gsplat kernels', _C is not None)
from t2bs.render.mesh_renderer import MeshRenderer
with MeshRenderer() as r: print('GL', r.ctx.info['GL_RENDERER'])
" || { tail -20 /tmp/gpu_check_logs/setup.log; exit 1; }
tail -2 /tmp/gpu_check_logs/setup.log

# What two calls on an H100 taught (2026-11-26, session 12; docs/BENCHMARKS.md): gsplat's kernels build in 73-89 s;
# a cold torch.compile of the step there takes minutes (the quick preset compiled did not finish in 111 s, nor in
# the ~150 s it had after a concurrent build), and the paper preset at 1000 eager steps needs more than 104 s with
# its 512 px grid, tracks and static fit. Two processes must not build gsplat at once (they share its build folder:
# both failed). So: one run at a time, generous limits, progress bars in the log (--progress) to see where a run
# that was cut off stood.
CASE=(--asset facecap --defects clean --time-budget 0 --progress)
PAPER=(--preset paper --size 512 --iterations "${PAPER_STEPS:-2000}")

# What the fourth lease measured (2026-11-27, session 16, H100; docs/BENCHMARKS.md): the paper preset's joint step
# runs at ~48 ms eager and ~21 ms with compile=true in a real run; before training a paper run spends ~90 s (grid at
# 512 px, tracks, the static fit), and compiling the step ~2.5 min; neither run at 2000 steps finished inside 200 s
# (eager) or 257 s (compiled), so no row came back. So now: the compiled paper preset alone, one process per case,
# each row written to its JSON as it finishes; later runs compile from inductor's warm on-disk cache. No expression
# basis (MediaPipe is absent there); the CPU rows to compare with are run with the same --set expression_shapes=.
# The fifth lease (2026-11-27, session 21, H100) ran both cases in one process: the compiled step then
# trained nothing (torch 2.11's guards missed the networks' requires_grad flip at the joint stage; reproduced and fixed
# on the CPU with torch 2.11), after 125 s of compiling, 43 s of recompiling at the joint stage and 23 ms a joint step.
# The fixed step is two graphs instead of 16 (the rasterizer between them). The same flip is the likeliest reason why
# the CUDA-graph step of the second lease trained nothing, so the graphs get a second chance here, through inductor's
# own switch (TORCHINDUCTOR_CUDAGRAPHS=1), no library option: a run that trains nothing still stops with an error.
# The sixth lease (2026-11-28, session 28, H200) runs this script detached (setsid), so that it goes on between the
# device tool's calls (each call only waits and copies $OUT back); the CUDA tests of today's code run beside the
# first measurement's set-up (their log: $OUT/tests.txt).
step cuda_tests 200 python3 -m pytest -q -p no:cacheprovider tests/test_recon.py tests/test_splat.py \
  -k "cuda or gsplat" -rs >"$OUT/tests.txt" 2>&1 &
TESTS=$!
# 1. The paper preset end to end with `compile=true` (512 px grid, 2000 control points, the 2000-step static fit,
# tracks, hidden-part pick) at $PAPER_STEPS of its 60k steps (the whole schedule, warm-up and decay, in fewer steps),
# mouth wide: does the compiled step train on the GPU (expression error), its measured ms per step
# ("joint_ms_per_step"), seconds per phase, peak GPU memory and the quality.
step paper_compile 400 python3 benchmarks/vcdgs.py "${CASE[@]}" "${PAPER[@]}" \
  --prompts "opening the mouth extremely wide" --methods full,rigid --set compile=true \
  --set expression_shapes= --json "$OUT/paper_compile.json"
wait $TESTS

# 2. Smiling with the two compiled graphs replayed as CUDA graphs (the 10-minutes-a-video target needs ~8 ms steps):
# its step rate beside the compiled one's, and smiling's quality if the graphs train (else the training's own check
# stops the run with an error).
TORCHINDUCTOR_CUDAGRAPHS=1 step paper_cudagraphs_smiling $(( END - $(date +%s) - 5 )) python3 benchmarks/vcdgs.py \
  "${CASE[@]}" "${PAPER[@]}" --prompts smiling --methods full,rigid --set compile=true --set expression_shapes= \
  --json "$OUT/paper_cudagraphs_smiling.json"
nvidia-smi --query-gpu=memory.used --format=csv,noheader >>"$OUT/gpu.txt"
cat "$OUT/summary.txt"
