"""Shared code of the LightFuse Blender scripts (bpy used as a Python module).

Conventions (``docs/design.md`` §2):

* World: right-handed, +Y up, metres.  A Blender point (x, y, z) is (x, z, -y) in LightFuse;
  ``C`` below is that change of basis, and a Blender 4x4 transform ``M`` becomes
  ``C4 @ M @ C4^-1``.
* Cameras: camera-to-world 4x4, OpenGL style (looks down -Z, +Y up).  A Blender camera object's
  local frame already is OpenGL style, so ``c2w = C4 @ camera.matrix_world``.  Intrinsics are
  ``fl_x, fl_y, cx, cy, w, h`` in pixels, pixel centres at +0.5.
* Matrices in JSON: 4x4 as a list of 4 rows.

Every script reports a user error (bad file, unknown name, ...) with :class:`UserError`: one
line on stderr naming the file / field and what was expected, exit code 2, no traceback
(:func:`run_main`).
"""

from __future__ import annotations

import json
import math
import os
import sys
import tempfile
import warnings

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
if HERE not in sys.path:
    sys.path.insert(0, HERE)

import lfio  # noqa: E402

warnings.filterwarnings("ignore", category=DeprecationWarning)  # bpy 5.0 API notices

DATASET_FORMAT = "lightfuse-dataset/1"
LAYOUT_FORMAT = "lightfuse-layout/1"
SCENE_KEY = "lightfuse"  # scene custom property holding the LightFuse record (JSON string)

# Blender (x, y, z) -> LightFuse (x, z, -y)
C3 = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])
C4 = np.eye(4)
C4[:3, :3] = C3
C4_INV = C4.T.copy()


class UserError(Exception):
    """An error in the user's input: reported as one line, exit code 2."""


def run_main(main, argv=None) -> None:
    """Run ``main(argv)``; user errors -> one line on stderr and exit code 2."""
    try:
        main(argv)
    except UserError as e:
        sys.stdout.flush()
        print(f"error: {e}", file=sys.stderr)
        sys.stderr.flush()
        os._exit(2)  # bpy's atexit handlers can print noise; leave quietly
    except lfio.ExrError as e:
        sys.stdout.flush()
        print(f"error: {e}", file=sys.stderr)
        sys.stderr.flush()
        os._exit(2)
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)


# ----------------------------------------------------------------------------- matrices


def bl_to_yup_matrix(m) -> np.ndarray:
    """Blender world 4x4 (mathutils.Matrix or array) -> the same transform in Y-up."""
    return C4 @ np.asarray(m, dtype=np.float64) @ C4_INV


def cam_bl_to_yup(m) -> np.ndarray:
    """Blender camera matrix_world -> LightFuse camera-to-world (both OpenGL-style camera axes)."""
    return C4 @ np.asarray(m, dtype=np.float64)


def cam_yup_to_bl(c2w) -> np.ndarray:
    return C4_INV @ np.asarray(c2w, dtype=np.float64)


def yup_to_bl_matrix(m) -> np.ndarray:
    return C4_INV @ np.asarray(m, dtype=np.float64) @ C4


def bl_to_yup_points(p: np.ndarray) -> np.ndarray:
    return np.asarray(p, dtype=np.float64) @ C3.T


def rows(m) -> list:
    """4x4 -> list of 4 rows of floats (JSON), tiny values rounded to clean zeros."""
    a = np.asarray(m, dtype=np.float64)
    a = np.where(np.abs(a) < 5e-8, 0.0, a)  # float32 noise of Blender matrices
    return [[float(round(v, 9)) + 0.0 for v in r] for r in a]


