"""import_scene.py -> edit -> export_layout.py round trip, and export_mesh_scene.py."""

from __future__ import annotations

import json
import math
import os

import numpy as np
import pytest

from bltest import REPO, run_script
from lfgltf_writer import random_component, write_glb

import lfio
import lfstate
from lfaxes import C3, bl_to_yup_matrix
from lfblend import ID_PROP, SCENE_KEY
from lffiles import read_layout_gltf
from lfgltf import GLB_MAGIC, read_gltf_json, trs_to_matrix


def _quat_y(deg):
    h = math.radians(deg) / 2
    return (0.0, math.sin(h), 0.0, math.cos(h))


@pytest.fixture(scope="module")
def lf_glb(tmp_path_factory):
    d = tmp_path_factory.mktemp("glb")
    rng = np.random.default_rng(1)
    comps = [random_component("background", 0, 200, rng),
             random_component("chair", 1, 50, rng, centre=(0.5, 0.3, -0.2)),
             random_component("lamp", 2, 40, rng, centre=(-0.6, 0.5, 0.4))]
    states = [("state0", {}),
              ("state1", {"chair": ((0.3, 0.0, 0.1), _quat_y(30)), "lamp": ((-0.2, 0.0, 0.0), _quat_y(-90))})]
    path = d / "scene.glb"
    write_glb(path, comps, states)
    return {"path": path, "components": comps, "states": states, "dir": d}


def test_import_then_move_then_export_gives_that_transform(lf_glb, tmp_path):
    blend = tmp_path / "edit.blend"
    run_script("import_scene.py", lf_glb["path"], "--out", blend)
    import bpy
    import mathutils

    bpy.ops.wm.open_mainfile(filepath=str(blend))
    rec = json.loads(bpy.context.scene[lfstate.SCENE_PROP])
    assert rec["states"] == ["state0", "state1"]
    chair = bpy.data.objects["chair"]
    bg = bpy.data.objects["background"]
    assert all(bg.lock_location) and all(bg.lock_rotation) and all(bg.lock_scale)
    # every surfel attribute is there; positions are the file's, converted to Blender axes
    comp = lf_glb["components"][1]
    me = chair.data
    for name in ("rotation", "scale", "opacity", "sh_0_0", "base_color", "metallic", "roughness"):
        assert name in me.attributes, name
    co = np.array([chair.matrix_world @ v.co for v in me.vertices])
    assert np.allclose(co @ C3.T, comp["position"], atol=1e-5)
    op = np.zeros(len(me.vertices), np.float32)
    me.attributes["opacity"].data.foreach_get("value", op)
    assert np.allclose(op, comp["opacity"], atol=1e-6)
    # the rotation attribute (Blender axes) gives the file's surfel normal (third column)
    qa = np.zeros(4 * len(me.vertices), np.float32)
    me.attributes["rotation"].data.foreach_get("value", qa)
    for i, qv in enumerate(qa.reshape(-1, 4)):
        R_bl = np.array(mathutils.Quaternion(tuple(qv)).to_matrix())  # (w, x, y, z)
        x, y, z, w = comp["rotation"][i]
        R_file = trs_to_matrix({"rotation": [x, y, z, w]})[:3, :3]
        assert np.allclose(C3 @ R_bl, R_file, atol=1e-5)  # every surfel frame, incl. its normal
    assert any(m.type == "NODES" for m in chair.modifiers)
    # states: state1 places the chair by the file's node transform, by the toolkit's apply_state
    # and by the same function saved in the .blend as its text block
    t, r = lf_glb["states"][1][1]["chair"]
    T = trs_to_matrix({"translation": t, "rotation": r})
    block = bpy.data.texts[lfstate.TEXT_BLOCK]
    with open(lfstate.__file__, encoding="utf-8") as f:
        assert block.as_string() == f.read()
    for apply_state in (lfstate.apply_state, block.as_module().apply_state):
        apply_state("state1")
        co1 = np.array([chair.matrix_world @ v.co for v in me.vertices]) @ C3.T
        assert np.allclose(co1, comp["position"] @ T[:3, :3].T + T[:3, 3], atol=1e-5)
        assert bpy.context.scene[lfstate.STATE_PROP] == "state1"
        apply_state("state0")
        co0 = np.array([chair.matrix_world @ v.co for v in me.vertices]) @ C3.T
        assert np.allclose(co0, comp["position"], atol=1e-5)
    with pytest.raises(lfstate.UnknownState, match="state7"):
        lfstate.apply_state("state7")
    # move the chair by script (Blender axes): rotate 40 deg about Z around a pivot, translate
    delta = (mathutils.Matrix.Translation((0.25, -0.4, 0.0)) @ mathutils.Matrix.Rotation(math.radians(40), 4, "Z"))
    chair.matrix_world = delta @ chair.matrix_world
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    out = tmp_path / "layout.json"
    run_script("export_layout.py", blend, "--out", out)
    lay = json.loads(out.read_text())
    import jsonschema

    with open(os.path.join(REPO, "schemas", "layout.schema.json")) as f:
        jsonschema.validate(lay, json.load(f))
    assert set(lay["objects"]) == {"chair", "lamp"}
    expect = bl_to_yup_matrix(np.array(delta))
    assert np.allclose(np.array(lay["objects"]["chair"]), expect, atol=1e-6)
    assert np.allclose(np.array(lay["objects"]["lamp"]), np.eye(4), atol=1e-6)


