"""Animated USD stages as input: what DCC tools export (a baked point cache is
``points.timeSamples`` on a ``Mesh``, rigid animation is time-sampled ``xformOp``s),
read with Pixar's ``pxr`` (``pip install 'hlbvh[usd]'``, the ``usd-core`` package)
into an :class:`hlbvh.scenes.AnimatedScene`.

What a stage becomes
--------------------
Frames
    Frame ``i`` is time code ``startTimeCode + i``, up to ``endTimeCode`` included;
    a stage without an authored range has one frame, at its start time code.
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
    :meth:`UsdScene.animated_ids` are the deforming and rigid meshes (a rigid one gets
    its world-space points every frame), :meth:`UsdScene.static_ids` the rest, so the
    accelerator is told what moves and never rebuilds what does not.
Instances
    Each instance proxy's mesh is its own world-space mesh: hlbvh cannot move a
    Mitsuba ``instance`` (its accelerator refuses a moving instance), so world-space
    copies are the honest model; a prototype shared by many instances costs memory per
    instance.
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
    ``normalize``): DistantLight -> ``directional`` (that irradiance), DomeLight ->
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
    the mesh. A diffuseColor read from a ``UsdUVTexture`` (its file on disk, not
    inside a .usdz) becomes a ``bitmap`` over the mesh's texture coordinates (the
    ``UsdPrimvarReader_float2``'s primvar, ``st`` by default; per point, or faceVarying
    with the points split where their uv differ); other textured inputs keep their
    authored value (said once per material). Without a material the ``displayColor`` primvar gives a
    diffuse colour: per point or per face as a Mitsuba mesh attribute
    (``vertex_color``, ``face_color``), its mean for other interpolations (said),
    else grey.
Not supported
    Curves, points, volumes, implicit shapes (Sphere, Cube, ...), point instancers,
    NURBS, UsdSkel skinning that is not baked (the rest points render), references and
    payloads that do not resolve: one warning line each on stderr, with the prim's path.

A stage that cannot be opened, has nothing renderable or a bad time range is one
``ValueError`` naming the file.
"""

from __future__ import annotations

import hashlib
import math
import os
import re
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import mitsuba as mi
import numpy as np

from .animated import AnimatedScene, FrameGeometry
from .normals import vertex_normals

try:
    from pxr import Gf, Sdf, Tf, Usd, UsdGeom, UsdLux, UsdRender, UsdShade
except ImportError as _error:  # pragma: no cover - depends on the installation
    raise ImportError(f"USD stages need Pixar's pxr module ({_error}): "
                      f"pip install 'hlbvh[usd]'") from None

#: File suffixes that name a USD stage.
SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")

DEFAULT_WIDTH = 640
DEFAULT_SPP = 16
DEFAULT_INTEGRATOR = {"type": "path", "max_depth": 8}
#: UsdPreviewSurface's defaults (its specification).
PREVIEW_DEFAULTS = {"diffuseColor": (0.18, 0.18, 0.18), "roughness": 0.5, "metallic": 0.0,
                    "opacity": 1.0, "opacityThreshold": 0.0,
                    "emissiveColor": (0.0, 0.0, 0.0)}
GREY = (0.5, 0.5, 0.5)
#: Prim types hlbvh does not render, named in their warning.
UNSUPPORTED = ("BasisCurves", "NurbsCurves", "HermiteCurves", "Points", "Volume",
               "OpenVDBAsset", "Field3DAsset", "NurbsPatch", "PointInstancer", "Sphere",
               "Cube", "Cylinder", "Cone", "Capsule", "Plane", "TetMesh")
#: Dict keys of the scene description that no shape id may take.
_RESERVED = {"type", "integrator", "camera"}
#: Stage axes to Mitsuba's Y-up: (x, y, z) -> (x, z, -y) for a Z-up stage.
_Z_UP_TO_Y_UP = np.array([[1, 0, 0], [0, 0, 1], [0, -1, 0]], dtype=np.float64)
#: USD's camera looks down -Z with +X right; Mitsuba's down +Z with +X left.
_USD_TO_MITSUBA_CAMERA = np.diag([-1.0, 1.0, -1.0, 1.0])
#: UsdLux area lights emit along -Z; Mitsuba's rectangle and disk along +Z.
_FLIP_Z = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass
class _Mesh:
    """One mesh prim as hlbvh renders it."""

    id: str
    path: Sdf.Path
    motion: str                       # "static", "deforming" or "rigid"
    faces: np.ndarray                 # (F, 3) uint32 of the first frame
    topology_varies: bool             # faces given every frame
    smooth: bool                      # vertex normals
    bsdf: dict
    emission: tuple | None
    local_points: np.ndarray | None = None     # (V, 3) float64, rigid meshes
    normals: np.ndarray | None = None           # (V, 3) authored world-space normals
    colors: tuple | None = None                 # ("vertex_color" | "face_color", (N, 3))
    point_count: int = 0                        # V of the first frame
    vertex_points: np.ndarray | None = None     # (V',) the point of each Mitsuba vertex
    texcoords: np.ndarray | None = None         # (V', 2) Mitsuba uv, with a texture


@dataclass
class _Stats:
    """What the traversal saw, for the lines said once per stage."""

    subdivided: list = field(default_factory=list)
    moving_normals: list = field(default_factory=list)
    face_varying: list = field(default_factory=list)


