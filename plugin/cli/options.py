"""The command-line options ``hlbvh render``, ``compare``, ``sweep`` and ``bench``
share, and their parsing: each value is checked here and a mistake raises a
:class:`hlbvh.errors.UserError` naming the option, so the command line reports it in
one line."""

from __future__ import annotations

import argparse
import math
import re
import sys
from dataclasses import replace
from pathlib import Path

from hlbvh import scenes
from hlbvh.accel.policy import (ACCELS, BUILD_OPTIONS, MOVING_ACCELS, STATICS, UPDATES,
                                 UpdatePolicy)
from hlbvh.errors import UserError, int_flag
from hlbvh.integrators.common import MAX_INTEGER_PROPERTY
from hlbvh.kernels.bvh import BuildConfig
from hlbvh.render.frame import MAX_SAMPLES
from hlbvh.render.settings import (DEFAULT_MAX_DEPTH, DEPTH_INTEGRATORS, INTEGRATORS,
                                   MAX_MOTION_KEYS, MAX_SEED, MAX_SUB_FRAMES,
                                   SCENE_INTEGRATORS, WRAPPER_INTEGRATORS,
                                   RenderSettings,
                                   scene_integrator_fields)


def add_scene_options(parser, out: str, *, builder_options: bool = True,
                      frames: str | None = None, spp: int | None = None) -> None:
    """The options of a scene and its renders (``hlbvh render``, ``compare``, ``sweep``): SCENE,
    ``--frames-dir``, ``--frames``, ``--resolution``, ``--spp``, ``--triangles``,
    ``--max-depth``, ``--seed``, ``--out``, ``--quiet``; with ``builder_options`` also
    the builder's options, ``--update`` and ``--static``. ``out``, ``frames`` and
    ``spp`` are the defaults the help states (``None``: every frame, the scene's spp);
    the caller applies them."""
    add = parser.add_argument
    add("scene", action=_SceneAction,
        help=f"a procedural scene ({', '.join(scenes.names())}; its options as "
             "NAME:KEY=VALUE,..., e.g. flock:birds=200 or rigid:instanced=true), a Mitsuba XML "
             "file (with --frames-dir) or an animated USD stage (.usd, .usda, .usdc, "
             ".usdz; pip install 'hlbvh[usd]'; STAGE:instancing=false renders every mesh "
             "in world space, no Mitsuba instances)")
    add("--camera", action=_CameraAction,
        help="of a USD stage: the prim path of the camera to render through (default: "
             "the stage's render settings' camera, else its first camera)")
    add("--no-default-light", action=_NoDefaultLightAction, nargs=0,
        help="of a USD stage without UsdLux lights: no default sky and sun (by default "
             "they light it, as a DCC's viewport does; STAGE:default_light=false)")
    add("--frames-dir", help="directory of per-frame meshes <dir>/<shape id>/frame_0001.ply "
                             "(with an XML scene)")
    add("--topology", help="of the meshes of --frames-dir: fixed (default: only positions "
                           "change), changing (every frame brings its faces), or per shape "
                           "ID=changing,ID=fixed")
    add("--frames", help="A:B (frames A .. B-1), A:B:STEP (every STEP-th of them, A::STEP "
                         "to the last) or N (the first N); default: "
                         + (frames or "every frame of the scene"))
    add("--resolution", help="W (W×W) or WxH; default: the scene's")
    add("--spp", help="samples per pixel; default: " + ("the scene's" if spp is None else str(spp)))
    add("--triangles", help="size of a procedural scene (default 200000)")
    add("--max-depth", help=f"longest path of the path integrator (default: the scene's "
                            f"integrator's, else {DEFAULT_MAX_DEPTH}; -1: unbounded)")
    if builder_options:
        for name in BUILD_OPTIONS:
            add(f"--{name.replace('_', '-')}", dest=name,
                help=f"builder option {name} (hlbvh.build; default {getattr(BuildConfig, name)!r})")
        add("--update", help="our accelerator's per-frame policy: auto, rebuild, fresh or refit "
                             "(default: the accelerator's own, auto)")
        add("--static", help="what traces the shapes that do not move: native (Mitsuba's own "
                             "accelerator, the fastest; default) or hlbvh (our watertight "
                             "traversal for every mesh, the accurate end)")
        add("--moving-accel", help="what traces the moving meshes: auto (default: per render, "
                                   "the cheapest by measured cost), hlbvh (our BVH), native "
                                   "(a Mitsuba sub-scene of them, rebuilt) or scene "
                                   "(Mitsuba's whole scene, rebuilt)")
    add("--shutter", help="motion blur: how long the shutter stays open, in frames, "
                          "centred on each frame (0.5: a 180-degree shutter, -0.25..0.25), "
                          "or =OPEN:CLOSE relative to the frame (--shutter=-0.25:0.25); our "
                          "BVH traces each ray at its time, native averages sub-frames; 0 "
                          "(default): each frame an instant")
    add("--motion-keys", help="with --shutter: intervals between a moving mesh's keys over "
                              f"the shutter (default 1: two keys; at most {MAX_MOTION_KEYS})")
    add("--sub-frames", help="with --shutter: native's sub-frames per frame, each a rebuild "
                             f"(default 16; at most {MAX_SUB_FRAMES})")
    add("--seed", default="0", help="frame i is rendered with seed SEED + i (default 0)")
    add("--out", help=f"output directory (default {out})")
    add("--quiet", action="store_true", help="no progress bars")


