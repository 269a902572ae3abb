"""A group of a scene's meshes that share one BVH (the static or the dynamic group of
:class:`hlbvh.SceneAccel`), rebuilt or refit as the update policy says, with what its
last update did."""

from __future__ import annotations

import drjit as dr

from hlbvh.accel.groups import Change, MeshUpdate
from hlbvh.accel.policy import RefitOrRebuild
from hlbvh.accel.scene_geometry import collect_geometry, named_build_error
from hlbvh.kernels.arrays import concat
from hlbvh.kernels.build import build
from hlbvh.kernels.bvh import BuildConfig
from hlbvh.kernels.geometry import half_area
from hlbvh.timing import clock_ms


class MeshGroup:
    """Meshes of a scene that share one BVH, and what the last update did to it.

    Args:
        name: what the group is called in statistics (``"static"``, ``"dynamic"``).

    Attributes:
        name: as given.
        indices: indices into ``scene.shapes()`` of the group's meshes, ascending.
        geometry: the :class:`SceneGeometry` of the meshes as last built or refit.
        bvh: the group's :class:`hlbvh.BVH`; None while the group has no triangles.
        built_sah: SAH cost of the group's last build, against which ``"auto"``
            measures a refit tree's drift.
        builds, refits: how often the group was built and refit so far.
        last: what the group's last update did (:class:`~hlbvh.accel.groups.MeshUpdate`;
            its ``ms`` includes the packing of the traversal records, its ``drift`` is
            over ``built_sah``).
    """

    native = False  # our BVH traces it (hlbvh.accel.groups.Group)

    def __init__(self, name: str):
        self.name = name
        self.indices: tuple = ()
        self.geometry = None
        self.bvh = None
        self.built_sah = None
        self.builds = 0
        self.refits = 0
        self.last = None
        self._built_indices = ()  # the meshes the tree was built over
        self._policy = RefitOrRebuild()  # what "auto" remembers of past refits
        self.keep()

    @property
    def triangles(self) -> int:
        return 0 if self.geometry is None else self.geometry.prim_count

    @property
    def stale(self) -> bool:
        """Whether the group's meshes are not those its BVH was built over (they
        changed, and the build that followed failed or has not run yet)."""
        return self.indices != self._built_indices

    def update(self, change: Change):
        """Bring the BVH up to date with the meshes ``change.indices`` when they moved,
        were reshaped (their faces or vertex counts changed) or are not those of the
        last build: built anew (with ``change.config``) when reshaped or not the same
        meshes, otherwise rebuilt or refit as ``change.policy`` says; kept otherwise."""
        self.indices = tuple(change.indices)
        if not (change.moved or change.reshaped or self.stale):
            self.keep()
            return
        start = clock_ms()
        shapes = change.shapes
        reshaped = change.reshaped or self.bvh is None or self.stale
        chosen, seeded, drift = self._policy.update(
            change.policy, reshaped, lambda seed: self._build(shapes, change.config, seed=seed),
            lambda: self._refit(shapes))
        decision = "build" if change.first else "rebuild"
        self.last = MeshUpdate(
            decision=decision if chosen == "rebuild" else chosen, ms=clock_ms() - start,
            triangles=self.triangles, sah_cost=self._sah(), seeded=seeded, drift=drift)

    def release(self):
        """Drop the tree and its geometry while the meshes are traced by another
        structure and have moved since (the tree is out of date, and its next update
        would build anew anyway): their memory is given back. The next update builds."""
        self.geometry, self.bvh, self._built_indices, self.built_sah = None, None, (), None
        self.keep()

    def keep(self):
        """Record that the last update left the group as it was."""
        self.last = MeshUpdate(decision="kept", ms=0.0, triangles=self.triangles,
                               sah_cost=self._sah())

    def _sah(self) -> float | None:
        return None if self.bvh is None else float(self.bvh.stats.sah_cost)

    def root_box(self) -> tuple[list, list]:
        """Lower and upper corner of the BVH's root box, as Python floats."""
        return ([float(c[0]) for c in self.bvh.node_min],
                [float(c[0]) for c in self.bvh.node_max])

    def _build(self, shapes, config: BuildConfig, seed: bool = True) -> bool:
        """A new BVH over the meshes' current triangles, its CSD sort seeded with the
        previous tree's order when ``seed``, the triangle count is unchanged and the
        order pays (:func:`hlbvh.kernels.csd.seed_pays`); whether it was. On failure
        the group is left as it was (and rebuilds on its next update)."""
        previous = self.bvh if seed else None
        geometry = collect_geometry(shapes, self.indices)
        bvh = None
        if geometry.prim_count:
            try:
                bvh = build(geometry.vertices, geometry.faces, previous=previous, config=config)
            except ValueError as error:
                raise named_build_error(shapes, self.indices, error) from error
        self.geometry, self.bvh, self._built_indices = geometry, bvh, self.indices
        self.built_sah = None if bvh is None else bvh.stats.sah_cost
        self.builds += 1
        return bvh is not None and bvh.stats.csd_seeded

    def _refit(self, shapes) -> float:
        """The same tree with boxes for the meshes' new positions; its SAH drift."""
        vertices = concat([shapes[i].vertex_positions_buffer() for i in self.indices])
        try:
            self.bvh.refit(vertices)
        except ValueError as error:
            raise named_build_error(shapes, self.indices, error) from error
        self.geometry.vertices = vertices
        self.refits += 1
        return self.bvh.stats.sah_cost / self.built_sah


def joined_sah_cost(groups: list) -> float | None:
    """SAH cost of the groups' BVHs traced together: each group's SAH cost weighted by
    its root box's area over the area of the box around them (a ray through that box
    enters each group through its root box); None without a group."""
    if len(groups) < 2:
        return float(groups[0].bvh.stats.sah_cost) if groups else None
    boxes = [g.root_box() for g in groups]
    union = _half_area([min(lo[k] for lo, _ in boxes) for k in range(3)],
                       [max(hi[k] for _, hi in boxes) for k in range(3)])
    return sum((_half_area(*box) / union if union > 0 else 1.0) * g.bvh.stats.sah_cost
               for g, box in zip(groups, boxes))


def _half_area(lo, hi) -> float:
    """Half the surface area of the box ``lo``..``hi`` (lists of Python floats), in
    double precision as the SAH cost's areas."""
    extent = dr.maximum(dr.scalar.Array3f64(hi) - dr.scalar.Array3f64(lo), 0.0)
    return float(half_area(extent))
