"""``hlbvh render --cluster local:N`` and ``--scheduler ADDRESS`` (Dask distributed, on
loopback): the same frames bit for bit as one process, a worker killed mid-run, Ctrl-C,
and the errors of a scheduler that is not there or workers that cannot do the work."""

import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

distributed = pytest.importorskip("distributed")

from cli_helpers import read_stats, write_twist_scene  # noqa: E402
from hlbvh import cli  # noqa: E402
from hlbvh.render import cluster  # noqa: E402
from hlbvh.render import images  # noqa: E402
from hlbvh.render.frame import STATS_FIELDS  # noqa: E402

# Bit for bit with one process when the moving meshes' structure is named: under "auto"
# each process chooses by its own timings.
TINY = ["--resolution", "16", "--spp", "1", "--quiet", "--moving-accel", "hlbvh"]
CLOTH = ["cloth", "--triangles", "300", *TINY]


def run_cli(*argv):
    """``hlbvh render argv`` in this process: (exit status, stderr lines)."""
    return cli.main(["render", *map(str, argv)])


def bits(directory, i):
    return images.read_exr(directory / f"frame_{i:04d}.exr").view(np.uint32)


def stats(directory):
    document, table = read_stats(directory)
    return document["frames"], table


def assert_same_frames(ours, reference, frames, cluster_run=True):
    rows, table = stats(ours)
    assert [row["frame"] for row in rows] == list(frames)  # each once, in order
    assert [int(r["frame"]) for r in table] == list(frames)
    if cluster_run:
        assert list(table[0]) == [*STATS_FIELDS, "worker"]
        assert all(r["worker"].startswith("tcp://127.0.0.1:") for r in table)
    for i in frames:
        assert np.array_equal(bits(ours, i), bits(reference, i)), f"frame {i}"
    assert not list(ours.glob(".*.tmp")) and not list(ours.glob(".*.row.json"))
    assert not (ours / ".hlbvh.lock").exists()


@pytest.fixture(scope="module")
def scheduler():
    """A LocalCluster of two single-threaded worker processes, on loopback."""
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  host="127.0.0.1", dashboard_address=None,
                                  silence_logs=40) as local:
        with distributed.Client(local) as client:
            yield local.scheduler_address, client


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """Frames 0..9 of the small cloth, rendered in this process."""
    out = tmp_path_factory.mktemp("single")
    assert run_cli(*CLOTH, "--frames", "0:10", "--out", out) == 0
    return out


def write_sequence(root, frames=4):
    """An XML scene with a twisting bar read from PLY frames."""
    return write_twist_scene(root, triangles=300, frames=frames)


def test01_local_cluster_renders_the_same_frames_as_one_process(tmp_path, reference):
    out = tmp_path / "cluster"
    assert run_cli(*CLOTH, "--frames", "0:6", "--cluster", "local:2", "--chunk-size", "2",
                   "--out", out) == 0
    assert_same_frames(out, reference, range(6))
    # A rerun renders nothing; a longer range only what is missing.
    before = {p.name: p.stat().st_mtime_ns for p in out.glob("frame_*")}
    assert run_cli(*CLOTH, "--frames", "0:6", "--cluster", "local:2", "--out", out) == 0
    assert {p.name: p.stat().st_mtime_ns for p in out.glob("frame_*")} == before


def test02_mesh_sequence_on_a_scheduler_equals_one_process(tmp_path, scheduler):
    xml, frames = write_sequence(tmp_path)
    argv = [xml, "--frames-dir", frames, *TINY]
    assert run_cli(*argv, "--out", tmp_path / "single") == 0
    assert run_cli(*argv, "--scheduler", scheduler[0], "--out", tmp_path / "cluster") == 0
    assert_same_frames(tmp_path / "cluster", tmp_path / "single", range(4))


# Run on the workers (by exec: a function of this module would not unpickle there): each
# frame starts a quarter second late, so that a worker seen finishing its chunk's first
# frame is still inside the chunk when it is killed. The images do not change.
_SLOW_FRAMES = """
import time
from hlbvh.render.frame import FrameRenderer
if not hasattr(FrameRenderer, "_fast_render"):
    FrameRenderer._fast_render = FrameRenderer.render
    def _slow_render(self, *args, **kwargs):
        time.sleep(0.25)
        return FrameRenderer._fast_render(self, *args, **kwargs)
    FrameRenderer.render = _slow_render
"""
_FAST_FRAMES = """
from hlbvh.render.frame import FrameRenderer
if hasattr(FrameRenderer, "_fast_render"):
    FrameRenderer.render = FrameRenderer._fast_render
    del FrameRenderer._fast_render
"""


def test03_a_worker_killed_mid_run(tmp_path, scheduler, reference):
    """A worker killed inside its chunk (after the chunk's first frame): the chunk is
    retried on another worker from its last complete frame, and the run ends with
    every frame, equal to one process's."""
    address, client = scheduler
    out = tmp_path / "cluster"
    pids = client.run(os.getpid)
    client.run(exec, _SLOW_FRAMES, {})
    status = []
    run = threading.Thread(target=lambda: status.append(run_cli(
        *CLOTH, "--frames", "0:10", "--scheduler", address, "--chunk-size", "5",
        "--out", out)))
    try:
        run.start()
        row = out / ".frame_0000.row.json"
        deadline = time.monotonic() + 300
        while not row.exists() and run.is_alive() and time.monotonic() < deadline:
            time.sleep(0.01)
        assert row.exists() and run.is_alive(), "the run ended before a worker was killed"
        victim = json.loads(row.read_text())["worker"]
        os.kill(pids[victim], signal.SIGKILL)
        run.join(600)
    finally:
        run.join(600)
        client.wait_for_workers(2, timeout=120)  # the nanny restarts the killed one
        client.run(exec, _FAST_FRAMES, {})
    assert status == [0]
    assert_same_frames(out, reference, range(10))
    # Frame 0 was the victim's; its chunk's last frame was rendered after the kill, by
    # another worker (the restarted one has another address).
    workers = {int(r["frame"]): r["worker"] for r in stats(out)[1]}
    assert workers[0] == victim and workers[4] != victim, workers