def check_rigid(m, where: str, tol: float = 1e-4) -> np.ndarray:
    """Validate a 4x4 rigid transform (rows); ``where`` names the file and field."""
    try:
        a = np.asarray(m, dtype=np.float64)
    except (TypeError, ValueError):
        raise UserError(f"{where}: expected a 4x4 matrix as a list of 4 rows of numbers") from None
    if a.shape != (4, 4):
        raise UserError(f"{where}: expected a 4x4 matrix as 4 rows of 4 numbers, got shape {list(a.shape)}")
    if not np.all(np.isfinite(a)):
        raise UserError(f"{where}: matrix has NaN or infinite entries")
    if np.abs(a[3] - [0, 0, 0, 1]).max() > tol:
        raise UserError(f"{where}: last row must be [0, 0, 0, 1], got {a[3].tolist()}")
    r = a[:3, :3]
    sv = np.linalg.svd(r, compute_uv=False)
    if np.abs(sv - 1).max() > tol or np.abs(r.T @ r - np.eye(3)).max() > tol:
        raise UserError(
            f"{where}: transform has scale or shear (singular values {np.round(sv, 6).tolist()}); "
            "expected a rigid transform (rotation + translation only)")
    if np.linalg.det(r) < 0:
        raise UserError(f"{where}: transform is a reflection (determinant < 0); expected a rotation")
    return a


# ----------------------------------------------------------------------------- cameras


def intrinsics(cam_data, w: int, h: int) -> dict:
    """Pixel intrinsics of a Blender perspective camera with sensor_fit HORIZONTAL, no shift."""
    f = cam_data.lens / cam_data.sensor_width * w
    return {"fl_x": f, "fl_y": f, "cx": w / 2.0, "cy": h / 2.0, "w": int(w), "h": int(h)}


def set_camera(cam_obj, frame: dict) -> None:
    """Place a Blender camera from a dataset frame (Y-up c2w + intrinsics)."""
    import mathutils

    where = frame.get("_where", "frame")
    try:
        c2w = np.asarray(frame["transform_matrix"], dtype=np.float64)
        w, h = int(frame["w"]), int(frame["h"])
        fx, fy = float(frame["fl_x"]), float(frame["fl_y"])
        cx, cy = float(frame["cx"]), float(frame["cy"])
    except (KeyError, TypeError, ValueError) as e:
        raise UserError(f"{where}: expected transform_matrix, fl_x, fl_y, cx, cy, w, h ({e})") from None
    if c2w.shape != (4, 4):
        raise UserError(f"{where}.transform_matrix: expected 4 rows of 4 numbers")
    if abs(fx - fy) > 1e-6 * fx:
        raise UserError(f"{where}: fl_x != fl_y (non-square pixels) is not supported by Cycles cameras")
    m = cam_yup_to_bl(c2w)
    # remove any scale from the rotation part (keep it a camera pose)
    u, _, vt = np.linalg.svd(m[:3, :3])
    m[:3, :3] = u @ vt
    cam_obj.matrix_world = mathutils.Matrix(m.tolist())
    cd = cam_obj.data
    cd.type = "PERSP"
    cd.sensor_fit = "HORIZONTAL"
    cd.sensor_width = 36.0
    cd.lens = fx / w * cd.sensor_width
    # principal point offset: Blender shift is in units of the larger image dimension
    cd.shift_x = -(cx - w / 2.0) / max(w, h)
    cd.shift_y = (cy - h / 2.0) / max(w, h)
    import bpy

    sc = bpy.context.scene
    sc.render.resolution_x = w
    sc.render.resolution_y = h
    sc.render.resolution_percentage = 100


# ----------------------------------------------------------------------------- environment


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
    tex.name = "lightfuse_env"
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


# ----------------------------------------------------------------------------- rendering


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


class quiet_stdout:
    """Silence Blender's per-tile render log on fd 1 (C-level stdout) for a block."""

    def __enter__(self):
        sys.stdout.flush()
        self.saved = os.dup(1)
        self.null = os.open(os.devnull, os.O_WRONLY)
        os.dup2(self.null, 1)

    def __exit__(self, *exc):
        sys.stdout.flush()
        os.dup2(self.saved, 1)
        os.close(self.saved)
        os.close(self.null)
        return False


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


# ----------------------------------------------------------------------------- scene record


