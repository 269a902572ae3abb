"""Hits inside instances expanded without Mitsuba's call through a shape pointer
(:mod:`hlbvh.accel.instance_shading`): every field of the surface interaction as Mitsuba's
own expansion gives it, for rotated, scaled, mirrored, still and moving instances, mesh
and analytic group shapes, and the shapes beside them."""

import drjit as dr
import hlbvh
import mitsuba as mi
import numpy as np

from test_accel import bounce_rays, camera_rays
from test_static import _rigid_scene, mixed_scene

#: Fields of mi.SurfaceInteraction3f compared (vectors as float arrays).
VECTORS = ("p", "n", "uv", "dp_du", "dp_dv", "dn_du", "dn_dv", "wi", "duv_dx", "duv_dy")


def _frame(si):
    return {"sh_s": si.sh_frame.s, "sh_t": si.sh_frame.t, "sh_n": si.sh_frame.n}


def assert_same_interactions(ours, theirs, valid, atol=2e-5):
    """Every field of ``ours`` equals ``theirs`` where ``valid`` (floats within ``atol``
    relative to their magnitude: Mitsuba's C++ and Dr.Jit may order a sum differently)."""
    valid = np.array(valid)
    assert valid.sum() > 50
    for name in VECTORS + ("sh_s", "sh_t", "sh_n", "t"):
        a = getattr(ours, name, None) if name in VECTORS + ("t",) else _frame(ours)[name]
        b = getattr(theirs, name, None) if name in VECTORS + ("t",) else _frame(theirs)[name]
        a = np.where(valid, np.array(a, dtype=np.float64), 0.0)  # misses: t infinite
        b = np.where(valid, np.array(b, dtype=np.float64), 0.0)
        err = np.abs(a - b) / (1.0 + np.abs(b))
        assert err.max() <= atol, (name, err.max())
    for name in ("shape", "instance"):
        assert np.array(getattr(ours, name) == getattr(theirs, name))[valid].all(), name
    assert (np.array(ours.prim_index) == np.array(theirs.prim_index))[valid].all()
    assert np.array(ours.is_valid() == theirs.is_valid()).all()


def _compare(scene, accel, flags=mi.RayFlags.All):
    for coherent, ray in ((True, camera_rays(scene, 48)), (False, bounce_rays(scene, 4096, seed=4))):
        pi = scene.ray_intersect_preliminary(ray, coherent)
        theirs = pi.compute_surface_interaction(ray, flags)
        ours = accel.shading.surface_interaction(pi, ray, flags)
        assert_same_interactions(ours, theirs, pi.is_valid())
        assert dr.count(pi.instance != None)[0] > 20  # noqa: E711 (JIT compare)
        # Through the accelerator's own hits: the same surfaces
        mine = accel.ray_intersect(ray, flags, coherent)
        agree = np.array(mine.is_valid() == theirs.is_valid()) & np.array(
            (mine.shape == theirs.shape) & (mine.instance == theirs.instance))
        assert agree.mean() >= 1 - 3 / dr.width(ray)


def test01_instance_hits_expand_as_mitsubas_for_every_field():
    """Still instances of a mesh group and of an analytic group (cube and rectangle),
    rotated, scaled non-uniformly, mirrored; every flag set and the minimal ones."""
    scene = mi.load_dict(_rigid_scene())
    accel = hlbvh.SceneAccel(scene)
    assert accel.shading is not None and accel.shading.usable
    _compare(scene, accel)
    _compare(scene, accel, mi.RayFlags.Minimal)


def test02_moving_instances_and_the_shapes_beside_them_expand_as_mitsubas():
    """After the instances moved (Mitsuba's update keeps its own reference current): the
    table of transforms follows; meshes, spheres, disks and an emitter beside them."""
    desc = _rigid_scene()
    beside = mixed_scene()
    desc.update({k: beside[k] for k in ("rock", "ball", "disk", "lamp", "sky")})
    scene = mi.load_dict(desc)
    params = mi.traverse(scene)
    moving = ["inst_0", "inst_3", "inst_4"]
    accel = hlbvh.SceneAccel(scene, moving=moving)
    _compare(scene, accel)
    for step in range(2):
        for key in moving:
            params[f"{key}.to_world"] = mi.Transform4f().translate(
                [0.3, 0.1 * step, -0.2]).rotate([0, 1, 1], 20.0) @ params[f"{key}.to_world"]
        params.update()
        accel.update()
        assert accel.last_update["groups"]["instances"]["decision"] in ("refit", "rebuild")
        _compare(scene, accel)


def test03_an_hlbvh_path_render_of_instances_equals_native():
    """The whole path through our integrator: images of instanced scenes equal the
    native accelerator's (same seed, same samples)."""
    for desc in (_rigid_scene(), mixed_scene()):
        desc = dict(desc)
        images = {}
        for accel in ("native", "hlbvh"):
            desc["integrator"] = {"type": "hlbvh_path", "accel": accel, "max_depth": 4}
            scene = mi.load_dict(desc)
            images[accel] = np.array(mi.render(scene, seed=3, spp=4))
        diff = np.abs(images["hlbvh"] - images["native"])
        assert diff.mean() <= 1e-4 * max(images["native"].mean(), 1e-3) + 1e-6


def test04_many_group_shapes_expand_through_a_switch_as_mitsubas(monkeypatch):
    """Past MOST_INLINE_CHILDREN group shapes each lane runs its own shape's expansion
    alone (a switch): the same fields, moving instances included."""
    import hlbvh.accel.instance_shading as shading

    monkeypatch.setattr(shading, "MOST_INLINE_CHILDREN", 0)
    scene = mi.load_dict(_rigid_scene())
    accel = hlbvh.SceneAccel(scene, moving=["inst_1", "inst_2"])
    _compare(scene, accel)
    _compare(scene, accel, mi.RayFlags.Minimal)
