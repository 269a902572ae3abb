"""Inputs past a limit are one line and exit status 2: a path name longer than the file
system takes (``--out`` or the scene, render and compare), ``sweep --spp-curve`` past
what a frame can hold, ``bench build --sizes`` past what a Dr.Jit array holds, a frame
too large for the scene's own resolution, said without blaming a flag the user did not
pass; integers past 32 bits (``--spp``, ``--max-depth``, ``--triangles``, an
integrator's depths, refused as Mitsuba's ``path`` refuses them), a machine's memory
running out, and a flag given as a scene option."""

import pytest

from cli_helpers import run_cli

LONG = "n" * 300  # one path name past the 255 bytes Linux file systems take
SMALL = ["--triangles", "200", "--frames", "0:1", "--resolution", "8", "--spp", "1",
         "--quiet"]


def _too_long(path) -> str:
    text = str(path)
    return (f"path {text[:48] + '...' + text[-24:]!r} is too long for the file system "
            f"({len(text)} bytes, its longest name {len(path.name)} bytes; a name may hold "
            f"at most 255 bytes on most file systems)")


@pytest.mark.parametrize("command", ["render", "compare"])
def test_an_out_name_too_long_is_one_line(tmp_path, capsys, command):
    out = tmp_path / LONG
    status, _, err = run_cli(capsys, command, "cloth", *SMALL, "--out", out)
    assert status == 2 and err == [f"hlbvh {command}: {_too_long(out)}"], err


@pytest.mark.parametrize("command", ["render", "compare"])
@pytest.mark.parametrize("suffix", [".usda", ".xml"])
def test_a_scene_name_too_long_is_one_line(tmp_path, capsys, command, suffix):
    pytest.importorskip("pxr") if suffix == ".usda" else None
    scene = tmp_path / f"{LONG}{suffix}"
    extra = ["--frames-dir", str(tmp_path)] if suffix == ".xml" else []
    status, _, err = run_cli(capsys, command, scene, *extra, "--quiet", "--out",
                             tmp_path / "out")
    assert status == 2 and err == [f"hlbvh {command}: {_too_long(scene)}"], err


def test_an_spp_curve_past_a_frame_s_samples_is_one_line(tmp_path, capsys):
    status, _, err = run_cli(capsys, "sweep", "cloth", *SMALL[:2], "--resolution", "8",
                             "--spp", "1", "--spp-curve", "1,100000000", "--quiet",
                             "--out", tmp_path / "sweep")
    assert status == 2 and err == [
        "hlbvh sweep: a frame of 8x8 pixels at 100000000 spp: 6400000000 samples, more "
        "than the 4294967295 a Dr.Jit array holds; lower it with --resolution or "
        "--spp-curve"], err
    assert not list((tmp_path / "sweep").glob("*.exr"))


def test_bench_sizes_past_a_dr_jit_array_is_one_line(capsys):
    status, _, err = run_cli(capsys, "bench", "build", "--sizes", "1000,10000000000")
    assert status == 2 and err == [
        "hlbvh bench: --sizes '10000000000': expected an integer in 1..1431655765"], err


def test_a_render_settings_resolution_too_large_names_the_frame_not_a_flag(tmp_path,
                                                                           capsys):
    """A stage whose render settings ask for 100000x100000 pixels: the line names the
    frame's size, not ``--resolution``, which the user never passed."""
    pytest.importorskip("pxr")
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdRender
    path = tmp_path / "huge.usda"
    stage = Usd.Stage.CreateNew(str(path))
    mesh = UsdGeom.Mesh.Define(stage, "/Q")
    mesh.CreatePointsAttr([(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)])
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    mesh.CreateSubdivisionSchemeAttr("none")
    UsdGeom.Camera.Define(stage, "/Cam").AddTranslateOp().Set(Gf.Vec3d(0.5, 0.5, 4))
    UsdLux.DomeLight.Define(stage, "/Sky")
    settings = UsdRender.Settings.Define(stage, "/Render/Settings")
    settings.CreateCameraRel().SetTargets([Sdf.Path("/Cam")])
    settings.CreateResolutionAttr(Gf.Vec2i(100000, 100000))
    stage.SetMetadata("renderSettingsPrimPath", "/Render/Settings")
    stage.GetRootLayer().Save()
    status, _, err = run_cli(capsys, "render", path, "--spp", "1", "--quiet", "--out",
                             tmp_path / "out")
    assert status == 2 and err == [
        "hlbvh render: a frame of 100000x100000 pixels at 1 spp: 10000000000 samples, more "
        "than the 4294967295 a Dr.Jit array holds; lower it with --resolution or --spp"], err


@pytest.mark.parametrize("prop, said", [
    ('<string name="accel" value="bogus"/>',
     "ValueError: integrator property accel='bogus': expected one of ('hlbvh', 'native')"),
    ('<string name="bogus_property" value="1"/>',
     'Found 1 unreferenced property in integrator plugin of type "hlbvh_path": - string '
     '"bogus_property": "1"'),
])
def test_a_bad_integrator_property_in_a_scene_file_says_its_cause(tmp_path, capsys, prop,
                                                                  said):
    """Through ``hlbvh render``: the cause ends the line (it was cut off at Mitsuba's
    "Traceback (most recent call last):")."""
    from cli_helpers import write_twist_scene
    xml, frames = write_twist_scene(tmp_path)
    text = xml.read_text().replace('<integrator type="path">',
                                   f'<integrator type="hlbvh_path">{prop}')
    xml.write_text(text)
    status, _, err = run_cli(capsys, "render", xml, "--frames-dir", frames, "--quiet",
                             "--out", tmp_path / "out")
    assert status == 2 and len(err) == 1 and err[0].startswith(
        f"hlbvh render: scene {str(xml)!r}: Mitsuba cannot load it: "), err
    assert err[0].endswith(said) and "Traceback" not in err[0], err


