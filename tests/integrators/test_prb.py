"""``hlbvh_prb`` against Mitsuba's ``prb``: the primal image and the gradients (forward
and backward mode, with respect to a mesh's vertex positions and a BSDF reflectance)
equal prb's with ``accel="native"``, are close with ``accel="hlbvh"``; the accelerator
is brought up to date by every render entry point; an Adam optimisation of a mesh's
vertices through ``hlbvh.traverse`` lands where native's lands; bad properties."""

import contextlib
import json

import drjit as dr
import hlbvh
import mitsuba as mi
import numpy as np
import pytest

from test_integrators import _hlbvh_traces_everything

T = mi.ScalarTransform4f
BOX = "box.vertex_positions"
FLOOR = "floor.bsdf.reflectance.value"


def shape_scene(res=16, spp=4, integrator=None) -> dict:
    """A small box on a floor (both meshes) under a textured rectangle light (a
    spatially varying area emitter, whose sample prb re-attaches by a ray) and a dim
    environment; box filter."""
    texture = np.linspace(0.5, 1.5, 4 * 4 * 3, dtype=np.float32).reshape(4, 4, 3)
    desc = {
        "type": "scene",
        "sensor": dict(
            type="perspective", fov=40,
            to_world=T().look_at(origin=[0, 2.2, 4], target=[0, 0.3, 0], up=[0, 1, 0]),
            film=dict(type="hdrfilm", width=res, height=res, rfilter=dict(type="box"),
                      pixel_format="rgb"),
            sampler=dict(type="independent", sample_count=spp),
        ),
        "floor": dict(type="cube", to_world=T().translate([0, -0.05, 0]).scale([2, 0.05, 2]),
                      bsdf=dict(type="diffuse",
                                reflectance=dict(type="rgb", value=[0.6, 0.5, 0.4]))),
        "box": dict(type="cube", to_world=T().translate([0.2, 0.3, 0]).scale(0.3),
                    bsdf=dict(type="diffuse",
                              reflectance=dict(type="rgb", value=[0.3, 0.6, 0.8]))),
        "light": dict(type="rectangle",
                      to_world=T().translate([0, 2.5, 0.5]).rotate([1, 0, 0], 90).scale(0.7),
                      emitter=dict(type="area",
                                   radiance=dict(type="bitmap", data=mi.TensorXf(texture), raw=True))),
        "sky": dict(type="constant", radiance=dict(type="rgb", value=0.2)),
    }
    if integrator is not None:
        desc["integrator"] = integrator
    return desc


PRB = dict(type="prb", max_depth=4)
NATIVE = dict(type="hlbvh_prb", accel="native", max_depth=4)


def hlbvh_options() -> dict:
    return dict(type="hlbvh_prb", accel="hlbvh", max_depth=4, **_hlbvh_traces_everything())


def _perturbed(params, key):
    """Write ``params[key]`` plus a scalar ``x`` with gradients enabled (the box moved
    along x by ``x``, or the reflectance raised by ``x``) and return ``x``."""
    x = mi.Float(0.0)
    dr.enable_grad(x)
    if key == BOX:
        v = dr.unravel(mi.Point3f, params[key])
        params[key] = dr.ravel(mi.Point3f(v.x + x, v.y, v.z))
    else:
        params[key] = params[key] + x
    params.update()
    return x


def forward(integrator: dict, key: str, seed=3):
    """(primal image, forward-mode derivative image) of ``shape_scene`` in ``key``."""
    scene = mi.load_dict(shape_scene())
    params = mi.traverse(scene)
    x = _perturbed(params, key)
    image = mi.render(scene, params, integrator=mi.load_dict(integrator), seed=seed)
    dr.forward(x)
    return np.array(image), np.array(dr.grad(image))


def backward(integrator: dict, key: str, seed=3) -> float:
    """The backward-mode derivative of the image's weighted mean in ``key``."""
    scene = mi.load_dict(shape_scene())
    params = mi.traverse(scene)
    x = _perturbed(params, key)
    image = mi.render(scene, params, integrator=mi.load_dict(integrator), seed=seed)
    weights = dr.linspace(mi.Float, 0.5, 1.5, dr.width(image.array))
    dr.backward(dr.mean(image.array * weights))
    return float(dr.grad(x)[0])


@pytest.mark.parametrize("options", [dict(), dict(hide_emitters=True), dict(max_depth=2),
                                     dict(max_depth=6, rr_depth=1)])
