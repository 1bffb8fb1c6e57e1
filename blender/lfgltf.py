"""glTF as LightFuse scenes use it (docs/formats.md): the extension and attribute names, the one
reader of .glb / .gltf files, accessors and node transforms."""

from __future__ import annotations

import json
import os
import struct

import numpy as np

from lfcli import UserError

KHR = "KHR_gaussian_splatting"
EXT = "LIGHTFUSE_gaussian_surfels"
# attributes of a splat primitive
ATTR_ROTATION = f"{KHR}:ROTATION"
ATTR_SCALE = f"{KHR}:SCALE"
ATTR_OPACITY = f"{KHR}:OPACITY"
ATTR_SH_PREFIX = f"{KHR}:SH_DEGREE_"  # then "<l>_COEF_<n>"
ATTR_BASE_COLOR = f"{EXT}:BASE_COLOR"
ATTR_METALLIC = f"{EXT}:METALLIC"
ATTR_ROUGHNESS = f"{EXT}:ROUGHNESS"
# the GLB container
GLB_MAGIC = b"glTF"
CHUNK_JSON = 0x4E4F534A
CHUNK_BIN = 0x004E4942

_CTYPES = {5126: np.float32, 5125: np.uint32, 5123: np.uint16, 5121: np.uint8, 5122: np.int16, 5120: np.int8}
_NCOMP = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}


def attr_sh(degree: int, coef: int) -> str:
    """The attribute name of spherical-harmonic coefficient ``coef`` of degree ``degree``."""
    return f"{ATTR_SH_PREFIX}{degree}_COEF_{coef}"


def read_gltf_json(path: str) -> tuple[dict, bytes | None]:
    """A .glb (JSON chunk, BIN chunk or None) or a .gltf (JSON, None)."""
    try:
        with open(path, "rb") as f:
            data = f.read()
    except OSError as e:
        raise UserError(f"{path}: cannot read ({e.strerror})") from None
    if data[:4] == GLB_MAGIC:
        try:
            _, _, total = struct.unpack_from("<4sII", data, 0)
            clen, ctype = struct.unpack_from("<II", data, 12)
            if ctype != CHUNK_JSON:
                raise ValueError("first chunk is not JSON")
            js = json.loads(data[20:20 + clen].decode("utf-8"))
            binc = None
            p = 20 + clen
            if p + 8 <= len(data):
                blen, btype = struct.unpack_from("<II", data, p)
                if btype == CHUNK_BIN:
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


def read_accessor(js: dict, binc: bytes | None, base_dir: str, idx, where: str) -> np.ndarray:
    try:
        acc = js["accessors"][idx]
        n = acc["count"]
        nc = _NCOMP[acc["type"]]
        dt = np.dtype(_CTYPES[acc["componentType"]]).newbyteorder("<")
        if "bufferView" not in acc:
            return np.zeros((n, nc), np.float32)
        bv = js["bufferViews"][acc["bufferView"]]
        buf = js["buffers"][bv["buffer"]]
    except (KeyError, IndexError, TypeError) as e:
        raise UserError(f"{where}: accessor {idx} is malformed ({e})") from None
    if "uri" in buf:
        if buf["uri"].startswith("data:"):
            raise UserError(f"{where}: data: URIs are not supported")
        p = os.path.join(base_dir, buf["uri"])
        try:
            with open(p, "rb") as f:
                data = f.read()
        except OSError:
            raise UserError(f"{where}: buffer file {p} not found") from None
    else:
        if binc is None:
            raise UserError(f"{where}: buffer {bv['buffer']} has no uri and the file has no BIN chunk")
        data = binc
    start = bv.get("byteOffset", 0) + acc.get("byteOffset", 0)
    stride = bv.get("byteStride", dt.itemsize * nc)
    need = start + stride * (n - 1) + dt.itemsize * nc if n else start
    if need > len(data) or need > bv.get("byteOffset", 0) + bv["byteLength"]:
        raise UserError(f"{where}: accessor {idx} needs {need} bytes, the buffer view/buffer is shorter "
                        "(truncated file?)")
    arr = np.lib.stride_tricks.as_strided(
        np.frombuffer(data, dtype=np.uint8, count=len(data) - start, offset=start),
        shape=(n, nc * dt.itemsize), strides=(stride, 1)).copy().view(dt).reshape(n, nc)
    arr = arr.astype(np.float32)
    if acc.get("normalized") and dt.kind in "ui":
        arr /= np.iinfo(dt).max
    if not np.all(np.isfinite(arr)):
        raise UserError(f"{where}: accessor {idx} contains NaN or infinite values")
    return arr


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
