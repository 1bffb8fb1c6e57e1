#!/usr/bin/env bash
# The demo, end to end: set up (scripts/setup.sh), generate the small `demo` dataset with
# Blender's Cycles, check the renderer on an oracle scene (the dataset's meshes surfelized with
# their true poses and environments, rendered and compared with Cycles), then `lightfuse run`:
# stages 1-3 and the evaluation (data/demo/recon/eval/), and the relightable scene edited into
# the test layout under a new environment. Outputs go to data/demo/ (ignored by git).
# Re-running reuses the dataset (--fresh regenerates it) and lightfuse run's up-to-date stages.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
out=data/demo
lf=target/release/lightfuse
if [ "${1:-}" = "--fresh" ] || [ ! -f "$out/dataset/dataset.json" ]; then
  echo "== generating the demo dataset with Cycles ($out/dataset)"
  start=$(date +%s)
  .venv/bin/python blender/generate.py --demo --seed 0 --out "$out/dataset" --force
  echo "   generated in $(( $(date +%s) - start )) s"
fi
echo "== exporting the reference state as a glTF mesh scene"
.venv/bin/python blender/export_mesh_scene.py --dataset "$out/dataset" --out "$out/mesh_scene.glb"
echo "== surfelizing (oracle scene: every state with its ground-truth poses and environment)"
"$lf" surfelize "$out/mesh_scene.glb" -o "$out/scene.glb" --spacing 0.005 --dataset "$out/dataset" --env-size 256x128
"$lf" info "$out/scene.glb"
echo "== converting"
"$lf" convert "$out/scene.glb" "$out/scene.usda"
"$lf" convert "$out/scene.glb" "$out/scene.ply"
echo "== rendering state0's cameras with LightFuse's one-bounce path tracer"
"$lf" render "$out/scene.glb" --state state0 --cameras "$out/dataset" --spp 32 --out "$out/render/state0"
echo "== against the dataset's Cycles images (full bounces, full-resolution environment)"
.venv/bin/python blender/compare_renders.py --ref "$out/dataset/state0" --test "$out/render/state0" || true
echo "== stages 1-3 and the evaluation (lightfuse run, fast preset): reconstruct, refine for ray tracing, invert materials and environments, relight the test arrangement"
"$lf" run "$out/dataset" -o "$out/recon"
python3 - "$out/dataset/dataset.json" "$out/test_layout.json" <<'PY'
import json, sys
d = json.load(open(sys.argv[1]))
test = next(s for s in d["states"] if s["split"] == "test")
json.dump({"format": "lightfuse-layout/1", "objects": test["object_poses"]}, open(sys.argv[2], "w"), indent=1)
PY
test_state=$(python3 -c 'import json,sys; print(next(s["name"] for s in json.load(open(sys.argv[1]))["states"] if s["split"] == "test"))' "$out/dataset/dataset.json")
echo "== the relightable scene edited: the test layout, under an environment no training state had"
test_env=$(python3 -c 'import json,sys; print(next(s for s in json.load(open(sys.argv[1]))["states"] if s["split"] == "test")["relight"][0]["environment"])' "$out/dataset/dataset.json")
"$lf" edit "$out/recon/relightable.glb" -o "$out/recon/relit.glb" --name relit --layout "$out/test_layout.json" --env "$out/dataset/$test_env"
echo "   render it: $lf render $out/recon/relit.glb --state relit --cameras $out/dataset --frames $test_state --spp 32 --out $out/recon/relit"
echo "done: $out/recon/scene.glb (reconstruction; report.json beside it), $out/recon/refined.glb (refined for ray tracing; refine/report.json), $out/recon/relightable.glb (materials and recovered environments; invert/report.json), $out/recon/eval/ (eval.md: the relighting tables; images/: Cycles | LightFuse | Baked | No re-tracing | error per view), $out/recon/relit.glb (the test layout under a new environment)"
echo "done: $out/scene.glb (open in any KHR_gaussian_splatting viewer), $out/scene.usda, $out/scene.ply"
