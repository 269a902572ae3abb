"""What traces the moving meshes, chosen per render by measured cost
(hlbvh.accel.choice): our HLBVH, a Mitsuba sub-scene of the moving meshes, or the whole
scene through Mitsuba's accelerator. With injected costs each is chosen where the costs
say, and the choice follows the render's film and samples; a forced choice is honoured;
hits through the native moving group are Mitsuba's, field for field; images under every
choice equal native's within today's tolerances."""

from dataclasses import replace

import drjit as dr
import hlbvh
import mitsuba as mi
import numpy as np
import pytest

from hlbvh import scenes
from hlbvh.accel import moving
from hlbvh.accel.choice import CostModel, RayBudget, queries_per_sample
from hlbvh.accel.moving import native_moving_possible
from hlbvh.accel.preparation import PROBE_RUN, query_ns, render_sample, time_structures
from hlbvh.scenes.animated import apply_frame

#: The native moving group needs a second Mitsuba scene in a kernel (not on OptiX).
needs_native_moving = pytest.mark.skipif(not native_moving_possible(),
                                         reason="OptiX traces one scene per kernel")

T = mi.ScalarTransform4f


def _costs(update, query, hits=(1.0, 0.0)) -> CostModel:
    model = CostModel()
    model.update_ms.update(update)
    model.query_ns.update(query)
    model.hit_fractions = hits
    return model


UPDATE = {"hlbvh": 5.0, "native": 40.0, "scene": 400.0}
QUERY = {"hlbvh": 200.0, "native": 100.0, "still": 90.0}


def test01_queries_per_sample_follow_hits_and_depth():
    assert queries_per_sample(0.0, 0.5, 8) == 1.0  # every camera ray escapes
    assert queries_per_sample(1.0, 0.0, 8) == 3.0  # one surface: a shadow ray, a bounce
    assert queries_per_sample(1.0, 1.0, 4) == 9.0  # closed room: every bounce lands
    assert queries_per_sample(0.5, 0.5, 1) == 2.0
    assert queries_per_sample(1.0, 0.5, -1) == pytest.approx(5.0)  # unbounded


@pytest.mark.parametrize("samples, expected", [
    (10_000, "hlbvh"),         # a preview: our cheap update wins
    (10_000_000, "native"),    # a final frame: Mitsuba's faster rays win
])
def test02_injected_costs_choose_where_they_say(samples, expected):
    chosen, estimates = _costs(UPDATE, QUERY).choose(RayBudget(samples, 8), "hlbvh")
    assert chosen == expected
    assert min(estimates, key=estimates.get) == expected
    # the whole scene before its rays were timed: counted at the still world's rate
    assert estimates["scene"] == pytest.approx(400.0 + samples * 3 * 90e-6)


def test03_the_whole_scene_wins_where_its_rebuild_pays():
    model = _costs(UPDATE, {**QUERY, "scene": 50.0})
    assert model.choose(RayBudget(100_000_000, 8), "native")[0] == "scene"
    assert model.choose(RayBudget(100_000, 8), "native")[0] == "hlbvh"


def test04_a_near_tie_keeps_the_current_structure():
    model = _costs({"hlbvh": 10.0, "native": 10.0}, {"hlbvh": 100.0, "native": 98.0})
    budget = RayBudget(10_000, 8)
    assert model.choose(budget, "hlbvh", ("hlbvh", "native"))[0] == "hlbvh"
    assert model.choose(budget, "native", ("hlbvh", "native"))[0] == "native"


def test05_unmeasured_mitsuba_updates_are_estimated_from_the_measured_build_rate():
    model = _costs({"hlbvh": 1.0}, QUERY)
    model.record_build_rate(ms=50.0, triangles=100_000)
    estimates = model.choose(RayBudget(1, 1), "hlbvh", triangles={"native": 20_000,
                                                                    "scene": 1_000_000})[1]
    assert estimates["native"] == pytest.approx(10.0 + 3 * 100e-6)
    assert estimates["scene"] == pytest.approx(500.0 + 3 * 90e-6)