def open_blend(path: str) -> None:
    """Open a .blend as the current file, quietly; a file Blender cannot open is a UserError."""
    import bpy

    try:
        with quiet_stdout():
            bpy.ops.wm.open_mainfile(filepath=os.path.abspath(path))
    except RuntimeError as e:
        raise UserError(f"{path}: cannot open as a Blender file ({str(e).strip()})") from None


def get_record(where: str) -> dict:
    """The LightFuse record stored in a generated scene.blend (objects, reference matrices)."""
    import bpy

    sc = bpy.context.scene
    raw = sc.get(SCENE_KEY)
    if raw is None:
        raise UserError(f"{where}: not a LightFuse scene (scene has no '{SCENE_KEY}' record); "
                        "expected a scene.blend written by blender/generate.py")
    try:
        rec = json.loads(raw)
        rec["objects"], rec["reference"]
    except (ValueError, KeyError, TypeError):
        raise UserError(f"{where}: the scene's '{SCENE_KEY}' record is malformed") from None
    return rec


def apply_layout_bl(rec: dict, layout_yup: dict, where: str) -> None:
    """Place objects: world = layout (Y-up, relative to reference) applied to the reference."""
    import bpy
    import mathutils

    names = {o["name"] for o in rec["objects"]}
    for name, m in layout_yup.items():
        if name not in names:
            raise UserError(f"{where}: objects.{name}: unknown object; the scene's objects are "
                            f"{', '.join(sorted(names))}")
        rigid = check_rigid(m, f"{where}: objects.{name}")
        ref = np.asarray(rec["reference"][name], dtype=np.float64)
        world = yup_to_bl_matrix(rigid) @ ref
        bpy.data.objects[name].matrix_world = mathutils.Matrix(world.tolist())
    for name in names - set(layout_yup):
        ref = np.asarray(rec["reference"][name], dtype=np.float64)
        bpy.data.objects[name].matrix_world = mathutils.Matrix(ref.tolist())
    bpy.context.view_layer.update()


def read_json(path: str, what: str) -> dict:
    try:
        with open(path, encoding="utf-8") as f:
            return json.load(f)
    except FileNotFoundError:
        raise UserError(f"{path}: {what} not found") from None
    except (OSError, UnicodeDecodeError) as e:
        raise UserError(f"{path}: cannot read {what} ({e})") from None
    except json.JSONDecodeError as e:
        raise UserError(f"{path}: not valid JSON (line {e.lineno}: {e.msg}); expected {what}") from None


def write_json(path: str, obj) -> None:
    import re

    text = json.dumps(obj, indent=1)
    # one line per innermost list of numbers (matrix rows)
    text = re.sub(r"\[\s+([-0-9.eE+,\s]+?)\s+\]",
                  lambda m: "[" + ", ".join(x.strip() for x in m.group(1).split(",")) + "]", text)
    tmp = path + ".tmp"
    with open(tmp, "w", encoding="utf-8") as f:
        f.write(text + "\n")
    os.replace(tmp, path)


def read_layout(path: str) -> dict:
    """layout.json -> {name: 4x4 array}; glTF/GLB with named nodes accepted too (node TRS)."""
    low = path.lower()
    if low.endswith((".glb", ".gltf")):
        return read_layout_gltf(path)
    if low.endswith((".usd", ".usda", ".usdc", ".usdz")):
        return read_layout_usd(path)
    d = read_json(path, "a layout.json")
    if not isinstance(d, dict) or d.get("format") != LAYOUT_FORMAT:
        raise UserError(f"{path}: field 'format' must be {LAYOUT_FORMAT!r}, got {d.get('format') if isinstance(d, dict) else type(d).__name__!r}")
    objs = d.get("objects")
    if not isinstance(objs, dict):
        raise UserError(f"{path}: field 'objects' must be an object mapping names to 4x4 matrices")
    return {k: check_rigid(v, f"{path}: objects.{k}") for k, v in objs.items()}


