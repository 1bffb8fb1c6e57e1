"""The env/*.exr files are 'already rotated': a horizontal roll of the lat-long map equals
Cycles' World Mapping rotation about Blender +Z (LightFuse +Y) by shift*360/W degrees; and
every preset builds and arranges."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bltest import run_script

import lfio
from lfenv import load_env, resolve_hdri, rotate_env, setup_world
from lfrender import render_beauty, setup_render


def _render_env(world_path, rotation_deg, tmpdir):
    import bpy
    import mathutils

    bpy.ops.wm.read_factory_settings(use_empty=True)
    sc = bpy.context.scene
    cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
    sc.collection.objects.link(cam)
    sc.camera = cam
    cam.data.lens = 12.0
    cam.matrix_world = mathutils.Matrix.Rotation(math.radians(80), 4, "X") @ mathutils.Matrix.Rotation(0.3, 4, "Y")
    sc.render.resolution_x, sc.render.resolution_y = 48, 32
    setup_render(4, 1, False)
    setup_world(world_path, rotation_deg)
    return render_beauty(str(tmpdir), 4, 11)


def test_rolled_env_equals_cycles_rotation(tmp_path):
    src = resolve_hdri("forest", None, "test")
    env = load_env(src)
    w = env.shape[1]
    shift = 173
    rolled = tmp_path / "rolled.exr"
    lfio.write_rgb_exr(str(rolled), rotate_env(env, shift))
    a = _render_env(src, shift * 360.0 / w, tmp_path)
    b = _render_env(str(rolled), 0.0, tmp_path)
    c = _render_env(src, 0.0, tmp_path)
    rel = np.abs(a - b).mean() / a.mean()
    assert rel < 2e-3, rel
    assert np.abs(a - c).mean() / a.mean() > 0.05  # the rotation matters


@pytest.mark.parametrize("preset", ["bedroom", "playroom", "livingroom", "kitchen"])
def test_presets_build(preset, tmp_path):
    run_script("generate.py", "--preset", preset, "--res", "8x8", "--views", "1", "--states", "2",
               "--relight", "1", "--spp", "1", "--out", tmp_path / preset)
    import json

    ds = json.loads((tmp_path / preset / "dataset.json").read_text())
    assert 3 <= len(ds["objects"]) <= 5
