"""The scene catalogue (blender/scenes.py) and the generator's camera paths: every declared
symmetry maps its object's surface onto itself and keeps its appearance (rendered: Cycles'
albedo pass from a camera turned by the symmetry: blender/lfsymmetry.py); the second family (scenes.FAMILY)
builds, stands its objects on their bases and on furniture tops, and its camera paths keep to
what they promise; and one small dataset of that family is generated end to end.

Tolerances. A symmetry is checked on the surface, not on vertices: points sampled on the mesh,
turned by the symmetry (a random angle for a continuous one), must land within 1.5 mm of the
surface. The meshes are tessellated (32-48 segments): a 0.13 m circle of 32 segments departs
from the true circle by r (1 - cos(pi/32)) = 0.6 mm, so a point turned off the vertices' angles
lands up to ~0.6 mm from the faces (measured: at most 0.61 mm, the small ball turned about x
through its UV sphere's rings); 1.5 mm allows that, and is far below what a false symmetry
gives (a handle, the sign's foot, Suzanne's ears: centimetres; the second test checks one)."""

from __future__ import annotations

import json
import math
import random

import bpy  # noqa: F401  (first: bmesh and mathutils come with it)
import numpy as np
import pytest

from bltest import run_script

import lfsymmetry
from lfaxes import bl_to_yup_points
from lfrender import make_tmpdir, setup_render


def _fresh():
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)


def _surface(ob):
    """The object's triangles in the Y-up object frame, and a BVH over them."""
    me = ob.data
    me.calc_loop_triangles()
    verts = bl_to_yup_points(np.array([v.co[:] for v in me.vertices]))
    tris = [tuple(t.vertices) for t in me.loop_triangles]
    return verts, tris, lfsymmetry.surface(verts, tris)


def test_declared_symmetries_map_each_object_onto_itself():
    import scenes

    rng = np.random.default_rng(0)
    for kind, symmetries in scenes.SYMMETRIES.items():
        _fresh()
        ob = scenes.build_mesh(kind, scenes.obj_parts(kind), scenes.MODIFIERS.get(kind, ()))
        verts, tris, bvh = _surface(ob)
        points = lfsymmetry.samples(verts, tris, 400, rng)
        for s in symmetries:
            centre = s.get("offset", [0, 0, 0])
            for angle in lfsymmetry.angles(s["order"], rng):
                far = lfsymmetry.departure(points, bvh, centre, s["axis"], angle)
                assert far < lfsymmetry.SURFACE_TOL, \
                    f"{kind}: {s} by {math.degrees(angle):.0f} deg leaves the surface by {far * 1e3:.1f} mm"


def _appearance_change(kind, centre, axis, angle):
    """(share of covered pixels whose coverage changes, share of pixels covered in both whose
    albedo changes by more than 0.02 in some channel) when `kind` is seen turned by `angle`."""
    import scenes

    _fresh()
    setup_render(1, 0, False)
    ob = scenes.build_mesh(kind, scenes.obj_parts(kind), scenes.MODIFIERS.get(kind, ()))
    ob.pass_index = 1
    tmp = make_tmpdir()
    try:
        coverage, albedo, covered = lfsymmetry.appearance_change(tmp, centre, axis, angle)
    finally:
        import shutil

        shutil.rmtree(tmp, ignore_errors=True)
    assert covered > 100, f"{kind}: the test camera sees {covered} pixels of it"
    return coverage, albedo


def test_declared_symmetries_keep_each_objects_appearance():
    """What the surface check above cannot see: the texture. Seen from a camera turned by the
    symmetry (Cycles' albedo pass, the dataset's own), a symmetric object must look the same:
    the checker ball and the striped cone and lamp (Wave bands even in x) after a half turn.
    Tolerances: at most 2 % of the covered pixels may change coverage or albedo (by > 0.02),
    room for a tessellated silhouette's edge pixels; measured: albedo 0 for every declared
    symmetry, coverage 0 but for the ring turned off its 32 segments' angles (0.8 %), against 18-25 % for the faint noise textures (plant, cushion, orange: mean albedo change
    ~0.013) and 94 % for the striped cone after a quarter turn (the next test)."""
    import scenes

    rng = np.random.default_rng(0)
    for kind, symmetries in scenes.SYMMETRIES.items():
        for s in symmetries:
            centre = s.get("offset", [0, 0, 0])
            angles = [rng.uniform(0.3, 2 * math.pi - 0.3)] if s["order"] == 0 else \
                [2 * math.pi * j / s["order"] for j in range(1, s["order"])]
            for angle in angles:
                coverage, albedo = _appearance_change(kind, centre, s["axis"], angle)
                assert coverage <= lfsymmetry.APPEARANCE_TOL and albedo <= lfsymmetry.APPEARANCE_TOL, \
                    f"{kind}: {s} by {math.degrees(angle):.0f} deg changes coverage {coverage:.1%}, albedo {albedo:.1%}"


