"""``hlbvh compare``: on a tiny animated scene it writes every file it promises, the
numbers on its pages are those of its JSON and CSV, and those numbers are the ones the
image files give; re-running resumes; user errors exit 2 with one line."""

import csv
import html.parser
import json
import math

import OpenImageIO as oiio
import pytest

from cli_helpers import run_cli
from hlbvh import cli
from hlbvh.render import images
from hlbvh.comparison import compare
from hlbvh.comparison.metrics import hit_agreement, image_metrics, noise_judge
from hlbvh.comparison.tables import column_title, format_value, read_results

FRAMES = (0, 1)
SIZE = 24
TINY = ["--triangles", "2000", "--resolution", str(SIZE), "--spp", "2", "--frames", "0:2",
        "--quiet"]


hlbvh = run_cli


@pytest.fixture(scope="module")
def compared(tmp_path_factory):
    """A compare of frames 0 and 1 of a small cloth: (exit status, its directory)."""
    out = tmp_path_factory.mktemp("compare") / "cloth"
    return cli.main(["compare", "cloth", *TINY, "--out", str(out)]), out


def markdown_table(text: str, heading: str) -> list[dict]:
    """The rows of the Markdown table under ``## heading`` as dicts of cell text."""
    lines = text.split(f"## {heading}\n", 1)[1].strip().splitlines()
    table = [line for line in lines[: next((k for k, line in enumerate(lines)
                                            if not line.startswith("|")), len(lines))]]
    cells = [[cell.strip() for cell in line.strip("|").split(" | ")] for line in table]
    return [dict(zip(cells[0], row)) for row in cells[2:]]


class _Sources(html.parser.HTMLParser):
    def __init__(self):
        super().__init__()
        self.sources = []

    def handle_starttag(self, tag, attrs):
        if tag == "img":
            self.sources.append(dict(attrs)["src"])


def png_size(path) -> tuple:
    source = oiio.ImageInput.open(str(path))
    assert source is not None, f"{path} is not an image"
    spec = source.spec()
    source.close()
    return spec.width, spec.height


def test01_compare_writes_every_file_it_promises(compared):
    status, out = compared
    assert status == 0
    for name in ("report.md", "report.html", "results.json", "results.csv", "build_ms.png"):
        assert (out / name).is_file(), name
    for i in FRAMES:
        frame = f"frame_{i:04d}"
        for directory in ("native", "hlbvh", "hits-native", "hits-hlbvh"):
            assert (out / directory / f"{frame}.exr").is_file()
            assert (out / directory / f"{frame}.png").is_file()
            assert (out / directory / "stats.json").is_file()
        assert png_size(out / "diff" / f"{frame}.png") == (SIZE, SIZE)
    assert png_size(out / "build_ms.png")[0] > 100
    assert not list(out.rglob(".*.tmp"))

    # The page shows, per frame, native, ours and the difference, and the plot: every
    # image it links exists inside the directory.
    parser = _Sources()
    parser.feed((out / "report.html").read_text())
    for i in FRAMES:
        frame = f"frame_{i:04d}.png"
        assert [f"native/{frame}", f"hlbvh/{frame}", f"diff/{frame}"] == [
            s for s in parser.sources if s.endswith(frame)]
    assert "build_ms.png" in parser.sources and "frame_ms.png" in parser.sources
    # It opens on the verdict, and the difference maps carry their scale.
    page = (out / "report.html").read_text()
    scale = read_results(out / "results.json")["settings"]["difference_scale"]
    assert page.split("<body>", 1)[1].split("</h1>", 1)[1].startswith(
        "\n<p><strong>A frame (build + render")
    assert f"pale yellow = {scale:.3g}" in page
    for source in parser.sources:
        assert (out / source).resolve().is_file() and (out / source).resolve().is_relative_to(
            out.resolve()), source


