"""Motion keys: a moving mesh's vertex positions at ``S + 1`` evenly spaced times over
the shutter, given per frame, so that our structures trace each ray at its own time
(motion blur of deforming meshes), and a camera's poses over the shutter.

Mitsuba's sensors draw a time per camera ray inside ``[shutter_open, shutter_close]``
and every bounce keeps it (``ray.time``), but no Mitsuba shape moves with it.
:func:`set_motion_keys` gives a mesh its keys for the frame being rendered: it writes
the mesh's own positions at the middle of the shutter (what Mitsuba's structures,
emitter sampling and shading start from) and keeps the keys, tied to the vertex buffer
it wrote. A later write of the mesh's positions without keys ends them, so keys given
for one frame never blur the next. :func:`set_camera_keys` gives a sensor its poses at
the keys: our integrators move each camera ray from the sensor's pose to the one at the
ray's time (:func:`camera_ray`). :func:`set_instance_keys` gives an instance of a shape
group its transforms at the keys (rigid motion blur): our two-level tree enters it at
its pose at each ray's time, interpolated as :mod:`hlbvh.kernels.srt` says.
"""

from __future__ import annotations

from dataclasses import dataclass
import math

import drjit as dr
import mitsuba as mi
import numpy as np

from hlbvh.kernels.keyed import checked_keys, mid_shutter
from hlbvh.kernels.srt import decompose, pose_at


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
    if mesh.emitter() is not None:
        raise ValueError(f"mesh {name!r} emits light: emitter sampling would place it at "
                         "its mid-shutter pose while our rays see it move; give its "
                         "motion without keys (each frame an instant), or light the "
                         "scene otherwise")
    open_, close = _checked_shutter(f"mesh {name!r}", shutter)
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


@dataclass(frozen=True)
class CameraKeys:
    """A sensor's poses at evenly spaced times over the shutter.

    Attributes:
        rotations: Quaternion4f of the ``S + 1`` poses' rotations (one entry a key).
        translations: Vector3f of their translations.
        shutter: ``(open, close)`` in the units of ``ray.time``.
        base: the sensor's ``to_world`` when the keys were given (its rays start from
            it), as a tuple of its affine entries; another pose ends the keys.
        to_base: the inverse of that pose.
    """

    rotations: object
    translations: object
    shutter: tuple
    base: tuple
    to_base: object


#: ``id(sensor) -> CameraKeys`` (see :func:`camera_keys`).
_CAMERAS: dict = {}


def set_camera_keys(sensor, to_worlds, shutter) -> None:
    """Give ``sensor`` its poses at ``len(to_worlds)`` evenly spaced times over
    ``shutter`` for the frame about to be rendered; its own ``to_world`` stays the pose
    its rays start from (our integrators move each camera ray to the pose at its time,
    rotations interpolated along the shortest arc, translations linearly).

    Args:
        sensor: the scene's ``mi.Sensor``.
        to_worlds: at least two rigid camera-to-world transforms (4x4 arrays or
            ``mi.ScalarTransform4f``), one per key.
        shutter: ``(open, close)`` in the units of ``ray.time``, ``close > open``.
    Raises:
        ValueError: a bad shutter, fewer than two poses, a pose that is not finite or
            not rigid, naming the sensor and the key.
    """
    name = sensor.id() or "<unnamed sensor>"
    open_, close = _checked_shutter(f"sensor {name!r}", shutter)
    matrices = _key_matrices(f"sensor {name!r}", to_worlds, "camera pose(s)", "")
    rotations, translations = [], []
    for k, m in enumerate(matrices):
        if m.shape != (4, 4) or not np.all(np.isfinite(m)):
            raise ValueError(f"sensor {name!r}: camera key {k} is not a finite 4x4 transform")
        r = m[:3, :3]
        if not np.allclose(r @ r.T, np.eye(3), atol=1e-4) or np.linalg.det(r) <= 0:
            raise ValueError(f"sensor {name!r}: camera key {k} is not rigid (a rotation "
                             "and a translation)")
        rotations.append(dr.scalar.Quaternion4f(dr.matrix_to_quat(dr.scalar.Matrix3f(r))))
        translations.append(m[:3, 3])
    for k in range(1, len(rotations)):  # the shortest arc between neighbouring keys
        if dr.dot(rotations[k - 1], rotations[k]) < 0:
            rotations[k] = -rotations[k]
    base = sensor.world_transform()
    quat = [mi.Float([float(q[c]) for q in rotations]) for c in range(4)]
    _CAMERAS[id(sensor)] = CameraKeys(
        mi.Quaternion4f(*quat), mi.Vector3f(*[mi.Float([float(t[c]) for t in translations])
                                              for c in range(3)]),
        (open_, close), _pose(base), base.inverse())