class SceneArgument(str):
    """The SCENE string, carrying ``camera`` (``--camera``) and ``default_light``
    (False with ``--no-default-light``): the options that qualify SCENE travel with it
    into :class:`hlbvh.render.source.SceneSpec`, whichever command parsed them."""

    camera: str | None = None
    default_light: bool = True

    @classmethod
    def of(cls, scene: str, camera: str | None, default_light: bool = True) -> SceneArgument:
        argument = cls(scene)
        argument.camera = camera
        argument.default_light = default_light
        return argument


class _SceneAction(argparse.Action):
    """SCENE as a :class:`SceneArgument` with the ``--camera`` and
    ``--no-default-light`` parsed before it."""

    def __call__(self, parser, namespace, value, option_string=None):
        setattr(namespace, self.dest, SceneArgument.of(
            value, getattr(namespace, "camera", None),
            not getattr(namespace, "no_default_light", False)))


class _CameraAction(argparse.Action):
    """``--camera``, also set on a SCENE parsed before it."""

    def __call__(self, parser, namespace, value, option_string=None):
        setattr(namespace, self.dest, value)
        scene = getattr(namespace, "scene", None)
        if isinstance(scene, str):
            namespace.scene = SceneArgument.of(scene, value,
                                               getattr(scene, "default_light", True))


class _NoDefaultLightAction(argparse.Action):
    """``--no-default-light``, also set on a SCENE parsed before it."""

    def __call__(self, parser, namespace, value, option_string=None):
        setattr(namespace, self.dest, True)
        scene = getattr(namespace, "scene", None)
        if isinstance(scene, str):
            namespace.scene = SceneArgument.of(scene, getattr(scene, "camera", None), False)


def out_flag(text: str | None, default: Path) -> Path:
    """``--out`` as given, or ``default`` when it is not; an empty ``--out ''`` is an
    error, not the default (the directory itself is checked by
    :func:`hlbvh.render.output.output_directory`)."""
    if text is None:
        return default
    if not text.strip():
        raise UserError("--out '': an empty path; give a directory, or leave --out out "
                        "for the default")
    return Path(text)


def render_settings(args, *, spp: int | None = None, integrator: str = "path",
                    accel: str = "native") -> RenderSettings:
    """The :class:`hlbvh.render.settings.RenderSettings` of the options :func:`add_scene_options`
    parsed into ``args``, with ``integrator`` and ``accel`` (``spp`` given here
    overrides ``--spp``; the builder options and ``--update`` are read when ``args``
    has them).

    Raises:
        UserError: a malformed number or choice, naming the option.
        ValueError: a builder option out of range, naming it.
    """
    build_options = {name: option_value(getattr(args, name)) for name in BUILD_OPTIONS
                     if getattr(args, name, None) is not None}
    update = getattr(args, "update", None)
    static = getattr(args, "static", None)
    moving_accel = getattr(args, "moving_accel", None)
    if spp is None and args.spp is not None:
        spp = int_flag("--spp", args.spp, least=1, most=MAX_SAMPLES)
    return RenderSettings(
        resolution=None if args.resolution is None else parse_resolution(args.resolution),
        spp=spp,
        integrator=integrator,
        max_depth=(DEFAULT_MAX_DEPTH if args.max_depth is None
                   else int_flag("--max-depth", args.max_depth, least=-1,
                                     most=MAX_INTEGER_PROPERTY)),
        accel=accel,
        build_options=build_options,
        update=None if update is None else choice("--update", update, UPDATES),
        seed=seed_flag(args.seed),
        static=UpdatePolicy.static if static is None else choice("--static", static, STATICS),
        moving_accel=(None if moving_accel is None
                      else choice("--moving-accel", moving_accel, MOVING_ACCELS)),
        **shutter_settings(args),
    )