@pytest.mark.parametrize("kind,angle", [("cone_toy", 90), ("cushion", 180), ("plant", 180)])
def test_a_texture_that_breaks_the_symmetry_fails_the_appearance_check(kind, angle):
    """The check above can fail: a striped cone turned a quarter turn, and the noise-textured
    cushion and plant (shapes symmetric under these turns) turned a half turn, change albedo."""
    _coverage, albedo = _appearance_change(kind, [0, 0.1, 0], [0, 1, 0], math.radians(angle))
    assert albedo > 0.1, (kind, angle, albedo)


def test_an_asymmetric_object_fails_the_check():
    """The check above can fail: Suzanne turned by a quarter turn is not Suzanne."""
    import scenes

    _fresh()
    ob = scenes.build_mesh("monkey", scenes.obj_parts("monkey"), scenes.MODIFIERS["monkey"])
    verts, tris, bvh = _surface(ob)
    points = lfsymmetry.samples(verts, tris, 400, np.random.default_rng(1))
    assert lfsymmetry.departure(points, bvh, [0, 0, 0], [0, 1, 0], math.pi / 2) > 0.01


@pytest.mark.parametrize("preset", ["study", "gallery", "workshop"])
def test_second_family_builds_stands_and_places_on_furniture(preset):
    import scenes

    _fresh()
    desc = scenes.build_scene(preset)
    spec = scenes.FAMILY[preset]
    kinds = [k for _n, k in spec["objects"]]
    # Nothing of the presets' object catalogue but the new kinds (and the sign's stripes).
    assert not set(kinds) & {"ball", "vase", "pot", "mug", "kettle", "lamp", "books", "plant"}
    for name, ob, _radius, _height in desc["movables"]:
        low = min(v.co.z for v in ob.data.vertices)
        assert abs(low) < 1e-6, f"{preset}/{name} does not stand on its base ({low})"
    assert ("floor" in desc["surfaces"]) != bool(spec.get("on_furniture"))
    tops = {round(z, 6) for _rect, z in desc["surfaces"].values()}
    for seed in range(5):
        arr = scenes.arrange(desc, random.Random(f"{seed}-arrange"))
        for name, m in arr.items():
            assert round(float(m[2][3]), 6) in tops, (preset, name, m[2][3])


@pytest.mark.parametrize("preset", ["sunroom", "atelier"])
def test_the_plain_family_is_untextured_and_stands_on_the_open_floor(preset):
    import scenes

    spec = scenes.PLAIN[preset]
    for m in (spec["floor"], spec["wall"]):
        assert "tex" not in scenes.MATERIALS[m], (preset, m)
    kinds = {k for _n, k in spec["objects"]}
    assert "chrome_bottle" in kinds, kinds  # a mirror in every plain scene
    _fresh()
    desc = scenes.build_scene(preset)
    walls = bpy.data.objects["walls"]
    assert len(walls.data.vertices) == 8 * len(spec.get("walls", ("-y", "-x")))  # one box a wall
    assert list(desc["surfaces"]) == ["floor"]
    for seed in range(5):
        arr = scenes.arrange(desc, random.Random(f"{seed}-arrange"))
        assert all(abs(float(m[2][3])) < 1e-9 for m in arr.values()), arr


