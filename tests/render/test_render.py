"""``hlbvh render``: frames and statistics written whole, hlbvh frames equal to native
ones within the plugin's tolerance, resuming, user errors, mesh sequences; and the
frame benchmark's rows."""

import math
import pathlib
import subprocess
import sys

import numpy as np
import OpenImageIO as oiio
import pytest

from cli_helpers import read_stats, run_cli, write_twist_scene
from hlbvh import cli
from hlbvh.comparison.bench import frame as bench_frame
from hlbvh.integrators.aov import CHANNELS
from hlbvh.render import images
from hlbvh.render.frame import STATS_FIELDS



def tiny(spp=4):
    """Options of a small, quick render."""
    return ["--triangles", "2000", "--resolution", "32", "--spp", str(spp), "--quiet"]


def render(capsys, *argv):
    """``hlbvh render argv`` in this process: (exit status, stdout, stderr lines)."""
    return run_cli(capsys, "render", *argv)


stats = read_stats


def frame_files(directory, i):
    return directory / f"frame_{i:04d}.exr", directory / f"frame_{i:04d}.png"


def mtimes(directory, frames):
    return {p.name: p.stat().st_mtime_ns for i in frames for p in frame_files(directory, i)}


def assert_close_to_native(ours, native):
    """The tolerance of tests/integrators/test_integrators.py::test11 (measured there: same
    seed and box filter, hits differ only in the last bits): 5e-4 absolute + 1e-4 relative
    per pixel, one pixel may exceed it, mean difference below 1e-6, and many pixels
    bit-identical."""
    diff = np.abs(ours - native)
    outside = (diff > 5e-4 + 1e-4 * np.abs(native)).any(axis=-1)
    assert outside.sum() <= 1, f"{outside.sum()} pixels beyond tolerance, max {diff.max()}"
    assert diff.mean() < 1e-6
    assert (diff == 0).all(axis=-1).mean() > 0.05


@pytest.fixture(scope="module")
def both_accels(tmp_path_factory):
    """Frames 0..2 of a small cloth, rendered by the CLI with each accelerator."""
    root = tmp_path_factory.mktemp("render")
    results = {}
    for accel in ("hlbvh", "native"):
        status = cli.main(["render", "cloth", "--frames", "0:3", "--accel", accel,
                           "--out", str(root / accel), *tiny()])
        results[accel] = (status, root / accel)
    return results


@pytest.mark.parametrize("accel", ["hlbvh", "native"])
def test01_frames_and_statistics_are_written_whole(both_accels, accel):
    status, directory = both_accels[accel]
    assert status == 0
    pixels = []
    for i in range(3):
        exr, png = frame_files(directory, i)
        image = images.read_exr(exr, ["R", "G", "B"])
        assert image.shape == (32, 32, 3) and np.isfinite(image).all() and image.mean() > 0.01
        source = oiio.ImageInput.open(str(png))
        spec = source.spec()
        source.close()
        assert (spec.width, spec.height, spec.nchannels, spec.format) == (32, 32, 3, oiio.UINT8)
        pixels.append(image)
    assert not np.array_equal(pixels[0], pixels[2])  # the cloth moved
    assert not list(directory.glob(".*.tmp"))

    document, table = stats(directory)
    rows = document["frames"]
    assert [row["frame"] for row in rows] == [0, 1, 2]
    assert document["settings"]["accel"] == accel and document["settings"]["spp"] == 4
    assert document["settings"]["scene"] == "cloth"
    for row in rows:
        assert set(row) == set(STATS_FIELDS) and row["accel"] == accel
        assert row["triangles"] >= 2000 and row["seed"] == row["frame"]
        for key in ("geometry_ms", "mitsuba_update_ms", "build_ms", "render_ms"):
            assert math.isfinite(row[key]) and row[key] >= 0, key
        if accel == "hlbvh":
            # what traced the moving cloth (chosen by cost); our BVH's SAH cost when ours
            assert row["moving_accel"] in ("hlbvh", "native", "scene")
            if row["moving_accel"] == "hlbvh":
                assert math.isfinite(row["sah_cost"]) and row["sah_cost"] >= 1
            else:
                assert row["sah_cost"] is None
        else:
            assert row["sah_cost"] is None and row["decision"] == "native"
            assert row["build_ms"] == row["mitsuba_update_ms"] and row["moving_accel"] == ""
    if accel == "hlbvh":
        assert rows[0]["decision"] == "build"
        assert {row["decision"] for row in rows[1:]} <= {"rebuild", "refit", "native"}
    # The CSV holds the same rows, in the documented columns.
    assert list(table[0]) == list(STATS_FIELDS)
    assert [int(r["frame"]) for r in table] == [0, 1, 2]
    assert [float(r["render_ms"]) for r in table] == pytest.approx(
        [row["render_ms"] for row in rows])


