"""A user's own scene (``generate.py --scene my.blend|my.glb --movable NAME,...``) as the
generator's scene: the movable objects, their states, the cameras and the ground truth.

What a preset builds procedurally (``scenes.py``) is found here in whatever the user brings:

* **Movable objects.** Each ``--movable`` name is a scene object (with its children: one rigid
  body, moved by its root) or a collection (each of its top-level objects is one movable). The
  rest of the scene is the background. A movable must be a closed surface of non-zero area
  (contact and interpenetration are checked on it).
* **States** (:func:`arrange`). By default each training state, and the test state, is a new
  arrangement: in a random order, each object is turned about the vertical by a random angle
  (upright as the scene has it) and stood at a random place on a support found by casting rays
  straight down (every upward-facing surface under that place: floor, table tops, shelves; not by
  name) whose footprint rays all meet it within FLAT_TOL, CONTACT_GAP above it; the place is
  kept when the object's triangles cross nothing (background or objects placed before), it is
  not inside a solid, and, with fixed cameras, some camera sees it. With ``--layouts`` the states
  are the user's: one layout.json per state (the rigid motion of each movable from the scene as
  loaded, Y-up, as ``export_layout.py`` writes), checked for rest (contact within REST_TOL under
  the footprint) and interpenetration.
* **Cameras** (:func:`auto_views`). By default, per state, cameras around the movable objects
  inside the scene: each aims at one object (in turn), from an elevation of 15-60°, at a distance
  that frames it with its surroundings, moved in where the line of sight to the object meets
  anything (no camera behind a wall), and refused inside a solid or outside the scene's bounds.
  ``--cameras scene`` renders from the scene's own cameras with their intrinsics;
  ``--cameras FILE`` from a JSON list of frames (``transform_matrix``, Y-up camera-to-world, and
  optional ``fl_x fl_y cx cy``).
* **Ground truth.** Each movable's metallic and roughness where every face's material is a
  Principled BSDF with plain (unlinked) inputs, area-weighted; otherwise the object records
  why not (``material_note``) and no numbers. The albedo pass is each material's Principled
  Base Color (its link or value) through an AOV added here; a material without a Principled BSDF
  writes 0 there and is named on stderr. Symmetries: the user's (``--symmetry NAME:ORDER``, about
  the vertical axis through the object's surface centroid, checked) or detected
  (:func:`detect_symmetries`: the vertical axis through the centroid, continuous or n-fold,
  accepted only when the surface and the albedo pass both map onto themselves,
  ``lfsymmetry``). Never guessed.
* **Lights.** The dataset is lit by environments only: the scene's lights are removed and named.

Geometry here is in Blender's world frame (Z up, metres) until it is written.
"""

from __future__ import annotations

import math
import os
import random
import sys

import numpy as np

import lfsymmetry
from lfaxes import bl_to_yup_matrix, bl_to_yup_points, yup_to_bl_matrix
from lfcli import UserError, quiet_stdout
from lffiles import read_json, read_layout

MOVE_TRIES = 600  # places tried per object and state before giving up
CONTACT_GAP = 5e-4  # an arranged object stands this far above its support: its base crosses nothing
FLAT_TOL = 3e-3  # every footprint ray must meet the support within this of its height
REST_TOL = 2e-3  # a given layout's object must have a surface within this under its base
PENETRATION_TOL = 1e-3  # a given layout's object lifted by this must cross nothing
UP_COS = 0.95  # a support's normal within ~18° of vertical
VIEW_TRIES = 400
GEOMETRY_TYPES = {"MESH", "CURVE", "SURFACE", "META", "FONT", "CURVES"}
CANDIDATE_ORDERS = (0, 8, 6, 5, 4, 3, 2)  # continuous first, then n-fold from the largest


# ----------------------------------------------------------------------------- loading


def load(path: str) -> list[str]:
    """Open a .blend, or import a .glb/.gltf into an empty scene; remove the scene's lights.
    Returns the names and types of the lights removed."""
    import bpy

    if not os.path.isfile(path):
        raise UserError(f"--scene {path}: file not found")
    low = path.lower()
    if low.endswith(".blend"):
        from lfblend import open_blend

        open_blend(path)
    elif low.endswith((".glb", ".gltf")):
        bpy.ops.wm.read_factory_settings(use_empty=True)
        try:
            with quiet_stdout():
                bpy.ops.import_scene.gltf(filepath=os.path.abspath(path))
        except RuntimeError as e:
            raise UserError(f"--scene {path}: cannot import as glTF ({str(e).strip().splitlines()[-1]})") from None
    else:
        raise UserError(f"--scene {path}: expected a .blend, .glb or .gltf file")
    lights = []
    for ob in list(bpy.data.objects):
        if ob.type == "LIGHT":
            lights.append(f"{ob.name} ({ob.data.type.lower()})")
            bpy.data.objects.remove(ob)
    bpy.context.view_layer.update()
    return lights


