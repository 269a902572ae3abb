"""Motion blur of deforming meshes through our keyed BVH (hlbvh.set_motion_keys): a
mesh given its positions at the shutter's keys renders as native's sub-frame
accumulation converges (judged by block means against two native accumulations'
noise); equal keys render what the still mesh renders, bit for bit; bad keys and a
structure that has no time are one line each."""

import hlbvh
import mitsuba as mi
import numpy as np
import pytest

T = mi.ScalarTransform4f
QUAD = np.array([[-0.3, -0.3, 0], [0.3, -0.3, 0], [0.3, 0.3, 0], [-0.3, 0.3, 0]], np.float32)
FACES = np.array([[0, 1, 2], [0, 2, 3]], np.uint32)
SHIFT = np.array([0.8, 0.0, 0.0], np.float32)  # the quad's motion over the shutter


def _mesh(v):
    mesh = mi.Mesh("mover", 4, 2)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(v.ravel())
    params["faces"] = mi.UInt32(FACES.ravel())
    params.update()
    return mesh


def _scene(integrator, v=QUAD, shutter=(0.0, 0.0), spp=64):
    return mi.load_dict({
        "type": "scene", "integrator": integrator,
        "sensor": {"type": "perspective", "to_world": T().look_at([0, 0, 3], [0, 0, 0], [0, 1, 0]),
                   "shutter_open": shutter[0], "shutter_close": shutter[1],
                   "film": {"type": "hdrfilm", "width": 48, "height": 32,
                            "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": spp}},
        "floor": {"type": "rectangle", "to_world": T().translate([0, 0, -1]).scale(3),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.2}}},
        "mover": _mesh(v), "light": {"type": "constant"}})


def _mover(scene):
    return next(s for s in scene.shapes() if s.id() == "mover")


def _blocks(image):
    """Means of 4x4-pixel blocks of the first channel."""
    return image[:, :, 0].reshape(8, 4, 12, 4).mean(axis=(1, 3))


def _accumulated(seed, sub_frames=16):
    """Native's sub-frame accumulation: the quad at stratified times, 4 spp each."""
    reference = _scene({"type": "path", "max_depth": 3})
    params = mi.traverse(reference)
    total = 0
    for j in range(sub_frames):
        params["mover.vertex_positions"] = mi.Float((QUAD + SHIFT * ((j + 0.5) / sub_frames)).ravel())
        params.update()
        total = total + np.array(mi.render(reference, seed=seed + j, spp=4))
    return total / sub_frames


def test01_a_deforming_mesh_blurs_as_natives_sub_frame_accumulation():
    ours = _scene({"type": "hlbvh_path", "max_depth": 3}, shutter=(0.0, 1.0))
    hlbvh.set_motion_keys(_mover(ours), [mi.Float(QUAD.ravel()), mi.Float((QUAD + SHIFT).ravel())],
                          (0.0, 1.0))
    blurred = _blocks(np.array(mi.render(ours, seed=1)))
    assert ours.integrator().scene_accel.moving_structure == "hlbvh"
    reference, other = _blocks(_accumulated(100)), _blocks(_accumulated(500))
    noise = np.std(reference - other)  # two native accumulations: the noise of one pair
    assert np.abs(blurred - reference).max() < 5 * noise
    # the still quad at mid-shutter (what Mitsuba renders) is far from it
    still = _blocks(np.array(mi.render(_scene({"type": "hlbvh_path", "max_depth": 3},
                                              QUAD + SHIFT / 2), seed=1)))
    assert np.abs(still - reference).max() > 20 * noise


def test02_equal_keys_render_the_still_mesh_bit_for_bit():
    ours = _scene({"type": "hlbvh_path", "max_depth": 3}, shutter=(0.0, 1.0), spp=4)
    hlbvh.set_motion_keys(_mover(ours), [mi.Float(QUAD.ravel())] * 3, (0.0, 1.0))
    still = _scene({"type": "hlbvh_path", "max_depth": 3, "moving": "mover",
                    "moving_accel": "hlbvh"}, shutter=(0.0, 1.0), spp=4)
    keyed = np.array(mi.render(ours, seed=3))
    assert ours.integrator().scene_accel.dynamic.keyed is not None
    np.testing.assert_array_equal(keyed, np.array(mi.render(still, seed=3)))


