"""One frame of an animation: its geometry (and a moving camera's pose and lens)
written into the loaded scene, the accelerator brought up to date, the render, and the
frame's statistics row (:data:`STATS_FIELDS`, timed with :func:`hlbvh.timing.clock_ms`)."""

from __future__ import annotations

import re
import resource
from pathlib import Path

import drjit as dr
import mitsuba as mi

from hlbvh import scenes
from hlbvh.accel.instance_shading import is_instance
from hlbvh.accel.keys import set_camera_keys, set_instance_keys, set_motion_keys
from hlbvh.accel.parameters import traverse
from hlbvh.accel.policy import UpdatePolicy
from hlbvh.accel.scene_geometry import ShapeError, scene_shapes
from hlbvh.errors import UserError
from hlbvh.render.settings import RenderSettings
from hlbvh.scenes.animated import FrameSensor
from hlbvh.timing import clock_ms

#: Columns of ``stats.csv``, and keys of every row of ``stats.json``.
STATS_FIELDS = ("frame", "accel", "triangles", "seed", "geometry_ms", "mitsuba_update_ms",
                "build_ms", "render_ms", "sah_cost", "decision", "moving_accel")

#: Most samples (width x height x spp) of one frame: Dr.Jit arrays hold at most
#: 2^32 - 1 entries, and ``mi.render`` traces them as one wavefront.
MAX_SAMPLES = 2**32 - 1

#: Most instances a native render is let to take: Mitsuba compiles its expansion of
#: hits for every instance, with a call through each group inside
#: (docs/decisions.md#instance-hit-expansion:
#: 17 s of compilation at 400 instances, more than 24 GB at 10k).
MOST_NATIVE_INSTANCES = 1000

#: Memory a frame takes per pixel and per sample, in bytes: about twice the peak of
#: ``mi.render`` on the LLVM backend (film, wavefront and the developed image;
#: docs/decisions.md#frame-memory), so a frame refused here would not have fit.
BYTES_PER_PIXEL, BYTES_PER_SAMPLE = 64, 32


