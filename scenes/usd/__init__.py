"""Animated USD stages as input: what DCC tools export (a baked point cache is
``points.timeSamples`` on a ``Mesh``, rigid animation is time-sampled ``xformOp``s),
read with Pixar's ``pxr`` (``pip install 'hlbvh[usd]'``, the ``usd-core`` package)
into an :class:`hlbvh.scenes.AnimatedScene`.

What a stage becomes
--------------------
Frames
    Frame ``i`` is time code ``startTimeCode + i`` (:mod:`.time_codes`).
Units and axes
    Everything is converted to Mitsuba's Y-up metres: positions are scaled by
    ``metersPerUnit`` and a Z-up stage is turned Z -> Y (``(x, y, z) -> (x, z, -y)``),
    so it renders upright.
Meshes (``UsdGeom.Mesh``)
    Visible prims of purpose ``default`` or ``render``, in world space, triangulated,
    each *deforming*, *rigid* or *static* from its time samples (:mod:`.meshes`,
    with per-face materials). :meth:`UsdScene.animated_ids` are the deforming meshes
    and the rigid instances and meshes (a rigid mesh that is not an instance gets its
    world-space points every frame), :meth:`UsdScene.static_ids` the rest, so the
    accelerator is told what moves and never rebuilds what does not.
Instances
    Instance proxies' meshes, and rigid meshes of at least
    :data:`RIGID_INSTANCE_TRIANGLES` triangles, are Mitsuba instances of shape groups
    (:mod:`.instances`, with ``instancing=False`` turning them off).
Cameras (``UsdGeom.Camera``)
    The named, the render settings', the first, or a framing default (:mod:`.camera`);
    a time-sampled camera moves the sensor with the frames (pose, field of view,
    clipping range).
Lights (``UsdLux``)
    In UsdLux's units, each type as the nearest Mitsuba emitter (:mod:`.lights`).
Materials
    ``UsdPreviewSurface``, else ``displayColor``, else grey (:mod:`.materials`);
    a MaterialX-only surface and a referenced ``.mtlx`` file (which usd-core does not
    read) are said. Every surface renders from both sides, as Storm draws it.
Point instancers (``UsdGeom.PointInstancer``)
    Each point an instance of its prototype's shape groups (:mod:`.instances`).
Not supported
    Curves, points, volumes, implicit shapes (Sphere, Cube, ...), NURBS, references
    and payloads that do not resolve: one warning line each on stderr, with the prim's
    path. UsdSkel skinning is pxr's own (``UsdSkelBakeSkinning`` into the session layer,
    in memory), over the time codes of the frames asked for only, widened by the
    shutter (:mod:`.skinning`), but over meshes whose points are time-sampled
    (already baked); where pxr cannot bake it the rest points render (said).
Inside a frame (motion blur)
    :meth:`UsdScene.frame_at` gives each moving mesh its points as pxr evaluates them at
    the fractional time code (interpolated samples, ``velocities`` and ``accelerations``
    from the frame's sample), placed by its xformOps at that time code, the motion
    scaled by its ``motion:blurScale``; instances likewise take their transform at that
    time code (xformOps, and a point instancer's points through
    ``ComputeInstanceTransformsAtTime`` with the frame as its base, so time-sampled
    ``velocities`` and ``angularVelocities`` move them). ``motion:nonlinearSampleCount``
    on a mesh with ``accelerations`` is reported as the ``--motion-keys`` that follows
    it.
No light
    A stage without UsdLux lights is said, and lit by a default sky and sun
    (``default_light=False``: not).

A stage that cannot be opened, has nothing renderable or a bad time range is one
``ValueError`` naming the file.

This module walks the stage and gives its frames; the meshes are read by
``meshes``, instances placed by ``instances``, time codes counted by
``time_codes``, skinning baked by ``skinning``; the materials, lights and camera are
converted by the mixins of ``materials``, ``lights`` and ``camera``, and what they share
(pxr, the constants, the prim helpers) is in ``prims``.
"""


from __future__ import annotations

import hashlib
import math
import re
from pathlib import Path

import mitsuba as mi
import numpy as np

from ..animated import AnimatedScene, FrameGeometry, FrameSensor
from .camera import SENSOR_ID, _Camera
from .instances import (Group, Instance, Placements, check_instance_transform, digest,
                        instancer_points, object_points)
