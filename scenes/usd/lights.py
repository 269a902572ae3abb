"""The lights of a USD stage (``UsdLux``) as Mitsuba emitters; a mixin of
:class:`hlbvh.scenes.usd.UsdScene`.

``intensity * 2**exposure * color`` (divided by the light's area with
``normalize``), UsdLux's radiance: DistantLight -> ``directional`` of the
irradiance of that radiance over its disc (``angle``), DomeLight ->
``constant``, or ``envmap`` with its latlong ``texture:file`` (OpenEXR's layout,
as Mitsuba's; the pole +Y, or DomeLight_1's ``poleAxis``; the colour then ignored,
said), SphereLight -> a ``sphere`` area light (``point`` with ``treatAsPoint``),
RectLight -> a ``rectangle``, DiskLight -> a ``disk`` area light, each emitting
along the light's -Z as UsdLux does; time-sampled lights keep their first frame.
Colour temperature and shaping (cones, IES) are not applied (said).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mitsuba as mi
import numpy as np

from .prims import (Sdf, UsdGeom, UsdLux, _FLIP_Z, _checked, _dome_pole, _local_asset,
                    _matrix, _stderr_captured, _transform_varies, _unreadable_image)

#: The largest radiance Mitsuba's single-precision emitters hold.
_LARGEST = float(np.finfo(np.float32).max)

#: A SphereLight whose radius is below this fraction of the farthest distance from its
#: centre to the scene's geometry is lit as a point light of the same power. Sampling a
#: sphere seen under a half-angle of sine ``s = r / d`` takes ``1 - cos`` of that angle,
#: about ``s^2 / 2``, from a single-precision cosine that steps by 2^-24 near 1: its
#: error is about ``6e-8 / s^2`` of the light, 1% at this ratio, 24% at a 1 mm bulb
#: seen from 2 m, and past ``s`` about 2.4e-4 the cosine is 1 and the light black. A
#: point of the same power gives the irradiance such a sphere does wherever it is
#: seen whole, and the sphere covers less than a pixel of most cameras.
SPHERE_POINT_RATIO = 2.5e-3


def distant_size_factor(angle: float) -> float:
    """UsdLux's ``sizeFactor`` of a DistantLight of angular diameter ``angle``
    (degrees): the irradiance its disc of unit radiance gives a surface facing it,
    ``pi sin^2(theta)`` for the half-angle ``theta`` up to 90 degrees,
    ``pi (2 - sin^2(theta))`` past it (clipped to 180), 1 for a parallel light
    (``angle`` 0). ``normalize`` divides the radiance by it, so that ``intensity``
    is then that irradiance."""
    theta = min(max(math.radians(angle) / 2, 0.0), math.pi)
    if theta == 0:
        return 1.0
    sine = math.sin(theta) ** 2
    return math.pi * (sine if theta <= math.pi / 2 else 2 - sine)


#: What lights a stage without UsdLux lights, as a DCC's viewport lights it: a uniform
#: sky and a sun (Mitsuba's Y-up world, the sun from above, behind a camera that looks
#: down -Z, and to its left). A floor of albedo 0.5 facing up renders about 0.45.
DEFAULT_LIGHTS = {
    "default_sky": {"type": "constant", "radiance": {"type": "rgb", "value": [0.3] * 3}},
    "default_sun": {"type": "directional", "direction": [0.35, -1.0, -0.6],
                    "irradiance": {"type": "rgb", "value": [2.0] * 3}},
}


class _Lights:
    """The lights of a USD stage, as methods of :class:`UsdScene`."""

    def _add_default_lights(self, default_light: bool) -> None:
        """A stage without UsdLux lights is said in one line, and lit by
        :data:`DEFAULT_LIGHTS` unless ``default_light`` is False (then only its
        emitting materials light it)."""
        if default_light:
            for name, light in DEFAULT_LIGHTS.items():
                self._lights[self._new_id(Sdf.Path(f"/{name}"))] = light
            self._warn(f"{self._where}: no UsdLux light; a default sky (radiance "
                       f"{DEFAULT_LIGHTS['default_sky']['radiance']['value'][0]:g}) and sun "
                       f"(irradiance {DEFAULT_LIGHTS['default_sun']['irradiance']['value'][0]:g}"
                       f", from above) light it, as a DCC's viewport does "
                       f"(--no-default-light: none)")
        else:
            self._warn(f"{self._where}: no UsdLux light, and --no-default-light: only "
                       f"emitting materials light it")

    def _add_light(self, prim, time, cache) -> None:
        """A UsdLux light as a Mitsuba emitter (or an emitting shape), in UsdLux's
        units: the radiance ``intensity * 2^exposure * color`` (divided by the light's
        size with ``normalize``); a DistantLight's irradiance is that radiance over its
        disc (:func:`distant_size_factor`).

        Raises:
            ValueError: naming the light and the attribute: an intensity, exposure,
                colour or size that is not finite or is negative, or a radiance past
                single precision.
        """
        path = prim.GetPath()
        where = f"{self._where}: {path}"
        kind = prim.GetTypeName()
        light = UsdLux.LightAPI(prim)
        if any(a.GetNumTimeSamples() > 1 for a in prim.GetAttributes()) or \
                _transform_varies(prim):
            self._warn(f"{self._where}: {path}: a time-sampled light; every frame uses its "
                       f"first frame's")
        intensity = _checked(f"{where}: inputs:intensity",
                             float(light.GetIntensityAttr().Get(time) or 0.0), least=0)
        exposure = _checked(f"{where}: inputs:exposure",
                            float(light.GetExposureAttr().Get(time) or 0.0))
        color = light.GetColorAttr().Get(time)
        color = _checked(f"{where}: inputs:color", np.array(
            [1.0, 1.0, 1.0] if color is None else list(color), dtype=np.float64), least=0)
        try:
            power = intensity * 2.0 ** exposure
        except OverflowError:
            power = math.inf
        if not power * float(color.max()) <= _LARGEST:
            raise ValueError(f"{where}: inputs:intensity {intensity:g} * 2^inputs:exposure "
                             f"{exposure:g} * inputs:color is past single precision "
                             f"({_LARGEST:.3g})")
        normalize = bool(light.GetNormalizeAttr().Get(time))
        if light.GetEnableColorTemperatureAttr().Get(time):
            self._warn(f"{self._where}: {path}: its colour temperature is not applied "
                       f"(RGB rendering); its colour alone tints it")
        if prim.HasAPI(UsdLux.ShapingAPI):
            self._warn(f"{self._where}: {path}: its shaping (cone, focus, IES) is not "
                       f"applied; it emits unshaped")
        transform = self._root @ _matrix(cache.GetLocalToWorldTransform(prim))
        scale = np.linalg.norm(transform[:3, :3], axis=0)
        reader = _READERS.get(kind)
        if reader is None:
            self._warn(f"{self._where}: {path}: a {kind} is not supported; it does not "
                       f"light the scene")
            return
        key = self._new_id(path)
        self._lights[key] = reader(_LightPrim(
            prim, kind, where, time, self.stage, power, color, power * color, normalize,
            transform, scale, transform[:3, :3] / np.where(scale > 0, scale, 1),
            self._scene_corners(time) if kind == "SphereLight" else None), self._warn)

    def _scene_corners(self, time) -> np.ndarray | None:
        """The 8 corners ``(8, 3)`` of the stage's world bounding box at ``time`` (its
        renderable prims, from their extents) in Mitsuba's Y-up metres, computed once;
        None when the stage bounds nothing. What pxr says of the prims it bounds is said
        where they are read, so not here."""
        if "_corners" not in self.__dict__:
            with _stderr_captured():
                box = UsdGeom.BBoxCache(time, [UsdGeom.Tokens.default_,
                                               UsdGeom.Tokens.render]) \
                    .ComputeWorldBound(self.stage.GetPseudoRoot()).ComputeAlignedRange()
            corners = None
            if not box.IsEmpty():
                low, high = np.array(box.GetMin()), np.array(box.GetMax())
                corners = np.array([[(low, high)[k >> axis & 1][axis] for axis in range(3)]
                                    for k in range(8)]) @ self._root[:3, :3].T + self._root[:3, 3]
            self._corners = corners
        return self._corners


@dataclass
class _LightPrim:
    """A UsdLux light at the first frame, as a light type's reader takes it: its
    radiance ``power * color`` (``intensity * 2^exposure``) before ``normalize``, and
    its transform in Mitsuba's Y-up metres with that transform's scale and rotation."""

    prim: object
    kind: str
    where: str  # the stage and the light's path, as messages name it
    time: object
    stage: object
    power: float
    color: np.ndarray
    radiance: np.ndarray
    normalize: bool
    transform: np.ndarray
    scale: np.ndarray
    rotation: np.ndarray
    scene_corners: np.ndarray | None = None  # a SphereLight's: what it may light


def _area_radiance(light: _LightPrim, area: float) -> np.ndarray:
    """The radiance of an area light of ``area`` (m^2): its radiance, divided by the
    area with ``normalize``.

    Raises:
        ValueError: naming the light (the stage and the prim): that radiance is past
            single precision (a tiny light with ``normalize``), where Mitsuba's emitter
            would hold an infinity and render black.
    """
    if not light.normalize or area <= 0:
        return light.radiance
    radiance = light.radiance / area
    if not float(radiance.max()) <= _LARGEST:
        raise ValueError(f"{light.where}: inputs:intensity * 2^inputs:exposure * inputs:color "
                         f"/ its area ({area:.3g} m^2, inputs:normalize) is "
                         f"{float(radiance.max()):.3g}, past single precision "
                         f"({_LARGEST:.3g})")
    return radiance


def _rgb(value) -> dict:
    return {"type": "rgb", "value": [float(v) for v in value]}


def _black() -> dict:
    """The BSDF of an emitting shape: black, as UsdLux's lights reflect nothing."""
    return {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0, 0, 0]}}


