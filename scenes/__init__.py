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

Procedural scenes (:func:`get`, :func:`names`, :func:`parse`)
-------------------------------------------------------------
Built from numpy, seeded (``seed=0``), ``frames=60`` at 24 frames per second,
``triangles=200_000`` by default: the least number of triangles (animated and static
together; any size, 2M and beyond), rounded up to what the tessellation allows.

=============  ==============================================================  ==================
name           what moves                                                      static shapes
=============  ==============================================================  ==================
``cloth``      a flag rippled by travelling waves (coherent deformation)       pole, ground
``twist``      a closed bar twisting, bending and bulging (skinning-like)      ground
``fracture``   a torus shell bursting into ``pieces=300`` tumbling shards      ground
               (``instanced=True``: each shard a shape group and an instance)
``rigid``      ``objects=240`` bodies in ``groups=8`` meshes, bouncing and      walls, columns,
               spinning (``instanced=True``: as instances of ``groups`` shape  ground
               groups, moved by their transforms)
``soup``       random triangles re-drawn every frame (incoherent, worst case)  ground
``world``      the ``cloth`` flag (``flag_triangles``: 1/11) over rolling     pole, terrain
               hills (``triangles=1_100_000`` in all): a moving object in a
               static world
``fog``        the ``world`` flag inside a box of fog (``density=0.12``, a         pole, terrain
               homogeneous medium behind a null interface; ``triangles=200_000``;
               its integrator ``volpath``)
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

    import hlbvh
    import mitsuba as mi
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
from .fog import Fog
from .fracture import Fracture
from .procedural import ProceduralScene
from .rigid import Rigid
from .sequence import SequenceScene
from .soup import Soup
from .twist import Twist
from .world import World

_PROCEDURAL = {cls.name: cls for cls in (Cloth, Twist, Fracture, Rigid, Soup, World, Flock, Fog)}


def names() -> list[str]:
    """Names of the procedural scenes :func:`get` builds."""
    return list(_PROCEDURAL)


def parse(spec: str) -> tuple[str, dict]:
    """A procedural scene's name and options from ``"name"`` or
    ``"name:key=value,key=value"`` (the command line's SCENE, e.g.
    ``flock:birds=200`` or ``rigid:instanced=true,objects=40``): each value typed as
    the option's default is (``true``/``false`` for a flag). ``triangles``, ``frames``
    and ``seed`` have their own flags and are not options here.

    Raises:
        ValueError: an unknown scene, an option the scene does not have (naming the
            ones it has), or a value of the wrong type.
    """
    name, _, rest = spec.partition(":")
    if name not in _PROCEDURAL:
        raise ValueError(f"scene {name!r}: unknown; expected one of {names()}")
    defaults = scene_options(name)
    options = {}
    for item in filter(None, (part.strip() for part in rest.split(","))) if rest else ():
        key, equals, text = item.partition("=")
        key = key.strip()
        if key in _FLAGGED:
            raise ValueError(f"scene {spec!r}: {item!r} is not a scene option; "
                             f"{_FLAGGED[key]}")
        if not equals or key not in defaults:
            expected = (f"expected key=value with key one of {sorted(defaults)}" if defaults
                        else f"{name!r} takes no options")
            raise ValueError(f"scene {spec!r}: {item!r} is not an option of {name!r}; "
                             f"{expected}")
        options[key] = _typed(spec, key, text.strip(), defaults[key])
    return name, options


#: What a procedural scene takes as a command-line flag, not as a NAME:KEY=VALUE option,
#: and what the line refusing KEY=VALUE says instead.
_FLAGGED = {"triangles": "give it as --triangles", "frames": "give it as --frames",
            "seed": "the scene's geometry is the same for every run (--seed seeds the "
                    "renders)"}


def scene_options(name: str) -> dict:
    """The options of procedural scene ``name`` beyond ``triangles``, ``frames`` and
    ``seed``, with their defaults."""
    import inspect

    signature = inspect.signature(_PROCEDURAL[name].__init__)
    return {key: p.default for key, p in signature.parameters.items()
            if key not in ("self", "triangles", "frames", "seed")
            and p.default is not inspect.Parameter.empty}


def _typed(spec: str, key: str, text: str, default):
    """``text`` as a value of ``default``'s type."""
    try:
        if isinstance(default, bool):
            if text.lower() not in ("true", "false", "1", "0", "yes", "no"):
                raise ValueError
            return text.lower() in ("true", "1", "yes")
        return int(text) if default is None else type(default)(text)  # None: a count unset
    except ValueError:
        kind = ("true or false" if isinstance(default, bool) else
                "an integer" if default is None or isinstance(default, int) else
                f"a {type(default).__name__}")
        raise ValueError(f"scene {spec!r}: {key}={text!r}, expected {kind}") from None


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
    "parse",
    "scene_options",
]
