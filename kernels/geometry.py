"""Triangle input: validation of what users pass, and triangles gathered in slot order."""

from __future__ import annotations

import drjit as dr

from .arrays import namespace_of, plain


def as_points(vertices):
    """Plain Array3f[V] from a flat Float (3·V, xyz interleaved) or any Array3f/Point3f."""
    if not dr.is_jit_v(vertices):
        raise TypeError(
            f"vertices: expected a Dr.Jit Float (3·V) or Array3f/Point3f, got {type(vertices).__name__}"
        )
    if dr.depth_v(vertices) == 1:
        if dr.type_v(vertices) not in (dr.VarType.Float32, dr.VarType.Float64):
            raise TypeError(f"vertices: expected floating point values, got {type(vertices).__name__}")
        if len(vertices) % 3:
            raise ValueError(
                f"vertices: a flat array needs 3 values per vertex, got {len(vertices)} values"
            )
        flat = plain(vertices, "Float")
        ns = namespace_of(flat)
        idx = dr.arange(ns.UInt32, len(flat) // 3) * 3
        return ns.Array3f(*(dr.gather(ns.Float, flat, idx + k) for k in range(3)))
    if dr.size_v(vertices) != 3:
        raise TypeError(f"vertices: expected 3 components per vertex, got {dr.size_v(vertices)}")
    return plain(vertices, "Array3f")


def as_faces(faces):
    """Plain flat UInt32 (3·F) from a flat UInt32/Int32 array or an Array3u."""
    if not dr.is_jit_v(faces):
        raise TypeError(f"faces: expected a Dr.Jit UInt32 array (3·F), got {type(faces).__name__}")
    if dr.depth_v(faces) > 1:
        ns = namespace_of(faces)
        f = plain(faces, "Array3u")
        flat = dr.zeros(ns.UInt32, 3 * len(f.x))
        idx = dr.arange(ns.UInt32, len(f.x)) * 3
        for k in range(3):
            dr.scatter(flat, f[k], idx + k)
        return flat
    if dr.type_v(faces) not in (dr.VarType.UInt32, dr.VarType.Int32):
        raise TypeError(f"faces: expected 32-bit integer indices, got {type(faces).__name__}")
    return plain(faces, "UInt32")


def checked_vertices(vertices, faces):
    """Array3f[V] of ``vertices`` after checking that every value is finite and that
    ``faces`` (flat UInt32) only index existing vertices; ValueError otherwise."""
    points = as_points(vertices)
    v = len(points.x)
    bad = dr.count(~(dr.isfinite(points.x) & dr.isfinite(points.y) & dr.isfinite(points.z)))
    top = dr.max(faces) if len(faces) else 0
    dr.eval(bad, top)
    if int(bad[0]):
        raise ValueError(
            f"vertices: {int(bad[0])} of {v} vertices have non-finite (NaN or infinite) "
            "coordinates; fix or drop them before building"
        )
    if len(faces) and int(top[0]) >= v:
        raise ValueError(
            f"faces: index {int(top[0])} is out of range for {v} vertices"
        )
    return points


def checked_faces(faces):
    """Flat UInt32 (3·F) after checking it holds at least one whole triangle."""
    flat = as_faces(faces)
    if len(flat) == 0:
        raise ValueError("faces: the mesh is empty (no triangles); there is nothing to build")
    if len(flat) % 3:
        raise ValueError(f"faces: a flat array needs 3 indices per triangle, got {len(flat)}")
    return flat


def slot_triangles(points, faces, prim_ids):
    """Array3f[F] × 3: the vertices of face ``prim_ids[s]`` for every slot ``s``."""
    ns = namespace_of(faces)
    f3 = prim_ids * 3
    return tuple(
        dr.gather(ns.Array3f, points, dr.gather(ns.UInt32, faces, f3 + k)) for k in range(3)
    )