class UsdScene(AnimatedScene):
    """An animated USD stage (``.usd``, ``.usda``, ``.usdc``, ``.usdz``) as an animated
    scene; what becomes what is in the module docstring.

    Args:
        path: the stage's root layer.
        camera: the prim path of the camera to render through (``None``: the render
            settings' camera, else the first camera, else a framing default).
        warn: called with each warning line (default: printed on stderr, prefixed
            ``hlbvh:``).

    Raises:
        ValueError: naming the file: it does not exist, USD cannot open it, its time
            range is reversed, nothing in it renders, the camera path names no camera.
    """

    name = "usd"

    def __init__(self, path, camera: str | None = None, warn=None):
        self._path = Path(path)
        emit = warn or _print_warning
        pending: list[str] = []
        self._warn = pending.append  # said once the stage is known to render
        self._where = f"stage {str(self._path)!r}"
        if not self._path.is_file():
            raise ValueError(f"{self._where}: no such file")
        self.stage = _open(self._path, self._where)
        self._start = float(self.stage.GetStartTimeCode())
        if self.stage.HasAuthoredTimeCodeRange():
            end = float(self.stage.GetEndTimeCode())
            if end < self._start:
                raise ValueError(f"{self._where}: endTimeCode {end:g} is before "
                                 f"startTimeCode {self._start:g}")
            self.frame_count = int(math.floor(end - self._start)) + 1
        else:
            self.frame_count = 1
        self.frames_per_second = float(self.stage.GetTimeCodesPerSecond())
        self._root = _root_transform(self.stage)
        self._ids: set[str] = set(_RESERVED)
        self._meshes: list[_Mesh] = []
        self._lights: dict = {}
        unresolved = self._collect()
        if not self._meshes:
            why = (f"; references or payloads that do not resolve: {', '.join(unresolved)}"
                   if unresolved else "")
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
        return [m.id for m in self._meshes if m.motion != "static"]

    def static_ids(self) -> list[str]:
        return [m.id for m in self._meshes if m.motion == "static"]

    def motions(self) -> dict[str, str]:
        """Each mesh id's motion: ``"static"``, ``"deforming"`` or ``"rigid"``."""
        return {m.id: m.motion for m in self._meshes}

    def prim_paths(self) -> dict[str, str]:
        """Each mesh id's prim path on the stage (an instance proxy's path for
        instanced meshes)."""
        return {m.id: str(m.path) for m in self._meshes}

    def triangle_counts(self) -> dict[str, int]:
        return {m.id: len(m.faces) for m in self._meshes}

    def frame(self, i: int) -> dict[str, FrameGeometry]:
        """World-space points (Mitsuba's Y-up metres, float32) of every moving mesh at
        frame ``i``'s time code; faces too where the mesh's topology is time-sampled.

        Raises:
            ValueError: ``i`` outside ``0 .. frame_count - 1``; a mesh whose point
                count changes while its faces do not.
        """
        time = Usd.TimeCode(self.time_code(i))
        cache = UsdGeom.XformCache(time)
        frame = {}
        for mesh in self._meshes:
            if mesh.motion == "static":
                continue
            points, faces = self._geometry(mesh, time, cache)
            if faces is None and mesh.vertex_points is None \
                    and len(points) <= int(mesh.faces.max(initial=0)):
                raise ValueError(f"{self._where}: mesh {mesh.path} has {len(points)} points "
                                 f"at time code {time.GetValue():g}, too few for its faces")
            if faces is None and mesh.vertex_points is None and len(points) != mesh.point_count:
                faces = mesh.faces  # more points than the first frame's: new vertex count
            frame[mesh.id] = FrameGeometry(
                np.ascontiguousarray(points, dtype=np.float32).reshape(-1),
                None if faces is None else faces.reshape(-1))
        return frame

    def world_triangles(self, i: int) -> dict[str, np.ndarray]:
        """Every mesh's triangles at frame ``i`` as ``(F, 3, 3)`` float64 world-space
        corners (Mitsuba's Y-up metres), computed from ``pxr`` alone: what the frames
        hold, for checks."""
        time = Usd.TimeCode(self.time_code(i))
        cache = UsdGeom.XformCache(time)
        result = {}
        for mesh in self._meshes:
            points, faces = self._geometry(mesh, time, cache)
            result[mesh.id] = points[faces if faces is not None else mesh.faces]
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
        files += [Path(name) for mesh in self._meshes for name in _filenames(mesh.bsdf)]
        digest = hashlib.sha256()
        for path in sorted(set(files)):
            digest.update(str(path).encode() + b"\0")
            try:
                digest.update(path.read_bytes())
            except OSError:
                digest.update(b"\0unreadable\0")
        return digest.hexdigest()

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
        for mesh in self._meshes:
            points, faces = self._geometry(mesh, time, cache)
            description[mesh.id] = _mitsuba_mesh(
                mesh, points, mesh.faces if faces is None else faces)
        description.update(self._lights)
        return description

    # ---- Reading the stage -------------------------------------------------------

    def _collect(self) -> list[str]:
        """Walks the stage once (through instance proxies): meshes, lights, and a
        warning for each prim that will not render. Returns the prim paths whose
        reference or payload does not resolve."""
        stats = _Stats()
        time = Usd.TimeCode(self._start)
        cache = UsdGeom.XformCache(time)
        unresolved = _unresolved_arcs(self.stage)
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
            elif kind in UNSUPPORTED or (kind and prim.IsA(UsdGeom.Gprim)):
                self._warn(f"{self._where}: {prim.GetPath()}: a {kind} is not supported; "
                           f"it is not rendered")
                prims.PruneChildren()  # a point instancer's prototypes render through it
            elif kind == "Skeleton":
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

    def _add_mesh(self, prim, time, cache, stats: _Stats) -> None:
        mesh = UsdGeom.Mesh(prim)
        path = prim.GetPath()
        if prim.HasAPI(_skel_binding()):
            self._warn(f"{self._where}: {path}: bound to a UsdSkel skeleton whose skinning "
                       f"is not applied (bake it into points); its rest points render")
        points_attr = mesh.GetPointsAttr()
        deforming = points_attr.GetNumTimeSamples() > 1
        topology_varies = any(a.GetNumTimeSamples() > 1 for a in (
            mesh.GetFaceVertexCountsAttr(), mesh.GetFaceVertexIndicesAttr()))
        rigid = not deforming and _transform_varies(prim)
        motion = "deforming" if deforming or topology_varies else "rigid" if rigid else "static"
        points = _array(points_attr.Get(time), 3)
        faces, source_faces, corners = _triangulate(mesh, time, len(points), path,
                                                    self._where, with_faces=True)
        if len(points) == 0 or len(faces) == 0:
            self._warn(f"{self._where}: {path}: a mesh without points or faces; it is not "
                       f"rendered")
            return
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
        if normals is not None and motion != "static":
            stats.moving_normals.append(str(path))
            normals = None
        transform = self._root @ _matrix(cache.GetLocalToWorldTransform(prim))
        if np.linalg.det(transform[:3, :3]) < 0:
            faces = faces[:, ::-1].copy()  # a mirroring transform: keep the faces outward
        if normals is not None:
            normals = normals @ np.linalg.inv(transform[:3, :3])
            length = np.linalg.norm(normals, axis=1, keepdims=True)
            normals = normals / np.where(length > 0, length, 1)
        double_sided = bool(mesh.GetDoubleSidedAttr().Get())
        parts = [(part, chosen, *self._material(
                    part, mesh, double_sided, time, len(points),
                    None if topology_varies else source_faces[chosen]))
                 for part, chosen in self._material_parts(prim, mesh, time, topology_varies,
                                                          source_faces, len(counts))]
        wanted = next((st for *_, st in parts if st is not None), None)
        uv = None if wanted is None else self._texcoords(
            prim, mesh, time, wanted, len(points), corners, topology_varies)
        vertex_points = None
        if uv is not None and uv[0] is not None:  # faceVarying: split by (point, uv)
            vertex_points, split_faces, texcoords = uv
            faces = split_faces if np.linalg.det(transform[:3, :3]) >= 0 \
                else split_faces[:, ::-1].copy()
        elif uv is not None:
            texcoords = uv[2]
        for part, chosen, bsdf, emission, colors, st in parts:
            if st is not None and uv is None:
                bsdf = self._material(part, mesh, double_sided, time, len(points), None,
                                      textures=False)[0]
            if vertex_points is not None:
                if colors is not None and colors[0] == "vertex_color":
                    colors = (colors[0], colors[1][vertex_points])
            self._meshes.append(_Mesh(
                id=self._new_id(part.GetPath()), path=path, motion=motion,
                faces=faces[chosen], topology_varies=topology_varies,
                smooth=normals is not None or scheme not in (None, UsdGeom.Tokens.none),
                bsdf=bsdf, emission=emission,
                normals=None if normals is None
                else normals if vertex_points is None else normals[vertex_points],
                colors=colors, point_count=len(points),
                local_points=points if motion == "rigid" else None,
                vertex_points=vertex_points,
                texcoords=None if uv is None else texcoords))

    def _texcoords(self, prim, mesh, time, name: str, point_count: int, corners,
                   topology_varies: bool):
        """The texture coordinates of primvar ``name`` as Mitsuba's uv (``(s, 1 - t)``:
        USD's t runs up the image, Mitsuba's v down): ``(None, None, (V, 2))`` per
        point, or, faceVarying, ``(vertex_points, faces, (V', 2))`` with the points
        split where the uv differ. ``None`` (said) when the mesh has no such primvar,
        it is of another interpolation or the topology is time-sampled."""
        primvar = UsdGeom.PrimvarsAPI(mesh).GetPrimvar(name)
        values = primvar.Get(time) if primvar and primvar.HasValue() else None
        interpolation = primvar.GetInterpolation() if primvar else None
        why = None
        if values is None:
            why = f"has no primvar {name!r}"
        elif topology_varies:
            why = "has a time-sampled topology"
        elif interpolation not in (UsdGeom.Tokens.vertex, UsdGeom.Tokens.varying,
                                   UsdGeom.Tokens.faceVarying):
            why = f"has {name!r} of interpolation {interpolation!r}"
        if why is None:
            values = _array(values, 2)
            indices = primvar.GetIndices(time) if primvar.IsIndexed() else None
            indices = (np.arange(len(values)) if indices is None
                       else np.array(indices, dtype=np.int64))
            if interpolation != UsdGeom.Tokens.faceVarying and len(indices) == point_count:
                st = values[indices]
                return None, None, np.stack([st[:, 0], 1 - st[:, 1]], axis=1)
            face_vertex = np.array(mesh.GetFaceVertexIndicesAttr().Get(time), dtype=np.int64)
            if interpolation == UsdGeom.Tokens.faceVarying and len(indices) == len(face_vertex):
                keys = np.stack([face_vertex, indices], axis=1)
                unique, inverse = np.unique(keys, axis=0, return_inverse=True)
                st = values[unique[:, 1]]
                return (unique[:, 0], inverse.reshape(-1)[corners].astype(np.uint32),
                        np.stack([st[:, 0], 1 - st[:, 1]], axis=1))
            why = f"has {name!r} of another length than its {interpolation} count"
        self._warn(f"{self._where}: {prim.GetPath()}: {why}; its textures are not "
                   f"mapped (their authored values are used)")
        return None

    def _material_parts(self, prim, mesh, time, topology_varies: bool, source_faces,
                        polygon_count: int) -> list:
        """``[(prim whose material binds, triangle selection)]``: the whole mesh, or,
        with ``materialBind`` GeomSubsets, one part per subset (its faces, its bound
        material) and one for the faces no subset takes (the mesh's material). A part
        is a Mitsuba mesh of its own holding all the mesh's points. A mesh whose
        topology is time-sampled is not split (said)."""
        everything = np.ones(len(source_faces), dtype=bool)
        subsets = [subset for subset in UsdGeom.Subset.GetAllGeomSubsets(mesh)
                   if subset.GetFamilyNameAttr().Get() == "materialBind"
                   and subset.GetElementTypeAttr().Get() == UsdGeom.Tokens.face]
        if not subsets:
            return [(prim, everything)]
        if topology_varies:
            self._warn(f"{self._where}: {prim.GetPath()}: its topology is time-sampled, so "
                       f"its {len(subsets)} GeomSubsets are not split out; the whole mesh "
                       f"takes the mesh's own material")
            return [(prim, everything)]
        taken = np.zeros(polygon_count, dtype=bool)
        parts = []
        for subset in subsets:
            polygons = np.array(subset.GetIndicesAttr().Get(time) or [], dtype=np.int64)
            polygons = polygons[(polygons >= 0) & (polygons < polygon_count)]
            chosen = np.isin(source_faces, polygons) & ~taken[source_faces]
            taken[polygons] = True
            if chosen.any():
                parts.append((subset.GetPrim(), chosen))
        rest = ~taken[source_faces]
        return ([(prim, rest)] if rest.any() else []) + parts

    def _geometry(self, mesh: _Mesh, time, cache):
        """``(points (V, 3) float64 world space, faces (F, 3) or None)`` of a mesh at
        ``time``: faces only when its topology is time-sampled."""
        prim = self.stage.GetPrimAtPath(mesh.path)
        if mesh.local_points is not None:
            local = mesh.local_points
        else:
            local = _array(UsdGeom.Mesh(prim).GetPointsAttr().Get(time), 3)
        transform = self._root @ _matrix(cache.GetLocalToWorldTransform(prim))
        points = local @ transform[:3, :3].T + transform[:3, 3]
        if mesh.vertex_points is not None:
            points = points[mesh.vertex_points]
        faces = None
        if mesh.topology_varies:
            faces = _triangulate(UsdGeom.Mesh(prim), time, len(local), mesh.path, self._where)
            if np.linalg.det(transform[:3, :3]) < 0:
                faces = faces[:, ::-1].copy()
        return points, faces

    def _material(self, prim, mesh, double_sided: bool, time, point_count: int,
                  source_faces, textures: bool = True) -> tuple:
        """``(bsdf, emission, colors, st)``: the mesh's BSDF dict, emitted radiance
        (``None``: none), the colour attribute its BSDF reads (``None``: none; see
        :meth:`_display_color`) and the primvar of texture coordinates a bitmap of it
        reads (``None``: none; ``textures=False``: the textured inputs' authored values
        instead)."""
        material, _ = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()
        shader = None
        if material:
            source = material.ComputeSurfaceSource()
            shader = source[0] if source and source[0] else None
            if shader is not None and shader.GetIdAttr().Get() != "UsdPreviewSurface":
                self._warn(f"{self._where}: {material.GetPath()}: surface shader "
                           f"{shader.GetIdAttr().Get()!r} is not a UsdPreviewSurface; "
                           f"{prim.GetPath()} renders grey")
                shader = None
        if shader is None:
            color = self._display_color(prim, mesh, time, point_count, source_faces)
            if isinstance(color, tuple) and isinstance(color[0], str):
                reflectance = {"type": "mesh_attribute", "name": color[0]}
                colors = color
            else:
                reflectance, colors = {"type": "rgb", "value": list(color)}, None
            bsdf = {"type": "diffuse", "reflectance": reflectance}
            return (_two_sided(bsdf) if double_sided else bsdf), None, colors, None
        values, textured = {}, []
        for name, default in PREVIEW_DEFAULTS.items():
            shader_input = shader.GetInput(name)
            value = shader_input.Get(time) if shader_input else None
            if shader_input and shader_input.HasConnectedSource():
                textured.append(name)
            values[name] = default if value is None else (
                tuple(float(v) for v in value) if isinstance(default, tuple) else float(value))
        base_color = {"type": "rgb", "value": list(values["diffuseColor"])}
        st = None
        if textures and "diffuseColor" in textured:
            bitmap = _uv_texture(shader.GetInput("diffuseColor"), time)
            if bitmap is not None:
                base_color, st = bitmap
                textured.remove("diffuseColor")
        if textured:
            self._warn_once(f"{self._where}: {material.GetPath()}: textured inputs "
                            f"({', '.join(textured)}) are not read; their authored values "
                            f"are used")
        bsdf = {"type": "principled",
                "base_color": base_color,
                "roughness": min(max(values["roughness"], 0.0), 1.0),
                "metallic": min(max(values["metallic"], 0.0), 1.0)}
        if double_sided:
            bsdf = _two_sided(bsdf)
        opacity = min(max(values["opacity"], 0.0), 1.0)
        if values["opacityThreshold"] > 0:
            opacity = 1.0 if opacity >= values["opacityThreshold"] else 0.0
        if opacity < 1:
            bsdf = {"type": "mask", "opacity": opacity, "bsdf": bsdf}
        emission = values["emissiveColor"]
        return bsdf, (emission if any(c > 0 for c in emission) else None), None, st

    def _display_color(self, prim, mesh, time, point_count: int, source_faces):
        """The ``displayColor`` primvar: one colour ``(r, g, b)`` when it is constant
        (grey without one); per point (``vertex``/``varying``) or per face
        (``uniform``) as a Mitsuba mesh attribute ``("vertex_color", (V, 3))`` or
        ``("face_color", (F, 3))`` (per triangle); other interpolations, or a mesh whose
        topology is time-sampled (``source_faces`` ``None``), get the mean colour
        (said)."""
        primvar = mesh.GetDisplayColorPrimvar()
        value = primvar.ComputeFlattened(time) if primvar and primvar.HasValue() else None
        if value is None or len(value) == 0:
            return GREY
        colors = _array(value, 3)
        if len(colors) == 1 or np.all(colors == colors[0]):
            return tuple(float(c) for c in colors[0])
        interpolation = primvar.GetInterpolation()
        if interpolation in (UsdGeom.Tokens.vertex, UsdGeom.Tokens.varying) \
                and len(colors) == point_count:
            return ("vertex_color", colors)
        if interpolation == UsdGeom.Tokens.uniform and source_faces is not None \
                and len(source_faces) and len(colors) > int(source_faces.max()):
            return ("face_color", colors[source_faces])
        self._warn(f"{self._where}: {prim.GetPath()}: displayColor of interpolation "
                   f"{interpolation!r} varies over the mesh; its mean colour is used")
        return tuple(float(c) for c in colors.mean(axis=0))

    def _warn_once(self, line: str) -> None:
        said = self.__dict__.setdefault("_said", set())
        if line not in said:
            said.add(line)
            self._warn(line)

    def _add_light(self, prim, time, cache) -> None:
        """A UsdLux light as a Mitsuba emitter (or an emitting shape)."""
        path = prim.GetPath()
        kind = prim.GetTypeName()
        light = UsdLux.LightAPI(prim)
        if any(a.GetNumTimeSamples() > 1 for a in prim.GetAttributes()) or \
                _transform_varies(prim):
            self._warn(f"{self._where}: {path}: a time-sampled light; every frame uses its "
                       f"first frame's")
        intensity = float(light.GetIntensityAttr().Get(time) or 0.0)
        exposure = float(light.GetExposureAttr().Get(time) or 0.0)
        color = light.GetColorAttr().Get(time)
        color = np.array([1.0, 1.0, 1.0] if color is None else list(color), dtype=np.float64)
        radiance = intensity * 2.0 ** exposure * color
        normalize = bool(light.GetNormalizeAttr().Get(time))
        if light.GetEnableColorTemperatureAttr().Get(time):
            self._warn(f"{self._where}: {path}: its colour temperature is not applied "
                       f"(RGB rendering); its colour alone tints it")
        if prim.HasAPI(UsdLux.ShapingAPI):
            self._warn(f"{self._where}: {path}: its shaping (cone, focus, IES) is not "
                       f"applied; it emits unshaped")
        transform = self._root @ _matrix(cache.GetLocalToWorldTransform(prim))
        scale = np.linalg.norm(transform[:3, :3], axis=0)
        rotation = transform[:3, :3] / np.where(scale > 0, scale, 1)
        key = self._new_id(path)
        black = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0, 0, 0]}}

        def rgb(value):
            return {"type": "rgb", "value": [float(v) for v in value]}

        if kind == "DistantLight":
            direction = rotation @ np.array([0.0, 0.0, -1.0])
            self._lights[key] = {"type": "directional", "direction": direction.tolist(),
                                 "irradiance": rgb(radiance)}
        elif kind in ("DomeLight", "DomeLight_1"):
            dome = UsdLux.DomeLight(prim) if kind == "DomeLight" else UsdLux.DomeLight_1(prim)
            texture = dome.GetTextureFileAttr().Get(time)
            layout = dome.GetTextureFormatAttr().Get(time)
            if texture is not None and texture.resolvedPath and layout in (
                    None, UsdLux.Tokens.automatic, UsdLux.Tokens.latlong):
                if not np.allclose(color, 1.0):
                    self._warn(f"{self._where}: {path}: a textured dome's colour is "
                               f"ignored (Mitsuba's envmap takes a scale only)")
                # Mitsuba's envmap and UsdLux's dome both follow OpenEXR's latlong
                # layout (longitude 0 along +Z, +pi/2 along +X, the top pole +Y): only the
                # pole differs, for DomeLight_1 whose poleAxis is the stage's Z up axis.
                to_world = np.eye(4)
                to_world[:3, :3] = rotation @ _dome_pole(dome, kind, self.stage)
                self._lights[key] = {"type": "envmap", "filename": texture.resolvedPath,
                                     "scale": intensity * 2.0 ** exposure,
                                     "to_world": mi.ScalarTransform4f(to_world.tolist())}
            else:
                if texture is not None and texture.path:
                    why = (f"is in the {layout} layout, not latlong" if texture.resolvedPath
                           else "does not resolve")
                    self._warn(f"{self._where}: {path}: texture {texture.path!r} {why}; "
                               f"the dome is a constant colour")
                self._lights[key] = {"type": "constant", "radiance": rgb(radiance)}
        elif kind == "SphereLight":
            sphere = UsdLux.SphereLight(prim)
            radius = float(sphere.GetRadiusAttr().Get(time) or 0.0) * float(scale.mean())
            centre = transform[:3, 3].tolist()
            if bool(sphere.GetTreatAsPointAttr().Get(time)) or radius <= 0:
                power_radius = max(radius, 0.0)
                factor = 1.0 if normalize or power_radius == 0 else math.pi * power_radius ** 2
                self._lights[key] = {"type": "point", "position": centre,
                                     "intensity": rgb(radiance * factor)}
            else:
                if normalize:
                    radiance = radiance / (4 * math.pi * radius ** 2)
                self._lights[key] = {"type": "sphere", "center": centre, "radius": radius,
                                     "bsdf": black,
                                     "emitter": {"type": "area", "radiance": rgb(radiance)}}
        elif kind in ("RectLight", "DiskLight"):
            if kind == "RectLight":
                rect = UsdLux.RectLight(prim)
                half = np.array([float(rect.GetWidthAttr().Get(time)) / 2,
                                 float(rect.GetHeightAttr().Get(time)) / 2, 1.0])
                area = 4 * half[0] * half[1] * scale[0] * scale[1]
                if rect.GetTextureFileAttr().Get(time):
                    self._warn(f"{self._where}: {path}: a rect light's texture is not read")
            else:
                r = float(UsdLux.DiskLight(prim).GetRadiusAttr().Get(time))
                half = np.array([r, r, 1.0])
                area = math.pi * r * r * scale[0] * scale[1]
            if normalize and area > 0:
                radiance = radiance / area
            to_world = transform @ np.diag([*half, 1.0]) @ _FLIP_Z
            self._lights[key] = {
                "type": "rectangle" if kind == "RectLight" else "disk",
                "to_world": mi.ScalarTransform4f(to_world.tolist()), "bsdf": black,
                "emitter": {"type": "area", "radiance": rgb(radiance)}}
        else:
            self._ids.discard(key)
            self._warn(f"{self._where}: {path}: a {kind} is not supported; it does not "
                       f"light the scene")

    # ---- The camera ----------------------------------------------------------------

    def _pick_camera(self, wanted: str | None):
        """The camera prim to render through, or ``None`` for the framing default."""
        if wanted is not None:
            prim = self.stage.GetPrimAtPath(wanted) if Sdf.Path.IsValidPathString(wanted) \
                else None
            if not prim or not prim.IsA(UsdGeom.Camera):
                found = [str(p.GetPath()) for p in self._cameras()]
                raise ValueError(f"{self._where}: camera {wanted!r} is not a UsdGeom.Camera "
                                 f"of the stage (its cameras: {found or 'none'})")
            return prim
        settings = UsdRender.Settings.GetStageRenderSettings(self.stage)
        if settings:
            targets = settings.GetCameraRel().GetForwardedTargets()
            if targets and self.stage.GetPrimAtPath(targets[0]).IsA(UsdGeom.Camera):
                return self.stage.GetPrimAtPath(targets[0])
        cameras = self._cameras()
        if cameras:
            return cameras[0]
        self._warn(f"{self._where}: no UsdGeom.Camera; a default camera frames the first "
                   f"frame's meshes")
        return None

    def _cameras(self) -> list:
        predicate = Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)
        return [p for p in Usd.PrimRange(self.stage.GetPseudoRoot(), predicate)
                if p.IsA(UsdGeom.Camera)]

    def _resolution(self, resolution) -> tuple[int, int]:
        if resolution is not None:
            try:
                width, height = (int(v) for v in resolution)
            except (TypeError, ValueError):
                raise ValueError(f"resolution={resolution!r}: expected (width, height)") from None
            if width < 1 or height < 1:
                raise ValueError(f"resolution={resolution!r}: expected positive sizes")
            return width, height
        settings = UsdRender.Settings.GetStageRenderSettings(self.stage)
        if settings and settings.GetResolutionAttr().HasAuthoredValue():
            width, height = settings.GetResolutionAttr().Get()
            return int(width), int(height)
        if self._camera is None:
            return DEFAULT_WIDTH, DEFAULT_WIDTH * 9 // 16
        camera = UsdGeom.Camera(self._camera).GetCamera(Usd.TimeCode(self._start))
        aspect = camera.horizontalAperture / camera.verticalAperture
        return DEFAULT_WIDTH, max(1, round(DEFAULT_WIDTH / aspect))

    def _sensor(self, width: int, height: int, spp: int) -> dict:
        """The perspective sensor: the stage's camera at the first frame, or the
        framing default."""
        film = {"type": "hdrfilm", "width": width, "height": height,
                "rfilter": {"type": "box"}}
        sampler = {"type": "independent", "sample_count": spp}
        if self._camera is None:
            return {"type": "perspective", **self._framing(width / height),
                    "film": film, "sampler": sampler}
        time = Usd.TimeCode(self._start)
        usd_camera = UsdGeom.Camera(self._camera)
        if _transform_varies(self._camera) or any(
                a.GetNumTimeSamples() > 1 for a in self._camera.GetAttributes()):
            self._warn_once(f"{self._where}: camera {self._camera.GetPath()} is time-sampled; "
                            f"hlbvh moves meshes, not sensors: every frame is rendered from "
                            f"its pose at time code {self._start:g}")
        camera = usd_camera.GetCamera(time)
        if camera.projection != Gf.Camera.Perspective:
            self._warn_once(f"{self._where}: camera {self._camera.GetPath()} is orthographic; "
                            f"rendered as a perspective camera of its focal length")
        to_world = self._root @ _matrix(camera.transform)
        scale = np.linalg.norm(to_world[:3, :3], axis=0)
        to_world[:3, :3] = to_world[:3, :3] / np.where(scale > 0, scale, 1)
        to_world = to_world @ _USD_TO_MITSUBA_CAMERA
        h_fov = 2 * math.degrees(math.atan(camera.horizontalAperture / (2 * camera.focalLength)))
        v_fov = 2 * math.degrees(math.atan(camera.verticalAperture / (2 * camera.focalLength)))
        # The whole aperture shows: a film wider than the aperture fits its height.
        wider = width / height > camera.horizontalAperture / camera.verticalAperture
        near, far = camera.clippingRange.min, camera.clippingRange.max
        units = float(UsdGeom.GetStageMetersPerUnit(self.stage))
        return {"type": "perspective", "fov": v_fov if wider else h_fov,
                "fov_axis": "y" if wider else "x",
                "near_clip": max(near * units, 1e-6), "far_clip": max(far * units, near * units * 2),
                "to_world": mi.ScalarTransform4f(to_world.tolist()),
                "film": film, "sampler": sampler}

    def _framing(self, aspect: float) -> dict:
        """A camera looking at the first frame's meshes from the front, above and to
        the side, far enough that their bounding sphere fits a 40-degree view."""
        corners = np.concatenate([t.reshape(-1, 3) for t in self.world_triangles(0).values()])
        low, high = corners.min(axis=0), corners.max(axis=0)
        centre = (low + high) / 2
        radius = max(float(np.linalg.norm(high - low)) / 2, 1e-3)
        fov = 40.0
        distance = radius / math.sin(math.radians(fov / 2) * min(1.0, aspect))
        direction = np.array([0.45, 0.35, 1.0])
        origin = centre + direction / np.linalg.norm(direction) * distance
        return {"fov": fov, "fov_axis": "x" if aspect < 1 else "y",
                "near_clip": distance * 1e-3, "far_clip": distance * 10,
                "to_world": mi.ScalarTransform4f().look_at(
                    origin=origin.tolist(), target=centre.tolist(), up=[0, 1, 0])}


