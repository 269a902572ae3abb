"""Animated USD stages as input: what DCC tools export (a baked point cache is
``points.timeSamples`` on a ``Mesh``, rigid animation is time-sampled ``xformOp``s),
read with Pixar's ``pxr`` (``pip install 'hlbvh[usd]'``, the ``usd-core`` package)
into an :class:`hlbvh.scenes.AnimatedScene`.

What a stage becomes
--------------------
Frames
    Frame ``i`` is time code ``startTimeCode + i``, up to ``endTimeCode`` included,
    as pxr reports them (an ``endTimeCode`` authored alone starts at 0); a stage
    without an authored ``endTimeCode`` has one frame, at its start time code.
Units and axes
    Everything is converted to Mitsuba's Y-up metres: positions are scaled by
    ``metersPerUnit`` and a Z-up stage is turned Z -> Y (``(x, y, z) -> (x, z, -y)``),
    so it renders upright.
Meshes (``UsdGeom.Mesh``)
    Only what renders: visible prims of purpose ``default`` or ``render``, traversed
    through instance proxies. Each mesh is handed to Mitsuba in world space, its points
    transformed through every ancestor's transform at each time code; polygons are
    triangulated as fans (exact for convex polygons, as DCC exports are), holes
    dropped. A subdivision scheme other than ``none`` renders the control cage with
    smooth vertex normals (said once per stage). Authored vertex normals are used on
    meshes that do not move (a moving mesh's normals are recomputed every frame by
    :func:`hlbvh.scenes.apply_frame`); ``doubleSided`` wraps the BSDF in ``twosided``.
Motion
    From the time samples: *deforming* (its points are time-sampled), *rigid* (only a
    transform, its own or an ancestor's, is), *static* (nothing is).
    :meth:`UsdScene.animated_ids` are the deforming meshes and the rigid instances and
    meshes (a rigid mesh that is not an instance gets its world-space points every frame),
    :meth:`UsdScene.static_ids` the rest, so the accelerator is told what moves and
    never rebuilds what does not.
Instances
    Every instance proxy's mesh, and a mesh of at least
    :data:`RIGID_INSTANCE_TRIANGLES` triangles that moves by a transform alone (rigid),
    is a Mitsuba ``instance`` of a ``shapegroup`` holding the mesh prim's parts in the
    prim's own space, its ``to_world`` the prim's transform at each time code: the
    proxies of one prototype mesh share one group (one per set of materials, where
    bindings outside the prototype differ), so a prototype's triangles are held once,
    and a rigid animation moves transforms only (hlbvh rebuilds its top level alone).
    Meshes whose material emits stay world-space meshes (Mitsuba refuses area emitters
    inside shape groups), as does everything with ``instancing=False`` (world-space
    copies, a prototype's triangles once per instance, a rigid mesh's points rewritten
    every frame).
Cameras (``UsdGeom.Camera``)
    The one named by ``camera=``, else the one the stage's render settings
    (``UsdRender.Settings``) name, else the first in traversal order, else a camera
    framing the first frame's meshes (said once). Focal length and apertures give the
    field of view, fitted so the whole aperture shows (``fov_axis`` ``x`` or ``y``),
    the clipping range gives ``near_clip``/``far_clip``. hlbvh's render loop moves
    meshes, not sensors: a time-sampled camera renders every frame from its pose at the
    first frame (said once).
Lights (``UsdLux``)
    ``intensity * 2**exposure * color`` (divided by the light's area with
    ``normalize``), UsdLux's radiance: DistantLight -> ``directional`` of the
    irradiance of that radiance over its disc (``angle``), DomeLight ->
    ``constant``, or ``envmap`` with its latlong ``texture:file`` (OpenEXR's layout,
    as Mitsuba's; the pole +Y, or DomeLight_1's ``poleAxis``; the colour then ignored,
    said), SphereLight -> a ``sphere`` area light (``point`` with ``treatAsPoint``),
    RectLight -> a ``rectangle``, DiskLight -> a ``disk`` area light, each emitting
    along the light's -Z as UsdLux does; time-sampled lights keep their first frame.
    Colour temperature and shaping (cones, IES) are not applied (said).
Per-face materials
    A mesh with ``materialBind`` GeomSubsets becomes one Mitsuba mesh per subset (id
    from the subset's path, its faces, its bound material) plus one for the faces no
    subset takes, each holding all the mesh's points and moving with it.
Materials
    ``UsdPreviewSurface`` bound with ``UsdShade.MaterialBindingAPI``: diffuseColor,
    roughness, metallic to ``principled``; opacity below 1 through a ``mask``
    (``opacityThreshold`` makes it a cutout); emissiveColor to an ``area`` emitter on
    the mesh. A diffuseColor or emissiveColor read from a ``UsdUVTexture`` becomes a
    ``bitmap`` over the mesh's texture coordinates (the ``UsdPrimvarReader_float2``'s
    primvar, ``st`` by default; per point, or faceVarying with the points split where
    their uv differ); a diffuseColor from a ``UsdPrimvarReader_float3`` reads its
    primvar as ``displayColor`` is read; other connected inputs keep their authored
    value (said once per material, naming them). Without a material the ``displayColor`` primvar gives a
    diffuse colour: per point or per face as a Mitsuba mesh attribute
    (``vertex_color``, ``face_color``), its mean for other interpolations (said),
    else grey.
Point instancers (``UsdGeom.PointInstancer``)
    Each mesh of each prototype is a shape group (in the prototype root's space) and
    each point an instance of its prototype's groups, its ``to_world`` the instancer's
    transform through the point's position, orientation and scale at each time code
    (the points move with their frames when any of those is time-sampled). Points
    hidden at the first frame (``invisibleIds``, inactive ids) or scaled to nothing at
    some frame are left out; an instancer whose number of points changes over time, or
    that names no prototype, is not rendered (each said once). Needs ``instancing``.
Not supported
    Curves, points, volumes, implicit shapes (Sphere, Cube, ...), NURBS, references
    and payloads that do not resolve: one warning line each on stderr, with the prim's
    path. UsdSkel skinning is pxr's own (``UsdSkelBakeSkinning`` into the session layer,
    in memory), but over meshes whose points are time-sampled (already baked); where
    pxr cannot bake it the rest points render (said).
No light
    A stage without UsdLux lights is said, and lit by a default sky and sun
    (``default_light=False``: not).

A stage that cannot be opened, has nothing renderable or a bad time range is one
``ValueError`` naming the file.

This module reads the stage and its meshes; the materials, lights and camera are
converted by the mixins of ``usd_materials``, ``usd_lights`` and ``usd_camera``, and what
they share (pxr, the constants, the prim helpers) is in ``usd_prims``.
"""


