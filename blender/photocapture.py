"""A generated dataset as a capture that looks like photos, real COLMAP over it, and the
imported cameras against Blender's (issue 48's check of `lightfuse import colmap`).

    .venv/bin/python blender/photocapture.py DATASET WORK [--views N] [--seed S] [--lightfuse BIN]

renders each state of DATASET again along an orbit, as a person walking round the room shoots
it (`render_layout.py`: the state's layout and environment, VIEWS cameras 360/VIEWS degrees
apart at 30-40 degrees of elevation, with a little jitter; the generator's own cameras are too
far apart for SfM), writes WORK/photos/<state>/<view>.jpg (8-bit sRGB JPEG, auto-exposed per
photo with a random offset, clipped, with sensor noise), WORK/match_masks (the moved objects blanked for feature
matching, as a user masks them, and the environment, which differs per state here),
WORK/masks (the id masks, `<image name>.png`), runs pycolmap's
SIFT extraction, exhaustive matching and incremental mapping over every state at once
(WORK/sparse/0), imports it (WORK/dataset) and prints the cameras' error against the dataset's
after one similarity transform (Umeyama), as JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys

import numpy as np
from PIL import Image

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import lfio  # noqa: E402


def frames_of(state: dict) -> list[dict]:
    """A state's views: its own frames, or (a test state) those of its first environment."""
    if state.get("frames"):
        return state["frames"]
    return state["relight"][0]["frames"] if state.get("relight") else []


