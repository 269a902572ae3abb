"""``hlbvh render`` as a hostile new user drives it, second round: a scene edited
between resumes, the scene's own integrator, frame entries that are not readable
files, bad face indices, Ctrl-C while rendering, unbounded clusters, schedulers that
never answer, and meshes, folders and files that used to end in a traceback. Every case
ends in complete frames only and, for a user error, one line naming what is wrong."""

import signal

import pytest

from cli_helpers import read_stats, run_cli, write_twist_scene
from hlbvh.integrators.path import PathIntegrator
from hlbvh.output import LOCK_NAME

TINY = ["--triangles", "200", "--resolution", "16", "--spp", "1", "--quiet"]


def frames_of(directory):
    """The frames ``stats.json`` and ``stats.csv`` record (they must agree)."""
    document, table = read_stats(directory)
    rows = [row["frame"] for row in document["frames"]]
    assert rows == [int(row["frame"]) for row in table]
    return rows


# ---------------------------------------------------------------------------------------
# Ctrl-C while rendering
# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("accel", ["hlbvh", "native"])
def test_ctrl_c_inside_mitsubas_render_stops_after_the_frame_and_resumes(
        tmp_path, capsys, monkeypatch, accel):
    """SIGINT raised inside ``mi.render`` (while Mitsuba's own handler is installed)
    stops the loop after that frame, exit 130; the same command renders the rest."""
    real = PathIntegrator.sample
    calls = []

    def sample(self, *args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            signal.raise_signal(signal.SIGINT)
        return real(self, *args, **kwargs)

    monkeypatch.setattr(PathIntegrator, "sample", sample)
    out = tmp_path / "out"
    argv = ["render", "cloth", "--frames", "0:4", "--accel", accel, "--out", out, *TINY]
    status, _, err = run_cli(capsys, *argv)
    assert status == 130 and err == ["hlbvh render: interrupted"], err
    assert frames_of(out) == [0, 1] and not (out / LOCK_NAME).exists()
    monkeypatch.undo()
    status, text, _ = run_cli(capsys, *argv)
    assert status == 0 and "2 rendered, 2 already complete" in text
