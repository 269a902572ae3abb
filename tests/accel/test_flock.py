"""Rigid motion as transforms: ``FrameGeometry(to_world=...)``, ``apply_frame`` moving
instances, the ``flock`` scene, and its animation rendered through our two levels
frame by frame as native renders it, rebuilding only the top level."""

import hlbvh
import hlbvh.accel.native_group
import mitsuba as mi
import numpy as np
import pytest

from hlbvh import scenes
from hlbvh.render.frame import FrameRenderer
from hlbvh.scenes.procedural import FPS
from hlbvh.render.settings import RenderSettings


def _flock(**kw):
    return scenes.get("flock", birds=12, triangles=2000, frames=6, **kw)


def _to_world(params, key):
    return np.array(params[f"{key}.to_world"].matrix).reshape(4, 4)


def test01_frames_move_the_birds_by_their_transforms():
    animation = _flock()
    assert animation.animated_ids() == [f"bird_{k}" for k in range(12)]
    scene = mi.load_dict(animation.scene_dict(resolution=(16, 12), spp=1))
    params = mi.traverse(scene)
    before = _to_world(params, "bird_3")
    frame = animation.frame(4)
    assert all(g.positions is None and g.to_world.shape == (4, 4) for g in frame.values())
    written = scenes.apply_frame(scene, params, frame)
    assert written == animation.animated_ids()
    after = _to_world(params, "bird_3")
    assert np.abs(after - before).max() > 1e-3
    assert np.allclose(after, frame["bird_3"].to_world, atol=1e-5)
    assert np.linalg.det(after[:3, :3]) > 0  # turned and scaled, never mirrored
    group = hlbvh.accel.native_group.shape_groups(scene)[0]
    assert animation.triangle_counts()["bird_0"] == group.primitive_count()


@pytest.mark.parametrize("bad, what", [
    (np.full((4, 4), np.nan), "not finite"),
    (np.diag([1.0, 0.0, 1.0, 1.0]), "singular"),
    (np.eye(3), "4x4"),
])
def test02_a_bad_transform_is_named_and_nothing_is_written(bad, what):
    animation = _flock()
    scene = mi.load_dict(animation.scene_dict(resolution=(16, 12), spp=1))
    params = mi.traverse(scene)
    before = _to_world(params, "bird_0")
    frame = animation.frame(2)
    frame["bird_5"] = scenes.FrameGeometry(to_world=bad)
    with pytest.raises(ValueError, match=f"'bird_5'.*{what}"):
        scenes.apply_frame(scene, params, frame)
    assert np.array_equal(_to_world(params, "bird_0"), before)


def test03_transforms_and_positions_go_to_their_own_kind_of_shape():
    animation = _flock()
    scene = mi.load_dict(animation.scene_dict(resolution=(16, 12), spp=1))
    with pytest.raises(ValueError, match="'terrain'.*no instance"):
        scenes.apply_frame(scene, None, {"terrain": scenes.FrameGeometry(to_world=np.eye(4))})
    with pytest.raises(ValueError, match="'bird_1'.*no mesh"):
        scenes.apply_frame(scene, None, {"bird_1": scenes.FrameGeometry(np.zeros(9, np.float32))})
    with pytest.raises(ValueError, match="one of them"):
        scenes.FrameGeometry()


def test04_an_instanced_animation_renders_as_native_rebuilding_only_the_top_level():
    animation = _flock()
    renderers = {accel: FrameRenderer(animation, RenderSettings(  # our top level traced
        resolution=(48, 32), spp=2, integrator="path", max_depth=3, accel=accel,
        moving_accel="hlbvh" if accel == "hlbvh" else None)) for accel in ("native", "hlbvh")}
    for i in range(3):
        rendered = {a: r.render(i) for a, r in renderers.items()}
        images = {a: np.array(image) for a, (image, _) in rendered.items()}
        assert rendered["hlbvh"][1]["decision"] in (("build",) if i == 0 else ("refit", "rebuild"))
        assert np.abs(images["hlbvh"] - images["native"]).mean() <= 1e-4 * images["native"].mean()
        update = renderers["hlbvh"].integrator.accel(renderers["hlbvh"].scene).last_update
        groups = update["groups"]
        # The frame's update is the last (the render trusts it, looks at no shape again):
        # the static world built once, the top level refit or rebuilt
        assert groups["static"]["decision"] == ("build" if i == 0 else "kept")
        assert groups["dynamic"]["triangles"] == 0
        if i > 0:
            assert groups["instances"]["decision"] in ("refit", "rebuild")
        assert groups["instances"]["instances"] == 12
    accel = renderers["hlbvh"].integrator.accel(renderers["hlbvh"].scene)
    assert accel.static.builds == 1
    assert accel.instances.triangles == animation.triangle_counts()["bird_0"]


def test05_flock_options_are_checked():
    for bad in (dict(birds=0), dict(bird_triangles=3), dict(birds="many")):
        with pytest.raises(ValueError, match=list(bad)[0]):
            scenes.get("flock", **bad)