def subtree(ob) -> list:
    out, todo = [], [ob]
    while todo:
        o = todo.pop()
        out.append(o)
        todo.extend(o.children)
    return out


def movable_roots(names: list[str]) -> list[tuple[str, object]]:
    """[(name, root object)] for the ``--movable`` names: an object, or each top-level object of
    a collection of that name."""
    import bpy

    roots = []
    for n in names:
        ob = bpy.data.objects.get(n)
        if ob is not None:
            roots.append(ob)
            continue
        coll = bpy.data.collections.get(n)
        if coll is not None:
            members = set(coll.all_objects)
            roots.extend(o for o in sorted(coll.all_objects, key=lambda o: o.name)
                         if o.parent not in members and o.type in GEOMETRY_TYPES | {"EMPTY"})
            continue
        scene_objects = sorted(o.name for o in bpy.data.objects if o.type in GEOMETRY_TYPES | {"EMPTY"})
        raise UserError(f"--movable {n}: no object or collection of that name in the scene; its objects are "
                        f"{', '.join(scene_objects[:40])}{' ...' if len(scene_objects) > 40 else ''}")
    seen, out = set(), []
    for ob in roots:
        if ob.name in seen:
            continue
        for other in roots:
            if other is not ob and ob in subtree(other):
                raise UserError(f"--movable: {ob.name} is a child of {other.name}; name one of them "
                                "(an object moves with its children)")
        seen.add(ob.name)
        out.append((ob.name, ob))
    if not out:
        raise UserError("--movable: the names given hold no object")
    if len(out) > 255:
        raise UserError(f"--movable: {len(out)} objects; masks are 8-bit, at most 255")
    return out


def triangles(objects) -> tuple[np.ndarray, np.ndarray]:
    """The world-space triangles (vertices (n, 3), indices (m, 3)) of the renderable geometry
    of ``objects``, with modifiers applied."""
    import bpy

    dg = bpy.context.evaluated_depsgraph_get()
    verts, tris, base = [], [], 0
    for ob in objects:
        if ob.type not in GEOMETRY_TYPES or ob.hide_render:
            continue
        ev = ob.evaluated_get(dg)
        try:
            me = ev.to_mesh()
        except RuntimeError:
            continue
        if me is None:
            continue
        me.calc_loop_triangles()
        m = np.array(ev.matrix_world, dtype=np.float64)
        v = np.array([x.co[:] for x in me.vertices], dtype=np.float64).reshape(-1, 3)
        t = np.array([x.vertices[:] for x in me.loop_triangles], dtype=np.int64).reshape(-1, 3)
        ev.to_mesh_clear()
        if len(t) == 0:
            continue
        verts.append(v @ m[:3, :3].T + m[:3, 3])
        tris.append(t + base)
        base += len(v)
    if not verts:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    return np.concatenate(verts), np.concatenate(tris)


def bvh(verts, tris):
    from mathutils import Vector
    from mathutils.bvhtree import BVHTree

    return BVHTree.FromPolygons([Vector(v) for v in verts], [tuple(int(i) for i in t) for t in tris])


def transformed(verts, m) -> np.ndarray:
    return verts @ m[:3, :3].T + m[:3, 3]


