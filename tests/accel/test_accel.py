"""hlbvh.SceneAccel and hlbvh.NativeAccel: mi.Scene's three queries with its
signatures, the scene's triangles collected into one BVH, analytic shapes, updates,
and bad input (unknown accel or option, unsupported shapes, empty scenes, NaN rays,
non-finite vertices)."""

import drjit as dr
import hlbvh
import mitsuba as mi
import numpy as np
import pytest
from hlbvh.accel.scene_geometry import collect_geometry
from meshes import empty_mesh_loads

T = mi.ScalarTransform4f


# ---------------------------------------------------------------------------------------
# Scenes (shared with test_integrators.py)
# ---------------------------------------------------------------------------------------


def _film(res, spp):
    return dict(
        film=dict(type="hdrfilm", width=res, height=res, rfilter=dict(type="box"),
                  pixel_format="rgb"),
        sampler=dict(type="independent", sample_count=spp),
    )


def cornell_box(res=32, spp=4) -> dict:
    """Mitsuba's Cornell box (meshes only) at a small size with a box filter."""
    desc = mi.cornell_box()
    desc["sensor"].update(_film(res, spp))
    return desc


def analytic_scene(res=32, spp=4) -> dict:
    """Meshes (rectangle, cube) with every analytic shape hlbvh supports (spheres, a
    disk, a cylinder), a spherical area light, a point light, an environment, and
    diffuse, dielectric and conductor BSDFs."""
    return {
        "type": "scene",
        "sensor": dict(
            type="perspective", fov=45,
            to_world=T().look_at(origin=[0, 1.6, 5], target=[0, 0.5, 0], up=[0, 1, 0]),
            **_film(res, spp),
        ),
        "floor": dict(type="rectangle", to_world=T().rotate([1, 0, 0], -90).scale(4)),
        "box": dict(type="cube", to_world=T().translate([1.6, 0.4, -0.6]).scale(0.4)),
        "ball": dict(type="sphere", center=[-0.8, 0.5, 0], radius=0.5),
        "glass": dict(type="sphere", center=[0.7, 0.4, 0.8], radius=0.4,
                      bsdf=dict(type="dielectric")),
        "mirror": dict(type="disk", to_world=T().translate([0, 1.2, -1.5]).scale(0.8),
                       bsdf=dict(type="conductor")),
        "tube": dict(type="cylinder", p0=[-1.8, 0, -1], p1=[-1.8, 1.4, -1], radius=0.3),
        "lamp": dict(type="sphere", center=[0.5, 3, 1], radius=0.3,
                     emitter=dict(type="area", radiance=dict(type="rgb", value=15))),
        "sun": dict(type="point", position=[-2, 3, 2], intensity=dict(type="rgb", value=6)),
        "sky": dict(type="constant", radiance=dict(type="rgb", value=0.1)),
    }


