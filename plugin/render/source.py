"""Where an animation comes from: a procedural scene of :mod:`hlbvh.scenes`, a Mitsuba XML
file with per-frame meshes, or a USD stage, named by one record (:class:`SceneSpec`) and
opened by :func:`open_animation` with what identifies it (a resume and a cluster's
workers check it) and the frames asked for."""

from __future__ import annotations

import re
import sys
from dataclasses import dataclass, replace
from pathlib import Path

from hlbvh import scenes
from hlbvh.errors import UserError, int_flag
from hlbvh.render.settings import frames_argument
from hlbvh.scenes.animated import MAX_TRIANGLES
from hlbvh.scenes.sequence import TOPOLOGIES


@dataclass(frozen=True)
class SceneSpec:
    """An animation as the command line names it, in one record: SCENE (a procedural
    scene with its options, a Mitsuba XML file, a USD stage with its options), and the
    strings of ``--frames-dir``, ``--triangles``, ``--frames`` (None: every frame),
    ``--topology``, ``--camera`` and ``--no-default-light``, and the ``--shutter``
    (``(open, close)`` in frames around each frame) the frames are read over: a USD
    stage's skinning is baked over the frames and the shutter around them.
    :func:`open_animation` opens it; :meth:`absolute` is what a cluster's worker, in its
    own working directory, opens as the client did."""

    scene: str
    frames_dir: str | None = None
    triangles: str | None = None
    frames: str | None = None
    topology: str | None = None
    camera: str | None = None
    default_light: bool = True
    shutter: tuple[float, float] = (0.0, 0.0)

    @classmethod
    def of(cls, scene, frames_dir=None, triangles=None, frames=None,
           topology=None, shutter=(0.0, 0.0)) -> SceneSpec:
        """The spec of the command line's values: SCENE (its ``--camera`` and
        ``--no-default-light`` ride on a :class:`hlbvh.cli.options.SceneArgument`),
        ``frames`` as the ``--frames`` text or a range, ``shutter`` the settings'."""
        if isinstance(frames, range):
            frames = frames_argument(frames)
        return cls(str(scene), None if frames_dir is None else str(frames_dir),
                   None if triangles is None else str(triangles), frames, topology,
                   getattr(scene, "camera", None), getattr(scene, "default_light", True),
                   tuple(float(value) for value in shutter))

    def absolute(self) -> SceneSpec:
        """The same spec with its files absolute (a USD stage's options written out)."""
        scene = self.scene
        stage = usd_stage(scene, self.default_light)
        if stage is not None:
            scene = usd_scene_string(stage[0].resolve(), stage[1])
        elif Path(scene).suffix.lower() == ".xml":
            scene = str(Path(scene).resolve())
        frames_dir = None if self.frames_dir is None else str(Path(self.frames_dir).resolve())
        return replace(self, scene=scene, frames_dir=frames_dir)


