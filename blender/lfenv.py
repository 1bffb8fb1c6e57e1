"""Environments of the LightFuse Blender scripts: the bundled HDRIs, equirectangular maps as
arrays (load, rotate, mean luminance) and the Cycles World that shows one."""

from __future__ import annotations

import math
import os

import numpy as np

import lfio
from lfcli import UserError
from lfstate import ENV_NODE


def bundled_hdri_dir() -> str:
    import bpy

    return bpy.utils.system_resource("DATAFILES", path="studiolights/world")


def bundled_hdris() -> list[str]:
    return ["city", "courtyard", "forest", "interior", "night", "studio", "sunrise", "sunset"]


# Procedural clear skies with a sun, by name: the sun's elevation in degrees. Blender's bundled
# studio HDRIs light softly; a sun casts the hard shadows a method must not paint into the floor
# (issue 44), so the plain family (scenes.PLAIN) is lit by these. Made here from a formula, not
# downloaded; `load_env` returns them like a file.
SUN_SKIES = {"sun_low": 18.0, "sun_mid": 38.0, "sun_high": 62.0}
PROCEDURAL = "procedural:"
# The sun's angular radius: 0.6 deg (the real sun's is 0.27) keeps it a few texels wide at
# 1024 x 512, so Cycles finds it at 64 spp; the shadows stay hard (a 1.2 deg penumbra is 2 mm
# behind a 10 cm object).
SUN_RADIUS_DEG = 0.6
# The sun's share of a horizontal surface's irradiance (the rest from the sky): ~0.8 under a
# clear sky at mid elevations.
SUN_SHARE = 0.8


def sun_sky(elevation_deg: float, width: int = 1024) -> np.ndarray:
    """A clear sky with a sun at `elevation_deg`, as a float32 (H, W, 3) equirectangular map
    (row 0 = the zenith): a blue gradient, brighter toward the horizon and round the sun, the sun
    a uniform disc of SUN_RADIUS_DEG at the map's middle column carrying SUN_SHARE of a
    horizontal surface's irradiance (integrated on this very grid), and a uniform grey-brown
    ground below the horizon reflecting 25 % of that irradiance. Which column the sun is in does
    not matter: the generator turns every map about the vertical by a random angle."""
    h = width // 2
    theta = (np.arange(h) + 0.5) / h * math.pi  # from the zenith
    phi = (np.arange(width) + 0.5) / width * 2 * math.pi - math.pi  # the sun at phi = 0
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    d = np.stack(np.broadcast_arrays(st * np.cos(phi)[None, :], ct, st * np.sin(phi)[None, :]), axis=-1)
    e = math.radians(elevation_deg)
    sun = np.array([math.cos(e), math.sin(e), 0.0])
    angle = np.arccos(np.clip(d @ sun, -1.0, 1.0))
    up = np.clip(ct, 0.0, 1.0)  # cos of the angle from the zenith, above the horizon
    zenith, horizon = np.array([0.18, 0.34, 0.80]), np.array([0.70, 0.80, 0.95])
    t = (1.0 - up) ** 2
    sky = (zenith * (1 - t)[..., None] + horizon * t[..., None]) * (1.0 + 2.5 * np.exp(-angle / 0.25))[..., None]
    above = np.broadcast_to(ct > 0, angle.shape)
    omega = (2 * math.pi / width) * (math.pi / h) * st  # texel solid angles, (h, 1)
    lum = np.array([0.2126, 0.7152, 0.0722])
    cos_up = np.broadcast_to(np.clip(ct, 0.0, None), angle.shape)
    disc = angle < math.radians(SUN_RADIUS_DEG)
    sky_e = float((np.where(above & ~disc, sky @ lum, 0.0) * cos_up * omega).sum())
    sun_e_unit = float((np.where(disc, 1.0, 0.0) * cos_up * omega).sum())
    if sun_e_unit <= 0:
        raise ValueError(f"sun_sky: elevation {elevation_deg} puts the sun below the horizon")
    sun_l = SUN_SHARE / (1 - SUN_SHARE) * sky_e / sun_e_unit
    sun_rgb = np.array([1.0, 0.95, 0.85]) / (np.array([1.0, 0.95, 0.85]) @ lum)
    ground = np.array([0.30, 0.26, 0.21]) / (np.array([0.30, 0.26, 0.21]) @ lum)
    ground_l = 0.25 * (sky_e + sun_l * sun_e_unit) / math.pi
    out = np.where(above[..., None], sky, ground * ground_l)
    out = np.where(disc[..., None], sun_rgb * sun_l, out)
    return out.astype(np.float32)


