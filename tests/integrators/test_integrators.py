"""The registered integrators: ``hlbvh_path`` against Mitsuba's C++ ``path``, pixel for
pixel, and ``hlbvh_aov``; from dict and XML scenes; bad properties."""

import gc
import subprocess
import sys
import weakref

import drjit as dr
import hlbvh
import mitsuba as mi
import numpy as np
import pytest

from folders import FOLDERS
from test_accel import analytic_scene, cornell_box


def render(scene, integrator: dict, seed=0) -> np.ndarray:
    return np.array(mi.render(scene, integrator=mi.load_dict(integrator), seed=seed))


SCENES = {"cornell_box": cornell_box, "analytic": analytic_scene}


@pytest.mark.parametrize("scene_name", SCENES)
@pytest.mark.parametrize("options", [
    dict(max_depth=6),
    dict(max_depth=3, hide_emitters=True),
    dict(max_depth=8, rr_depth=2),
])
def test01_path_native_bit_identical_to_cpp_path(scene_name, options):
    scene = mi.load_dict(SCENES[scene_name]())
    reference = render(scene, dict(type="path", **options), seed=7)
    ours = render(scene, dict(type="hlbvh_path", accel="native", **options), seed=7)
    assert reference.mean() > 0.01  # the scene is lit: the comparison means something
    np.testing.assert_array_equal(ours, reference)


XML_SCENE = """
<scene version="3.0.0">
    <integrator type="hlbvh_path">
        <string name="accel" value="native"/>
        <string name="builder" value="lbvh"/>
        <integer name="leaf_size" value="2"/>
        <integer name="max_depth" value="5"/>
    </integrator>
    <sensor type="perspective">
        <float name="fov" value="40"/>
        <transform name="to_world">
            <lookat origin="0, 1, 6" target="0, 0.5, 0" up="0, 1, 0"/>
        </transform>
        <sampler type="independent"><integer name="sample_count" value="4"/></sampler>
        <film type="hdrfilm">
            <integer name="width" value="32"/>
            <integer name="height" value="32"/>
            <rfilter type="box"/>
        </film>
    </sensor>
    <shape type="rectangle">
        <transform name="to_world"><rotate x="1" angle="-90"/><scale value="5"/></transform>
    </shape>
    <shape type="cube">
        <transform name="to_world"><scale value="0.5"/><translate x="-1" y="0.5"/></transform>
    </shape>
    <shape type="sphere">
        <point name="center" x="1" y="0.6" z="0"/>
        <float name="radius" value="0.6"/>
    </shape>
    <shape type="sphere">
        <point name="center" x="0" y="4" z="2"/>
        <float name="radius" value="0.5"/>
        <emitter type="area"><rgb name="radiance" value="20"/></emitter>
    </shape>
</scene>
"""


def test02_path_from_xml_scene_bit_identical():
    scene = mi.load_string(XML_SCENE)
    assert "accel='native'" in str(scene.integrator())
    ours = np.array(mi.render(scene, seed=1))
    reference = render(scene, dict(type="path", max_depth=5), seed=1)
    assert reference.mean() > 0.01
    np.testing.assert_array_equal(ours, reference)


def test03_path_from_dict_scene_bit_identical():
    desc = analytic_scene()
    desc["integrator"] = dict(type="hlbvh_path", accel="native", max_depth=4,
                              builder="sah", morton_bits="auto")
    scene = mi.load_dict(desc)
    ours = np.array(mi.render(scene, seed=2))
    reference = render(scene, dict(type="path", max_depth=4), seed=2)
    np.testing.assert_array_equal(ours, reference)


@pytest.mark.parametrize("props, message", [
    (dict(accel="embree"), "accel='embree'"),
    (dict(builder="bvh2"), "builder='bvh2'"),
    (dict(leaf_size=99), "leaf_size=99"),
    (dict(leaf_sise=4), "leaf_sise"),
    (dict(max_depth=-3), "max_depth=-3"),
])
@pytest.mark.parametrize("kind", ["hlbvh_path", "hlbvh_aov"])
def test04_bad_properties_raise_naming_them(kind, props, message):
    if kind == "hlbvh_aov" and "max_depth" in props:
        message = "max_depth"  # not a property of hlbvh_aov: Mitsuba names it unreferenced
    with pytest.raises(Exception, match=message):
        mi.load_dict(dict(type=kind, **props))


def test05_register_again_is_harmless():
    hlbvh.register()
    scene = mi.load_dict(cornell_box())
    a = render(scene, dict(type="hlbvh_path", accel="native", max_depth=3))
    hlbvh.register()
    b = render(scene, dict(type="hlbvh_path", accel="native", max_depth=3))
    np.testing.assert_array_equal(a, b)


