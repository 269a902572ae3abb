"""Only what moves goes through our BVH (``static="native"``, the default): the still
shapes, of any type, through Mitsuba's own accelerator over a sub-scene; answers equal
Mitsuba's and a float64 brute force before and after motion; the first motion, declared
moving shapes, a shape that starts moving late; the public update path."""

import drjit as dr
import hlbvh
import mitsuba as mi
import numpy as np
import pytest

from reference import brute_force
from test_accel import bounce_rays, camera_rays

T = mi.ScalarTransform4f


def _film(res=24, spp=2):
    return dict(film=dict(type="hdrfilm", width=res, height=res, rfilter=dict(type="box"),
                          pixel_format="rgb"),
                sampler=dict(type="independent", sample_count=spp))


def _mesh(name, vertices, faces, bsdf=None):
    props = mi.Properties()
    if bsdf is not None:
        props["bsdf"] = mi.load_dict(bsdf)
    mesh = mi.Mesh(name, len(vertices), len(faces), props=props)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(np.asarray(vertices, np.float32).ravel())
    params["faces"] = mi.UInt32(np.asarray(faces, np.uint32).ravel())
    params.update()
    return mesh


def _blob(seed, center, count=300, size=0.35):
    """A soup of ``count`` small triangles around ``center``."""
    rng = np.random.default_rng(seed)
    c = np.asarray(center) + rng.uniform(-0.6, 0.6, (count, 1, 3))
    v = (c + size * rng.uniform(-0.5, 0.5, (count, 3, 3))).reshape(-1, 3)
    return v, np.arange(3 * count).reshape(count, 3)


def mixed_scene(res=24, spp=2, extra=None) -> dict:
    """Static meshes, analytic shapes, two instances of one group (one rotated and
    mirrored, one scaled non-uniformly) and a mesh that the tests move (``mover``)."""
    desc = {
        "type": "scene",
        "sensor": dict(type="perspective", fov=50,
                       to_world=T().look_at(origin=[0, 2, 6], target=[0, 0.5, 0], up=[0, 1, 0]),
                       **_film(res, spp)),
        "floor": dict(type="rectangle", to_world=T().rotate([1, 0, 0], -90).scale(5)),
        "rock": _mesh("rock", *_blob(1, [-1.5, 0.6, 0])),
        "mover": _mesh("mover", *_blob(2, [0.3, 0.8, 0.6]),
                       bsdf=dict(type="diffuse", reflectance=dict(type="rgb", value=[0.8, 0.2, 0.1]))),
        "ball": dict(type="sphere", center=[1.6, 0.5, -0.5], radius=0.5),
        "disk": dict(type="disk", to_world=T().translate([0, 1.5, -2]).scale(0.7)),
        "group": {"type": "shapegroup", "cube": {"type": "cube"},
                  "s": {"type": "sphere", "center": [0, 1.2, 0], "radius": 0.3}},
        "copy_a": {"type": "instance", "shapegroup": {"type": "ref", "id": "group"},
                   "to_world": T().translate([-0.5, 0.4, -1.2]).rotate([0, 1, 0], 35)
                   .scale([-0.4, 0.4, 0.4])},
        "copy_b": {"type": "instance", "shapegroup": {"type": "ref", "id": "group"},
                   "to_world": T().translate([1.0, 0.3, 1.3]).scale([0.5, 0.25, 0.3])},
        "lamp": dict(type="sphere", center=[0, 4, 1], radius=0.4,
                     emitter=dict(type="area", radiance=dict(type="rgb", value=12))),
        "sky": dict(type="constant", radiance=dict(type="rgb", value=0.2)),
    }
    desc.update(extra or {})
    return desc


def _move(params, key, offset):
    """Mitsuba's own update (the scene's accelerator is rebuilt: the reference stays
    current) moving mesh ``key`` by ``offset``."""
    v = np.array(params[f"{key}.vertex_positions"]).reshape(-1, 3) + np.asarray(offset)
    params[f"{key}.vertex_positions"] = mi.Float(v.astype(np.float32).ravel())
    params.update()


