"""The contract every animated scene keeps, and how a frame reaches a loaded Mitsuba scene.

An animated scene is a Mitsuba scene description (``scene_dict``) plus, for each frame,
the new geometry of the shapes that move (``frame``), and the sensor's pose and lens
where the camera moves. A render loop looks like::

    scene_desc = hlbvh.scenes.get("cloth", triangles=500_000)
    scene = mi.load_dict(scene_desc.scene_dict(resolution=(640, 360), spp=16))
    params = mi.traverse(scene)
    for i in range(scene_desc.frame_count):
        apply_frame(scene, params, scene_desc.frame(i))
        image = mi.render(scene, params, spp=16, seed=i)
"""

from __future__ import annotations

import abc
import numbers
import operator
from dataclasses import dataclass
from typing import Any

import drjit as dr
import mitsuba as mi
import numpy as np

from hlbvh.kernels.srt import pose_at

from .normals import vertex_normals

#: The most triangles a scene's mesh may have (``--triangles``, ``bench --sizes``): its
#: faces are one Dr.Jit array of three indices per triangle, and a Dr.Jit array holds
#: fewer than 2^32 entries.
MAX_TRIANGLES = (2**32 - 1) // 3


@dataclass(frozen=True)
class FrameGeometry:
    """The geometry of one shape in one frame: new vertices for a mesh, a new transform
    for an instance (rigid motion).

    Attributes:
        positions: a mesh's new vertex positions, flat ``x0, y0, z0, x1, ...`` in world
            space: a numpy ``float32`` array of shape ``(3V,)`` or an ``mi.Float`` of
            width ``3V``; ``None`` for an instance.
        faces: ``None`` when the mesh keeps its triangles (then ``V`` equals the shape's
            current vertex count); otherwise the new triangles, flat vertex indices
            ``(3F,)``: a numpy ``uint32`` array or an ``mi.UInt32``. Given whenever the
            topology may have changed (a sequence shape declared ``topology="changing"``
            gives it every frame).
        to_world: an instance's new object-to-world transform, a ``(4, 4)`` numpy array
            (affine: last row ``0 0 0 1``); ``None`` for a mesh.
    Raises:
        ValueError: neither or both of ``positions`` and ``to_world``.
    """

    positions: Any = None
    faces: Any = None
    to_world: Any = None

    def __post_init__(self):
        if (self.positions is None) == (self.to_world is None):
            raise ValueError("FrameGeometry: give positions (a mesh) or to_world (an "
                             "instance), one of them")

    @property
    def vertex_count(self) -> int:
        """``V``, the number of vertices ``positions`` holds (0 for an instance)."""
        return 0 if self.positions is None else _width(self.positions) // 3

    @property
    def face_count(self) -> int | None:
        """``F``, the number of triangles ``faces`` holds, or ``None`` without faces."""
        return None if self.faces is None else _width(self.faces) // 3


@dataclass(frozen=True)
class FrameSensor:
    """A moving camera in one frame: the sensor's pose, and its lens where that changes.
    A frame gives it under the sensor's id (a scene description's ``"camera"``), beside
    its shapes' :class:`FrameGeometry`.

    Attributes:
        to_world: the camera-to-world transform, a ``(4, 4)`` numpy array in
            Mitsuba's camera convention (looking down +Z, +X to the left), rigid.
        fov: ``(horizontal, vertical)`` field of view of the camera's aperture in
            degrees, or ``None`` to keep the sensor's. The film shows the whole
            aperture: its horizontal field of view is the larger of ``horizontal``
            and ``vertical`` widened by the film's aspect.
        clip: ``(near, far)`` clipping distances in metres, or ``None`` to keep the
            sensor's.
    """

    to_world: Any
    fov: tuple[float, float] | None = None
    clip: tuple[float, float] | None = None