def test03_keys_end_with_the_next_write_of_the_mesh():
    """Keys belong to the positions written with them: a later write without keys
    renders the mesh still (no blur left over from an earlier frame)."""
    ours = _scene({"type": "hlbvh_path", "max_depth": 3}, shutter=(0.0, 1.0), spp=4)
    hlbvh.set_motion_keys(_mover(ours), [mi.Float(QUAD.ravel()), mi.Float((QUAD + SHIFT).ravel())],
                          (0.0, 1.0))
    mi.render(ours, seed=1)
    params = hlbvh.traverse(ours)
    params["mover.vertex_positions"] = mi.Float(QUAD.ravel())
    params.update()
    mi.render(ours, seed=1)
    assert ours.integrator().scene_accel.dynamic.keyed is None


@pytest.mark.parametrize("keys, shutter, message", [
    ([QUAD, QUAD + SHIFT], (1.0, 0.0), r"shutter \(1.0, 0.0\): expected finite open < close"),
    ([QUAD, np.full_like(QUAD, np.nan)], (0.0, 1.0), r"keys\[1\]: .*non-finite"),
    ([QUAD, QUAD[:3]], (0.0, 1.0), r"keys\[1\]"),
    ([QUAD], (0.0, 1.0), r"mesh 'mover'"),
])
def test04_bad_keys_are_one_line_naming_the_mesh(keys, shutter, message):
    scene = _scene({"type": "hlbvh_path"})
    with pytest.raises(ValueError, match=message):
        hlbvh.set_motion_keys(_mover(scene), [mi.Float(k.ravel()) for k in keys], shutter)


@pytest.mark.parametrize("forced", ["scene", "native"])
def test05_a_structure_without_time_is_refused_for_keyed_meshes(forced):
    scene = _scene({"type": "hlbvh_path", "moving_accel": forced, "moving": "mover"},
                   shutter=(0.0, 1.0), spp=1)
    mi.render(scene)
    hlbvh.set_motion_keys(_mover(scene), [mi.Float(QUAD.ravel()), mi.Float((QUAD + SHIFT).ravel())],
                          (0.0, 1.0))
    with pytest.raises(ValueError, match=f"moving_accel='{forced}': a moving mesh has motion keys"):
        scene.integrator().update_accel(scene)


def test06_motion_vectors_give_a_translating_quad_its_speed_in_pixels():
    """``hlbvh_aov``'s motion channel: the quad moves 0.8 units to the right over the
    shutter, seen from 3 units away: the pixels it covers move by the projected
    distance per unit of ray.time (1% at most off), the floor by none."""
    scene = _scene({"type": "hlbvh_aov"}, shutter=(0.0, 2.0), spp=1)
    hlbvh.set_motion_keys(_mover(scene), [mi.Float(QUAD.ravel()), mi.Float((QUAD + SHIFT).ravel())],
                          (0.0, 2.0))
    image = np.array(mi.render(scene))
    shape, motion_x, motion_y = image[..., 4], image[..., 12], image[..., 13]
    # the perspective camera's focal length in pixels: width / (2 tan(fov/2)), fov 39.3
    focal = 48 / (2 * np.tan(np.radians(39.3077) / 2))
    expected = 0.8 * focal / 3 / 2.0  # 0.8 over 3 units away, over a shutter of 2
    on_quad = shape == 0
    assert on_quad.sum() > 20
    np.testing.assert_allclose(motion_x[on_quad], expected, rtol=0.01)
    np.testing.assert_allclose(motion_y[on_quad], 0.0, atol=1e-3)
    assert np.all(motion_x[shape == 1] == 0.0)


