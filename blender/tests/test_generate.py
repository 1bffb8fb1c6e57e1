"""generate.py: the tiny dataset validates, its depth / normals / masks agree with the meshes of
scene.blend, its recorded poses match the placements, and render_layout.py reproduces it."""

from __future__ import annotations

import json
import os

import jsonschema
import numpy as np
import pytest

from bltest import check_frame, run_script, scene_trees

import lfio
from lfaxes import C3, check_rigid


def test_tiny_dataset_is_valid(tiny_dataset, schema):
    print(f"tiny dataset generated in {tiny_dataset['seconds']:.1f} s")
    ds = tiny_dataset["json"]
    jsonschema.Draft202012Validator(schema("dataset.schema.json")).validate(ds)
    train = [s for s in ds["states"] if s["split"] == "train"]
    test = [s for s in ds["states"] if s["split"] == "test"]
    assert len(train) == 2 and len(test) == 1
    relight = [r for r in test[0]["relight"] if "training_state" not in r]
    novel = [r for r in test[0]["relight"] if "training_state" in r]
    assert len(relight) == 2
    # novel-state synthesis: the test layout under every training state's own environment file
    assert [(r["training_state"], r["environment"]) for r in novel] == [
        (s["name"], s["environment"]) for s in train]
    train_envs = {s["environment_source"]["name"] for s in train}
    test_envs = {r["environment_source"]["name"] for r in relight}
    assert not train_envs & test_envs, "test environments must not be used in training"
    assert 3 <= len(ds["objects"]) <= 5
    for o in ds["objects"]:  # ground-truth material, evaluation only
        assert 0 <= o["material"]["metallic"] <= 1 and 0 <= o["material"]["roughness"] <= 1, o
    root = tiny_dataset["path"]
    for st in ds["states"]:
        runs = st.get("relight", []) + ([st] if "frames" in st else [])
        for run in runs:
            assert os.path.isfile(os.path.join(root, run["environment"]))
            for fr in run["frames"]:
                for k in ("file_path", "depth_file_path", "normal_file_path", "mask_path", "albedo_file_path"):
                    assert os.path.isfile(os.path.join(root, fr[k])), fr[k]
                rgb = lfio.read_rgb_exr(os.path.join(root, fr["file_path"]))
                assert rgb.shape == (32, 32, 3) and np.isfinite(rgb).all() and rgb.mean() > 0
    assert os.path.isfile(os.path.join(root, "scene.blend"))
    # environments were written already rotated: they are full lat-long maps
    env = lfio.read_rgb_exr(os.path.join(root, train[0]["environment"]))
    assert env.shape[1] == 2 * env.shape[0]


def test_same_seed_same_dataset(tmp_path):
    args = ["--preset", "demo", "--res", "16x12", "--views", "1", "--states", "1", "--relight", "1",
            "--spp", "2", "--seed", "3"]
    run_script("generate.py", *args, "--out", tmp_path / "a")
    run_script("generate.py", *args, "--out", tmp_path / "b")
    da = json.loads((tmp_path / "a" / "dataset.json").read_text())
    db = json.loads((tmp_path / "b" / "dataset.json").read_text())
    assert da == db
    for st in da["states"]:
        for run in st.get("relight", [st]):
            for fr in run["frames"]:
                # Cycles' multithreaded BVH build and sums may change the last float bits of a few
                # pixels: equal up to float32 rounding, masks identical
                for k in ("file_path", "depth_file_path", "normal_file_path", "albedo_file_path"):
                    ca = lfio.read_exr(str(tmp_path / "a" / fr[k]))
                    cb = lfio.read_exr(str(tmp_path / "b" / fr[k]))
                    assert ca.keys() == cb.keys()
                    for c in ca:
                        assert np.allclose(ca[c], cb[c], rtol=1e-5, atol=1e-5), (k, c)
                ma = lfio.read_png_gray8(str(tmp_path / "a" / fr["mask_path"]))
                mb = lfio.read_png_gray8(str(tmp_path / "b" / fr["mask_path"]))
                assert (ma == mb).all()


# ----------------------------------------------------------------------------- geometry


@pytest.fixture(scope="module")
def scene_bvh(tiny_dataset):
    """BVHs of scene.blend at the reference state, in Blender world coordinates."""
    return scene_trees(tiny_dataset["path"])


def test_depth_normals_masks_agree_with_meshes(tiny_dataset, scene_bvh):
    """Back-projected depth lies on the surface of the object the mask names, in the object's
    reference frame (through the recorded pose), and the normal pass matches the mesh normal."""
    root, ds = tiny_dataset["path"], tiny_dataset["json"]
    stats = {"depth_err": [], "cos": [], "cos_smooth": [], "norm": [], "ids": set(), "miss": 0}
    for st in ds["states"]:
        frames = st["frames"] if "frames" in st else st["relight"][0]["frames"]
        for fr in frames:
            check_frame(root, fr, st["object_poses"], scene_bvh, stats)
    err = np.array(stats["depth_err"])
    cos = np.array(stats["cos"])
    assert len(err) > 1000
    assert err.max() < 2e-3, f"max depth error {err.max():.2e} m"
    assert np.median(err) < 1e-4
    assert np.abs(np.array(stats["norm"]) - 1).max() < 1e-3, "normals are not unit length"
    # flat faces: the face normal; smooth-shaded faces (spheres, tori) differ from the face
    # normal by at most about a facet angle
    assert cos.min() > 0.9999, f"worst flat-face normal cosine {cos.min():.6f}"
    cs = np.array(stats["cos_smooth"])
    assert len(cs) > 20 and cs.min() > 0.93 and np.median(cs) > 0.99
    assert stats["ids"] >= {0} and len(stats["ids"]) >= 3, "objects should be visible in the masks"
    assert stats["miss"] > 0, "some pixels should see the environment"


