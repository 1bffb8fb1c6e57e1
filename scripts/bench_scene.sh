#!/usr/bin/env bash
# The learned scene `cargo bench --bench trace` renders in `render_reconstruction_16spp`:
# stage 1's reconstruction of the demo dataset (fast preset), in data/bench (or the folder given).
# A learned scene is what stages 2-3 and `evaluate` trace, and it traces slower than surfelized
# meshes (larger, overlapping, less opaque surfels). Each step is skipped when its output exists.
# Cost here: ~5 min generation, ~4 min stage 1.
#
# Usage: bash scripts/bench_scene.sh [out-dir]; then LIGHTFUSE_BENCH_DIR=out-dir cargo bench --bench trace
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:-data/bench}
bash scripts/setup.sh
if [ ! -f "$out/dataset/dataset.json" ]; then
  echo "== generating the demo dataset with Cycles ($out/dataset)"
  .venv/bin/python blender/generate.py --demo --seed 0 --out "$out/dataset" --force --quiet
fi
if [ ! -f "$out/recon/scene.glb" ]; then
  echo "== stage 1 (fast preset) into $out/recon"
  target/release/lightfuse reconstruct "$out/dataset" -o "$out/recon" --resume
fi
echo "bench scene ready: $out/recon/scene.glb"
