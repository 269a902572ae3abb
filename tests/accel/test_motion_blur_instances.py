"""Motion blur of moving instances (hlbvh.set_instance_keys): an instance turning 90
degrees inside the shutter renders as native's sub-frame accumulation converges (the
noise judge); equal keys render what the still instance renders, bit for bit; the
top-level boxes hold every point of the instance at any time of the shutter (random
rotations up to 180 degrees, scales through zero); a ray at a time meets the instance
where its pose then puts it; motion vectors; bad keys one line each; ``hlbvh render
rigid:instanced=true --shutter`` blurs its bodies."""

import drjit as dr
import hlbvh
import mitsuba as mi
import numpy as np
import pytest

from hlbvh.comparison.metrics import noise_judge
from hlbvh.kernels.build import build
from hlbvh.kernels.instances import two_level
from hlbvh.kernels.srt import KeyTable, compose, decompose, interpolate, pose_at
from hlbvh.kernels.traversal import any_hit, closest_instance_hit

T = mi.ScalarTransform4f
SHUTTER = (0.0, 1.0)


def _turn(degrees: float) -> np.ndarray:
    return np.array(T().rotate([0, 0, 1], degrees).matrix, np.float64)


def _scene(integrator, spp=16, shutter=SHUTTER, width=32, second=False):
    """A bar (an instance of a shape group holding one rectangle) before a floor;
    ``second``: another instance of it, below."""
    more = {"second": {"type": "instance", "shape": {"type": "ref", "id": "group"},
                       "to_world": T().translate([0, -0.6, 0])}} if second else {}
    return mi.load_dict({**more,
        "type": "scene", "integrator": integrator,
        "sensor": {"type": "perspective", "to_world": T().look_at([0, 0, 3], [0, 0, 0], [0, 1, 0]),
                   "shutter_open": shutter[0], "shutter_close": shutter[1],
                   "film": {"type": "hdrfilm", "width": width, "height": width,
                            "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": spp}},
        "floor": {"type": "rectangle", "to_world": T().translate([0, 0, -1]).scale(3),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.6}}},
        "group": {"type": "shapegroup", "bar": {
            "type": "rectangle", "to_world": T().scale([0.8, 0.15, 1]),
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.1}}}},
        "inst": {"type": "instance", "shape": {"type": "ref", "id": "group"}},
        "light": {"type": "constant"}})


def _instance(scene):
    return next(s for s in scene.shapes() if s.id() == "inst")


def _accumulated(seed, sub_frames=16):
    """Native's sub-frame accumulation: the bar turned to its exact angle at stratified
    times over the shutter, one sample each."""
    scene = _scene({"type": "direct"}, spp=1)
    params = mi.traverse(scene)
    total = 0
    for j in range(sub_frames):
        params["inst.to_world"] = T(_turn(90.0 * (j + 0.5) / sub_frames).astype(np.float32))
        params.update()
        total = total + np.array(mi.render(scene, seed=seed + j))
    return total / sub_frames


def test01_an_instance_turning_90_degrees_blurs_as_natives_sub_frame_accumulation():
    ours = _scene({"type": "hlbvh_direct"})
    hlbvh.set_instance_keys(_instance(ours), [_turn(0), _turn(90)], SHUTTER)
    blurred = np.array(mi.render(ours, seed=1))
    assert ours.integrator().scene_accel.instances.tree.motion is not None
    reference, again = _accumulated(100), _accumulated(500)
    assert noise_judge(blurred, reference, again)["passed"]
    # the still bar at mid-shutter (what Mitsuba renders) is another image
    still = _scene({"type": "hlbvh_direct"})
    params = mi.traverse(still)
    params["inst.to_world"] = T(_turn(45).astype(np.float32))
    params.update()
    assert not noise_judge(np.array(mi.render(still, seed=1)), reference, again)["passed"]


