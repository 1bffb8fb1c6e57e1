"""LightFuse's one-bounce path tracer against Cycles on the very same scene (issue 4, "Show").

The `demo` dataset's scene is exported as a glTF mesh scene (`export_mesh_scene.py`, baked base
colours), surfelized at 5 mm into an oracle scene (`lightfuse surfelize --dataset`), and state0's
eight cameras are rendered by both renderers under the same 256x128 environment (the very map
stored in the oracle scene, written out by `lightfuse convert` to .gltf), Cycles limited to one
indirect bounce (`--max-bounces 1`, as eq. path-estimator).  `compare_renders.py` gives PSNR in
sRGB averaged over views, and over the pixels where both renderers saw only the environment.

Thresholds are the issue's: >= 30 dB over all pixels, >= 45 dB on the background.  Sample counts
keep noise from deciding: Cycles 512 spp against LightFuse 128 spp gives 33.0 dB, Cycles 1024
against LightFuse 256 spp 33.75 dB (measured), so noise costs under 1 dB here.  The 1 cm default
scene reaches only ~28.8 dB: the remaining gap is the surfel discretisation of texture and
silhouette edges, not shading (see the issue note).

A control shows the test can fail: the same environment rotated by 5 degrees about +Y drops the
background agreement far below 45 dB.

The DCC loop (issue 13) runs on the same oracle scene: imported into Blender, two objects moved
by script, the layout exported, relit by LightFuse and rendered by Cycles; see its test.
"""
import json
import os
import subprocess
import sys

import pytest

from bltest import BLENDER_DIR, ok, run_script

from lfstate import COMPONENT_PROP

CYCLES_SPP = 512
LIGHTFUSE_SPP = 128


