"""The intersectors our integrators trace through: one HLBVH over a Mitsuba scene
(:class:`SceneAccel`) and the scene's own accelerator (:class:`NativeAccel`, Embree on
the LLVM backend, OptiX on CUDA), behind the same three methods as ``mi.Scene``.

Mitsuba 3 does not let Python supply the intersection routine of its native
accelerator, so the integration point is the integrator: every ray query of our
integrators goes to one of these objects, and a hit comes back as a
``mi.PreliminaryIntersection3f`` whose ``shape``/``shape_index``/``prim_index``/
``prim_uv`` are exactly what Mitsuba's own query would have produced, so that
``compute_surface_interaction`` (Mitsuba's code) fills in the surface interaction.

What :class:`SceneAccel` puts in its BVH, and what it does not:

* meshes (``obj``, ``ply``, ``serialized``, ``rectangle``, ``cube``, ... anything with
  ``is_mesh()``): their world-space triangles, all in one BVH;
* ``sphere``, ``disk``, ``cylinder``: the few analytic shapes, intersected by
  Mitsuba's own per-shape routine (``shape.ray_intersect_preliminary``, called once per
  analytic shape, not through a shape pointer: see DRJIT_NOTES pitfall 11) and merged
  with the BVH's hit by nearest ``t``;
* instances, curves, SDF grids and ellipsoids: rejected with a ``ValueError`` naming
  the shape (never rendered wrong);
* a scene without any geometry (only an environment, say) is valid, as it is for
  Mitsuba: every ray misses; so are meshes without triangles: nothing hits them.

``coherent`` is accepted everywhere for signature compatibility; it is a performance
hint of Embree's and :class:`SceneAccel` traces coherent and incoherent rays alike.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from hlbvh.kernels.build import build
from hlbvh.kernels.bvh import BuildConfig
from hlbvh.kernels.traversal import any_hit, closest_hit

ACCELS = ("hlbvh", "native")

#: Analytic shape types intersected by Mitsuba's own per-shape routine.
_ANALYTIC = ("Sphere", "Disk", "Cylinder")


@dataclass
class SceneGeometry:
    """What :class:`SceneAccel` collected from a scene, all on the scene's device.

    Attributes:
        vertices: Float (3·V): world-space positions of every mesh, concatenated.
        faces: UInt32 (3·F): triangles of every mesh, indices into ``vertices``
            (each mesh's indices offset by the vertices before it).
        prim_shape: UInt32 (F): for each global triangle, the index of its mesh in
            ``scene.shapes()``.
        prim_local: UInt32 (F): for each global triangle, its index inside its mesh.
        analytic: ``(index into scene.shapes(), shape)`` of every analytic shape.
        signature: the JIT variable indices of every mesh's buffers at collection
            time; a ``params.update()`` that changed a mesh changes it.
    """

    vertices: mi.Float
    faces: mi.UInt32
    prim_shape: mi.UInt32
    prim_local: mi.UInt32
    analytic: list
    signature: tuple

    @property
    def prim_count(self) -> int:
        return len(self.prim_shape)


def _describe(shape) -> str:
    return f"shape {shape.id()!r} ({shape.class_name()})"


def geometry_signature(shapes) -> tuple:
    """The JIT variable indices of every mesh's vertex and face buffers, in the order
    of ``shapes``: equal signatures mean the triangles did not change."""
    return tuple(
        (s.vertex_positions_buffer().index, s.faces_buffer().index) if s.is_mesh() else None
        for s in shapes
    )


def collect_geometry(shapes) -> SceneGeometry:
    """World-space triangles of every mesh among ``shapes`` in one vertex/face buffer,
    and the list of the analytic shapes.

    Args:
        shapes: ``scene.shapes()``; the indices stored refer to this list.

    A Python loop over the scene's shapes (a few), none over triangles.

    Raises:
        ValueError: naming the shape, for an instance, a curve, an SDF grid, ellipsoids
            or any other shape type this accelerator does not intersect, and for a
            mesh with non-finite vertex positions. Meshes without triangles are
            skipped (nothing can hit them), as Mitsuba's own accelerator does.
    """
    vertices, faces, prim_shape, prim_local, analytic = [], [], [], [], []
    vertex_base = 0
    for index, shape in enumerate(shapes):
        if shape.is_mesh():
            face_count = shape.face_count()
            if face_count == 0:
                continue  # nothing to hit, as for Mitsuba's own accelerator
            vertices.append(shape.vertex_positions_buffer())
            faces.append(shape.faces_buffer() + dr.opaque(mi.UInt32, vertex_base))
            prim_shape.append(dr.full(mi.UInt32, index, face_count))
            prim_local.append(dr.arange(mi.UInt32, face_count))
            vertex_base += shape.vertex_count()
        elif shape.class_name() in _ANALYTIC:
            analytic.append((index, shape))
        else:
            raise ValueError(
                f"{_describe(shape)}: hlbvh intersects meshes and the analytic shapes "
                f"{', '.join(s.lower() for s in _ANALYTIC)}; instances, shape groups, "
                "curves, SDF grids and ellipsoids are not supported yet. Use "
                "accel='native' for this scene."
            )
    if vertices:
        geometry = SceneGeometry(
            dr.concat(vertices), dr.concat(faces), dr.concat(prim_shape),
            dr.concat(prim_local), analytic, geometry_signature(shapes),
        )
        _check_finite(shapes, geometry)
    else:
        geometry = SceneGeometry(
            mi.Float(), mi.UInt32(), mi.UInt32(), mi.UInt32(), analytic,
            geometry_signature(shapes),
        )
    dr.eval(geometry.vertices, geometry.faces, geometry.prim_shape, geometry.prim_local)
    return geometry


def _check_finite(shapes, geometry: SceneGeometry):
    """One reduction over all vertices; on failure, find and name the culprit mesh."""
    if dr.all(dr.isfinite(geometry.vertices)):
        return
    for shape in shapes:
        if shape.is_mesh() and not dr.all(dr.isfinite(shape.vertex_positions_buffer())):
            raise ValueError(
                f"{_describe(shape)} has non-finite (NaN or infinite) vertex positions: "
                "fix the mesh or the parameters written into it"
            )


def _bind_overloads(args: tuple, long_names: tuple, given: dict) -> dict:
    """Bind the positional arguments after ``ray`` the way ``mi.Scene``'s overloads do.

    ``mi.Scene.ray_intersect`` and ``ray_test`` each have a short overload
    ``f(ray, active)`` and a long one ``f(ray, <long_names...>, active)``: a single
    positional argument is ``active``; several fill ``long_names`` then ``active`` in
    order.

    Args:
        args: the positional arguments after ``ray``.
        long_names: the long overload's parameter names before ``active``.
        given: the keyword arguments, defaults filled in, with ``active`` None when not
            passed by keyword.
    Returns:
        ``given`` with the positional arguments bound and ``active`` never None.
    """
    names = long_names + ("active",)
    if len(args) == 1 and given["active"] is None:
        names = ("active",)
    elif len(args) > len(names):
        raise TypeError(f"expected at most {len(names) + 1} positional arguments (ray, "
                        f"{', '.join(names)}), got {len(args) + 1}")
    bound = dict(given)
    for name, value in zip(names, args):
        bound[name] = value
    if bound["active"] is None:
        bound["active"] = True
    return bound


class _Accel:
    """The three query methods of ``mi.Scene`` with its signatures, keyword names and
    defaults (every overload: ``ray_intersect(ray, active)`` and ``ray_test(ray,
    active)`` included, and the keyword-only ``reorder``, ``reorder_hint``,
    ``reorder_hint_bits``, which are thread-reordering hints for CUDA), bound here once
    and handed to a subclass's ``_preliminary``, ``_intersect`` and ``_test``."""

    def ray_intersect_preliminary(self, ray, coherent=False, active=True, *, reorder=False,
                                  reorder_hint=0, reorder_hint_bits=0):
        """``mi.Scene.ray_intersect_preliminary``: the closest hit's parameters.

        Args:
            ray: ``mi.Ray3f`` (``maxt`` honoured; hits at t <= 0 are never reported).
            coherent: hint that the rays are coherent (camera rays). It changes
                Embree's answer on a few edge rays, so pass what Mitsuba would.
            active: Bool mask.
        Returns:
            ``mi.PreliminaryIntersection3f`` with ``t``, ``prim_uv``, ``prim_index``
            (local to the shape), ``shape_index`` (into ``scene.shapes()``), ``shape``,
            ``instance`` null; on a miss ``valid`` False and ``t`` infinite.
        """
        return self._preliminary(ray, coherent, active, (reorder, reorder_hint, reorder_hint_bits))

    def ray_intersect(self, ray, *args, ray_flags=mi.RayFlags.All, coherent=False, active=None,
                      reorder=False, reorder_hint=0, reorder_hint_bits=0):
        """``mi.Scene.ray_intersect``: ``(ray, active=True)`` or
        ``(ray, ray_flags, coherent, active=True)``.

        Returns:
            ``mi.SurfaceInteraction3f`` computed by Mitsuba from the closest hit.
        """
        a = _bind_overloads(args, ("ray_flags", "coherent"),
                            dict(ray_flags=ray_flags, coherent=coherent, active=active))
        return self._intersect(ray, a["ray_flags"], a["coherent"], a["active"],
                               (reorder, reorder_hint, reorder_hint_bits))

    def ray_test(self, ray, *args, coherent=False, active=None):
        """``mi.Scene.ray_test``: ``(ray, active=True)`` or ``(ray, coherent, active=True)``.

        Returns:
            Bool per ray: whether anything lies on it at 0 < t <= ``ray.maxt``.
        """
        a = _bind_overloads(args, ("coherent",), dict(coherent=coherent, active=active))
        return self._test(ray, a["coherent"], a["active"])

    def _intersect(self, ray, ray_flags, coherent, active, reorder):
        """The closest hit, expanded by Mitsuba, as ``mi.Scene.ray_intersect`` does."""
        pi = self._preliminary(ray, coherent, active, reorder)
        return pi.compute_surface_interaction(ray, ray_flags, active)


class NativeAccel(_Accel):
    """The scene's own accelerator (Embree or OptiX) behind the same interface as
    :class:`SceneAccel`: the reference our images are compared against. Every query is
    the scene's, with the same arguments.

    Args:
        scene: the ``mi.Scene``. Mitsuba rebuilds its accelerator itself in
            ``params.update()``, so :meth:`update` has nothing to do.
    """

    name = "native"

    def __init__(self, scene):
        self.scene = scene

    def update(self):
        """Nothing to do: ``params.update()`` already rebuilt Mitsuba's accelerator.

        Returns:
            self.
        """
        return self

    def _preliminary(self, ray, coherent, active, reorder):
        return self.scene.ray_intersect_preliminary(ray, coherent, *reorder, active)

    def _intersect(self, ray, ray_flags, coherent, active, reorder):
        return self.scene.ray_intersect(ray, ray_flags, coherent, *reorder, active)

    def _test(self, ray, coherent, active):
        return self.scene.ray_test(ray, coherent, active)


class SceneAccel(_Accel):
    """One HLBVH over the triangles of every mesh of a Mitsuba scene, plus the scene's
    analytic shapes, queried with ``mi.Scene``'s own signatures.

    Args:
        scene: the ``mi.Scene`` (JIT variant: LLVM or CUDA).
        **options: options of :func:`hlbvh.build` (``builder``, ``leaf_size``,
            ``morton_bits``, ``quantization``, ``coarse_bits``, ``p``, ``sah_bins``).
    Raises:
        ValueError: for an unknown or invalid option (naming it), or for a shape this
            accelerator cannot intersect (see the module docstring), naming the shape.

    Attributes:
        shapes: ``scene.shapes()`` when built. The accelerator keeps the shapes, not
            the scene: an integrator that the scene owns can cache it without a
            reference cycle keeping the scene alive.
        shapes_dr: ``scene.shapes_dr()``, where hits find their shape pointer.
        config: the validated :class:`hlbvh.BuildConfig`.
        geometry: the :class:`SceneGeometry` the BVH was built over.
        bvh: the :class:`hlbvh.BVH`, or None when the scene has no triangles.
    """

    name = "hlbvh"

    def __init__(self, scene, **options):
        self.config = BuildConfig.from_options(**options)
        self.options = options
        self.shapes = list(scene.shapes())
        self.shapes_dr = scene.shapes_dr()
        self.geometry = None
        self.bvh = None
        self.update()

    def is_for(self, scene) -> bool:
        """Whether this accelerator was built over ``scene``'s shapes."""
        shapes = scene.shapes()
        return len(shapes) == len(self.shapes) and all(a is b for a, b in zip(shapes, self.shapes))

    def changed(self) -> bool:
        """Whether a mesh got new vertex or face buffers (a ``params.update()`` with
        new values) since the last build."""
        return geometry_signature(self.shapes) != self.geometry.signature

    def update(self):
        """Re-collect the meshes' triangles and rebuild the BVH; call it after
        ``params.update()`` changed the scene.

        Returns:
            self.
        """
        self.geometry = collect_geometry(self.shapes)
        if self.geometry.prim_count == 0:
            self.bvh = None
        else:
            try:
                self.bvh = build(self.geometry.vertices, self.geometry.faces, **self.options)
            except ValueError as e:
                raise ValueError(f"building the HLBVH of the scene's meshes failed: {e}") from e
        return self

    def _preliminary(self, ray, coherent, active, reorder):
        """The BVH's closest triangle hit, then each analytic shape's own routine,
        merged by nearest ``t``; ``coherent`` and ``reorder`` change nothing here."""
        n = dr.width(ray)
        active = mi.Bool(active) & dr.full(mi.Bool, True, n)
        t, prim_uv, prim_index, shape_index = self._closest_mesh_hit(ray, active)
        for index, shape in self.geometry.analytic:
            pi_s = shape.ray_intersect_preliminary(ray, 0, active)
            closer = pi_s.is_valid() & (pi_s.t < t)
            t = dr.select(closer, pi_s.t, t)
            prim_uv = dr.select(closer, pi_s.prim_uv, prim_uv)
            prim_index = dr.select(closer, pi_s.prim_index, prim_index)
            shape_index = dr.select(closer, index, shape_index)
        pi = dr.zeros(mi.PreliminaryIntersection3f, n)
        pi.valid = active & (t < dr.inf)
        pi.t = dr.select(pi.valid, t, dr.inf)
        pi.prim_uv = mi.Point2f(prim_uv)
        pi.prim_index = dr.select(pi.valid, prim_index, 0)
        pi.shape_index = dr.select(pi.valid, shape_index, 0xFFFFFFFF)
        if dr.width(self.shapes_dr) > 0:  # a scene may have no shape at all
            pi.shape = dr.gather(mi.ShapePtr, self.shapes_dr, pi.shape_index, pi.valid)
        return pi

    def _closest_mesh_hit(self, ray, active):
        """(t, prim_uv, prim_index, shape_index) of the BVH's closest hit; t infinite
        where there is none."""
        n = dr.width(ray)
        if self.bvh is None:
            return (dr.full(mi.Float, dr.inf, n), dr.zeros(mi.Point2f, n),
                    dr.zeros(mi.UInt32, n), dr.zeros(mi.UInt32, n))
        t, u, v, prim, valid = closest_hit(self.bvh, ray.o, ray.d, ray.maxt, active)
        valid = mi.Bool(valid)
        prim = mi.UInt32(prim)
        return (
            dr.select(valid, mi.Float(t), dr.inf),
            mi.Point2f(mi.Float(u), mi.Float(v)),
            dr.gather(mi.UInt32, self.geometry.prim_local, prim, valid),
            dr.gather(mi.UInt32, self.geometry.prim_shape, prim, valid),
        )

    def _test(self, ray, coherent, active):
        active = mi.Bool(active) & dr.full(mi.Bool, True, dr.width(ray))
        if self.bvh is None:
            hit = dr.zeros(mi.Bool, dr.width(ray))
        else:
            hit = mi.Bool(any_hit(self.bvh, ray.o, ray.d, ray.maxt, active))
        for _, shape in self.geometry.analytic:
            hit |= shape.ray_test(ray, active & ~hit)
        return hit & active


def make_accel(scene, accel: str = "hlbvh", **options):
    """The intersector named ``accel`` for ``scene``.

    Args:
        scene: the ``mi.Scene``.
        accel: ``"hlbvh"`` (:class:`SceneAccel`) or ``"native"`` (:class:`NativeAccel`).
        **options: :func:`hlbvh.build` options, validated in both cases (so a typo is
            caught even while rendering natively) and used by ``"hlbvh"``.
    Raises:
        ValueError: for any other ``accel``, or an unknown or invalid option.
    """
    if accel == "hlbvh":
        return SceneAccel(scene, **options)
    if accel == "native":
        BuildConfig.from_options(**options)
        return NativeAccel(scene)
    raise ValueError(f"accel={accel!r}: expected one of {ACCELS}")