@pytest.mark.parametrize("path", ["orbit", "low", "high", "inside"])
def test_camera_paths_keep_their_promises(path):
    import generate

    size, furniture = 2.0, [((0.2, 1.4, -1.95, -1.25), 0.85)]
    mats = generate.make_cameras(random.Random(3), 24, size, 320, 240, path=path, furniture=furniture)
    assert len(mats) == 24
    for m in mats:
        m = np.asarray(m)
        eye, forward = m[:3, 3], -m[:3, 2]
        assert abs(np.linalg.norm(forward) - 1) < 1e-6
        el = math.degrees(math.asin(-forward[2]))  # looking down by this much
        if path == "inside":
            assert abs(eye[0]) < size - 0.2 and abs(eye[1]) < size - 0.2 and 1.0 <= eye[2] <= 1.6, eye
            (x0, x1, y0, y1), top = furniture[0]
            over = x0 - 0.15 < eye[0] < x1 + 0.15 and y0 - 0.15 < eye[1] < y1 + 0.15
            assert not over or eye[2] >= top + 0.3, eye  # clear of the workbench
        else:
            lo, hi = {"orbit": (28, 62), "low": (8, 18), "high": (65, 82)}[path]
            # The elevation is drawn for the eye about a jittered target near the middle.
            assert lo - 5 <= el <= hi + 5, (path, el)
            assert max(abs(eye[0]), abs(eye[1])) > size or eye[2] > 2.5, eye  # outside the room
        if path == "low":
            assert eye[0] > 0 or eye[1] > 0, eye  # over the open sides, not behind a wall


def test_a_second_family_dataset_end_to_end(tmp_path):
    """generate.py writes a workshop dataset (cameras inside the room): its objects, their
    declared symmetries and materials, and frames that see the room."""
    import lfio

    out = tmp_path / "workshop"
    run_script("generate.py", "--preset", "workshop", "--res", "24x18", "--views", "3", "--states", "1",
               "--relight", "1", "--test-views", "1", "--spp", "2", "--seed", "5", "--out", out, "--quiet")
    ds = json.loads((out / "dataset.json").read_text())
    import scenes

    assert [o["name"] for o in ds["objects"]] == [n for n, _k in scenes.FAMILY["workshop"]["objects"]]
    by_name = {o["name"]: o for o in ds["objects"]}
    assert by_name["rolling_pin"]["symmetries"] == scenes.SYMMETRIES["rolling_pin"]
    assert by_name["monkey"]["symmetries"] == []
    assert by_name["square_tin"]["material"]["metallic"] == 0.0
    frames = [fr for st in ds["states"] for run in st.get("relight", [st]) for fr in run["frames"]]
    assert len(frames) >= 4
    for fr in frames:
        z = lfio.read_exr(str(out / fr["depth_file_path"]))["Z"]
        assert (z > 0).mean() > 0.5, fr["file_path"]  # inside a room: mostly surfaces


def test_a_plain_family_dataset_is_lit_by_its_sun_skies_on_a_plain_floor(tmp_path):
    """generate.py --preset sunroom: the training states under the preset's sun skies and HDRI
    (their names recorded as the source), the test state under its own three, and an albedo
    pass that is plain on every upward face (nothing textured to hide a baked shadow)."""
    import lfio
    import scenes

    out = tmp_path / "sunroom"
    run_script("generate.py", "--preset", "sunroom", "--res", "32x32", "--views", "2", "--test-views", "1",
               "--spp", "4", "--seed", "2", "--out", out, "--quiet")
    ds = json.loads((out / "dataset.json").read_text())
    spec = scenes.PLAIN["sunroom"]
    train = [s for s in ds["states"] if s["split"] == "train"]
    test = next(s for s in ds["states"] if s["split"] == "test")
    assert [s["environment_source"]["name"] for s in train] == spec["train_envs"]
    relit = [r for r in test["relight"] if not r.get("training_state")]  # (not the synthesis runs)
    assert [r["environment_source"]["name"] for r in relit] == spec["test_envs"]
    assert [r["environment"] for r in relit] == [f"env/{n}.exr" for n in spec["test_envs"]]
    assert all(":" not in f["file_path"] for r in relit for f in r["frames"])
    floor = []
    for st in train:
        for fr in st["frames"]:
            n = lfio.read_exr(str(out / fr["normal_file_path"]))
            a = lfio.read_exr(str(out / fr["albedo_file_path"]))
            z = lfio.read_exr(str(out / fr["depth_file_path"]))["Z"]
            up = (n["G"] > 0.99) & (z > 0)  # Y-up world: the floor (and the bench's top)
            floor.append(np.stack([a["R"], a["G"], a["B"]], -1)[up])
    floor = np.concatenate(floor)
    assert len(floor) > 100
    # Every upward face (the floor, the walls' and the bench's tops, the tin's lid) is one plain
    # colour: a handful of distinct values, the floor's the most common. A texture would give
    # hundreds.
    values, counts = np.unique(floor.round(2), axis=0, return_counts=True)
    assert len(values) <= 6, values
    assert np.allclose(values[counts.argmax()], scenes.MATERIALS["concrete"]["color"], atol=0.01), values
