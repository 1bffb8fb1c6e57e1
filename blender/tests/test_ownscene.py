"""generate.py --scene: a user's own scene as a multi-state dataset, on two scenes the project
does not ship (tests/own_scenes.py builds them: a .blend room with a table and a shelf, and a
.glb corner read back through Blender's glTF importer).

On both: the dataset validates; its depth, normals and masks agree with the saved scene's
meshes (so the masks carry the right ids); in every state every object rests on a surface
(contact within 2 mm under its base) and crosses nothing; every camera sees a movable object
and none stands inside a solid; `lightfuse run` completes on it. Then `--layouts` reproduces an
artist's poses, the scene's own cameras, the recorded truth (materials, symmetries, lights), and
one clear line for each bad input.

Tolerances. Objects are stood CONTACT_GAP (0.5 mm) above their support, so no triangle of theirs
touches it; the 2 mm the issue allows is checked from below the base by rays. Depth against the
mesh: 2 mm at most (float32 passes at pixel centres; the presets' test uses the same bound)."""

from __future__ import annotations

import json
import math

import jsonschema
import numpy as np
import pytest

import own_scenes
from bltest import check_frame, ok, run, run_script, scene_trees

import lfio
from lfaxes import C3

SMALL = ["--res", "40x30", "--views", "4", "--test-views", "2", "--states", "2", "--relight", "1", "--spp", "4",
         "--seed", "3", "--quiet"]


def _build(kind, folder):
    if kind == "blend":
        path = folder / "room.blend"
        names = own_scenes.room_blend(path)
    else:
        path = folder / "corner.glb"
        names = own_scenes.corner_glb(path)
    return path, names


@pytest.fixture(scope="module", params=["blend", "glb"])
def own(request, tmp_path_factory):
    folder = tmp_path_factory.mktemp(f"own_{request.param}")
    path, names = _build(request.param, folder)
    out = folder / "dataset"
    p = run_script("generate.py", "--scene", path, "--movable", ",".join(names), *SMALL, "--out", out)
    ds = json.loads((out / "dataset.json").read_text())
    return {"kind": request.param, "scene": path, "names": names, "path": out, "json": ds, "stderr": p.stderr,
            "folder": folder}


def _placed(trees, oid, pose):
    """The object's vertices (Blender world) and BVH in a state (pose: Y-up, from state0)."""
    from mathutils.bvhtree import BVHTree

    verts, polys = trees["raw"][oid]
    vy = (verts @ C3.T) @ pose[:3, :3].T + pose[:3, 3]
    vb = vy @ C3
    return vb, BVHTree.FromPolygons([tuple(v) for v in vb], polys, epsilon=0.0)


def test_an_own_scene_makes_a_valid_dataset_whose_passes_agree_with_its_meshes(own, schema):
    ds = own["json"]
    jsonschema.Draft202012Validator(schema("dataset.schema.json")).validate(ds)
    assert [o["name"] for o in ds["objects"]] == own["names"]
    assert ds["generator"]["preset"] == "own" and ds["generator"]["scene"] == own["scene"].name
    trees = scene_trees(str(own["path"]))
    stats = {"depth_err": [], "cos": [], "cos_smooth": [], "norm": [], "ids": set(), "miss": 0}
    for st in ds["states"]:
        frames = st["frames"] if "frames" in st else st["relight"][0]["frames"]
        for fr in frames:
            check_frame(str(own["path"]), fr, st["object_poses"], trees, stats)
    err = np.array(stats["depth_err"])
    assert len(err) > 1000 and err.max() < 2e-3, err.max()
    # every object is seen in some mask, with its own id (check_frame: on its own surface)
    assert stats["ids"] >= set(range(len(own["names"]) + 1)), stats["ids"]


def test_objects_rest_on_surfaces_and_cross_nothing_in_every_state(own):
    from mathutils import Vector

    ds = own["json"]
    trees = scene_trees(str(own["path"]))
    names = trees["names"]
    for st in ds["states"]:
        placed = {oid: _placed(trees, oid, np.array(st["object_poses"][n])) for oid, n in names.items()}
        for oid, (vb, tree) in placed.items():
            others = [trees["trees"][0]] + [t for k, (_v, t) in placed.items() if k != oid]
            for k, t in enumerate(others):
                assert not tree.overlap(t), f"{st['name']}: {names[oid]} crosses {'the background' if k == 0 else 'an object'}"
            zmin = vb[:, 2].min()
            base = vb[vb[:, 2] < zmin + 1e-3]
            gaps = []
            for p in base:
                hits = [t.ray_cast(Vector((p[0], p[1], zmin + 1e-3)), Vector((0, 0, -1)), 1.0) for t in others]
                below = [zmin - h[0][2] for h in hits if h[0] is not None]
                gaps.append(min(below) if below else np.inf)
            assert 0 <= min(gaps) <= 2e-3, f"{st['name']}: {names[oid]} is {min(gaps) * 1e3:.2f} mm above its support"
            # upright: a turn about the vertical only
            pose = np.array(st["object_poses"][names[oid]])
            assert abs(pose[1, 1] - 1) < 1e-6, (st["name"], names[oid])
    moved = sum(np.abs(np.array(st["object_poses"][n]) - np.eye(4)).max() > 1e-3
                for st in ds["states"] for n in names.values())
    assert moved >= len(names), "the states should differ"