class AnimatedScene(abc.ABC):
    """A Mitsuba scene whose meshes move from frame to frame.

    Subclasses: the procedural scenes (``hlbvh.scenes.get(name)``) and
    :class:`hlbvh.scenes.SequenceScene` (a user's scene plus per-frame mesh files).

    Attributes:
        name: what the scene is called (``"cloth"``, ``"twist"``, ..., ``"sequence"``).
        frame_count: the number of frames; ``frame(i)`` accepts ``0 <= i < frame_count``.
    """

    name: str = ""
    frame_count: int = 0

    @abc.abstractmethod
    def scene_dict(self, resolution: tuple[int, int] | None = None, spp: int | None = None,
                   integrator: dict | None = None) -> dict:
        """A description for ``mi.load_dict``: sensor, integrator, emitters, shapes.

        The film uses a ``box`` reconstruction filter, so two renders with the same
        seed are bit-comparable. Every shape keeps its id through ``mi.load_dict`` with
        the default ``optimize=True`` (no shape is merged into another), so
        ``mi.traverse`` names its buffers ``"<id>.vertex_positions"`` and
        ``"<id>.faces"``. Shapes are handed over as already-built Mitsuba objects: each
        call builds new ones, so load each returned dict once.

        Args:
            resolution: film ``(width, height)`` in pixels; ``None`` keeps the scene's.
            spp: samples per pixel of the sampler; ``None`` keeps the scene's.
            integrator: a Mitsuba integrator dict (``{"type": "path", ...}``); ``None``
                keeps the scene's.
        """

    @abc.abstractmethod
    def animated_ids(self) -> list[str]:
        """Ids of the shapes whose geometry ``frame`` gives (meshes, and instances
        moved by their transform), in a fixed order."""

    @abc.abstractmethod
    def static_ids(self) -> list[str]:
        """Ids of the shapes that never change (their buffers stay as loaded)."""

    @abc.abstractmethod
    def frame(self, i: int) -> dict[str, FrameGeometry]:
        """The geometry of frame ``i`` for every id of :meth:`animated_ids`, and a
        :class:`FrameSensor` under the sensor's id where the camera moves.

        A pure function of the scene's parameters and ``i`` (random access, no state
        carried between calls). Apply it with :func:`apply_frame` before rendering
        frame ``i``, frame 0 included.

        Raises:
            ValueError: ``i`` outside ``0 .. frame_count - 1``.
        """

    @abc.abstractmethod
    def triangle_counts(self) -> dict[str, int]:
        """Triangles per shape id (animated and static) as loaded, computed without
        building the geometry where the scene allows it."""

    def integrator_description(self) -> dict | None:
        """The scene's own integrator as ``{"type": plugin, property: value, ...}``, or
        ``None`` when the scene leaves the integrator to whoever renders it (the
        procedural scenes: ``hlbvh render``'s flags and defaults decide)."""
        return None

    def triangle_count(self) -> int:
        """Total triangles of the scene as loaded (the sum of :meth:`triangle_counts`)."""
        return sum(self.triangle_counts().values())

    def frame_at(self, time: float) -> dict:
        """The geometry at ``time`` in frames, between two frames too (a shutter's keys),
        clamped to the animation's first and last frame. By default a mesh's positions
        are interpolated linearly between the frames around ``time`` (mesh sequences
        between their files), an instance's ``to_world`` as instances are moved inside
        the shutter (:mod:`hlbvh.kernels.srt`: rotation by slerp, stretch and
        translation linearly); a mesh whose triangles the frames give (its topology may
        change) and the camera take the nearer frame's. A scene that knows its motion
        between frames may override it."""
        time = min(max(float(time), 0.0), float(self.frame_count - 1))
        i = min(int(time), self.frame_count - 1)
        f = time - i
        if f == 0.0:
            return self.frame(i)
        before, after = self.frame(i), self.frame(i + 1)
        return {key: _between(geometry, after.get(key), f) for key, geometry in before.items()}

    def _check_frame_index(self, i) -> int:
        """``i`` as an int, after checking it names a frame of this scene."""
        if isinstance(i, bool) or not isinstance(i, numbers.Integral):
            raise TypeError(f"frame index {i!r}: expected an int")
        if not 0 <= int(i) < self.frame_count:
            raise ValueError(
                f"frame {i} of scene {self.name!r}: expected 0 <= frame < {self.frame_count}"
            )
        return int(i)


def _between(before, after, f: float):
    """A shape's geometry a fraction ``f`` of the way from ``before`` to ``after``
    (:meth:`AnimatedScene.frame_at`)."""
    interpolated = (isinstance(before, FrameGeometry) and isinstance(after, FrameGeometry)
                    and before.positions is not None and after.positions is not None
                    and before.faces is None and after.faces is None
                    and before.vertex_count == after.vertex_count)
    if interpolated:
        return FrameGeometry(positions=before.positions * (1.0 - f) + after.positions * f)
    if (isinstance(before, FrameGeometry) and isinstance(after, FrameGeometry)
            and before.to_world is not None and after.to_world is not None):
        return FrameGeometry(to_world=pose_at([before.to_world, after.to_world], f))
    return before if f < 0.5 or after is None else after


