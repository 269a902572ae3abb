"""What a USD stage costs and where its limits are said: UsdSkel skinning baked over
the frames asked for only, its bad inputs named in our own line; the scene digest a
resume compares, whatever the temporary folder; the rewritten textures' cache bounded;
lights too small for single precision lit as points or refused in one line."""

import math
import os
import tempfile
import time

import numpy as np
import pytest

pytest.importorskip("pxr")

import mitsuba as mi  # noqa: E402
from pxr import Gf, Usd, UsdGeom, UsdLux, UsdSkel, Vt  # noqa: E402

from cli_helpers import run_cli  # noqa: E402
from hlbvh.render.source import SceneSpec, open_animation  # noqa: E402
from hlbvh.scenes.usd import prims as usd_prims  # noqa: E402
from hlbvh.scenes.usd import UsdScene  # noqa: E402

from test_usd_lights import ALBEDO, HEIGHT, _above, _floor_stage  # noqa: E402
from test_usd_stages import _scaled_texture, _stage  # noqa: E402


# ---- UsdSkel skinning ---------------------------------------------------------------------


def _skinned(path, end, keys):
    """A stage of time codes 0..``end``: a quad bound to a one-joint skeleton whose
    animation, keyed at time codes ``keys`` only, moves it +x by ``t / end``."""
    stage = _stage(path, 0, end, quad="/Char/Body")
    UsdLux.DomeLight.Define(stage, "/Sky")
    UsdSkel.Root.Define(stage, "/Char")
    skeleton = UsdSkel.Skeleton.Define(stage, "/Char/Skel")
    skeleton.CreateJointsAttr(["root"])
    skeleton.CreateBindTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1)]))
    skeleton.CreateRestTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1)]))
    animation = UsdSkel.Animation.Define(stage, "/Char/Skel/Walk")
    animation.CreateJointsAttr(["root"])
    for t in keys:
        animation.CreateTranslationsAttr().Set(Vt.Vec3fArray([Gf.Vec3f(t / end, 0, 0)]), t)
    animation.CreateRotationsAttr().Set(Vt.QuatfArray([Gf.Quatf(1)]))
    animation.CreateScalesAttr().Set(Vt.Vec3hArray([Gf.Vec3h(1, 1, 1)]))
    UsdSkel.BindingAPI.Apply(skeleton.GetPrim()).CreateAnimationSourceRel().SetTargets(
        [animation.GetPath()])
    binding = UsdSkel.BindingAPI.Apply(stage.GetPrimAtPath("/Char/Body"))
    binding.CreateSkeletonRel().SetTargets([skeleton.GetPath()])
    binding.CreateJointIndicesPrimvar(False, 1).Set([0, 0, 0, 0])
    binding.CreateJointWeightsPrimvar(False, 1).Set([1.0] * 4)
    binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1))
    stage.GetRootLayer().Save()
    return path


def _body_samples(animation) -> int:
    return UsdGeom.Mesh(animation.stage.GetPrimAtPath("/Char/Body")) \
        .GetPointsAttr().GetNumTimeSamples()


@pytest.mark.parametrize("keys", ["every", "ends"])
def test01_skinning_is_baked_over_the_frames_asked_only(tmp_path, keys):
    """endTimeCode 1000, the joint keyed at every time code or at 0 and 1000 alone:
    frames 0:2 and 500:502 bake a handful of time codes (pxr's bake over the stage's
    range holds 1,001 copies of the points), each frame's points those of the whole
    range's bake, and a frame outside those asked is refused."""
    end = 1000
    path = _skinned(tmp_path / "walk.usda", end, range(end + 1) if keys == "every" else (0, end))
    whole = UsdScene(path, warn=lambda line: None)
    assert _body_samples(whole) > end
    for asked in (range(0, 2), range(500, 502)):
        animation, _, frames = open_animation(SceneSpec(str(path), frames=f"{asked.start}:"
                                                                          f"{asked.stop}"))
        assert frames == asked and _body_samples(animation) <= 5
        (body,) = animation.animated_ids()
        for i in asked:
            corners = animation.world_triangles(i)[body].reshape(-1, 3)
            np.testing.assert_array_equal(corners, whole.world_triangles(i)[body].reshape(-1, 3))
            assert corners[:, 0].min() == pytest.approx(-1 + i / end)
            points = animation.frame(i)[body].positions.reshape(-1, 3)
            assert points[:, 0].min() == pytest.approx(-1 + i / end)
        with pytest.raises(ValueError, match=rf"frame 3 \(time code 3\): its UsdSkel skinning "
                                             rf"was baked over time codes {asked.start}\.\."
                                             rf"{asked.stop - 1} only"):
            animation.frame(3)