def open_edges(verts, tris) -> int:
    """Edges not shared by exactly two triangles once coincident vertices are merged (a glTF
    mesh splits its vertices at UV seams and hard edges)."""
    scale = max(float(np.ptp(verts, axis=0).max()), 1e-9)
    key = np.round(verts / (scale * 1e-6)).astype(np.int64)
    _, ids = np.unique(key, axis=0, return_inverse=True)
    ids = ids.reshape(-1)
    t = ids[tris]
    t = t[(t[:, 0] != t[:, 1]) & (t[:, 1] != t[:, 2]) & (t[:, 0] != t[:, 2])]
    e = np.sort(np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    return int((counts != 2).sum())


class Movable:
    """One movable object: its root, the objects that move with it, its triangles as loaded, and
    what arranging it needs (surface centroid, base height, footprint, radius)."""

    def __init__(self, name, root):
        self.name, self.root = name, root
        self.objects = subtree(root)
        self.loaded = np.array(root.matrix_world, dtype=np.float64)
        self.verts, self.tris = triangles(self.objects)
        if len(self.tris) == 0:
            raise UserError(f"--movable {name}: has no renderable geometry (no mesh faces)")
        a, b, c = (self.verts[self.tris[:, i]] for i in range(3))
        area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
        if area.sum() < 1e-10:
            raise UserError(f"--movable {name}: its mesh has zero area")
        n_open = open_edges(self.verts, self.tris)
        if n_open:
            raise UserError(f"--movable {name}: its mesh is not closed ({n_open} edges not shared by exactly two "
                            "faces); a movable object must be a closed (manifold) surface so its contact and "
                            "interpenetration can be checked")
        self.centroid = (area[:, None] * (a + b + c) / 3).sum(0) / area.sum()
        self.zmin = float(self.verts[:, 2].min())
        self.height = float(self.verts[:, 2].max()) - self.zmin
        d = self.verts[:, :2] - self.centroid[:2]
        self.radius_xy = float(np.linalg.norm(d, axis=1).max())
        self.radius = float(np.linalg.norm(self.verts - self.centroid, axis=1).max())
        # The footprint: the base's outermost points by direction (vertices within 1 % of the
        # height, at least 1 mm, of the lowest), relative to the centroid's vertical.
        low = self.verts[self.verts[:, 2] <= self.zmin + max(0.01 * self.height, 1e-3)][:, :2] - self.centroid[:2]
        foot = [np.zeros(2)]
        ang = np.arctan2(low[:, 1], low[:, 0])
        r = np.linalg.norm(low, axis=1)
        for s in range(12):
            sel = (ang >= -math.pi + s * math.pi / 6) & (ang < -math.pi + (s + 1) * math.pi / 6) & (r > 1e-4)
            if sel.any():
                foot.append(low[sel][r[sel].argmax()])
        self.foot = np.array(foot)
        # The frame an evaluation measures poses in: world axes, origin on the base under the
        # surface centroid (the vertical symmetry axis passes through the centroid).
        self.base = np.array([self.centroid[0], self.centroid[1], self.zmin])

    def foot_points(self, m) -> np.ndarray:
        """The footprint's points (on the base, world) once the object is moved by ``m``."""
        local = np.column_stack([self.foot + self.base[:2], np.full(len(self.foot), self.base[2])])
        return transformed(local, m)

    def motion(self, x, y, z, yaw) -> np.ndarray:
        """The world rigid motion that turns the object by ``yaw`` about its centroid's vertical
        and puts its base centre at (x, y, z)."""
        c, s = math.cos(yaw), math.sin(yaw)
        m = np.eye(4)
        m[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
        m[:3, 3] = np.array([x, y, z]) - m[:3, :3] @ self.base
        return m


# ----------------------------------------------------------------------------- ray queries


def first_hit(trees, origin, direction, dist=1e9):
    """(distance, location, normal) of the nearest hit among BVHs, or None."""
    from mathutils import Vector

    best = None
    o, d = Vector(origin), Vector(direction)
    for t in trees:
        loc, nrm, _i, dd = t.ray_cast(o, d, dist)
        if loc is not None and (best is None or dd < best[0]):
            best = (dd, np.array(loc), np.array(nrm))
    return best


def surfaces_below(trees, x, y, top, bottom):
    """Heights of the upward-facing surfaces (|normal z| > UP_COS) met by a ray straight down at
    (x, y) from ``top`` to ``bottom``, highest first."""
    out, z = [], top
    while z > bottom:
        h = first_hit(trees, (x, y, z), (0, 0, -1), z - bottom)
        if h is None:
            break
        if abs(h[2][2]) > UP_COS:
            out.append(float(h[1][2]))
        z = float(h[1][2]) - 1e-4
    return out


def inside_solid(trees, p) -> bool:
    """Whether ``p`` is inside a closed solid: every ray from it, in 14 directions, meets a face
    from behind (a back face, by the face's winding)."""
    dirs = [(1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1), (0, 0, -1)]
    dirs += [(sx, sy, sz) for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]
    for d in dirs:
        d = np.array(d, float) / np.linalg.norm(d)
        h = first_hit(trees, p, d)
        if h is None or float(h[2] @ d) <= 0:
            return False
    return True


# ----------------------------------------------------------------------------- the scene


class OwnScene:
    """The loaded scene: its movables, the background's BVH and bounds, the ground truth."""

    def __init__(self, a):
        import bpy

        self.lights = load(a.scene)
        self.cameras = sorted(o.name for o in bpy.data.objects if o.type == "CAMERA")  # before ours
        roots = movable_roots([n.strip() for n in a.movable.split(",") if n.strip()])
        self.movables = [Movable(n, r) for n, r in roots]
        moving = {o.name for m in self.movables for o in m.objects}
        self.static_verts, self.static_tris = triangles([o for o in bpy.data.objects if o.name not in moving])
        if len(self.static_tris) == 0:
            raise UserError(f"--scene {a.scene}: nothing but the movable objects; expected a scene to stand them in")
        self.static = bvh(self.static_verts, self.static_tris)
        self.lo = self.static_verts.min(0)
        self.hi = self.static_verts.max(0)
        if not self._has_support():
            raise UserError(f"--scene {a.scene}: no upward-facing surface to stand objects on (rays cast down "
                            "over the scene meet no floor, table or shelf)")
        self.source = a.scene

    def _has_support(self) -> bool:
        for x in np.linspace(self.lo[0], self.hi[0], 9)[1:-1]:
            for y in np.linspace(self.lo[1], self.hi[1], 9)[1:-1]:
                if surfaces_below([self.static], x, y, self.hi[2] + 1, self.lo[2] - 1):
                    return True
        return False

    # ------------------------------------------------------------------ states

    def placed_tree(self, mv, motion):
        return bvh(transformed(mv.verts, motion), mv.tris)

    def arrange(self, rng: random.Random, visible=None) -> dict:
        """A new arrangement: {name: world motion from the scene as loaded}."""
        motions, trees = {}, []
        order = list(self.movables)
        rng.shuffle(order)
        for mv in order:
            for _ in range(MOVE_TRIES):
                yaw = rng.uniform(0, 2 * math.pi)
                r = mv.radius_xy
                if self.hi[0] - self.lo[0] <= 2 * r or self.hi[1] - self.lo[1] <= 2 * r:
                    break
                x = rng.uniform(self.lo[0] + r, self.hi[0] - r)
                y = rng.uniform(self.lo[1] + r, self.hi[1] - r)
                levels = surfaces_below([self.static] + trees, x, y, self.hi[2] + 1, self.lo[2] - 1)
                if not levels:
                    continue
                h = levels[rng.randrange(len(levels))]
                m = mv.motion(x, y, h + CONTACT_GAP, yaw)
                if not self._stands(mv, m, [self.static] + trees, h):
                    continue
                tree = self.placed_tree(mv, m)
                if any(tree.overlap(t) for t in [self.static] + trees):
                    continue
                centre = transformed(mv.centroid[None], m)[0]
                if inside_solid([self.static] + trees, centre + np.array([0, 0, 0.5 * mv.height])):
                    continue
                if visible is not None and not visible(centre):
                    continue
                motions[mv.name] = m
                trees.append(tree)
                break
            else:
                raise UserError(f"--movable {mv.name}: no place to stand it found in {MOVE_TRIES} tries (a flat "
                                f"upward-facing surface wider than its {2 * mv.radius_xy:.2f} m footprint, with room "
                                "above it, crossing nothing)")
            if mv.name not in motions:
                raise UserError(f"--movable {mv.name}: wider ({2 * mv.radius_xy:.2f} m) than the scene")
        return motions

    def _stands(self, mv, m, trees, h) -> bool:
        """Every footprint ray of the object moved by ``m`` meets an upward surface at ``h``."""
        for p in mv.foot_points(m):
            hit = first_hit(trees, (p[0], p[1], h + 0.05), (0, 0, -1), 0.05 + 2 * FLAT_TOL)
            if hit is None or abs(hit[1][2] - h) > FLAT_TOL or abs(hit[2][2]) < UP_COS:
                return False
        return True

    def check_layout(self, motions: dict, where: str) -> None:
        """A given layout: each object rests (a surface within REST_TOL under its footprint) and,
        lifted by PENETRATION_TOL, crosses nothing."""
        placed = {mv.name: (mv, motions.get(mv.name, np.eye(4))) for mv in self.movables}
        trees = {n: self.placed_tree(mv, m) for n, (mv, m) in placed.items()}
        for n, (mv, m) in placed.items():
            lift = np.eye(4)
            lift[2, 3] = PENETRATION_TOL
            tree = self.placed_tree(mv, lift @ m)
            for k, t in [("the background", self.static)] + [(k, t) for k, t in trees.items() if k != n]:
                if tree.overlap(t):
                    raise UserError(f"{where}: objects.{n}: passes through {k} (by more than "
                                    f"{PENETRATION_TOL * 1e3:.0f} mm)")
            others = [self.static] + [t for k, t in trees.items() if k != n]
            zmin = float(transformed(mv.verts, m)[:, 2].min())
            gaps = []
            for p in mv.foot_points(m):
                hit = first_hit(others, (p[0], p[1], zmin + 0.01), (0, 0, -1), 1e3)
                gaps.append(np.inf if hit is None else zmin - float(hit[1][2]))
            if min(gaps) > REST_TOL:
                below = "nothing" if not np.isfinite(min(gaps)) else f"the nearest surface {min(gaps) * 1e3:.1f} mm"
                raise UserError(f"{where}: objects.{n}: does not rest on anything ({below} under its base); "
                                f"expected contact within {REST_TOL * 1e3:.0f} mm")

    def layouts(self, paths: list[str]) -> list[dict]:
        names = {mv.name for mv in self.movables}
        out = []
        for p in paths:
            lay = read_layout(p)
            for k in lay:
                if k not in names:
                    raise UserError(f"{p}: objects.{k}: not a movable object; the movables are {', '.join(sorted(names))}")
            motions = {k: yup_to_bl_matrix(v) for k, v in lay.items()}
            self.check_layout(motions, p)
            out.append({mv.name: motions.get(mv.name, np.eye(4)) for mv in self.movables})
        return out

    # ------------------------------------------------------------------ cameras

    def state_trees(self, motions):
        return {mv.name: self.placed_tree(mv, motions[mv.name]) for mv in self.movables}

    def auto_views(self, motions, n, rng, w, h, lens=35.0) -> list[np.ndarray]:
        """n camera matrices (Blender world) around the objects as arranged by ``motions``."""
        import mathutils

        trees = self.state_trees(motions)
        vfov = 2 * math.atan(18.0 / lens * min(h / w, 1.0))
        order = list(self.movables)
        rng.shuffle(order)
        size = self.hi - self.lo
        mats = []
        for i in range(n):
            mv = order[i % len(order)]
            centre = transformed(mv.centroid[None], motions[mv.name])[0]
            others = [self.static] + [t for k, t in trees.items() if k != mv.name]
            near = max(1.2 * mv.radius / math.tan(vfov / 2), 0.3)
            for _ in range(VIEW_TRIES):
                half = max(3.0 * mv.radius, 0.35) * rng.uniform(1.2, 2.2)
                d = half / math.tan(vfov / 2)
                az, el = rng.uniform(0, 2 * math.pi), math.radians(rng.uniform(15, 60))
                direction = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
                hit = first_hit(others, centre, direction, d + 0.15)
                if hit is not None:
                    d = hit[0] - 0.15
                if d < near:
                    continue
                eye = centre + d * direction
                if np.any(eye[:2] < self.lo[:2]) or np.any(eye[:2] > self.hi[:2]) or \
                        not self.lo[2] < eye[2] < self.hi[2] + 0.5 * size[2]:
                    continue
                if inside_solid(list(trees.values()) + [self.static], eye):
                    continue
                jitter = np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), rng.uniform(-0.2, 0.2)]) * mv.radius
                target = mathutils.Vector(centre + jitter)
                e = mathutils.Vector(eye)
                rot = (target - e).to_track_quat("-Z", "Y").to_matrix().to_4x4()
                mats.append(np.array(mathutils.Matrix.Translation(e) @ rot))
                break
            else:
                raise UserError(f"no camera place found for {mv.name} in {VIEW_TRIES} tries (inside the scene's "
                                "bounds, not inside a solid, with a clear line of sight)")
        return mats

    # ------------------------------------------------------------------ ground truth

    def frame(self, name, motion) -> np.ndarray:
        """The object's evaluation frame (Y-up 4x4) under a world motion from the loaded scene."""
        mv = self._by_name(name)
        t = np.eye(4)
        t[:3, 3] = mv.base
        return bl_to_yup_matrix(motion @ t)

    def _by_name(self, name):
        return next(mv for mv in self.movables if mv.name == name)

    def detect_symmetries(self, mv, tmp, rng, declared=None) -> list[dict]:
        """The object's rotational symmetries through its surface centroid (which lies on every
        axis of a symmetric object), each passing both of ``lfsymmetry``'s checks (surface and
        albedo pass). Detected: about the vertical, the first of CANDIDATE_ORDERS that passes;
        then about a horizontal axis (the surface's two horizontal principal directions and the
        two commonest directions of its vertical faces' normals), the first of continuous,
        four- and two-fold that passes: with the vertical one that generates a ball's, a box's or
        a cylinder's whole group. ``declared`` (an order about the vertical) is checked instead,
        and refused when it fails."""
        import bpy

        verts = bl_to_yup_points(mv.verts)
        centre = bl_to_yup_points(mv.centroid[None])[0]
        tree = lfsymmetry.surface(verts, mv.tris)
        points = lfsymmetry.samples(verts, mv.tris, 400, np.random.default_rng(rng.randrange(2**31)))
        tol = max(lfsymmetry.SURFACE_TOL, 0.01 * mv.radius)
        offset = [0.0, round(float(mv.centroid[2] - mv.zmin), 6), 0.0]

        def passes(axis, order):
            """None when the rotations pass both checks, else what failed."""
            turns = lfsymmetry.angles(order, rng)
            far = max(lfsymmetry.departure(points, tree, centre, axis, t) for t in turns)
            if far >= tol:
                return f"the surface leaves itself by {far * 1e3:.1f} mm (tolerance {tol * 1e3:.1f} mm)"
            worst = 0.0
            for t in turns[:1] if order == 0 else turns:
                coverage, albedo, _covered = lfsymmetry.appearance_change(tmp, centre, axis, t,
                                                                         scale=max(mv.radius, 0.02) / 0.15)
                worst = max(worst, coverage, albedo)
            if worst > lfsymmetry.APPEARANCE_TOL:
                return f"its albedo changes on {worst:.0%} of its pixels (a texture breaks the symmetry)"
            return None

        hidden = {}
        for ob in bpy.data.objects:
            if ob.type in GEOMETRY_TYPES and ob not in mv.objects:
                hidden[ob.name] = ob.hide_render
                ob.hide_render = True
        try:
            up = [0.0, 1.0, 0.0]
            if declared is not None:
                failed = passes(up, declared)
                if failed:
                    raise UserError(f"--symmetry {mv.name}:{declared}: turned about its vertical axis {failed}")
                return [{"axis": [0, 1, 0], "order": declared, "offset": offset}]
            found = []
            for order in CANDIDATE_ORDERS:
                if passes(up, order) is None:
                    found.append({"axis": [0, 1, 0], "order": order, "offset": offset})
                    break
            for axis in horizontal_axes(verts, mv.tris):
                order = next((o for o in (0, 4, 2) if passes(axis, o) is None), None)
                if order is not None:
                    found.append({"axis": [round(float(x), 6) + 0.0 for x in axis], "order": order,
                                  "offset": offset})
                    break
            return found
        finally:
            for name, h in hidden.items():
                bpy.data.objects[name].hide_render = h