def test05b_renders_correct_what_the_probe_guessed():
    """A structure's first render compiles its kernel and is not counted; then its own
    renders decide: at a number of samples where another structure's estimate comes
    near the best measured frame, that one is tried once, and the better kept."""
    model = _costs({"hlbvh": 4.0, "native": 40.0, "scene": 400.0}, QUERY, hits=(0.6, 0.1))
    budget = RayBudget(500_000, 8)
    model.record_render("hlbvh", 900.0, budget.samples)  # compiling: not counted
    assert model.renders == {}
    model.record_render("hlbvh", 120.0, budget.samples)
    assert model.renders == {"hlbvh": {500_000: 120.0}}
    # the probe says native's rays cost half: it is tried at this budget
    assert model.choose(budget, "hlbvh")[0] == "native"
    model.record_render("native", 500.0, budget.samples)  # its first render compiles
    assert model.choose(budget, "native")[0] == "native"  # still to be measured here
    model.record_render("native", 100.0, budget.samples)
    chosen, estimates = model.choose(budget, "native")
    assert chosen == "hlbvh" and estimates == {"hlbvh": 124.0, "native": 140.0,
                                               "scene": pytest.approx(estimates["scene"])}
    # four times the samples: measured per sample, the line through its renders
    model.record_render("hlbvh", 40.0, 125_000)
    assert model.render_ms("hlbvh", RayBudget(2_000_000, 8)) == pytest.approx(440.0)
    # native, measured at one count only, takes the fixed cost hlbvh's line showed
    assert model.render_ms("native", RayBudget(2_000_000, 8)) == pytest.approx(
        13.333333 + (100.0 - 13.333333) * 4)


def test05c_the_probe_traces_runs_of_neighbouring_pixels_as_a_render_does():
    """The probe's camera rays come in runs of neighbouring pixels (a render's lanes
    trace neighbouring pixels; rays through random pixels made our traversal look two
    to four times dearer than in the renders): neighbouring rays of a run are about a
    pixel apart. The timing's half keeps whole runs."""
    animation, scene = _world()
    accel = hlbvh.SceneAccel(scene, moving=["flag"])
    sensor = scene.sensors()[0]
    n = 4 * PROBE_RUN
    rays = render_sample(accel, sensor, n=n).rays
    d = np.array(rays.d).T[:n]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    width = int(sensor.film().size()[0])
    fov = np.radians(float(mi.traverse(sensor)["x_fov"][0]))
    runs = d.reshape(-1, PROBE_RUN, 3)
    angles = np.arccos(np.clip((runs[:, 1:] * runs[:, :-1]).sum(-1), -1, 1))
    assert np.median(angles) < 2.5 * fov / width  # random pixels: ~fov/3 apart
    seen = []
    query_ns(lambda r: seen.append(np.array(r.d).T) or accel.ray_intersect_preliminary(r),
                    rays, run=PROBE_RUN)
    halves = [x for x in seen if len(x) == n]  # 2n rays in all: the half is n
    assert halves and np.array_equal(halves[0][:PROBE_RUN], np.array(rays.d).T[:PROBE_RUN])
    assert np.array_equal(halves[0][PROBE_RUN:2 * PROBE_RUN],
                          np.array(rays.d).T[2 * PROBE_RUN:3 * PROBE_RUN])


# ---------------------------------------------------------------------------------------
# Through the accelerator and the integrator
# ---------------------------------------------------------------------------------------


def _world(moving_accel="auto", integrator="hlbvh_path"):
    animation = scenes.get("world", triangles=20_000, frames=8)
    scene = mi.load_dict(animation.scene_dict(
        resolution=(48, 27), spp=2,
        integrator={"type": integrator, "max_depth": 4, "moving": "flag",
                    "moving_accel": moving_accel}))
    return animation, scene