def test06_aov_channels_are_consistent():
    """Misses carry depth 0 and index -1; hits a depth > 0, a valid shape index and a
    unit normal; and the shape indices seen are those of the scene's visible shapes."""
    desc = analytic_scene(spp=1)
    scene = mi.load_dict(desc)
    img = render(scene, dict(type="hlbvh_aov", accel="native"))
    channels = img.shape[-1]
    assert channels == 3 + len(hlbvh.integrators.aov.CHANNELS)
    depth, shape, prim = img[..., 3], img[..., 4], img[..., 5]
    hit = depth > 0
    assert hit.any() and (~hit).any()
    assert np.all(shape[~hit] == -1) and np.all(prim[~hit] == -1)
    assert np.all((shape[hit] >= 0) & (shape[hit] < len(scene.shapes())))
    normal = img[..., 6:9]
    np.testing.assert_allclose(np.linalg.norm(normal[hit], axis=-1), 1, atol=1e-4)


def test07_path_on_a_scene_without_geometry_equals_native():
    """An environment and nothing else: every ray misses, in both accelerators."""
    desc = dict(cornell_box())
    desc = {k: v for k, v in desc.items() if k in ("type", "sensor")}
    desc["sky"] = dict(type="constant", radiance=dict(type="rgb", value=0.5))
    scene = mi.load_dict(desc)
    reference = render(scene, dict(type="path", max_depth=4), seed=3)
    for accel in ("native", "hlbvh"):
        ours = render(scene, dict(type="hlbvh_path", accel=accel, max_depth=4), seed=3)
        np.testing.assert_array_equal(ours, reference)


# ---------------------------------------------------------------------------------------
# hlbvh against native
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("scene_name", SCENES)
def test10_aov_primary_hits_hlbvh_equal_native(scene_name):
    scene = mi.load_dict(SCENES[scene_name](spp=1))
    native = render(scene, dict(type="hlbvh_aov", accel="native"), seed=4)
    ours = render(scene, dict(type="hlbvh_aov", accel="hlbvh"), seed=4)
    shape_n, prim_n = native[..., 4], native[..., 5]
    shape_o, prim_o = ours[..., 4], ours[..., 5]
    same = (shape_n == shape_o) & (prim_n == prim_o)
    # Edge-grazing rays may pick the neighbouring triangle: allow a pixel or two.
    assert same.mean() >= 1 - 2 / same.size, f"{(~same).sum()} pixels differ"
    # Triangles: t within 4e-7 relative (measured); cylinders up to 7.7e-5 (Embree
    # evaluates them in double precision, the direct call in float32).
    depth_n, depth_o = native[..., 3], ours[..., 3]
    np.testing.assert_allclose(depth_o[same], depth_n[same], rtol=2e-4)


def _hlbvh_traces_everything() -> dict:
    """Properties that make ``accel="hlbvh"`` trace every shape through hlbvh's own
    trees and routines: ``static="hlbvh"`` where the integrators take that option (its
    default, ``"native"``, hands the shapes that never move to Mitsuba's accelerator,
    and these scenes never move); without the option hlbvh traces them anyway."""
    try:
        mi.load_dict(dict(type="hlbvh_aov", accel="hlbvh", static="hlbvh"))
    except Exception:
        return {}
    return {"static": "hlbvh"}


@pytest.mark.parametrize("scene_name", SCENES)
def test12_aov_positions_and_normals_hlbvh_equal_native(scene_name):
    """Where both accelerators hit the same primitive, the world-space position and the
    shading normal of the hit (computed by Mitsuba from each accelerator's t and
    barycentrics) agree. On triangles within 2e-6 of the distance and 1e-5 (measured
    over seeds 4-6: 1.7e-7 and 1 ulp); on analytic shapes, which Embree evaluates in
    double precision and hlbvh by their own float32 routines, within 2e-4 of the
    distance and 5e-3 (measured: 7.7e-5 and 1.5e-3, next to a silhouette)."""
    scene = mi.load_dict(SCENES[scene_name](spp=1))
    names = list(hlbvh.integrators.aov.CHANNELS)
    native = render(scene, dict(type="hlbvh_aov", accel="native"), seed=4)[..., 3:]
    ours = render(scene, dict(type="hlbvh_aov", accel="hlbvh", **_hlbvh_traces_everything()),
                  seed=4)[..., 3:]
    channel = {name: k for k, name in enumerate(names)}
    depth = native[..., channel["depth"]]
    same = (depth > 0) & (ours[..., channel["depth"]] > 0)
    for c in ("shape_index", "prim_index"):
        same &= ours[..., channel[c]] == native[..., channel[c]]
    assert same.mean() >= (depth > 0).mean() - 2 / same.size and same.mean() > 0.3
    is_mesh = np.array([shape.is_mesh() for shape in scene.shapes()])
    mesh = is_mesh[native[same][:, channel["shape_index"]].astype(int)]
    assert mesh.any()
    position = [channel[f"position.{a}"] for a in "XYZ"]
    normal = [channel[f"normal.{a}"] for a in "XYZ"]
    p_ours, p_native = ours[same][:, position], native[same][:, position]
    assert np.abs(p_native).max() > 0.5  # positions, not zeros
    error = np.linalg.norm(p_ours - p_native, axis=-1) / depth[same]
    n_ours, n_native = ours[same][:, normal], native[same][:, normal]
    np.testing.assert_allclose(np.linalg.norm(n_native, axis=-1), 1, atol=1e-4)
    n_error = np.abs(n_ours - n_native).max(axis=-1)
    assert error[mesh].max() <= 2e-6 and n_error[mesh].max() <= 1e-5, (
        error[mesh].max(), n_error[mesh].max())
    if not mesh.all():
        assert error[~mesh].max() <= 2e-4 and n_error[~mesh].max() <= 5e-3, (
            error[~mesh].max(), n_error[~mesh].max())


