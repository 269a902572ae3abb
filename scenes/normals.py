"""Vertex normals that come out the same every time.

Mitsuba recomputes a mesh's vertex normals on ``params.update()`` with a parallel
scatter-add, whose float sums depend on thread timing: two updates with identical
positions can give normals differing in the last bit, and renders differing by an ulp
in a few pixels. Two scenes meant to be compared pixel for pixel (native and hlbvh)
would then disagree for no reason of theirs. This module computes the same weighting
as Mitsuba (each face's unit normal weighted by its angle at the vertex: Thürmer and
Wüthrich, JGT 1998) with the scatter-adds on one thread, in a fixed order. (That
holds on the LLVM backend; on CUDA the atomic adds keep their hardware order.)
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi


def vertex_normals(positions: mi.Float, faces: mi.UInt32) -> mi.Float:
    """Angle-weighted unit vertex normals, bit-reproducible, evaluated on return.

    Args:
        positions: flat ``mi.Float`` of ``3V`` vertex coordinates.
        faces: flat ``mi.UInt32`` of ``3F`` vertex indices (counter-clockwise faces).

    Returns:
        flat ``mi.Float`` of ``3V``; a vertex no proper face touches gets ``(1, 0, 0)``,
        as in Mitsuba.
    """
    vertex_count = dr.width(positions) // 3
    vertices = dr.unravel(mi.Point3f, positions)
    corners = dr.unravel(mi.Vector3u, faces)
    p = [dr.gather(mi.Point3f, vertices, corners[k]) for k in range(3)]
    n = dr.cross(p[1] - p[0], p[2] - p[0])
    length_sqr = dr.squared_norm(n)
    proper = length_sqr > 0
    n *= dr.rsqrt(length_sqr)
    sums = [dr.zeros(mi.Float, vertex_count) for _ in range(3)]
    threads = dr.thread_count()
    dr.set_thread_count(1)  # one thread: the scatter-adds run in a fixed order
    try:
        for k in range(3):
            d0 = dr.normalize(p[(k + 1) % 3] - p[k])
            d1 = dr.normalize(p[(k + 2) % 3] - p[k])
            weighted = n * dr.safe_acos(dr.dot(d0, d1))
            for axis in range(3):
                dr.scatter_add(sums[axis], weighted[axis], corners[k], proper)
        total = mi.Vector3f(*sums)
        length_sqr = dr.squared_norm(total)
        unit = dr.select(length_sqr > 0, total * dr.rsqrt(length_sqr), mi.Vector3f(1, 0, 0))
        result = dr.ravel(unit)
        dr.eval(result)
        dr.sync_thread()
    finally:
        dr.set_thread_count(threads)
    return result
