"""Motion is seen however a shape is written: an instance turned or mirrored so that
its world box stays the same, through ``mi.traverse`` and ``hlbvh.traverse``, with
scalar and JIT transforms and through the animation loaders' ``apply_frame``; the same
values written again are no motion. After each write the accelerator's hits equal those
of a scene loaded afresh with the new transform (Mitsuba's own query over it)."""

import drjit as dr
import hlbvh
import mitsuba as mi
import numpy as np
import pytest

from hlbvh.accel.motion import shape_state
from hlbvh.scenes.animated import FrameGeometry, apply_frame

T = mi.ScalarTransform4f


def _l_plate() -> mi.Mesh:
    """An L-shaped plate in [-1, 1]^2 (z = 0): a turn by 90 degrees about z, or a
    mirror in x, keeps its box and moves most of its surface."""
    squares = [(-1, -1), (0, -1), (-1, 0)]  # three of the four unit squares
    v, f = [], []
    for x, y in squares:
        b = len(v)
        v += [(x, y, 0), (x + 1, y, 0), (x + 1, y + 1, 0), (x, y + 1, 0)]
        f += [(b, b + 1, b + 2), (b, b + 2, b + 3)]
    mesh = mi.Mesh("plate", len(v), len(f))
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(np.array(v, np.float32).ravel())
    params["faces"] = mi.UInt32(np.array(f, np.uint32).ravel())
    params.update()
    return mesh


def _scene_dict(to_world=None) -> dict:
    d = {"type": "scene", "integrator": {"type": "hlbvh_path"},
         "group": {"type": "shapegroup", "plate": _l_plate()},
         "inst": {"type": "instance", "shapegroup": {"type": "ref", "id": "group"}},
         "floor": {"type": "rectangle", "to_world": T().translate([0, 0, -2]).scale(4)}}
    if to_world is not None:
        d["inst"]["to_world"] = to_world
    return d


def _rays() -> mi.Ray3f:
    """A grid of rays straight down over the plate's box."""
    xs = (np.arange(24) + 0.5) / 24 * 2 - 1
    x, y = np.meshgrid(xs, xs)
    n = x.size
    return mi.Ray3f(mi.Point3f(mi.Float(x.ravel()), mi.Float(y.ravel()), dr.full(mi.Float, 3, n)),
                    mi.Vector3f(0, 0, -1))


def _assert_hits_as_loaded(accel, matrix):
    """The accelerator's closest hits equal Mitsuba's over a scene loaded with the
    instance at ``matrix``: the same shape (plate or floor) at the same t."""
    reference = mi.load_dict(_scene_dict(T(matrix.tolist())))
    ray = _rays()
    ours, theirs = accel.ray_intersect_preliminary(ray), reference.ray_intersect_preliminary(ray)
    on_plate = np.array(theirs.instance != None)  # noqa: E711 (JIT pointer compare)
    assert 0 < on_plate.sum() < dr.width(ray)
    np.testing.assert_array_equal(np.array(ours.instance != None), on_plate)  # noqa: E711
    np.testing.assert_allclose(np.array(ours.t), np.array(theirs.t), rtol=1e-6)


TURNS = [T().rotate([0, 0, 1], a).matrix for a in (90, 180, 270)] + [
    T().scale([-1, 1, 1]).matrix,            # mirrored in x: same box
    T().scale([1, 1, -1]).matrix,            # mirrored in z (normals flipped): same box
    T().rotate([0, 0, 1], 90).matrix,        # back to an earlier pose
]


def _write(params, how, matrix):
    if how == "scalar":
        params["inst.to_world"] = T(np.asarray(matrix).tolist())
    elif how == "scalar_affine":
        params["inst.to_world"] = mi.ScalarAffineTransform4f(np.asarray(matrix, np.float32))
    elif how == "jit":
        params["inst.to_world"] = mi.Transform4f(np.asarray(matrix, np.float32))
    params.update()


