"""``hlbvh render`` (and compare, sweep, bench) as a careless or hostile user drives
it: a full disk, files truncated behind its back, a kill between two writes, two
writers on one folder, huge numbers, bad paths, Ctrl-C inside a Dr.Jit loop, inside
Mitsuba's render and while the command starts, instanced scenes, corrupt meshes and
frame entries that are not readable mesh files, a scene edited between resumes, the
scene's own integrator, unbounded clusters and schedulers that do not speak Dask.
Every case ends in complete frames only and, for a user error, one line naming the
flag or file, exit status 2."""

import errno
import fcntl
import json
import os
import shutil
import socket
import subprocess
import sys
import threading
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import hlbvh
from cli_helpers import interrupt_second_render, read_stats, run_cli, write_twist_scene
from meshes import soup
from hlbvh import scenes
from hlbvh.render import images
from hlbvh.render import output
from hlbvh.render.frame import FrameRenderer
from hlbvh.render.output import LOCK_NAME
from hlbvh.render.animation import render_animation
from hlbvh.render.settings import RenderSettings
from hlbvh.scenes import FrameGeometry, apply_frame, sequence
from hlbvh.scenes.procedural import mesh_object

TINY = ["--triangles", "200", "--resolution", "16", "--spp", "1", "--accel", "native",
        "--quiet"]
#: TINY under the command's default accelerator (or the --accel a test passes itself).
TINY_ANY_ACCEL = [a for a in TINY if a not in ("--accel", "native")]


def stats(directory):
    document, table = read_stats(directory)
    return [row["frame"] for row in document["frames"]], [int(r["frame"]) for r in table]


def frame_path(directory, i, ext):
    return directory / f"frame_{i:04d}.{ext}"


def assert_only_complete_frames(directory):
    """Every frame file decodes whole, every row's frame has both files, json and csv
    agree, no temporary file is left."""
    assert not list(directory.glob(".*.tmp")), list(directory.glob(".*.tmp"))
    rows = set()
    if (directory / "stats.json").exists():
        json_rows, csv_rows = stats(directory)
        assert json_rows == csv_rows
        rows = set(json_rows)
    for path in [*directory.glob("frame_*.exr"), *directory.glob("frame_*.png")]:
        images.check_image(path)
    for i in rows:
        assert frame_path(directory, i, "exr").is_file() and frame_path(directory, i, "png").is_file()


def mtimes(directory):
    return {p.name: p.stat().st_mtime_ns for p in directory.iterdir()}


def mount_tmpfs(path, options):
    """Mount a tmpfs (as root); skip the test where that is not allowed."""
    path.mkdir(parents=True, exist_ok=True)
    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("mounting a tmpfs needs root")
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(path)],
                          capture_output=True, text=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.strip()}")


def write_scene(root, instances=False, frames=3):
    """A twisting bar (PLY frames) over a floor; with ``instances`` also a shape group
    instanced once (:func:`cli_helpers.write_twist_scene`)."""
    return write_twist_scene(root, triangles=400, frames=frames, instances=instances)


# ---------------------------------------------------------------------------------------
# A full disk, a short write
# ---------------------------------------------------------------------------------------


def test01_full_disk_leaves_only_complete_frames_and_one_line(tmp_path, capsys):
    disk = tmp_path / "disk"
    mount_tmpfs(disk, "size=24k")
    try:
        status, _, err = run_cli(capsys, "render", "cloth", "--frames", "0:12", "--out", disk,
                                 *TINY[:2], "--resolution", "48", *TINY[4:])
        assert status == 2 and len(err) == 1, err
        assert "could not be written" in err[0] and "--out" in err[0]
        assert_only_complete_frames(disk)
        kept = tmp_path / "kept"
        shutil.copytree(disk, kept)
    finally:
        subprocess.run(["umount", str(disk)], check=True)
    # The same command on a disk with room finishes the frames.
    status, out, _ = run_cli(capsys, "render", "cloth", "--frames", "0:12", "--out", kept,
                             *TINY[:2], "--resolution", "48", *TINY[4:])
    assert status == 0 and "already complete" in out
    assert stats(kept)[0] == list(range(12))
    assert_only_complete_frames(kept)