def _distant(light: _LightPrim, warn) -> dict:
    """A DistantLight as a ``directional`` emitter: Mitsuba's directional light is
    parallel, so the disc's irradiance, without its soft shadows."""
    angle = _checked(f"{light.where}: inputs:angle", float(
        UsdLux.DistantLight(light.prim).GetAngleAttr().Get(light.time)), least=0)
    irradiance = (light.radiance if light.normalize
                  else light.radiance * distant_size_factor(angle))
    direction = light.rotation @ np.array([0.0, 0.0, -1.0])
    return {"type": "directional", "direction": direction.tolist(),
            "irradiance": _rgb(irradiance)}


def _dome(light: _LightPrim, warn) -> dict:
    """A DomeLight (or DomeLight_1) as an ``envmap`` of its latlong texture, else a
    ``constant`` of its radiance (a texture that cannot be read said)."""
    dome = (UsdLux.DomeLight(light.prim) if light.kind == "DomeLight"
            else UsdLux.DomeLight_1(light.prim))
    texture = dome.GetTextureFileAttr().Get(light.time)
    layout = dome.GetTextureFormatAttr().Get(light.time)
    latlong = layout in (None, UsdLux.Tokens.automatic, UsdLux.Tokens.latlong)
    resolved = texture.resolvedPath if texture is not None else ""
    filename = _local_asset(resolved) if resolved and latlong else None
    problem = None
    if resolved and latlong:
        problem = ("cannot be read from its package" if filename is None
                   else _unreadable_image(filename))
    if resolved and latlong and problem is None:
        if not np.allclose(light.color, 1.0):
            warn(f"{light.where}: a textured dome's colour is "
                 f"ignored (Mitsuba's envmap takes a scale only)")
        # Mitsuba's envmap and UsdLux's dome both follow OpenEXR's latlong
        # layout (longitude 0 along +Z, +pi/2 along +X, the top pole +Y): only the
        # pole differs, for DomeLight_1 whose poleAxis is the stage's Z up axis.
        to_world = np.eye(4)
        to_world[:3, :3] = light.rotation @ _dome_pole(dome, light.kind, light.stage)
        return {"type": "envmap", "filename": filename, "scale": light.power,
                "to_world": mi.ScalarTransform4f(to_world.tolist())}
    if texture is not None and texture.path:
        why = (problem or f"is in the {layout} layout, not latlong"
               if resolved else "does not resolve")
        warn(f"{light.where}: texture {texture.path!r} {why}; "
             f"the dome is a constant colour")
    return {"type": "constant", "radiance": _rgb(light.radiance)}


