"""Affine transforms interpolated in time as production renderers move instances (OptiX's
SRT motion transforms, Embree's quaternion motion): each key's 3x3 part split by polar
decomposition ``M = R S`` (``R`` a rotation, ``S`` symmetric: scale and shear), its
translation ``T`` apart. At a time between two keys ``S`` and ``T`` are interpolated
linearly and ``R`` along the shortest arc (quaternion slerp; neighbouring keys'
quaternions have their signs aligned when the keys are made), so a turning instance
turns, where interpolating the matrices would shrink it through the turn.

Two forms of the same interpolation: numpy in double on the host (per instance and
key: the keys themselves, a pose between two frames, the bounds of a motion), and
Dr.Jit per lane (:class:`KeyTable`: a ray's or a hit's transform at its own time).

A key is :data:`KEY` floats: the quaternion ``(x, y, z, w)``, ``S``'s upper triangle
``(xx, xy, xz, yy, yz, zz)`` and ``T``. A reflection (``det M < 0``) keeps ``R`` a
rotation and puts the sign into ``S``; a scale of 0 is a rank-deficient ``S`` (the
instance is flat or a point at that time: rays miss it there, nothing fails).

**The bounds** (:func:`swept_boxes`): between two keys, a point ``c`` of the object
moves along ``p(u) = T(u) + R(u) S(u) c``, ``u`` in [0, 1] over the segment. ``T`` and
``S`` are linear (no second derivative), ``R(u)`` turns at the constant rate ``phi``
(the segment's rotation angle) about one axis, so ``|R' v| <= phi |v|`` and
``|R'' v| <= phi^2 |v|``, and::

    |p''(u)| = |R'' S c + 2 R' S' c| <= phi^2 max(|S0 c|, |S1 c|) + 2 phi |(S1 - S0) c|

(``|S(u) c|`` is convex in ``u``: at most its larger end). A function whose second
derivative is bounded by ``B`` departs from the chord between samples ``h`` apart by
at most ``h^2 B / 8``, so the box over the positions at evenly spaced samples, padded
by that, holds every position in between. The object's points are convex combinations
of its box's corners and each pose is affine, so the corners' padded boxes hold the
whole instance at every time of the shutter.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import drjit as dr
import numpy as np


#: Floats of one key: quaternion (4), symmetric stretch (6), translation (3).
KEY = 13
#: Largest rotation (radians) between two samples of a segment in :func:`swept_boxes`:
#: the padding then stays below 0.5% of the object's reach for any turn.
SAMPLE_ANGLE = np.pi / 16
#: A pose whose determinant is below this times the cube of its 3x3 part's Frobenius
#: norm (flattened to about a millionth of its size along some direction, or exactly
#: scaled to nothing, where float rounding leaves a determinant of a few ulps) is
#: taken as scaled to nothing: rays miss the instance at that time.
FLAT = 2.0 ** -20
#: Relative margin added to each swept box: the per-lane float interpolation may place
#: a corner a few ulps from where the double one on the host does.
FLOAT_MARGIN = 1e-5


# ---- Host (numpy, double) ----


def decompose(matrices) -> np.ndarray:
    """The keys (``(K, KEY)``) of ``K`` affine 4x4 ``matrices`` (``(K, 4, 4)``), each
    key's quaternion on the side of its predecessor's (the shortest arc between them)."""
    m = np.asarray(matrices, np.float64)
    u, sigma, vt = np.linalg.svd(m[:, :3, :3])
    flip = np.linalg.det(u @ vt) < 0  # a reflection: the sign goes into S
    u[flip, :, 2] *= -1
    sigma[flip, 2] *= -1
    r = u @ vt
    s = np.einsum("kji,kj,kjl->kil", vt, sigma, vt)  # V diag(sigma) V^T
    q = _quaternions(r)
    for k in range(1, len(q)):  # (keys of one instance: a handful)
        if np.dot(q[k - 1], q[k]) < 0:
            q[k] = -q[k]
    upper = s[:, [0, 0, 0, 1, 1, 2], [0, 1, 2, 1, 2, 2]]
    return np.concatenate([q, upper, m[:, :3, 3]], axis=1)


def compose(keys: np.ndarray) -> np.ndarray:
    """The affine 4x4 matrices (``(..., 4, 4)``) of keys (``(..., KEY)``): ``R S`` and
    ``T``."""
    keys = np.asarray(keys, np.float64)
    r = np.stack([np.stack(row, -1) for row in _rotation([keys[..., i] for i in range(4)])], -2)
    out = np.zeros(keys.shape[:-1] + (4, 4))
    out[..., :3, :3] = r @ _stretch(keys)
    out[..., :3, 3] = keys[..., 10:13]
    out[..., 3, 3] = 1.0
    return out


def interpolate(a: np.ndarray, b: np.ndarray, f) -> np.ndarray:
    """Keys a fraction ``f`` (broadcast against the keys' leading shape) of the way from
    keys ``a`` to ``b`` (``(..., KEY)``): the quaternion by slerp, the rest linearly."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    f = np.asarray(f, np.float64)[..., None]
    cos = np.clip(np.sum(a[..., :4] * b[..., :4], -1, keepdims=True), -1.0, 1.0)
    theta = np.arccos(cos)
    sin = np.sin(theta)
    near = sin < 1e-6  # (nearly) the same rotation: the chord is the arc
    wa = np.where(near, 1 - f, np.sin((1 - f) * theta) / np.where(near, 1.0, sin))
    wb = np.where(near, f, np.sin(f * theta) / np.where(near, 1.0, sin))
    q = wa * a[..., :4] + wb * b[..., :4]
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    rest = a[..., 4:] + f * (b[..., 4:] - a[..., 4:])
    return np.concatenate([q, rest], -1)


def pose_at(matrices, x: float) -> np.ndarray:
    """The 4x4 pose a fraction ``x`` (in [0, 1]) through ``len(matrices) - 1`` evenly
    spaced segments; a key's own matrix where ``x`` falls on one (no round trip through
    the decomposition)."""
    matrices = np.asarray(matrices, np.float64)
    segments = len(matrices) - 1
    at = min(max(float(x), 0.0), 1.0) * segments
    k = min(int(np.floor(at)), segments - 1)
    f = at - k
    if f == 0.0:
        return matrices[k].copy()
    if f == 1.0:
        return matrices[k + 1].copy()
    keys = decompose(matrices[k:k + 2])
    return compose(interpolate(keys[0], keys[1], f))


def swept_boxes(keys: list, lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """World boxes holding each object over its whole motion (module docstring: the
    bound).

    Args:
        keys: per object, its keys (``(S + 1, KEY)``, ``S >= 1``).
        lo, hi: ``(N, 3)`` each object's box in object space.
    Returns:
        ``(lo, hi)``, ``(N, 3)`` each, in double.
    """
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    owner = np.concatenate([np.full(len(k) - 1, i) for i, k in enumerate(keys)])
    a = np.concatenate([k[:-1] for k in keys]).astype(np.float64)
    b = np.concatenate([k[1:] for k in keys]).astype(np.float64)
    phi = 2 * np.arccos(np.clip(np.abs(np.sum(a[:, :4] * b[:, :4], -1)), 0.0, 1.0))
    samples = int(np.clip(np.ceil(phi.max(initial=0.0) / SAMPLE_ANGLE), 1, 64)) + 1
    f = np.linspace(0.0, 1.0, samples)
    poses = compose(interpolate(a[:, None, :], b[:, None, :], f[None, :]))  # (G, n, 4, 4)
    bits = (np.arange(8)[:, None] >> np.arange(3)) & 1
    corners = np.where(bits[None] == 1, hi[owner][:, None], lo[owner][:, None])  # (G, 8, 3)
    p = np.einsum("gnij,gcj->gnci", poses[..., :3, :3], corners) + poses[:, :, None, :3, 3]
    # the bound on |p''| per corner and segment, then the padding between samples
    s0, s1 = _stretch(a), _stretch(b)
    reach = np.maximum(np.linalg.norm(np.einsum("gij,gcj->gci", s0, corners), axis=-1),
                       np.linalg.norm(np.einsum("gij,gcj->gci", s1, corners), axis=-1))
    change = np.linalg.norm(np.einsum("gij,gcj->gci", s1 - s0, corners), axis=-1)
    bound = phi[:, None] ** 2 * reach + 2 * phi[:, None] * change
    pad = bound.max(axis=1) / (8.0 * (samples - 1) ** 2)
    seg_lo = p.min(axis=(1, 2)) - pad[:, None]
    seg_hi = p.max(axis=(1, 2)) + pad[:, None]
    out_lo = np.full((len(keys), 3), np.inf)
    out_hi = np.full((len(keys), 3), -np.inf)
    np.minimum.at(out_lo, owner, seg_lo)
    np.maximum.at(out_hi, owner, seg_hi)
    margin = FLOAT_MARGIN * np.maximum(np.abs(out_lo), np.abs(out_hi)).max(axis=1, keepdims=True)
    return out_lo - margin, out_hi + margin


def _stretch(keys: np.ndarray) -> np.ndarray:
    """The symmetric 3x3 ``S`` of keys (``(..., KEY)``)."""
    xx, xy, xz, yy, yz, zz = (keys[..., 4 + i] for i in range(6))
    return np.stack([np.stack([xx, xy, xz], -1), np.stack([xy, yy, yz], -1),
                     np.stack([xz, yz, zz], -1)], -2)


def _quaternions(r: np.ndarray) -> np.ndarray:
    """``(K, 4)`` unit quaternions ``(x, y, z, w)`` of rotation matrices ``(K, 3, 3)``
    (from the largest of the four diagonal combinations: no cancellation)."""
    q = np.empty((len(r), 4))
    for k, m in enumerate(r):
        trace = np.trace(m)
        candidates = [trace, m[0, 0], m[1, 1], m[2, 2]]
        which = int(np.argmax(candidates))
        if which == 0:
            s = 2 * np.sqrt(max(1 + trace, 0.0))
            q[k] = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s,
                    (m[1, 0] - m[0, 1]) / s, s / 4]
        else:
            i = which - 1
            j, l = (i + 1) % 3, (i + 2) % 3
            s = 2 * np.sqrt(max(1 + m[i, i] - m[j, j] - m[l, l], 0.0))
            v = np.empty(3)
            v[i] = s / 4
            v[j] = (m[j, i] + m[i, j]) / s
            v[l] = (m[l, i] + m[i, l]) / s
            q[k] = [*v, (m[l, j] - m[j, l]) / s]
    return q / np.linalg.norm(q, axis=1, keepdims=True)


# ---- Per lane (Dr.Jit) ----


@dataclass
class KeyTable:
    """Entries' keys, read per lane at each lane's time.

    Attributes:
        keys: Float, :data:`KEY` floats a key, each entry's keys one after the other.
        base: UInt32 per entry: its first key's index.
        segments: UInt32 per entry: its key count minus one (0: an entry without keys,
            whose pose is its caller's).
        shutter: ``(open, close)`` in ``ray.time`` units, every entry's.
    """

    keys: Any
    base: Any
    segments: Any
    shutter: tuple

    @classmethod
    def of(cls, ns, keys: list, shutter: tuple) -> "KeyTable":
        """The table of entries whose keys are ``keys`` (per entry ``(S + 1, KEY)``, or
        None for an entry without keys)."""
        counts = np.array([0 if k is None else len(k) for k in keys], np.int64)
        base = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.uint32)
        flat = np.concatenate([np.asarray(k, np.float32).ravel() for k in keys if k is not None])
        segments = np.maximum(counts - 1, 0).astype(np.uint32)
        table = cls(ns.Float(flat), ns.UInt32(base), ns.UInt32(segments), tuple(shutter))
        dr.eval(table.keys, table.base, table.segments)
        return table

    def time(self, ray_time):
        """``ray_time`` normalised to the shutter (0 at open, 1 at close)."""
        open_, close = self.shutter
        return (ray_time - open_) * (1.0 / (close - open_))

    def keyed(self, entry, active):
        """Bool: the lanes of ``active`` whose entry has keys (the table read as
        ``entry``'s type: plain in a kernel, AD in shading)."""
        UInt32 = type(entry)
        return active & (dr.gather(UInt32, UInt32(self.segments), entry, active) > 0)

    def rows_at(self, entry, time, active) -> list:
        """The pose of each lane's ``entry`` at its ``time`` (Float in [0, 1] over the
        shutter, clamped; NaN: a pose of NaN, which nothing hits), as the 12 floats of
        its rows (``A`` row-major, then ``b``)."""
        Float, UInt32 = type(time), type(entry)
        table = Float(self.keys)
        segments = dr.gather(UInt32, UInt32(self.segments), entry, active)
        known = ~dr.isnan(time)
        x = dr.clip(dr.select(known, time, 0.0), 0.0, 1.0) * Float(segments)
        k = dr.minimum(UInt32(dr.floor(x)), dr.maximum(segments, 1) - 1)
        f = x - Float(k)
        first = (dr.gather(UInt32, UInt32(self.base), entry, active) + k) * KEY
        a = [dr.gather(Float, table, first + i, active) for i in range(KEY)]
        b = [dr.gather(Float, table, first + KEY + i, active) for i in range(KEY)]
        q = _slerp(a[:4], b[:4], f)
        s = [dr.fma(f, y - x_, x_) for x_, y in zip(a[4:10], b[4:10])]
        t = [dr.fma(f, y - x_, x_) for x_, y in zip(a[10:], b[10:])]
        r = _rotation(q)
        sym = [[s[0], s[1], s[2]], [s[1], s[3], s[4]], [s[2], s[4], s[5]]]
        rows = [r[i][0] * sym[0][j] + r[i][1] * sym[1][j] + r[i][2] * sym[2][j]
                for i in range(3) for j in range(3)] + t
        return [dr.select(known, v, dr.nan) for v in rows]


