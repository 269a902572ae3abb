"""Triangle input: validation of what users pass, and triangles gathered in slot order."""

from __future__ import annotations

import drjit as dr

from .arrays import namespace_of, plain


def as_points(vertices):
    """Plain flat Float[3·V] (xyz interleaved) from a flat Float or any Array3f/Point3f."""
    if vertices is None or not dr.is_jit_v(vertices):
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
        return plain(vertices, "Float")
    if dr.size_v(vertices) != 3:
        raise TypeError(f"vertices: expected 3 components per vertex, got {dr.size_v(vertices)}")
    points = plain(vertices, "Array3f")
    ns = namespace_of(points)
    flat = dr.zeros(ns.Float, 3 * dr.width(points))
    dr.scatter(flat, points, dr.arange(ns.UInt32, dr.width(points)))
    return flat


def as_faces(faces):
    """Plain flat UInt32 (3·F) from a flat UInt32/Int32 array or an Array3u."""
    if faces is None or not dr.is_jit_v(faces):
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
    """Flat Float[3·V] of ``vertices`` after checking that every value is finite and
    that ``faces`` (flat UInt32) only index existing vertices; ValueError otherwise."""
    points = as_points(vertices)
    v = len(points) // 3
    if v == 0:
        raise ValueError("vertices: the array is empty; pass the positions the faces index")
    bad = dr.count(~dr.isfinite(points))
    top = dr.max(faces) if len(faces) else 0
    dr.eval(bad, top)
    if int(bad[0]):
        raise ValueError(
            f"vertices: {int(bad[0])} of {3 * v} coordinates are non-finite (NaN or infinite); "
            "fix or drop those vertices before building"
        )
    if len(faces) and int(top[0]) >= v:
        hint = " (a negative index?)" if int(top[0]) >= 2**31 else ""
        raise ValueError(
            f"faces: index {int(top[0])} is out of range for {v} vertices{hint}"
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


def gather_triangles(points, faces, prims):
    """Matrix3f[len(prims)]: row k holds vertex k of face ``prims[i]``.

    Args:
        points: flat Float[3·V] vertex positions.
        faces: flat UInt32[3·F] vertex indices.
        prims: UInt32 face indices.
    """
    ns = namespace_of(faces)
    face = dr.gather(ns.Array3u, faces, prims)
    return ns.Matrix3f(*(dr.gather(ns.Array3f, points, face[k]) for k in range(3)))


def pack_triangles(tri):
    """Flat Float[9·F] holding the rows of Matrix3f ``tri`` triangle after triangle, so
    that :func:`unpack_triangles` reads one triangle with one contiguous gather."""
    ns = namespace_of(tri[0].x)
    packed = dr.zeros(ns.Float, 9 * dr.width(tri))
    dr.scatter(packed, tri, dr.arange(ns.UInt32, dr.width(tri)))
    return packed


def unpack_triangles(packed, prims):
    """Matrix3f[len(prims)]: the triangles ``prims`` of a :func:`pack_triangles` array."""
    return dr.gather(namespace_of(packed).Matrix3f, packed, prims)