def test02_a_short_write_reported_as_success_is_caught(tmp_path, capsys, monkeypatch):
    """A writer that says it succeeded while its file was cut short (what OpenImageIO
    does on a full disk) never puts the file in place."""
    create = images.oiio.ImageOutput.create
    written = []

    class Short:
        def __init__(self, output):
            self.output = output

        def open(self, path, spec):
            self.path = path
            return self.output.open(path, spec)

        def write_image(self, pixels):
            return self.output.write_image(pixels)

        def geterror(self):
            return self.output.geterror()

        def close(self):
            closed = self.output.close()
            written.append(self.path)
            if len(written) == 3:  # frame 1's EXR
                with open(self.path, "r+b") as f:
                    f.truncate(os.path.getsize(self.path) // 2)
            return closed

    monkeypatch.setattr(images.oiio.ImageOutput, "create",
                        staticmethod(lambda name: Short(create(name))))
    out = tmp_path / "out"
    status, _, err = run_cli(capsys, "render", "cloth", "--frames", "0:3", "--out", out, *TINY)
    assert status == 2 and len(err) == 1 and "frame 1 could not be written" in err[0], err
    assert "does not decode whole" in err[0]
    assert not frame_path(out, 1, "exr").exists() and stats(out) == ([0], [0])
    assert_only_complete_frames(out)


def test03_a_failed_statistics_write_stops_and_the_next_run_heals(tmp_path, capsys,
                                                                  monkeypatch):
    out = tmp_path / "out"
    real = output.Statistics._write_csv
    calls = []

    def failing(self):
        calls.append(1)
        if len(calls) == 2:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real(self)

    monkeypatch.setattr(output.Statistics, "_write_csv", failing)
    status, _, err = run_cli(capsys, "render", "cloth", "--frames", "0:3", "--out", out, *TINY)
    assert status == 2 and len(err) == 1 and "No space left on device" in err[0], err
    monkeypatch.undo()
    status, out_text, _ = run_cli(capsys, "render", "cloth", "--frames", "0:3", "--out", out,
                                  *TINY)
    assert status == 0 and "1 rendered, 2 already complete" in out_text
    assert stats(out) == ([0, 1, 2], [0, 1, 2])


# ---------------------------------------------------------------------------------------
# Resume checks the files, and heals the csv
# ---------------------------------------------------------------------------------------


def test04_resume_rerenders_truncated_and_empty_frames(tmp_path, capsys):
    out = tmp_path / "out"
    argv = ["render", "cloth", "--frames", "0:5", "--out", out, *TINY]
    assert run_cli(capsys, *argv)[0] == 0
    with open(frame_path(out, 3, "exr"), "r+b") as f:
        f.truncate(100)
    frame_path(out, 4, "png").write_bytes(b"")
    status, out_text, _ = run_cli(capsys, *argv)
    assert status == 0 and "2 rendered, 3 already complete" in out_text
    assert_only_complete_frames(out)
    assert stats(out)[0] == [0, 1, 2, 3, 4]


def test05_a_kill_between_json_and_csv_is_healed(tmp_path, capsys):
    out = tmp_path / "out"
    argv = ["render", "cloth", "--frames", "0:3", "--out", out, *TINY]
    assert run_cli(capsys, *argv)[0] == 0
    lines = (out / "stats.csv").read_text().splitlines(keepends=True)
    (out / "stats.csv").write_text("".join(lines[:-1]))  # the last frame's row not yet written
    status, out_text, _ = run_cli(capsys, *argv)
    assert status == 0 and "0 rendered, 3 already complete" in out_text
    assert stats(out) == ([0, 1, 2], [0, 1, 2])


# ---------------------------------------------------------------------------------------
# One writer per folder
# ---------------------------------------------------------------------------------------


def test06_a_second_writer_is_refused_and_changes_nothing(tmp_path, capsys):
    out = tmp_path / "out"
    argv = ["render", "cloth", "--frames", "0:2", "--out", out, *TINY]
    assert run_cli(capsys, *argv)[0] == 0
    in_flight = out / ".frame_0002.exr.0123abcd.tmp"  # the other run's temporary file
    in_flight.write_bytes(b"half")
    with open(out / LOCK_NAME, "a+") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        lock.write(json.dumps({"pid": os.getpid(), "host": socket.gethostname()}))
        lock.flush()
        before = mtimes(out)
        status, _, err = run_cli(capsys, "render", "cloth", "--frames", "0:4", "--out", out,
                                 *TINY[:4], "--spp", "4", *TINY[6:])
        assert status == 2 and len(err) == 1, err
        assert "another render" in err[0] and f"process {os.getpid()}" in err[0]
        assert mtimes(out) == before and in_flight.exists()


def test07_a_lock_left_by_a_dead_process_is_taken_over(tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    (out / LOCK_NAME).write_text(json.dumps({"pid": dead.pid, "host": socket.gethostname()}))
    status, _, err = run_cli(capsys, "render", "cloth", "--frames", "0:1", "--out", out, *TINY)
    assert status == 0
    assert any("taking over" in line and f"process {dead.pid}" in line for line in err), err
    assert not (out / LOCK_NAME).exists()


# ---------------------------------------------------------------------------------------
# Big numbers
# ---------------------------------------------------------------------------------------


class Frames:
    """A frame range that fails the test when more than ``limit`` frames are drawn from
    it: a billion frames must be iterated, never listed."""

    def __init__(self, frames, limit):
        self.frames, self.limit = frames, limit

    def __len__(self):
        return len(self.frames)

    def __getitem__(self, k):
        return self.frames[k]

    def __iter__(self):
        for count, i in enumerate(self.frames):
            assert count < self.limit, "the frame range is being listed"
            yield i


def test08_a_billion_frames_are_iterated_not_listed(tmp_path, monkeypatch):
    animation = scenes.get("cloth", triangles=200, frames=10**9)
    settings = RenderSettings(resolution=(8, 8), spp=1, accel="native")
    real = FrameRenderer.render
    calls = []

    def render_twice(self, i, spp=None):
        calls.append(i)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(self, i, spp)

    monkeypatch.setattr(FrameRenderer, "render", render_twice)
    with pytest.raises(KeyboardInterrupt):
        render_animation(animation, Frames(range(0, 10**9), 5), tmp_path, settings,
                         progress=False)
    assert calls == [0, 1] and stats(tmp_path) == ([0], [0])
    assert not (tmp_path / LOCK_NAME).exists()


@pytest.mark.parametrize("argv, message", [
    (["--resolution", "100000x100000"], "4294967295"),
    (["--seed", "4294967295", "--frames", "0:3"], "--seed 4294967293 or less"),
    (["--seed", "5000000000"], "--seed '5000000000'"),
])
def test09_sizes_and_seeds_past_their_limits_are_refused_before_any_frame(
        tmp_path, capsys, argv, message):
    out = tmp_path / "out"
    status, _, err = run_cli(capsys, "render", "cloth", "--out", out, *TINY, *argv)
    assert status == 2 and len(err) == 1 and message in err[0], err
    assert not list(out.glob("frame_*"))


def test10_a_frame_larger_than_the_memory_limit_is_refused(tmp_path):
    """12000² under an address-space limit: refused with the limit, not a crash."""
    code = f"""
import resource, sys
from hlbvh import cli
vm = [int(l.split()[1]) * 1024 for l in open("/proc/self/status") if l.startswith("VmSize")][0]
resource.setrlimit(resource.RLIMIT_AS, (vm + 2 * 2**30, resource.RLIM_INFINITY))
sys.exit(cli.main(["render", "cloth", "--triangles", "200", "--frames", "0:1", "--resolution",
                   "12000", "--spp", "1", "--accel", "native", "--quiet", "--out", {str(tmp_path)!r}]))
"""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=300)
    assert done.returncode == 2, done.stderr
    assert done.stderr.count("\n") == 1 and "GiB" in done.stderr and "--resolution" in done.stderr
    assert not list(tmp_path.glob("frame_*"))


# ---------------------------------------------------------------------------------------
# User errors of every verb: one line, exit status 2
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("verb", ["render", "compare", "sweep"])
@pytest.mark.parametrize("out, message", [
    ("{file}", "is not a directory"),
    ("{file}/sub", "cannot create it"),
    ("/dev/null", "is not a directory"),
    ("", "--out '': an empty path"),
])
def test11_bad_out_paths(tmp_path, capsys, verb, out, message):
    afile = tmp_path / "afile"
    afile.write_text("x")
    argv = [verb, "cloth", "--frames", "0:2", "--out", out.format(file=afile), *TINY]
    if verb != "render":
        argv.remove("--accel")
        argv.remove("native")
    status, _, err = run_cli(capsys, *argv)
    assert status == 2 and len(err) == 1 and "--out" in err[0] and message in err[0], err


def test12_read_only_out_and_a_frame_path_that_is_a_directory(tmp_path, capsys):
    frozen = tmp_path / "frozen"
    if os.geteuid() == 0:
        mount_tmpfs(frozen, "ro,size=64k")
    else:
        frozen.mkdir()
        frozen.chmod(0o500)
    try:
        status, _, err = run_cli(capsys, "render", "cloth", "--out", frozen / "x", *TINY)
        assert status == 2 and len(err) == 1 and f"--out {frozen / 'x'}" in err[0], err
        status, _, err = run_cli(capsys, "render", "cloth", "--out", frozen, *TINY)
        assert status == 2 and len(err) == 1 and "cannot be written" in err[0], err
    finally:
        if os.geteuid() == 0:
            subprocess.run(["umount", str(frozen)], check=True)
    out = tmp_path / "out"
    frame_path(out, 1, "exr").mkdir(parents=True)
    status, _, err = run_cli(capsys, "render", "cloth", "--frames", "0:3", "--out", out, *TINY)
    assert status == 2 and len(err) == 1 and "frame 1 could not be written" in err[0], err
    assert "frame_0001.exr" in err[0] and stats(out)[0] == [0]


@pytest.mark.parametrize("argv, flag", [
    (["bench", "build", "--sizes", "0"], "--sizes"),
    (["bench", "build", "--sizes", "-5"], "--sizes"),
    (["bench", "build", "--sizes", "abc"], "--sizes"),
    (["bench", "build", "--repeats", "-1"], "--repeats"),
    (["bench", "trace", "--resolution", "0"], "--resolution"),
    (["bench", "trace", "--builder", "bvh"], "--builder"),
    (["compare", "cloth", "--seed", "5e9"], "--seed"),
    (["compare", "cloth", "--seed", "5000000000"], "--seed"),
    (["sweep", "cloth", "--triangles", "200", "--seed", "4294967295"], "--seed"),
])
def test13_bench_compare_and_sweep_flags(tmp_path, capsys, argv, flag):
    status, _, err = run_cli(capsys, *argv, *(["--out", tmp_path / "o"] if argv[0] != "bench" else []))
    assert status == 2 and len(err) == 1 and err[0].startswith(f"hlbvh {argv[0]}: {flag}"), err
    assert not (tmp_path / "o").exists()


def test14_ctrl_c_inside_a_dr_jit_loop_exits_130_with_complete_frames(tmp_path, capsys,
                                                                       monkeypatch):
    """Dr.Jit turns a KeyboardInterrupt inside a traced loop into a RuntimeError."""
    real = FrameRenderer._update_accel
    calls = []

    def follow(self, *args):
        calls.append(1)
        if len(calls) == 2:
            def body(k):
                raise KeyboardInterrupt
            dr.while_loop((mi.UInt32(0),), lambda k: k < 3, body)
        return real(self, *args)

    monkeypatch.setattr(FrameRenderer, "_update_accel", follow)
    out = tmp_path / "out"
    argv = TINY_ANY_ACCEL
    status, _, err = run_cli(capsys, "render", "cloth", "--frames", "0:3", "--out", out, *argv)
    assert status == 130 and err == ["hlbvh render: interrupted"]
    assert stats(out) == ([0], [0]) and not frame_path(out, 1, "exr").exists()
    assert_only_complete_frames(out)
    assert not (out / LOCK_NAME).exists()


# ---------------------------------------------------------------------------------------
# Instances
# ---------------------------------------------------------------------------------------


def test15_static_instances_render_with_both_accelerators_alike(tmp_path, capsys):
    """A still instance is traced by Mitsuba's own accelerator under the default
    static="native": hlbvh's frames equal native's (the moving mesh through our BVH)."""
    xml, frames = write_scene(tmp_path, instances=True)
    rendered = {}
    for accel in ("native", "hlbvh"):
        out = tmp_path / accel
        status, _, err = run_cli(capsys, "render", xml, "--frames-dir", frames, "--frames",
                                 "0:2", "--accel", accel, "--out", out, "--quiet")
        assert status == 0, err
        rendered[accel] = images.read_exr(frame_path(out, 0, "exr"), ["R", "G", "B"])
    reference = np.asarray(mi.render(mi.load_file(str(xml)), seed=0))
    np.testing.assert_allclose(rendered["native"], reference, atol=1e-4)
    np.testing.assert_allclose(rendered["hlbvh"], rendered["native"], atol=1e-3)
    plain_xml, _ = write_scene(tmp_path / "plain")
    plain = np.asarray(mi.render(mi.load_file(str(plain_xml)), seed=0))
    assert np.abs(plain - rendered["hlbvh"]).max() > 0.05  # the instance is in the picture


# ---------------------------------------------------------------------------------------
# Minor ones
# ---------------------------------------------------------------------------------------


def test16_random_bytes_in_a_ply_name_the_file_and_frame(tmp_path, capsys):
    xml, frames = write_scene(tmp_path)
    garbage = b"ply\nformat ascii 1.0\n" + bytes(range(128, 256)) * 3
    (frames / "bar" / "frame_0002.ply").write_bytes(garbage)
    status, _, err = run_cli(capsys, "render", xml, "--frames-dir", frames, "--out",
                             tmp_path / "out", *TINY[2:])
    assert status == 2 and len(err) == 1, err
    assert "frame 1 of shape 'bar'" in err[0] and "frame_0002.ply" in err[0]
    (tmp_path / "bar.ply").write_bytes(garbage)
    status, _, err = run_cli(capsys, "render", xml, "--frames-dir", frames, "--out",
                             tmp_path / "out", *TINY[2:])
    assert status == 2 and len(err) == 1 and "scene.xml" in err[0], err


def test17_the_changing_topology_hint_is_a_flag_the_cli_takes(tmp_path, capsys):
    xml, frames = write_scene(tmp_path)
    smaller = scenes.get("twist", triangles=100, frames=1)
    mesh_object("bar", smaller.frame(0)["bar"].positions.reshape(-1, 3),
                smaller.parts["bar"].faces, {"type": "diffuse"}).write_ply(
        str(frames / "bar" / "frame_0002.ply"))
    argv = ["render", xml, "--frames-dir", frames, *TINY[2:]]
    status, _, err = run_cli(capsys, *argv, "--out", tmp_path / "fixed")
    assert status == 2 and len(err) == 1 and "--topology bar=changing" in err[0], err
    for topology in ("bar=changing", "changing"):
        out = tmp_path / topology
        status, _, err = run_cli(capsys, *argv, "--topology", topology, "--out", out)
        assert status == 0, err
        assert stats(out)[0] == [0, 1, 2]
    status, _, err = run_cli(capsys, *argv, "--topology", "bar:changing", "--out", tmp_path / "x")
    assert status == 2 and len(err) == 1 and err[0].startswith("hlbvh render: --topology"), err


@pytest.mark.slow
@pytest.mark.parametrize("flag, value", [
    ("SymbolicConditionals", False), ("KernelFreezing", False), ("OptimizeLoops", False),
    ("PacketOps", False), ("Debug", True),
])
def test18_dr_jit_flags_change_no_tree_and_no_hit(flag, value):
    """Whatever a user sets among Dr.Jit's flags (conditionals evaluated, no kernel
    freezing, no loop optimisation, no packet gathers, debug checks), the build, the
    refit and both traversals give the same arrays and hits as with the defaults."""
    from hlbvh.kernels import traversal

    V, F = soup(1500, seed=5)
    Vf, Ff = mi.Float(np.ravel(V).astype(np.float32)), mi.UInt32(np.ravel(F))
    rng = np.random.default_rng(1)
    o = mi.Point3f(*rng.uniform(-0.2, 1.2, (3, 1000)).astype(np.float32))
    d = mi.Vector3f(*rng.normal(size=(3, 1000)).astype(np.float32))

    def run():
        bvh = hlbvh.build(Vf, Ff)
        hits = traversal.closest_hit(bvh, o, d, mi.Float(np.inf))
        occluded = traversal.any_hit(bvh, o, d, mi.Float(np.inf))
        tree = (bvh.node_min, bvh.node_first, bvh.prim_ids)
        bvh.refit(Vf * 1.01)
        refit = traversal.closest_hit(bvh, o, d, mi.Float(np.inf))[0]
        return [np.array(x) for x in (*hits, occluded, *tree, refit, bvh.node_max)]

    expected = run()
    with dr.scoped_set_flag(getattr(dr.JitFlag, flag), value):
        got = run()
    for a, b in zip(got, expected):
        np.testing.assert_array_equal(a, b)


# ---------------------------------------------------------------------------------------
# Ctrl-C while rendering
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("accel", ["hlbvh", "native"])
def test19_ctrl_c_inside_mitsubas_render_stops_after_the_frame_and_resumes(
        tmp_path, capsys, monkeypatch, accel):
    """SIGINT raised inside ``mi.render`` (while Mitsuba's own handler is installed)
    stops the loop after that frame, exit 130; the same command renders the rest."""
    interrupt_second_render(monkeypatch)
    out = tmp_path / "out"
    argv = ["render", "cloth", "--frames", "0:4", "--accel", accel, "--out", out, *TINY_ANY_ACCEL]
    status, _, err = run_cli(capsys, *argv)
    assert status == 130 and err == ["hlbvh render: interrupted"], err
    assert stats(out) == ([0, 1], [0, 1]) and not (out / LOCK_NAME).exists()
    monkeypatch.undo()
    status, text, _ = run_cli(capsys, *argv)
    assert status == 0 and "2 rendered, 2 already complete" in text


# ---------------------------------------------------------------------------------------
# Frame files: every entry that looks like a frame is read or named; what Mitsuba's
# loader would misread or fail on is named with its frame and file
# ---------------------------------------------------------------------------------------


def ascii_ply(path, vertices, faces, index_type="int"):
    """An ASCII PLY of ``vertices`` (rows of x y z) and ``faces`` (rows of indices)."""
    lines = ["ply", "format ascii 1.0", f"element vertex {len(vertices)}",
             "property float x", "property float y", "property float z",
             f"element face {len(faces)}", f"property list uchar {index_type} vertex_indices",
             "end_header"]
    lines += [" ".join(map(str, v)) for v in vertices]
    lines += [" ".join(map(str, [len(f), *f])) for f in faces]
    path.write_text("\n".join(lines) + "\n")


def binary_ply(path, vertices, faces):
    """A little-endian binary PLY with signed 32-bit indices."""
    vertices = np.asarray(vertices, dtype="<f4")
    rows = np.zeros(len(faces), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    rows["n"], rows["i"] = 3, faces
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {len(vertices)}\nproperty float x\nproperty float y\n"
              f"property float z\nelement face {len(faces)}\n"
              "property list uchar int vertex_indices\nend_header\n")
    path.write_bytes(header.encode() + vertices.tobytes() + rows.tobytes())


QUAD = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)]


