"""Render Cycles ground truth of a LightFuse scene under any layout, environment and cameras.

Opens a dataset's ``scene.blend`` (from ``generate.py``), moves the objects by a layout
(``layout.json``, or a ``.glb``/``.gltf`` whose default scene has nodes named like the objects,
transforms relative to the reference state, +Y up), lights it with an equirectangular
environment (file + rotation about +Y in degrees, as Cycles' Mapping Z rotation after the axis
change) and renders the given cameras with the same passes as the dataset: ``rgb/`` (linear
EXR), ``depth/`` (planar metres, 0 = no hit), ``normal/`` (Y-up world), ``mask/`` (8-bit PNG ids)
and ``albedo/``.  ``frames.json`` in ``--out`` lists the frames (dataset frame fields).

Cameras: ``--dataset D --state NAME`` (that state's frames; the first ``relight`` entry's for a
test state) or ``--cameras cameras.json`` (``{"frames": [...]}`` with ``transform_matrix``,
``fl_x, fl_y, cx, cy, w, h``).

With ``--dataset`` and ``--state``, defaults come from the dataset: the state's environment, its
render seed, and the generator's spp, bounces and denoising; so rendering a state's own layout reproduces
its images.  ``--max-bounces 1`` matches a one-bounce estimator.

Example::

    .venv/bin/python blender/render_layout.py --dataset data/demo --state state1 \\
        --layout my_layout.json --env data/demo/env/test0_forest.exr --env-rotation 30 --out data/render
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import lfio  # noqa: E402
from lfaxes import rows, set_camera  # noqa: E402
from lfblend import apply_layout_bl, get_record, open_blend  # noqa: E402
from lfcli import Parser, UserError, run_main  # noqa: E402
from lfenv import resolve_hdri, setup_world  # noqa: E402
from lffiles import DATASET_FORMAT, read_json, read_layout, write_json  # noqa: E402
from lfrender import frame_seed, make_tmpdir, render_beauty, render_geometry, setup_render, write_geometry  # noqa: E402


def parse_args(argv):
    p = Parser(prog="render_layout.py", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--dataset", help="dataset folder (dataset.json + scene.blend)")
    p.add_argument("--scene", help="scene .blend (default: DATASET/scene.blend)")
    p.add_argument("--state", help="take cameras (and defaults) from this dataset state")
    p.add_argument("--cameras", help="cameras.json: {\"frames\": [...]} with dataset frame fields")
    p.add_argument("--layout", help="layout.json or .glb/.gltf with named object nodes (default: reference layout)")
    p.add_argument("--env", help="equirectangular environment .exr/.hdr or a bundled HDRI name "
                                 "(default: the state's environment)")
    p.add_argument("--env-rotation", type=float, default=0.0, help="rotation of the map about +Y, degrees")
    p.add_argument("--env-strength", type=float, default=1.0, help="environment strength multiplier")
    p.add_argument("--spp", type=int, help="samples per pixel (default: the dataset's, else 64)")
    p.add_argument("--max-bounces", type=int, help="max light bounces (default: the dataset's, else 4)")
    p.add_argument("--seed", type=int, help="seed; frame i uses frame_seed(seed, i) (default: the state's)")
    p.add_argument("--denoise", action=argparse.BooleanOptionalAction, default=None,
                   help="OpenImageDenoise the RGB (default: as the dataset was generated, else off)")
    p.add_argument("--rgb-only", action="store_true", help="skip depth/normal/mask/albedo")
    p.add_argument("--threads", type=int, default=2, help="Cycles CPU threads (default 2)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--quiet", action="store_true", help="no per-frame progress lines")
    return p.parse_args(argv)


def main(argv=None):
    a = parse_args(argv)
    t0 = time.time()
    ds = None
    if a.dataset:
        ds = read_json(os.path.join(a.dataset, "dataset.json"), "a LightFuse dataset.json")
        if ds.get("format") != DATASET_FORMAT:
            raise UserError(f"{os.path.join(a.dataset, 'dataset.json')}: field 'format' must be "
                            f"{DATASET_FORMAT!r}")
    scene_path = a.scene or (os.path.join(a.dataset, ds.get("scene", "scene.blend")) if ds else None)
    if not scene_path:
        raise UserError("command line: give --scene FILE.blend or --dataset DIR")
    if not os.path.isfile(scene_path):
        raise UserError(f"{scene_path}: scene file not found")

    # cameras and defaults
    frames, state, run = None, None, None
    if a.state:
        if not ds:
            raise UserError("--state needs --dataset")
        states = {s.get("name"): s for s in ds.get("states", [])}
        if a.state not in states:
            raise UserError(f"--state: no state {a.state!r} in {a.dataset}/dataset.json; states are "
                            f"{', '.join(states)}")
        state = states[a.state]
        run = state["relight"][0] if "relight" in state and "frames" not in state else state
        frames = run["frames"]
    if a.cameras:
        cj = read_json(a.cameras, "a cameras.json")
        frames = cj.get("frames") if isinstance(cj, dict) else cj
        if not isinstance(frames, list) or not frames:
            raise UserError(f"{a.cameras}: field 'frames' must be a non-empty list of frames")
        for i, f in enumerate(frames):
            if isinstance(f, dict):
                f["_where"] = f"{a.cameras}: frames[{i}]"
    if frames is None:
        raise UserError("command line: give cameras with --cameras FILE or --dataset DIR --state NAME")
    gen = (ds or {}).get("generator", {})
    spp = a.spp or gen.get("spp", 64)
    bounces = a.max_bounces if a.max_bounces is not None else gen.get("max_bounces", 4)
    seed = a.seed if a.seed is not None else (run or {}).get("render_seed", 0)
    denoise = a.denoise if a.denoise is not None else bool(gen.get("denoise", False))
    if a.env:
        env_path = resolve_hdri(a.env, None, "--env")
    elif run and run.get("environment"):
        env_path = os.path.join(a.dataset, run["environment"])
        if not os.path.isfile(env_path):
            raise UserError(f"{env_path}: environment of state {a.state!r} not found")
    else:
        raise UserError("command line: give --env FILE (or --dataset DIR --state NAME)")

    import bpy

    open_blend(scene_path)
    rec = get_record(scene_path)
    layout = read_layout(a.layout) if a.layout else {}
    apply_layout_bl(rec, layout, a.layout or "layout")
    sc = bpy.context.scene
    cam = sc.camera
    if cam is None:
        cam = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
        sc.collection.objects.link(cam)
        sc.camera = cam
    setup_render(spp, bounces, denoise, a.threads)
    setup_world(env_path, a.env_rotation, a.env_strength)

    out = os.path.abspath(a.out)
    for sub in ("rgb",) + (() if a.rgb_only else ("depth", "normal", "mask", "albedo")):
        os.makedirs(os.path.join(out, sub), exist_ok=True)
    tmp = make_tmpdir()
    out_frames = []
    try:
        for i, f in enumerate(frames):
            if not isinstance(f, dict):
                raise UserError(f"frames[{i}]: expected an object with camera fields")
            f.setdefault("_where", f"frames[{i}]")
            set_camera(cam, f)
            rel = {"file_path": f"rgb/{i:03d}.exr"}
            if not a.rgb_only:
                rel.update({"depth_file_path": f"depth/{i:03d}.exr", "normal_file_path": f"normal/{i:03d}.exr",
                            "mask_path": f"mask/{i:03d}.png", "albedo_file_path": f"albedo/{i:03d}.exr"})
                write_geometry(out, rel, render_geometry(tmp))
            rgb = render_beauty(tmp, spp, frame_seed(seed, i))
            lfio.write_rgb_exr(os.path.join(out, rel["file_path"]), rgb)
            fr = dict(rel)
            for k in ("transform_matrix", "fl_x", "fl_y", "cx", "cy", "w", "h"):
                fr[k] = f[k]
            out_frames.append(fr)
            if not a.quiet:
                print(f"[render_layout] view {i + 1}/{len(frames)} ({time.time() - t0:.0f} s)", flush=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    write_json(os.path.join(out, "frames.json"), {
        "frames": out_frames, "environment": os.path.abspath(env_path), "environment_rotation": a.env_rotation,
        "layout": {k: rows(v) for k, v in layout.items()}, "spp": spp, "max_bounces": bounces, "denoise": denoise,
        "seed": seed})
    print(f"[render_layout] wrote {len(out_frames)} frames to {out} in {time.time() - t0:.1f} s", flush=True)


if __name__ == "__main__":
    run_main(main)
