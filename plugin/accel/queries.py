"""``mi.Scene``'s three ray queries (``ray_intersect_preliminary``, ``ray_intersect``,
``ray_test``) with its signatures, overloads and defaults, bound once in :class:`SceneQueries`
for every intersector, and :class:`NativeAccel`, the scene's own accelerator behind
them (the reference hlbvh's images are compared against)."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi


def _bind_overloads(args: tuple, long_names: tuple, given: dict) -> dict:
    """Bind the positional arguments after ``ray`` the way ``mi.Scene``'s overloads do.

    ``mi.Scene.ray_intersect`` and ``ray_test`` each have a short overload
    ``f(ray, active)`` and a long one ``f(ray, <long_names...>, active)``: a single
    positional argument is ``active``; several fill ``long_names`` then ``active`` in
    order.

    Args:
        args: the positional arguments after ``ray``.
        long_names: the long overload's parameter names before ``active``.
        given: the keyword arguments, defaults filled in, with ``active`` None when not
            passed by keyword.
    Returns:
        ``given`` with the positional arguments bound and ``active`` never None.
    """
    names = long_names + ("active",)
    if len(args) == 1 and given["active"] is None:
        names = ("active",)
    elif len(args) > len(names):
        raise TypeError(f"expected at most {len(names) + 1} positional arguments (ray, "
                        f"{', '.join(names)}), got {len(args) + 1}")
    bound = dict(given)
    for name, value in zip(names, args):
        bound[name] = value
    if bound["active"] is None:
        bound["active"] = True
    return bound


def checked_scene(scene):
    """``scene``, after checking it is a loaded ``mi.Scene`` (TypeError otherwise)."""
    if not isinstance(scene, mi.Scene):
        raise TypeError(
            f"scene: expected a loaded mi.Scene (mi.load_file / mi.load_dict), got "
            f"{type(scene).__name__}"
        )
    return scene


def _checked_ray(ray):
    """``ray``, after checking it is a ray (anything with ``o``, ``d`` and ``maxt``, as
    ``mi.Ray3f``); TypeError otherwise."""
    if not all(hasattr(ray, name) for name in ("o", "d", "maxt")):
        raise TypeError(f"ray: expected an mi.Ray3f, got {type(ray).__name__}")
    widths = {name: dr.width(getattr(ray, name)) for name in ("o", "d", "maxt", "time")
              if hasattr(ray, name)}
    if len(set(widths.values()) - {1}) > 1:
        raise ValueError("ray: its fields hold different numbers of rays ("
                         + ", ".join(f"{k} {v}" for k, v in widths.items())
                         + "); give every field one entry per ray, or one for all")
    return ray


def _no_rays(ray) -> bool:
    """Whether ``ray`` holds no rays (its origins or directions are empty; ``maxt``
    and ``time`` may still be width-1 defaults)."""
    return dr.width(ray.o) == 0 or dr.width(ray.d) == 0


class SceneQueries:
    """The three query methods of ``mi.Scene`` with its signatures, keyword names and
    defaults (every overload: ``ray_intersect(ray, active)`` and ``ray_test(ray,
    active)`` included, and the keyword-only ``reorder``, ``reorder_hint``,
    ``reorder_hint_bits``, which are thread-reordering hints for CUDA), bound here once
    and handed to a subclass's ``_preliminary``, ``_intersect`` and ``_test``."""

    def ray_intersect_preliminary(self, ray, coherent=False, active=True, *, reorder=False,
                                  reorder_hint=0, reorder_hint_bits=0):
        """``mi.Scene.ray_intersect_preliminary``: the closest hit's parameters.

        Args:
            ray: ``mi.Ray3f`` (``maxt`` honoured; hits at t <= 0 are never reported).
            coherent: hint that the rays are coherent (camera rays). It changes
                Embree's answer on a few edge rays, so pass what Mitsuba would.
            active: Bool mask.
        Returns:
            ``mi.PreliminaryIntersection3f`` with ``t``, ``prim_uv``, ``prim_index``
            (local to the shape), ``shape_index`` (into ``scene.shapes()``), ``shape``,
            ``instance`` null; on a miss ``valid`` False and ``t`` infinite.
        """
        if _no_rays(_checked_ray(ray)):
            return dr.zeros(mi.PreliminaryIntersection3f, 0)
        return self._preliminary(ray, coherent, active, (reorder, reorder_hint, reorder_hint_bits))

    def ray_intersect(self, ray, *args, ray_flags=mi.RayFlags.All, coherent=False, active=None,
                      reorder=False, reorder_hint=0, reorder_hint_bits=0):
        """``mi.Scene.ray_intersect``: ``(ray, active=True)`` or
        ``(ray, ray_flags, coherent, active=True)``.

        Returns:
            ``mi.SurfaceInteraction3f`` computed by Mitsuba from the closest hit.
        """
        a = _bind_overloads(args, ("ray_flags", "coherent"),
                            dict(ray_flags=ray_flags, coherent=coherent, active=active))
        if _no_rays(_checked_ray(ray)):
            return dr.zeros(mi.SurfaceInteraction3f, 0)
        return self._intersect(ray, a["ray_flags"], a["coherent"], a["active"],
                               (reorder, reorder_hint, reorder_hint_bits))

    def ray_test(self, ray, *args, coherent=False, active=None):
        """``mi.Scene.ray_test``: ``(ray, active=True)`` or ``(ray, coherent, active=True)``.

        Returns:
            Bool per ray: whether anything lies on it at 0 < t <= ``ray.maxt``.
        """
        a = _bind_overloads(args, ("coherent",), dict(coherent=coherent, active=active))
        if _no_rays(_checked_ray(ray)):
            return dr.zeros(mi.Bool, 0)  # Mitsuba's own query aborts the process on it
        return self._test(ray, a["coherent"], a["active"])

    def _intersect(self, ray, ray_flags, coherent, active, reorder):
        """The closest hit, expanded by Mitsuba, as ``mi.Scene.ray_intersect`` does."""
        pi = self._preliminary(ray, coherent, active, reorder)
        return self.surface_interaction(pi, ray, ray_flags, active)

    def surface_interaction(self, pi, ray, ray_flags=mi.RayFlags.All, active=True):
        """The surface interaction of the hits ``pi`` of ``ray``:
        ``pi.compute_surface_interaction(ray, ray_flags, active)`` (Mitsuba's)."""
        return pi.compute_surface_interaction(ray, ray_flags, active)

    def points_over_shutter(self, pi, si, active=True):
        """Where each hit of ``pi`` (expanded as ``si``) is at the shutter's open and
        close, and the shutter's length in the units of ``ray.time``: ``(p_open,
        p_close, length)``. Here, where nothing moves inside a frame, the hit itself
        twice (``length`` 1)."""
        return si.p, si.p, 1.0


