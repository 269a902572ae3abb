"""SceneAccel's per-frame update: static meshes kept, moving ones rebuilt (seeded with
last frame's order), refit or rebuilt as the ``update`` policy says; hits checked
against Mitsuba's native accelerator after every frame of every animated scene kind."""

import math

import drjit as dr
import hlbvh
import mitsuba as mi
import numpy as np
import pytest
from hlbvh import scenes
from hlbvh.kernels.traversal import any_hit, closest_hit

from reference import tree_sah_cost
from test_accel import _compare_preliminary, bounce_rays, camera_rays

#: Frames applied after frame 0 (of a 40-frame animation: poses far enough apart for
#: refit trees to drift).
FRAMES = (8, 16, 24)


def load(name, triangles=3000, **options):
    """An animated scene loaded at frame 0 (small: a few thousand triangles)."""
    animation = scenes.get(name, triangles=triangles, frames=40, **options)
    scene = mi.load_dict(animation.scene_dict(resolution=(24, 24), spp=2,
                                              integrator=dict(type="path", max_depth=4)))
    params = mi.traverse(scene)
    scenes.apply_frame(scene, params, animation.frame(0))
    return animation, scene, params


def shape_indices(scene, ids) -> tuple:
    """Indices into scene.shapes() of the shapes with these ids, ascending."""
    return tuple(sorted(i for i, s in enumerate(scene.shapes()) if s.id() in ids))


def rays(scene):
    """Camera rays (coherent) and rays from random points in random directions."""
    return ((True, camera_rays(scene, 64)), (False, bounce_rays(scene, seed=11)))


def assert_hits_equal_native(accel, scene, static=()):
    """Closest hits and shadow tests of ``accel`` equal the scene's on all but 2 of
    4096 rays (test_accel's tolerance and tie handling); so do the closest hits of the
    rays whose native hit lies on one of the ``static`` shapes."""
    for coherent, ray in rays(scene):
        n = dr.width(ray)
        ours = accel.ray_intersect_preliminary(ray, coherent)
        theirs = scene.ray_intersect_preliminary(ray, coherent)
        assert _compare_preliminary(ray, ours, theirs) >= 1 - 2 / n
        occluded = np.array(accel.ray_test(ray, coherent, True))
        assert np.mean(occluded == np.array(scene.ray_test(ray, coherent, True))) >= 1 - 2 / n
        np.testing.assert_array_equal(occluded, np.array(ours.is_valid()))
        if static:
            on_static = np.isin(np.array(theirs.shape_index), static) & np.array(theirs.is_valid())
            assert on_static.sum() > 0
            same = ((np.array(ours.shape_index) == np.array(theirs.shape_index))
                    & (np.array(ours.prim_index) == np.array(theirs.prim_index)))
            assert (~same[on_static]).sum() <= 2


# ---------------------------------------------------------------------------------------
# Every scene kind, every policy: hits equal native after each frame
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("update", ["rebuild", "refit", "auto"])
@pytest.mark.parametrize("name", [n for n in scenes.names() if n != "flock"])
def test01_hits_equal_native_after_every_frame(name, update):
    """(Every mesh scene: flock's instances need static="native",
    tests/accel/test_flock.py.) Frame 0 builds one static group; the first frame that moves
    the animated meshes moves them to the dynamic group (the static BVH is rebuilt once
    without them); later frames keep the static BVH (same object, no build) and update only
    the dynamic one. Hits, on static shapes too, equal native after every frame."""
    animation, scene, params = load(name)
    accel = hlbvh.SceneAccel(scene, static="hlbvh", update=update)
    static = shape_indices(scene, animation.static_ids())
    animated = shape_indices(scene, animation.animated_ids())
    assert accel.last_update["decision"] == "build" and accel.static.indices == accel.meshes
    assert_hits_equal_native(accel, scene)
    for k, i in enumerate(FRAMES):
        scenes.apply_frame(scene, params, animation.frame(i))
        static_bvh, static_builds = accel.static.bvh, accel.static.builds
        accel.update()
        assert accel.static.indices == static and accel.dynamic.indices == animated
        groups = accel.last_update["groups"]
        if k == 0:
            assert groups["static"]["decision"] == "rebuild" and accel.static.builds == 2
            assert groups["dynamic"]["decision"] == "rebuild"
        else:
            assert accel.static.bvh is static_bvh and accel.static.builds == static_builds == 2
            assert groups["static"]["decision"] == "kept" and groups["static"]["ms"] == 0
            expected = {"rebuild": {"rebuild"}, "refit": {"refit"},
                        "auto": {"refit", "rebuild"}}[update]
            assert groups["dynamic"]["decision"] in expected
        assert accel.last_update["triangles"] == sum(
            s.face_count() for s in scene.shapes() if s.is_mesh())
        assert_hits_equal_native(accel, scene, static)


