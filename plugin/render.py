"""``hlbvh render``: an animated scene rendered frame by frame to EXR and PNG, with
per-frame statistics; interrupted renders resume where they stopped.

Usage::

    hlbvh render cloth --frames 0:24 --resolution 640x360 --spp 16 --out out/cloth
    hlbvh render fracture --triangles 1000000 --frames 8 --accel native
    hlbvh render scene.xml --frames-dir frames/ --integrator aov --out out/mine

``SCENE`` is a procedural scene (``hlbvh.scenes.names()``: cloth, twist, fracture,
rigid, soup; ``--triangles`` sets its size) or a Mitsuba XML file whose animated meshes
are read from ``--frames-dir`` (see :class:`hlbvh.scenes.SequenceScene`).
``--frames A:B`` renders frames ``A .. B-1``, ``--frames N`` the first ``N``; the
default is every frame of the scene (60 for procedural scenes, whose motion goes on
past that: any ``B`` is allowed there). ``--resolution W`` means ``W×W``.

Each frame
----------
1. its geometry is written into the loaded scene with :func:`hlbvh.scenes.apply_frame`,
   whose ``params.update()`` makes Mitsuba rebuild its own accelerator (Embree on the
   LLVM backend) whatever ``--accel`` says;
2. with ``--accel hlbvh`` our :class:`hlbvh.SceneAccel` follows (built, rebuilt or
   refit, as its ``update`` policy decides), timed on its own;
3. ``mi.render(scene, seed=seed + frame)``: the same seed for a frame whatever the
   accelerator, so renders of both are comparable pixel by pixel (box filter);
4. ``frame_NNNN.exr`` (linear float32, every film channel: R, G, B, and the AOVs of
   ``--integrator aov``) and ``frame_NNNN.png`` (8-bit sRGB of R, G, B) are written
   through :mod:`hlbvh.images`, each to a temporary file renamed into place;
5. its row (:data:`STATS_FIELDS`) is added to ``stats.csv`` and ``stats.json``, both
   rewritten whole and atomically.

A frame is complete when its EXR and its PNG decode whole, at one size (the
``--resolution`` when given), and its row is in ``stats.json``. Running the same
command again renders only the frames of the range that are not complete (after an
interrupt: from the one that was being rendered; a truncated or emptied file: that
frame again), rewrites ``stats.csv`` from ``stats.json`` (a kill between the two writes
is healed), and removes the temporary files a killed process left. A write that fails
(a full disk) leaves no partial file and stops with one line; the frames before it stay
complete. ``stats.json`` records the settings (scene, size, resolution, spp,
integrator, accelerator, builder options, seed); rendering into a directory that
holds frames of other settings is refused, so one directory never mixes two renders.
One render writes into a directory at a time: it holds the directory's lock file
(:data:`LOCK_NAME`, naming its pid and host); a second is refused, and a lock left by a
process that died is taken over. Frame ranges are iterated, never listed, and the seed
of the last frame, the film's size and the samples per frame are checked against what
Dr.Jit and the machine's memory hold before any frame is rendered.

Statistics (``stats.json``: ``{"settings": {...}, "frames": [row, ...]}``)
--------------------------------------------------------------------------
``frame``, ``accel``, ``triangles`` (of every mesh at that frame), ``seed``;
``geometry_ms`` (reading or generating the frame and writing it into the scene),
``mitsuba_update_ms`` (Mitsuba's ``params.update()``: its own accelerator's rebuild),
``build_ms`` (``hlbvh``: our accelerator's update; ``native``: ``params.update()``,
the native rebuild), ``render_ms``; ``sah_cost`` of our BVH (C_trav = C_isect = 1,
normalised by the root's area; empty for ``native``, Embree does not report one);
``decision``: ``build`` (first frame), ``rebuild``, ``refit``, ``kept`` (nothing
moved), or ``native`` (Mitsuba rebuilt its accelerator). Times are wall-clock
milliseconds with the device synchronised; the first frame of a process includes
compiling kernels that Dr.Jit's disk cache did not hold.
"""

