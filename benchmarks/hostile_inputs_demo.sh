#!/usr/bin/env bash
# The five worst cases of issue 39, reproduced against one t2bs source tree.
#   bash benchmarks/hostile_inputs_demo.sh SRC WORK
# SRC: the t2bs src/ folder to test (e.g. /work/main/src for "before", ./src for "after");
# WORK: an empty scratch folder. Each case prints one line starting with "case N:".
# Case 1 runs a pickled `touch WORK/pwned-*` if the checkpoint loader executes project files.
set -u
SRC=$(realpath "$1"); WORK=$(realpath -m "$2")
mkdir -p "$WORK"
export PYTHONPATH="$SRC" OMP_NUM_THREADS=1
t2bs() { python3 -m t2bs.cli "$@"; }
P="$WORK/proj"
rm -rf "$P" "$WORK"/pwned-* "$WORK/gen.py"
t2bs character "a cartoon fox" -o "$P" --size 32 >/dev/null 2>&1
VID=(--prompts smiling --samples 1 --size 32 --views 3)
t2bs videos "$P" "${VID[@]}" --frames 3 >/dev/null 2>&1

# 1. A pickled os.system call in recon/.checkpoints/ (named by the job key, so a resume loads it).
REC=(--iterations 4 --control-points 8 --set resolution=32 --set static_iters=2 --set perceptual=none
     --track-weight 0 --no-hidden-pick --no-preview)
python3 - "$P" "$WORK/pwned-checkpoint" <<'EOF'
import os, sys, torch
from pathlib import Path
from t2bs.project import Project
from t2bs.recon.stage import recon_job
from t2bs.recon.config import preset
cfg = preset("quick", iterations=4, global_iters=0, num_control_points=8, resolution=32, static_iters=2,
             perceptual="none", track_weight=0.0, hidden_pick=False, method="full", device="auto", seed=0)
project = Project(sys.argv[1])
grid = project.path("videos", "smiling-s0")
key = recon_job(project, grid, cfg).key
class Payload:
    def __reduce__(self):
        return (os.system, (f"touch {sys.argv[2]}",))
ckpt = project.path("recon", ".checkpoints", f"smiling-s0-{key}.pt")
ckpt.parent.mkdir(parents=True, exist_ok=True)
torch.save({"key": key, "step": 1, "model": Payload()}, ckpt)
EOF
t2bs reconstruct "$P" "${REC[@]}" > "$WORK/case1.log" 2>&1
echo "case 1: rc=$? pickle executed: $([ -e "$WORK/pwned-checkpoint" ] && echo YES || echo no)" \
     "| $(grep -m1 -o 'warning: .*discarded.*' "$WORK/case1.log" | cut -c1-120)"

# 2. A --command template that quotes {prompt} itself, and a prompt with $(...) in it.
cat > "$WORK/gen.py" <<'EOF'
import sys
open(sys.argv[1] + "/m.obj", "w").write("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")
EOF
t2bs character "a fox \$(touch $WORK/pwned-template)" -o "$WORK/cmd" --size 16 --backend command \
    --command "python3 $WORK/gen.py {out} '{prompt}'" >/dev/null 2>&1
echo "case 2: rc=$? prompt executed: $([ -e "$WORK/pwned-template" ] && echo YES || echo no)"

# 3. A videos re-run (other settings) killed with -9 while it writes the new grid, then the old settings again.
python3 -m t2bs.cli videos "$P" "${VID[@]}" --frames 40 --size 96 >/dev/null 2>&1 &  # not the function: $! is python
RUN=$!
for _ in $(seq 3000); do  # until it writes frames (in place before, in a staging folder after)
  [ -e "$P/videos/smiling-s0/frames/view00/0005.png" ] && break
  compgen -G "$P/videos/smiling-s0/.t2bs-staging-*/frames/view00/0000.png" >/dev/null && break
  sleep 0.02
done
KEY=$(grep -o '"key": "[0-9a-f]*"' "$P/videos/smiling-s0/done.json")
kill -9 $RUN; wait $RUN 2>/dev/null
echo "case 3: killed; the grid folder now holds $(ls "$P/videos/smiling-s0/frames/view00" | wc -l) view-0 frames," \
     "grid.json: $([ -e "$P/videos/smiling-s0/grid.json" ] && echo yes || echo MISSING)," \
     "done.json: $([ "$(grep -o '"key": "[0-9a-f]*"' "$P/videos/smiling-s0/done.json" 2>/dev/null)" = "$KEY" ] && echo 'the old one' || echo 'gone or new')"
OUT=$(t2bs videos "$P" "${VID[@]}" --frames 3 2>&1 | tail -1)
REC3=$(t2bs reconstruct "$P" --iterations 1 --set static_iters=1 --set resolution=16 --no-preview 2>&1 | grep -oE "error: .*|Traceback.*|reconstruct: [0-9]+ reconstructed" | head -1)
echo "case 3: then the old settings again: ${OUT:0:45} | reconstruct: ${REC3:0:90}"

# 4. A NaN in blendshapes/model.npz with a previous retargeting result in place.
t2bs blendshapes "$P" --source gt --force >/dev/null 2>&1
mkdir -p "$P/retarget/drv"
printf 'frame,time,s0\n0,0.0000,0.100000\n' > "$P/retarget/drv/weights.csv"
echo '{"frames": 1}' > "$P/retarget/drv/report.json"
cp "$P/blendshapes/model.glb" "$P/retarget/drv/animation.glb"; echo preview > "$P/retarget/drv/preview.mp4"
BEFORE=$(cat "$P"/retarget/drv/* | md5sum)
python3 - "$P/blendshapes/model.npz" <<'EOF'
import sys, numpy as np
z = dict(np.load(sys.argv[1])); z["basis"] = z["basis"].copy(); z["basis"][0, 0, 0] = np.nan; np.savez(sys.argv[1], **z)
EOF
python3 - "$WORK/drv.mp4" "$(dirname "$SRC")/../shared/assets/facecap.glb" <<'EOF' 2>/dev/null
import sys, imageio.v2 as imageio
from t2bs.eval.bench_retarget import driver_weights, render_driver
from pathlib import Path
video = render_driver(driver_weights(8), 192, asset=Path(sys.argv[2]))  # a face MediaPipe finds (shared asset)
imageio.mimwrite(sys.argv[1], list(video), fps=8, macro_block_size=1)
EOF
t2bs retarget "$P" --driver "$WORK/drv.mp4" -o "$P/retarget/drv" > "$WORK/case4.log" 2>&1
RC=$?
ERR=$(grep -m1 -E "error|Traceback|Error" "$WORK/case4.log")
echo "case 4: rc=$RC weights.csv has NaN: $(grep -qi nan "$P/retarget/drv/weights.csv" && echo YES || echo no) old outputs intact: $([ "$(cat "$P"/retarget/drv/* | md5sum)" = "$BEFORE" ] && echo yes || echo NO) | ${ERR:0:110}"

# 5. The viewer on an address this machine cannot bind (timeout 20 s stands in for "forever").
S=$(date +%s.%N)
timeout -s KILL 20 python3 -m t2bs.cli view "$P" --host 10.255.255.1 > "$WORK/case5.log" 2>&1
RC=$?
ERR=$(grep -m1 -E "error|Error|warning" "$WORK/case5.log")
echo "case 5: rc=$RC after $(python3 -c "print(round($(date +%s.%N) - $S, 1))") s | ${ERR:0:110}"
