"""``hlbvh sweep``: with two settings on a tiny animated scene it writes a row per setting
and native and both plots, its numbers are consistent with each other, and it names a
winner its own numbers agree with; bad settings exit 2 with one line."""

import contextlib
import io
import math

import OpenImageIO as oiio
import pytest

from cli_helpers import interrupt_second_render, run_cli
from hlbvh import cli
from hlbvh.comparison import sweep
from hlbvh.comparison.tables import column_title, format_value, read_results

SIZE = 24
SPP = 2
TINY = ["--triangles", "2000", "--resolution", str(SIZE), "--spp", str(SPP),
        "--spp-curve", "1,4", "--frames", "0:3", "--quiet"]


hlbvh = run_cli


@pytest.fixture(scope="module")
def swept(tmp_path_factory):
    """A sweep of three settings over frames 0..2 of a small cloth: (status, stdout,
    dir)."""
    out = tmp_path_factory.mktemp("sweep") / "cloth"
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        status = cli.main(["sweep", "cloth", *TINY, "--settings",
                           "lbvh,builder=hlbvh+update=refit,static_hlbvh", "--out", str(out)])
    return status, printed.getvalue(), out


def image_size(path) -> tuple:
    source = oiio.ImageInput.open(str(path))
    assert source is not None, f"{path} is not an image"
    spec = source.spec()
    source.close()
    return spec.width, spec.height


def test01_three_settings_give_their_rows_and_both_plots(swept):
    status, _, out = swept
    assert status == 0
    for name in ("report.md", "report.html", "results.json", "results.csv"):
        assert (out / name).is_file(), name
    for plot in ("build_vs_sah.png", "frame_vs_spp.png"):
        assert image_size(out / plot)[0] > 100, plot
    results = read_results(out / "results.json")
    rows = results["rows"]
    assert [row["setting"] for row in rows] == ["native", "lbvh", "builder=hlbvh+update=refit",
                                                "static_hlbvh"]
    assert results["settings"]["spp_curve"] == [1, 2, 4]
    for row in rows:
        for key in ("build_ms", "build_cold_ms", "mrays_primary", "mrays_secondary",
                    "render_ms", "frame_ms", "frame_ms_spp1", "frame_ms_spp2", "frame_ms_spp4"):
            assert math.isfinite(row[key]) and row[key] > 0, (row["setting"], key)
    native, lbvh, refit, accurate = rows
    assert native["sah_cost"] is None and native["decisions"] == "native x3"
    assert lbvh["sah_cost"] >= 1 and refit["sah_cost"] >= 1
    assert lbvh["decisions"] == "rebuild x3" and refit["decisions"] == "refit x3"
    assert lbvh["options"] == "builder=lbvh"
    assert accurate["options"] == "update=auto+static=hlbvh"
    # Native (hlbvh_path through Mitsuba's accelerator) renders Mitsuba's C++ path
    # integrator's image bit for bit; every setting renders native's image within the
    # plugin's tolerance (same seed, box filter).
    assert native["image.max_abs_diff"] == 0 and native["image.psnr_db"] == math.inf
    for row in (lbvh, refit, accurate):
        assert row["image.fraction_within_tolerance"] >= 1 - 1 / SIZE**2
        assert row["image.mean_abs_diff"] < 1e-5


def test02_numbers_are_consistent_with_each_other(swept):
    _, _, out = swept
    for row in read_results(out / "results.json")["rows"]:
        assert row["frame_ms"] == row[f"frame_ms_spp{SPP}"]
    table = (out / "report.md").read_text().split("## Sweep\n", 1)[1].strip().splitlines()
    header = [cell.strip() for cell in table[0].strip("|").split(" | ")]
    rows = read_results(out / "results.json")["rows"]
    for row, line in zip(rows, table[2:]):
        cells = dict(zip(header, (cell.strip() for cell in line.strip("|").split(" | "))))
        for key, value in row.items():
            assert cells[column_title(key)] == format_value(value, 4), key


