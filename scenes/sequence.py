"""What users bring: a Mitsuba scene (XML file or dict) plus per-frame mesh files.

Layout of the frames directory (one subdirectory per animated shape, named by the
shape's id in the scene, one file per frame)::

    <frames_dir>/<shape_id>/frame_0001.ply
    <frames_dir>/<shape_id>/frame_0002.ply
    ...

Files are named ``frame_<number>.<ply|obj>``, the number with any zero padding. The
smallest number found in any subdirectory is frame 0, and every animated shape must
have a file for every number up to the largest: a gap is reported when the sequence is
opened. Other files are ignored. Each file is read by Mitsuba's own ``ply`` or ``obj``
plugin, with the ``to_world`` of the scene's shape when it has one (as if the scene
pointed at that file), so files hold what the scene's shape would.

Topology per shape: ``"fixed"`` (the default) means every frame has the vertex and
face counts and the faces of the shape in the scene, and only positions are handed
on; ``"changing"`` means every frame brings its own faces (any counts).
"""

from __future__ import annotations

import hashlib
import os
import re
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from .animated import AnimatedScene, FrameGeometry

TOPOLOGIES = ("fixed", "changing")
FRAME_FILE = re.compile(r"^frame_(\d+)\.(ply|obj)$", re.IGNORECASE)