def _agreement(scene, ray, ours, theirs, rtol=2e-5) -> float:
    """Fraction of rays where ours and Mitsuba's both miss, or hit the same primitive of
    the same shape (pointer, index and instance) at the same t; a different primitive
    at the same t is a tie either way. Outside instances, our shape pointer must be the
    shape our index names, always."""
    v_o, v_t = np.array(ours.is_valid()), np.array(theirs.is_valid())
    both = v_o & v_t
    t_o, t_t = np.array(ours.t), np.array(theirs.t)
    o = np.abs(np.array(ray.o)).max(axis=0)
    t_o, t_t = np.where(both, t_o, 0), np.where(both, t_t, 0)
    same_t = both & (np.abs(t_o - t_t) <= rtol * (t_t + o))
    same = (np.array(ours.shape == theirs.shape) & np.array(ours.instance == theirs.instance)
            & (np.array(ours.shape_index) == np.array(theirs.shape_index))
            & (np.array(ours.prim_index) == np.array(theirs.prim_index)))
    # Our shape pointer is the shape our index names (outside instances)
    direct = np.array(ours.is_valid() & (ours.instance == None))  # noqa: E711
    named = np.array(dr.gather(mi.ShapePtr, scene.shapes_dr(), ours.shape_index,
                               ours.is_valid()) == ours.shape)
    assert named[direct].all()
    return np.mean((~v_o & ~v_t) | (same_t & same) | (same_t & ~same & (t_o == t_t)))


def _rays(scene):
    return ((True, camera_rays(scene, 48)), (False, bounce_rays(scene, 4096, seed=3)))


def test01_mixed_scene_hits_equal_native_before_and_after_motion():
    """Every field Mitsuba's query gives (t, shape, shape_index, prim_index,
    instance) and every shadow test, on camera and incoherent rays: equal on all but
    2 of 4096, before the mover moves, after its first motion and after more."""
    scene = mi.load_dict(mixed_scene())
    params = mi.traverse(scene)
    accel = hlbvh.SceneAccel(scene)
    for step in range(3):
        if step:
            _move(params, "mover", [0.2 * step, 0.1, -0.3])
            accel.update()
        for coherent, ray in _rays(scene):
            allowed = 1 - 2 / dr.width(ray)
            ours = accel.ray_intersect_preliminary(ray, coherent)
            theirs = scene.ray_intersect_preliminary(ray, coherent)
            assert dr.count(theirs.instance != None)[0] > 20  # noqa: E711 (instances seen)
            assert _agreement(scene, ray, ours, theirs) >= allowed
            occluded = np.array(accel.ray_test(ray, coherent, True))
            assert np.mean(occluded == np.array(scene.ray_test(ray, coherent, True))) >= allowed
    assert accel.last_update["moving"] == ["mover"]
    assert accel.static.builds == 2 and accel.dynamic.bvh is not None


def _world_triangles(scene):
    """Every mesh's triangles in one soup, and each triangle's (shape index, prim)."""
    vs, fs, owners = [], [], []
    base = 0
    for index, shape in enumerate(scene.shapes()):
        v = np.array(shape.vertex_positions_buffer()).reshape(-1, 3)
        f = np.array(shape.faces_buffer()).reshape(-1, 3)
        vs.append(v), fs.append(f + base)
        owners += [(index, k) for k in range(len(f))]
        base += len(v)
    return np.concatenate(vs), np.concatenate(fs), np.array(owners)


