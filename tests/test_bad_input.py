"""Bad input everywhere a user can give it: ``hlbvh.build``, ``BVH.refit``, the
accelerators (``SceneAccel``, ``make_accel``, their query methods), the integrators'
properties, scene dicts, and the command line. Each mistake gets a ValueError or a
TypeError whose message names the thing that is wrong (and, where there is one, the
fix); nothing crashes with an internal error, nothing hangs."""

from __future__ import annotations

import gc
import re
import subprocess
import sys

import numpy as np
import pytest

import hlbvh
import drjit as dr
import mitsuba as mi
from meshes import empty_mesh_loads

V = mi.Float([0, 0, 0, 1, 0, 0, 0, 1, 0])
F = mi.UInt32([0, 1, 2])


def causes(error: BaseException):
    """``error`` and every exception it was raised from or during."""
    while error is not None:
        yield error
        error = error.__cause__ or error.__context__


def raises_naming(kind, pattern: str, fn):
    """Call ``fn``; assert that it raises and that an exception of ``kind`` among the
    raised one and its causes (Mitsuba wraps errors of Python plugins) matches
    ``pattern``."""
    with pytest.raises(Exception) as info:
        fn()
    errors = [(type(e), str(e)) for e in causes(info.value)]
    # The tracebacks hold what fn made (a scene with an empty mesh, say, which breaks
    # Mitsuba's later renders while it lives): keep only the messages.
    for e in causes(info.value):
        e.__traceback__ = None
    del info
    gc.collect()
    found = [message for error_type, message in errors if issubclass(error_type, kind)]
    assert found, f"no {kind.__name__} among {[t.__name__ for t, _ in errors]}"
    assert any(re.search(pattern, message) for message in found), found


# ---------------------------------------------------------------------------------------
# hlbvh.build and BVH.refit
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("vertices, faces, kind, pattern", [
    ([0, 0, 0, 1, 0, 0, 0, 1, 0], F, TypeError, "vertices: expected a Dr.Jit"),
    (np.zeros(9, np.float32), F, TypeError, "vertices: expected a Dr.Jit"),
    (None, F, TypeError, "vertices: expected a Dr.Jit"),
    (mi.ScalarPoint3f(0, 0, 0), F, TypeError, "vertices"),
    (mi.Point2f([0, 1], [0, 1]), F, TypeError, "3 components per vertex"),
    (mi.UInt32([0, 0, 0, 1, 0, 0, 0, 1, 0]), F, TypeError, "floating point"),
    (mi.Float([0, 0, 0, 1]), F, ValueError, "3 values per vertex"),
    (mi.Float(), F, ValueError, "vertices: the array is empty"),
    (mi.Float([0, 0, np.nan, 1, 0, 0, 0, 1, 0]), F, ValueError, "non-finite"),
    (mi.Float([0, 0, 0, 1, -np.inf, 0, 0, 1, 0]), F, ValueError, "non-finite"),
    (V, [0, 1, 2], TypeError, "faces: expected a Dr.Jit"),
    (V, np.array([0, 1, 2]), TypeError, "faces: expected a Dr.Jit"),
    (V, None, TypeError, "faces: expected a Dr.Jit"),
    (V, mi.Float([0, 1, 2]), TypeError, "faces: expected 32-bit integer"),
    (V, mi.UInt64([0, 1, 2]), TypeError, "faces: expected 32-bit integer"),
    (V, mi.UInt32(), ValueError, "faces: the mesh is empty"),
    (V, mi.UInt32([0, 1]), ValueError, "3 indices per triangle"),
    (V, mi.UInt32([0, 1, 3]), ValueError, "index 3 is out of range for 3 vertices"),
    (V, mi.Int32([0, -1, 2]), ValueError, "out of range.*negative"),
])
def test01_build_rejects_bad_arrays_naming_them(vertices, faces, kind, pattern):
    with pytest.raises(kind, match=pattern):
        hlbvh.build(vertices, faces)


@pytest.mark.parametrize("options, pattern", [
    (dict(leafsize=4), r"unknown build option\(s\) \['leafsize'\]: expected some of"),
    (dict(builder="bvh"), "builder='bvh': expected one of"),
    (dict(builder=None), "builder=None"),
    (dict(leaf_size=0), "leaf_size=0: expected an int in 1..16"),
    (dict(leaf_size=17), "leaf_size=17"),
    (dict(leaf_size="4"), "leaf_size='4'"),
    (dict(leaf_size=4.0), "leaf_size=4.0"),
    (dict(leaf_size=True), "leaf_size=True"),
    (dict(morton_bits=31), "morton_bits=31: expected 30, 60 or 'auto'"),
    (dict(morton_bits=30.0), "morton_bits=30.0"),
    (dict(morton_bits="30"), "morton_bits='30'"),
    (dict(quantization="sphere"), "quantization='sphere': expected one of"),
    (dict(coarse_bits=13), "coarse_bits=13: expected a multiple of 3"),
    (dict(coarse_bits=27), "coarse_bits=27"),
    (dict(p=0), "p=0: expected an int in 1..5"),
    (dict(p=6), "p=6"),
    (dict(sah_bins=1), "sah_bins=1: expected an int in 2..64"),
    (dict(sah_bins=65), "sah_bins=65"),
])
def test02_build_rejects_bad_options_naming_them(options, pattern):
    with pytest.raises(ValueError, match=pattern):
        hlbvh.build(V, F, **options)


