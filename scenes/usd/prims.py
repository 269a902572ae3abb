"""What the USD modules share: pxr's import (the other modules take its modules from
here, so a missing pxr is one clear error), the constants of the conversion, the mesh
record, and the helpers that read prims (opening a stage, matrices, triangulation,
normals, textures)."""

from __future__ import annotations

import contextlib
import functools
import hashlib
import os
import re
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import mitsuba as mi
import numpy as np

from ..normals import vertex_normals

try:
    from pxr import Ar, Gf, Sdf, Tf, Usd, UsdGeom, UsdLux, UsdRender, UsdShade  # noqa: F401
except ImportError as _error:  # pragma: no cover - depends on the installation
    raise ImportError(f"USD stages need Pixar's pxr module ({_error}): "
                      f"pip install 'hlbvh[usd]'") from None


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
               "OpenVDBAsset", "Field3DAsset", "NurbsPatch", "Sphere",
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
    emission: tuple | dict | None    # an RGB radiance, or a bitmap texture's dict
    local_points: np.ndarray | None = None     # (V, 3) float64, rigid meshes
    normals: np.ndarray | None = None           # (V, 3) authored world-space normals
    attributes: dict = field(default_factory=dict)  # Mitsuba mesh attributes: (N, width)
    point_count: int = 0                        # V of the first frame
    vertex_points: np.ndarray | None = None     # (V',) the point of each Mitsuba vertex
    texcoords: np.ndarray | None = None         # (V', 2) Mitsuba uv, with a texture
    mirrored: bool = False                      # faces flipped: the first frame mirrors

@dataclass
class _Stats:
    """What the traversal saw, for the lines said once per stage."""

    subdivided: list = field(default_factory=list)
    moving_normals: list = field(default_factory=list)
    face_varying: list = field(default_factory=list)

def _print_warning(line: str) -> None:
    """A warning line on stderr, as ``hlbvh render`` says them."""
    print(f"hlbvh: {line}", file=sys.stderr)

@contextlib.contextmanager
def _stderr_captured():
    """Everything written to the process's stderr (file descriptor 2, where USD's C++
    diagnostics go, multi-line) during the block kept off the terminal; yields a list
    that holds the captured lines once the block ends."""
    lines: list[str] = []
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as sink:
        os.dup2(sink.fileno(), 2)
        try:
            yield lines
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)
            sink.seek(0)
            lines.extend(sink.read().decode(errors="replace").splitlines())


def _open(path: Path, where: str):
    """``Usd.Stage.Open`` with USD's own diagnostics kept off stderr (they are
    multi-line and repeated): a failure is one ``ValueError``."""
    with _stderr_captured():
        try:
            stage = Usd.Stage.Open(str(path), Usd.Stage.LoadAll)
            error = None
        except Tf.ErrorException as caught:
            stage, error = None, caught
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

def _checked(what: str, value, least: float | None = None, strictly: bool = False):
    """``value`` (a number, a vector or an array of them) when every component is
    finite and, with ``least``, at least ``least`` (above it with ``strictly``); else
    a ValueError naming ``what`` (the stage, the prim and the attribute) and the first
    value that fails, so that a NaN, an infinity or a negative size never reaches
    Mitsuba (where it becomes NaN pixels, a blank image or a RuntimeError)."""
    values = np.asarray(value, dtype=np.float64).reshape(-1)
    bad = ~np.isfinite(values)
    if least is not None:
        bad |= (values <= least) if strictly else (values < least)
    if bad.any():
        expected = "finite" if least is None else \
            f"finite and {'>' if strictly else '>='} {least:g}"
        if values.size == 1:
            shown = f"is {values[0]:g}"
        elif values.size <= 4:
            shown = "is (" + ", ".join(f"{v:g}" for v in values) + ")"
        else:
            first = int(np.flatnonzero(bad)[0])
            shown = f"holds {values[first]:g} (value {first} of {values.size})"
        raise ValueError(f"{what} {shown}: expected {expected} values")
    return value

