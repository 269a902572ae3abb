"""A hit on a mesh with motion keys, shaded where the mesh is at the ray's time.

Mitsuba's ``compute_surface_interaction`` reads the mesh's stored vertices (the
mid-shutter pose :func:`hlbvh.accel.keys.set_motion_keys` wrote), so it places a hit at
the barycentric coordinates our keyed traversal found, but on the triangle of another
time. :func:`at_ray_time` moves the interaction to the triangle at the ray's time: the
position by the difference of the two barycentric points, the geometric normal to the
triangle's, and the shading frame and the position's derivatives by the rotation that
takes the one face normal to the other. Where the two triangles are equal (a still
mesh among moving ones, equal keys) nothing is touched, so the interaction is
Mitsuba's bit for bit. Vertex normals and uv are read from the mesh as Mitsuba reads
them (the keys hold positions only). :func:`shutter_points` gives a hit's point at the
shutter's open and close (motion vectors).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from hlbvh.kernels.keyed import lerp_vertex, ray_keys


def at_ray_time(si, pi, ray, group, first_face: mi.UInt32, time: mi.Float, active):
    """``si`` (Mitsuba's interaction of ``pi``) moved to the keyed ``group``'s triangles
    at each ray's ``time`` (normalised to the shutter).

    Args:
        si: SurfaceInteraction3f from ``pi.compute_surface_interaction``.
        pi: the PreliminaryIntersection3f it expands.
        ray: the Ray3f traced.
        group: the :class:`~hlbvh.accel.mesh_group.MeshGroup` with ``keyed`` set.
        first_face: UInt32 per index of ``scene.shapes()``: the shape's first face in
            the group, ``0xFFFFFFFF`` for a shape outside it.
        time: Float, each ray's time normalised to the group's shutter.
        active: Bool, the lanes to move.
    Returns:
        the moved SurfaceInteraction3f.
    """
    on, face = _on_group(pi, first_face, active)
    keys = ray_keys(group.keyed, time)
    at_time, at_mid = [], []
    for corner in range(3):
        vertex = dr.gather(mi.UInt32, group.geometry.faces, 3 * face + corner, on)
        at_time.append(mi.Point3f(*[lerp_vertex(a, b, keys.f, keys.g)
                                    for a, b in zip(_key_point(group, keys.k, vertex, on),
                                                    _key_point(group, keys.k + 1, vertex, on))]))
        at_mid.append(mi.Point3f(*[dr.gather(mi.Float, group.geometry.vertices,
                                             3 * vertex + c, on) for c in range(3)]))

    def normal(p):
        return dr.normalize(dr.cross(p[1] - p[0], p[2] - p[0]))

    si = mi.SurfaceInteraction3f(si)
    si.p = dr.select(on, si.p + (_barycentric(pi, at_time) - _barycentric(pi, at_mid)), si.p)
    n_mid, n_time = normal(at_mid), normal(at_time)
    turned = on & dr.any(n_mid != n_time) & dr.all(dr.isfinite(n_time))
    # The rotation taking n_mid to n_time (Rodrigues, with the unnormalised axis).
    axis, cos = dr.cross(n_mid, n_time), dr.dot(n_mid, n_time)
    scale = dr.rcp(dr.maximum(1.0 + cos, 1e-6))

    def rotated(x):
        return x * cos + dr.cross(axis, x) + axis * (dr.dot(axis, x) * scale)

    si.n = dr.select(turned, dr.mulsign(n_time, dr.dot(si.n, n_mid)), si.n)
    si.sh_frame = dr.select(turned, mi.Frame3f(dr.normalize(rotated(si.sh_frame.n))),
                            si.sh_frame)
    si.dp_du = dr.select(turned, rotated(si.dp_du), si.dp_du)
    si.dp_dv = dr.select(turned, rotated(si.dp_dv), si.dp_dv)
    si.wi = dr.select(turned, si.to_local(-ray.d), si.wi)
    return si


def shutter_points(pi, group, first_face: mi.UInt32, active):
    """Where the hits of ``pi`` on the keyed ``group``'s meshes are at the shutter's
    open and close (the same barycentric point on the triangle of the first and the
    last key): ``(p_open, p_close, on)``, ``on`` the lanes with such a hit."""
    on, face = _on_group(pi, first_face, active)
    last = mi.UInt32(group.keyed.keys - 1)
    first, final = [], []
    for corner in range(3):
        vertex = dr.gather(mi.UInt32, group.geometry.faces, 3 * face + corner, on)
        first.append(mi.Point3f(*_key_point(group, mi.UInt32(0), vertex, on)))
        final.append(mi.Point3f(*_key_point(group, last, vertex, on)))
    return _barycentric(pi, first), _barycentric(pi, final), on


def _on_group(pi, first_face: mi.UInt32, active):
    """The lanes whose hit is on a mesh of the keyed group (outside any instance), and
    the hit's face in the group."""
    base = dr.gather(mi.UInt32, first_face, pi.shape_index, active & pi.is_valid())
    outside_instances = dr.reinterpret_array(mi.UInt32, pi.instance) == 0
    on = active & pi.is_valid() & (base != 0xFFFFFFFF) & outside_instances
    return on, base + pi.prim_index


def _key_point(group, key, vertex, on) -> list:
    """The x, y, z of ``vertex`` of the group at key ``key`` (UInt32 per lane)."""
    first = key * dr.width(group.geometry.vertices) + 3 * vertex
    return [dr.gather(mi.Float, group.key_points, first + c, on) for c in range(3)]


def _barycentric(pi, p: list):
    """The point of the triangle ``p`` (three Point3f) at ``pi``'s barycentric
    coordinates, as Mitsuba weighs them (``(1 - u - v)·p0 + u·p1 + v·p2``)."""
    u, v = pi.prim_uv.x, pi.prim_uv.y
    return p[0] * (1.0 - u - v) + p[1] * u + p[2] * v
