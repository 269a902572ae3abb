"""UsdSkel skinning of a USD stage, computed by pxr's own ``UsdSkelBakeSkinning`` into
the stage's session layer (in memory: the files are never written) as the points and
transforms a DCC's baked export holds, which the mesh loader then reads like any other.

Only the time codes a render reads are baked (:func:`bake_skinning`): pxr bakes every
time code of the stage's playback range inside the interval it is given, so a stage of
10,000 frames rendered for two would otherwise hold 10,000 copies of every skinned
mesh's points. The inputs pxr does not check in a way a user sees are checked first
(:func:`check_bindings`): weights that are not finite (pxr would bake NaN points) and
joint indices past the skeleton's joints (pxr prints a raw warning per time code and
leaves the mesh at rest). Bindings authored without ``SkelBindingAPI`` (glTF
converters' morph targets: ``skel:blendShapes`` on a mesh that lacks the schema),
which UsdSkel ignores, get the schema in the session layer first
(:func:`apply_bindings`), so their blend shapes (``UsdSkelBlendShape`` offsets,
``pointIndices``, inbetweens) are baked by pxr, weighted by the skeleton animation's
``blendShapeWeights``, like any other.
"""

from __future__ import annotations

import numpy as np

from .prims import Gf, Sdf, Tf, Usd, UsdGeom, _checked, _stderr_captured
from .time_codes import transform_attributes

try:
    from pxr import UsdSkel
except ImportError:  # pragma: no cover - UsdSkel is optional in some USD builds
    UsdSkel = None


def skel_binding():
    """``UsdSkel.BindingAPI`` (the schema's name where this USD build has no UsdSkel)."""
    return "SkelBindingAPI" if UsdSkel is None else UsdSkel.BindingAPI


def _skinned_meshes(stage) -> list:
    """The mesh prims pxr skins: bound to a skeleton, under a ``SkelRoot``."""
    return [prim for prim in stage.Traverse()
            if prim.IsA(UsdGeom.Mesh) and prim.HasAPI(UsdSkel.BindingAPI)
            and UsdSkel.Root.Find(prim)
            and UsdSkel.BindingAPI(prim).GetInheritedSkeleton()]


def check_bindings(stage, where: str) -> list[str]:
    """Check every skinned mesh's joint weights and indices, as pxr's skinning queries
    resolve them (inherited primvars, a mesh's own ``skel:joints`` order).

    Returns:
        The lines to say (naming ``where``, the stage, and the prim), one per mesh whose
        joint indices point past its joints: pxr leaves it at rest.
    Raises:
        ValueError: naming the stage, the prim and the primvar: a joint weight that is
            not finite (every skinned point would be NaN).
    """
    lines = []
    cache = UsdSkel.Cache()
    for root in (prim for prim in stage.Traverse() if prim.IsA(UsdSkel.Root)):
        cache.Populate(UsdSkel.Root(root), Usd.PrimDefaultPredicate)
        for binding in cache.ComputeSkelBindings(UsdSkel.Root(root), Usd.PrimDefaultPredicate):
            skeleton = binding.GetSkeleton().GetJointsAttr().Get() or []
            for query in binding.GetSkinningTargets():
                path = query.GetPrim().GetPath()
                weights = query.GetJointWeightsPrimvar()
                if weights:
                    _checked(f"{where}: {path}: primvars:skel:jointWeights", np.asarray(
                        weights.ComputeFlattened() or [], dtype=np.float64))
                indices = np.asarray((query.GetJointIndicesPrimvar().ComputeFlattened()
                                      if query.GetJointIndicesPrimvar() else None) or [],
                                     dtype=np.int64)
                order = query.GetJointOrder()
                count = len(skeleton if order is None else order)
                bad = (indices < 0) | (indices >= count)
                if bad.any():
                    first = int(np.flatnonzero(bad)[0])
                    lines.append(f"{where}: {path}: primvars:skel:jointIndices holds "
                                 f"{indices[first]} (value {first} of {len(indices)}), "
                                 f"outside its {count} joints 0..{count - 1}: UsdSkel does "
                                 f"not skin it; its rest points render")
    return list(dict.fromkeys(lines))  # a nested SkelRoot's meshes are its parent's too


def _bound_without_api(stage) -> list:
    """The prims that author UsdSkel binding properties (``skel:skeleton``,
    ``skel:blendShapes``, ``primvars:skel:jointWeights``, ...) without
    ``SkelBindingAPI`` applied: UsdSkel ignores such bindings (since USD 23.08; before,
    it honoured them with a deprecation warning), which exports from glTF converters
    author for their morph targets."""
    return [prim for prim in stage.Traverse() if not prim.HasAPI(UsdSkel.BindingAPI)
            and any(name.startswith(("skel:", "primvars:skel:"))
                    for name in prim.GetAuthoredPropertyNames())]


def apply_bindings(stage, where: str) -> list[str]:
    """Apply ``SkelBindingAPI`` in the session layer (in memory) to every prim that
    authors UsdSkel bindings without it (:func:`_bound_without_api`), so that pxr's
    bake skins them and applies their blend shapes as their author bound them.

    Returns:
        One line to say (naming ``where``, the stage, the first prim and how many
        others), or none.
    """
    prims = _bound_without_api(stage)
    if not prims:
        return []
    target = stage.GetEditTarget()
    stage.SetEditTarget(Usd.EditTarget(stage.GetSessionLayer()))
    try:
        for prim in prims:
            UsdSkel.BindingAPI.Apply(prim)
    finally:
        stage.SetEditTarget(target)
    others = f" and {len(prims) - 1} other prims" if len(prims) > 1 else ""
    return [f"{where}: {prims[0].GetPath()}{others} author UsdSkel bindings (skel:...) "
            f"without SkelBindingAPI, which UsdSkel ignores since USD 23.08 (usdview "
            f"shows them at rest); they are applied as authored: skinned, blend shapes "
            f"weighted by their skeleton's animation"]


