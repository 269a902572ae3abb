"""Binned SAH build (kernels/sah/) against a reference written the obvious way: a
numpy build that splits one node at a time, breadth-first, with the same bins, the same
float32 cost arithmetic and the same tie rule (first axis, then lowest plane). Every test
runs on both ways the kernels split a level: one lane per node (small inputs, the HLBVH
top level) and one lane per item."""

import hlbvh  # noqa: F401  (sets up libLLVM before drjit is imported)

import re

import drjit as dr
import numpy as np
import pytest

from hlbvh.kernels import sah
from hlbvh.kernels.sah import SahTree, binned_sah

import mitsuba as mi

from hlbvh.kernels.arrays import namespace_of

# The plain (non-AD) types of the variant's backend: LLVM here, CUDA where a GPU is.
jit = namespace_of(mi.Float)
Array3f, Float, UInt32 = jit.Array3f, jit.Float, jit.UInt32

F32 = np.float32


@pytest.fixture(autouse=True, params=["node lanes", "item lanes"])
def lanes(request, monkeypatch):
    """Run the test with the inputs split one lane per node (up to the module's
    threshold, above every input here) or one lane per item (threshold 0)."""
    if request.param == "item lanes":
        monkeypatch.setattr(sah, "NODE_LANES_MAX_ITEMS", 0)
    return request.param


# ---------------------------------------------------------------------------------------
# Reference: binned SAH written node by node in numpy
# ---------------------------------------------------------------------------------------

def _half_area32(lo, hi, scale):
    """float32 half area of the box with extents multiplied by ``scale`` (1 / the node's
    largest extent), rounded like the kernel's fma(dx, dy + dz, dy * dz)."""
    d = ((hi - lo).astype(F32) * scale).astype(F32)
    return (d[..., 0].astype(np.float64) * (d[..., 1] + d[..., 2])
            + (d[..., 1] * d[..., 2])).astype(F32)


def _bins_of(c, bins):
    """Bin index per item and axis, the definition in binned_sah's docstring."""
    cmin, cmax = c.min(0), c.max(0)
    extent = (cmax - cmin).astype(F32)
    out = np.zeros(c.shape, np.int64)
    for a in range(3):
        if extent[a] > 0:
            f = ((c[:, a] - cmin[a]) / extent[a] * F32(bins)).astype(F32)
            out[:, a] = np.where(f < bins, f, bins - 1).astype(np.int64)
    return out


def reference_costs(lo, hi, w, bins):
    """SAH cost (float32, inf when a side is empty) of every plane: array [3, bins-1],
    plane p putting bins 0..p on the left; and the items' bins [n, 3]."""
    c = ((lo + hi) * F32(0.5)).astype(F32)
    b = _bins_of(c, bins)
    largest = (hi.max(0) - lo.min(0)).astype(F32).max()
    scale = F32(1) / largest if largest > 0 else F32(1)
    costs = np.full((3, bins - 1), np.inf, F32)
    for a in range(3):
        for p in range(bins - 1):
            left = b[:, a] <= p
            wl, wr = w[left].sum(), w[~left].sum()
            if wl == 0 or wr == 0:
                continue
            al = _half_area32(lo[left].min(0), hi[left].max(0), scale)
            ar = _half_area32(lo[~left].min(0), hi[~left].max(0), scale)
            cl = (al * F32(wl)).astype(F32)
            costs[a, p] = F32(np.float64(ar) * np.float64(F32(wr)) + np.float64(cl))
    return costs, b


def reference_split(lo, hi, w, bins):
    """Boolean 'goes left' per item of one node (middle index when no plane is valid)."""
    costs, b = reference_costs(lo, hi, w, bins)
    n = len(lo)
    if not np.isfinite(costs).any():
        return np.arange(n) < n // 2
    a, p = np.unravel_index(np.argmin(costs), costs.shape)
    return b[:, a] <= p