def apply_frame(
    scene: mi.Scene,
    params: mi.SceneParameters | None,
    frame_geometry: dict[str, FrameGeometry | FrameSensor],
    deterministic_normals: bool = True,
) -> list[str]:
    """Write one frame's geometry (and camera) into a loaded scene and let Mitsuba
    refresh it.

    Sets ``params[f"{id}.vertex_positions"]`` (and ``params[f"{id}.faces"]`` when the
    frame gives faces) for every mesh of ``frame_geometry``, and, for a mesh with
    vertex normals, ``params[f"{id}.vertex_normals"]``; ``params[f"{id}.to_world"]``
    for every instance it moves; for a :class:`FrameSensor`, the sensor's
    ``to_world``, and its ``x_fov``, ``near_clip`` and ``far_clip`` where it gives the
    lens (Mitsuba's perspective sensor refreshes what it derives from them); then
    calls ``params.update()``
    once: with ``mi.traverse(scene)``'s parameters it recomputes bounds and rebuilds
    the native acceleration structure; with ``hlbvh.traverse(scene)``'s the meshes
    refresh themselves and Mitsuba's accelerator is not rebuilt (for renders whose
    every ray query goes through our accelerator).

    Args:
        scene: the scene loaded from the animated scene's ``scene_dict``.
        params: ``mi.traverse(scene)`` or ``hlbvh.traverse(scene)``; ``None``
            traverses the scene here (``mi.traverse``).
        frame_geometry: the result of ``AnimatedScene.frame(i)``.
        deterministic_normals: compute vertex normals with
            :func:`hlbvh.scenes.normals.vertex_normals` (Mitsuba's weighting, the same
            bits every time; on one thread). ``False`` leaves them to Mitsuba, whose
            parallel sums may differ in the last bit from one update to the next, so
            two scenes given the same frame may no longer render bit-identically.

    Returns:
        The shapes' ids written, in the order of ``frame_geometry`` (a sensor's left
        out).

    Raises:
        ValueError: an id that names no mesh (or, for a transform, no instance) of the
            scene, positions that are empty, not a multiple of 3 long or not finite, a
            vertex count that differs from the mesh's without new faces, faces indexing
            past the last vertex, a transform that is not finite or not invertible; a
            sensor entry whose id names no sensor (or one without the lens parameters
            it gives), a field of view outside ``(0, 180)`` degrees, a clipping range
            not ``0 < near < far``. Nothing is written then.
    """
    if params is None:
        params = mi.traverse(scene)
    mesh_ids = {shape.id() for shape in scene.shapes() if isinstance(shape, mi.Mesh)}
    instance_ids = {shape.id() for shape in scene.shapes() if shape.class_name() == "Instance"}
    sensors = {sensor.id(): sensor for sensor in scene.sensors()}
    staged, transforms, poses, lenses = [], [], [], []
    for shape_id, geometry in frame_geometry.items():
        if isinstance(geometry, FrameSensor):
            if shape_id not in sensors or f"{shape_id}.to_world" not in params:
                raise ValueError(f"frame sensor {shape_id!r}: the scene has no sensor with "
                                 f"that id (its sensors: {sorted(sensors)})")
            poses.append((shape_id, geometry.to_world))
            lenses.append(_checked_lens(shape_id, geometry, sensors[shape_id], params))
            continue
        if geometry.to_world is not None:
            if shape_id not in instance_ids or f"{shape_id}.to_world" not in params:
                raise ValueError(f"frame transform for shape {shape_id!r}: the scene has no "
                                 "instance with that id")
            transforms.append((shape_id, geometry.to_world))
            continue
        key = f"{shape_id}.vertex_positions"
        if shape_id not in mesh_ids or key not in params:
            raise ValueError(
                f"frame geometry for shape {shape_id!r}: the scene has no mesh with that id "
                f"(its meshes: {sorted(mesh_ids)}); load the scene from the same "
                f"animated scene's scene_dict()"
            )
        positions = _checked_positions(shape_id, geometry.positions)
        vertex_count = dr.width(positions) // 3
        faces = None
        if geometry.faces is None:
            current = dr.width(params[key]) // 3
            if vertex_count != current:
                raise ValueError(
                    f"frame geometry for shape {shape_id!r}: {vertex_count} vertices given "
                    f"but the mesh has {current} and no faces were given; pass faces when "
                    f"the topology changes"
                )
        else:
            faces = _checked_faces(shape_id, geometry.faces, vertex_count)
        staged.append((shape_id, positions, faces))
    # A scalar transform: Mitsuba converts it on the write, in half the time of a JIT one
    for (shape_id, _), matrix in zip(transforms + poses, np.concatenate(
            [_checked_transforms(transforms), _checked_transforms(poses, "sensor")])):
        params[f"{shape_id}.to_world"] = mi.ScalarAffineTransform4f(matrix)
    for lens in lenses:
        for key, value in lens.items():
            params[key] = value
    for shape_id, positions, faces in staged:
        params[f"{shape_id}.vertex_positions"] = positions
        if faces is not None:
            params[f"{shape_id}.faces"] = faces
        normals_key = f"{shape_id}.vertex_normals"
        if deterministic_normals and normals_key in params and dr.width(params[normals_key]):
            triangles = faces if faces is not None else params[f"{shape_id}.faces"]
            params[normals_key] = vertex_normals(positions, triangles)
    params.update()
    return [shape_id for shape_id, geometry in frame_geometry.items()
            if not isinstance(geometry, FrameSensor)]


