"""Keyed trees (motion blur of deforming meshes, :mod:`hlbvh.kernels.keyed`): a tree's
slots at S+1 keys, traced at each ray's time. Against the still tree (equal keys), a
brute force over the triangles interpolated at each ray's time, the containment of
every triangle in its leaf's interpolated box, rays through a moving grid's shared
edges and vertices, and bad keys."""

from __future__ import annotations

import numpy as np
import pytest

import hlbvh  # noqa: F401  (sets up libLLVM and the variant before drjit is used)
import drjit as dr
import mitsuba as mi

from reference import brute_force, median_split_bvh, random_soup, triangle_grid  # noqa: E402

from hlbvh.kernels import keyed as keyed_module  # noqa: E402
from hlbvh.kernels.keyed import build_keyed, keyed_tree, ray_keys  # noqa: E402
from hlbvh.kernels.layout.slots import LEAF_BIT, NODE_HI, NODE_LO, NODE_REF, SLOT, TRI_P  # noqa: E402
from hlbvh.kernels.traversal import any_hit, closest_hit, intersect, occluded  # noqa: E402

T_REL = 1e-5  # t against the float64 reference, relative to the hit's conditioning


# ---------------------------------------------------------------------------------------
# Helpers
# ---------------------------------------------------------------------------------------


def flat(points):
    """A (V, 3) numpy array as a flat mi.Float (3·V)."""
    return mi.Float(np.ascontiguousarray(points, np.float32).ravel())


def build(vertices, faces, builder="hlbvh", leaf_size=4):
    if builder == "median":
        return median_split_bvh(vertices, faces, leaf_size)
    return hlbvh.build(flat(vertices), mi.UInt32(np.ravel(faces)), builder=builder,
                       leaf_size=leaf_size)


def trace(tree, o, d, time, maxt=np.inf):
    """closest_hit and any_hit of numpy rays at numpy times; numpy results."""
    O, D = mi.Point3f(np.asarray(o, np.float32).T), mi.Vector3f(np.asarray(d, np.float32).T)
    T = mi.Float(np.asarray(time, np.float32))
    t, u, v, prim, valid = closest_hit(tree, O, D, maxt, time=T)
    return {"t": t.numpy(), "u": u.numpy(), "v": v.numpy(), "prim": prim.numpy(),
            "valid": valid.numpy(), "any": any_hit(tree, O, D, maxt, time=T).numpy()}


def at_time(keys, time):
    """The vertices (V, 3) float64 at normalised ``time``: keys ``k`` and ``k + 1``
    interpolated, ``k = min(floor(time·S), S - 1)``."""
    s = len(keys) - 1
    x = float(np.float32(np.float32(time) * np.float32(s)))  # as the kernel rounds it
    k = min(int(np.floor(x)), s - 1)
    f = x - k
    return (1 - f) * np.asarray(keys[k], np.float64) + f * np.asarray(keys[k + 1], np.float64)


def moving_keys(vertices, rng, count, amplitude):
    """``count`` keys: ``vertices`` displaced by a random offset per vertex and key."""
    return [(vertices + amplitude * rng.normal(size=vertices.shape)).astype(np.float32)
            for _ in range(count)]


# ---------------------------------------------------------------------------------------
# (a) Equal keys: the still tree's hits, bit for bit
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("builder", ["hlbvh", "median"])
def test01_equal_keys_trace_bit_identical_to_the_still_tree(builder):
    rng = np.random.default_rng(1)
    vertices, faces = random_soup(400, seed=2)
    bvh = build(vertices, faces, builder)
    o = (rng.random((4000, 3)) * 1.4 - 0.2).astype(np.float32)
    d = rng.normal(size=(4000, 3)).astype(np.float32)
    O, D = mi.Point3f(o.T), mi.Vector3f(d.T)
    still = [x.numpy() for x in closest_hit(bvh, O, D, 10.0)]
    still_any = any_hit(bvh, O, D, 10.0).numpy()
    assert still[4].sum() > 500
    for count in (2, 4):  # S = 1, and S = 3 (rays reading different keys)
        tree = keyed_tree(bvh, [flat(vertices)] * count)
        assert tree.keys == count and dr.width(tree.records) == count * tree.slots * SLOT
        for time in (rng.random(4000).astype(np.float32), 0.0, 1.0, 0.5):
            keyed = [x.numpy() for x in closest_hit(tree, O, D, 10.0, time=time)]
            for ours, theirs in zip(keyed, still):
                np.testing.assert_array_equal(ours, theirs)
            np.testing.assert_array_equal(any_hit(tree, O, D, 10.0, time=time).numpy(),
                                          still_any)