from __future__ import annotations

import contextlib
import csv
import fcntl
import io
import json
import os
import re
import resource
import socket
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from hlbvh import images, scenes
from hlbvh.accel import ACCELS, UPDATES, scene_shapes
from hlbvh.cli import UserError
from hlbvh.integrators.common import BUILD_OPTIONS
from hlbvh.kernels.bvh import BuildConfig
from hlbvh.scenes.sequence import TOPOLOGIES

#: Columns of ``stats.csv``, and keys of every row of ``stats.json``.
STATS_FIELDS = ("frame", "accel", "triangles", "seed", "geometry_ms", "mitsuba_update_ms",
                "build_ms", "render_ms", "sah_cost", "decision")

#: ``--integrator`` choices and the registered integrators they name.
INTEGRATORS = {"path": "hlbvh_path", "aov": "hlbvh_aov"}

#: Longest path of ``--integrator path`` unless ``--max-depth`` says otherwise.
DEFAULT_MAX_DEPTH = 8

#: Largest seed of a frame: Mitsuba's samplers take 32-bit seeds.
MAX_SEED = 2**32 - 1

#: Most samples (width x height x spp) of one frame: Dr.Jit arrays hold at most
#: 2^32 - 1 entries, and ``mi.render`` traces them as one wavefront.
MAX_SAMPLES = 2**32 - 1

#: Memory a frame takes per pixel and per sample, in bytes: measured peaks of
#: ``mi.render`` on the LLVM backend (about 40 per pixel at 1 spp, 15 per sample at
#: 4 spp; film, wavefront and the developed image), doubled.
BYTES_PER_PIXEL, BYTES_PER_SAMPLE = 64, 32

#: The lock file of an output directory (see :func:`output_lock`).
LOCK_NAME = ".hlbvh.lock"

_STALE = re.compile(r"^\.(frame_\d+\.(exr|png)|stats\.(csv|json))\.[0-9a-f]+\.tmp$")


# ---------------------------------------------------------------------------------------
# Settings
# ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RenderSettings:
    """How the frames of an animation are rendered.

    Attributes:
        resolution: film ``(width, height)``; ``None`` keeps the scene's.
        spp: samples per pixel; ``None`` keeps the scene's.
        integrator: ``"path"`` (``hlbvh_path``) or ``"aov"`` (``hlbvh_aov``).
        max_depth: longest path of ``"path"`` (-1: unbounded).
        accel: ``"hlbvh"`` or ``"native"``.
        build_options: options of :func:`hlbvh.build` (``builder``, ``leaf_size``, ...),
            validated for both accelerators.
        update: our accelerator's per-frame policy (``"rebuild"``, ``"refit"``,
            ``"auto"``), or ``None`` for its default; handed to the integrator as its
            ``update`` property.
        seed: frame ``i`` is rendered with seed ``seed + i``.
    Raises:
        ValueError: naming the setting, for any value outside the above.
    """

    resolution: tuple[int, int] | None = None
    spp: int | None = None
    integrator: str = "path"
    max_depth: int = DEFAULT_MAX_DEPTH
    accel: str = "hlbvh"
    build_options: dict = field(default_factory=dict)
    update: str | None = None
    seed: int = 0

    def __post_init__(self):
        if self.resolution is not None and (
            len(self.resolution) != 2 or not all(_is_int(v) and v >= 1 for v in self.resolution)
        ):
            raise ValueError(f"resolution={self.resolution!r}: expected (width, height) >= 1")
        if self.spp is not None and not (_is_int(self.spp) and self.spp >= 1):
            raise ValueError(f"spp={self.spp!r}: expected an int >= 1")
        if self.integrator not in INTEGRATORS:
            raise ValueError(f"integrator={self.integrator!r}: expected one of {tuple(INTEGRATORS)}")
        if not (_is_int(self.max_depth) and self.max_depth >= -1):
            raise ValueError(f"max_depth={self.max_depth!r}: expected -1 (unbounded) or an int >= 0")
        if self.accel not in ACCELS:
            raise ValueError(f"accel={self.accel!r}: expected one of {ACCELS}")
        BuildConfig.from_options(**self.build_options)
        if self.update is not None and self.update not in UPDATES:
            raise ValueError(f"update={self.update!r}: expected one of {UPDATES}")
        if not (_is_int(self.seed) and 0 <= self.seed <= MAX_SEED):
            raise ValueError(f"seed={self.seed!r}: expected an int in 0..{MAX_SEED}")

    def integrator_dict(self) -> dict:
        """The Mitsuba description of the integrator these settings ask for."""
        description = {"type": INTEGRATORS[self.integrator], "accel": self.accel,
                       **self.build_options}
        if self.integrator == "path":
            description["max_depth"] = self.max_depth
        if self.update is not None:
            description["update"] = self.update
        return description

    def as_dict(self) -> dict:
        """The settings as JSON values (what ``stats.json`` records)."""
        record = asdict(self)
        record["resolution"] = None if self.resolution is None else list(self.resolution)
        return record


