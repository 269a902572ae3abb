"""USD geometry inside a frame, for motion blur: :meth:`UsdScene.frame_at` evaluates
moving meshes and instances at fractional time codes as pxr does (``velocities`` from
the frame's sample, ``motion:blurScale``, interpolated samples, xformOps, point
instancers' ``ComputeInstanceTransformsAtTime``), and ``hlbvh render --shutter`` of a
velocity-moving quad and of a turning instance renders blurred, as native's sub-frame
mean."""

import numpy as np
import pytest

pytest.importorskip("pxr")

from pxr import Gf, Usd, UsdGeom, UsdLux, Vt  # noqa: E402

from cli_helpers import run_cli  # noqa: E402
from hlbvh.render import images  # noqa: E402
from hlbvh.render.source import SceneSpec, open_animation  # noqa: E402
from hlbvh.scenes.usd import UsdScene  # noqa: E402

#: Time codes per second of the stages below: velocities are in units per second, a
#: frame is one time code.
TCPS = 24.0
QUAD = [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)]


def _stage(path, end=3, velocity=None, samples=None, blur_scale=None, light=False,
           quad="/Quad"):
    """A Y-up stage in metres, frames 0..``end``, with a quad (prim path ``quad``) facing
    a camera at z=4: its points one time sample at 0 with ``velocity`` (units per second) when
    given, else ``samples`` (``{time code: offset along x}``), else still; its
    ``motion:blurScale`` when given; a distant light when ``light`` (else the default
    sky and sun)."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetStartTimeCode(0)
    stage.SetEndTimeCode(end)
    stage.SetTimeCodesPerSecond(TCPS)
    mesh = UsdGeom.Mesh.Define(stage, quad)
    points = mesh.CreatePointsAttr()
    if velocity is not None:
        points.Set(Vt.Vec3fArray(QUAD), 0)
        mesh.CreateVelocitiesAttr().Set(Vt.Vec3fArray([velocity] * 4), 0)
    elif samples is not None:
        for code, dx in samples.items():
            points.Set(Vt.Vec3fArray([(x + dx, y, z) for x, y, z in QUAD]), code)
    else:
        points.Set(Vt.Vec3fArray(QUAD))
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    mesh.CreateSubdivisionSchemeAttr("none")
    if blur_scale is not None:
        UsdGeom.MotionAPI.Apply(mesh.GetPrim()).CreateMotionBlurScaleAttr(blur_scale)
    UsdGeom.Camera.Define(stage, "/Cam").AddTranslateOp().Set(Gf.Vec3d(0, 0, 4))
    if light:
        sun = UsdLux.DistantLight.Define(stage, "/Sun")  # along -z, onto the quad
        sun.CreateIntensityAttr(3.0)
        sun.CreateNormalizeAttr(True)  # an irradiance of 3: the quad on black
    stage.GetRootLayer().Save()
    return stage


def _quad(frame):
    return frame["Quad"].positions.reshape(-1, 3).astype(np.float64)


def test01_velocities_move_the_points_inside_the_frame_and_blur_scale_scales_them(tmp_path):
    """One time sample and velocities: a quarter frame later the points moved by
    velocity x 0.25 / timeCodesPerSecond (pxr's ComputePointsAtTime from the frame's
    sample), a quarter frame before by minus that; ``motion:blurScale`` 0.5 halves the
    motion inside the frame and leaves the frame itself where it was. The mesh is
    moving (keyed by the frame pipeline), not static."""
    velocity = np.array([4.8, -2.4, 1.2])
    path = tmp_path / "moving.usda"
    _stage(path, velocity=tuple(velocity))
    animation = UsdScene(path, warn=lambda line: None)
    assert "Quad" in animation.animated_ids()
    still = _quad(animation.frame(1))
    np.testing.assert_allclose(still, np.array(QUAD) + velocity * 1 / TCPS, atol=1e-6)
    np.testing.assert_allclose(_quad(animation.frame_at(1.25)),
                               still + velocity * 0.25 / TCPS, atol=1e-6)
    np.testing.assert_allclose(_quad(animation.frame_at(0.75)),
                               still - velocity * 0.25 / TCPS, atol=1e-6)

    halved = tmp_path / "halved.usda"
    _stage(halved, velocity=tuple(velocity), blur_scale=0.5)
    animation = UsdScene(halved, warn=lambda line: None)
    np.testing.assert_allclose(_quad(animation.frame(1)), still, atol=1e-6)
    np.testing.assert_allclose(_quad(animation.frame_at(1.25)),
                               still + velocity * 0.125 / TCPS, atol=1e-6)


def test02_a_fractional_time_equals_pxr_s_own_get_and_xform(tmp_path):
    """Two time samples of the points (0 and 2) and a time-sampled translate on the
    mesh's parent: at time 0.3 the world points are pxr's Get(0.3) through the parent's
    transform at 0.3, not a blend of the frames around it (frame 1 lies between the
    samples too, so the two agree only where pxr's interpolation is used)."""
    path = tmp_path / "sampled.usda"
    stage = _stage(path, end=2, samples={0: 0.0, 2: 2.0}, quad="/Rig/Quad")
    op = UsdGeom.Xform.Define(stage, "/Rig").AddRotateYOp()
    op.Set(0.0, 0)
    op.Set(90.0, 2)  # pxr interpolates the angle: not a blend of two frames' points
    stage.GetRootLayer().Save()
    inner = stage.GetPrimAtPath("/Rig/Quad")
    animation = UsdScene(path, warn=lambda line: None)
    mesh = {v: k for k, v in animation.prim_paths().items()}["/Rig/Quad"]
    for time in (0.3, 1.6):
        code = Usd.TimeCode(time)
        local = np.array(UsdGeom.Mesh(inner).GetPointsAttr().Get(code), dtype=np.float64)
        world = np.array(UsdGeom.XformCache(code).GetLocalToWorldTransform(inner),
                         dtype=np.float64)
        expected = local @ world[:3, :3] + world[3, :3]
        got = animation.frame_at(time)[mesh].positions.reshape(-1, 3)
        np.testing.assert_allclose(got, expected, atol=1e-5)


def test03_a_skinned_stage_s_baked_span_covers_the_shutter():
    """The span a stage is baked over reaches the whole frames that hold the shutter's
    times around the frames asked (frames 1..2 with -0.25..0.25: time codes 0..3),
    within the stage's range."""
    scene = UsdScene.__new__(UsdScene)
    scene._start, scene.frame_count = 10.0, 5
    scene._shutter = (-0.25, 0.25)
    assert scene.time_span(range(1, 3)) == (10.0, 13.0)
    scene._shutter = (0.0, 0.0)
    assert scene.time_span(range(1, 3)) == (11.0, 12.0)
    scene._shutter = (-2.0, 3.0)
    assert scene.time_span(range(0, 2)) == (10.0, 14.0)


def _big_grid(stage, path, n=40):
    """A mesh at ``path``: a 2x2 grid in z=0 of ``2 * (n - 1)^2`` triangles (3042 for
    40), past RIGID_INSTANCE_TRIANGLES: moved by a transform alone, it is an instance."""
    big = UsdGeom.Mesh.Define(stage, path)
    xs, ys = np.meshgrid(np.linspace(-1, 1, n), np.linspace(-1, 1, n))
    big.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(
        np.stack([xs.ravel(), ys.ravel(), np.zeros(n * n)], 1).astype(np.float32)))
    quads = [(r * n + c, r * n + c + 1, (r + 1) * n + c + 1, (r + 1) * n + c)
             for r in range(n - 1) for c in range(n - 1)]
    big.CreateFaceVertexCountsAttr([4] * len(quads))
    big.CreateFaceVertexIndicesAttr([i for q in quads for i in q])
    big.CreateSubdivisionSchemeAttr("none")
    return big