def _sphere(light: _LightPrim, warn) -> dict:
    """A SphereLight as a ``sphere`` area light, or a ``point`` of the sphere's power:
    with ``treatAsPoint``, a radius of 0, or a radius below :data:`SPHERE_POINT_RATIO`
    of the farthest distance to the scene's geometry (said)."""
    sphere = UsdLux.SphereLight(light.prim)
    radius = _checked(f"{light.where}: inputs:radius",
                      float(sphere.GetRadiusAttr().Get(light.time) or 0.0), least=0) \
        * float(light.scale.mean())
    centre = light.transform[:3, 3]
    reach = 0.0 if light.scene_corners is None else \
        float(np.linalg.norm(light.scene_corners - centre, axis=1).max())
    small = 0 < radius < SPHERE_POINT_RATIO * reach
    if small:
        warn(f"{light.where}: a SphereLight of radius {radius:.3g} m, {radius / reach:.2g} "
             f"of the farthest distance to the scene ({reach:.3g} m), cannot be sampled "
             f"as a sphere in single precision; it is lit as a point light of the same "
             f"power")
    if bool(sphere.GetTreatAsPointAttr().Get(light.time)) or radius <= 0 or small:
        # A point of the sphere's power: a sphere of radiance L seen from afar is a
        # disc of area pi r^2, an intensity of L pi r^2 in every direction (L / 4
        # with normalize, whatever the radius).
        factor = 0.25 if light.normalize else math.pi * radius ** 2
        if factor == 0:
            warn(f"{light.where}: a SphereLight of radius 0 without inputs:normalize "
                 f"emits nothing (UsdLux: radiance times its area)")
        return {"type": "point", "position": centre.tolist(),
                "intensity": _rgb(light.radiance * factor)}
    radiance = _area_radiance(light, 4 * math.pi * radius ** 2)
    return {"type": "sphere", "center": centre.tolist(), "radius": radius, "bsdf": _black(),
            "emitter": {"type": "area", "radiance": _rgb(radiance)}}