def _inside(trees, p):
    """Inside a closed solid: the first face met in each of 6 directions is seen from behind."""
    from mathutils import Vector

    for d in [(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)]:
        best = None
        for t in trees:
            loc, n, _i, dist = t.ray_cast(Vector(p), Vector(d))
            if loc is not None and (best is None or dist < best[0]):
                best = (dist, np.array(n))
        if best is None or best[1] @ np.array(d) <= 0:
            return False
    return True


def test_every_camera_sees_an_object_and_none_stands_inside_a_solid(own):
    ds = own["json"]
    trees = scene_trees(str(own["path"]))
    for st in ds["states"]:
        placed = [_placed(trees, oid, np.array(st["object_poses"][n]))[1] for oid, n in trees["names"].items()]
        frames = st["frames"] if "frames" in st else st["relight"][0]["frames"]
        for fr in frames:
            mask = lfio.read_png_gray8(str(own["path"] / fr["mask_path"]))
            assert (mask > 0).sum() >= 4, f"{fr['mask_path']}: sees no movable object"
            eye = C3.T @ np.array(fr["transform_matrix"])[:3, 3]
            assert not _inside([trees["trees"][0], *placed], eye), f"{fr['file_path']}: camera inside a solid"


def test_lightfuse_run_completes_on_an_own_scene(own, tmp_path):
    ds = str(own["path"])
    work = tmp_path / "work"
    ok("--quiet", "reconstruct", ds, "-o", work, "--iterations", "20")
    ok("--quiet", "refine", ds, work, "--iterations", "5")
    p = run("run", ds, "-o", work, "--iterations", "4", "--bounces", "1")
    assert p.returncode == 0, p.stderr
    assert "stage 3: invert: ran" in p.stderr and "evaluate: ran" in p.stderr, p.stderr
    ev = json.loads((work / "eval" / "eval.json").read_text())
    assert ev["runs"], ev


def test_the_truth_recorded_is_what_the_scene_says(own):
    """Materials where they are plain Principled inputs, a note where not; the symmetries the
    checks find (about the vertical: a plain cylinder, ball, cone, torus continuous, a cube and a
    four-sided pyramid four-fold; about a horizontal axis: a ball continuous, a cylinder and a
    torus upside down, nothing for a cone, a pyramid, or a block with a knob on top); the
    scene's lamp named as ignored."""
    by = {o["name"]: o for o in own["json"]["objects"]}
    order = {o: [s["order"] for s in by[o]["symmetries"]] for o in by}
    if own["kind"] == "blend":
        assert "ceiling_lamp (point)" in own["stderr"] and "lit by environments only" in own["stderr"]
        assert "material" not in by["can"] and "Roughness" in by["can"]["material_note"]
        assert by["ball"]["material"] == {"metallic": 0.0, "roughness": 0.3}
        assert order["can"] == [0, 2] and order["ball"] == [0, 0] and order["cone"] == [0]
    else:
        assert by["pyramid"]["material"]["metallic"] == 1.0
        assert order["block"] == [4] and order["pyramid"] == [4] and order["ring"] == [0, 2]
    for o in by.values():  # the vertical first, every axis through the same point
        assert not o["symmetries"] or o["symmetries"][0]["axis"] == [0, 1, 0]
        assert len({tuple(s["offset"]) for s in o["symmetries"]}) <= 1
        assert all(abs(s["axis"][1]) < 1e-9 for s in o["symmetries"][1:])


