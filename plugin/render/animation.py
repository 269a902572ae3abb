"""An animation's frames rendered into a folder, resuming (:func:`render_animation`):
what ``hlbvh render`` (:mod:`hlbvh.cli.render`, whose docstring says what a frame does,
what is written and how a resume is decided), ``compare`` and ``sweep`` run."""

from __future__ import annotations

import sys

from hlbvh.render.frame import FrameRenderer
from hlbvh.render.output import (Statistics, output_directory, output_lock, recorded_settings,
                                 remove_stale_files, write_frame)
from hlbvh.render.settings import RenderSettings, check_seed


def render_animation(animation, frames, out_dir, settings: RenderSettings,
                     source: dict | None = None,
                     progress: bool = True) -> tuple[list[dict], list[int]]:
    """Render ``frames`` of ``animation`` into ``out_dir``, resuming a previous run.

    Args:
        animation: the :class:`hlbvh.scenes.AnimatedScene`.
        frames: the frame indices, a sequence iterated once (e.g. ``range(0, 24)``).
        out_dir: the output directory (created if needed).
        settings: the :class:`hlbvh.render.settings.RenderSettings`.
        source: what identifies the scene (JSON values, e.g. ``{"scene": "cloth",
            "triangles": 200000}``), recorded with the settings.
        progress: show a progress bar on stderr.
    Returns:
        ``(rows, rendered)``: every row of the directory's statistics (earlier runs'
        included) in frame order, and the frames this call rendered.
    Raises:
        UserError: ``out_dir`` cannot be used (:func:`hlbvh.render.output.output_directory`) or another
            render holds it (:func:`hlbvh.render.output.output_lock`), it holds frames of other settings or
            unreadable statistics, a seed or the frame's size is out of range, or a
            write failed (a full disk): no partial file is left, the frames finished
            before it stay complete.
        ValueError: a frame cannot be read or applied; the frames finished before it
            stay complete.
        KeyboardInterrupt: Ctrl-C; the frames finished before it stay complete. During
            ``mi.render`` Mitsuba's own SIGINT handler takes the signal and only cancels
            the integrator (its "winding down" warning), which a wavefront render does
            not act on: the integrator's ``should_stop()`` says so once the frame in
            flight is rendered, and that frame (whole: the JIT variants render every
            pass) is written before the interrupt is raised here.
    """
    from tqdm import tqdm

    directory = output_directory(out_dir)
    check_seed(settings.seed, frames)
    with output_lock(directory):
        remove_stale_files(directory)
        renderer, rendered = FrameRenderer(animation, settings), []
        record = recorded_settings(source, settings, renderer)
        statistics = Statistics(directory, record, tuple(record["resolution"]))
        with tqdm(total=len(frames), desc=f"{animation.name} {settings.accel}",
                  unit="frame", file=sys.stderr, disable=not progress,
                  dynamic_ncols=True) as bar:
            for i in frames:
                if not statistics.complete(i):
                    image, row = renderer.render(i)
                    write_frame(directory, i, image, renderer, row, statistics.add)
                    rendered.append(i)
                    bar.set_postfix(build=f"{row['build_ms']:.0f}ms",
                                    render=f"{row['render_ms']:.0f}ms")
                    if renderer.integrator.should_stop():
                        raise KeyboardInterrupt
                bar.update()
    return statistics.ordered(), rendered
