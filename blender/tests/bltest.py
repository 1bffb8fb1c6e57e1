"""Helpers shared by the Blender toolkit tests (imported by name; pytest's conftest modules
of different folders would shadow each other): running the toolkit's scripts and the
lightfuse binary, and the work folders the stage tests start from."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys

BLENDER_DIR = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
REPO = os.path.dirname(BLENDER_DIR)
SCHEMAS = os.path.join(REPO, "schemas")
LIGHTFUSE = os.environ.get("LIGHTFUSE_BIN", os.path.join(REPO, "target", "release", "lightfuse"))
sys.path.insert(0, BLENDER_DIR)
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import numpy as np  # noqa: E402

import lfio  # noqa: E402
from lfaxes import C3  # noqa: E402
from lfblend import ID_PROP, SCENE_KEY  # noqa: E402

TINY_ARGS = ["--preset", "demo", "--res", "32x32", "--views", "3", "--states", "2", "--relight", "2",
             "--test-views", "2", "--spp", "4", "--seed", "7"]


def run_script(name: str, *args, check: bool = True) -> subprocess.CompletedProcess:
    """Run blender/<name> with the venv's Python; returns the completed process."""
    cmd = [sys.executable, os.path.join(BLENDER_DIR, name), *map(str, args)]
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    if check and p.returncode != 0:
        raise AssertionError(f"{name} failed ({p.returncode}):\nstdout:\n{p.stdout[-3000:]}\nstderr:\n{p.stderr[-3000:]}")
    return p


def run(*args):
    """Run the lightfuse binary (``LIGHTFUSE_BIN``, default the release build)."""
    return subprocess.run([LIGHTFUSE, *map(str, args)], capture_output=True, text=True)


def ok(*args):
    """Run the lightfuse binary, which must succeed; returns its stdout."""
    p = run(*args)
    assert p.returncode == 0, f"lightfuse {' '.join(map(str, args))}:\n{p.stderr[-3000:]}"
    return p.stdout


def a_day_of_training(checkpoint, report):
    """Writes a day's training time into a stage's checkpoint, as after a run over several
    sittings, once checked that it holds what the report of the run that wrote it says."""
    c = json.loads(checkpoint.read_text())
    assert 0 < report["training_seconds"] <= report["seconds"]
    assert c["training_seconds"] == report["training_seconds"]
    c["training_seconds"] = 86400.0
    checkpoint.write_text(json.dumps(c))


def assert_a_day_carried_over(resumed, log, resumed_from):
    """A run resumed after `a_day_of_training`: its report and the log lines it wrote (after
    iteration `resumed_from`) count the day and this run's training on top of it."""
    assert 86400.0 < resumed["training_seconds"] < 86400.0 + resumed["seconds"]
    for line in log:
        assert (line["training_seconds"] > 86400.0) == (line["iteration"] > resumed_from), line
    assert log[-1]["training_seconds"] == resumed["training_seconds"]


def stages(tiny_dataset, tmp_path, refine=False):
    """A work folder with stage 1 (20 iterations) and, with `refine`, stage 2 (5) on the tiny
    dataset: the starting point of the later stages' tests."""
    work = tmp_path / "work"
    ok("--quiet", "reconstruct", tiny_dataset["path"], "-o", work, "--iterations", "20")
    if refine:
        ok("--quiet", "refine", tiny_dataset["path"], work, "--iterations", "5")
    return work


def renamed_object_dataset(ds, dest, name="teapot"):
    """A copy of dataset folder `ds` at `dest` whose first object is called `name` (its poses
    too): a dataset that does not match a scene reconstructed from `ds`."""
    shutil.copytree(ds, dest)
    d = json.loads((dest / "dataset.json").read_text())
    old = d["objects"][0]["name"]
    d["objects"][0]["name"] = name
    for s in d["states"]:
        if s.get("object_poses"):
            s["object_poses"] = {(name if k == old else k): v for k, v in s["object_poses"].items()}
    (dest / "dataset.json").write_text(json.dumps(d))
    return dest