def test04_open_animation_hands_the_shutter_to_the_stage(tmp_path, capsys):
    """A SceneSpec's shutter reaches the stage: the time codes it reads cover the
    shutter around the frames asked (frames 0:2 with -0.25..0.25 read time code 2),
    and a moving instance is no longer said to keep its frame's pose."""
    path = tmp_path / "rigid.usda"
    stage = _stage(path, samples={0: 0.0, 3: 3.0})
    op = UsdGeom.Xform.Define(stage, "/Mover").AddTranslateOp()
    op.Set(Gf.Vec3d(0, 0, 0), 0)
    op.Set(Gf.Vec3d(1, 0, 0), 3)
    _big_grid(stage, "/Mover/Big")
    stage.GetRootLayer().Save()
    animation, *_ = open_animation(SceneSpec(str(path), frames="0:2", shutter=(-0.25, 0.25)))
    assert animation.time_span(range(0, 2)) == (0.0, 2.0)
    assert "frame's pose" not in capsys.readouterr().err
    closed, *_ = open_animation(SceneSpec(str(path), frames="0:2"))
    assert closed.time_span(range(0, 2)) == (0.0, 1.0)


def test05_render_with_a_shutter_blurs_a_velocity_moving_quad_as_native(tmp_path, capsys):
    """``hlbvh render stage.usda --shutter 0.5`` of a quad moved by velocities alone:
    the blurred frame differs from the still one, and is another sample of native's
    sub-frame mean (noise_judge against two native renders with different seeds)."""
    path = tmp_path / "fast.usda"
    _stage(path, end=1, velocity=(48.0, 0.0, 0.0), light=True)  # 2 units a frame
    _assert_blurred_as_native(tmp_path, capsys, path, frame=0)