def env_name(src: str) -> str:
    """The name of a resolved environment (`resolve_hdri`'s result): a procedural sky's own
    name, or the file's stem."""
    if src.startswith(PROCEDURAL):
        return src[len(PROCEDURAL):]
    return os.path.splitext(os.path.basename(src))[0]


def resolve_hdri(spec: str, hdri_dir: str | None, where: str) -> str:
    """A name of a bundled HDRI (or one in hdri_dir), of a procedural sun sky (SUN_SKIES:
    returned as "procedural:<name>", which `load_env` makes) or a path to an .exr/.hdr file."""
    if spec in SUN_SKIES:
        return PROCEDURAL + spec
    cands = []
    if os.sep in spec or spec.lower().endswith((".exr", ".hdr")):
        cands.append(spec)
    else:
        d = hdri_dir or bundled_hdri_dir()
        cands += [os.path.join(d, spec + ".exr"), os.path.join(d, spec + ".hdr")]
    for c in cands:
        if os.path.isfile(c):
            return os.path.abspath(c)
    raise UserError(f"{where}: HDRI {spec!r} not found (looked for {cands[0]}); expected an existing "
                    f"equirectangular .exr/.hdr or one of {', '.join(bundled_hdris() + list(SUN_SKIES))}")


def load_env(path: str) -> np.ndarray:
    """Equirectangular environment as float32 (H, W, 3), row 0 = top (+Y / Blender +Z)."""
    if path.startswith(PROCEDURAL):
        return sun_sky(SUN_SKIES[path[len(PROCEDURAL):]])
    if path.lower().endswith(".exr"):
        try:
            return lfio.read_rgb_exr(path)
        except lfio.ExrError:
            pass  # e.g. PIZ: let Blender decode it
    try:
        img = lfio.load_image_bpy(path)
    except RuntimeError as e:
        raise UserError(f"{path}: cannot read environment image ({e})") from None
    return img


def rotate_env(env: np.ndarray, shift_px: int) -> np.ndarray:
    """The map Cycles shows when its Mapping node rotates the lookup by +shift_px*360/W degrees
    about Blender +Z (LightFuse +Y): a horizontal roll of the lat-long image."""
    return np.roll(env, shift_px, axis=1)


def env_mean_luminance(env: np.ndarray) -> float:
    h = env.shape[0]
    theta = (np.arange(h) + 0.5) / h * math.pi
    wgt = np.sin(theta)[:, None]
    lum = env[..., 0] * 0.2126 + env[..., 1] * 0.7152 + env[..., 2] * 0.0722
    return float((lum * wgt).sum() / (wgt.sum() * env.shape[1]))


def setup_world(path: str, rotation_deg: float = 0.0, strength: float = 1.0) -> None:
    """World = Environment Texture (equirectangular) with a Mapping rotation about Blender Z."""
    import bpy

    sc = bpy.context.scene
    world = sc.world or bpy.data.worlds.new("World")
    sc.world = world
    nt = world.node_tree
    if nt is None:
        world.use_nodes = True
        nt = world.node_tree
    nt.nodes.clear()
    tc = nt.nodes.new("ShaderNodeTexCoord")
    mp = nt.nodes.new("ShaderNodeMapping")
    mp.vector_type = "POINT"
    mp.inputs["Rotation"].default_value = (0.0, 0.0, math.radians(rotation_deg))
    tex = nt.nodes.new("ShaderNodeTexEnvironment")
    tex.name = ENV_NODE
    if path.startswith(PROCEDURAL):  # a sun sky: Blender reads images from files
        import tempfile

        made = os.path.join(tempfile.mkdtemp(prefix="lightfuse_sky_"), path[len(PROCEDURAL):] + ".exr")
        lfio.write_rgb_exr(made, load_env(path))
        path = made
    try:
        img = bpy.data.images.load(path, check_existing=True)
    except RuntimeError as e:
        raise UserError(f"{path}: cannot load environment image ({e})") from None
    img.colorspace_settings.name = "Linear Rec.709"
    tex.image = img
    tex.interpolation = "Linear"
    bg = nt.nodes.new("ShaderNodeBackground")
    bg.inputs["Strength"].default_value = strength
    out = nt.nodes.new("ShaderNodeOutputWorld")
    nt.links.new(tc.outputs["Generated"], mp.inputs["Vector"])
    nt.links.new(mp.outputs["Vector"], tex.inputs["Vector"])
    nt.links.new(tex.outputs["Color"], bg.inputs["Color"])
    nt.links.new(bg.outputs["Background"], out.inputs["Surface"])