def test_layouts_reproduce_an_artists_poses(tmp_path):
    path, names = _build("blend", tmp_path)

    def turn(deg, x, z, y=0.0):
        c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
        return [[c, 0, s, x], [0, 1, 0, y], [-s, 0, c, z], [0, 0, 0, 1]]

    # Motions from the scene as loaded (Y-up): the crate along the floor, the ball onto the
    # table (0.72 m top; the ball rests at 0 as loaded), the cone down from the shelf.
    layouts = [
        {"crate": turn(30, -0.4, 0.3), "ball": turn(0, 0.3, -0.2)},
        {"crate": turn(-75, -0.4, 0.5), "ball": turn(45, 0.95, -0.2, 0.72)},
        {"crate": turn(90, 0.5, 0.9), "cone": turn(0, 1.0, -0.8, -0.43), "can": turn(0, -0.2, -0.3)},
    ]
    files = []
    for i, lay in enumerate(layouts):
        f = tmp_path / f"layout{i}.json"
        f.write_text(json.dumps({"format": "lightfuse-layout/1", "objects": lay}))
        files.append(str(f))
    out = tmp_path / "ds"
    run_script("generate.py", "--scene", path, "--movable", ",".join(names), "--layouts", ",".join(files),
               "--res", "16x12", "--views", "1", "--relight", "1", "--spp", "1", "--out", out, "--quiet")
    ds = json.loads((out / "dataset.json").read_text())
    assert [s["name"] for s in ds["states"]] == ["state0", "state1", "test0"]
    L = [{n: np.array(lay.get(n, np.eye(4))) for n in names} for lay in layouts]
    for st, lk in zip(ds["states"], L):
        for n in names:
            want = lk[n] @ np.linalg.inv(L[0][n])
            assert np.abs(np.array(st["object_poses"][n]) - want).max() < 1e-5, (st["name"], n)
    # scene.blend holds state0: each object where the first layout put it
    import bpy

    from lfaxes import yup_to_bl_matrix

    bpy.ops.wm.open_mainfile(filepath=str(path))
    loaded = {n: np.array(bpy.data.objects[n].matrix_world) for n in names}
    bpy.ops.wm.open_mainfile(filepath=str(out / "scene.blend"))
    for n in names:
        want = yup_to_bl_matrix(L[0][n]) @ loaded[n]
        assert np.abs(np.array(bpy.data.objects[n].matrix_world) - want).max() < 1e-5, n


def test_the_scenes_own_cameras_are_used_with_their_intrinsics(tmp_path):
    path, names = _build("blend", tmp_path)
    out = tmp_path / "ds"
    run_script("generate.py", "--scene", path, "--movable", ",".join(names), "--cameras", "scene",
               "--res", "24x18", "--states", "1", "--relight", "1", "--spp", "1", "--out", out, "--quiet")
    ds = json.loads((out / "dataset.json").read_text())
    import bpy

    bpy.ops.wm.open_mainfile(filepath=str(path))
    cam = bpy.data.objects["artist_cam"]
    want = C3 @ np.array(cam.matrix_world)[:3, 3]
    f = cam.data.lens / cam.data.sensor_width * 24  # sensor fit AUTO, landscape: the width
    for st in ds["states"]:
        for run_ in st.get("relight", [st]):
            assert len(run_["frames"]) == 1
            fr = run_["frames"][0]
            assert np.abs(np.array(fr["transform_matrix"])[:3, 3] - want).max() < 1e-5
            assert abs(fr["fl_x"] - f) < 1e-6, (fr["fl_x"], f)
            mask = lfio.read_png_gray8(str(out / fr["mask_path"]))
            assert (mask > 0).any(), "the objects are arranged where the scene's camera sees them"


def test_cameras_from_a_file_and_a_collection_of_movables(own, tmp_path):
    """--cameras FILE renders from the file's frames (here the first dataset's own training
    frames: the second with a doubled focal length, the others without intrinsics, so the
    default's) and each image is rendered with its own frame's intrinsics (the depth pass agrees
    with the meshes through them); --movable with a collection's name takes its objects."""
    if own["kind"] != "blend":
        pytest.skip("one scene is enough")
    first = [dict(f) for f in own["json"]["states"][0]["frames"]]
    for i, f in enumerate(first):
        if i == 1:
            f["fl_x"] = f["fl_y"] = 2 * f["fl_x"]
        else:
            for k in ("fl_x", "fl_y", "cx", "cy"):
                f.pop(k)
    cams = tmp_path / "cams.json"
    cams.write_text(json.dumps({"frames": first}))
    out = tmp_path / "ds"
    run_script("generate.py", "--scene", own["scene"], "--movable", "crate,can,Toys", "--cameras", cams,
               "--res", "40x30", "--states", "1", "--relight", "1", "--spp", "1", "--out", out, "--quiet")
    ds = json.loads((out / "dataset.json").read_text())
    assert [o["name"] for o in ds["objects"]] == ["crate", "can", "ball", "cone"]
    for st in ds["states"]:
        for run_ in st.get("relight", [st]):
            assert len(run_["frames"]) == len(first)
            for got, want, orig in zip(run_["frames"], first, own["json"]["states"][0]["frames"]):
                assert np.abs(np.array(got["transform_matrix"]) - np.array(want["transform_matrix"])).max() < 1e-6
                assert all(abs(got[k] - want.get(k, orig[k])) < 1e-6 for k in ("fl_x", "fl_y", "cx", "cy"))
    trees = scene_trees(str(out))
    stats = {"depth_err": [], "cos": [], "cos_smooth": [], "norm": [], "ids": set(), "miss": 0}
    for fr in ds["states"][0]["frames"]:
        check_frame(str(out), fr, ds["states"][0]["object_poses"], trees, stats)
    assert max(stats["depth_err"]) < 2e-3


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    folder = tmp_path_factory.mktemp("bad")
    path, names = _build("blend", folder)
    return folder, path, names