def _bad_binding(path, weights=None, indices=None):
    _skinned(path, 2, range(3))
    stage = Usd.Stage.Open(str(path))
    binding = UsdSkel.BindingAPI(stage.GetPrimAtPath("/Char/Body"))
    if weights is not None:
        binding.GetJointWeightsPrimvar().Set(weights)
    if indices is not None:
        binding.GetJointIndicesPrimvar().Set(indices)
    stage.GetRootLayer().Save()
    return path


def test02_a_skinning_weight_that_is_not_finite_is_named(tmp_path, capsys):
    """NaN in primvars:skel:jointWeights: the weights named (the authored points are
    finite; pxr's bake would make them NaN)."""
    path = _bad_binding(tmp_path / "nan.usda", weights=[1.0, float("nan"), 1.0, 1.0])
    status, _, err = run_cli(capsys, "render", path, "--frames", "0:1", "--resolution", "8",
                             "--spp", "1", "--out", tmp_path / "out", "--quiet")
    assert status == 2 and err == [
        f"hlbvh render: stage {str(path)!r}: /Char/Body: primvars:skel:jointWeights is "
        f"(1, nan, 1, 1): expected finite values"], err


def test03_joint_indices_past_the_skeleton_are_our_one_line(tmp_path, capfd):
    """A joint index 7 of a one-joint skeleton: one line of ours naming the prim and the
    value, none of pxr's raw warnings (one per time code), and the rest points."""
    path = _bad_binding(tmp_path / "index.usda", indices=[0, 7, 0, 0])
    said = []
    animation = UsdScene(path, warn=said.append)
    err = capfd.readouterr().err
    assert "Warning" not in err and "joint index" not in err, err
    assert [line for line in said if "Body" in line] == [
        f"stage {str(path)!r}: /Char/Body: primvars:skel:jointIndices holds 7 (value 1 of "
        f"4), outside its 1 joints 0..0: UsdSkel does not skin it; its rest points render"]
    (body,) = animation.prim_paths()
    corners = animation.world_triangles(2)[body].reshape(-1, 3)
    assert corners[:, 0].min() == -1 and corners[:, 0].max() == 1


def _morphing(path, skeleton=True):
    """A glTF converter's morph targets: time codes 0..2, a quad with two blend
    shapes, "lift" (every point +z) and "widen" (points 1 and 2 +x/2), its bindings
    authored without SkelBindingAPI; with ``skeleton``, under a SkelRoot and bound to
    a skeleton whose animation weighs both 0 at time code 0 and 1 at 2."""
    stage = _stage(path, 0, 2, quad="/Char/Body")
    UsdLux.DomeLight.Define(stage, "/Sky")
    binding = UsdSkel.BindingAPI(stage.GetPrimAtPath("/Char/Body"))  # not applied
    if skeleton:
        UsdSkel.Root.Define(stage, "/Char")
        bound = UsdSkel.Skeleton.Define(stage, "/Char/Skel")
        animation = UsdSkel.Animation.Define(stage, "/Char/Skel/Morph")
        animation.CreateBlendShapesAttr(["lift", "widen"])
        for t, w in ((0, 0.0), (2, 1.0)):
            animation.CreateBlendShapeWeightsAttr().Set([w, w], t)
        UsdSkel.BindingAPI.Apply(bound.GetPrim()).CreateAnimationSourceRel().SetTargets(
            [animation.GetPath()])
        binding.CreateSkeletonRel().SetTargets([bound.GetPath()])
    lift = UsdSkel.BlendShape.Define(stage, "/Char/Body/Lift")
    lift.CreateOffsetsAttr([Gf.Vec3f(0, 0, 1)] * 4)
    widen = UsdSkel.BlendShape.Define(stage, "/Char/Body/Widen")
    widen.CreateOffsetsAttr([Gf.Vec3f(0.5, 0, 0)] * 2)
    widen.CreatePointIndicesAttr([1, 2])
    binding.CreateBlendShapesAttr(["lift", "widen"])
    binding.CreateBlendShapeTargetsRel().SetTargets([lift.GetPath(), widen.GetPath()])
    stage.GetRootLayer().Save()
    return path


