"""The shapes of a scene that do not move, traced by Mitsuba's own accelerator (Embree
on the LLVM backend, OptiX on CUDA) over a sub-scene made of those very shape objects:
the static group of :class:`hlbvh.SceneAccel` with ``static="native"``.

Why a sub-scene and not the scene itself: the scene's accelerator covers the moving
shapes too, and our per-frame updates refresh a moved mesh without rebuilding it, so
it may hold buffers the mesh no longer has. A sub-scene of the shapes that stay still
is always current. It is built once, and again only when a shape leaves it or a shape
group's own shapes change (a sub-scene is not told of its groups' updates).

How the sub-scene is made: a ``mi.Properties("scene")`` holding the shape objects
under keys of our own, and every shape group of the scene (an instance is traced
through its group's accelerator, which the sub-scene builds). Mitsuba keeps each
shape's id and object (``mi.load_dict`` would rename the shapes to their keys, in the
first scene too). A shape that emits light adds its emitter to the sub-scene's list,
which nothing samples.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from hlbvh.accel.groups import Change, NativeUpdate
from hlbvh.accel.instance_shading import group_members
from hlbvh.accel.motion import member_states, members_changed
from hlbvh.accel.scene_geometry import check_finite
from hlbvh.timing import clock_ms


class NativeGroup:
    """Shapes of a scene in a Mitsuba sub-scene, and what its last update did: the static
    group (built once, again when a shape leaves it), or the moving meshes' native
    group (built anew whenever they moved, :mod:`hlbvh.accel.choice`).

    Args:
        groups: the scene's shape groups (see :func:`shape_groups`); none for the
            moving meshes' group.
        name: its name in statistics (``"static"``, ``"native_moving"``).

    Attributes:
        name: as given.
        indices: indices into ``scene.shapes()`` of the shapes it traces, ascending.
        scene: the sub-scene; None while it holds no shape.
        builds: how often it was built.
        build_ms: how long its last build took (0 before one).
        last: what the last update did (:class:`~hlbvh.accel.groups.NativeUpdate`:
            ``"build"``, ``"rebuild"`` or ``"kept"``).
    """

    native = True  # a Mitsuba sub-scene traces it (hlbvh.accel.groups.Group)
    bvh = None

    def __init__(self, groups: list, name: str = "static"):
        self.name = name
        self.groups = groups
        self.indices: tuple = ()
        self.scene = None
        self.builds = 0
        self.build_ms = 0.0
        self.last = None
        self._shape_index = None  # UInt32: index into scene.shapes() per sub-scene shape
        self._built = False
        self._triangles = 0
        self._members = [group_members(g) for g in groups]  # each group's shapes
        self._handles = {}  # their parameter handles (hlbvh.accel.motion)
        self._group_states = []  # each group's shapes' states when the sub-scene was built
        self.keep()

    @property
    def triangles(self) -> int:
        return self._triangles

    def update(self, change: Change):
        """Trace the shapes ``change.indices``: a new sub-scene when they are not those of
        the last build, when they moved, or when a shape group's shapes changed;
        nothing otherwise.

        Raises:
            ValueError: naming a mesh with non-finite vertex positions (first build, and
                every build of moving shapes).
        """
        shapes, indices, moved = change.shapes, change.indices, change.moved
        reshaped = self._changed_groups() if self._built else []
        if self._built and tuple(indices) == self.indices and not reshaped and not moved:
            self.keep()
            return
        start = clock_ms()
        decision = "rebuild" if self._built else "build"
        self._group_states = [member_states(m, self._handles) for m in self._members]
        if not self._built or moved:
            check_finite(shapes, indices)  # later static builds trace fewer of the same shapes
        self.indices = tuple(indices)
        self.scene, self._shape_index = _sub_scene(shapes, self.indices, self.groups)
        self._triangles = sum(shapes[i].face_count() for i in self.indices if shapes[i].is_mesh())
        self._built = True
        self.builds += 1
        self.build_ms = clock_ms() - start
        self.last = NativeUpdate(decision=decision, ms=self.build_ms,
                                 triangles=self._triangles, shapes=len(self.indices),
                                 left=list(change.left), groups_changed=reshaped)

    def keep(self):
        """Record that the last update left the sub-scene as it was."""
        self.last = NativeUpdate(decision="kept", ms=0.0, triangles=self.triangles,
                                 shapes=len(self.indices))

    @property
    def stale(self) -> bool:
        """Whether a shape group's own shapes changed since the sub-scene was built."""
        return bool(self._built and self._changed_groups())

    def _changed_groups(self) -> list[str]:
        """Ids of the shape groups whose shapes changed (a mesh's buffers, another
        shape's box or parameters) since the sub-scene was built (it is then built again
        over the groups as they are)."""
        return [g.id() for g, members, states in zip(self.groups, self._members,
                                                     self._group_states)
                if members_changed(members, states, self._handles)]

    def preliminary(self, ray, coherent, active, reorder) -> mi.PreliminaryIntersection3f:
        """The sub-scene's closest hit, as the whole scene would report it: for a hit
        outside any instance, ``shape_index`` is turned from the sub-scene's index into
        the index into ``scene.shapes()``; inside an instance it is the shape's index in
        its group, the same in both scenes."""
        pi = self.scene.ray_intersect_preliminary(ray, coherent, *reorder, active)
        direct = pi.is_valid() & (pi.instance == None)  # noqa: E711 (JIT pointer compare)
        pi.shape_index = dr.select(
            direct, dr.gather(mi.UInt32, self._shape_index, pi.shape_index, direct),
            pi.shape_index)
        return pi

    def test(self, ray, coherent, active) -> mi.Bool:
        """Whether anything of the sub-scene lies on the ray."""
        return self.scene.ray_test(ray, coherent, active)


def shape_groups(scene) -> list:
    """The shape groups of ``scene`` (the shared geometry its instances refer to): they
    are not among ``scene.shapes()``, so they are found in the scene's object graph."""
    return [node for node in mi.traverse(scene).hierarchy
            if isinstance(node, mi.Shape) and node.class_name().startswith("ShapeGroup")]


def _sub_scene(shapes, indices: tuple, groups: list):
    """A Mitsuba scene of the shapes ``shapes[i]`` (``i`` in ``indices``) and the shape
    groups, and for each of its shapes the index into ``shapes``; ``(None, None)``
    without shapes."""
    if not indices:
        return None, None
    props = mi.Properties("scene")
    for k, i in enumerate(indices):
        props[f"hlbvh_static_{k}"] = shapes[i]
    for k, group in enumerate(groups):
        props[f"hlbvh_group_{k}"] = group
    scene = mi.Scene(props)
    where = {id(shapes[i]): i for i in indices}
    order = [where[id(shape)] for shape in scene.shapes()]
    return scene, mi.UInt32(order)