def _checked_lens(sensor_id: str, frame_sensor: FrameSensor, sensor, params) -> dict:
    """The parameters a :class:`FrameSensor`'s lens writes (``{key: value}``): the
    horizontal field of view that shows the whole aperture on the sensor's film, and
    the clipping range; after checking the values and that the sensor has those
    parameters (a ValueError naming the sensor otherwise)."""
    written = {}
    if frame_sensor.fov is not None:
        horizontal, vertical = _checked_pair(sensor_id, "fov", frame_sensor.fov)
        if not (0 < horizontal < 180 and 0 < vertical < 180):
            raise ValueError(f"frame sensor {sensor_id!r}: fov is ({horizontal:g}, "
                             f"{vertical:g}): expected degrees in (0, 180)")
        width, height = sensor.film().crop_size()
        widened = 2 * np.degrees(np.arctan(np.tan(np.radians(vertical) / 2)
                                           * int(width) / int(height)))
        written[f"{sensor_id}.x_fov"] = mi.Float(max(horizontal, float(widened)))
    if frame_sensor.clip is not None:
        near, far = _checked_pair(sensor_id, "clip", frame_sensor.clip)
        if not 0 < near < far:
            raise ValueError(f"frame sensor {sensor_id!r}: clip is ({near:g}, {far:g}): "
                             f"expected 0 < near < far")
        written[f"{sensor_id}.near_clip"], written[f"{sensor_id}.far_clip"] = near, far
    missing = [key for key in written if key not in params]
    if missing:
        raise ValueError(f"frame sensor {sensor_id!r}: the sensor ({sensor.class_name()}) "
                         f"has no parameter {missing[0].split('.', 1)[1]!r}")
    return written


def _checked_pair(sensor_id: str, what: str, pair) -> tuple[float, float]:
    """``pair`` as two finite floats, or a ValueError naming the sensor and ``what``."""
    values = np.asarray(pair, dtype=np.float64).reshape(-1)
    if values.size != 2 or not np.isfinite(values).all():
        raise ValueError(f"frame sensor {sensor_id!r}: {what} is {pair!r}: expected two "
                         f"finite numbers")
    return float(values[0]), float(values[1])


def checked_resolution(resolution) -> tuple[int, int]:
    """``resolution`` as ``(width, height)`` ints, after checking it is two positive
    integers (what every scene's ``scene_dict`` takes); a ValueError naming it
    otherwise."""
    try:
        width, height = resolution
        width, height = operator.index(width), operator.index(height)
    except (TypeError, ValueError):
        raise ValueError(f"resolution={resolution!r}: expected (width, height), two ints") from None
    if width < 1 or height < 1:
        raise ValueError(f"resolution={resolution!r}: expected positive sizes")
    return int(width), int(height)


def _width(array) -> int:
    """Number of scalar entries of a flat numpy or Dr.Jit array."""
    return int(array.size) if isinstance(array, np.ndarray) else dr.width(array)