def test08_blend_shapes_bound_without_skelbindingapi_follow_their_weights(tmp_path):
    """Frame i (weights i/2) holds the rest points plus each blend shape's offsets times
    its weight, exactly; a time inside the frame (the shutter's) its own weight; the
    binding without SkelBindingAPI said (UsdSkel ignores it: pxr's bake alone left
    the quad still)."""
    path = _morphing(tmp_path / "morph.usda")
    said = []
    animation = UsdScene(path, warn=said.append)
    assert [line for line in said if "SkelBindingAPI" in line] == [
        f"stage {str(path)!r}: /Char/Body author UsdSkel bindings (skel:...) without "
        f"SkelBindingAPI, which UsdSkel ignores since USD 23.08 (usdview shows them at "
        f"rest); they are applied as authored: skinned, blend shapes weighted by their "
        f"skeleton's animation"]
    (body,) = animation.animated_ids()
    rest = np.array([(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)], dtype=np.float32)
    lift = np.array([(0, 0, 1)] * 4, dtype=np.float32)
    widen = np.array([(0, 0, 0), (0.5, 0, 0), (0.5, 0, 0), (0, 0, 0)], dtype=np.float32)
    for i in range(3):
        w = np.float32(i / 2)
        points = np.asarray(animation.frame(i)[body].positions).reshape(-1, 3)
        np.testing.assert_array_equal(points, rest + w * lift + w * widen)
    points = np.asarray(animation.frame_at(0.5)[body].positions).reshape(-1, 3)
    np.testing.assert_allclose(points, rest + 0.25 * (lift + widen), atol=1e-6)


def test09_blend_shapes_with_no_skeleton_bound_are_said_and_rest(tmp_path):
    """skel:blendShapes on a mesh that no Skeleton binds (none on the stage): one line
    naming it (UsdSkel has no weights for them), the quad still (nothing said before)."""
    path = _morphing(tmp_path / "unbound.usda", skeleton=False)
    said = []
    assert UsdScene(path, warn=said.append).animated_ids() == []
    assert [line for line in said if "blend" in line] == [
        f"stage {str(path)!r}: /Char/Body: blend shapes (skel:blendShapes) are not "
        f"applied: UsdSkel weighs them by the animation of a Skeleton bound to the mesh "
        f"(skel:skeleton) under a SkelRoot, and none is; the rest points render"]


# ---- The scene digest and the texture cache ----------------------------------------------


def _textured(tmp_path):
    texture = tmp_path / "map.exr"
    mi.Bitmap(np.full((4, 4, 3), 0.5, dtype=np.float32)).write(str(texture))
    return _scaled_texture(tmp_path / "map.usda", texture, "diffuseColor",
                           scale=(2, 1, 1, 1), lit=True)


def test04_a_resume_under_another_tmpdir_is_not_refused(tmp_path, capsys, monkeypatch):
    """A scaled texture is rewritten into the temporary folder; a farm job run again
    with its own ``$TMPDIR`` finds its frame complete (the scene digest unchanged)."""
    path = _textured(tmp_path)
    for name in ("a", "b"):
        (tmp_path / name).mkdir()
        monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / name))
        status, out, err = run_cli(capsys, "render", path, "--resolution", "8", "--spp", "1",
                                   "--out", tmp_path / "out", "--quiet")
        assert status == 0, err
    assert "0 rendered, 1 already complete" in out, out
    assert (tmp_path / "b" / "hlbvh-textures").is_dir()