def test03_build_accepts_numpy_integers_as_options():
    bvh = hlbvh.build(V, F, leaf_size=np.int64(2), p=np.int32(3), morton_bits=np.uint8(60))
    assert bvh.config.leaf_size == 2 and type(bvh.config.leaf_size) is int
    assert bvh.stats.morton_bits == 60


def test04_build_rejects_a_previous_that_is_not_a_bvh():
    with pytest.raises(TypeError, match="previous: expected an hlbvh BVH"):
        hlbvh.build(V, F, previous="last frame")
    with pytest.raises(TypeError):
        hlbvh.build(V, F, None, "lbvh")  # options are keyword-only


@pytest.mark.parametrize("vertices, kind, pattern", [
    (mi.Float([0, 0, np.nan, 1, 0, 0, 0, 1, 0]), ValueError, "non-finite"),
    (mi.Float([0, 0, 0, 1, 0, 0]), ValueError, "index 2 is out of range for 2 vertices"),
    (np.zeros(9, np.float32), TypeError, "vertices: expected a Dr.Jit"),
    (None, TypeError, "vertices: expected a Dr.Jit"),
])
def test05_refit_rejects_bad_vertices_and_keeps_the_tree(vertices, kind, pattern):
    bvh = hlbvh.build(V, F)
    before = np.array(bvh.node_min)
    with pytest.raises(kind, match=pattern):
        bvh.refit(vertices)
    np.testing.assert_array_equal(np.array(bvh.node_min), before)
    assert bvh.intersect(mi.Ray3f(mi.Point3f(0.2, 0.2, 1), mi.Vector3f(0, 0, -1))).is_valid()[0]


# ---------------------------------------------------------------------------------------
# The accelerators
# ---------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def cornell():
    desc = mi.cornell_box()
    desc["sensor"]["film"]["width"] = desc["sensor"]["film"]["height"] = 8
    return desc


@pytest.mark.parametrize("make", [
    lambda s: hlbvh.SceneAccel(s, static="hlbvh", leafsize=2),
    lambda s: hlbvh.make_accel(s, "hlbvh", leafsize=2),
    lambda s: hlbvh.make_accel(s, "native", leafsize=2),
])
def test06_accelerators_reject_unknown_options_naming_them(make, cornell):
    with pytest.raises(ValueError, match="leafsize"):
        make(mi.load_dict(cornell))


@pytest.mark.parametrize("options, pattern", [
    (dict(builder="x"), "builder='x'"),
    (dict(leaf_size=0), "leaf_size=0"),
    (dict(update="sometimes"), "update='sometimes'"),
    (dict(refit_tolerance=0.5), "refit_tolerance=0.5"),
    (dict(refit_tolerance=float("nan")), "refit_tolerance=nan"),
])
def test07_scene_accel_rejects_bad_option_values_naming_them(options, pattern, cornell):
    with pytest.raises(ValueError, match=pattern):
        hlbvh.SceneAccel(mi.load_dict(cornell), static="hlbvh", **options)


@pytest.mark.parametrize("accel", ["embree", None, "HLBVH", 3])
def test08_make_accel_rejects_unknown_accelerators(accel, cornell):
    with pytest.raises(ValueError, match="accel=.*expected one of"):
        hlbvh.make_accel(mi.load_dict(cornell), accel)


@pytest.mark.parametrize("scene", [3, None, "scene.xml"])
def test09_accelerators_reject_what_is_not_a_scene(scene):
    with pytest.raises(TypeError, match="scene"):
        hlbvh.SceneAccel(scene, static="hlbvh")


@pytest.mark.parametrize("query", ["ray_intersect_preliminary", "ray_intersect", "ray_test"])
def test10_queries_reject_what_is_not_a_ray(query, cornell):
    accel = hlbvh.SceneAccel(mi.load_dict(cornell), static="hlbvh")
    with pytest.raises(TypeError, match="ray"):
        getattr(accel, query)(3)