def test02_report_numbers_equal_the_json_and_csv(compared):
    _, out = compared
    results = read_results(out / "results.json")
    rows = results["rows"]
    assert [row["frame"] for row in rows] == list(FRAMES)
    table = markdown_table((out / "report.md").read_text(), "Frames")
    assert len(table) == len(rows)
    for row, cells in zip(rows, table):
        assert list(cells) == [column_title(key) for key in row]
        cells = dict(zip(row, cells.values()))  # by key
        for key, value in row.items():
            assert cells[key] == format_value(value), key
            if isinstance(value, float) and math.isfinite(value):
                assert float(cells[key]) == pytest.approx(value, rel=1e-5), key
    with open(out / "results.csv", newline="") as f:
        for row, line in zip(rows, csv.DictReader(f)):
            for key, value in row.items():
                if isinstance(value, (int, float)) and not isinstance(value, bool):
                    assert float(line[key]) == value, key
    settings = {r["setting"]: r["value"] for r in markdown_table((out / "report.md").read_text(),
                                                                 "Settings")}
    assert settings["tolerance"] == format_value(compare.TOLERANCE)
    assert settings["spp"] == "2" and settings["scene"] == "cloth"

    def refuse(constant):
        raise AssertionError(f"non-standard JSON constant {constant} in results.json")

    # Strict JSON: json.loads alone accepts NaN and Infinity, which JSON does not.
    raw = json.loads((out / "results.json").read_text(), parse_constant=refuse)
    assert [row["frame"] for row in raw["rows"]] == list(FRAMES)


def test03_numbers_are_those_of_the_rendered_files(compared):
    """Metrics recomputed from the EXRs equal the report's; timings equal the renders'
    statistics; hlbvh agrees with native as the plugin's tests require."""
    _, out = compared
    rows = read_results(out / "results.json")["rows"]
    stats = {accel: {r["frame"]: r for r in json.loads(
        (out / accel / "stats.json").read_text())["frames"]} for accel in ("native", "hlbvh")}
    for row in rows:
        i, name = row["frame"], f"frame_{row['frame']:04d}.exr"
        native, ours = (images.read_exr(out / a / name, ["R", "G", "B"]) for a in ("native", "hlbvh"))
        expected = image_metrics(native, ours, compare.TOLERANCE)
        for key in ("max_abs_diff", "mean_abs_diff", "fraction_identical",
                    "fraction_within_tolerance", "psnr_db"):
            assert row[f"image.{key}"] == expected[key], key
        judged = noise_judge(ours, native, images.read_exr(
            out / "native-noise" / name, ["R", "G", "B"]) if row["noise.seed"] is not None else None)
        assert row["noise.largest_z"] == judged["largest_z"]
        assert row["noise.passed"] == judged["passed"] is True
        hits = hit_agreement(*(images.read_exr(out / f"hits-{a}" / name,
                                               ["shape_index", "prim_index"])
                               for a in ("native", "hlbvh")))
        assert row["hits.fraction_agree"] == hits["fraction_agree"]
        for accel in ("native", "hlbvh"):
            assert row[f"build_ms.{accel}"] == stats[accel][i]["build_ms"]
            assert row[f"render_ms.{accel}"] == stats[accel][i]["render_ms"]
            assert row[f"frame_ms.{accel}"] == pytest.approx(
                stats[accel][i]["build_ms"] + stats[accel][i]["render_ms"])
        assert row["build_speedup"] == pytest.approx(
            stats["native"][i]["build_ms"] / stats["hlbvh"][i]["build_ms"])
        assert row["sah_cost"] == stats["hlbvh"][i]["sah_cost"]
        if stats["hlbvh"][i]["moving_accel"] == "hlbvh":  # else no tree of ours traced it
            assert row["sah_cost"] >= 1
        # Same seed, box filter: ours equals native within the plugin's tolerance (one
        # pixel may branch differently), and the camera rays hit the same primitives
        # but for an edge tie or two.
        pixels = SIZE * SIZE
        assert row["image.fraction_within_tolerance"] >= 1 - 1 / pixels
        assert row["image.fraction_identical"] > 0.05
        assert row["hits.fraction_agree"] >= 1 - 2 / pixels
    # The difference maps share one scale: the largest difference of any frame.
    scale = read_results(out / "results.json")["settings"]["difference_scale"]
    # (1 when every frame is identical: a map of zeros needs some scale).
    largest = max(row["image.max_abs_diff"] for row in rows)
    assert scale == (largest if largest > 0 else 1.0), (scale, largest)


def test04_running_again_resumes_without_rendering(compared, capsys):
    _, out = compared
    before = {p: p.stat().st_mtime_ns for p in out.glob("*/frame_*.exr")}
    rows = read_results(out / "results.json")["rows"]
    status, printed, errors = hlbvh(capsys, "compare", "cloth", *TINY, "--out", out)
    assert status == 0 and not errors
    assert "report.html" in printed and "build speedup" in printed
    assert {p: p.stat().st_mtime_ns for p in out.glob("*/frame_*.exr")} == before
    assert read_results(out / "results.json")["rows"] == rows