def break_frame(frames, case):
    """Make frame 1 (or, for links, a frame after the last) of shape ``bar`` what
    ``case`` names; returns the file the message must name."""
    bar = frames / "bar"
    second = bar / "frame_0002.ply"
    if case == "dangling link":
        (bar / "frame_0004.ply").symlink_to(bar / "gone.ply")
        return bar / "frame_0004.ply"
    if case == "looping link":
        (bar / "frame_0004.ply").symlink_to(bar / "frame_0004.ply")
        return bar / "frame_0004.ply"
    if case == "negative index, ascii":
        ascii_ply(second, QUAD, [(0, 1, 2), (0, 2, -1)])
    elif case == "negative index, binary":
        binary_ply(second, QUAD, [(0, 1, 2), (-1, 2, 3)])
    elif case == "face past the end":
        ascii_ply(second, QUAD, [(0, 1, 2), (0, 2, 9)])
    elif case == "no vertices":
        ascii_ply(second, [], [])
    elif case == "empty file":
        second.write_bytes(b"")
    elif case == "PLY named .obj":
        second.rename(bar / "frame_0002.obj")
        return bar / "frame_0002.obj"
    return second


@pytest.mark.parametrize("case, message", [
    ("dangling link", "a symbolic link that leads to no file (No such file or directory); "
                      "make it a readable mesh file or remove it"),
    ("looping link", "a symbolic link that leads to no file (Too many levels of symbolic "
                     "links); make it a readable mesh file or remove it"),
    ("negative index, ascii", "face 1 has vertex index -1; indices must be 0 or more"),
    ("negative index, binary", "face 1 has vertex index -1; indices must be 0 or more"),
    ("face past the end", "a face has vertex index 9, past its 4 vertices"),
    ("no vertices", "Mitsuba read 0 vertices and 0 faces from it; a frame needs at least "
                    "one triangle"),
    ("empty file", "the file is empty (0 bytes)"),
    ("PLY named .obj", "it holds PLY data but is named .obj; name it .ply"),
])
def test20_frame_files_that_are_not_meshes_name_the_frame_and_file(tmp_path, capsys, case,
                                                                  message):
    xml, frames = write_twist_scene(tmp_path, triangles=100)
    named = break_frame(frames, case)
    out = tmp_path / "out"
    status, _, err = run_cli(capsys, "render", xml, "--frames-dir", frames, "--topology",
                             "changing", "--accel", "native", "--out", out, *TINY_ANY_ACCEL[2:])
    assert status == 2 and len(err) == 1, err
    if "link" in case:
        where = f"frame file {str(named)!r} of shape 'bar': "
    else:
        where = f"frame 1 of shape 'bar' ({str(named)!r}): "
    assert err[0] == f"hlbvh render: {where}{message}"
    assert not list(out.glob("frame_0001.*"))


