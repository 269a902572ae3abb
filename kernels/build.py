"""The build facade: ``hlbvh.build(vertices, faces, **options) -> BVH``.

Three builders behind one word (see :class:`~hlbvh.kernels.bvh.BuildConfig`):

- ``"lbvh"`` (Lauterbach et al. 2009): Morton codes, CSD sort, then the hierarchy
  emission over every bit plane.
- ``"hlbvh"`` (Pantaleoni & Luebke 2010): Morton codes, CSD sort; the coarse clusters
  (primitives sharing the top ``coarse_bits`` key bits) get a binned-SAH top level, and
  the emission builds each cluster's sub-tree from bit plane ``coarse_bits`` down.
- ``"sah"`` (Wald 2007): a binned SAH over all primitives, the quality reference.

Every stage is a function of Dr.Jit arrays; the host reads back only sizes (segment,
split and cluster counts) and the statistics.
"""

from __future__ import annotations

import contextlib
import time

import drjit as dr

from .bounds import internal_levels, leaf_histogram, node_bounds, sah_cost, triangle_boxes
from .bvh import BVH, BuildConfig, BuildStats
from .csd import csd_sort
from .emission import NodeRecords, emit_hierarchy
from .geometry import checked_faces, checked_vertices, gather_triangles, warn_if_out_of_range
from .morton import choose_key, morton_codes, point_bounds
from .arrays import namespace_of
from .sah import binned_sah


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