from .lights import _Lights
from .materials import _Materials
from .meshes import (mesh_frame, mesh_parts, read_mesh, renders, shading_normals,
                     stats_lines, world_geometry)
from .prims import (DEFAULT_INTEGRATOR, DEFAULT_SPP, Sdf, UNSUPPORTED, Usd, UsdGeom, UsdLux,
                    _Mesh, _RESERVED, _Stats, cached_name, _filenames, _matrix,
                    _mitsuba_mesh, _open, _print_warning, _root_transform, _unresolved_arcs,
                    _visibility_varies)
from .said import (grouped_arcs, materialx_arcs, materialx_line, nothing_renderable,
                   usd_quiet)
from .skinning import bake_skinning
from .time_codes import (MAX_FRAMES, frame_range, sample_times as _sample_times,
                         transform_attributes)


def _checked_shutter(shutter, where: str) -> tuple[float, float]:
    """``shutter`` as ``(open, close)`` floats; a ValueError naming the stage unless
    both are finite with open <= close."""
    try:
        open_, close = (float(value) for value in shutter)
    except (TypeError, ValueError):
        open_, close = math.nan, math.nan
    if not (math.isfinite(open_) and math.isfinite(close) and open_ <= close):
        raise ValueError(f"{where}: shutter {shutter!r}: expected (open, close) in frames, "
                         f"finite with open <= close")
    return open_, close