from __future__ import annotations

import functools
import hashlib
import math
import re
import sys
from dataclasses import dataclass
from pathlib import Path

import mitsuba as mi
import numpy as np

from .animated import AnimatedScene, FrameGeometry
from .usd_camera import _Camera
from .usd_lights import _Lights
from .usd_materials import _Materials
from .usd_prims import (DEFAULT_INTEGRATOR, DEFAULT_SPP, Gf, Sdf, UNSUPPORTED, Usd, UsdGeom,
                        UsdLux, _Mesh, _RESERVED, _Stats, _array, _filenames, _has_normals,
                        _bake_skinning, _matrix, _mitsuba_mesh, _open, _print_warning,
                        _root_transform,
                        _skel_binding, _stderr_captured, _transform_varies, _triangulate, _unresolved_arcs,
                        _vertex_normals, _visibility_varies)


#: A rigid mesh of at least this many triangles is an instance (its transform moved every
#: frame), a smaller one a world-space mesh whose points are rewritten: each distinct
#: group mesh adds its own expansion to every render, which outweighs rewriting and
#: rebuilding a small mesh (300 distinct rigid meshes, measured in docs/decisions.md:
#: even at about 2k triangles each, instances 1.6x slower at 768, faster from 4.8k).
RIGID_INSTANCE_TRIANGLES = 2048

#: The most frames a stage's time range may hold: frame ``i`` renders with seed
#: ``--seed + i``, and seeds are 32-bit.
MAX_FRAMES = 2**32

#: The largest time code magnitude taken: past it, float64 time codes no longer step by
#: 1, so ``startTimeCode + i`` would not name distinct frames.
MAX_TIME_CODE = 2.0**52


def _check_time_codes(stage, where: str) -> None:
    """Refuse a stage whose start or end time code is not finite, lies past
    :data:`MAX_TIME_CODE`, or whose range holds more than :data:`MAX_FRAMES` frames, in
    one short line (such a range cannot be counted or rendered frame by frame)."""
    start, end = float(stage.GetStartTimeCode()), float(stage.GetEndTimeCode())
    for name, value in (("startTimeCode", start), ("endTimeCode", end)):
        if not math.isfinite(value) or abs(value) > MAX_TIME_CODE:
            raise ValueError(f"{where}: {name} {value:.6g}: expected a finite time code "
                             f"within +-2^52 (frame i is at startTimeCode + i)")
    if end - start >= MAX_FRAMES:
        raise ValueError(f"{where}: startTimeCode..endTimeCode {start:.6g}..{end:.6g} holds "
                         f"more than 2^32 frames (a frame's seed is 32-bit)")


def _grouped_arcs(arcs: list[tuple[str, str]]) -> list[tuple[str, str]]:
    """``(who, what USD said)`` once per distinct unresolved asset, sorted: ``who`` is
    the prim's path, or the first path and how many other prims reference the same
    missing file (548 references to one missing file are one line, the same line for
    every command)."""
    grouped: dict[str, list[str]] = {}
    for path, said in arcs:
        grouped.setdefault(said, []).append(path)
    result = []
    for said, paths in sorted(grouped.items()):
        paths.sort()
        who = paths[0] if len(paths) == 1 else f"{paths[0]} and {len(paths) - 1} other prims"
        result.append((who, said))
    return result


def _usd_quiet(method):
    """``method`` of a :class:`UsdScene` with USD's own diagnostics (multi-line C++
    output on stderr) said as one warning line per distinct message, once per stage,
    and numpy's floating-point warnings off (the values that matter are checked and
    named); lines already ours (``hlbvh: ...``) pass through unchanged."""
    @functools.wraps(method)
    def wrapped(self, *args, **kwargs):
        with np.errstate(all="ignore"), _stderr_captured() as said:
            result = method(self, *args, **kwargs)
        for line in said:
            if line.startswith("hlbvh: "):
                print(line, file=sys.stderr)
            elif line.strip():
                text = " ".join(line.split(" -- ", 1)[-1].split())
                self._warn_once(f"{self._where}: USD says: {text[:300]}")
        return result
    return wrapped


def _transform_attributes(prim) -> list:
    """The xformOp attributes of ``prim`` and of its ancestors: what its world
    transform is computed from."""
    found = []
    while prim and not prim.IsPseudoRoot():
        xformable = UsdGeom.Xformable(prim)
        if xformable:
            found += [op.GetAttr() for op in xformable.GetOrderedXformOps()]
        prim = prim.GetParent()
    return found