@pytest.mark.parametrize("static", ["native", "hlbvh"])
def test02_meshes_only_hits_equal_a_float64_brute_force(static):
    """Static meshes and a moving one: the nearest hit's t, shape and primitive equal
    a float64 brute force over every triangle, before and after motion (ties: any
    triangle within the tolerance of the nearest)."""
    desc = {"type": "scene", "rock": _mesh("rock", *_blob(4, [-0.5, 0, 0], 200)),
            "pebbles": _mesh("pebbles", *_blob(5, [0.5, 0.2, 0], 200)),
            "mover": _mesh("mover", *_blob(6, [0, 0.1, 0.5], 200))}
    scene = mi.load_dict(desc)
    params = mi.traverse(scene)
    accel = hlbvh.SceneAccel(scene, static=static)
    for step in range(2):
        if step:
            _move(params, "mover", [0.1, -0.2, -0.4])
            accel.update()
        ray = bounce_rays(scene, 2048, seed=step)
        V, F, owners = _world_triangles(scene)
        ref = brute_force(V.astype(np.float64), F, np.array(ray.o).T.astype(np.float64),
                          np.array(ray.d).T.astype(np.float64))
        pi = accel.ray_intersect_preliminary(ray)
        valid = np.array(pi.is_valid())
        assert np.mean(valid == ref["valid"]) >= 1 - 2 / 2048
        both = valid & ref["valid"]
        t = np.array(pi.t)[both]
        assert np.allclose(t, ref["t"][both], rtol=1e-4, atol=1e-5)
        hit = np.stack([np.array(pi.shape_index), np.array(pi.prim_index)], 1)[both]
        rows = np.flatnonzero(both)
        tied = [np.any(np.all(owners[np.abs(ref["t_all"][r] - ref["t"][r]) <= 1e-5 * (1 + ref["t"][r])]
                              == h, axis=1)) for r, h in zip(rows, hit)]
        assert np.mean(tied) >= 1 - 2 / 2048


def test03_instances_curves_and_sdf_grids_beside_a_moving_mesh_render_like_native(tmp_path):
    """Shapes only Mitsuba intersects (static instances, a curve, an SDF grid) beside a
    moving mesh: hlbvh_path with accel="hlbvh" renders native's image, frame by frame."""
    curve = tmp_path / "curve.txt"
    curve.write_text("-1.5 0.2 1 0.05\n-1 0.8 1 0.05\n-0.5 0.3 1 0.05\n0 1 1 0.05\n")
    x = np.linspace(-1, 1, 8, dtype=np.float32)
    sdf = np.sqrt(x[:, None, None] ** 2 + x[None, :, None] ** 2 + x[None, None, :] ** 2) - 0.7
    extra = {"hair": {"type": "bsplinecurve", "filename": str(curve)},
             "blob": {"type": "sdfgrid", "grid": mi.TensorXf(sdf[..., None]),
                      "to_world": T().translate([-2.2, 0.2, -1.5]).scale(0.8)}}
    images = {}
    for accel in ("native", "hlbvh"):
        scene = mi.load_dict(mixed_scene(res=24, spp=4, extra=dict(
            extra, integrator=dict(type="hlbvh_path", accel=accel, max_depth=4))))
        params = mi.traverse(scene)
        images[accel] = []
        for frame in range(3):
            if frame:
                _move(params, "mover", [0.15, 0.0, -0.2])
            images[accel].append(np.array(mi.render(scene, seed=frame)))
    for ours, native in zip(images["hlbvh"], images["native"]):
        assert native.mean() > 0.02
        assert np.abs(ours - native).mean() < 2e-4 and np.abs(ours - native).max() < 0.05


def test04_the_first_motion_rebuilds_the_static_world_once_unless_declared():
    """Undeclared, the mover's first motion rebuilds the sub-scene without it (and
    last_update names it); declared, the sub-scene is built once without it. Later
    frames keep it."""
    for declared in ((), ("mover",)):
        scene = mi.load_dict(mixed_scene())
        params = mi.traverse(scene)
        accel = hlbvh.SceneAccel(scene, moving=declared)
        assert accel.last_update["groups"]["static"]["decision"] == "build"
        assert (accel.dynamic.bvh is not None) == bool(declared)
        _move(params, "mover", [0.1, 0, 0])
        static = accel.update().last_update["groups"]["static"]
        if declared:
            assert static["decision"] == "kept" and static["left"] == []
        else:
            assert static["decision"] == "rebuild" and static["left"] == ["mover"]
        for _ in range(3):
            _move(params, "mover", [0.1, 0, 0])
            assert accel.update().last_update["groups"]["static"]["decision"] == "kept"
        assert accel.static.builds == (1 if declared else 2)


