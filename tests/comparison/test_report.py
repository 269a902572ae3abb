"""``hlbvh.comparison.report`` and ``hlbvh.comparison.plots`` on a tiny fake run (two
frames of small synthetic images written with ``hlbvh.render.images``): every promised file is
written, the numbers on the pages are the JSON's and the CSV's, the Pareto front and the
crossover are right on hand-made data, and the HTML page shows every image in a real
browser (headless Chromium)."""

import csv
import html
import html.parser
import json
import math
import os
import re
import shutil
import subprocess

import numpy as np
import matplotlib.text
import pytest

from hlbvh.render import images
from hlbvh.comparison import crossover, plots, report
from hlbvh.comparison.metrics import hit_agreement, image_metrics
from hlbvh.comparison.tables import column_title, format_value, read_results

SIZE = 16
FRAMES = (0, 1)
ROLES = ("native", "hlbvh", "diff")


def synthetic_frame(i: int) -> tuple[np.ndarray, np.ndarray]:
    """(native, ours): a colour ramp, ours equal in frame 0 and off in a few pixels in 1."""
    y, x = np.mgrid[0:SIZE, 0:SIZE].astype(np.float32) / SIZE
    native = np.stack([x, y, 0.5 * (x + y) + 0.1 * i], axis=-1).astype(np.float32)
    ours = native.copy()
    if i:
        ours[3, 4, 0] += np.float32(0.25)
        ours[5, 6, 2] -= np.float32(1e-6)
    return native, ours


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A fake comparison of two frames: the report directory, what went in, the files.

    Frame 0's images live inside the report directory (in a folder whose name a URL must
    escape); frame 1's outside it, so the report copies them in.
    """
    root = tmp_path_factory.mktemp("report")
    out = root / "report"
    inside, outside = out / "renders #1 (100%)", root / "elsewhere"
    rows, pictures = [], {}
    for i in FRAMES:
        native, ours = synthetic_frame(i)
        where = inside if i == 0 else outside
        pictures[i] = {
            "native": images.write_png(where / "native" / f"frame_{i:04d}.png", native),
            "hlbvh": images.write_png(where / "hlbvh" / f"frame_{i:04d}.png", ours),
            "diff": images.write_difference_map(where / "diff" / f"frame_{i:04d}.png",
                                                native, ours),
        }
        hits = np.zeros((SIZE, SIZE, 2), np.int64)
        test_hits = hits.copy()
        test_hits[0, :i, 1] = 1
        rows.append({
            "frame": i,
            "image": image_metrics(native, ours, tolerance=1e-3),
            "hits": hit_agreement(hits, test_hits),
            "build_ms": {"native": 12.5 + i, "hlbvh": 1.0 / 3.0},
            "sah_cost": np.float32(41.123456789),
            "fraction_like": 0.9999995,
            "rebuilt": bool(i),
            "note": None if i else "a | pipe",
            "leaf_sizes": [1, 2.5, 4],
        })
    plot = plots.plot_per_frame(root / "plots in" / "build_ms.png", FRAMES,
                                  [row["build_ms"]["native"] for row in rows],
                                  [row["build_ms"]["hlbvh"] for row in rows])
    settings = {"scene": "fake", "spp": 2, "tolerance": 1e-3,
                "build_options": {"builder": "hlbvh", "leaf_size": 4}, "frames": "0:2"}
    files = report.write_report(out, "fake run", rows, pictures, settings, plots=[plot])
    return {"out": out, "rows": rows, "pictures": pictures, "settings": settings,
            "files": files, "plot": plot}


def markdown_table(text: str, heading: str) -> list[dict]:
    """The rows of the Markdown table under ``## heading``, as dicts of unescaped cell
    text (``\\|`` is a literal bar)."""
    lines = text.split(f"## {heading}\n", 1)[1].strip().splitlines()
    lines = lines[: next((k for k, line in enumerate(lines) if not line.startswith("|")),
                         len(lines))]
    cells = [[cell.strip().replace("\\|", "|")
              for cell in re.split(r"(?<!\\)\|", line.strip()[1:-1])] for line in lines]
    assert set("".join(cells[1])) <= {"-"}, "the second line separates the header"
    return [dict(zip(cells[0], row)) for row in cells[2:]]


class _Page(html.parser.HTMLParser):
    """Tables (by the preceding h2) and image sources of an HTML page."""

    def __init__(self):
        super().__init__()
        self.tables, self.sources, self.heading = {}, [], None
        self._row = self._cell = None

    def handle_starttag(self, tag, attrs):
        if tag == "img":
            self.sources.append(dict(attrs)["src"])
        elif tag == "h2":
            self._cell = []
        elif tag == "table":
            self.tables[self.heading] = []
        elif tag == "tr":
            self._row = []
        elif tag in ("td", "th"):
            self._cell = []

    def handle_endtag(self, tag):
        if tag == "h2":
            self.heading = "".join(self._cell)
        elif tag in ("td", "th"):
            self._row.append("".join(self._cell))
        elif tag == "tr":
            self.tables[self.heading].append(self._row)

    def handle_data(self, data):
        if self._cell is not None:
            self._cell.append(data)


def parse_html(path) -> _Page:
    page = _Page()
    page.feed(path.read_text(encoding="utf-8"))
    return page


# ---- Files ----


def test01_every_promised_file_is_written(run):
    out, files = run["out"], run["files"]
    assert files == {"md": out / "report.md", "html": out / "report.html",
                     "json": out / "results.json", "csv": out / "results.csv"}
    for path in files.values():
        assert path.is_file() and path.stat().st_size > 0, path
    assert not [p for p in out.rglob("*") if p.name.endswith(".tmp")]
    # Frame 1's images and the plot were outside: copied in, byte for byte.
    results = read_results(files["json"])
    for i in FRAMES:
        for role in ROLES:
            link = results["images"][str(i)][role]
            assert (out / link).resolve().is_relative_to(out.resolve())
            assert (out / link).read_bytes() == run["pictures"][i][role].read_bytes()
    assert results["images"]["1"]["native"] == "images/frame_1_native.png"
    assert results["images"]["0"]["native"] == "renders #1 (100%)/native/frame_0000.png"
    assert results["plots"] == ["plots/0_build_ms.png"]
    assert (out / "plots/0_build_ms.png").read_bytes() == run["plot"].read_bytes()
    assert results["kind"] == "compare" and results["title"] == "fake run"


def test02_json_is_strict_and_holds_the_rows(run):
    text = run["files"]["json"].read_text()

    def refuse(constant):
        raise AssertionError(f"non-standard JSON constant {constant}")

    raw = json.loads(text, parse_constant=refuse)
    assert raw["rows"][0]["image.psnr_db"] == "inf"  # identical frame
    results = read_results(run["files"]["json"])
    rows = results["rows"]
    assert [row["frame"] for row in rows] == list(FRAMES)
    for row, given in zip(rows, run["rows"]):
        assert row["image.psnr_db"] == given["image"]["psnr_db"]
        assert row["image.max_abs_diff"] == given["image"]["max_abs_diff"]
        assert row["build_ms.native"] == given["build_ms"]["native"]
        assert row["sah_cost"] == float(given["sah_cost"])  # numpy scalar -> float
        assert row["leaf_sizes"] == [1, 2.5, 4] and row["rebuilt"] is bool(row["frame"])
    assert rows[0]["image.psnr_db"] == math.inf
    assert rows[1]["image.max_abs_diff"] == 0.25
    assert results["settings"]["build_options.leaf_size"] == 4


def test03_markdown_numbers_are_the_json_numbers(run):
    rows = read_results(run["files"]["json"])["rows"]
    text = run["files"]["md"].read_text(encoding="utf-8")
    table = markdown_table(text, "Frames")
    assert len(table) == len(rows)
    for row, cells in zip(rows, table):
        assert list(cells) == [column_title(key) for key in row]
        cells = dict(zip(row, cells.values()))  # by key
        for key, value in row.items():
            assert cells[key] == format_value(value), key
            if isinstance(value, float):
                parsed = float(cells[key])
                if math.isfinite(value):
                    assert parsed == pytest.approx(value, rel=1e-5, abs=0.0), key
                else:
                    assert parsed == value, key
            elif isinstance(value, int) and not isinstance(value, bool):
                assert int(cells[key]) == value, key
    title = column_title
    assert table[0][title("note")] == "a | pipe" and table[1][title("note")] == "-"
    assert table[0][title("fraction_like")] == "0.9999995"  # not rounded up to "1"
    assert table[1][title("image.fraction_identical")] != "1"
    settings = {r["setting"]: r["value"] for r in markdown_table(text, "Settings")}
    assert settings == {"scene": "fake", "spp": "2", "tolerance": "0.001",
                        "build_options.builder": "hlbvh", "build_options.leaf_size": "4",
                        "frames": "0:2"}


def test04_html_tables_show_the_same_cells(run):
    rows = read_results(run["files"]["json"])["rows"]
    page = parse_html(run["files"]["html"])
    header, *body = page.tables["Frames"]
    assert header == [column_title(key) for key in rows[0]]
    assert body == [[format_value(row[key]) for key in rows[0]] for row in rows]
    assert ["setting", "value"] == page.tables["Settings"][0]


def test05_csv_holds_the_exact_numbers(run):
    rows = read_results(run["files"]["json"])["rows"]
    with open(run["files"]["csv"], newline="") as f:
        lines = list(csv.DictReader(f))
    assert len(lines) == len(rows)
    for row, line in zip(rows, lines):
        assert list(line) == list(row)
        for key, value in row.items():
            if isinstance(value, (int, float)) and not isinstance(value, bool):
                assert float(line[key]) == value, key  # repr: exact, inf included
    assert json.loads(lines[0]["leaf_sizes"]) == [1, 2.5, 4]
    assert lines[1]["note"] == ""


def test06_page_shows_each_frame_side_by_side_and_the_plot(run):
    page = parse_html(run["files"]["html"])
    results = read_results(run["files"]["json"])
    expected = [results["images"][str(i)][role] for i in FRAMES for role in ROLES]
    # The plots first (after the verdict), then the images frame by frame.
    assert page.sources == [_url(link) for link in results["plots"] + expected]
    md_links = re.findall(r"!\[[^\]]*\]\(([^)]*)\)", run["files"]["md"].read_text())
    assert md_links == [_url(link) for link in results["plots"] + expected]
    text = run["files"]["html"].read_text()
    assert "native" in text and "hlbvh (ours)" in text and "difference" in text


def test06b_page_opens_on_the_verdict_and_captions_the_scale(run, tmp_path):
    """The verdict is the first thing under the title, before the plots, images and
    tables; a caption given for a role replaces its default."""
    files = report.write_report(tmp_path, "t", run["rows"], run["pictures"], run["settings"],
                                plots=[run["plot"]], verdict="Ours is as good.",
                                captions={"diff": "difference: 0 to 0.25"})
    text = files["html"].read_text()
    body = text.split("<body>", 1)[1]
    assert body.index("Ours is as good.") < body.index("<img") < body.index("<table")
    assert body.count("<figcaption>difference: 0 to 0.25</figcaption>") == len(FRAMES)
    markdown = files["md"].read_text()
    assert markdown.index("Ours is as good.") < markdown.index("![") < markdown.index("| ")


def _url(link: str) -> str:
    """A relative file path as it must appear in a link: percent-encoded."""
    from urllib.parse import quote

    return quote(link)


def test07_nonfinite_mismatch_is_called_out(tmp_path):
    native = np.zeros((2, 2, 3), np.float32)
    ours = native.copy()
    ours[0, 0, 0] = np.nan
    rows = [{"frame": 3, "image": image_metrics(native, ours, 0.0)}]
    files = report.write_report(tmp_path, "nan", rows, {}, {"scene": "x"})
    assert "nonfinite_mismatch_pixels" in files["md"].read_text()
    assert 'class="warning"' in files["html"].read_text()
    clean = report.write_report(tmp_path / "clean", "ok", [{"frame": 0, "x": 1.0}], {}, {})
    assert "Warning" not in clean["md"].read_text()


@pytest.mark.parametrize("frames, pictures, message", [
    ([{"x": 1}], {}, "'frame'"),
    ([{"frame": 0}], {5: {}}, "no row"),
    ([{"frame": 0}], {0: {"native": "missing.png"}}, "no such image"),
    ([{"frame": 0}], {0: {"native": "frame.exr"}}, "browser"),
])
def test08_bad_input_is_a_value_error(tmp_path, frames, pictures, message):
    with pytest.raises(ValueError, match=message):
        report.write_report(tmp_path / "r", "t", frames, pictures, {})
    assert not (tmp_path / "r" / "report.html").exists()


def test09_format_value():
    assert [format_value(v) for v in (None, True, False, 3, "s", 0.5, 1.0 / 3.0)] == [
        "-", "yes", "no", "3", "s", "0.5", "0.333333"]
    assert [format_value(v) for v in (math.inf, -math.inf, math.nan)] == ["inf", "-inf", "nan"]
    # Just below a whole number it keeps the digits that tell it apart.
    assert format_value(0.9999995) == "0.9999995"
    assert format_value(0.99999999999) == "0.99999999999"
    assert format_value(99.999996) == "99.999996"
    assert format_value(1.0) == "1" and format_value(2.5e10) == "2.5e+10"
    assert format_value([1, 0.5, None]) == "[1, 0.5, -]"


# ---- Sweep reports ----


def test10_sweep_report_names_the_winner_by_its_own_numbers(tmp_path):
    rows = [
        {"setting": "native", "build_ms": 40.0, "frame_ms": 90.0, "sah_cost": 30.0},
        {"setting": "lbvh", "build_ms": 5.0, "frame_ms": 70.5, "sah_cost": 45.0},
        {"setting": "hlbvh", "build_ms": 7.0, "frame_ms": 61.25, "sah_cost": 36.0},
        {"setting": "broken", "build_ms": 1.0, "frame_ms": math.nan, "sah_cost": 99.0},
    ]
    files = report.write_sweep_report(tmp_path, "sweep", rows, {"scene": "fake", "spp": 4})
    results = read_results(files["json"])
    assert results["winner"] == {"label": "hlbvh", "objective": "frame_ms", "value": 61.25}
    assert report.winner(rows)["setting"] == "hlbvh"
    assert report.winner(rows, "build_ms")["setting"] == "broken"
    text = files["md"].read_text()
    assert "Fastest by frame_ms: hlbvh (frame_ms = 61.25)" in text
    table = markdown_table(text, "Sweep")
    assert [r["setting"] for r in table] == ["native", "lbvh", "hlbvh", "broken"]
    assert table[3][column_title("frame_ms")] == "nan"
    assert '<tr class="winner"><td>hlbvh</td>' in files["html"].read_text()
    with pytest.raises(ValueError, match="objective"):
        report.winner(rows, "mrays")
    with pytest.raises(ValueError, match="'setting'"):
        report.write_sweep_report(tmp_path / "b", "s", [{"frame_ms": 1.0}], {})


# ---- Plots: Pareto front and crossover on hand-made data ----


def test11_pareto_front_of_hand_made_points():
    #        0       1       2       3       4 (= 1)  5       6          7           8
    build = [1.0,    2.0,    3.0,    4.0,    2.0,     5.0,    math.nan,  0.5,        1.0]
    sah = [5.0,      3.0,    4.0,    1.0,    3.0,     5.0,    0.0,       math.inf,   6.0]
    # 2 is beaten by 1; 5 by everything before it; 8 by 0 (same build, worse SAH);
    # 6 and 7 are not finite; the equal points 1 and 4 both stay.
    assert plots.pareto_front(build, sah) == [0, 1, 4, 3]
    assert plots.pareto_front([3.0], [7.0]) == [0]
    assert plots.pareto_front([1.0, 2.0, 3.0], [3.0, 2.0, 1.0]) == [0, 1, 2]
    assert plots.pareto_front([1.0, 2.0, 3.0], [1.0, 2.0, 3.0]) == [0]
    with pytest.raises(ValueError, match="equal length"):
        plots.pareto_front([1.0, 2.0], [1.0])
    with pytest.raises(ValueError, match="non-empty"):
        plots.pareto_front([], [])


def test12_crossover_of_hand_made_frame_times():
    """The one crossover definition (hlbvh.comparison.crossover), used by the frame
    benchmark, the sweep and the plot."""
    spp = [1, 2, 4, 8]
    # Frame time = build + spp * render: ours 8 + 2 spp, native 11 + spp: equal at 3 spp.
    ours = [8 + 2 * s for s in spp]
    assert crossover.crossover_spp(spp, ours, [11 + s for s in spp]) == 3.0
    # Equal exactly at a measured spp: that spp.
    assert crossover.crossover_spp(spp, ours, [12 + s for s in spp]) == 4.0
    # Ours faster throughout, native faster (or equal) from the start: none.
    assert crossover.crossover_spp(spp, ours, [100 + s for s in spp]) is None
    assert crossover.crossover_spp(spp, ours, [8 + 2 * s for s in spp]) is None
    assert crossover.crossover_spp(spp, ours, [1 + s for s in spp]) is None
    # Not linear: interpolated between the two measured spp around the sign change.
    assert crossover.crossover_spp([1, 16], [10, 30], [15, 25]) == pytest.approx(8.5)
    with pytest.raises(ValueError, match="increasing"):
        crossover.crossover_spp([4, 2], [1, 2], [2, 1])
    # In words: the number, or which side of the measured range it lies on.
    assert crossover.describe(spp, ours, [11 + s for s in spp]) == "3 spp"
    assert crossover.describe(spp, ours, [100 + s for s in spp]) == "> 8 spp"
    assert crossover.describe(spp, ours, [1 + s for s in spp]) == "< 1 spp"
    with pytest.raises(ValueError, match="equal length"):
        crossover.crossover_spp([1, 2], [1, 2], [1])


def test13_plots_are_pngs_and_mark_the_crossover(tmp_path):
    spp = [1, 2, 4, 8]
    path = plots.plot_frame_time_vs_spp(
        tmp_path / "spp.png", spp,
        {"native": [11 + s for s in spp], "hlbvh": [8 + 2 * s for s in spp]})
    pareto = plots.plot_build_vs_sah(tmp_path / "pareto.png", ["a", "b", "c"],
                                     [1.0, 2.0, 3.0], [3.0, 1.0, 2.0])
    for written in (path, pareto):
        image = images.read_exr(written)  # OpenImageIO reads PNG too
        assert image.shape[:2] == (450, 700)
    assert not list(tmp_path.glob("*.tmp")) and not list(tmp_path.glob(".*.tmp"))
    with pytest.raises(ValueError, match="native"):
        plots.plot_frame_time_vs_spp(tmp_path / "x.png", spp, {"hlbvh": spp})
    with pytest.raises(ValueError, match="labels"):
        plots.plot_build_vs_sah(tmp_path / "y.png", ["a"], [1.0, 2.0], [1.0, 2.0])


def test13b_frame_time_plot_draws_measured_points_and_labels_apart():
    """Only the measured spp are drawn (no interpolated curve), every crossover is
    marked on the lines and named in the legend, no two texts overlap, and the machine
    is written on the plot."""
    spp = [1, 4, 16]
    series = {"native": [129.0, 154.0, 240.0], "a": [100.0, 147.0, 358.0],
              "b": [97.0, 151.0, 347.0], "c": [85.0, 138.0, 350.0], "d": [60.0, 109.0, 297.0]}
    figure = plots.frame_time_figure(spp, series, note="measured on Some CPU, 2 cores")
    axes = figure.axes[0]
    crossings = {label: crossover.crossover_spp(spp, ms, series["native"])
                 for label, ms in series.items() if label != "native"}
    lines = [line for line in axes.get_lines() if len(line.get_xdata()) > 1]
    assert len(lines) == len(series)
    for line in lines:
        assert list(line.get_xdata()) == spp
    marks = sorted(float(line.get_xdata()[0]) for line in axes.get_lines()
                   if len(line.get_xdata()) == 1)
    assert marks == pytest.approx(sorted(crossings.values()))
    legend = [text.get_text() for text in axes.get_legend().get_texts()]
    for label, at in crossings.items():
        assert f"{label}: native faster from {at:.3g} spp" in legend
    figure.canvas.draw()
    renderer = figure.canvas.get_renderer()
    texts = [t for t in figure.findobj(matplotlib.text.Text) if t.get_visible() and t.get_text()]
    boxes = [t.get_window_extent(renderer) for t in texts]
    for i in range(len(boxes)):
        for j in range(i + 1, len(boxes)):
            assert not boxes[i].overlaps(boxes[j]), (texts[i].get_text(), texts[j].get_text())
    assert "measured on Some CPU, 2 cores" in [t.get_text() for t in texts]


# ---- The page in a real browser ----

_IMAGE_CHECK = """
<script>
window.addEventListener("load", () => {
  const all = Array.from(document.images);
  const check = document.createElement("pre");
  check.id = "image-check";
  check.textContent = JSON.stringify({
    total: all.length,
    loaded: all.filter(img => img.complete && img.naturalWidth > 0).length,
    images: all.map(img => [img.getAttribute("src"), img.naturalWidth, img.naturalHeight]),
  });
  document.body.appendChild(check);
});
</script>
"""


def chromium() -> str | None:
    return next((shutil.which(name) for name in ("chromium", "chromium-browser")
                 if shutil.which(name)), None)


def images_in_browser(page, profile) -> dict:
    """Load ``page`` in headless Chromium with :data:`_IMAGE_CHECK` appended (the copy
    sits next to it, so relative links resolve the same) and return what the script
    found: ``total`` and ``loaded`` image counts and ``[src, width, height]`` each."""
    checked = page.with_name(f"_check_{page.name}")
    checked.write_text(page.read_text(encoding="utf-8").replace(
        "</body>", _IMAGE_CHECK + "</body>"), encoding="utf-8")
    try:
        done = subprocess.run(
            [chromium(), "--headless", "--no-sandbox", "--disable-gpu",
             "--disable-background-networking", "--disable-component-update", "--disable-sync",
             "--no-first-run", f"--user-data-dir={profile}", "--virtual-time-budget=5000",
             "--dump-dom", checked.as_uri()],
            capture_output=True, text=True, timeout=60,
        )
    finally:
        checked.unlink()
    found = re.search(r'<pre id="image-check">(.*?)</pre>', done.stdout, re.S)
    assert found, f"the check script did not run (exit {done.returncode}): {done.stderr[-2000:]}"
    return json.loads(html.unescape(found.group(1)))


@pytest.mark.skipif(chromium() is None,
                    reason="no chromium binary (Debian: apt-get install chromium)")
def test14_report_html_shows_every_image_in_chromium(run, tmp_path):
    out = run["out"]
    seen = images_in_browser(out / "report.html", tmp_path / "profile")
    frames = len(FRAMES) * len(ROLES)
    assert seen["total"] == frames + 1, seen
    assert seen["loaded"] == seen["total"], seen
    # The plot first (after the verdict), then the frames' images.
    assert seen["images"][0][1:] == [700, 450]
    for src, width, height in seen["images"][1:]:
        assert (width, height) == (SIZE, SIZE), src

    # The check can fail: a page with one broken link is caught, and that image named.
    broken = out / "broken.html"
    link = _url(read_results(out / "results.json")["images"]["1"]["diff"])
    broken.write_text((out / "report.html").read_text().replace(
        f'src="{link}"', 'src="images/no_such_frame.png"'))
    seen = images_in_browser(broken, tmp_path / "profile")
    broken.unlink()
    assert seen["total"] == frames + 1 and seen["loaded"] == frames
    assert [src for src, width, _ in seen["images"] if width == 0] == ["images/no_such_frame.png"]


def test15_the_directory_can_be_moved(run, tmp_path):
    """Every link is relative and points inside the report directory, so a copy of the
    directory elsewhere shows the same images."""
    from urllib.parse import unquote

    moved = tmp_path / "moved report"
    shutil.copytree(run["out"], moved)
    page = parse_html(moved / "report.html")
    md_links = re.findall(r"!\[[^\]]*\]\(([^)]*)\)", (moved / "report.md").read_text())
    assert len(page.sources) == len(md_links) == len(FRAMES) * len(ROLES) + 1
    for link in page.sources + md_links:
        assert "://" not in link and not link.startswith("/"), link
        target = (moved / unquote(link)).resolve()
        assert target.is_relative_to(moved.resolve()) and target.is_file(), link
    results = read_results(moved / "results.json")
    for roles in results["images"].values():
        for link in roles.values():
            assert (moved / link).is_file(), link


def test16_tables_name_the_cpu_with_its_vector_width():
    """Benchmark tables name the CPU with its family, model and vector instruction set:
    one model name covers CPUs of 8 and of 16 lanes per packet, whose ratios differ."""
    from hlbvh.comparison.machine import cpu_model, simd_isa

    name = cpu_model()
    assert name and name != "unknown CPU"
    if os.path.exists("/proc/cpuinfo"):
        assert "(family " in name and simd_isa() in ("AVX-512", "AVX2", "")
        if simd_isa():
            assert name.endswith(f", {simd_isa()})")