def test02_equal_keys_render_the_still_instance_bit_for_bit():
    pose = _turn(30) @ np.diag([1.0, 1.5, 1.0, 1.0])
    integrator = {"type": "hlbvh_path", "max_depth": 3, "moving": "inst"}
    keyed, still = _scene(integrator, spp=4), _scene(integrator, spp=4)
    hlbvh.set_instance_keys(_instance(keyed), [pose] * 3, SHUTTER)
    params = mi.traverse(still)
    params["inst.to_world"] = mi.ScalarAffineTransform4f(pose.astype(np.float32))
    params.update()
    assert np.array_equal(np.array(mi.render(keyed, seed=3)), np.array(mi.render(still, seed=3)))
    assert keyed.integrator().scene_accel.instances.tree.motion is None


def _random_keys(rng, count, segments):
    """Per instance ``segments + 1`` affine keys: turns up to 180 degrees a segment
    about random axes, stretches that pass through zero, translations."""
    out = []
    for _ in range(count):
        axis = rng.normal(size=3)
        angles = np.cumsum(rng.uniform(0, 180, segments + 1))
        keys = []
        for k, angle in enumerate(angles):
            m = np.array(T().translate(rng.normal(size=3).tolist())
                         .rotate((axis + 0.3 * rng.normal(size=3)).tolist(), float(angle))
                         .scale(rng.uniform(-1.5, 1.5, 3).tolist()).matrix, np.float64)
            if k == 1:
                m[:3, 0] = 0.0  # a key scaled to nothing along one axis
            keys.append(m)
        out.append(np.stack(keys).astype(np.float32).astype(np.float64))
    return out


def _group(corners: bool):
    """A small group, its vertices and its BVH: 20 small random triangles spread over a
    box of side 2, then (``corners``) three triangles through the corners of a box
    around them (the points that reach farthest when the group turns)."""
    rng = np.random.default_rng(7)
    centres = np.repeat(rng.uniform(-1, 1, (20, 3)), 3, axis=0)
    small = centres + rng.uniform(-0.15, 0.15, (60, 3))
    around = np.where((np.arange(9)[:, None] % 8 >> np.arange(3)) & 1, 1.2, -1.2)
    vertices = np.concatenate([small] + ([around] if corners else [])).astype(np.float32)
    faces = np.arange(len(vertices), dtype=np.uint32)
    return vertices, build(mi.Float(vertices.ravel()), mi.UInt32(faces))


def _two_level(matrices, corners=True, shutter=SHUTTER):
    """The two-level tree over instances of :func:`_group` with keys ``matrices``."""
    vertices, bvh = _group(corners)
    count = len(matrices)
    rows = np.concatenate([np.concatenate([pose_at(m, 0.5)[:3, :3].ravel(),
                                           pose_at(m, 0.5)[:3, 3]]) for m in matrices])
    motion = KeyTable.of(mi, [decompose(m) for m in matrices], shutter)
    tree, top = two_level([bvh], mi.UInt32(np.zeros(count, np.uint32)),
                          mi.Float(rows.astype(np.float32)), motion=motion)
    return vertices, tree, top, motion


