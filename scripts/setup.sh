#!/usr/bin/env bash
# Installs everything LightFuse needs, idempotently: the Python venv with pinned bpy (Blender
# as a module, Cycles on the CPU), usd-core and pyoidn (whose Open Image Denoise library the
# `denoise` feature links), the release build with that feature, and the pinned npm tools
# (Khronos glTF-Validator, Babylon.js loaders) that the tests check our files with.
set -euo pipefail
cd "$(dirname "$0")/.."
say() { [ "${QUIET:-0}" = 1 ] || echo "setup: $*" >&2; }

# Python: one venv, pinned requirements; re-installed only when requirements change.
PY=${PYTHON:-python3}
req=blender/requirements.txt
stamp=.venv/.requirements.sha256
want=$(sha256sum "$req" | cut -d' ' -f1)
if [ ! -x .venv/bin/python ] || [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  say "creating .venv (bpy, usd-core, pytest) from $req"
  "$PY" -m venv .venv
  .venv/bin/python -m pip install --quiet --disable-pip-version-check --upgrade pip
  .venv/bin/python -m pip install --quiet --disable-pip-version-check -r "$req"
  echo "$want" > "$stamp"
fi

# Open Image Denoise from the venv's pyoidn wheel (lib/libOpenImageDenoise.so*): the oidn
# crate links it from $OIDN_DIR/lib and build.rs embeds that directory as the rpath.
source scripts/oidn_env.sh
say "building lightfuse (release, --features denoise)"
cargo build --release --locked --bins --features denoise ${QUIET:+--quiet}

# npm tools, from the lock file.
lock_want=$(sha256sum tools/package-lock.json | cut -d' ' -f1)
if [ ! -d tools/node_modules ] || [ "$(cat tools/node_modules/.lock.sha256 2>/dev/null)" != "$lock_want" ]; then
  say "installing npm tools (gltf-validator, babylon.js loaders)"
  (cd tools && npm ci --no-audit --no-fund --loglevel=error)
  echo "$lock_want" > tools/node_modules/.lock.sha256
fi
say "ready"