def _world_and_native():
    """``_world()`` through :func:`hlbvh.traverse` and the same scene rendered natively,
    both at frame 1: (animation, scene, params, reference, reference's params)."""
    animation, scene = _world()
    params = hlbvh.traverse(scene)
    reference = mi.load_dict(animation.scene_dict(
        resolution=(48, 27), spp=2, integrator={"type": "hlbvh_path", "max_depth": 4,
                                                 "accel": "native"}))
    ref_params = mi.traverse(reference)
    apply_frame(scene, params, animation.frame(1))
    apply_frame(reference, ref_params, animation.frame(1))
    return animation, scene, params, reference, ref_params


def _inject(accel):
    """The test's costs in place of measured ones (no probe, updates not recorded)."""
    accel.moving_meshes.costs = _costs(UPDATE, QUERY)
    accel.moving_meshes.costs.record_update = lambda structure, ms: None
    accel.moving_meshes.probed = True


def test06_the_choice_follows_the_film_and_samples_of_each_render():
    animation, scene = _world()
    params = hlbvh.traverse(scene)
    integrator = scene.integrator()
    apply_frame(scene, params, animation.frame(1))
    accel = integrator.update_accel(scene, spp=1)
    _inject(accel)
    chosen = []
    for spp in (1, 8192, 1):
        apply_frame(scene, params, animation.frame(2 + len(chosen)))
        accel = integrator.update_accel(scene, spp=spp)
        chosen.append(accel.moving_structure)
        assert accel.last_update["moving_accel"]["chosen"] == chosen[-1]
        assert set(accel.last_update["moving_accel"]["estimates_ms"]) == (
            {"hlbvh", "native", "scene"} if native_moving_possible() else {"hlbvh", "scene"})
    assert chosen == ["hlbvh", "native" if native_moving_possible() else "scene", "hlbvh"]
    # the native group was rebuilt for its frame, our BVH caught up after it
    assert accel.last_update["groups"]["dynamic"]["decision"] == "rebuild"


def test06a_our_tree_is_given_back_while_another_structure_traces_moved_meshes():
    """Once the moving meshes moved while the native group or the whole scene traced
    them, our tree is out of date: it is dropped (its memory given back), and a switch
    back builds it anew; the images on both sides of the switch equal native's."""
    animation, scene, params, reference, ref_params = _world_and_native()
    integrator = scene.integrator()
    accel = integrator.update_accel(scene, spp=1)
    _inject(accel)
    held = []
    for frame, spp in ((2, 1), (3, 8192), (4, 8192), (5, 1)):
        apply_frame(scene, params, animation.frame(frame))
        apply_frame(reference, ref_params, animation.frame(frame))
        accel = integrator.update_accel(scene, spp=spp)
        held.append((accel.moving_structure, accel.dynamic.bvh is not None))
        with integrator.updated():
            ours = np.array(mi.render(scene, seed=frame, spp=2))
        expected = np.array(mi.render(reference, seed=frame))
        if accel.moving_structure == "hlbvh":  # today's tolerance: one edge-tie pixel
            diff = np.abs(ours - expected)
            assert (diff > 5e-4 + 1e-4 * np.abs(expected)).any(axis=-1).sum() <= 1
        else:  # Mitsuba's own queries: bit for bit
            np.testing.assert_array_equal(ours, expected)
    other = "native" if native_moving_possible() else "scene"
    assert held == [("hlbvh", True), (other, False), (other, False), ("hlbvh", True)]
    assert accel.last_update["groups"]["dynamic"]["decision"] == "rebuild"


