#!/usr/bin/env bash
# Set up (idempotent) and run the main job on the offline default: text -> blendshape rig with the
# quick preset (procedural character, 3 expression videos, VCDGS on CPU, PCA model, landmarks).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
t2bs create "${1:-a cartoon fox with big ears}" -o "${2:-runs/demo}" --preset quick
