"""``hlbvh render --cluster local:N`` and ``--scheduler ADDRESS``: the frames of an
animation rendered by the workers of a Dask ``distributed`` cluster, written into one
``--out`` folder that every worker sees.

How the work is cut and written
-------------------------------
- The client (the ``hlbvh render`` process) checks everything a local render checks
  (the options, the folder, its lock, the settings recorded there, the seeds, that the
  frame fits in memory and that the accelerator takes the scene) and skips the frames
  already complete.
- The missing frames go out in contiguous chunks (``--chunk-size``; by default the
  range split in at least two chunks per worker, at most :data:`MAX_CHUNK` frames each),
  a few chunks per worker in flight at a time, so a billion frames are never listed.
  A chunk is one task, :func:`render_chunk`: its worker loads the scene (once per
  process), makes a :class:`hlbvh.render.frame.FrameRenderer` whose first frame is a fresh
  build, and renders the chunk's frames in order, so the accelerator's policy (seeded
  rebuilds, refits) works inside the chunk as in one process.
- Each frame is written as in a local render (EXR, PNG, atomically, read back), then
  its row to a hidden row file beside it (:func:`hlbvh.render.output.row_path`). A chunk whose
  worker dies is retried by Dask elsewhere and resumes after its last complete frame.
- The rows come back to the client, which writes ``stats.json`` and ``stats.csv`` once,
  in frame order, when the work ends (also after an error or Ctrl-C, then with the row
  files of every frame complete by then), with a ``worker`` column (the worker's
  address); the next run, local or not, records row files that a killed client left.
- Each worker process runs one chunk at a time with as many Dr.Jit threads as the
  worker has threads (a local cluster: the machine's cores shared among its workers),
  so nothing is oversubscribed.
- Ctrl-C sets a Dask ``Event`` that every chunk checks before each frame, waits for the
  chunks to finish the frame they are on (written whole; a second Ctrl-C stops waiting),
  cancels the tasks and closes a local cluster: only complete frames are left, and no
  worker writes into the folder once the command has returned.
"""

from __future__ import annotations

import functools
import math
import os
import secrets
import socket
import struct
import sys
import threading
from dataclasses import dataclass
from pathlib import Path

import drjit as dr
from distributed import (Client, Event, KilledWorker, LocalCluster, as_completed, get_worker,
                         wait)
from distributed.comm.addressing import parse_address, parse_host_port

from hlbvh.errors import UserError
from hlbvh.render.frame import FrameRenderer, available_memory
from hlbvh.render.output import (Statistics, frame_images_complete, output_directory, output_lock,
                          read_row, recorded_settings, remove_stale_files, row_files, row_path,
                          write_frame, write_row)
from hlbvh.render.settings import RenderSettings, check_seed
from hlbvh.render.source import SceneSpec, open_animation

#: Most frames in a chunk unless ``--chunk-size`` says otherwise.
MAX_CHUNK = 16

#: Chunks in flight per worker: one running, one queued behind it.
IN_FLIGHT = 2

#: Seconds to wait for a scheduler to answer, and for its first worker.
CONNECT_TIMEOUT = 10

#: Memory a ``--cluster local:N`` worker process is given room for: about three times
#: what one takes once it has imported hlbvh (165 MiB on Linux with Dr.Jit 1.5), for
#: its scene and its frame.
WORKER_BYTES = 512 * 2**20

#: Largest first message a Dask scheduler sends (its handshake, a few hundred bytes):
#: a length past this is another protocol's bytes.
MAX_HANDSHAKE = 2**20

#: The port of a ``--scheduler`` address that names none (Dask's).
DEFAULT_PORT = 8786

#: Seconds Ctrl-C waits for the chunks to stop after the frame they are on (a second
#: Ctrl-C stops waiting).
CANCEL_TIMEOUT = 300

# One chunk at a time per worker process: Dr.Jit's thread pool is the process's.
_ONE_CHUNK = threading.Lock()


@dataclass(frozen=True)
class ChunkJob:
    """Everything a chunk needs but its frames."""

    spec: SceneSpec
    settings: RenderSettings
    out: str
    cancel: str
    threads: int | None = None


