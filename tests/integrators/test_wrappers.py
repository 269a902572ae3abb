"""Mitsuba's wrapper integrators (``moment``, ``aov``, ``stokes``) around ours: Mitsuba's
C++ render calls our ``sample()`` directly, so the nested integrator's rays go through
our intersector, and the wrapper's outputs equal those of the wrapper around the C++
integrator it mirrors; a render through a wrapper follows the meshes that moved."""

import subprocess
import sys

import hlbvh
import mitsuba as mi
import numpy as np
import pytest

from folders import FOLDERS
from test_accel import cornell_box
from test_integrators import render

OURS = {"path": dict(max_depth=3), "direct": dict(), "volpath": dict(max_depth=3)}
WRAPPERS = {"moment": dict(), "aov": dict(aovs="dd.y:depth,nn:sh_normal")}


@pytest.mark.parametrize("wrapper", WRAPPERS)
@pytest.mark.parametrize("inner", OURS)
@pytest.mark.parametrize("accel", ["native", "hlbvh"])
def test01_wrapper_around_ours_equals_wrapper_around_cpp(wrapper, inner, accel):
    """Every channel of the wrapper's output (moment: the colour and its second
    moment; aov: the colour and its own AOVs) equals the wrapper around Mitsuba's
    integrator. The Cornell box is still: ``accel="hlbvh"`` hands it to Mitsuba's
    accelerator (static="native"), so both are bit-identical."""
    scene = mi.load_dict(cornell_box(res=16, spp=2))
    options = OURS[inner]
    reference = render(scene, dict(type=wrapper, **WRAPPERS[wrapper],
                                   inner=dict(type=inner, **options)), seed=1)
    integrator = mi.load_dict(dict(type=wrapper, **WRAPPERS[wrapper],
                                   inner=dict(type=f"hlbvh_{inner}", accel=accel, **options)))
    ours = np.array(mi.render(scene, integrator=integrator, seed=1))
    assert reference.shape[-1] > 3 and reference.mean() > 0.01
    np.testing.assert_array_equal(ours, reference)


def test02_a_render_through_a_wrapper_follows_moved_meshes():
    """After a mesh moved (hlbvh.traverse's update, which leaves Mitsuba's own
    accelerator alone), a render through ``moment`` updates our intersector from the
    nested integrator's sample() and equals a fresh integrator's render of the moved
    scene."""
    desc = cornell_box(res=16, spp=2)
    desc["integrator"] = dict(type="moment", inner=dict(type="hlbvh_path", max_depth=3,
                                                        static="hlbvh"))
    scene = mi.load_dict(desc)
    before = np.array(mi.render(scene, seed=1))
    params = hlbvh.traverse(scene)
    key = next(k for k in params.keys() if k.endswith("vertex_positions"))
    params[key] = params[key] * 0.9
    params.update()
    after = np.array(mi.render(scene, seed=1))
    fresh = render(scene, dict(type="moment", inner=dict(type="hlbvh_path", max_depth=3,
                                                         static="hlbvh")), seed=1)
    assert not np.array_equal(before, after)
    np.testing.assert_array_equal(after, fresh)


STOKES_SCRIPT = """
import sys
sys.path[:0] = {tests!r}
import hlbvh, mitsuba as mi, numpy as np
backend = mi.variant().split("_")[0]
mi.set_variant(backend + "_ad_spectral_polarized")
hlbvh.register()
from test_accel import cornell_box
scene = mi.load_dict(cornell_box(res=8, spp=2))
images = []
for inner in (dict(type="path", max_depth=3), dict(type="hlbvh_path", accel="hlbvh", max_depth=3),
              dict(type="direct"), dict(type="hlbvh_direct", accel="hlbvh")):
    images.append(np.array(mi.render(scene, integrator=mi.load_dict(dict(type="stokes", inner=inner)),
                                     seed=1)))
assert images[0].shape[-1] > 3 and images[0].mean() > 0.01
assert np.array_equal(images[0], images[1]) and np.array_equal(images[2], images[3])
print("ok")
"""