def test_export_layout_refuses_scale_and_shear(lf_glb, tmp_path):
    blend = tmp_path / "edit.blend"
    run_script("import_scene.py", lf_glb["path"], "--out", blend)
    import bpy

    bpy.ops.wm.open_mainfile(filepath=str(blend))
    bpy.data.objects["lamp"].scale = (1.0, 1.3, 1.0)
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    p = run_script("export_layout.py", blend, "--out", tmp_path / "l.json", check=False)
    assert p.returncode == 2
    assert "lamp" in p.stderr and "scale or shear" in p.stderr
    assert "Traceback" not in p.stderr + p.stdout
    assert not (tmp_path / "l.json").exists()


def test_import_refuses_non_lightfuse_gltf(lf_glb, tmp_path):
    plain = tmp_path / "plain.glb"
    write_glb(plain, lf_glb["components"][:1], [("s", {})], extension=False)
    p = run_script("import_scene.py", plain, "--out", tmp_path / "x.blend", check=False)
    assert p.returncode == 2
    assert "plain.glb" in p.stderr and "not a LightFuse scene" in p.stderr
    assert "Traceback" not in p.stderr + p.stdout
    junk = tmp_path / "junk.glb"
    junk.write_bytes(b"hello, not a gltf")
    p = run_script("import_scene.py", junk, "--out", tmp_path / "x.blend", check=False)
    assert p.returncode == 2 and "junk.glb" in p.stderr and "Traceback" not in p.stderr


def test_export_mesh_scene(tiny_dataset, tmp_path):
    out = tmp_path / "mesh.glb"
    run_script("export_mesh_scene.py", "--dataset", tiny_dataset["path"], "--state", "state1",
               "--bake-res", "32", "--out", out)
    assert out.read_bytes()[:4] == GLB_MAGIC
    js, binc = read_gltf_json(str(out))
    assert binc is not None
    names = {n["name"]: n for n in js["nodes"]}
    objs = tiny_dataset["json"]["objects"]
    assert set(names) == {"background"} | {o["name"] for o in objs}
    for o in objs:
        assert names[o["name"]]["extras"][ID_PROP] == o["id"]
    # Y-up: node transform = state1 placement in LightFuse's world
    import bpy

    bpy.ops.wm.open_mainfile(filepath=os.path.join(tiny_dataset["path"], "scene.blend"))
    rec = json.loads(bpy.context.scene[SCENE_KEY])
    st1 = tiny_dataset["json"]["states"][1]["object_poses"]
    for o in objs:
        want = np.array(st1[o["name"]]) @ bl_to_yup_matrix(np.array(rec["reference"][o["name"]]))
        got = trs_to_matrix(names[o["name"]])
        assert np.allclose(got, want, atol=1e-5), o["name"]
    # PBR metallic-roughness on every material; baked base colour textures exist
    mats = js["materials"]
    assert mats
    textured = 0
    for m in mats:
        pbr = m["pbrMetallicRoughness"]
        assert "baseColorFactor" in pbr or "baseColorTexture" in pbr
        assert "roughnessFactor" in pbr
        textured += "baseColorTexture" in pbr
    assert textured >= 1 and js.get("images")
    assert any(m["pbrMetallicRoughness"].get("metallicFactor", 1.0) == 1.0 for m in mats), "a metal"
    # the baked image is not flat
    img = js["images"][0]
    bv = js["bufferViews"][img["bufferView"]]
    png = tmp_path / "baked.png"
    png.write_bytes(binc[bv.get("byteOffset", 0):bv.get("byteOffset", 0) + bv["byteLength"]])
    px = lfio.load_image_bpy(str(png))
    assert px.std() > 0.02


RUST_WRITER = os.path.join(REPO, "target", "debug", "examples", "write_test_scene")


def test_import_a_scene_written_by_the_rust_writer(tmp_path):
    """The Rust writer's .glb imports, and state1 exports as state1's transforms."""
    import subprocess

    assert os.path.isfile(RUST_WRITER), "build the Rust examples first (cargo test builds them)"
    glb = tmp_path / "rust.glb"
    subprocess.run([RUST_WRITER, str(glb), "20"], check=True, capture_output=True)
    blend = tmp_path / "rust.blend"
    run_script("import_scene.py", glb, "--state", "state1", "--out", blend)
    out = tmp_path / "layout.json"
    run_script("export_layout.py", blend, "--out", out)
    lay = json.loads(out.read_text())["objects"]
    want = read_layout_gltf(str(glb), scene_index=1)
    assert set(lay) == set(want) and lay
    for k in want:
        assert np.allclose(np.array(lay[k]), want[k], atol=2e-6), k
