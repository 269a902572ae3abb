"""The structures a SceneAccel query asks (hlbvh.accel.structures): listed in the order
queries ask them, each one's closest hit and occlusion agreeing lane by lane, the
accelerator's hit the nearest of theirs, and the list following update(), not made
anew per query."""

import drjit as dr
import hlbvh
import mitsuba as mi
import numpy as np
import pytest

from hlbvh.accel.hits import TIE, NearestHit
from hlbvh.accel.structures import InstanceTree, MeshTree, OwnRoutine, SubScene

T = mi.ScalarTransform4f


def _scene(instance=True) -> mi.Scene:
    """A floor, a cube and a sphere, and (``instance``) an instance of a shape group
    holding a cube."""
    desc = {
        "type": "scene",
        "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(4)},
        "box": {"type": "cube", "to_world": T().translate([1.2, 0.5, 0]).scale(0.5)},
        "ball": {"type": "sphere", "center": [-1.2, 0.6, 0], "radius": 0.6},
    }
    if instance:
        desc["group"] = {"type": "shapegroup", "cube": {"type": "cube"}}
        desc["copy"] = {"type": "instance", "shape": {"type": "ref", "id": "group"},
                        "to_world": T().translate([0, 0.4, -1.5]).scale(0.4)}
    return mi.load_dict(desc)


def _rays(n=4000, seed=3) -> mi.Ray3f:
    """Rays from a box around the shapes in random directions, every fourth with a
    short ``maxt``."""
    rng = np.random.default_rng(seed)
    o = rng.uniform([-3, 0.05, -3], [3, 2.5, 3], (n, 3)).astype(np.float32)
    d = rng.normal(size=(n, 3)).astype(np.float32)
    ray = mi.Ray3f(mi.Point3f(o.T), mi.Vector3f(d.T))
    ray.maxt = mi.Float(np.where(np.arange(n) % 4 == 0, 1.0, np.inf).astype(np.float32))
    return ray


@pytest.mark.parametrize("options, kinds", [
    (dict(moving=["box", "ball", "copy"], moving_accel="hlbvh"),
     [SubScene, MeshTree, InstanceTree, OwnRoutine]),
    (dict(moving=["box", "ball", "copy"], moving_accel="native"),
     [SubScene, SubScene, InstanceTree, OwnRoutine]),
    (dict(static="hlbvh"), [MeshTree, OwnRoutine]),
])
def test01_the_structures_are_listed_in_query_order(options, kinds):
    """Still world, our joined tree, the moving meshes' sub-scene, the instances' tree,
    the analytic shapes' own routines: only those that trace the scene."""
    accel = hlbvh.SceneAccel(_scene(instance="static" not in options), **options)
    assert [type(s) for s in accel._structures] == kinds
    if options.get("moving_accel") == "native":
        assert accel._structures[1].group is accel.native_moving


def test02_each_structure_closest_and_occluded_agree_and_the_nearest_wins():
    """Every structure's closest hit is found on exactly the lanes it says are
    occluded, and the accelerator's hit is the nearest of the structures' (within the
    tie tolerance), as are its shadow tests their union."""
    accel = hlbvh.SceneAccel(_scene(), moving=["box", "ball", "copy"], moving_accel="hlbvh")
    ray = _rays()
    n = dr.width(ray)
    active = dr.full(mi.Bool, True, n)
    nearest, occluded = np.full(n, np.inf, np.float32), np.zeros(n, bool)
    for structure in accel._structures:
        hit = NearestHit.none(n)
        structure.closest(mi.Ray3f(ray), active, hit, False, (False, 0, 0))
        t = np.array(hit.t)
        blocked = np.array(structure.occluded(ray, active, False))
        assert np.isfinite(t).any(), type(structure).__name__
        np.testing.assert_array_equal(np.isfinite(t), blocked, type(structure).__name__)
        nearest, occluded = np.minimum(nearest, t), occluded | blocked
    t = np.array(accel.ray_intersect_preliminary(ray).t)
    np.testing.assert_array_equal(np.isfinite(t), np.isfinite(nearest))
    np.testing.assert_allclose(t, nearest, rtol=2 * TIE)
    np.testing.assert_array_equal(np.array(accel.ray_test(ray)), occluded)


def test03_the_list_follows_update_not_queries():
    """Queries trace the list the last update made (the same list, not one per query);
    a mesh that starts moving puts our tree in it at the next update."""
    scene = _scene(instance=False)
    accel = hlbvh.SceneAccel(scene, moving_accel="hlbvh")
    listed = accel._structures
    assert [type(s) for s in listed] == [SubScene]
    accel.ray_intersect_preliminary(_rays(64)), accel.ray_test(_rays(64))
    assert accel._structures is listed
    params = mi.traverse(scene)
    params["box.vertex_positions"] = params["box.vertex_positions"] + 0.1
    params.update()
    accel.update()
    assert [type(s) for s in accel._structures] == [SubScene, MeshTree]
