"""The env/*.exr files are 'already rotated': a horizontal roll of the lat-long map equals
Cycles' World Mapping rotation about Blender +Z (LightFuse +Y) by shift*360/W degrees; and
every preset builds and arranges."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bltest import run_script

import lfio
from lfenv import SUN_SHARE, SUN_SKIES, load_env, resolve_hdri, rotate_env, setup_world
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


@pytest.mark.parametrize("name", sorted(SUN_SKIES))
def test_a_sun_sky_has_its_sun_at_its_elevation_carrying_its_share(name):
    """The plain family's procedural skies: the brightest texel at the named elevation, the sun
    disc SUN_SHARE of a horizontal surface's irradiance, a uniform ground below the horizon."""
    env = load_env(resolve_hdri(name, None, "test"))
    h, w, _ = env.shape
    assert (h, w) == (512, 1024) and env.dtype == np.float32 and np.isfinite(env).all()
    lum = env @ np.array([0.2126, 0.7152, 0.0722])
    sun = lum > 1000 * np.median(lum)
    rows = np.nonzero(sun)[0]
    assert 4 <= len(rows) <= 40, len(rows)  # a disc of 0.6 deg radius: ~9 texels of 0.35 deg
    elevation = 90.0 - (rows.mean() + 0.5) / h * 180.0
    assert abs(elevation - SUN_SKIES[name]) < 0.2, elevation
    theta = (np.arange(h) + 0.5) / h * math.pi
    weight = (np.clip(np.cos(theta), 0, None) * np.sin(theta))[:, None]  # cos to the zenith x dOmega
    share = (lum * weight)[sun].sum() / (lum * weight).sum()
    assert abs(share - SUN_SHARE) < 1e-3, share
    ground = lum[h // 2:]
    assert ground.std() < 1e-6 * ground.mean() and ground.mean() > 0


@pytest.mark.parametrize("preset", ["bedroom", "playroom", "livingroom", "kitchen"])
def test_presets_build(preset, tmp_path):
    run_script("generate.py", "--preset", preset, "--res", "8x8", "--views", "1", "--states", "2",
               "--relight", "1", "--spp", "1", "--out", tmp_path / preset)
    import json

    ds = json.loads((tmp_path / preset / "dataset.json").read_text())
    assert 3 <= len(ds["objects"]) <= 5