def test21_an_unreadable_frames_folder_and_scene_file_are_named(tmp_path, capsys, monkeypatch):
    """A folder that cannot be listed and a scene that cannot be read (as a user
    without root's override meets them) get one line each."""
    xml, frames = write_twist_scene(tmp_path, triangles=100)
    argv = ["render", xml, "--frames-dir", frames, "--out", tmp_path / "out", *TINY_ANY_ACCEL[2:]]
    real_iterdir, real_open = Path.iterdir, open

    def iterdir(self):
        if self == (frames / "bar").resolve():
            raise PermissionError(13, "Permission denied", str(self))
        return real_iterdir(self)

    monkeypatch.setattr(Path, "iterdir", iterdir)
    status, _, err = run_cli(capsys, *argv)
    assert status == 2 and err == [
        f"hlbvh render: frames directory {str((frames / 'bar').resolve())!r}: cannot be "
        f"listed (Permission denied)"], err
    monkeypatch.undo()

    def unreadable(name, *args, **kwargs):
        if Path(name) == xml:
            raise PermissionError(13, "Permission denied", str(name))
        return real_open(name, *args, **kwargs)

    monkeypatch.setattr(sequence, "open", unreadable, raising=False)
    status, _, err = run_cli(capsys, *argv)
    assert status == 2 and err == [
        f"hlbvh render: scene {str(xml)!r}: the file cannot be read (Permission denied)"], err


