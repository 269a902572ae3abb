"""The benchmarks run end to end at small sizes (a few thousand triangles, tiny images):
``hlbvh bench build|trace|frame`` (table and ``--json``), the ``main()`` of
``bench.trace``, ``bench.frame`` and ``readme_figures`` with their flags. Every table
has the rows and columns it promises and every ratio is finite and positive; no time
is asserted."""

from __future__ import annotations

import functools
import json
import math

import numpy as np
import pytest

import hlbvh  # noqa: F401  (sets up Dr.Jit's LLVM and the variant)
import mitsuba as mi
from cli_helpers import run_cli
from hlbvh import scenes
from hlbvh.comparison import readme_figures
from hlbvh.comparison.bench import (build as bench_build, frame as bench_frame,
                                    trace as bench_trace)

#: The cloth is a 200k-triangle flag unless told otherwise; the benchmarks that trace
#: it (bench trace, readme_figures) name no size, so tests shrink it here.
SMALL_CLOTH = 2000


@pytest.fixture
def small_cloth(monkeypatch):
    real = scenes.get

    def get(name, **kwargs):
        if name == "cloth":
            kwargs["triangles"] = min(kwargs.get("triangles", SMALL_CLOTH), SMALL_CLOTH)
        return real(name, **kwargs)

    monkeypatch.setattr(scenes, "get", get)


def positive(value) -> bool:
    return isinstance(value, (int, float)) and math.isfinite(value) and value > 0


def strict_json(text: str):
    def refuse(constant):
        raise AssertionError(f"non-standard JSON constant {constant}")

    return json.loads(text, parse_constant=refuse)


# ---------------------------------------------------------------------------------------
# bench build
# ---------------------------------------------------------------------------------------


def test01_subdivided_box_is_a_closed_surface_of_about_the_size_asked():
    """Midpoint subdivision keeps the rounded box closed (every edge in exactly two
    triangles, both windings) and its new vertices on the surface |x|^4 = 1."""
    for triangles in (800, 5000):
        vertices, faces = bench_build.subdivided_box(triangles)
        v = vertices.numpy().reshape(-1, 3)
        f = faces.numpy().reshape(-1, 3).astype(np.int64)
        assert triangles / 4 <= len(f) <= 4 * triangles
        assert f.max() < len(v)
        directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
        pairs, counts = np.unique(np.sort(directed, axis=1), axis=0, return_counts=True)
        assert np.all(counts == 2), "an edge not shared by exactly two triangles"
        assert len(np.unique(directed, axis=0)) == len(directed), "inconsistent winding"
        used = np.unique(f)
        np.testing.assert_allclose((np.abs(v[used]) ** 4).sum(axis=1), 1, rtol=1e-4)


def test02_bench_build_rows_columns_and_ratios():
    rows = bench_build.run(sizes=(2000,), repeats=1)
    assert [(r["mesh"], r["builder"]) for r in rows] == [
        (m, b) for m in ("grid", "soup", "box") for b in ("hlbvh", "lbvh", "sah")]
    embree = bench_build._embree() is not None
    for r in rows:
        assert r["triangles"] >= 500 and r["cores"] >= 1 and r["launches"] > 0
        for key in ("build", "pack", "ready", "seeded", "refit", "native"):
            assert set(r[key]) == {"cold", "min", "median"}, key
            assert all(positive(v) for v in r[key].values()), (key, r[key])
        assert positive(r["native_over_ready"]) and positive(r["mtris_per_s_per_core"])
        assert r["native_over_ready"] == pytest.approx(r["native"]["min"] / r["ready"]["min"])
        assert r["mtris_per_s_per_core"] == pytest.approx(
            r["triangles"] / r["ready"]["min"] / 1e3 / r["cores"])
        assert r["sah_cost"] >= 1 and r["stage_ms"]
        for key in ("embree_low", "embree_medium", "embree_refit"):
            assert (key in r) == embree, key
    by_mesh = {r["mesh"]: r["triangles"] for r in rows}
    assert by_mesh["soup"] == 2000
    table = bench_build.format_table(rows).splitlines()
    head = table[0].split()
    for column in ("mesh", "builder", "ready", "native", "E.low", "E.med", "E.refit",
                   "nat/rdy", "SAH"):
        assert column in head, column
    body = table[2:2 + len(rows)]
    assert [line.split()[:3] for line in body] == [
        [r["mesh"], str(r["triangles"]), r["builder"]] for r in rows]
    for line, r in zip(body, rows):
        assert f"{r['native_over_ready']:6.2f}x" in line
        if not embree:  # the Embree columns show a dash, not a crash
            assert line.split().count("-") == 3
    assert table[-2].startswith("stages of the first row's last build")