class FrameRenderer:
    """An animated scene loaded once, rendering any of its frames with timings.

    Args:
        animation: the :class:`hlbvh.scenes.AnimatedScene`.
        settings: the :class:`hlbvh.render.settings.RenderSettings`.
    Raises:
        ValueError: the integrator cannot be made from the settings (naming what
            Mitsuba or the builder objected to).
        UserError: the frame does not fit in Dr.Jit's arrays or the machine's memory
            (:func:`check_frame_fits`), ``accel="native"`` over more than
            :data:`MOST_NATIVE_INSTANCES` instances, or ``accel="hlbvh"`` with ``static="hlbvh"``
            and the scene holds shapes our BVHs do not intersect (instances, curves,
            ...).

    Attributes:
        scene: the loaded ``mi.Scene``; ``params``: its parameters (with
        ``accel="hlbvh"`` through :func:`hlbvh.traverse`, whose update skips Mitsuba's
        whole-scene rebuild, since nothing queries Mitsuba's own accelerator then);
        integrator: its hlbvh integrator (inside a wrapper: the wrapped one).
    """

    def __init__(self, animation, settings: RenderSettings):
        self.animation = animation
        self.settings = settings
        description = settings.integrator_dict()
        ours = description.get("nested", description)  # inside a wrapper, if any
        if settings.accel == "hlbvh" and "moving" not in ours:
            # The animation says what moves: its static structure is built once, never
            # rebuilt without the moving shapes at their first motion.
            ours["moving"] = ",".join(animation.animated_ids())
        try:
            mi.load_dict(description)  # a bad property fails here, alone, before the scene
        except RuntimeError as error:
            raise ValueError(
                f"integrator {description['type']}: {_mitsuba_message(error)}"
            ) from None
        self.scene = mi.load_dict(_with_shutter(animation.scene_dict(
            resolution=settings.resolution, spp=settings.spp, integrator=description),
            settings.shutter))
        self.params = (traverse(self.scene) if settings.accel == "hlbvh"
                       else mi.traverse(self.scene))
        self.integrator = _ours(self.scene, self.params)
        sensor = self.scene.sensors()[0]
        width, height = sensor.film().crop_size()
        check_frame_fits(int(width), int(height), int(sensor.sampler().sample_count()))
        instances = sum(is_instance(s) for s in self.scene.shapes())
        if settings.accel == "native" and instances > MOST_NATIVE_INSTANCES:
            raise UserError(f"the scene has {instances} instances: Mitsuba's own renderer "
                            f"compiles a call for each (more than {MOST_NATIVE_INSTANCES} "
                            "take minutes and tens of GB); render it with --accel hlbvh")
        if settings.accel == "hlbvh":
            try:
                scene_shapes(self.scene.shapes(), ours.get("static", UpdatePolicy.static))
            except ShapeError as error:
                raise UserError(f"{error.reason} Render this scene with --accel native "
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
        # ---- The frame's geometry into the scene; its shapes update themselves ----
        # (with our accelerator, through hlbvh.traverse: Mitsuba's is never rebuilt);
        # a moving camera's sensor is written with them, from the same frame
        # description, so every render of frame i (resumed, on a worker) sees its pose
        start = clock_ms()
        parameters = _TimedUpdate(self.params)
        accumulated = self.settings.shutter_open and self.settings.accel == "native"
        if not accumulated:  # (native's sub-frames each write their own geometry)
            scenes.apply_frame(self.scene, parameters, self.animation.frame(i))
        if self.settings.shutter_open and self.settings.accel == "hlbvh":
            self._key_motion(i)
        geometry_ms = clock_ms() - start - parameters.update_ms

        # ---- Our accelerator follows ----
        if self.settings.accel == "hlbvh":
            build_ms, sah_cost, decision, moving_accel = self._update_accel(spp or 0)
        else:
            build_ms, sah_cost, decision, moving_accel = parameters.update_ms, None, "native", ""

        # ---- Render ----
        seed = self.settings.seed + i
        start = clock_ms()
        if accumulated:
            image = self.accumulated(i, seed, spp, parameters)
        else:
            with self.integrator.updated():  # updated above: the render need not look again
                image = mi.render(self.scene, seed=seed, spp=0 if spp is None else spp)
        dr.eval(image)
        render_ms = clock_ms() - start

        row = {
            "frame": i, "accel": self.settings.accel, "triangles": self.triangle_count(),
            "seed": seed, "geometry_ms": round(geometry_ms, 3),
            "mitsuba_update_ms": round(parameters.update_ms, 3), "build_ms": round(build_ms, 3),
            "render_ms": round(render_ms, 3), "sah_cost": sah_cost, "decision": decision,
            "moving_accel": moving_accel,
        }
        return image, row

    def _key_motion(self, i: int):
        """Give every animated mesh its positions, every moving instance its transforms,
        and a moving camera its poses, at the shutter's keys around frame ``i``
        (:meth:`~hlbvh.scenes.AnimatedScene.frame_at`; ``settings.motion_keys``
        intervals), so that our integrators trace each ray at its time."""
        open_, close = self.settings.shutter
        count = self.settings.motion_keys
        times = [i + open_ + k * (close - open_) / count for k in range(count + 1)]
        frames = [self.animation.frame_at(t) for t in times]
        for shape in self.scene.shapes():
            given = [frame.get(shape.id()) for frame in frames]
            if all(isinstance(g, scenes.FrameGeometry) and g.positions is not None
                   and g.faces is None for g in given):
                set_motion_keys(shape, [mi.Float(g.positions) for g in given], (open_, close))
            elif all(isinstance(g, scenes.FrameGeometry) and g.to_world is not None
                     for g in given):
                set_instance_keys(shape, [g.to_world for g in given], (open_, close))
        for sensor in self.scene.sensors():
            given = [frame.get(sensor.id()) for frame in frames]
            if all(isinstance(g, FrameSensor) for g in given):
                set_camera_keys(sensor, [g.to_world for g in given], (open_, close))

    def accumulated(self, i: int, seed: int, spp: int | None, parameters=None) -> mi.TensorXf:
        """Frame ``i`` with the shutter open as sub-frames: the mean of
        ``settings.sub_frames`` renders of the geometry at stratified times inside the
        shutter (each at the frame's samples over the sub-frames, its own seed), each an
        update of the accelerator (native's: a rebuild, the only way Mitsuba has; ours:
        what the benchmark compares our blurred frame with). The same estimator as a
        blurred render in expectation."""
        parameters = self.params if parameters is None else parameters
        open_, close = self.settings.shutter
        count = self.settings.sub_frames
        each = max((spp or int(self.scene.sensors()[0].sampler().sample_count())) // count, 1)
        total = None
        for j in range(count):
            scenes.apply_frame(self.scene, parameters, self.animation.frame_at(
                i + open_ + (j + 0.5) * (close - open_) / count))
            image = mi.render(self.scene, seed=seed * count + j, spp=each)
            total = image if total is None else total + image
        return total * (1.0 / count)

    def _update_accel(self, spp: int) -> tuple[float, float | None, str, str]:
        """Bring our accelerator up to date with the frame, for a render at ``spp`` (0:
        the scene's), before the render (whose own update then finds nothing changed):
        (ms, SAH cost, decision, what traced the moving meshes) as the accelerator's
        preparation reports them (:class:`hlbvh.accel.preparation.Prepared`; the whole
        scene's rebuild, when it traces them, is in the ms and said ``"native"``)."""
        prepared = self.integrator.update_accel(self.scene, 0, spp).prepared
        return prepared.ms, prepared.sah_cost, prepared.decision, prepared.traced_by

    def triangle_count(self) -> int:
        """Triangles of every mesh of the scene as it is now, an instance's counted as
        its shape group's primitives (each instance of a group counts them again)."""
        return sum(s.face_count() if s.is_mesh() else
                   s.effective_primitive_count() if is_instance(s) else 0
                   for s in self.scene.shapes())

    def channel_names(self, image) -> list[str]:
        """Names of the film's channels in ``image``: R, G, B (, A), then the AOVs."""
        aovs = list(self.scene.integrator().aov_names())  # a wrapper's, if any
        colour = image.shape[2] - len(aovs)
        return ["R", "G", "B", "A"][:colour] + aovs


#: Mitsuba's sensor plugins, whose shutter a scene description's sensor entry sets.
SENSOR_TYPES = ("perspective", "thinlens", "orthographic", "telecentric", "radiancemeter",
                "irradiancemeter", "distant", "batch")


def _with_shutter(description: dict, shutter: tuple) -> dict:
    """The scene description with every sensor's ``shutter_open``/``shutter_close``
    set to ``shutter`` (frame-relative, in frames: a ray's time is then a frame offset
    inside the shutter), where the shutter is open."""
    if shutter[1] > shutter[0]:
        for entry in description.values():
            if isinstance(entry, dict) and entry.get("type") in SENSOR_TYPES:
                entry["shutter_open"], entry["shutter_close"] = shutter
    return description


def _ours(scene: mi.Scene, params) -> mi.Integrator:
    """The scene's hlbvh integrator: its own, or the one its wrapper (``moment``,
    ``stokes``) holds, found among the scene's objects in ``params``."""
    top = scene.integrator()
    if hasattr(top, "update_accel"):
        return top
    return next(node for node in params.hierarchy
                if isinstance(node, mi.Integrator) and hasattr(node, "update_accel"))


def check_frame_fits(width: int, height: int, spp: int, spp_flag: str = "--spp") -> None:
    """Refuse a frame that Dr.Jit cannot index (:data:`MAX_SAMPLES`) or that needs more
    memory than this process can still get (:func:`available_memory`, with
    :data:`BYTES_PER_PIXEL` and :data:`BYTES_PER_SAMPLE`): it would otherwise fail
    deep inside ``mi.render`` or crash the process.

    Raises:
        UserError: naming the frame's size (the scene's own or ``--resolution``'s) and
            spp, the limit and the need, and the flags that lower them (``spp_flag``:
            the one that set the spp, e.g. ``--spp-curve``).
    """
    samples = width * height * spp
    what = f"a frame of {width}x{height} pixels at {spp} spp"
    lower = f"lower it with --resolution or {spp_flag}"
    if samples > MAX_SAMPLES:
        raise UserError(f"{what}: {samples} samples, more than the {MAX_SAMPLES} a Dr.Jit "
                        f"array holds; {lower}")
    need = width * height * BYTES_PER_PIXEL + samples * BYTES_PER_SAMPLE
    available = available_memory()
    if available is not None and need > available:
        raise UserError(f"{what} needs about {need / 2**30:.1f} GiB, this process can get "
                        f"{available / 2**30:.1f} GiB; {lower}")


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
        start = clock_ms()
        self._params.update()
        self.update_ms = clock_ms() - start


def _mitsuba_message(error: Exception) -> str:
    """The informative part of a Mitsuba loader error, on one line."""
    lines = [line.strip() for line in str(error).strip().splitlines() if line.strip()]
    useful = [line for line in lines if not line.startswith(("File ", "Traceback"))]
    text = " ".join(useful[-2:] if len(useful) > 1 else useful) or type(error).__name__
    return re.sub(r"\[[\w.]+:\d+\]\s*", "", text)

