"""Small, dependency-free image I/O for the LightFuse Blender scripts.

* OpenEXR (scanline, single part) reader for the NONE, ZIPS and ZIP codecs, and a writer
  (ZIP codec, FLOAT channels).  This is all the scripts need: Cycles writes its multilayer
  render results uncompressed, and every dataset EXR is written here.  Other codecs (for
  example the PIZ/DWAB-compressed HDRIs bundled with Blender) are read through ``bpy`` instead
  (:func:`load_image_bpy`).
* 8-bit greyscale PNG writer/reader (object-id masks).

Arrays are numpy ``float32`` of shape (H, W, C), row 0 = top of the image.
"""

from __future__ import annotations

import os
import struct
import zlib

import numpy as np

EXR_MAGIC = 20000630
_COMP_NONE, _COMP_RLE, _COMP_ZIPS, _COMP_ZIP = 0, 1, 2, 3
_LINES = {_COMP_NONE: 1, _COMP_ZIPS: 1, _COMP_ZIP: 16}
_PTYPE = {0: np.dtype("<u4"), 1: np.dtype("<f2"), 2: np.dtype("<f4")}


class ExrError(ValueError):
    """A file is not an EXR this module can read (message names the file)."""


def _cstr(buf: bytes, pos: int) -> tuple[str, int]:
    end = buf.index(b"\0", pos)
    return buf[pos:end].decode("latin-1"), end + 1


def _unzip(data: bytes, expected: int) -> bytes:
    raw = np.frombuffer(zlib.decompress(data), dtype=np.uint8)
    if raw.size != expected:
        raise ExrError(f"ZIP chunk has {raw.size} bytes, expected {expected}")
    # Undo the predictor: t[0] = raw[0], t[i] = t[i-1] + raw[i] - 128 (mod 256).
    t = (np.cumsum(np.concatenate([[raw[0]], (raw[1:].astype(np.int64) - 128)])) & 0xFF).astype(np.uint8)
    half = (raw.size + 1) // 2
    out = np.empty_like(t)
    out[0::2] = t[:half]
    out[1::2] = t[half:]
    return out.tobytes()


def _zip(data: bytes) -> bytes:
    b = np.frombuffer(data, dtype=np.uint8)
    t = np.concatenate([b[0::2], b[1::2]])
    d = t.astype(np.int16)
    d[1:] = (t[1:].astype(np.int16) - t[:-1].astype(np.int16) + 128) & 0xFF
    return zlib.compress(d.astype(np.uint8).tobytes(), 6)


def read_exr_header(path: str) -> dict:
    with open(path, "rb") as f:
        buf = f.read()
    return _parse_header(buf, path)[0]


def _parse_header(buf: bytes, path: str):
    """Return (first part's header, position after the header(s)); see _parse_parts."""
    parts, pos, _ = _parse_parts(buf, path)
    return parts[0], pos


def _parse_one(buf: bytes, pos: int, path: str):
    hdr: dict = {}
    while buf[pos] != 0:
        name, pos = _cstr(buf, pos)
        typ, pos = _cstr(buf, pos)
        size = struct.unpack_from("<i", buf, pos)[0]
        pos += 4
        val = buf[pos:pos + size]
        pos += size
        if typ == "chlist":
            chans = []
            p = 0
            while val[p] != 0:
                cname, p = _cstr(val, p)
                ptype = struct.unpack_from("<i", val, p)[0]
                xs, ys = struct.unpack_from("<ii", val, p + 8)
                p += 16
                if xs != 1 or ys != 1:
                    raise ExrError(f"{path}: subsampled channel {cname!r} not supported")
                chans.append((cname, ptype))
            hdr[name] = chans
        elif typ == "compression":
            hdr[name] = val[0]
        elif typ == "box2i":
            hdr[name] = struct.unpack("<4i", val)
        elif typ == "int":
            hdr[name] = struct.unpack("<i", val)[0]
        elif typ == "string":
            hdr[name] = val.decode("latin-1")
        else:
            hdr[name] = (typ, val)
    return hdr, pos + 1