def test03_bench_build_embree_columns():
    pytest.importorskip("embreex")
    rows = bench_build.run(sizes=(2000,), meshes=("grid",), builders=("lbvh",), repeats=1)
    for key in ("embree_low", "embree_medium", "embree_refit"):
        assert all(positive(v) for v in rows[0][key].values()), key
    assert "-" not in bench_build.format_table(rows).splitlines()[2].split()


def test04_hlbvh_bench_build_table_and_json(capsys):
    argv = ["bench", "build", "--sizes", "1500", "--repeats", "1", "--builder", "lbvh,hlbvh"]
    status, table, errors = run_cli(capsys, *argv)
    assert status == 0 and not errors
    lines = table.splitlines()
    assert lines[0].split()[:3] == ["mesh", "tris", "builder"]
    assert [line.split()[0] + " " + line.split()[2] for line in lines[2:8]] == [
        f"{m} {b}" for m in ("grid", "soup", "box") for b in ("lbvh", "hlbvh")]
    status, printed, errors = run_cli(capsys, *argv, "--json")
    assert status == 0 and not errors
    rows = strict_json(printed)
    assert [(r["mesh"], r["builder"]) for r in rows] == [
        (m, b) for m in ("grid", "soup", "box") for b in ("lbvh", "hlbvh")]
    assert all(positive(r["native_over_ready"]) for r in rows)


# ---------------------------------------------------------------------------------------
# bench trace
# ---------------------------------------------------------------------------------------

KINDS = [(k, q) for k in ("coherent", "incoherent", "shadow") for q in ("closest", "any")]
RATIOS = ("ratio", "ratio_median", "ratio_cpu", "ours_mrays", "native_mrays")


def test05_hlbvh_bench_trace_with_cornell_box_and_cloth(capsys, small_cloth):
    """The CLI's trace suite traces the grid, Cornell box and the cloth (their default
    branches), each kind and query, and prints them as JSON or as a table."""
    argv = ["bench", "trace", "--sizes", "2000", "--repeats", "1", "--resolution", "12"]
    status, printed, errors = run_cli(capsys, *argv, "--json")
    assert status == 0 and not errors
    rows = strict_json(printed)
    assert [(r["scene"], r["kind"], r["query"]) for r in rows] == [
        (s, k, q) for s in ("grid 2k", "cornell box", "cloth") for k, q in KINDS]
    triangles = {r["scene"]: r["triangles"] for r in rows}
    assert triangles["cornell box"] == sum(
        s.face_count() for s in mi.load_dict(mi.cornell_box()).shapes())
    assert SMALL_CLOTH <= triangles["cloth"] < 2 * SMALL_CLOTH + 10
    for r in rows:
        assert all(positive(r[key]) for key in RATIOS), r
        assert r["rays"] > 0 and 0.9 <= r["agree"] <= 1, r
        if r["kind"] == "coherent":
            assert r["rays"] == 12 * 12
    status, table, errors = run_cli(capsys, *argv)
    assert status == 0 and not errors
    lines = table.splitlines()
    assert lines[0].split()[:5] == ["scene", "tris", "rays", "rays", "kind"]
    assert len(lines) == 2 + len(rows)
    assert [line.split()[0] for line in lines[2:]] == ["grid"] * 6 + ["cornell"] * 6 + ["cloth"] * 6


def test06_bench_trace_main_flags(capsys):
    """``python -m hlbvh.comparison.bench.trace`` with --no-cornell, --no-cloth,
    --threads and --builder: the grid alone, traced with the builder and threads named."""
    status = bench_trace.main(["--sizes", "2000", "--repeats", "1", "--resolution", "10",
                               "--no-cornell", "--no-cloth", "--threads", "1",
                               "--builder", "lbvh"])
    out = capsys.readouterr().out.splitlines()
    assert status == 0
    assert out[0].startswith(f"hlbvh trace benchmark ({mi.variant()}, builder=lbvh, 1 threads")
    body = out[3:]
    assert len(body) == 6 and all(line.startswith("grid 2k") for line in body)
    for line, (kind, query) in zip(body, KINDS):
        cells = line.split()
        assert cells[4:6] == [kind, query]  # after "grid 2k", triangles, rays
        assert all(positive(float(c)) for c in cells[6:11])  # Mr/s, Embree, three ratios


# ---------------------------------------------------------------------------------------
# bench frame
# ---------------------------------------------------------------------------------------


