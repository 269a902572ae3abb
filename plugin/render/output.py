"""An output directory of rendered frames: its statistics (``stats.json``, the record,
and ``stats.csv`` written from it), when a frame is complete, the row files cluster
workers leave beside their frames, the temporary files a killed render leaves, and the
lock file that gives a directory one writer at a time."""

from __future__ import annotations

import contextlib
import csv
import fcntl
import io
import json
import os
import re
import socket
import sys
from pathlib import Path

from hlbvh.accel.policy import UpdatePolicy
from hlbvh.render import images
from hlbvh.errors import UserError
from hlbvh.render.frame import STATS_FIELDS, FrameRenderer

#: The lock file of an output directory (see :func:`output_lock`).
LOCK_NAME = ".hlbvh.lock"

_STALE = re.compile(r"^\.(frame_\d+\.(exr|png)|stats\.(csv|json))\.[0-9a-f]+\.tmp$")


class Statistics:
    """``stats.json`` and ``stats.csv`` of an output directory: the settings and one row
    per complete frame, rewritten whole (atomically) whenever a row is added. The json
    is the record; the csv is written from it after it, and again when a directory is
    opened, so a kill between the two writes is healed by the next run.

    Args:
        directory: the output directory.
        settings: what the frames are rendered with (JSON values).
        resolution: ``(width, height)`` every frame must have, or ``None`` (then the
            EXR and the PNG of a frame need only agree).
    """

    def __init__(self, directory: Path, settings: dict, resolution=None):
        self.directory = directory
        self.settings = settings
        self.resolution = resolution
        self.rows: dict[int, dict] = {}
        path = directory / "stats.json"
        stored_settings = settings
        if path.exists():
            try:
                stored = json.loads(path.read_text())
                stored_settings, rows = stored["settings"], stored["frames"]
                self.rows = {int(row["frame"]): row for row in rows}
            except (OSError, ValueError, KeyError, TypeError) as error:
                raise UserError(
                    f"{path}: unreadable ({type(error).__name__}: {error}); remove it to "
                    f"render this directory's frames again, or choose another --out"
                ) from None
        if stored_settings != settings and self.rows:
            differ = sorted(k for k in set(settings) | set(stored_settings)
                            if settings.get(k) != stored_settings.get(k))
            changes = ", ".join(
                f"{k}: the scene file or a file it names was edited" if k == "scene_sha256"
                else f"{k}: {_setting_text(stored_settings, k)} -> {_setting_text(settings, k)}"
                for k in differ)
            raise UserError(
                f"{directory} holds frames rendered with other settings ({changes}); "
                f"choose another --out, or remove the directory to start over"
            )
        # Rows that cluster workers left beside their frames (a run that stopped before
        # writing its statistics) join the record here.
        found = row_files(directory)
        if found:
            self.add_rows(found)
        elif self.rows:
            self._write_csv()

    def complete(self, i: int) -> bool:
        """Whether frame ``i`` has its row and its images (:func:`frame_images_complete`)."""
        return i in self.rows and frame_images_complete(self.directory, i, self.resolution)

    def add(self, row: dict) -> None:
        """Record frame ``row["frame"]``'s row: ``stats.json``, then ``stats.csv``."""
        self.add_rows([row])

    def add_rows(self, rows: list[dict]) -> None:
        """Record rows (one write of ``stats.json``, then of ``stats.csv``), then remove
        the row files (:func:`row_path`) of their frames."""
        for row in rows:
            self.rows[int(row["frame"])] = row
        document = {"settings": self.settings, "frames": self.ordered()}
        with images.atomic_output(self.directory / "stats.json") as temporary:
            temporary.write_text(json.dumps(document, indent=1) + "\n")
        self._write_csv()
        for row in rows:
            row_path(self.directory, int(row["frame"])).unlink(missing_ok=True)

    def ordered(self) -> list[dict]:
        """Every row, in frame order."""
        return [self.rows[i] for i in sorted(self.rows)]

    def _write_csv(self) -> None:
        ordered = self.ordered()
        fields = STATS_FIELDS + (("worker",) if any("worker" in r for r in ordered) else ())
        table = io.StringIO()
        writer = csv.DictWriter(table, fieldnames=fields, extrasaction="ignore",
                                lineterminator="\n")
        writer.writeheader()
        writer.writerows(ordered)
        with images.atomic_output(self.directory / "stats.csv") as temporary:
            temporary.write_text(table.getvalue())


def _setting_text(settings: dict, key: str) -> str:
    """Recorded setting ``key`` as a refusal names it: its value, or ``unset`` where the
    record leaves it to a default (``None``, or not recorded), with the accelerator's
    default where it has one (``update``, ``moving_accel``)."""
    value = settings.get(key)
    if value is not None:
        return repr(value)
    default = getattr(UpdatePolicy, key, None)
    return "unset" if default is None else f"unset (the default, {default!r})"


def recorded_settings(source: dict | None, settings, renderer: FrameRenderer) -> dict:
    """What ``stats.json`` records as a folder's settings: what identifies the scene
    (``source``), the :class:`hlbvh.render.settings.RenderSettings` as JSON values, and the
    ``resolution`` and ``spp`` the loaded scene renders at (its film's size, its
    sampler's count) in place of a ``None`` that left them to the scene: a resumed
    folder then refuses a scene edited to render other frames."""
    sensor = renderer.scene.sensors()[0]
    width, height = sensor.film().crop_size()
    return {**(source or {}), **settings.as_dict(), "resolution": [int(width), int(height)],
            "spp": int(sensor.sampler().sample_count())}


def frame_name(i: int) -> str:
    """File name (without extension) of frame ``i``: ``frame_0007``."""
    return f"frame_{i:04d}"


