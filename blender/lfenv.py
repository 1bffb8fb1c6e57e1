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


def resolve_hdri(spec: str, hdri_dir: str | None, where: str) -> str:
    """A name of a bundled HDRI (or one in hdri_dir) or a path to an .exr/.hdr file."""
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
                    f"equirectangular .exr/.hdr or one of {', '.join(bundled_hdris())}")


def load_env(path: str) -> np.ndarray:
    """Equirectangular environment as float32 (H, W, 3), row 0 = top (+Y / Blender +Z)."""
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