def test04_ctrl_c_leaves_complete_frames_and_a_rerun_finishes(tmp_path, scheduler,
                                                              reference, monkeypatch):
    real = cluster._result

    def interrupted(future):
        real(future)
        raise KeyboardInterrupt

    monkeypatch.setattr(cluster, "_result", interrupted)
    out = tmp_path / "cluster"
    # Five chunks of two frames; two workers hold at most four in flight, and the fifth
    # is submitted only after a first result (here: Ctrl-C), so at most 8 frames finish
    # whatever the workers' speed.
    argv = [*CLOTH, "--frames", "0:10", "--out", out]
    assert run_cli(*argv, "--scheduler", scheduler[0], "--chunk-size", "2") == 130
    assert not (out / ".hlbvh.lock").exists() and not list(out.glob(".*.tmp"))
    rows, _ = stats(out)
    assert 2 <= len(rows) <= 8
    for row in rows:
        assert np.array_equal(bits(out, row["frame"]), bits(reference, row["frame"]))
    monkeypatch.undo()
    assert run_cli(*argv) == 0
    rows, table = stats(out)
    assert [row["frame"] for row in rows] == list(range(10))
    for i in range(10):
        assert np.array_equal(bits(out, i), bits(reference, i))


def one_line_error(capsys, *argv):
    status = run_cli(*argv)
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    return status, err


def test05_a_scheduler_that_is_not_there(tmp_path, capsys, monkeypatch, reference):
    monkeypatch.setattr(cluster, "CONNECT_TIMEOUT", 3)
    out = tmp_path / "out"
    shutil.copytree(reference, out)
    before = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    status, err = one_line_error(capsys, *CLOTH, "--frames", "0:12", "--scheduler",
                                 "tcp://127.0.0.1:9", "--out", out)
    assert status == 2 and len(err) == 1 and "no Dask scheduler answers" in err[0], err
    assert {p.name: p.stat().st_mtime_ns for p in out.iterdir()} == before
    for argv, message in [(["--cluster", "remote:2"], "expected local:N"),
                          (["--cluster", "local:0"], "expected local:N"),
                          (["--cluster", "local:1", "--scheduler", "tcp://127.0.0.1:9"],
                           "one of --cluster"),
                          (["--chunk-size", "3"], "--chunk-size")]:
        status, err = one_line_error(capsys, *CLOTH, "--frames", "0:2", *argv, "--out", out)
        assert status == 2 and len(err) == 1 and message in err[0], err


def start_worker(address, prefix=(), code="pass"):
    """A ``dask worker`` process (``code`` run first in it), ``prefix`` before python."""
    launch = (f"import sys; {code}; from distributed.cli.dask_worker import main; "
              f"sys.argv = ['dask-worker', {address!r}, '--nthreads', '1', '--no-nanny', "
              f"'--no-dashboard']; main()")
    return subprocess.Popen([*prefix, sys.executable, "-c", launch],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


@pytest.fixture
def bare_scheduler():
    """A scheduler with no worker of its own."""
    with distributed.LocalCluster(n_workers=0, host="127.0.0.1", dashboard_address=None,
                                  silence_logs=40) as local:
        yield local.scheduler_address


def test06_a_worker_that_cannot_import_hlbvh(tmp_path, capsys, bare_scheduler):
    worker = start_worker(bare_scheduler, code="sys.modules['hlbvh'] = None")
    try:
        status, err = one_line_error(capsys, *CLOTH, "--frames", "0:2", "--scheduler",
                                     bare_scheduler, "--out", tmp_path / "out")
    finally:
        worker.kill()
        worker.wait()
    assert status == 2 and len(err) == 1 and "cannot import hlbvh" in err[0], err


def test07_a_worker_that_does_not_see_the_scene(tmp_path, capsys, bare_scheduler):
    if os.geteuid() != 0 or shutil.which("unshare") is None:
        pytest.skip("hiding the files from a worker needs root (a mount namespace)")
    xml, frames = write_sequence(tmp_path / "scene")
    # The worker's view of the scene's folder is an empty tmpfs: another machine's.
    hide = ["unshare", "-m", "sh", "-c", f"mount -t tmpfs tmpfs {tmp_path / 'scene'} && "
            f"exec \"$0\" \"$@\""]
    worker = start_worker(bare_scheduler, prefix=hide)
    try:
        status, err = one_line_error(capsys, xml, "--frames-dir", frames, *TINY,
                                     "--scheduler", bare_scheduler, "--out", tmp_path / "out")
    finally:
        worker.kill()
        worker.wait()
    assert status == 2 and len(err) == 1, err
    assert "worker tcp://" in err[0] and "scene.xml" in err[0] and "same path" in err[0]