def test06_accelerations_curve_the_motion_and_their_sample_count_is_said(tmp_path):
    """Velocities and accelerations: frame_at is pxr's ComputePointsAtTime from the
    frame's sample (the curve, not a line between frames); with an open shutter the
    mesh's ``motion:nonlinearSampleCount`` is said as the ``--motion-keys`` it asks."""
    path = tmp_path / "falling.usda"
    stage = _stage(path, velocity=(0.0, 0.0, 0.0))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Quad"))
    mesh.CreateAccelerationsAttr().Set(Vt.Vec3fArray([(0.0, -TCPS * TCPS, 0.0)] * 4), 0)
    UsdGeom.MotionAPI.Apply(mesh.GetPrim()).CreateNonlinearSampleCountAttr(5)
    stage.GetRootLayer().Save()
    said = []
    animation = UsdScene(path, warn=said.append, shutter=(-0.25, 0.25))
    for time, frame in ((1.0, 1), (1.25, 1), (1.75, 2)):
        expected = np.array(mesh.ComputePointsAtTime(Usd.TimeCode(time), Usd.TimeCode(frame)))
        np.testing.assert_allclose(_quad(animation.frame_at(time)), expected, atol=1e-5)
    # y = -1 - t^2 / 2 (t in frames): -1.78125 at 1.25, not -1.875 on the line between
    # frames 1 (-1.5) and 2 (-3)
    assert _quad(animation.frame_at(1.25))[0, 1] == pytest.approx(-1 - 1.25 ** 2 / 2)
    assert any("/Quad: its accelerations curve its motion; motion:nonlinearSampleCount 5 "
               "asks for 5 samples over the shutter: --motion-keys 4 gives them" in line
               for line in said)


def test07_a_skinned_stage_opened_for_one_frame_blurs_over_its_shutter(tmp_path):
    """UsdSkel skinning (pxr's bake) of a stage opened for frame 1 with a shutter of
    -0.25..0.25: frame_at reads the skinned quad at 0.75 and 1.25 (it moves +x by the
    time code), not refused as outside the frames baked, nor held at frame 1's pose."""
    from test_usd_stages import _skinned

    path = _skinned(tmp_path / "char.usda", baked_points=False)
    animation = UsdScene(path, warn=lambda line: None, frames=range(1, 2),
                         shutter=(-0.25, 0.25))
    (body,) = [i for i, p in animation.prim_paths().items() if p == "/Char/Body"]
    for time in (0.75, 1.0, 1.25):
        xs = animation.frame_at(time)[body].positions.reshape(-1, 3)[:, 0]
        assert (xs.min(), xs.max()) == pytest.approx((-1 + time, 1 + time))