@pytest.mark.parametrize("scene_name", SCENES)
@pytest.mark.parametrize("options", [dict(max_depth=6), dict(max_depth=3, hide_emitters=True)])
def test11_path_hlbvh_close_to_native(scene_name, options):
    """Same seed, box filter: both accelerators trace the same paths; hits differ only in
    the last bits of t and the barycentrics (the triangle tests round differently, and
    Embree evaluates cylinders in double precision), which shifts later vertices a
    little.

    Measured over 40 seeds at this size (32x32, 4 spp, max_depth 6): largest pixel
    difference 4.9e-6 (Cornell box) and 7.7e-5 (analytic scene, next to the cylinder,
    on a pixel of value 0.048); mean difference <= 3.4e-8; bit-identical pixels 13-16%
    (Cornell box: nearly every path meets a triangle) and 75-78% (analytic scene).
    Tolerances: 5e-4 absolute + 1e-4 relative per pixel (6x the worst measured), mean
    below 1e-6. One pixel may exceed it: a path can branch differently (a tie between
    two faces of a box edge, or a Russian-roulette draw that the last bits flip): seen
    on the Cornell box in 1 pixel of 40 seeds x 1024 pixels, and in 1 pixel of each
    128x128x16 render, differences 0.008-0.025; never on the analytic scene."""
    scene = mi.load_dict(SCENES[scene_name]())
    native = render(scene, dict(type="hlbvh_path", accel="native", **options), seed=5)
    ours = render(scene, dict(type="hlbvh_path", accel="hlbvh", **options), seed=5)
    diff = np.abs(ours - native)
    outside = (diff > 5e-4 + 1e-4 * np.abs(native)).any(axis=-1)
    assert outside.sum() <= 1, f"{outside.sum()} pixels beyond tolerance, max {diff.max()}"
    assert diff.mean() < 1e-6
    assert (diff == 0).all(axis=-1).mean() > 0.05  # same rays, mostly same bits


VARIANT_SCRIPT = """
import sys
sys.path[:0] = {tests!r}
import hlbvh, mitsuba as mi, numpy as np
from test_accel import cornell_box
backend = mi.variant().split("_")[0]  # llvm here, cuda where a GPU is
mi.set_variant("scalar_rgb")
hlbvh.register()
try:
    mi.load_dict(dict(type="hlbvh_path"))
except Exception as e:
    assert "need a JIT variant" in str(e), e
else:
    raise AssertionError("hlbvh_path accepted a scalar variant")
mi.set_variant(backend + "_ad_spectral")
hlbvh.register()
scene = mi.load_dict(cornell_box(res=8, spp=2))
ref = mi.render(scene, integrator=mi.load_dict(dict(type="path", max_depth=3)), seed=1)
ours = mi.render(scene, integrator=mi.load_dict(dict(type="hlbvh_path", accel="native",
                                                     max_depth=3)), seed=1)
assert np.array_equal(np.array(ref), np.array(ours))
print("ok")
"""


