"""How the frames of an animation are rendered (:class:`RenderSettings`), and the limits
every frame's settings are checked against before any frame is rendered."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from hlbvh.accel.policy import ACCELS, BUILD_OPTIONS, UpdatePolicy
from hlbvh.errors import UserError
from hlbvh.integrators.common import MAX_INTEGER_PROPERTY
from hlbvh.kernels.bvh import BuildConfig

#: ``--integrator`` choices and the registered integrators they name.
INTEGRATORS = {"path": "hlbvh_path", "direct": "hlbvh_direct", "volpath": "hlbvh_volpath",
               "aov": "hlbvh_aov"}

#: Integrators a scene may name that ``hlbvh render`` runs, and the ``--integrator``
#: choice each is (Mitsuba's ``path``, ``direct`` and ``volpath`` run as ours, which
#: mirror them).
SCENE_INTEGRATORS = {"path": "path", "hlbvh_path": "path", "direct": "direct",
                     "hlbvh_direct": "direct", "volpath": "volpath",
                     "hlbvh_volpath": "volpath", "hlbvh_aov": "aov"}

#: Mitsuba's integrators that wrap one other and trace nothing themselves (``moment``:
#: its second moment too; ``stokes``: the Stokes vector, in polarized variants):
#: ``hlbvh render`` keeps the wrapper of a scene around the nested integrator it runs
#: as ours. (Mitsuba's ``aov`` traces its own channels through the scene's accelerator:
#: ``--integrator aov`` is ours.)
WRAPPER_INTEGRATORS = ("moment", "stokes")

#: The ``--integrator`` choices that take ``max_depth``.
DEPTH_INTEGRATORS = ("path", "volpath")

#: Longest path of ``--integrator path`` unless ``--max-depth`` or the scene's own
#: integrator says otherwise.
DEFAULT_MAX_DEPTH = 8

#: Longest path of a scene's path tracer (``path``, ``volpath``, ours) that names none
#: (theirs: unbounded).
SCENE_MAX_DEPTH = -1

#: Largest seed of a frame: Mitsuba's samplers take 32-bit seeds.
MAX_SEED = 2**32 - 1

#: Most intervals between a moving mesh's keys over the shutter: each key holds the
#: moving meshes' whole tree again.
MAX_MOTION_KEYS = 64

#: Most sub-frames native renders per frame with an open shutter (each a rebuild).
MAX_SUB_FRAMES = 1024


@dataclass(frozen=True)
class RenderSettings:
    """How the frames of an animation are rendered.

    Attributes:
        resolution: film ``(width, height)``; ``None`` keeps the scene's.
        spp: samples per pixel; ``None`` keeps the scene's.
        integrator: ``"path"`` (``hlbvh_path``), ``"direct"`` (``hlbvh_direct``),
            ``"volpath"`` (``hlbvh_volpath``) or ``"aov"`` (``hlbvh_aov``).
        max_depth: longest path of ``"path"`` and ``"volpath"`` (-1: unbounded; at most
            2^31 - 1, Mitsuba's largest integer property).
        accel: ``"hlbvh"`` or ``"native"``.
        build_options: options of :func:`hlbvh.build` (``builder``, ``leaf_size``, ...),
            validated for both accelerators.
        update: our accelerator's per-frame policy (``"rebuild"``, ``"refit"``,
            ``"auto"``), or ``None`` for its default; handed to the integrator as its
            ``update`` property.
        static: what traces the shapes that do not move, ``"native"`` (Mitsuba's own
            accelerator) or ``"hlbvh"`` (our watertight traversal); the integrator's
            ``static`` property.
        moving_accel: what traces the moving meshes (``"auto"``, ``"hlbvh"``,
            ``"native"``, ``"scene"``; :data:`hlbvh.accel.policy.MOVING_ACCELS`), or
            ``None`` for the accelerator's default (``"auto"``); the integrator's
            ``moving_accel`` property.
        seed: frame ``i`` is rendered with seed ``seed + i``.
        properties: the integrator's other properties (``rr_depth``,
            ``hide_emitters``, ...: what a scene's own integrator sets), handed on as
            they are; numbers, booleans and strings.
        wrapper: a Mitsuba integrator around it (``{"type": one of
            WRAPPER_INTEGRATORS, property: value}``, a scene's own), or None.
        shutter: ``(open, close)`` in frames, relative to each frame (``(-0.25,
            0.25)``: a quarter frame either side); ``(0, 0)``, the default, is closed
            (each frame an instant). Open, our accelerator traces every ray at its time
            through the moving meshes' keys; native renders the mean of
            ``sub_frames`` sub-frames at stratified times (a rebuild each).
        motion_keys: ``S``, the intervals between the keys of a moving mesh over an
            open shutter (``S + 1`` keys: a build and ``S + 1`` refits a frame).
        sub_frames: native's sub-frames per frame with an open shutter (each at the
            frame's samples over ``sub_frames``).
    Raises:
        ValueError: naming the setting, for any value outside the above.
    """

    resolution: tuple[int, int] | None = None
    spp: int | None = None
    integrator: str = "path"
    max_depth: int = DEFAULT_MAX_DEPTH
    accel: str = "hlbvh"
    build_options: dict = field(default_factory=dict)
    update: str | None = None
    seed: int = 0
    static: str = UpdatePolicy.static
    moving_accel: str | None = None
    properties: dict = field(default_factory=dict)
    wrapper: dict | None = None
    shutter: tuple[float, float] = (0.0, 0.0)
    motion_keys: int = 1
    sub_frames: int = 16

    def __post_init__(self):
        if self.resolution is not None and (
            len(self.resolution) != 2 or not all(_is_int(v) and v >= 1 for v in self.resolution)
        ):
            raise ValueError(f"resolution={self.resolution!r}: expected (width, height) >= 1")
        if self.spp is not None and not (_is_int(self.spp) and self.spp >= 1):
            raise ValueError(f"spp={self.spp!r}: expected an int >= 1")
        if self.integrator not in INTEGRATORS:
            raise ValueError(f"integrator={self.integrator!r}: expected one of {tuple(INTEGRATORS)}")
        if not (_is_int(self.max_depth) and -1 <= self.max_depth <= MAX_INTEGER_PROPERTY):
            raise ValueError(f"max_depth={self.max_depth!r}: expected -1 (unbounded) or an "
                             f"int in 0..{MAX_INTEGER_PROPERTY}")
        if self.accel not in ACCELS:
            raise ValueError(f"accel={self.accel!r}: expected one of {ACCELS}")
        self.config  # the builder's options, checked where hlbvh.build checks them
        self.policy  # the accelerator's, checked where SceneAccel checks them
        if not (_is_int(self.seed) and 0 <= self.seed <= MAX_SEED):
            raise ValueError(f"seed={self.seed!r}: expected an int in 0..{MAX_SEED}")
        for name, value in self.properties.items():
            _check_property(f"integrator property {name}", value)
        open_, close = (float(v) for v in self.shutter)
        if not (np.isfinite(open_) and np.isfinite(close) and open_ <= close):
            raise ValueError(f"shutter={tuple(self.shutter)!r}: expected finite open <= close "
                             "(frames relative to each frame, e.g. (-0.25, 0.25))")
        if not (_is_int(self.motion_keys) and 1 <= self.motion_keys <= MAX_MOTION_KEYS):
            raise ValueError(f"motion_keys={self.motion_keys!r}: expected an int in "
                             f"1..{MAX_MOTION_KEYS}")
        if not (_is_int(self.sub_frames) and 1 <= self.sub_frames <= MAX_SUB_FRAMES):
            raise ValueError(f"sub_frames={self.sub_frames!r}: expected an int in "
                             f"1..{MAX_SUB_FRAMES}")
        if self.wrapper is not None:
            if self.wrapper.get("type") not in WRAPPER_INTEGRATORS:
                raise ValueError(f"wrapper={self.wrapper!r}: expected a type among "
                                 f"{WRAPPER_INTEGRATORS}")
            for name, value in self.wrapper.items():
                _check_property(f"wrapper property {name}", value)

    @property
    def shutter_open(self) -> bool:
        """Whether the shutter stays open for a while (motion blur)."""
        return self.shutter[1] > self.shutter[0]

    @property
    def config(self) -> BuildConfig:
        """The builder's config these settings give our accelerator (validated)."""
        return BuildConfig.from_options(**self.build_options)

    @property
    def policy(self) -> UpdatePolicy:
        """The update policy these settings give our accelerator (validated; its own
        defaults where a setting is None)."""
        given = {"update": self.update, "static": self.static,
                 "moving_accel": self.moving_accel}
        return UpdatePolicy(**{k: v for k, v in given.items() if v is not None}).validated()

    def integrator_dict(self) -> dict:
        """The Mitsuba description of the integrator these settings ask for."""
        description = {"type": INTEGRATORS[self.integrator], **self.properties,
                       "accel": self.accel, **self.build_options}
        if self.integrator in DEPTH_INTEGRATORS:
            description["max_depth"] = self.max_depth
        if self.update is not None:
            description["update"] = self.update
        description["static"] = self.static
        if self.moving_accel is not None:
            description["moving_accel"] = self.moving_accel
        if self.wrapper is not None:
            return {**self.wrapper, "nested": description}
        return description

    def as_dict(self) -> dict:
        """The settings as JSON values (what ``stats.json`` records; ``wrapper`` only
        when there is one, so folders recorded without it still resume)."""
        record = asdict(self)
        record["resolution"] = None if self.resolution is None else list(self.resolution)
        if self.wrapper is None:
            del record["wrapper"]
        if self.shutter_open:
            record["shutter"] = list(self.shutter)
        else:  # folders recorded before shutters existed still resume
            for name in ("shutter", "motion_keys", "sub_frames"):
                del record[name]
        return record


def scene_integrator_fields(description: dict) -> dict:
    """The :class:`RenderSettings` fields that a scene's own integrator (``{"type":
    ..., property: value}``, one of :data:`SCENE_INTEGRATORS`) decides: ``integrator``,
    ``max_depth`` (of a path tracer; :data:`SCENE_MAX_DEPTH` when it names none),
    ``accel`` (``"hlbvh"`` for Mitsuba's ``path``), ``build_options``, ``update``,
    ``static``, and every other property as ``properties``."""
    kind = description["type"]
    properties = {k: v for k, v in description.items() if k != "type"}
    fields = {"integrator": SCENE_INTEGRATORS[kind]}
    if fields["integrator"] in DEPTH_INTEGRATORS:
        fields["max_depth"] = properties.pop("max_depth", SCENE_MAX_DEPTH)
    fields["accel"] = properties.pop("accel", "hlbvh")
    fields["build_options"] = {name: properties.pop(name) for name in BUILD_OPTIONS
                               if name in properties}
    fields["update"] = properties.pop("update", None)
    fields["static"] = properties.pop("static", UpdatePolicy.static)
    fields["moving_accel"] = properties.pop("moving_accel", None)
    fields["properties"] = properties
    return fields


def _check_property(what: str, value) -> None:
    if not isinstance(value, (bool, int, float, str)):
        raise ValueError(f"{what}={value!r}: expected a number, a boolean or a string")


def _is_int(value) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


def check_seed(seed: int, frames) -> None:
    """Refuse a ``--seed`` whose last frame's seed (``seed + frame``) is past
    :data:`MAX_SEED`, before any frame is rendered.

    Raises:
        UserError: naming ``--seed`` and the largest one that fits ``frames``, or
            ``--frames`` where its last frame is past :data:`MAX_SEED` (no seed fits).
    """
    last = frames[-1]
    if last > MAX_SEED:
        raise UserError(f"--frames: frame {last} is past {MAX_SEED}, the last frame a seed "
                        f"numbers (frame i renders with seed --seed + i; seeds are 32-bit)")
    if seed + last > MAX_SEED:
        raise UserError(f"--seed {seed}: frame {last} would get seed {seed + last}, past "
                        f"{MAX_SEED} (seeds are 32-bit); use --seed {MAX_SEED - last} or less")


def frames_argument(frames: range) -> str:
    """The ``--frames`` text of a frame range: ``"A:B"``, or ``"A:B:STEP"`` where it skips
    frames (what a record or a cluster's worker is given)."""
    step = "" if frames.step == 1 else f":{frames.step}"
    return f"{frames.start}:{frames.stop}{step}"


def frames_text(frames: range) -> str:
    """A frame range as the command line's summaries say it: its first and last frame
    (``"0..23"``), and the step where it skips frames (``"0..90 in steps of 10"``, of
    ``--frames 0:100:10``)."""
    text = f"{frames[0]}..{frames[-1]}"
    return text if frames.step == 1 or len(frames) == 1 else f"{text} in steps of {frames.step}"
