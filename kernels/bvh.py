"""What a user of the kernels touches: :class:`BuildConfig` (the options of
:func:`hlbvh.build`), :class:`BuildStats` (what a build measured) and :class:`BVH`, the
tree record (:class:`hlbvh.kernels.tree.Tree`, whose docstring gives the node layout)
with the conveniences that hand it to the stages: ``refit`` and the two ray queries.

This module sits above the stages it calls (refit, traversal) and below the builders
that return its :class:`BVH`; no stage imports it.
"""

from __future__ import annotations

import dataclasses
import numbers
from dataclasses import dataclass, field
from typing import Any

from .morton import QUANTIZATIONS
from .refit import refit
from .traversal import intersect, occluded
from .tree import Tree

BUILDERS = ("hlbvh", "lbvh", "sah")


@dataclass
class BuildConfig:
    """Options of :func:`hlbvh.build`. A user's choice is ``builder``; the rest are the
    expert's knobs, with defaults the benchmark justified.

    Attributes:
        builder: ``"hlbvh"`` (Pantaleoni & Luebke 2010: binned SAH over the coarse
            clusters, partial breadth-first emission below; the default), ``"lbvh"``
            (Lauterbach et al. 2009: Morton order and emission all the way; fastest) or
            ``"sah"`` (full binned SAH, Wald 2007; slowest, the quality reference).
        leaf_size: most primitives in a leaf (1..16). A segment of more primitives with
            identical keys is split at its middle index.
        morton_bits: 30 (10 bits per axis, UInt32 keys), 60 (20 bits per axis, UInt64
            keys) or ``"auto"`` (60 when the scene's primitives are too small for its
            bounds to be told apart at 30 bits; and ``"rank"`` quantisation when not
            even at 60 bits: see :func:`hlbvh.kernels.morton.choose_key`).
        quantization: ``"cube"`` quantises centroids in the cube over the largest extent
            (keeps cells square on flat scenes), ``"axis"`` per axis, ``"rank"`` by each
            centroid's rank along each axis (cells adapt to where the primitives are;
            slowest).
        coarse_bits: the top ``3m`` key bits that define the coarse clusters of the CSD
            sort and of the SAH top level (a multiple of 3).
        p: bit planes emitted per pass of the hierarchy emission (1..5).
        sah_bins: bins per axis of the binned SAH.
    """

    builder: str = "hlbvh"
    leaf_size: int = 4
    morton_bits: int | str = 30
    quantization: str = "cube"
    coarse_bits: int = 12
    p: int = 2
    sah_bins: int = 16

    def validated(self) -> "BuildConfig":
        """Self, after checking every field; raises ValueError naming the bad option.
        Integer options accept any integer type (numpy's too) but not bools or floats,
        and are stored as Python ints."""
        if self.builder not in BUILDERS:
            raise ValueError(f"builder={self.builder!r}: expected one of {BUILDERS}")
        self.leaf_size = integer_option("leaf_size", self.leaf_size, range(1, 17))
        if self.morton_bits != "auto":
            self.morton_bits = integer_option("morton_bits", self.morton_bits, (30, 60), "30, 60 or 'auto'")
        if self.quantization not in QUANTIZATIONS:
            raise ValueError(
                f"quantization={self.quantization!r}: expected one of {QUANTIZATIONS}"
            )
        self.p = integer_option("p", self.p, range(1, 6))
        self.sah_bins = integer_option("sah_bins", self.sah_bins, range(2, 65))
        self.coarse_bits = integer_option(
            "coarse_bits", self.coarse_bits, range(0, 25, 3), "a multiple of 3 in 0..24"
        )
        return self

    @classmethod
    def from_options(cls, **options) -> "BuildConfig":
        """A validated config from keyword options; unknown names raise ValueError."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(options) - names)
        if unknown:
            raise ValueError(
                f"unknown build option(s) {unknown}: expected some of {sorted(names)}"
            )
        return cls(**options).validated()


def integer_option(name: str, value, allowed, expected: str = "") -> int:
    """``value`` as a Python int if it is an integer (bools and floats are not) in
    ``allowed``; otherwise a ValueError naming the option and what it accepts."""
    if (
        isinstance(value, bool)
        or not isinstance(value, numbers.Integral)
        or int(value) not in allowed
    ):
        if not expected:
            expected = f"an int in {allowed[0]}..{allowed[-1]}"
        raise ValueError(f"{name}={value!r}: expected {expected}")
    return int(value)


class _OnFirstRead:
    """A dataclass field that may be given a function instead of a value: the function
    is called when the field is first read, and its result kept. Statistics that cost a
    kernel and a host round trip, which tracing does not need, are set so.

    Args:
        empty: the value of a field that was never given one.
    """

    def __init__(self, empty):
        self._empty = empty

    def __set_name__(self, owner, name):
        self._name = "_" + name

    def __get__(self, obj, owner=None):
        if obj is None:
            return None  # the dataclass default: not given
        value = obj.__dict__.get(self._name)
        if callable(value):
            value = obj.__dict__[self._name] = value()
        return self._empty() if value is None else value

    def __set__(self, obj, value):
        obj.__dict__[self._name] = value


@dataclass
class BuildStats:
    """What a build measured about itself.

    ``sah_cost`` uses C_trav = C_isect = 1: sum over internal nodes of area/root area,
    plus sum over leaves of count * area/root area. ``morton_bits`` and
    ``quantization`` are the key the build used (what ``"auto"`` chose; 0 and ``""``
    for the ``"sah"`` builder, which uses no keys). ``csd_runs`` and ``csd_resorted``
    are the CSD sort's run count and how many keys it had to sort (see
    :class:`~hlbvh.kernels.csd.CsdResult`), ``csd_seeded`` whether it started from the
    previous frame's order. ``stage_ms`` holds the wall time of
    each stage, synchronised (the device finished before the clock stopped).
    ``sah_cost`` and ``leaf_histogram`` (leaves of 1, 2, ..., ``leaf_size`` primitives)
    are computed when first read: each a kernel and a host round trip that a tree needs
    not pay before it is traced.
    """

    builder: str = ""
    prim_count: int = 0
    node_count: int = 0
    leaf_count: int = 0
    depth: int = 0
    sah_cost: float = _OnFirstRead(float)
    csd_runs: int = 0
    csd_resorted: int = 0
    csd_seeded: bool = False
    coarse_clusters: int = 0
    morton_bits: int = 30
    quantization: str = ""
    leaf_histogram: list[int] = _OnFirstRead(list)
    stage_ms: dict[str, float] = field(default_factory=dict)
    total_ms: float = 0.0

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


class BVH(Tree):
    """A built hierarchy (:class:`~hlbvh.kernels.tree.Tree`, the record every stage
    takes) with the conveniences a user calls on it, each handing the record to the
    stage that does the work. :func:`hlbvh.build` returns one."""

    def refit(self, vertices) -> "BVH":
        """:func:`hlbvh.kernels.refit.refit`: new boxes for new vertex positions (same
        faces, same tree), in place; returns self."""
        return refit(self, vertices)

    def intersect(self, ray, active=True):
        """:func:`hlbvh.kernels.traversal.intersect`: closest hit of ``ray`` (anything
        with ``o``, ``d``, ``maxt``) as a ``mi.PreliminaryIntersection3f`` with
        ``prim_index`` the input face index and the shape fields null."""
        return intersect(self, ray, active)

    def occluded(self, ray, active=True):
        """:func:`hlbvh.kernels.traversal.occluded`: whether anything lies on ``ray`` in
        (0, maxt), a Bool per ray."""
        return occluded(self, ray, active)