def test02_nothing_changed_keeps_everything():
    animation, scene, params = load("rigid")
    accel = hlbvh.SceneAccel(scene, static="hlbvh")
    scenes.apply_frame(scene, params, animation.frame(3))
    accel.update()
    bvhs = accel.static.bvh, accel.dynamic.bvh
    assert not accel.changed()
    accel.update()
    assert accel.last_update["decision"] == "kept"
    assert (accel.static.bvh, accel.dynamic.bvh) == bvhs
    assert (accel.static.builds, accel.dynamic.builds) == (2, 1)


# ---------------------------------------------------------------------------------------
# Temporal coherence and refit
# ---------------------------------------------------------------------------------------


def _trace(bvh, ray):
    t, u, v, prim, valid = closest_hit(bvh, ray.o, ray.d, ray.maxt)
    occluded = any_hit(bvh, ray.o, ray.d, ray.maxt)
    return tuple(np.array(x) for x in (t, prim, valid, occluded))


@pytest.mark.parametrize("name", ["cloth", "fracture"])
def test03_seeded_build_gives_the_hits_of_a_fresh_build(name):
    """A build whose CSD sort starts from last frame's order gives the tree of a build
    from scratch (the same nodes; primitives with equal Morton keys may come in last
    frame's order instead of index order: measured, a few dozen swapped neighbours of
    2852) and the same hits: same validity and occlusion everywhere, the same t on the
    same triangle, another triangle only at the same t (a tie). SceneAccel offers its
    rebuilds last frame's order when the triangle count is unchanged."""
    animation, scene, params = load(name)
    accel = hlbvh.SceneAccel(scene, static="hlbvh")
    ray = bounce_rays(scene, seed=2)
    for i in FRAMES:
        previous = accel.dynamic.bvh
        scenes.apply_frame(scene, params, animation.frame(i))
        accel.update()
        # Seeded where last frame's order was offered and paid (kernels.csd.seed_pays).
        seeded_now = accel.last_update["groups"]["dynamic"]["seeded"]
        assert seeded_now == (previous is not None and accel.dynamic.bvh.stats.csd_seeded)
        if previous is None:
            continue
        geometry = accel.dynamic.geometry
        seeded = hlbvh.build(geometry.vertices, geometry.faces, previous=previous)
        fresh = hlbvh.build(geometry.vertices, geometry.faces)
        for field in ("node_first", "node_count"):
            np.testing.assert_array_equal(getattr(seeded, field), getattr(fresh, field))
        assert seeded.stats.sah_cost == pytest.approx(fresh.stats.sah_cost, rel=1e-6)
        (t_s, prim_s, valid_s, occluded_s), (t_f, prim_f, valid_f, occluded_f) = (
            _trace(seeded, ray), _trace(fresh, ray))
        np.testing.assert_array_equal(valid_s, valid_f)
        np.testing.assert_array_equal(occluded_s, occluded_f)
        same = (prim_s == prim_f)[valid_s]
        np.testing.assert_array_equal(t_s[valid_s][same], t_f[valid_s][same])
        np.testing.assert_allclose(t_s[valid_s][~same], t_f[valid_s][~same], rtol=1e-5)
        assert (~same).sum() <= 2