def compare(ref, test):
    p = subprocess.run([sys.executable, os.path.join(BLENDER_DIR, "compare_renders.py"), "--ref", ref,
                        "--test", test, "--json"], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    return json.loads(p.stdout)


@pytest.fixture(scope="module")
def oracle(tmp_path_factory):
    """The demo dataset, its oracle scene at 5 mm and state0's environment as the scene stores it."""
    root = tmp_path_factory.mktemp("vs_cycles")
    ds = root / "demo"
    run_script("generate.py", "--demo", "--seed", "0", "--out", ds)
    mesh = root / "mesh_scene.glb"
    run_script("export_mesh_scene.py", "--dataset", ds, "--out", mesh)
    scene = root / "scene.glb"
    ok("surfelize", mesh, "-o", scene, "--spacing", "0.005", "--dataset", ds, "--env-size", "256x128")
    ok("convert", scene, root / "scene.gltf")
    env_dir = root / "scene.env"
    env = next(env_dir / n for n in sorted(os.listdir(env_dir)) if n.endswith("_state0.exr"))
    return {"root": root, "dataset": ds, "scene": scene, "env": env}


def test_one_bounce_render_matches_cycles(oracle):
    root, ds = oracle["root"], oracle["dataset"]
    cy, ours = root / "cycles", root / "lightfuse"
    run_script("render_layout.py", "--dataset", ds, "--state", "state0", "--env", oracle["env"],
               "--spp", CYCLES_SPP, "--max-bounces", "1", "--no-denoise", "--rgb-only", "--quiet", "--out", cy)
    ok("render", oracle["scene"], "--state", "state0", "--cameras", ds, "--spp", LIGHTFUSE_SPP,
       "--out", ours)
    r = compare(cy, ours)
    print(f"LightFuse vs Cycles, state0, 8 views: {r['psnr_all']:.2f} dB, background {r['psnr_background']:.2f} dB")
    assert len(r["views"]) == 8
    assert r["psnr_all"] >= 30.0, r
    assert r["psnr_background"] >= 45.0, r

    # Control: a 5 degree turn of the environment must be caught by the background figure.
    turned = root / "turned"
    ok("render", oracle["scene"], "--state", "state0", "--cameras", ds, "--spp", "4",
       "--env", oracle["env"], "--env-rotation", "5", "--out", turned)
    assert compare(cy, turned)["psnr_background"] < 40.0


MOVE_TWO_OBJECTS = f'''
import math, sys
import bpy
bpy.ops.wm.open_mainfile(filepath=sys.argv[1])
objs = sorted((o for o in bpy.data.objects if o.get({COMPONENT_PROP!r}) not in (None, "background")),
              key=lambda o: o[{COMPONENT_PROP!r}])
assert len(objs) >= 2, [o.name for o in bpy.data.objects]
# As a person would in the viewport: slide one object across the floor (Blender Z up) and turn
# it; lift the other a little, turn it and slide it the other way.
a, b = objs[0], objs[1]
a.location.x += 0.12; a.location.y -= 0.08; a.rotation_euler.z += math.radians(35)
b.location.x -= 0.10; b.location.y += 0.06; b.rotation_euler.z -= math.radians(60)
bpy.ops.wm.save_as_mainfile(filepath=sys.argv[2])
print(a[{COMPONENT_PROP!r}], b[{COMPONENT_PROP!r}])
'''


def test_dcc_loop_blender_edit_relit_by_lightfuse_matches_cycles(oracle, tmp_path):
    """The DCC loop (issue 13): the relightable oracle scene imported into Blender
    (import_scene.py), two objects moved by script, the layout exported (export_layout.py),
    relit by `lightfuse render --layout`, and the same layout rendered by Cycles on the
    dataset's own scene (render_layout.py), same cameras, same environment, one bounce.

    Measured: 33.04 dB over all pixels, background 85.2 dB (LightFuse 128 spp, Cycles 512 spp;
    the ball and the pot moved), the same as the static comparison above (33.00 dB): the edit
    costs no agreement. Required: >= 30 dB, the static test's bar. Control: LightFuse rendering
    the *unedited* arrangement against Cycles' edited one gives 25.3 dB; required at least 4 dB
    below the edited figure (measured 7.7), so the test sees whether the layout arrived."""
    ds = oracle["dataset"]
    blend, edited = tmp_path / "scene.blend", tmp_path / "edited.blend"
    run_script("import_scene.py", oracle["scene"], "--out", blend)
    script = tmp_path / "move.py"
    script.write_text(MOVE_TWO_OBJECTS)
    p = subprocess.run([sys.executable, script, blend, edited], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-3000:]
    moved = p.stdout.split()[-2:]
    layout = tmp_path / "layout.json"
    run_script("export_layout.py", edited, "--out", layout)
    objects = json.loads(layout.read_text())["objects"]
    assert set(moved) <= set(objects), (moved, objects)

    cy, ours, still = tmp_path / "cycles", tmp_path / "lightfuse", tmp_path / "unedited"
    run_script("render_layout.py", "--dataset", ds, "--state", "state0", "--layout", layout,
               "--env", oracle["env"], "--spp", CYCLES_SPP, "--max-bounces", "1", "--no-denoise",
               "--rgb-only", "--quiet", "--out", cy)
    ok("render", oracle["scene"], "--state", "state0", "--layout", layout, "--cameras", ds,
       "--spp", LIGHTFUSE_SPP, "--out", ours)
    r = compare(cy, ours)
    ok("render", oracle["scene"], "--state", "state0", "--cameras", ds, "--spp", "16", "--out", still)
    control = compare(cy, still)
    print(f"DCC loop (moved {moved}): LightFuse vs Cycles {r['psnr_all']:.2f} dB "
          f"(background {r['psnr_background']:.2f} dB); unedited control {control['psnr_all']:.2f} dB")
    assert len(r["views"]) == 8
    assert r["psnr_all"] >= 30.0, r
    assert control["psnr_all"] < r["psnr_all"] - 4.0, (control, r)