# ---------------------------------------------------------------------------------------
# (b) Against a brute force over the triangles at each ray's time
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("segments", [1, 3])
@pytest.mark.parametrize("builder", ["hlbvh", "median"])
def test02_moving_soup_matches_brute_force_at_each_rays_time(segments, builder):
    rng = np.random.default_rng(10 + segments)
    vertices, faces = random_soup(300, seed=3)
    keys = moving_keys(vertices, rng, segments + 1, 0.08)
    if builder == "median":  # a hand-made tree over key 0 (refit through its binary levels)
        tree = keyed_tree(median_split_bvh(keys[0], faces, 4), [flat(k) for k in keys])
    else:  # built over the mid-shutter pose
        tree = build_keyed([flat(k) for k in keys], mi.UInt32(faces.ravel()))
    n = 2000
    o = (rng.random((n, 3)) * 1.4 - 0.2).astype(np.float32)
    d = rng.normal(size=(n, 3)).astype(np.float32)
    time = rng.random(n).astype(np.float32)
    time[:8] = [0, 1, 0.5, 1 / 3, 2 / 3, 0.25, 0.75, 1e-7]
    ours = trace(tree, o, d, time)

    hits = 0
    for i in range(n):
        at = at_time(keys, time[i])
        ref = brute_force(at, faces, o[i:i + 1], d[i:i + 1])
        assert ours["valid"][i] == ref["valid"][0], f"ray {i} at time {time[i]}"
        assert ours["any"][i] == ref["valid"][0], f"ray {i} at time {time[i]}"
        if not ref["valid"][0]:
            assert np.isinf(ours["t"][i])
            continue
        hits += 1
        t_ref, prim = ref["t"][0], int(ours["prim"][i])
        # Conditioning as tests/kernels/test_traversal.py's: relative to the farthest vertex
        # of the hit triangle, over the cosine between ray and triangle.
        corners = at[faces[ref["prim"][0]]]
        normal = np.cross(corners[1] - corners[0], corners[2] - corners[0])
        unit = d[i] / np.linalg.norm(d[i])
        cos = abs(normal @ unit) / np.linalg.norm(normal)
        reach = np.max(np.linalg.norm(corners - o[i], axis=1)) / np.linalg.norm(d[i])
        assert abs(ours["t"][i] - t_ref) <= T_REL * max(t_ref, reach) / cos, (i, ours["t"][i], t_ref)
        # The same triangle, or one the reference hits at the same distance.
        assert prim == ref["prim"][0] or \
            abs(ref["t_all"][0, prim] - t_ref) <= T_REL * max(t_ref, reach) / cos, i
    assert hits > 300  # the test exercises hits, not just misses


# ---------------------------------------------------------------------------------------
# (c) Every triangle inside its leaf's interpolated box, at any time
# ---------------------------------------------------------------------------------------


def _leaf_children(records, keys, total, root):
    """For each triangle record (slot), ``(node slot, child)`` of the leaf holding it:
    a walk down the wide nodes of key 0, a level at a time. Returns two int arrays
    indexed by slot (-1 where no leaf holds the slot)."""
    rec = records.reshape(total, keys, SLOT)
    node_of = np.full(total, -1)
    child_of = np.full(total, -1)
    frontier = np.array([root])
    while len(frontier):
        refs = rec[frontier + 1, 0, NODE_REF - SLOT:NODE_REF - SLOT + 4].view(np.uint32)
        nodes, children = np.nonzero(refs != 0xFFFFFFFF)
        ref = refs[nodes, children].astype(np.int64)
        leaf = (ref & LEAF_BIT) != 0
        first = (ref & 0x7FFFFFFF) >> 4
        count = (ref & 15) + 1
        for j in range(16):  # a leaf's slots first .. first + count - 1
            take = leaf & (count > j)
            node_of[first[take] + j] = frontier[nodes[take]]
            child_of[first[take] + j] = children[take]
        frontier = ref[~leaf]
    return node_of, child_of