def reference_tree(lo, hi, w, leaf_items, bins):
    """(node_first, node_count, node_min, node_max, item_order) of the breadth-first
    binned SAH tree, children of a level's internal nodes numbered in parent order."""
    first, count, nmin, nmax = [0], [0], [None], [None]
    order = np.empty(len(lo), np.int64)
    level = [(0, np.arange(len(lo)), 0)]  # (node id, items in slot order, first slot)
    next_id = 1
    while level:
        nxt = []
        for node, items, slot in level:
            nmin[node], nmax[node] = lo[items].min(0), hi[items].max(0)
            if len(items) <= leaf_items:
                first[node], count[node] = slot, len(items)
                order[slot:slot + len(items)] = items
                continue
            left = reference_split(lo[items], hi[items], w[items], bins)
            first[node], count[node] = next_id, 0
            first += [0, 0]; count += [0, 0]; nmin += [None, None]; nmax += [None, None]
            nxt += [(next_id, items[left], slot),
                    (next_id + 1, items[~left], slot + int(left.sum()))]
            next_id += 2
        level = nxt
    return (np.array(first), np.array(count), np.array(nmin), np.array(nmax), order)


# ---------------------------------------------------------------------------------------
# Helpers
# ---------------------------------------------------------------------------------------

def random_boxes(n, seed, size=0.05, flat_axes=()):
    rng = np.random.default_rng(seed)
    c = rng.random((n, 3)).astype(F32)
    e = (rng.random((n, 3)) * size).astype(F32)
    for a in flat_axes:
        c[:, a] = 0.25
        e[:, a] = 0
    return (c - e).astype(F32), (c + e).astype(F32)


def build(lo, hi, w=None, leaf_items=4, bins=16):
    n = len(lo)
    w = np.ones(n, np.uint32) if w is None else w
    tree = binned_sah(Array3f(*lo.T), Array3f(*hi.T), UInt32(w), leaf_items, bins)
    return tree


def as_numpy(tree: SahTree):
    return dict(
        first=tree.node_first.numpy(), count=tree.node_count.numpy(),
        min=tree.node_min.numpy().T, max=tree.node_max.numpy().T,
        order=tree.item_order.numpy(), depth_of=tree.leaf_depth.numpy(),
        levels=[l.numpy() for l in tree.levels],
    )


def check_structure(tree: SahTree, lo, hi, leaf_items):
    """The invariants every SahTree must satisfy, checked node by node."""
    t = as_numpy(tree)
    n, T = len(lo), len(t["first"])
    assert tree.size == T and len(t["order"]) == n
    # every item in exactly one slot
    assert np.array_equal(np.sort(t["order"]), np.arange(n))
    slot_owner = np.full(n, -1)
    depth = np.full(T, -1)
    depth[0] = 0
    lo_of = np.zeros((T, 3), F32)
    hi_of = np.zeros((T, 3), F32)
    span = {}  # node -> (first slot, end slot) of its subtree
    for v in range(T - 1, -1, -1):
        f, c = int(t["first"][v]), int(t["count"][v])
        if c:  # leaf
            assert c <= leaf_items
            assert np.all(slot_owner[f:f + c] == -1), "a slot belongs to two leaves"
            slot_owner[f:f + c] = v
            items = t["order"][f:f + c]
            lo_of[v], hi_of[v] = lo[items].min(0), hi[items].max(0)
            span[v] = (f, f + c)
        else:
            assert v < f < T - 1, "children must follow their parent"
            for ch in (f, f + 1):
                assert np.all(t["min"][ch] >= t["min"][v]) and np.all(t["max"][ch] <= t["max"][v])
            lo_of[v] = np.minimum(lo_of[f], lo_of[f + 1])
            hi_of[v] = np.maximum(hi_of[f], hi_of[f + 1])
            (a0, a1), (b0, b1) = span[f], span[f + 1]
            assert a1 == b0, "a subtree's slots must be contiguous, left before right"
            span[v] = (a0, b1)
    assert np.all(slot_owner >= 0), "a slot belongs to no leaf"
    assert span[0] == (0, n)
    # node boxes equal the union of their items' boxes
    assert np.array_equal(t["min"], lo_of) and np.array_equal(t["max"], hi_of)
    # depths by walking down from the root; levels list the internal nodes per depth
    for v in range(T):
        if not t["count"][v]:
            depth[t["first"][v]] = depth[t["first"][v] + 1] = depth[v] + 1
    assert np.all(depth >= 0)
    assert np.array_equal(t["depth_of"], depth)
    assert tree.depth == depth.max() + 1
    internal = np.flatnonzero(t["count"] == 0)
    expected_levels = [internal[depth[internal] == d] for d in range(depth.max())]
    if not len(internal):
        expected_levels = []
    assert len(t["levels"]) == len(expected_levels)
    for got, want in zip(t["levels"], expected_levels):
        assert np.array_equal(np.sort(got), want)
    return t