def test03_stokes_around_ours_in_a_polarized_variant():
    """In a fresh process (the variant is global): ``stokes`` around hlbvh_path and
    hlbvh_direct equals it around path and direct, every Stokes channel."""
    tests = FOLDERS
    done = subprocess.run([sys.executable, "-c", STOKES_SCRIPT.format(tests=tests)],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0 and done.stdout.strip().endswith("ok"), done.stderr[-3000:]


# ---- hlbvh render of a scene whose integrator is a wrapper ----------------------------

PATH_INTEGRATOR = '<integrator type="path"><integer name="max_depth" value="8"/></integrator>'


def _wrapped_twist_scene(root, wrapper: str) -> tuple:
    """The command-line tests' twist scene with its ``path`` inside ``wrapper`` (XML)."""
    from cli_helpers import write_twist_scene
    scene, frames = write_twist_scene(root)
    scene.write_text(scene.read_text().replace(PATH_INTEGRATOR, wrapper))
    return scene, frames


def _channels(path) -> dict:
    import OpenImageIO as oiio
    image = oiio.ImageInput.open(str(path))
    names, pixels = image.spec().channelnames, image.read_image(format="float")
    image.close()
    return dict(zip(names, np.moveaxis(pixels, 2, 0)))


def test04_hlbvh_render_keeps_a_moment_wrapper_around_the_path_it_runs_as_ours(
        tmp_path, capsys):
    from cli_helpers import read_stats, run_cli
    scene, frames = _wrapped_twist_scene(
        tmp_path, f'<integrator type="moment">{PATH_INTEGRATOR}</integrator>')
    images = {}
    for accel in ("hlbvh", "native"):
        status, _, err = run_cli(capsys, "render", scene, "--frames-dir", frames,
                                 "--accel", accel, "--out", tmp_path / accel)
        assert status == 0, err
        assert "the scene's 'moment' wraps it, its outputs kept" in err[0]
        images[accel] = _channels(tmp_path / accel / "frame_0002.exr")
        document, rows = read_stats(tmp_path / accel)
        assert document["settings"]["wrapper"] == {"type": "moment"}
    ours = images["hlbvh"]
    assert sorted(ours) == sorted(["R", "G", "B"] + [f"{m}nested.{c}" for m in ("", "m2_")
                                                     for c in "XYZ"])
    assert ours["m2_nested.X"].max() > 0  # the second moment was written
    for name, values in ours.items():  # a frame after motion, as native renders it
        np.testing.assert_allclose(values, images["native"][name], atol=1e-4)


def test05_hlbvh_render_refuses_a_wrapper_of_two_integrators_in_one_line(tmp_path, capsys):
    from cli_helpers import run_cli
    scene, frames = _wrapped_twist_scene(
        tmp_path, f'<integrator type="moment">{PATH_INTEGRATOR}{PATH_INTEGRATOR}</integrator>')
    status, _, err = run_cli(capsys, "render", scene, "--frames-dir", frames,
                             "--out", tmp_path / "out")
    assert status == 2 and len(err) == 1
    assert "its integrator 'moment' holds 2 integrators" in err[0]


def test06_mitsubas_aov_is_not_taken_as_a_wrapper_and_a_bad_wrapper_is_named():
    from hlbvh.render.settings import RenderSettings
    with pytest.raises(ValueError, match="wrapper=.*'aov'"):
        RenderSettings(wrapper={"type": "aov"})
    settings = RenderSettings(wrapper={"type": "moment"})
    assert settings.integrator_dict()["type"] == "moment"
    assert settings.integrator_dict()["nested"]["type"] == "hlbvh_path"
    assert "wrapper" not in RenderSettings().as_dict()  # older folders still resume


@pytest.mark.parametrize("wrapper", WRAPPERS)
@pytest.mark.parametrize("moving_accel", ["scene", "auto"])
def test07_a_wrapper_renders_when_the_whole_scene_traces_the_moving_meshes(
        wrapper, moving_accel):
    """With the whole scene chosen (forced, or by ``auto``), the nested integrator's
    ``sample()`` traces the scene's own queries, as its own render does: a render through
    the wrapper of a moving mesh equals the wrapper around ``accel="native"``, frame by
    frame (it raised "query the scene itself" before): bit for bit through the whole
    scene; under ``auto``, whatever it chose, within float rounding (our traversal and
    Mitsuba's part on a few paths' last bits)."""
    def scene(inner):
        desc = cornell_box(res=16, spp=2)
        desc["integrator"] = dict(type=wrapper, **WRAPPERS[wrapper], inner=inner)
        return mi.load_dict(desc)

    inner = mi.load_dict(dict(type="hlbvh_path", max_depth=3, moving_accel=moving_accel))
    ours = scene(inner)
    reference = scene(dict(type="hlbvh_path", max_depth=3, accel="native"))
    params, ref_params = hlbvh.traverse(ours), mi.traverse(reference)
    key, ref_key = (next(k for k in p.keys() if k.endswith("vertex_positions"))
                    for p in (params, ref_params))
    still = mi.Float(ref_params[ref_key])
    for frame in range(1, 3):
        moved = still * (1.0 - 0.05 * frame)
        params[key], ref_params[ref_key] = moved, mi.Float(moved)
        params.update()
        ref_params.update()
        image, expected = (np.array(mi.render(ours, seed=frame)),
                           np.array(mi.render(reference, seed=frame)))
        if moving_accel == "scene":
            np.testing.assert_array_equal(image, expected)
        else:
            np.testing.assert_allclose(image, expected, rtol=1e-4, atol=1e-7)
    if moving_accel == "scene":
        assert inner.scene_accel.moving_structure == "scene"