def test05_a_shape_that_starts_moving_late_leaves_the_static_world():
    """The rock stays still for 10 updates, then moves: one rebuild of the sub-scene
    then, naming it, and hits equal native's after it."""
    scene = mi.load_dict(mixed_scene())
    params = mi.traverse(scene)
    accel = hlbvh.SceneAccel(scene, moving="mover")
    for _ in range(10):
        _move(params, "mover", [0.02, 0, 0])
        assert accel.update().last_update["groups"]["static"]["decision"] == "kept"
    _move(params, "rock", [0, 0.3, 0])
    update = accel.update().last_update
    assert update["groups"]["static"]["left"] == ["rock"]
    assert update["moving"] == ["rock", "mover"] or update["moving"] == ["mover", "rock"]
    assert accel.static.builds == 2
    ray = bounce_rays(scene, 4096, seed=9)
    assert _agreement(scene, ray, accel.ray_intersect_preliminary(ray),
                      scene.ray_intersect_preliminary(ray)) >= 1 - 2 / 4096


def test06_moving_shapes_we_cannot_trace_and_unknown_ids_are_named():
    scene = mi.load_dict(mixed_scene())
    with pytest.raises(ValueError, match=r"no shape of the scene has the id\(s\) \['flag'\]"):
        hlbvh.SceneAccel(scene, moving="mover, flag")
    # (an instance moves through our two levels, but not one of a group with a sphere)
    with pytest.raises(ValueError, match="'copy_a' \\(Instance\\) moved, and its shape group "
                                         "holds shapes other than meshes"):
        hlbvh.SceneAccel(scene, moving=["copy_a"])
    accel = hlbvh.SceneAccel(scene)
    params = mi.traverse(scene)
    params["copy_b.to_world"] = mi.Transform4f().translate([0, 0.1, 0]) @ params["copy_b.to_world"]
    params.update()
    with pytest.raises(ValueError, match="'copy_b' \\(Instance\\) moved, and its shape group"):
        accel.update()
    with pytest.raises(RuntimeError, match="last update\\(\\) failed"):
        accel.ray_test(bounce_rays(scene, 16))


def test07_a_moving_sphere_is_traced_by_its_own_routine():
    """A sphere that moves leaves the sub-scene and is intersected where it is now."""
    scene = mi.load_dict(mixed_scene())
    accel = hlbvh.SceneAccel(scene)
    ball = next(s for s in scene.shapes() if s.id() == "ball")
    params = mi.traverse(scene)
    params["ball.to_world"] = mi.Transform4f().translate([-3.0, 0.0, 0.0]) @ params["ball.to_world"]
    params.update()
    accel.update()
    assert accel.last_update["groups"]["static"]["left"] == ["ball"]
    ray = mi.Ray3f(mi.Point3f(-1.4, 0.5, 5), mi.Vector3f(0, 0, -1))
    pi = accel.ray_intersect_preliminary(ray)
    assert pi.is_valid()[0] and pi.shape == ball and abs(pi.t[0] - 5.0) < 0.6