# ---- Helpers -------------------------------------------------------------------------


def _print_warning(line: str) -> None:
    """A warning line on stderr, as ``hlbvh render`` says them."""
    print(f"hlbvh: {line}", file=sys.stderr)


def _open(path: Path, where: str):
    """``Usd.Stage.Open`` with USD's own diagnostics kept off stderr (they are
    multi-line and repeated): a failure is one ``ValueError``."""
    saved = os.dup(2)
    with tempfile.TemporaryFile() as sink:
        os.dup2(sink.fileno(), 2)
        try:
            stage = Usd.Stage.Open(str(path), Usd.Stage.LoadAll)
            error = None
        except Tf.ErrorException as caught:
            stage, error = None, caught
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
        if stage is None:
            text = " ".join(str(error).split()) if error else "no stage"
            reason = re.sub(r".*?Error in '[^']*' at line \d+ in file [^ ]+ : ", "", text)
            raise ValueError(f"{where}: USD cannot open it as a stage ({reason[:200]})")
    return stage


def _unresolved_arcs(stage) -> list[tuple[str, str]]:
    """``(prim path, what USD said)`` for each reference or payload USD could not
    resolve, once per prim."""
    found = {}
    for error in stage.GetCompositionErrors():
        site = getattr(error, "rootSite", None)
        path = str(getattr(site, "path", "") or "") or "?"
        text = " ".join(str(error).split())
        found.setdefault(path, text.split(" for ")[0][:200])
    return list(found.items())