def open_animation(spec: SceneSpec) -> tuple:
    """The animated scene ``spec`` names, what identifies it, and the frame range.

    Returns:
        ``(animation, source, range)``.
    Raises:
        UserError: an unknown scene, a missing file, options that do not fit the kind
            of scene, a bad frame range.
    """
    scene, frames_dir, triangles, frames = spec.scene, spec.frames_dir, spec.triangles, spec.frames
    topology, camera = spec.topology, spec.camera
    start, stop, step = parse_frames(frames)
    stage = usd_stage(scene, spec.default_light)
    if camera is not None and stage is None:
        raise UserError(f"--camera picks a camera of a USD stage; {str(scene)!r} is not one")
    if not spec.default_light and stage is None:
        raise UserError(f"--no-default-light is for USD stages without lights; "
                        f"{str(scene)!r} is not a USD stage")
    if str(scene).partition(":")[0] in scenes.names():
        if frames_dir is not None:
            raise UserError(f"--frames-dir is for XML scenes; {scene!r} is procedural")
        if topology is not None:
            raise UserError(f"--topology is for the meshes of an XML scene's --frames-dir; "
                            f"{scene!r} is procedural")
        try:
            name, options = scenes.parse(str(scene))
        except ValueError as error:
            raise UserError(str(error)) from None
        if triangles is not None:
            options["triangles"] = int_flag("--triangles", triangles, least=1,
                                           most=MAX_TRIANGLES)
        try:
            default = scenes.get(name, **options).frame_count
        except ValueError as error:
            raise UserError(str(error)) from None
        # A procedural scene's motion is a function of time: frames past its own count
        # are as valid as the others.
        stop = default if stop is None else stop
        animation = scenes.get(name, **options, frames=max(default, stop))
        source = {"scene": str(scene), "triangles": animation.triangles}
    elif stage is not None:
        held: list[str] = []  # the stage's warnings, said once the frames are valid
        # refused by UsdScene as soon as it has read the stage's time range, when they
        # reach past it (a stop past any stage's frames: to the last)
        asked = range(start, sys.maxsize if stop is None else stop)
        animation, source = _open_usd(stage, scene, frames_dir, triangles, topology, camera,
                                      held.append, asked, spec.shutter)
        stop = animation.frame_count if stop is None else stop
        for line in held:
            print(f"hlbvh: {line}", file=sys.stderr)
        animation.warn_with(None)
    else:
        path = Path(scene)
        if path.suffix.lower() != ".xml" or not path.is_file():
            raise UserError(
                f"scene {scene!r}: not a procedural scene ({', '.join(scenes.names())}) "
                f"nor an existing Mitsuba .xml file"
            )
        if frames_dir is None:
            raise UserError(f"scene {scene!r}: an XML scene needs --frames-dir with its "
                            f"per-frame meshes")
        if triangles is not None:
            raise UserError("--triangles sizes procedural scenes; an XML scene has its own")
        kinds = parse_topology(topology)
        animation = scenes.SequenceScene(path, frames_dir, topology=kinds)
        source = {"scene": str(path.resolve()), "frames_dir": str(Path(frames_dir).resolve()),
                  "scene_sha256": animation.source_digest()}
        if topology is not None:
            source["topology"] = kinds
        stop = animation.frame_count if stop is None else stop
    if stop > animation.frame_count:
        raise UserError(f"--frames {frames}: {scene!r} has frames 0:{animation.frame_count}")
    if start >= stop:
        raise UserError(f"--frames {frames}: the range is empty (expected A < B)")
    return animation, source, range(start, stop, step)


#: Suffixes of the USD stages :func:`open_animation` opens as :class:`hlbvh.scenes.usd.UsdScene`.
USD_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")

#: The options a USD stage takes after its path (``shot.usda:instancing=false``), with
#: their defaults: :class:`hlbvh.scenes.usd.UsdScene`'s arguments
#: (``--no-default-light`` is ``default_light=false``).
USD_OPTIONS = {"instancing": True, "default_light": True}


def usd_stage(scene, default_light: bool = True) -> tuple[Path, dict] | None:
    """``(path, options)`` of a USD stage named by SCENE (``shot.usda`` or
    ``shot.usda:instancing=false``), None for any other scene; ``default_light`` False
    (``--no-default-light``) is one of its options.

    Raises:
        UserError: an option the stage does not take, given twice, or a value that is
            not ``true``/``false``.
    """
    suffixes = "|".join(re.escape(suffix) for suffix in USD_SUFFIXES)
    match = re.fullmatch(rf"(.*?(?:{suffixes}))(?::(.*))?", str(scene), re.IGNORECASE)
    if not match:
        return None
    options = {}
    for item in filter(None, (part.strip() for part in (match.group(2) or "").split(","))):
        key, equals, value = (part.strip() for part in item.partition("="))
        if not equals or key not in USD_OPTIONS:
            raise UserError(f"scene {str(scene)!r}: {item!r} is not an option of a USD "
                            f"stage; expected key=value with key one of {sorted(USD_OPTIONS)}")
        if value.lower() not in ("true", "false"):
            raise UserError(f"scene {str(scene)!r}: {key}={value!r}: expected true or false")
        if key in options:
            raise UserError(f"scene {str(scene)!r}: {key} is given twice; give it once")
        options[key] = value.lower() == "true"
    if not default_light:
        options["default_light"] = False
    return Path(match.group(1)), options