def camera_rays(scene, res=32, seed=0) -> mi.Ray3f:
    """One ray through a random point of each pixel of the scene's sensor (pixel
    centres of a symmetric camera line up with the seams between walls)."""
    sensor = scene.sensors()[0]
    idx = dr.arange(mi.UInt32, res * res)
    jitter = np.random.default_rng(seed).uniform(size=(2, res * res)).astype(np.float32)
    uv = mi.Point2f(mi.Float(idx % res) + jitter[0], mi.Float(idx // res) + jitter[1]) / res
    ray, _ = sensor.sample_ray(0.0, 0.5, uv, mi.Point2f(0.5))
    return ray


def bounce_rays(scene, n=4096, seed=0) -> mi.Ray3f:
    """Incoherent rays: from random points on random shapes, in random directions."""
    rng = np.random.default_rng(seed)
    bbox = scene.bbox()
    lo, hi = np.array(bbox.min), np.array(bbox.max)
    o = rng.uniform(lo, hi, (n, 3))
    d = rng.normal(size=(n, 3))
    return mi.Ray3f(mi.Point3f(*o.T.astype(np.float32)), mi.Vector3f(*d.T.astype(np.float32)))


# ---------------------------------------------------------------------------------------
# Construction and bad input
# ---------------------------------------------------------------------------------------


def test01_make_accel_picks_by_name_and_rejects_others():
    scene = mi.load_dict(cornell_box())
    assert isinstance(hlbvh.make_accel(scene, "native"), hlbvh.NativeAccel)
    with pytest.raises(ValueError, match="accel='embree'"):
        hlbvh.make_accel(scene, "embree")


@pytest.mark.parametrize("accel", ["hlbvh", "native"])
def test02_unknown_or_invalid_option_names_it(accel):
    scene = mi.load_dict(cornell_box())
    with pytest.raises(ValueError, match="leaf_sise"):
        hlbvh.make_accel(scene, accel, leaf_sise=4)
    with pytest.raises(ValueError, match="builder='fast'"):
        hlbvh.make_accel(scene, accel, builder="fast")


def test03_instances_are_rejected_naming_the_shape():
    scene = mi.load_dict({
        "type": "scene",
        "group": {"type": "shapegroup", "s": {"type": "sphere"}},
        "copy": {"type": "instance", "shapegroup": {"type": "ref", "id": "group"}},
        "floor": {"type": "rectangle"},
    })
    with pytest.raises(ValueError, match="'copy' \\(Instance\\)"):
        hlbvh.SceneAccel(scene, static="hlbvh")


def test04_curves_are_rejected_naming_the_shape(tmp_path):
    path = tmp_path / "curve.txt"
    path.write_text("0 0 0 0.1\n1 0 0 0.1\n2 1 0 0.1\n3 1 0 0.1\n")
    scene = mi.load_dict({"type": "scene",
                          "hair": {"type": "linearcurve", "filename": str(path)}})
    with pytest.raises(ValueError, match="'hair' \\(LinearCurve\\)"):
        hlbvh.SceneAccel(scene, static="hlbvh")


def _scene_with_mesh(positions: np.ndarray, mesh_id="tri") -> mi.Scene:
    mesh = mi.Mesh(mesh_id, len(positions), len(positions) // 3)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(positions.ravel().astype(np.float32))
    params["faces"] = mi.UInt32(np.arange(len(positions), dtype=np.uint32))
    params.update()
    return mi.load_dict({"type": "scene", mesh_id: mesh})


def test05_non_finite_vertices_name_the_shape():
    positions = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [np.nan, 0, 1],
                          [0, 1, 1]], dtype=np.float32)
    scene = _scene_with_mesh(positions, "broken-mesh")
    with pytest.raises(ValueError, match="'broken-mesh'.*non-finite"):
        hlbvh.SceneAccel(scene, static="hlbvh")


def test06_scene_without_geometry_misses_everywhere():
    scene = mi.load_dict({"type": "scene", "sky": {"type": "constant"}})
    accel = hlbvh.SceneAccel(scene, static="hlbvh")
    ray = mi.Ray3f(mi.Point3f(0, 0, 0), mi.Vector3f([1, 0, 0], [0, 1, 0], [0, 0, 1]))
    pi = accel.ray_intersect_preliminary(ray)
    assert not dr.any(pi.is_valid()) and dr.all(pi.t == dr.inf)
    assert not dr.any(accel.ray_test(ray))
    assert not dr.any(accel.ray_intersect(ray).is_valid())


@pytest.mark.skipif(not empty_mesh_loads(), reason="Mitsuba's OptiX build aborts on a mesh without faces")
def test07_meshes_without_triangles_name_the_shape():
    """Mitsuba's obj/ply loaders refuse a mesh without faces; one built in Python would
    silently vanish from the image, so the accelerator names it instead."""
    scene = mi.load_dict({"type": "scene", "empty": mi.Mesh("empty", 0, 0),
                          "ball": {"type": "sphere"}})
    with pytest.raises(ValueError, match="'empty' \\(Mesh\\) has no triangles"):
        hlbvh.SceneAccel(scene, static="hlbvh")


# ---------------------------------------------------------------------------------------
# Signatures: the overloads of mi.Scene
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("accel_name", ["native", "hlbvh"])
def test08_overloads_bind_arguments_like_mi_scene(accel_name):
    """mi.Scene's short overloads take (ray, active); the long ones (ray, ray_flags,
    coherent, active) and (ray, coherent, active); ray_intersect_preliminary only
    (ray, coherent, active). Same answers as the scene for every spelling."""
    scene = mi.load_dict(analytic_scene())
    accel = hlbvh.make_accel(scene, accel_name)
    ray = camera_rays(scene, 8)
    mask = mi.Bool(np.arange(64) % 3 == 0)
    calls = [
        ("ray_test", (ray, mask), {}),
        ("ray_test", (ray, True, mask), {}),
        ("ray_test", (ray,), dict(coherent=True)),
        ("ray_test", (ray,), dict(active=mask)),
        ("ray_test", (ray, False), dict(active=mask)),
        ("ray_intersect", (ray, mask), {}),
        ("ray_intersect", (ray, mi.RayFlags.All, True), {}),
        ("ray_intersect", (ray, mi.RayFlags.All, False, mask), {}),
        ("ray_intersect", (ray,), dict(active=mask)),
        ("ray_intersect_preliminary", (ray, True, mask), {}),
        ("ray_intersect_preliminary", (ray, mask), {}),
        ("ray_intersect_preliminary", (ray,), dict(active=mask)),
        ("ray_intersect_preliminary", (ray,), dict(coherent=True, reorder=False, active=mask)),
        ("ray_intersect", (ray,), dict(ray_flags=mi.RayFlags.All, coherent=False, active=mask)),
    ]
    fields = {"ray_test": (), "ray_intersect": ("t", "prim_index", "p", "n", "uv"),
              "ray_intersect_preliminary": ("t", "prim_index", "shape_index", "prim_uv")}
    for name, args, kwargs in calls:
        ours = getattr(accel, name)(*args, **kwargs)
        theirs = getattr(scene, name)(*args, **kwargs)
        what = f"{name}{args[1:]}{kwargs}"
        if name == "ray_test":
            np.testing.assert_array_equal(ours, theirs, err_msg=what)
            continue
        valid = np.array(theirs.is_valid())
        np.testing.assert_array_equal(np.array(ours.is_valid()), valid, err_msg=what)
        assert np.array(ours.shape == theirs.shape)[valid].all(), what
        for field in fields[name]:
            np.testing.assert_array_equal(np.array(getattr(ours, field))[..., valid],
                                          np.array(getattr(theirs, field))[..., valid],
                                          err_msg=f"{what}: {field}")


class _RecordingScene:
    """Stands in for a mi.Scene: records the arguments each query receives."""

    def __init__(self):
        self.calls = []

    def __getattr__(self, name):
        return lambda *args: self.calls.append((name, args)) or name


def test09_native_accel_hands_mitsuba_every_argument_in_its_order():
    """NativeAccel forwards each query with Mitsuba's own positional order: (ray,
    coherent, reorder, reorder_hint, reorder_hint_bits, active) for the preliminary
    query, (ray, ray_flags, coherent, reorder..., active) for the full one, (ray,
    coherent, active) for the shadow test, whatever spelling the caller used."""
    scene = _RecordingScene()
    accel = hlbvh.NativeAccel(scene)
    ray = mi.Ray3f(mi.Point3f(0, 0, 0), mi.Vector3f(0, 0, 1))
    mask = mi.Bool(True)
    accel.ray_intersect_preliminary(ray, True, mask, reorder=True, reorder_hint=7,
                                    reorder_hint_bits=3)
    accel.ray_intersect(ray, mi.RayFlags.Minimal, False, mask)
    accel.ray_intersect(ray, mask)
    accel.ray_test(ray, True, mask)
    accel.ray_test(ray, active=mask)
    assert [(name, args[1:]) for name, args in scene.calls] == [
        ("ray_intersect_preliminary", (True, True, 7, 3, mask)),
        ("ray_intersect", (mi.RayFlags.Minimal, False, False, 0, 0, mask)),
        ("ray_intersect", (mi.RayFlags.All, False, False, 0, 0, mask)),
        ("ray_test", (True, mask)),
        ("ray_test", (False, mask)),
    ]
    assert all(args[0] is ray for _, args in scene.calls)


# ---------------------------------------------------------------------------------------
# Collection
# ---------------------------------------------------------------------------------------


def test10_collected_triangles_are_the_meshes_world_space_triangles():
    """Every global triangle maps back to (shape index, local index) and has exactly
    that mesh's world-space vertices (numpy reference built shape by shape)."""
    scene = mi.load_dict(analytic_scene())
    accel = hlbvh.SceneAccel(scene, static="hlbvh")
    geometry = collect_geometry(scene.shapes())
    vertices = np.array(geometry.vertices).reshape(-1, 3)
    faces = np.array(geometry.faces).reshape(-1, 3)
    prim_shape, prim_local = np.array(geometry.prim_shape), np.array(geometry.prim_local)
    shapes = scene.shapes()
    meshes = [i for i, s in enumerate(shapes) if s.is_mesh()]
    assert sorted(set(prim_shape)) == meshes
    assert sorted(i for i, _ in accel.analytic) == [i for i, s in enumerate(shapes)
                                                    if not s.is_mesh()]
    for i in meshes:
        mesh = shapes[i]
        mv = np.array(mesh.vertex_positions_buffer()).reshape(-1, 3)
        mf = np.array(mesh.faces_buffer()).reshape(-1, 3)
        rows = np.nonzero(prim_shape == i)[0]
        np.testing.assert_array_equal(prim_local[rows], np.arange(mesh.face_count()))
        np.testing.assert_array_equal(vertices[faces[rows]], mv[mf])


# ---------------------------------------------------------------------------------------
# Hits against the native accelerator
# ---------------------------------------------------------------------------------------


def _compare_preliminary(ray, ours, theirs, rtol=2e-5) -> float:
    """Fraction of rays on which ``ours`` agrees with ``theirs`` (Mitsuba's): both miss,
    or both hit at the same ``t`` (same shape pointer too when the same primitive),
    where a different primitive at the same ``t`` is a tie (coplanar or edge-sharing
    triangles, either answer is right).

    "Same t": within ``rtol`` of ``t + |o|/|d|``, i.e. relative to the magnitude of
    the coordinates involved: Embree's and our triangle tests, and Embree's double-
    precision callback for cylinders against Mitsuba's float32 routine, round
    differently (measured up to 1e-5 of that scale on 200k rays)."""
    v_o, v_t = np.array(ours.is_valid()), np.array(theirs.is_valid())
    both = v_o & v_t
    o, d = np.array(ray.o), np.array(ray.d)
    scale = np.array(theirs.t)[both] + np.abs(o).max(axis=0)[both] / np.linalg.norm(d, axis=0)[both]
    same_t = np.zeros_like(both)
    same_t[both] = np.abs(np.array(ours.t)[both] - np.array(theirs.t)[both]) <= rtol * scale
    same_prim = (both & (np.array(ours.shape_index) == np.array(theirs.shape_index))
                 & (np.array(ours.prim_index) == np.array(theirs.prim_index)))
    assert np.array(ours.shape == theirs.shape)[same_prim].all()
    assert not dr.any(ours.instance != None)  # noqa: E711 (JIT pointer compare)
    return np.mean((~v_o & ~v_t) | (both & same_t))


@pytest.mark.parametrize("scene_fn", [cornell_box, analytic_scene])
def test11_preliminary_hits_and_shadow_tests_equal_native(scene_fn):
    """Camera rays (coherent) and rays from inside the scene in every direction
    (incoherent): at most 2 of 4096 may disagree (a grazing ray on a seam)."""
    scene = mi.load_dict(scene_fn())
    accel = hlbvh.SceneAccel(scene, static="hlbvh")
    for coherent, ray in ((True, camera_rays(scene, 64)), (False, bounce_rays(scene))):
        allowed = 1 - 2 / dr.width(ray)
        ours = accel.ray_intersect_preliminary(ray, coherent)
        theirs = scene.ray_intersect_preliminary(ray, coherent)
        assert _compare_preliminary(ray, ours, theirs) >= allowed
        occluded = np.array(accel.ray_test(ray, coherent, True))
        assert np.mean(occluded == np.array(scene.ray_test(ray, coherent, True))) >= allowed
        np.testing.assert_array_equal(occluded, np.array(ours.is_valid()))


def test12_analytic_hits_equal_native():
    """Spheres, disks, cylinders go through Mitsuba's own routine in both accelerators:
    spheres and disks give the same bits; cylinders differ in the last bits (Embree's
    callback evaluates them in double precision, a direct JIT call in float32)."""
    scene = mi.load_dict(analytic_scene())
    accel = hlbvh.SceneAccel(scene, static="hlbvh")
    ray = bounce_rays(scene, 16384, seed=3)
    ours, theirs = accel.ray_intersect(ray), scene.ray_intersect(ray)
    shape_index = np.array(accel.ray_intersect_preliminary(ray).shape_index)
    hit = np.array(ours.is_valid())
    for index, shape in accel.analytic:
        on_shape = hit & (shape_index == index)
        assert on_shape.sum() > 50
        np.testing.assert_array_equal(np.array(theirs.is_valid())[on_shape], True)
        t_o, t_t = np.array(ours.t)[on_shape], np.array(theirs.t)[on_shape]
        if shape.class_name() == "Cylinder":
            np.testing.assert_allclose(t_o, t_t, rtol=1e-4)
        else:
            for field in ("t", "p", "n", "uv"):
                a, b = np.array(getattr(ours, field)), np.array(getattr(theirs, field))
                np.testing.assert_array_equal(a[..., on_shape], b[..., on_shape], err_msg=field)


def test13_nan_and_degenerate_rays_miss_cleanly():
    scene = mi.load_dict(analytic_scene())
    accel = hlbvh.SceneAccel(scene, static="hlbvh")
    nan, inf = float("nan"), float("inf")
    o = mi.Point3f([nan, 0, 0, 0, 0, inf], [0, nan, 1, 1, 1, 0], [5, 5, 5, 5, 5, 5])
    d = mi.Vector3f([0, 0, nan, 0, 0, 0], [0, 0, 0, 0, 0, 0], [-1, -1, -1, 0, -1, -1])
    ray = mi.Ray3f(o, d)
    ray.maxt = mi.Float(1e30, 1e30, 1e30, 1e30, nan, 1e30)
    pi = accel.ray_intersect_preliminary(ray)
    assert not dr.any(pi.is_valid())
    assert not dr.any(accel.ray_test(ray))
    si = accel.ray_intersect(ray)
    assert not dr.any(si.is_valid())


@pytest.mark.parametrize("accel_name", ["native", "hlbvh"])
def test13b_no_rays_give_empty_answers(accel_name):
    """A ray of width 0 gives answers of width 0 from every query, as from mi.Scene."""
    scene = mi.load_dict(analytic_scene())
    accel = hlbvh.make_accel(scene, accel_name)
    ray = mi.Ray3f(mi.Point3f(), mi.Vector3f())
    assert dr.width(accel.ray_intersect_preliminary(ray).t) == 0
    assert dr.width(accel.ray_test(ray)) == 0
    assert dr.width(accel.ray_intersect(ray).t) == 0


def test14_update_follows_params_update():
    """Move the Cornell box's geometry through params.update(): changed() notices,
    update() rebuilds, and the hits follow the native ones again."""
    scene = mi.load_dict(cornell_box())
    accel = hlbvh.SceneAccel(scene, static="hlbvh")
    assert not accel.changed()
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.endswith("vertex_positions"))
    params[key] = params[key] * 0.5 + 0.1
    params.update()
    assert accel.changed()
    accel.update()
    assert not accel.changed()
    ray = bounce_rays(scene, seed=5)
    ours, theirs = accel.ray_intersect_preliminary(ray), scene.ray_intersect_preliminary(ray)
    assert _compare_preliminary(ray, ours, theirs) >= 1 - 2 / dr.width(ray)