def test22_apply_frame_takes_tensors_and_vectors_and_names_other_types():
    animation = scenes.get("cloth", triangles=200)
    scene = mi.load_dict(animation.scene_dict(resolution=(8, 8), spp=1))
    (shape, geometry), = animation.frame(3).items()
    flat = np.asarray(geometry.positions, dtype=np.float32).reshape(-1)
    for given in (mi.TensorXf(flat.reshape(-1, 3)), mi.Point3f(flat.reshape(-1, 3).T)):
        apply_frame(scene, None, {shape: FrameGeometry(given)})
        np.testing.assert_array_equal(np.asarray(mi.traverse(scene)[f"{shape}.vertex_positions"]),
                                      flat)
    with pytest.raises(ValueError) as raised:
        apply_frame(scene, None, {shape: FrameGeometry(flat.tolist())})
    assert str(raised.value) == (
        f"frame geometry for shape {shape!r}: positions of type list; expected a flat numpy "
        f"or Dr.Jit array (3 per entry), a tensor, or an array of 3-vectors")


# ---------------------------------------------------------------------------------------
# What the scene file decides: recorded, checked on resume, honoured
# ---------------------------------------------------------------------------------------

PATH_8 = '<integrator type="path"><integer name="max_depth" value="8"/></integrator>'


