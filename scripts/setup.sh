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

python3 -m pip install -q -e ".[diffusers,viewer,ray,test]"

if [ -f tools/js/package.json ] && [ ! -d tools/js/node_modules ]; then
  (cd tools/js && npm install --silent --no-audit --no-fund >/dev/null)
fi
