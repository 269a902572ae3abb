"""``fracture``: a ceramic torus shattering into hundreds of tumbling shards."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import mitsuba as mi
import numpy as np

from . import meshes
from .animated import FrameGeometry
from .procedural import (
    DEFAULT_FRAMES,
    DEFAULT_TRIANGLES,
    FPS,
    Part,
    ProceduralScene,
    View,
    ground,
    glossy,
    mesh_object,
    positive_int,
)
from .rigid_motion import affines, random_unit_vectors, rotate, rotation_matrices

SHARD_COLOUR = (0.78, 0.36, 0.20)

MAJOR = 1.2  # torus radius around its axis
MINOR = 0.45  # tube radius of the outer surface
THICKNESS = 0.07  # shell thickness
CENTRE = np.array([0.0, MAJOR + MINOR, 0.0])  # standing upright, touching the ground
EXPLOSION_START = 3 / FPS  # seconds the torus stays whole
DRAG = 1.6  # 1/s: velocities decay as exp(-DRAG t)
GRAVITY = 4.0  # m/s^2


@dataclass(frozen=True)
class Shards:
    """The shattered shell: one mesh, pieces that never share a vertex, each piece's
    vertices contiguous.

    Attributes:
        positions: float64 ``(V, 3)`` rest vertices (the whole torus).
        faces: uint32 ``(F, 3)``.
        piece: int64 ``(V,)`` piece of each vertex, non-decreasing.
        starts: int64 ``(P,)`` first vertex of each piece.
        centres: float64 ``(P, 3)`` rest centre of each piece (mean of its outer vertices).
    """

    positions: np.ndarray
    faces: np.ndarray
    piece: np.ndarray
    starts: np.ndarray
    centres: np.ndarray


class Fracture(ProceduralScene):
    """A hollow ceramic torus standing on the ground bursts into ``pieces`` shards that
    fly apart, tumble, slow down in the air and land (the paper's chaotic fracturing).

    Parts: ``shards`` (animated, one mesh), ``ground`` (static). The torus shell is a
    periodic ``nu x nv`` quad grid on its outer surface; the quads are split into
    irregular pieces by a jittered Voronoi diagram of ``pieces`` sites on the surface.
    Each shard is a closed solid: its patch of the outer surface, the same patch on the
    inner surface (``THICKNESS`` inside) and walls along its cracks, with vertices of its
    own, so its topology never changes while the shards scatter: the Morton order of
    the triangles is shuffled frame after frame.

    Triangles: ``4 nu nv`` on the two surfaces plus 4 per crack edge between two quads;
    the grid is sized so both together meet the budget, usually within 1%.

    With ``instanced=True`` every shard is a shape group of its own (``group_k``,
    the shard about its rest centre) and an instance ``shard_k`` moved by its
    ``to_world``: the same motion, the same triangles, no vertex rewritten. The shards
    share no geometry, so instancing saves the per-frame vertex writes and rebuild but
    not memory, and the expansion of hits grows with the number of groups (Mitsuba's
    per instance, ours per group mesh; docs/decisions.md#fracture-one-mesh):
    the one-mesh model stays the
    default.

    Args:
        pieces: about how many shards: the sites fill a ``gu x gv`` grid of at least
            ``pieces`` cells (a site no quad centre is nearest to, at tiny triangle
            budgets, gives no shard).
        instanced: the shards as instances of one shape group each.
        others: see :class:`ProceduralScene`.
    """

    name = "fracture"

    def __init__(
        self,
        triangles: int = DEFAULT_TRIANGLES,
        frames: int = DEFAULT_FRAMES,
        seed: int = 0,
        pieces: int = 300,
        instanced: bool = False,
    ):
        super().__init__(triangles, frames, seed)
        self.pieces = positive_int("pieces", pieces, least=2)
        if not isinstance(instanced, bool):
            raise ValueError(f"instanced={instanced!r}: expected True or False")
        self.instanced = instanced

    def __repr__(self) -> str:
        return super().__repr__()[:-1] + f", pieces={self.pieces}" + (
            ", instanced=True)" if self.instanced else ")")

    # ---- The cracked shell -----------------------------------------------------------

    @functools.cached_property
    def _layout(self) -> tuple[int, int, np.ndarray]:
        """``(nu, nv, labels)``: the grid whose triangles (surfaces and crack walls)
        come closest above the budget, and the piece of every quad, int64 ``(nu, nv)``.

        The crack walls grow like the square root of the grid: a few rounds of the model
        ``walls = alpha sqrt(nu nv)``, fitted on the last grid tried, find the size."""
        budget = max(self.triangles - 2, 64)
        quads = math.ceil(budget / 4)  # surfaces alone meet the budget: the fallback
        best = None
        for _ in range(6):
            nu, nv = _grid_for(quads)
            labels = self._labels_for(nu, nv)
            total = 4 * nu * nv + 4 * _crack_edges(labels)
            if total >= budget and (best is None or total < best[0]):
                best = (total, nu, nv, labels)
            alpha = 4 * _crack_edges(labels) / math.sqrt(4 * nu * nv)
            # Solve 4 Q + alpha sqrt(4 Q) = budget for Q.
            root = (-alpha + math.sqrt(alpha * alpha + 4 * budget)) / 2
            guess = max(16, math.ceil(root * root / 4))
            quads = guess if total < budget or guess < quads else quads + 1
            if total >= budget and total <= budget * 1.01:
                break
        return best[1], best[2], best[3]

    def _labels_for(self, nu: int, nv: int) -> np.ndarray:
        """int64 ``(nu, nv)``: the piece of every quad, pieces numbered 0..P-1.

        Sites: one per cell of a ``gu x gv`` grid over the surface's (u, v) parameters,
        jittered inside its cell; each quad goes to the nearest site by arc length, found
        among the sites of the 3 x 3 cells around the quad's cell (Worley's trick)."""
        ratio = MAJOR / MINOR
        gv = max(2, round(math.sqrt(self.pieces / ratio)))
        gu = max(2, math.ceil(self.pieces / gv))
        jitter = np.random.default_rng(self.seed).uniform(0.15, 0.85, (gu, gv, 2))
        # Quad centres in cell units, and the arc length of one cell unit along u and v.
        cu = ((np.arange(nu) + 0.5) * (gu / nu))[:, None]
        cv = ((np.arange(nv) + 0.5) * (gv / nv))[None, :]
        unit_u, unit_v = 2 * np.pi * MAJOR / gu, 2 * np.pi * MINOR / gv
        a0, b0 = np.floor(cu).astype(np.int64), np.floor(cv).astype(np.int64)
        best = np.full((nu, nv), np.inf)
        site = np.zeros((nu, nv), dtype=np.int64)
        for da in (-1, 0, 1):
            for db in (-1, 0, 1):
                a, b = (a0 + da) % gu, (b0 + db) % gv
                su = a0 + da + jitter[a, b, 0]
                sv = b0 + db + jitter[a, b, 1]
                d2 = ((cu - su) * unit_u) ** 2 + ((cv - sv) * unit_v) ** 2
                closer = d2 < best
                best = np.where(closer, d2, best)
                site = np.where(closer, a * gv + b, site)
        return np.unique(site, return_inverse=True)[1].reshape(nu, nv)

    def triangle_counts(self) -> dict[str, int]:
        if self.instanced:
            counts = dict(zip(self.animated_ids(), (len(f) for _, f in self._pieces)))
            return {**counts, "ground": 2}
        nu, nv, labels = self._layout
        return {"shards": 4 * nu * nv + 4 * _crack_edges(labels), "ground": 2}

    @functools.cached_property
    def _shards(self) -> Shards:
        nu, nv, labels = self._layout
        count = int(labels.max()) + 1
        inner = MINOR - THICKNESS
        u_of = np.arange(nu) * (2 * np.pi / nu)
        v_of = np.arange(nv) * (2 * np.pi / nv)

        def surface(i, j, minor):
            return meshes.torus_point(u_of[i % nu], v_of[j % nv], MAJOR, minor) + CENTRE

        # ---- Outer and inner surfaces: the torus grid, vertices split per piece ----
        corners = meshes.grid_faces(nu, nv, wrap_u=True, wrap_v=True).astype(np.int64)
        tri_piece = np.repeat(labels.reshape(-1), 2)
        keys, vertex = np.unique(corners * count + tri_piece[:, None], return_inverse=True)
        vertex = vertex.reshape(-1, 3)
        grid_vertex, shell_piece = keys // count, keys % count
        gi, gj = grid_vertex // nv, grid_vertex % nv
        outer = surface(gi, gj, MINOR)
        shell = len(keys)

        # ---- Crack walls: a quad per piece on each side of a crack edge ----
        # Edge (a, b) seen from the piece it bounds, oriented so the wall faces the
        # neighbour: along u the edge runs +v and the wall of the lower piece faces +u.
        crack_u, crack_v = _crack_masks(labels)
        iu, ju = np.nonzero(crack_u)
        iv, jv = np.nonzero(crack_v)
        walls = [
            # (edge start (i, j), edge end (i, j), piece, flip)
            ((iu + 1, ju), (iu + 1, ju + 1), labels[iu, ju], True),
            ((iu + 1, ju), (iu + 1, ju + 1), labels[(iu + 1) % nu, ju], False),
            ((iv, jv + 1), (iv + 1, jv + 1), labels[iv, jv], False),
            ((iv, jv + 1), (iv + 1, jv + 1), labels[iv, (jv + 1) % nv], True),
        ]
        wall_positions, wall_faces, wall_piece = [], [], []
        base = 2 * shell
        for (ai, aj), (bi, bj), piece, flip in walls:
            quad = np.stack(
                [surface(ai, aj, MINOR), surface(bi, bj, MINOR),
                 surface(bi, bj, inner), surface(ai, aj, inner)], axis=1,
            )
            first = base + 4 * np.arange(len(piece))[:, None]
            tris = np.array([[0, 1, 2], [0, 2, 3]])
            tris = tris[:, ::-1] if flip else tris
            wall_faces.append((first[:, None, :] + tris[None]).reshape(-1, 3))
            wall_positions.append(quad.reshape(-1, 3))
            wall_piece.append(np.repeat(piece, 4))
            base += 4 * len(piece)

        positions = np.concatenate(
            [outer, surface(gi, gj, inner), *wall_positions]
        )
        faces = np.concatenate([vertex, (vertex + shell)[:, ::-1], *wall_faces])
        piece = np.concatenate([shell_piece, shell_piece, *wall_piece])

        # ---- Each piece's centre ----
        weight = np.bincount(shell_piece, minlength=count)
        centres = np.stack(
            [np.bincount(shell_piece, outer[:, k], minlength=count) / weight for k in range(3)],
            axis=1,
        )

        # ---- Vertices renumbered piece by piece ----
        order = np.argsort(piece, kind="stable")
        renumber = np.empty_like(order)
        renumber[order] = np.arange(len(order))
        starts = np.searchsorted(piece[order], np.arange(count))
        return Shards(
            positions[order], renumber[faces].astype(np.uint32), piece[order], starts, centres
        )

    @functools.cached_property
    def _flight(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per piece: initial velocity ``(P, 3)``, spin axis ``(P, 3)``, spin rate
        ``(P,)`` in rad/s."""
        shards = self._shards
        count = len(shards.centres)
        rng = np.random.default_rng([self.seed, 1])
        outward = shards.centres - CENTRE
        outward /= np.linalg.norm(outward, axis=1, keepdims=True)
        direction = outward + 0.35 * random_unit_vectors(rng, count) + [0.0, 0.6, 0.0]
        direction /= np.linalg.norm(direction, axis=1, keepdims=True)
        velocity = direction * rng.uniform(2.0, 4.0, count)[:, None]
        return velocity, random_unit_vectors(rng, count), rng.uniform(2.0, 9.0, count)

    # ---- The ProceduralScene hooks ---------------------------------------------------

    def _build_parts(self) -> dict[str, Part]:
        parts = {} if self.instanced else {
            "shards": Part(self._shards.faces, glossy(SHARD_COLOUR, roughness=0.3))}
        parts["ground"] = ground()
        return parts

    def _motion(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """At time ``t``: every vertex moved ``(V, 3)``, and each piece's turn
        ``(P, 3, 3)`` and translation ``(P, 3)`` carrying it from its rest centre."""
        shards = self._shards
        velocity, axis, spin = self._flight
        s = max(0.0, t - EXPLOSION_START)
        # Linear drag: x(s) = x0 + v tau(s) - (g / drag) (s - tau(s)) y, tau = (1 - e^-ds)/d.
        tau = (1.0 - math.exp(-DRAG * s)) / DRAG
        centres = shards.centres + velocity * tau
        centres[:, 1] -= GRAVITY / DRAG * (s - tau)
        piece = shards.piece
        offsets = rotate(shards.positions - shards.centres[piece], axis[piece], (spin * tau)[piece])
        positions = centres[piece] + offsets
        # A shard that reaches the ground rests on it: lifted by its lowest vertex's depth.
        lift = -np.minimum(np.minimum.reduceat(positions[:, 1], shards.starts), 0.0)
        positions[:, 1] += lift[piece]
        centres[:, 1] += lift
        return positions, rotation_matrices(axis, spin * tau), centres

    def _animated_positions(self, t: float, i: int) -> dict[str, np.ndarray]:
        return {} if self.instanced else {"shards": self._motion(t)[0]}

    # ---- The instanced variant ---------------------------------------------------------

    @functools.cached_property
    def _pieces(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Each shard's ``(positions about its rest centre (n, 3), faces (m, 3))``."""
        shards = self._shards
        ends = list(shards.starts[1:]) + [len(shards.positions)]
        owner = shards.piece[shards.faces[:, 0]]
        order = np.argsort(owner, kind="stable")
        bounds = np.searchsorted(owner[order], np.arange(len(ends) + 1))
        return [(shards.positions[a:b] - shards.centres[k],
                 (shards.faces[order[bounds[k]:bounds[k + 1]]] - a).astype(np.uint32))
                for k, (a, b) in enumerate(zip(shards.starts, ends))]

    def animated_ids(self) -> list[str]:
        if self.instanced:
            return [f"shard_{k}" for k in range(len(self._shards.starts))]
        return super().animated_ids()

    def transforms(self, t: float) -> np.ndarray:
        """Every shard's ``to_world`` at time ``t`` (``(P, 4, 4)``): the motion of the
        one-mesh model as transforms of the shards about their rest centres."""
        _, turns, centres = self._motion(t)
        return affines(turns, centres)

    def frame(self, i: int) -> dict[str, FrameGeometry]:
        return self._transform_frame(i) if self.instanced else super().frame(i)

    def scene_dict(self, resolution=None, spp=None, integrator=None) -> dict:
        """See :meth:`ProceduralScene.scene_dict`; instanced: the shape groups
        ``group_k`` and the shards ``shard_k`` as their instances, at frame 0."""
        scene = super().scene_dict(resolution, spp, integrator)
        if self.instanced:
            bsdf = glossy(SHARD_COLOUR, roughness=0.3)
            for k, ((rest, faces), shard, m) in enumerate(
                    zip(self._pieces, self.animated_ids(), self.transforms(0.0))):
                scene[f"group_{k}"] = {"type": "shapegroup", f"piece_{k}": mesh_object(
                    f"piece_{k}", rest, faces, bsdf)}
                scene[shard] = {"type": "instance", "shape": {"type": "ref", "id": f"group_{k}"},
                                "to_world": mi.ScalarTransform4f(m.astype(np.float32))}
        return scene

    def _view(self) -> View:
        return View(origin=(0.8, 3.2, 11.0), target=(0.0, 1.8, 0.0), fov=45.0)


def _grid_for(quads: int) -> tuple[int, int]:
    """Quads around the torus axis (nu) and around its tube (nv), about square, at
    least ``quads`` of them."""
    nv = max(4, math.ceil(math.sqrt(quads / (MAJOR / MINOR))))
    return max(4, math.ceil(quads / nv)), nv


def _crack_masks(labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where quad (i, j) and its neighbour (i+1, j), resp. (i, j+1), lie in different
    pieces (the grid wraps around both ways)."""
    return labels != np.roll(labels, -1, axis=0), labels != np.roll(labels, -1, axis=1)


def _crack_edges(labels: np.ndarray) -> int:
    """Grid edges between two pieces."""
    return sum(int(mask.sum()) for mask in _crack_masks(labels))