def edit(xml, old, new):
    text = xml.read_text()
    assert old in text
    xml.write_text(text.replace(old, new))


def test23_a_scene_edited_between_resumes_is_refused_in_one_line(tmp_path, capsys):
    xml, frames = write_twist_scene(tmp_path, triangles=100)
    out = tmp_path / "out"
    argv = ["render", xml, "--frames-dir", frames, "--accel", "native", "--out", out, "--quiet"]
    assert run_cli(capsys, *argv, "--frames", "0:2")[0] == 0
    document, _ = read_stats(out)
    assert (document["settings"]["resolution"], document["settings"]["spp"]) == ([24, 16], 1)
    assert len(document["settings"]["scene_sha256"]) == 64
    before = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    edit(xml, '"width" value="24"', '"width" value="32"')
    edit(xml, '"sample_count" value="1"', '"sample_count" value="4"')
    status, _, err = run_cli(capsys, *argv, "--frames", "0:3")
    assert status == 2 and err == [
        f"hlbvh render: {out} holds frames rendered with other settings (resolution: "
        f"[24, 16] -> [32, 16], scene_sha256: the scene file or a file it names was edited, "
        f"spp: 1 -> 4); choose another --out, or remove the directory to start over"], err
    assert {p.name: p.stat().st_mtime_ns for p in out.iterdir()} == before
    # A file the scene includes, and a file it names (its mesh), each edited alone.
    edit(xml, '"width" value="32"', '"width" value="24"')
    edit(xml, '"sample_count" value="4"', '"sample_count" value="1"')
    edit(xml, '<emitter type="constant"/>', '<include filename="light.xml"/>')
    light = tmp_path / "light.xml"
    light.write_text('<scene version="3.0.0"><emitter type="constant"/></scene>')
    brighter = (b'<scene version="3.0.0"><emitter type="constant"><rgb name="radiance" '
                b'value="2"/></emitter></scene>')
    moved = (frames / "bar" / "frame_0002.ply").read_bytes()
    for k, (path, edited) in enumerate([(light, brighter), (tmp_path / "bar.ply", moved)]):
        again = tmp_path / f"again{k}"
        base = ["render", xml, "--frames-dir", frames, "--accel", "native", "--out", again,
                "--quiet"]
        assert run_cli(capsys, *base, "--frames", "0:1")[0] == 0
        original = path.read_bytes()
        path.write_bytes(edited)
        status, _, err = run_cli(capsys, *base, "--frames", "0:3")
        path.write_bytes(original)
        assert status == 2 and err == [
            f"hlbvh render: {again} holds frames rendered with other settings (scene_sha256: "
            f"the scene file or a file it names was edited); choose another --out, or remove "
            f"the directory to start over"], err