def test07_an_animation_gives_its_meshes_between_frames():
    """``frame_at``: a procedural mesh halfway between two frames is their mean (the
    default's linear interpolation), a whole frame is that frame, and times outside
    the animation are its first or last frame."""
    from hlbvh import scenes

    animation = scenes.get("cloth", triangles=2000, frames=4)
    (key,) = animation.animated_ids()
    at = {t: np.asarray(animation.frame_at(t)[key].positions) for t in (1.5, 2.0, -1.0, 9.0)}
    one, two = (np.asarray(animation.frame(i)[key].positions) for i in (1, 2))
    np.testing.assert_allclose(at[1.5], 0.5 * (one + two), rtol=0, atol=1e-6)
    assert not np.allclose(at[1.5], one)
    np.testing.assert_array_equal(at[2.0], two)
    np.testing.assert_array_equal(at[-1.0], np.asarray(animation.frame(0)[key].positions))
    np.testing.assert_array_equal(at[9.0], np.asarray(animation.frame(3)[key].positions))


def _looking(x):
    return T().look_at([x, 0, 3], [x, 0, 0], [0, 1, 0])


def test08_a_moving_camera_blurs_as_natives_sub_frame_accumulation():
    """A camera sliding 0.5 sideways over the shutter (hlbvh.set_camera_keys), the
    scene still: the blurred image equals native's accumulation of 16 sub-frames from
    the camera's stratified poses within block-mean noise; the still camera does not."""
    ours = _scene({"type": "hlbvh_path", "max_depth": 3}, shutter=(0.0, 1.0))
    sensor = ours.sensors()[0]
    params = mi.traverse(ours)  # the sensor's own pose: the mid-shutter one
    params["sensor.to_world"] = _looking(0.25)
    params.update()
    hlbvh.set_camera_keys(sensor, [_looking(0.0), _looking(0.5)], (0.0, 1.0))
    blurred = _blocks(np.array(mi.render(ours, seed=1)))

    def accumulated(seed, sub_frames=16):
        reference = _scene({"type": "path", "max_depth": 3})
        ref_params = mi.traverse(reference)
        total = 0
        for j in range(sub_frames):
            ref_params["sensor.to_world"] = _looking(0.5 * (j + 0.5) / sub_frames)
            ref_params.update()
            total = total + np.array(mi.render(reference, seed=seed + j, spp=4))
        return _blocks(total / sub_frames)

    reference, other = accumulated(100), accumulated(500)
    noise = np.std(reference - other)
    assert np.abs(blurred - reference).max() < 5 * noise
    hlbvh.clear_camera_keys(sensor)
    still = _blocks(np.array(mi.render(ours, seed=1)))
    assert np.abs(still - reference).max() > 10 * noise


@pytest.mark.parametrize("poses, shutter, message", [
    ([_looking(0.0), _looking(0.5)], (0.5, 0.5), r"sensor 'sensor': shutter \(0.5, 0.5\)"),
    ([_looking(0.0)], (0.0, 1.0), "at least two keys"),
    ([_looking(0.0), _looking(0.5).scale(2.0)], (0.0, 1.0), "camera key 1 is not rigid"),
    ([_looking(0.0), np.full((4, 4), np.nan)], (0.0, 1.0), "camera key 1 is not a finite"),
])
def test09_bad_camera_keys_are_one_line_naming_the_sensor(poses, shutter, message):
    scene = _scene({"type": "hlbvh_path"})
    with pytest.raises(ValueError, match=message):
        hlbvh.set_camera_keys(scene.sensors()[0], poses, shutter)