def _root_transform(stage) -> np.ndarray:
    """The stage's units and up axis to Mitsuba's Y-up metres, a 4x4 matrix."""
    root = np.eye(4)
    root[:3, :3] *= float(UsdGeom.GetStageMetersPerUnit(stage))
    if UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z:
        root[:3, :3] = _Z_UP_TO_Y_UP @ root[:3, :3]
    return root


def _matrix(gf_matrix) -> np.ndarray:
    """A ``Gf.Matrix4d`` (row vectors, ``p * M``) as a numpy 4x4 acting on columns."""
    return np.array(gf_matrix, dtype=np.float64).T


def _array(value, width: int) -> np.ndarray:
    """A ``Vt`` array of vectors as ``(N, width)`` float64 (empty when ``None``)."""
    if value is None:
        return np.zeros((0, width))
    return np.array(value, dtype=np.float64).reshape(-1, width)


def _transform_varies(prim) -> bool:
    """Whether the prim's or an ancestor's transform is time-sampled."""
    while prim and not prim.IsPseudoRoot():
        xformable = UsdGeom.Xformable(prim)
        if xformable and xformable.TransformMightBeTimeVarying():
            return True
        prim = prim.GetParent()
    return False


def _triangulate(mesh, time, point_count: int, path, where: str, with_faces: bool = False):
    """Fan triangulation of a mesh's polygons at ``time``: ``(F, 3)`` uint32, holes
    left out, winding flipped for ``orientation = leftHanded``; with ``with_faces``
    also each triangle's polygon index (``(F,)``) and its corners' face-vertex indices
    (``(F, 3)``, positions in ``faceVertexIndices``, where faceVarying values sit).

    Raises:
        ValueError: indices that do not add up to the face counts, or that point past
            the last point.
    """
    counts = np.array(mesh.GetFaceVertexCountsAttr().Get(time) or [], dtype=np.int64)
    indices = np.array(mesh.GetFaceVertexIndicesAttr().Get(time) or [], dtype=np.int64)
    if counts.sum() != len(indices):
        raise ValueError(f"{where}: mesh {path}: faceVertexCounts add up to {counts.sum()} "
                         f"but faceVertexIndices holds {len(indices)}")
    if len(indices) and (indices.min() < 0 or indices.max() >= point_count):
        raise ValueError(f"{where}: mesh {path}: a face index points past its "
                         f"{point_count} points")
    offsets = np.cumsum(counts) - counts
    keep = counts >= 3
    holes = np.array(mesh.GetHoleIndicesAttr().Get(time) or [], dtype=np.int64)
    keep[holes[(holes >= 0) & (holes < len(counts))]] = False
    per_face = np.where(keep, counts - 2, 0)
    face = np.repeat(np.arange(len(counts)), per_face)
    first_triangle = np.cumsum(per_face) - per_face
    k = np.arange(len(face)) - first_triangle[face] + 1
    start = offsets[face]
    corners = np.stack([start, start + k, start + k + 1], axis=1)
    corners = corners.reshape(-1, 3)
    if mesh.GetOrientationAttr().Get(time) == UsdGeom.Tokens.leftHanded:
        corners = corners[:, ::-1].copy()
    triangles = indices[corners].astype(np.uint32).reshape(-1, 3)
    return (triangles, face, corners) if with_faces else triangles


