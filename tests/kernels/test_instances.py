"""Two levels (rigid motion): instances of shared geometry under a top-level tree over
their world boxes; closest and any hits equal a float64 brute force over every
instance's world-space triangles, for rotated, scaled, mirrored and translated
instances sharing groups, before and after the instances move (only the top level
rebuilt)."""

import drjit as dr
import hlbvh
import mitsuba as mi
import numpy as np
import pytest

from hlbvh.kernels.instances import two_level, world_boxes
from hlbvh.kernels.layout.packing import packed_records
from hlbvh.kernels.traversal import any_hit, closest_instance_hit
from reference import brute_force, random_soup, triangle_grid


def _rotation(rng):
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    angle = rng.uniform(0, 2 * np.pi)
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def _transforms(rng, count):
    """Rows (A row-major, b) of ``count`` transforms: rotations times non-uniform,
    partly mirroring scales, and translations."""
    rows = []
    for _ in range(count):
        a = _rotation(rng) @ np.diag(rng.uniform(0.3, 2.0, 3) * rng.choice([-1, 1], 3))
        rows.append(np.concatenate([a.ravel(), rng.uniform(-3, 3, 3)]))
    return np.asarray(rows, np.float32)


GROUPS = [random_soup(300, 1), (triangle_grid(6, 4)[0] / 6.0, triangle_grid(6, 4)[1])]


def _world(rows, groups_of):
    """Every instance's world-space triangles (float64) and each one's (instance, face
    counted over the groups)."""
    face_base = np.cumsum([0] + [len(f) for _, f in GROUPS])
    vertices, faces, owner, base = [], [], [], 0
    for k, (row, g) in enumerate(zip(rows, groups_of)):
        v, f = GROUPS[g]
        a, b = row[:9].reshape(3, 3).astype(np.float64), row[9:].astype(np.float64)
        vertices.append(v.astype(np.float64) @ a.T + b)
        faces.append(f + base)
        owner += [(k, face_base[g] + i) for i in range(len(f))]
        base += len(v)
    return np.concatenate(vertices), np.concatenate(faces), np.array(owner)


def _check(tl, rows, groups_of, rng, n=3000):
    vertices, faces, owner = _world(rows, groups_of)
    # From anywhere, towards points near the instances' vertices (plenty of hits and
    # misses both); every tenth ray in a random direction.
    o = rng.uniform(-5, 5, (n, 3))
    d = vertices[rng.integers(len(vertices), size=n)] + rng.normal(0, 0.1, (n, 3)) - o
    d[::10] = rng.normal(size=(len(d[::10]), 3))
    ref = brute_force(vertices, faces, o, d)
    ray = (mi.Point3f(*o.T.astype(np.float32)), mi.Vector3f(*d.T.astype(np.float32)),
           mi.Float(np.inf))
    t, u, v, prim, inst, valid = (np.array(x) for x in closest_instance_hit(tl, *ray))
    assert ref["valid"].sum() > 50
    assert np.mean(valid == ref["valid"]) >= 1 - 2 / n
    both = valid & ref["valid"]
    np.testing.assert_allclose(t[both], ref["t"][both], rtol=1e-4, atol=1e-5)
    ours = np.stack([inst, prim], 1)[both]
    tied = [np.any(np.all(owner[np.abs(ref["t_all"][r] - ref["t"][r]) <= 1e-5 * (1 + ref["t"][r])]
                          == h, axis=1)) for r, h in zip(np.flatnonzero(both), ours)]
    assert np.mean(tied) >= 1 - 2 / n
    occluded = np.array(any_hit(tl, *ray))
    assert np.mean(occluded == ref["valid"]) >= 1 - 2 / n


@pytest.mark.parametrize("count", [1, 12, 40])
def test01_instances_hit_as_their_world_triangles(count):
    """Closest hits (t, instance, face) and any hits against a float64 brute force over
    the instances' world-space triangles."""
    rng = np.random.default_rng(count)
    bvhs = [hlbvh.build(mi.Float(v.ravel()), mi.UInt32(f.ravel())) for v, f in GROUPS]
    rows = _transforms(rng, count)
    groups_of = [k % 2 for k in range(count)]
    tl, _ = two_level(bvhs, mi.UInt32(groups_of), mi.Float(rows.ravel()))
    _check(tl, rows, groups_of, rng)