def _sample_times(attributes, first: float, last: float) -> list[float]:
    """``first``, ``last`` and every time sample of ``attributes`` between them,
    sorted: the time codes where the attributes take their authored values (between
    two samples a value is interpolated, outside them held), so a check made there
    costs what the stage authors, not how many frames its range holds."""
    times = {first, last}
    interval = Gf.Interval(first, last)
    for attribute in attributes:
        times.update(attribute.GetTimeSamplesInInterval(interval))
    return sorted(times)


@dataclass
class _Group:
    """A shape group: a mesh prim's parts in the prim's own space, shared by the
    instances of one prototype mesh."""

    id: str
    parts: list  # _Mesh, local_points their object-space points

    @property
    def triangles(self) -> int:
        return sum(len(part.faces) for part in self.parts)


@dataclass
class _Instance:
    """A mesh prim rendered as an instance of a :class:`_Group`."""

    id: str
    path: Sdf.Path  # the mesh prim's, or the point instancer's
    motion: str  # "static" or "rigid"
    group: _Group
    point: tuple | None = None  # a point instancer's: (its instance index, the mesh's
    #                             transform into its prototype root's space)


def _digest(array) -> str | None:
    """A digest of a mesh's colours or texture coordinates (None stays None)."""
    if array is None:
        return None
    if isinstance(array, tuple):
        return array[0] + ":" + _digest(array[1])
    return hashlib.sha256(np.ascontiguousarray(array).tobytes()).hexdigest()


def _object_points(part) -> np.ndarray:
    """A group part's Mitsuba vertices in its object space."""
    return part.local_points if part.vertex_points is None else part.local_points[part.vertex_points]