def test03_top_level_boxes_hold_the_instances_at_every_time_of_the_shutter():
    """Every vertex of the group, through each instance's pose at 400 random times (the
    per-lane interpolation the traversal uses), lies in that instance's top-level box
    (the proxy triangle the top level is built over)."""
    rng = np.random.default_rng(3)
    matrices = _random_keys(rng, 24, 3)
    vertices, tree, top, motion = _two_level(matrices)
    slot = np.array(top.prim_ids)  # each slot's proxy triangle: lo, hi, lo of its box
    lo, hi = np.empty((len(matrices), 3)), np.empty((len(matrices), 3))
    lo[slot] = np.stack([np.array(top.tri_p0[i]) for i in range(3)], 1)
    hi[slot] = np.stack([np.array(top.tri_p1[i]) for i in range(3)], 1)
    samples = 400
    entry = np.repeat(np.arange(len(matrices), dtype=np.uint32), samples)
    times = rng.uniform(0, 1, entry.size).astype(np.float32)
    times[::samples] = 0.0
    times[1::samples] = 1.0
    rows = motion.rows_at(mi.UInt32(entry), mi.Float(times), mi.Bool(True))
    rows = np.stack([np.array(r) for r in rows], axis=1)  # (N, 12)
    a, b = rows[:, :9].reshape(-1, 3, 3), rows[:, 9:]
    points = np.einsum("nij,vj->nvi", a, vertices) + b[:, None, :]  # (N, V, 3)
    inside = (points >= lo[entry][:, None] - 1e-6) & (points <= hi[entry][:, None] + 1e-6)
    assert inside.all(), f"{(~inside).sum()} coordinates outside their box"
    # the interpolation turns: halfway through a 180-degree segment the reach is kept
    keys = decompose(np.stack([_turn(0), _turn(179)]))
    half = compose(interpolate(keys[0], keys[1], 0.5))
    np.testing.assert_allclose(half, _turn(89.5), atol=1e-9)


def test04_a_ray_at_its_time_meets_the_instance_where_its_pose_puts_it():
    """Rays aimed at a triangle's centre through an instance's pose at each ray's time
    hit it there at the expected distance; at a time where the instance is scaled to
    nothing, rays miss it (no failure)."""
    rng = np.random.default_rng(5)
    matrices = _random_keys(rng, 6, 2)
    vertices, tree, top, motion = _two_level(matrices, corners=False)
    n = 3000
    entry = rng.integers(0, len(matrices), n)
    times = rng.uniform(0, 1, n)
    face = rng.integers(0, 20, n)
    centre = vertices.reshape(-1, 3, 3)[face].mean(axis=1)
    poses = np.stack([pose_at(matrices[e], t) for e, t in zip(entry, times)])
    target = np.einsum("nij,nj->ni", poses[:, :3, :3], centre) + poses[:, :3, 3]
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    origin = target - 20 * direction
    o, d = mi.Point3f(*origin.T.astype(np.float32)), mi.Vector3f(*direction.T.astype(np.float32))
    t, _, _, _, inst, valid = closest_instance_hit(tree, o, d, 1e4, time=mi.Float(times))
    t, valid = np.array(t), np.array(valid)
    scaled = np.abs(np.linalg.det(poses[:, :3, :3])) > 1e-3  # not (nearly) flat then
    assert valid[scaled].all() and np.all(t[scaled] <= 20 * (1 + 1e-4))
    assert np.mean(np.abs(t[scaled] - 20) < 1e-3) > 0.9  # mostly the aimed triangle itself
    # at the key scaled to nothing (time 0.5: key 1 of 2 segments), nothing is hit
    flat = closest_instance_hit(tree, o, d, 1e4, time=mi.Float(np.full(n, 0.5)))[-1]
    assert not np.array(flat).any()
    assert not np.array(any_hit(tree, o, d, 1e4, time=mi.Float(np.full(n, 0.5)))).any()
    with pytest.raises(ValueError, match="pass time="):
        closest_instance_hit(tree, o, d, 1e4)


