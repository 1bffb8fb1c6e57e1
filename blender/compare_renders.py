#!/usr/bin/env python3
"""Compare LightFuse renders with Cycles renders of the same cameras: PSNR in sRGB.

``--ref`` is a ``render_layout.py`` output folder (``rgb/NAME.exr``, ``depth/NAME.exr``) or any
folder of ``NAME.exr`` files; ``--test`` is a ``lightfuse render`` output folder (``NAME.exr``
with R, G, B, A, Z, ...).  Views are matched by NAME.  Images are clamped to [0, 1] and encoded
with the sRGB OETF before the mean squared error (peak 1), like an 8-bit preview but without
quantisation.

Reported per view and averaged over views (mean of per-view PSNRs):

* ``all``: every pixel;
* ``background``: pixels where neither renderer saw a surface (LightFuse ``A == 0`` at every
  sample and, when the reference has a depth pass, Cycles depth 0): environment only.

Example::

    .venv/bin/python blender/compare_renders.py --ref /tmp/cmp/cycles --test /tmp/cmp/lf --json

Exit code 2 with a one-line message on bad input (missing folder, no common views, size mismatch).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import struct
import sys
import zlib

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import lfio  # noqa: E402
from lfcli import UserError  # noqa: E402


def read_exr(path: str) -> dict[str, np.ndarray]:
    if not os.path.isfile(path):
        raise UserError(f"{path}: cannot read (no such file)")
    try:
        return lfio.read_exr(path)
    except (struct.error, IndexError, KeyError, zlib.error, lfio.ExrError) as e:
        raise UserError(f"{path}: unreadable EXR ({e})") from None


def srgb(linear: np.ndarray) -> np.ndarray:
    x = np.clip(np.nan_to_num(linear, nan=0.0), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a - b) ** 2)) if a.size else float("nan")
    return float("inf") if mse == 0 else -10.0 * math.log10(mse)


def rgb(ch: dict[str, np.ndarray], path: str) -> np.ndarray:
    missing = [c for c in "RGB" if c not in ch]
    if missing:
        raise UserError(f"{path}: channels: expected R, G, B, missing {missing}")
    return np.stack([ch["R"], ch["G"], ch["B"]], -1)


def compare(ref_dir: str, test_dir: str) -> dict:
    for d in (ref_dir, test_dir):
        if not os.path.isdir(d):
            raise UserError(f"{d}: expected a folder of renders")
    ref_rgb_dir = os.path.join(ref_dir, "rgb") if os.path.isdir(os.path.join(ref_dir, "rgb")) else ref_dir
    ref_depth_dir = os.path.join(ref_dir, "depth")
    names = sorted(
        os.path.splitext(f)[0] for f in os.listdir(test_dir)
        if f.endswith(".exr") and os.path.exists(os.path.join(ref_rgb_dir, os.path.splitext(f)[0] + ".exr"))
    )
    if not names:
        raise UserError(f"{test_dir}: no NAME.exr with a matching {ref_rgb_dir}/NAME.exr")
    views = []
    for name in names:
        tp, rp = os.path.join(test_dir, name + ".exr"), os.path.join(ref_rgb_dir, name + ".exr")
        t, r = read_exr(tp), read_exr(rp)
        a, b = srgb(rgb(t, tp)), srgb(rgb(r, rp))
        if a.shape != b.shape:
            raise UserError(f"{tp}: size {a.shape[1]}x{a.shape[0]}, expected {b.shape[1]}x{b.shape[0]} as {rp}")
        bg = t["A"] == 0 if "A" in t else np.zeros(a.shape[:2], bool)
        dp = os.path.join(ref_depth_dir, name + ".exr")
        if os.path.exists(dp):
            z = read_exr(dp)
            zc = z.get("Z", z.get("R", z.get("V")))
            if zc is not None and zc.shape == bg.shape:
                bg &= zc == 0
        views.append({
            "view": name,
            "psnr_all": psnr(a, b),
            "psnr_background": psnr(a[bg], b[bg]) if bg.any() else None,
            "background_pixels": int(bg.sum()),
            "pixels": int(bg.size),
            "mean_linear_test": [float(v) for v in rgb(t, tp).reshape(-1, 3).mean(0)],
            "mean_linear_ref": [float(v) for v in rgb(r, rp).reshape(-1, 3).mean(0)],
        })
    bgs = [v["psnr_background"] for v in views if v["psnr_background"] is not None]
    return {
        "views": views,
        "psnr_all": float(np.mean([v["psnr_all"] for v in views])),
        "psnr_background": float(np.mean(bgs)) if bgs else None,
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="compare_renders.py", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--ref", required=True, help="reference (Cycles) render folder")
    p.add_argument("--test", required=True, help="LightFuse render folder")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    a = p.parse_args(argv)
    try:
        rep = compare(a.ref, a.test)
    except UserError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if a.json:
        print(json.dumps(rep, indent=1))
    else:
        for v in rep["views"]:
            bg = v["psnr_background"]
            print(f"{v['view']}: PSNR sRGB {v['psnr_all']:.2f} dB, background "
                  f"{'-' if bg is None else f'{bg:.2f} dB'} ({v['background_pixels']} px)")
        bg = rep["psnr_background"]
        print(f"mean over {len(rep['views'])} views: {rep['psnr_all']:.2f} dB, background "
              f"{'-' if bg is None else f'{bg:.2f} dB'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