def horizontal_axes(verts, tris) -> list[np.ndarray]:
    """Candidate horizontal symmetry axes (Y-up unit vectors, y = 0): the two principal
    directions of the surface's horizontal extent (area-weighted triangle centres), then the
    two commonest directions (by area, modulo a half turn) of its vertical faces' normals; the
    same direction (within 2°) once."""
    t = np.asarray(tris)
    a, b, c = verts[t[:, 0]], verts[t[:, 1]], verts[t[:, 2]]
    cross = np.cross(b - a, c - a)
    area = 0.5 * np.linalg.norm(cross, axis=1)
    mid = (a + b + c) / 3
    xz = mid[:, [0, 2]] - (area[:, None] * mid[:, [0, 2]]).sum(0) / max(area.sum(), 1e-12)
    cov = (area[:, None, None] * xz[:, :, None] * xz[:, None, :]).sum(0)
    _, vecs = np.linalg.eigh(cov)
    angles = [math.atan2(vecs[1, i], vecs[0, i]) for i in (1, 0)]
    n = cross / np.maximum(2 * area[:, None], 1e-12)
    side = np.abs(n[:, 1]) < 0.05
    if side.any():
        theta = np.mod(np.arctan2(n[side, 2], n[side, 0]), math.pi)
        bins = np.round(np.degrees(theta)).astype(int) % 180
        weight = np.bincount(bins, weights=area[side], minlength=180)
        for k in np.argsort(weight)[::-1][:2]:
            if weight[k] > 0:
                angles.append(math.radians(k))
    out = []
    for th in angles:
        d = np.array([math.cos(th), 0.0, math.sin(th)])
        if all(abs(float(d @ e)) < math.cos(math.radians(2)) for e in out):
            out.append(d)
    return out