def camera_keys(sensor) -> CameraKeys | None:
    """The keys :func:`set_camera_keys` gave ``sensor``, while its ``to_world`` is still
    the one it had then (None otherwise, and the keys are dropped)."""
    keys = _CAMERAS.get(id(sensor))
    if keys is None:
        return None
    if keys.base != _pose(sensor.world_transform()):
        del _CAMERAS[id(sensor)]
        return None
    return keys


def clear_camera_keys(sensor) -> None:
    """Forget ``sensor``'s keys (its next frame renders from its own pose only)."""
    _CAMERAS.pop(id(sensor), None)


def camera_ray(scene, ray):
    """``ray`` (a camera ray of ``scene``'s first sensor) moved from the sensor's pose
    to its pose at the ray's time, where the sensor has keys (:func:`set_camera_keys`);
    ``ray`` itself otherwise."""
    if not scene.sensors():
        return ray
    keys = camera_keys(scene.sensors()[0])
    if keys is None:
        return ray
    open_, close = keys.shutter
    segments = dr.width(keys.translations) - 1
    x = dr.clip((ray.time - open_) * (1.0 / (close - open_)), 0.0, 1.0) * segments
    k = dr.minimum(mi.UInt32(dr.floor(x)), segments - 1)
    f = x - mi.Float(k)
    q = dr.slerp(dr.gather(mi.Quaternion4f, keys.rotations, k),
                 dr.gather(mi.Quaternion4f, keys.rotations, k + 1), f)
    t = dr.lerp(dr.gather(mi.Vector3f, keys.translations, k),
                dr.gather(mi.Vector3f, keys.translations, k + 1), f)
    # the ray in the camera's frame, then out through the pose at its time
    o, d = keys.to_base @ ray.o, keys.to_base @ ray.d
    moved = type(ray)(ray)  # a RayDifferential3f stays one (its differentials unmoved)
    moved.o = mi.Point3f(_rotated(q, mi.Vector3f(o)) + t)
    moved.d = _rotated(q, mi.Vector3f(d))
    return moved


def _rotated(q, v) -> mi.Vector3f:
    """``v`` rotated by the unit quaternion ``q``: ``v + 2w(u x v) + 2 u x (u x v)``
    with ``u`` its vector part, ``w`` its scalar part."""
    u = mi.Vector3f(q.x, q.y, q.z)
    c = dr.cross(u, v)
    return v + 2.0 * (q.w * c + dr.cross(u, c))


def _pose(transform) -> tuple:
    """A transform's first three rows (a JIT transform's, width one) as host floats."""
    m = transform.matrix
    return tuple(float(dr.slice(m[r][c], 0)) for r in range(3) for c in range(4))


@dataclass(frozen=True)
class InstanceKeys:
    """An instance's keys for one frame.

    Attributes:
        keys: ``(S + 1, KEY)`` numpy: each key's rotation, stretch and translation
            (:func:`hlbvh.kernels.srt.decompose`); None where every key is the same
            transform (the instance is still: traced as one).
        shutter: ``(open, close)``, in the units of ``ray.time``.
        written: the first entry of the ``to_world`` :func:`set_instance_keys` wrote
            (a Float held, so that its variable stays its own while the keys are kept;
            a later write gives the instance another).
    """

    keys: object
    shutter: tuple
    written: object


#: ``id(instance) -> InstanceKeys`` of the instances given keys (:func:`instance_keys`).
_INSTANCES: dict = {}