def test08_stale_queries_and_emptied_meshes_are_refused_in_one_line():
    """A query after the mover changed but before update() is refused naming it; an
    update that finds a mesh emptied of faces names it and leaves the process usable."""
    scene = mi.load_dict(mixed_scene())
    accel = hlbvh.SceneAccel(scene, moving="mover")
    params = mi.traverse(scene)
    _move(params, "mover", [0.3, 0, 0])
    ray = bounce_rays(scene, 64)
    with pytest.raises(RuntimeError) as stale:
        accel.ray_intersect_preliminary(ray)
    assert str(stale.value) == (
        "SceneAccel: shape 'mover' (Mesh) changed since the accelerator's last update(); "
        "call update() before tracing (it would answer from the old geometry)")
    accel.update()
    accel.ray_intersect_preliminary(ray)
    faces = mi.UInt32(params["mover.faces"])  # a new handle: Mitsuba writes into the old
    params["mover.faces"] = mi.UInt32()
    params.update()
    with pytest.raises(ValueError) as emptied:
        accel.update()
    assert str(emptied.value) == ("shape 'mover' (Mesh) has no triangles any more: it would "
                                  "silently be missing from the image; give it faces")
    params["mover.faces"] = faces
    params.update()
    accel.update()
    assert _agreement(scene, ray, accel.ray_intersect_preliminary(ray),
                      scene.ray_intersect_preliminary(ray)) >= 1 - 2 / 64


def test09_rays_of_mismatched_widths_are_named():
    accel = hlbvh.SceneAccel(mi.load_dict(mixed_scene()))
    ray = mi.Ray3f(mi.Point3f([0, 1, 2], [0, 0, 0], [5, 5, 5]), mi.Vector3f([0, 0], [0, 0], [-1, -1]))
    with pytest.raises(ValueError) as ragged:
        accel.ray_intersect_preliminary(ray)
    assert str(ragged.value) == ("ray: its fields hold different numbers of rays (o 3, d 2, "
                                 "maxt 1, time 1); give every field one entry per ray, or one "
                                 "for all")


def test10_a_hand_written_loop_with_hlbvh_traverse_renders_like_hlbvh_render():
    """The README's loop (hlbvh.traverse, params.update(), mi.render) gives the frames
    FrameRenderer (what `hlbvh render` runs) gives, bit for bit, and never lets Mitsuba
    rebuild its own accelerator (our HLBVH tracing the flag in both: a choice by
    measured cost may pick another structure in one of them)."""
    from hlbvh.render.frame import FrameRenderer
    from hlbvh.render.settings import RenderSettings
    animation = hlbvh.scenes.get("cloth", triangles=3000, frames=4)
    settings = RenderSettings(resolution=(32, 18), spp=2, integrator="path", max_depth=4,
                              moving_accel="hlbvh")
    renderer = FrameRenderer(animation, settings)
    expected = [np.array(renderer.render(i)[0]) for i in range(3)]

    scene = mi.load_dict(animation.scene_dict(
        resolution=(32, 18), spp=2,
        integrator=dict(type="hlbvh_path", max_depth=4, moving="flag", moving_accel="hlbvh")))
    params = hlbvh.traverse(scene)
    native_tree = mi.traverse(scene)  # Mitsuba's parameters, to see what it rebuilds
    for i in range(3):
        params["flag.vertex_positions"] = mi.Float(animation.frame(i)["flag"].positions)
        params["flag.vertex_normals"] = hlbvh.scenes.normals.vertex_normals(
            params["flag.vertex_positions"], params["flag.faces"])
        nodes = [node for node, _ in params.update()]
        assert not any(isinstance(node, mi.Scene) for node in nodes)
        np.testing.assert_array_equal(np.array(mi.render(scene, seed=i)), expected[i])
    assert scene.integrator().accel(scene).static.builds == 1
    assert native_tree is not None