def test07_hlbvh_bench_frame_through_the_cli(capsys, monkeypatch):
    """``hlbvh bench frame`` hands its options to bench_frame.run and prints its two
    tables (the suite's scenes and drift frames, which the CLI does not set, made small
    here)."""
    seen = {}
    real = bench_frame.run

    def small(**kwargs):
        seen.update(kwargs)
        return real(scenes=("fracture",), spps=(1, 2), drift_frames=2, **kwargs)

    monkeypatch.setattr(bench_frame, "run", small)
    status, table, errors = run_cli(capsys, "bench", "frame", "--sizes", "1500", "--repeats",
                                    "1", "--resolution", "8", "--builder", "lbvh")
    assert status == 0 and not errors
    assert seen == {"repeats": 1, "sizes": [1500], "resolution": (8, 8), "builder": "lbvh"}
    lines = table.splitlines()
    assert lines[0].startswith("per-frame build (ms)")
    assert lines[3].split()[0] == "fracture" and "(over 2 frames)" in lines[3]
    frames = [line for line in lines if line.startswith("fracture") and "|" in line]
    assert [line.split()[2] for line in frames] == ["1", "2"]
    for line in frames:
        ratio = line.split("|")[3].split()[0]
        assert ratio.endswith("x") and positive(float(ratio[:-1]))
    assert "builder=lbvh" in lines[-1]


def test08_bench_frame_main_flags_json(capsys):
    status = bench_frame.main(["--scenes", "twist", "--sizes", "1200", "--spp", "1,2",
                               "--resolution", "8", "--repeats", "1", "--drift-frames", "3",
                               "--builder", "lbvh", "--max-depth", "2", "--json"])
    assert status == 0
    rows = strict_json(capsys.readouterr().out)
    assert [(r["scene"], r["spp"]) for r in rows] == [("twist", 1), ("twist", 2)]
    for r in rows:
        assert set(r) == set(bench_frame.ROW_KEYS)
        assert r["builder"] == "lbvh" and r["drift_frames"] == 3 and r["resolution"] == [8, 8]
        assert r["triangles"] >= 1200
        assert positive(r["native_over_hlbvh"]) and positive(r["sah_drift_max"])
        assert r["sah_drift_max"] >= r["sah_drift_last"]


# ---------------------------------------------------------------------------------------
# readme_figures
# ---------------------------------------------------------------------------------------

FIGURE_FLAGS = ["--build-sizes", "1500", "--sah-max", "1500", "--trace-sizes", "1500",
                "--frame-sizes", "1200", "--frame-scenes", "fracture",
                "--world-triangles", "1500",
                "--sweep-triangles", "1500", "--sweep-settings", "hlbvh,lbvh",
                "--resolution", "8", "--repeats", "1", "--spp", "1", "--spp-curve", "1,2",
                "--frames", "0:2", "--quiet"]


@pytest.mark.slow
def test09_readme_figures_main_and_replot(tmp_path, capsys, small_cloth):
    out = tmp_path / "docs"
    assert readme_figures.main(["--out", str(out), *FIGURE_FLAGS]) == 0
    printed = capsys.readouterr().out
    assert str(out / "bench.md") in printed
    md = (out / "bench.md").read_text()
    for heading in ("## Build (`hlbvh bench build --sizes 1500 --repeats 1`",
                    "## Trace (`hlbvh bench trace --sizes 1500 --resolution 8",
                    "## Frame (`python -m hlbvh.comparison.bench.frame --scenes fracture "
                    "--sizes 1200 --resolution 8 --spp 1,2 --repeats 1 --drift-frames 20`, "
                    "and `--scenes world --sizes 1500` with the same options)",
                    "## Sweep (`hlbvh sweep cloth --triangles 1500 --resolution 8 --spp 1 "
                    "--spp-curve 1,2 --frames 0:2 --settings hlbvh,lbvh`)"):
        assert heading in md, heading
    assert "--sweep-settings hlbvh,lbvh" in md  # the command as given
    document = strict_json((out / "bench.json").read_text())
    built = [(r["mesh"], r["builder"]) for r in document["build"]]
    assert [m for m, b in built if b == "hlbvh"] == ["grid", "soup", "box"]
    assert [b for m, b in built if m == "grid"] == ["hlbvh", "lbvh", "sah"]
    # sah only up to --sah-max triangles
    assert all((r["builder"] == "sah") <= (r["triangles"] <= 1500) for r in document["build"])
    assert {r["scene"] for r in document["trace"]} == {"grid 1k", "cornell box", "cloth"}
    assert [(r["scene"], r["spp"]) for r in document["frame"]] == [
        ("world", 1), ("world", 2), ("fracture", 1), ("fracture", 2)]
    assert [r["setting"] for r in document["sweep"]][-2:] == ["hlbvh", "lbvh"]
    for section, key in (("build", "native_over_ready"), ("trace", "ratio"),
                         ("frame", "native_over_hlbvh")):
        assert all(positive(r[key]) for r in document[section]), section
    assert document["machine_before"]["variant"] == mi.variant()
    plots = [out / "sweep.png", out / "sweep_frame_vs_spp.png"]
    assert all(p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for p in plots)

    # --replot draws both plots again from bench.json alone.
    for p in plots:
        p.unlink()
    assert readme_figures.main(["--out", str(out), "--replot"]) == 0
    assert "drawn from" in capsys.readouterr().out
    assert all(p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for p in plots)