def usd_scene_string(path, options: dict) -> str:
    """SCENE of a stage at ``path`` with ``options`` (the inverse of :func:`usd_stage`)."""
    extra = ",".join(f"{k}={str(v).lower()}" for k, v in sorted(options.items()))
    return f"{path}:{extra}" if extra else str(path)


def _open_usd(stage: tuple, scene: str, frames_dir, triangles, topology, camera,
              warn, frames: range, shutter: tuple) -> tuple:
    """``(animation, source)`` of a USD stage (``stage``: :func:`usd_stage`'s path and
    options) opened for ``frames`` and the ``shutter`` around them (what its skinning is
    baked over): a
    :class:`hlbvh.scenes.usd.UsdScene` (imported here, ``pxr`` being an optional extra)
    and what identifies it (with its options, and the camera when ``--camera`` names
    one, so a resume through others is refused)."""
    path, options = stage
    for flag, value in (("--frames-dir", frames_dir), ("--triangles", triangles),
                        ("--topology", topology)):
        if value is not None:
            raise UserError(f"{flag} is not for USD stages; {scene!r} brings its own "
                            f"animation")
    try:
        from hlbvh.scenes.usd import UsdScene
    except ImportError as error:
        raise UserError(f"scene {scene!r}: {error}") from None
    try:
        animation = UsdScene(str(path), camera=camera, warn=warn, frames=frames,
                             shutter=shutter, **options)
    except ValueError as error:
        raise UserError(str(error)) from None
    source = {"scene": usd_scene_string(path.resolve(), options),
              "scene_sha256": animation.source_digest()}
    if camera is not None:
        source["camera"] = camera
    return animation, source


def parse_frames(text) -> tuple[int, int | None, int]:
    """``"A:B"``, ``"A:"``, ``":B"``, ``"A:B:STEP"`` (every STEP-th frame of A .. B-1,
    ``"A::STEP"`` to the last) or ``"N"`` (``0:N``) -> ``(A, B or None, STEP)``;
    ``None`` -> ``(0, None, 1)``. What the text alone can refuse (a step below 1, an
    empty range ``A >= B``) is refused here, before any scene is opened.

    Raises:
        UserError: naming ``--frames``.
    """
    if text is None:
        return 0, None, 1
    match = re.fullmatch(r"\s*(\d*)\s*:\s*(\d*)\s*(?::\s*(\d+)\s*)?|\s*(\d+)\s*", text)
    if not match:
        raise UserError(f"--frames {text!r}: expected A:B (frames A .. B-1), A:B:STEP "
                        f"(every STEP-th of them) or a count N")
    if match.group(4) is not None:
        count = int(match.group(4))
        if count < 1:
            raise UserError(f"--frames {text!r}: expected a count >= 1")
        return 0, count, 1
    start = int(match.group(1) or 0)
    stop = int(match.group(2)) if match.group(2) else None
    step = int(match.group(3)) if match.group(3) else 1
    if step < 1:
        raise UserError(f"--frames {text!r}: expected a STEP >= 1")
    if stop is not None and start >= stop:
        raise UserError(f"--frames {text!r}: the range is empty (expected A < B)")
    return start, stop, step


def parse_topology(text: str | None):
    """``--topology``: ``None`` or ``"fixed"`` -> ``"fixed"``, ``"changing"``, or
    ``"ID=changing,ID=fixed"`` -> ``{"ID": "changing", ...}`` (what
    :class:`hlbvh.scenes.SequenceScene` takes)."""
    if text is None:
        return "fixed"
    word = text.strip()
    if word in TOPOLOGIES:
        return word
    kinds = {}
    for part in word.split(","):
        shape, _, kind = part.partition("=")
        if not shape.strip() or kind.strip() not in TOPOLOGIES:
            raise UserError(f"--topology {text!r}: expected fixed, changing, or "
                            f"ID=changing,ID=fixed per shape")
        kinds[shape.strip()] = kind.strip()
    return kinds
