"""The oracle-scene pipeline end to end: a dataset's scene exported as a glTF mesh scene
(export_mesh_scene.py), surfelized by `lightfuse surfelize --dataset`, carries every state with
the ground-truth object poses, so each object lands where Blender placed it in that state."""
import json

import numpy as np

from bltest import ok, run_script

SPACING = 0.02


def info(path):
    return json.loads(ok("info", "--json", path))


def test_oracle_scene_places_objects_like_blender(tiny_dataset, tmp_path):
    ds = tiny_dataset["path"]
    ref, moved = tmp_path / "ref.glb", tmp_path / "state1.glb"
    run_script("export_mesh_scene.py", "--dataset", ds, "--out", ref, "--bake-res", "32")
    run_script("export_mesh_scene.py", "--dataset", ds, "--state", "state1", "--out", moved, "--bake-res", "32")
    oracle = tmp_path / "oracle.glb"
    ok("surfelize", ref, "-o", oracle, "--spacing", SPACING, "--dataset", ds, "--env-size", "64x32")
    ok("surfelize", moved, "-o", tmp_path / "s1.glb", "--spacing", SPACING)
    o = info(oracle)
    names = [s["name"] for s in o["states"]]
    train = [s["name"] for s in tiny_dataset["json"]["states"] if s["split"] == "train"]
    assert names[: len(train)] == train
    assert any(n.startswith("test0_") for n in names) and len(o["environments"]) >= len(train)
    state1 = next(s for s in o["states"] if s["name"] == "state1")
    direct = info(tmp_path / "s1.glb")["states"][0]["component_bounds"]
    objects = [c["name"] for c in o["components"][1:]]
    assert objects
    for name in objects:
        a, b = state1["component_bounds"][name], direct[name]
        # Two independent jittered samplings of the same surface: bounds agree to a spacing.
        for k in ("min", "max"):
            assert np.allclose(a[k], b[k], atol=2 * SPACING), (name, k, a[k], b[k])
