"""Procedural triangle meshes as numpy arrays: grids, tori, rounded boxes, capped tubes.

Every builder returns ``(positions, faces)``: positions ``float64 (V, 3)``, faces
``uint32 (F, 3)`` of vertex indices, triangles wound counter-clockwise seen from
outside (Mitsuba's geometric normal ``cross(p1 - p0, p2 - p0)`` points out). All are
vectorised: no Python loop over vertices or faces. Triangle counts are closed-form, so
a scene can report its size without building anything:

=====================  ====================  ========================
builder                triangles             vertices
=====================  ====================  ========================
``grid(nu, nv)``       ``2 nu nv``           ``(nu+1)(nv+1)``
``torus(..)``          ``2 nu nv``           ``nu nv``
``rounded_box(n, ..)`` ``12 n^2``            ``6 n^2 + 2``
``capped_tube(s, r)``  ``2 s r + 2 s``       ``(r+1) s + 2 (s+1)``
=====================  ====================  ========================
"""

from __future__ import annotations

import numpy as np


def grid_faces(nu: int, nv: int, wrap_u: bool = False, wrap_v: bool = False) -> np.ndarray:
    """Triangles of an ``nu x nv`` grid of quads, two per quad.

    Vertex ``(i, j)`` has index ``i * nv_vertices + j``, with ``nv_vertices = nv`` when
    ``wrap_v`` (column ``nv`` is column 0) and ``nv + 1`` otherwise; likewise along u.
    The triangles face ``cross(d/du, d/dv)``.

    Returns:
        uint32 ``(2 nu nv, 3)``.
    """
    su = nu if wrap_u else nu + 1
    sv = nv if wrap_v else nv + 1
    i, j = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    i1 = (i + 1) % su
    j1 = (j + 1) % sv
    c00, c10, c11, c01 = i * sv + j, i1 * sv + j, i1 * sv + j1, i * sv + j1
    quads = np.stack([c00, c10, c11, c00, c11, c01], axis=-1).reshape(-1, 3)
    return quads.astype(np.uint32)


def grid(nu: int, nv: int) -> tuple[np.ndarray, np.ndarray]:
    """A flat ``nu x nv`` quad grid over the unit square in the xy plane, facing +z.

    Returns:
        positions ``(nu+1)(nv+1) x 3`` with ``z = 0`` (vertex ``(i, j)`` at
        ``(i / nu, j / nv, 0)``), faces ``2 nu nv x 3``.
    """
    u, v = np.meshgrid(np.linspace(0.0, 1.0, nu + 1), np.linspace(0.0, 1.0, nv + 1), indexing="ij")
    positions = np.stack([u, v, np.zeros_like(u)], axis=-1).reshape(-1, 3)
    return positions, grid_faces(nu, nv)


def torus_point(u, v, major: float, minor) -> np.ndarray:
    """Points of a torus around the z axis at angles ``u`` (around the axis) and ``v``
    (around the tube), arrays broadcast together; returns ``(..., 3)``."""
    ring = major + minor * np.cos(v)
    return np.stack([ring * np.cos(u), ring * np.sin(u), minor * np.sin(v)], axis=-1)


def torus(major: float, minor: float, nu: int, nv: int) -> tuple[np.ndarray, np.ndarray]:
    """A closed torus around the z axis, ``nu`` quads around the axis, ``nv`` around
    the tube, vertex ``(i, j)`` at angles ``(2 pi i / nu, 2 pi j / nv)``."""
    u, v = np.meshgrid(
        np.arange(nu) * (2 * np.pi / nu), np.arange(nv) * (2 * np.pi / nv), indexing="ij"
    )
    positions = torus_point(u, v, major, minor).reshape(-1, 3)
    return positions, grid_faces(nu, nv, wrap_u=True, wrap_v=True)


def rounded_box(n: int, exponent: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """The unit ball of the ``exponent``-norm: a sphere (2), a rounded cube (6 or more).

    A cube with each face an ``n x n`` grid, welded along its edges, every vertex pushed
    onto the surface ``|x|^e + |y|^e + |z|^e = 1`` along its ray from the centre.
    """
    t = np.linspace(-1.0, 1.0, n + 1)
    a, b = np.meshgrid(t, t, indexing="ij")
    one = np.ones_like(a)
    # Six faces, each (a, b, normal) with a x b = normal so the grid faces outward.
    faces_xyz = [
        (one, a, b), (-one, b, a),
        (b, one, a), (a, -one, b),
        (a, b, one), (b, a, -one),
    ]
    cube = np.concatenate([np.stack(f, axis=-1).reshape(-1, 3) for f in faces_xyz])
    per_face = (n + 1) ** 2
    quads = grid_faces(n, n).astype(np.int64)
    faces = np.concatenate([quads + k * per_face for k in range(6)])
    # Weld the duplicated edge vertices on their exact integer lattice coordinates.
    lattice = np.rint((cube + 1.0) * (n / 2)).astype(np.int64)
    key = (lattice[:, 0] * (n + 1) + lattice[:, 1]) * (n + 1) + lattice[:, 2]
    _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    corners = cube[first]
    norm = (np.abs(corners) ** exponent).sum(axis=1) ** (1.0 / exponent)
    return corners / norm[:, None], inverse.reshape(-1)[faces].astype(np.uint32)


def capped_tube(
    segments: int, rings: int, exponent: float = 2.0
) -> tuple[np.ndarray, np.ndarray]:
    """A closed prism along y from ``y = 0`` to ``y = 1``: a superellipse cross-section
    ``|x|^e + |z|^e = 1`` (a circle for 2, a rounded square for 4 or more) with
    ``segments`` quads around and ``rings`` along the height, closed by two flat caps
    (fans with their own rim vertices, so the rim stays sharp under smooth shading).
    """
    angle = np.arange(segments) * (2 * np.pi / segments)
    c, s = np.cos(angle), np.sin(angle)
    radius = (np.abs(c) ** exponent + np.abs(s) ** exponent) ** (-1.0 / exponent)
    x, z = radius * c, radius * s
    height = np.linspace(0.0, 1.0, rings + 1)
    # Side vertex (i, j): ring i (height), segment j; the grid faces cross(dy, dangle),
    # which points outward (the angle runs from x towards z).
    side = np.stack(
        [np.broadcast_to(x, (rings + 1, segments)),
         np.broadcast_to(height[:, None], (rings + 1, segments)),
         np.broadcast_to(z, (rings + 1, segments))], axis=-1,
    ).reshape(-1, 3)
    side_faces = grid_faces(rings, segments, wrap_v=True)
    base = side.shape[0]
    caps, cap_faces = [], []
    for k, (y, outward) in enumerate(((0.0, -1.0), (1.0, 1.0))):
        centre = base + k * (segments + 1)
        rim = np.stack([x, np.full(segments, y), z], axis=-1)
        caps.append(np.concatenate([[[0.0, y, 0.0]], rim]))
        j = np.arange(segments)
        a, b = centre + 1 + j, centre + 1 + (j + 1) % segments
        fan = np.stack([np.full(segments, centre), a, b], axis=-1)
        # The fan (centre, j, j + 1) faces -y: the bottom cap keeps it, the top reverses.
        cap_faces.append(fan[:, ::-1] if outward > 0 else fan)
    positions = np.concatenate([side, *caps])
    faces = np.concatenate([side_faces.astype(np.int64), *cap_faces]).astype(np.uint32)
    return positions, faces