# ---------------------------------------------------------------------------------------
# On a worker
# ---------------------------------------------------------------------------------------


def render_chunk(job: ChunkJob, frames: list[int]) -> list[dict]:
    """Render the frames of one chunk into ``job.out`` on this worker; frames already
    complete (images whole and their row file there: a retried chunk) are skipped.

    Returns:
        The rows of the chunk's frames, each with ``worker`` (this worker's address).
    Raises:
        UserError: this worker does not see the scene's files or the output folder.
        ValueError: a frame cannot be read or applied.
    """
    worker = get_worker()
    with _ONE_CHUNK:
        dr.set_thread_count(job.threads or worker.state.nthreads)
        animation = _animation(job.spec, worker.address)
        directory = Path(job.out)
        if not directory.is_dir():
            raise UserError(f"worker {worker.address} does not see --out {directory}: every "
                            f"worker needs the output folder at the same path (a shared "
                            f"file system)")
        cancel = Event(job.cancel)
        renderer, rows = None, []
        for i in frames:
            if cancel.is_set():
                break
            row = read_row(row_path(directory, i)) if row_path(directory, i).exists() else None
            if row is None or not frame_images_complete(directory, i, job.settings.resolution):
                renderer = renderer or FrameRenderer(animation, job.settings)
                image, row = renderer.render(i)
                row["worker"] = worker.address
                write_frame(directory, i, image, renderer, row,
                            functools.partial(write_row, directory))
            rows.append(row)
        return rows


@functools.lru_cache(maxsize=1)
def _animation(spec: SceneSpec, worker: str):
    """The spec's animation, opened once per worker process."""
    try:
        return open_animation(spec)[0]
    except (UserError, ValueError) as error:
        raise UserError(f"worker {worker}: {error} (every worker needs the scene's files at "
                        f"the same path)") from None


# ---------------------------------------------------------------------------------------
# On the client
# ---------------------------------------------------------------------------------------


def render_on_cluster(animation, spec: SceneSpec, frames: range, out_dir,
                      settings: RenderSettings, source: dict | None = None, *, cluster: str | None = None,
                      scheduler: str | None = None, chunk_size: int | None = None,
                      progress: bool = True) -> tuple[list[dict], list[int]]:
    """Render ``frames`` of the animation of ``spec`` on a Dask cluster into ``out_dir``,
    resuming a previous run (local or not); see the module docstring.

    Args:
        animation: the animation as the client opened it (from ``spec``).
        spec: the scene, as :class:`hlbvh.render.source.SceneSpec`, its files absolute
            (:meth:`~hlbvh.render.source.SceneSpec.absolute`).
        frames: the frame range.
        out_dir: the output folder, seen by every worker at the same path.
        settings: the :class:`hlbvh.render.settings.RenderSettings`.
        source: what identifies the scene, recorded with the settings.
        cluster: ``"local:N"``: a ``LocalCluster`` of N worker processes on this machine.
        scheduler: the address of a running Dask scheduler (exclusive with ``cluster``).
        chunk_size: frames per chunk; ``None``: see the module docstring.
        progress: one progress bar over all frames on stderr.
    Returns:
        ``(rows, rendered)`` as :func:`hlbvh.render.animation.render_animation` returns them.
    Raises:
        UserError: what a local render refuses; a bad ``cluster``, a scheduler that
            cannot be reached or has no workers; a worker that cannot import hlbvh, does
            not see the files, or died rendering a chunk too often. Frames finished
            before are kept and recorded.
        ValueError: a frame cannot be read or applied.
    """
    from tqdm import tqdm

    directory = output_directory(out_dir)
    check_seed(settings.seed, frames)
    renderer = FrameRenderer(animation, settings)  # refuses what every worker would refuse
    with _connected(cluster, scheduler) as (client, workers, threads), output_lock(directory):
        remove_stale_files(directory)
        record = recorded_settings(source, settings, renderer)
        statistics = Statistics(directory, record, tuple(record["resolution"]))
        statistics.add_rows([])  # the settings on record before any worker writes a row
        size = chunk_size or max(1, min(MAX_CHUNK, math.ceil(len(frames) / (2 * workers))))
        job = ChunkJob(spec, settings, str(directory.resolve()),
                       f"hlbvh-cancel-{secrets.token_hex(6)}", threads)
        rows, submitted = [], []
        with tqdm(total=len(frames), desc=f"{animation.name} {settings.accel} on "
                  f"{workers} workers", unit="frame", file=sys.stderr,
                  disable=not progress, dynamic_ncols=True) as bar:
            try:
                _run_chunks(client, job, _chunks(frames, statistics, size, bar),
                            workers * IN_FLIGHT, rows, submitted, bar)
            except KeyboardInterrupt:
                _cancel(client, job, submitted)
                raise
            finally:
                # With the rows of frames whose chunk did not end (an error, Ctrl-C).
                statistics.add_rows(rows + row_files(directory))
        rendered = sorted({int(row["frame"]) for row in rows})
    return statistics.ordered(), rendered