def test02_hlbvh_frames_agree_with_native_frame_by_frame(both_accels):
    for i in range(3):
        ours = images.read_exr(frame_files(both_accels["hlbvh"][1], i)[0], ["R", "G", "B"])
        native = images.read_exr(frame_files(both_accels["native"][1], i)[0], ["R", "G", "B"])
        assert_close_to_native(ours, native)


def test03_resume_renders_only_incomplete_frames_and_cleans_temporary_files(tmp_path, capsys):
    out = tmp_path / "out"
    status, summary, _ = render(capsys, "cloth", "--frames", "0:2", "--accel", "native",
                                "--out", out, *tiny())
    assert status == 0 and "2 rendered, 0 already complete" in summary
    before, rows_before = mtimes(out, [0, 1]), stats(out)[0]["frames"]

    # A crash left a half-written temporary file, and frame 3 got an EXR but no PNG
    # nor statistics row.
    stale = out / ".frame_0002.exr.deadbeef.tmp"
    stale.write_bytes(b"\x76\x2f\x31\x01 half an EXR")
    frame_files(out, 3)[0].write_bytes(b"not an image")

    status, summary, _ = render(capsys, "cloth", "--frames", "0:4", "--accel", "native",
                                "--out", out, *tiny())
    assert status == 0 and "2 rendered, 2 already complete" in summary
    assert mtimes(out, [0, 1]) == before
    rows = stats(out)[0]["frames"]
    assert rows[:2] == rows_before and [row["frame"] for row in rows] == [0, 1, 2, 3]
    for i in (2, 3):
        assert np.isfinite(images.read_exr(frame_files(out, i)[0])).all()
    assert not stale.exists() and not list(out.glob(".*.tmp"))

    # A frame is complete only with its PNG too.
    frame_files(out, 1)[1].unlink()
    before = mtimes(out, [0, 2, 3])
    status, summary, _ = render(capsys, "cloth", "--frames", "0:4", "--accel", "native",
                                "--out", out, *tiny())
    assert status == 0 and "1 rendered, 3 already complete" in summary
    assert frame_files(out, 1)[1].is_file() and mtimes(out, [0, 2, 3]) == before

    # Other settings into the same directory: refused, nothing touched.
    before = mtimes(out, range(4))
    status, _, err = render(capsys, "cloth", "--frames", "0:5", "--accel", "native",
                            "--out", out, *tiny(spp=2))
    assert status == 2 and len(err) == 1 and "other settings" in err[0] and "spp" in err[0]
    assert mtimes(out, range(4)) == before and not frame_files(out, 4)[0].exists()


@pytest.fixture
def sequence(tmp_path):
    """A scene file with a twisting bar (PLY) over a floor, and 4 frames of the bar
    written by Mitsuba."""
    write_twist_scene(tmp_path, triangles=800, frames=4)
    return tmp_path


