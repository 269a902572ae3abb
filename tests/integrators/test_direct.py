"""``hlbvh_direct`` against Mitsuba's C++ ``direct``: bit-identical with
``accel="native"`` over its properties and emitter types, close with ``accel="hlbvh"``;
bad properties."""

import mitsuba as mi
import numpy as np
import pytest

from test_accel import analytic_scene, cornell_box
from test_integrators import _hlbvh_traces_everything, render

SCENES = {"cornell_box": cornell_box, "analytic": analytic_scene}


@pytest.mark.parametrize("scene_name", SCENES)
@pytest.mark.parametrize("options", [
    dict(),
    dict(hide_emitters=True),
    dict(emitter_samples=3, bsdf_samples=2),
    dict(shading_samples=2),
    dict(emitter_samples=0),
    dict(bsdf_samples=0),
])
def test01_direct_native_bit_identical_to_cpp_direct(scene_name, options):
    """The analytic scene has an area, a point and an environment emitter and delta
    BSDFs (dielectric, conductor); the Cornell box one area light over meshes."""
    scene = mi.load_dict(SCENES[scene_name]())
    reference = render(scene, dict(type="direct", **options), seed=7)
    ours = render(scene, dict(type="hlbvh_direct", accel="native", **options), seed=7)
    assert reference.mean() > 0.01
    np.testing.assert_array_equal(ours, reference)


@pytest.mark.parametrize("scene_name", SCENES)
@pytest.mark.parametrize("options", [dict(), dict(hide_emitters=True, emitter_samples=2)])
def test02_direct_hlbvh_close_to_native(scene_name, options):
    """Every shape through hlbvh's traversal: the same rays, hits that differ in the
    last bits (test_integrators' test11 tolerances: 5e-4 + 1e-4 relative a pixel, one
    pixel may branch)."""
    scene = mi.load_dict(SCENES[scene_name]())
    native = render(scene, dict(type="hlbvh_direct", accel="native", **options), seed=5)
    ours = render(scene, dict(type="hlbvh_direct", accel="hlbvh", **options,
                              **_hlbvh_traces_everything()), seed=5)
    diff = np.abs(ours - native)
    outside = (diff > 5e-4 + 1e-4 * np.abs(native)).any(axis=-1)
    assert outside.sum() <= 1, f"{outside.sum()} pixels beyond tolerance, max {diff.max()}"
    assert diff.mean() < 1e-6
    assert native.mean() > 0.01


@pytest.mark.parametrize("props, message", [
    (dict(shading_samples=2, bsdf_samples=1), "shading_samples"),
    (dict(emitter_samples=0, bsdf_samples=0), "at least one sample"),
    (dict(emitter_samples=-1), "emitter_samples=-1"),
    (dict(accel="embree"), "accel='embree'"),
])
def test03_bad_properties_raise_naming_them(props, message):
    with pytest.raises(Exception, match=message):
        mi.load_dict(dict(type="hlbvh_direct", **props))


def test04_direct_from_xml_scene():
    """The integrator of an XML scene, its properties read from there."""
    scene = mi.load_string("""
<scene version="3.0.0">
    <integrator type="hlbvh_direct">
        <string name="accel" value="native"/>
        <integer name="emitter_samples" value="2"/>
    </integrator>
    <sensor type="perspective">
        <transform name="to_world"><lookat origin="0, 1, 5" target="0, 0, 0" up="0, 1, 0"/></transform>
        <sampler type="independent"><integer name="sample_count" value="2"/></sampler>
        <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="16"/>
            <rfilter type="box"/></film>
    </sensor>
    <shape type="rectangle"><transform name="to_world"><rotate x="1" angle="-90"/><scale value="4"/></transform></shape>
    <shape type="sphere"><point name="center" x="0" y="3" z="0"/><float name="radius" value="0.5"/>
        <emitter type="area"><rgb name="radiance" value="10"/></emitter></shape>
</scene>""")
    assert "emitter_samples=2" in str(scene.integrator())
    ours = np.array(mi.render(scene, seed=1))
    reference = render(scene, dict(type="direct", emitter_samples=2), seed=1)
    assert reference.mean() > 0.01
    np.testing.assert_array_equal(ours, reference)