def test11_non_finite_and_empty_meshes_are_named(cornell):
    mesh = mi.Mesh("spiky", 3, 1)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float([0, 0, 0, 1, np.nan, 0, 0, 1, 0])
    params["faces"] = mi.UInt32([0, 1, 2])
    params.update()
    raises_naming(ValueError, "'spiky'.*non-finite",
                  lambda: hlbvh.SceneAccel(mi.load_dict(dict(cornell, spiky=mesh)), static="hlbvh"))
    if empty_mesh_loads():
        raises_naming(ValueError, "'hollow'.*no triangles",
                      lambda: hlbvh.SceneAccel(mi.load_dict(dict(cornell, hollow=mi.Mesh("hollow", 0, 0))),
                                               static="hlbvh"))


def _break_and_restore(cornell, fresh: bool):
    """A scene's mesh given non-finite positions (the update must fail naming it), then
    its good positions back (``fresh``: a new array with the same values; otherwise the
    very array it had before, as a user who kept it would); returns whether a ray at
    the back wall still hits. (``params[key]`` is a handle that the next assignment
    overwrites: keep a copy.)"""
    scene = mi.load_dict(cornell)
    accel = hlbvh.SceneAccel(scene, static="hlbvh")
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.endswith("vertex_positions"))
    good = mi.Float(params[key])  # the same JIT variable as the mesh's buffer
    values = np.array(good)
    bad = values.copy()
    bad[4] = np.inf
    params[key] = mi.Float(bad)
    params.update()
    raises_naming(ValueError, "non-finite", accel.update)
    params[key] = mi.Float(values) if fresh else good
    params.update()
    ray = mi.Ray3f(mi.Point3f(0, 0, 3.9), mi.Vector3f(0, 0, -1))
    assert scene.ray_intersect_preliminary(ray).is_valid()[0]
    return bool(accel.update().ray_intersect_preliminary(ray).is_valid()[0])


def test12_after_a_failed_update_new_good_positions_trace_again(cornell):
    assert _break_and_restore(cornell, fresh=True)


def test12b_after_a_failed_update_the_old_positions_trace_again(cornell):
    """The mesh's very array written back after a failed update (the same JIT
    variable): the mesh had already left the static group, so it must be rebuilt,
    not "kept" in no BVH at all (the Cornell box once dropped from 36 to 6 triangles)."""
    assert _break_and_restore(cornell, fresh=False)


# ---------------------------------------------------------------------------------------
# Integrator properties and scene dicts
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("props, pattern", [
    (dict(accel="embree"), "accel='embree'"),
    (dict(accel="native", leaf_size=99), "leaf_size=99"),  # validated even for native
    (dict(builder=1.5), "builder=1.5"),
    (dict(morton_bits=31), "morton_bits=31"),
    (dict(leaf_size=4.5), "leaf_size=4.5"),
    (dict(quantization="sphere"), "quantization='sphere'"),
    (dict(update="sometimes"), "update='sometimes'"),
    (dict(max_depth=-5), "max_depth=-5"),
    (dict(leafsize=2), "leafsize"),  # Mitsuba: an unreferenced property
])
@pytest.mark.parametrize("kind", ["hlbvh_path", "hlbvh_aov"])
def test13_integrator_properties_are_checked_naming_them(kind, props, pattern, cornell):
    if kind == "hlbvh_aov" and "max_depth" in props:
        pattern = "max_depth"  # not an aov property: Mitsuba names it unreferenced
    raises_naming(Exception, pattern, lambda: mi.load_dict(dict(cornell, integrator=dict(type=kind, **props))))


@pytest.mark.parametrize("kind", ["hlbvh_path", "hlbvh_aov"])
def test14_rendering_a_scene_with_a_bad_mesh_names_it(kind, cornell):
    mesh = mi.Mesh("spiky", 3, 1)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float([0, 0, 0, 1, np.nan, 0, 0, 1, 0])
    params["faces"] = mi.UInt32([0, 1, 2])
    params.update()
    scene = mi.load_dict(dict(cornell, spiky=mesh, integrator=dict(type=kind)))
    raises_naming(ValueError, "'spiky'.*non-finite", lambda: mi.render(scene))
    if empty_mesh_loads():
        scene = mi.load_dict(dict(cornell, hollow=mi.Mesh("hollow", 0, 0), integrator=dict(type=kind)))
        raises_naming(ValueError, "'hollow'.*no triangles", lambda: mi.render(scene))


# ---------------------------------------------------------------------------------------
# Command line
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("argv", [["frobnicate"], ["render"], ["render", "--frames", "x", "nope.xml"]])
def test15_command_line_mistakes_exit_non_zero_without_a_traceback(argv):
    result = subprocess.run([sys.executable, "-m", "hlbvh.cli", *argv], capture_output=True,
                            text=True, timeout=300)
    assert result.returncode != 0
    assert "Traceback" not in result.stderr, result.stderr
    assert result.stderr.strip()