def unweighted_lines(stage, where: str) -> list[str]:
    """One line (naming ``where``, the stage, the first mesh and how many others) for
    the meshes that author blend shapes (``skel:blendShapes``) with no Skeleton bound
    to them under a SkelRoot: UsdSkel weighs blend shapes by a bound skeleton's
    animation (``blendShapeWeights``), so pxr leaves them at rest; none when every
    such mesh has one. Read after :func:`apply_bindings`, whose schema the inherited
    binding needs."""
    meshes = [prim.GetPath() for prim in stage.Traverse() if prim.IsA(UsdGeom.Mesh)
              and UsdSkel.BindingAPI(prim).GetBlendShapesAttr().HasAuthoredValue()
              and not (UsdSkel.Root.Find(prim)
                       and UsdSkel.BindingAPI(prim).GetInheritedSkeleton())]
    if not meshes:
        return []
    others = f" and {len(meshes) - 1} other meshes" if len(meshes) > 1 else ""
    return [f"{where}: {meshes[0]}{others}: blend shapes (skel:blendShapes) are not "
            f"applied: UsdSkel weighs them by the animation of a Skeleton bound to the "
            f"mesh (skel:skeleton) under a SkelRoot, and none is; the rest points render"]


def _animation_attributes(stage) -> list:
    """The attributes whose time samples pxr's bake follows: every skeleton
    animation's, and the transforms of the skeletons and skinned meshes."""
    found = []
    for prim in stage.Traverse():
        if prim.IsA(UsdSkel.Animation):
            found += prim.GetAttributes()
        elif prim.IsA(UsdSkel.Skeleton):
            found += transform_attributes(prim)
    for prim in _skinned_meshes(stage):
        found += transform_attributes(prim)
    return found


def bake_span(attributes, first: float, last: float) -> tuple[float, float]:
    """The interval to bake so that time codes ``first .. last`` read the skinning pxr
    computes: widened to the authored samples of ``attributes`` just before ``first``
    and just after ``last`` (pxr bakes at the samples inside the interval it is given,
    and a mesh between two samples outside it would be left at rest)."""
    low, high = first, last
    for attribute in attributes:
        if attribute.GetNumTimeSamples() == 0:
            continue
        below = attribute.GetBracketingTimeSamples(first)
        above = attribute.GetBracketingTimeSamples(last)
        if below:
            low = min(low, below[0])
        if above:
            high = max(high, above[1])
    return low, high


def bake_skinning(stage, first: float, last: float, where: str) -> tuple[bool, list[str]]:
    """UsdSkel's own skinning of every skinned mesh of ``stage`` at the time codes
    ``first .. last`` (a render's: the interval of the frames it reads), into the
    session layer: at the stage's playback time codes inside that interval (pxr's own
    step, ``timeCodesPerSecond / framesPerSecond``) and at the animation's samples that
    bracket it, no others. A mesh whose points are time-sampled already holds its
    skinning (baked by the export): its own points are kept. Bindings authored without
    ``SkelBindingAPI`` are applied first (:func:`apply_bindings`).

    Returns:
        ``(baked, lines)``: False when the stage has no skeleton, or this USD build has no
        ``UsdSkelBakeSkinning`` or it fails (the rest points then render, said by the
        mesh loader); the lines to say (:func:`apply_bindings`, :func:`unweighted_lines`,
        :func:`check_bindings`; pxr's own diagnostics,
        once each, those on joint indices left to :func:`check_bindings`'s line).
    Raises:
        ValueError: see :func:`check_bindings`.
    """
    if UsdSkel is None or not hasattr(UsdSkel, "BakeSkinning"):
        return False, []
    if not any(prim.IsA(UsdSkel.Skeleton) for prim in stage.Traverse()):
        return False, unweighted_lines(stage, where)
    lines = apply_bindings(stage, where)
    lines += unweighted_lines(stage, where) + check_bindings(stage, where)
    low, high = bake_span(_animation_attributes(stage), first, last)
    baked = [prim.GetPath() for prim in stage.Traverse() if prim.IsA(UsdGeom.Mesh)
             and UsdGeom.Mesh(prim).GetPointsAttr().GetNumTimeSamples() > 1]
    session = stage.GetSessionLayer()
    target = stage.GetEditTarget()
    stage.SetEditTarget(Usd.EditTarget(session))
    # pxr bakes every playback time code of the stage's range inside the interval:
    # the session layer's range (stronger than the root layer's) narrows it to ours.
    stage.SetStartTimeCode(first)
    stage.SetEndTimeCode(last)
    try:
        with _stderr_captured() as said:
            done = bool(UsdSkel.BakeSkinning(stage.Traverse(), Gf.Interval(low, high)))
    except Tf.ErrorException:
        done = False
    finally:
        session.ClearStartTimeCode()
        session.ClearEndTimeCode()
        stage.SetEditTarget(target)
    with Sdf.ChangeBlock():
        for path in baked:
            spec = session.GetPrimAtPath(path)
            if spec:
                del session.GetPrimAtPath(path.GetParentPath()).nameChildren[path.name]
    for text in dict.fromkeys(" ".join(line.split(" -- ", 1)[-1].split()) for line in said):
        if text and "joint index" not in text:
            lines.append(f"{where}: USD says: {text[:300]}")
    return done, lines