@pytest.mark.parametrize("update", ["auto", "refit", "rebuild"])
def test06b_our_update_cost_is_a_frames_refit_not_the_first_build(update):
    """The probe takes our HLBVH's update cost from a frame's refit of the tree just
    built (what an ``"auto"`` or ``"refit"`` frame pays), not from the first build, which
    compiles: the tree, the group's record and what the policy remembers are left as
    they were; under ``"rebuild"`` no refit is made."""
    animation = scenes.get("world", triangles=20_000, frames=8)
    scene = mi.load_dict(animation.scene_dict(
        resolution=(48, 27), spp=2,
        integrator={"type": "hlbvh_path", "max_depth": 4, "moving": "flag", "update": update}))
    accel = hlbvh.SceneAccel(scene, moving="flag", update=update)
    group = accel.dynamic
    built, build_ms = group.last, group.last.ms
    arrays = {k: np.array(getattr(group.bvh, k)) for k in ("node_min", "node_max", "prim_ids")}
    sensor = scene.sensors()[0]
    time_structures(accel, render_sample(accel, sensor))
    assert group.last is built and group.bvh is not None
    for name, before in arrays.items():
        assert np.array_equal(np.array(getattr(group.bvh, name)), before)
    if update == "rebuild":
        assert group.refits == 0 and accel.moving_meshes.costs.update_ms["hlbvh"] == build_ms
    else:
        assert group.refits == moving.MEASURED_REFITS
        assert accel.moving_meshes.costs.update_ms["hlbvh"] != build_ms
        apply_frame(scene, hlbvh.traverse(scene), animation.frame(1))
        assert accel.update().last_update["groups"]["dynamic"]["decision"] == "refit"


@needs_native_moving
def test06c_moving_meshes_that_are_nearly_the_whole_scene_choose_ours_or_the_scene():
    """When less than NATIVE_MIN_STILL_SHARE of the triangles stay still (the cloth),
    the native moving group is no candidate (it would rebuild nearly what the whole
    scene rebuilds and trace two structures): a probe does not build it; the world's
    flag (nine tenths of it still) keeps all three."""
    for name, expected in (("cloth", ("hlbvh", "scene")), ("world", moving.STRUCTURES)):
        animation = scenes.get(name, triangles=20_000, frames=4)
        scene = mi.load_dict(animation.scene_dict(
            resolution=(32, 18), spp=1,
            integrator={"type": "hlbvh_path", "max_depth": 3,
                        "moving": ",".join(animation.animated_ids())}))
        accel = scene.integrator().update_accel(scene, spp=1)
        time_structures(accel, render_sample(accel, scene.sensors()[0]))
        share = accel.moving_meshes.still_share
        assert (share < moving.NATIVE_MIN_STILL_SHARE) == (name == "cloth"), share
        assert accel.moving_meshes.allowed() == expected
        assert (accel.native_moving.builds == 0) == (name == "cloth")


@pytest.mark.parametrize("forced", ["hlbvh", pytest.param("native", marks=needs_native_moving),
                                    "scene"])
def test07_a_forced_choice_is_honoured_whatever_the_costs(forced):
    animation, scene = _world(moving_accel=forced)
    params = hlbvh.traverse(scene)
    integrator = scene.integrator()
    for frame, spp in ((1, 1), (2, 8192)):
        apply_frame(scene, params, animation.frame(frame))
        accel = integrator.update_accel(scene, spp=spp)
        assert accel.moving_structure == forced
    expected = hlbvh.NativeAccel if forced == "scene" else hlbvh.SceneAccel
    assert isinstance(integrator.accel(scene), expected)


@pytest.mark.parametrize("options, message", [
    ({"moving_accel": "bogus"}, "moving_accel='bogus': expected one of"),
    ({"moving_accel": "native", "static": "hlbvh"}, "moving_accel='native' with static='hlbvh'"),
])
def test08_bad_choices_name_the_option(options, message):
    scene = mi.load_dict({"type": "scene", "ball": {"type": "sphere"}})
    with pytest.raises(ValueError, match=message):
        hlbvh.SceneAccel(scene, **options)
    with pytest.raises(Exception, match=message):
        mi.load_dict({"type": "hlbvh_path", **options})


