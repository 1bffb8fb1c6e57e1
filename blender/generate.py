"""Generate a synthetic multi-state LightFuse dataset (format ``lightfuse-dataset/1``).

Builds a procedural open room (``--preset bedroom|playroom|livingroom|kitchen|demo``, the
second family's ``study|gallery|workshop``: other shapes, materials and camera paths, or the
plain family's ``sunroom|atelier``: untextured floors and walls, procedural sun skies with hard
shadows, chrome and glossy objects; ``scenes.PLAIN``), then renders with Cycles on the CPU:

* K training states (``--states``, default 3): each a new seeded, physically plausible
  arrangement of the movable objects (upright on the floor or a furniture top, no overlap) under
  a different bundled HDRI (or procedural sun sky, ``lfenv.SUN_SKIES``) with a different
  rotation, from ``--views`` cameras around and above the room;
* one held-out test state ``test0`` (a new arrangement) rendered from the same cameras under
  ``--relight`` environments not used in training (the ``relight`` list).

Or your own scene (``--scene my.blend|my.glb --movable NAME,...``; ``ownscene.py`` and
``docs/own-scene.md``): the named objects (or collections) move, the rest is the background;
each state is a new arrangement on supports found by ray casting (or ``--layouts``, one
layout.json per state), seen by cameras placed around the objects (or ``--cameras scene|FILE``);
the scene's materials render as they are, its lights are dropped (environments only).

Per frame: linear HDR RGB (EXR, channels R G B), planar depth (EXR, channel Z, metres along the
camera's viewing axis, 0 = no hit), world-space unit normals (EXR, R G B = x y z in the Y-up
world, 0 = no hit), object-id mask (8-bit greyscale PNG, value = object id, 0 = background and
furniture) and albedo (EXR, R G B = the Principled base colour, 0 = no hit).  Depth, normals, mask
and albedo are sampled at the pixel centres (one sample, ~zero filter width); RGB is the
antialiased Cycles render.

Ground truth (never for training): ``object_poses`` (per state, per object, the Y-up 4x4 that
maps the object's points in state0 to its points in that state) and the environment maps in
``env/``.  Each ``env/*.exr`` is **already rotated and exposure-scaled**: it is exactly the map
Cycles used, with World rotation 0 and strength 1 (``environment_source`` records the source
HDRI, the rotation about +Y in degrees and the scale that produced it).  Also for evaluation only, each
object records ``reference_pose`` (its own frame, origin at its base centre, in state0's Y-up
world) and ``symmetries`` (rotations that leave it looking the same; ``scenes.SYMMETRIES``), so
pose errors can forgive what no image can tell apart, and ``material`` (``metallic`` and
``roughness``: its Principled BSDF inputs, area-weighted over its faces when its parts differ).

The scene is saved as ``scene.blend`` (objects at the reference state 0, a ``lightfuse`` record
with object ids and reference matrices), so ``render_layout.py`` can render any other layout.
The same ``--seed`` (and options) gives the same dataset.

Examples::

    .venv/bin/python blender/generate.py --demo --out data/demo
    .venv/bin/python blender/generate.py --preset kitchen --res 320x240 --views 24 --out data/kitchen
"""

from __future__ import annotations

import argparse
import math
import os
import random
import shutil
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import numpy as np  # noqa: E402

import lfio  # noqa: E402
from lfaxes import bl_to_yup_matrix, cam_bl_to_yup, intrinsics, rows, set_intrinsics  # noqa: E402
from lfblend import ID_PROP, SCENE_KEY  # noqa: E402
from lfcli import Parser, UserError, quiet_stdout, run_main  # noqa: E402
from lfenv import bundled_hdris, env_name, env_mean_luminance, load_env, resolve_hdri, rotate_env, setup_world  # noqa: E402
from lffiles import DATASET_FORMAT, write_json  # noqa: E402
from lfrender import frame_seed, make_tmpdir, render_beauty, render_geometry, setup_render, write_geometry  # noqa: E402

# The paper-like presets, the demo, and the second family (scenes.FAMILY: other shapes,
# materials and camera paths, for measuring on scenes nothing was tuned on).
PRESET_NAMES = ["bedroom", "playroom", "livingroom", "kitchen", "demo", "study", "gallery", "workshop",
                "sunroom", "atelier"]