def test10_an_animation_renders_blurred_frames_with_an_open_shutter():
    """The frame pipeline with ``shutter=(-0.5, 0.5)``: our frame traces the moving
    meshes' keys (our HLBVH, said in the row), native's is the mean of its sub-frames;
    the two agree within the noise two native accumulations show, and the blurred frame
    is not the still one. A closed shutter records no shutter setting (old folders
    resume)."""
    from hlbvh import scenes
    from hlbvh.comparison.metrics import noise_judge
    from hlbvh.render.frame import FrameRenderer
    from hlbvh.render.settings import RenderSettings

    animation = scenes.get("world", triangles=20_000, frames=6)

    def frame(accel, shutter, seed=0):
        settings = RenderSettings(resolution=(64, 36), spp=16, accel=accel, shutter=shutter,
                                  sub_frames=8, seed=seed)
        image, row = FrameRenderer(animation, settings).render(3)
        return np.array(image), row, settings

    blurred, row, settings = frame("hlbvh", (-0.5, 0.5))
    assert row["moving_accel"] == "hlbvh" and settings.as_dict()["shutter"] == [-0.5, 0.5]
    still = frame("hlbvh", (0.0, 0.0))[0]
    assert not np.array_equal(blurred, still)
    reference, again = frame("native", (-0.5, 0.5), 100)[0], frame("native", (-0.5, 0.5), 200)[0]
    assert noise_judge(blurred, reference, again)["passed"]
    assert "shutter" not in RenderSettings().as_dict()
    with pytest.raises(ValueError, match=r"shutter=\(0.5, -0.5\): expected finite open <= close"):
        RenderSettings(shutter=(0.5, -0.5))


def test11_the_command_line_takes_a_shutter(tmp_path, capsys):
    """``--shutter 0.5`` (centred) and ``--shutter=OPEN:CLOSE``: render says the shutter
    and what traced the moving meshes, records it; compare judges the blurred frames
    against native's sub-frames; a bad value, or keys without a shutter, one line."""
    import json

    from cli_helpers import run_cli

    small = ["--triangles", "3000", "--frames", "0:2", "--resolution", "32x18", "--spp", "8",
             "--quiet"]
    status, out, err = run_cli(capsys, "render", "cloth", *small, "--shutter", "0.5",
                               "--motion-keys", "2", "--out", tmp_path / "r")
    assert status == 0, err
    assert "shutter -0.25..0.25 of a frame (moving meshes traced by our BVH" in out
    settings = json.loads((tmp_path / "r" / "stats.json").read_text())["settings"]
    assert settings["shutter"] == [-0.25, 0.25] and settings["motion_keys"] == 2
    status, out, err = run_cli(capsys, "compare", "cloth", *small, "--shutter=-0.5:0",
                               "--sub-frames", "4", "--out", tmp_path / "c")
    assert status == 0, err
    assert "Motion blur over -0.5..0 of a frame" in out and "mean of 4 sub-frames" in out
    assert "within Monte Carlo noise of native's on every frame" in out
    for flags, message in ((["--shutter", "x"], "--shutter 'x': expected a length"),
                           (["--shutter=1:0"], "--shutter '1:0'"),
                           (["--motion-keys", "2"], "--motion-keys 2: it sets the keys of an "
                                                    "open shutter"),
                           (["--shutter", "1", "--motion-keys", "0"], "--motion-keys")):
        status, _, err = run_cli(capsys, "render", "cloth", *flags, "--out", tmp_path / "x")
        assert status == 2 and len(err) == 1 and message in err[0], err


def test12_what_blur_does_not_support_is_one_line():
    """An emitting mesh cannot take keys (emitter sampling would see it still), and
    hlbvh_prb refuses derivatives through a blurred mesh; its primal render works."""
    import drjit as dr

    panel = mi.load_dict({"type": "scene", "panel": {
        "type": "rectangle", "emitter": {"type": "area"}}}).shapes()[0]
    with pytest.raises(ValueError, match="mesh 'panel' emits light"):
        hlbvh.set_motion_keys(panel, [panel.vertex_positions_buffer()] * 2, (0.0, 1.0))
    scene = _scene({"type": "hlbvh_prb", "max_depth": 3}, shutter=(0.0, 1.0), spp=2)
    hlbvh.set_motion_keys(_mover(scene), [mi.Float(QUAD.ravel()), mi.Float((QUAD + SHIFT).ravel())],
                          (0.0, 1.0))
    assert np.array(mi.render(scene, seed=1)).mean() > 0
    params = mi.traverse(scene)
    dr.enable_grad(params["floor.bsdf.reflectance.value"])
    params.update()
    image = mi.render(scene, params, seed=1)
    with pytest.raises(ValueError, match="hlbvh_prb: a moving mesh has motion keys"):
        dr.backward(dr.sum(image, axis=None))