def shutter_settings(args) -> dict:
    """``--shutter``, ``--motion-keys`` and ``--sub-frames`` as RenderSettings fields
    (those not given left to the settings' defaults); the last two need the first."""
    fields = {}
    shutter = getattr(args, "shutter", None)
    if shutter is not None:
        parts = shutter.split(":")
        try:
            values = [float(p) for p in parts]
        except ValueError:
            values = []
        if len(values) == 1:  # a length, centred on the frame
            values = [-values[0] / 2, values[0] / 2]
        if len(values) != 2 or not (math.isfinite(values[0]) and math.isfinite(values[1])
                                    and values[0] <= values[1]):
            raise UserError(f"--shutter {shutter!r}: expected a length in frames >= 0 "
                            "(0.5) or OPEN:CLOSE, finite frames relative to each frame with "
                            "OPEN <= CLOSE (--shutter=-0.25:0.25)")
        open_, close = values
        fields["shutter"] = (open_, close)
    for flag, name, most in (("--motion-keys", "motion_keys", MAX_MOTION_KEYS),
                             ("--sub-frames", "sub_frames", MAX_SUB_FRAMES)):
        text = getattr(args, name, None)
        if text is not None:
            if shutter is None:
                raise UserError(f"{flag} {text}: it sets the keys of an open shutter; give "
                                "--shutter OPEN:CLOSE too")
            fields[name] = int_flag(flag, text, least=1, most=most)
    return fields


def scene_render_settings(args, animation, scene: str) -> tuple[RenderSettings, str | None]:
    """The settings of ``hlbvh render``: the scene's own integrator and its properties
    (:meth:`hlbvh.scenes.AnimatedScene.integrator_description`) where it has one, each
    replaced by the flag that names it (``--integrator``, ``--accel``, ``--max-depth``,
    the builder options, ``--update``); what no flag and no scene says takes the
    defaults of :func:`render_settings`. Returns the settings and the line that says
    what the flags override (``None`` when they override nothing).

    Raises:
        UserError: a malformed flag, or a scene integrator that ``hlbvh render`` does not
            run (not one of :data:`hlbvh.render.settings.SCENE_INTEGRATORS`) without an
            ``--integrator`` to replace it.
        ValueError: a value out of range, from a flag or the scene.
    """
    integrator = getattr(args, "integrator", None)
    integrator = None if integrator is None else choice("--integrator", integrator,
                                                        tuple(INTEGRATORS))
    accel = getattr(args, "accel", None)
    accel = None if accel is None else choice("--accel", accel, ACCELS)
    flags = render_settings(args, integrator=integrator or "path", accel=accel or "hlbvh")
    own = animation.integrator_description()
    if own is None:
        return flags, None
    wrapper = None
    if own["type"] in WRAPPER_INTEGRATORS and "nested" in own:
        wrapper = {k: v for k, v in own.items() if k != "nested"}
        own = own["nested"]
    kind = own["type"]
    named = kind if wrapper is None else f"{wrapper['type']} around {kind}"
    if kind not in SCENE_INTEGRATORS or (integrator and SCENE_INTEGRATORS[kind] != integrator):
        if integrator is None:
            raise UserError(
                f"scene {scene!r}: its integrator {named!r} is not one hlbvh render runs "
                f"({', '.join(SCENE_INTEGRATORS)}, or {'/'.join(WRAPPER_INTEGRATORS)} "
                f"around one); pass --integrator {'/'.join(INTEGRATORS)} to render with "
                f"hlbvh's instead")
        return flags, (f"--integrator {integrator} overrides the scene's integrator "
                       f"{named!r} (its properties are not used)")
    fields = scene_integrator_fields(own)
    fields["wrapper"] = wrapper
    overrides = []

    def override(flag: str, name: str, value, scene_value):
        # a flag for a property the scene leaves unset overrides nothing
        if scene_value is not None and value != scene_value:
            overrides.append(f"{flag} {value} (the scene's {name}: {scene_value!r})")

    if args.max_depth is not None and fields["integrator"] in DEPTH_INTEGRATORS:
        override("--max-depth", "max_depth", flags.max_depth, fields["max_depth"])
        fields["max_depth"] = flags.max_depth
    if accel is not None:
        if kind.startswith("hlbvh_"):  # Mitsuba's integrators name no accelerator
            override("--accel", "accel", accel, fields["accel"])
        fields["accel"] = accel
    for name, value in flags.build_options.items():
        override(f"--{name.replace('_', '-')}", name, value, fields["build_options"].get(name))
    fields["build_options"] = {**fields["build_options"], **flags.build_options}
    if flags.update is not None:
        override("--update", "update", flags.update, fields["update"])
        fields["update"] = flags.update
    if getattr(args, "static", None) is not None:
        override("--static", "static", flags.static, fields["static"])
        fields["static"] = flags.static
    if flags.moving_accel is not None:
        override("--moving-accel", "moving_accel", flags.moving_accel, fields["moving_accel"])
        fields["moving_accel"] = flags.moving_accel
    # Mitsuba's path has always run as hlbvh_path (the README says so); the other
    # integrators that run as ours are said, once
    lines = [] if kind.startswith("hlbvh_") or kind == "path" else [
        f"the scene's integrator {kind!r} runs as {INTEGRATORS[fields['integrator']]} "
        f"(which mirrors it, every ray through the chosen accelerator)"]
    if wrapper is not None:
        lines.append(f"the scene's {wrapper['type']!r} wraps it, its outputs kept")
    if overrides:
        lines.append(f"the command line overrides the scene's integrator {kind!r}: "
                     f"{', '.join(overrides)}")
    line = "; ".join(lines) or None
    return replace(flags, **fields), line