def test07b_bench_frame_takes_scenes_with_options_and_no_native(capsys, monkeypatch):
    """``--scenes`` names scenes with their options (``+`` between a scene's options),
    ``--no-native`` runs hlbvh's frames alone; bad ones are one line, exit status 2."""
    seen = {}
    real = bench_frame.run

    def small(**kwargs):
        seen.update(kwargs)
        return real(spps=(1,), drift_frames=2, **kwargs)

    monkeypatch.setattr(bench_frame, "run", small)
    status, table, errors = run_cli(capsys, "bench", "frame", "--scenes", "flock:birds=3+bird_triangles=24",
                                    "--no-native", "--sizes", "600", "--repeats", "1",
                                    "--resolution", "8")
    assert status == 0 and not errors
    assert seen["scenes"] == ["flock:birds=3,bird_triangles=24"] and seen["native"] is False
    assert "3 instances" in table and "no nat." in table
    for argv, named in ((["frame", "--scenes", "nest"], "'nest'"),
                        (["frame", "--scenes", "flock:wings=2"], "'wings=2'"),
                        (["build", "--scenes", "flock"], "bench frame"),
                        (["trace", "--no-native"], "bench frame")):
        status, _, errors = run_cli(capsys, "bench", *argv)
        assert status == 2 and len(errors) == 1 and named in errors[0]


def test07c_bench_frame_renders_every_scene_with_the_integrator_asked(capsys, monkeypatch):
    """``--integrator direct`` renders both accelerators' frames with ``hlbvh_direct``
    (the table's heading and each row say so); a bad choice, or the flag on another
    suite, is one line, exit status 2."""
    seen = {}
    real = bench_frame.run

    def small(**kwargs):
        seen.update(kwargs)
        return real(scenes=("twist",), spps=(1,), drift_frames=2, **kwargs)

    monkeypatch.setattr(bench_frame, "run", small)
    status, table, errors = run_cli(capsys, "bench", "frame", "--integrator", "direct",
                                    "--sizes", "600", "--repeats", "1", "--resolution", "8")
    assert status == 0 and not errors
    assert seen["integrator"] == "direct"
    assert "hlbvh (hlbvh_direct, accel=hlbvh)" in table
    assert "native (hlbvh_direct, accel=native)" in table
    rows = real(scenes=("twist",), sizes=(600,), spps=(1,), repeats=1,
                           drift_frames=2, resolution=8, integrator="direct")
    assert [r["integrator"] for r in rows] == ["direct"]
    for argv, named in ((["frame", "--integrator", "ptracer"], "'ptracer'"),
                        (["build", "--integrator", "direct"], "bench frame")):
        status, _, errors = run_cli(capsys, "bench", *argv)
        assert status == 2 and len(errors) == 1 and named in errors[0]


# ---------------------------------------------------------------------------------------
# bench frame --shutter: motion blur
# ---------------------------------------------------------------------------------------