def assert_equals_reference(tree, lo, hi, w, leaf_items, bins):
    t = as_numpy(tree)
    first, count, nmin, nmax, order = reference_tree(lo, hi, w, leaf_items, bins)
    assert np.array_equal(t["count"], count)
    assert np.array_equal(t["first"], first)
    assert np.array_equal(t["order"], order)
    assert np.array_equal(t["min"], np.stack(nmin)) and np.array_equal(t["max"], np.stack(nmax))


def subtree_items(t, v):
    """Items under node v (numpy tree dict)."""
    if t["count"][v]:
        f = t["first"][v]
        return set(t["order"][f:f + t["count"][v]].tolist())
    return subtree_items(t, t["first"][v]) | subtree_items(t, t["first"][v] + 1)


# ---------------------------------------------------------------------------------------
# Tests
# ---------------------------------------------------------------------------------------

@pytest.mark.parametrize("n, leaf_items, seed", [(300, 4, 0), (500, 1, 1), (1000, 8, 2)])
def test01_structure_invariants(n, leaf_items, seed):
    lo, hi = random_boxes(n, seed)
    check_structure(build(lo, hi, leaf_items=leaf_items), lo, hi, leaf_items)


@pytest.mark.parametrize("bins", [16, 4, 2])
def test02_root_split_equals_bruteforce_best_plane(bins):
    lo, hi = random_boxes(400, 10 + bins, size=0.1)
    w = np.ones(len(lo), np.uint32)
    tree = build(lo, hi, w, leaf_items=4, bins=bins)
    t = as_numpy(tree)
    costs, b = reference_costs(lo, hi, w, bins)
    a, p = np.unravel_index(np.argmin(costs), costs.shape)
    # the best plane is unique by a margin, so the comparison is not a coin toss
    second = np.partition(costs.ravel(), 1)[1]
    assert second > costs[a, p] * (1 + 1e-4)
    left = subtree_items(t, t["first"][0])
    assert left == set(np.flatnonzero(b[:, a] <= p).tolist())


@pytest.mark.parametrize("bins", [16, 5, 64])
def test03_whole_tree_equals_reference_build(bins):
    lo, hi = random_boxes(300, 3, size=0.08)
    tree = build(lo, hi, leaf_items=2, bins=bins)
    assert_equals_reference(tree, lo, hi, np.ones(300, np.uint32), 2, bins)


def test04_weights_steer_the_split():
    # clusters: few hundred items, leaf_items=1, weights = primitive counts
    lo, hi = random_boxes(200, 4, size=0.03)
    w = np.random.default_rng(4).integers(1, 500, 200).astype(np.uint32)
    w[lo[:, 0] < 0.15] = 100000  # heavy clusters on one side pull the plane there
    weighted_left = reference_split(lo, hi, w, 16)
    plain_left = reference_split(lo, hi, np.ones_like(w), 16)
    assert not np.array_equal(weighted_left, plain_left), "the test must tell weights apart"
    tree = build(lo, hi, w, leaf_items=1)
    t = check_structure(tree, lo, hi, 1)
    assert np.all(t["count"][t["count"] > 0] == 1)
    assert_equals_reference(tree, lo, hi, w, 1, 16)


