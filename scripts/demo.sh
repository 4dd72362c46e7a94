#!/usr/bin/env bash
# Set up (idempotent) and run the main job on the offline default.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
t2bs render "${1:-../shared/assets/turtle.glb}" -o runs/demo
