"""Cycles rendering for the LightFuse Blender scripts: the render setup (CPU, fixed threads, the
dataset's passes, no colour management), the beauty render and the geometry passes at the pixel
centres, converted to LightFuse conventions."""

from __future__ import annotations

import os
import tempfile

import numpy as np

import lfio
from lfaxes import C3
from lfcli import quiet_stdout


def setup_render(spp: int, max_bounces: int, denoise: bool, threads: int = 2) -> None:
    """Cycles on the CPU, fixed threads, passes for the dataset, no colour management."""
    import bpy

    sc = bpy.context.scene
    sc.render.engine = "CYCLES"
    cy = sc.cycles
    cy.device = "CPU"
    cy.samples = int(spp)
    cy.use_adaptive_sampling = False
    cy.use_denoising = bool(denoise)
    if denoise:
        cy.denoiser = "OPENIMAGEDENOISE"
    cy.max_bounces = int(max_bounces)
    for k in ("diffuse_bounces", "glossy_bounces", "transmission_bounces", "volume_bounces"):
        setattr(cy, k, int(max_bounces))
    cy.transparent_max_bounces = max(int(max_bounces), 1)
    cy.sample_clamp_direct = 0.0
    cy.sample_clamp_indirect = 0.0
    cy.caustics_reflective = True
    cy.caustics_refractive = True
    cy.blur_glossy = 0.0
    cy.use_light_tree = True
    sc.render.threads_mode = "FIXED"
    sc.render.threads = int(threads)
    sc.render.use_persistent_data = True  # keeps the BVH between frames: ~5x faster
    sc.render.film_transparent = False
    sc.view_settings.view_transform = "Standard"
    sc.view_settings.look = "None"
    sc.view_settings.exposure = 0.0
    sc.view_settings.gamma = 1.0
    sc.render.use_compositing = False
    sc.render.use_sequencer = False
    vl = sc.view_layers[0]
    vl.use_pass_combined = True
    vl.use_pass_z = True
    vl.use_pass_normal = True
    vl.use_pass_object_index = True
    if "albedo" not in [a.name for a in vl.aovs]:
        a = vl.aovs.add()
        a.name = "albedo"
        a.type = "COLOR"
    s = sc.render.image_settings
    s.media_type = "MULTI_LAYER_IMAGE"
    s.file_format = "OPEN_EXR_MULTILAYER"
    s.exr_codec = "NONE"
    s.color_depth = "32"


def _render_exr(tmpdir: str) -> dict[str, np.ndarray]:
    import bpy

    sc = bpy.context.scene
    path = os.path.join(tmpdir, "render.exr")
    sc.render.filepath = path
    sc.render.use_file_extension = False
    with quiet_stdout():
        bpy.ops.render.render(write_still=True)
    ch = lfio.read_exr(path)
    os.remove(path)
    vl = sc.view_layers[0].name
    return {k[len(vl) + 1:]: v for k, v in ch.items() if k.startswith(vl + ".")}


def frame_seed(base: int, index: int) -> int:
    return (int(base) * 7919 + int(index) * 104729 + 17) % 2147483647


def render_beauty(tmpdir: str, spp: int, seed: int, filter_width: float = 1.5) -> np.ndarray:
    """Linear HDR RGB (H, W, 3)."""
    import bpy

    sc = bpy.context.scene
    sc.cycles.samples = spp
    sc.cycles.seed = seed
    sc.cycles.pixel_filter_type = "BLACKMAN_HARRIS"
    sc.cycles.filter_width = filter_width
    ch = _render_exr(tmpdir)
    return np.stack([ch["Combined.R"], ch["Combined.G"], ch["Combined.B"]], -1)


def render_geometry(tmpdir: str) -> dict[str, np.ndarray]:
    """Depth / normal / mask / albedo at the pixel centres (1 sample, ~zero filter width),
    converted to LightFuse conventions: planar depth (0 = no hit), Y-up unit normals,
    integer object ids, base colour."""
    import bpy

    sc = bpy.context.scene
    saved = (sc.cycles.samples, sc.cycles.filter_width, sc.cycles.use_denoising, sc.cycles.seed)
    sc.cycles.samples = 1
    sc.cycles.filter_width = 0.01
    sc.cycles.use_denoising = False
    sc.cycles.seed = 0
    try:
        ch = _render_exr(tmpdir)
    finally:
        sc.cycles.samples, sc.cycles.filter_width, sc.cycles.use_denoising, sc.cycles.seed = saved
    depth = ch["Depth.Z"].astype(np.float32)
    hit = depth < 1e9
    depth = np.where(hit, depth, 0.0).astype(np.float32)
    nb = np.stack([ch["Normal.X"], ch["Normal.Y"], ch["Normal.Z"]], -1).astype(np.float64)
    n = nb @ C3.T
    ln = np.linalg.norm(n, axis=-1, keepdims=True)
    n = np.where(ln > 1e-8, n / np.maximum(ln, 1e-12), 0.0)
    n[~hit] = 0.0
    mask = np.rint(ch["Object Index.X"]).astype(np.int32)
    mask[~hit] = 0
    alb = np.stack([ch["albedo.R"], ch["albedo.G"], ch["albedo.B"]], -1)
    alb[~hit] = 0.0
    return {"depth": depth, "normal": n.astype(np.float32), "mask": mask, "albedo": alb.astype(np.float32)}


def write_geometry(out_root: str, rel: dict, g: dict) -> None:
    lfio.write_exr(os.path.join(out_root, rel["depth_file_path"]), {"Z": g["depth"]})
    lfio.write_rgb_exr(os.path.join(out_root, rel["normal_file_path"]), g["normal"])
    lfio.write_png_gray8(os.path.join(out_root, rel["mask_path"]), g["mask"])
    lfio.write_rgb_exr(os.path.join(out_root, rel["albedo_file_path"]), g["albedo"])


def make_tmpdir() -> str:
    return tempfile.mkdtemp(prefix="lightfuse_render_")