def build(vertices, faces, previous: BVH | None = None, **options) -> BVH:
    """Build a BVH over a triangle mesh.

    Args:
        vertices: flat Float (3·V, xyz interleaved) or Array3f/Point3f (V), of the
            LLVM or CUDA backend; every coordinate finite.
        faces: flat UInt32 (3·F) vertex indices, or Array3u (F); F >= 1.
        previous: a BVH of an earlier frame of the same mesh: its primitive order
            seeds the CSD sort (temporal coherence). Ignored when the triangle count
            changed. The tree has the same shape as without it; only primitives with equal
            Morton keys may keep last frame's relative order (and so change leaf boxes).
        **options: fields of :class:`BuildConfig` (builder, leaf_size, morton_bits,
            quantization, coarse_bits, p, sah_bins).
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
    config = BuildConfig.from_options(**options)
    if previous is not None and not isinstance(previous, BVH):
        raise TypeError(f"previous: expected an hlbvh BVH or None, got {type(previous).__name__}")
    clock = _StageClock()
    stats = BuildStats(builder=config.builder)

    # ---- Triangles, their boxes and centroids ----
    with clock("triangles"):
        faces = checked_faces(faces)
        points = checked_vertices(vertices, faces)
        ns = namespace_of(faces)
        UInt32 = ns.UInt32
        prim_count = len(faces) // 3
        tri_lo, tri_hi = triangle_boxes(gather_triangles(points, faces, dr.arange(UInt32, prim_count)))
        dr.eval(tri_lo, tri_hi)
        warn_if_out_of_range(tri_lo, tri_hi)
    stats.prim_count = prim_count

    if config.builder == "sah":
        with clock("sah"):
            tree = binned_sah(
                tri_lo, tri_hi, dr.full(UInt32, 1, prim_count), config.leaf_size, config.sah_bins
            )
            prim_ids = tree.item_order
            tri = gather_triangles(points, faces, prim_ids)
            dr.eval(tri)
        node_first, node_count = tree.node_first, tree.node_count
        node_min, node_max, levels = tree.node_min, tree.node_max, tree.levels
        node_depth = tree.leaf_depth
        stats.morton_bits = 0
    else:
        node_first, node_count, node_depth, prim_ids, tri, slot_lo, slot_hi = _morton_build(
            config, stats, clock, previous, tri_lo, tri_hi, points, faces
        )
        with clock("bounds"):
            levels = internal_levels(node_count, node_depth)
            node_min, node_max = node_bounds(
                node_first, node_count, slot_lo, slot_hi, levels, config.leaf_size
            )

    stats.stage_ms = dict(clock.ms)
    stats.total_ms = sum(clock.ms.values())

    # ---- Statistics (not part of the build time) ----
    stats.node_count = len(node_count)
    stats.leaf_histogram = leaf_histogram(node_count, config.leaf_size)
    stats.leaf_count = sum(stats.leaf_histogram)
    stats.depth = int(dr.max(node_depth)[0]) + 1
    stats.sah_cost = sah_cost(node_min, node_max, node_count)
    return BVH(
        node_min=node_min,
        node_max=node_max,
        node_first=node_first,
        node_count=node_count,
        prim_ids=prim_ids,
        tri_p0=tri[0],
        tri_p1=tri[1],
        tri_p2=tri[2],
        faces=faces,
        levels=levels,
        config=config,
        stats=stats,
    )


def _morton_build(config: BuildConfig, stats: BuildStats, clock, previous, tri_lo, tri_hi, points, faces):
    """The "lbvh" and "hlbvh" builders up to the node records (no boxes yet).

    Returns (node_first, node_count, node_depth, prim_ids, slot triangles (Matrix3f),
    slot triangle boxes lo, hi).
    """
    ns = namespace_of(tri_lo.x)
    UInt32 = ns.UInt32
    prim_count = len(tri_lo.x)

    # ---- Morton codes of the centroids, quantised in the centroids' bounds ----
    with clock("morton"):
        centroid = (tri_lo + tri_hi) * 0.5
        lo, hi = point_bounds(centroid)
        bits, quantization = config.morton_bits, config.quantization
        if bits == "auto":
            bits, quantization = choose_key(tri_lo, tri_hi, lo, hi, quantization)
        keys = morton_codes(centroid, lo, hi, bits, quantization)
    stats.morton_bits, stats.quantization = bits, quantization
    coarse_bits = config.coarse_bits  # the same coarse voxels for 30- and 60-bit keys

    # ---- CSD sort, from last frame's order when there is one ----
    with clock("csd"):
        start = None
        if previous is not None and previous.prim_count == prim_count:
            start = previous.prim_ids
        csd = csd_sort(keys, bits, coarse_bits, start)
        prim_ids, sorted_keys = csd.order, csd.sorted_keys
    stats.csd_runs = csd.runs
    stats.coarse_clusters = csd.coarse_clusters

    # ---- Triangles in slot order (mesh vertices are shared and local: mostly cached) ----
    with clock("triangles"):
        tri = gather_triangles(points, faces, prim_ids)
        slot_lo, slot_hi = triangle_boxes(tri)
        dr.eval(tri, slot_lo, slot_hi)

    capacity = 2 * prim_count - 1
    records = NodeRecords(
        first=dr.zeros(UInt32, capacity),
        count=dr.zeros(UInt32, capacity),
        depth=dr.zeros(UInt32, capacity),
        total=dr.opaque(UInt32, 1),
    )
    if config.builder == "lbvh" or coarse_bits == 0 or csd.coarse_clusters == 1:
        level = 0 if config.builder == "lbvh" else coarse_bits
        roots = (UInt32(0), UInt32(prim_count), UInt32(0), UInt32(0))
        prim_root = dr.zeros(UInt32, prim_count)
    else:
        with clock("sah_top"):
            roots, prim_root = _sah_top_level(config, records, sorted_keys, bits, coarse_bits, slot_lo, slot_hi)
        level = coarse_bits

    # ---- Hierarchy emission below the roots ----
    with clock("emission"):
        emit_hierarchy(sorted_keys, bits, level, roots, prim_root, records, config.leaf_size, config.p)
        used = dr.arange(UInt32, int(records.total[0]))
        node_first = dr.gather(UInt32, records.first, used)
        node_count = dr.gather(UInt32, records.count, used)
        node_depth = dr.gather(UInt32, records.depth, used)
        dr.eval(node_first, node_count, node_depth)
    return node_first, node_count, node_depth, prim_ids, tri, slot_lo, slot_hi


def _sah_top_level(config, records: NodeRecords, sorted_keys, bits, coarse_bits, slot_lo, slot_hi):
    """Binned SAH over the coarse clusters; writes the top tree's internal nodes into
    ``records`` and returns the clusters as emission roots (start, end, node, depth)
    and each primitive's cluster."""
    ns = namespace_of(sorted_keys)
    UInt32, Array3f = ns.UInt32, ns.Array3f
    n = len(sorted_keys)

    # ---- Coarse clusters: runs of equal coarse key in sorted order ----
    slot = dr.arange(UInt32, n)
    coarse = sorted_keys >> type(sorted_keys)(bits - coarse_bits)
    head = (slot == 0) | (coarse != dr.gather(type(coarse), coarse, dr.maximum(slot, 1) - 1))
    start = dr.compress(head)
    clusters = len(start)
    after = dr.arange(UInt32, clusters) + 1
    last = after == dr.opaque(UInt32, clusters)
    end = dr.select(last, dr.opaque(UInt32, n), dr.gather(UInt32, start, after, ~last))
    cluster_of = dr.cumsum(UInt32(head)) - 1

    # ---- Cluster boxes: union of their triangles' boxes ----
    lo = dr.full(Array3f, dr.inf, clusters)
    hi = dr.full(Array3f, -dr.inf, clusters)
    # ReduceMode.Local: Auto picks Expand for small targets, which bakes the cluster
    # count into the kernel (a new kernel for every new count, i.e. most frames).
    dr.scatter_reduce(dr.ReduceOp.Min, lo, slot_lo, cluster_of, mode=dr.ReduceMode.Local)
    dr.scatter_reduce(dr.ReduceOp.Max, hi, slot_hi, cluster_of, mode=dr.ReduceMode.Local)

    # ---- SAH top level, one cluster per leaf ----
    top = binned_sah(lo, hi, end - start, 1, config.sah_bins)
    t = len(top.node_count)
    nodes = dr.arange(UInt32, t)
    internal = top.node_count == 0
    dr.scatter(records.first, top.node_first, nodes, internal)
    dr.scatter(records.depth, top.leaf_depth, nodes, internal)
    records.total = dr.opaque(UInt32, t)

    # ---- Each cluster's emission root is its top-level leaf ----
    cluster_node = dr.zeros(UInt32, clusters)
    cluster_depth = dr.zeros(UInt32, clusters)
    leaf_cluster = dr.gather(UInt32, top.item_order, top.node_first, ~internal)
    dr.scatter(cluster_node, nodes, leaf_cluster, ~internal)
    dr.scatter(cluster_depth, top.leaf_depth, leaf_cluster, ~internal)
    return (start, end, cluster_node, cluster_depth), cluster_of