def test04_mesh_sequence_renders_and_bad_frame_files_are_named(sequence, capsys):
    out = sequence / "out"
    argv = [sequence / "scene.xml", "--frames-dir", sequence / "frames", "--out", out,
            "--spp", "2", "--quiet"]
    status, summary, _ = render(capsys, *argv, "--frames", "0:2")
    assert status == 0 and "2 rendered" in summary
    rows = stats(out)[0]["frames"]
    assert [row["frame"] for row in rows] == [0, 1] and rows[0]["triangles"] >= 800
    image = images.read_exr(frame_files(out, 1)[0])
    assert image.shape == (16, 24, 3) and np.isfinite(image).all()
    before = mtimes(out, [0, 1])

    # A corrupt file: frames before it are rendered, it is named with its frame.
    frames = sequence / "frames" / "bar"
    (frames / "frame_0004.ply").write_bytes(b"ply\nformat ascii 1.0\nelement vertex 3\nend_header\n1 2\n")
    status, _, err = render(capsys, *argv, "--frames", "0:4")
    assert status == 2 and len(err) == 1
    assert "frame 3 of shape 'bar'" in err[0] and "frame_0004.ply" in err[0]
    assert mtimes(out, [0, 1]) == before
    assert [row["frame"] for row in stats(out)[0]["frames"]] == [0, 1, 2]
    assert frame_files(out, 2)[0].is_file() and not frame_files(out, 3)[0].exists()

    # A missing file: named with its frame before anything is rendered.
    before = mtimes(out, [0, 1, 2])
    (frames / "frame_0002.ply").unlink()
    status, _, err = render(capsys, *argv, "--frames", "0:4")
    assert status == 2 and len(err) == 1
    assert "frame 1 of shape 'bar'" in err[0] and "frame_0002.ply" in err[0]
    assert mtimes(out, [0, 1, 2]) == before


@pytest.mark.parametrize("argv, message", [
    (["nosuchscene"], "not a procedural scene"),
    (["cloth", "--frames", "5:3"], "range is empty"),
    (["cloth", "--frames", "1-4"], "expected A:B"),
    (["cloth", "--spp", "0"], "--spp"),
    (["cloth", "--resolution", "32x0"], "--resolution"),
    (["cloth", "--accel", "embree"], "--accel"),
    (["cloth", "--leaf-size", "99"], "leaf_size=99"),
    (["cloth", "--integrator", "ptracer"], "--integrator"),
    (["cloth", "--frames-dir", "frames"], "--frames-dir is for XML scenes"),
    (["{xml}"], "needs --frames-dir"),
    (["{xml}", "--frames-dir", "{tmp}/nowhere"], "no such directory"),
    (["{xml}", "--frames-dir", "{frames}", "--frames", "2:9"], "has frames 0:4"),
    (["{xml}", "--frames-dir", "{frames}", "--triangles", "5"], "--triangles"),
])
def test05_user_errors_exit_2_with_one_line(sequence, capsys, argv, message):
    fill = dict(xml=sequence / "scene.xml", frames=sequence / "frames", tmp=sequence)
    argv = [a.format(**fill) for a in argv]
    status, out, err = render(capsys, *argv, "--out", sequence / "out", "--quiet")
    assert status == 2
    assert len(err) == 1 and err[0].startswith("hlbvh render:") and message in err[0], err
    assert not (sequence / "out").exists()