def test10_bench_frame_with_a_shutter_times_a_blurred_frame_four_ways(capsys, monkeypatch):
    """``--shutter`` (parsed as ``hlbvh render`` parses it) adds, per scene and spp, our
    blurred frame, our own and native's sub-frame accumulations and our still frame,
    their ratios, the keyed trees' memory and SAH over the shutter, in the JSON rows and
    in a table of their own; ``--motion-keys``/``--sub-frames`` reach them; the flags on
    another suite, or ``--equal-error`` with a closed shutter, are one line."""
    seen = {}
    real = bench_frame.run

    def small(**kwargs):
        seen.update(kwargs)
        return real(scenes=("twist",), spps=(2,), drift_frames=2, **kwargs)

    monkeypatch.setattr(bench_frame, "run", small)
    status, text, errors = run_cli(capsys, "bench", "frame", "--sizes", "600", "--repeats",
                                   "1", "--resolution", "8", "--shutter=-0.5:0.5",
                                   "--motion-keys", "2", "--sub-frames", "2", "--json")
    assert status == 0 and not errors
    assert seen["shutter"] == (-0.5, 0.5) and seen["motion_keys"] == 2 \
        and seen["sub_frames"] == 2
    [row] = strict_json(text)
    assert set(row) == set(bench_frame.ROW_KEYS) | set(bench_frame.BLUR_KEYS)
    assert row["shutter"] == [-0.5, 0.5] and row["motion_keys"] == 2 and row["sub_frames"] == 2
    for key in ("blurred_median_ms", "own_sub_frames_median_ms", "native_sub_frames_median_ms",
                "still_median_ms", "native_sub_over_blurred", "own_sub_over_blurred",
                "blur_overhead", "keyed_degradation"):
        assert positive(row[key]), key
    # three keys' slots and positions over one pose's slots
    assert 3 <= row["keyed_memory_ratio"] < 6
    table = bench_frame.format_table([row])
    blur = table[table.index("motion blur"):].splitlines()
    assert "shutter -0.5:0.5 of a frame, S=2 key intervals, K=2 sub-frames" in blur[0]
    assert blur[1].split()[:9] == ["scene", "tris", "spp", "|", "blurred", "own", "sub",
                                   "nat.", "sub"]
    cells = blur[3].split()
    assert cells[0] == "twist" and cells[2] == "2"
    for argv, named in ((["build", "--shutter", "0.5"], "bench frame"),
                        (["frame", "--shutter", "1:0"], "--shutter '1:0'"),
                        (["frame", "--motion-keys", "2"], "--motion-keys 2"),
                        (["frame", "--equal-error"], "--equal-error")):
        status, _, errors = run_cli(capsys, "bench", *argv)
        assert status == 2 and len(errors) == 1 and named in errors[0], errors


def test11_time_to_equal_error_interpolates_each_methods_time_at_one_rmse():
    """Our blurred frame and native's accumulation at a few spp against our blurred
    frame at a high spp (its own noise taken out): each RMSE falls as its spp rises,
    and each method's time at the common RMSE lies on its log-log line."""
    animation = scenes.get("twist", triangles=600, frames=2)
    ways = bench_frame.blur_renderers(animation, (12, 8), (-0.5, 0.5), 1, 2, max_depth=2)
    result = bench_frame.time_to_equal_error(ways, spps=(1, 4, 16), native_spps=(2, 8, 32),
                                             reference_spp=256)
    assert set(result["levels"]) == {"ours blurred", "native sub-frames"}
    for points in result["levels"].values():
        rmse = [p["rmse"] for p in points]
        assert rmse[0] > rmse[-1] > 0 and all(positive(p["ms"]) for p in points)
    assert positive(result["target_rmse"]) and positive(result["native_over_ours"])
    assert 0 < result["reference_noise_rmse"] < result["levels"]["ours blurred"][-1]["rmse"]
    # the interpolation of hand-made points: time 10 ms at RMSE 0.1, 40 ms at 0.05
    points = [{"ms": 10.0, "rmse": 0.1}, {"ms": 40.0, "rmse": 0.05}]
    assert bench_frame._time_at(points, 0.05 * 2 ** 0.5) == (pytest.approx(20.0), False)
    assert bench_frame._time_at(points, 0.025) == (pytest.approx(160.0), True)
    assert bench_frame._common_rmse([[0.1, 0.05], [0.08, 0.02]]) == pytest.approx(
        (0.05 * 0.08) ** 0.5)


def test12_bench_keyed_topology_ab_prints_both_topologies(capsys):
    """``bench_keyed --topology-ab``: the mid-shutter and the union-box keyed trees of a
    scene's moving meshes, each query's row with its SAH over the shutter, its
    degradation over the still SAH (one number for both queries) and its times."""
    from hlbvh.comparison.bench import keyed as bench_keyed

    assert bench_keyed.main(["--topology-ab", "twist", "--triangles", "600", "--frame", "2",
                             "--frame-resolution", "8x6", "--repeats", "1", "--shutter", "2",
                             "--builder", "sah"]) == 0
    lines = capsys.readouterr().out.splitlines()
    rows = [[c.strip() for c in line.strip("|").split("|")] for line in lines[2:6]]
    assert [(r[0], r[1]) for r in rows] == [("closest", "mid"), ("closest", "union"),
                                            ("any", "mid"), ("any", "union")]
    for r in rows:
        assert positive(float(r[2])) and float(r[3]) > 0.5 and positive(float(r[4]))
    assert rows[0][2:4] == rows[2][2:4] and rows[1][2:4] == rows[3][2:4]
    assert "twist frame 2, sah builder" in lines[7]