def test24_the_scenes_own_integrator_is_honoured_and_a_flag_says_what_it_overrides(
        tmp_path, capsys):
    xml, frames = write_twist_scene(tmp_path, triangles=100)
    edit(xml, PATH_8, '<integrator type="hlbvh_path"><string name="accel" value="native"/>'
                      '<integer name="max_depth" value="1"/></integrator>')
    out = tmp_path / "out"
    argv = ["render", xml, "--frames-dir", frames, "--frames", "0:1", "--quiet"]
    status, _, err = run_cli(capsys, *argv, "--out", out)
    assert status == 0 and err == [], err
    settings = read_stats(out)[0]["settings"]
    assert (settings["integrator"], settings["accel"], settings["max_depth"]) == ("path", "native", 1)
    ours = images.read_exr(out / "frame_0000.exr", ["R", "G", "B"])
    reference = np.asarray(mi.render(mi.load_file(str(xml)), seed=0))
    np.testing.assert_allclose(ours, reference, atol=1e-4)

    status, _, err = run_cli(capsys, *argv, "--max-depth", "3", "--accel", "hlbvh",
                             "--out", tmp_path / "flags")
    assert status == 0 and err == [
        "hlbvh render: the command line overrides the scene's integrator 'hlbvh_path': "
        "--max-depth 3 (the scene's max_depth: 1), --accel hlbvh (the scene's accel: "
        "'native')"], err
    settings = read_stats(tmp_path / "flags")[0]["settings"]
    assert (settings["accel"], settings["max_depth"]) == ("hlbvh", 3)

    edit(xml, '<integer name="max_depth" value="1"/></integrator>', '</integrator>')
    edit(xml, 'type="hlbvh_path"><string name="accel" value="native"/>', 'type="direct">')
    status, _, err = run_cli(capsys, *argv, "--out", tmp_path / "direct")
    assert status == 0 and err == [
        "hlbvh render: the scene's integrator 'direct' runs as hlbvh_direct (which mirrors "
        "it, every ray through the chosen accelerator)"], err
    edit(xml, 'type="direct">', 'type="ptracer">')
    status, _, err = run_cli(capsys, *argv, "--out", tmp_path / "ptracer")
    assert status == 2 and len(err) == 1 and err[0].startswith(
        f"hlbvh render: scene {str(xml)!r}: its integrator 'ptracer' is not one hlbvh render "
        f"runs ("), err
    status, _, err = run_cli(capsys, *argv, "--integrator", "aov", "--out", tmp_path / "aov")
    assert status == 0 and err == [
        "hlbvh render: --integrator aov overrides the scene's integrator 'ptracer' (its "
        "properties are not used)"], err


