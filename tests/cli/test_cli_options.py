"""``hlbvh render`` and ``hlbvh compare`` with valid values of the builder options,
``--max-depth``, ``--update`` and ``--seed``: each reaches the build (the tree hlbvh.build
returned, spied on where the accelerator calls it, and the statistics' SAH cost) or the
render (the statistics' decisions and seeds, the image); what ``hlbvh doctor`` and the
verbs' ``--help`` say."""

from __future__ import annotations

import json

import numpy as np
import pytest

import hlbvh  # noqa: F401  (sets up Dr.Jit's LLVM and the variant)
from cli_helpers import read_stats, run_cli
from hlbvh.render import images
from hlbvh.accel import mesh_group

SMALL = ["--triangles", "1500", "--resolution", "16", "--spp", "1", "--quiet"]


class _Builds(list):
    seeded: list


@pytest.fixture
def builds(monkeypatch):
    """The BVHs hlbvh.build returns to the accelerator's mesh groups, in call order."""
    made = _Builds()
    real = mesh_group.build

    def spy(vertices, faces, previous=None, **options):
        bvh = real(vertices, faces, previous=previous, **options)
        made.append(bvh)
        seeded.append(previous is not None)
        return bvh

    seeded = made.seeded = []  # per build: whether last frame's tree was offered

    monkeypatch.setattr(mesh_group, "build", spy)
    return made


#: Our HLBVH tracing the moving meshes (the choice by cost would pick Mitsuba's whole
#: scene for these small ones, and the tests are about our tree's options and policy).
OURS = ("--moving-accel", "hlbvh")


def render(capsys, out, *argv, frames="0:1", scene="cloth"):
    """``hlbvh render`` of a small scene into ``out``: its statistics' rows."""
    status, _, errors = run_cli(capsys, "render", scene, *SMALL, "--frames", frames,
                                "--out", out, *argv)
    assert status == 0 and not errors, errors
    return read_stats(out)[0]["frames"]


def image(out, i=0):
    return images.read_exr(out / f"frame_{i:04d}.exr")


@pytest.mark.parametrize("argv, field, value", [
    (["--builder", "sah"], "builder", "sah"),
    (["--builder", "lbvh"], "builder", "lbvh"),
    (["--leaf-size", "2"], "leaf_size", 2),
    (["--morton-bits", "60"], "morton_bits", 60),
    (["--quantization", "axis"], "quantization", "axis"),
    (["--coarse-bits", "9"], "coarse_bits", 9),
    (["--p", "3"], "p", 3),
    (["--builder", "sah", "--sah-bins", "4"], "sah_bins", 4),
])
def test01_builder_options_reach_the_build(tmp_path, capsys, builds, argv, field, value):
    """Each builder option given to ``hlbvh render`` is the option of the tree the
    accelerator built (its BuildConfig; for the Morton bits also its statistics)."""
    render(capsys, tmp_path / "out", *argv)
    assert builds, "the accelerator built nothing"
    assert all(getattr(bvh.config, field) == value for bvh in builds), [
        getattr(bvh.config, field) for bvh in builds]
    if field == "morton_bits":
        assert all(bvh.stats.morton_bits == 60 for bvh in builds)
    if field == "builder":
        assert all(bvh.stats.builder == value for bvh in builds)


def test02_tree_options_show_in_the_statistics(tmp_path, capsys):
    """The statistics' SAH cost is that of the tree the options give: the builders,
    the SAH's bin count and the quantisation of the keys each change it (the same frame
    of the same scene), and an option that leaves the tree alone (``--p``, bit planes
    per emission pass) does not."""
    cost = {}
    for name, argv in {"default": [], "sah": ["--builder", "sah"],
                       "sah4": ["--builder", "sah", "--sah-bins", "4"],
                       "lbvh": ["--builder", "lbvh"],
                       "lbvh_axis": ["--builder", "lbvh", "--quantization", "axis"],
                       "p3": ["--p", "3"]}.items():
        rows = render(capsys, tmp_path / name, *argv, *OURS)
        cost[name] = rows[0]["sah_cost"]
    assert len({cost[k] for k in ("default", "sah", "sah4", "lbvh", "lbvh_axis")}) == 5, cost
    assert cost["p3"] == pytest.approx(cost["default"], rel=1e-6)


def test03_update_reaches_the_accelerator(tmp_path, capsys, builds):
    """``--update``: the statistics' decision per frame is the policy's; ``fresh``
    rebuilds without offering last frame's tree to the sort, ``rebuild`` offers it."""
    decisions, seeded = {}, {}
    for update in ("refit", "rebuild", "fresh"):
        start = len(builds)
        rows = render(capsys, tmp_path / update, "--update", update, *OURS, frames="0:3")
        decisions[update] = [row["decision"] for row in rows]
        seeded[update] = builds.seeded[start:]
    assert decisions["refit"] == ["build", "refit", "refit"]
    assert decisions["rebuild"] == decisions["fresh"] == ["build", "rebuild", "rebuild"]
    assert seeded["rebuild"] == [False, True, True]
    assert seeded["fresh"] == [False, False, False]
    assert seeded["refit"] == [False]