def test06_a_native_render_of_too_many_instances_is_refused_in_one_line():
    from hlbvh.errors import UserError
    from hlbvh.render.frame import MOST_NATIVE_INSTANCES
    animation = scenes.get("flock", birds=MOST_NATIVE_INSTANCES + 1, triangles=200, frames=2)
    with pytest.raises(UserError, match="instances.*--accel hlbvh"):
        FrameRenderer(animation, RenderSettings(resolution=(8, 8), spp=1, accel="native"))


def test07_rigid_instanced_moves_the_mesh_variants_bodies_by_transforms():
    """rigid(instanced=True): the bodies of the mesh variant, as instances; every
    group its own triangle count; rendered through our two levels as native renders."""
    kw = dict(objects=10, groups=4, triangles=6000, frames=4)
    meshes, instanced = scenes.get("rigid", **kw), scenes.get("rigid", instanced=True, **kw)
    counts = instanced.triangle_counts()
    assert len({counts[f"body_{g}"] for g in range(4)}) == 4
    assert instanced.animated_ids() == [f"body_{k}" for k in range(10)]
    assert instanced.static_ids() == meshes.static_ids()
    # The transforms carry the mesh variant's motion: body 0 (a sphere) sits where the
    # mesh variant's body 0 does (its vertices' centre), and as large
    scene = mi.load_dict(instanced.scene_dict(resolution=(16, 12), spp=1))
    scenes.apply_frame(scene, None, instanced.frame(3))
    params = mi.traverse(scene)
    m = _to_world(params, "body_0")
    vertices = meshes.frame(3)["bodies_0"].positions.reshape(-1, 3)
    body = vertices[:len(vertices) // 3]  # group 0 holds bodies 0, 4 and 8
    assert np.allclose(m[:3, 3], body.mean(axis=0), atol=1e-3)
    assert np.isclose(np.abs(np.linalg.det(m[:3, :3])) ** (1 / 3),
                      np.linalg.norm(body - body.mean(axis=0), axis=1).max(), rtol=1e-3)
    renderers = {accel: FrameRenderer(instanced, RenderSettings(
        resolution=(48, 32), spp=2, integrator="path", max_depth=3, accel=accel))
        for accel in ("native", "hlbvh")}
    for i in range(3):
        images = {a: np.array(r.render(i)[0]) for a, r in renderers.items()}
        assert np.abs(images["hlbvh"] - images["native"]).mean() <= 1e-4 * images["native"].mean()
    with pytest.raises(ValueError, match="instanced"):
        scenes.get("rigid", instanced="yes")


# ---- Scene options on the command line, and the comparison harness ----


def test08_scene_specs_carry_typed_options_and_name_bad_ones():
    assert scenes.parse("flock") == ("flock", {})
    assert scenes.parse("rigid:instanced=true, objects=40") == (
        "rigid", {"instanced": True, "objects": 40})
    assert scenes.parse("world:flag_triangles=5000") == ("world", {"flag_triangles": 5000})
    assert scenes.scene_options("fracture") == {"pieces": 300, "instanced": False}
    for spec, named in (("flock:bird=3", "'bird=3'"), ("flock:birds=many", "birds='many'"),
                        ("rigid:instanced=maybe", "true or false"), ("flock:birds", "'birds'"),
                        ("flock:triangles=5", "'triangles=5'"), ("nest:x=1", "'nest'")):
        with pytest.raises(ValueError, match=named):
            scenes.parse(spec)


def test09_the_command_line_renders_a_scene_with_its_options(tmp_path, capsys):
    from cli_helpers import run_cli

    out = tmp_path / "birds"
    status, printed, errors = run_cli(capsys, "render", "flock:birds=3", "--triangles", "800",
                                      "--frames", "1", "--resolution", "8", "--spp", "1",
                                      "--out", out, "--quiet")
    assert status == 0 and not errors
    assert "flock:birds=3" in (out / "stats.json").read_text()
    status, _, errors = run_cli(capsys, "render", "flock:wings=2", "--out", tmp_path / "x")
    assert status == 2 and len(errors) == 1 and "'wings=2' is not an option" in errors[0]
    assert not (tmp_path / "x").exists()


def test10_bench_frame_times_the_top_level_of_an_instanced_scene(monkeypatch):
    from hlbvh.comparison.bench import frame as bench_frame

    def rows(spec):
        return bench_frame.run(repeats=1, sizes=(800,), resolution=8, scenes=(spec,),
                               spps=(1, 2), drift_frames=3, max_depth=2)

    found = rows("flock:birds=6")
    assert [r["spp"] for r in found] == [1, 2]
    for r in found:
        assert r["instances"] == 6 and r["scene"] == "flock:birds=6"
        assert r["triangles"] == scenes.get("flock", birds=6, triangles=800).triangle_count()
        assert r["build_min_ms"] > 0 and r["seeded_min_ms"] > 0 and r["refit_min_ms"] > 0
        assert r["sah_fresh"] > 0 and r["sah_drift_max"] >= r["sah_drift_last"] > 0.5
        assert r["native_over_hlbvh"] > 0
    table = bench_frame.format_table(found)
    assert "6 instances" in table
    # Past what native takes: the hlbvh side alone, the table says native refused.
    monkeypatch.setattr(hlbvh.render.frame, "MOST_NATIVE_INSTANCES", 4)
    found = rows("flock:birds=6")
    assert all(r["native_frame_min_ms"] is None and r["native_over_hlbvh"] is None
               and r["hlbvh_frame_min_ms"] > 0 and r["crossover_spp"] is None for r in found)
    assert "no nat." in bench_frame.format_table(found)
    found = bench_frame.run(repeats=1, sizes=(800,), resolution=8, scenes=("flock:birds=2",),
                            spps=(1,), drift_frames=2, max_depth=2, native=False)
    assert found[0]["native_frame_min_ms"] is None and found[0]["hlbvh_frame_min_ms"] > 0


def test11_a_sweep_leaves_out_what_an_instanced_scene_cannot_take(tmp_path, capsys):
    from cli_helpers import run_cli

    out = tmp_path / "sweep"
    status, printed, errors = run_cli(capsys, "sweep", "flock:birds=4", "--triangles", "800",
                                      "--resolution", "8", "--spp", "1", "--spp-curve", "1",
                                      "--frames", "0:2", "--settings", "lbvh,static_hlbvh",
                                      "--out", out, "--quiet")
    assert status == 0
    assert len(errors) == 1 and "static_hlbvh left out" in errors[0] and "bird_0" in errors[0]
    assert "1 settings and native" in printed


def test12_fracture_instanced_moves_the_one_mesh_models_shards_by_transforms():
    """fracture(instanced=True): each shard a group of its own and an instance; its
    transform carries the one-mesh model's vertices; rendered as native renders it,
    the top level alone rebuilt."""
    kw = dict(triangles=2500, pieces=6, frames=40)
    mesh, instanced = scenes.get("fracture", **kw), scenes.get("fracture", instanced=True, **kw)
    shards = instanced.animated_ids()
    assert shards == [f"shard_{k}" for k in range(len(shards))] and len(shards) >= 4
    assert instanced.triangle_count() == mesh.triangle_count()
    assert instanced.static_ids() == ["ground"]
    scene = mi.load_dict(instanced.scene_dict(resolution=(16, 12), spp=1))
    groups = hlbvh.accel.native_group.shape_groups(scene)
    assert len(groups) == len(shards)
    # Frame 30 (shards in flight, some landed): the world vertices through each
    # transform are the mesh model's
    moved = mesh.frame(30)["shards"].positions.reshape(-1, 3)
    scenes.apply_frame(scene, None, instanced.frame(30))
    world = np.concatenate([(rest @ m[:3, :3].T) + m[:3, 3] for (rest, _), m in
                            zip(instanced._pieces, instanced.transforms(30 / FPS))])
    assert np.abs(world - moved).max() < 1e-5
    renderers = {accel: FrameRenderer(instanced, RenderSettings(  # our top level traced
        resolution=(40, 30), spp=2, integrator="path", max_depth=3, accel=accel,
        moving_accel="hlbvh" if accel == "hlbvh" else None)) for accel in ("native", "hlbvh")}
    for i in (0, 20, 30):
        rendered = {a: r.render(i) for a, r in renderers.items()}
        images = {a: np.array(image) for a, (image, _) in rendered.items()}
        assert np.abs(images["hlbvh"] - images["native"]).mean() <= 1e-4 * images["native"].mean()
        update = renderers["hlbvh"].integrator.accel(renderers["hlbvh"].scene).last_update
        assert update["groups"]["dynamic"]["triangles"] == 0
    with pytest.raises(ValueError, match="instanced"):
        scenes.get("fracture", instanced="yes")


def test13_compare_reports_an_instanced_scene_as_natives(tmp_path, capsys):
    from cli_helpers import run_cli

    out = tmp_path / "compare"
    status, printed, errors = run_cli(capsys, "compare", "rigid:instanced=true+objects=6",
                                      "--triangles", "3000", "--frames", "0:2",
                                      "--resolution", "24", "--spp", "1", "--out", out, "--quiet")
    assert status == 2 and "instanced='true+objects=6'" in errors[0]  # ',' between options
    status, printed, errors = run_cli(capsys, "compare", "rigid:instanced=true,objects=6,groups=3",
                                      "--triangles", "3000", "--frames", "0:2",
                                      "--resolution", "24", "--spp", "1", "--out", out, "--quiet")
    assert status == 0 and not errors
    assert (out / "report.html").is_file() and "native vs hlbvh" in printed
    assert "within Monte Carlo noise of native's on every frame" in printed