class UsdScene(_Materials, _Lights, _Camera, AnimatedScene):
    """An animated USD stage (``.usd``, ``.usda``, ``.usdc``, ``.usdz``) as an animated
    scene; what becomes what is in the module docstring.

    Args:
        path: the stage's root layer.
        camera: the prim path of the camera to render through (``None``: the render
            settings' camera, else the first camera, else a framing default).
        warn: called with each warning line (default: printed on stderr, prefixed
            ``hlbvh:``).
        instancing: rigid meshes and prototypes' meshes as Mitsuba instances (see
            the module docstring); False: every mesh in world space.
        default_light: light a stage without UsdLux lights by a default sky and sun
            (:data:`hlbvh.scenes.usd_lights.DEFAULT_LIGHTS`; said either way).

    Raises:
        ValueError: naming the file: it does not exist, USD cannot open it, its time
            range is reversed, nothing in it renders, the camera path names no camera.
    """

    name = "usd"

    def __init__(self, path, camera: str | None = None, warn=None, instancing: bool = True,
                 default_light: bool = True):
        self._path = Path(path)
        emit = warn or _print_warning
        pending: list[str] = []
        self._warn = pending.append  # said once the stage is known to render
        self._where = f"stage {str(self._path)!r}"
        if not self._path.is_file():
            raise ValueError(f"{self._where}: no such file")
        self.stage = _open(self._path, self._where)
        _check_time_codes(self.stage, self._where)
        self._start = float(self.stage.GetStartTimeCode())
        # pxr's range: an endTimeCode authored alone runs from time code 0 to it
        # (HasAuthoredTimeCodeRange needs both); a startTimeCode alone is one frame.
        if self.stage.HasAuthoredMetadata("endTimeCode"):
            end = float(self.stage.GetEndTimeCode())
            if end < self._start:
                raise ValueError(f"{self._where}: endTimeCode {end:g} is before "
                                 f"startTimeCode {self._start:g}")
            self.frame_count = int(math.floor(end - self._start)) + 1
        else:
            self.frame_count = 1
        self.frames_per_second = float(self.stage.GetTimeCodesPerSecond())
        self._skinned = _bake_skinning(self.stage, self._start,
                                       self._start + self.frame_count - 1)
        self._root = _root_transform(self.stage, self._where)
        self._ids: set[str] = set(_RESERVED)
        self._instancing = bool(instancing)
        self._meshes: list[_Mesh] = []  # in world space
        self._groups: dict[tuple, _Group] = {}
        self._instances: list[_Instance] = []
        self._shapes: list = []  # the meshes and instances, in the stage's order
        self._lights: dict = {}
        unresolved = self._collect()
        if not self._lights:
            self._add_default_lights(default_light)
        if not self._shapes:
            why = (f"; references or payloads that do not resolve: {', '.join(unresolved)}"
                   if unresolved else "")
            # What was seen and left out (a point instancer's reason) says why, in short
            skipped = [line.removeprefix(f"{self._where}: ") for line in pending
                       if "not rendered" in line and "reference or payload" not in line]
            if skipped:
                more = f" (and {len(skipped) - 2} more)" if len(skipped) > 2 else ""
                why += "; " + "; ".join(skipped[:2]) + more
            raise ValueError(f"{self._where}: nothing renderable (no visible UsdGeom.Mesh "
                             f"of purpose default or render){why}")
        self._camera = self._pick_camera(camera)
        self._warn = emit
        for line in pending:
            emit(line)

    def warn_with(self, warn=None) -> None:
        """Where later warning lines go (those said while rendering, such as a
        time-sampled camera's): ``warn``, or stderr for ``None``."""
        self._warn = warn or _print_warning

    def __repr__(self) -> str:
        return (f"UsdScene({str(self._path)!r}, frames={self.frame_count}, "
                f"animated={self.animated_ids()})")

    # ---- The AnimatedScene contract ----------------------------------------------

    def time_code(self, i: int) -> float:
        """The time code of frame ``i``: ``startTimeCode + i``."""
        return self._start + self._check_frame_index(i)

    def animated_ids(self) -> list[str]:
        return [m.id for m in self._shapes if m.motion != "static"]

    def static_ids(self) -> list[str]:
        return [m.id for m in self._shapes if m.motion == "static"]

    def motions(self) -> dict[str, str]:
        """Each mesh's or instance's id's motion: ``"static"``, ``"deforming"`` or
        ``"rigid"``."""
        return {m.id: m.motion for m in self._shapes}

    def prim_paths(self) -> dict[str, str]:
        """Each mesh's or instance's id's prim path on the stage (an instance proxy's
        path for instanced meshes)."""
        return {m.id: str(m.path) for m in self._shapes}

    def instance_groups(self) -> dict[str, str]:
        """Each instance's id and the id of the shape group it instances."""
        return {m.id: m.group.id for m in self._instances}

    def triangle_counts(self) -> dict[str, int]:
        return {m.id: m.group.triangles if isinstance(m, _Instance) else len(m.faces)
                for m in self._shapes}

    @_usd_quiet
    def frame(self, i: int) -> dict[str, FrameGeometry]:
        """World-space points (Mitsuba's Y-up metres, float32) of every moving mesh at
        frame ``i``'s time code; faces too where the mesh's topology is time-sampled,
        where its point count or its transform's mirroring differs from the first
        frame's, and for every later call once a mesh was given faces (the loaded mesh
        then holds that frame's faces, so whichever frames came before, the frame
        applied is the same).

        Raises:
            ValueError: naming the stage, the prim and the frame: ``i`` outside
                ``0 .. frame_count - 1``; a mesh whose point count changes while its
                faces do not; points or a transform that are not finite; an instance
                whose transform is singular at this frame.
        """
        time = Usd.TimeCode(self.time_code(i))
        at = self._at(i)
        cache = UsdGeom.XformCache(time)
        frame = {}
        given = self.__dict__.setdefault("_faces_given", set())
        moving = [m for m in self._instances if m.motion != "static"]
        moved = self._transforms(moving, cache)
        for instance in moving:
            self._check_instance_transform(instance, moved[instance.id], at)
        for mesh in self._shapes:
            if mesh.motion == "static":
                continue
            if isinstance(mesh, _Instance):
                frame[mesh.id] = FrameGeometry(to_world=moved[mesh.id])
                continue
            points, faces = self._geometry(mesh, time, cache, at)
            if faces is None and mesh.vertex_points is None \
                    and len(points) <= int(mesh.faces.max(initial=0)):
                raise ValueError(f"{self._where}: mesh {mesh.path} has {len(points)} points "
                                 f"at {at}, too few for its faces")
            if faces is None and (mesh.id in given or (
                    mesh.vertex_points is None and len(points) != mesh.point_count)):
                faces = mesh.faces  # a new vertex count, or back to the first frame's
            if faces is not None:
                given.add(mesh.id)
            frame[mesh.id] = FrameGeometry(
                np.ascontiguousarray(points, dtype=np.float32).reshape(-1),
                None if faces is None else faces.reshape(-1))
        return frame

    @_usd_quiet
    def world_triangles(self, i: int) -> dict[str, np.ndarray]:
        """Every mesh's triangles at frame ``i`` as ``(F, 3, 3)`` float64 world-space
        corners (Mitsuba's Y-up metres), computed from ``pxr`` alone: what the frames
        hold, for checks."""
        time = Usd.TimeCode(self.time_code(i))
        cache = UsdGeom.XformCache(time)
        result = {}
        for mesh in self._meshes:
            points, faces = self._geometry(mesh, time, cache, self._at(i))
            result[mesh.id] = points[faces if faces is not None else mesh.faces]
        placed = self._transforms(self._instances, cache)
        for instance in self._instances:
            m = placed[instance.id]
            result[instance.id] = np.concatenate([
                (_object_points(part) @ m[:3, :3].T + m[:3, 3])[part.faces]
                for part in instance.group.parts])
        return result

    def source_digest(self) -> str:
        """SHA-256 (hex) of every layer the stage uses and the textures its lights and
        materials read, so a render folder can tell that the stage changed between two
        runs."""
        # A layer inside a .usdz package is "package.usdz[layer.usdc]": the package is
        # the file that changes.
        files = [Path(layer.realPath.split("[")[0]) for layer in self.stage.GetUsedLayers()
                 if layer.realPath]
        files += [Path(name) for light in self._lights.values() for name in _filenames(light)]
        files += [Path(name) for mesh in self._meshes + self._group_parts()
                  for name in _filenames({"bsdf": mesh.bsdf, "emission": mesh.emission}
                                         if isinstance(mesh.emission, dict) else mesh.bsdf)]
        digest = hashlib.sha256()
        for path in sorted(set(files)):
            digest.update(str(path).encode() + b"\0")
            try:
                digest.update(path.read_bytes())
            except OSError:
                digest.update(b"\0unreadable\0")
        return digest.hexdigest()

    @_usd_quiet
    def scene_dict(self, resolution=None, spp=None, integrator=None) -> dict:
        """See :meth:`AnimatedScene.scene_dict`: the camera, lights and every mesh at
        the first frame (apply ``frame(i)`` before rendering frame ``i``). Defaults: a
        width of 640 with the camera aperture's aspect (the render settings' resolution
        where the stage has one), 16 spp, ``path`` with ``max_depth`` 8."""
        width, height = self._resolution(resolution)
        spp = DEFAULT_SPP if spp is None else spp
        if not isinstance(spp, int) or isinstance(spp, bool) or spp < 1:
            raise ValueError(f"spp={spp!r}: expected a positive int")
        description = {
            "type": "scene",
            "integrator": dict(DEFAULT_INTEGRATOR if integrator is None else integrator),
            "camera": self._sensor(width, height, spp),
        }
        time = Usd.TimeCode(self._start)
        cache = UsdGeom.XformCache(time)
        for group in self._groups.values():
            description[group.id] = {"type": "shapegroup", **{
                part.id: _mitsuba_mesh(part, _object_points(part), part.faces)
                for part in group.parts}}
        placed = self._transforms(self._instances, cache)
        for shape in self._shapes:
            if isinstance(shape, _Instance):
                description[shape.id] = {
                    "type": "instance", "shape": {"type": "ref", "id": shape.group.id},
                    "to_world": mi.ScalarTransform4f(placed[shape.id].astype(np.float32))}
                continue
            points, faces = self._geometry(shape, time, cache, self._at(0))
            description[shape.id] = _mitsuba_mesh(
                shape, points, shape.faces if faces is None else faces)
        description.update(self._lights)
        return description

    def _group_parts(self) -> list:
        return [part for group in self._groups.values() for part in group.parts]

    # ---- Reading the stage -------------------------------------------------------

    @_usd_quiet
    def _collect(self) -> list[str]:
        """Walks the stage once (through instance proxies): meshes, lights, and a
        warning for each prim that will not render. Returns the prim paths whose
        reference or payload does not resolve."""
        stats = _Stats()
        time = Usd.TimeCode(self._start)
        cache = UsdGeom.XformCache(time)
        unresolved = _grouped_arcs(_unresolved_arcs(self.stage))
        for path, said in unresolved:
            self._warn(f"{self._where}: {path}: a reference or payload does not resolve "
                       f"({said}); what it would bring is not rendered")
        predicate = Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)
        prims = iter(Usd.PrimRange(self.stage.GetPseudoRoot(), predicate))
        for prim in prims:
            if prim.IsPseudoRoot():
                continue
            imageable = UsdGeom.Imageable(prim)
            if imageable and not self._renders(prim, imageable, time):
                if _visibility_varies(prim):
                    self._warn(f"{self._where}: {prim.GetPath()}: invisible at the first "
                               f"frame, and its time-sampled visibility is not followed: "
                               f"it is not rendered")
                prims.PruneChildren()
                continue
            kind = prim.GetTypeName()
            if prim.IsA(UsdGeom.Mesh):
                self._add_mesh(prim, time, cache, stats)
            elif prim.IsA(UsdLux.BoundableLightBase) or prim.IsA(UsdLux.NonboundableLightBase):
                self._add_light(prim, time, cache)
            elif prim.IsA(UsdGeom.PointInstancer):
                self._add_point_instancer(prim, time, cache, stats)
                prims.PruneChildren()  # its prototypes render through it
            elif kind in UNSUPPORTED or (kind and prim.IsA(UsdGeom.Gprim)):
                self._warn(f"{self._where}: {prim.GetPath()}: a {kind} is not supported; "
                           f"it is not rendered")
                prims.PruneChildren()  # a point instancer's prototypes render through it
            elif kind == "Skeleton" and not self._skinned:
                self._warn(f"{self._where}: {prim.GetPath()}: UsdSkel skinning is not "
                           f"applied (bake it into points); its meshes render at rest")
        if stats.subdivided:
            self._warn(f"{self._where}: {len(stats.subdivided)} mesh(es) with a subdivision "
                       f"scheme ({stats.subdivided[0]}, ...) render their control cage, "
                       f"with smooth normals")
        if stats.face_varying:
            self._warn(f"{self._where}: {len(stats.face_varying)} mesh(es) with normals "
                       f"that are not per vertex ({stats.face_varying[0]}, ...): vertex "
                       f"normals are computed from the points instead")
        if stats.moving_normals:
            self._warn(f"{self._where}: {len(stats.moving_normals)} moving mesh(es) with "
                       f"authored normals ({stats.moving_normals[0]}, ...): their normals "
                       f"are recomputed from the points every frame")
        return [f"{path} ({said})" for path, said in unresolved]

    def _renders(self, prim, imageable, time) -> bool:
        """Whether an imageable prim (and so its subtree) renders: visible at the first
        frame, of purpose default or render."""
        if imageable.ComputeVisibility(time) == UsdGeom.Tokens.invisible:
            return False
        purpose = imageable.ComputePurpose()
        return purpose in (UsdGeom.Tokens.default_, UsdGeom.Tokens.render)

    def _new_id(self, path: Sdf.Path) -> str:
        """A Mitsuba id from a prim path, unique in the scene: ``/World/Flag`` ->
        ``World_Flag`` (``mi.traverse`` keys are ``id.parameter``, so no dots)."""
        base = re.sub(r"[^A-Za-z0-9_]", "_", str(path)).strip("_") or "prim"
        if base[0].isdigit():
            base = f"prim_{base}"
        candidate, k = base, 1
        while candidate in self._ids:
            k += 1
            candidate = f"{base}_{k}"
        self._ids.add(candidate)
        return candidate

    def _add_mesh(self, prim, time, cache, stats: _Stats, group_only: bool = False):
        """A mesh prim as world-space meshes or an instance of its shape group; with
        ``group_only`` (a point instancer's prototype) only the group's parts and
        meshes are made and returned (None: not renderable in a group)."""
        mesh = UsdGeom.Mesh(prim)
        path = prim.GetPath()
        points_attr = mesh.GetPointsAttr()
        deforming = points_attr.GetNumTimeSamples() > 1
        if prim.HasAPI(_skel_binding()) and not deforming and not self._skinned:
            self._warn(f"{self._where}: {path}: bound to a UsdSkel skeleton whose skinning "
                       f"is not applied (bake it into points); its rest points render")
        topology_varies = any(a.GetNumTimeSamples() > 1 for a in (
            mesh.GetFaceVertexCountsAttr(), mesh.GetFaceVertexIndicesAttr()))
        rigid = not deforming and _transform_varies(prim)
        motion = "deforming" if deforming or topology_varies else "rigid" if rigid else "static"
        points = _array(points_attr.Get(time), 3)
        self._check_finite(path, "points", points, f"time code {time.GetValue():g}")
        faces, source_faces, corners = _triangulate(mesh, time, len(points), path,
                                                    self._where, with_faces=True)
        if len(points) == 0 or len(faces) == 0:
            self._warn(f"{self._where}: {path}: a mesh without points or faces; it is not "
                       f"rendered")
            return None
        if group_only and motion != "static":
            self._warn(f"{self._where}: {path}: a point instancer's prototype whose points "
                       f"are time-sampled renders its first frame's points")
            motion = "static"
        counts = np.array(mesh.GetFaceVertexCountsAttr().Get(time) or [], dtype=np.int64)
        if (counts < 3).any():
            self._warn(f"{self._where}: {path}: {int((counts < 3).sum())} face(s) of fewer "
                       f"than 3 vertices are left out")
        if _visibility_varies(prim):
            self._warn(f"{self._where}: {path}: its visibility is time-sampled; its value "
                       f"at the first frame holds for every frame")
        scheme = mesh.GetSubdivisionSchemeAttr().Get()
        normals = _vertex_normals(mesh, time, len(points))
        if normals is None and _has_normals(mesh):
            stats.face_varying.append(str(path))
        if scheme not in (None, UsdGeom.Tokens.none):
            stats.subdivided.append(str(path))
        transform = self._placement(prim, cache)
        double_sided = bool(mesh.GetDoubleSidedAttr().Get())
        parts = [(part, chosen, *self._material(
                    part, mesh, double_sided, time, len(points),
                    None if topology_varies else source_faces[chosen]))
                 for part, chosen in self._material_parts(prim, mesh, time, topology_varies,
                                                          source_faces, len(counts))]
        # A prototype's copy, or a large mesh moved by a transform alone: an instance of
        # a shape group (area emitters cannot be inside one: Mitsuba refuses them there)
        emits = any(part[3] is not None for part in parts)
        if group_only and emits:
            self._warn(f"{self._where}: {path}: a point instancer's prototype whose material "
                       f"emits is not rendered (Mitsuba refuses emitters in shape groups)")
            return None
        instanced = group_only or (
            self._instancing and motion != "deforming" and not emits
            and (prim.IsInstanceProxy()
                 or (motion == "rigid" and len(faces) >= RIGID_INSTANCE_TRIANGLES))
            and self._invertible(prim, motion))
        if normals is not None and motion != "static" and not instanced:
            stats.moving_normals.append(str(path))
            normals = None
        if normals is not None:
            if not instanced:  # to world space (an instance takes them there itself)
                linear = transform[:3, :3]
                normals = normals @ (np.linalg.inv(linear) if np.linalg.det(linear) != 0
                                     else np.linalg.pinv(linear))
            length = np.linalg.norm(normals, axis=1, keepdims=True)
            normals = normals / np.where(length > 0, length, 1)
        wanted = next((st for *_, st in parts if st is not None), None)
        uv = None if wanted is None else self._texcoords(
            prim, mesh, time, wanted, len(points), corners, topology_varies)
        vertex_points = None
        if uv is not None and uv[0] is not None:  # faceVarying: split by (point, uv)
            vertex_points, faces, texcoords = uv
        elif uv is not None:
            texcoords = uv[2]
        mirrored = not instanced and bool(np.linalg.det(transform[:3, :3]) < 0)
        if mirrored:
            faces = faces[:, ::-1].copy()  # a mirroring transform: keep the faces outward
        meshes = []
        for part, chosen, bsdf, emission, colors, st in parts:
            if st is not None and uv is None:
                bsdf, emission = self._material(part, mesh, double_sided, time, len(points),
                                                None, textures=False)[:2]
            if vertex_points is not None:
                if colors is not None and colors[0] == "vertex_color":
                    colors = (colors[0], colors[1][vertex_points])
            meshes.append(_Mesh(
                id="", path=path, motion="static" if instanced else motion,
                faces=faces[chosen], topology_varies=topology_varies,
                smooth=normals is not None or scheme not in (None, UsdGeom.Tokens.none),
                bsdf=bsdf, emission=emission,
                normals=None if normals is None
                else normals if vertex_points is None else normals[vertex_points],
                colors=colors, point_count=len(points), mirrored=mirrored,
                local_points=points if motion == "rigid" or instanced else None,
                vertex_points=vertex_points,
                texcoords=None if uv is None else texcoords))
        if group_only:
            return self._group(prim, parts, meshes)
        if instanced:
            instance_id = self._new_id(path)  # first: the id the mesh has without instancing
            self._add(_Instance(instance_id, path, motion, self._group(prim, parts, meshes)))
            return None
        for (part, *_), made in zip(parts, meshes):
            made.id = self._new_id(part.GetPath())
            self._meshes.append(made)
            self._shapes.append(made)

    def _group(self, prim, parts: list, meshes: list) -> _Group:
        """The shape group of ``meshes`` (the mesh prim's parts in its own space): copies
        of one prototype mesh with the same materials share one."""
        source = prim.GetPrimInPrototype() if prim.IsInstanceProxy() else prim
        key = (str(source.GetPath()),) + tuple(
            (part.GetName(), repr(made.bsdf), _digest(made.colors), _digest(made.texcoords))
            for (part, *_), made in zip(parts, meshes))
        group = self._groups.get(key)
        if group is None:
            for (part, *_), made in zip(parts, meshes):
                inside = part.GetPrimInPrototype() if part.IsInstanceProxy() else part
                made.id = self._new_id(inside.GetPath())
            group = _Group(self._new_id(Sdf.Path(f"{source.GetPath()}_group")), meshes)
            self._groups[key] = group
        return group

    def _add(self, instance: "_Instance") -> None:
        self._instances.append(instance)
        self._shapes.append(instance)

    def _invertible(self, prim, motion: str) -> bool:
        """Whether the prim's transform can be an instance's: finite and invertible at
        the first frame and, when it moves, at every time sample of its transform's
        attributes up to the last frame (an animation that scales a prop to nothing to
        hide it keeps the prop a world-space mesh, whose triangles then collapse; an
        instance's transform must be invertible). The work follows the samples the
        stage authors, not the length of its time range; a scale interpolated through
        0 between two samples is named by :meth:`frame` at the frame where it is."""
        times = [self._start] if motion != "rigid" else _sample_times(
            _transform_attributes(prim), self._start, self.time_code(self.frame_count - 1))
        caches = self.__dict__.setdefault("_time_caches", {})
        for t in times:
            if t not in caches:
                caches[t] = UsdGeom.XformCache(Usd.TimeCode(t))
            m = _matrix(caches[t].GetLocalToWorldTransform(prim))
            if not np.isfinite(m).all() or abs(np.linalg.det(m[:3, :3])) <= 1e-30:
                return False
        return True

    def _transforms(self, instances: list, cache) -> dict:
        """Each instance's object-to-world 4x4 (Mitsuba's Y-up metres) in ``cache``'s
        time, by id; a point instancer's points in one batch."""
        result, points = {}, {}
        for instance in instances:
            if instance.point is None:
                result[instance.id] = self._placement(instance.path, cache)
            else:
                points.setdefault(str(instance.path), []).append(instance)
        for path, chosen in points.items():
            index = np.array([m.point[0] for m in chosen])
            relative = np.stack([m.point[1] for m in chosen])
            placed = (self._placement(path, cache)
                      @ self._point_transforms(path, cache.GetTime())[index] @ relative)
            result.update(zip((m.id for m in chosen), placed))
        return result

    def _placement(self, prim, cache) -> np.ndarray:
        """The local-to-world 4x4 of ``prim`` (or of the prim at that path) in Mitsuba's
        Y-up metres."""
        if not isinstance(prim, Usd.Prim):
            prim = self.stage.GetPrimAtPath(prim)
        return self._root @ _matrix(cache.GetLocalToWorldTransform(prim))

    def _point_transforms(self, path, time) -> np.ndarray:
        """``(N, 4, 4)``: each instance of the point instancer at ``path`` from its
        prototype root's space to the instancer's at ``time`` (every instance, masked
        or not, so indices stay the authored ones); the last time's kept."""
        kept = self.__dict__.setdefault("_points_at", {})
        key = (str(path), time.GetValue())
        if key not in kept:
            instancer = UsdGeom.PointInstancer(self.stage.GetPrimAtPath(path))
            xforms = instancer.ComputeInstanceTransformsAtTime(
                time, time, UsdGeom.PointInstancer.IncludeProtoXform,
                UsdGeom.PointInstancer.IgnoreMask)
            kept.pop(next((k for k in kept if k[0] == key[0]), None), None)
            kept[key] = np.array(xforms, np.float64).reshape(-1, 4, 4).transpose(0, 2, 1)
        return kept[key]

    def _add_point_instancer(self, prim, time, cache, stats: _Stats) -> None:
        """A ``UsdGeom.PointInstancer``: a shape group per mesh of each prototype, and
        for each point an instance of each of its prototype's groups, its transform the
        point's (position, orientation, scale) at each frame. Points hidden at the first
        frame (invisible or inactive ids), or whose transform is singular at some frame,
        are left out (said); an instancer whose count of points changes over time, or
        whose points name no prototype, is not rendered (said)."""
        path = prim.GetPath()
        if not self._instancing:
            self._warn(f"{self._where}: {path}: a PointInstancer renders through Mitsuba "
                       f"instances, which instancing=False turns off; it is not rendered")
            return
        instancer = UsdGeom.PointInstancer(prim)
        indices = np.array(instancer.GetProtoIndicesAttr().Get(time) or [], np.int64)
        targets = instancer.GetPrototypesRel().GetTargets()
        if not len(indices):
            self._warn(f"{self._where}: {path}: a PointInstancer without points at the first "
                       f"frame; nothing of it renders")
            return
        if ((indices < 0) | (indices >= len(targets))).any():
            self._warn(f"{self._where}: {path}: a PointInstancer whose protoIndices name "
                       f"no prototype (it has {len(targets)}); it is not rendered")
            return
        shown = np.ones(len(indices), bool)
        mask = instancer.ComputeMaskAtTime(time)
        if len(mask):
            shown &= np.array(mask, bool)
        attributes = [instancer.GetPositionsAttr(), instancer.GetOrientationsAttr(),
                      instancer.GetScalesAttr(), instancer.GetProtoIndicesAttr()]
        if hasattr(instancer, "GetOrientationsfAttr"):  # newer USD: float orientations
            attributes.append(instancer.GetOrientationsfAttr())
        last = self.time_code(self.frame_count - 1)
        for t in _sample_times(attributes, self._start, last):  # one time's held at a time
            m = self._point_transforms(path, Usd.TimeCode(t))
            if len(m) != len(indices):
                self._warn(f"{self._where}: {path}: a PointInstancer whose number of points "
                           f"changes over time is not supported; it is not rendered")
                return
            shown &= np.isfinite(m).all(axis=(1, 2)) & (
                np.abs(np.linalg.det(np.nan_to_num(m[:, :3, :3]))) > 1e-30)
        members = []  # per prototype: (group, the mesh's transform into the root's space)
        for target in targets:
            root = self.stage.GetPrimAtPath(target)
            found = []
            if root:
                into_root = np.linalg.inv(_matrix(cache.GetLocalToWorldTransform(root)))
                predicate = Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)
                for inside in Usd.PrimRange(root, predicate):
                    if inside.IsA(UsdGeom.Mesh) and self._renders(
                            inside, UsdGeom.Imageable(inside), time):
                        group = self._add_mesh(inside, time, cache, stats, group_only=True)
                        if group is not None:
                            found.append((group, into_root @ _matrix(
                                cache.GetLocalToWorldTransform(inside))))
            members.append(found)
        left = int((~shown).sum())
        if left:
            self._warn(f"{self._where}: {path}: {left} of its {len(indices)} points are not "
                       f"rendered (hidden at the first frame, or scaled to nothing at some "
                       f"frame)")
        moving = _transform_varies(prim) or any(a.GetNumTimeSamples() > 1 for a in attributes)
        for i in np.flatnonzero(shown):
            made = members[indices[i]]
            for j, (group, relative) in enumerate(made):
                suffix = f"_{i}" if len(made) == 1 else f"_{i}_{j}"
                self._add(_Instance(self._new_id(Sdf.Path(f"{path}{suffix}")), path,
                                    "rigid" if moving else "static", group,
                                    point=(int(i), relative)))

    def _geometry(self, mesh: _Mesh, time, cache, at: str):
        """``(points (V, 3) float64 world space, faces (F, 3) or None)`` of a mesh at
        ``time`` (``at`` names it: the frame and time code): faces when its topology
        is time-sampled, or when its transform mirrors at this time and not at the
        first frame (or the reverse), so its faces keep facing out.

        Raises:
            ValueError: naming the stage, the mesh and ``at``: its transform or its
                points are not finite.
        """
        prim = self.stage.GetPrimAtPath(mesh.path)
        if mesh.local_points is not None:
            local = mesh.local_points
        else:
            local = _array(UsdGeom.Mesh(prim).GetPointsAttr().Get(time), 3)
        transform = self._placement(prim, cache)
        self._check_finite(mesh.path, "transform", transform, at)
        self._check_finite(mesh.path, "points", local, at)
        points = local @ transform[:3, :3].T + transform[:3, 3]
        if mesh.vertex_points is not None:
            points = points[mesh.vertex_points]
        faces = None
        mirrored = bool(np.linalg.det(transform[:3, :3]) < 0)
        if mesh.topology_varies:
            faces = _triangulate(UsdGeom.Mesh(prim), time, len(local), mesh.path, self._where)
            if mirrored:
                faces = faces[:, ::-1].copy()
        elif mirrored != mesh.mirrored:
            faces = mesh.faces[:, ::-1].copy()
        return points, faces

    def _at(self, i: int) -> str:
        """Frame ``i`` and its time code, as messages name them."""
        return f"frame {i} (time code {self.time_code(i):g})"

    def _check_finite(self, path, what: str, values: np.ndarray, at: str) -> None:
        """A ValueError naming the stage, the prim, ``what`` (``"points"``, ``(V, 3)``,
        or ``"transform"``, a 4x4) and ``at`` when ``values`` holds a NaN or an
        infinity."""
        bad = ~np.isfinite(values)
        if not bad.any():
            return
        if what == "points":
            first = int(np.flatnonzero(bad.any(axis=1))[0])
            raise ValueError(f"{self._where}: {path}: its points at {at} are not finite "
                             f"(point {first} of {len(values)})")
        raise ValueError(f"{self._where}: {path}: its {what} at {at} is not finite")

    def _check_instance_transform(self, instance: _Instance, matrix: np.ndarray,
                                  at: str) -> None:
        """A ValueError naming the stage, the instance's prim and ``at`` when its
        transform there is not finite or is singular (a scale interpolated through 0
        between two time samples: an instance's transform must be invertible)."""
        self._check_finite(instance.path, "transform", matrix, at)
        if abs(np.linalg.det(matrix[:3, :3])) <= 1e-30:
            raise ValueError(f"{self._where}: {instance.path}: its transform at {at} is "
                             f"singular, which a Mitsuba instance cannot take; "
                             f"{self._path.name}:instancing=false renders it as a "
                             f"world-space mesh")

    def _warn_once(self, line: str) -> None:
        said = self.__dict__.setdefault("_said", set())
        if line not in said:
            said.add(line)
            self._warn(line)

    # ---- The camera ----------------------------------------------------------------

