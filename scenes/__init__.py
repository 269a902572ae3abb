"""Animated scenes for Mitsuba 3: procedural scenes people render, and loaders for
what users bring. (Imports Mitsuba, Dr.Jit and numpy only: never the kernels or the
plugin.)

The interface
-------------
Every scene is an :class:`AnimatedScene`:

``scene.name: str``, ``scene.frame_count: int``
    What it is called, and how many frames it has (``frame(i)`` for
    ``0 <= i < frame_count``).
``scene.scene_dict(resolution=None, spp=None, integrator=None) -> dict``
    A description for ``mi.load_dict``: a perspective camera whose film has a ``box``
    reconstruction filter (renders with the same seed are bit-comparable), an
    integrator, lights, materials and meshes. ``None`` keeps the scene's own value
    (procedural scenes: ``(640, 360)``, 16 spp, ``{"type": "path", "max_depth": 8}``).
    Meshes are handed over as already-built ``mi.Mesh`` objects, so they keep their ids
    through ``mi.load_dict``'s default ``optimize=True`` (Mitsuba never merges an object
    it did not build); each call builds new ones: load each returned dict once.
``scene.animated_ids() -> list[str]``, ``scene.static_ids() -> list[str]``
    Ids of the shapes that change per frame and of those that never do. In the loaded
    scene, ``mi.traverse`` names a shape's buffers ``f"{id}.vertex_positions"`` and
    ``f"{id}.faces"``.
``scene.frame(i) -> dict[str, FrameGeometry]``
    For every animated id, the frame's ``positions`` (flat ``3V``: numpy ``float32``
    from procedural scenes, ``mi.Float`` from sequences) and ``faces`` (``None`` unless
    the topology may have changed; flat ``3F``). Random access: a pure function of
    the scene and ``i``. Procedural scenes' ``scene_dict`` holds frame 0; a sequence's
    holds the scene file's own geometry: apply ``frame(i)`` before rendering frame
    ``i``, frame 0 included.
``scene.triangle_counts() -> dict[str, int]``, ``scene.triangle_count() -> int``
    Triangles per shape and in total, for procedural scenes computed in closed form
    without building any geometry.

:func:`apply_frame(scene, params, frame_geometry, deterministic_normals=True)
<apply_frame>` writes a frame into a loaded scene (``params[f"{id}.vertex_positions"]``,
faces when given, and vertex normals computed the same way as Mitsuba but
bit-reproducibly, see :mod:`hlbvh.scenes.normals`), calls ``params.update()`` once and
returns the ids it changed. Two scenes loaded from the same animation and given the
same frame render bit-identically (box filter, same seed).

Procedural scenes (:func:`get`, :func:`names`)
----------------------------------------------
Built from numpy, seeded (``seed=0``), ``frames=60`` at 24 frames per second,
``triangles=200_000`` by default: the least number of triangles (animated and static
together; any size, 2M and beyond), rounded up to what the tessellation allows.

=============  ==============================================================  ==================
name           what moves                                                      static shapes
=============  ==============================================================  ==================
``cloth``      a flag rippled by travelling waves (coherent deformation)       pole, ground
``twist``      a closed bar twisting, bending and bulging (skinning-like)      ground
``fracture``   a torus shell bursting into ``pieces=300`` tumbling shards      ground
``rigid``      ``objects=240`` bodies in ``groups=8`` meshes, bouncing and      walls, columns,
               spinning (``instanced=True``: as instances of ``groups`` shape  ground
               groups, moved by their transforms)
``soup``       random triangles re-drawn every frame (incoherent, worst case)  ground
``world``      the ``cloth`` flag (``flag_triangles``: 1/11) over rolling     pole, terrain
               hills (``triangles=1_100_000`` in all): a moving object in a
               static world
``flock``      ``birds=10_000`` instances of one bird (``bird_triangles=300``)  terrain
               circling over the hills (``triangles=500_000``): rigid motion,
               transforms only (see :class:`Flock` for native references)
=============  ==============================================================  ==================

Sequences (:class:`SequenceScene`)
----------------------------------
``SequenceScene(scene, frames_dir, topology="fixed", box_filter=True)``: a Mitsuba
XML file or dict plus ``<frames_dir>/<shape_id>/frame_0001.ply`` (or ``.obj``), one
file per frame per animated shape, matched to the scene's shapes by id and read by
Mitsuba's own plugins. Missing, corrupt or mis-sized files raise a ``ValueError``
naming the file and the frame. See :mod:`hlbvh.scenes.sequence`.

Example::

    import hlbvh, mitsuba as mi
    from hlbvh import scenes

    animation = scenes.get("fracture", triangles=1_000_000)
    scene = mi.load_dict(animation.scene_dict(resolution=(512, 512), spp=4))
    params = mi.traverse(scene)
    for i in range(animation.frame_count):
        scenes.apply_frame(scene, params, animation.frame(i))
        image = mi.render(scene, params, seed=i)
"""

from __future__ import annotations

from .animated import AnimatedScene, FrameGeometry, apply_frame
from .cloth import Cloth
from .flock import Flock
from .fracture import Fracture
from .procedural import ProceduralScene
from .rigid import Rigid
from .sequence import SequenceScene
from .soup import Soup
from .twist import Twist
from .world import World

_PROCEDURAL = {cls.name: cls for cls in (Cloth, Twist, Fracture, Rigid, Soup, World, Flock)}


def names() -> list[str]:
    """Names of the procedural scenes :func:`get` builds."""
    return list(_PROCEDURAL)


def get(name: str, **kwargs) -> AnimatedScene:
    """The procedural scene ``name`` (see :func:`names`), built with ``kwargs``
    (``triangles``, ``frames``, ``seed`` and the scene's own options).

    Raises:
        ValueError: an unknown name, or a bad option (naming it).
    """
    if name not in _PROCEDURAL:
        raise ValueError(f"scene {name!r}: unknown; expected one of {names()}")
    try:
        return _PROCEDURAL[name](**kwargs)
    except TypeError as error:
        raise ValueError(f"scene {name!r}: {error}") from None


__all__ = [
    "AnimatedScene",
    "FrameGeometry",
    "ProceduralScene",
    "SequenceScene",
    "Cloth",
    "Twist",
    "Fracture",
    "Flock",
    "Rigid",
    "Soup",
    "World",
    "apply_frame",
    "get",
    "names",
]