def test12_register_after_a_variant_change(tmp_path):
    """In a fresh process (the variant is global): a scalar variant is refused with a
    clear error; after switching to a spectral JIT variant and register(), hlbvh_path
    renders bit-identically to path there too."""
    tests = FOLDERS
    done = subprocess.run([sys.executable, "-c", VARIANT_SCRIPT.format(tests=tests)],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0 and done.stdout.strip().endswith("ok"), done.stderr[-3000:]


def test13_accel_is_cached_per_scene_and_follows_updates():
    """The HLBVH is built on the first render, reused by the next, rebuilt for another
    scene, rebuilt after params.update() gave a mesh new vertices, and does not keep
    the scene alive once the user lets go of it."""
    desc = cornell_box(res=8, spp=1)
    desc["integrator"] = dict(type="hlbvh_path", max_depth=2, static="hlbvh")
    scene = mi.load_dict(desc)
    integrator = scene.integrator()
    mi.render(scene)
    first = integrator.accel(scene)
    bvh = first.static.bvh
    mi.render(scene)
    assert integrator.accel(scene) is first and first.static.bvh is bvh
    assert first.last_update["decision"] == "kept"

    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.endswith("vertex_positions"))
    params[key] = params[key] * 0.9
    params.update()
    mi.render(scene)
    assert integrator.accel(scene) is first and first.dynamic.builds == 1

    other = mi.load_dict(cornell_box(res=8, spp=1))
    mi.render(other, integrator=integrator)
    assert integrator.accel(other) is not first

    alive = weakref.ref(integrator.accel(other))
    del scene, integrator, first, other, params
    gc.collect()
    assert alive() is None


@pytest.mark.parametrize("integrator", [
    dict(type="hlbvh_path", max_depth=4),
    dict(type="hlbvh_path", max_depth=3, hide_emitters=True),
    dict(type="hlbvh_aov"),
    dict(type="hlbvh_volpath", max_depth=4),
    dict(type="hlbvh_prb", max_depth=4),
])
def test13b_later_renders_of_a_scene_compile_nothing(integrator):
    """Three renders of one scene (same seed): the first builds the intersector and
    compiles the render's kernels, the second and third launch only kernels the first
    compiled (a build inside the first render's recording changed its kernel: a
    compile on the second render). Checked on what Dr.Jit reports as a compile, so it
    holds with an empty kernel cache."""
    desc = cornell_box(res=16, spp=2)
    desc["integrator"] = integrator
    scene = mi.load_dict(desc)
    compiled = []
    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        for _ in range(3):
            dr.kernel_history()
            dr.eval(mi.render(scene, seed=3))
            compiled.append([k["hash"] for k in dr.kernel_history()
                             if k["type"] == dr.KernelType.JIT and k.get("cache_hit") == 0])
    assert compiled[1:] == [[], []], f"renders 2 and 3 compiled {compiled[1:]}"


@pytest.mark.parametrize("builder", ["lbvh", "sah"])
def test14_builder_options_reach_the_build(builder):
    """Builder properties of the integrator are the options of the scene's HLBVH, and
    every builder renders the same image as native (within test11's tolerance)."""
    desc = cornell_box(res=16, spp=2)
    desc["integrator"] = dict(type="hlbvh_path", max_depth=4, builder=builder, leaf_size=2,
                              static="hlbvh")
    scene = mi.load_dict(desc)
    ours = np.array(mi.render(scene, seed=8))
    config = scene.integrator().accel(scene).static.bvh.config
    assert (config.builder, config.leaf_size) == (builder, 2)
    native = render(scene, dict(type="hlbvh_path", accel="native", max_depth=4), seed=8)
    np.testing.assert_allclose(ours, native, atol=5e-4, rtol=1e-4)


@pytest.mark.parametrize("integrator", ["hlbvh_path", "hlbvh_aov"])
def test30_a_render_updates_the_accelerator_once(integrator, monkeypatch):
    """mi.render by sensor index re-enters the integrator's render (Mitsuba turns the
    index into the sensor and calls it again): the accelerator is still updated once,
    a look at every shape that costs ~35 us a shape (10k instances: 0.35 s)."""
    desc = analytic_scene()
    desc["integrator"] = {"type": integrator, "accel": "hlbvh"}
    scene = mi.load_dict(desc)
    mi.render(scene, spp=1)
    calls = []
    real = hlbvh.SceneAccel.update
    monkeypatch.setattr(hlbvh.SceneAccel, "update", lambda self: calls.append(1) or real(self))
    dr.eval(mi.render(scene, spp=1))
    dr.eval(mi.render(scene, sensor=scene.sensors()[0], spp=1))
    assert len(calls) == 2


def test31_renders_inside_updated_trust_the_last_update(monkeypatch):
    """A caller that just updated the accelerator (a frame loop) renders inside
    ``integrator.updated()``: no look at the shapes again; outside it, every render
    looks (and follows a shape that moved)."""
    desc = analytic_scene()
    desc["integrator"] = {"type": "hlbvh_path", "accel": "hlbvh"}
    scene = mi.load_dict(desc)
    integrator = scene.integrator()
    integrator.update_accel(scene)
    calls = []
    real = hlbvh.SceneAccel.update
    monkeypatch.setattr(hlbvh.SceneAccel, "update", lambda self: calls.append(1) or real(self))
    with integrator.updated():
        inside = np.array(mi.render(scene, spp=1, seed=2))
    assert calls == [] and not integrator._updated
    outside = np.array(mi.render(scene, spp=1, seed=2))
    assert calls == [1]
    np.testing.assert_array_equal(inside, outside)
