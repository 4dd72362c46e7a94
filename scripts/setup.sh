#!/usr/bin/env bash
# One-time set-up on a fresh Debian machine (idempotent; re-runs are fast).
# System packages: Mesa's EGL for headless OpenGL rendering, Chromium for the browser tests,
# Node for the glTF validator and three.js check. Python: this package with every extra.
set -euo pipefail
cd "$(dirname "$0")/.."

APT_PACKAGES="libegl1 libgl1-mesa-dri libegl-mesa0 libgles2 chromium chromium-driver"
missing=""
for p in $APT_PACKAGES; do dpkg -s "$p" >/dev/null 2>&1 || missing="$missing $p"; done
if [ -n "$missing" ]; then
  SUDO=""; [ "$(id -u)" = 0 ] || SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends $missing >/dev/null
fi

python3 -m pip install -q -e ".[diffusers,viewer,ray,usd,test]"

# MediaPipe face mesh for `t2bs retarget`: 0.10.21 is the last wheel with the face-mesh model inside,
# and it needs numpy<2, so it lives in its own venv (t2bs calls it in a subprocess). --no-deps + the
# imports it really uses keeps it to ~400 MB (its full requirements pull jax and opencv-contrib).
MP_VENV="${T2BS_MEDIAPIPE_VENV:-$HOME/.cache/t2bs/mediapipe-venv}"
if [ ! -x "$MP_VENV/bin/python" ] || ! "$MP_VENV/bin/python" -c "import mediapipe" >/dev/null 2>&1; then
  python3 -m venv "$MP_VENV"
  "$MP_VENV/bin/pip" install -q --no-deps "mediapipe==0.10.21"
  "$MP_VENV/bin/pip" install -q "numpy<2" "protobuf>=4.25.3,<5" absl-py attrs flatbuffers opencv-python-headless matplotlib
fi

if [ -f tools/js/package.json ] && [ ! -d tools/js/node_modules ]; then
  (cd tools/js && npm install --silent --no-audit --no-fund >/dev/null)
fi
