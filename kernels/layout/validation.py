"""Validation of a tree made by hand (or whose topology arrays were reassigned) before
it is packed: child and leaf ranges inside the arrays, every node the child of exactly
one node, and the packed slots covering every slot exactly once (a cycle, a shared
subtree, an out-of-range child, stale levels or a slot in no leaf or in two is a
ValueError); its depths come from a breadth-first walk when its levels do not hold
every internal node. A tree as the builder returned it is packed without these checks
(they cost a third of the packing and a host round trip each): the tests run them on
every builder's trees (:func:`hlbvh.kernels.layout.packing.check_tree`).
"""

from __future__ import annotations

import drjit as dr

from ..arrays import namespace_of
from .slots import MAX_DEPTH, MAX_LEAF_SIZE


def checked_levels(first, count, internal, levels, n_nodes, n_prims):
    """The internal nodes by depth to pack a tree made by hand by, after checking its
    child and leaf ranges and parents (ValueError): its own ``levels`` when they hold
    every internal node (the packed layout is then checked slot by slot, so stale levels
    cannot pass), a walk from the root otherwise."""
    UInt32 = type(first)
    # Sizes enter kernels as opaque values: a literal would compile new kernels for
    # every tree of a new size, i.e. every frame of an animation.
    nodes_o, prims_o = dr.opaque(UInt32, n_nodes), dr.opaque(UInt32, n_prims)
    bad = dr.select(internal, first + 1 >= nodes_o,
                    (count > MAX_LEAF_SIZE) | (first + count > prims_o) | (first + count < first))
    if dr.any(bad, axis=None)[0]:
        raise ValueError(
            "corrupt BVH: a child index or leaf range lies outside the node/slot "
            f"arrays, or a leaf holds more than {MAX_LEAF_SIZE} triangles"
        )
    _check_parents(first, internal, n_nodes)
    if sum(dr.width(level) for level in levels) != int(dr.count(internal)[0]):
        levels = _levels(first, internal, n_nodes)
    return levels



def _levels(first, internal, n_nodes):
    """Internal nodes by depth, root first, from a breadth-first walk (every node has
    one parent, :func:`_check_parents`, so the walk meets each node once, or loops in a
    cycle, which the node count bounds); ValueError when deeper than ``MAX_DEPTH``."""
    ns = namespace_of(first)
    UInt32 = ns.UInt32
    levels = []
    nodes = dr.arange(UInt32, 1 if bool(internal[0]) else 0)
    visited = 1
    while dr.width(nodes):
        visited += 2 * dr.width(nodes)
        if visited > n_nodes:
            raise ValueError("corrupt BVH: the tree holds a cycle (a node is its own ancestor)")
        if len(levels) == MAX_DEPTH:
            raise ValueError(too_deep())
        levels.append(nodes)
        # Both children of every node (no dr.concat: it would bake the width in).
        pair = dr.arange(UInt32, 2 * dr.width(nodes))
        children = dr.gather(UInt32, first, dr.gather(UInt32, nodes, pair >> 1)) + (pair & 1)
        nodes = dr.gather(UInt32, children,
                          dr.compress(dr.gather(ns.Bool, internal, children)))
    return levels


def too_deep() -> str:
    return (f"BVH depth above {MAX_DEPTH} levels exceeds the traversal stack: rebuild "
            "with a builder that bounds the depth")


def _check_parents(first, internal, n_nodes):
    """ValueError unless every node but the root is the child of exactly one node (and
    the root of none): a shared subtree or a cycle through the root fails here."""
    UInt32 = type(first)
    parents = dr.zeros(UInt32, n_nodes)
    left = dr.compress(internal)
    children = dr.gather(UInt32, first, left)
    # Local, not Expand: Expand's kernel holds the array's size (a compile per size).
    for child in (children, children + 1) if dr.width(children) else ():
        dr.scatter_add(parents, UInt32(1), child, mode=dr.ReduceMode.Local)
    expected = dr.select(dr.arange(UInt32, n_nodes) == 0, 0, 1)  # the root has no parent
    if not dr.all(parents == expected, axis=None)[0]:
        raise ValueError(
            "corrupt BVH: a node is the child of two nodes, or of none, or the root is a "
            "child (a cycle)"
        )



def check_layout(node_slot, record_of, total):
    """ValueError unless the wide nodes' two slots each and the triangles' one slot
    each cover every slot exactly once: what stale levels, an unreachable part of the
    tree, or a primitive slot in no leaf or in two (two triangles on one record, none
    on another) would break."""
    UInt32 = type(record_of)
    written = dr.zeros(UInt32, total)
    node_slots = [node_slot, node_slot + 1] if dr.width(node_slot) else []
    for slots in node_slots + [record_of]:
        dr.scatter_add(written, UInt32(1), slots, mode=dr.ReduceMode.Local)
    if not dr.all(written == 1, axis=None)[0]:
        raise ValueError(
            "corrupt BVH: its levels, child links or leaf ranges do not describe one tree "
            "holding every primitive slot once"
        )
