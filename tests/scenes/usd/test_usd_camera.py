"""Animated USD cameras: a time-sampled camera moves the sensor with the frames (its
world transform, parents' xformOps included, its field of view and clipping range at
the frame's time code), through ``apply_frame`` and the ``hlbvh render`` pipeline."""

import math

import numpy as np
import pytest

pxr = pytest.importorskip("pxr")

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402
from pxr import Gf, Usd, UsdGeom, UsdLux  # noqa: E402

from cli_helpers import run_cli  # noqa: E402
from hlbvh import scenes  # noqa: E402
from hlbvh.render import images  # noqa: E402
from hlbvh.scenes.animated import FrameSensor  # noqa: E402
from hlbvh.scenes.usd import UsdScene  # noqa: E402

#: The camera's keys at time codes 0, 1, 2: its translation, its parent rig's turn
#: about Y (degrees), its focal length (mm) and its clipping range.
TRANSLATE = [(0.0, 1.0, 6.0), (0.5, 1.2, 5.5), (1.0, 1.5, 5.0)]
RIG_TURN = [0.0, 10.0, 20.0]
FOCAL = [30.0, 35.0, 45.0]
CLIPPING = [(0.1, 100.0), (0.2, 80.0), (0.5, 50.0)]


def _quad(stage, path, corners, colour):
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr([Gf.Vec3f(*c) for c in corners])
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    mesh.CreateDisplayColorPrimvar().Set([colour])
    return mesh