def test05_the_texture_cache_keeps_its_bound_least_recently_used_first(tmp_path,
                                                                        monkeypatch):
    """Past CACHE_BYTES, a new scaled texture removes the entries least recently used
    (not those used within the grace period), and a texture used again is kept."""
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))
    folder = usd_prims.cache_folder("hlbvh-textures")
    now = time.time()
    for k, age in enumerate((5000, 4000, 3000, 10)):  # seconds since last use
        entry = folder / f"old{k}"
        entry.mkdir(parents=True)
        (entry / "map.exr").write_bytes(b"x" * 1000)
        os.utime(entry / "map.exr", (now - age, now - age))
    monkeypatch.setattr(usd_prims, "CACHE_BYTES", 2500)
    UsdScene(_textured(tmp_path), warn=lambda line: None)
    kept = sorted(entry.name for entry in folder.iterdir())
    assert "old0" not in kept and "old1" not in kept and "old3" in kept, kept
    assert len(kept) == 3 and any(len(name) == 64 for name in kept), kept  # the new one


# ---- Lights too small for single precision -----------------------------------------------


def _bulb(radius):
    def light(stage):
        bulb = _above(UsdLux.SphereLight.Define(stage, "/Bulb"))
        bulb.CreateRadiusAttr(radius)
        bulb.CreateIntensityAttr(50.0)
        bulb.CreateNormalizeAttr(True)
    return light


@pytest.mark.parametrize("radius", [1e-3, 1e-4])
def test06_a_tiny_sphere_light_is_a_point_of_the_same_power_said(tmp_path, radius):
    """A normalized SphereLight of 1 mm or 0.1 mm 2 m over the floor (a sphere sampled
    in single precision gives 0.95 or 0 of the light there): the floor's irradiance
    that of the point it tends to, ``intensity / 4 / d^2``, and one line said."""
    said = []
    animation = UsdScene(_floor_stage(tmp_path / "bulb.usda", _bulb(radius)),
                         warn=said.append)
    image = np.array(mi.render(mi.load_dict(animation.scene_dict(resolution=(8, 8), spp=4)),
                               seed=1))
    expected = ALBEDO / math.pi * 50 / 4 / HEIGHT ** 2
    assert float(image[..., 0].mean()) == pytest.approx(expected, rel=0.01)
    assert [line for line in said if "/Bulb" in line] == [
        f"stage {str(tmp_path / 'bulb.usda')!r}: /Bulb: a SphereLight of radius {radius:.3g} "
        f"m, {radius / 14.3178:.2g} of the farthest distance to the scene (14.3 m), cannot "
        f"be sampled as a sphere in single precision; it is lit as a point light of the "
        f"same power"]


@pytest.mark.parametrize("kind", ["RectLight", "DiskLight"])
def test07_a_tiny_area_light_whose_radiance_overflows_is_refused(tmp_path, capsys, kind):
    """A 1e-30 m RectLight or DiskLight with normalize: its radiance (5e60) is past
    single precision, one line naming the stage and the prim (it rendered black)."""
    def light(stage):
        panel = _above(getattr(UsdLux, kind).Define(stage, "/Panel"))
        if kind == "RectLight":
            panel.CreateWidthAttr(1e-30)
            panel.CreateHeightAttr(1e-30)
        else:
            panel.CreateRadiusAttr(1e-30)
        panel.CreateIntensityAttr(5.0)
        panel.CreateNormalizeAttr(True)
    path = _floor_stage(tmp_path / "tiny.usda", light)
    status, _, err = run_cli(capsys, "render", path, "--frames", "0:1", "--resolution", "8",
                             "--spp", "1", "--out", tmp_path / "out", "--quiet")
    area = 1e-60 if kind == "RectLight" else math.pi * 1e-60
    assert status == 2 and err == [
        f"hlbvh render: stage {str(path)!r}: /Panel: inputs:intensity * 2^inputs:exposure "
        f"* inputs:color / its area ({area:.3g} m^2, inputs:normalize) is "
        f"{5 / area:.3g}, past single precision (3.4e+38)"], err