def _vertex_normals(mesh, time, point_count: int) -> np.ndarray | None:
    """Authored per-vertex normals ((V, 3), in the mesh's space), or ``None`` when
    there are none or they are not per vertex (faceVarying normals are recomputed)."""
    primvar = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("normals")
    if primvar and primvar.HasAuthoredValue():
        value, interpolation = primvar.ComputeFlattened(time), primvar.GetInterpolation()
    else:
        value, interpolation = mesh.GetNormalsAttr().Get(time), mesh.GetNormalsInterpolation()
    if value is None or interpolation not in (UsdGeom.Tokens.vertex, UsdGeom.Tokens.varying):
        return None
    normals = _array(value, 3)
    return normals if len(normals) == point_count else None


def _visibility_varies(prim) -> bool:
    """Whether the visibility of the prim or of an ancestor is time-sampled."""
    while prim and not prim.IsPseudoRoot():
        attribute = UsdGeom.Imageable(prim).GetVisibilityAttr()
        if attribute and attribute.GetNumTimeSamples() > 1:
            return True
        prim = prim.GetParent()
    return False


def _has_normals(mesh) -> bool:
    """Whether a mesh authors normals at all (attribute or primvar)."""
    primvar = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("normals")
    return bool(primvar and primvar.HasAuthoredValue()) or mesh.GetNormalsAttr().HasAuthoredValue()