def _rect_or_disk(light: _LightPrim, warn) -> dict:
    """A RectLight as a ``rectangle``, a DiskLight as a ``disk`` area light, each
    emitting along the light's -Z as UsdLux does."""
    where, time, scale = light.where, light.time, light.scale
    if light.kind == "RectLight":
        rect = UsdLux.RectLight(light.prim)
        half = np.array([_checked(f"{where}: inputs:width",
                                  float(rect.GetWidthAttr().Get(time)), 0, True) / 2,
                         _checked(f"{where}: inputs:height",
                                  float(rect.GetHeightAttr().Get(time)), 0, True) / 2,
                         1.0])
        area = 4 * half[0] * half[1] * scale[0] * scale[1]
        if rect.GetTextureFileAttr().Get(time):
            warn(f"{where}: a rect light's texture is not read")
    else:
        r = _checked(f"{where}: inputs:radius",
                     float(UsdLux.DiskLight(light.prim).GetRadiusAttr().Get(time)), 0, True)
        half = np.array([r, r, 1.0])
        area = math.pi * r * r * scale[0] * scale[1]
    radiance = _area_radiance(light, area)
    to_world = light.transform @ np.diag([*half, 1.0]) @ _FLIP_Z
    return {"type": "rectangle" if light.kind == "RectLight" else "disk",
            "to_world": mi.ScalarTransform4f(to_world.tolist()), "bsdf": _black(),
            "emitter": {"type": "area", "radiance": _rgb(radiance)}}


#: Each UsdLux light type's reader: the Mitsuba emitter (or emitting shape) it becomes.
_READERS = {"DistantLight": _distant, "DomeLight": _dome, "DomeLight_1": _dome,
            "SphereLight": _sphere, "RectLight": _rect_or_disk, "DiskLight": _rect_or_disk}