@pytest.mark.parametrize("traverse", ["mi", "hlbvh"])
@pytest.mark.parametrize("how", ["scalar", "scalar_affine", "jit", "apply_frame"])
def test01_a_turn_or_mirror_that_keeps_the_box_is_seen(traverse, how):
    scene = mi.load_dict(_scene_dict())
    accel = hlbvh.SceneAccel(scene, moving=["inst"])
    params = mi.traverse(scene) if traverse == "mi" else hlbvh.traverse(scene)
    box = scene.shapes()[[s.id() for s in scene.shapes()].index("inst")].bbox()
    exact = 0  # poses whose box is the first one's to the bit (the mirrors)
    for matrix in TURNS:
        matrix = np.array(matrix, np.float64)
        if how == "apply_frame":
            apply_frame(scene, params, {"inst": FrameGeometry(to_world=matrix)})
        else:
            _write(params, how, matrix)
        inst = scene.shapes()[[s.id() for s in scene.shapes()].index("inst")]
        np.testing.assert_allclose([inst.bbox().min, inst.bbox().max], [box.min, box.max],
                                   atol=1e-6)  # the box says nothing
        exact += inst.bbox() == box
        assert accel.changed()
        accel.update()
        assert accel.last_update["decision"] != "kept", matrix
        _assert_hits_as_loaded(accel, matrix)
    assert exact >= 2


@pytest.mark.parametrize("traverse", ["mi", "hlbvh"])
def test02_the_same_transform_written_again_is_no_motion(traverse):
    scene = mi.load_dict(_scene_dict())
    accel = hlbvh.SceneAccel(scene, moving=["inst"])
    params = mi.traverse(scene) if traverse == "mi" else hlbvh.traverse(scene)
    turn = np.array(TURNS[0], np.float32)
    _write(params, "scalar_affine", turn)
    accel.update()
    assert accel.last_update["decision"] != "kept"
    _write(params, "jit", turn)
    assert not accel.changed()
    accel.update()
    assert accel.last_update["decision"] == "kept"
    _assert_hits_as_loaded(accel, turn)


def test03_a_shape_state_holds_values_not_the_variables_mitsuba_writes_into():
    """Mitsuba writes a new transform into the variables the instance already holds:
    a state taken before the write must still tell the old pose."""
    scene = mi.load_dict(_scene_dict())
    inst = scene.shapes()[[s.id() for s in scene.shapes()].index("inst")]
    params = mi.traverse(scene)
    handles = {}
    _write(params, "scalar_affine", np.array(TURNS[0], np.float32))
    before = shape_state(inst, handles)
    _write(params, "scalar_affine", np.array(TURNS[1], np.float32))
    after = shape_state(inst, handles)
    assert after.moved(before)
    assert not shape_state(inst, handles).moved(after)


def test04_a_sphere_whose_radius_is_written_in_place_is_seen():
    """Another shape's own scalar parameter (a sphere's radius and centre), written
    through its parameters, is motion too."""
    scene = mi.load_dict({"type": "scene", "ball": {"type": "sphere", "radius": 0.5}})
    accel = hlbvh.SceneAccel(scene, moving=["ball"])
    params = mi.traverse(scene)
    keys = [k for k in params.keys() if k.startswith("ball.")]
    assert keys
    ray = mi.Ray3f(mi.Point3f(0, 0, 5), mi.Vector3f(0, 0, -1))
    t0 = accel.ray_intersect_preliminary(ray).t[0]
    params["ball.to_world"] = T().scale(0.25)
    params.update()
    assert accel.changed()
    accel.update()
    t1 = accel.ray_intersect_preliminary(ray).t[0]
    assert abs(t0 - 4.5) < 1e-5 and abs(t1 - 4.75) < 1e-5