@pytest.mark.parametrize("argv, message", [
    (["nonsense"], "not a procedural scene"),
    (["cloth", "--tolerance", "-1"], "--tolerance"),
    (["cloth", "--frames", "3:1"], "--frames"),
    (["cloth", "--leaf-size", "99"], "leaf_size"),
    (["cloth", "--update", "sometimes"], "--update"),
    (["cloth", "--spp", "zero"], "--spp"),
])
def test05_user_errors_exit_2_with_one_line(tmp_path, capsys, argv, message):
    status, _, errors = hlbvh(capsys, "compare", *argv, "--quiet", "--out", tmp_path / "x")
    assert status == 2
    assert len(errors) == 1 and message in errors[0] and errors[0].startswith("hlbvh compare:")
    assert not (tmp_path / "x").exists()


def test06_other_settings_in_the_directory_are_refused(compared, capsys):
    """A report directory holds one comparison: rendering other settings into it is a
    user error, and the files already there are untouched."""
    _, out = compared
    before = (out / "results.json").read_bytes()
    status, _, errors = hlbvh(capsys, "compare", "cloth", *TINY, "--seed", "3", "--out", out)
    assert status == 2 and len(errors) == 1 and "other settings" in errors[0]
    assert (out / "results.json").read_bytes() == before



def row(frame, ours, native, z, speedup, agree, still=40.0, moving="hlbvh"):
    """A hand-made row of a compare: frame times, the judge's z, hit agreement."""
    return {"frame": frame, "frame_ms": {"hlbvh": ours, "native": native},
            "build_speedup": speedup,
            "motion_overhead": {"hlbvh": ours / still, "native": native / still},
            "moving_accel": moving,
            "noise": {"passed": abs(z) < 6, "largest_z": z, "nonfinite_pixels": 0,
                      "largest_z_block": "8x8 at 16,24 channel 1"},
            "image": {"max_abs_diff": 0.01 * abs(z), "fraction_identical": 0.5 + z / 100},
            "hits": {"fraction_agree": agree}}


def test07_verdict_states_the_numbers_of_the_rows():
    """The report's opening paragraph, on hand-made rows: medians of frame time and build
    speedup, the judge's largest block z and the frames beyond the limit, the
    bit-identical range as a figure, the worst hit agreement."""
    rows = [row(0, 50.0, 100.0, 0.5, 4.0, 1.0), row(1, 60.0, 90.0, -9.0, 6.0, 0.999),
            row(2, 500.0, 95.0, 2.0, 5.0, 1.0)]
    text = compare.verdict(rows)
    assert text.startswith("A frame (build + render, median of 3) takes 60.0 ms with hlbvh "
                           "and 95.0 ms with native: hlbvh is 1.58x faster.")
    assert "Median build speedup 5.00x" in text
    assert ("hlbvh is 1.58x faster. Our HLBVH traced the moving meshes on every frame of "
            "hlbvh's. Motion overhead (a frame over native's render of it without a rebuild; "
            "1.0 is a still frame): hlbvh 1.50, native 2.38. ") in text
    assert ("NOT within Monte Carlo noise of native's on 1 of 3 frames (1; largest block |z| "
            "9.0 on frame 1, 8x8 at 16,24 channel 1; limit 6") in text
    assert "Pixels bit-identical to native's: 41.0-52.0% a frame" in text
    assert "largest pixel difference 0.09" in text and "at least 99.900% of pixels" in text
    clean = compare.verdict([row(0, 50.0, 40.0, 0.25, 0.5, 1.0)])
    assert "hlbvh is 1.25x slower" in clean
    assert ("within Monte Carlo noise of native's on every frame (largest block |z| 0.25, "
            "limit 6") in clean


def test08_bench_without_native_traces_with_our_bvh_alone():
    """``bench frame --no-native`` renders no native frame: hlbvh's renderer alone, and
    its moving meshes traced by our BVH (the choice would hand rigid's to Mitsuba's
    native group or whole scene: native frames after all)."""
    from hlbvh.comparison.bench import frame as bench_frame
    from hlbvh.scenes import get

    animation = get("rigid", instanced=True, frames=2)
    alone = bench_frame._renderers(animation, (16, 16), 2, "hlbvh", native=False)
    assert list(alone) == ["hlbvh"] and alone["hlbvh"].settings.moving_accel == "hlbvh"
    both = bench_frame._renderers(animation, (16, 16), 2, "hlbvh", native=True)
    assert both["hlbvh"].settings.moving_accel is None