class SequenceScene(AnimatedScene):
    """A scene whose animated meshes are read from a directory of per-frame files.

    Args:
        scene: a Mitsuba XML file, or a scene dict for ``mi.load_dict`` (objects already
            built in it, such as an ``mi.Mesh``, are shared by every ``scene_dict``).
        frames_dir: the directory of per-frame meshes (layout in the module docstring).
        topology: ``"fixed"`` or ``"changing"`` for every animated shape, or a dict from
            shape id to either (shapes it leaves out are ``"fixed"``).
        box_filter: give every film a ``box`` reconstruction filter (renders with the
            same seed are then bit-comparable); ``False`` keeps the scene's filters.

    Raises:
        ValueError: the scene cannot be loaded or has no sensor; the directory does not
            exist or holds no frame files; a subdirectory names no mesh of the scene; a
            frame file is missing (naming the file and the frame) or given twice.
    """

    name = "sequence"

    def __init__(
        self,
        scene: str | os.PathLike | dict,
        frames_dir: str | os.PathLike,
        topology: str | dict[str, str] = "fixed",
        box_filter: bool = True,
    ):
        if isinstance(scene, dict):
            self._source = dict(scene)
        else:
            path = Path(scene)
            if not path.is_file():
                raise ValueError(f"scene {str(scene)!r}: no such file (expected a Mitsuba XML file or a dict)")
            try:
                with open(path, "rb"):
                    pass
            except OSError as error:
                raise ValueError(f"scene {str(scene)!r}: the file cannot be read "
                                 f"({error.strerror})") from None
            self._source = path.resolve()
        self._box_filter = bool(box_filter)
        self._frames_dir = Path(frames_dir).resolve()
        if not self._frames_dir.is_dir():
            raise ValueError(f"frames directory {str(frames_dir)!r}: no such directory")

        # ---- The scene's shapes, as loaded ----
        state = self._parse()
        reference = self._instantiate(state)
        self._to_world = {}
        for node in state.nodes:
            if node.type == mi.ObjectType.Shape and "to_world" in node.props.keys():
                self._to_world[node.props.id()] = node.props["to_world"]
        self._meshes = {}  # id -> (vertex count, face count)
        self._writable = set()  # ids of meshes whose vertex positions Mitsuba lets us set
        self._shape_ids = []
        faces = {}
        for shape in reference.shapes():
            self._shape_ids.append(shape.id())
            if isinstance(shape, mi.Mesh):
                self._meshes[shape.id()] = (shape.vertex_count(), shape.face_count())
                faces[shape.id()] = mi.UInt32(shape.faces_buffer())
                if "vertex_positions" in mi.traverse(shape).keys():
                    self._writable.add(shape.id())
        del reference

        # ---- The frame files ----
        self._files, self.frame_count = self._scan_frames()
        self._topology = self._topologies(topology)
        self._fixed_faces = {
            sid: faces[sid] for sid, kind in self._topology.items() if kind == "fixed"
        }

    def __repr__(self) -> str:
        return (
            f"SequenceScene({str(self._source) if isinstance(self._source, Path) else 'dict'}, "
            f"{str(self._frames_dir)!r}, frames={self.frame_count}, "
            f"animated={self.animated_ids()})"
        )

    # ---- The AnimatedScene contract ----------------------------------------------

    def animated_ids(self) -> list[str]:
        return list(self._files)

    def static_ids(self) -> list[str]:
        return [sid for sid in self._shape_ids if sid not in self._files]

    def triangle_counts(self) -> dict[str, int]:
        """Triangles of every mesh as the scene loads them (frame files not read)."""
        return {sid: face_count for sid, (_, face_count) in self._meshes.items()}

    def integrator_description(self) -> dict | None:
        """The scene's own integrator as ``{"type": plugin, property: value, ...}``, or
        ``None`` when it has none.

        Raises:
            ValueError: a property of it that is not a number, a boolean or a string
                (a nested integrator, a texture), which could not be handed on.
        """
        state = self._parse()
        for index in _references(state.root):
            node = state.nodes[index]
            if node.type != mi.ObjectType.Integrator:
                continue
            description = {"type": node.props.plugin_name()}
            for name, value in node.props.items():
                if not isinstance(value, (bool, int, float, str)):
                    raise ValueError(
                        f"scene {self._describe()}: its integrator "
                        f"{node.props.plugin_name()!r} has property {name!r} of a kind "
                        f"hlbvh cannot hand on ({type(value).__name__}); replace the "
                        f"integrator (hlbvh render: --integrator path or aov)")
                description[name] = value
            return description
        return None

    def source_digest(self) -> str | None:
        """SHA-256 (hex) of what the scene is made of: the XML file, the files it
        includes, and every file a ``filename`` property names (meshes, textures), so a
        render folder can tell that the scene changed between two runs; ``None`` for a
        dict scene. A file that cannot be read counts as its absence."""
        if not isinstance(self._source, Path):
            return None
        state = self._parse()
        files = [Path(str(name)) for name in state.files]
        with _resolving_next_to(self._source):
            resolver = mi.file_resolver()
            for node in state.nodes:
                value = node.props["filename"] if "filename" in node.props.keys() else None
                if isinstance(value, str):
                    files.append(Path(str(resolver.resolve(value))))
        digest = hashlib.sha256()
        for path in dict.fromkeys(files):
            digest.update(str(path).encode() + b"\0")
            try:
                with open(path, "rb") as handle:
                    for block in iter(lambda: handle.read(1 << 20), b""):
                        digest.update(block)
            except OSError:
                digest.update(b"\0unreadable\0")
        return digest.hexdigest()

    def frame(self, i: int) -> dict[str, FrameGeometry]:
        """Reads frame ``i`` of every animated shape.

        Raises:
            ValueError: naming the file and the frame, when a file is gone, cannot be
                read by Mitsuba (corrupt), or, for a ``"fixed"`` shape, has another
                vertex count, face count or faces than the scene's shape.
        """
        i = self._check_frame_index(i)
        return {sid: self._read_frame(sid, i) for sid in self._files}

    def scene_dict(
        self,
        resolution: tuple[int, int] | None = None,
        spp: int | None = None,
        integrator: dict | None = None,
    ) -> dict:
        """See :meth:`AnimatedScene.scene_dict`. The scene as the file or dict describes
        it (its own geometry, not frame 0), with its films resized to ``resolution``, its
        samplers set to ``spp``, a box filter unless ``box_filter=False``, and
        ``integrator`` in place of its own. Every shape is handed over already built
        (Mitsuba is told not to merge meshes), keyed by its id; shapes without an id get
        ``shape_<k>``. Instances and their shape groups, which Mitsuba does not take
        built, are described by :meth:`_instancing`."""
        state = self._parse()
        _configure_films(state, resolution, spp, self._box_filter)
        scene = self._instantiate(state)
        description = {"type": "scene"}
        own = scene.integrator()
        if integrator is not None or own is not None:
            description["integrator"] = dict(integrator) if integrator is not None else own
        for shape in scene.shapes():
            if shape.class_name() != "Instance":
                description[shape.id()] = shape
        description.update(self._instancing())
        for k, sensor in enumerate(scene.sensors()):
            description[_free_key(description, sensor.id() or f"sensor_{k}")] = sensor
        for k, emitter in enumerate(scene.emitters()):
            if emitter.get_shape() is None:  # area lights come with their shape
                description[_free_key(description, emitter.id() or f"emitter_{k}")] = emitter
        return description

    def _instancing(self) -> dict:
        """The scene's shape groups and instances as dicts for ``mi.load_dict``: a
        built instance or shape group in a scene dict fails ("Couldn't find key"), so
        each group is described with its shapes built, each instance with its
        ``to_world`` and a reference to its group. Read from a parse tree of its own
        (instantiating a tree takes its references)."""
        state = self._parse()
        groups, instances = {}, {}
        for node in state.nodes:
            if node.type != mi.ObjectType.Shape:
                continue
            kind = node.props.plugin_name()
            if kind == "shapegroup":
                groups[node.props.id()] = _references(node)
            elif kind == "instance":
                description = {"type": "instance"}
                if "to_world" in node.props.keys():
                    description["to_world"] = node.props["to_world"]
                for k, child in enumerate(_references(node)):
                    description[f"group_{k}"] = {"type": "ref", "id": state.nodes[child].props.id()}
                instances[node.props.id()] = description
        if not instances:
            return {}
        # The groups' shapes, built as the only shapes of a scene of their own.
        members = [child for children in groups.values() for child in children]
        root = state.root.props
        for name in list(root.keys()):
            del root[name]
        for k, child in enumerate(members):
            root[f"member_{k}"] = mi.Properties.ResolvedReference(child)
        built = {shape.id(): shape for shape in self._instantiate(state).shapes()}
        description = {}
        for group, children in groups.items():
            description[group] = {"type": "shapegroup", **{
                state.nodes[child].props.id(): built[state.nodes[child].props.id()]
                for child in children}}
        return {**description, **instances}

    # ---- Loading the scene ---------------------------------------------------------

    def _parse(self) -> mi.parser.ParserState:
        """The scene's parse tree, references resolved, every top-level shape named."""
        config = self._config()
        try:
            with _resolving_next_to(self._source):
                if isinstance(self._source, Path):
                    state = mi.parser.parse_file(config, str(self._source))
                else:
                    state = mi.parser.parse_dict(config, self._source)
            mi.parser.transform_upgrade(config, state)
            mi.parser.transform_resolve(config, state)
        except RuntimeError as error:
            raise ValueError(f"scene {self._describe()}: Mitsuba cannot parse it: {error}") from None
        if state.root.type != mi.ObjectType.Scene:
            raise ValueError(f"scene {self._describe()}: expected a scene, got {state.root.type}")
        if not any(node.type == mi.ObjectType.Sensor for node in state.nodes):
            raise ValueError(f"scene {self._describe()}: it has no sensor; add a camera")
        taken = {node.props.id() for node in state.nodes}
        count = 0
        for node in state.nodes:
            if node.type == mi.ObjectType.Shape and not node.props.id():
                while f"shape_{count}" in taken:
                    count += 1
                node.props.set_id(f"shape_{count}")
                taken.add(f"shape_{count}")
        return state

    def _instantiate(self, state: mi.parser.ParserState) -> mi.Scene:
        """The Mitsuba scene of a parse tree, meshes never merged."""
        config = self._config()
        try:
            with _resolving_next_to(self._source):
                mi.parser.transform_merge_equivalent(config, state)
                return mi.parser.instantiate(config, state)
        except (RuntimeError, UnicodeDecodeError) as error:
            raise ValueError(f"scene {self._describe()}: Mitsuba cannot load it: "
                             f"{_first_line(error)}") from None

    @staticmethod
    def _config() -> mi.parser.ParserConfig:
        config = mi.parser.ParserConfig(mi.variant())
        config.merge_meshes = False
        return config

    def _describe(self) -> str:
        return repr(str(self._source)) if isinstance(self._source, Path) else "(dict)"

    # ---- The frame files -----------------------------------------------------------

    def _scan_frames(self) -> tuple[dict[str, list[Path]], int]:
        """Every animated shape's files in frame order, and the frame count."""
        found: dict[str, dict[int, Path]] = {}
        for entry in _entries(self._frames_dir):
            if not entry.is_dir():
                continue
            if entry.name not in self._writable:
                reason = (
                    "Mitsuba exposes no vertex positions for it (e.g. a rectangle): "
                    "make it a ply or obj shape"
                    if entry.name in self._meshes
                    else "the scene has no mesh with that id"
                )
                raise ValueError(
                    f"frames directory {str(entry)!r}: shape {entry.name!r} cannot be "
                    f"animated: {reason} (animatable meshes: {sorted(self._writable)})"
                )
            numbered: dict[int, Path] = {}
            for file in _entries(entry):
                match = FRAME_FILE.match(file.name)
                if not match:
                    continue
                if not file.is_file():
                    raise ValueError(
                        f"frame file {str(file)!r} of shape {entry.name!r}: "
                        f"{_not_a_file(file)}; make it a readable mesh file or remove it"
                    )
                number = int(match.group(1))
                if number in numbered:
                    raise ValueError(
                        f"frame file number {number} of shape {entry.name!r} is given twice: "
                        f"{str(numbered[number])!r} and {str(file)!r}; keep one"
                    )
                numbered[number] = file
            if not numbered:
                raise ValueError(
                    f"frames directory {str(entry)!r}: no frame files (expected "
                    f"frame_0001.ply, frame_0002.ply, ... or .obj)"
                )
            found[entry.name] = numbered
        if not found:
            raise ValueError(
                f"frames directory {str(self._frames_dir)!r}: no per-shape subdirectories "
                f"(expected <frames_dir>/<shape_id>/frame_0001.ply, ...)"
            )
        first = min(min(numbered) for numbered in found.values())
        last = max(max(numbered) for numbered in found.values())
        files = {}
        for shape_id, numbered in found.items():
            for number in range(first, last + 1):
                if number not in numbered:
                    example = next(iter(numbered.values()))
                    digits = len(FRAME_FILE.match(example.name).group(1))
                    missing = example.with_name(f"frame_{number:0{digits}d}{example.suffix}")
                    raise ValueError(
                        f"frame {number - first} of shape {shape_id!r}: missing file "
                        f"{str(missing)!r} (the sequence runs from frame_{first:0{digits}d} "
                        f"to frame_{last:0{digits}d})"
                    )
            files[shape_id] = [numbered[n] for n in range(first, last + 1)]
        return files, last - first + 1

    def _topologies(self, topology) -> dict[str, str]:
        if isinstance(topology, str):
            topology = {sid: topology for sid in self._files}
        if not isinstance(topology, dict):
            raise TypeError(f"topology={topology!r}: expected 'fixed', 'changing' or a dict")
        for sid, kind in topology.items():
            if kind not in TOPOLOGIES:
                raise ValueError(f"topology of shape {sid!r}: {kind!r}; expected one of {TOPOLOGIES}")
            if sid not in self._files:
                raise ValueError(
                    f"topology given for shape {sid!r}, which has no frame files "
                    f"(animated shapes: {self.animated_ids()})"
                )
        return {sid: topology.get(sid, "fixed") for sid in self._files}

    def _read_frame(self, shape_id: str, i: int) -> FrameGeometry:
        path = self._files[shape_id][i]
        where = f"frame {i} of shape {shape_id!r} ({str(path)!r})"
        # face_normals: Mitsuba need not compute vertex normals only to drop them.
        plugin = {"type": path.suffix.lower()[1:], "filename": str(path), "face_normals": True}
        if shape_id in self._to_world:
            plugin["to_world"] = self._to_world[shape_id]
        if not path.is_file():
            raise ValueError(f"{where}: the file is missing")
        try:
            with open(path, "rb") as handle:
                head = handle.read(4)
        except OSError as error:
            raise ValueError(f"{where}: the file cannot be read ({error.strerror})") from None
        if not head:
            raise ValueError(f"{where}: the file is empty (0 bytes)")
        kind = path.suffix.lower()[1:]
        if kind == "obj" and head.startswith(b"ply"):
            raise ValueError(f"{where}: it holds PLY data but is named .obj; name it .ply")
        if kind == "ply" and self._topology[shape_id] == "changing":
            negative = _ply_negative_index(path)
            if negative is not None:
                raise ValueError(f"{where}: face {negative[0]} has vertex index "
                                 f"{negative[1]}; indices must be 0 or more")
        try:
            mesh = mi.load_dict(plugin)
        except (RuntimeError, UnicodeDecodeError) as error:
            raise ValueError(f"{where}: Mitsuba cannot read it: {_first_line(error)}") from None
        if mesh.vertex_count() == 0 or mesh.face_count() == 0:
            raise ValueError(f"{where}: Mitsuba read {mesh.vertex_count()} vertices and "
                             f"{mesh.face_count()} faces from it; a frame needs at least "
                             f"one triangle")
        positions = mesh.vertex_positions_buffer()
        faces = mesh.faces_buffer()
        if self._topology[shape_id] == "changing":
            largest = int(dr.max(faces, axis=None)[0])
            if largest >= mesh.vertex_count():
                raise ValueError(f"{where}: a face has vertex index {largest}, past its "
                                 f"{mesh.vertex_count()} vertices")
            return FrameGeometry(positions, faces)
        vertex_count, face_count = self._meshes[shape_id]
        if mesh.vertex_count() != vertex_count or mesh.face_count() != face_count:
            raise ValueError(
                f"{where}: {mesh.vertex_count()} vertices and {mesh.face_count()} faces, but "
                f"the scene's shape has {vertex_count} and {face_count} (topology 'fixed'); "
                f"{_changing_hint(shape_id)}"
            )
        if not dr.all(mi.UInt32(faces) == self._fixed_faces[shape_id], axis=None):
            raise ValueError(
                f"{where}: its faces differ from the scene's shape (topology 'fixed'); "
                f"{_changing_hint(shape_id)}"
            )
        return FrameGeometry(positions)