def test01_native_primal_equals_prb(options):
    scene = mi.load_dict(shape_scene())
    reference = mi.render(scene, integrator=mi.load_dict({**PRB, **options}), seed=7)
    ours = mi.render(scene, integrator=mi.load_dict({**NATIVE, **options}), seed=7)
    assert np.array(reference).mean() > 0.05
    np.testing.assert_array_equal(np.array(ours), np.array(reference))


@pytest.mark.parametrize("key", [BOX, FLOOR])
def test02_native_gradients_equal_prb(key):
    """Forward mode: the primal image and the derivative image; backward mode: the
    derivative of a weighted mean."""
    image_ref, grad_ref = forward(PRB, key)
    image, grad = forward(NATIVE, key)
    assert np.abs(grad_ref).max() > 1e-3, "the derivative image is empty"
    np.testing.assert_array_equal(image, image_ref)
    np.testing.assert_allclose(grad, grad_ref, rtol=1e-5, atol=1e-6)
    reference = backward(PRB, key)
    assert abs(reference) > 1e-4
    assert backward(NATIVE, key) == pytest.approx(reference, rel=1e-5, abs=1e-7)


@pytest.mark.parametrize("key", [BOX, FLOOR])
def test03_hlbvh_gradients_close_to_native(key):
    """Every shape through our trees: hits that differ from Embree's in the last bits
    (test_integrators' tolerances per pixel, one pixel may branch)."""
    image_ref, grad_ref = forward(NATIVE, key)
    image, grad = forward(hlbvh_options(), key)
    for ours, ref in ((image, image_ref), (grad, grad_ref)):
        diff = np.abs(ours - ref)
        outside = (diff > 5e-4 + 1e-4 * np.abs(ref)).any(axis=-1)
        assert outside.sum() <= 1, f"{outside.sum()} pixels beyond tolerance, max {diff.max()}"
    assert np.abs(grad_ref).max() > 1e-3
    assert backward(hlbvh_options(), key) == pytest.approx(backward(NATIVE, key), rel=1e-3)


def _moved_box(integrator: dict):
    """The scene with ``integrator``, rendered once (its accelerator built), then the
    box moved by 0.4 along x through :func:`hlbvh.traverse` (no scene rebuild with
    accel="hlbvh") and the floor's reflectance made differentiable; (scene, params)."""
    scene = mi.load_dict(shape_scene(integrator=integrator))
    mi.render(scene, seed=1)
    with pytest.warns(UserWarning) if integrator["accel"] == "native" else contextlib.nullcontext():
        params = hlbvh.traverse(scene)
    v = dr.unravel(mi.Point3f, params[BOX])
    params[BOX] = dr.ravel(mi.Point3f(v.x + 0.4, v.y, v.z))
    params.update()
    dr.enable_grad(params[FLOOR])
    params.update()
    return scene, params


@pytest.mark.parametrize("entry", ["render", "render_forward", "render_backward"])
def test04_every_render_entry_updates_the_accelerator(entry):
    """Each entry point, called first after a move that skipped Mitsuba's rebuild,
    traces the moved box: its image (or gradients) equal native's (Mitsuba's
    rebuilt scene) within tolerance, where a stale accelerator would show the box at
    its old place."""
    results = []
    for options in (dict(NATIVE), hlbvh_options()):
        scene, params = _moved_box(options)
        integrator = scene.integrator()
        if entry == "render":
            results.append(np.array(integrator.render(scene, seed=2)))
        elif entry == "render_forward":
            dr.set_grad(params[FLOOR], 1.0)
            results.append(np.array(integrator.render_forward(scene, params, seed=2)))
        else:
            grad_in = dr.full(mi.TensorXf, 1.0, (16, 16, 3))
            integrator.render_backward(scene, params, grad_in, seed=2)
            results.append(np.array(dr.grad(params[FLOOR])))
    native, ours = results
    assert np.abs(native).max() > 1e-3
    np.testing.assert_allclose(ours, native, rtol=1e-3, atol=5e-4)
    if entry == "render":
        stale = np.array(mi.render(mi.load_dict(shape_scene()), integrator=mi.load_dict(NATIVE),
                                   seed=2))
        assert np.abs(stale - native).max() > 0.05  # the move shows