def _field(rec, slot, key, field):
    """Float ``field`` (0..31 over a wide node's two slots) of ``slot`` at ``key``."""
    return rec[slot + field // SLOT, key, field % SLOT]


def _motions(rng, vertices, segments):
    """Keys of three motions of ``vertices``: a rotation by up to a turn about a random
    axis, a scale from +1 to -1 and back (through zero between keys), and a random
    displacement per vertex and key."""
    centre = vertices.mean(axis=0)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rotations = []
    for angle in np.linspace(0, 2 * np.pi * rng.random(), segments + 1):
        r = np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k
        rotations.append(((vertices - centre) @ r.T + centre).astype(np.float32))
    scales = [((vertices - centre) * s + centre).astype(np.float32)
              for s in np.where(np.arange(segments + 1) % 2, -1.0, 1.0)]
    return {"rotation": rotations, "scale_through_zero": scales,
            "random": moving_keys(vertices, rng, segments + 1, 0.3)}


@pytest.mark.parametrize("segments", [1, 2, 4])
def test03_every_triangle_lies_in_its_leafs_interpolated_box_at_any_time(segments):
    rng = np.random.default_rng(20 + segments)
    vertices, faces = triangle_grid(10, 8)  # shared vertices, leaves of several triangles
    vertices = (vertices / 5 + [3.0, -7.0, 0.5]).astype(np.float32)
    faces = faces.astype(np.uint32)
    bvh = build(vertices, faces)
    times = np.concatenate([np.linspace(0, 1, 4 * segments + 1),
                            rng.random(60), [1e-7, 1 - 2**-24]]).astype(np.float32)
    for name, keys in _motions(rng, vertices, segments).items():
        tree = keyed_tree(bvh, [flat(k) for k in keys])
        rec = tree.records.numpy().reshape(tree.slots, tree.keys, SLOT)
        node_of, child_of = _leaf_children(rec.ravel(), tree.keys, tree.slots, tree.root)
        slots = np.flatnonzero(node_of >= 0)
        assert len(slots) == len(faces)  # every triangle in a leaf
        # Every (triangle, time) pair: the kernel's keys and interpolation.
        slot = np.repeat(slots, len(times))
        time = np.tile(times, len(slots))
        rk = ray_keys(tree, mi.Float(time))
        key = rk.k.numpy().astype(np.int64)

        def at(values_of_key):
            """A field interpolated at each pair's time, as traversal reads it."""
            a, b = (mi.Float(values_of_key(key + j).astype(np.float32)) for j in (0, 1))
            return keyed_module.lerp(a, b, rk.f, rk.g).numpy()

        node, child = node_of[slot], child_of[slot]
        for axis in range(3):
            lo = at(lambda k: _field(rec, node, k, NODE_LO[axis] + child))
            hi = at(lambda k: _field(rec, node, k, NODE_HI[axis] + child))
            for c in range(3):
                p = at(lambda k: rec[slot, k, TRI_P[c] + axis])
                outside = ~((lo <= p) & (p <= hi))
                assert not outside.any(), (
                    f"{name}: {outside.sum()} vertices outside their leaf's box, e.g. "
                    f"{p[outside][:3]} not in [{lo[outside][:3]}, {hi[outside][:3]}]")


def test04_the_float_lerp_would_put_vertices_outside_their_box():
    """Why the interpolation is in double: ``fma(f, b - a, a)`` in float32 is not
    monotone (the rounding of ``b - a``), and leaves a vertex outside its interpolated
    box, what test03 would find with it. Here a box corner stays at 1e-9 (another
    vertex holds it) while this vertex goes from 1 to 1e-9: at the end of the shutter
    (f = 1) the float lerp puts it at 0, below the corner; ours at 1e-9."""
    lo_a = lo_b = np.float32(1e-9)
    p_a, p_b = np.float32(1.0), np.float32(1e-9)
    f = np.float32(1)
    naive = lambda a, b: np.float32(a + f * np.float32(b - a))  # noqa: E731
    assert naive(p_a, p_b) < naive(lo_a, lo_b)
    F64 = dr.float64_array_t(mi.Float)
    ours = lambda a, b: keyed_module.lerp(mi.Float(a), mi.Float(b), F64(f),  # noqa: E731
                                          1.0 - F64(f)).numpy()[0]
    assert ours(p_a, p_b) == p_b and ours(lo_a, lo_b) == lo_b


# ---------------------------------------------------------------------------------------
# (d) Watertight at every time
# ---------------------------------------------------------------------------------------


def _grid_point(vertices, n, u, v):
    """Points at grid coordinates ``(u, v)`` (arrays) on the mesh of
    ``triangle_grid(n, n)`` with ``vertices`` (float64): on the triangle that holds
    them, barycentrically, so a point on an edge or at a vertex depends on that edge's
    (vertex's) own vertices only."""
    i = np.minimum(np.floor(u).astype(int), n - 1)
    j = np.minimum(np.floor(v).astype(int), n - 1)
    a, b = (u - i)[:, None], (v - j)[:, None]
    corner = lambda di, dj: vertices[(j + dj) * (n + 1) + i + di]  # noqa: E731
    c00, c10, c01, c11 = corner(0, 0), corner(1, 0), corner(0, 1), corner(1, 1)
    # Each square is split along its (0,0)-(1,1) diagonal (triangle_grid's faces).
    return np.where(a >= b, c00 + a * (c10 - c00) + b * (c11 - c10),
                    c00 + b * (c01 - c00) + a * (c11 - c01))


def test05_rays_through_a_moving_grids_shared_edges_and_vertices_never_miss():
    n, segments = 8, 3
    rng = np.random.default_rng(5)
    grid, faces = triangle_grid(n, n)
    # Each key: the grid bent, turned a little about a random axis and moved (its normal
    # stays within ~45 degrees of z, and no triangle folds over).
    keys = []
    for k in range(segments + 1):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        cross = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]],
                          [-axis[1], axis[0], 0]])
        angle = 0.4 * rng.random()
        turn = np.eye(3) + np.sin(angle) * cross + (1 - np.cos(angle)) * cross @ cross
        bent = grid.astype(np.float64)
        bent[:, 2] += 0.2 * np.sin(bent[:, 0] * (k + 1) / 3)
        keys.append((bent @ turn.T + rng.normal(size=3)).astype(np.float32))
    tree = build_keyed([flat(k) for k in keys], mi.UInt32(faces.ravel()))

    # Interior vertices and points on interior edges (axis-parallel and diagonal).
    targets = [(i, j) for i in range(1, n) for j in range(1, n)]
    for f in (0.25, 0.5, 1 / 3):
        targets += [(i + f, j) for i in range(n) for j in range(1, n)]
        targets += [(i, j + f) for i in range(1, n) for j in range(n)]
        targets += [(i + f, j + f) for i in range(n) for j in range(n)]
    uv = np.tile(np.array(targets, np.float64), (6, 1))
    time = rng.random(len(uv)).astype(np.float32)
    time[:len(targets)] = rng.integers(0, segments + 1, len(targets)) / segments  # keys
    p = np.concatenate([_grid_point(at_time(keys, t), n, uv[i:i + 1, 0], uv[i:i + 1, 1])
                        for i, t in enumerate(time)])
    # From either side, 2-3 units off the surface, up to 1 unit aside: never grazing.
    side = np.where(rng.random((len(p), 1)) < 0.5, 1.0, -1.0)
    o = p + side * (2 + rng.random((len(p), 1))) * [0, 0, 1] + \
        (rng.random((len(p), 3)) - 0.5) * [2, 2, 0]
    ours = trace(tree, o.astype(np.float32), (p - o).astype(np.float32), time)
    assert ours["valid"].all(), f"{np.sum(~ours['valid'])} of {len(p)} rays slipped through"
    assert ours["any"].all()
    np.testing.assert_allclose(ours["t"], 1.0, rtol=1e-4)


