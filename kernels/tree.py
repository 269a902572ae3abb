"""The tree record: the binary hierarchy the builders produce and every later stage
reads, as plain arrays with the configuration and statistics of its build.

Node layout (binary tree, flat structure-of-arrays, ``N`` nodes, root at index 0):

==================  ==========  ==========================================================
field               type        meaning
==================  ==========  ==========================================================
``node_min``        Array3f[N]  lower corner of the node's box
``node_max``        Array3f[N]  upper corner of the node's box
``node_first``      UInt32[N]   internal node: index of its left child; the right child is
                                always ``node_first + 1`` (siblings are adjacent).
                                leaf: index of its first primitive slot
``node_count``      UInt32[N]   0 for an internal node; for a leaf the number of
                                primitives (slots ``node_first .. node_first+count-1``)
``prim_ids``        UInt32[F]   slot -> index of the triangle in the input ``faces``
``tri_p0/p1/p2``    Array3f[F]  the triangle's vertices, stored in slot order so a leaf
                                reads contiguous memory
==================  ==========  ==========================================================

``levels`` lists, root first, the internal nodes of each depth (one UInt32 array per
depth); bottom-up passes (bounds, refit) walk it backwards without any synchronisation
inside a kernel. Every array is of the backend of the input vertices.

``built_topology`` is :meth:`Tree.topology_key` as the builder returned the tree (None for
a tree made by hand): while the key still matches, the tree is the builder's own, whose
invariants the tests check on every builder, and the packer skips validating it on
every frame.

``kept`` holds what later stages keep for the tree between calls, one object per stage
(the packer's and the refit's state), each made and read by its own stage only: this
module imports no stage and knows none of their fields. The conveniences a user calls
on a tree (``refit``, ``intersect``) are :class:`hlbvh.kernels.bvh.BVH`'s, a layer above
the stages.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from .arrays import Array3f, UInt32


@dataclass
class Tree:
    """A built hierarchy over a triangle mesh (layout in the module docstring): a plain
    record of arrays, what the builder writes and the later stages read. ``config`` and
    ``stats`` are the build's :class:`~hlbvh.kernels.bvh.BuildConfig` and
    :class:`~hlbvh.kernels.bvh.BuildStats`."""

    node_min: Array3f
    node_max: Array3f
    node_first: UInt32
    node_count: UInt32
    prim_ids: UInt32
    tri_p0: Array3f
    tri_p1: Array3f
    tri_p2: Array3f
    faces: UInt32
    levels: list[UInt32]
    config: Any
    stats: Any
    built_topology: tuple | None = None
    kept: dict = field(default_factory=dict, repr=False, compare=False)

    def topology_key(self) -> tuple:
        """The Dr.Jit variables of the arrays that give the tree its shape (``node_first``,
        ``node_count``, ``prim_ids``, ``levels``): assigning any of them changes it. (A
        refit assigns only boxes and triangles.)"""
        return (self.node_first.index, self.node_count.index, self.prim_ids.index,
                tuple(level.index for level in self.levels))

    def kept_state(self, kind: type):
        """The stage state of class ``kind`` kept for this tree (``kind()`` on first
        use): each stage keys its own state by its own class."""
        state = self.kept.get(kind)
        if state is None:
            state = self.kept[kind] = kind()
        return state

    @property
    def size(self) -> int:
        """Number of nodes."""
        return len(self.node_count)

    @property
    def prim_count(self) -> int:
        return len(self.prim_ids)