def inverse(m: list) -> tuple:
    """``(rows, det)``: the inverse of the affine transform of rows ``m`` (12 Float: A
    row-major, then b) as 12 Float (A⁻¹, -A⁻¹ b), by the adjugate over the
    determinant (infinite or NaN where ``det`` is 0), and Float ``det``."""
    a = [m[0:3], m[3:6], m[6:9]]
    cof = [[a[(r + 1) % 3][(c + 1) % 3] * a[(r + 2) % 3][(c + 2) % 3]
            - a[(r + 1) % 3][(c + 2) % 3] * a[(r + 2) % 3][(c + 1) % 3]
            for c in range(3)] for r in range(3)]
    det = a[0][0] * cof[0][0] + a[0][1] * cof[0][1] + a[0][2] * cof[0][2]
    inv = [[cof[c][r] / det for c in range(3)] for r in range(3)]  # adjugate / det
    b = m[9:12]
    t = [-(inv[r][0] * b[0] + inv[r][1] * b[1] + inv[r][2] * b[2]) for r in range(3)]
    return [inv[0][0], inv[0][1], inv[0][2], inv[1][0], inv[1][1], inv[1][2],
            inv[2][0], inv[2][1], inv[2][2], *t], det


def inverse_or_nan(m: list) -> list:
    """:func:`inverse` of the rows ``m``, NaN where the pose is flat (:data:`FLAT`) or
    not finite: a ray taken through it hits nothing."""
    inv, det = inverse(m)
    norm2 = sum(x * x for x in m[:9])
    flat = ~(dr.abs(det) > FLAT * norm2 * dr.sqrt(norm2))
    return [dr.select(flat, dr.nan, x) for x in inv]


def _slerp(a: list, b: list, f) -> list:
    """Quaternions (4 Float each) a fraction ``f`` from ``a`` to ``b`` along the arc
    (their chord, normalised, where they nearly coincide)."""
    cos = dr.clip(a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3], -1.0, 1.0)
    theta = dr.acos(cos)
    sin = dr.sin(theta)
    near = sin < 1e-4
    inv = dr.rcp(dr.select(near, 1.0, sin))
    wa = dr.select(near, 1.0 - f, dr.sin((1.0 - f) * theta) * inv)
    wb = dr.select(near, f, dr.sin(f * theta) * inv)
    q = [wa * x + wb * y for x, y in zip(a, b)]
    norm = dr.rsqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return [c * norm for c in q]


def _rotation(q: list) -> list:
    """The 3x3 rotation (rows of three) of the unit quaternion ``(x, y, z, w)``: Dr.Jit
    Floats per lane, or numpy arrays on the host."""
    x, y, z, w = q
    return [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