def _is_int(value) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


# ---------------------------------------------------------------------------------------
# One frame
# ---------------------------------------------------------------------------------------


class FrameRenderer:
    """An animated scene loaded once, rendering any of its frames with timings.

    Args:
        animation: the :class:`hlbvh.scenes.AnimatedScene`.
        settings: the :class:`RenderSettings`.
    Raises:
        ValueError: the integrator cannot be made from the settings (naming what
            Mitsuba or the builder objected to).
        UserError: the frame does not fit in Dr.Jit's arrays or the machine's memory
            (:func:`check_frame_fits`), or ``accel="hlbvh"`` and the scene holds shapes
            our accelerator does not intersect (instances, curves, ...).

    Attributes:
        scene: the loaded ``mi.Scene``; ``params``: its ``mi.traverse``;
        integrator: its hlbvh integrator.
    """

    def __init__(self, animation, settings: RenderSettings):
        self.animation = animation
        self.settings = settings
        description = settings.integrator_dict()
        try:
            mi.load_dict(description)  # a bad property fails here, alone, before the scene
        except RuntimeError as error:
            raise ValueError(
                f"integrator {description['type']}: {_mitsuba_message(error)}"
            ) from None
        self.scene = mi.load_dict(animation.scene_dict(
            resolution=settings.resolution, spp=settings.spp, integrator=description))
        self.params = mi.traverse(self.scene)
        self.integrator = self.scene.integrator()
        sensor = self.scene.sensors()[0]
        width, height = sensor.film().crop_size()
        check_frame_fits(int(width), int(height), int(sensor.sampler().sample_count()))
        if settings.accel == "hlbvh":
            try:
                scene_shapes(self.scene.shapes())
            except ValueError as error:
                reason = str(error).split(" Use accel=")[0]
                raise UserError(f"{reason} Render this scene with --accel native "
                                f"(Mitsuba's own accelerator).") from None

    def render(self, i: int, spp: int | None = None) -> tuple[mi.TensorXf, dict]:
        """Apply frame ``i`` and render it.

        Args:
            i: the frame index.
            spp: samples per pixel for this render; ``None`` keeps the scene's.
        Returns:
            ``(image, row)``: the film's channels ``(H, W, C)`` and the frame's
            statistics (keys :data:`STATS_FIELDS`).
        Raises:
            ValueError: the frame's geometry cannot be read or applied (naming the file
                and the frame for sequences).
        """
        # ---- The frame's geometry into the scene; Mitsuba updates itself ----
        # With our accelerator, Mitsuba's own (Embree) is never queried: skip its rebuild.
        start = _clock()
        parameters = _TimedUpdate(self.params)
        scenes.apply_frame(self.scene, parameters, self.animation.frame(i),
                           rebuild_native=self.settings.accel == "native")
        geometry_ms = _clock() - start - parameters.update_ms

        # ---- Our accelerator follows ----
        if self.settings.accel == "hlbvh":
            build_ms, sah_cost, decision = self._follow()
        else:
            build_ms, sah_cost, decision = parameters.update_ms, None, "native"

        # ---- Render ----
        seed = self.settings.seed + i
        start = _clock()
        image = mi.render(self.scene, seed=seed, spp=0 if spp is None else spp)
        dr.eval(image)
        render_ms = _clock() - start

        row = {
            "frame": i, "accel": self.settings.accel, "triangles": self.triangle_count(),
            "seed": seed, "geometry_ms": round(geometry_ms, 3),
            "mitsuba_update_ms": round(parameters.update_ms, 3), "build_ms": round(build_ms, 3),
            "render_ms": round(render_ms, 3), "sah_cost": sah_cost, "decision": decision,
        }
        return image, row

    def _follow(self) -> tuple[float, float | None, str]:
        """Bring our accelerator up to date with the scene: (ms, SAH cost, decision),
        the decision and SAH cost as the accelerator reports them (``last_update``)."""
        start = _clock()
        update = self.integrator.accel(self.scene).last_update
        return _clock() - start, update["sah_cost"], update["decision"]

    def triangle_count(self) -> int:
        """Triangles of every mesh of the scene as it is now."""
        return sum(s.face_count() for s in self.scene.shapes() if s.is_mesh())

    def channel_names(self, image) -> list[str]:
        """Names of the film's channels in ``image``: R, G, B (, A), then the AOVs."""
        aovs = list(self.integrator.aov_names())
        colour = image.shape[2] - len(aovs)
        return ["R", "G", "B", "A"][:colour] + aovs