def _refused(*args):
    p = run_script("generate.py", *args, "--res", "8x8", "--views", "1", "--relight", "1", "--spp", "1",
                   check=False)
    assert p.returncode == 2, (p.returncode, p.stderr[-2000:])
    line = p.stderr.strip().splitlines()[-1]
    assert line.startswith("error: ") and "Traceback" not in p.stderr, p.stderr
    return line


def test_bad_input_is_refused_in_one_line(room, tmp_path):
    folder, path, names = room
    out = tmp_path / "out"
    line = _refused("--scene", path, "--movable", "crate,teapot", "--out", out)
    assert "--movable teapot" in line and "crate" in line  # names the scene's objects
    # a layout that floats an object, and one that puts it through the table
    for lay, what in [({"ball": [[1, 0, 0, 0], [0, 1, 0, 0.3], [0, 0, 1, 0], [0, 0, 0, 1]]}, "does not rest"),
                      ({"crate": [[1, 0, 0, 0.5], [0, 1, 0, 0.62], [0, 0, 1, -0.2], [0, 0, 0, 1]]}, "passes through")]:
        f = tmp_path / "bad_layout.json"
        f.write_text(json.dumps({"format": "lightfuse-layout/1", "objects": lay}))
        line = _refused("--scene", path, "--movable", ",".join(names), "--layouts", f"{f},{f},{f}", "--out", out)
        assert str(f) in line and what in line, line
    f = tmp_path / "unknown.json"
    f.write_text(json.dumps({"format": "lightfuse-layout/1", "objects": {"table": np.eye(4).tolist()}}))
    line = _refused("--scene", path, "--movable", ",".join(names), "--layouts", f"{f},{f},{f}", "--out", out)
    assert "objects.table" in line and "not a movable" in line
    line = _refused("--scene", path, "--movable", "crate", "--states", "3", "--layouts", f"{f},{f}", "--out", out)
    assert "--layouts: 2 files for 3 training states" in line
    line = _refused("--scene", path, "--movable", "crate", "--symmetry", "crate:0", "--out", out)
    assert "--symmetry crate:0" in line  # a box is not a solid of revolution
    line = _refused("--scene", folder / "missing.blend", "--movable", "crate", "--out", out)
    assert "file not found" in line
    line = _refused("--movable", "crate", "--out", out)
    assert "--movable" in line and "only with --scene" in line
    assert not out.exists(), "nothing is written for a refused command"


def test_an_open_or_flat_mesh_and_a_scene_without_support_are_refused(tmp_path):
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.mesh.primitive_cube_add(size=4, location=(0, 0, -2))  # the ground
    bpy.ops.mesh.primitive_plane_add(size=0.3, location=(0, 0, 0.2))
    bpy.context.active_object.name = "sheet"  # open: four boundary edges
    me = bpy.data.meshes.new("sliver")  # one triangle of three points on a line
    me.from_pydata([(0, 0, 0.1), (0.1, 0, 0.1), (0.2, 0, 0.1)], [], [(0, 1, 2)])
    bpy.context.scene.collection.objects.link(bpy.data.objects.new("sliver", me))
    bpy.ops.mesh.primitive_cube_add(size=0.2, location=(-0.5, 0, 0.1))
    bpy.context.active_object.name = "box"
    scene = tmp_path / "s.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(scene))
    out = tmp_path / "out"
    assert "--movable sheet: its mesh is not closed" in _refused("--scene", scene, "--movable", "sheet", "--out", out)
    assert "--movable sliver: its mesh has zero area" in _refused("--scene", scene, "--movable", "sliver", "--out", out)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.mesh.primitive_cube_add(size=0.2, location=(0, 0, 0.1))
    bpy.context.active_object.name = "box"
    bpy.ops.mesh.primitive_plane_add(size=2, location=(0, -1, 1), rotation=(math.pi / 2, 0, 0))  # a wall only
    scene2 = tmp_path / "wall.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(scene2))
    assert "no upward-facing surface" in _refused("--scene", scene2, "--movable", "box", "--out", out)