@pytest.mark.parametrize("flag, value, expected", [
    ("--spp", "4294967296", "1..4294967295"),  # Mitsuba's sampler counts in 32 bits
    ("--max-depth", "4294967296", "-1..2147483647"),  # Mitsuba's integer properties
    ("--max-depth", "2147483648", "-1..2147483647"),
    ("--triangles", "10000000000", "1..1431655765"),  # bench --sizes' bound
])
def test01_integers_past_32_bits_are_one_line_naming_the_flag(tmp_path, capsys, flag, value,
                                                              expected):
    """Each ended in a traceback deep in Mitsuba's loader, the integrator or numpy."""
    status, _, err = run_cli(capsys, "render", "cloth", "--frames", "0:1", "--resolution",
                             "8", "--quiet", flag, value, "--out", tmp_path / "out")
    assert status == 2 and err == [
        f"hlbvh render: {flag} {value!r}: expected an integer in {expected}"], err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("props", [
    {"max_depth": 2**31}, {"max_depth": 2**32}, {"max_depth": 2**32 - 1},
    {"rr_depth": 2**40}, {"rr_depth": 2**31}, {"max_depth": -2}, {"rr_depth": 0},
    {"max_depth": 2.5}, {"max_depth": True},
])
@pytest.mark.parametrize("kind", ["hlbvh_path", "hlbvh_volpath"])
def test02_depths_mitsuba_s_path_refuses_are_refused_naming_them(kind, props):
    """Mitsuba's ``path`` refuses each (its integer properties are 32-bit signed); ours
    took max_depth 2^31 and 2^32 and rr_depth 2^40, and traced them as other depths."""
    import mitsuba as mi
    with pytest.raises(RuntimeError):
        mi.load_dict({"type": "path", **props})
    (name, value), = props.items()
    with pytest.raises(RuntimeError, match=f"ValueError: {name}={value!r}: expected "):
        mi.load_dict({"type": kind, **props})


@pytest.mark.parametrize("kind", ["path", "hlbvh_path", "hlbvh_volpath"])
def test03_the_largest_depths_mitsuba_s_path_takes_load(kind):
    import mitsuba as mi
    mi.load_dict({"type": kind, "max_depth": 2**31 - 1, "rr_depth": 2**31 - 1})


def test04_a_scene_file_s_depth_past_32_bits_is_one_line(tmp_path, capsys):
    """hlbvh_path with max_depth 2^31 in a scene file: rendered (as another depth)."""
    from cli_helpers import write_twist_scene
    xml, frames = write_twist_scene(tmp_path)
    xml.write_text(xml.read_text().replace(
        '<integrator type="path"><integer name="max_depth" value="8"/>',
        '<integrator type="hlbvh_path"><integer name="max_depth" value="2147483648"/>'))
    status, _, err = run_cli(capsys, "render", xml, "--frames-dir", frames, "--quiet",
                             "--out", tmp_path / "out")
    assert status == 2 and len(err) == 1 and "max_depth=2147483648" in err[0], err
    assert "2147483647" in err[0] and "Traceback" not in err[0], err


def test05_running_out_of_memory_is_one_line(tmp_path, capsys, monkeypatch):
    """A scene too large for the machine's memory (numpy's allocation refused, as for
    ``--triangles 1431655765`` on a machine of 12 GB): one line, exit status 2."""
    from hlbvh.cli import render

    def too_large(spec):
        raise MemoryError("Unable to allocate 5.33 GiB for an array with shape "
                          "(32768, 21847) and data type float64")

    monkeypatch.setattr(render, "open_animation", too_large)
    status, _, err = run_cli(capsys, "render", "cloth", "--quiet", "--out", tmp_path / "out")
    assert status == 2 and err == [
        "hlbvh render: out of memory (Unable to allocate 5.33 GiB for an array with shape "
        "(32768, 21847) and data type float64); ask for less (--triangles, --resolution, "
        "--spp) or use a machine with more memory"], err


@pytest.mark.parametrize("scene, said", [
    ("cloth:frames=4", "'frames=4' is not a scene option; give it as --frames"),
    ("cloth:triangles=9", "'triangles=9' is not a scene option; give it as --triangles"),
    ("cloth:bogus=1", "'bogus=1' is not an option of 'cloth'; 'cloth' takes no options"),
    ("flock:frames=4", "'frames=4' is not a scene option; give it as --frames"),
])
def test06_a_flag_given_as_a_scene_option_names_the_flag(tmp_path, capsys, scene, said):
    """``cloth:frames=4`` ended "...key one of none"."""
    status, _, err = run_cli(capsys, "render", scene, "--quiet", "--out", tmp_path / "out")
    assert status == 2 and err == [f"hlbvh render: scene {scene!r}: {said}"], err


@pytest.mark.parametrize("argv, said", [
    (["--resolution", "4294967296"],  # Mitsuba's film refused it in a traceback
     "--resolution '4294967296': expected W or WxH, integers in 1..4294967295"),
    (["--frames", "99999999999999999999999"],  # the line said "use --seed 0 or less"
     "--frames: frame 99999999999999999999998 is past 4294967295, the last frame a seed "
     "numbers (frame i renders with seed --seed + i; seeds are 32-bit)"),
])
def test07_a_film_side_or_a_frame_past_32_bits_is_one_line(tmp_path, capsys, argv, said):
    status, _, err = run_cli(capsys, "render", "cloth", "--triangles", "200", "--spp", "1",
                             "--quiet", *argv, "--out", tmp_path / "out")
    assert status == 2 and err == [f"hlbvh render: {said}"], err
    assert not list((tmp_path / "out").glob("frame_*"))