def check_frame_fits(width: int, height: int, spp: int) -> None:
    """Refuse a frame that Dr.Jit cannot index (:data:`MAX_SAMPLES`) or that needs more
    memory than this process can still get (:func:`available_memory`, with
    :data:`BYTES_PER_PIXEL` and :data:`BYTES_PER_SAMPLE`): it would otherwise fail
    deep inside ``mi.render`` or crash the process.

    Raises:
        UserError: naming ``--resolution`` and ``--spp``, the limit and the need.
    """
    samples = width * height * spp
    what = f"--resolution {width}x{height} at --spp {spp}"
    if samples > MAX_SAMPLES:
        raise UserError(f"{what}: {samples} samples per frame, more than the {MAX_SAMPLES} "
                        f"a Dr.Jit array holds; lower --resolution or --spp")
    need = width * height * BYTES_PER_PIXEL + samples * BYTES_PER_SAMPLE
    available = available_memory()
    if available is not None and need > available:
        raise UserError(f"{what}: a frame needs about {need / 2**30:.1f} GiB, this process "
                        f"can get {available / 2**30:.1f} GiB; lower --resolution or --spp")


def available_memory() -> int | None:
    """Bytes this process can still allocate, or ``None`` when nothing says: the least
    of the system's available memory, the cgroup's limit less its use, and the
    address-space limit (``RLIMIT_AS``) less what the process maps now."""
    limits = []
    meminfo = _proc_fields("/proc/meminfo")
    if "MemAvailable" in meminfo:
        limits.append(meminfo["MemAvailable"])
    try:
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        if limit != "max":
            used = int(Path("/sys/fs/cgroup/memory.current").read_text())
            limits.append(int(limit) - used)
    except (OSError, ValueError):
        pass
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft != resource.RLIM_INFINITY:
        limits.append(soft - _proc_fields("/proc/self/status").get("VmSize", 0))
    return max(min(limits), 0) if limits else None


def _proc_fields(path: str) -> dict[str, int]:
    """``Name: N kB`` lines of a /proc file, in bytes (empty where there is none)."""
    fields = {}
    try:
        for line in Path(path).read_text().splitlines():
            name, _, value = line.partition(":")
            parts = value.split()
            if len(parts) == 2 and parts[1] == "kB" and parts[0].isdigit():
                fields[name] = int(parts[0]) * 1024
    except OSError:
        pass
    return fields