def write_stage(path, moving: bool, focal_keys=FOCAL, held: int = 2):
    """A still scene (a floor, two coloured panels, a sun) in metres, Y-up, time codes
    0..2, seen by ``/Rig/Cam``: with ``moving`` its translation, its parent's turn,
    focal length and clipping range keyed at 0, 1, 2; without, all held at time code
    ``held``'s values."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetStartTimeCode(0)
    stage.SetEndTimeCode(2)
    _quad(stage, "/Floor", [(-4, 0, -4), (-4, 0, 4), (4, 0, 4), (4, 0, -4)], (0.6, 0.6, 0.6))
    _quad(stage, "/Red", [(-1.5, 0, -1), (-0.5, 0, -1), (-0.5, 1.5, -1), (-1.5, 1.5, -1)],
          (0.9, 0.1, 0.1))
    _quad(stage, "/Blue", [(0.5, 0, 0), (1.5, 0, 0), (1.5, 2, 0), (0.5, 2, 0)],
          (0.1, 0.2, 0.9))
    sun = UsdLux.DistantLight.Define(stage, "/Sun")
    sun.CreateIntensityAttr(2.0)
    sun.CreateNormalizeAttr(True)  # its intensity is the irradiance
    sun.AddRotateXOp().Set(-60.0)
    turn = UsdGeom.Xform.Define(stage, "/Rig").AddRotateYOp()
    camera = UsdGeom.Camera.Define(stage, "/Rig/Cam")
    move = camera.AddTranslateOp()
    focal, clipping = camera.CreateFocalLengthAttr(), camera.CreateClippingRangeAttr()
    for t in (0, 1, 2) if moving else (None,):
        k = held if t is None else t
        time = Usd.TimeCode.Default() if t is None else t
        turn.Set(RIG_TURN[k], time)
        move.Set(Gf.Vec3d(*TRANSLATE[k]), time)
        focal.Set(focal_keys[k], time)
        clipping.Set(Gf.Vec2f(*CLIPPING[k]), time)
    stage.GetRootLayer().Save()
    return path


@pytest.fixture(scope="module")
def stages(tmp_path_factory):
    root = tmp_path_factory.mktemp("usd_camera")
    return {"moving": write_stage(root / "moving.usda", True),
            "still": write_stage(root / "still.usda", False),
            "still_1": write_stage(root / "still_1.usda", False, held=1)}


def _loaded(path, frame: int, keep_camera: bool = True):
    """The stage loaded at 32x24, 4 spp, with frame ``frame`` applied (without its
    sensor entry unless ``keep_camera``)."""
    animation = UsdScene(path, warn=lambda line: None)
    scene = mi.load_dict(animation.scene_dict(resolution=(32, 24), spp=4,
                                              integrator={"type": "path", "max_depth": 3}))
    geometry = animation.frame(frame)
    if not keep_camera:
        geometry = {k: g for k, g in geometry.items() if not isinstance(g, FrameSensor)}
    scenes.apply_frame(scene, mi.traverse(scene), geometry)
    return animation, scene


def _camera_rays(scene):
    """The sensor's rays through a 9x7 grid of film positions: origins, directions and
    lengths as one ``(N, 7)`` array."""
    u, v = np.meshgrid(np.linspace(0, 1, 9), np.linspace(0, 1, 7))
    ray, _ = scene.sensors()[0].sample_ray(0.0, 0.5, mi.Point2f(u.ravel(), v.ravel()),
                                           mi.Point2f(0.5, 0.5))
    return np.column_stack([np.array(ray.o).T, np.array(ray.d).T, np.array(ray.maxt)])


def test01_moving_camera_frame_equals_a_still_camera_at_its_pose(stages):
    _, still = _loaded(stages["still"], 2)
    animation, moving = _loaded(stages["moving"], 2)
    assert animation.camera_moves() and animation.animated_ids() == []
    # The rays: the same pose, field of view (a film narrower than the aperture: its
    # horizontal one, the same number either way), near and far clip, bit for bit
    np.testing.assert_array_equal(_camera_rays(moving), _camera_rays(still))
    # The images: the same seed and rays give the same paths
    ours = np.array(mi.render(moving, seed=3))
    theirs = np.array(mi.render(still, seed=3))
    assert theirs.mean() > 0.02
    np.testing.assert_array_equal(ours, theirs)
    # A camera frozen at its first pose renders another image
    _, frozen = _loaded(stages["moving"], 2, keep_camera=False)
    assert np.abs(np.array(mi.render(frozen, seed=3)) - theirs).mean() > 0.02


def test02_the_camera_at_a_fractional_time_code_interpolates_its_keys(stages):
    animation = UsdScene(stages["moving"], warn=lambda line: None)
    at = animation.camera_at(1.5)
    local = np.mean(TRANSLATE[1:], axis=0)
    turn = math.radians(np.mean(RIG_TURN[1:]))
    expected = [local[0] * math.cos(turn) + local[2] * math.sin(turn), local[1],
                -local[0] * math.sin(turn) + local[2] * math.cos(turn)]
    np.testing.assert_allclose(at.to_world[:3, 3], expected, atol=1e-9)
    # It looks down the rig's turned -Z (Mitsuba's +Z), upright, unscaled
    np.testing.assert_allclose(at.to_world[:3, 2], [-math.sin(turn), 0, -math.cos(turn)],
                               atol=1e-9)
    np.testing.assert_allclose(at.to_world[:3, 1], [0, 1, 0], atol=1e-9)
    focal = np.mean(FOCAL[1:])
    gf = UsdGeom.Camera(animation.stage.GetPrimAtPath("/Rig/Cam")).GetCamera(1.5)
    assert at.fov == pytest.approx(tuple(
        2 * math.degrees(math.atan(a / 2 / focal))
        for a in (gf.horizontalAperture, gf.verticalAperture)))
    assert at.clip == pytest.approx(tuple(np.mean(CLIPPING[1:], axis=0)))
    # Frames give it at their time codes, under the sensor's id, and between frames
    # (a shutter's times) at the time code itself, not the nearer frame's
    for time in (0, 1, 2, 1.5, 0.25):
        sensor = animation.frame_at(time)["camera"]
        np.testing.assert_array_equal(sensor.to_world, animation.camera_at(time).to_world)
        assert sensor.fov == animation.camera_at(time).fov
    still = UsdScene(stages["still"], warn=lambda line: None)
    assert not still.camera_moves() and "camera" not in still.frame(1)


def test03_render_of_a_still_scene_with_a_moving_camera_writes_different_frames(
        stages, tmp_path, capsys):
    tiny = ["--resolution", "24x18", "--spp", "2", "--accel", "hlbvh", "--quiet"]
    out = tmp_path / "moving"
    status, _, err = run_cli(capsys, "render", stages["moving"], "--frames", "0:2",
                             "--out", out, *tiny)
    assert status == 0, err
    first = images.read_exr(out / "frame_0000.exr", ["R", "G", "B"])
    second = images.read_exr(out / "frame_0001.exr", ["R", "G", "B"])
    assert np.abs(first - second).mean() > 0.01
    # Frame 1 is what a still camera at time code 1's pose renders (the same seed),
    # rendered alone (a resume's case) or after frame 0
    for stage, folder in ((stages["still_1"], "still"), (stages["moving"], "alone")):
        status, _, err = run_cli(capsys, "render", stage, "--frames", "1:2",
                                 "--out", tmp_path / folder, *tiny)
        assert status == 0, err
    at_pose = images.read_exr(tmp_path / "still" / "frame_0001.exr", ["R", "G", "B"])
    assert at_pose.mean() > 0.02 and np.abs(second - at_pose).max() < 1e-3
    np.testing.assert_array_equal(
        images.read_exr(tmp_path / "alone" / "frame_0001.exr", ["R", "G", "B"]), second)


def test04_a_bad_lens_at_a_later_frame_is_named(tmp_path):
    path = write_stage(tmp_path / "bad.usda", True, focal_keys=[30.0, 35.0, 0.0])
    animation = UsdScene(path, warn=lambda line: None)
    animation.frame(1)
    with pytest.raises(ValueError, match=r"camera /Rig/Cam at time code 2: focalLength "
                                         r"is 0: expected finite and > 0"):
        animation.frame(2)


def test05_apply_frame_names_a_bad_sensor_entry(stages):
    animation = UsdScene(stages["moving"], warn=lambda line: None)
    scene = mi.load_dict(animation.scene_dict(resolution=(8, 6), spp=1))
    params = mi.traverse(scene)
    good = animation.camera_at(1)
    before = np.array(params["camera.to_world"].matrix)
    for entry, message in (
            ({"lens": good}, r"frame sensor 'lens': the scene has no sensor"),
            ({"camera": FrameSensor(good.to_world, fov=(200.0, 30.0))},
             r"frame sensor 'camera': fov is \(200, 30\): expected degrees in \(0, 180\)"),
            ({"camera": FrameSensor(good.to_world, clip=(5.0, 1.0))},
             r"frame sensor 'camera': clip is \(5, 1\): expected 0 < near < far"),
            ({"camera": FrameSensor(np.zeros((4, 4)))},
             r"frame transform for sensor 'camera': its to_world is singular")):
        with pytest.raises(ValueError, match=message):
            scenes.apply_frame(scene, params, entry)
    np.testing.assert_array_equal(np.array(params["camera.to_world"].matrix), before)
    assert scenes.apply_frame(scene, params, {"camera": good}) == []
    assert float(dr.ravel(params["camera.x_fov"])[0]) == pytest.approx(
        max(good.fov[0], 2 * math.degrees(math.atan(
            math.tan(math.radians(good.fov[1]) / 2) * 8 / 6))), rel=1e-6)
    assert (params["camera.near_clip"], params["camera.far_clip"]) == pytest.approx(good.clip)
    # A lens value the sensor has no parameter for is one line, not left out
    orthographic = mi.load_dict({"type": "scene", "camera": {"type": "orthographic"},
                                 "ball": {"type": "sphere"}})
    with pytest.raises(ValueError, match=r"frame sensor 'camera': the sensor "
                                         r"\(OrthographicCamera\) has no parameter 'x_fov'"):
        scenes.apply_frame(orthographic, None, {"camera": good})