@pytest.mark.parametrize("moving", ["twin", "still"])
def test11_coplanar_shapes_of_two_structures_tie_to_the_lower_index(moving):
    """A mesh lying exactly on another, one still (Mitsuba's sub-scene) and one moving
    (our BVH): the two intersectors round the distance differently in the last bits,
    and the hit of the lower index in ``scene.shapes()`` is kept whichever structure
    traced it, with that structure's own ``t``."""
    v = np.array([[-1, -1, 0], [1, -1, 0], [0, 1, 0]], np.float32)
    scene = mi.load_dict({"type": "scene", "still": _mesh("still", v, [[0, 1, 2]]),
                          "twin": _mesh("twin", v, [[0, 1, 2]])})
    assert [s.id() for s in scene.shapes()] == ["still", "twin"]
    accel = hlbvh.SceneAccel(scene, moving=moving)
    ray = mi.Ray3f(mi.Point3f(0, 0, 2), mi.Vector3f(0, 0, -1))
    pi = accel.ray_intersect_preliminary(ray)
    own = (accel.static.scene.ray_intersect_preliminary(ray).t if moving == "twin"
           else accel.dynamic.bvh.intersect(ray).t)
    assert pi.is_valid()[0] and pi.shape_index[0] == 0 and pi.t[0] == own[0]


def test12_the_static_flag_reaches_the_accelerator(tmp_path, capsys):
    """`hlbvh render --static hlbvh` renders through our BVHs for every mesh (the
    statistics record it, and the SAH cost covers the still ground and pole too); a
    bad value is one line naming the flag."""
    from cli_helpers import run_cli
    import json
    sah = {}
    for static in ("native", "hlbvh"):
        out = tmp_path / static
        status, _, err = run_cli(capsys, "render", "cloth", "--triangles", "2000", "--frames",
                                 "0:2", "--resolution", "16", "--spp", "1", "--static", static,
                                 "--out", out, "--quiet")
        assert status == 0, err
        stats = json.loads((out / "stats.json").read_text())
        assert stats["settings"]["static"] == static
        sah[static] = stats["frames"][-1]["sah_cost"]
    assert sah["native"] != sah["hlbvh"]
    status, _, err = run_cli(capsys, "render", "cloth", "--static", "embree", "--out",
                             tmp_path / "bad", "--quiet")
    assert status == 2 and err == ["hlbvh render: --static 'embree': expected one of native, hlbvh"]


def _rigid_scene() -> dict:
    """A floor and 12 instances of two shape groups (a mesh blob; a cube with a
    rectangle), rotated, scaled non-uniformly and mirrored."""
    rng = np.random.default_rng(5)
    desc = {"type": "scene",
            "sensor": dict(type="perspective", fov=60,
                           to_world=T().look_at(origin=[0, 4, 8], target=[0, 1, 0], up=[0, 1, 0]),
                           **_film()),
            "floor": dict(type="rectangle", to_world=T().rotate([1, 0, 0], -90).scale(6)),
            "rocks": {"type": "shapegroup", "rock": _mesh("rock", *_blob(8, [0, 0, 0], 150))},
            "boxes": {"type": "shapegroup", "cube": {"type": "cube"},
                      "lid": {"type": "rectangle",
                              "to_world": T().translate([0, 1.5, 0]).scale(0.5)}}}
    for k in range(12):
        desc[f"inst_{k}"] = {
            "type": "instance", "shapegroup": {"type": "ref", "id": ["rocks", "boxes"][k % 2]},
            "to_world": T().translate(list(rng.uniform(-3, 3, 3) + [0, 1.5, 0]))
            .rotate(list(rng.normal(size=3)), float(rng.uniform(0, 360)))
            .scale(list(rng.uniform(0.3, 0.8, 3) * rng.choice([-1, 1], 3)))}
    return desc


