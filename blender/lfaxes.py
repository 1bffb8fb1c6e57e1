"""Axes, matrices and cameras of the LightFuse Blender scripts.

Conventions (``docs/design.md`` §2):

* World: right-handed, +Y up, metres.  A Blender point (x, y, z) is (x, z, -y) in LightFuse;
  ``C`` below is that change of basis, and a Blender 4x4 transform ``M`` becomes
  ``C4 @ M @ C4^-1``.
* Cameras: camera-to-world 4x4, OpenGL style (looks down -Z, +Y up).  A Blender camera object's
  local frame already is OpenGL style, so ``c2w = C4 @ camera.matrix_world``.  Intrinsics are
  ``fl_x, fl_y, cx, cy, w, h`` in pixels, pixel centres at +0.5.
* Matrices in JSON: 4x4 as a list of 4 rows.
"""

from __future__ import annotations

import numpy as np

from lfcli import UserError

# Blender (x, y, z) -> LightFuse (x, z, -y)
C3 = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])
C4 = np.eye(4)
C4[:3, :3] = C3
C4_INV = C4.T.copy()


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
    set_intrinsics(cam_obj.data, {"fl_x": fx, "cx": cx, "cy": cy, "w": w, "h": h})
    import bpy

    sc = bpy.context.scene
    sc.render.resolution_x = w
    sc.render.resolution_y = h
    sc.render.resolution_percentage = 100


def set_intrinsics(cd, intr: dict) -> None:
    """Set a Blender camera's data from pixel intrinsics (``fl_x``, ``cx``, ``cy``, ``w``, ``h``;
    square pixels): the inverse of :func:`intrinsics`, with the principal point as a lens shift.
    The render resolution is the caller's."""
    w, h = int(intr["w"]), int(intr["h"])
    cd.type = "PERSP"
    cd.sensor_fit = "HORIZONTAL"
    cd.sensor_width = 36.0
    cd.lens = float(intr["fl_x"]) / w * cd.sensor_width
    # principal point offset: Blender shift is in units of the larger image dimension
    cd.shift_x = -(float(intr["cx"]) - w / 2.0) / max(w, h)
    cd.shift_y = (float(intr["cy"]) - h / 2.0) / max(w, h)