# The plain family's (scenes.PLAIN) default size: the training side of the third-party scene
# issue 44 was found on (3 states x 16 views at 128 x 128, 3 test environments), with 8 test
# views (as scripts/paper_tables.sh's presets), which a 2-core machine generates in ~30 min.
PLAIN_SIZE = dict(res="128x128", views=16, test_views=8, states=3, spp=64, relight=3, max_bounces=4,
                  denoise=True)
# Captures are denoised (OpenImageDenoise, guided by albedo and normal) by default: a photograph
# is nearly noise-free, and 16-spp speckle alone would cap any reconstruction's PSNR against the
# demo's captures at ~28 dB (measured: raw 16 spp vs 512 spp, covered pixels).
DEMO = dict(res="128x96", views=8, states=3, spp=16, relight=5, max_bounces=4, denoise=True)
FULL = dict(res="320x240", views=24, states=3, spp=64, relight=5, max_bounces=4, denoise=True)


def parse_args(argv):
    p = Parser(prog="generate.py", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--preset", default=None, help=f"scene preset: {', '.join(PRESET_NAMES)} (default bedroom)")
    p.add_argument("--scene", help="your own scene instead of a preset: a .blend, .glb or .gltf (needs --movable)")
    p.add_argument("--movable", help="with --scene: comma-separated names of the objects (or collections: each of "
                                     "their top-level objects) that move between states; the rest is the background")
    p.add_argument("--layouts", help="with --scene: comma-separated layout.json files, one per training state and "
                                     "then the test state's (each movable's rigid motion from the scene as loaded, "
                                     "Y-up); default: a new random arrangement per state")
    p.add_argument("--cameras", help="with --scene: auto (default: around the movable objects, per state), scene "
                                     "(the scene's own cameras) or a JSON file of frames with transform_matrix")
    p.add_argument("--symmetry", action="append", metavar="NAME:ORDER",
                   help="with --scene: an object's symmetry about its vertical axis through its surface centroid "
                        "(0 continuous, n >= 2 n-fold, none), checked; repeatable. Default: detected by the same "
                        "check (surface and albedo)")
    p.add_argument("--demo", action="store_true",
                   help="small demo: preset 'demo', %(d)s unless overridden" % {"d": DEMO})
    p.add_argument("--res", help="WxH in pixels (default 320x240; demo 128x96)")
    p.add_argument("--views", type=int, help="cameras per state (default 24; demo 8)")
    p.add_argument("--test-views", type=int, help="cameras of the test state (default = --views)")
    p.add_argument("--states", type=int, help="training states K (default 3)")
    p.add_argument("--relight", type=int, help="test environments, not used in training (default 5; "
                                                "with --test-envs: all of those)")
    p.add_argument("--spp", type=int, help="Cycles samples per pixel (default 64; demo 16)")
    p.add_argument("--max-bounces", type=int, help="Cycles max bounces (default 4)")
    p.add_argument("--seed", type=int, default=0, help="random seed (arrangements, cameras, lighting, noise)")
    p.add_argument("--denoise", action=argparse.BooleanOptionalAction, default=None,
                   help="OpenImageDenoise the RGB (default on; --no-denoise keeps the path tracer's noise)")
    p.add_argument("--hdri-dir", help="folder of <name>.exr HDRIs (default: the ones bundled with bpy)")
    p.add_argument("--train-envs", help="comma-separated HDRI names or paths for the training states")
    p.add_argument("--test-envs", help="comma-separated HDRI names or paths for the test state")
    p.add_argument("--threads", type=int, default=2, help="Cycles CPU threads (default 2)")
    p.add_argument("--out", required=True, help="output dataset folder (created; must be empty or absent)")
    p.add_argument("--force", action="store_true", help="overwrite an existing non-empty --out")
    p.add_argument("--quiet", action="store_true", help="no per-frame progress lines")
    a = p.parse_args(argv)
    if a.scene is not None:
        if a.preset is not None or a.demo:
            raise UserError("--scene: give either --scene or --preset/--demo, not both")
        if not a.movable:
            raise UserError("--scene: --movable is required (the names of the objects that move between states)")
        a.preset = "own"
    else:
        for k in ("movable", "layouts", "cameras", "symmetry"):
            if getattr(a, k) is not None:
                raise UserError(f"--{k}: only with --scene (your own scene)")
    if a.preset is None:
        a.preset = "demo" if a.demo else "bedroom"
    if a.scene is not None:
        if a.layouts and a.states is None:
            a.states = max(len([x for x in a.layouts.split(",") if x.strip()]) - 1, 1)
        return _sized(a, FULL, {})
    if a.preset not in PRESET_NAMES:
        raise UserError(f"--preset: unknown preset {a.preset!r}; expected one of {', '.join(PRESET_NAMES)}")
    import bpy  # noqa: F401  (first: scenes' bmesh and mathutils come with it)
    import scenes

    base = DEMO if a.demo else PLAIN_SIZE if a.preset in scenes.PLAIN else FULL
    return _sized(a, base, {} if a.hdri_dir else scenes.PRESETS[a.preset])


def _sized(a, base: dict, spec: dict):
    """Fill the options left out from ``base`` (a size) and ``spec`` (a preset's environments),
    and check them."""
    # A preset that names its environments (the plain family's sun skies) uses them unless told
    # otherwise; --hdri-dir means the user's own HDRIs instead.
    if a.train_envs is None and "train_envs" in spec:
        a.train_envs = ",".join(spec["train_envs"])
    if a.test_envs is None and a.relight is None and "test_envs" in spec:
        a.test_envs = ",".join(spec["test_envs"])
    for k, v in base.items():
        if getattr(a, k) is None:
            setattr(a, k, v)
    try:
        w, h = (int(x) for x in a.res.lower().split("x"))
        assert 8 <= w <= 8192 and 8 <= h <= 8192
    except (ValueError, AssertionError):
        raise UserError(f"--res: expected WxH with 8..8192 pixels each, e.g. 128x96, got {a.res!r}") from None
    a.w, a.h = w, h
    if a.test_views is None:
        a.test_views = a.views
    for k in ("views", "test_views", "states", "spp", "threads"):
        if getattr(a, k) < 1:
            raise UserError(f"--{k.replace('_', '-')}: must be at least 1, got {getattr(a, k)}")
    if a.relight < 0 or a.max_bounces < 0:
        raise UserError("--relight and --max-bounces must be >= 0")
    return a


def choose_envs(a, rng: random.Random):
    """[(spec, where)] for training states and for the test state; distinct sets."""
    if a.hdri_dir:
        if not os.path.isdir(a.hdri_dir):
            raise UserError(f"--hdri-dir {a.hdri_dir}: folder not found")
        names = sorted(os.path.splitext(f)[0] for f in os.listdir(a.hdri_dir)
                       if f.lower().endswith((".exr", ".hdr")))
        if not names:
            raise UserError(f"--hdri-dir {a.hdri_dir}: no HDRI (.exr/.hdr) found in this folder")
    else:
        names = bundled_hdris()

    def stem(spec):
        return os.path.splitext(os.path.basename(spec))[0]

    if a.train_envs:
        train = [s.strip() for s in a.train_envs.split(",") if s.strip()]
    else:
        pool = names[:]
        rng.shuffle(pool)
        test_pool = pool[:a.relight] if not a.test_envs else []
        rest = [n for n in pool if n not in test_pool] or pool
        train = [rest[i % len(rest)] for i in range(a.states)]
    if a.test_envs:
        test = [s.strip() for s in a.test_envs.split(",") if s.strip()]
        a.relight = len(test)  # all of them
    else:
        test = [n for n in names if n not in {stem(t) for t in train}]
        rng.shuffle(test)
        test = test[:a.relight]
    if len(train) < a.states:
        train = [train[i % len(train)] for i in range(a.states)]
    if len(test) < a.relight:
        raise UserError(f"--relight {a.relight}: only {len(test)} environments not used in training are "
                        "available; lower --relight or pass --test-envs")
    train = [(resolve_hdri(s, a.hdri_dir, "--train-envs" if a.train_envs else "training environment"), s)
             for s in train[:a.states]]
    test = [(resolve_hdri(s, a.hdri_dir, "--test-envs" if a.test_envs else "test environment"), s)
            for s in test[:a.relight]]
    return train, test


def make_env(src: str, out_path: str, rng: random.Random, cache: dict) -> dict:
    """Write the rotated, exposure-normalised copy of an HDRI; return its provenance."""
    if src not in cache:
        cache[src] = load_env(src)
    env = cache[src]
    w = env.shape[1]
    shift = rng.randrange(w)
    scale = 1.0 / max(env_mean_luminance(env), 1e-6)
    lfio.write_rgb_exr(out_path, rotate_env(env, shift) * np.float32(scale))
    return {"name": env_name(src), "rotation_deg": shift * 360.0 / w,
            "scale": scale}


CAMERA_PATHS = ("orbit", "low", "high", "inside")


def make_cameras(rng: random.Random, n: int, size: float, w: int, h: int, lens: float = 35.0,
                 path: str = "orbit", furniture=()):
    """n cameras looking at the room's middle; Blender world matrices. ``path``: "orbit" around
    and above the room at 28-62° elevation (the presets'); "low" at 8-18° over the open sides
    (+x, +y: the walls stand at -x and -y); "high" at 65-82°; "inside" at eye height
    (1.0-1.6 m) within 0.25-0.6 m of the room's edges, inside it, clear of the furniture
    (``furniture``: ((x0, x1, y0, y1), top) pairs)."""
    import mathutils

    def look(eye, target):
        rot = (target - eye).to_track_quat("-Z", "Y").to_matrix().to_4x4()
        return np.array(mathutils.Matrix.Translation(eye) @ rot)

    if path not in CAMERA_PATHS:
        raise ValueError(path)
    if path == "inside":
        mats = []
        while len(mats) < n:
            side = rng.randrange(4)
            inset = rng.uniform(0.25, 0.6)
            along = rng.uniform(-size + 0.25, size - 0.25)
            x, y = [(-size + inset, along), (size - inset, along), (along, -size + inset), (along, size - inset)][side]
            z = rng.uniform(1.0, 1.6)
            if any(x0 - 0.15 < x < x1 + 0.15 and y0 - 0.15 < y < y1 + 0.15 and z < top + 0.3
                   for (x0, x1, y0, y1), top in furniture):
                continue
            target = mathutils.Vector((rng.uniform(-0.35, 0.35) * size, rng.uniform(-0.35, 0.35) * size,
                                       rng.uniform(0.2, 0.6)))
            mats.append(look(mathutils.Vector((x, y, z)), target))
        return mats
    vfov = 2 * math.atan(18.0 / lens * h / w)
    radius = size * 1.1
    dist = radius / math.sin(vfov / 2)
    if path in ("low", "high"):
        lo, hi = (math.radians(-70), math.radians(160)) if path == "low" else (0.0, 2 * math.pi)
        el_range = (8, 18) if path == "low" else (65, 82)
        mats = []
        for i in range(n):
            az = lo + (hi - lo) * (i + 0.5 + rng.uniform(-0.3, 0.3)) / n
            el = math.radians(rng.uniform(*el_range))
            d = dist * rng.uniform(0.9, 1.1)
            target = mathutils.Vector((rng.uniform(-0.15, 0.15) * size, rng.uniform(-0.15, 0.15) * size,
                                       rng.uniform(0.1, 0.35)))
            eye = target + d * mathutils.Vector((math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)))
            mats.append(look(eye, target))
        return mats
    az0 = rng.uniform(0, 2 * math.pi)
    mats = []
    for i in range(n):
        az = az0 + 2 * math.pi * (i + rng.uniform(-0.3, 0.3)) / n
        el = math.radians(rng.uniform(28, 62))
        d = dist * rng.uniform(0.9, 1.1)
        target = mathutils.Vector((rng.uniform(-0.15, 0.15) * size, rng.uniform(-0.15, 0.15) * size,
                                   rng.uniform(0.1, 0.35)))
        eye = target + d * mathutils.Vector((math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)))
        rot = (target - eye).to_track_quat("-Z", "Y").to_matrix().to_4x4()
        mats.append(np.array(mathutils.Matrix.Translation(eye) @ rot))
    return mats