def read_gltf_json(path: str) -> tuple[dict, bytes | None]:
    import struct

    try:
        with open(path, "rb") as f:
            data = f.read()
    except OSError as e:
        raise UserError(f"{path}: cannot read ({e.strerror})") from None
    if data[:4] == b"glTF":
        try:
            _, _, total = struct.unpack_from("<4sII", data, 0)
            clen, ctype = struct.unpack_from("<II", data, 12)
            if ctype != 0x4E4F534A:
                raise ValueError("first chunk is not JSON")
            js = json.loads(data[20:20 + clen].decode("utf-8"))
            binc = None
            p = 20 + clen
            if p + 8 <= len(data):
                blen, btype = struct.unpack_from("<II", data, p)
                if btype == 0x004E4942:
                    binc = data[p + 8:p + 8 + blen]
                    if len(binc) != blen:
                        raise ValueError("BIN chunk truncated")
            return js, binc
        except (struct.error, ValueError, UnicodeDecodeError) as e:
            raise UserError(f"{path}: malformed GLB ({e})") from None
    try:
        return json.loads(data.decode("utf-8")), None
    except (ValueError, UnicodeDecodeError):
        raise UserError(f"{path}: not a glTF file (neither GLB nor glTF JSON)") from None


def trs_to_matrix(node: dict) -> np.ndarray:
    if "matrix" in node:
        return np.asarray(node["matrix"], dtype=np.float64).reshape(4, 4).T  # column-major
    t = node.get("translation", [0, 0, 0])
    x, y, z, w = node.get("rotation", [0, 0, 0, 1])
    s = node.get("scale", [1, 1, 1])
    r = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                  [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                  [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    m = np.eye(4)
    m[:3, :3] = r * np.asarray(s)[None, :]
    m[:3, 3] = t
    return m


def read_layout_usd(path: str) -> dict:
    """Transforms of the Xform children of a USD stage's default prim (components), as authored
    (default variant selections), relative to the reference state.  The stage must be Y-up."""
    if not os.path.isfile(path):
        raise UserError(f"{path}: layout file not found")
    try:
        from pxr import Usd, UsdGeom
    except ImportError:
        raise UserError(f"{path}: reading USD needs usd-core (pip install usd-core)") from None
    try:
        stage = Usd.Stage.Open(path)
    except Exception as e:  # pxr raises Tf.ErrorException
        raise UserError(f"{path}: cannot open as USD ({str(e).strip().splitlines()[-1]})") from None
    up = UsdGeom.GetStageUpAxis(stage)
    if up != UsdGeom.Tokens.y:
        raise UserError(f"{path}: upAxis is {up!r}; expected 'Y' (LightFuse is +Y up)")
    root = stage.GetDefaultPrim() or stage.GetPseudoRoot()
    out = {}
    for prim in root.GetChildren():
        if not prim.IsA(UsdGeom.Xformable) or prim.GetName() == "background":
            continue
        m = np.array(UsdGeom.Xformable(prim).GetLocalTransformation(), dtype=np.float64).T  # row-vector
        out[prim.GetName()] = check_rigid(m, f"{path}: {prim.GetPath()}")
    return out


def read_layout_gltf(path: str, scene_index: int | None = None) -> dict:
    """Object nodes of a glTF scene (default scene) -> {name: 4x4}; nodes are the layout's
    transforms relative to the reference state (LightFuse scene convention)."""
    js, _ = read_gltf_json(path)
    scenes = js.get("scenes") or []
    si = js.get("scene", 0) if scene_index is None else scene_index
    if not scenes or si >= len(scenes):
        raise UserError(f"{path}: field 'scenes' has no scene {si}")
    nodes = js.get("nodes") or []
    out = {}
    for ni in scenes[si].get("nodes", []):
        nd = nodes[ni]
        name = nd.get("name")
        if not name or name == "background":
            continue
        out[name] = check_rigid(trs_to_matrix(nd), f"{path}: nodes[{ni}] ({name})")
    return out