# ----------------------------------------------------------------------------- materials


def principled(mat):
    """The Principled BSDF that feeds the material's surface output, or None."""
    if mat is None or mat.node_tree is None:
        return None
    nodes = mat.node_tree.nodes
    out = next((n for n in nodes if n.type == "OUTPUT_MATERIAL" and n.is_active_output), None) or \
        next((n for n in nodes if n.type == "OUTPUT_MATERIAL"), None)
    if out is None:
        return None
    todo, seen = [out], set()
    while todo:
        n = todo.pop()
        if n.name in seen:
            continue
        seen.add(n.name)
        if n.type == "BSDF_PRINCIPLED":
            return n
        for s in n.inputs:
            if s.type == "SHADER":
                todo.extend(link.from_node for link in s.links)
    return None


def add_albedo_aovs(objects) -> list[str]:
    """Give every material of ``objects`` an ``albedo`` AOV output fed by its Principled BSDF's
    Base Color (the dataset's albedo pass). Returns the materials without one (albedo 0)."""
    missing, done = [], set()
    for ob in objects:
        for slot in getattr(ob, "material_slots", []):
            mat = slot.material
            if mat is None or mat.name in done:
                continue
            done.add(mat.name)
            bsdf = principled(mat)
            if bsdf is None:
                missing.append(mat.name)
                continue
            nt = mat.node_tree
            aov = next((n for n in nt.nodes if n.type == "OUTPUT_AOV" and n.aov_name == "albedo"), None)
            if aov is None:
                aov = nt.nodes.new("ShaderNodeOutputAOV")
                aov.aov_name = "albedo"
            base = bsdf.inputs["Base Color"]
            if base.links:
                nt.links.new(base.links[0].from_socket, aov.inputs["Color"])
            else:
                aov.inputs["Color"].default_value = base.default_value
    return missing