def test05_motion_vectors_give_a_translating_instance_its_speed_in_pixels():
    """``hlbvh_aov``'s motion channel: the bar moves 0.8 units to the right over a
    shutter of 2, seen from 3 units away: the pixels it covers move by the projected
    distance per unit of ray.time (1% at most off), the floor by none."""
    scene = _scene({"type": "hlbvh_aov"}, spp=1, shutter=(0.0, 2.0), width=48)
    hlbvh.set_instance_keys(_instance(scene),
                            [np.eye(4), np.array(T().translate([0.8, 0, 0]).matrix)], (0.0, 2.0))
    image = np.array(mi.render(scene))
    motion_x, motion_y = image[..., 12], image[..., 13]
    # 0.8 units at the bar's depth on the film (the sensor's own projection), over 2
    sensor = scene.sensors()[0]
    ends = []
    for x in (0.0, 0.8):
        it = dr.zeros(mi.Interaction3f, 1)
        it.p = mi.Point3f(x, 0, 0)
        ends.append(float(sensor.sample_direction(it, mi.Point2f(0.5))[0].uv.x[0]))
    expected = (ends[1] - ends[0]) / 2.0
    moving = motion_x != 0
    assert moving.sum() > 20
    np.testing.assert_allclose(motion_x[moving], expected, rtol=0.01)
    np.testing.assert_allclose(motion_y[moving], 0.0, atol=1e-3)
    assert moving[0, 0] == 0 and moving.mean() < 0.3  # the floor stands still


def test06_bad_keys_are_one_line_each():
    scene = _scene({"type": "hlbvh_direct"}, spp=1)
    instance = _instance(scene)
    cases = [(([np.eye(4)] * 2, (1.0, 1.0)), "instance 'inst': shutter (1.0, 1.0): expected "
                                               "finite open < close"),
             (([np.eye(4)] * 2, (0.0, np.nan)), "instance 'inst': shutter"),
             (([np.eye(4)], SHUTTER), "instance 'inst': 1 transform(s): expected at least two"),
             (([np.eye(4), np.full((4, 4), np.nan)], SHUTTER),
              "instance 'inst': key 1 is not a finite 4x4 transform"),
             (([np.eye(4), np.eye(3)], SHUTTER), "instance 'inst': key 1 is not a finite 4x4"),
             (([np.eye(4), np.ones((4, 4))], SHUTTER), "instance 'inst': key 1 is not affine")]
    for (keys, shutter), message in cases:
        with pytest.raises(ValueError) as error:
            hlbvh.set_instance_keys(instance, keys, shutter)
        assert message in str(error.value) and "\n" not in str(error.value)
    floor = next(s for s in scene.shapes() if s.id() == "floor")
    with pytest.raises(ValueError, match="shape 'floor' .* is not an instance"):
        hlbvh.set_instance_keys(floor, [np.eye(4)] * 2, SHUTTER)
    # two instances keyed over different shutters: the accelerator names them, one line
    scene = _scene({"type": "hlbvh_direct"}, spp=1, second=True)
    hlbvh.set_instance_keys(_instance(scene), [_turn(0), _turn(90)], SHUTTER)
    second = next(s for s in scene.shapes() if s.id() == "second")
    hlbvh.set_instance_keys(second, [_turn(0), _turn(90)], (0.0, 2.0))
    with pytest.raises(ValueError, match=r"^instances '\w+' and '\w+' have keys over "
                       r"different shutters \(\(0.0, [12].0\) and \(0.0, [12].0\)\): give "
                       "every instance keys over the same shutter$"):
        hlbvh.SceneAccel(scene)


def test07_keys_end_when_to_world_is_written_without_them():
    scene = _scene({"type": "hlbvh_direct"}, spp=1)
    instance = _instance(scene)
    hlbvh.set_instance_keys(instance, [_turn(0), _turn(60)], SHUTTER)
    from hlbvh.accel.keys import instance_keys
    written = np.array(mi.traverse(instance)["to_world"].matrix, np.float64).reshape(4, 4)
    np.testing.assert_allclose(written, _turn(30), atol=1e-6)  # the mid-shutter pose
    assert instance_keys(instance) is not None
    params = mi.traverse(scene)
    params["inst.to_world"] = T(_turn(10).astype(np.float32))
    params.update()
    assert instance_keys(instance) is None


