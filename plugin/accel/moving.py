"""The moving meshes of a :class:`hlbvh.SceneAccel` and the structures that can trace
them: our HLBVH (:class:`MeshGroup`), a Mitsuba sub-scene of them (:class:`NativeGroup`),
or the whole scene through Mitsuba's own accelerator; which one traces them now, which
fell behind while another did, and the measured costs that choose among them
(:mod:`hlbvh.accel.choice`)."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from hlbvh.accel.choice import STRUCTURES, CostModel, RayBudget
from hlbvh.accel.groups import Change
from hlbvh.accel.mesh_group import MeshGroup
from hlbvh.accel.native_group import NativeGroup


#: Refits :meth:`MovingMeshes.measure_ours` makes to time one as a frame makes it.
MEASURED_REFITS = 3

#: The least share of the scene's mesh triangles that must stay still for the native
#: moving group to be a candidate: below it, its build is nearly the whole scene's while
#: every ray queries two structures instead of one, so the whole scene is the better
#: Mitsuba structure.
NATIVE_MIN_STILL_SHARE = 0.1


class MovingMeshes:
    """The moving meshes' structures and the choice among them.

    Args:
        moving_accel: the policy's ``moving_accel`` (``"auto"`` or a forced structure).
        choosable: whether the still world is Mitsuba's (``static="native"``): only then
            may anything but our HLBVH trace the moving meshes.
    Raises:
        ValueError: ``"native"`` forced where it cannot be traced
            (:func:`native_moving_possible`).

    Attributes:
        ours: our HLBVH's :class:`MeshGroup` (``"dynamic"`` in statistics).
        native: the Mitsuba sub-scene's :class:`NativeGroup` (``"native_moving"``).
        structure: what traces them now, one of :data:`hlbvh.accel.choice.STRUCTURES`.
        costs: the :class:`hlbvh.accel.choice.CostModel`.
        estimates: each structure's estimated frame at the last :meth:`plan` (None
            before one).
        probed: whether the probe timed the structures' queries.
        instances: whether the scene has moving instances (set by the accelerator):
            the choice is then between our top level and the whole scene too.
        still_share: the share of the scene's mesh triangles not in moving meshes (set
            by the accelerator; see :data:`NATIVE_MIN_STILL_SHARE`).
    """

    def __init__(self, moving_accel: str, choosable: bool):
        if moving_accel == "native" and not native_moving_possible():
            raise ValueError(
                "moving_accel='native': a second Mitsuba scene traced in the same kernel as "
                "the still world's is refused by OptiX on CUDA; use 'scene', 'hlbvh' or "
                "'auto' there")
        self.ours = MeshGroup("dynamic")
        self.native = NativeGroup([], name="native_moving")
        self.structure = moving_accel if moving_accel in ("native", "scene") else "hlbvh"
        self.costs = CostModel()
        self.estimates = None
        self.probed = False
        self.instances = False
        self.still_share = 1.0
        # Whether the whole scene's accelerator was rebuilt by us once (before that, the
        # writes it misses may predate this object's record of motion)
        self.scene_rebuilt_once = False
        # Whether a moving mesh has motion keys this frame (hlbvh.accel.keys): only our
        # HLBVH traces a ray at its time, Mitsuba's structures have one pose
        self.keyed = False
        self._forced = moving_accel
        # Whether our update's cost is a build's (first or catch-up), not a frame's
        self._ours_from_build = False
        self._choosable = choosable
        # Structures whose view of the moving meshes is out of date: the scene's own
        # accelerator may predate writes made before the accelerator existed.
        self._behind = {"scene"}

    @property
    def indices(self) -> tuple:
        """Indices into ``scene.shapes()`` of the moving meshes, ascending."""
        return self.ours.indices

    def allowed(self) -> tuple:
        """The structures :meth:`plan` chooses among (moving instances alone, or moving
        meshes that are nearly the whole scene: ours or the whole scene)."""
        if self._forced != "auto" or self.keyed:
            return ("hlbvh",) if self.keyed else (self._forced,)
        if not self._choosable:
            return ("hlbvh",)
        if (not native_moving_possible() or not self.indices
                or self.still_share < NATIVE_MIN_STILL_SHARE):
            return ("hlbvh", "scene")
        return STRUCTURES

    def fell_behind(self, meshes_moved: bool, anything_moved: bool):
        """Record what a frame's motion leaves behind: the structures not updated this
        frame when the moving meshes moved, the whole scene when anything did."""
        if meshes_moved:
            self._behind |= {"hlbvh", "native"} - {self.structure}
        if anything_moved:
            self._behind.add("scene")

    def update(self, shapes, states: dict, before: dict | None, changed: list, config,
               policy):
        """Bring the structure that traces the moving meshes up to date (``changed``: the
        moving meshes whose state differs from ``before``, the last update's states;
        ``before`` None at the first update); the others keep. Moving meshes with
        motion keys go through ours, whatever traced them before."""
        if self.keyed:
            if self._forced not in ("auto", "hlbvh"):
                raise ValueError(
                    f"moving_accel={self._forced!r}: a moving mesh has motion keys (an "
                    "open shutter), which only our HLBVH traces at each ray's time; use "
                    "'hlbvh' or 'auto'")
            self.structure = "hlbvh"
        if self.structure == "hlbvh":
            self.update_ours(shapes, states, before, changed, config, policy)
        elif "hlbvh" in self._behind:
            self.ours.release()  # out of date: a switch back builds anew anyway
        else:
            self.ours.keep()
        if self.structure == "native":
            self.update_native(shapes, moved=bool(changed))
        else:
            self.native.keep()

    def update_ours(self, shapes, states, before, changed, config, policy):
        """Our HLBVH over the moving meshes, refit or rebuilt as the policy says (rebuilt
        when it fell behind while another structure traced them)."""
        first = before is None
        behind = "hlbvh" in self._behind
        group = self.ours
        moved = bool((first and group.indices) or changed or behind)
        reshaped = moved and (first or behind or any(states[i].reshaped(before[i])
                                                     for i in changed))
        group.update(Change(shapes, group.indices, moved=moved, reshaped=reshaped, first=first,
                            policy=policy, config=config))
        if group.last.decision != "kept" and group.indices:
            # a frame's update as the policy makes it; a first or catch-up build (which
            # compiles, often) only until one is measured, then replaced, not averaged in
            if not (first or behind):
                if self._ours_from_build:
                    # the first update after a build runs the refit's kernels for the
                    # first time (compiled on a cold cache: 300 ms for 5): timed again
                    self.costs.update_ms["hlbvh"] = group.last.ms
                    self.measure_ours(shapes, config, policy)
                else:
                    self.costs.record_update("hlbvh", group.last.ms)
                self._ours_from_build = False
            elif "hlbvh" not in self.costs.update_ms:
                self.costs.record_update("hlbvh", group.last.ms)
                self._ours_from_build = True
        self._behind.discard("hlbvh")

    def measure_ours(self, shapes, config, policy):
        """Take as our HLBVH's update cost what a frame's refit of it costs, timed on the
        tree just built (the last of :data:`MEASURED_REFITS` refits over the meshes as
        they are: the first compiles, the first two allocate their buffers). The build
        that made the tree, often the accelerator's first, compiles too and is no
        frame's cost, yet it is all that is known of a structure the choice has not
        used; so does the first frame's refit on a cold kernel cache. Only under
        ``"auto"`` and ``"refit"``, whose frames refit, and only right after a build or
        a frame's update, where a refit of the same positions gives the same boxes and
        is accepted: the tree and what the policy remembers stay as they were."""
        group = self.ours
        if (group.bvh is None or policy.update not in ("auto", "refit")
                or group.last.decision not in ("build", "rebuild", "refit")):
            return
        built = group.last
        for _ in range(MEASURED_REFITS):
            group.update(Change(shapes, group.indices, moved=True, policy=policy,
                                config=config))
        self.costs.update_ms["hlbvh"] = group.last.ms
        self._ours_from_build = False
        group.last = built

    def update_native(self, shapes, moved: bool = False):
        """The Mitsuba sub-scene of the moving meshes, built anew when they ``moved`` (or
        moved while another structure traced them)."""
        self.native.update(Change(shapes, self.indices, moved=moved or "native" in self._behind))
        if self.native.last.decision != "kept" and self.indices:
            self.costs.record_update("native", self.native.last.ms)
        self._behind.discard("native")

    def plan(self, budget: RayBudget, shapes) -> str:
        """Choose the structure for a render of ``budget`` by the measured costs; returns
        it."""
        allowed = self.allowed()
        if len(allowed) == 1:
            self.structure = allowed[0]
        elif self.indices or self.instances:
            self.structure, self.estimates = self.costs.choose(
                budget, self.structure, allowed, self._triangles(shapes))
        return self.structure

    def needs_probe(self, budget: RayBudget, shapes) -> bool:
        """Whether :meth:`plan` wants a probe for a render of ``budget``: a choice among
        several structures, moving meshes to trace, no probe yet, and one that could
        move the choice (:meth:`CostModel.worth_probing`)."""
        allowed = self.allowed()
        return (not self.probed and len(allowed) > 1 and bool(self.indices or self.instances)
                and self.costs.worth_probing(budget, self.structure, allowed,
                                             self._triangles(shapes)))

    def _triangles(self, shapes) -> dict:
        """The triangles each Mitsuba structure rebuilds: ``"native"`` the moving
        meshes', ``"scene"`` the whole scene's."""
        return {"native": sum(shapes[i].face_count() for i in self.indices),
                "scene": sum(s.face_count() for s in shapes if s.is_mesh())}

    def behind(self, structure: str) -> bool:
        """Whether ``structure`` misses motion since it last traced the moving meshes."""
        return structure in self._behind

    @property
    def scene_behind(self) -> bool:
        """Whether the scene's own accelerator misses motion since its last rebuild."""
        return self.behind("scene")

    def scene_rebuilt(self, ms: float, ns: float | None = None):
        """The whole scene's accelerator was rebuilt in ``ms``; ``ns``: a query's time
        through it, when timed."""
        self.costs.record_update("scene", ms)
        self._behind.discard("scene")
        self.scene_rebuilt_once = True
        if ns is not None:
            self.costs.record_queries("scene", ns)

    def record(self) -> dict:
        """What ``last_update["moving_accel"]`` says: the choice and its costs."""
        return dict(chosen=self.structure, estimates_ms=self.estimates,
                    update_ms=dict(self.costs.update_ms), query_ns=dict(self.costs.query_ns),
                    hit_fractions=self.costs.hit_fractions)


def native_moving_possible() -> bool:
    """Whether the moving meshes can have a Mitsuba sub-scene of their own beside the
    still world's: a kernel traces one OptiX scene at most (Dr.Jit disables the queries
    of a second, leaving rays unanswered), so not on CUDA; Embree takes any number."""
    return dr.backend_v(mi.Float) != dr.JitBackend.CUDA


def still_share(shapes, moving: tuple) -> float:
    """The share of the mesh triangles of ``shapes`` outside the meshes ``moving`` (1.0
    without meshes)."""
    total = sum(s.face_count() for s in shapes if s.is_mesh())
    return 1.0 - sum(shapes[i].face_count() for i in moving) / total if total else 1.0