def _entries(directory: Path) -> list[Path]:
    """The entries of a frames directory, sorted.

    Raises:
        ValueError: naming the directory, when it cannot be listed (no permission).
    """
    try:
        return sorted(directory.iterdir())
    except OSError as error:
        raise ValueError(f"frames directory {str(directory)!r}: cannot be listed "
                         f"({error.strerror})") from None


def _not_a_file(path: Path) -> str:
    """Why an entry named like a frame file is not a regular file, in words."""
    if path.is_symlink():
        try:
            path.stat()
        except OSError as error:
            return f"a symbolic link that leads to no file ({error.strerror})"
    return "a directory" if path.is_dir() else "not a regular file"


#: numpy types of PLY's scalar types.
_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2",
              "int16": "i2", "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4",
              "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4",
              "double": "f8", "float64": "f8"}


def _ply_negative_index(path: Path) -> tuple[int, int] | None:
    """``(face, index)`` of the first negative vertex index in a PLY file's faces, or
    ``None``. Mitsuba's loader reads such an index as another vertex without a word, so
    it is looked for before the file reaches Mitsuba. Indices of an unsigned type
    cannot be negative and are not read; a header this does not follow is left to
    Mitsuba."""
    data = path.read_bytes()
    end = data.find(b"end_header")
    if end < 0:
        return None
    body = data[data.index(b"\n", end) + 1:]
    form, elements = None, []
    for line in data[:end].decode("ascii", "replace").splitlines():
        words = line.split()
        if words[:1] == ["format"] and len(words) > 1:
            form = words[1]
        elif words[:1] == ["element"] and len(words) == 3 and words[2].isdigit():
            elements.append((words[1], int(words[2]), []))
        elif words[:1] == ["property"] and elements:
            elements[-1][2].append(words[1:])
    faces = [e for e in elements if e[0] == "face"]
    if form is None or not faces:
        return None
    index_type = next((p[2] for p in faces[0][2] if p[0] == "list" and len(p) == 4), None)
    if index_type is None or _PLY_TYPES.get(index_type, "u")[0] == "u":
        return None
    try:
        return _ply_first_negative(body, form, elements)
    except (ValueError, IndexError, KeyError):
        return None


