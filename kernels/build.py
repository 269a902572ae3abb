"""The build facade: ``hlbvh.build(vertices, faces, **options) -> BVH``.

Three builders behind one word (see :class:`~hlbvh.kernels.bvh.BuildConfig`):

- ``"lbvh"`` (Lauterbach et al. 2009): Morton codes, CSD sort, then the hierarchy
  emission over every bit plane.
- ``"hlbvh"`` (Pantaleoni & Luebke 2010): Morton codes, CSD sort; the coarse clusters
  the sort found (primitives sharing the top ``coarse_bits`` key bits) get a binned-SAH
  top level, and the emission builds each cluster's sub-tree from bit plane
  ``coarse_bits`` down.
- ``"sah"`` (Wald 2007): a binned SAH over all primitives, the quality reference.

Then, for all three, the node boxes bottom-up. Every stage is a function of Dr.Jit
arrays; the host reads back only sizes (segment, split, cluster and level counts) and
the statistics.
"""

from __future__ import annotations

import contextlib
import functools
import time
from dataclasses import dataclass
from typing import Any

import drjit as dr

from .arrays import namespace_of
from .bounds import internal_levels, leaf_histogram, node_bounds, sah_cost
from .bvh import BVH, BuildConfig, BuildStats
from .csd import CsdResult, csd_sort, seed_pays
from .emission import NodeRecords, emit_hierarchy
from .geometry import (checked_faces, checked_vertices, gather_triangles,
                       records_to_triangles, slot_triangles, triangle_boxes,
                       triangle_records, warn_if_out_of_range)
from .morton import choose_key, morton_codes, point_bounds
from .sah import binned_sah
from .top_level import top_level


class _StageClock:
    """Wall time of each stage, the device synchronised before the clock stops."""

    def __init__(self):
        self.ms: dict[str, float] = {}

    @contextlib.contextmanager
    def __call__(self, name: str):
        t0 = time.perf_counter()
        yield
        dr.sync_thread()
        self.ms[name] = self.ms.get(name, 0.0) + (time.perf_counter() - t0) * 1e3


@dataclass
class _Tree:
    """What a builder made: the node records and boxes, the internal nodes by depth, and
    the primitives and their triangles in slot order."""

    node_first: Any
    node_count: Any
    node_min: Any
    node_max: Any
    levels: list
    prim_ids: Any
    tri: Any  # Matrix3f, rows p0, p1, p2


def build(vertices, faces, previous: BVH | None = None, config: BuildConfig | None = None,
          **options) -> BVH:
    """Build a BVH over a triangle mesh.

    Args:
        vertices: flat Float (3·V, xyz interleaved) or Array3f/Point3f (V), of the
            LLVM or CUDA backend; every coordinate finite.
        faces: flat UInt32 (3·F) vertex indices, or Array3u (F); F >= 1.
        previous: a BVH of an earlier frame of the same mesh: its primitive order
            seeds the CSD sort (temporal coherence). Ignored when the triangle count
            changed, and when a sample of that order under the new keys says the sort
            would sort every key anyway (:func:`~hlbvh.kernels.csd.seed_pays`;
            ``stats.csd_seeded`` says whether it was used). The tree has the same
            shape as without it; only primitives with equal Morton keys may keep last
            frame's relative order (and so change leaf boxes).
        config: a validated :class:`BuildConfig` (what callers that parsed their
            options once pass down), or None to make one from ``options``.
        **options: fields of :class:`BuildConfig` (builder, leaf_size, morton_bits,
            quantization, coarse_bits, p, sah_bins); not with ``config``.
    Returns:
        A :class:`BVH` whose ``stats`` say what the build measured.
    Warns:
        UserWarning: when the scene is less than 2**-100 wide or reaches beyond 2**125,
            where float32 ray tracing loses hits (see
            :func:`~hlbvh.kernels.geometry.warn_if_out_of_range`).
    Raises:
        ValueError: unknown or invalid options, empty input, non-finite vertices,
            faces indexing missing vertices.
        TypeError: inputs that are not Dr.Jit arrays of the expected kinds.
    """
    if config is None:
        config = BuildConfig.from_options(**options)
    elif options or not isinstance(config, BuildConfig):
        raise TypeError("build: pass a BuildConfig as config, or options, not both")
    if previous is not None and not isinstance(previous, BVH):
        raise TypeError(f"previous: expected an hlbvh BVH or None, got {type(previous).__name__}")
    clock = _StageClock()
    stats = BuildStats(builder=config.builder)

    # ---- The triangles, checked ----
    with clock("triangles"):
        faces = checked_faces(faces)
        points = checked_vertices(vertices, faces)
    stats.prim_count = len(faces) // 3

    # ---- The tree and its boxes ----
    if config.builder == "sah":
        tree = _sah_tree(config, stats, clock, points, faces)
    else:
        tree = _morton_tree(config, stats, clock, points, faces, previous)
    stats.stage_ms = dict(clock.ms)
    stats.total_ms = sum(clock.ms.values())
    return _bvh(tree, faces, config, stats)