def frame_images_complete(directory: Path, i: int, resolution=None) -> bool:
    """Whether frame ``i``'s EXR and PNG decode whole, at one size (``resolution``,
    ``(width, height)``, when given), the PNG with the EXR's colour channels."""
    name = frame_name(i)
    width, height = resolution or (None, None)
    try:
        width, height, channels = images.check_image(directory / f"{name}.exr", width, height)
        images.check_image(directory / f"{name}.png", width, height, min(channels, 3))
    except OSError:
        return False
    return True


def row_path(directory: Path, i: int) -> Path:
    """Where a cluster worker keeps frame ``i``'s row until the client records it:
    ``.frame_0007.row.json`` (hidden; :func:`remove_stale_files` keeps it)."""
    return directory / f".{frame_name(i)}.row.json"


def write_row(directory: Path, row: dict) -> None:
    """Write a frame's row file (:func:`row_path`), atomically."""
    with images.atomic_output(row_path(directory, int(row["frame"]))) as temporary:
        temporary.write_text(json.dumps(row) + "\n")


def row_files(directory: Path) -> list[dict]:
    """The rows of every readable row file in ``directory``."""
    rows = (read_row(path) for path in directory.glob(".frame_*.row.json"))
    return [row for row in rows if row is not None]


def read_row(path: Path) -> dict | None:
    """The row in a row file, or ``None`` (and the file removed) if it is unreadable."""
    try:
        row = json.loads(path.read_text())
        int(row["frame"])
        return row
    except (OSError, ValueError, KeyError, TypeError):
        path.unlink(missing_ok=True)
        return None


def remove_stale_files(directory: Path) -> list[Path]:
    """Remove the temporary files a killed render left in ``directory`` (hidden
    ``.frame_NNNN.exr.<hex>.tmp``, ``.stats.json.<hex>.tmp``, ...); returns them."""
    stale = [p for p in directory.glob(".*.tmp") if _STALE.match(p.name) and p.is_file()]
    for path in stale:
        path.unlink(missing_ok=True)
    return stale


def output_directory(path) -> Path:
    """``--out`` as a directory that exists and can be written, created if needed.

    Raises:
        UserError: naming ``--out``: a file (``/dev/null``), a path under
            a file, a directory that cannot be created or written (read-only).
    """
    directory = Path(path)
    if directory.exists() and not directory.is_dir():
        raise UserError(f"--out {path}: it exists and is not a directory; choose a directory")
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise UserError(f"--out {path}: cannot create it ({_reason(error)}); choose a "
                        f"directory that can be written") from None
    if not os.access(directory, os.W_OK | os.X_OK):
        raise UserError(f"--out {path}: the directory cannot be written (read-only or no "
                        f"permission); choose another")
    return directory


@contextlib.contextmanager
def output_lock(directory: Path):
    """Hold ``directory``'s lock file (:data:`LOCK_NAME`) for the ``with`` body, so one
    directory has one writer at a time.

    The file is locked with ``flock``, which the kernel releases when its process ends,
    however it ends, and it names the owner's pid and host. A lock file whose lock is
    free was left by a process that died: it is taken over, with a message on stderr.
    The file is removed when the body ends.

    Raises:
        UserError: another process holds the lock (naming its pid and host).
    """
    path = directory / LOCK_NAME
    while True:
        handle = open(path, "a+")
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            owner = _lock_owner(handle)
            handle.close()
            raise UserError(f"--out {directory}: another render is writing into it "
                            f"({owner}, lock file {path}); wait for it to end or choose "
                            f"another --out") from None
        try:
            current = os.stat(path).st_ino == os.fstat(handle.fileno()).st_ino
        except FileNotFoundError:
            current = False
        if current:  # not a file its previous owner removed while we opened it
            break
        handle.close()
    try:
        previous = _lock_owner(handle)
        if previous != "an unknown process":
            print(f"hlbvh: {path}: taking over the lock left by {previous}, which is no "
                  f"longer running", file=sys.stderr)
        handle.seek(0)
        handle.truncate()
        handle.write(json.dumps({"pid": os.getpid(), "host": socket.gethostname()}) + "\n")
        handle.flush()
        yield path
    finally:
        path.unlink(missing_ok=True)
        handle.close()


def _lock_owner(handle) -> str:
    """Who a lock file names: ``process 123 on host h``."""
    handle.seek(0)
    try:
        owner = json.loads(handle.read())
        return f"process {int(owner['pid'])} on host {owner['host']}"
    except (ValueError, KeyError, TypeError):
        return "an unknown process"


def write_frame(directory: Path, i: int, image, renderer: FrameRenderer, row: dict,
                record) -> None:
    """Frame ``i``'s EXR and PNG, then ``record(row)`` (the statistics, or a cluster
    worker's row file): the frame is complete once this returns.

    Raises:
        UserError: a write failed or came out short (a full disk, a directory where the
            file goes); its temporary file is gone and the frame is not complete.
    """
    pixels = images.as_image(image)
    try:
        images.write_exr(directory / f"{frame_name(i)}.exr", pixels,
                         channel_names=renderer.channel_names(pixels))
        images.write_png(directory / f"{frame_name(i)}.png", pixels[..., :3])
        record(row)
    except OSError as error:
        named = error.filename2 or error.filename
        where = f"{named}: " if named else ""
        raise UserError(f"--out {directory}: frame {i} could not be written ({where}"
                        f"{_reason(error)}); the frames before it are complete: free space "
                        f"or fix the directory, then run the same command again") from None


def _reason(error: OSError) -> str:
    """What an ``OSError`` says, without its file name."""
    return error.strerror or str(error)