def _cloth_scene(integrator: dict) -> dict:
    from meshes import grid

    v, f = grid(12)
    mesh = mi.Mesh("cloth", len(v), len(f))
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(v.ravel())
    params["faces"] = mi.UInt32(f.ravel())
    params.update()
    return {"type": "scene", "integrator": integrator, "cloth": mesh,
            "light": {"type": "constant"},
            "sensor": {"type": "perspective", "fov": 50,
                       "to_world": T().look_at([0.5, 0.5, 2], [0.5, 0.5, 0], [0, 1, 0]),
                       "film": {"type": "hdrfilm", "width": 24, "height": 24,
                                "rfilter": {"type": "box"}},
                       "sampler": {"type": "independent", "sample_count": 2}}}


def _lift(params):
    positions = np.array(params["cloth.vertex_positions"]).reshape(-1, 3)
    positions[:, 2] += 0.3 * positions[:, 0]  # tilt the cloth
    params["cloth.vertex_positions"] = mi.Float(positions.ravel())
    params.update()


@pytest.mark.parametrize("integrator", [{"type": "path"}, {"type": "direct"},
                                        {"type": "hlbvh_path", "accel": "native"}],
                         ids=["path", "direct", "hlbvh_path-native"])
def test05_mitsubas_accelerator_is_brought_up_to_date_for_integrators_that_query_it(integrator):
    """A scene whose integrator traces through Mitsuba's own accelerator, animated with
    hlbvh.traverse, renders what a scene loaded with the new geometry renders (one
    warning says the rebuild is not skipped)."""
    scene = mi.load_dict(_cloth_scene(integrator))
    with pytest.warns(UserWarning, match="traces through Mitsuba's own accelerator"):
        params = hlbvh.traverse(scene)
    _lift(params)
    image = np.array(mi.render(scene, seed=3))
    fresh = mi.load_dict(_cloth_scene(integrator))
    _lift(mi.traverse(fresh))
    np.testing.assert_array_equal(image, np.array(mi.render(fresh, seed=3)))


def test06_our_integrator_with_our_accelerator_skips_mitsubas_rebuild():
    """With hlbvh_path (accel="hlbvh") the scene's own accelerator is left as it was
    (the point of hlbvh.traverse), while our render follows the new geometry."""
    import warnings

    scene = mi.load_dict(_cloth_scene({"type": "hlbvh_path"}))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        params = hlbvh.traverse(scene)
    ray = mi.Ray3f(mi.Point3f(0.9, 0.5, 2), mi.Vector3f(0, 0, -1))
    before = scene.ray_intersect_preliminary(ray).t[0]
    _lift(params)
    assert scene.ray_intersect_preliminary(ray).t[0] == before  # Mitsuba's: not rebuilt
    image = np.array(mi.render(scene, seed=3))
    fresh = mi.load_dict(_cloth_scene({"type": "hlbvh_path"}))
    _lift(mi.traverse(fresh))
    np.testing.assert_array_equal(image, np.array(mi.render(fresh, seed=3)))