def test08b_without_a_second_native_scene_the_native_group_is_never_chosen(monkeypatch):
    """Where a kernel traces one Mitsuba scene at most (OptiX), "auto" chooses between
    ours and the whole scene, and a forced "native" is one line saying why."""
    monkeypatch.setattr(moving, "native_moving_possible", lambda: False)
    animation, scene = _world()
    params = hlbvh.traverse(scene)
    integrator = scene.integrator()
    apply_frame(scene, params, animation.frame(1))
    accel = integrator.update_accel(scene, spp=1)
    _inject(accel)
    for spp in (1, 8192):
        accel = integrator.update_accel(scene, spp=spp)
        assert "native" not in accel.last_update["moving_accel"]["estimates_ms"]
        assert accel.moving_structure in ("hlbvh", "scene")
    with pytest.raises(ValueError, match="moving_accel='native'.*OptiX"):
        hlbvh.SceneAccel(scene, moving_accel="native")


def test09_a_bad_choice_on_the_command_line_is_one_line(capsys):
    from hlbvh import cli

    status = cli.main(["render", "cloth", "--moving-accel", "bogus", "--frames", "1",
                       "--resolution", "8", "--spp", "1", "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 2 and len(err) == 1 and "--moving-accel" in err[0] and "bogus" in err[0]


# ---------------------------------------------------------------------------------------
# Hits through the native moving group: Mitsuba's, field for field
# ---------------------------------------------------------------------------------------


def _mesh(name, offset):
    from meshes import grid

    v, f = grid(8)
    v = v + np.asarray(offset, np.float32)
    mesh = mi.Mesh(name, len(v), len(f))
    p = mi.traverse(mesh)
    p["vertex_positions"] = mi.Float(v.ravel())
    p["faces"] = mi.UInt32(f.ravel())
    p.update()
    return mesh


def _fields(pi) -> dict:
    return {name: np.array(getattr(pi, name)) for name in
            ("t", "prim_uv", "prim_index", "shape_index")} | {
        "shape": np.array(dr.reinterpret_array(mi.UInt32, pi.shape)),
        "instance": np.array(dr.reinterpret_array(mi.UInt32, pi.instance))}


@needs_native_moving
def test10_native_moving_group_hits_are_mitsubas_field_for_field():
    scene = mi.load_dict({
        "type": "scene",
        "still": _mesh("still", (0, 0, 0)), "mover": _mesh("mover", (0.3, 0.2, 0.5)),
        "later": _mesh("later", (-0.4, 0.1, 0.9)),
        "ball": {"type": "sphere", "center": [0.5, 0.5, -0.5], "radius": 0.3},
        "group": {"type": "shapegroup", "tri": _mesh("tri", (0, 0, 0))},
        "inst": {"type": "instance", "shapegroup": {"type": "ref", "id": "group"},
                 "to_world": T().translate([0.2, -0.3, 1.3])}})
    accel = hlbvh.SceneAccel(scene, moving=["mover"], moving_accel="native")
    params = mi.traverse(scene)  # Mitsuba's own rebuild: its query is the reference
    rng = np.random.default_rng(3)
    o = rng.uniform(-1, 2, (4000, 3)).astype(np.float32)
    o[:, 2] = 3
    d = (rng.uniform(-0.2, 1.2, (4000, 3)) - o).astype(np.float32)
    d[:, 2] = -3
    ray = mi.Ray3f(mi.Point3f(*o.T), mi.Vector3f(*d.T))

    def check():
        ours, theirs = _fields(accel.ray_intersect_preliminary(ray)), _fields(
            scene.ray_intersect_preliminary(ray))
        valid = np.isfinite(theirs["t"])
        assert valid.sum() > 1000
        np.testing.assert_array_equal(np.isfinite(ours["t"]), valid)
        for name in ours:
            np.testing.assert_array_equal(ours[name][..., valid], theirs[name][..., valid], name)
        np.testing.assert_array_equal(np.array(accel.ray_test(ray)),
                                      np.array(scene.ray_test(ray)))

    check()
    for key, shift in (("mover", 0.1), ("later", -0.2)):  # "later" enters the group
        v = np.array(params[f"{key}.vertex_positions"]).reshape(-1, 3)
        v[:, 2] += shift
        params[f"{key}.vertex_positions"] = mi.Float(v.ravel())
        params.update()
        accel.update()
        assert accel.last_update["groups"]["native_moving"]["decision"] == "rebuild"
        check()
    assert accel.native_moving.indices == accel.dynamic.indices and len(accel.dynamic.indices) == 2


@pytest.mark.parametrize("forced", ["hlbvh", pytest.param("native", marks=needs_native_moving),
                                    "scene", "auto"])
def test11_images_under_every_choice_equal_native(forced):
    animation, scene = _world(moving_accel=forced)
    params = hlbvh.traverse(scene)
    reference = mi.load_dict(animation.scene_dict(
        resolution=(48, 27), spp=2, integrator={"type": "hlbvh_path", "max_depth": 4,
                                                 "accel": "native"}))
    ref_params = mi.traverse(reference)
    for frame in (1, 2):
        apply_frame(scene, params, animation.frame(frame))
        apply_frame(reference, ref_params, animation.frame(frame))
        ours = np.array(mi.render(scene, seed=frame))
        theirs = np.array(mi.render(reference, seed=frame))
        diff = np.abs(ours - theirs)
        outside = (diff > 5e-4 + 1e-4 * np.abs(theirs)).any(axis=-1)
        assert outside.sum() <= 1 and diff.mean() < 1e-6, (forced, frame)
        if forced in ("native", "scene"):  # Mitsuba's own queries: bit for bit
            np.testing.assert_array_equal(ours, theirs)


def test12_moving_instances_alone_choose_between_our_top_level_and_the_whole_scene():
    """A scene whose only motion is instances' transforms: the choice is ours (the top
    level over the instances) or Mitsuba's whole scene, by the same costs; under the
    whole scene the images are native's (its instance hits expanded as ours)."""
    animation = scenes.get("rigid", triangles=6000, frames=4, instanced=True, objects=12,
                           groups=2)
    description = animation.scene_dict(resolution=(32, 18), spp=1)
    integrator = {"type": "hlbvh_path", "max_depth": 3,
                  "moving": ",".join(animation.animated_ids())}
    scene = mi.load_dict(dict(description, integrator=integrator))
    params = hlbvh.traverse(scene)
    ours = scene.integrator()
    apply_frame(scene, params, animation.frame(1))
    accel = ours.update_accel(scene, spp=1)
    assert not accel.dynamic.indices and accel.moving_meshes.allowed() == ("hlbvh", "scene")
    _inject(accel)
    reference = mi.load_dict(dict(animation.scene_dict(resolution=(32, 18), spp=1),
                                  integrator=dict(integrator, accel="native")))
    ref_params = mi.traverse(reference)
    chosen = []
    for frame, spp in ((2, 1), (3, 65536)):
        apply_frame(scene, params, animation.frame(frame))
        apply_frame(reference, ref_params, animation.frame(frame))
        accel = ours.update_accel(scene, spp=spp)
        chosen.append(accel.moving_structure)
        with ours.updated():
            image = np.array(mi.render(scene, seed=frame, spp=2))
        theirs = np.array(mi.render(reference, seed=frame, spp=2))
        diff = np.abs(image - theirs)
        assert ((diff > 5e-4 + 1e-4 * np.abs(theirs)).any(axis=-1)).sum() <= 1
    assert chosen == ["hlbvh", "scene"]


@needs_native_moving
def test13_the_whole_scene_after_the_native_group_sees_every_motion():
    """Frames traced by the native group (whose builds clear Mitsuba's marks of change
    on the moving meshes), then by the whole scene: the scene's rebuild still takes
    every motion, and the images stay native's."""
    animation, scene, params, reference, ref_params = _world_and_native()
    integrator = scene.integrator()
    accel = integrator.update_accel(scene, spp=1)
    _inject(accel)
    # the whole scene wins at a large budget only
    accel.moving_meshes.costs.update_ms["scene"] = 300.0
    chosen, written = [], None
    # frame 3 again at a final frame's budget: no write since the native group's build
    for frame, spp in ((2, 512), (3, 512), (3, 1_000_000), (4, 1_000_000)):
        if frame != written:
            apply_frame(scene, params, animation.frame(frame))
            apply_frame(reference, ref_params, animation.frame(frame))
            written = frame
        accel = integrator.update_accel(scene, spp=spp)
        chosen.append(accel.moving_structure)
        with integrator.updated():
            ours = np.array(mi.render(scene, seed=frame, spp=2))
        np.testing.assert_array_equal(ours, np.array(mi.render(reference, seed=frame)))
    assert chosen == ["native", "native", "scene", "scene"]


@needs_native_moving
@pytest.mark.parametrize("other", ["native", "auto"])
def test14_the_whole_scene_sees_motion_whatever_another_scene_built(other):
    """One mesh in two scenes: scene B traces it with the native moving group (or probes
    that group under ``auto``), whose Mitsuba sub-scene build clears the mesh's mark of
    change; scene A, traced by the whole scene and animated through hlbvh.traverse,
    still rebuilds over the moved mesh (from our record of motion, not Mitsuba's marks)
    and renders what a native render of the moved mesh renders."""
    from meshes import grid

    v, f = grid(2)  # 8 triangles beside the floor's 2: the native group is a candidate
    v = (v - 0.5).astype(np.float32)

    def scene(mover, **integrator):
        return mi.load_dict({
            "type": "scene",
            "integrator": {"type": "hlbvh_path", "max_depth": 3, "moving": "mover",
                           **integrator},
            "sensor": {"type": "perspective", "to_world": T().look_at([0, 0, 3], [0, 0, 0],
                                                                      [0, 1, 0]),
                       "film": {"type": "hdrfilm", "width": 32, "height": 32,
                                "rfilter": {"type": "box"}},
                       "sampler": {"type": "independent", "sample_count": 2}},
            "floor": {"type": "rectangle", "to_world": T().translate([0, 0, -1]).scale(3)},
            "mover": mover, "light": {"type": "constant"}})

    def mesh():
        m = mi.Mesh("mover", len(v), len(f))
        p = mi.traverse(m)
        p["vertex_positions"], p["faces"] = mi.Float(v.ravel()), mi.UInt32(f.ravel())
        p.update()
        return m

    shared = mesh()
    a, b = scene(shared, moving_accel="scene"), scene(shared, moving_accel=other)
    reference = scene(mesh(), accel="native")
    params, ref_params = hlbvh.traverse(a), mi.traverse(reference)
    for frame in range(1, 4):
        moved = (v + np.float32(0.3 * frame) * np.float32([1, 0, 0])).ravel()
        params["mover.vertex_positions"] = mi.Float(moved)  # each scene its own buffer
        ref_params["mover.vertex_positions"] = mi.Float(moved)
        params.update()
        ref_params.update()
        mi.render(b, seed=frame)  # B's build over the shared mesh clears its mark
        np.testing.assert_array_equal(np.array(mi.render(a, seed=frame)),
                                      np.array(mi.render(reference, seed=frame)))
    assert a.integrator().scene_accel.moving_structure == "scene"
    assert b.integrator().scene_accel.moving_meshes.costs.update_ms.get("native") is not None


@needs_native_moving
def test15_a_decal_on_a_still_floor_shows_the_same_surface_under_ours_and_the_native_group():
    """A moving decal coplanar with a still floor: our BVH and the native moving group
    show the same surface in every pixel (the tie rule: the lower index in
    scene.shapes()), not each its own rounding's mix of the two."""
    def shape_ids(moving_accel):
        scene = mi.load_dict({
            "type": "scene",
            "integrator": {"type": "hlbvh_aov", "moving": "decal",
                           "moving_accel": moving_accel},
            "sensor": {"type": "perspective",
                       "to_world": T().look_at([0, 2, 3], [0, 0, 0], [0, 1, 0]),
                       "film": {"type": "hdrfilm", "width": 64, "height": 48,
                                "rfilter": {"type": "box"}},
                       "sampler": {"type": "independent", "sample_count": 1}},
            "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(3)},
            "decal": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(0.5)}})
        assert [s.id() for s in scene.shapes()] == ["decal", "floor"]
        return np.array(mi.render(scene))[..., 4]  # the shape_index channel

    ours, native = shape_ids("hlbvh"), shape_ids("native")
    np.testing.assert_array_equal(ours, native)
    assert (ours == 0).sum() > 300  # the decal, index 0, wins its ties: a whole square


# ---------------------------------------------------------------------------------------
# The first frames: the probe only where it could move the choice
# ---------------------------------------------------------------------------------------


def test16_the_probe_waits_for_a_timed_render_and_a_structure_that_could_win():
    """No probe before a render through the current structure was timed (the first
    compiles); then only when another structure's update alone, at the build rate the
    still world's sub-scene showed, leaves MIN_SAVING_MS below the current frame."""
    model = CostModel()
    model.record_update("hlbvh", 5.0)
    model.record_build_rate(ms=900.0, triangles=1_000_000)  # 0.9 us a triangle
    triangles = {"native": 100_000, "scene": 1_100_000}  # 90 ms, 990 ms
    preview, final = RayBudget(130_000, 8), RayBudget(16 * 130_000, 8)

    def worth(budget):
        return model.worth_probing(budget, "hlbvh", moving.STRUCTURES, triangles)

    assert not worth(preview) and not worth(final)  # nothing rendered yet
    model.record_render("hlbvh", 900.0, preview.samples)  # compiles: not timed
    assert not worth(preview)
    model.record_render("hlbvh", 57.0, preview.samples)
    assert not worth(preview)  # 62 ms a frame: no Mitsuba update fits below it
    model.record_render("hlbvh", 900.0, final.samples)
    assert worth(final)  # 905 ms: the native group's 90 ms update leaves room
    assert not model.worth_probing(final, "hlbvh", ("hlbvh",), triangles)


def test17_the_first_frames_pay_no_probe():
    """An animation's first two frames through the integrator: neither is probed (the
    native group not built, no query timed), and what traced them is our HLBVH."""
    animation, scene = _world()
    params = hlbvh.traverse(scene)
    integrator = scene.integrator()
    for frame in (0, 1):
        apply_frame(scene, params, animation.frame(frame))
        mi.render(scene, seed=frame)
        accel = integrator.scene_accel
        assert not accel.prepared.probed and accel.prepared.traced_by == "hlbvh"
    assert accel.native_moving.builds == 0 and not accel.moving_meshes.costs.query_ns


def test18_a_frames_update_replaces_the_first_builds_cost():
    """Without a probe, our update's cost is the first build's (which compiles) only
    until a frame's update is measured: that one replaces it, timed again where its
    refit ran kernels for the first time (compiled on a cold cache: here the first
    refit made to look 1 s long), and the next are averaged."""
    animation, scene = _world()
    params = hlbvh.traverse(scene)
    accel = hlbvh.SceneAccel(scene, moving="flag")
    costs = accel.moving_meshes.costs
    assert costs.update_ms["hlbvh"] == accel.dynamic.last.ms  # the build's
    group, update = accel.dynamic, accel.dynamic.update
    compiled = []

    def first_refit_compiles(change):
        update(change)
        if group.last.decision == "refit" and not compiled:
            compiled.append(group.last.ms)
            group.last = replace(group.last, ms=1000.0)

    group.update = first_refit_compiles
    apply_frame(scene, params, animation.frame(1))
    refit = accel.update().dynamic.last
    measured = costs.update_ms["hlbvh"]
    assert refit.decision == "refit" and compiled and measured < 1000.0
    apply_frame(scene, params, animation.frame(2))
    second = accel.update().dynamic.last.ms
    assert costs.update_ms["hlbvh"] == pytest.approx(0.5 * (measured + second))