class _TimedUpdate:
    """``mi.SceneParameters`` as :func:`hlbvh.scenes.apply_frame` uses them, with the
    wall time of ``update()`` (Mitsuba's own refresh and accelerator rebuild) kept in
    ``update_ms``. Values are evaluated as they are set, so pending arithmetic is not
    counted as Mitsuba's."""

    def __init__(self, params):
        self._params = params
        self.update_ms = 0.0

    def __contains__(self, key):
        return key in self._params

    def __getitem__(self, key):
        return self._params[key]

    def __setitem__(self, key, value):
        dr.eval(value)
        self._params[key] = value

    def update(self):
        start = _clock()
        self._params.update()
        self.update_ms = _clock() - start


def _clock() -> float:
    """Milliseconds since an arbitrary origin, after the device finished its work."""
    dr.sync_thread()
    return time.perf_counter() * 1e3


def _mitsuba_message(error: Exception) -> str:
    """The informative part of a Mitsuba loader error, on one line."""
    lines = [line.strip() for line in str(error).strip().splitlines() if line.strip()]
    useful = [line for line in lines if not line.startswith(("File ", "Traceback"))]
    text = " ".join(useful[-2:] if len(useful) > 1 else useful) or type(error).__name__
    return re.sub(r"\[[\w.]+:\d+\]\s*", "", text)


# ---------------------------------------------------------------------------------------
# The output directory
# ---------------------------------------------------------------------------------------


