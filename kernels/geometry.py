"""Triangle input: validation of what users pass; the faces read once in input order
(their centroids, which the Morton keys are made of, and packed triangle records); the
triangles and their boxes in slot order (from those records when building, through the
faces when refitting)."""

from __future__ import annotations

import warnings

import drjit as dr

from .arrays import namespace_of, plain

#: Scenes less wide than this lose hits (see :func:`warn_if_out_of_range`).
SMALLEST_EXTENT = 2.0**-100
#: Scenes with a coordinate or an extent beyond this overflow (see :func:`warn_if_out_of_range`).
LARGEST_COORDINATE = 2.0**125


def as_points(vertices):
    """Plain flat Float[3·V] (xyz interleaved) from a flat Float or any Array3f/Point3f."""
    if vertices is None or not dr.is_jit_v(vertices):
        raise TypeError(
            f"vertices: expected a Dr.Jit Float (3·V) or Array3f/Point3f, got {type(vertices).__name__}"
        )
    if dr.is_tensor_v(vertices):
        raise TypeError(f"vertices: expected a flat Float (3·V) or Array3f/Point3f, got a "
                        f"tensor of shape {tuple(vertices.shape)} ({type(vertices).__name__}); "
                        "pass its .array (flat, xyz interleaved)")
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


def checked_vertices(vertices, faces, top=None):
    """Flat Float[3·V] of ``vertices`` after checking that every value is finite and
    that ``faces`` (flat UInt32) only index existing vertices; ValueError otherwise.

    ``top``: the largest index in ``faces`` when the caller knows it (a refit: the build
    read it), which spares a pass over the faces."""
    points = as_points(vertices)
    v = len(points) // 3
    if v == 0:
        raise ValueError("vertices: the array is empty; pass the positions the faces index")
    bad = dr.count(~dr.isfinite(points))
    if top is None:
        largest = dr.max(faces) if len(faces) else dr.zeros(type(faces), 1)
        dr.eval(bad, largest)  # both reductions, then one wait
        top = int(largest[0])
    if int(bad[0]):
        raise ValueError(
            f"vertices: {int(bad[0])} of {3 * v} coordinates are non-finite (NaN or infinite); "
            "fix or drop those vertices before building"
        )
    if len(faces) and top >= v:
        hint = " (a negative index?)" if top >= 2**31 else ""
        raise ValueError(
            f"faces: index {top} is out of range for {v} vertices{hint}"
        )
    return points


def warn_if_out_of_range(lo, hi, stacklevel: int = 3):
    """Warn when the scene's box lies past the scales float32 ray tracing handles.

    - Extent below :data:`SMALLEST_EXTENT` (2**-100, about 7.9e-31): Dr.Jit's CPU
      kernels flush values below 2**-126 (1.2e-38) to zero, and the ray/triangle test
      multiplies coordinate differences, so triangle sizes and hit distances near that
      lose precision, then hits. The margin of 2**20 leaves room for triangles down to
      a millionth of the scene's size (where hits are lost: docs/decisions.md#tiny-scenes).
    - A coordinate or an extent beyond :data:`LARGEST_COORDINATE` (2**125, about
      4.3e37): sums and differences of coordinates overflow float32 (max 3.4e38) and
      the reciprocal of an extent beyond 2**126 is subnormal, which the kernels flush to
      zero (the SAH builders then see every box as empty).

    Args:
        lo, hi: Array3f[1], the scene's box (a built tree's root box: the union of its
            triangles' boxes).
        stacklevel: passed to ``warnings.warn`` (3: the caller of the function that
            called this one).
    Returns:
        The warning's text, or None when the scene is within range (one host read of
        six floats).
    """
    lo, hi = [float(c[0]) for c in lo], [float(c[0]) for c in hi]
    extent = max(h - l for l, h in zip(lo, hi))  # Python floats: no overflow
    largest = max(extent, *map(abs, lo + hi))
    message = None
    if 0 < extent < SMALLEST_EXTENT:
        message = (
            f"the scene is only {extent:.3g} wide, below 2**-100 ({SMALLEST_EXTENT:.2g}): "
            "float32 kernels flush values below 1.2e-38 to zero, so hits on its small triangles are lost; "
            "scale the scene (and its rays) up, e.g. to metres"
        )
    elif largest > LARGEST_COORDINATE:
        message = (
            f"the scene reaches {largest:.3g}, beyond 2**125 ({LARGEST_COORDINATE:.2g}): "
            "sums and differences of its coordinates overflow float32 (3.4e38) and the "
            "SAH builders lose their splits; scale the scene (and its rays) down"
        )
    if message:
        warnings.warn(f"hlbvh.build: {message}", stacklevel=stacklevel)
    return message


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
    return triangles_of(points, dr.gather(namespace_of(faces).Array3u, faces, prims))