def _sah_tree(config: BuildConfig, stats: BuildStats, clock, points, faces) -> _Tree:
    """The "sah" builder (Wald 2007): a binned SAH over all triangles, which also gives
    the node boxes."""
    with clock("sah"):
        tree = binned_sah(*triangle_boxes(_input_triangles(points, faces)),
                          dr.full(namespace_of(faces).UInt32, 1, stats.prim_count),
                          config.leaf_size, config.sah_bins)
    with clock("triangles"):
        tri = gather_triangles(points, faces, tree.item_order)
        dr.eval(tri)
    for level in tree.levels:  # one at a time: levels of one size in one kernel would
        dr.eval(level)         # make a kernel for every count of such levels
    stats.morton_bits = 0
    return _Tree(tree.node_first, tree.node_count, tree.node_min, tree.node_max, tree.levels,
                 tree.item_order, tri)


def _input_triangles(points, faces):
    """Matrix3f[F]: the triangles in input order."""
    return gather_triangles(points, faces, dr.arange(namespace_of(faces).UInt32, len(faces) // 3))


def _morton_tree(config: BuildConfig, stats: BuildStats, clock, points, faces, previous) -> _Tree:
    """The "lbvh" and "hlbvh" builders (pbrt-v4's buildHLBVH: Morton codes, the sort,
    the upper tree, emitLBVH below): Morton keys, the CSD sort, the triangles in slot
    order, the SAH top level over the coarse clusters ("hlbvh"), the hierarchy emission
    below it, then the node boxes bottom-up."""
    UInt32 = namespace_of(faces).UInt32
    prim_count = len(faces) // 3

    # ---- Morton keys of the triangles' centroids ----
    with clock("triangles"):
        centroid, tri_records = triangle_records(points, faces)
    with clock("morton"):
        keys, bits = _morton_keys(config, stats, centroid, tri_records, prim_count)

    # ---- The CSD sort, seeded with last frame's order where that pays ----
    with clock("csd"):
        csd = _sorted(keys, bits, config.coarse_bits, previous, prim_count, stats)
    with clock("triangles"):
        tri, slot_boxes = slot_triangles(records_to_triangles(tri_records, csd.order))
    del tri_records  # 64 bytes a triangle, no longer needed

    # ---- The upper tree: the SAH top level over the coarse clusters ("hlbvh") ----
    # Not cleared: the top level and the emission write each node's record once.
    records = NodeRecords(*(dr.empty(UInt32, 2 * prim_count - 1) for _ in range(3)),
                          total=dr.opaque(UInt32, 1))
    if config.builder == "lbvh" or config.coarse_bits == 0 or csd.coarse_clusters == 1:
        level = 0 if config.builder == "lbvh" else config.coarse_bits
        roots = (UInt32(0), UInt32(prim_count), UInt32(0), UInt32(0))
    else:
        with clock("sah_top"):
            top = top_level(csd.cluster_start, slot_boxes, config.sah_bins)
            top.write_internal(records)
        level = config.coarse_bits
        roots = top.roots

    # ---- The emission: each cluster's sub-tree from bit plane `level` down ----
    with clock("emission"):
        emit_hierarchy(csd.sorted_keys, bits, level, roots, records, config.leaf_size, config.p)
        used = dr.arange(UInt32, int(records.total[0]))
        node_first, node_count, node_depth = (
            dr.gather(UInt32, a, used) for a in (records.first, records.count, records.depth))
        dr.eval(node_first, node_count, node_depth)

    # ---- The node boxes, bottom-up ----
    with clock("bounds"):
        levels = internal_levels(node_count, node_depth)
        node_min, node_max = node_bounds(node_first, node_count, slot_boxes, levels,
                                         config.leaf_size)
    return _Tree(node_first, node_count, node_min, node_max, levels, csd.order, tri)


def _morton_keys(config: BuildConfig, stats: BuildStats, centroid, tri_records, prim_count):
    """``(keys, bits)``: the centroids' Morton keys, of the width and quantisation the
    config asks for (or ``"auto"`` chooses, from the triangles' boxes)."""
    lo, hi = point_bounds(centroid)
    bits, quantization = config.morton_bits, config.quantization
    if bits == "auto":
        UInt32 = namespace_of(tri_records).UInt32
        bits, quantization = choose_key(
            *triangle_boxes(records_to_triangles(tri_records, dr.arange(UInt32, prim_count))),
            lo, hi, quantization)
    keys = morton_codes(centroid, lo, hi, bits, quantization)
    stats.morton_bits, stats.quantization = bits, quantization
    return keys, bits


def _sorted(keys, bits: int, coarse_bits: int, previous, prim_count: int,
            stats: BuildStats) -> CsdResult:
    """The CSD sort of ``keys``, seeded with ``previous``'s order when it has as many
    primitives and a sample says the seed pays."""
    seed = previous.prim_ids if previous is not None and previous.prim_count == prim_count else None
    if seed is not None and not seed_pays(keys, bits, coarse_bits, seed):
        seed = None  # it would sort every key anyway: the gathers through it cost
    csd = csd_sort(keys, bits, coarse_bits, seed)
    stats.csd_seeded = seed is not None
    stats.csd_runs = csd.runs
    stats.csd_resorted = csd.resorted
    stats.coarse_clusters = csd.coarse_clusters
    return csd


def _bvh(tree: _Tree, faces, config: BuildConfig, stats: BuildStats) -> BVH:
    """The :class:`BVH` of ``tree``, with the statistics that need no host read (the
    others computed when first read)."""
    # ---- Statistics (not part of the build time, but paid every frame) ----
    root = dr.zeros(namespace_of(faces).UInt32, 1)
    warn_if_out_of_range(dr.gather(type(tree.node_min), tree.node_min, root),
                         dr.gather(type(tree.node_max), tree.node_max, root), stacklevel=4)
    # Every internal node has two children: a binary tree of N nodes has (N + 1) / 2
    # leaves, and its deepest nodes are leaves, one level below the deepest internal one.
    stats.node_count = len(tree.node_count)
    stats.leaf_count = (stats.node_count + 1) // 2
    stats.depth = len(tree.levels) + 1
    stats.leaf_histogram = functools.partial(leaf_histogram, tree.node_count, config.leaf_size)
    stats.sah_cost = functools.partial(sah_cost, tree.node_min, tree.node_max, tree.node_count)
    bvh = BVH(
        node_min=tree.node_min,
        node_max=tree.node_max,
        node_first=tree.node_first,
        node_count=tree.node_count,
        prim_ids=tree.prim_ids,
        tri_p0=tree.tri[0],
        tri_p1=tree.tri[1],
        tri_p2=tree.tri[2],
        faces=faces,
        levels=tree.levels,
        config=config,
        stats=stats,
    )
    # Evaluated (a literal, e.g. a one-primitive tree's order, would be given a new
    # variable when first read), so the key stays valid while nobody assigns them.
    dr.make_opaque(bvh.node_first, bvh.node_count, bvh.prim_ids, *bvh.levels)
    bvh.built_topology = bvh.topology_key()
    return bvh