def test08_a_blur_scale_that_is_not_finite_is_one_line_naming_the_prim(tmp_path):
    path = tmp_path / "nan.usda"
    _stage(path, velocity=(1.0, 0.0, 0.0), blur_scale=float("nan"))
    animation = UsdScene(path, warn=lambda line: None)
    with pytest.raises(ValueError, match=r"/Quad: motion:blurScale nan at frame 1 "
                                         r"\(time code 1\): expected a finite scale"):
        animation.frame_at(1.25)


def _turning(path, end=2, blur_scale=None):
    """A stage whose big grid (an instance, at /Mover/Big) turns about z 90 degrees a
    frame (rotateZ 0 at time code 0, 90 * ``end`` at ``end``) in front of the camera,
    under a distant light, with ``motion:blurScale`` on /Mover when given; the small
    quad of :func:`_stage` is removed."""
    stage = _stage(path, end=end, light=True)
    stage.RemovePrim("/Quad")
    mover = UsdGeom.Xform.Define(stage, "/Mover")
    op = mover.AddRotateZOp()
    op.Set(0.0, 0)
    op.Set(90.0 * end, end)
    if blur_scale is not None:
        UsdGeom.MotionAPI.Apply(mover.GetPrim()).CreateMotionBlurScaleAttr(blur_scale)
    _big_grid(stage, "/Mover/Big")
    stage.GetRootLayer().Save()
    return stage


def test09_a_moving_instance_takes_pxr_s_transform_at_the_fractional_time_code(tmp_path):
    """An instance turning 90 degrees a frame: frame_at(1.25) and frame_at(0.75) give
    its transform as pxr's XformCache gives it at time codes 1.25 and 0.75 (not frame
    1's pose); ``motion:blurScale`` 0.5 on its parent halves the time from the frame
    (time code 1.125), and 0 holds the frame's pose."""
    path = tmp_path / "turning.usda"
    stage = _turning(path)
    big = stage.GetPrimAtPath("/Mover/Big")

    def pxr_at(code):
        return np.array(UsdGeom.XformCache(Usd.TimeCode(code)).GetLocalToWorldTransform(big),
                        dtype=np.float64).T

    animation = UsdScene(path, warn=lambda line: None, shutter=(-0.25, 0.25))
    (instance,) = animation.instance_groups()
    for time in (0.75, 1.0, 1.25):
        np.testing.assert_allclose(animation.frame_at(time)[instance].to_world,
                                   pxr_at(time), atol=1e-9)
    assert not np.allclose(pxr_at(1.25), pxr_at(1.0), atol=0.1)
    for scale, code in ((0.5, 1.125), (0.0, 1.0)):
        scaled = tmp_path / f"scaled_{scale}.usda"
        _turning(scaled, blur_scale=scale)
        animation = UsdScene(scaled, warn=lambda line: None)
        np.testing.assert_allclose(animation.frame_at(1.25)[instance].to_world,
                                   pxr_at(code), atol=1e-9)