def test03_the_winner_is_the_fastest_by_its_own_numbers(swept):
    _, printed, out = swept
    results = read_results(out / "results.json")
    rows = results["rows"]
    fastest = min(rows, key=lambda row: row["frame_ms"])
    assert results["winner"] == {"label": fastest["setting"], "objective": "frame_ms",
                                 "value": fastest["frame_ms"]}
    ours = min(rows[1:], key=lambda row: row["frame_ms"])
    assert f"at {SPP} spp: {fastest['setting']} ({fastest['frame_ms']:.1f} ms" in printed
    if fastest is not ours:
        assert f"fastest hlbvh setting: {ours['setting']} ({ours['frame_ms']:.1f} ms)" in printed
    page = (out / "report.md").read_text()
    native = rows[0]
    assert (f"The fastest hlbvh setting at {SPP} spp is {ours['setting']}: "
            f"{ours['frame_ms']:.1f} ms a frame, ") in page
    assert f"native's {native['frame_ms']:.1f} ms; native is" in page
    assert '<tr class="winner">' in (out / "report.html").read_text()


def test04_settings_are_parsed_named_or_spelled_out():
    named = sweep.parse_settings("lbvh,refit")
    assert [(s.label, s.build_options, s.update) for s in named] == [
        ("lbvh", {"builder": "lbvh"}, None), ("refit", {}, "refit")]
    (spelled,) = sweep.parse_settings("builder=sah+leaf-size=2+update=auto")
    assert spelled.build_options == {"builder": "sah", "leaf_size": 2}
    assert spelled.update == "auto"
    assert spelled.description() == "builder=sah+leaf_size=2+update=auto"
    assert [s.label for s in sweep.parse_settings(None)] == list(sweep.SETTINGS)
    (accurate,) = sweep.parse_settings("static=hlbvh")
    assert accurate.static == "hlbvh" and accurate.description() == "static=hlbvh"


@pytest.mark.parametrize("argv, message", [
    (["nonsense"], "not a procedural scene"),
    (["cloth", "--settings", "fastest"], "unknown setting 'fastest'"),
    (["cloth", "--settings", "leaf_size=99"], "leaf_size"),
    (["cloth", "--settings", "update=sometimes"], "update"),
    (["cloth", "--settings", "static=embree"], "static='embree'"),
    (["cloth", "--settings", "colour=red"], "colour=red"),
    (["cloth", "--settings", "lbvh,,sah"], "--settings"),
    (["cloth", "--settings", "lbvh,lbvh"], "more than once"),
    (["cloth", "--frames", "0:1"], "at least two"),
    (["cloth", "--spp-curve", "1,x"], "--spp-curve"),
])
def test05_user_errors_exit_2_with_one_line(tmp_path, capsys, argv, message):
    status, _, errors = hlbvh(capsys, "sweep", *argv, "--quiet", "--out", tmp_path / "x")
    assert status == 2
    assert len(errors) == 1 and message in errors[0] and errors[0].startswith("hlbvh sweep:")
    assert not (tmp_path / "x").exists()


@pytest.mark.parametrize("command", ["sweep", "compare"])
def test06_ctrl_c_inside_a_render_stops_the_command(tmp_path, capsys, monkeypatch, command):
    """SIGINT inside ``mi.render`` (where Mitsuba's own handler only cancels the
    integrator) stops a sweep or a comparison after that render, exit 130, one line."""
    interrupt_second_render(monkeypatch)
    extra = ["--settings", "lbvh"] if command == "sweep" else []
    args = [a for a in TINY if a not in ("--spp-curve", "1,4")] if command == "compare" else TINY
    status, _, err = hlbvh(capsys, command, "cloth", *args, *extra, "--out", tmp_path / "x")
    assert status == 130 and err == [f"hlbvh {command}: interrupted"], err
    assert not (tmp_path / "x" / "report.html").exists()


def test09_a_volpath_scene_is_swept_with_ours_mirroring_it(tmp_path, capsys):
    """The fog scene's own integrator is Mitsuba's volpath: the sweep renders it with
    hlbvh_volpath (its properties kept), and says so in one line."""
    status, _, errors = hlbvh(capsys, "sweep", "fog", "--triangles", "3000", "--resolution",
                              "12", "--spp", "1", "--spp-curve", "1", "--frames", "0:2",
                              "--settings", "hlbvh", "--quiet", "--out", tmp_path / "fog")
    assert status == 0, errors
    assert errors == ["hlbvh sweep: the scene's integrator 'volpath' runs as hlbvh_volpath "
                      "(which mirrors it, every ray through the chosen accelerator)"]
    settings = read_results(tmp_path / "fog" / "results.json")["settings"]
    assert settings["integrator"] == "volpath"
