"""Writes the COLMAP fixtures `tests/colmap.rs` reads, with real COLMAP (pycolmap, pinned in
blender/requirements.txt): a small reconstruction as COLMAP's binary and text models, and every
camera model's projection of a fixed set of camera-frame points (`lens.json`).

Run from the repository root: `.venv/bin/python tests/data/colmap/make_fixtures.py`. The files
are committed (a few kB) so the Rust tests need no Python; rerun this when pycolmap's pin moves.
"""

import json
import os

import numpy as np
import pycolmap

HERE = os.path.dirname(os.path.abspath(__file__))

# Plausible parameters per model: focal lengths ~ the image width, principal point near the
# centre, distortion strong enough to matter at the border (|displacement| of pixels) but
# monotonic over the image, as calibrated lenses are.
PARAMS = {
    "SIMPLE_PINHOLE": [70.0, 32.5, 23.5],
    "PINHOLE": [72.0, 68.0, 31.0, 25.0],
    "SIMPLE_RADIAL": [70.0, 32.0, 24.0, -0.12],
    "RADIAL": [70.0, 32.0, 24.0, -0.10, 0.03],
    "OPENCV": [72.0, 69.0, 31.5, 24.5, -0.11, 0.02, 0.002, -0.001],
    "OPENCV_FISHEYE": [40.0, 41.0, 32.0, 24.0, 0.05, -0.01, 0.004, -0.001],
    "FULL_OPENCV": [72.0, 69.0, 31.5, 24.5, -0.11, 0.02, 0.002, -0.001, 0.004, 0.01, -0.005, 0.002],
    "FOV": [60.0, 61.0, 32.0, 24.0, 0.6],
    "SIMPLE_RADIAL_FISHEYE": [40.0, 32.0, 24.0, 0.04],
    "RADIAL_FISHEYE": [40.0, 32.0, 24.0, 0.04, -0.01],
    "THIN_PRISM_FISHEYE": [40.0, 41.0, 32.0, 24.0, 0.04, -0.01, 0.002, -0.001, 0.003, -0.001, 0.001, -0.002],
    "RAD_TAN_THIN_PRISM_FISHEYE": [40.0, 41.0, 32.0, 24.0, 0.04, -0.01, 0.003, -0.001, 0.0005, -0.0002,
                                   0.002, -0.001, 0.001, -0.002, 0.0005, 0.0003],
    "SIMPLE_DIVISION": [70.0, 32.0, 24.0, -0.1],
    "DIVISION": [72.0, 69.0, 31.5, 24.5, -0.1],
    "SIMPLE_FISHEYE": [40.0, 32.0, 24.0],
    "FISHEYE": [40.0, 41.0, 32.0, 24.0],
    "EUCM": [40.0, 41.0, 32.0, 24.0, 0.6, 1.1],
    "EQUIRECTANGULAR": [64.0, 32.0],
}


def lens_fixture():
    rng = np.random.default_rng(7)
    # Directions within ~35 degrees of the axis (inside every model's valid range), z = 1..3.
    xy = rng.uniform(-0.7, 0.7, size=(24, 2))
    z = rng.uniform(1.0, 3.0, size=(24, 1))
    cam = np.hstack([xy * z, z])
    out = []
    for name, params in PARAMS.items():
        c = pycolmap.Camera.create_from_model_name(1, name, 50.0, 64, 48)
        c.params = params
        entry = {"model": name, "model_id": int(c.model.value), "width": 64, "height": 48,
                 "params": params}
        if name == "EQUIRECTANGULAR":
            entry["pixels"] = None
        else:
            pix = c.img_from_cam(cam, check_cheirality=False)
            entry["pixels"] = pix.tolist()
        out.append(entry)
    return {"generator": f"pycolmap {pycolmap.__version__}", "camera_points": cam.tolist(),
            "models": out}


def reconstruction():
    rec = pycolmap.Reconstruction()
    cams = [
        pycolmap.Camera.create_from_model_name(1, "PINHOLE", 50.0, 64, 48),
        pycolmap.Camera.create_from_model_name(2, "OPENCV", 50.0, 64, 48),
        pycolmap.Camera.create_from_model_name(3, "SIMPLE_RADIAL", 50.0, 32, 24),
    ]
    cams[0].params = PARAMS["PINHOLE"]
    cams[1].params = PARAMS["OPENCV"]
    cams[2].params = [35.0, 16.0, 12.0, -0.05]
    for c in cams:
        rec.add_camera_with_trivial_rig(c)
    rng = np.random.default_rng(3)
    names = ["state0/IMG_0001.jpg", "state0/IMG_0002.jpg", "state1/IMG_0101.jpg",
             "test/IMG_0201.jpg"]
    points = rng.uniform(-1, 1, size=(6, 3)) + np.array([0, 0, 4.0])
    point_ids = [rec.add_point3D(p, pycolmap.Track(), np.array([200, 100, 50], np.uint8))
                 for p in points]
    for i, name in enumerate(names):
        cam = cams[i % 3]
        angle = 0.2 * i
        q = np.array([np.cos(angle / 2), 0.1, np.sin(angle / 2), 0.05])
        q /= np.linalg.norm(q)
        # pycolmap's Rotation3d takes xyzw.
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([q[1], q[2], q[3], q[0]])),
                                np.array([0.3 * i, -0.1, 0.2]))
        pix = []
        for p in points:
            pc = pose * p
            pix.append(cam.img_from_cam(pc))
        img = pycolmap.Image(name=name, keypoints=np.array(pix), camera_id=cam.camera_id,
                             image_id=i + 1)
        rec.add_image_with_trivial_frame(img, pose)
        for k, pid in enumerate(point_ids):
            rec.add_observation(pid, pycolmap.TrackElement(i + 1, k))
    rec.update_point_3d_errors()
    return rec


def main():
    with open(os.path.join(HERE, "lens.json"), "w") as f:
        json.dump(lens_fixture(), f, indent=1)
        f.write("\n")
    rec = reconstruction()
    for kind, write in [("bin", rec.write_binary), ("txt", rec.write_text)]:
        d = os.path.join(HERE, "model_" + kind)
        os.makedirs(d, exist_ok=True)
        write(d)
    truth = {"generator": f"pycolmap {pycolmap.__version__}", "images": {}, "points": {}}
    for iid, img in rec.images.items():
        m = img.cam_from_world().matrix()
        truth["images"][img.name] = {"image_id": iid, "camera_id": img.camera_id,
                                     "cam_from_world": m.tolist(),
                                     "num_points2D": img.num_points2D()}
    for pid, p in rec.points3D.items():
        truth["points"][str(pid)] = {"xyz": p.xyz.tolist(), "error": p.error,
                                     "track_length": p.track.length()}
    truth["cameras"] = {str(cid): {"model": c.model.name, "params": list(c.params),
                                   "width": c.width, "height": c.height}
                        for cid, c in rec.cameras.items()}
    with open(os.path.join(HERE, "model_truth.json"), "w") as f:
        json.dump(truth, f, indent=1)
        f.write("\n")


if __name__ == "__main__":
    main()