class _Statistics:
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
            changes = ", ".join(f"{k}: {stored_settings.get(k)!r} -> {settings.get(k)!r}"
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


def check_seed(seed: int, frames) -> None:
    """Refuse a ``--seed`` whose last frame's seed (``seed + frame``) is past
    :data:`MAX_SEED`, before any frame is rendered.

    Raises:
        UserError: naming ``--seed`` and the largest one that fits ``frames``.
    """
    last = frames[-1]
    if seed + last > MAX_SEED:
        raise UserError(f"--seed {seed}: frame {last} would get seed {seed + last}, past "
                        f"{MAX_SEED} (seeds are 32-bit); use --seed {max(MAX_SEED - last, 0)} "
                        f"or less")


def _reason(error: OSError) -> str:
    """What an ``OSError`` says, without its file name."""
    return error.strerror or str(error)


def render_animation(animation, frames, out_dir, settings: RenderSettings,
                     source: dict | None = None,
                     progress: bool = True) -> tuple[list[dict], list[int]]:
    """Render ``frames`` of ``animation`` into ``out_dir``, resuming a previous run.

    Args:
        animation: the :class:`hlbvh.scenes.AnimatedScene`.
        frames: the frame indices, a sequence iterated once (e.g. ``range(0, 24)``).
        out_dir: the output directory (created if needed).
        settings: the :class:`RenderSettings`.
        source: what identifies the scene (JSON values, e.g. ``{"scene": "cloth",
            "triangles": 200000}``), recorded with the settings.
        progress: show a progress bar on stderr.
    Returns:
        ``(rows, rendered)``: every row of the directory's statistics (earlier runs'
        included) in frame order, and the frames this call rendered.
    Raises:
        UserError: ``out_dir`` cannot be used (:func:`output_directory`) or another
            render holds it (:func:`output_lock`), it holds frames of other settings or
            unreadable statistics, a seed or the frame's size is out of range, or a
            write failed (a full disk): no partial file is left, the frames finished
            before it stay complete.
        ValueError: a frame cannot be read or applied; the frames finished before it
            stay complete.
    """
    from tqdm import tqdm

    directory = output_directory(out_dir)
    check_seed(settings.seed, frames)
    with output_lock(directory):
        remove_stale_files(directory)
        statistics = _Statistics(directory, {**(source or {}), **settings.as_dict()},
                                 settings.resolution)
        renderer, rendered = None, []
        with tqdm(total=len(frames), desc=f"{animation.name} {settings.accel}",
                  unit="frame", file=sys.stderr, disable=not progress,
                  dynamic_ncols=True) as bar:
            for i in frames:
                if not statistics.complete(i):
                    renderer = renderer or FrameRenderer(animation, settings)
                    image, row = renderer.render(i)
                    write_frame(directory, i, image, renderer, row, statistics.add)
                    rendered.append(i)
                    bar.set_postfix(build=f"{row['build_ms']:.0f}ms",
                                    render=f"{row['render_ms']:.0f}ms")
                bar.update()
    return statistics.ordered(), rendered


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


# ---------------------------------------------------------------------------------------
# Command line
# ---------------------------------------------------------------------------------------


def configure(parser) -> None:
    """Options of ``hlbvh render`` (values are checked in :func:`run`, so every
    mistake is reported in one line)."""
    parser.description = __doc__.split("\n\n")[0]
    add_scene_options(parser, "out/render/<scene>-<accel>")
    parser.add_argument("--integrator", default="path",
                        help="path (hlbvh_path, default) or aov (hlbvh_aov)")
    parser.add_argument("--accel", default="hlbvh", help="hlbvh (default) or native")
    parser.add_argument("--cluster", help="local:N: render on a Dask LocalCluster of N worker "
                                          "processes on this machine")
    parser.add_argument("--scheduler", help="ADDRESS (tcp://host:8786) of a running Dask "
                                            "scheduler whose workers see --out and the scene")
    parser.add_argument("--chunk-size", help="frames per task with --cluster/--scheduler "
                                             "(default: at least two chunks per worker, at "
                                             "most 16 frames)")


def add_scene_options(parser, out: str, *, builder_options: bool = True,
                      frames: str | None = None, spp: int | None = None) -> None:
    """The options of a scene and its renders (``hlbvh render``, ``compare``, ``sweep``): SCENE,
    ``--frames-dir``, ``--frames``, ``--resolution``, ``--spp``, ``--triangles``,
    ``--max-depth``, ``--seed``, ``--out``, ``--quiet``; with ``builder_options`` also
    the builder's options and ``--update``. ``out``, ``frames`` and ``spp`` are the
    defaults the help states (``None``: every frame, the scene's spp); the caller
    applies them."""
    add = parser.add_argument
    add("scene", help=f"a procedural scene ({', '.join(scenes.names())}) or a Mitsuba XML "
                      "file (with --frames-dir)")
    add("--frames-dir", help="directory of per-frame meshes <dir>/<shape id>/frame_0001.ply "
                             "(with an XML scene)")
    add("--topology", help="of the meshes of --frames-dir: fixed (default: only positions "
                           "change), changing (every frame brings its faces), or per shape "
                           "ID=changing,ID=fixed")
    add("--frames", help="A:B (frames A .. B-1) or N (the first N); default: "
                         + (frames or "every frame of the scene"))
    add("--resolution", help="W (W×W) or WxH; default: the scene's")
    add("--spp", help="samples per pixel; default: " + ("the scene's" if spp is None else str(spp)))
    add("--triangles", help="size of a procedural scene (default 200000)")
    add("--max-depth", default=str(DEFAULT_MAX_DEPTH),
        help=f"longest path of the path integrator (default {DEFAULT_MAX_DEPTH}; -1: unbounded)")
    if builder_options:
        for name in BUILD_OPTIONS:
            add(f"--{name.replace('_', '-')}", dest=name,
                help=f"builder option {name} (hlbvh.build; default {getattr(BuildConfig, name)!r})")
        add("--update", help="our accelerator's per-frame policy: rebuild, fresh, refit or auto "
                             "(default: the accelerator's own)")
    add("--seed", default="0", help="frame i is rendered with seed SEED + i (default 0)")
    add("--out", help=f"output directory (default {out})")
    add("--quiet", action="store_true", help="no progress bars")


def run(args) -> int:
    """``hlbvh render``: see the module docstring. Returns the exit status (0)."""
    settings = RenderSettings(
        resolution=None if args.resolution is None else parse_resolution(args.resolution),
        spp=None if args.spp is None else _int_flag("--spp", args.spp, least=1),
        integrator=_choice("--integrator", args.integrator, tuple(INTEGRATORS)),
        max_depth=_int_flag("--max-depth", args.max_depth, least=-1),
        accel=_choice("--accel", args.accel, ACCELS),
        build_options={name: _option_value(getattr(args, name)) for name in BUILD_OPTIONS
                       if getattr(args, name) is not None},
        update=None if args.update is None else _choice("--update", args.update, UPDATES),
        seed=seed_flag(args.seed),
    )
    animation, source, frames = open_animation(args.scene, args.frames_dir, args.triangles,
                                               args.frames, args.topology)
    out = out_flag(args.out, Path("out/render") / f"{Path(args.scene).stem}-{settings.accel}")
    if args.cluster is None and args.scheduler is None:
        if args.chunk_size is not None:
            raise UserError("--chunk-size cuts the frames of --cluster or --scheduler runs")
        rows, rendered = render_animation(animation, frames, out, settings, source,
                                          progress=not args.quiet)
    else:
        try:
            from hlbvh import cluster
        except ModuleNotFoundError as error:
            raise UserError(f"--cluster and --scheduler need Dask's distributed ({error}): "
                            f"pip install 'hlbvh[cluster]'") from None
        chunk = None if args.chunk_size is None else _int_flag("--chunk-size", args.chunk_size, 1)
        spec = cluster.SceneSpec.of(args.scene, args.frames_dir, args.triangles, frames,
                                    args.topology)
        rows, rendered = cluster.render_on_cluster(
            animation, spec, frames, out, settings, source, cluster=args.cluster,
            scheduler=args.scheduler, chunk_size=chunk, progress=not args.quiet)
    ours = [row for row in rows if row["frame"] in frames]
    print(f"{out}: frames {frames.start}..{frames.stop - 1} of {animation.name} with "
          f"{settings.accel}: {len(rendered)} rendered, {len(frames) - len(rendered)} "
          f"already complete; "
          f"median build {_median(ours, 'build_ms'):.1f} ms, render "
          f"{_median(ours, 'render_ms'):.1f} ms; statistics in {out / 'stats.csv'}")
    return 0


def out_flag(text: str | None, default: Path) -> Path:
    """``--out`` as given, or ``default`` when it is not; an empty ``--out ''`` is an
    error, not the default (the directory itself is checked by
    :func:`output_directory`)."""
    if text is None:
        return default
    if not text.strip():
        raise UserError("--out '': an empty path; give a directory, or leave --out out "
                        "for the default")
    return Path(text)


def seed_flag(text: str) -> int:
    """``--seed``: an integer in 0 .. :data:`MAX_SEED`."""
    return _int_flag("--seed", text, least=0, most=MAX_SEED)


def open_animation(scene: str, frames_dir, triangles, frames, topology=None) -> tuple:
    """The animated scene, what identifies it, and the frame range, from the command
    line's strings (``topology``: ``--topology``, see :func:`parse_topology`).

    Returns:
        ``(animation, source, range)``.
    Raises:
        UserError: an unknown scene, a missing file, options that do not fit the kind
            of scene, a bad frame range.
    """
    start, stop = parse_frames(frames)
    if scene in scenes.names():
        if frames_dir is not None:
            raise UserError(f"--frames-dir is for XML scenes; {scene!r} is procedural")
        if topology is not None:
            raise UserError(f"--topology is for the meshes of an XML scene's --frames-dir; "
                            f"{scene!r} is procedural")
        options = {}
        if triangles is not None:
            options["triangles"] = _int_flag("--triangles", triangles, least=1)
        default = scenes.get(scene, **options).frame_count
        # A procedural scene's motion is a function of time: frames past its own count
        # are as valid as the others.
        stop = default if stop is None else stop
        animation = scenes.get(scene, **options, frames=max(default, stop))
        source = {"scene": scene, "triangles": animation.triangles}
    else:
        path = Path(scene)
        if path.suffix.lower() != ".xml" or not path.is_file():
            raise UserError(
                f"scene {scene!r}: not a procedural scene ({', '.join(scenes.names())}) "
                f"nor an existing Mitsuba .xml file"
            )
        if frames_dir is None:
            raise UserError(f"scene {scene!r}: an XML scene needs --frames-dir with its "
                            f"per-frame meshes")
        if triangles is not None:
            raise UserError("--triangles sizes procedural scenes; an XML scene has its own")
        kinds = parse_topology(topology)
        animation = scenes.SequenceScene(path, frames_dir, topology=kinds)
        source = {"scene": str(path.resolve()), "frames_dir": str(Path(frames_dir).resolve())}
        if topology is not None:
            source["topology"] = kinds
        stop = animation.frame_count if stop is None else stop
    if stop > animation.frame_count:
        raise UserError(f"--frames {frames}: {scene!r} has frames 0:{animation.frame_count}")
    if start >= stop:
        raise UserError(f"--frames {frames}: the range is empty (expected A < B)")
    return animation, source, range(start, stop)


def parse_frames(text) -> tuple[int, int | None]:
    """``"A:B"``, ``"A:"``, ``":B"`` or ``"N"`` (``0:N``) -> ``(A, B or None)``; ``None``
    -> ``(0, None)``."""
    if text is None:
        return 0, None
    match = re.fullmatch(r"\s*(\d*)\s*:\s*(\d*)\s*|\s*(\d+)\s*", text)
    if not match:
        raise UserError(f"--frames {text!r}: expected A:B (frames A .. B-1) or a count N")
    if match.group(3) is not None:
        count = int(match.group(3))
        if count < 1:
            raise UserError(f"--frames {text!r}: expected a count >= 1")
        return 0, count
    return int(match.group(1) or 0), int(match.group(2)) if match.group(2) else None


def parse_topology(text: str | None):
    """``--topology``: ``None`` or ``"fixed"`` -> ``"fixed"``, ``"changing"``, or
    ``"ID=changing,ID=fixed"`` -> ``{"ID": "changing", ...}`` (what
    :class:`hlbvh.scenes.SequenceScene` takes)."""
    if text is None:
        return "fixed"
    word = text.strip()
    if word in TOPOLOGIES:
        return word
    kinds = {}
    for part in word.split(","):
        shape, _, kind = part.partition("=")
        if not shape.strip() or kind.strip() not in TOPOLOGIES:
            raise UserError(f"--topology {text!r}: expected fixed, changing, or "
                            f"ID=changing,ID=fixed per shape")
        kinds[shape.strip()] = kind.strip()
    return kinds


def parse_resolution(text: str) -> tuple[int, int]:
    """``"W"`` -> ``(W, W)``; ``"WxH"`` -> ``(W, H)``."""
    match = re.fullmatch(r"\s*(\d+)\s*(?:[xX×]\s*(\d+)\s*)?", text)
    if not match or int(match.group(1)) < 1 or (match.group(2) and int(match.group(2)) < 1):
        raise UserError(f"--resolution {text!r}: expected W or WxH, positive integers")
    width = int(match.group(1))
    return width, int(match.group(2)) if match.group(2) else width


def _int_flag(flag: str, text: str, least: int, most: int | None = None) -> int:
    expected = f"an integer >= {least}" if most is None else f"an integer in {least}..{most}"
    try:
        value = int(text)
    except ValueError:
        raise UserError(f"{flag} {text!r}: expected {expected}") from None
    if value < least or (most is not None and value > most):
        raise UserError(f"{flag} {text!r}: expected {expected}")
    return value


def _choice(flag: str, text: str, choices) -> str:
    if text not in choices:
        raise UserError(f"{flag} {text!r}: expected one of {', '.join(choices)}")
    return text


def _option_value(text: str):
    """A builder option from the command line: an int when it is one, else the word."""
    return int(text) if re.fullmatch(r"-?\d+", text.strip()) else text.strip()


def _median(rows: list[dict], key: str) -> float:
    values = [row[key] for row in rows if row.get(key) is not None]
    return float(np.median(values)) if values else float("nan")