def set_instance_keys(instance, to_worlds, shutter) -> None:
    """Give ``instance`` (a Mitsuba ``instance`` of a ``shapegroup``) its transforms at
    ``len(to_worlds)`` evenly spaced times over ``shutter`` for the frame about to be
    rendered. Its own ``to_world`` is set to its pose at the middle of the shutter (what
    Mitsuba's box, shading and native render see); our traversal and shading take it at
    each ray's time (rotation, stretch and translation interpolated per key segment).
    A later write of its ``to_world`` without keys ends them.

    Args:
        instance: the scene's ``mi.Shape`` of class ``Instance``.
        to_worlds: at least two affine object-to-world transforms (4x4 arrays or
            ``mi.ScalarTransform4f``), one per key; a key may scale to nothing (the
            instance is then missed at that time).
        shutter: ``(open, close)`` in the units of ``ray.time``, ``close > open``.
    Raises:
        ValueError: a bad shutter, fewer than two keys, a key that is not a finite
            affine 4x4, naming the instance and the key.
    """
    name = instance.id() or "<unnamed instance>"
    if instance.class_name() != "Instance":
        raise ValueError(f"shape {name!r} ({instance.class_name()}) is not an instance: "
                         "give a mesh its keys with set_motion_keys")
    open_, close = _checked_shutter(f"instance {name!r}", shutter)
    matrices = _key_matrices(f"instance {name!r}", to_worlds, "transform(s)",
                             " (S + 1 over the shutter, S >= 1)")
    for k, m in enumerate(matrices):
        if m.shape != (4, 4) or not np.all(np.isfinite(m)):
            raise ValueError(f"instance {name!r}: key {k} is not a finite 4x4 transform")
        if np.any(m[3] != (0.0, 0.0, 0.0, 1.0)):
            raise ValueError(f"instance {name!r}: key {k} is not affine (its last row is "
                             f"{m[3].tolist()}, expected [0, 0, 0, 1])")
    matrices = np.stack(matrices).astype(np.float32).astype(np.float64)
    still = bool(np.all(matrices == matrices[0]))
    params = mi.traverse(instance)
    params["to_world"] = mi.ScalarAffineTransform4f(pose_at(matrices, 0.5).astype(np.float32))
    params.update()
    _INSTANCES[id(instance)] = InstanceKeys(None if still else decompose(matrices),
                                            (open_, close), _first_entry(instance))


def instance_keys(instance) -> InstanceKeys | None:
    """The keys :func:`set_instance_keys` gave ``instance``, while its ``to_world`` is
    still the one written then (None otherwise, and the keys are dropped)."""
    keys = _INSTANCES.get(id(instance))
    if keys is None:
        return None
    if keys.written.index != _first_entry(instance).index:
        del _INSTANCES[id(instance)]
        return None
    return keys


def _first_entry(instance) -> mi.Float:
    """The first entry of ``instance``'s ``to_world`` as Mitsuba holds it now (a
    handle on its variable, not a copy of its value)."""
    return mi.Float(mi.traverse(instance)["to_world"].matrix[0][0])


def moves_in_shutter(instance) -> bool:
    """Whether ``instance`` has keys of more than one pose (:func:`instance_keys`)."""
    keys = instance_keys(instance)
    return keys is not None and keys.keys is not None


def clear_instance_keys(instance) -> None:
    """Forget ``instance``'s keys (its next frame renders unblurred)."""
    _INSTANCES.pop(id(instance), None)


def instances_keys(instances: list) -> tuple:
    """``(keys, shutter)``: per instance of ``instances`` its keys (``(S + 1, KEY)``
    numpy, None for an instance without keys or with equal ones), and the shutter they
    share; ``(None, None)`` when none has keys.

    Raises:
        ValueError: keys over two different shutters, naming an instance of each.
    """
    given = [(instance, instance_keys(instance)) for instance in instances]
    moving = [(instance, keys) for instance, keys in given
              if keys is not None and keys.keys is not None]
    if not moving:
        return None, None
    first, shutter = moving[0][0], moving[0][1].shutter
    for instance, keys in moving:
        if keys.shutter != shutter:
            raise ValueError(f"instances {first.id()!r} and {instance.id()!r} have keys "
                             f"over different shutters ({shutter} and {keys.shutter}): "
                             "give every instance keys over the same shutter")
    return [None if k is None else k.keys for _, k in given], shutter


def _checked_shutter(what: str, shutter) -> tuple[float, float]:
    """``shutter`` as ``(open, close)``, finite with open < close, or a ValueError that
    names ``what`` (the object given keys)."""
    open_, close = (float(v) for v in shutter)
    if not (math.isfinite(open_) and math.isfinite(close) and close > open_):
        raise ValueError(f"{what}: shutter ({open_}, {close}): expected finite "
                         "open < close (a closed shutter needs no keys)")
    return open_, close


def _key_matrices(what: str, to_worlds, noun: str, hint: str) -> list:
    """The keys' transforms (``mi.Transform4f`` or 4x4 arrays) as float64 numpy arrays,
    at least two of them, or a ValueError naming ``what`` and counting ``noun``."""
    matrices = [np.asarray(m.matrix if hasattr(m, "matrix") else m, np.float64)
                for m in to_worlds]
    if len(matrices) < 2:
        raise ValueError(f"{what}: {len(matrices)} {noun}: expected at least two keys{hint}")
    return matrices