def _ply_first_negative(body: bytes, form: str, elements) -> tuple[int, int] | None:
    """``(face, index)`` of the first negative index of a PLY body whose faces hold
    only their vertex-index list, the elements before them skipped (raises
    ``ValueError`` for a layout it does not follow). Binary faces that all have as many
    corners as the first are read as one numpy table, others face by face."""
    if form == "ascii":
        lines = body.split(b"\n")
        start = 0
        for name, count, properties in elements:
            if name == "face":
                (_,) = properties
                chosen = lines[start:start + count]
                if b"-" not in b" ".join(chosen):
                    return None
                for k, line in enumerate(chosen):
                    negative = [int(v) for v in line.split()[1:] if int(v) < 0]
                    if negative:
                        return k, negative[0]
                return None
            start += count
        return None
    order = "<" if form == "binary_little_endian" else ">"
    offset = 0
    for name, count, properties in elements:
        if name == "face":
            ((_, count_type, index_type, _),) = properties
            count_dtype = np.dtype(order + _PLY_TYPES[count_type])
            index_dtype = np.dtype(order + _PLY_TYPES[index_type])
            corners = int(np.frombuffer(body, count_dtype, 1, offset)[0])
            row = np.dtype([("n", count_dtype), ("i", index_dtype, (corners,))])
            if count and len(body) - offset >= count * row.itemsize:
                table = np.frombuffer(body, row, count, offset)
                if (table["n"] == corners).all():
                    bad = np.flatnonzero((table["i"] < 0).any(axis=1))
                    if not len(bad):
                        return None
                    indices = table["i"][bad[0]]
                    return int(bad[0]), int(indices[indices < 0][0])
            for k in range(count):
                corners = int(np.frombuffer(body, count_dtype, 1, offset)[0])
                offset += count_dtype.itemsize
                indices = np.frombuffer(body, index_dtype, corners, offset)
                offset += corners * index_dtype.itemsize
                if (indices < 0).any():
                    return k, int(indices[indices < 0][0])
            return None
        if any(p[0] == "list" for p in properties):
            raise ValueError("a list property before the faces")
        offset += count * sum(np.dtype(_PLY_TYPES[p[0]]).itemsize for p in properties)
    return None


