"""``fog``: the ``world`` scene with its flag waving inside a box of fog (a
homogeneous participating medium behind a null interface), rendered with ``volpath``."""

from __future__ import annotations

import mitsuba as mi

from .world import World

#: The fog box: from ``(x, y, z)`` low to high, around the pole and the flag's sweep.
#: Its floor is above the meadow (y = 0): a face coplanar with the ground would make
#: which surface a ray meets first a matter of the last bit of t.
FOG_LOW, FOG_HIGH = (-3.0, 0.5, -4.5), (6.0, 7.0, 4.5)


class Fog(World):
    """:class:`World` with a box of fog (``fog``, a cube with a ``null`` BSDF whose
    interior is a homogeneous medium: extinction ``density`` per unit length, a bluish
    white albedo) holding the pole and the flag; the flag moves inside the medium, the
    terrain lies outside it. Its integrator is Mitsuba's ``volpath`` (``max_depth``
    8), which ``hlbvh render`` and ``compare`` run as ``hlbvh_volpath``.

    Args:
        density: the fog's extinction coefficient (default 0.12: about one mean free
            path across the box).
        triangles, flag_triangles, frames, seed: see :class:`World` (default
            triangles: 200k, the flag 1/11 of them).
    """

    name = "fog"

    def __init__(self, triangles: int = 200_000, flag_triangles: int | None = None,
                 frames: int = 60, seed: int = 0, density: float = 0.12):
        super().__init__(triangles=triangles, flag_triangles=flag_triangles, frames=frames,
                         seed=seed)
        if not (isinstance(density, (int, float)) and not isinstance(density, bool)
                and 0 < density < float("inf")):
            raise ValueError(f"density={density!r}: expected a positive number")
        self.density = float(density)

    def integrator_description(self) -> dict:
        return {"type": "volpath", "max_depth": 8}

    def static_ids(self) -> list[str]:
        """The world's still shapes and the fog's box (a cube mesh that never moves)."""
        return super().static_ids() + ["fog"]

    def scene_dict(self, resolution=None, spp=None, integrator=None) -> dict:
        scene = super().scene_dict(resolution, spp, integrator=(
            self.integrator_description() if integrator is None else integrator))
        centre = [(lo + hi) / 2 for lo, hi in zip(FOG_LOW, FOG_HIGH)]
        half = [(hi - lo) / 2 for lo, hi in zip(FOG_LOW, FOG_HIGH)]
        scene["fog"] = {
            "type": "cube",
            "to_world": mi.ScalarTransform4f().translate(centre).scale(half),
            "bsdf": {"type": "null"},
            "interior": {
                "type": "homogeneous",
                "sigma_t": {"type": "rgb", "value": [self.density] * 3},
                "albedo": {"type": "rgb", "value": [0.85, 0.88, 0.92]},
            },
        }
        return scene