def test04_seed_and_max_depth_reach_the_render(tmp_path, capsys):
    """``--seed S``: frame i is rendered with seed S + i (the statistics say so, and the
    image differs from seed 0's but equals a render of the same frame at that seed);
    ``--max-depth``: a longer path gathers more light."""
    # one structure traces the moving meshes in every run (under auto the choice by
    # measured cost may differ between runs, and so may the last bits of a frame)
    render(capsys, tmp_path / "seed0", *OURS, frames="1:2")
    rows = render(capsys, tmp_path / "seed5", "--seed", "5", *OURS, frames="1:2")
    assert [row["seed"] for row in rows] == [6]
    seed0, seed5 = image(tmp_path / "seed0", 1), image(tmp_path / "seed5", 1)
    assert not np.array_equal(seed0, seed5)
    again = render(capsys, tmp_path / "seed5b", "--seed", "5", *OURS, frames="0:2")
    assert [row["seed"] for row in again] == [5, 6]
    np.testing.assert_array_equal(image(tmp_path / "seed5b", 1), seed5)

    depth = {}
    for d in ("1", "2", "6"):
        render(capsys, tmp_path / f"depth{d}", "--max-depth", d)
        depth[d] = image(tmp_path / f"depth{d}")[..., :3]
    # max_depth 1: only emitters seen directly (the sky); each bounce adds light.
    assert depth["1"].mean() < depth["2"].mean() < depth["6"].mean()


def test05_compare_options_reach_both_renders_and_the_build(tmp_path, capsys, builds):
    """``hlbvh compare`` hands the builder options, --update, --seed and --max-depth on:
    hlbvh's tree has the options, its statistics the policy's decisions and the seeds,
    the report the settings, and both accelerators' images agree as they must."""
    out = tmp_path / "compare"
    status, _, errors = run_cli(
        capsys, "compare", "cloth", *SMALL, "--frames", "0:2", "--out", out,
        "--builder", "lbvh", "--morton-bits", "60", "--quantization", "axis", "--p", "3",
        "--update", "refit", "--seed", "3", "--max-depth", "3", *OURS)
    assert status == 0 and not errors, errors
    assert builds and all((b.config.builder, b.config.morton_bits, b.config.quantization,
                           b.config.p) == ("lbvh", 60, "axis", 3) for b in builds)
    rows = {accel: read_stats(out / accel)[0]["frames"] for accel in ("native", "hlbvh")}
    assert [r["seed"] for r in rows["hlbvh"]] == [r["seed"] for r in rows["native"]] == [3, 4]
    assert [r["decision"] for r in rows["hlbvh"]][1:] == ["refit"]
    results = json.loads((out / "results.json").read_text())
    settings = results["settings"]
    assert settings["max_depth"] == 3 and settings["seed"] == 3
    assert settings["build_options.builder"] == "lbvh" and settings["update"] == "refit"
    assert settings["build_options.morton_bits"] == 60
    # The same seeds and depth on both sides: the images agree pixel for pixel but for
    # the last bits.
    for row in results["rows"]:
        assert row["image.fraction_within_tolerance"] >= 1 - 1 / 256


def test_a_flag_for_a_property_the_scene_leaves_unset_overrides_nothing(tmp_path, capsys):
    """``--update`` or ``--moving-accel`` on a scene whose integrator does not set them
    fills them in silently (and is recorded); one the scene sets is said as overridden."""
    from cli_helpers import read_stats, run_cli, write_twist_scene
    xml, frames = write_twist_scene(tmp_path)
    argv = ["render", xml, "--frames-dir", frames, "--frames", "0:1", "--quiet"]
    status, _, err = run_cli(capsys, *argv, "--update", "refit", "--moving-accel", "hlbvh",
                             "--out", tmp_path / "unset")
    assert status == 0 and err == [], err
    settings = read_stats(tmp_path / "unset")[0]["settings"]
    assert (settings["update"], settings["moving_accel"]) == ("refit", "hlbvh")
    xml.write_text(xml.read_text().replace(
        '<integrator type="path"><integer name="max_depth" value="8"/>',
        '<integrator type="hlbvh_path"><integer name="max_depth" value="8"/>'
        '<string name="update" value="rebuild"/>'))
    status, _, err = run_cli(capsys, *argv, "--update", "refit", "--out", tmp_path / "set")
    assert status == 0 and len(err) == 1
    assert "--update refit (the scene's update: 'rebuild')" in err[0]


def test06_doctor_reports_usd_core(capsys, monkeypatch):
    """Its version where it is installed, how to install it where it is not (USD
    stages need it)."""
    from importlib import metadata
    Usd = pytest.importorskip("pxr.Usd")
    status, out, _ = run_cli(capsys, "doctor")
    version = ".".join(map(str, Usd.GetVersion()))
    assert status == 0
    assert f"usd-core   {metadata.version('usd-core')} (pxr {version})" in out.splitlines()
    monkeypatch.setitem(__import__("sys").modules, "pxr", None)  # import pxr fails
    status, out, _ = run_cli(capsys, "doctor")
    assert status == 0
    assert "usd-core   not installed (pip install usd-core)" in out.splitlines()


@pytest.mark.parametrize("verb, description", [
    ("doctor", "Report Dr.Jit, Mitsuba, the libLLVM in use, variants, usd-core"),
    ("bench", "Build, trace, frame and prb benchmarks against native"),
])
def test07_verbs_help_has_a_description(capsys, verb, description):
    with pytest.raises(SystemExit):
        run_cli(capsys, verb, "--help")
    out = capsys.readouterr().out
    assert description in out.split("\n\n")[1], out