def scene_trees(root):
    """BVHs of a generated dataset's scene.blend (folder ``root``) at the reference state, in
    Blender world coordinates: {"trees": {id: BVH} (0 = every background mesh), "names": {id:
    name}, "raw": {id: (vertices, polygons)}, "rec": the scene's record, "smooth": {id: [bool]}}.
    Opens the .blend in this process."""
    import bpy
    from mathutils.bvhtree import BVHTree

    bpy.ops.wm.open_mainfile(filepath=os.path.join(root, "scene.blend"))
    rec = json.loads(bpy.context.scene[SCENE_KEY])
    names = {o["id"]: o["name"] for o in rec["objects"]}

    def tree(objs):
        verts, polys, smooth = [], [], []
        for ob in objs:
            smooth += [p.use_smooth for p in ob.data.polygons]
            mw = ob.matrix_world
            base = len(verts)
            verts += [mw @ v.co for v in ob.data.vertices]
            polys += [[base + i for i in p.vertices] for p in ob.data.polygons]
        return BVHTree.FromPolygons(verts, polys, epsilon=0.0), verts, polys, smooth

    static = [ob for ob in bpy.data.objects if ob.type == "MESH" and ob.get(ID_PROP, 0) == 0]
    t, _v, _p, sm = tree(static)
    trees, smooth = {0: t}, {0: sm}
    raw = {}
    for i, n in names.items():
        root = bpy.data.objects[n]
        t, v, p, sm = tree([root, *(o for o in root.children_recursive if o.type == "MESH")])
        trees[i], smooth[i] = t, sm
        raw[i] = (np.array([x[:] for x in v]), p)
    return {"trees": trees, "names": names, "raw": raw, "rec": rec, "smooth": smooth}


def pixel_rays(fr):
    """Y-up world origin and (unnormalised, camera z = -1) directions through pixel centres."""
    w, h = fr["w"], fr["h"]
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    dc = np.stack([(u - fr["cx"]) / fr["fl_x"], -(v - fr["cy"]) / fr["fl_y"], -np.ones_like(u)], -1)
    c2w = np.array(fr["transform_matrix"])
    return c2w[:3, 3], dc @ c2w[:3, :3].T


def check_frame(root, fr, poses, bvh, stats):
    from mathutils import Vector

    depth = lfio.read_exr(os.path.join(root, fr["depth_file_path"]))["Z"]
    normal = lfio.read_rgb_exr(os.path.join(root, fr["normal_file_path"]))
    mask = lfio.read_png_gray8(os.path.join(root, fr["mask_path"]))
    o_y, d_y = pixel_rays(fr)
    h, w = depth.shape
    for y in range(h):
        for x in range(w):
            m = int(mask[y, x])
            dy = d_y[y, x]
            if m == 0:
                P = np.eye(4)
            else:
                P = np.array(poses[bvh["names"][m]])
            # ray in the object's reference frame (Y-up), then Blender axes
            Pinv = np.linalg.inv(P)
            o_ref = Pinv[:3, :3] @ o_y + Pinv[:3, 3]
            d_ref = Pinv[:3, :3] @ dy
            ob = C3.T @ o_ref
            db = C3.T @ d_ref
            nrm = np.linalg.norm(db)
            loc, n, pi, t = bvh["trees"][m].ray_cast(Vector(ob), Vector(db / nrm))
            if depth[y, x] == 0:
                assert m == 0, "no-hit pixel with a non-zero id"
                # nothing at all along the ray: static scene and every object in this state
                for oid, tr in bvh["trees"].items():
                    Q = np.eye(4) if oid == 0 else np.linalg.inv(np.array(poses[bvh["names"][oid]]))
                    oo = C3.T @ (Q[:3, :3] @ o_y + Q[:3, 3])
                    dd = C3.T @ (Q[:3, :3] @ dy)
                    assert tr.ray_cast(Vector(oo), Vector(dd / np.linalg.norm(dd)))[0] is None
                stats["miss"] += 1
                continue
            assert loc is not None, f"pixel ({x},{y}) id {m}: depth {depth[y, x]} but the ray misses"
            planar = t / nrm
            stats["depth_err"].append(abs(planar - depth[y, x]))
            n_y = P[:3, :3] @ (C3 @ np.array(n[:]))
            if np.dot(n_y, dy) > 0:  # face normal seen from behind (open/back faces)
                n_y = -n_y
            key = "cos_smooth" if bvh["smooth"][m][pi] else "cos"
            stats[key].append(float(np.dot(n_y, normal[y, x])))
            stats["norm"].append(float(np.linalg.norm(normal[y, x])))
            stats["ids"].add(m)