# ---------------------------------------------------------------------------------------
# (e) Bad keys, and the time argument
# ---------------------------------------------------------------------------------------


def test06_bad_keys_raise_one_clear_error_naming_the_key():
    vertices, faces = triangle_grid(3, 3)
    bvh = build(vertices, faces)
    good = flat(vertices)
    with pytest.raises(ValueError, match=r"keys\[2\]: 15 vertices, but keys\[0\] has 16"):
        keyed_tree(bvh, [good, good, flat(vertices[:-1])])
    for bad in (np.nan, np.inf):
        broken = vertices.copy()
        broken[5, 1] = bad
        with pytest.raises(ValueError, match=r"keys\[1\]: 1 of 48 coordinates are non-finite"):
            keyed_tree(bvh, [good, flat(broken), good])
    with pytest.raises(ValueError, match="at least 2"):
        keyed_tree(bvh, [good])
    with pytest.raises(ValueError, match="faces index vertex 15, but each key holds 9"):
        keyed_tree(bvh, [flat(vertices[:9])] * 2)
    with pytest.raises(TypeError, match=r"keys\[1\]"):
        keyed_tree(bvh, [good, vertices])
    with pytest.raises(TypeError, match="list of the vertex positions"):
        keyed_tree(bvh, good)
    with pytest.raises(ValueError, match=r"keys\[0\]: a flat array needs 3 values"):
        build_keyed([mi.Float(1, 2), good], mi.UInt32(faces.ravel()))