def optimise(accel: str, steps=3):
    """Adam on the box's vertex positions towards the image of the box moved by 0.3
    along x, through ``hlbvh.traverse`` and ``params.update(opt)``: (vertices after
    ``steps`` steps, the scene, whether update skipped the rebuild)."""
    options = dict(NATIVE) if accel == "native" else hlbvh_options()
    target_scene = mi.load_dict(shape_scene(spp=16))
    target_params = mi.traverse(target_scene)
    v = dr.unravel(mi.Point3f, target_params[BOX])
    target_params[BOX] = dr.ravel(mi.Point3f(v.x + 0.3, v.y, v.z))
    target_params.update()
    target = mi.render(target_scene, integrator=mi.load_dict(PRB), seed=100)

    scene = mi.load_dict(shape_scene(integrator=options))
    with pytest.warns(UserWarning) if accel == "native" else contextlib.nullcontext():
        params = hlbvh.traverse(scene)
    opt = mi.ad.Adam(lr=0.02)
    opt[BOX] = params[BOX]
    params.update(opt)
    for step in range(steps):
        image = mi.render(scene, params, seed=step)
        loss = dr.mean(dr.square(image - target))
        dr.backward(loss)
        opt.step()
        params.update(opt)
    return np.array(params[BOX]), scene, params.skips_rebuild


def test05_adam_optimisation_lands_where_natives_lands():
    start = np.array(mi.traverse(mi.load_dict(shape_scene()))[BOX])
    native, _, native_skips = optimise("native")
    ours, scene, skips = optimise("hlbvh")
    assert skips and not native_skips  # hlbvh_prb with accel="hlbvh": no scene rebuild
    assert np.abs(native - start).max() > 0.01, "the optimisation did not move the box"
    np.testing.assert_allclose(ours, native, atol=2e-4)
    # The mesh the optimiser rewrites is a moving one of our accelerator
    assert scene.integrator().update_accel(scene).last_update["moving"] == ["box"]


@pytest.mark.parametrize("props, message", [
    (dict(max_depth=-2), "max_depth"),
    (dict(rr_depth=0), "rr_depth"),
    (dict(accel="embree"), "accel='embree'"),
])
def test06_bad_properties_raise_naming_them(props, message):
    with pytest.raises(Exception, match=message):
        mi.load_dict(dict(type="hlbvh_prb", **props))


def test07_hlbvh_bench_prb(capsys):
    """``hlbvh bench prb`` at a tiny size: one row, both loops timed, the ratio of their
    medians, the two loops' flags where each other's are (same descent), the table."""
    from cli_helpers import run_cli
    from hlbvh.comparison.bench import prb as bench_prb

    status, table, errors = run_cli(capsys, "bench", "prb", "--sizes", "1500", "--repeats",
                                    "1", "--resolution", "8", "--json")
    assert status == 0 and not errors
    [row] = json.loads(table)
    assert tuple(row) == bench_prb.ROW_KEYS
    assert row["triangles"] >= 1500 and row["resolution"] == 8 and row["repeats"] == 1
    assert all(row[k] > 0 for k in ("prb_min_ms", "hlbvh_min_ms", "prb_cold_ms"))
    assert row["ratio"] == pytest.approx(row["prb_median_ms"] / row["hlbvh_median_ms"])
    assert row["agree"] > 0.99
    lines = bench_prb.format_table([row]).splitlines()
    assert lines[0].startswith("hlbvh prb benchmark") and lines[3].split()[0] == "world"
    assert lines[3].split()[-2:] == [f"{row['ratio']:.2f}x", f"{100 * row['agree']:.4f}%"]


def _count_queries(monkeypatch):
    """Record, from now on, every closest-hit and shadow query as (the pass's mode,
    "closest" | "shadow"), and every store of kept answers made; (queries, stores)."""
    from hlbvh.accel import SceneAccel
    from hlbvh.integrators import prb
    mode, asked, stores = [None], [], []
    real_sample, real_closest, real_test, real_init = (
        prb.PRBIntegrator.sample, prb._preliminary, SceneAccel.ray_test,
        prb._ReplayHits.__init__)

    def sample(self, *args, **kwargs):
        mode[0] = kwargs["mode"] if "mode" in kwargs else args[0]
        return real_sample(self, *args, **kwargs)

    def closest(*args):
        asked.append((mode[0], "closest"))
        return real_closest(*args)

    def test(self, *args, **kwargs):
        asked.append((mode[0], "shadow"))
        return real_test(self, *args, **kwargs)

    def init(self, *args, **kwargs):
        real_init(self, *args, **kwargs)
        stores.append(self)

    monkeypatch.setattr(prb.PRBIntegrator, "sample", sample)
    monkeypatch.setattr(prb, "_preliminary", closest)
    monkeypatch.setattr(SceneAccel, "ray_test", test)
    monkeypatch.setattr(prb._ReplayHits, "__init__", init)
    return asked, stores