class NativeAccel(SceneQueries):
    """The scene's own accelerator (Embree or OptiX) behind the same interface as
    :class:`SceneAccel`: the reference our images are compared against. Every query is
    the scene's, with the same arguments.

    Args:
        scene: the ``mi.Scene``. Mitsuba rebuilds its accelerator itself in
            ``params.update()``, so :meth:`update` has nothing to do.
        shading: an :class:`hlbvh.accel.instance_shading.InstanceShading` that expands
            the hits (inside instances: field for field as Mitsuba does, without the call
            through a shape pointer that Mitsuba compiles for every instance), or None
            for Mitsuba's own expansion.
    """

    name = "native"

    def __init__(self, scene, shading=None):
        self.scene = scene
        self.shading = shading

    def update(self):
        """Nothing to do: ``params.update()`` already rebuilt Mitsuba's accelerator.

        Returns:
            self.
        """
        return self

    def _preliminary(self, ray, coherent, active, reorder):
        return self.scene.ray_intersect_preliminary(ray, coherent, *reorder, active)

    def _intersect(self, ray, ray_flags, coherent, active, reorder):
        if self.shading is not None:
            return super()._intersect(ray, ray_flags, coherent, active, reorder)
        return self.scene.ray_intersect(ray, ray_flags, coherent, *reorder, active)

    def _test(self, ray, coherent, active):
        return self.scene.ray_test(ray, coherent, active)

    def surface_interaction(self, pi, ray, ray_flags=mi.RayFlags.All, active=True):
        """The hits ``pi`` of ``ray`` expanded by ``shading`` where given, else by Mitsuba."""
        if self.shading is None:
            return super().surface_interaction(pi, ray, ray_flags, active)
        return self.shading.surface_interaction(pi, ray, ray_flags, active)
