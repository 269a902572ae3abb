"""The lights of a USD stage (``UsdLux``) as Mitsuba emitters; a mixin of
:class:`hlbvh.scenes.usd.UsdScene`."""

from __future__ import annotations

import math

import mitsuba as mi
import numpy as np

from .usd_prims import UsdLux, _FLIP_Z, _dome_pole, _matrix, _transform_varies


class _Lights:
    """The lights of a USD stage, as a method of :class:`UsdScene`."""

    def _add_light(self, prim, time, cache) -> None:
        """A UsdLux light as a Mitsuba emitter (or an emitting shape)."""
        path = prim.GetPath()
        kind = prim.GetTypeName()
        light = UsdLux.LightAPI(prim)
        if any(a.GetNumTimeSamples() > 1 for a in prim.GetAttributes()) or \
                _transform_varies(prim):
            self._warn(f"{self._where}: {path}: a time-sampled light; every frame uses its "
                       f"first frame's")
        intensity = float(light.GetIntensityAttr().Get(time) or 0.0)
        exposure = float(light.GetExposureAttr().Get(time) or 0.0)
        color = light.GetColorAttr().Get(time)
        color = np.array([1.0, 1.0, 1.0] if color is None else list(color), dtype=np.float64)
        radiance = intensity * 2.0 ** exposure * color
        normalize = bool(light.GetNormalizeAttr().Get(time))
        if light.GetEnableColorTemperatureAttr().Get(time):
            self._warn(f"{self._where}: {path}: its colour temperature is not applied "
                       f"(RGB rendering); its colour alone tints it")
        if prim.HasAPI(UsdLux.ShapingAPI):
            self._warn(f"{self._where}: {path}: its shaping (cone, focus, IES) is not "
                       f"applied; it emits unshaped")
        transform = self._root @ _matrix(cache.GetLocalToWorldTransform(prim))
        scale = np.linalg.norm(transform[:3, :3], axis=0)
        rotation = transform[:3, :3] / np.where(scale > 0, scale, 1)
        key = self._new_id(path)
        black = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0, 0, 0]}}

        def rgb(value):
            return {"type": "rgb", "value": [float(v) for v in value]}

        if kind == "DistantLight":
            direction = rotation @ np.array([0.0, 0.0, -1.0])
            self._lights[key] = {"type": "directional", "direction": direction.tolist(),
                                 "irradiance": rgb(radiance)}
        elif kind in ("DomeLight", "DomeLight_1"):
            dome = UsdLux.DomeLight(prim) if kind == "DomeLight" else UsdLux.DomeLight_1(prim)
            texture = dome.GetTextureFileAttr().Get(time)
            layout = dome.GetTextureFormatAttr().Get(time)
            if texture is not None and texture.resolvedPath and layout in (
                    None, UsdLux.Tokens.automatic, UsdLux.Tokens.latlong):
                if not np.allclose(color, 1.0):
                    self._warn(f"{self._where}: {path}: a textured dome's colour is "
                               f"ignored (Mitsuba's envmap takes a scale only)")
                # Mitsuba's envmap and UsdLux's dome both follow OpenEXR's latlong
                # layout (longitude 0 along +Z, +pi/2 along +X, the top pole +Y): only the
                # pole differs, for DomeLight_1 whose poleAxis is the stage's Z up axis.
                to_world = np.eye(4)
                to_world[:3, :3] = rotation @ _dome_pole(dome, kind, self.stage)
                self._lights[key] = {"type": "envmap", "filename": texture.resolvedPath,
                                     "scale": intensity * 2.0 ** exposure,
                                     "to_world": mi.ScalarTransform4f(to_world.tolist())}
            else:
                if texture is not None and texture.path:
                    why = (f"is in the {layout} layout, not latlong" if texture.resolvedPath
                           else "does not resolve")
                    self._warn(f"{self._where}: {path}: texture {texture.path!r} {why}; "
                               f"the dome is a constant colour")
                self._lights[key] = {"type": "constant", "radiance": rgb(radiance)}
        elif kind == "SphereLight":
            sphere = UsdLux.SphereLight(prim)
            radius = float(sphere.GetRadiusAttr().Get(time) or 0.0) * float(scale.mean())
            centre = transform[:3, 3].tolist()
            if bool(sphere.GetTreatAsPointAttr().Get(time)) or radius <= 0:
                power_radius = max(radius, 0.0)
                factor = 1.0 if normalize or power_radius == 0 else math.pi * power_radius ** 2
                self._lights[key] = {"type": "point", "position": centre,
                                     "intensity": rgb(radiance * factor)}
            else:
                if normalize:
                    radiance = radiance / (4 * math.pi * radius ** 2)
                self._lights[key] = {"type": "sphere", "center": centre, "radius": radius,
                                     "bsdf": black,
                                     "emitter": {"type": "area", "radiance": rgb(radiance)}}
        elif kind in ("RectLight", "DiskLight"):
            if kind == "RectLight":
                rect = UsdLux.RectLight(prim)
                half = np.array([float(rect.GetWidthAttr().Get(time)) / 2,
                                 float(rect.GetHeightAttr().Get(time)) / 2, 1.0])
                area = 4 * half[0] * half[1] * scale[0] * scale[1]
                if rect.GetTextureFileAttr().Get(time):
                    self._warn(f"{self._where}: {path}: a rect light's texture is not read")
            else:
                r = float(UsdLux.DiskLight(prim).GetRadiusAttr().Get(time))
                half = np.array([r, r, 1.0])
                area = math.pi * r * r * scale[0] * scale[1]
            if normalize and area > 0:
                radiance = radiance / area
            to_world = transform @ np.diag([*half, 1.0]) @ _FLIP_Z
            self._lights[key] = {
                "type": "rectangle" if kind == "RectLight" else "disk",
                "to_world": mi.ScalarTransform4f(to_world.tolist()), "bsdf": black,
                "emitter": {"type": "area", "radiance": rgb(radiance)}}
        else:
            self._ids.discard(key)
            self._warn(f"{self._where}: {path}: a {kind} is not supported; it does not "
                       f"light the scene")
