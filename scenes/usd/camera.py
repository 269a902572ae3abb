"""The camera of a USD stage (``UsdGeom.Camera``, or a framing default) as a Mitsuba
sensor; a mixin of :class:`hlbvh.scenes.usd.UsdScene`.

The one named by ``camera=``, else the one the stage's render settings
(``UsdRender.Settings``) name, else the first in traversal order, else a camera
framing the first frame's meshes (said once). Focal length and apertures give the
field of view, fitted so the whole aperture shows (``fov_axis`` ``x`` or ``y``),
the clipping range gives ``near_clip``/``far_clip``. A camera that moves (its
transform, its own xformOps or an ancestor's, or its lens time-sampled) moves the
sensor: each frame gives a :class:`~hlbvh.scenes.animated.FrameSensor` of its pose,
field of view and clipping range at the frame's time code (:meth:`_Camera.camera_at`,
which takes any time code, fractional ones included, for times inside a shutter).
"""

from __future__ import annotations

import math

import mitsuba as mi
import numpy as np

from ..animated import FrameSensor, checked_resolution
from .prims import (DEFAULT_WIDTH, Sdf, Usd, UsdGeom, UsdRender, _USD_TO_MITSUBA_CAMERA,
                    _checked, _matrix, _transform_varies)


#: The sensor's id in the scene description, under which a frame gives a moving camera.
SENSOR_ID = "camera"