def _skel_binding():
    """``UsdSkel.BindingAPI`` (imported when a mesh is checked: UsdSkel is optional in
    some USD builds)."""
    try:
        from pxr import UsdSkel
    except ImportError:  # pragma: no cover
        return "SkelBindingAPI"
    return UsdSkel.BindingAPI


def _dome_pole(dome, kind: str, stage) -> np.ndarray:
    """The rotation (3x3, in the dome's space) that takes a latlong map's +Y pole to the
    dome's pole: none for a ``DomeLight`` (its pole is +Y whatever the up axis),
    a ``DomeLight_1``'s ``poleAxis`` (``scene``: the stage's up axis) otherwise."""
    pole = "Y"
    if kind == "DomeLight_1":
        axis = dome.GetPoleAxisAttr().Get() or "scene"
        pole = str(UsdGeom.GetStageUpAxis(stage)) if axis == "scene" else str(axis)
    if pole == "Z":
        return np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # rotateX(90): +Y -> +Z
    return np.eye(3)


#: UsdUVTexture's wrap modes as Mitsuba's bitmap's (``black`` clamps).
_WRAPS = {"repeat": "repeat", "mirror": "mirror", "clamp": "clamp", "black": "clamp",
          "useMetadata": "repeat"}


def _uv_texture(shader_input, time):
    """``(bitmap texture dict, st primvar name)`` of a UsdPreviewSurface input
    connected to a ``UsdUVTexture`` whose file resolves (its ``st`` read by a
    ``UsdPrimvarReader_float2``, ``st`` by default), else ``None``."""
    texture = _connected_shader(shader_input)
    if texture is None or texture.GetIdAttr().Get() != "UsdUVTexture":
        return None
    file_input = texture.GetInput("file")
    asset = file_input.Get(time) if file_input else None
    if asset is None or not asset.resolvedPath or "[" in asset.resolvedPath:
        return None  # missing, or inside a .usdz package Mitsuba cannot read from
    name = "st"
    reader = _connected_shader(texture.GetInput("st"))
    if reader is not None and reader.GetInput("varname"):
        name = str(reader.GetInput("varname").Get(time) or "st")
    wrap = texture.GetInput("wrapS")
    wrap = str(wrap.Get(time)) if wrap and wrap.Get(time) else "useMetadata"
    return {"type": "bitmap", "filename": asset.resolvedPath,
            "wrap_mode": _WRAPS.get(wrap, "repeat")}, name


