"""``hlbvh compare``'s verdict judged against Monte Carlo noise: hlbvh's frame passes
when it is another sample of native's image (paths parting on ties, another seed) and
fails when it renders other geometry (a vertex moved by a pixel's width); native is
rendered again with another seed (the noise) only for the frames that are not
bit-identical; a rerun over fewer frames leaves no older difference map."""

import numpy as np
import pytest

from cli_helpers import run_cli
from hlbvh.comparison import compare
from hlbvh.comparison.tables import read_results
from hlbvh.scenes.animated import FrameGeometry

TINY = ["--triangles", "500", "--resolution", "16", "--spp", "1", "--frames", "0:2",
        "--quiet"]


class _MovedVertex:
    """An animation whose frames move one vertex of the first animated mesh by
    ``pixels`` pixel widths to the camera's right: the vertex furthest right on screen,
    so that its move changes the mesh's outline."""

    def __init__(self, animation, width: int, pixels: float = 1.0):
        self._animation = animation
        view = animation._view()
        self._origin = np.asarray(view.origin)
        forward = np.asarray(view.target) - self._origin
        self._forward = forward / np.linalg.norm(forward)
        right = np.cross(self._forward, (0.0, 1.0, 0.0))
        self._right = right / np.linalg.norm(right)
        self._pixel = pixels * 2 * np.tan(np.radians(view.fov) / 2) / width

    def __getattr__(self, name):
        return getattr(self._animation, name)

    def frame(self, i):
        frame = dict(self._animation.frame(i))
        shape = self._animation.animated_ids()[0]
        points = np.array(frame[shape].positions, np.float32).reshape(-1, 3)
        depth = (points - self._origin) @ self._forward
        screen_x = ((points - self._origin) @ self._right) / np.maximum(depth, 1e-6)
        k = int(np.argmax(np.where(depth > 0, screen_x, -np.inf)))
        points[k] += self._right * depth[k] * self._pixel
        frame[shape] = FrameGeometry(points.reshape(-1), frame[shape].faces)
        return frame


def _hlbvh_render(monkeypatch, animation=lambda a: a, **settings):
    """Make the render into ``hlbvh/`` render ``animation(the animation)`` with
    ``settings`` replaced (e.g. ``accel="native"``); the other renders as they are."""
    from dataclasses import replace
    real = compare.render_animation

    def render(animation_, frames, out_dir, settings_, source=None, progress=True):
        if out_dir.name == "hlbvh":
            animation_, settings_ = animation(animation_), replace(settings_, **settings)
        return real(animation_, frames, out_dir, settings_, source, progress)

    monkeypatch.setattr(compare, "render_animation", render)


def test01_bit_identical_frames_pass_without_a_noise_render(tmp_path, capsys, monkeypatch):
    _hlbvh_render(monkeypatch, accel="native")
    status, printed, err = run_cli(capsys, "compare", "cloth", *TINY, "--out", tmp_path)
    assert status == 0 and not err, err
    rows = read_results(tmp_path / "results.json")["rows"]
    assert [row["noise.seed"] for row in rows] == [None, None]
    assert [row["noise.largest_z"] for row in rows] == [0.0, 0.0]
    assert not (tmp_path / "native-noise").exists()
    assert "within Monte Carlo noise of native's on every frame" in printed
    assert "Pixels bit-identical to native's: 100.0-100.0% a frame" in printed


def test02_another_native_seed_passes(tmp_path, capsys, monkeypatch):
    """hlbvh's folder rendered by native with another seed: no pixel need agree, and it
    is an unbiased sample of the same image, so it passes (the old pixel count failed
    it); native's noise render has a third seed."""
    _hlbvh_render(monkeypatch, accel="native", seed=7)
    status, printed, err = run_cli(capsys, "compare", "cloth", *TINY, "--out", tmp_path)
    assert status == 0 and not err, err
    rows = read_results(tmp_path / "results.json")["rows"]
    assert [row["noise.seed"] for row in rows] == [1, 2]
    assert all(row["noise.passed"] and abs(row["noise.largest_z"]) < 6 for row in rows)
    assert all(row["image.fraction_identical"] < 0.5 for row in rows)
    assert sorted(p.name for p in (tmp_path / "native-noise").glob("*.exr")) == [
        "frame_0000.exr", "frame_0001.exr"]


def test03_paths_parting_on_ties_pass(tmp_path, capsys):
    """rigid:instanced=true traced by our BVH: a few bounce rays hit a neighbouring
    triangle and their paths part from native's (6 pixels past 5e-4, which the old
    pixel count failed), primary hits all agree: another sample, a pass."""
    status, printed, err = run_cli(capsys, "compare", "rigid:instanced=true", "--resolution",
                                   "64x36", "--spp", "4", "--frames", "1:2",
                                   "--moving-accel", "hlbvh", "--quiet", "--out", tmp_path)
    assert status == 0 and not err, err
    row, = read_results(tmp_path / "results.json")["rows"]
    assert row["image.fraction_within_tolerance"] < 1 - 1 / (64 * 36)
    assert row["noise.passed"] and row["noise.seed"] == 2


def test04_a_vertex_moved_by_a_pixel_fails(tmp_path, capsys, monkeypatch):
    """hlbvh's frames render the cloth with its outline's vertex moved by one pixel's
    width: other geometry, more than the noise of 256 spp, so the frame fails (status
    1) and the verdict names it and the block."""
    _hlbvh_render(monkeypatch, lambda a: _MovedVertex(a, 64), moving_accel="hlbvh")
    status, printed, err = run_cli(capsys, "compare", "cloth", "--triangles", "50",
                                   "--resolution", "64", "--spp", "256", "--frames", "1:2",
                                   "--quiet", "--out", tmp_path)
    assert status == 1 and not err, err
    row, = read_results(tmp_path / "results.json")["rows"]
    assert not row["noise.passed"] and row["noise.blocks_over_limit"] >= 1
    assert "NOT within Monte Carlo noise of native's on 1 of 1 frames (1; largest" in printed
    assert row["noise.largest_z_block"] in printed


def test05_a_rerun_over_fewer_frames_keeps_no_older_difference_map(tmp_path, capsys):
    assert run_cli(capsys, "compare", "cloth", *TINY, "--out", tmp_path)[0] == 0
    assert sorted(p.name for p in (tmp_path / "diff").iterdir()) == [
        "frame_0000.png", "frame_0001.png"]
    fewer = [*TINY[:-2], "0:1", "--quiet"]
    assert run_cli(capsys, "compare", "cloth", *fewer, "--out", tmp_path)[0] == 0
    assert sorted(p.name for p in (tmp_path / "diff").iterdir()) == ["frame_0000.png"]


def test06_help_states_the_exit_status(capsys):
    with pytest.raises(SystemExit):
        run_cli(capsys, "compare", "--help")
    text = " ".join(capsys.readouterr().out.split())
    assert ("exit status: 0 when hlbvh's images are within Monte Carlo noise of native's "
            "on every frame") in text
    assert "1 when a frame is not, 2 for a user error" in text