class _resolving_next_to:
    """Context in which Mitsuba's file resolver also looks next to an XML file (as
    ``mi.load_file`` does), so the scene's relative paths work."""

    def __init__(self, source):
        self._directory = source.parent if isinstance(source, Path) else None

    def __enter__(self):
        self._saved = mi.file_resolver()
        if self._directory is not None:
            resolver = mi.FileResolver(self._saved)
            resolver.prepend(str(self._directory))
            mi.set_file_resolver(resolver)

    def __exit__(self, *exc):
        mi.set_file_resolver(self._saved)


def _configure_films(state, resolution, spp, box_filter: bool) -> None:
    """Sets size, samples per pixel and box filter on every sensor of a parse tree,
    adding the film, sampler or filter node a sensor leaves to its defaults.

    Nodes are addressed by index: appending to ``state.nodes`` may move them."""
    if resolution is not None:
        try:
            width, height = (int(v) for v in resolution)
        except (TypeError, ValueError):
            raise ValueError(f"resolution={resolution!r}: expected (width, height)") from None
        if width < 1 or height < 1:
            raise ValueError(f"resolution={resolution!r}: expected positive sizes")
    if spp is not None and (not isinstance(spp, int) or isinstance(spp, bool) or spp < 1):
        raise ValueError(f"spp={spp!r}: expected a positive int")
    sensors = [k for k, node in enumerate(state.nodes) if node.type == mi.ObjectType.Sensor]
    for sensor in sensors:
        film = _child(state, sensor, mi.ObjectType.Film, "film", "hdrfilm")
        sampler = _child(state, sensor, mi.ObjectType.Sampler, "sampler", "independent")
        if resolution is not None:
            state.nodes[film].props["width"] = width
            state.nodes[film].props["height"] = height
        if spp is not None:
            state.nodes[sampler].props["sample_count"] = spp
        if box_filter:
            box = _add_node(state, mi.ObjectType.ReconstructionFilter, "box")
            props = state.nodes[film].props
            for name, value in list(props.items()):
                if (
                    isinstance(value, mi.Properties.ResolvedReference)
                    and state.nodes[value.index()].type == mi.ObjectType.ReconstructionFilter
                ):
                    del props[name]
            props["rfilter"] = box