#: A rigid mesh of at least this many triangles is an instance (its transform moved every
#: frame), a smaller one a world-space mesh whose points are rewritten: each distinct
#: group mesh adds its own expansion to every render, which outweighs rewriting and
#: rebuilding a small mesh (300 distinct rigid meshes, measured in docs/decisions.md#usd-instancing:
#: even at about 2k triangles each, instances 1.6x slower at 768, faster from 4.8k).
RIGID_INSTANCE_TRIANGLES = 2048


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
            (:data:`hlbvh.scenes.usd.lights.DEFAULT_LIGHTS`; said either way).
        frames: the frames that will be read (``None``: all): UsdSkel skinning is
            baked over their time codes (:meth:`time_span`) only, and :meth:`frame` of
            a frame outside them is refused when the stage is skinned. A range that
            reaches past the stage's last frame is refused as soon as the stage's time
            range is read, before any mesh is (a ``stop`` past
            :data:`~.time_codes.MAX_FRAMES`, more frames than any stage holds, reads to
            the last frame: ``range(A, sys.maxsize)`` for ``--frames A:``).
        shutter: ``(open, close)`` in frames relative to each frame, the times
            :meth:`frame_at` will be asked for around the frames (``(0, 0)``: none): the
            skinning is baked over them too, and with an open shutter what does not blur
            is said (a curve that wants more keys).

    Raises:
        ValueError: naming the file: it does not exist, USD cannot open it, its time
            range is reversed, nothing in it renders, the camera path names no camera,
            a skinned mesh's joint weight is not finite, the shutter is not finite
            with open <= close.
    """

    name = "usd"

    def __init__(self, path, camera: str | None = None, warn=None, instancing: bool = True,
                 default_light: bool = True, frames: range | None = None,
                 shutter: tuple[float, float] = (0.0, 0.0)):
        self._path = Path(path)
        emit = warn or _print_warning
        pending: list[str] = []
        self._warn = pending.append  # said once the stage is known to render
        self._where = f"stage {str(self._path)!r}"
        if not self._path.is_file():
            raise ValueError(f"{self._where}: no such file")
        self.stage = _open(self._path, self._where)
        self._start, self.frame_count = frame_range(self.stage, self._where)
        self._check_frames(frames)
        self.frames_per_second = float(self.stage.GetTimeCodesPerSecond())
        self._shutter = _checked_shutter(shutter, self._where)
        self._span = self.time_span(frames)
        self._skinned, said = bake_skinning(self.stage, *self._span, self._where)
        pending += said
        self._root = _root_transform(self.stage, self._where)
        self._placements = Placements(self.stage, self._root)
        self._ids: set[str] = set(_RESERVED)
        self._instancing = bool(instancing)
        self._meshes: list[_Mesh] = []  # in world space
        self._groups: dict[tuple, Group] = {}
        self._instances: list[Instance] = []
        self._shapes: list = []  # the meshes and instances, in the stage's order
        self._lights: dict = {}
        unresolved = self._collect()
        if not self._lights:
            self._add_default_lights(default_light)
        if not self._shapes:
            raise nothing_renderable(self._where, unresolved, pending)
        self._camera = self._pick_camera(camera)
        if self._shutter[1] > self._shutter[0]:
            pending += self._unblurred_lines()
        self._warn = emit
        for line in pending:
            emit(line)

    def warn_with(self, warn=None) -> None:
        """Where later warning lines go (those said while rendering, such as an
        orthographic camera's): ``warn``, or stderr for ``None``."""
        self._warn = warn or _print_warning

    def __repr__(self) -> str:
        return (f"UsdScene({str(self._path)!r}, frames={self.frame_count}, "
                f"animated={self.animated_ids()})")

    # ---- The AnimatedScene contract ----------------------------------------------

    def time_code(self, i: int) -> float:
        """The time code of frame ``i``: ``startTimeCode + i``."""
        return self._start + self._check_frame_index(i)

    def _check_frames(self, frames: range | None) -> None:
        """Refuse ``frames`` that reach past the stage's last frame (see the class's
        ``frames``)."""
        if frames is None:
            return
        to_last = frames.stop > MAX_FRAMES
        stop = self.frame_count if to_last else frames.stop
        if not frames.start < stop <= self.frame_count:
            last = self._start + self.frame_count - 1
            asked = f"{frames.start}:{'' if to_last else frames.stop}"
            raise ValueError(f"{self._where} has frames 0:{self.frame_count} (time codes "
                             f"{self._start:g}..{last:g}, startTimeCode..endTimeCode); frames "
                             f"{asked} reach past them")

    def time_span(self, frames: range | None = None) -> tuple[float, float]:
        """``(first, last)``: the time codes that reading ``frames`` (``None``: every
        frame) reads, within the stage's range: a frame reads its own time code and,
        through :meth:`frame_at`, those of the shutter around it, out to the whole
        frames that hold them (skinning is baked at frames, and read between them)."""
        frames = range(self.frame_count) if frames is None else frames
        first = min(max(frames.start, 0), self.frame_count - 1)
        last = min(max(frames.stop - 1, first), self.frame_count - 1)
        open_, close = self._shutter
        first = max(min(first, math.floor(first + open_)), 0)
        last = min(max(last, math.ceil(last + close)), self.frame_count - 1)
        return self._start + first, self._start + last

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
        return {m.id: m.group.triangles if isinstance(m, Instance) else len(m.faces)
                for m in self._shapes}

    def frame(self, i: int) -> dict[str, FrameGeometry | FrameSensor]:
        """World-space points (Mitsuba's Y-up metres, float32) of every moving mesh at
        frame ``i``'s time code; faces too where the mesh's topology is time-sampled,
        where its point count or its transform's mirroring differs from the first
        frame's, and for every later call once a mesh was given faces (the loaded mesh
        then holds that frame's faces, so whichever frames came before, the frame
        applied is the same). Where the camera moves (:meth:`camera_moves`), the
        sensor's pose and lens at that time code under ``"camera"``
        (:meth:`camera_at`).

        Raises:
            ValueError: naming the stage, the prim and the frame: ``i`` outside
                ``0 .. frame_count - 1``; a mesh whose point count changes while its
                faces do not; points or a transform that are not finite; an instance
                whose transform is singular at this frame; a skinned stage's frame
                outside the frames it was opened for; a moving camera whose lens or
                transform would not make a sensor at this frame.
        """
        return self._frame(i, 0.0)

    def frame_at(self, time: float) -> dict[str, FrameGeometry | FrameSensor]:
        """:meth:`AnimatedScene.frame_at` (``time`` in frames) as pxr evaluates the
        stage there, for the frame nearest to ``time`` within the animation (the frame
        whose shutter holds it; the base of velocities): each moving mesh's
        points at the fractional time code (:func:`~.meshes.points_at`: its samples
        interpolated, or moved by its velocities and accelerations from the frame's
        sample) and its xformOps at that time code, the time from the frame scaled by
        the mesh's ``motion:blurScale`` (0: no blur); a moving camera at that very time
        code (:meth:`camera_at`, clamped to the animation); each moving instance's
        transform at its own scaled time code (its xformOps there; a point instancer's
        points by ``ComputeInstanceTransformsAtTime`` from the frame's samples, moved by
        their velocities and angular velocities where authored). The time is not
        clamped: a shutter reaching past
        the stage's first or last frame reads what pxr gives there (samples held,
        velocities extrapolated), so a one-frame stage blurs by its velocities.

        Raises:
            ValueError: as :meth:`frame`, naming the time code; a skinned stage's time
                code outside the frames and shutter it was opened for.
        """
        time = float(time)
        if not math.isfinite(time):
            raise ValueError(f"{self._where}: frame_at({time}): expected a finite time")
        i = min(max(math.floor(time + 0.5), 0), self.frame_count - 1)
        frame = self._frame(i, time - i)
        if SENSOR_ID in frame:
            clamped = min(max(time, 0.0), float(self.frame_count - 1))
            frame[SENSOR_ID] = self.camera_at(self._start + clamped)
        return frame

    @usd_quiet
    def _frame(self, i: int, offset: float) -> dict[str, FrameGeometry | FrameSensor]:
        """:meth:`frame` ``i`` with its moving meshes and instances ``offset`` frames
        from it (each scaled by its ``motion:blurScale``; see :meth:`frame_at`)."""
        at = self._baked_at(i)
        time = Usd.TimeCode(self.time_code(i))
        cache = UsdGeom.XformCache(time)
        caches = {time.GetValue(): cache}  # a cache per time code the meshes are read at
        frame = {}
        given = self.__dict__.setdefault("_faces_given", set())
        moving = [m for m in self._shapes if m.motion != "static"]
        paths = {str(m.path): m.path for m in moving}  # a point instancer's points share one
        scaled = {key: self._blurred_code(path, time, offset, at) for key, path in paths.items()}
        codes = {m.id: scaled[str(m.path)] for m in moving}
        for code in set(codes.values()) - set(caches):
            caches[code] = UsdGeom.XformCache(Usd.TimeCode(code))

        def inside(code):
            return at if code == time.GetValue() else self._baked(
                code, f"time code {code:g} (inside {at})")

        instances = [m for m in moving if isinstance(m, Instance)]
        for code in sorted({codes[m.id] for m in instances}):
            chosen = [m for m in instances if codes[m.id] == code]
            moved = self._placements.instances(chosen, caches[code], base=time)
            for instance in chosen:
                check_instance_transform(self._where, self._path.name, instance,
                                         moved[instance.id], inside(code))
                frame[instance.id] = FrameGeometry(to_world=moved[instance.id])
        for mesh in moving:
            if isinstance(mesh, Instance):
                continue
            code = codes[mesh.id]
            frame[mesh.id] = mesh_frame(self._placements, mesh, Usd.TimeCode(code),
                                        caches[code], inside(code), self._where, given,
                                        base=time)
        frame = {m.id: frame[m.id] for m in moving}  # in the stage's order
        if self.camera_moves():
            frame[SENSOR_ID] = self.camera_at(self.time_code(i))
        return frame

    def _blurred_code(self, path, time, offset: float, at: str) -> float:
        """The time code the moving mesh or instance at prim ``path`` is read at
        ``offset`` frames from frame time code ``time``: the offset scaled by the prim's
        ``motion:blurScale`` (an instance proxy's, a rigid mesh's or a point
        instancer's; inherited as pxr computes it), so a prim authored not to blur holds
        the frame's pose."""
        code = time.GetValue()
        if not offset:
            return code
        prim = self.stage.GetPrimAtPath(path)
        scale = UsdGeom.MotionAPI(prim).ComputeMotionBlurScale(time)
        if not math.isfinite(scale):
            raise ValueError(f"{self._where}: {path}: motion:blurScale {scale} at "
                             f"{at}: expected a finite scale")
        return code + offset * scale

    @usd_quiet
    def world_triangles(self, i: int) -> dict[str, np.ndarray]:
        """Every mesh's triangles at frame ``i`` as ``(F, 3, 3)`` float64 world-space
        corners (Mitsuba's Y-up metres), computed from ``pxr`` alone: what the frames
        hold, for checks."""
        at = self._baked_at(i)
        time = Usd.TimeCode(self.time_code(i))
        cache = UsdGeom.XformCache(time)
        result = {}
        for mesh in self._meshes:
            points, faces = world_geometry(self._placements, mesh, time, cache, at,
                                           self._where)
            result[mesh.id] = points[faces if faces is not None else mesh.faces]
        placed = self._placements.instances(self._instances, cache)
        for instance in self._instances:
            m = placed[instance.id]
            result[instance.id] = np.concatenate([
                (object_points(part) @ m[:3, :3].T + m[:3, 3])[part.faces]
                for part in instance.group.parts])
        return result

    def source_digest(self) -> str:
        """SHA-256 (hex) of every layer the stage uses and the textures its lights and
        materials read, so a render folder can tell that the stage changed between two
        runs. A texture rewritten into the temporary folder (scaled, or taken out of a
        .usdz package) counts by its name there, which is its content's digest, not by
        where that folder is: a resume under another ``$TMPDIR`` (a farm job's own)
        agrees."""
        # A layer inside a .usdz package is "package.usdz[layer.usdc]": the package is
        # the file that changes.
        files = [Path(layer.realPath.split("[")[0]) for layer in self.stage.GetUsedLayers()
                 if layer.realPath]
        files += [Path(name) for light in self._lights.values() for name in _filenames(light)]
        files += [Path(name) for mesh in self._meshes + self._group_parts()
                  for name in _filenames({"bsdf": mesh.bsdf, "emission": mesh.emission}
                                         if isinstance(mesh.emission, dict) else mesh.bsdf)]
        digest = hashlib.sha256()
        for name, path in sorted({(cached_name(path) or str(path), path) for path in files}):
            digest.update(name.encode() + b"\0")
            if cached_name(path) is not None:
                continue  # its name holds its content's digest
            try:
                digest.update(path.read_bytes())
            except OSError:
                digest.update(b"\0unreadable\0")
        return digest.hexdigest()

    @usd_quiet
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
            SENSOR_ID: self._sensor(width, height, spp),
        }
        time = Usd.TimeCode(self._start)
        cache = UsdGeom.XformCache(time)
        for group in self._groups.values():
            description[group.id] = {"type": "shapegroup", **{
                part.id: _mitsuba_mesh(part, object_points(part), part.faces)
                for part in group.parts}}
        placed = self._placements.instances(self._instances, cache)
        for shape in self._shapes:
            if isinstance(shape, Instance):
                description[shape.id] = {
                    "type": "instance", "shape": {"type": "ref", "id": shape.group.id},
                    "to_world": mi.ScalarTransform4f(placed[shape.id].astype(np.float32))}
                continue
            points, faces = world_geometry(self._placements, shape, time, cache, self._at(0),
                                           self._where)
            description[shape.id] = _mitsuba_mesh(
                shape, points, shape.faces if faces is None else faces)
        description.update(self._lights)
        return description

    def _group_parts(self) -> list:
        return [part for group in self._groups.values() for part in group.parts]

    # ---- Reading the stage -------------------------------------------------------

    @usd_quiet
    def _collect(self) -> list[str]:
        """Walks the stage once (through instance proxies): meshes, lights, and a
        warning for each prim that will not render, and one for each MaterialX document
        usd-core could not read (naming the materials meshes are bound to in it).
        Returns the prim paths whose reference or payload does not resolve."""
        stats = _Stats()
        time = Usd.TimeCode(self._start)
        cache = UsdGeom.XformCache(time)
        self._materialx, arcs = materialx_arcs(_unresolved_arcs(self.stage))
        self._unbuilt: set[str] = set()  # bound materials that are not on the stage
        unresolved = grouped_arcs(arcs)
        for path, said in unresolved:
            self._warn(f"{self._where}: {path}: a reference or payload does not resolve "
                       f"({said}); what it would bring is not rendered")
        predicate = Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)
        prims = iter(Usd.PrimRange(self.stage.GetPseudoRoot(), predicate))
        for prim in prims:
            if prim.IsPseudoRoot():
                continue
            imageable = UsdGeom.Imageable(prim)
            if imageable and not renders(imageable, time):
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
        for file, prims in sorted(self._materialx.items()):
            self._warn(materialx_line(self._where, file, prims, sorted(
                bound for bound in self._unbuilt
                if any(Sdf.Path(bound).HasPrefix(Sdf.Path(who)) for who in prims))))
        for line in stats_lines(stats, self._where):
            self._warn(line)
        return [f"{path} ({said})" for path, said in unresolved]

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
        read = read_mesh(prim, time, self._where, self._warn, self._skinned, group_only, stats)
        if read is None:
            return None
        path, motion, point_count = read.path, read.motion, len(read.points)
        transform = self._placements.of(prim, cache)
        parts = [(part, chosen, *self._material(
                    part, read.mesh, time, point_count,
                    None if read.topology_varies else read.source_faces[chosen]))
                 for part, chosen in self._material_parts(prim, read.mesh, time,
                                                          read.topology_varies,
                                                          read.source_faces, read.polygon_count)]
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
                 or (motion == "rigid" and len(read.faces) >= RIGID_INSTANCE_TRIANGLES))
            and self._invertible(prim, motion))
        normals = shading_normals(read, transform, instanced, stats)
        wanted = next((st for *_, st in parts if st is not None), None)
        uv = None if wanted is None else self._texcoords(
            prim, read.mesh, time, wanted, point_count, read.corners, read.topology_varies)
        if uv is None:  # no texture coordinates: bitmaps give way to authored values
            parts = [(part, chosen, *self._material(
                        part, read.mesh, time, point_count, None,
                        textures=False)[:2], attributes, st) if st is not None
                     else (part, chosen, bsdf, emission, attributes, st)
                     for part, chosen, bsdf, emission, attributes, st in parts]
        meshes = mesh_parts(read, parts, normals, uv, transform, instanced)
        if group_only:
            return self._group(prim, parts, meshes)
        if instanced:
            instance_id = self._new_id(path)  # first: the id the mesh has without instancing
            self._add(Instance(instance_id, path, motion, self._group(prim, parts, meshes)))
            return None
        for (part, *_), made in zip(parts, meshes):
            made.id = self._new_id(part.GetPath())
            self._meshes.append(made)
            self._shapes.append(made)

    def _group(self, prim, parts: list, meshes: list) -> Group:
        """The shape group of ``meshes`` (the mesh prim's parts in its own space): copies
        of one prototype mesh with the same materials share one."""
        source = prim.GetPrimInPrototype() if prim.IsInstanceProxy() else prim
        key = (str(source.GetPath()),) + tuple(
            (part.GetName(), repr(made.bsdf), digest(made.texcoords),
             *((name, digest(values)) for name, values in sorted(made.attributes.items())))
            for (part, *_), made in zip(parts, meshes))
        group = self._groups.get(key)
        if group is None:
            for (part, *_), made in zip(parts, meshes):
                inside = part.GetPrimInPrototype() if part.IsInstanceProxy() else part
                made.id = self._new_id(inside.GetPath())
            group = Group(self._new_id(Sdf.Path(f"{source.GetPath()}_group")), meshes)
            self._groups[key] = group
        return group

    def _add(self, instance: Instance) -> None:
        self._instances.append(instance)
        self._shapes.append(instance)

    def _invertible(self, prim, motion: str) -> bool:
        """Whether the prim's transform can be an instance's: finite and invertible at
        the first frame and, when it moves, at every time sample of its transform's
        attributes up to the last frame (:meth:`Placements.invertible`). The work
        follows the samples the stage authors, not the length of its time range; a
        scale interpolated through 0 between two samples is named by :meth:`frame` at
        the frame where it is."""
        times = [self._start] if motion != "rigid" else _sample_times(
            transform_attributes(prim), self._start, self.time_code(self.frame_count - 1))
        return self._placements.invertible(prim, times)

    def _add_point_instancer(self, prim, time, cache, stats: _Stats) -> None:
        """A ``UsdGeom.PointInstancer``: a shape group per mesh of each prototype, and
        for each point that renders (:func:`instancer_points`) an instance of each of
        its prototype's groups, its transform the point's (position, orientation,
        scale) at each frame; the points left out are said."""
        path = prim.GetPath()
        if not self._instancing:
            self._warn(f"{self._where}: {path}: a PointInstancer renders through Mitsuba "
                       f"instances, which instancing=False turns off; it is not rendered")
            return
        points = instancer_points(prim, time, self._placements, self._start,
                                  self.time_code(self.frame_count - 1), self._where,
                                  self._warn)
        if points is None:
            return
        members = [self._prototype_groups(target, time, cache, stats)
                   for target in points.targets]
        left = int((~points.shown).sum())
        if left:
            self._warn(f"{self._where}: {path}: {left} of its {len(points.indices)} points "
                       f"are not rendered (hidden at the first frame, or scaled to nothing "
                       f"at some frame)")
        for i in np.flatnonzero(points.shown):
            made = members[points.indices[i]]
            for j, (group, relative) in enumerate(made):
                suffix = f"_{i}" if len(made) == 1 else f"_{i}_{j}"
                self._add(Instance(self._new_id(Sdf.Path(f"{path}{suffix}")), path,
                                   "rigid" if points.moving else "static", group,
                                   point=(int(i), relative)))

    def _prototype_groups(self, target, time, cache, stats: _Stats) -> list:
        """``[(group, the mesh's transform into the prototype root's space)]``: a shape
        group per renderable mesh under a point instancer's prototype ``target``."""
        root = self.stage.GetPrimAtPath(target)
        found = []
        if root:
            into_root = np.linalg.inv(_matrix(cache.GetLocalToWorldTransform(root)))
            predicate = Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)
            for inside in Usd.PrimRange(root, predicate):
                if inside.IsA(UsdGeom.Mesh) and renders(UsdGeom.Imageable(inside), time):
                    group = self._add_mesh(inside, time, cache, stats, group_only=True)
                    if group is not None:
                        found.append((group, into_root @ _matrix(
                            cache.GetLocalToWorldTransform(inside))))
        return found

    def _at(self, i: int) -> str:
        """Frame ``i`` and its time code, as messages name them."""
        return f"frame {i} (time code {self.time_code(i):g})"

    def _baked_at(self, i: int) -> str:
        """:meth:`_at`, and a ValueError naming it when the stage's skinning was not
        baked at frame ``i`` (outside the frames the stage was opened for), where its
        skinned meshes would hold the nearest baked pose."""
        return self._baked(self.time_code(i), self._at(i))

    def _baked(self, code: float, at: str) -> str:
        """``at`` (naming time code ``code``), and a ValueError naming it when the
        stage is skinned and ``code`` lies outside the time codes its skinning was baked
        over (:meth:`time_span`) but inside the stage's range (past the range, pxr holds
        the first or last baked pose, as it holds any sample)."""
        first, last = self._span
        end = self._start + self.frame_count - 1
        if self._skinned and (first > self._start and code < first
                              or last < end and code > last):
            raise ValueError(f"{self._where}: {at}: its UsdSkel skinning was baked over time "
                             f"codes {first:g}..{last:g} only (the frames and shutter it "
                             f"was opened for); open it with frames and a shutter that hold "
                             f"this time")
        return at

    def _unblurred_lines(self) -> list[str]:
        """What an open shutter does not blur as the stage authors it: a mesh whose
        ``accelerations`` curve its motion gets the keys ``--motion-keys`` asks for,
        joined linearly, and its ``motion:nonlinearSampleCount`` is said as the
        ``--motion-keys`` it asks."""
        lines = []
        time = Usd.TimeCode(self._start)
        for mesh in {m.path: m for m in self._meshes if m.motion == "deforming"}.values():
            prim = self.stage.GetPrimAtPath(mesh.path)
            if UsdGeom.Mesh(prim).GetAccelerationsAttr().GetNumTimeSamples() > 0:
                count = UsdGeom.MotionAPI(prim).ComputeNonlinearSampleCount(time)
                lines.append(f"{self._where}: {mesh.path}: its accelerations curve its "
                             f"motion; motion:nonlinearSampleCount {count} asks for "
                             f"{count} samples over the shutter: --motion-keys "
                             f"{max(count - 1, 1)} gives them (keys are joined linearly)")
        return lines

    def _warn_once(self, line: str) -> None:
        said = self.__dict__.setdefault("_said", set())
        if line not in said:
            said.add(line)
            self._warn(line)

    # ---- The camera ----------------------------------------------------------------