def _l_plate_stage(path):
    """A Y-up stage in metres, time codes 0..4: a ground, and an L-shaped plate of
    2166 triangles (an instance: a rigid mesh of 2048+ triangles) turned 0, 90, 180,
    270 degrees about the vertical, then mirrored, its world box the same throughout;
    a camera above it, a sky."""
    from pxr import Gf, Usd, UsdGeom, UsdLux

    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetStartTimeCode(0)
    stage.SetEndTimeCode(4)
    ground = UsdGeom.Mesh.Define(stage, "/Ground")
    ground.CreatePointsAttr([(-3, -0.2, -3), (3, -0.2, -3), (3, -0.2, 3), (-3, -0.2, 3)])
    ground.CreateFaceVertexCountsAttr([4])
    ground.CreateFaceVertexIndicesAttr([0, 3, 2, 1])
    n = 19  # cells a side of each of the L's three unit squares
    points, counts, indices = [], [], []
    for qx, qz in ((-1, -1), (0, -1), (-1, 0)):
        base = len(points)
        points += [(qx + x / n, 0.0, qz + z / n) for z in range(n + 1) for x in range(n + 1)]
        for z in range(n):
            for x in range(n):
                a = base + z * (n + 1) + x
                counts.append(4)
                indices += [a, a + n + 1, a + n + 2, a + 1]
    mover = UsdGeom.Xform.Define(stage, "/Mover")
    turn = mover.AddRotateYOp()
    scale = mover.AddScaleOp()
    for t, (angle, sx) in enumerate(((0, 1), (90, 1), (180, 1), (270, 1), (0, -1))):
        turn.Set(float(angle), t)
        scale.Set(Gf.Vec3f(sx, 1, 1), t)
    plate = UsdGeom.Mesh.Define(stage, "/Mover/Plate")
    plate.CreatePointsAttr(points)
    plate.CreateFaceVertexCountsAttr(counts)
    plate.CreateFaceVertexIndicesAttr(indices)
    plate.CreateDoubleSidedAttr(True)
    camera = UsdGeom.Camera.Define(stage, "/Cam")
    camera.AddTranslateOp().Set(Gf.Vec3d(0.3, 4, 0.2))
    camera.AddRotateXOp().Set(-90.0)
    UsdLux.DomeLight.Define(stage, "/Sky").CreateIntensityAttr(1.0)
    stage.GetRootLayer().Save()
    return path


@pytest.mark.parametrize("moving_accel", ["hlbvh", "auto", "scene"])
def test07_a_usd_instance_turned_in_place_renders_as_native_frame_by_frame(tmp_path,
                                                                           moving_accel):
    """The case a hostile user found: a USD plate turned by 90 degrees at a time (and
    mirrored), its box unchanged, rendered through the animation loop (scalar
    transforms written each frame): each frame equals native's, and differs from the
    frame before."""
    pytest.importorskip("pxr")
    from hlbvh.render.frame import FrameRenderer
    from hlbvh.render.settings import RenderSettings
    from hlbvh.scenes.usd import UsdScene
    from test_render import assert_close_to_native

    path = _l_plate_stage(tmp_path / "plate.usda")
    settings = dict(resolution=(32, 32), spp=2, max_depth=2)
    ours = FrameRenderer(UsdScene(path, warn=lambda line: None),
                         RenderSettings(accel="hlbvh", moving_accel=moving_accel, **settings))
    native = FrameRenderer(UsdScene(path, warn=lambda line: None),
                           RenderSettings(accel="native", **settings))
    assert ours.animation.instance_groups()  # the plate is an instance
    previous = None
    for i in range(5):
        image, row = ours.render(i)
        image = np.array(image)
        assert_close_to_native(image, np.array(native.render(i)[0]))
        if previous is not None:
            assert not np.array_equal(image, previous)
            assert row["decision"] != "kept"
        previous = image


@pytest.mark.parametrize("wrapper, skips", [("moment", True), ("aov", False)])
def test08_a_wrapper_around_ours_skips_the_rebuild_only_when_it_traces_nothing_itself(
        wrapper, skips):
    """``moment`` only averages its nested integrator's samples: around ours, Mitsuba's
    rebuild is skipped; Mitsuba's ``aov`` queries the scene for its own channels, so the
    scene is kept current (with the warning). Either way the render follows the cloth."""
    import warnings

    nested = {"type": "hlbvh_path", "max_depth": 3}
    integrator = ({"type": "moment", "nested": nested} if wrapper == "moment" else
                  {"type": "aov", "aovs": "dd.y:depth", "nested": nested})
    scene = mi.load_dict(_cloth_scene(integrator))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        params = hlbvh.traverse(scene)
    assert params.skips_rebuild == skips
    assert bool([w for w in caught if "Mitsuba's own accelerator" in str(w.message)]) != skips
    _lift(params)
    fresh = mi.load_dict(_cloth_scene(integrator))
    _lift(mi.traverse(fresh))
    np.testing.assert_allclose(np.array(mi.render(scene, seed=3)),
                               np.array(mi.render(fresh, seed=3)), atol=1e-4)
