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
from pathlib import Path

import drjit as dr
import mitsuba as mi

from .animated import AnimatedScene, FrameGeometry
from .frame_files import FRAME_FILE, entries, not_a_file, ply_negative_index
from .parse_tree import configure_films, references, resolving_next_to

TOPOLOGIES = ("fixed", "changing")


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
        ``None`` when it has none. A wrapper (``moment``, ``stokes``, ``aov``) holding
        one integrator has it, described the same way, under ``"nested"``.

        Raises:
            ValueError: a property of it that is not a number, a boolean, a string or
                one nested integrator (a texture, a second nested integrator), which
                could not be handed on.
        """
        state = self._parse()
        for index in references(state.root):
            node = state.nodes[index]
            if node.type == mi.ObjectType.Integrator:
                return self._integrator(state, node)
        return None

    def _integrator(self, state, node) -> dict:
        """An integrator node of the parse tree as :meth:`integrator_description` says."""
        plugin = node.props.plugin_name()
        description, nested = {"type": plugin}, []
        for name, value in node.props.items():
            child = (state.nodes[value.index()]
                     if isinstance(value, mi.Properties.ResolvedReference) else None)
            if child is not None and child.type == mi.ObjectType.Integrator:
                nested.append(child)
            elif isinstance(value, (bool, int, float, str)):
                description[name] = value
            else:
                raise ValueError(
                    f"scene {self._describe()}: its integrator {plugin!r} has property "
                    f"{name!r} of a kind hlbvh cannot hand on ({type(value).__name__}); "
                    f"replace the integrator (hlbvh render: --integrator path or aov)")
        if len(nested) > 1:
            raise ValueError(
                f"scene {self._describe()}: its integrator {plugin!r} holds {len(nested)} "
                f"integrators; hlbvh render runs a wrapper around one (or replace it: "
                f"--integrator path)")
        if nested:
            description["nested"] = self._integrator(state, nested[0])
        return description

    def source_digest(self) -> str | None:
        """SHA-256 (hex) of what the scene is made of: the XML file, the files it
        includes, and every file a ``filename`` property names (meshes, textures), so a
        render folder can tell that the scene changed between two runs; ``None`` for a
        dict scene. A file that cannot be read counts as its absence."""
        if not isinstance(self._source, Path):
            return None
        state = self._parse()
        files = [Path(str(name)) for name in state.files]
        with resolving_next_to(self._source):
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

    def scene_dict(self, resolution: tuple[int, int] | None = None, spp: int | None = None,
                   integrator: dict | None = None) -> dict:
        """See :meth:`AnimatedScene.scene_dict`. The scene as the file or dict describes
        it (its own geometry, not frame 0), with its films resized to ``resolution``, its
        samplers set to ``spp``, a box filter unless ``box_filter=False``, and
        ``integrator`` in place of its own. Every shape is handed over already built
        (Mitsuba is told not to merge meshes), keyed by its id; shapes without an id get
        ``shape_<k>``. Instances and their shape groups, which Mitsuba does not take
        built, are described by :meth:`_instancing`."""
        state = self._parse()
        configure_films(state, resolution, spp, self._box_filter)
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
                groups[node.props.id()] = references(node)
            elif kind == "instance":
                description = {"type": "instance"}
                if "to_world" in node.props.keys():
                    description["to_world"] = node.props["to_world"]
                for k, child in enumerate(references(node)):
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
            with resolving_next_to(self._source):
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
            with resolving_next_to(self._source):
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
        for entry in entries(self._frames_dir):
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
            for file in entries(entry):
                match = FRAME_FILE.match(file.name)
                if not match:
                    continue
                if not file.is_file():
                    raise ValueError(
                        f"frame file {str(file)!r} of shape {entry.name!r}: "
                        f"{not_a_file(file)}; make it a readable mesh file or remove it"
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
            negative = ply_negative_index(path)
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
    """A loader error on one line: its first line and, when that one ends in a colon,
    what it introduces: the traceback of a Python plugin's constructor (a bad property
    of one of hlbvh's integrators) by its last line, the exception itself, a list (the
    properties no plugin took) by its first items. Mitsuba's message about a corrupt
    file can quote its bytes, which Python then fails to decode: those are replaced."""
    if isinstance(error, UnicodeDecodeError):
        text = bytes(error.object).decode("utf-8", "replace")
    else:
        text = str(error)
    lines = [line.strip() for line in text.strip().splitlines() if line.strip()]
    if not lines:
        return type(error).__name__
    head = "Traceback (most recent call last):"
    if lines[0].endswith(head) and len(lines) > 1:
        return lines[0].removesuffix(head) + lines[-1]
    if lines[0].endswith(":") and len(lines) > 1:
        return " ".join(lines[:4])[:400]
    return lines[0]
