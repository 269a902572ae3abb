"""The role every group of a :class:`hlbvh.SceneAccel` plays (:class:`Group`): the still
world (:class:`~hlbvh.accel.native_group.NativeGroup` or our static
:class:`~hlbvh.accel.mesh_group.MeshGroup`), the moving meshes' structures
(:mod:`hlbvh.accel.moving`) and the moving instances
(:class:`~hlbvh.accel.instance_group.InstanceGroup`). The accelerator asks a group what
it is through these members, not by its class."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Protocol

from hlbvh.accel.policy import UpdatePolicy
from hlbvh.kernels.bvh import BuildConfig


@dataclass(frozen=True)
class Change:
    """What an update of the accelerator asks of one group (the one argument of
    :meth:`Group.update`); a group that finds nothing to do keeps.

    Attributes:
        shapes: ``scene.shapes()``.
        indices: indices into ``shapes`` of the shapes it traces from now on.
        moved: they moved since its last update (a native group is built anew, a BVH
            refit or rebuilt as ``policy`` says).
        reshaped: their faces or vertex counts changed (a BVH must be built anew).
        first: the accelerator's first update (a build is called ``"build"``).
        policy: the accelerator's :class:`~hlbvh.accel.policy.UpdatePolicy`.
        config: the builder config of its BVHs (a mesh group's; others keep theirs).
        left: ids of the shapes that moved out of it (said in its record).
    """

    shapes: list
    indices: tuple
    moved: bool = False
    reshaped: bool = False
    first: bool = False
    policy: UpdatePolicy = field(default_factory=UpdatePolicy)
    config: BuildConfig | None = None
    left: tuple = ()


@dataclass(frozen=True)
class GroupUpdate:
    """What one update did to a group (its :attr:`Group.last`).

    Attributes:
        decision: one of :data:`hlbvh.accel.policy.DECISIONS`.
        ms: wall time of the update, device synchronised.
        triangles: triangles of the meshes it traces after the update.
        sah_cost: its tree's SAH cost after the update (None without one of ours).
    """

    decision: str
    ms: float
    triangles: int
    sah_cost: float | None = None

    def as_dict(self) -> dict:
        """The record as a plain dict (``last_update["groups"][name]``)."""
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class MeshUpdate(GroupUpdate):
    """A :class:`~hlbvh.accel.mesh_group.MeshGroup`'s update.

    Attributes:
        seeded: a build whose CSD sort started from the previous tree's order.
        drift: a refit tree's SAH cost over its last build's (None without a refit).
    """

    seeded: bool = False
    drift: float | None = None


@dataclass(frozen=True)
class NativeUpdate(GroupUpdate):
    """A :class:`~hlbvh.accel.native_group.NativeGroup`'s update (``sah_cost`` None:
    Mitsuba's tree does not say).

    Attributes:
        shapes: how many shapes it traces.
        left: ids of the shapes whose motion made this update rebuild it.
        groups_changed: ids of the shape groups whose shapes changed, which made this
            update rebuild it.
    """

    shapes: int = 0
    left: list = field(default_factory=list)
    groups_changed: list = field(default_factory=list)


@dataclass(frozen=True)
class InstanceUpdate(GroupUpdate):
    """An :class:`~hlbvh.accel.instance_group.InstanceGroup`'s update (``sah_cost``:
    its top level's).

    Attributes:
        instances: how many moving instances it traces.
        groups: how many shape groups they use.
        drift: the top level's refit drift (None without a refit).
        groups_rebuilt: ids of the shape groups whose own shapes changed, their BVHs
            built again.
    """

    instances: int = 0
    groups: int = 0
    drift: float | None = None
    groups_rebuilt: list = field(default_factory=list)


class Group(Protocol):
    """What the accelerator reads of a group, and the one way it brings a group up to
    date (:meth:`update`).

    Attributes:
        name: its name in ``last_update["groups"]``.
        indices: indices into ``scene.shapes()`` of the shapes it traces, ascending.
        native: whether a Mitsuba (sub-)scene traces it (its hits carry Mitsuba's shape
            and instance pointers); otherwise our BVHs do.
        bvh: the BVH of ours it traces through (None for a native group, and while the
            group has no triangles).
        last: what its last update did (a :class:`GroupUpdate` of its kind).
    """

    name: str
    indices: tuple
    native: bool
    bvh: object
    last: GroupUpdate

    @property
    def triangles(self) -> int:
        """Triangles of the meshes it traces."""

    @property
    def stale(self) -> bool:
        """Whether its shapes changed since it was built, and it has not followed yet."""

    def update(self, change: Change) -> None:
        """Trace ``change.indices`` as they are now: build, rebuild or refit what the
        change asks for, keep (:meth:`keep`) when it asks for nothing; record it in
        :attr:`last`."""

    def keep(self) -> None:
        """Record that an update left it as it was."""