@pytest.mark.parametrize("mode", ["rebuild", "refit", "auto"])
def test13_moving_instances_hit_as_natives_do(mode):
    """Instances that move are traced through our two-level hierarchy: every hit field
    (shape, shape_index, prim_index, instance, t) and shadow test as Mitsuba's, after
    each move, whether the top level was rebuilt or refit; only the top level is
    brought up to date, the still world stays built."""
    scene = mi.load_dict(_rigid_scene())
    params = mi.traverse(scene)
    accel = hlbvh.SceneAccel(scene, moving=[f"inst_{k}" for k in range(0, 12, 3)],
                             update=mode)
    assert accel.last_update["groups"]["instances"]["instances"] == 4
    for step in range(3):
        if step:
            for k in range(0, 12, 3):
                key = f"inst_{k}.to_world"
                params[key] = mi.Transform4f().translate([0.2 * step, 0.1, -0.1]) @ params[key]
            params.update()
            update = accel.update().last_update
            top = update["groups"]["instances"]
            assert top["decision"] in ("refit", "rebuild")
            assert top["decision"] == mode or mode == "auto"
            assert (top["drift"] is None) == (mode == "rebuild")
            assert update["groups"]["static"]["decision"] == "kept"
        for coherent, ray in _rays(scene):
            theirs = scene.ray_intersect_preliminary(ray, coherent)
            ours = accel.ray_intersect_preliminary(ray, coherent)
            assert dr.count(theirs.instance != None)[0] > 50  # noqa: E711
            assert _agreement(scene, ray, ours, theirs) >= 1 - 2 / dr.width(ray)
            occluded = np.array(accel.ray_test(ray, coherent, True))
            assert np.mean(occluded == np.array(scene.ray_test(ray, coherent, True))) >= \
                1 - 2 / dr.width(ray)
    assert accel.static.builds == 1


def test13b_auto_refits_the_top_level_until_it_drifts():
    """update="auto" on the top level: a small motion refits it (its drift reported,
    within the tolerance); instances thrown far across each other drift past it and
    rebuild; the policy's back-off applies as to meshes."""
    scene = mi.load_dict(_rigid_scene())
    params = mi.traverse(scene)
    moving = [f"inst_{k}" for k in range(12)]
    accel = hlbvh.SceneAccel(scene, moving=moving)
    for key in moving:
        params[f"{key}.to_world"] = mi.Transform4f().translate([0.01, 0, 0]) @ params[f"{key}.to_world"]
    params.update()
    top = accel.update().last_update["groups"]["instances"]
    assert top["decision"] == "refit" and 1 <= top["drift"] <= accel.policy.refit_tolerance
    # Every instance moved to where another was (the same box around them all): the
    # tree's nodes, built for neighbours, now each span the scene
    centres = [np.array(params[f"{key}.to_world"].translation()).ravel() for key in moving]
    order = np.roll(np.arange(12), 5)
    for k, key in enumerate(moving):
        step = [float(v) for v in centres[order[k]] - centres[k]]
        params[f"{key}.to_world"] = mi.Transform4f().translate(step) @ params[f"{key}.to_world"]
    params.update()
    top = accel.update().last_update["groups"]["instances"]
    assert top["decision"] == "rebuild" and top["drift"] > accel.policy.refit_tolerance
    ray = next(iter(_rays(scene)))[1]
    ours, theirs = accel.ray_intersect_preliminary(ray), scene.ray_intersect_preliminary(ray)
    assert _agreement(scene, ray, ours, theirs) >= 1 - 2 / dr.width(ray)


def _lid_moved(value):
    return value @ mi.Transform4f().scale([6.0, 6.0, 1.0])  # six times as wide


@pytest.mark.parametrize("moving,key,change", [
    ([], "rocks.rock.vertex_positions", lambda v: v * 1.4 + 0.1),
    (["inst_0", "inst_2"], "rocks.rock.vertex_positions", lambda v: v * 1.4 + 0.1),
    ([], "boxes.lid.to_world", _lid_moved)], ids=["still", "moving", "analytic"])