def _parse_parts(buf: bytes, path: str):
    if len(buf) < 8 or struct.unpack_from("<i", buf, 0)[0] != EXR_MAGIC:
        raise ExrError(f"{path}: not an OpenEXR file (bad magic number)")
    flags = struct.unpack_from("<I", buf, 4)[0]
    if flags & 0x200 or flags & 0x800:
        raise ExrError(f"{path}: tiled or deep EXR is not supported")
    multipart = bool(flags & 0x1000)
    pos = 8
    parts = []
    while True:
        hdr, pos = _parse_one(buf, pos, path)
        parts.append(hdr)
        if not multipart or buf[pos] == 0:
            break
    if multipart:
        pos += 1
    return parts, pos, multipart


def read_exr(path: str) -> dict[str, np.ndarray]:
    """Read every channel of a scanline EXR (single or multi-part): {name: float32 (H, W)}."""
    try:
        with open(path, "rb") as f:
            buf = f.read()
    except OSError as e:
        raise ExrError(f"{path}: cannot read ({e.strerror})") from None
    try:
        return _read_exr(buf, path)
    except (struct.error, IndexError, KeyError, zlib.error) as e:
        raise ExrError(f"{path}: truncated or malformed EXR ({e})") from None


def _read_exr(buf: bytes, path: str) -> dict[str, np.ndarray]:
    parts, pos, multipart = _parse_parts(buf, path)
    tables = []
    for hdr in parts:
        comp = hdr.get("compression", 0)
        if comp not in _LINES:
            raise ExrError(f"{path}: EXR compression {comp} not supported here (NONE, ZIPS, ZIP only)")
        x0, y0, x1, y1 = hdr["dataWindow"]
        h = y1 - y0 + 1
        n = hdr.get("chunkCount") or (h + _LINES[comp] - 1) // _LINES[comp]
        tables.append(struct.unpack_from(f"<{n}Q", buf, pos))
        pos += 8 * n
    out = {}
    for hdr, offsets in zip(parts, tables):
        comp = hdr.get("compression", 0)
        x0, y0, x1, y1 = hdr["dataWindow"]
        w, h = x1 - x0 + 1, y1 - y0 + 1
        chans = sorted(hdr["channels"], key=lambda c: c[0].encode())
        lines = _LINES[comp]
        res = {c: np.zeros((h, w), np.float32) for c, _ in chans}
        for off in offsets:
            if multipart:
                off += 4
            y, size = struct.unpack_from("<ii", buf, off)
            data = buf[off + 8: off + 8 + size]
            row0 = y - y0
            n = min(lines, h - row0)
            expected = sum(_PTYPE[t].itemsize for _, t in chans) * w * n
            if size < expected:
                data = _unzip(data, expected) if comp in (_COMP_ZIP, _COMP_ZIPS) else data
            p = 0
            for r in range(n):
                for cname, t in chans:
                    dt = _PTYPE[t]
                    res[cname][row0 + r] = np.frombuffer(data, dt, w, p).astype(np.float32)
                    p += dt.itemsize * w
        out.update(res)
    return out


def write_exr(path: str, channels: dict[str, np.ndarray]) -> None:
    """Write float32 channels {name: (H, W)} as a ZIP-compressed scanline EXR (atomically)."""
    names = sorted(channels, key=lambda c: c.encode())
    arrs = [np.ascontiguousarray(channels[n], dtype="<f4") for n in names]
    h, w = arrs[0].shape

    def attr(name, typ, val):
        return name.encode() + b"\0" + typ.encode() + b"\0" + struct.pack("<i", len(val)) + val

    ch = b"".join(n.encode() + b"\0" + struct.pack("<iB3xii", 2, 0, 1, 1) for n in names) + b"\0"
    header = struct.pack("<iI", EXR_MAGIC, 2)
    header += attr("channels", "chlist", ch)
    header += attr("compression", "compression", bytes([_COMP_ZIP]))
    header += attr("dataWindow", "box2i", struct.pack("<4i", 0, 0, w - 1, h - 1))
    header += attr("displayWindow", "box2i", struct.pack("<4i", 0, 0, w - 1, h - 1))
    header += attr("lineOrder", "lineOrder", bytes([0]))
    header += attr("pixelAspectRatio", "float", struct.pack("<f", 1.0))
    header += attr("screenWindowCenter", "v2f", struct.pack("<2f", 0.0, 0.0))
    header += attr("screenWindowWidth", "float", struct.pack("<f", 1.0))
    header += b"\0"
    chunks = []
    for y in range(0, h, 16):
        n = min(16, h - y)
        raw = b"".join(a[y + r].tobytes() for r in range(n) for a in arrs)
        z = _zip(raw)
        data = z if len(z) < len(raw) else raw
        chunks.append(struct.pack("<ii", y, len(data)) + data)
    table_pos = len(header)
    pos = table_pos + 8 * len(chunks)
    offs = []
    for c in chunks:
        offs.append(pos)
        pos += len(c)
    _atomic_write(path, header + struct.pack(f"<{len(offs)}Q", *offs) + b"".join(chunks))