def _flat(shape_id: str, what: str, values, flat_type):
    """``values`` (numpy, a flat Dr.Jit array, a tensor, or an array of 3-vectors such
    as ``mi.Point3f``/``mi.Vector3u``) as one flat ``flat_type`` array of x, y, z (or
    three corners) per entry.

    Raises:
        ValueError: naming the shape, for any other type (a list, a 3-vector of the
            wrong length).
    """
    if isinstance(values, np.ndarray):
        return flat_type(np.ascontiguousarray(values).reshape(-1).astype(
            np.float32 if flat_type is mi.Float else np.uint32))
    if dr.is_tensor_v(values):
        return flat_type(dr.detach(values).array)
    if dr.is_jit_v(values) and dr.depth_v(values) == 1:
        return flat_type(dr.detach(values))
    if dr.is_jit_v(values) and dr.depth_v(values) == 2 and dr.size_v(values) == 3:
        vectors = dr.detach(values)
        flat = dr.zeros(flat_type, 3 * dr.width(vectors))
        index = dr.arange(mi.UInt32, dr.width(vectors)) * 3
        for k in range(3):
            dr.scatter(flat, flat_type(vectors[k]), index + k)
        return flat
    raise ValueError(f"frame geometry for shape {shape_id!r}: {what} of type "
                     f"{type(values).__name__}; expected a flat numpy or Dr.Jit array (3 "
                     f"per entry), a tensor, or an array of 3-vectors")


def _checked_transforms(transforms: list, kind: str = "shape") -> np.ndarray:
    """The ``(id, to_world)`` pairs' matrices as float32 ``(K, 4, 4)``, after checking
    each is a finite, invertible 4x4 (an instance scaled to nothing would vanish, or
    break its inverse); checked all at once, the first bad one named as the ``kind``
    (shape or sensor) of that id."""
    matrices = []
    for shape_id, to_world in transforms:
        matrix = np.asarray(to_world, dtype=np.float64)
        if matrix.shape != (4, 4):
            raise ValueError(f"frame transform for {kind} {shape_id!r}: shape {matrix.shape}; "
                             "expected a 4x4 matrix")
        matrices.append(matrix)
    if not matrices:
        return np.zeros((0, 4, 4), np.float32)
    stack = np.stack(matrices)
    finite = np.isfinite(stack).all(axis=(1, 2))
    singular = np.abs(np.linalg.det(np.where(finite[:, None, None], stack, 1.0)[:, :3, :3])) <= 1e-30
    for (shape_id, _), is_finite, is_singular in (
            zip(transforms, finite, singular) if (~finite | singular).any() else ()):
        if not is_finite:
            raise ValueError(f"frame transform for {kind} {shape_id!r}: its to_world is not finite")
        if is_singular:
            raise ValueError(f"frame transform for {kind} {shape_id!r}: its to_world is singular "
                             "(a scale of 0)")
    return stack.astype(np.float32)


def _checked_positions(shape_id: str, positions) -> mi.Float:
    """``positions`` as an ``mi.Float`` after checking size and finiteness."""
    result = _flat(shape_id, "positions", positions, mi.Float)
    size = dr.width(result)
    if size == 0 or size % 3 != 0:
        raise ValueError(
            f"frame geometry for shape {shape_id!r}: {size} position values; expected a "
            f"non-empty flat array of 3 per vertex"
        )
    if not bool(dr.all(dr.isfinite(result), axis=None)):
        raise ValueError(f"frame geometry for shape {shape_id!r}: non-finite vertex positions")
    return result


def _checked_faces(shape_id: str, faces, vertex_count: int) -> mi.UInt32:
    """``faces`` as an ``mi.UInt32`` after checking size and index range."""
    if isinstance(faces, np.ndarray):
        flat = np.ascontiguousarray(faces).reshape(-1).astype(np.int64)
        bad = flat[(flat < 0) | (flat >= vertex_count)]
        result = mi.UInt32(flat.astype(np.uint32))
    else:
        result = _flat(shape_id, "faces", faces, mi.UInt32)
        bad = [int(dr.max(result, axis=None)[0])] if dr.width(result) else []
        bad = [b for b in bad if b >= vertex_count]
    size = dr.width(result)
    if size == 0 or size % 3 != 0:
        raise ValueError(
            f"frame geometry for shape {shape_id!r}: {size} face indices; expected a "
            f"non-empty flat array of 3 per triangle"
        )
    if len(bad):
        raise ValueError(
            f"frame geometry for shape {shape_id!r}: face index {int(bad[0])} outside "
            f"0 .. {vertex_count - 1}"
        )
    return result
