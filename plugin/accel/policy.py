"""What a user chooses for an accelerator: which one (``ACCELS``), and how it follows
the scene from frame to frame (:class:`UpdatePolicy`), with the builder's options
beside it; :func:`split_options` parses a mixed dict of both, once, into typed
objects (naming a bad option), which are then passed down."""

from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass

from hlbvh.kernels.bvh import BUILDERS, BuildConfig, integer_option

ACCELS = ("hlbvh", "native")
#: What traces the shapes that do not move (option ``static``): ``"native"``, the scene's
#: own accelerator (Embree on LLVM, OptiX on CUDA) over a sub-scene of those shapes,
#: built once; ``"hlbvh"``, our BVH and watertight traversal for every mesh.
STATICS = ("native", "hlbvh")
#: What traces the moving meshes (option ``moving_accel``): ``"auto"`` picks per render
#: by measured cost among the three others (:mod:`hlbvh.accel.choice`); ``"hlbvh"``, our
#: HLBVH refit or rebuilt; ``"native"``, a Mitsuba sub-scene of the moving meshes built
#: anew when they change; ``"scene"``, the whole scene through Mitsuba's own accelerator,
#: rebuilt when anything moves.
MOVING_ACCELS = ("auto", "hlbvh", "native", "scene")
#: Per-frame policies of :meth:`SceneAccel.update` (option ``update``).
UPDATES = ("rebuild", "fresh", "refit", "auto")
#: The options of :func:`hlbvh.build` an accelerator accepts.
BUILD_OPTIONS = tuple(f.name for f in dataclasses.fields(BuildConfig))
#: The accelerator's own options (:class:`UpdatePolicy`).
UPDATE_OPTIONS = ("update", "refit_tolerance", "static", "moving", "static_builder",
                  "static_leaf_size", "moving_accel")
#: The static tree's leaf size with the "sah" builder under ``static_leaf_size="auto"``.
STATIC_SAH_LEAF_SIZE = 2
#: What an update did to a group, from the least work to the most: ``kept`` (nothing
#: changed), ``refit``, ``rebuild``, ``build`` (the accelerator's first build).
DECISIONS = ("kept", "refit", "rebuild", "build")


@dataclass
class UpdatePolicy:
    """What traces the shapes that do not move, which shapes move from the start, and
    how :meth:`SceneAccel.update` brings the dynamic group up to date when only its
    meshes' vertex positions changed (new faces or vertex counts always rebuild).

    Attributes:
        update: ``"auto"`` (default): refit, then rebuild if the refit tree's SAH
            cost exceeds ``refit_tolerance`` times the SAH cost of the group's last
            build; after 2, 3, 4, 5 refits rejected in a row it rebuilds straight away
            for 1, 3, 7, then 15 updates, so a scene that never refits well does not
            pay a refit every frame. ``"rebuild"``: a new BVH every update, its CSD sort
            seeded with last frame's order (temporal coherence) where that pays;
            always the best tree. ``"fresh"``: the same without the seed (temporal
            reuse off, for comparison). ``"refit"``: the tree of the last build with
            new boxes (:meth:`hlbvh.BVH.refit`), much cheaper, never wrong, but slower
            to trace as the geometry moves away from the pose it was built for.
        refit_tolerance: the drift ``"auto"`` accepts, a number >= 1 (default 1.05;
            looser tolerances let refit trees trace measurably slower).
        static: ``"native"`` (default): shapes that have not moved are traced by the
            scene's own accelerator (Embree on LLVM, OptiX on CUDA), any shape type
            included, and only the moving meshes by hlbvh: the fastest images.
            ``"hlbvh"``: every mesh in our BVHs, traced by our watertight traversal (no
            ray slips between two triangles sharing an edge, also at extreme
            coordinates, where Embree's test may miss), the analytic shapes by their own
            routine; instances, curves and the like are refused.
        moving: ids of shapes that will move (a tuple of str, or one str of ids
            separated by commas or spaces): they are in the dynamic group from the
            first build, so their first motion does not rebuild the static structure
            without them. Unknown ids are refused, naming them.
        static_builder: with ``static="hlbvh"``, the builder of the static group once
            meshes have moved out of it (``"sah"`` by default: it is built once and
            traced every frame, so the best tree pays), or ``"same"`` for the scene's
            own builder.
        static_leaf_size: the most triangles in a leaf of that static tree: ``"auto"``
            (default: 2 with the ``"sah"`` static builder, whose trees trace faster
            with leaves of 2, while ``"hlbvh"`` trees trace slower with them; otherwise
            the scene's ``leaf_size``), ``"same"`` (the scene's ``leaf_size``) or an
            int in 1..16.
        moving_accel: what traces the moving meshes with ``static="native"`` (one of
            :data:`MOVING_ACCELS`): ``"auto"`` (default) chooses, per render, the one
            whose update and rays cost least for that render's film, samples and depth
            (:mod:`hlbvh.accel.choice`); the others force it. With ``static="hlbvh"``
            every mesh is ours: only ``"auto"`` and ``"hlbvh"`` are accepted.

    The defaults' measurements (frame times of each policy, the static tree's builder
    and leaf size) are in docs/decisions.md#update-policy and
    docs/decisions.md#static-leaf-size.
    """

    update: str = "auto"
    refit_tolerance: float = 1.05
    static: str = "native"
    moving: tuple = ()
    static_builder: str = "sah"
    static_leaf_size: int | str = "auto"
    moving_accel: str = "auto"

    def validated(self) -> "UpdatePolicy":
        """Self, after checking every field; raises ValueError naming the bad one."""
        if self.update not in UPDATES:
            raise ValueError(f"update={self.update!r}: expected one of {UPDATES}")
        tolerance = self.refit_tolerance
        if (isinstance(tolerance, (bool, str)) or not isinstance(tolerance, numbers.Real)
                or not math.isfinite(tolerance) or tolerance < 1):
            raise ValueError(
                f"refit_tolerance={tolerance!r}: expected a finite number >= 1 (the SAH "
                "cost a refit tree may reach, relative to a fresh build's)"
            )
        self.refit_tolerance = float(tolerance)
        if self.static not in STATICS:
            raise ValueError(f"static={self.static!r}: expected one of {STATICS}")
        if self.moving_accel not in MOVING_ACCELS:
            raise ValueError(
                f"moving_accel={self.moving_accel!r}: expected one of {MOVING_ACCELS}")
        if self.static == "hlbvh" and self.moving_accel not in ("auto", "hlbvh"):
            raise ValueError(
                f"moving_accel={self.moving_accel!r} with static='hlbvh': every mesh is "
                "traced by our BVH there; use static='native' to trace moving meshes "
                "natively")
        self.moving = _shape_ids(self.moving)
        if self.static_builder not in BUILDERS + ("same",):
            raise ValueError(
                f"static_builder={self.static_builder!r}: expected one of {BUILDERS + ('same',)}"
            )
        if self.static_leaf_size not in ("auto", "same"):
            self.static_leaf_size = integer_option(
                "static_leaf_size", self.static_leaf_size, range(1, 17),
                "'auto', 'same' or an int in 1..16")
        return self

    def static_config(self, config: BuildConfig) -> BuildConfig:
        """The builder config of the static group's tree, from the scene's
        ``config``."""
        builder = config.builder if self.static_builder == "same" else self.static_builder
        leaf_size = config.leaf_size
        if self.static_leaf_size == "auto":
            if builder == "sah":
                leaf_size = STATIC_SAH_LEAF_SIZE
        elif self.static_leaf_size != "same":
            leaf_size = self.static_leaf_size
        return dataclasses.replace(config, builder=builder, leaf_size=leaf_size)