def test09_verdict_says_what_traced_the_moving_meshes_and_what_that_compares():
    """Where Mitsuba's whole scene traced the moving meshes (what the choice gives cloth at
    most budgets), hlbvh's frames are Mitsuba's own: the verdict says the comparison is of
    Mitsuba with itself and how to compare our BVH; a mix is counted per structure."""
    scene = compare.verdict([row(i, 100.0, 100.0, 0.0, 1.0, 1.0, moving="scene")
                             for i in range(3)])
    assert ("hlbvh is 1.00x faster. The whole scene (Mitsuba's own accelerator, rebuilt) "
            "traced the moving meshes on every frame of hlbvh's: this compares Mitsuba with "
            "itself; --moving-accel hlbvh forces our BVH, the comparison of hlbvh itself. "
            "Motion overhead") in scene
    mixed = compare.verdict([row(0, 50.0, 100.0, 0.5, 4.0, 1.0),
                             row(1, 50.0, 100.0, 0.5, 4.0, 1.0, moving="native"),
                             row(2, 50.0, 100.0, 0.5, 4.0, 1.0, moving="native"),
                             row(3, 50.0, 100.0, 0.5, 4.0, 1.0, moving="scene")])
    assert ("What traced the moving meshes on hlbvh's frames: our HLBVH on 1 of 4, a Mitsuba "
            "sub-scene of the moving meshes (the native group) on 2 of 4, the whole scene "
            "(Mitsuba's own accelerator, rebuilt) on 1 of 4: the native group's frames do not "
            "compare our BVH on the moving meshes; the whole scene's frames compare Mitsuba "
            "with itself; --moving-accel hlbvh forces our BVH") in mixed


def test10_blur_frame_shows_a_blurred_pair_beside_the_still_one(tmp_path, capsys):
    """``--blur-frame N`` renders the frames still and frame N once more with the
    shutter open (a whole compare into blur/): the report shows its native accumulation,
    our blurred frame and their difference beside frame N's still pair, frame N's row
    holds its numbers under ``blur``, the verdict says its times and judgement; a frame
    not compared is one line."""
    out = tmp_path / "main"
    status, printed, errors = hlbvh(capsys, "compare", "twist", *TINY, "--blur-frame", "1",
                                    "--shutter", "0.5", "--sub-frames", "2", "--out", out)
    assert status == 0 and not errors
    results = read_results(out / "results.json")
    assert "shutter" not in results["settings"]  # the frames themselves still
    assert results["settings"]["blur_frame"] == 1
    assert results["settings"]["blur_shutter"] == [-0.25, 0.25]
    still, blurred = results["rows"]
    assert "blur.passed" not in still and blurred["blur.passed"] is True
    assert blurred["blur.shutter.sub_frames"] == 2
    inner = read_results(out / "blur" / "results.json")
    assert [r["frame"] for r in inner["rows"]] == [1]
    assert inner["settings"]["shutter"] == [-0.25, 0.25]
    assert blurred["blur.frame_ms.hlbvh"] == inner["rows"][0]["frame_ms.hlbvh"]
    assert blurred["blur.largest_z"] == inner["rows"][0]["noise.largest_z"]
    roles = results["images"]["1"]
    assert list(roles) == ["native", "hlbvh", "diff", "native blurred", "hlbvh blurred",
                           "diff blurred"]
    assert roles["hlbvh blurred"] == "blur/hlbvh/frame_0001.png"
    assert list(results["images"]["0"]) == ["native", "hlbvh", "diff"]
    page = (out / "report.html").read_text()
    sources = _Sources()
    sources.feed(page)
    assert "blur/native/frame_0001.png" in sources.sources
    assert "the mean of 2 sub-frames" in page
    verdict = (out / "report.md").read_text().split("\n\n")[1]
    assert "Frame 1 blurred (shutter -0.25..0.25" in verdict
    assert "ours is within Monte Carlo noise of native's" in verdict.split("Frame 1 blurred")[1]
    assert "Frame 1 blurred" in printed
    status, _, errors = hlbvh(capsys, "compare", "twist", *TINY, "--blur-frame", "5",
                              "--out", tmp_path / "other")
    assert status == 2 and len(errors) == 1 and "--blur-frame '5'" in errors[0]