class _Camera:
    """The camera of a USD stage, as methods of :class:`UsdScene`."""

    def camera_at(self, time_code: float) -> FrameSensor | None:
        """The stage's camera at ``time_code`` (any time code, between samples too:
        USD interpolates them) as a :class:`FrameSensor`: its world transform (its
        own and its ancestors' xformOps, in Mitsuba's Y-up metres, scale removed),
        its aperture's fields of view from the focal length and apertures, its
        clipping range in metres. ``None`` for the framing default, which does not
        move.

        Raises:
            ValueError: naming the camera and the time code, where a value would not
                make a sensor (see :meth:`_lens`).
        """
        return None if self._camera is None else self._lens(self._camera, time_code)

    def camera_moves(self) -> bool:
        """Whether the stage's camera is time-sampled (its transform, its own or an
        ancestor's, or an attribute of its lens), so frames move the sensor."""
        return self._camera is not None and (_transform_varies(self._camera) or any(
            a.GetNumTimeSamples() > 1 for a in self._camera.GetAttributes()))

    def _pick_camera(self, wanted: str | None):
        """The camera prim to render through (checked by :meth:`_checked_camera`), or
        ``None`` for the framing default."""
        if wanted is not None:
            prim = self.stage.GetPrimAtPath(wanted) if Sdf.Path.IsValidPathString(wanted) \
                else None
            if not prim or not prim.IsA(UsdGeom.Camera):
                found = [str(p.GetPath()) for p in self._cameras()]
                raise ValueError(f"{self._where}: camera {wanted!r} is not a UsdGeom.Camera "
                                 f"of the stage (its cameras: {found or 'none'})")
            return self._checked_camera(prim)
        settings = UsdRender.Settings.GetStageRenderSettings(self.stage)
        if settings:
            targets = settings.GetCameraRel().GetForwardedTargets()
            if targets and self.stage.GetPrimAtPath(targets[0]).IsA(UsdGeom.Camera):
                return self._checked_camera(self.stage.GetPrimAtPath(targets[0]))
        cameras = self._cameras()
        if cameras:
            return self._checked_camera(cameras[0])
        self._warn(f"{self._where}: no UsdGeom.Camera; a default camera frames the first "
                   f"frame's meshes")
        return None

    def _checked_camera(self, prim):
        """``prim`` when its first frame's camera makes a Mitsuba sensor
        (:meth:`_lens`); else the ValueError naming the camera and the attribute."""
        self._lens(prim, self._start)
        return prim

    def _lens(self, prim, time_code: float) -> FrameSensor:
        """The camera ``prim`` at ``time_code`` as a :class:`FrameSensor`
        (:meth:`camera_at`), after checking it makes a Mitsuba sensor: focal length
        and apertures finite and above 0, a clipping range of finite ``0 <= near <
        far``, a finite transform that does not scale it to nothing; else a ValueError
        naming the camera, the time code (after the first frame's) and the attribute
        (Mitsuba would divide by zero, render a blank image or refuse the sensor)."""
        where = f"{self._where}: camera {prim.GetPath()}" + (
            "" if time_code == self._start else f" at time code {time_code:g}")
        usd_camera = UsdGeom.Camera(prim)
        time = Usd.TimeCode(time_code)
        for name, attribute in (("focalLength", usd_camera.GetFocalLengthAttr()),
                                ("horizontalAperture", usd_camera.GetHorizontalApertureAttr()),
                                ("verticalAperture", usd_camera.GetVerticalApertureAttr())):
            _checked(f"{where}: {name}", float(attribute.Get(time)), least=0, strictly=True)
        near, far = _checked(f"{where}: clippingRange",
                             tuple(usd_camera.GetClippingRangeAttr().Get(time)), least=0)
        if not near < far:
            raise ValueError(f"{where}: clippingRange is ({near:g}, {far:g}): expected "
                             f"near < far")
        camera = usd_camera.GetCamera(time)
        to_world = self._root @ _matrix(camera.transform)
        if not np.isfinite(to_world).all() or abs(np.linalg.det(to_world[:3, :3])) <= 1e-30:
            raise ValueError(f"{where}: its transform (xformOps, its own or an "
                             f"ancestor's) is not finite or scales it to nothing")
        to_world[:3, :3] = to_world[:3, :3] / np.linalg.norm(to_world[:3, :3], axis=0)
        fov = tuple(2 * math.degrees(math.atan(aperture / (2 * camera.focalLength)))
                    for aperture in (camera.horizontalAperture, camera.verticalAperture))
        units = float(UsdGeom.GetStageMetersPerUnit(self.stage))
        return FrameSensor(to_world=to_world @ _USD_TO_MITSUBA_CAMERA, fov=fov,
                           clip=(max(near * units, 1e-6), max(far * units, near * units * 2)))

    def _cameras(self) -> list:
        predicate = Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)
        return [p for p in Usd.PrimRange(self.stage.GetPseudoRoot(), predicate)
                if p.IsA(UsdGeom.Camera)]

    def _resolution(self, resolution) -> tuple[int, int]:
        if resolution is not None:
            return checked_resolution(resolution)
        settings = UsdRender.Settings.GetStageRenderSettings(self.stage)
        if settings and settings.GetResolutionAttr().HasAuthoredValue():
            width, height = settings.GetResolutionAttr().Get()
            if width < 1 or height < 1:
                raise ValueError(f"{self._where}: render settings {settings.GetPath()}: "
                                 f"resolution is ({width}, {height}): expected positive "
                                 f"integers")
            return int(width), int(height)
        if self._camera is None:
            return DEFAULT_WIDTH, DEFAULT_WIDTH * 9 // 16
        camera = UsdGeom.Camera(self._camera).GetCamera(Usd.TimeCode(self._start))
        aspect = camera.horizontalAperture / camera.verticalAperture
        return DEFAULT_WIDTH, max(1, round(DEFAULT_WIDTH / aspect))

    def _sensor(self, width: int, height: int, spp: int) -> dict:
        """The perspective sensor: the stage's camera at the first frame
        (:meth:`camera_at`; the frames move it where it moves), or the framing
        default."""
        film = {"type": "hdrfilm", "width": width, "height": height,
                "rfilter": {"type": "box"}}
        sampler = {"type": "independent", "sample_count": spp}
        if self._camera is None:
            return {"type": "perspective", **self._framing(width / height),
                    "film": film, "sampler": sampler}
        if UsdGeom.Camera(self._camera).GetProjectionAttr().Get(
                Usd.TimeCode(self._start)) != UsdGeom.Tokens.perspective:
            self._warn_once(f"{self._where}: camera {self._camera.GetPath()} is orthographic; "
                            f"rendered as a perspective camera of its focal length")
        lens = self.camera_at(self._start)
        h_fov, v_fov = lens.fov
        # The whole aperture shows: a film wider than the aperture fits its height.
        wider = width / height > math.tan(math.radians(h_fov) / 2) / math.tan(
            math.radians(v_fov) / 2)
        return {"type": "perspective", "fov": v_fov if wider else h_fov,
                "fov_axis": "y" if wider else "x",
                "near_clip": lens.clip[0], "far_clip": lens.clip[1],
                "to_world": mi.ScalarTransform4f(lens.to_world.tolist()),
                "film": film, "sampler": sampler}

    def _framing(self, aspect: float) -> dict:
        """A camera looking at the first frame's meshes from the front, above and to
        the side, far enough that their bounding sphere fits a 40-degree view."""
        corners = np.concatenate([t.reshape(-1, 3) for t in self.world_triangles(0).values()])
        low, high = corners.min(axis=0), corners.max(axis=0)
        centre = (low + high) / 2
        radius = max(float(np.linalg.norm(high - low)) / 2, 1e-3)
        fov = 40.0
        distance = radius / math.sin(math.radians(fov / 2) * min(1.0, aspect))
        direction = np.array([0.45, 0.35, 1.0])
        origin = centre + direction / np.linalg.norm(direction) * distance
        return {"fov": fov, "fov_axis": "x" if aspect < 1 else "y",
                "near_clip": distance * 1e-3, "far_clip": distance * 10,
                "to_world": mi.ScalarTransform4f().look_at(
                    origin=origin.tolist(), target=centre.tolist(), up=[0, 1, 0])}