def _replayed(asked):
    """The queries the replay asked (of :func:`_count_queries`)."""
    return [kind for m, kind in asked if m == dr.ADMode.Backward]


@pytest.mark.parametrize("kept", [True, False])
def test08_the_replay_reads_the_primal_pass_s_answers(monkeypatch, kept):
    """A backward pass's replay traces the rays its primal pass traced: their answers
    are kept and read back, so the replay asks the intersector only for a textured
    emitter's point; the derivative is the one a traced replay gives. Without room
    for them (the memory limit), the replay traces again."""
    from hlbvh.integrators import prb
    reference = backward(hlbvh_options(), BOX)
    if not kept:
        monkeypatch.setattr(prb, "REPLAY_CACHE_BYTES", 0)
    asked, _ = _count_queries(monkeypatch)
    assert backward(hlbvh_options(), BOX) == pytest.approx(reference, rel=1e-6)
    replay = _replayed(asked)
    primal = [kind for m, kind in asked if m == dr.ADMode.Primal]
    # Dr.Jit may record a loop's body more than once: count in recordings of the body
    bodies = primal.count("shadow") // 2  # two primal passes: the render's, the backward's
    assert bodies >= 1 and primal.count("closest") == 2 * (1 + bodies)
    if kept:  # a textured emitter's point alone, once a recording of the body
        assert replay == ["closest"] * bodies
    else:  # the camera ray, and per body the next vertex and the emitter's point
        assert sorted(replay) == ["closest"] * (1 + 2 * bodies) + ["shadow"] * bodies


@pytest.mark.parametrize("max_depth, first", [(1000, None), (-1, 1)])
def test09_the_kept_answers_are_as_deep_as_the_paths(monkeypatch, max_depth, first):
    """The store of the primal pass's answers is sized by the paths (here under a
    bright sky none goes past 8 vertices), not by ``max_depth`` (1000, or
    unbounded), which would ask 1001 vertices a path; from a first stretch of eight
    vertices, or of one, doubling while paths go on (1, 2, 4, 8: four stretches of
    the primal loop). The replay reads it (no shadow ray traced) and its derivative is that of
    a traced replay."""
    from hlbvh.integrators import prb
    options = dict(hlbvh_options(), max_depth=max_depth)
    monkeypatch.setattr(prb, "REPLAY_CACHE_BYTES", 0)
    reference = backward(options, BOX)
    monkeypatch.undo()
    if first is not None:
        monkeypatch.setattr(prb, "REPLAY_FIRST_DEPTHS", first)
    asked, stores = _count_queries(monkeypatch)
    assert backward(options, BOX) == pytest.approx(reference, rel=1e-6)
    [store] = stores
    assert dr.width(store.hits) == store.n * 9 and dr.width(store.occluded) == store.n * 8
    assert store.kept and store.depths == 8
    assert "shadow" not in _replayed(asked)


def test10_a_store_that_would_outgrow_the_limit_is_given_up(monkeypatch):
    """Where the store, doubled for paths that go on, would pass the memory limit,
    the answers are given up: the rest of the primal pass and the replay trace, and
    the derivative is still that of a traced replay."""
    from hlbvh.integrators import prb
    n = 16 * 16 * 4
    monkeypatch.setattr(prb, "REPLAY_CACHE_BYTES", 0)
    reference = backward(hlbvh_options(), BOX)
    monkeypatch.setattr(prb, "REPLAY_FIRST_DEPTHS", 1)
    # Room for the first stretch's two slots a path, not for the doubled store's three
    monkeypatch.setattr(prb, "REPLAY_CACHE_BYTES", n * 2 * prb._BYTES_PER_VERTEX)
    asked, stores = _count_queries(monkeypatch)
    assert backward(hlbvh_options(), BOX) == pytest.approx(reference, rel=1e-6)
    [store] = stores
    assert not store.kept and store.hits is None
    assert "shadow" in _replayed(asked)