def material_truth(mv) -> dict:
    """{"material": {metallic, roughness}} area-weighted when every face's material is a
    Principled BSDF with plain Metallic and Roughness inputs; else {"material_note": why not}."""
    import bpy

    dg = bpy.context.evaluated_depsgraph_get()
    acc, total = np.zeros(2), 0.0
    for ob in mv.objects:
        if ob.type != "MESH" or ob.hide_render:
            continue
        me = ob.evaluated_get(dg).data
        for poly in me.polygons:
            slots = ob.material_slots
            mat = slots[poly.material_index].material if poly.material_index < len(slots) else None
            bsdf = principled(mat)
            if bsdf is None:
                what = "no material" if mat is None else f"material {mat.name!r} is not a Principled BSDF"
                return {"material_note": f"{ob.name}: {what}; no metallic/roughness truth"}
            linked = [k for k in ("Metallic", "Roughness") if bsdf.inputs[k].links]
            if linked:
                return {"material_note": f"{ob.name}: material {mat.name!r} drives {' and '.join(linked)} by a "
                                         "texture or node; no metallic/roughness truth"}
            acc += poly.area * np.array([bsdf.inputs["Metallic"].default_value,
                                         bsdf.inputs["Roughness"].default_value])
            total += poly.area
    if total <= 0:
        return {"material_note": "no mesh faces; no metallic/roughness truth"}
    m, r = acc / total
    return {"material": {"metallic": round(float(m), 6), "roughness": round(float(r), 6)}}


