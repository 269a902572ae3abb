"""Which shapes of a scene moved since the accelerator last looked: a state per shape
that a later look compares with, without comparing any geometry.

* A mesh's state is its vertex and face buffers themselves: a ``params[...]``
  assignment gives the mesh new Dr.Jit variables, so their indices differ. Holding the
  arrays keeps their indices from being given to other arrays meanwhile.
* Any other shape's state is its bounding box and its own parameters (``to_world``
  and the like, as ``mi.traverse(shape)`` lists them, without its BSDF's or other
  children's), held the same way. The box alone would miss a motion that keeps it (an
  instance turned by 90 degrees about a symmetric group).

A look costs two method calls per mesh and, per other shape, a read of each of its own
parameters through handles that one ``mi.traverse`` of the shape gave the first time
(a traversal per look would cost ~30 us a shape, 0.3 s for 10k instances), and no
kernel.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi


@dataclass(frozen=True)
class MeshState:
    """A mesh's buffers as last seen."""

    vertices: mi.Float
    faces: mi.UInt32

    def moved(self, before: "MeshState") -> bool:
        """Whether the mesh got other vertex or face buffers than ``before``."""
        return (self.vertices.index != before.vertices.index
                or self.faces.index != before.faces.index)

    def reshaped(self, before: "MeshState") -> bool:
        """Whether its faces or vertex count changed (a refit cannot follow)."""
        return (self.faces.index != before.faces.index
                or dr.width(self.vertices) != dr.width(before.vertices))


@dataclass(frozen=True)
class ShapeState:
    """Any other shape's bounding box and own parameters as last seen."""

    box: tuple
    values: tuple  # held: their Dr.Jit variables keep their indices while held
    identity: tuple  # what tells them apart (:func:`_identity`), taken once

    def moved(self, before: "ShapeState") -> bool:
        """Whether its box or any of its own parameters changed since ``before``."""
        return self.box != before.box or self.identity != before.identity

    def reshaped(self, before: "ShapeState") -> bool:
        return self.moved(before)


def shape_state(shape, handles: dict | None = None) -> MeshState | ShapeState:
    """The state of ``shape`` now (see the module docstring); ``handles`` keeps each
    shape's parameter handles between looks."""
    if shape.is_mesh():
        return MeshState(shape.vertex_positions_buffer(), shape.faces_buffer())
    box = shape.bbox()
    handles = {} if handles is None else handles
    if id(shape) not in handles:
        params = mi.traverse(shape)
        handles[id(shape)] = [params.properties[key][:3] for key in params.keys()
                              if "." not in key]
    own = tuple(value if kind is None else mi.get_property(value, kind, node)
                for value, kind, node in handles[id(shape)])
    return ShapeState((tuple(box.min), tuple(box.max)), own, _identity(own))


def shape_states(shapes, indices, handles: dict | None = None) -> dict:
    """``{index: state}`` of ``shapes[i]`` for every ``i`` in ``indices``; ``handles``
    as :func:`shape_state`'s (the caller keeps the shapes alive)."""
    return {i: shape_state(shapes[i], handles) for i in indices}


def _identity(values: tuple) -> tuple:
    """What tells two parameter sets apart: the Dr.Jit variable indices of JIT values
    (of a transform, its matrix's: its inverse is derived from it, and collecting both
    doubles the cost of a look at an instance), the values themselves otherwise."""
    identity = []
    for value in values:
        if type(value).__name__.endswith("Transform4f"):  # any variant's, affine or not
            value = value.matrix
        indices = dr.detail.collect_indices(value)
        identity.append(tuple(indices) if indices else repr(value))
    return tuple(identity)


def member_states(shapes, handles: dict) -> list:
    """Each shape's :func:`shape_state`: what a shape group's members are compared with
    later, by :func:`members_changed` (``handles`` as :func:`shape_state`'s)."""
    return [shape_state(shape, handles) for shape in shapes]


def members_changed(shapes, states: list, handles: dict) -> bool:
    """Whether a shape among ``shapes`` changed since ``states`` were taken."""
    return any(shape_state(shape, handles).moved(before) for shape, before in zip(shapes, states))