@pytest.mark.parametrize("traverse", [mi.traverse, hlbvh.traverse], ids=["mitsuba", "hlbvh"])
def test13c_a_shape_group_whose_shapes_change_is_traced_anew(moving, key, change, traverse):
    """A group's own shape changed (a mesh deformed, ``rocks.rock.vertex_positions``;
    an analytic shape moved, ``boxes.lid.to_world``): its still instances (the native
    sub-scene) and its moving ones (our two levels) follow on the next update, the
    statistics name the group, a query before it is refused; hits as a scene loaded
    with the changed group gives them."""
    scene = mi.load_dict(_rigid_scene())
    accel = hlbvh.SceneAccel(scene, moving=moving)
    params = traverse(scene)
    group = key.split(".")[0]
    params[key] = change(params[key])
    params.update()
    ray = next(iter(_rays(scene)))[1]
    with pytest.raises(RuntimeError, match="shape group"):
        accel.ray_intersect_preliminary(ray)
    update = accel.update().last_update["groups"]
    assert update["static"]["groups_changed"] == [group]
    assert update["instances"]["groups_rebuilt"] == ([group] if moving else [])
    reference = mi.load_dict(_rigid_scene())  # the changed group, built by Mitsuba alone
    theirs = mi.traverse(reference)
    theirs[key] = change(theirs[key])
    theirs.update()
    ours, truth = accel.ray_intersect_preliminary(ray), reference.ray_intersect_preliminary(ray)
    assert dr.count(truth.instance != None)[0] > 50  # noqa: E711
    # (two scenes: their shape pointers differ, so hits are compared by t)
    assert _same_t(ours, truth).mean() >= 1 - 2 / dr.width(ray)
    before = mi.load_dict(_rigid_scene()).ray_intersect_preliminary(ray)
    assert (~_same_t(before, truth)).sum() > 20  # the change shows in the hits


def _same_t(a, b):
    """Per ray: both miss, or both hit at the same t."""
    valid, expected = np.array(a.is_valid()), np.array(b.is_valid())
    t = np.where(valid, np.array(a.t), 0.0)  # misses: t infinite
    t_expected = np.where(expected, np.array(b.t), 0.0)
    return (valid == expected) & (~expected | (np.abs(t - t_expected) <= 2e-5 * (1 + t_expected)))


def test13d_copies_of_one_geometry_in_two_groups_are_told_apart():
    """Two shape groups of the same mesh with other materials (USD prototypes often
    are): box and primitive count match both, so the group an instance uses is told by
    its id; moving instances of each hit the right group's mesh, as Mitsuba's query."""
    vertices, faces = _blob(8, [0, 0, 0], 150)
    desc = {"type": "scene", "sensor": dict(type="perspective", fov=60, to_world=T().look_at(
                origin=[0, 4, 8], target=[0, 1, 0], up=[0, 1, 0]), **_film()),
            "floor": dict(type="rectangle", to_world=T().rotate([1, 0, 0], -90).scale(6))}
    for name, colour in (("red", [0.8, 0.1, 0.1]), ("blue", [0.1, 0.1, 0.8])):
        bsdf = {"type": "diffuse", "reflectance": {"type": "rgb", "value": colour}}
        desc[name] = {"type": "shapegroup", f"{name}_rock": _mesh(f"{name}_rock", vertices, faces, bsdf)}
    for k in range(6):
        desc[f"inst_{k}"] = {"type": "instance",
                             "shapegroup": {"type": "ref", "id": ["red", "blue"][k % 2]},
                             "to_world": T().translate([1.6 * k - 4, 1.0, 0.5 * (k % 2)])}
    scene = mi.load_dict(desc)
    params = mi.traverse(scene)
    moving = [f"inst_{k}" for k in range(6)]
    accel = hlbvh.SceneAccel(scene, moving=moving)
    for step in range(2):
        if step:
            for key in moving:
                params[f"{key}.to_world"] = mi.Transform4f().translate([0.1, 0.2, 0.0]) @ \
                    params[f"{key}.to_world"]
            params.update()
            accel.update()
        for coherent, ray in _rays(scene):
            theirs = scene.ray_intersect_preliminary(ray, coherent)
            ours = accel.ray_intersect_preliminary(ray, coherent)
            assert dr.count(theirs.instance != None)[0] > 20  # noqa: E711
            assert np.array(ours.shape == theirs.shape).mean() >= 1 - 2 / dr.width(ray)
            assert _agreement(scene, ray, ours, theirs) >= 1 - 2 / dr.width(ray)