def _shape_ids(value) -> tuple:
    """``moving`` as a tuple of ids: from one string (ids separated by commas or
    spaces, as an XML property gives them) or a sequence of strings."""
    if isinstance(value, str):
        return tuple(part for part in value.replace(",", " ").split() if part)
    if isinstance(value, (list, tuple, set, frozenset)) and all(isinstance(v, str) for v in value):
        return tuple(dict.fromkeys(value))
    raise ValueError(f"moving={value!r}: expected shape ids, as a tuple of str or one str "
                     "of ids separated by commas")


def split_options(options: dict) -> tuple[UpdatePolicy, BuildConfig]:
    """The update policy and the builder's config among an accelerator's options,
    both validated (the one place they are).

    Args:
        options: keyword options: :data:`UPDATE_OPTIONS` and :data:`BUILD_OPTIONS`.
    Returns:
        ``(UpdatePolicy, BuildConfig)``.
    Raises:
        ValueError: an unknown option or a bad value, naming it.
    """
    known = BUILD_OPTIONS + UPDATE_OPTIONS
    unknown = sorted(set(options) - set(known))
    if unknown:
        raise ValueError(
            f"unknown accelerator option(s) {unknown}: expected some of {sorted(known)}"
        )
    policy = UpdatePolicy(**{k: v for k, v in options.items() if k in UPDATE_OPTIONS})
    config = BuildConfig.from_options(
        **{k: v for k, v in options.items() if k not in UPDATE_OPTIONS})
    return policy.validated(), config


#: Most updates in a row that ``"auto"`` rebuilds without trying a refit first.
MAX_REFITS_SKIPPED = 15


class RefitOrRebuild:
    """What :class:`UpdatePolicy` decides for one tree, update after update, with the
    memory ``"auto"`` keeps (refits rejected in a row, refits to skip after them).
    Used by the mesh groups' BVHs and by the instances' top level."""

    def __init__(self):
        self._rejected = self._refits_to_skip = self._refits_skipped = 0

    def update(self, policy: UpdatePolicy, must_build: bool, build, refit) -> tuple:
        """Build or refit the tree as ``policy`` says: ``build(seed)`` (a new tree,
        seeded with the last one's order when ``seed``; returns whether the seed was
        used), ``refit()`` (the same tree with new boxes; returns its SAH cost over its
        last build's). ``must_build``: a refit cannot follow (new primitives, a first
        build).

        Returns:
            ``(decision, seeded, drift)``: ``"rebuild"`` or ``"refit"``, whether a build
            was seeded, a refit's drift (None without a refit).
        """
        if must_build or policy.update in ("rebuild", "fresh"):
            return "rebuild", build(policy.update != "fresh"), None
        if policy.update == "auto" and self._refits_skipped < self._refits_to_skip:
            # Recent refits drifted past the tolerance: rebuild without trying one.
            self._refits_skipped += 1
            return "rebuild", build(True), None
        drift = refit()
        rejected = policy.update == "auto" and drift > policy.refit_tolerance
        self._back_off(rejected)
        return ("rebuild", build(True), drift) if rejected else ("refit", False, drift)

    def _back_off(self, rejected: bool):
        """After ``k >= 2`` refits in a row drifted past the tolerance, skip the next
        ``2**(k-1) - 1`` refits (at most :data:`MAX_REFITS_SKIPPED`): a scene whose every
        refit is rejected (bodies tumbling apart) pays a wasted refit only now and then,
        one whose refits are rejected now and then (a slow drift) is not held back, and
        one that settles is refit again soon. An accepted refit resets the count."""
        self._rejected = self._rejected + 1 if rejected else 0
        self._refits_to_skip = min(2 ** max(self._rejected - 1, 0) - 1, MAX_REFITS_SKIPPED)
        self._refits_skipped = 0