def _root_transform(stage, where: str) -> np.ndarray:
    """The stage's units and up axis to Mitsuba's Y-up metres, a 4x4 matrix.

    Raises:
        ValueError: ``metersPerUnit`` is not a finite number above 0.
    """
    root = np.eye(4)
    root[:3, :3] *= _checked(f"{where}: metersPerUnit",
                             float(UsdGeom.GetStageMetersPerUnit(stage)), least=0, strictly=True)
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
        ValueError: a negative face count, indices that do not add up to the face
            counts, or that point past the last point.
    """
    counts = np.array(mesh.GetFaceVertexCountsAttr().Get(time) or [], dtype=np.int64)
    indices = np.array(mesh.GetFaceVertexIndicesAttr().Get(time) or [], dtype=np.int64)
    if (counts < 0).any():
        first = int(np.flatnonzero(counts < 0)[0])
        raise ValueError(f"{where}: mesh {path}: faceVertexCounts holds {counts[first]} "
                         f"(face {first}): a face has 0 or more vertices")
    if counts.sum() != len(indices):
        raise ValueError(f"{where}: mesh {path}: faceVertexCounts add up to {counts.sum()} "
                         f"but faceVertexIndices holds {len(indices)}")
    if len(indices) and indices.min() < 0:
        raise ValueError(f"{where}: mesh {path}: faceVertexIndices holds {indices.min()}: "
                         f"expected indices >= 0")
    if len(indices) and indices.max() >= point_count:
        raise ValueError(f"{where}: mesh {path}: faceVertexIndices holds {indices.max()}, "
                         f"past its {point_count} points")
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

@functools.lru_cache(maxsize=256)
def _image_problem(path: str, stamp: tuple) -> str | None:
    """Why Mitsuba cannot read the image at ``path`` (``stamp``: its size and
    modification time, so a changed file is read again), or ``None`` when it can: a
    texture that is a folder or not an image is said and left out before the scene
    loads, where Mitsuba would raise."""
    if not os.path.isfile(path):
        return "is not a file"
    try:
        mi.Bitmap(path)
    except RuntimeError as error:
        reason = " ".join(str(error).split())
        return f"is not an image Mitsuba reads ({reason[:120]})"
    return None


def _unreadable_image(path: str) -> str | None:
    """:func:`_image_problem` of ``path`` at its current size and modification time."""
    try:
        stat = os.stat(path)
    except OSError:
        return "cannot be read"
    return _image_problem(path, (stat.st_size, stat.st_mtime_ns))


def _local_asset(resolved: str) -> str | None:
    """A file Mitsuba can open holding the asset pxr resolved to ``resolved``: the file
    itself, or, for an asset inside a .usdz package (``shot.usdz[0/map.png]``, however
    the converter laid the package out), its bytes read through pxr's resolver and
    written once to ``hlbvh-usdz/<their SHA-256>/<its name>`` in the temporary folder (a
    path that depends on the bytes alone, so cluster workers agree; :func:`_written_once`).
    ``None`` when pxr cannot open it."""
    if not Ar.IsPackageRelativePath(resolved):
        return resolved
    asset = Ar.GetResolver().OpenAsset(Ar.ResolvedPath(resolved))
    if asset is None:
        return None
    data = bytes(asset.GetBuffer())
    inner = Ar.SplitPackageRelativePathInner(resolved)[1]
    return _written_once("hlbvh-usdz", hashlib.sha256(data).hexdigest(), Path(inner).name,
                         lambda path: Path(path).write_bytes(data))


#: The most bytes each folder of rewritten files (``hlbvh-textures/``, ``hlbvh-usdz/`` in
#: the temporary folder) keeps once a new file is written: the least recently used
#: entries go first (a scaled texture is a float OpenEXR, 72 MB for a 1.1 MB 4k JPEG).
CACHE_BYTES = 2**30

#: Entries used this recently (seconds) are kept whatever the folder's size: a render
#: that opened its stage reads them when its scene loads.
CACHE_GRACE_S = 3600.0


def cache_folder(kind: str) -> Path:
    """Where rewritten files of ``kind`` (``hlbvh-textures``, ``hlbvh-usdz``) live: in
    the temporary folder (``$TMPDIR``), which a render farm gives each job and cleans
    after it, and which :data:`CACHE_BYTES` bounds on a workstation."""
    return Path(tempfile.gettempdir()) / kind


def cached_name(path: Path) -> str | None:
    """``kind/<content digest>/name`` of a file :func:`_written_once` wrote (its name
    depends on its content alone, so it stands for that content), ``None`` for any
    other file: what a scene digest names it by, wherever the temporary folder is."""
    for kind in ("hlbvh-textures", "hlbvh-usdz"):
        if path.parent.parent == cache_folder(kind):
            return f"{kind}/{path.parent.name}/{path.name}"
    return None


def _written_once(kind: str, digest: str, name: str, write) -> str:
    """``<temporary folder>/<kind>/<digest>/<name>``, written by ``write(path)`` unless
    it is there (then marked used): a path that depends on the content (``digest``)
    alone, so cluster workers agree; written to a partial file (same suffix) moved
    into place, so a concurrent process never reads half of it; the folder then
    trimmed to :data:`CACHE_BYTES` (:func:`_trim_cache`)."""
    target = cache_folder(kind) / digest / name
    if target.is_file():
        with contextlib.suppress(OSError):
            os.utime(target)  # least recently used goes first
        return str(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    partial = target.parent / f".{os.getpid()}.{name}"
    write(str(partial))
    os.replace(partial, target)
    _trim_cache(cache_folder(kind))
    return str(target)


def _trim_cache(folder: Path, limit: int | None = None) -> None:
    """Remove the least recently used entries (``<digest>/`` folders, by their newest
    file's modification time) of ``folder`` until it holds at most ``limit`` bytes
    (:data:`CACHE_BYTES`), never one used in the last :data:`CACHE_GRACE_S` seconds;
    files another process removes meanwhile are skipped."""
    limit = CACHE_BYTES if limit is None else limit
    entries = []
    for entry in folder.iterdir():
        try:
            stats = [f.stat() for f in entry.iterdir()]
        except OSError:
            continue
        entries.append((max((st.st_mtime for st in stats), default=0.0),
                        sum(st.st_size for st in stats), entry))
    total = sum(size for _, size, _ in entries)
    now = time.time()
    for used, size, entry in sorted(entries):
        if total <= limit or now - used < CACHE_GRACE_S:
            break
        shutil.rmtree(entry, ignore_errors=True)
        total -= size

def _filenames(description: dict) -> list[str]:
    """Every ``filename`` a Mitsuba description dict names, nested ones included."""
    names = [description["filename"]] if "filename" in description else []
    for value in description.values():
        if isinstance(value, dict):
            names += _filenames(value)
    return names

def _connected_shader(shader_input):
    """The shader whose output feeds an input, followed as pxr does through the
    interface inputs of materials and node graphs, or ``None``."""
    if not shader_input or not shader_input.HasConnectedSource():
        return None
    outputs = shader_input.GetValueProducingAttributes(shaderOutputsOnly=True)
    return UsdShade.Shader(outputs[0].GetPrim()) if outputs else None


def _interface_value(shader_input, time):
    """``(True, value)`` when an input takes its value from an interface input of its
    material or node graph (Blender, usdzconvert and pxr's own tutorial connect a
    primvar reader's ``varname`` to the material's ``inputs:frame:stPrimvarName``);
    else ``(False, the input's own authored value or None)``."""
    if not shader_input:
        return False, None
    if shader_input.HasConnectedSource():
        for attribute in shader_input.GetValueProducingAttributes():
            if UsdShade.Input.IsInput(attribute):
                return True, attribute.Get(time)
    return False, shader_input.Get(time)


def _input_value(shader_input, time):
    """An input's value as :func:`_interface_value` finds it (``None``: none)."""
    return _interface_value(shader_input, time)[1]

def _two_sided(bsdf: dict) -> dict:
    """``bsdf`` seen from both sides: wrapped in ``twosided``, inside its ``mask``
    where it has one (``twosided`` takes no BSDF that transmits, and a mask passes
    light through).

    Every USD surface renders so, ``doubleSided`` or not, as Storm (usdview) draws it:
    Storm culls no back faces unless its "Cull Backfaces" view setting is on (off by
    default; UsdGeom's ``doubleSided = false`` only allows a renderer to cull them),
    and shades a single-sided back face with the material, not black. Mitsuba's BSDFs
    are one-sided (a back face reflects nothing: the opaque black the single-sided
    sides of DCC exports rendered as). Storm keeps the front's normal on that back
    face, lit from the front's side; ``twosided`` lights it from the side it faces."""
    if bsdf["type"] == "mask":
        return {**bsdf, "bsdf": _two_sided(bsdf["bsdf"])}
    return {"type": "twosided", "material": bsdf}

def _mitsuba_mesh(mesh: _Mesh, points: np.ndarray, faces: np.ndarray) -> mi.Mesh:
    """A Mitsuba mesh holding ``points`` (world space) and ``faces``, its BSDF (seen
    from both sides, :func:`_two_sided`), an area
    emitter when the material emits, and vertex normals when smooth (authored ones
    where given, else computed bit-reproducibly)."""
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(_two_sided(mesh.bsdf))
    if mesh.emission is not None:
        radiance = mesh.emission if isinstance(mesh.emission, dict) else {
            "type": "rgb", "value": [float(c) for c in mesh.emission]}
        props["emitter"] = mi.load_dict({"type": "area", "radiance": radiance})
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
    for name, values in mesh.attributes.items():
        shape.add_attribute(name, values.shape[1], mi.Float(
            np.ascontiguousarray(values, np.float32).reshape(-1)))
    params.update()
    return shape