# ----------------------------------------------------------------------------- cameras given


def scene_cameras(names, w, h) -> list[tuple[np.ndarray, dict]]:
    """The scene's own perspective cameras ``names``: (Blender world matrix, intrinsics)."""
    import bpy

    cams = [bpy.data.objects[n] for n in names]
    if not cams:
        raise UserError("--cameras scene: the scene has no camera")
    out = []
    for c in cams:
        cd = c.data
        if cd.type != "PERSP":
            raise UserError(f"--cameras scene: camera {c.name} is {cd.type.lower()}; expected perspective")
        fit = cd.sensor_fit
        if fit == "AUTO":
            f = cd.lens / cd.sensor_width * max(w, h)
        elif fit == "HORIZONTAL":
            f = cd.lens / cd.sensor_width * w
        else:
            f = cd.lens / cd.sensor_height * h
        big = max(w, h)
        intr = {"fl_x": f, "fl_y": f, "cx": w / 2.0 - cd.shift_x * big, "cy": h / 2.0 + cd.shift_y * big,
                "w": int(w), "h": int(h)}
        m = np.array(c.matrix_world, dtype=np.float64)
        u, _, vt = np.linalg.svd(m[:3, :3])
        m[:3, :3] = u @ vt
        out.append((m, intr))
    return out


def file_cameras(path, w, h, default_intr) -> list[tuple[np.ndarray, dict]]:
    """Cameras from a JSON file: {"frames": [{"transform_matrix": Y-up camera-to-world (OpenGL
    axes), optional "fl_x", "fl_y", "cx", "cy"}]} (a dataset.json's frames qualify)."""
    from lfaxes import cam_yup_to_bl

    d = read_json(path, "a camera file")
    frames = d.get("frames") if isinstance(d, dict) else None
    if not isinstance(frames, list) or not frames:
        raise UserError(f"{path}: field 'frames' must be a non-empty list of frames with a transform_matrix")
    out = []
    for i, fr in enumerate(frames):
        where = f"{path}: frames[{i}]"
        try:
            c2w = np.asarray(fr["transform_matrix"], dtype=np.float64)
        except (KeyError, TypeError, ValueError):
            raise UserError(f"{where}.transform_matrix: expected 4 rows of 4 numbers") from None
        if c2w.shape != (4, 4) or not np.all(np.isfinite(c2w)):
            raise UserError(f"{where}.transform_matrix: expected 4 rows of 4 finite numbers")
        m = cam_yup_to_bl(c2w)
        u, sv, vt = np.linalg.svd(m[:3, :3])
        if np.abs(sv - 1).max() > 1e-3:
            raise UserError(f"{where}.transform_matrix: has scale (singular values {np.round(sv, 4).tolist()}); "
                            "expected a rigid camera pose")
        m[:3, :3] = u @ vt
        intr = dict(default_intr)
        for k in ("fl_x", "fl_y", "cx", "cy"):
            if k in fr:
                try:
                    intr[k] = float(fr[k])
                except (TypeError, ValueError):
                    raise UserError(f"{where}.{k}: expected a number") from None
        if abs(intr["fl_x"] - intr["fl_y"]) > 1e-6 * intr["fl_x"]:
            raise UserError(f"{where}: fl_x != fl_y (non-square pixels) is not supported by Cycles cameras")
        out.append((m, intr))
    return out