def write_rgb_exr(path: str, rgb: np.ndarray) -> None:
    write_exr(path, {"R": rgb[..., 0], "G": rgb[..., 1], "B": rgb[..., 2]})


def read_rgb_exr(path: str) -> np.ndarray:
    ch = read_exr(path)
    if not all(c in ch for c in "RGB"):
        raise ExrError(f"{path}: expected channels R, G, B, found {sorted(ch)}")
    return np.stack([ch["R"], ch["G"], ch["B"]], -1)


def write_png_gray8(path: str, img: np.ndarray) -> None:
    """8-bit greyscale PNG (values clipped to 0..255)."""
    a = np.clip(np.asarray(img), 0, 255).astype(np.uint8)
    h, w = a.shape
    raw = b"".join(b"\0" + a[y].tobytes() for y in range(h))

    def chunk(t, d):
        return struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d) & 0xFFFFFFFF)

    png = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0))
    png += chunk(b"IDAT", zlib.compress(raw, 9)) + chunk(b"IEND", b"")
    _atomic_write(path, png)


def read_png_gray8(path: str) -> np.ndarray:
    """Read an 8-bit greyscale, non-interlaced PNG (any filter type) to uint8 (H, W)."""
    with open(path, "rb") as f:
        buf = f.read()
    if buf[:8] != b"\x89PNG\r\n\x1a\n":
        raise ValueError(f"{path}: not a PNG file")
    pos, idat, w = 8, b"", 0
    while pos < len(buf):
        n = struct.unpack_from(">I", buf, pos)[0]
        t = buf[pos + 4:pos + 8]
        d = buf[pos + 8:pos + 8 + n]
        pos += 12 + n
        if t == b"IHDR":
            w, h, depth, ctype, _, _, il = struct.unpack(">IIBBBBB", d)
            if depth != 8 or ctype != 0 or il:
                raise ValueError(f"{path}: expected 8-bit greyscale non-interlaced PNG")
        elif t == b"IDAT":
            idat += d
    raw = zlib.decompress(idat)
    out = np.zeros((h, w), np.uint8)
    prev = np.zeros(w, np.int32)
    for y in range(h):
        f = raw[y * (w + 1)]
        line = np.frombuffer(raw, np.uint8, w, y * (w + 1) + 1).astype(np.int32)
        cur = np.zeros(w, np.int32)
        for x in range(w):
            a = cur[x - 1] if x else 0
            b = prev[x]
            c = prev[x - 1] if x else 0
            if f == 0:
                p = 0
            elif f == 1:
                p = a
            elif f == 2:
                p = b
            elif f == 3:
                p = (a + b) // 2
            else:
                pa, pb, pc = abs(b - c), abs(a - c), abs(a + b - 2 * c)
                p = a if pa <= pb and pa <= pc else (b if pb <= pc else c)
            cur[x] = (line[x] + p) & 0xFF
        out[y] = cur
        prev = cur
    return out


def _atomic_write(path: str, data: bytes) -> None:
    tmp = path + ".tmp"
    with open(tmp, "wb") as f:
        f.write(data)
    os.replace(tmp, path)


def load_image_bpy(path: str) -> np.ndarray:
    """Any image Blender can read, as float32 RGB (H, W, 3), row 0 = top (needs bpy)."""
    import bpy

    img = bpy.data.images.load(path, check_existing=False)
    try:
        img.colorspace_settings.name = "Non-Color"  # raw values, no view transform
        w, h = img.size
        px = np.empty(w * h * 4, np.float32)
        img.pixels.foreach_get(px)
    finally:
        bpy.data.images.remove(img)
    return px.reshape(h, w, 4)[::-1, :, :3].copy()