@pytest.mark.parametrize("name", ["cloth", "twist", "fracture"])
def test04_refit_hits_equal_rebuild_hits(name):
    """A refit tree is slower, never wrong: its closest and any hits equal a rebuilt
    tree's (same validity; same t on the same triangle; another triangle only at the
    same t, a tie on a shared edge, at most 2 of 4096 rays)."""
    animation, scene, params = load(name)
    refit = hlbvh.SceneAccel(scene, static="hlbvh", update="refit")
    rebuild = hlbvh.SceneAccel(scene, static="hlbvh", update="rebuild")
    for i in FRAMES:
        scenes.apply_frame(scene, params, animation.frame(i))
        refit.update()
        rebuild.update()
        for _, ray in rays(scene):
            a = refit.ray_intersect_preliminary(ray)
            b = rebuild.ray_intersect_preliminary(ray)
            valid = np.array(a.is_valid())
            np.testing.assert_array_equal(valid, np.array(b.is_valid()))
            same = ((np.array(a.shape_index) == np.array(b.shape_index))
                    & (np.array(a.prim_index) == np.array(b.prim_index)))[valid]
            t_a, t_b = np.array(a.t)[valid], np.array(b.t)[valid]
            np.testing.assert_array_equal(t_a[same], t_b[same])
            np.testing.assert_allclose(t_a[~same], t_b[~same], rtol=1e-5)
            assert (~same).sum() <= 2
            np.testing.assert_array_equal(refit.ray_test(ray), rebuild.ray_test(ray))
        assert_hits_equal_native(refit, scene)  # and both are right: native agrees
    assert refit.dynamic.builds == 1 and refit.dynamic.refits == len(FRAMES) - 1
    assert rebuild.dynamic.refits == 0


def _reference_cost(group) -> float:
    """tests/reference.py's SAH cost of a group's tree over its current triangles."""
    bvh, geometry = group.bvh, group.geometry
    return tree_sah_cost(np.array(geometry.vertices).reshape(-1, 3),
                         np.array(geometry.faces).reshape(-1, 3), np.array(bvh.node_first),
                         np.array(bvh.node_count), np.array(bvh.prim_ids))


def test05_auto_rebuilds_when_the_refit_tree_drifts():
    """A soup re-scattered every frame: the refit tree's SAH cost explodes, so "auto"
    rebuilds (reporting the drift it saw), and after two, three, four refits rejected in
    a row it rebuilds without trying one for 1, 3, 7 updates; a cloth's gentle
    deformation stays refit. With an unbounded tolerance "auto" refits the soup like
    "refit" does."""
    animation, scene, params = load("soup")
    auto = hlbvh.SceneAccel(scene, static="hlbvh", update="auto", refit_tolerance=1.3)
    lax = hlbvh.SceneAccel(scene, static="hlbvh", update="auto", refit_tolerance=1e30)
    tried = []
    for k, i in enumerate(range(1, 11)):
        scenes.apply_frame(scene, params, animation.frame(i))
        auto.update()
        lax.update()
        if k == 0:
            continue  # the animated meshes left the static group: a rebuild
        dynamic = auto.last_update["groups"]["dynamic"]
        assert dynamic["decision"] == "rebuild"
        if dynamic["drift"] is not None:
            tried.append(k)
            assert dynamic["drift"] > 1.3
        # The cost reported is the tree's for this frame's triangles (a numpy reference
        # recomputes every box from them), not a stale build's.
        assert dynamic["sah_cost"] == pytest.approx(_reference_cost(auto.dynamic), rel=1e-5)
        assert lax.last_update["groups"]["dynamic"]["decision"] == "refit"
        assert lax.last_update["groups"]["dynamic"]["drift"] > 1.3
        if k in (1, 3, 9):
            assert_hits_equal_native(auto, scene)
            assert_hits_equal_native(lax, scene)
    assert tried == [1, 2, 4, 8] and auto.dynamic.refits == len(tried)

    animation, scene, params = load("cloth")
    auto = hlbvh.SceneAccel(scene, static="hlbvh", update="auto")
    for i in (1, 2, 3):
        scenes.apply_frame(scene, params, animation.frame(i))
        auto.update()
    dynamic = auto.last_update["groups"]["dynamic"]
    assert dynamic["decision"] == "refit" and dynamic["drift"] <= 1.3


