"""Motion keys: a moving mesh's vertex positions at ``S + 1`` evenly spaced times over
the shutter, given per frame, so that our structures trace each ray at its own time
(motion blur of deforming meshes).

Mitsuba's sensors draw a time per camera ray inside ``[shutter_open, shutter_close]``
and every bounce keeps it (``ray.time``), but no Mitsuba shape moves with it.
:func:`set_motion_keys` gives a mesh its keys for the frame being rendered: it writes
the mesh's own positions at the middle of the shutter (what Mitsuba's structures,
emitter sampling and shading start from) and keeps the keys, tied to the vertex buffer
it wrote. A later write of the mesh's positions without keys ends them, so keys given
for one frame never blur the next.
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import drjit as dr
import mitsuba as mi

from hlbvh.kernels.keyed import checked_keys, mid_shutter


@dataclass(frozen=True)
class MotionKeys:
    """A mesh's keys for one frame.

    Attributes:
        points: ``S + 1`` flat Float arrays (3·V) of world-space positions, key ``k`` at
            time ``open + k·(close - open)/S``.
        shutter: ``(open, close)``, in the units of ``ray.time``.
        buffer: the vertex buffer :func:`set_motion_keys` wrote (held, so that its
            variable index stays its own while the keys are kept).
    """

    points: list
    shutter: tuple
    buffer: mi.Float

    @property
    def count(self) -> int:
        return len(self.points)


#: ``id(mesh) -> MotionKeys`` of the meshes given keys (see :func:`motion_keys`).
_KEYS: dict = {}


def set_motion_keys(mesh, keys, shutter) -> None:
    """Give ``mesh`` its positions at ``len(keys)`` evenly spaced times over ``shutter``
    for the frame about to be rendered.

    Args:
        mesh: a ``mi.Mesh`` of the scene (world-space positions, as Mitsuba stores them).
        keys: at least two flat Float (3·V) or Array3f (V) arrays, one per key, each of
            the mesh's vertex count.
        shutter: ``(open, close)`` in the units of ``ray.time`` (the sensor's
            ``shutter_open`` and ``shutter_close``), ``close > open``.
    Raises:
        ValueError: a bad shutter, or keys of another vertex count or not finite,
            naming the mesh and the key.
    """
    name = mesh.id() or "<unnamed mesh>"
    open_, close = (float(v) for v in shutter)
    if not (math.isfinite(open_) and math.isfinite(close) and close > open_):
        raise ValueError(f"mesh {name!r}: shutter ({open_}, {close}): expected finite "
                         "open < close (a closed shutter needs no keys)")
    try:
        points = checked_keys(keys, mesh.faces_buffer())
    except (TypeError, ValueError) as error:
        raise ValueError(f"mesh {name!r}: {error}") from None
    if dr.width(points[0]) != 3 * mesh.vertex_count():
        raise ValueError(f"mesh {name!r}: keys of {dr.width(points[0]) // 3} vertices, "
                         f"the mesh has {mesh.vertex_count()}")
    params = mi.traverse(mesh)
    if "vertex_positions" not in params:  # a rectangle or cube keeps a transform instead
        raise ValueError(f"mesh {name!r} ({mesh.class_name()}) has no vertex_positions "
                         "parameter to key: load it as a triangle mesh (obj, ply, "
                         "mi.Mesh)")
    params["vertex_positions"] = mid_shutter(points)
    params.update()
    _KEYS[id(mesh)] = MotionKeys(points, (open_, close), mesh.vertex_positions_buffer())


def motion_keys(mesh) -> MotionKeys | None:
    """The keys :func:`set_motion_keys` gave ``mesh``, while its vertex buffer is still
    the one written then (None otherwise, and the keys are dropped)."""
    keys = _KEYS.get(id(mesh))
    if keys is None:
        return None
    if keys.buffer.index != mesh.vertex_positions_buffer().index:
        del _KEYS[id(mesh)]
        return None
    return keys


def clear_motion_keys(mesh) -> None:
    """Forget ``mesh``'s keys (its next frame renders unblurred)."""
    _KEYS.pop(id(mesh), None)
