"""Refit: new vertex positions, same faces, same tree: recompute the triangles in slot
order and the boxes only. A tree packed for traversal before is refit and repacked in one
go (:func:`hlbvh.kernels.layout.refit_packed`); any other through its binary levels."""

from __future__ import annotations

import functools
import time

import drjit as dr

from .bounds import node_bounds, sah_cost
from .arrays import namespace_of
from .geometry import checked_vertices, slot_triangles, triangles_of
from .layout import refit_packed


def refit(bvh, vertices):
    """Update ``bvh`` in place for new vertex positions.

    Args:
        bvh: a :class:`hlbvh.kernels.bvh.BVH`.
        vertices: flat Float (3·V) or Array3f (V), the same V as the build's or more
            (the faces decide which are read).
    Returns:
        ``bvh``, with its triangles, boxes, ``stats.sah_cost`` and
        ``stats.stage_ms['refit']`` updated.
    """
    t0 = time.perf_counter()
    faces, top = _slot_faces(bvh)
    points = checked_vertices(vertices, bvh.faces, top)
    if not refit_packed(bvh, points, faces):
        tri, boxes = slot_triangles(triangles_of(points, faces))
        bvh.tri_p0, bvh.tri_p1, bvh.tri_p2 = tri[0], tri[1], tri[2]
        bvh.node_min, bvh.node_max = node_bounds(
            bvh.node_first, bvh.node_count, boxes, bvh.levels, bvh.config.leaf_size
        )
    dr.sync_thread()
    bvh.stats.stage_ms["refit"] = (time.perf_counter() - t0) * 1e3
    bvh.stats.sah_cost = functools.partial(sah_cost, bvh.node_min, bvh.node_max, bvh.node_count)
    return bvh


def _slot_faces(bvh):
    """``(Array3u[F], int)``: the vertex indices of each slot's face and the largest of
    them, computed on the first refit and cached on ``bvh`` (keyed by its ``faces`` and
    ``prim_ids`` arrays), so that a refit reads three vertices a slot rather than its
    face first, and checks the vertex count without a pass over the faces."""
    key = (bvh.faces.index, bvh.prim_ids.index)
    cache = getattr(bvh, "_refit_faces", None)
    if cache is None or cache[0] != key:
        faces = dr.gather(namespace_of(bvh.faces).Array3u, bvh.faces, bvh.prim_ids)
        largest = dr.max(bvh.faces)
        dr.eval(faces, largest)
        cache = bvh._refit_faces = (key, faces, int(largest[0]))
    return cache[1], cache[2]
