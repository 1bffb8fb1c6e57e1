"""Rotational symmetries of an object, checked twice: on its surface and on its appearance.

A dataset's ``symmetries`` (evaluation only: pose errors forgive them) must be true ones, never
guessed. A rotation about an axis through a point is a symmetry of an object when

* **the surface maps onto itself**: points sampled on its triangles, turned, land on the surface
  (:func:`departure`, within a tolerance that allows the tessellation: a circle of 32 segments
  departs from the true circle by r (1 - cos(pi/32)) = 0.005 r), and
* **it looks the same**: Cycles' albedo pass (the dataset's own) seen from a camera turned by the
  rotation about the same axis is the view of the object turned back (:func:`appearance_change`):
  what the surface check cannot see, a texture or a decal.

The preset catalogue's declared symmetries are tested with these (``tests/test_scenes.py``), and
``generate.py --scene`` detects a user's objects' symmetries with them (``ownscene``).
"""

from __future__ import annotations

import math

import numpy as np

from lfaxes import C3

# The surface check's tolerance for the presets' objects (0.1-0.3 m, 32-48 segments: measured
# departures up to 0.61 mm, against centimetres for a false symmetry); objects of other sizes
# scale it (ownscene: 1 % of the object's radius, at least this).
SURFACE_TOL = 1.5e-3
# The appearance check's: the share of covered pixels whose coverage changes, and of those covered
# in both views whose albedo changes by more than ALBEDO_STEP in some channel (silhouette edges of
# a tessellated object; measured 0-0.8 % for true symmetries, 18-94 % for textures that break one).
APPEARANCE_TOL = 0.02
ALBEDO_STEP = 0.02


def surface(verts, tris):
    """A BVH over triangles (vertices as an (n, 3) array, triangles as index triples)."""
    from mathutils import Vector
    from mathutils.bvhtree import BVHTree

    return BVHTree.FromPolygons([Vector(v) for v in np.asarray(verts, float)], [tuple(t) for t in tris])


def samples(verts, tris, n, rng):
    """n points uniformly on the triangles (by area)."""
    verts = np.asarray(verts, float)
    t = np.asarray(tris)
    a, b, c = verts[t[:, 0]], verts[t[:, 1]], verts[t[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    pick = rng.choice(len(t), size=n, p=area / area.sum())
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    return a[pick] + u[:, None] * (b - a)[pick] + v[:, None] * (c - a)[pick]


def rotation(axis, angle):
    """The 3x3 rotation by ``angle`` (radians) about ``axis`` (Rodrigues)."""
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def angles(order, rng, margin=0.1):
    """The rotations a symmetry of ``order`` claims: n-fold, every non-trivial multiple of 2pi/n;
    continuous (0), three random angles at least ``margin`` from a full turn."""
    if order == 0:
        return [rng.uniform(margin, 2 * math.pi - margin) for _ in range(3)]
    return [2 * math.pi * j / order for j in range(1, order)]


def departure(points, bvh, centre, axis, angle):
    """How far (the largest distance, metres) ``points`` on the surface land from it when turned
    by ``angle`` about ``axis`` through ``centre`` (all in one frame)."""
    from mathutils import Vector

    centre = np.asarray(centre, float)
    turned = (np.asarray(points, float) - centre) @ rotation(axis, angle).T + centre
    return max(bvh.find_nearest(Vector(p))[3] for p in turned)


def _albedo_turned(tmp, centre, axis, angle, res, scale):
    """The albedo and coverage (mask > 0) at the pixel centres of a camera looking at `centre`
    (Y-up world), turned about `axis` through `centre` by `angle`: the view of the scene turned by
    -angle. With one sample at ~zero filter width (lfrender.render_geometry), each pixel is one
    ray, the same ray in both frames. ``scale`` moves the camera out for larger objects."""
    import bpy
    from mathutils import Matrix, Vector

    from lfrender import render_geometry

    sc = bpy.context.scene
    sc.render.resolution_x = sc.render.resolution_y = res
    sc.render.resolution_percentage = 100
    cam = bpy.data.objects.get("turned_cam")
    if cam is None:
        cam = bpy.data.objects.new("turned_cam", bpy.data.cameras.new("turned_cam"))
        sc.collection.objects.link(cam)
        cam.data.lens = 50
    sc.camera = cam
    c = Vector(C3.T @ np.asarray(centre, float))
    eye = c + Vector((0.55, -0.45, 0.35)) * scale
    look = (c - eye).normalized().to_track_quat("-Z", "Y").to_matrix().to_4x4()
    turn = Matrix.Rotation(angle, 4, Vector(C3.T @ np.asarray(axis, float)))
    cam.matrix_world = Matrix.Translation(c) @ turn @ Matrix.Translation(-c) @ Matrix.Translation(eye) @ look
    g = render_geometry(tmp)
    return g["albedo"], g["mask"] > 0


def appearance_change(tmp, centre, axis, angle, res=64, scale=1.0):
    """(share of covered pixels whose coverage changes, share of pixels covered in both whose
    albedo changes by more than ALBEDO_STEP in some channel, pixels covered at angle 0) when what
    the render sees with a non-zero object index (the caller shows the object alone, its
    ``pass_index`` > 0, and has called ``lfrender.setup_render``) is viewed turned by ``angle``
    about ``axis`` through ``centre`` (Y-up world). The scene's camera and resolution are kept."""
    import bpy

    sc = bpy.context.scene
    saved = (sc.camera, sc.render.resolution_x, sc.render.resolution_y, sc.render.resolution_percentage)
    try:
        a0, m0 = _albedo_turned(tmp, centre, axis, 0.0, res, scale)
        a1, m1 = _albedo_turned(tmp, centre, axis, angle, res, scale)
    finally:
        sc.camera, sc.render.resolution_x, sc.render.resolution_y, sc.render.resolution_percentage = saved
        cam = bpy.data.objects.get("turned_cam")
        if cam is not None and saved[0] is not cam:
            data = cam.data
            bpy.data.objects.remove(cam)
            bpy.data.cameras.remove(data)
    both = m0 & m1
    changed = (np.abs(a0 - a1).max(-1) > ALBEDO_STEP)[both]
    covered = int(m0.sum())
    return float((m0 ^ m1).sum() / max(covered, 1)), float(changed.mean()) if both.any() else 1.0, covered