def test10_point_instancer_points_are_pxr_s_at_the_fractional_time_code(tmp_path):
    """A point instancer of two quads: positions sampled at 0 and 2 (interpolated) and
    orientations sampled once, turned by ``angularVelocities`` 90 degrees a frame (about
    z): frame_at(t) gives each point ComputeInstanceTransformsAtTime(t, frame) (the
    frame nearest t as the base), through the instancer's own translate at t. Angular
    velocities alone make the points move (keyed), which the positions' sample would
    not say for frame 0."""
    path = tmp_path / "instancer.usda"
    stage = _stage(path, end=2, light=True)
    stage.RemovePrim("/Quad")
    instancer = UsdGeom.PointInstancer.Define(stage, "/Points")
    move = instancer.AddTranslateOp()
    move.Set(Gf.Vec3d(0, 0, 0), 0)
    move.Set(Gf.Vec3d(0, 2, 0), 2)
    prototype = UsdGeom.Mesh.Define(stage, "/Points/Proto/Quad")
    prototype.CreatePointsAttr(Vt.Vec3fArray([(x * 0.5, y * 0.5, z) for x, y, z in QUAD]))
    prototype.CreateFaceVertexCountsAttr([4])
    prototype.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    instancer.CreatePrototypesRel().AddTarget("/Points/Proto")
    instancer.CreateProtoIndicesAttr([0, 0])
    positions = instancer.CreatePositionsAttr()
    positions.Set(Vt.Vec3fArray([(-1, 0, 0), (1, 0, 0)]), 0)
    positions.Set(Vt.Vec3fArray([(-1, 0, 0), (3, 0, 0)]), 2)
    instancer.CreateOrientationsAttr().Set(Vt.QuathArray([Gf.Quath(1, 0, 0, 0)] * 2), 0)
    instancer.CreateAngularVelocitiesAttr().Set(Vt.Vec3fArray([(0, 0, 90 * TCPS)] * 2), 0)
    stage.GetRootLayer().Save()
    animation = UsdScene(path, warn=lambda line: None, shutter=(-0.25, 0.25))
    ids = sorted(animation.instance_groups())
    assert ids == sorted(animation.animated_ids()) and len(ids) == 2
    for time, frame in ((0.25, 0), (0.75, 1), (1.25, 1)):
        got = animation.frame_at(time)
        base = np.array(UsdGeom.XformCache(Usd.TimeCode(time)).GetLocalToWorldTransform(
            instancer.GetPrim()), dtype=np.float64).T
        points = instancer.ComputeInstanceTransformsAtTime(Usd.TimeCode(time),
                                                           Usd.TimeCode(frame))
        for k, instance in enumerate(ids):
            expected = base @ np.array(points[k], dtype=np.float64).T
            np.testing.assert_allclose(got[instance].to_world, expected, atol=1e-5)
    turned = animation.frame_at(1.25)[ids[0]].to_world[:3, :3]
    angle = np.radians(112.5)  # 1.25 frames of 90 degrees from the sample at 0
    np.testing.assert_allclose(turned @ [1, 0, 0], [np.cos(angle), np.sin(angle), 0],
                               atol=1e-5)


def test11_render_with_a_shutter_blurs_a_turning_instance_as_native(tmp_path, capsys):
    """``hlbvh render stage.usda --shutter 0.5`` of the instance turning 90 degrees a
    frame (frame 1, time codes 0.75..1.25): the blurred frame differs from the still
    one, and is another sample of native's sub-frame mean (noise_judge against two
    native renders with different seeds), which the still frame is not."""
    path = tmp_path / "turning.usda"
    _turning(path)
    _assert_blurred_as_native(tmp_path, capsys, path, frame=1)


def _assert_blurred_as_native(tmp_path, capsys, path, frame: int):
    """``hlbvh render`` of the stage's ``frame`` at 48x48, 16 spp, with ``--shutter 0.5``
    and without: the blurred frame differs from the still one and passes the noise
    judge against two native sub-frame means (different seeds), which the still frame
    fails."""
    from hlbvh.comparison.metrics import noise_judge

    def render(name, *flags):
        out = tmp_path / name
        status, _, err = run_cli(capsys, "render", path, "--frames", f"{frame}:{frame + 1}",
                                 "--resolution", "48x48", "--spp", "16", "--out", out, *flags)
        assert status == 0, err
        return images.read_exr(out / f"frame_{frame:04d}.exr", ["R", "G", "B"])

    blurred = render("blurred", "--accel", "hlbvh", "--shutter", "0.5")
    still = render("still", "--accel", "hlbvh")
    assert np.abs(blurred - still).max() > 0.1
    reference = render("native", "--accel", "native", "--shutter", "0.5", "--seed", "100")
    again = render("again", "--accel", "native", "--shutter", "0.5", "--seed", "200")
    assert noise_judge(blurred, reference, again)["passed"]
    assert not noise_judge(still, reference, again)["passed"]