def with_scene_integrator(args, animation, settings: RenderSettings,
                          verb: str) -> RenderSettings:
    """``settings``, or, for a scene whose own integrator is Mitsuba's ``direct`` or
    ``volpath`` (which ours mirror), the settings of that integrator and its properties
    (:func:`scene_render_settings`, the flags replacing what they name), with one line
    on stderr saying what was mapped: what ``compare`` and ``sweep`` render such a
    scene with (a ``path`` scene keeps the flags' path, as before)."""
    own = animation.integrator_description()
    if own is None or SCENE_INTEGRATORS.get(own["type"]) not in ("direct", "volpath"):
        return settings
    mapped, line = scene_render_settings(args, animation, args.scene)
    if line is not None:
        print(f"hlbvh {verb}: {line}", file=sys.stderr)
    return replace(mapped, spp=settings.spp)


def seed_flag(text: str) -> int:
    """``--seed``: an integer in 0 .. :data:`hlbvh.render.settings.MAX_SEED`."""
    return int_flag("--seed", text, least=0, most=MAX_SEED)


def parse_resolution(text: str) -> tuple[int, int]:
    """``"W"`` -> ``(W, W)``; ``"WxH"`` -> ``(W, H)``, each side in 1 ..
    :data:`hlbvh.render.frame.MAX_SAMPLES` (Mitsuba's film takes no larger side; the
    frame's pixels times its samples are checked against the same bound later)."""
    match = re.fullmatch(r"\s*(\d+)\s*(?:[xX×]\s*(\d+)\s*)?", text)
    sides = [] if not match else [int(side) for side in match.groups() if side]
    if not sides or not all(1 <= side <= MAX_SAMPLES for side in sides):
        raise UserError(f"--resolution {text!r}: expected W or WxH, integers in "
                        f"1..{MAX_SAMPLES}")
    return sides[0], sides[-1]


def choice(flag: str, text: str, choices) -> str:
    """``text`` when it is one of ``choices``."""
    if text not in choices:
        raise UserError(f"{flag} {text!r}: expected one of {', '.join(choices)}")
    return text


def option_value(text: str):
    """A builder option from the command line: an int when it is one, else the word."""
    return int(text) if re.fullmatch(r"-?\d+", text.strip()) else text.strip()