def test07_time_argument_clamped_nan_misses_and_still_trees_ignore_it():
    vertices, faces = triangle_grid(2, 2)
    keys = [vertices, vertices + np.float32([0, 0, 1])]
    tree = build_keyed([flat(k) for k in keys], mi.UInt32(faces.ravel()))
    o, d = mi.Point3f(0.5, 0.7, 5), mi.Vector3f(0, 0, -1)
    t = lambda time: closest_hit(tree, o, d, 100.0, time=time)[0].numpy()  # noqa: E731
    np.testing.assert_array_equal(t(mi.Float(-3, 0, 0.25, 1, 7)), [5, 5, 4.75, 4, 4])
    assert np.isinf(t(mi.Float(np.nan)))[0] and not any_hit(tree, o, d, 100.0, time=mi.Float(np.nan))[0]
    with pytest.raises(ValueError, match="pass time="):
        closest_hit(tree, o, d, 100.0)
    # The facades, with a Python float time.
    ray = mi.Ray3f(o, d)
    assert intersect(tree, ray, time=0.5).t[0] == pytest.approx(4.5)
    assert occluded(tree, ray, time=0.5)[0]
    # A still tree is the same at every time.
    bvh = build(vertices, faces)
    assert closest_hit(bvh, o, d, 100.0, time=mi.Float(0.3))[0][0] == 5
    # Keys as Point3f (V) make the same tree as flat keys (3·V).
    points = keyed_tree(tree.bvh, [mi.Point3f(k.T) for k in keys])
    np.testing.assert_array_equal(points.records.numpy(), tree.records.numpy())


def test08_a_triangle_flat_at_one_key_is_hit_between_keys():
    """A still tree packs a zero-area triangle with NaN vertices; a keyed tree keeps the
    vertices of a triangle flat only at some keys (here: collapsed to a line at key 1)."""
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    collapsed = np.array([[0, 0, 0], [1, 0, 0], [0.5, 0, 0]], np.float32)
    faces = np.array([[0, 1, 2]], np.uint32)
    tree = build_keyed([flat(vertices), flat(collapsed), flat(vertices)],
                       mi.UInt32(faces.ravel()))
    o, d = mi.Point3f(0.3, 0.1, 1), mi.Vector3f(0, 0, -1)
    valid = closest_hit(tree, o, d, 10.0, time=mi.Float(0, 0.2, 0.4, 0.6, 0.8, 1))[4].numpy()
    np.testing.assert_array_equal(valid, [True, True, True, True, True, True])
    # Flat at every key: never hit (as the still tree).
    tree = build_keyed([flat(collapsed)] * 2, mi.UInt32(faces.ravel()))
    assert not closest_hit(tree, o, d, 10.0, time=mi.Float(0.5))[4][0]