def _chunks(frames: range, statistics, size: int, bar):
    """Contiguous runs of at most ``size`` incomplete frames, the range iterated once;
    complete frames count on the progress bar as they are passed."""
    chunk = []
    for i in frames:
        if statistics.complete(i):
            bar.update()
            if chunk:
                yield chunk
                chunk = []
            continue
        chunk.append(i)
        if len(chunk) == size:
            yield chunk
            chunk = []
    if chunk:
        yield chunk


def _run_chunks(client, job: ChunkJob, chunks, window: int, rows: list, submitted: list,
                bar) -> None:
    """Submit chunks, at most ``window`` in flight, collecting their rows as they end
    (``submitted``: the futures of the chunks not yet done)."""
    def submit(chunk):
        future = client.submit(render_chunk, job, chunk, pure=False,
                               key=f"hlbvh-frames-{chunk[0]}-{chunk[-1]}-{secrets.token_hex(4)}")
        submitted.append(future)
        running.add(future)

    running = as_completed()
    for chunk in chunks:
        submit(chunk)
        if len(submitted) >= window:
            break
    for future in running:
        submitted.remove(future)
        done = _result(future)
        rows.extend(done)
        bar.update(len(done))
        following = next(chunks, None)
        if following is not None:
            submit(following)


def _result(future) -> list[dict]:
    """A chunk's rows, its errors turned into one line."""
    try:
        return future.result()
    except KilledWorker as error:
        raise UserError(f"the workers rendering {_frames_of(future)} died repeatedly "
                        f"({error}); finished frames are kept: run again to resume") from None


def _frames_of(future) -> str:
    """``frames A..B`` from a chunk's key."""
    _, _, first, last, _ = future.key.split("-")
    return f"frames {first}..{last}"


def _cancel(client, job: ChunkJob, submitted: list) -> None:
    """Tell every chunk to stop before its next frame and wait until they have (a
    queued chunk stops before its first): a worker is never still writing into the
    folder once the command has returned and released its lock. Then cancel what is
    left."""
    Event(job.cancel, client=client).set()
    try:
        wait(submitted, timeout=CANCEL_TIMEOUT)
    except (TimeoutError, KeyboardInterrupt):
        pass
    client.cancel(submitted, force=True)