def srgb(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def look_target(frames: list[dict]) -> np.ndarray:
    """The point nearest (least squares) to every camera's optical axis: what they look at."""
    a, b = np.zeros((3, 3)), np.zeros(3)
    for f in frames:
        m = np.array(f["transform_matrix"])
        c, d = m[:3, 3], -m[:3, 2]
        p = np.eye(3) - np.outer(d, d)
        a += p
        b += p @ c
    return np.linalg.solve(a, b)


def orbit(frames: list[dict], views: int, rng, res: tuple[int, int], closer: float) -> list[dict]:
    """VIEWS cameras round the generator's cameras' target, at `closer` times their median
    distance, 30-40 degrees up, each looking at the target (+Y up, OpenGL axes), with the first
    frame's field of view at `res`."""
    target = look_target(frames)
    dist = closer * float(np.median([np.linalg.norm(np.array(f["transform_matrix"])[:3, 3] - target)
                                     for f in frames]))
    k = res[0] / frames[0]["w"]
    f0 = {"fl_x": frames[0]["fl_x"] * k, "fl_y": frames[0]["fl_y"] * k, "cx": frames[0]["cx"] * k,
          "cy": frames[0]["cy"] * k, "w": res[0], "h": res[1]}
    start = rng.uniform(0, 2 * np.pi)
    out = []
    for v in range(views):
        az = start + 2 * np.pi * v / views + rng.normal(0, 0.03)
        el = np.radians(35 + rng.uniform(-5, 5))
        eye = target + dist * np.array([np.cos(el) * np.cos(az), np.sin(el), np.cos(el) * np.sin(az)])
        back = (eye - target) / np.linalg.norm(eye - target)
        right = np.cross([0.0, 1.0, 0.0], back)
        right /= np.linalg.norm(right)
        up = np.cross(back, right)
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, up, back, eye
        out.append({"transform_matrix": m.tolist(), **{k: f0[k] for k in ("fl_x", "fl_y", "cx", "cy", "w", "h")}})
    return out


def render_orbits(ds_dir: str, work: str, views: int, seed: int, res: tuple[int, int],
                  closer: float) -> list[tuple[dict, str, list[dict]]]:
    """Each state rendered along an orbit; returns (state, folder, frames) with frame paths
    relative to the folder. Kept across runs (a state whose frames.json exists is not redone)."""
    rng = np.random.default_rng(seed)
    ds = json.load(open(os.path.join(ds_dir, "dataset.json")))
    here = os.path.dirname(os.path.abspath(__file__))
    out = []
    for st in ds["states"]:
        cams = orbit(frames_of(st), views, rng, res, closer)
        folder = os.path.join(work, "render", st["name"])
        if not os.path.isfile(os.path.join(folder, "frames.json")):
            os.makedirs(os.path.join(work, "render"), exist_ok=True)
            cam_file = os.path.join(work, "render", st["name"] + ".cameras.json")
            json.dump({"frames": cams}, open(cam_file, "w"))
            layout = os.path.join(work, "render", st["name"] + ".layout.json")
            json.dump({"format": "lightfuse-layout/1", "objects": st.get("object_poses", {})}, open(layout, "w"))
            subprocess.run([sys.executable, os.path.join(here, "render_layout.py"), "--dataset", ds_dir,
                            "--state", st["name"], "--cameras", cam_file, "--layout", layout,
                            "--out", folder, "--quiet"], check=True)
        frames = json.load(open(os.path.join(folder, "frames.json")))["frames"]
        out.append((st, folder, frames))
    return out


def make_capture(states: list[tuple[dict, str, list[dict]]], work: str, seed: int = 0) -> list[dict]:
    """Writes the photos and masks; returns [{name, state, split, transform_matrix}] of each."""
    rng = np.random.default_rng(seed + 1)
    shots = []
    for st, root, frames in states:
        for v, fr in enumerate(frames):
            exr = lfio.read_exr(os.path.join(root, fr["file_path"]))
            rgb = np.stack([exr["R"], exr["G"], exr["B"]], axis=-1)
            # Auto-exposure: the median luminance to 0.18, off by a random third of a stop or so.
            lum = rgb @ np.array([0.2126, 0.7152, 0.0722])
            gain = 0.18 / max(float(np.median(lum)), 1e-4) * float(np.exp(rng.normal(0.0, 0.25)))
            photo = rgb * gain + rng.normal(0.0, 0.004, size=rgb.shape)
            img = (srgb(photo) * 255.0 + 0.5).astype(np.uint8)
            name = f"{st['name']}/{v:03d}.jpg"
            path = os.path.join(work, "photos", name)
            os.makedirs(os.path.dirname(path), exist_ok=True)
            Image.fromarray(img).save(path, quality=92)
            ids = np.array(Image.open(os.path.join(root, fr["mask_path"])))
            # Matching sees the background only: not the moved objects (as a user masks them)
            # and not the environment (a different HDRI per state here, where a real room's
            # outside would be one world).
            depth = lfio.read_exr(os.path.join(root, fr["depth_file_path"]))["Z"]
            still = (ids == 0) & (depth > 0)
            for folder, arr in [("masks", ids.astype(np.uint8)),
                                ("match_masks", np.where(still, 255, 0).astype(np.uint8))]:
                p = os.path.join(work, folder, name + ".png")
                os.makedirs(os.path.dirname(p), exist_ok=True)
                Image.fromarray(arr).save(p)
            shots.append({"name": name, "state": st["name"], "split": st["split"],
                          "transform_matrix": fr["transform_matrix"]})
    return shots


def run_sfm(work: str, camera_model: str = "SIMPLE_RADIAL") -> str:
    """pycolmap over every photo at once; returns the model folder."""
    import pycolmap

    db = os.path.join(work, "database.db")
    if os.path.exists(db):
        os.remove(db)
    reader = pycolmap.ImageReaderOptions()
    reader.mask_path = os.path.join(work, "match_masks")
    reader.camera_model = camera_model
    # The presets' walls and floors are plain or softly striped: more, weaker SIFT features
    # (COLMAP's defaults are for photographs of textured places) and a lower bar for the first
    # pair and each registration.
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = 2
    extraction.sift.peak_threshold = 0.002
    extraction.sift.max_num_features = 8192
    pycolmap.extract_features(db, os.path.join(work, "photos"), reader_options=reader,
                              extraction_options=extraction,
                              camera_mode=pycolmap.CameraMode.SINGLE, device=pycolmap.Device.cpu)
    pycolmap.match_exhaustive(db, device=pycolmap.Device.cpu)
    sparse = os.path.join(work, "sparse")
    shutil.rmtree(sparse, ignore_errors=True)
    os.makedirs(sparse)
    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.mapper.init_min_num_inliers = 50
    mapping.mapper.abs_pose_min_num_inliers = 20
    mapping.min_model_size = 3
    mapping.random_seed = 0
    maps = pycolmap.incremental_mapping(db, os.path.join(work, "photos"), sparse, options=mapping)
    if not maps:
        raise RuntimeError("COLMAP registered no model")
    # The largest model, as sparse/0 (incremental_mapping numbers them from 0 in the order found).
    best = max(maps, key=lambda k: maps[k].num_reg_images())
    if best != 0:
        raise RuntimeError(f"COLMAP's largest model is {best}, not 0: {[m.num_reg_images() for m in maps.values()]}")
    return os.path.join(sparse, "0")


def umeyama(src: np.ndarray, dst: np.ndarray):
    """s, R, t minimising |s R src + t - dst|² (Umeyama 1991)."""
    ms, md = src.mean(0), dst.mean(0)
    a, b = src - ms, dst - md
    cov = b.T @ a / len(src)
    u, d, vt = np.linalg.svd(cov)
    e = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        e[2, 2] = -1
    r = u @ e @ vt
    s = np.trace(np.diag(d) @ e) / a.var(0).sum()
    return s, r, md - s * r @ ms


def camera_errors(shots: list[dict], dataset: str) -> dict:
    """The imported cameras against the generator's, after one similarity."""
    ds = json.load(open(os.path.join(dataset, "dataset.json")))
    got = {}
    for st in ds["states"]:
        for fr in st["frames"]:
            stem = os.path.splitext(os.path.basename(fr["file_path"]))[0]
            got[f"{st['name']}/{stem}.jpg"] = np.array(fr["transform_matrix"])
    names = [s["name"] for s in shots if s["name"] in got]
    truth = {s["name"]: np.array(s["transform_matrix"]) for s in shots}
    src = np.array([got[n][:3, 3] for n in names])
    dst = np.array([truth[n][:3, 3] for n in names])
    s, r, t = umeyama(src, dst)
    pos = np.linalg.norm((s * (r @ src.T)).T + t - dst, axis=1)
    rot = []
    for n in names:
        d = truth[n][:3, :3].T @ (r @ got[n][:3, :3])
        rot.append(np.degrees(np.arccos(np.clip((np.trace(d) - 1) / 2, -1, 1))))
    rot = np.array(rot)
    return {
        "registered": len(names), "photos": len(shots),
        "position_error_m": {"median": float(np.median(pos)), "max": float(pos.max())},
        "rotation_error_deg": {"median": float(np.median(rot)), "max": float(rot.max())},
        "scale_to_truth": float(s),
    }


def import_and_check(a, shots) -> dict:
    model = run_sfm(a.work, a.camera_model)
    out = os.path.join(a.work, "dataset")
    shutil.rmtree(out, ignore_errors=True)
    test = sorted({s["state"] for s in shots if s["split"] == "test"})
    cmd = [a.lightfuse, "--quiet", "import", "colmap", model, "--images", os.path.join(a.work, "photos"),
           "--masks", os.path.join(a.work, "masks"), "-o", out]
    if test:
        cmd += ["--test-states", ",".join(test)]
    subprocess.run(cmd, check=True)
    return camera_errors(shots, out)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("dataset")
    p.add_argument("work")
    p.add_argument("--views", type=int, default=24, help="photos per state (default 24: 15 degrees apart)")
    p.add_argument("--res", default="480x360", help="photo size WxH (default 480x360)")
    p.add_argument("--closer", type=float, default=0.75,
                   help="orbit radius over the generator's cameras' median distance (default 0.75)")
    p.add_argument("--camera-model", default="SIMPLE_RADIAL",
                   help="the COLMAP camera model SfM fits (default SIMPLE_RADIAL, COLMAP's own default)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--lightfuse", default="target/release/lightfuse")
    a = p.parse_args(argv)
    res = tuple(int(x) for x in a.res.lower().split("x"))
    shots = make_capture(render_orbits(a.dataset, a.work, a.views, a.seed, res, a.closer), a.work, a.seed)
    print(json.dumps(import_and_check(a, shots), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