def _references(node) -> list[int]:
    """Indices of the nodes a parse-tree node refers to (its children)."""
    return [value.index() for _, value in node.props.items()
            if isinstance(value, mi.Properties.ResolvedReference)]


def _child(state, parent: int, kind, name: str, plugin: str) -> int:
    """Index of node ``parent``'s child of type ``kind``, added as ``plugin`` (under
    the property ``name``) when missing."""
    for _, value in state.nodes[parent].props.items():
        if (
            isinstance(value, mi.Properties.ResolvedReference)
            and state.nodes[value.index()].type == kind
        ):
            return value.index()
    reference = _add_node(state, kind, plugin)
    state.nodes[parent].props[name] = reference
    return reference.index()


def _add_node(state, kind, plugin: str) -> mi.Properties.ResolvedReference:
    """Appends a node of plugin ``plugin`` with default properties; its reference."""
    node = mi.parser.SceneNode()
    node.type = kind
    node.props = mi.Properties(plugin)
    state.nodes.append(node)
    return mi.Properties.ResolvedReference(len(state.nodes) - 1)


def _free_key(description: dict, key: str) -> str:
    """``key``, or ``key_1``, ``key_2``, ... if the description already has it."""
    candidate, k = key, 0
    while candidate in description:
        k += 1
        candidate = f"{key}_{k}"
    return candidate


def _changing_hint(shape_id: str) -> str:
    """How to declare a shape's topology as changing, in Python and on the command line."""
    return (f"if its topology changes, pass topology={{{shape_id!r}: 'changing'}} "
            f"(hlbvh render: --topology {shape_id}=changing)")


def _first_line(error: Exception) -> str:
    """The first line of a loader error. Mitsuba's message about a corrupt file can
    quote its bytes, which Python then fails to decode: those are replaced."""
    if isinstance(error, UnicodeDecodeError):
        text = bytes(error.object).decode("utf-8", "replace")
    else:
        text = str(error)
    return text.strip().splitlines()[0] if text.strip() else type(error).__name__