def test05_same_input_builds_bit_identical_arrays():
    lo, hi = random_boxes(5000, 5)
    a, b = as_numpy(build(lo, hi)), as_numpy(build(lo, hi))
    for key in ("first", "count", "min", "max", "order", "depth_of"):
        assert np.array_equal(a[key], b[key]) and a[key].tobytes() == b[key].tobytes()
    assert all(np.array_equal(x, y) for x, y in zip(a["levels"], b["levels"]))


def test06_one_item_is_a_single_leaf():
    lo, hi = random_boxes(1, 6)
    tree = build(lo, hi, leaf_items=1)
    t = check_structure(tree, lo, hi, 1)
    assert tree.size == 1 and tree.depth == 1 and tree.levels == []
    assert t["first"][0] == 0 and t["count"][0] == 1 and t["order"][0] == 0


def test07_two_items_split_into_two_leaves():
    lo = np.array([[0, 0, 0], [2, 0, 0]], F32)
    hi = lo + 1
    tree = build(lo, hi, leaf_items=1)
    t = check_structure(tree, lo, hi, 1)
    assert tree.size == 3 and tree.depth == 2
    assert list(t["count"]) == [0, 1, 1] and list(t["order"]) == [0, 1]


@pytest.mark.parametrize("n, leaf_items", [(37, 4), (64, 1), (5, 2)])
def test08_equal_centroids_split_at_the_middle_index(n, leaf_items):
    # same centre, different sizes: no plane separates them
    c = np.full((n, 3), 0.5, F32)
    e = np.linspace(0.01, 0.4, n, dtype=F32)[:, None] * np.ones(3, F32)
    lo, hi = (c - e).astype(F32), (c + e).astype(F32)
    tree = build(lo, hi, leaf_items=leaf_items)
    t = check_structure(tree, lo, hi, leaf_items)
    assert np.array_equal(t["order"], np.arange(n)), "middle splits keep the input order"
    assert tree.depth == int(np.ceil(np.log2(n / leaf_items))) + 1
    assert_equals_reference(tree, lo, hi, np.ones(n, np.uint32), leaf_items, 16)


@pytest.mark.parametrize("flat_axes", [(2,), (0, 1)])
def test09_flat_inputs(flat_axes):
    lo, hi = random_boxes(400, 9, flat_axes=flat_axes)
    tree = build(lo, hi, leaf_items=3)
    check_structure(tree, lo, hi, 3)
    assert_equals_reference(tree, lo, hi, np.ones(400, np.uint32), 3, 16)


def test10_duplicates_and_clumps():
    # many exact duplicates beside a spread: planes with an empty side, middle splits
    lo, hi = random_boxes(200, 11)
    lo = np.concatenate([lo, np.repeat(lo[:3], 50, axis=0)])
    hi = np.concatenate([hi, np.repeat(hi[:3], 50, axis=0)])
    tree = build(lo, hi, leaf_items=2)
    check_structure(tree, lo, hi, 2)
    assert_equals_reference(tree, lo, hi, np.ones(len(lo), np.uint32), 2, 16)


def test11_bad_input_raises_clear_errors():
    lo, hi = random_boxes(10, 12)
    good = (Array3f(*lo.T), Array3f(*hi.T), UInt32(np.ones(10, np.uint32)))
    with pytest.raises(ValueError, match="leaf_items"):
        binned_sah(*good, 0)
    with pytest.raises(ValueError, match="bins"):
        binned_sah(*good, 4, bins=1)
    with pytest.raises(ValueError, match="bins"):
        binned_sah(*good, 4, bins=65)
    with pytest.raises(ValueError, match="one entry per item"):
        binned_sah(good[0], good[1], UInt32(1, 2), 4)
    with pytest.raises(ValueError, match="no items"):
        binned_sah(Array3f(), Array3f(), UInt32(), 4)
    with pytest.raises(TypeError, match="item_min"):
        binned_sah(lo, good[1], good[2], 4)