def test09_traced_inside_a_symbolic_loop():
    """An integrator traces inside its own symbolic loop, each bounce at the ray's time."""
    vertices, faces = triangle_grid(1, 1)
    tree = build_keyed([flat(vertices), flat(vertices + np.float32([0, 0, 1]))],
                       mi.UInt32(faces.ravel()))

    def body(i, total):
        t = closest_hit(tree, mi.Point3f(0.3, 0.3, 5), mi.Vector3f(0, 0, -1), 100.0,
                        time=mi.Float(i) / 4)[0]
        return i + 1, total + t

    _, total = dr.while_loop((dr.zeros(mi.UInt32, 8), dr.zeros(mi.Float, 8)),
                             lambda i, total: i < 5, body, mode="symbolic")
    np.testing.assert_allclose(total.numpy(), 5 + 4.75 + 4.5 + 4.25 + 4)


# ---------------------------------------------------------------------------------------
# (f) The keyed tree's SAH over the shutter, and the topology it is built over
# ---------------------------------------------------------------------------------------


def _key_node_boxes(bvh, keys, faces):
    """Each binary node's box (lo, hi: (N, 3) float64) at each key, by recursion over
    the tree's arrays (a tiny tree)."""
    first, count = bvh.node_first.numpy(), bvh.node_count.numpy()
    prims = bvh.prim_ids.numpy()
    boxes = []
    for key in keys:
        tri = np.asarray(key, np.float64)[faces]  # (F, 3, 3)
        lo, hi = np.empty((len(first), 3)), np.empty((len(first), 3))

        def visit(n):
            if count[n]:
                corners = tri[prims[first[n]:first[n] + count[n]]].reshape(-1, 3)
                lo[n], hi[n] = corners.min(0), corners.max(0)
            else:
                for c in (first[n], first[n] + 1):
                    visit(c)
                lo[n] = np.minimum(lo[first[n]], lo[first[n] + 1])
                hi[n] = np.maximum(hi[first[n]], hi[first[n] + 1])
        visit(0)
        boxes.append((lo, hi))
    return boxes


def _brute_sah_over_time(bvh, keys, faces, samples=4001):
    """The SAH over the shutter by brute force: at ``samples`` times, each node's box
    interpolated between its boxes at the two keys around the time, the weighted sum of
    half areas and the root's, each averaged over the times, then divided."""
    boxes = _key_node_boxes(bvh, keys, faces)
    count = bvh.node_count.numpy()
    weight = np.where(count == 0, 1.0, count)
    s = len(keys) - 1
    total = root = 0.0
    for time in (np.arange(samples) + 0.5) / samples:
        k = min(int(time * s), s - 1)
        f = time * s - k
        lo = (1 - f) * boxes[k][0] + f * boxes[k + 1][0]
        hi = (1 - f) * boxes[k][1] + f * boxes[k + 1][1]
        e = hi - lo
        area = e[:, 0] * e[:, 1] + e[:, 1] * e[:, 2] + e[:, 2] * e[:, 0]
        total += weight @ area
        root += area[0]
    return total / root


