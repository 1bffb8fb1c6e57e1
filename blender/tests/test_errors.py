"""Bad input: one clear error each (names the file / field and what was expected), exit code 2,
no Python traceback."""

from __future__ import annotations

import json

import pytest

from bltest import run_script

EYE = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]


def assert_user_error(p, *words):
    out = p.stdout + p.stderr
    assert p.returncode == 2, out[-2000:]
    assert "Traceback" not in out, out[-2000:]
    for w in words:
        assert w in p.stderr, (w, p.stderr)


def test_unknown_preset(tmp_path):
    p = run_script("generate.py", "--preset", "garage", "--out", tmp_path / "d", check=False)
    assert_user_error(p, "--preset", "garage", "bedroom")
    assert not (tmp_path / "d").exists()


def test_missing_hdri(tmp_path):
    p = run_script("generate.py", "--demo", "--states", "1", "--train-envs", str(tmp_path / "nope.exr"),
                   "--out", tmp_path / "d", check=False)
    assert_user_error(p, "nope.exr", "not found")
    p = run_script("generate.py", "--demo", "--hdri-dir", tmp_path, "--out", tmp_path / "d2", check=False)
    assert_user_error(p, str(tmp_path), "no HDRI")
    p = run_script("generate.py", "--demo", "--test-envs", "forest,not_an_hdri", "--out", tmp_path / "d3",
                   check=False)
    assert_user_error(p, "--test-envs", "not_an_hdri", "not found")


def _layout(tmp_path, objects):
    f = tmp_path / "layout.json"
    f.write_text(json.dumps({"format": "lightfuse-layout/1", "objects": objects}))
    return f


def test_layout_with_unknown_object(tiny_dataset, tmp_path):
    f = _layout(tmp_path, {"sofa_that_is_not_there": EYE})
    p = run_script("render_layout.py", "--dataset", tiny_dataset["path"], "--state", "state0", "--layout", f,
                   "--out", tmp_path / "r", check=False)
    assert_user_error(p, "layout.json", "sofa_that_is_not_there", "unknown object")


@pytest.mark.parametrize("kind", ["scale", "shear"])
def test_layout_with_scale_or_shear(tiny_dataset, tmp_path, kind):
    name = tiny_dataset["json"]["objects"][0]["name"]
    m = [r[:] for r in EYE]
    if kind == "scale":
        m[0][0] = 1.5
    else:
        m[0][1] = 0.3
    f = _layout(tmp_path, {name: m})
    p = run_script("render_layout.py", "--dataset", tiny_dataset["path"], "--state", "state0", "--layout", f,
                   "--out", tmp_path / "r", check=False)
    assert_user_error(p, "layout.json", f"objects.{name}", "scale or shear", "rigid")


def test_scene_file_not_lightfuse(tiny_dataset, tmp_path):
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.mesh.primitive_cube_add()
    plain = tmp_path / "plain.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(plain))
    p = run_script("render_layout.py", "--scene", plain, "--cameras", tmp_path / "c.json",
                   "--env", "forest", "--out", tmp_path / "r", check=False)
    assert_user_error(p, "c.json")  # cameras checked first: missing file
    cams = {"frames": tiny_dataset["json"]["states"][0]["frames"][:1]}
    (tmp_path / "c.json").write_text(json.dumps(cams))
    p = run_script("render_layout.py", "--scene", plain, "--cameras", tmp_path / "c.json",
                   "--env", "forest", "--out", tmp_path / "r", check=False)
    assert_user_error(p, "plain.blend", "not a LightFuse scene")
    junk = tmp_path / "junk.blend"
    junk.write_bytes(b"this is not a blend file")
    p = run_script("render_layout.py", "--scene", junk, "--cameras", tmp_path / "c.json",
                   "--env", "forest", "--out", tmp_path / "r", check=False)
    assert_user_error(p, "junk.blend")
    p = run_script("export_layout.py", plain, "--out", tmp_path / "l.json", check=False)
    assert_user_error(p, "plain.blend", "not a LightFuse scene")


def test_help_for_every_script():
    for s in ("generate.py", "render_layout.py", "export_mesh_scene.py", "import_scene.py", "export_layout.py"):
        p = run_script(s, "--help")
        assert "usage:" in p.stdout and "--out" in p.stdout