def test12_grid_mesh_leaves_and_bounds():
    # the kind of input the "sah" builder sees: triangles of a grid, tightly packed
    k = 60
    x, y = np.meshgrid(np.arange(k, dtype=F32), np.arange(k, dtype=F32), indexing="ij")
    p0 = np.stack([x.ravel(), y.ravel(), np.zeros(k * k, F32)], 1) / k
    lo = np.concatenate([p0, p0]).astype(F32)
    hi = (lo + F32(1 / k)).astype(F32)
    hi[:, 2] = lo[:, 2]
    tree = build(lo, hi, leaf_items=4)
    check_structure(tree, lo, hi, 4)


@pytest.mark.parametrize("scale", [2.0**100, 2.0**-100])
def test13_same_tree_at_extreme_scales(scale):
    # power-of-two scales are exact in float32: near 1e+30 and 1e-30 the tree must be
    # the one built at scale 1 (areas would overflow or underflow if not normalised)
    lo, hi = random_boxes(500, 13)
    a = as_numpy(build(lo, hi))
    b = as_numpy(build((lo * F32(scale)).astype(F32), (hi * F32(scale)).astype(F32)))
    for key in ("first", "count", "order"):
        assert np.array_equal(a[key], b[key])
    assert np.array_equal(a["min"] * F32(scale), b["min"])


def _kernel_shape(entry):
    """A launched kernel's LLVM IR without what Dr.Jit varies per buffer (its name,
    which is a hash of the rest, and the alignment it proved for each pointer)."""
    ir = entry["ir"]
    ir = ir.getvalue() if hasattr(ir, "getvalue") else str(ir)
    ir = re.sub(r"@drjit_[0-9a-f]+", "@kernel", ir)
    ir = re.sub(r"align \d+", "align", ir)
    return re.sub(r"(<\d+ x ptr> %\w+), i32 \d+", r"\1", ir)  # gather/scatter alignment


def test14_new_sizes_reuse_the_same_kernels():
    # sizes and offsets enter the kernels as opaque values: after a few builds (which
    # meet Dr.Jit's variants for single-entry arrays), a build of a new size and depth
    # launches only kernels that ran before
    def kernels(n, seed):
        lo, hi = random_boxes(n, seed)
        dr.kernel_history()
        build(lo, hi, np.arange(n, dtype=np.uint32) % 7 + 1, leaf_items=2)
        return {_kernel_shape(e) for e in dr.kernel_history() if e["type"] == dr.KernelType.JIT}

    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        first = kernels(700, 14) | kernels(1913, 15) | kernels(3001, 16)
        second = kernels(2222, 17)
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert second <= first, f"{len(second - first)} kernel(s) specialised on a size"


@pytest.mark.parametrize("n, leaf_items, bins", [(1, 1, 16), (3, 1, 2), (17, 2, 7), (300, 1, 16),
                                                 (1000, 4, 64), (4096, 1, 16)])
def test15_node_lanes_and_item_lanes_build_the_same_tree(lanes, monkeypatch, n, leaf_items, bins):
    """The two ways of splitting a level are one algorithm: the same arrays bit for bit,
    on boxes with clumps, flat stretches and items of weight 0 (both ways meet the same
    inputs in one process, so the node lanes' frozen kernels replay on new sizes)."""
    if lanes == "item lanes":
        pytest.skip("compares both ways itself")
    rng = np.random.default_rng(n)
    c = rng.random((n, 3)).astype(F32)
    c[: n // 3, 2] = F32(0.5)
    c[n // 3: n // 2] = np.round(c[n // 3: n // 2] * 3) / 3
    e = (rng.random((n, 3)) * 0.05).astype(F32)
    lo, hi, w = c - e, c + e, rng.integers(0, 4, n).astype(np.uint32)
    node = as_numpy(build(lo, hi, w, leaf_items=leaf_items, bins=bins))
    monkeypatch.setattr(sah, "NODE_LANES_MAX_ITEMS", 0)
    item = as_numpy(build(lo, hi, w, leaf_items=leaf_items, bins=bins))
    levels = node.pop("levels"), item.pop("levels")
    assert len(levels[0]) == len(levels[1])
    assert all(np.array_equal(a, b) for a, b in zip(*levels))
    for key in node:
        assert np.array_equal(node[key], item[key]), key
