"""The settings ``hlbvh sweep`` measures (``--settings``, comma separated; default:
every name of :data:`SETTINGS`): their grid, their parsing, and what each asks of
the renderer (:class:`Setting`).

A *setting* is a set of builder options (:class:`hlbvh.BuildConfig`) plus our
accelerator's per-frame ``update`` policy, each varying one knob from the defaults:
``hlbvh`` (the defaults), ``lbvh``, ``sah`` (the builder); ``morton60`` (60-bit keys),
``axis``, ``rank`` (quantisation per axis, or by rank, instead of in a cube);
``coarse6``, ``coarse18`` (``coarse_bits``); ``p1``, ``p5`` (bit planes per emission
pass); ``leaf1``, ``leaf8`` (``leaf_size``); ``rebuild`` (a build every frame, seeded
with last frame's order where that pays), ``fresh`` (the same, unseeded), ``refit``
(refit every frame), ``auto`` (refit while the SAH cost stays near the last build's:
the accelerator's default); ``static_hlbvh`` (``static="hlbvh"``: the still shapes
too in our BVHs and watertight traversal, the accuracy end of the trade; every other
setting leaves them to Mitsuba's accelerator, ``static="native"``); ``moving_native``,
``moving_scene`` and ``moving_auto`` (``moving_accel``: the moving meshes in a Mitsuba
sub-scene rebuilt each frame, the whole scene rebuilt, or the choice by measured cost;
every other setting traces them with our BVH, the one it measures). A setting without
an ``update`` rebuilds every frame, so that the builder settings measure their
builder. A setting may also be spelled out: ``builder=lbvh+leaf_size=8+update=refit``
or ``static=hlbvh+update=auto`` (its label is that text). ``native`` (Mitsuba's own
accelerator) is always measured, as the reference.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from hlbvh.accel.policy import BUILD_OPTIONS, UPDATES
from hlbvh.cli.options import option_value
from hlbvh.errors import UserError
from hlbvh.render.settings import RenderSettings

#: The default grid: each setting varies one knob of the defaults (builder options, and
#: ``update``: our accelerator's per-frame policy).
SETTINGS = {
    "hlbvh": {},
    "lbvh": {"builder": "lbvh"},
    "sah": {"builder": "sah"},
    "morton60": {"morton_bits": 60},
    "axis": {"quantization": "axis"},
    "rank": {"quantization": "rank"},
    "coarse6": {"coarse_bits": 6},
    "coarse18": {"coarse_bits": 18},
    "p1": {"p": 1},
    "p5": {"p": 5},
    "leaf1": {"leaf_size": 1},
    "leaf8": {"leaf_size": 8},
    "rebuild": {"update": "rebuild"},
    "fresh": {"update": "fresh"},
    "refit": {"update": "refit"},
    "auto": {"update": "auto"},
    "static_hlbvh": {"static": "hlbvh", "update": "auto"},
    "moving_native": {"moving_accel": "native"},
    "moving_scene": {"moving_accel": "scene"},
    "moving_auto": {"moving_accel": "auto", "update": "auto"},
}

#: The label of Mitsuba's own accelerator among the rows.
NATIVE = "native"


@dataclass(frozen=True)
class Setting:
    """One point of the sweep.

    Attributes:
        label: its name in tables and plots.
        build_options: options of :func:`hlbvh.build`.
        update: our accelerator's per-frame policy, or ``None`` for a rebuild every frame.
        accel: ``"hlbvh"``, or ``"native"`` for Mitsuba's accelerator.
        static: what traces the still shapes (``"native"`` or ``"hlbvh"``).
        moving_accel: what traces the moving meshes: ``"hlbvh"`` unless the setting
            names another (a builder setting measures our BVH, so the choice by cost
            is not left to pick Mitsuba's for it).
    """

    label: str
    build_options: dict = field(default_factory=dict)
    update: str | None = None
    accel: str = "hlbvh"
    static: str = "native"
    moving_accel: str = "hlbvh"

    def render_settings(self, base: RenderSettings) -> RenderSettings:
        """``base`` with this setting's accelerator, builder options and policy (a
        rebuild every frame when it names none)."""
        update = None if self.accel == NATIVE else (self.update or "rebuild")
        return replace(base, accel=self.accel, build_options=dict(self.build_options),
                       update=update, static=self.static,
                       moving_accel=None if self.accel == NATIVE else self.moving_accel)

    def description(self) -> str:
        """The options as ``key=value`` joined by ``+`` (``defaults`` when none)."""
        options = {**self.build_options, **({"update": self.update} if self.update else {}),
                   **({"static": self.static} if self.static != "native" else {}),
                   **({"moving_accel": self.moving_accel}
                      if self.moving_accel != "hlbvh" else {})}
        return "+".join(f"{k}={v}" for k, v in options.items()) or (
            "Mitsuba's accelerator" if self.accel == NATIVE else "defaults")


def parse_settings(text: str | None) -> list[Setting]:
    """``--settings``: names of :data:`SETTINGS` and spelled-out settings
    (``key=value+key=value``), comma separated; ``None`` for every name of the grid.

    Raises:
        UserError: an unknown name, a malformed or invalid option (naming it), or a
            label given twice.
    """
    if text is None:
        words = list(SETTINGS)
    else:
        words = [word.strip() for word in text.split(",")]
        if not all(words):
            raise UserError(f"--settings {text!r}: expected names or key=value+... separated "
                            "by single commas")
    settings = []
    for word in words:
        if word in SETTINGS:
            options = dict(SETTINGS[word])
        elif "=" in word:
            options = _spelled_out(word)
        else:
            raise UserError(f"--settings: unknown setting {word!r}; expected one of "
                            f"{', '.join(SETTINGS)} or key=value+key=value")
        update = options.pop("update", None)
        static = options.pop("static", "native")
        moving_accel = options.pop("moving_accel", "hlbvh")
        if update is not None and update not in UPDATES:
            raise UserError(f"--settings {word!r}: update={update!r}: expected one of "
                            f"{', '.join(UPDATES)}")
        try:
            RenderSettings(build_options=options, static=static, moving_accel=moving_accel)
        except ValueError as error:
            raise UserError(f"--settings {word!r}: {error}") from None
        settings.append(Setting(word, options, update, static=static, moving_accel=moving_accel))
    labels = [s.label for s in settings]
    twice = sorted({label for label in labels if labels.count(label) > 1})
    if twice:
        raise UserError(f"--settings: {', '.join(twice)} given more than once")
    return settings


#: The accelerator's own options a spelled-out setting may name.
_POLICY_KEYS = ("update", "static", "moving_accel")


def _spelled_out(word: str) -> dict:
    options = {}
    for part in word.split("+"):
        key, _, value = part.partition("=")
        key = key.strip().replace("-", "_")
        if key not in (*BUILD_OPTIONS, *_POLICY_KEYS) or not value.strip():
            raise UserError(f"--settings {word!r}: {part!r} is not key=value with a key among "
                            f"{', '.join((*BUILD_OPTIONS, *_POLICY_KEYS))}")
        options[key] = option_value(value)
    return options