@pytest.mark.parametrize("segments", [1, 3])
def test10_sah_over_shutter_is_the_exact_average_of_the_interpolated_boxes(segments):
    rng = np.random.default_rng(20 + segments)
    vertices, faces = random_soup(24, seed=5)
    keys = moving_keys(vertices, rng, segments + 1, 0.15)
    tree = build_keyed([flat(k) for k in keys], mi.UInt32(faces.ravel()), topology="mid",
                       leaf_size=2)
    expected = _brute_sah_over_time(tree.bvh, keys, faces)
    assert tree.sah == pytest.approx(expected, rel=1e-6)
    # The average of the SAH at each instant is another number (the quadratic's ratio):
    # what is computed is the ratio of the integrals, not a sample at the keys.
    at_keys = np.mean([keyed_module.sah_over_shutter(tree.bvh, [flat(k)] * 2) for k in keys])
    assert abs(at_keys - expected) > 1e-3 * expected
    # Equal keys: the still tree's SAH cost at that pose.
    still = build(keys[0], faces, leaf_size=2)
    assert keyed_module.sah_over_shutter(still, [flat(keys[0])] * 3) == \
        pytest.approx(float(still.stats.sah_cost), rel=1e-9)
    assert tree.still_sah == pytest.approx(float(keyed_module.build(
        keyed_module.mid_shutter([flat(k) for k in keys]), mi.UInt32(faces.ravel()),
        leaf_size=2).stats.sah_cost), rel=1e-9)


def _swap_keys(seed=6, count=400):
    """A soup whose triangles trade places over the shutter: key 1 is key 0 with every
    triangle moved to where a random other triangle was (the tree built at mid-shutter,
    where the triangles are halfway, groups triangles that are far apart at both ends)."""
    vertices, faces = random_soup(count, seed=seed)
    tri = vertices.reshape(count, 3, 3)
    centre = tri.mean(1, keepdims=True)
    order = np.random.default_rng(seed).permutation(count)
    moved = (tri - centre + centre[order]).reshape(-1, 3).astype(np.float32)
    return vertices, moved, faces


def test11_a_scrambling_motion_degrades_and_builds_the_union_topology():
    vertices, moved, faces = _swap_keys()
    keys, f = [flat(vertices), flat(moved)], mi.UInt32(faces.ravel())
    mid = build_keyed(keys, f, topology="mid", builder="sah")
    union = build_keyed(keys, f, topology="union", builder="sah")
    assert mid.topology == "mid" and union.topology == "union"
    assert mid.degradation > 1.5  # the mid-shutter tree's boxes sweep the scene
    assert union.sah < 0.98 * mid.sah
    chosen = build_keyed(keys, f, topology="auto", tolerance=1.05, builder="sah")
    assert chosen.topology == "union" and chosen.sah == pytest.approx(union.sah)
    # A tolerance above the degradation keeps the mid-shutter tree; so does a Morton
    # builder, whose union topology is its mid-shutter one (the same box centres).
    assert build_keyed(keys, f, topology="auto", tolerance=mid.degradation * 1.01,
                       builder="sah").topology == "mid"
    assert build_keyed(keys, f, topology="auto", tolerance=1.05).topology == "mid"
    # The union topology traces the same hits as the mid-shutter one (any topology is
    # a correct keyed tree).
    rng = np.random.default_rng(3)
    o = (rng.random((3000, 3)) * 1.4 - 0.2).astype(np.float32)
    d = rng.normal(size=(3000, 3)).astype(np.float32)
    time = rng.random(3000).astype(np.float32)
    a, b = trace(mid, o, d, time), trace(chosen, o, d, time)
    assert a["valid"].sum() > 300
    np.testing.assert_array_equal(a["valid"], b["valid"])
    np.testing.assert_allclose(a["t"][a["valid"]], b["t"][b["valid"]], rtol=1e-6)


def test12_a_still_or_rigid_shutter_keeps_the_mid_shutter_topology():
    vertices, faces = random_soup(300, seed=8)
    f = mi.UInt32(faces.ravel())
    for keys in ([vertices] * 3, [vertices, vertices + np.float32([0.3, -0.2, 0.1])]):
        tree = build_keyed([flat(k) for k in keys], f, topology="auto")
        assert tree.topology == "mid"
        assert tree.degradation == pytest.approx(1.0, abs=1e-6)
    with pytest.raises(ValueError, match="topology='sideways'"):
        build_keyed([flat(vertices)] * 2, f, topology="sideways")