def test06_console_script_exits_2_without_traceback():
    script = pathlib.Path(sys.executable).with_name("hlbvh")
    done = subprocess.run([str(script), "render", "cloth", "--frames", "x"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 2
    assert done.stderr.strip() == ("hlbvh render: --frames 'x': expected A:B (frames A .. "
                                   "B-1), A:B:STEP (every STEP-th of them) or a count N")


def test07_aov_frames_hold_named_channels_equal_to_native(tmp_path, capsys):
    for accel in ("hlbvh", "native"):
        status, _, _ = render(capsys, "fracture", "--frames", "4:5", "--integrator", "aov",
                              "--accel", accel, "--out", tmp_path / accel, *tiny(spp=1))
        assert status == 0
    names = list(CHANNELS)
    ours = images.read_exr(frame_files(tmp_path / "hlbvh", 4)[0], names)
    native = images.read_exr(frame_files(tmp_path / "native", 4)[0], names)
    hit = native[..., 0] > 0
    assert hit.any() and (~hit).any()
    same = (ours[..., 1] == native[..., 1]) & (ours[..., 2] == native[..., 2])
    assert same.mean() >= 1 - 2 / same.size  # edge ties may pick a neighbour
    np.testing.assert_allclose(ours[..., 0][same], native[..., 0][same], rtol=1e-5)
    assert not frame_files(tmp_path / "native", 0)[0].exists()


def test08_frame_benchmark_rows_have_the_promised_keys():
    rows = bench_frame.run(repeats=1, sizes=(1500,), resolution=16, scenes=("fracture",),
                           spps=(1, 2), drift_frames=3)
    assert [(r["scene"], r["spp"]) for r in rows] == [("fracture", 1), ("fracture", 2)]
    for r in rows:
        assert set(r) == set(bench_frame.ROW_KEYS)
        for key in bench_frame.ROW_KEYS:
            if key == "mitsuba_update_ms":  # 0: hlbvh frames skip Mitsuba's rebuild
                assert math.isfinite(r[key]) and r[key] >= 0, key
            elif key.endswith("_ms") or key.startswith("sah_"):
                assert math.isfinite(r[key]) and r[key] > 0, key
        assert r["native_over_hlbvh"] == pytest.approx(
            r["native_frame_min_ms"] / r["hlbvh_frame_min_ms"])
        # One warm frame (repeats=1): its time is that frame's build (or update) plus
        # its render, for each accelerator.
        assert r["hlbvh_frame_min_ms"] == pytest.approx(
            r["hlbvh_build_ms"] + r["hlbvh_render_ms"])
        assert r["native_frame_min_ms"] == pytest.approx(
            r["native_update_ms"] + r["native_render_ms"])
        assert r["crossover_spp"] is None or r["crossover_spp"] >= 0
        assert r["triangles"] >= 1500 and r["drift_frames"] == 3
    assert rows[0]["crossover_spp"] == rows[1]["crossover_spp"]
    table = bench_frame.format_table(rows)
    assert "fracture" in table and "crossover" in table


def test09_timing_returns_the_result_and_a_non_negative_time():
    """hlbvh.timing: the one clock of the frame rows, the sweep and the benchmarks."""
    from hlbvh import timing

    calls = []
    ms, result = timing.timed(lambda a, b=0: calls.append((a, b)) or a + b, 2, b=3)
    assert result == 5 and calls == [(2, 3)] and ms >= 0
    wall, cpu, result = timing.timed_cpu(sum, [1, 2])
    assert result == 3 and wall >= 0 and cpu >= 0
    first = timing.clock_ms()
    assert timing.clock_ms() >= first


def test10_a_stepped_range_renders_every_step_th_frame_and_resumes(tmp_path, capsys):
    """``--frames 0:5:2`` renders 0, 2, 4 and says so; ``0:5`` then renders the two
    left between them."""
    out = tmp_path / "out"
    status, summary, _ = render(capsys, "cloth", "--frames", "0:5:2", "--accel", "native",
                                "--out", out, *tiny(spp=1))
    assert status == 0 and f"{out}: frames 0..4 in steps of 2 of cloth with native: 3 " \
        "rendered, 0 already complete" in summary, summary
    assert [row["frame"] for row in stats(out)[0]["frames"]] == [0, 2, 4]
    assert not frame_files(out, 1)[0].exists()
    status, summary, _ = render(capsys, "cloth", "--frames", "0:5", "--accel", "native",
                                "--out", out, *tiny(spp=1))
    assert status == 0 and "frames 0..4 of cloth with native: 2 rendered, 3 already " \
        "complete" in summary, summary


@pytest.mark.parametrize("frames, said", [
    ("5:3", "the range is empty (expected A < B)"),
    ("3:3", "the range is empty (expected A < B)"),
    ("0:9:0", "expected a STEP >= 1"),
])
def test11_a_range_the_text_refuses_is_refused_before_the_scene_is_made(
        tmp_path, capsys, monkeypatch, frames, said):
    """The scene (a procedural one built twice, a stage read whole) is not made for a
    range that its text shows to be wrong."""
    from hlbvh import scenes
    made = []
    real = scenes.get
    monkeypatch.setattr(scenes, "get", lambda *a, **k: made.append(a) or real(*a, **k))
    status, _, err = render(capsys, "cloth", "--frames", frames, "--out", tmp_path / "out",
                            *tiny())
    assert status == 2 and err == [f"hlbvh render: --frames {frames!r}: {said}"], err
    assert made == []


def test12_a_resume_refusal_names_a_default_not_none(tmp_path, capsys):
    out = tmp_path / "out"
    argv = ["cloth", "--frames", "0:1", "--accel", "native", "--out", out, *tiny(spp=1)]
    assert render(capsys, *argv, "--moving-accel", "hlbvh")[0] == 0
    status, _, err = render(capsys, *argv)
    assert status == 2 and len(err) == 1, err
    assert "(moving_accel: 'hlbvh' -> unset (the default, 'auto'))" in err[0], err


def test13_the_summary_names_the_stage_s_file(tmp_path, capsys):
    """Not ``of usd``: a user renders many stages."""
    pytest.importorskip("pxr")
    from pxr import Gf, UsdGeom, UsdLux
    path = tmp_path / "quad_shot.usda"
    stage, mesh = _stage_with_mesh(path, 0, 3, [4], [0, 1, 2, 3])
    points = mesh.CreatePointsAttr()
    for t in range(4):
        points.Set([(0, 0, 0), (1, 0, 0), (1, 1 + 0.1 * t, 0), (0, 1, 0)], t)
    mesh.CreateSubdivisionSchemeAttr("none")
    UsdGeom.Camera.Define(stage, "/Cam").AddTranslateOp().Set(Gf.Vec3d(0.5, 0.5, 4))
    UsdLux.DomeLight.Define(stage, "/Sky")
    stage.GetRootLayer().Save()
    out = tmp_path / "out"
    status, summary, _ = render(capsys, path, "--frames", "0:4:3", "--resolution", "8",
                                "--spp", "1", "--quiet", "--out", out)
    assert status == 0 and f"{out}: frames 0..3 in steps of 3 of quad_shot.usda with " \
        "hlbvh: 2 rendered" in summary, summary


def _stage_with_mesh(path, start: int, end: int, counts: list, indices: list):
    """A new stage at ``path`` of time codes ``start..end`` with a mesh ``/Q`` of
    those faces (its points left to the caller): ``(stage, mesh)``."""
    from pxr import Usd, UsdGeom
    stage = Usd.Stage.CreateNew(str(path))
    stage.SetStartTimeCode(start)
    stage.SetEndTimeCode(end)
    mesh = UsdGeom.Mesh.Define(stage, "/Q")
    mesh.CreateFaceVertexCountsAttr(counts)
    mesh.CreateFaceVertexIndicesAttr(indices)
    return stage, mesh


@pytest.mark.parametrize("frames", ["0:9", "5:", "2:7:2"])
def test14_a_stage_s_range_is_refused_before_its_meshes_are_read(tmp_path, capsys,
                                                                  monkeypatch, frames):
    """As soon as the stage's time range is read: a large stage's meshes (and their
    skinning, baked over the frames asked) took seconds before the refusal."""
    pytest.importorskip("pxr")
    from hlbvh.scenes.usd import UsdScene
    path = tmp_path / "short.usda"
    stage, mesh = _stage_with_mesh(path, 1, 5, [3], [0, 1, 2])
    mesh.CreatePointsAttr([(0, 0, 0), (1, 0, 0), (1, 1, 0)])
    stage.GetRootLayer().Save()
    read = []
    monkeypatch.setattr(UsdScene, "_collect", lambda self: read.append(1))
    status, _, err = render(capsys, path, "--frames", frames, "--out", tmp_path / "out",
                            "--resolution", "8", "--quiet")
    asked = frames.rpartition(":")[0] if frames.count(":") == 2 else frames
    assert status == 2 and err == [
        f"hlbvh render: stage {str(path)!r} has frames 0:5 (time codes 1..5, "
        f"startTimeCode..endTimeCode); frames {asked} reach past them"], err
    assert read == []