class _connected:
    """A Dask client of a new ``LocalCluster`` (``"local:N"``) or of the scheduler at an
    address: ``(client, workers, Dr.Jit threads per worker or None)``; closed on exit
    (a local cluster's workers are stopped)."""

    def __init__(self, cluster: str | None, scheduler: str | None):
        if (cluster is None) == (scheduler is None):
            raise UserError("give one of --cluster local:N and --scheduler ADDRESS")
        self.cluster_text, self.scheduler = cluster, scheduler
        self.cluster = self.client = None

    def __enter__(self):
        threads = None
        if self.cluster_text is not None:
            workers = parse_cluster(self.cluster_text)
            threads = max(1, (os.cpu_count() or 1) // workers)
            self.cluster = LocalCluster(n_workers=workers, threads_per_worker=1,
                                        processes=True, host="127.0.0.1",
                                        dashboard_address=None, silence_logs=40)
            self.client = Client(self.cluster)
        else:
            try:
                check_scheduler_greets(self.scheduler)
                self.client = Client(self.scheduler, timeout=CONNECT_TIMEOUT)
            except (OSError, TimeoutError, ValueError) as error:
                raise UserError(f"--scheduler {self.scheduler}: no Dask scheduler answers "
                                f"there ({error}); start one with 'dask scheduler' or check "
                                f"the address") from None
            try:
                self.client.wait_for_workers(1, timeout=CONNECT_TIMEOUT)
            except TimeoutError:
                self.client.close()
                raise UserError(f"--scheduler {self.scheduler}: no worker joined within "
                                f"{CONNECT_TIMEOUT} s; start workers with 'dask worker "
                                f"{self.scheduler}'") from None
        # A worker that cannot unpickle a task (hlbvh missing there) never answers for
        # it: every worker is asked to import hlbvh first, by a builtin it can unpickle.
        answers = self.client.run(exec, "import hlbvh.render.cluster", on_error="return")
        failed = {worker: error for worker, error in answers.items()
                  if isinstance(error, BaseException)}
        if failed:
            worker, error = next(iter(failed.items()))
            self.__exit__()
            raise UserError(f"worker {worker} cannot import hlbvh ({type(error).__name__}: "
                            f"{error}); install hlbvh ('pip install hlbvh[cluster]') in "
                            f"every worker's environment")
        return self.client, len(answers), threads

    def __exit__(self, *exc):
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()


def parse_cluster(text: str) -> int:
    """``--cluster local:N`` -> N, from 1 to what this machine runs
    (:func:`machine_capacity`: a worker per core, :data:`WORKER_BYTES` of memory each).

    Raises:
        UserError: a malformed value, or more workers than the machine runs, naming its
            cores and free memory.
    """
    kind, _, count = text.partition(":")
    if kind != "local" or not count.isdigit() or int(count) < 1:
        raise UserError(f"--cluster {text!r}: expected local:N (N worker processes on this "
                        f"machine); for other machines use --scheduler ADDRESS")
    cores, memory = machine_capacity()
    most = cores if memory is None else max(1, min(cores, memory // WORKER_BYTES))
    if int(count) > most:
        free = "" if memory is None else f", {memory / 2**30:.1f} GiB free"
        raise UserError(f"--cluster {text!r}: this machine runs at most {most} workers "
                        f"({cores} cores{free}, {WORKER_BYTES // 2**20} MiB a worker); use "
                        f"local:1 .. local:{most}, or --scheduler ADDRESS for more machines")
    return int(count)


def machine_capacity() -> tuple[int, int | None]:
    """The cores this process may run on, and the bytes it can still allocate
    (:func:`hlbvh.render.frame.available_memory`; ``None`` when nothing says)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return cores or 1, available_memory()


def check_scheduler_greets(address: str) -> None:
    """Refuse a ``tcp://`` address where no Dask scheduler answers, within
    :data:`CONNECT_TIMEOUT`, before a Dask client connects: a scheduler sends its
    handshake first (an 8-byte length, then the message), while the client waits for it
    without a deadline once the connection is made, and reads another protocol's reply
    (an HTTP server's) as a length to allocate. Other schemes are left to Dask.

    Raises:
        UserError: nothing listens there, the connection is made but nothing is sent,
            or what is sent is not a Dask handshake.
        ValueError: a malformed address.
    """
    scheme, location = parse_address(address)
    if scheme != "tcp":
        return
    host, port = parse_host_port(location, DEFAULT_PORT)
    with socket.create_connection((host, port), timeout=CONNECT_TIMEOUT) as probe:
        header = b""
        try:
            while len(header) < 8:
                received = probe.recv(8 - len(header))
                if not received:
                    break
                header += received
        except TimeoutError:
            raise UserError(f"--scheduler {address}: something accepts connections there but "
                            f"sends nothing within {CONNECT_TIMEOUT} s, which a Dask scheduler "
                            f"does at once (another kind of server?); check the address") from None
    if len(header) < 8 or struct.unpack("Q", header)[0] > MAX_HANDSHAKE:
        raise UserError(f"--scheduler {address}: what answers there is not a Dask scheduler "
                        f"(it began {header!r}); check the address")
