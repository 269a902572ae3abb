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

The scene's own accelerator is then out of date: render such a scene only with our
integrators and ``accel="hlbvh"`` (``accel="native"`` and Mitsuba's C++ integrators
query it), or call ``mi.traverse(scene).update()`` after a change of an emitter or
sensor that needs the scene.
"""

from __future__ import annotations

import mitsuba as mi


class ShapeParameters(mi.SceneParameters):
    """``mi.SceneParameters`` whose ``update()`` never notifies the scene itself (see
    the module docstring); made by :func:`traverse`."""

    def set_dirty(self, key: str):
        """Mark ``key``'s object and its parents for the next ``update()``, the scene
        (the root, depth 0) excepted."""
        entry = super().set_dirty(key)
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
    return ShapeParameters(params.properties, params.hierarchy)
