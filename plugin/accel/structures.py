"""The structures a :class:`hlbvh.SceneAccel` query asks, each behind the same two
queries (pbrt's ``Intersect`` and ``IntersectP``):

- ``closest(ray, active, hit, coherent, reorder)``: narrow ``ray.maxt`` to how far the
  nearest hit so far reaches (:meth:`NearestHit.reach`: past it by the tie tolerance,
  so a hit that ties is still seen), trace, and merge this structure's hit into ``hit``
  (:meth:`NearestHit.take` or :meth:`~NearestHit.take_native`, where the one tie rule
  lives);
- ``occluded(ray, active, coherent)``: whether anything of the structure lies on the
  ray within ``ray.maxt`` (``active``: the lanes still unoccluded).

``coherent`` and ``reorder`` (``(reorder, reorder_hint, reorder_hint_bits)``) are
Mitsuba's hints, handed to the structures Mitsuba traces; our traversal traces coherent
and incoherent rays alike, and each analytic shape's own routine takes no hints.

:func:`scene_structures` lists them in the order queries ask them: the still world's
Mitsuba sub-scene, our joined BVHs, the keyed group (traced at each ray's time), the
moving meshes' Mitsuba sub-scene, the instances' two-level tree, the analytic shapes'
own routines. A structure holds its group, not a copy of its arrays: it answers from
the group as the last update left it.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from hlbvh.kernels.arrays import concat
from hlbvh.kernels.layout import joined
from hlbvh.kernels.traversal import any_hit, closest_hit, closest_instance_hit


class SubScene:
    """A Mitsuba sub-scene of shapes (a :class:`~hlbvh.accel.native_group.NativeGroup`:
    the still world, or the moving meshes' native group), traced by Mitsuba's own
    accelerator; its hits keep Mitsuba's shape and instance pointers."""

    def __init__(self, group):
        self.group = group

    def closest(self, ray, active, hit, coherent, reorder):
        ray.maxt = hit.reach(ray.maxt)
        hit.take_native(self.group.preliminary(ray, coherent, active, reorder))

    def occluded(self, ray, active, coherent) -> mi.Bool:
        return self.group.test(ray, coherent, active)


class MeshTree:
    """Our traversal slots over meshes' triangles, with each face index's mesh (index
    into ``scene.shapes()``) and in-mesh index: our still groups' BVHs joined into one
    tree (:meth:`joined_groups`), or a keyed group's tree traced at each ray's time
    (:meth:`keyed_group`, motion blur of deforming meshes)."""

    def __init__(self, tree, prim_shape: mi.UInt32, prim_local: mi.UInt32, shutter=None):
        self.tree, self.prim_shape, self.prim_local = tree, prim_shape, prim_local
        self.shutter = shutter  # (open, close) of the keys; None: a tree without time

    @classmethod
    def joined_groups(cls, groups: list) -> "MeshTree":
        """One tree over ``groups``' BVHs, in their order (the static group first: its
        slots stay cached while the dynamic group changes), packed now, not inside some
        integrator's symbolic loop."""
        return cls(joined([g.bvh for g in groups]),
                   concat([g.geometry.prim_shape for g in groups]),
                   concat([g.geometry.prim_local for g in groups]))

    @classmethod
    def keyed_group(cls, group) -> "MeshTree":
        """The tree of ``group``, a mesh group with motion keys, at each ray's time."""
        return cls(group.keyed, group.geometry.prim_shape, group.geometry.prim_local,
                   group.shutter)

    def time(self, ray) -> mi.Float | None:
        """``ray.time`` normalised to the keys' shutter (0 at open, 1 at close); None
        for a tree without time."""
        if self.shutter is None:
            return None
        open_, close = self.shutter
        return (ray.time - open_) * (1.0 / (close - open_))

    def closest(self, ray, active, hit, coherent, reorder):
        ray.maxt = hit.reach(ray.maxt)
        t, u, v, prim, valid = closest_hit(self.tree, ray.o, ray.d, ray.maxt, active,
                                           time=self.time(ray))
        valid, prim = mi.Bool(valid), mi.UInt32(prim)
        hit.take(*_distance_and_uv(t, u, v, valid),
                 dr.gather(mi.UInt32, self.prim_local, prim, valid),
                 dr.gather(mi.UInt32, self.prim_shape, prim, valid))

    def occluded(self, ray, active, coherent) -> mi.Bool:
        return mi.Bool(any_hit(self.tree, ray.o, ray.d, ray.maxt, active,
                               time=self.time(ray)))


class InstanceTree:
    """The moving instances' two-level tree (an
    :class:`~hlbvh.accel.instance_group.InstanceGroup`): our top level over them, a ray
    entering an instance traced through its group's BVH; a hit reports the shape's
    index in its group and the instance's index into ``scene.shapes()``. Instances with
    keys over the shutter are entered at their pose at each ray's time."""

    def __init__(self, group):
        self.group = group

    def time(self, ray) -> mi.Float | None:
        """``ray.time`` normalised to the instances' keys' shutter (0 at open, 1 at
        close); None when no instance has keys."""
        motion = self.group.tree.motion
        return None if motion is None else motion.time(ray.time)

    def closest(self, ray, active, hit, coherent, reorder):
        ray.maxt = hit.reach(ray.maxt)
        t, u, v, prim, inst, valid = closest_instance_hit(self.group.tree, ray.o, ray.d,
                                                          ray.maxt, active,
                                                          time=self.time(ray))
        valid = mi.Bool(valid)
        local, in_group, instance = self.group.hit_fields(mi.UInt32(prim), mi.UInt32(inst),
                                                          valid)
        hit.take(*_distance_and_uv(t, u, v, valid), local, in_group, instance=instance)

    def occluded(self, ray, active, coherent) -> mi.Bool:
        return mi.Bool(any_hit(self.group.tree, ray.o, ray.d, ray.maxt, active,
                               time=self.time(ray)))


class OwnRoutine:
    """An analytic shape (sphere, disk, cylinder) traced by its own intersection
    routine, called directly: a call through a shape pointer inside a symbolic loop
    would trace every registered shape."""

    def __init__(self, index: int, shape):
        self.index, self.shape = index, shape  # index: the shape's into scene.shapes()

    def closest(self, ray, active, hit, coherent, reorder):
        ray.maxt = hit.reach(ray.maxt)
        pi = self.shape.ray_intersect_preliminary(ray, 0, active)
        hit.take(dr.select(pi.is_valid(), pi.t, dr.inf), pi.prim_uv, pi.prim_index,
                 dr.full(mi.UInt32, self.index, dr.width(hit.t)))

    def occluded(self, ray, active, coherent) -> mi.Bool:
        return self.shape.ray_test(ray, active)


def scene_structures(still_world, joined_tree, keyed_tree, native_moving, instances,
                     routines) -> list:
    """The structures that trace the scene now, in the order queries ask them: the
    still world's :class:`SubScene` (a NativeGroup, or None), our joined
    :class:`MeshTree` and the keyed one (or None), the moving meshes' sub-scene (a
    NativeGroup while it traces them, or None), the instances' :class:`InstanceTree`
    (an InstanceGroup, or None), and an :class:`OwnRoutine` for each ``(index, shape)``
    of ``routines``. A group without a scene or a tree (nothing in it) is left out."""
    structures = [SubScene(still_world)] if _has_scene(still_world) else []
    structures += [tree for tree in (joined_tree, keyed_tree) if tree is not None]
    if _has_scene(native_moving):
        structures.append(SubScene(native_moving))
    if instances is not None and instances.tree is not None:
        structures.append(InstanceTree(instances))
    return structures + [OwnRoutine(index, shape) for index, shape in routines]


def _distance_and_uv(t, u, v, valid: mi.Bool) -> tuple:
    """Our traversal's hit as :meth:`NearestHit.take` takes it: ``t`` (infinite where
    not ``valid``) and ``prim_uv``, in the variant's types."""
    return dr.select(valid, mi.Float(t), dr.inf), mi.Point2f(mi.Float(u), mi.Float(v))


def _has_scene(group) -> bool:
    """Whether ``group`` (a NativeGroup or None) holds a Mitsuba sub-scene to trace."""
    return group is not None and group.scene is not None