def test02_moving_instances_rebuild_only_the_top_level():
    """New transforms: the geometry trees stay the same objects (and slots), the top
    level is rebuilt (seeded by the last one), and the hits follow the new poses."""
    rng = np.random.default_rng(7)
    bvhs = [hlbvh.build(mi.Float(v.ravel()), mi.UInt32(f.ravel())) for v, f in GROUPS]
    groups_of = [k % 2 for k in range(20)]
    rows = _transforms(rng, 20)
    tl, top = two_level(bvhs, mi.UInt32(groups_of), mi.Float(rows.ravel()))
    rows = rows.copy()
    rows[:, 9:] += rng.uniform(-0.5, 0.5, (20, 3)).astype(np.float32)  # every instance moves
    tl2, top2 = two_level(bvhs, mi.UInt32(groups_of), mi.Float(rows.ravel()), previous=top,
                          config=hlbvh.BuildConfig(leaf_size=4))
    assert top2 is not top and top2.prim_count == 20
    # Every top-level leaf holds one instance, whatever the config's leaf size (a ray
    # enters an instance only past a test of its own box)
    assert top2.stats.leaf_count == 20 and top2.stats.leaf_histogram == [20]
    _check(tl2, rows, groups_of, rng)


def test03_world_boxes_hold_every_world_vertex():
    rng = np.random.default_rng(3)
    bvhs = [hlbvh.build(mi.Float(v.ravel()), mi.UInt32(f.ravel())) for v, f in GROUPS]
    rows = _transforms(rng, 10)
    groups_of = [k % 2 for k in range(10)]
    lo, hi = (np.array(x).T for x in world_boxes(bvhs, mi.UInt32(groups_of),
                                                  mi.Float(rows.ravel())))
    for k, (row, g) in enumerate(zip(rows, groups_of)):
        v = GROUPS[g][0].astype(np.float64) @ row[:9].reshape(3, 3).T + row[9:]
        assert (v >= lo[k] - 1e-5).all() and (v <= hi[k] + 1e-5).all()


def test04_a_singular_transform_is_refused():
    bvhs = [hlbvh.build(mi.Float(v.ravel()), mi.UInt32(f.ravel())) for v, f in GROUPS]
    rows = _transforms(np.random.default_rng(1), 2)
    rows[1, :9] = np.diag([1.0, 0.0, 1.0]).ravel()  # a scale of 0
    with pytest.raises(ValueError, match=r"^instance 1: its transform is singular \(a scale of 0\)$"):
        two_level(bvhs, mi.UInt32([0, 1]), mi.Float(rows.ravel()))
    rows[1, 0] = np.nan
    with pytest.raises(ValueError, match="^instance 1: its transform is not finite$"):
        two_level(bvhs, mi.UInt32([0, 1]), mi.Float(rows.ravel()))


@pytest.mark.parametrize("leaf_size", [1, 4])
def test05_the_top_level_is_written_in_place_behind_the_kept_trees(leaf_size):
    """Frame after frame, rebuilt and refit, the top level goes into the room kept
    behind the geometry trees' slots (no copy of them): the same records array, the
    room enough for any top level over as many instances, the trees' slots untouched,
    and the hits those of the new poses."""
    from hlbvh.kernels.instances import refit_top_level, top_level_room
    from hlbvh.kernels.layout.slots import SLOT

    rng = np.random.default_rng(11)
    config = hlbvh.BuildConfig(leaf_size=leaf_size)
    bvhs = [hlbvh.build(mi.Float(v.ravel()), mi.UInt32(f.ravel())) for v, f in GROUPS]
    groups_of = [k % 2 for k in range(33)]
    which = mi.UInt32(groups_of)
    rows = _transforms(rng, 33)
    tl, top = two_level(bvhs, which, mi.Float(rows.ravel()), config)
    trees = np.array(tl.records)[:SLOT * tl.top_base]
    assert tl.groups.room == top_level_room(33)
    for step in range(4):
        rows = rows.copy()
        rows[:, 9:] += rng.uniform(-1.5, 1.5, (33, 3)).astype(np.float32)
        if step % 2:
            new = refit_top_level(top, bvhs, which, mi.Float(rows.ravel()), kept=tl)
        else:
            new, top = two_level(bvhs, which, mi.Float(rows.ravel()), config,
                                 previous=top, kept=tl)
        assert new.records is tl.records and new.groups is tl.groups
        used = dr.width(packed_records(top, tl.top_base)[0]) // SLOT
        assert used <= tl.groups.room
        assert np.array_equal(np.array(new.records)[:SLOT * tl.top_base], trees, equal_nan=True)
        _check(new, rows, groups_of, rng, n=1500)
        tl = new
    for m in (1, 2, 3, 100, 1000):  # any tree over m instances fits its room
        lone = two_level(bvhs[:1], mi.UInt32(np.zeros(m, np.uint32)),
                         mi.Float(_transforms(rng, m).ravel()), config)[0]
        assert lone.records is lone.groups.records