def object_material(ob) -> dict:
    """Ground truth for evaluation: the Principled BSDF Metallic and Roughness inputs of the
    object's material slots, area-weighted over its faces (one slot: that slot's values)."""
    acc = np.zeros(2)
    total = 0.0
    for poly in ob.data.polygons:
        mat = ob.material_slots[poly.material_index].material
        bsdf = mat.node_tree.nodes["Principled BSDF"]
        acc += poly.area * np.array([bsdf.inputs["Metallic"].default_value, bsdf.inputs["Roughness"].default_value])
        total += poly.area
    m, r = acc / max(total, 1e-12)
    return {"metallic": round(float(m), 6), "roughness": round(float(r), 6)}


def frame_paths(prefix: str, geo_prefix: str, i: int) -> dict:
    return {"file_path": f"{prefix}/rgb/{i:03d}.exr",
            "depth_file_path": f"{geo_prefix}/depth/{i:03d}.exr",
            "normal_file_path": f"{geo_prefix}/normal/{i:03d}.exr",
            "mask_path": f"{geo_prefix}/mask/{i:03d}.png",
            "albedo_file_path": f"{geo_prefix}/albedo/{i:03d}.exr"}


def main(argv=None):
    a = parse_args(argv)
    t0 = time.time()
    final = os.path.abspath(a.out)
    if os.path.exists(final) and not os.path.isdir(final):
        raise UserError(f"--out {final}: exists and is not a folder")
    if os.path.isdir(final) and os.listdir(final) and not a.force:
        raise UserError(f"--out {final}: folder exists and is not empty; pass --force to overwrite")
    # everything is written to a sibling work folder, renamed into place when complete
    out = f"{final}.partial-{os.getpid()}"
    try:
        _run(a, out, final, t0)
    except BaseException:
        shutil.rmtree(out, ignore_errors=True)
        raise


