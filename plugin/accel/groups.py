"""The role every group of a :class:`hlbvh.SceneAccel` plays (:class:`Group`): the still
world (:class:`~hlbvh.accel.native_group.NativeGroup` or our static
:class:`~hlbvh.accel.mesh_group.MeshGroup`), the moving meshes' structures
(:mod:`hlbvh.accel.moving`) and the moving instances
(:class:`~hlbvh.accel.instance_group.InstanceGroup`). The accelerator asks a group what
it is through these members, not by its class."""

from __future__ import annotations

from typing import Protocol


class Group(Protocol):
    """What the accelerator reads of a group (each group's ``update`` takes what its
    kind of structure needs, and is called by the code that owns it).

    Attributes:
        name: its name in ``last_update["groups"]``.
        indices: indices into ``scene.shapes()`` of the shapes it traces, ascending.
        native: whether a Mitsuba (sub-)scene traces it (its hits carry Mitsuba's shape
            and instance pointers); otherwise our BVHs do.
        bvh: the BVH of ours it traces through (None for a native group, and while the
            group has no triangles).
        last: what its last update did: ``decision`` (one of
            :data:`hlbvh.accel.policy.DECISIONS`), ``ms``, and what its kind reports.
    """

    name: str
    indices: tuple
    native: bool
    bvh: object
    last: dict

    @property
    def triangles(self) -> int:
        """Triangles of the meshes it traces."""

    @property
    def stale(self) -> bool:
        """Whether its shapes changed since it was built, and it has not followed yet."""

    def keep(self) -> None:
        """Record that an update left it as it was."""
