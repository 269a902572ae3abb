"""Surface interactions of a scene with instances, expanded without Mitsuba's call
through a shape pointer.

Mitsuba expands a hit (``pi.compute_surface_interaction``) with a call through the
hit's shape or instance pointer. On the JIT backends such a call is recorded once for
every shape the variant knows, and an instance's own expansion holds a second call of
that kind through its group's shapes, so the kernel that expands hits grows with the
number of instances: its compilation takes about 40 ms an instance
(docs/decisions.md#instance-hit-expansion),
and a scene of 10k instances does not fit in 24 GB. Here a hit inside an instance is
expanded as Mitsuba's ``Instance`` does it (the ray taken into object space, the group
shape's own expansion, the result taken back to world space) with the instance's
transform gathered per lane from a table, and each group shape called directly; a hit
on any other shape is expanded by that shape's own call. The kernel then holds one
expansion per distinct shape, however many instances there are; past a few shapes,
as a switch, where each lane runs its own shape's expansion alone.

An instance with keys over the shutter (:func:`hlbvh.accel.keys.set_instance_keys`) is
expanded with its pose at the ray's time (:class:`hlbvh.kernels.srt.KeyTable`, the
interpolation the traversal entered it with): position, normals and frames are where
the instance is when the ray meets it. Lanes of other instances keep the table's
transforms, bit for bit.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from hlbvh.accel.keys import instances_keys
from hlbvh.kernels.srt import KeyTable, inverse_or_nan


_NO_SLOT = 0xFFFFFFFF
ROW = 24  # floats a transform takes in the table: to_world's 12, its inverse transpose's 12


def is_instance(shape) -> bool:
    """Whether ``shape`` is a Mitsuba ``instance``."""
    return shape.class_name() == "Instance"


def registry_id(shape) -> int:
    """The id a JIT shape pointer to ``shape`` holds."""
    return int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(shape))[0])


def group_members(group) -> list:
    """The shapes a shape group holds, in the group's order (its ``shape_index``)."""
    params = mi.traverse(group)
    return [node for node, (parent, _) in params.hierarchy.items()
            if parent is group and isinstance(node, mi.Shape)]


def to_world_rows(instance) -> list:
    """The instance's ``to_world`` as 12 one-entry arrays (A row-major, then b), read
    without a host round trip."""
    m = mi.traverse(instance)["to_world"].matrix
    return [m[r][c] for r in range(3) for c in range(3)] + [m[r][3] for r in range(3)]


def _read(handles: dict, indices) -> mi.Float:
    """The table rows (:data:`ROW` floats) of the instances ``i`` in ``indices``, read
    through their ``to_world`` handles (:func:`to_world_handle`) to the host entry by
    entry and sent back as one array: a numpy view of a matrix would launch a kernel per
    matrix, and joining one-entry arrays on the device costs a Python call per entry.
    The inverse transpose is read too, not computed: Mitsuba's instance uses the one its
    transform holds, which a rotation about an axis of other than unit length leaves
    different from the matrix's."""
    transforms = [mi.get_property(*handles[i]) for i in indices]
    pairs = [(t.matrix, t.inverse_transpose) for t in transforms]
    if pairs and pairs[0][0][0][0].state not in _READ_DIRECTLY:
        dr.eval(pairs)  # one evaluation for all, where the values are still lazy
    rows = np.empty((len(pairs), ROW), np.float32)
    for k, (m, it) in enumerate(pairs):
        r0, r1, r2, i0, i1, i2, i3 = m[0], m[1], m[2], it[0], it[1], it[2], it[3]
        rows[k] = (r0[0][0], r0[1][0], r0[2][0], r1[0][0], r1[1][0], r1[2][0],
                   r2[0][0], r2[1][0], r2[2][0], r0[3][0], r1[3][0], r2[3][0],
                   i0[0][0], i0[1][0], i0[2][0], i1[0][0], i1[1][0], i1[2][0],
                   i2[0][0], i2[1][0], i2[2][0], i3[0][0], i3[1][0], i3[2][0])
    return mi.Float(rows.ravel())


