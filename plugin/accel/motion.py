"""Which shapes of a scene moved since the accelerator last looked: a state per shape
that a later look compares with, without comparing any geometry.

* A mesh's state is its vertex and face buffers themselves: a ``params[...]``
  assignment gives the mesh new Dr.Jit variables, so their indices differ. Holding the
  arrays keeps their indices from being given to other arrays meanwhile.
* Any other shape's state is its bounding box and the values of its own parameters
  (``to_world`` and the like, as ``mi.traverse(shape)`` lists them, without its BSDF's
  or other children's), copied to the host. The box alone would miss a motion that
  keeps it (an instance turned by 90 degrees, or mirrored, about a symmetric group);
  the parameters' Dr.Jit variables would too: Mitsuba writes a new transform into the
  variables its shape already holds, so their indices stay the same from one write to
  the next while their values change.

A look costs two method calls per mesh and, per other shape, a read of each of its own
parameters through handles that one ``mi.traverse`` of the shape gave the first time
(a traversal per look would cost ~30 us a shape, 0.3 s for 10k instances): a
transform's twelve affine entries, read one by one from the host (evaluated and literal
variables are read without a kernel), a small array's values, a large one's variable
indices (a texture or a buffer is replaced, not written in place).
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
    identity: tuple  # what tells its parameters apart (:func:`_identity`), taken once
    held: tuple  # its large JIT parameters, held so that their indices stay theirs

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
    return ShapeState((tuple(box.min), tuple(box.max)), _identity(own), own)


def shape_states(shapes, indices, handles: dict | None = None) -> dict:
    """``{index: state}`` of ``shapes[i]`` for every ``i`` in ``indices``; ``handles``
    as :func:`shape_state`'s (the caller keeps the shapes alive)."""
    return {i: shape_state(shapes[i], handles) for i in indices}


def _identity(values: tuple) -> tuple:
    """What tells two parameter sets apart, as host values that a later write cannot
    change: a transform's affine entries (its inverse is derived from them), the values
    of a JIT array of at most :data:`_READ_LIMIT` entries, the variable indices of a
    larger one (kept theirs by the state holding the array), anything else as it is."""
    identity = []
    for value in values:
        if type(value).__name__.endswith("Transform4f"):  # any variant's, affine or not
            identity.append(_entries(value.matrix))
            continue
        indices = dr.detail.collect_indices(value)
        if not indices:
            identity.append(repr(value))
        elif dr.width(value) * len(indices) <= _READ_LIMIT:
            identity.append(_entries(value))
        else:
            identity.append(tuple(indices))
    return tuple(identity)


#: The largest JIT parameter (entries times fields) a look reads by value.
_READ_LIMIT = 64

#: Variable states whose entries the host reads without launching a kernel.
_READ_DIRECTLY = (dr.VarState.Evaluated, dr.VarState.Literal)


def _entries(value) -> tuple:
    """The entries of a JIT array or matrix as host floats, evaluated first (one kernel
    for all of them) if some are still lazy. A 4x4 matrix gives its first three rows
    (an affine transform's last row is 0 0 0 1)."""
    rows = [value[r] for r in range(3)] if dr.is_matrix_v(value) else [value]
    leaves = [leaf for row in rows for leaf in _leaves(row)]
    if any(leaf.state not in _READ_DIRECTLY for leaf in leaves):
        dr.eval(leaves)
    return tuple(leaf[k] for leaf in leaves for k in range(dr.width(leaf)))


def _leaves(value) -> list:
    """The flat JIT arrays a (possibly nested) Dr.Jit array is made of."""
    if dr.depth_v(value) <= 1:
        return [value]
    return [leaf for k in range(len(value)) for leaf in _leaves(value[k])]


def member_states(shapes, handles: dict) -> list:
    """Each shape's :func:`shape_state`: what a shape group's members are compared with
    later, by :func:`members_changed` (``handles`` as :func:`shape_state`'s)."""
    return [shape_state(shape, handles) for shape in shapes]


def members_changed(shapes, states: list, handles: dict) -> bool:
    """Whether a shape among ``shapes`` changed since ``states`` were taken."""
    return any(shape_state(shape, handles).moved(before) for shape, before in zip(shapes, states))