def test06_new_faces_force_a_rebuild():
    """Under "refit": fewer triangles, or the same number of other triangles, rebuild
    (seeded only when the count is unchanged); hits follow native."""
    animation, scene, params = load("cloth")
    accel = hlbvh.SceneAccel(scene, static="hlbvh", update="refit")
    flag = animation.frame(1)["flag"]
    scenes.apply_frame(scene, params, {"flag": flag})
    accel.update()
    faces = np.array(params["flag.faces"]).reshape(-1, 3)
    changes = [faces[::-1], faces[: len(faces) // 2]]  # same count, other order; fewer
    for new_faces in changes:
        frame = scenes.FrameGeometry(np.array(flag.positions), new_faces.ravel())
        scenes.apply_frame(scene, params, {"flag": frame})
        accel.update()
        dynamic = accel.last_update["groups"]["dynamic"]
        assert dynamic["decision"] == "rebuild" and dynamic["triangles"] == len(new_faces)
        assert dynamic["seeded"] == (new_faces is changes[0])
        assert_hits_equal_native(accel, scene)
    assert accel.dynamic.refits == 0


# ---------------------------------------------------------------------------------------
# Options and bad input
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("options, message", [
    (dict(update="sometimes"), "update='sometimes'"),
    (dict(update="auto", refit_tolerance=0.9), "refit_tolerance=0.9"),
    (dict(refit_tolerance=math.nan), "refit_tolerance=nan"),
    (dict(refit_tolerance="1.3"), "refit_tolerance='1.3'"),
    (dict(refit_tolerance=True), "refit_tolerance=True"),
    (dict(updates="auto"), "updates"),
    (dict(static_builder="best"), "static_builder='best'"),
    (dict(static_leaf_size=0), "static_leaf_size=0"),
    (dict(static_leaf_size="small"), "static_leaf_size='small'"),
    (dict(static_leaf_size=True), "static_leaf_size=True"),
])
@pytest.mark.parametrize("accel", ["hlbvh", "native"])
def test07_bad_update_options_name_the_option(accel, options, message):
    _, scene, _ = load("cloth", triangles=200)
    with pytest.raises(ValueError, match=message):
        hlbvh.make_accel(scene, accel, **options)
    with pytest.raises(Exception, match=message):
        mi.load_dict(dict(type="hlbvh_path", **options))


@pytest.mark.parametrize("restore", ["next frame", "same array"])
def test08_non_finite_positions_name_the_mesh(restore):
    """Whether the update would rebuild (first change) or refit (later ones); after
    the error, good positions trace again, be they new or the very array (the same JIT
    variable) the mesh had before the failed update."""
    animation, scene, params = load("cloth", triangles=500)
    accel = hlbvh.SceneAccel(scene, static="hlbvh", update="refit")
    flag = next(s for s in scene.shapes() if s.id() == "flag")
    for i in (1, 2):
        before = flag.vertex_positions_buffer()  # params[...] would be updated in place
        positions = np.array(before)
        positions[7] = np.inf
        params["flag.vertex_positions"] = mi.Float(positions)
        params.update()
        with pytest.raises(ValueError, match="'flag' \\(Mesh\\) has non-finite"):
            accel.update()
        if restore == "same array":
            params["flag.vertex_positions"] = before
            params.update()
        else:
            scenes.apply_frame(scene, params, animation.frame(i))
        accel.update()
        assert accel.last_update["triangles"] == sum(
            s.face_count() for s in scene.shapes() if s.is_mesh())
        assert_hits_equal_native(accel, scene)


# ---------------------------------------------------------------------------------------
# Renders through the integrator
# ---------------------------------------------------------------------------------------

INTEGRATOR_XML = """
<integrator type="hlbvh_path" version="3.0.0">
    <integer name="max_depth" value="4"/>
    <string name="update" value="auto"/>
    <float name="refit_tolerance" value="1.2"/>
    <string name="moving_accel" value="hlbvh"/>
</integrator>
"""


def test09_renders_with_refit_and_auto_match_native():
    """hlbvh_path with update="refit" (from a dict) and "auto" (from XML), our HLBVH
    tracing the moving meshes, against native, frame by frame: test_integrators' tolerance (5e-4 absolute + 1e-4 relative
    per pixel, one pixel may exceed it, mean difference below 1e-6)."""
    animation, scene, params = load("cloth")
    native = mi.load_dict(dict(type="hlbvh_path", accel="native", max_depth=4))
    ours = {"refit": mi.load_dict(dict(type="hlbvh_path", max_depth=4, update="refit",
                                       moving_accel="hlbvh")),
            "auto": mi.load_string(INTEGRATOR_XML)}
    for i in (0,) + FRAMES:
        scenes.apply_frame(scene, params, animation.frame(i))
        reference = np.array(mi.render(scene, integrator=native, seed=i))
        for update, integrator in ours.items():
            image = np.array(mi.render(scene, integrator=integrator, seed=i))
            diff = np.abs(image - reference)
            outside = (diff > 5e-4 + 1e-4 * np.abs(reference)).any(axis=-1)
            assert outside.sum() <= 1, f"{update}, frame {i}: {outside.sum()} pixels, max {diff.max()}"
            assert diff.mean() < 1e-6
    refit, auto = (ours[k].accel(scene) for k in ("refit", "auto"))
    assert refit.policy.update == "refit" and refit.dynamic.refits == len(FRAMES) - 1
    assert (auto.policy.update, auto.policy.refit_tolerance) == ("auto", 1.2)
    assert auto.dynamic.refits == len(FRAMES) - 1


@pytest.mark.parametrize("static_builder, static_leaf_size, expected, leaf", [
    ("sah", "auto", "sah", 2), ("same", "auto", "lbvh", 4), ("sah", "same", "sah", 4),
    ("same", 3, "lbvh", 3),
])
def test10_the_static_group_is_rebuilt_once_with_the_static_builder(
        static_builder, static_leaf_size, expected, leaf):
    """After the first motion the static group (built once, traced every frame) gets
    the static builder and leaf size ("auto": leaves of 2 for "sah"); the dynamic group
    keeps the scene's; hits stay native's."""
    animation, scene, params = load("cloth")
    accel = hlbvh.SceneAccel(scene, static="hlbvh", builder="lbvh", static_builder=static_builder,
                             static_leaf_size=static_leaf_size)
    assert accel.static.bvh.stats.builder == "lbvh"  # first build: nothing known to move
    scenes.apply_frame(scene, params, animation.frame(8))
    accel.update()
    assert accel.static.bvh.stats.builder == expected
    assert accel.static.bvh.config.leaf_size == leaf
    assert 1 < int(np.max(np.array(accel.static.bvh.node_count))) <= leaf
    assert accel.dynamic.bvh.stats.builder == "lbvh"
    assert accel.dynamic.bvh.config.leaf_size == 4
    static_bvh = accel.static.bvh
    scenes.apply_frame(scene, params, animation.frame(16))
    accel.update()
    assert accel.static.bvh is static_bvh
    assert_hits_equal_native(accel, scene, shape_indices(scene, animation.static_ids()))


def test11_fresh_rebuilds_without_last_frames_order_and_hits_equal_native():
    """update="fresh" (temporal reuse off) rebuilds unseeded; "rebuild" seeds."""
    for update, seeded in (("fresh", False), ("rebuild", True)):
        animation, scene, params = load("cloth")
        accel = hlbvh.SceneAccel(scene, static="hlbvh", update=update)
        for frame in (8, 16):
            scenes.apply_frame(scene, params, animation.frame(frame))
            accel.update()
        assert accel.last_update["groups"]["dynamic"]["seeded"] is seeded
        assert accel.last_update["groups"]["dynamic"]["decision"] == "rebuild"
        assert_hits_equal_native(accel, scene)


def test12_the_sah_cost_of_two_groups_weighs_each_by_its_share_of_their_box():
    """With a static and a dynamic group, ``last_update["sah_cost"]`` is the cost of a
    ray through the box around both: each group's own cost (the numpy reference's, from
    its triangles) times its root box's area over that box's, boxes from the
    triangles."""
    animation, scene, params = load("cloth")
    accel = hlbvh.SceneAccel(scene, static="hlbvh", moving="flag")
    scenes.apply_frame(scene, params, animation.frame(8))
    accel.update()

    def half_area(lo, hi):
        e = np.maximum(hi - lo, 0)
        return e[0] * e[1] + e[1] * e[2] + e[2] * e[0]

    boxes, costs = [], []
    for group in (accel.static, accel.dynamic):
        v = np.array(group.geometry.vertices, np.float64).reshape(-1, 3)
        used = v[np.array(group.geometry.faces).reshape(-1)]
        boxes.append((used.min(axis=0), used.max(axis=0)))
        costs.append(_reference_cost(group))
    union = half_area(np.minimum(*[b[0] for b in boxes]), np.maximum(*[b[1] for b in boxes]))
    expected = sum(half_area(*box) / union * cost for box, cost in zip(boxes, costs))
    assert accel.last_update["sah_cost"] == pytest.approx(expected, rel=1e-4)
    assert accel.last_update["sah_cost"] < max(costs)  # the small flag weighs less