def _filenames(description: dict) -> list[str]:
    """Every ``filename`` a Mitsuba description dict names, nested ones included."""
    names = [description["filename"]] if "filename" in description else []
    for value in description.values():
        if isinstance(value, dict):
            names += _filenames(value)
    return names


def _connected_shader(shader_input):
    """The shader an input is connected to, or ``None``."""
    if not shader_input or not shader_input.HasConnectedSource():
        return None
    sources, _ = shader_input.GetConnectedSources()
    if not sources:
        return None
    return UsdShade.Shader(sources[0].source.GetPrim())


def _two_sided(bsdf: dict) -> dict:
    return {"type": "twosided", "material": bsdf}


def _mitsuba_mesh(mesh: _Mesh, points: np.ndarray, faces: np.ndarray) -> mi.Mesh:
    """A Mitsuba mesh holding ``points`` (world space) and ``faces``, its BSDF, an area
    emitter when the material emits, and vertex normals when smooth (authored ones
    where given, else computed bit-reproducibly)."""
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(mesh.bsdf)
    if mesh.emission is not None:
        props["emitter"] = mi.load_dict({"type": "area", "radiance": {
            "type": "rgb", "value": [float(c) for c in mesh.emission]}})
    shape = mi.Mesh(mesh.id, len(points), len(faces), props=props,
                    has_vertex_normals=mesh.smooth,
                    has_vertex_texcoords=mesh.texcoords is not None)
    params = mi.traverse(shape)
    params["vertex_positions"] = mi.Float(np.ascontiguousarray(points, np.float32).reshape(-1))
    params["faces"] = mi.UInt32(np.ascontiguousarray(faces, np.uint32).reshape(-1))
    if mesh.smooth:
        if mesh.normals is not None:
            params["vertex_normals"] = mi.Float(
                np.ascontiguousarray(mesh.normals, np.float32).reshape(-1))
        else:
            params["vertex_normals"] = vertex_normals(params["vertex_positions"],
                                                      params["faces"])
    if mesh.texcoords is not None:
        params["vertex_texcoords"] = mi.Float(
            np.ascontiguousarray(mesh.texcoords, np.float32).reshape(-1))
    if mesh.colors is not None:
        name, values = mesh.colors
        shape.add_attribute(name, 3, mi.Float(np.ascontiguousarray(values, np.float32)
                                              .reshape(-1)))
    params.update()
    return shape