# ---------------------------------------------------------------------------------------
# Clusters: bounded by the machine; schedulers that do not speak Dask
# ---------------------------------------------------------------------------------------


def test25_a_local_cluster_is_bounded_by_the_machine(tmp_path, capsys, monkeypatch):
    cluster = pytest.importorskip("hlbvh.render.cluster")
    argv = ["render", "cloth", "--frames", "0:2", "--out", tmp_path / "out", *TINY_ANY_ACCEL]
    status, _, err = run_cli(capsys, *argv, "--cluster", "local:100000")
    assert status == 2 and len(err) == 1 and "this machine runs at most" in err[0], err
    monkeypatch.setattr(cluster, "machine_capacity", lambda: (16, 3 * 2**30))
    status, _, err = run_cli(capsys, *argv, "--cluster", "local:7")
    assert status == 2 and err == [
        "hlbvh render: --cluster 'local:7': this machine runs at most 6 workers (16 cores, "
        "3.0 GiB free, 512 MiB a worker); use local:1 .. local:6, or --scheduler ADDRESS "
        "for more machines"], err
    assert not (tmp_path / "out").exists() or not list((tmp_path / "out").iterdir())


class Server:
    """A TCP server on 127.0.0.1 that does one of: accept and never send (``"silent"``),
    answer what it is sent with an HTTP error (``"http"``), greet with another
    protocol's banner (``"ssh"``)."""

    def __init__(self, kind):
        self.kind, self.socket = kind, socket.create_server(("127.0.0.1", 0))
        self.address = f"tcp://127.0.0.1:{self.socket.getsockname()[1]}"
        self.connections = []
        threading.Thread(target=self.serve, daemon=True).start()

    def serve(self):
        while True:
            try:
                connection, _ = self.socket.accept()
            except OSError:
                return
            self.connections.append(connection)
            if self.kind == "ssh":
                connection.sendall(b"SSH-2.0-OpenSSH_9.2\r\n")
            elif self.kind == "http" and connection.recv(1024):
                connection.sendall(b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n")

    def close(self):
        self.socket.close()
        for connection in self.connections:
            connection.close()


@pytest.mark.parametrize("kind, message", [
    ("silent", "something accepts connections there but sends nothing within 1 s, which a "
               "Dask scheduler does at once (another kind of server?); check the address"),
    ("http", "something accepts connections there but sends nothing within 1 s, which a "
             "Dask scheduler does at once (another kind of server?); check the address"),
    ("ssh", "what answers there is not a Dask scheduler (it began b'SSH-2.0-'); check the "
            "address"),
])
def test26_a_scheduler_address_that_does_not_speak_dask_is_one_line(tmp_path, capsys,
                                                                   monkeypatch, kind, message):
    cluster = pytest.importorskip("hlbvh.render.cluster")
    monkeypatch.setattr(cluster, "CONNECT_TIMEOUT", 1)
    server = Server(kind)
    try:
        status, _, err = run_cli(capsys, "render", "cloth", "--frames", "0:2", "--scheduler",
                                 server.address, "--out", tmp_path / "out", *TINY_ANY_ACCEL)
    finally:
        server.close()
    assert status == 2 and err == [f"hlbvh render: --scheduler {server.address}: {message}"], err


# ---------------------------------------------------------------------------------------
# Ctrl-C during start-up
# ---------------------------------------------------------------------------------------

STARTING = """
import signal, sys

class Interrupt:
    \"\"\"Ctrl-C as the command imports {module}.\"\"\"
    def find_spec(self, name, path, target=None):
        if name == {module!r}:
            signal.raise_signal(signal.SIGINT)
        return None

sys.meta_path.insert(0, Interrupt())
from hlbvh.cli.command import main
sys.exit(main(["render", "cloth", "--frames", "0:1", "--out", {out!r}]))
"""


@pytest.mark.parametrize("module", ["mitsuba", "hlbvh.cli.render"])
def test27_ctrl_c_while_the_command_starts_is_one_line(tmp_path, module):
    """The console script (a file named ``hlbvh``) interrupted while it imports
    Mitsuba (the package) or a verb's module (the parser)."""
    script = tmp_path / "hlbvh"
    script.write_text(STARTING.format(module=module, out=str(tmp_path / "out")))
    done = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                          timeout=120)
    assert (done.returncode, done.stderr) == (130, "hlbvh: interrupted\n")
    assert not (tmp_path / "out").exists()