#: States whose entries are read without an evaluation first.
_READ_DIRECTLY = (dr.VarState.Evaluated, dr.VarState.Literal)


def _positions(ids: list) -> mi.UInt32:
    """A table from registry id to the position of that id in ``ids``
    (:data:`_NO_SLOT` for ids not there)."""
    table = [_NO_SLOT] * (max(ids, default=0) + 1)
    for k, rid in enumerate(ids):
        table[rid] = k
    return mi.UInt32(table)


def to_world_handle(instance) -> tuple:
    """What reads the instance's current ``to_world`` (``mi.get_property``'s
    arguments), from one traversal."""
    return mi.traverse(instance).properties["to_world"][:3]


def _matrix4(row) -> np.ndarray:
    """The 4x4 ``to_world`` of a table row (numpy)."""
    m = np.eye(4)
    m[:3, :3] = row[:9].reshape(3, 3)
    m[:3, 3] = row[9:12]
    return m


class InstanceShading:
    """The expansion of hits of a scene whose shapes include instances.

    Args:
        shapes: ``scene.shapes()``.
        group_of: a function giving the shape group an instance uses (raising
            ValueError when it cannot be told).

    Attributes:
        usable: False when some instance's group cannot be told: then
            :meth:`surface_interaction` is Mitsuba's own.
        slots: ``{index into shapes: slot}`` of every instance, its row in the table of
            transforms.
    """

    def __init__(self, shapes, group_of):
        self.shapes = shapes
        instances = [i for i, s in enumerate(shapes) if is_instance(s)]
        self._others = [s for s in shapes if not is_instance(s)]
        self.slots = {i: k for k, i in enumerate(instances)}
        self.usable = bool(instances)
        self._children, bases, where = [], [], {}
        self._handles = {i: to_world_handle(shapes[i]) for i in instances} if self.usable else {}
        self._motion = None  # KeyTable by slot, where instances have keys (refresh)
        self._rows = _read(self._handles, instances) if self.usable else None
        if self.usable:
            table = np.array(self._rows, np.float64).reshape(-1, ROW)
            try:
                for k, i in enumerate(instances):
                    group = group_of(shapes[i], _matrix4(table[k]))
                    if id(group) not in where:
                        where[id(group)] = len(self._children)
                        self._children += group_members(group)
                    bases.append(where[id(group)])
            except ValueError:
                self.usable = False
        if not self.usable:
            return
        self._slot_of_id = _positions([registry_id(shapes[i]) for i in instances])
        self._other_of_id = _positions([registry_id(s) for s in self._others])
        self._child_base = mi.UInt32(bases)

    def refresh(self, indices):
        """Read again the transforms of the instances ``shapes[i]``, ``i`` in
        ``indices``, and every instance's keys over the shutter."""
        if not self.usable:
            return
        keys, shutter = instances_keys([self.shapes[i] for i in self.slots])
        self._motion = None if keys is None else KeyTable.of(mi, keys, shutter)
        if not indices:
            return
        slots = np.array([self.slots[i] for i in indices], np.uint32)
        offsets = (ROW * slots[:, None] + np.arange(ROW, dtype=np.uint32)).ravel()
        dr.scatter(self._rows, _read(self._handles, indices), mi.UInt32(offsets))
        dr.eval(self._rows)

    def rows_of(self, indices) -> mi.Float:
        """The transforms of the instances ``shapes[i]``, ``i`` in ``indices``, as one
        Float of 12 an instance (the two-level builder's input)."""
        k = dr.arange(mi.UInt32, 12 * len(indices))
        slots = dr.gather(mi.UInt32, mi.UInt32([ROW * self.slots[i] for i in indices]), k // 12)
        out = dr.gather(mi.Float, self._rows, slots + k % 12)
        dr.eval(out)
        return out

    def surface_interaction(self, pi, ray, ray_flags=mi.RayFlags.All, active=True):
        """``pi.compute_surface_interaction(ray, ray_flags, active)``, field for field
        (see the module docstring); Mitsuba's own when not :attr:`usable`."""
        if not self.usable:
            return pi.compute_surface_interaction(ray, ray_flags, active)
        flags = int(ray_flags)
        ray = mi.Ray3f(ray)
        active = mi.Bool(active) & pi.is_valid()
        in_instance = active & (pi.instance != None)  # noqa: E711 (JIT compare)
        # ---- Hits inside instances: as Mitsuba's Instance expands them ----
        slot = dr.gather(mi.UInt32, self._slot_of_id,
                         dr.reinterpret_array(mi.UInt32, pi.instance), in_instance)
        to_world = mi.AffineTransform4f(*self._matrices(slot, in_instance, ray.time))
        to_object = to_world.inverse()
        local_ray = to_object @ ray
        child = dr.gather(mi.UInt32, self._child_base, slot, in_instance) + pi.shape_index
        si = _expanded(self._children, child, local_ray, pi, flags, in_instance)
        si = _to_world(si, to_world, to_object, flags)
        si.prim_index = pi.prim_index
        si.instance = pi.instance
        # ---- Hits on other shapes: each shape's own expansion ----
        other = active & ~in_instance
        which = dr.gather(mi.UInt32, self._other_of_id,
                          dr.reinterpret_array(mi.UInt32, pi.shape), other)
        other &= which != _NO_SLOT  # a switch must not see an index past its shapes
        si = dr.select(other, _expanded(self._others, which, ray, pi, flags, other), si)
        return _finalized(si, ray, flags, active)

    def shutter_points(self, pi, si, active):
        """Where hits on instances with keys are at the shutter's open and close (the
        hit's object-space point through the poses there): ``(p_open, p_close, on,
        shutter)``, ``on`` the lanes on such instances; None when no instance has
        keys."""
        if self._motion is None:
            return None
        motion = self._motion
        on = mi.Bool(active) & pi.is_valid() & (pi.instance != None)  # noqa: E711
        slot = dr.gather(mi.UInt32, self._slot_of_id,
                         dr.reinterpret_array(mi.UInt32, pi.instance), on)
        on = motion.keyed(slot, on)
        now = inverse_or_nan(motion.rows_at(slot, motion.time(si.time), on))
        p = _affine(now, si.p)
        ends = [_affine(motion.rows_at(slot, dr.full(mi.Float, t, dr.width(p.x)), on), p)
                for t in (0.0, 1.0)]
        return ends[0], ends[1], on, motion.shutter

    def _matrices(self, slot, active, time) -> tuple:
        """Each lane's instance's object-to-world matrix and its inverse transpose
        (affine: the one's last row, the other's last column 0 0 0 1); an instance with
        keys: its pose at ``time`` (``ray.time``)."""
        m = [dr.gather(mi.Float, self._rows, slot * ROW + c, active) for c in range(ROW)]
        if self._motion is None:
            return _matrix_pair(m)
        keyed = self._motion.keyed(slot, active)
        rows = self._motion.rows_at(slot, self._motion.time(time), keyed)
        moved = [dr.select(keyed, a, b) for a, b in zip(rows, m[:12])]
        transposed = _transposed(inverse_or_nan(moved))
        return _matrix_pair(moved + [dr.select(keyed, a, b) for a, b in zip(transposed, m[12:])])


def _matrix_pair(m: list) -> tuple:
    """The table row ``m`` (:data:`ROW` Float) as ``(matrix, inverse transpose)``."""
    t = m[12:]
    return (mi.Matrix4f(m[0], m[1], m[2], m[9],
                        m[3], m[4], m[5], m[10],
                        m[6], m[7], m[8], m[11],
                        0.0, 0.0, 0.0, 1.0),
            mi.Matrix4f(t[0], t[1], t[2], 0.0,
                        t[3], t[4], t[5], 0.0,
                        t[6], t[7], t[8], 0.0,
                        t[9], t[10], t[11], 1.0))


def _transposed(inv: list) -> list:
    """The inverse rows ``inv`` (12 Float: A⁻¹ row-major, then -A⁻¹ b) as the table's
    inverse transpose entries (its 3x3 transposed, then its last row: -A⁻¹ b)."""
    return [inv[0], inv[3], inv[6], inv[1], inv[4], inv[7], inv[2], inv[5], inv[8], *inv[9:]]


def _affine(rows: list, p) -> mi.Point3f:
    """``A p + b`` for the rows (12 Float) of an affine transform."""
    return mi.Point3f(*[dr.fma(rows[3 * r], p.x, dr.fma(rows[3 * r + 1], p.y,
                                                         dr.fma(rows[3 * r + 2], p.z, rows[9 + r])))
                        for r in range(3)])


#: Most group shapes expanded by a direct call each: every such call runs on every
#: lane, so past a few shapes a switch (each lane runs its own shape's expansion
#: alone) is the cheaper kernel.
MOST_INLINE_CHILDREN = 4


def _expanded(shapes: list, which, ray, pi, flags: int, active):
    """``shapes[which].compute_surface_interaction(ray, pi, flags)`` per lane of
    ``active`` (zeros elsewhere)."""
    if len(shapes) > MOST_INLINE_CHILDREN:
        targets = [lambda ray, pi, active, shape=shape:
                   shape.compute_surface_interaction(ray, pi, flags, active) for shape in shapes]
        return dr.switch(which, targets, ray, pi, active=active,
                         label="hlbvh instance shape expansion")
    si = dr.zeros(mi.SurfaceInteraction3f, dr.width(ray))
    for k, shape in enumerate(shapes):
        mask = active & (which == k)
        si = dr.select(mask, shape.compute_surface_interaction(ray, pi, flags, mask), si)
    return si


def _to_world(si, to_world, to_object, flags: int):
    """The group shape's interaction ``si`` taken to world space, as Mitsuba's
    ``Instance`` takes it (the same operations in the same order)."""
    si.p = to_world @ mi.Point3f(si.p)
    si.n = dr.normalize(to_world @ mi.Normal3f(si.n))
    if flags & int(mi.RayFlags.ShadingFrame):
        si.sh_frame.n = dr.normalize(to_world @ mi.Normal3f(si.sh_frame.n))
        si.initialize_sh_frame()
    if flags & int(mi.RayFlags.dPdUV):
        si.dp_du = to_world @ mi.Vector3f(si.dp_du)
        si.dp_dv = to_world @ mi.Vector3f(si.dp_dv)
    if flags & (int(mi.RayFlags.dNGdUV) | int(mi.RayFlags.dNSdUV)):
        n = si.n if flags & int(mi.RayFlags.dNGdUV) else si.sh_frame.n
        tn = to_world @ mi.Normal3f(dr.normalize(to_object @ mi.Normal3f(n)))
        inv_len = dr.rcp(dr.norm(tn))
        tn *= inv_len
        si.dn_du = mi.Vector3f(to_world @ mi.Normal3f(si.dn_du)) * inv_len
        si.dn_dv = mi.Vector3f(to_world @ mi.Normal3f(si.dn_dv)) * inv_len
        si.dn_du -= tn * dr.dot(tn, si.dn_du)
        si.dn_dv -= tn * dr.dot(tn, si.dn_dv)
    return si


def _finalized(si, ray, flags: int, active):
    """What Mitsuba fills in after a shape's expansion: time, wavelengths, the shading
    frame, the incident direction, no pointers on a miss."""
    si.t = dr.select(active, si.t, dr.inf)
    si.shape = dr.select(active, si.shape, dr.zeros(mi.ShapePtr, dr.width(si.t)))
    si.instance = dr.select(active, si.instance, dr.zeros(mi.ShapePtr, dr.width(si.t)))
    si.time = ray.time
    si.wavelengths = ray.wavelengths
    if flags & int(mi.RayFlags.ShadingFrame):
        si.initialize_sh_frame()
    si.wi = dr.select(active, si.to_local(-ray.d), -ray.d)
    si.duv_dx = dr.zeros(mi.Vector2f, dr.width(si.t))
    si.duv_dy = dr.zeros(mi.Vector2f, dr.width(si.t))
    return si