def _run(a, out: str, final: str, t0: float) -> None:
    rng_env = random.Random(f"{a.seed}-env")
    train_envs, test_envs = choose_envs(a, rng_env)

    import bpy
    import mathutils

    import scenes

    if a.scene is None:
        bpy.ops.wm.read_factory_settings(use_empty=True)
        desc = scenes.build_scene(a.preset)
        movables = [(name, ob, [ob]) for name, ob, *_rest in desc["movables"]]
        meta = {name: {"symmetries": desc["symmetries"][name], "material": object_material(ob)}
                for name, ob, _parts in movables}
    else:
        import ownscene

        own = ownscene.OwnScene(a)  # opens or imports the scene: before anything is added to it
    sc = bpy.context.scene
    cam = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    sc.collection.objects.link(cam)
    sc.camera = cam
    cam.data.sensor_fit = "HORIZONTAL"
    cam.data.sensor_width = 36.0
    cam.data.lens = 35.0
    cam.data.clip_start = 0.05
    cam.data.clip_end = 1000.0
    sc.render.resolution_x, sc.render.resolution_y = a.w, a.h
    sc.render.resolution_percentage = 100
    setup_render(a.spp, a.max_bounces, a.denoise, a.threads)
    intr = intrinsics(cam.data, a.w, a.h)
    K = a.states
    if a.scene is None:
        arrangements = [scenes.arrange(desc, random.Random(f"{a.seed}-arrange-{k}")) for k in range(K + 1)]

        def views(k, n, rng):
            return [(m, intr) for m in make_cameras(rng, n, desc["size"], a.w, a.h, path=desc["cameras"],
                                                    furniture=list(zip(desc["obstacles"], desc["tops"])))]

        def frame(_name, world):
            return bl_to_yup_matrix(world)
    else:
        tmp = make_tmpdir()
        try:
            desc = ownscene.build(own, a, a.w, a.h, intr, tmp)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
        movables, meta, arrangements = desc["movables"], desc["meta"], desc["arrangements"]
        views, frame = desc["views"], desc["frame"]
        sc.camera = cam
    objects = [{"id": i + 1, "name": name, **meta[name]} for i, (name, *_r) in enumerate(movables)]
    for i, (name, ob, parts) in enumerate(movables):
        for o in parts:
            o.pass_index = i + 1
            o[ID_PROP] = i + 1
    for ob in bpy.data.objects:
        if ID_PROP not in ob:
            ob.pass_index = 0
            ob[ID_PROP] = 0

    if os.path.isdir(out):
        shutil.rmtree(out)
    os.makedirs(os.path.join(out, "env"))
    ref = arrangements[0]
    for o in objects:  # each object's own frame in the reference state (evaluation only)
        o["reference_pose"] = rows(frame(o["name"], ref[o["name"]]))

    def place(arr):
        for name, ob, *_r in movables:
            ob.matrix_world = mathutils.Matrix(arr[name].tolist())
        bpy.context.view_layer.update()

    def poses(arr):
        if arr is ref:  # the reference state: exactly the identity
            return {name: rows(np.eye(4)) for name, *_r in movables}
        return {name: rows(bl_to_yup_matrix(arr[name] @ np.linalg.inv(ref[name]))) for name, *_r in movables}

    tmp = make_tmpdir()
    current_intr = intr
    states = []
    env_cache: dict = {}
    nframes = 0
    try:
        for k in range(K + 1):
            is_test = k == K
            name = "test0" if is_test else f"state{k}"
            place(arrangements[k])
            rng_cam = random.Random(f"{a.seed}-cams-{k}")
            cams = views(k, a.test_views if is_test else a.views, rng_cam)
            rng_rot = random.Random(f"{a.seed}-envrot-{k}")
            st = {"name": name, "split": "test" if is_test else "train"}
            envs = test_envs if is_test else [train_envs[k]]
            runs = []
            for j, (src, spec) in enumerate(envs):
                ename = env_name(src)
                env_rel = f"env/{ename}.exr" if is_test else f"env/{name}.exr"
                if is_test and any(r["env_rel"] == env_rel for r in runs):
                    env_rel = f"env/{ename}_{j}.exr"
                prov = make_env(src, os.path.join(out, env_rel), rng_rot, env_cache)
                runs.append({"env_rel": env_rel, "prov": prov,
                             "prefix": f"{name}/{os.path.splitext(os.path.basename(env_rel))[0]}" if is_test else name,
                             "seed": a.seed * 1000 + k * 10 + j})
            if is_test:
                # Novel-state synthesis (the paper's Table 2): the test layout under each training
                # state's own lighting, the very environment file that state was rendered with.
                for i, t in enumerate(states):
                    runs.append({"env_rel": t["environment"], "prov": t["environment_source"],
                                 "prefix": f"{name}/{t['name']}", "training_state": t["name"],
                                 "seed": a.seed * 1000 + 900 + i})
            geo_prefix = name
            for sub in ("depth", "normal", "mask", "albedo"):
                os.makedirs(os.path.join(out, geo_prefix, sub), exist_ok=True)
            rels = []
            for r_i, run in enumerate(runs):
                os.makedirs(os.path.join(out, run["prefix"], "rgb"), exist_ok=True)
                setup_world(os.path.join(out, run["env_rel"]))
                frames = []
                for i, (m, view_intr) in enumerate(cams):
                    cam.matrix_world = mathutils.Matrix(m.tolist())
                    if view_intr != current_intr:  # a preset's never differ: its camera is untouched
                        set_intrinsics(cam.data, view_intr)
                        current_intr = view_intr
                    rel = frame_paths(run["prefix"], geo_prefix, i)
                    if r_i == 0:
                        write_geometry(out, rel, render_geometry(tmp))
                    rgb = render_beauty(tmp, a.spp, frame_seed(run["seed"], i))
                    lfio.write_rgb_exr(os.path.join(out, rel["file_path"]), rgb)
                    fr = dict(rel)
                    fr["transform_matrix"] = rows(cam_bl_to_yup(m))
                    fr.update(view_intr)
                    frames.append(fr)
                    nframes += 1
                    if not a.quiet:
                        print(f"[generate] {name} {os.path.basename(run['env_rel'])} view {i + 1}/{len(cams)} "
                              f"({time.time() - t0:.0f} s)", flush=True)
                rel = {"environment": run["env_rel"], "environment_source": run["prov"],
                       "render_seed": run["seed"], "frames": frames}
                if "training_state" in run:
                    rel["training_state"] = run["training_state"]
                rels.append(rel)
            st["object_poses"] = poses(arrangements[k])
            if is_test:
                st["relight"] = rels
            else:
                st.update(rels[0])
            states.append(st)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

    # save the scene at the reference state with state0's environment
    place(ref)
    setup_world(os.path.join(out, states[0]["environment"]))
    record = {"version": 1, "preset": a.preset, "objects": objects,
              "reference": {n: rows(ref[n]) for n, *_r in movables},
              "states": {s["name"]: s["object_poses"] for s in states}}
    import json

    sc[SCENE_KEY] = json.dumps(record)
    sc.cycles.seed = 0
    blend = os.path.join(out, "scene.blend")
    with quiet_stdout():
        bpy.ops.wm.save_as_mainfile(filepath=blend, relative_remap=True, compress=True)
    dataset = {
        "format": DATASET_FORMAT, "up": "+Y",
        "objects": objects,
        "scene": "scene.blend",
        "generator": {"tool": "blender/generate.py", "preset": a.preset, "seed": a.seed, "spp": a.spp,
                      "max_bounces": a.max_bounces, "denoise": a.denoise, "filter_width": 1.5,
                      "resolution": [a.w, a.h], "blender": bpy.app.version_string,
                      "mask_format": "png8", "depth_channel": "Z",
                      **({"scene": desc["source"], "cameras": a.cameras or "auto",
                          "layouts": bool(a.layouts)} if a.scene else {})},
        "states": states,
    }
    write_json(os.path.join(out, "dataset.json"), dataset)
    if os.path.isdir(final):
        shutil.rmtree(final)
    os.replace(out, final)
    out = final
    print(f"[generate] wrote {out}: {len(states)} states, {nframes} frames in {time.time() - t0:.1f} s", flush=True)


if __name__ == "__main__":
    run_main(main)