def test_recorded_poses_match_placement(tiny_dataset, scene_bvh):
    """In each state, every object stands upright (rotation about +Y only) on the floor or a
    furniture top, moved relative to state0, and movable objects do not interpenetrate."""
    from mathutils.bvhtree import BVHTree

    ds = tiny_dataset["json"]
    rec = scene_bvh["rec"]
    import scenes

    tops = {0.0} | {f[3] for f in scenes.PRESETS["demo"]["furniture"]}
    moved = 0
    for st in ds["states"]:
        trees = []
        for oid, name in scene_bvh["names"].items():
            P = np.array(st["object_poses"][name])
            check_rigid(P, name)
            R = P[:3, :3]
            assert abs(R[1, 1] - 1) < 1e-6, f"{st['name']}/{name}: not upright"
            verts, polys = scene_bvh["raw"][oid]
            vy = (verts @ C3.T) @ R.T + P[:3, 3]
            bottom = vy[:, 1].min()
            assert min(abs(bottom - t) for t in tops) < 1e-5, f"{st['name']}/{name} floats at {bottom}"
            if st["name"] != "state0":
                moved += np.abs(P - np.eye(4)).max() > 1e-3
            else:
                assert np.allclose(P, np.eye(4), atol=1e-8)
            trees.append(BVHTree.FromPolygons([tuple(v) for v in vy], polys))
        for i in range(len(trees)):
            for j in range(i + 1, len(trees)):
                assert not trees[i].overlap(trees[j]), f"{st['name']}: objects {i + 1} and {j + 1} intersect"
    assert moved >= 2 * len(scene_bvh["names"]) - 1
    # scene.blend holds the reference placement and the same poses
    import bpy

    for st in ds["states"]:
        assert rec["states"][st["name"]] == st["object_poses"]
    for name, m in rec["reference"].items():
        assert np.allclose(np.array(bpy.data.objects[name].matrix_world), np.array(m), atol=1e-6)


def psnr(a, b):
    mse = float(((a - b) ** 2).mean())
    peak = max(float(a.max()), 1.0)
    return 99.0 if mse == 0 else 10 * np.log10(peak * peak / mse)


def test_render_layout_reproduces_a_state(tiny_dataset, tmp_path):
    root, ds = tiny_dataset["path"], tiny_dataset["json"]
    st = ds["states"][1]
    layout = tmp_path / "layout.json"
    layout.write_text(json.dumps({"format": "lightfuse-layout/1", "objects": st["object_poses"]}))
    out = tmp_path / "render"
    run_script("render_layout.py", "--dataset", root, "--state", st["name"], "--layout", layout, "--out", out)
    fr_out = json.loads((out / "frames.json").read_text())["frames"]
    assert len(fr_out) == len(st["frames"])
    for a, b in zip(st["frames"], fr_out):
        ra = lfio.read_rgb_exr(os.path.join(root, a["file_path"]))
        rb = lfio.read_rgb_exr(str(out / b["file_path"]))
        assert psnr(ra, rb) >= 40.0
        ma = lfio.read_png_gray8(os.path.join(root, a["mask_path"]))
        mb = lfio.read_png_gray8(str(out / b["mask_path"]))
        assert (ma == mb).mean() > 0.99
    # and a different layout (state0's) gives different images
    ref = tmp_path / "ref.json"
    ref.write_text(json.dumps({"format": "lightfuse-layout/1", "objects": {}}))
    out2 = tmp_path / "render_ref"
    run_script("render_layout.py", "--dataset", root, "--state", st["name"], "--layout", ref, "--out", out2,
               "--rgb-only", "--max-bounces", "1")
    ra = lfio.read_rgb_exr(os.path.join(root, st["frames"][0]["file_path"]))
    rb = lfio.read_rgb_exr(str(out2 / "rgb" / "000.exr"))
    assert psnr(ra, rb) < 40.0


def test_render_layout_reads_gltf_node_transforms(tiny_dataset, tmp_path):
    """A LightFuse .glb whose default scene places the objects as in state1 is a layout."""
    import mathutils

    from lfgltf_writer import random_component, write_glb

    root, ds = tiny_dataset["path"], tiny_dataset["json"]
    st = ds["states"][1]
    rng = np.random.default_rng(0)
    comps = [random_component("background", 0, 4, rng)] + [random_component(o["name"], o["id"], 4, rng)
                                                            for o in ds["objects"]]
    trs = {}
    for name, m in st["object_poses"].items():
        m = np.array(m)
        q = mathutils.Matrix(m[:3, :3].tolist()).to_quaternion()
        trs[name] = (m[:3, 3].tolist(), (q.x, q.y, q.z, q.w))
    glb = tmp_path / "layout.glb"
    write_glb(glb, comps, [("state1", trs)])
    out = tmp_path / "render"
    run_script("render_layout.py", "--dataset", root, "--state", st["name"], "--layout", glb, "--out", out,
               "--rgb-only")
    for i, a in enumerate(st["frames"]):
        ra = lfio.read_rgb_exr(os.path.join(root, a["file_path"]))
        rb = lfio.read_rgb_exr(str(out / "rgb" / f"{i:03d}.exr"))
        assert psnr(ra, rb) >= 40.0
