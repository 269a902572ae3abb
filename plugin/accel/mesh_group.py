"""A group of a scene's meshes that share one BVH (the static or the dynamic group of
:class:`hlbvh.SceneAccel`), rebuilt or refit as the update policy says, with what its
last update did."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from hlbvh.accel.groups import Change, MeshUpdate
from hlbvh.accel.keys import motion_keys
from hlbvh.accel.policy import RefitOrRebuild, UpdatePolicy
from hlbvh.accel.scene_geometry import collect_geometry, named_build_error
from hlbvh.kernels.arrays import concat
from hlbvh.kernels.build import build
from hlbvh.kernels.bvh import BuildConfig
from hlbvh.kernels.geometry import half_area
from hlbvh.kernels.keyed import build_keyed
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
            over ``built_sah``; a keyed group's ``sah_cost`` is its SAH over the
            shutter and its ``drift`` that over the still tree's at mid-shutter,
            :attr:`hlbvh.kernels.keyed.KeyedTree.degradation`).
        keyed: where a mesh of the group has motion keys
            (:func:`hlbvh.accel.keys.set_motion_keys`), the group's
            :class:`~hlbvh.kernels.keyed.KeyedTree` (built over the mid-shutter pose,
            refit per key; the meshes without keys the same at every key), else None.
        shutter: the keys' ``(open, close)`` while ``keyed``.
        key_points: the group's vertices at each key, in one flat Float (key ``k``'s
            3·V values from ``k·3·V``), while ``keyed``: where shading reads a hit's
            triangle at its time.
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
        self.keyed = self.shutter = self.key_points = None
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
        keys = [motion_keys(shapes[i]) for i in self.indices]
        if any(keys):
            self._build_keyed(shapes, keys, change.config, change.policy)
            self.last = MeshUpdate(decision="build" if change.first else "rebuild",
                                   ms=clock_ms() - start, triangles=self.triangles,
                                   sah_cost=self.traced_sah(), drift=self.keyed.degradation)
            return
        self.keyed = self.shutter = self.key_points = None
        reshaped = change.reshaped or self.bvh is None or self.stale
        chosen, seeded, drift = self._policy.update(
            change.policy, reshaped, lambda seed: self._build(shapes, change.config, seed=seed),
            lambda: self._refit(shapes))
        decision = "build" if change.first else "rebuild"
        self.last = MeshUpdate(
            decision=decision if chosen == "rebuild" else chosen, ms=clock_ms() - start,
            triangles=self.triangles, sah_cost=self.traced_sah(), seeded=seeded, drift=drift)

    def release(self):
        """Drop the tree and its geometry while the meshes are traced by another
        structure and have moved since (the tree is out of date, and its next update
        would build anew anyway): their memory is given back. The next update builds."""
        self.geometry, self.bvh, self._built_indices, self.built_sah = None, None, (), None
        self.keyed = self.shutter = self.key_points = None
        self.keep()

    def keep(self):
        """Record that the last update left the group as it was."""
        self.last = MeshUpdate(decision="kept", ms=0.0, triangles=self.triangles,
                               sah_cost=self.traced_sah())

    def traced_sah(self) -> float | None:
        """The SAH cost of what the group traces: a keyed tree's over the shutter (a ray
        at a uniform time in it), else the tree's."""
        if self.keyed is not None:
            return self.keyed.sah
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

    def _build_keyed(self, shapes, keys: list, config: BuildConfig, policy: UpdatePolicy):
        """A keyed tree over the meshes' keys: built over the mid-shutter pose, refit
        per key (:func:`hlbvh.kernels.keyed.build_keyed`); a mesh without keys is at
        its positions at every key. Every mesh with keys must have the same number of
        keys over the same shutter (one tree, one time per ray).

        Under the ``"auto"`` policy, a mid-shutter tree whose SAH over the shutter
        passes ``refit_tolerance`` times the still tree's (the drift ``"auto"`` accepts
        of a refit tree) is built again over the triangles' boxes over the shutter
        with the ``"sah"`` builder, the better kept (``topology="auto"``); the other
        policies keep the mid-shutter tree."""
        given = [k for k in keys if k is not None]
        first = given[0]
        for i, k in zip(self.indices, keys):
            if k is not None and (k.count, k.shutter) != (first.count, first.shutter):
                raise ValueError(
                    f"mesh {shapes[i].id()!r}: {k.count} motion keys over shutter "
                    f"{k.shutter}, another moving mesh {first.count} over {first.shutter}: "
                    "give every moving mesh the same keys' times")
        geometry = collect_geometry(shapes, self.indices)
        points = [concat([k.points[j] if k is not None else shapes[i].vertex_positions_buffer()
                          for i, k in zip(self.indices, keys)]) for j in range(first.count)]
        try:
            keyed = build_keyed(points, geometry.faces, config=config,
                                topology="auto" if policy.update == "auto" else "mid",
                                tolerance=policy.refit_tolerance)
        except ValueError as error:
            raise named_build_error(shapes, self.indices, error) from error
        self.geometry, self.keyed, self.bvh = geometry, keyed, keyed.bvh
        self.shutter, self.key_points = first.shutter, mi.Float(concat(points))
        self._built_indices, self.built_sah = self.indices, keyed.bvh.stats.sah_cost
        self.builds += 1
        dr.eval(self.key_points)

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
    """SAH cost of the groups' BVHs traced together: each group's SAH cost (a keyed
    group's over the shutter) weighted by its root box's area over the area of the box
    around them (a ray through that box enters each group through its root box); None
    without a group."""
    if len(groups) < 2:
        return groups[0].traced_sah() if groups else None
    boxes = [g.root_box() for g in groups]
    union = _half_area([min(lo[k] for lo, _ in boxes) for k in range(3)],
                       [max(hi[k] for _, hi in boxes) for k in range(3)])
    return sum((_half_area(*box) / union if union > 0 else 1.0) * g.traced_sah()
               for g, box in zip(groups, boxes))


def _half_area(lo, hi) -> float:
    """Half the surface area of the box ``lo``..``hi`` (lists of Python floats), in
    double precision as the SAH cost's areas."""
    extent = dr.maximum(dr.scalar.Array3f64(hi) - dr.scalar.Array3f64(lo), 0.0)
    return float(half_area(extent))