def visible_from(views):
    """A test of whether a world point projects inside some view (5 % margin), in front of it."""
    world_to_camera = [(np.linalg.inv(m), intr) for m, intr in views]

    def test(p):
        for inv, intr in world_to_camera:
            q = inv @ np.append(p, 1.0)  # camera looks down -Z
            if q[2] >= -0.05:
                continue
            u = intr["cx"] + intr["fl_x"] * q[0] / -q[2]
            v = intr["cy"] - intr["fl_y"] * q[1] / -q[2]
            if 0.05 * intr["w"] < u < 0.95 * intr["w"] and 0.05 * intr["h"] < v < 0.95 * intr["h"]:
                return True
        return False
    return test


# ----------------------------------------------------------------------------- the generator's view


def parse_symmetries(specs, names) -> dict:
    """``--symmetry NAME:ORDER`` (0 = continuous, n >= 2, or ``none``) -> {name: order or None}."""
    out = {}
    for spec in specs or []:
        name, _, order = spec.rpartition(":")
        if not name:
            raise UserError(f"--symmetry {spec}: expected NAME:ORDER (0 continuous, n >= 2, or none)")
        if name not in names:
            raise UserError(f"--symmetry {spec}: {name} is not a movable object ({', '.join(sorted(names))})")
        if order == "none":
            out[name] = None
            continue
        try:
            o = int(order)
        except ValueError:
            o = -1
        if o < 0 or o == 1:
            raise UserError(f"--symmetry {spec}: ORDER must be 0 (continuous), n >= 2 or none")
        out[name] = o
    return out


def build(sc: OwnScene, a, w, h, default_intr, tmp) -> dict:
    """The scene for generate.py, once ``sc`` is loaded and the render set up: movables, objects'
    ground truth, the K + 1 arrangements (Blender world matrices of each movable's root) and a
    camera maker per state (k, n, rng) -> [(Blender world matrix, intrinsics)]."""
    import bpy

    if sc.lights:
        print(f"note: the dataset is lit by environments only; the scene's lights were ignored: "
              f"{', '.join(sc.lights)}", file=sys.stderr, flush=True)
    missing = add_albedo_aovs(bpy.data.objects)
    if missing:
        print(f"note: no Principled BSDF in material(s) {', '.join(missing)}: their albedo pass is 0",
              file=sys.stderr, flush=True)
    names = [mv.name for mv in sc.movables]
    declared = parse_symmetries(a.symmetry, set(names))
    if a.cameras in (None, "auto"):
        fixed = None
    elif a.cameras == "scene":
        fixed = scene_cameras(sc.cameras, w, h)
    else:
        fixed = file_cameras(a.cameras, w, h, default_intr)
    K = a.states
    if a.layouts:
        paths = [p.strip() for p in a.layouts.split(",") if p.strip()]
        if len(paths) != K + 1:
            raise UserError(f"--layouts: {len(paths)} files for {K} training states and the test state; expected "
                            f"{K + 1} (one per training state, then the test state's)")
        motions = sc.layouts(paths)
    else:
        visible = visible_from(fixed) if fixed else None
        motions = [sc.arrange(random.Random(f"{a.seed}-arrange-{k}"), visible) for k in range(K + 1)]
    arrangements = [{mv.name: m[mv.name] @ mv.loaded for mv in sc.movables} for m in motions]

    def views(k, n, rng):
        if fixed is not None:
            return fixed
        return [(m, default_intr) for m in sc.auto_views(motions[k], n, rng, w, h)]

    sym_rng = random.Random(f"{a.seed}-symmetry")
    meta = {}
    setup_for_checks = bpy.context.scene.camera
    for i, mv in enumerate(sc.movables):
        for ob in mv.objects:
            ob.pass_index = i + 1
        if mv.name in declared and declared[mv.name] is None:
            sym = []
        else:
            sym = sc.detect_symmetries(mv, tmp, sym_rng, declared.get(mv.name))
        meta[mv.name] = {"symmetries": sym, **material_truth(mv)}
    bpy.context.scene.camera = setup_for_checks
    return {"movables": [(mv.name, mv.root, mv.objects) for mv in sc.movables], "meta": meta,
            "arrangements": arrangements, "views": views,
            "frame": lambda name, world: sc.frame(name, world @ np.linalg.inv(sc._by_name(name).loaded)),
            "fixed_cameras": fixed is not None, "source": os.path.basename(a.scene)}