def test08_the_render_command_blurs_rigid_instanced_bodies(tmp_path, capsys):
    """``hlbvh render rigid:instanced=true --shutter 0.5``: its bodies are given keys
    (their exact poses at the shutter's keys), and the frame differs from the still
    one's; ``frame_at`` interpolates an instance between frames as the keys do."""
    from cli_helpers import run_cli
    from hlbvh import scenes

    small = ["--triangles", "3000", "--frames", "1:2", "--resolution", "32x18", "--spp", "4",
             "--quiet"]
    for name, flags in (("blur", ["--shutter", "0.5"]), ("still", [])):
        status, _, err = run_cli(capsys, "render", "rigid:instanced=true", *small, *flags,
                                 "--out", tmp_path / name)
        assert status == 0, err
    blurred = mi.Bitmap(str(tmp_path / "blur" / "frame_0001.exr"))
    still = mi.Bitmap(str(tmp_path / "still" / "frame_0001.exr"))
    assert not np.array_equal(np.array(blurred), np.array(still))
    # in process: every body traced at its pose at each ray's time
    from hlbvh.render.frame import FrameRenderer
    from hlbvh.render.settings import RenderSettings

    rigid = scenes.get("rigid", instanced=True, triangles=3000, frames=3)
    renderer = FrameRenderer(rigid, RenderSettings(resolution=(32, 18), spp=4,
                                                   shutter=(-0.25, 0.25)))
    renderer.render(1)
    motion = renderer.integrator.scene_accel.instances.tree.motion
    assert motion is not None and np.all(np.array(motion.segments) == 1)
    assert dr.width(motion.segments) == rigid.objects
    # the default frame_at: an instance's pose between frames by the keys' interpolation
    body = rigid.animated_ids()[0]
    a, b = rigid.frame(1)[body].to_world, rigid.frame(2)[body].to_world
    between = scenes.AnimatedScene.frame_at(rigid, 1.25)[body].to_world
    np.testing.assert_allclose(between, pose_at([a, b], 0.25), atol=1e-6)
    exact = rigid.frame_at(1.25)[body].to_world
    np.testing.assert_allclose(exact, rigid.transforms(1.25 / 24)[0], atol=1e-6)
    assert np.abs(between - exact).max() < 0.05  # (the exact path bends a little)


def test09_a_hit_is_shaded_where_the_instance_is_at_the_ray_time():
    """The bar tilts 80 degrees about x over the shutter; rays at random times aimed at
    points of it where its pose then puts them: the interaction's position is that
    point and its normal the bar's normal turned as far (not the mid-shutter pose's)."""
    scene = _scene({"type": "hlbvh_direct"}, spp=1)
    tilt = [np.array(T().rotate([1, 0, 0], a).matrix, np.float64) for a in (0.0, 80.0)]
    hlbvh.set_instance_keys(_instance(scene), tilt, SHUTTER)
    accel = hlbvh.SceneAccel(scene)
    rng = np.random.default_rng(2)
    n = 500
    times = rng.uniform(0, 1, n)
    x, y, angle = rng.uniform(-0.7, 0.7, n), rng.uniform(-0.12, 0.12, n), np.radians(80 * times)
    target = np.stack([x, y * np.cos(angle), y * np.sin(angle)], 1)  # R_x(angle) (x, y, 0)
    normal = np.stack([np.zeros(n), -np.sin(angle), np.cos(angle)], 1)  # R_x(angle) z
    ray = mi.Ray3f(mi.Point3f(*(target + 3 * normal).T.astype(np.float32)),
                   mi.Vector3f(*(-normal).T.astype(np.float32)))
    ray.time = mi.Float(times.astype(np.float32))
    si = accel.ray_intersect(ray)
    assert np.array(si.is_valid()).all()
    p = np.stack([np.array(c) for c in si.p], 1)
    np.testing.assert_allclose(p, target, atol=2e-4)
    n_hit = np.stack([np.array(c) for c in si.n], 1)
    np.testing.assert_allclose(np.abs(np.sum(n_hit * normal, 1)), 1.0, atol=1e-4)