def triangles_of(points, face):
    """Matrix3f: row k holds vertex k of each face ``face`` (Array3u of vertex indices
    into flat Float[3·V] ``points``)."""
    ns = namespace_of(points)
    return ns.Matrix3f(*(dr.gather(ns.Array3f, points, face[k]) for k in range(3)))


def triangle_boxes(tri):
    """Array3f lower and upper corners of each triangle's box; ``tri`` a Matrix3f whose
    rows are the vertices (:func:`gather_triangles`)."""
    return dr.minimum(dr.minimum(tri[0], tri[1]), tri[2]), dr.maximum(dr.maximum(tri[0], tri[1]), tri[2])


#: Floats per packed box record: lo.xyz, hi.xyz, two zeros (a power of two, so a
#: record is read with one packet gather).
BOX_RECORD = 8


def slot_triangles(tri):
    """``(tri, boxes)``, evaluated together (one kernel): the triangles in slot order
    (a lazy Matrix3f, rows p0, p1, p2: :func:`gather_triangles` or
    :func:`records_to_triangles`) and their boxes as packed records (Float[8·F], see
    :func:`box_records`). A record per slot keeps a box in one cache line where three
    lower and three upper coordinates in six arrays would take six: leaves read their
    slots' boxes at random places."""
    ns = namespace_of(tri[0].x)
    lo, hi = triangle_boxes(tri)
    n = dr.width(tri[0].x)
    boxes = dr.empty(ns.Float, BOX_RECORD * n)
    zero = dr.zeros(ns.Float, n)
    dr.scatter(boxes, ns.ArrayXf([lo.x, lo.y, lo.z, hi.x, hi.y, hi.z, zero, zero]),
               dr.arange(ns.UInt32, n))
    dr.eval(tri, boxes)
    return tri, boxes


def box_records(boxes, index, active=True):
    """``(lo, hi)``, Array3f: the packed box records ``index`` of ``boxes``
    (:func:`slot_triangles`), one packet gather each."""
    ns = namespace_of(boxes)
    r = dr.gather(ns.ArrayXf, boxes, index, active, shape=(BOX_RECORD, dr.width(index)))
    return ns.Array3f(r[0], r[1], r[2]), ns.Array3f(r[3], r[4], r[5])


#: Floats per packed triangle record: p0, p1, p2 (xyz each), seven zeros.
TRIANGLE_RECORD = 16


def triangle_records(points, faces):
    """``(centroid, records)``, evaluated together, in input order: the centre of each
    face's box (Array3f[F], what the Morton keys quantise) and the face's vertices as
    packed records (Float[16·F]). Reading a face through ``faces`` and the vertex array
    takes four cache lines at random places; its record, one (see
    :func:`records_to_triangles`)."""
    ns = namespace_of(faces)
    n = len(faces) // 3
    tri = gather_triangles(points, faces, dr.arange(ns.UInt32, n))
    lo, hi = triangle_boxes(tri)
    centroid = (lo + hi) * 0.5
    records = dr.empty(ns.Float, TRIANGLE_RECORD * n)
    rows = [c for p in (tri[0], tri[1], tri[2]) for c in p]
    rows += [dr.zeros(ns.Float, n)] * (TRIANGLE_RECORD - len(rows))
    dr.scatter(records, ns.ArrayXf(rows), dr.arange(ns.UInt32, n))
    dr.eval(centroid, records)
    return centroid, records


def records_to_triangles(records, prims):
    """Matrix3f[len(prims)] (lazy): the triangles of faces ``prims`` read from their
    packed records (:func:`triangle_records`), one packet gather each."""
    ns = namespace_of(prims)
    r = dr.gather(ns.ArrayXf, records, prims, shape=(TRIANGLE_RECORD, dr.width(prims)))
    return ns.Matrix3f(*(ns.Array3f(r[3 * k], r[3 * k + 1], r[3 * k + 2]) for k in range(3)))


def half_area(d):
    """Half the surface area of a box of extent ``d`` (Array3f, or Array3f64): the SAH
    needs only ratios of areas."""
    return dr.fma(d.x, d.y + d.z, d.y * d.z)
