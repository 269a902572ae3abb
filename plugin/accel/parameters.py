"""A scene's parameters, updated without Mitsuba's whole-scene rebuild: the public way
to animate a scene rendered with ``accel="hlbvh"``.

``mi.traverse(scene)`` gives ``mi.SceneParameters``, whose ``update()`` notifies every
changed object and then the scene, which rebuilds its whole accelerator (Embree or
OptiX, shape groups included) as soon as one shape changed: hundreds of milliseconds a
frame for a million static triangles, although our integrators never query that
accelerator. :func:`traverse` gives the same parameters, the same keys and the same
writes; its ``update()`` notifies the changed objects and their parents as Mitsuba's
does, every one but the scene itself. Each shape refreshes what it derives from its
parameters (bounds, normals, sampling tables); our accelerators follow on their next
update (an hlbvh integrator updates its own at the start of every render), rebuilding
or refitting only what moved.

Mitsuba's own accelerator is then out of date, so the rebuild is skipped only where
nothing queries it: when the scene's integrator is one of ours with ``accel="hlbvh"``.
A scene whose integrator traces through Mitsuba's accelerator (Mitsuba's C++ ``path``,
``volpath``, ``ptracer``, ``aov``, a wrapper such as ``moment`` around one of those, or
ours with ``accel="native"``) is updated as ``mi.traverse`` updates it, rebuild included, with
one warning saying so: its images are never rendered from old geometry. A scene
without an integrator is taken to be traced through our accelerator (a
:class:`hlbvh.SceneAccel` of the caller's); a render that passes another integrator
than the scene's (``mi.render(scene, integrator=...)``) must use ``mi.traverse``. Call ``mi.traverse(scene).update()``
after a change of an emitter or sensor that needs the scene.
"""

from __future__ import annotations

import warnings

import mitsuba as mi


class ShapeParameters(mi.SceneParameters):
    """``mi.SceneParameters`` whose ``update()`` does not notify the scene itself when
    the scene's integrator traces through our accelerator (see the module docstring);
    made by :func:`traverse`.

    Attributes:
        skips_rebuild: whether ``update()`` skips the scene's own rebuild.
    """

    skips_rebuild = True

    def set_dirty(self, key: str):
        """Mark ``key``'s object and its parents for the next ``update()``, the scene
        (the root, depth 0) excepted when :attr:`skips_rebuild`."""
        entry = super().set_dirty(key)
        if not self.skips_rebuild:
            return entry
        node = self.properties[key][2]
        while node is not None:  # up to the root: a walk of the key's depth, per write
            parent, depth = self.hierarchy[node]
            if parent is None and isinstance(node, mi.Scene):
                self.nodes_to_update.pop((depth, node), None)
            node = parent
        return entry


def traverse(scene: mi.Scene) -> ShapeParameters:
    """The parameters of ``scene``, as ``mi.traverse(scene)``, whose ``update()`` does
    not rebuild the scene's own accelerator.

    A hand-written animation loop::

        scene = mi.load_file("shot.xml")          # integrator hlbvh_path, accel="hlbvh"
        params = hlbvh.traverse(scene)
        for frame in range(frames):
            params["flag.vertex_positions"] = positions(frame)
            params.update()                        # the flag refreshes itself, nothing else
            image = mi.render(scene, seed=frame)   # our accelerator follows the flag

    Args:
        scene: a loaded ``mi.Scene``.
    Returns:
        :class:`ShapeParameters`.
    Raises:
        TypeError: ``scene`` is not a ``mi.Scene``.
    """
    if not isinstance(scene, mi.Scene):
        raise TypeError(f"scene: expected a loaded mi.Scene, got {type(scene).__name__}")
    params = mi.traverse(scene)
    shape_params = ShapeParameters(params.properties, params.hierarchy)
    integrator = scene.integrator()
    if integrator is not None and not _traces_through_ours(integrator, params.hierarchy):
        shape_params.skips_rebuild = False
        name = getattr(integrator, "accel_name", None)
        what = (f"{integrator.class_name()} with accel={name!r}" if name
                else f"integrator {integrator.class_name()!r}")
        warnings.warn(
            f"hlbvh.traverse: the scene's {what} traces through Mitsuba's own "
            "accelerator, so update() rebuilds it as mi.traverse's does (no time saved); "
            "an hlbvh integrator with accel='hlbvh' skips that rebuild",
            stacklevel=2)
    return shape_params


#: Mitsuba's integrators that trace nothing themselves: each sample is their nested
#: integrators' (``aov`` is not among them: its own channels query the scene).
WRAPPERS = ("MomentIntegrator", "StokesIntegrator")


def _traces_through_ours(integrator, hierarchy) -> bool:
    """Whether every ray ``integrator`` traces goes through our accelerator: it is one of
    ours with ``accel="hlbvh"``, or a wrapper (:data:`WRAPPERS`) whose nested
    integrators all are (found among the scene's objects, ``hierarchy``)."""
    if getattr(integrator, "accel_name", None) == "hlbvh":
        return True
    if integrator.class_name() not in WRAPPERS:
        return False
    nested = [node for node in hierarchy
              if isinstance(node, mi.Integrator) and node is not integrator]
    return bool(nested) and all(getattr(n, "accel_name", None) == "hlbvh" for n in nested)
