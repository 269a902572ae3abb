"""What published USD stages hold and :mod:`hlbvh.scenes.usd` now reads as their
authors meant: no light (a said default sky and sun, ``--no-default-light``), colour
from a primvar reader, a textured emission, UsdSkel skinning (pxr's own baking; none
over points already baked), a time range of ``endTimeCode`` alone."""

import numpy as np
import pytest

pytest.importorskip("pxr")

import mitsuba as mi  # noqa: E402
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdShade, UsdSkel, Vt  # noqa: E402

from cli_helpers import run_cli  # noqa: E402
from hlbvh.cli.options import SceneArgument  # noqa: E402
from hlbvh.render import cluster  # noqa: E402
from hlbvh.render.source import SceneSpec, open_animation  # noqa: E402
from hlbvh.scenes.usd import UsdScene  # noqa: E402
from hlbvh.scenes.usd.lights import DEFAULT_LIGHTS  # noqa: E402


def _stage(path, start=None, end=None, quad="/Quad"):
    """A Y-up stage in metres with a quad (at prim path ``quad``) facing a camera at
    z=4 (nothing lights it)."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    if start is not None:
        stage.SetStartTimeCode(start)
    if end is not None:
        stage.SetEndTimeCode(end)
    mesh = UsdGeom.Mesh.Define(stage, quad)
    mesh.CreatePointsAttr([(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)])
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    mesh.CreateSubdivisionSchemeAttr("none")
    UsdGeom.Camera.Define(stage, "/Cam").AddTranslateOp().Set(Gf.Vec3d(0, 0, 4))
    return stage


def _render(animation, size=8, spp=4):
    scene = mi.load_dict(animation.scene_dict(resolution=(size, size), spp=spp))
    return np.array(mi.render(scene, seed=0))


# ---- No light -------------------------------------------------------------------------


def test_a_stage_without_light_is_said_and_lit_by_the_default_sky_and_sun(tmp_path, capsys):
    path = tmp_path / "dark.usda"
    stage = _stage(path)
    stage.GetRootLayer().Save()
    said = []
    animation = UsdScene(path, warn=said.append)
    assert [line for line in said if "light" in line] == [
        f"stage {str(path)!r}: no UsdLux light; a default sky (radiance 0.3) and sun "
        f"(irradiance 2, from above) light it, as a DCC's viewport does "
        f"(--no-default-light: none)"]
    description = animation.scene_dict(resolution=(8, 8), spp=1)
    assert description["default_sky"] == DEFAULT_LIGHTS["default_sky"]
    assert description["default_sun"] == DEFAULT_LIGHTS["default_sun"]
    assert _render(animation)[4, 4, 0] > 0.1  # the grey quad is lit

    said.clear()
    dark = UsdScene(path, warn=said.append, default_light=False)
    assert [line for line in said if "light" in line] == [
        f"stage {str(path)!r}: no UsdLux light, and --no-default-light: only emitting "
        f"materials light it"]
    assert not np.any(_render(dark))

    # The flag, through the command line, a resume's source and a cluster's spec.
    scene = SceneArgument.of(str(path), None, default_light=False)
    animation, source, _ = open_animation(SceneSpec.of(scene, frames="0:1"))
    assert source["scene"].endswith(":default_light=false")
    assert "default_sky" not in animation.scene_dict(resolution=(8, 8), spp=1)
    assert SceneSpec.of(scene, None, None, range(0, 1)).absolute().scene.endswith(
        ":default_light=false")
    status, _, err = run_cli(capsys, "render", path, "--no-default-light", "--frames", "0:1",
                             "--out", tmp_path / "out", "--resolution", "8", "--spp", "1",
                             "--quiet")
    assert status == 0 and any("--no-default-light: only emitting" in line for line in err)
    status, _, err = run_cli(capsys, "render", "cloth", "--no-default-light",
                             "--out", tmp_path / "cloth")
    assert status == 2 and err == ["hlbvh render: --no-default-light is for USD stages "
                                   "without lights; 'cloth' is not a USD stage"]


def test_a_lit_stage_gets_no_default_light(tmp_path):
    stage = _stage(tmp_path / "lit.usda")
    UsdLux.DomeLight.Define(stage, "/Sky")
    stage.GetRootLayer().Save()
    said = []
    description = UsdScene(tmp_path / "lit.usda", warn=said.append).scene_dict(
        resolution=(8, 8), spp=1)
    assert "default_sky" not in description and not any("UsdLux" in line for line in said)


# ---- Materials --------------------------------------------------------------------------


def _surface(stage):
    material = UsdShade.Material.Define(stage, "/Looks/Look")
    surface = UsdShade.Shader.Define(stage, "/Looks/Look/Surface")
    surface.CreateIdAttr("UsdPreviewSurface")
    material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
    UsdShade.MaterialBindingAPI.Apply(stage.GetPrimAtPath("/Quad")).Bind(material)
    return surface


@pytest.mark.parametrize("per_vertex", [False, True])
def test_diffuse_colour_from_a_primvar_reader_reads_the_primvar(tmp_path, per_vertex):
    stage = _stage(tmp_path / "reader.usda")
    UsdLux.DomeLight.Define(stage, "/Sky")
    quad = UsdGeom.Mesh(stage.GetPrimAtPath("/Quad"))
    colours = quad.CreateDisplayColorPrimvar(
        UsdGeom.Tokens.vertex if per_vertex else UsdGeom.Tokens.constant)
    colours.Set([(0.9, 0.1, 0.1)] * (4 if per_vertex else 1))
    if per_vertex:
        colours.Set([(0.9, 0.1, 0.1), (0.9, 0.1, 0.1), (0.1, 0.1, 0.9), (0.1, 0.1, 0.9)])
    surface = _surface(stage)
    reader = UsdShade.Shader.Define(stage, "/Looks/Look/Colour")
    reader.CreateIdAttr("UsdPrimvarReader_float3")
    reader.CreateInput("varname", Sdf.ValueTypeNames.Token).Set("displayColor")
    surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(
        reader.ConnectableAPI(), "result")
    stage.GetRootLayer().Save()
    said = []
    animation = UsdScene(tmp_path / "reader.usda", warn=said.append)
    assert not any("not read" in line or "Colour" in line for line in said), said
    base = animation._meshes[0].bsdf["base_color"]
    if per_vertex:
        assert base == {"type": "mesh_attribute", "name": "vertex_color"}
        image = _render(animation, size=16)
        assert image[15, 8, 0] > 3 * image[15, 8, 2] and image[0, 8, 2] > 3 * image[0, 8, 0]
    else:
        assert base == {"type": "rgb", "value": pytest.approx([0.9, 0.1, 0.1])}


def test_a_textured_emission_reads_its_texture_and_no_authored_white(tmp_path):
    texture = tmp_path / "glow.exr"
    pixels = np.zeros((4, 4, 3), dtype=np.float32)
    pixels[..., 0] = 2.0  # red light
    mi.Bitmap(pixels).write(str(texture))
    stage = _stage(tmp_path / "glow.usda")
    UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/Quad")).CreatePrimvar(
        "st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex).Set(
        [(0, 0), (1, 0), (1, 1), (0, 1)])
    surface = _surface(stage)
    image = UsdShade.Shader.Define(stage, "/Looks/Look/Glow")
    image.CreateIdAttr("UsdUVTexture")
    image.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(Sdf.AssetPath(str(texture)))
    surface.CreateInput("emissiveColor", Sdf.ValueTypeNames.Color3f).Set((1, 1, 1))
    surface.GetInput("emissiveColor").ConnectToSource(image.ConnectableAPI(), "rgb")
    stage.GetRootLayer().Save()
    said = []
    animation = UsdScene(tmp_path / "glow.usda", warn=said.append, default_light=False)
    assert not any("not read" in line for line in said), said
    assert animation._meshes[0].emission["filename"] == str(texture)
    centre = _render(animation)[4, 4]
    assert centre[0] == pytest.approx(2.0, rel=1e-3) and centre[1] == centre[2] == 0


def _scaled_texture(path, texture, name, scale=None, bias=None, lit=False):
    """A stage whose quad's input ``name`` reads ``texture`` through a UsdUVTexture with
    ``scale`` and ``bias`` (float4, as UsdUVTexture declares them); ``lit``: a dome."""
    stage = _stage(path)
    if lit:
        UsdLux.DomeLight.Define(stage, "/Sky")
    UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/Quad")).CreatePrimvar(
        "st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex).Set(
        [(0, 0), (1, 0), (1, 1), (0, 1)])
    surface = _surface(stage)
    image = UsdShade.Shader.Define(stage, "/Looks/Look/Map")
    image.CreateIdAttr("UsdUVTexture")
    image.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(Sdf.AssetPath(str(texture)))
    for key, value in (("scale", scale), ("bias", bias)):
        if value is not None:
            image.CreateInput(key, Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(*value))
    surface.CreateInput(name, Sdf.ValueTypeNames.Color3f).ConnectToSource(
        image.ConnectableAPI(), "rgb")
    stage.GetRootLayer().Save()
    return path


def _srgb_to_linear(c):
    return c / 12.92 if c <= 0.04045 else ((c + 0.055) / 1.055) ** 2.4


@pytest.mark.parametrize("suffix", ["exr", "png"])
def test_a_textured_emission_honours_the_texture_s_scale_and_bias(tmp_path, suffix):
    """UsdUVTexture outputs linear texel * scale + bias: an OpenEXR of (0.2, 0.4, 0.6)
    or an 8-bit sRGB PNG of (128, 255, 0), scale (2, 0.5, 1), bias (0.1, 0.05, 0)."""
    texture = tmp_path / f"glow.{suffix}"
    if suffix == "exr":
        mi.Bitmap(np.full((4, 4, 3), (0.2, 0.4, 0.6), dtype=np.float32)).write(str(texture))
        texel = (0.2, 0.4, 0.6)
    else:
        mi.Bitmap(np.full((4, 4, 3), (128, 255, 0), dtype=np.uint8)).write(str(texture))
        texel = (_srgb_to_linear(128 / 255), 1.0, 0.0)
    path = _scaled_texture(tmp_path / "glow.usda", texture, "emissiveColor",
                           scale=(2, 0.5, 1, 1), bias=(0.1, 0.05, 0, 0))
    expected = [2 * texel[0] + 0.1, 0.5 * texel[1] + 0.05, texel[2]]
    said = []
    animation = UsdScene(path, warn=said.append, default_light=False)
    assert not any("/Looks" in line for line in said), said
    assert animation._meshes[0].emission["filename"].endswith("glow.exr")
    assert _render(animation)[4, 4] == pytest.approx(expected, rel=1e-3)


def test_a_diffuse_texture_honours_scale_and_bias_as_its_colour_would(tmp_path):
    """A constant map (0.2, 0.4, 0.6) with scale (2, 0.5, 1) and bias (0.1, 0.05, 0)
    renders as a map of the hand-computed (0.5, 0.25, 0.6) without them does (the same
    uv, so the same paths); the map alone does not."""
    renders = {}
    for name, texel, scale, bias in (("scaled", (0.2, 0.4, 0.6), (2, 0.5, 1, 1), (0.1, 0.05, 0, 0)),
                                     ("plain", (0.2, 0.4, 0.6), None, None),
                                     ("computed", (0.5, 0.25, 0.6), None, None)):
        texture = tmp_path / f"{name}.exr"
        mi.Bitmap(np.full((4, 4, 3), texel, dtype=np.float32)).write(str(texture))
        renders[name] = _render(UsdScene(_scaled_texture(
            tmp_path / f"{name}.usda", texture, "diffuseColor", scale, bias, lit=True),
            warn=lambda line: None))
    np.testing.assert_allclose(renders["scaled"], renders["computed"], rtol=1e-4, atol=1e-6)
    assert abs(renders["plain"][4, 4, 1] - renders["computed"][4, 4, 1]) > 0.05


def test_a_texture_scale_that_is_not_finite_is_named(tmp_path):
    texture = tmp_path / "map.exr"
    mi.Bitmap(np.ones((4, 4, 3), dtype=np.float32)).write(str(texture))
    path = _scaled_texture(tmp_path / "nan.usda", texture, "diffuseColor",
                           scale=(float("nan"), 1, 1, 1))
    with pytest.raises(ValueError) as caught:
        UsdScene(path, warn=lambda line: None)
    assert str(caught.value) == (f"stage {str(path)!r}: /Looks/Look/Map: inputs:scale is "
                                 f"(nan, 1, 1, 1): expected finite values")


def _read_through(stage, surface, name, kind, varname, values, interpolation, type_name):
    """``surface``'s input ``name`` connected to a primvar reader of ``kind`` reading
    primvar ``varname`` of ``values`` on /Quad."""
    primvar = UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/Quad")).CreatePrimvar(
        varname, type_name, interpolation)
    primvar.Set(values)
    reader = UsdShade.Shader.Define(stage, f"/Looks/Look/{name}_reader")
    reader.CreateIdAttr(kind)
    reader.CreateInput("varname", Sdf.ValueTypeNames.Token).Set(varname)
    value_type = Sdf.ValueTypeNames.Color3f if kind.endswith("float3") else \
        Sdf.ValueTypeNames.Float
    surface.CreateInput(name, value_type).ConnectToSource(reader.ConnectableAPI(), "result")


@pytest.mark.parametrize("varying", [False, True])
def test_an_emission_from_a_primvar_reader_reads_the_primvar(tmp_path, varying):
    """A constant primvar is the emitter's radiance; one that varies gives its mean, said
    (Mitsuba's area emitter cannot sample a mesh attribute)."""
    path = tmp_path / "glow.usda"
    stage = _stage(path)
    glow = [(1, 0, 0), (1, 0, 0), (0, 0, 1), (0, 0, 1)] if varying else [(0.5, 2, 0)]
    _read_through(stage, _surface(stage), "emissiveColor", "UsdPrimvarReader_float3", "glow",
                  glow, UsdGeom.Tokens.vertex if varying else UsdGeom.Tokens.constant,
                  Sdf.ValueTypeNames.Color3fArray)
    stage.GetRootLayer().Save()
    said = []
    animation = UsdScene(path, warn=said.append, default_light=False)
    expected = (0.5, 0.0, 0.5) if varying else (0.5, 2.0, 0.0)
    assert [line for line in said if "varies" in line] == ([
        f"stage {str(path)!r}: /Quad: glow of interpolation 'vertex' varies over the mesh "
        f"(Mitsuba's area emitter samples one radiance or a texture, not a mesh "
        f"attribute); its mean (0.5, 0.0, 0.5) is used"] if varying else [])
    assert animation._meshes[0].emission == pytest.approx(expected)
    assert _render(animation)[4, 4] == pytest.approx(expected, rel=1e-5)


def test_roughness_metallic_and_opacity_from_primvar_readers_read_the_primvars(tmp_path):
    """Per point: Mitsuba mesh attributes the BSDF reads (clamped to [0, 1]); constant:
    the value. An opacity from 0 at the quad's left edge to 1 at its right shows the
    sky through its left side."""
    path = tmp_path / "readers.usda"
    stage = _stage(path)
    UsdLux.DomeLight.Define(stage, "/Sky")
    surface = _surface(stage)
    floats = Sdf.ValueTypeNames.FloatArray
    _read_through(stage, surface, "roughness", "UsdPrimvarReader_float", "rough",
                  [0.0, 0.5, 1.5, -1.0], UsdGeom.Tokens.vertex, floats)
    _read_through(stage, surface, "metallic", "UsdPrimvarReader_float", "metal", [0.75],
                  UsdGeom.Tokens.constant, floats)
    _read_through(stage, surface, "opacity", "UsdPrimvarReader_float", "alpha",
                  [0.0, 1.0, 1.0, 0.0], UsdGeom.Tokens.vertex, floats)
    stage.GetRootLayer().Save()
    said = []
    animation = UsdScene(path, warn=said.append)
    assert not any("not read" in line or "reads" in line for line in said), said
    (mesh,) = animation._meshes
    assert mesh.bsdf["opacity"] == {"type": "mesh_attribute", "name": "vertex_opacity"}
    principled = mesh.bsdf["bsdf"]
    assert principled["roughness"] == {"type": "mesh_attribute", "name": "vertex_roughness"}
    assert principled["metallic"] == pytest.approx(0.75)
    np.testing.assert_array_equal(mesh.attributes["vertex_roughness"][:, 0], [0, 0.5, 1, 0])
    image = _render(animation, size=16, spp=64)
    left, right = image[:, :3].mean(), image[:, 13:].mean()
    assert left > 0.8 and right < 0.4, (left, right)


def test_a_cutout_s_opacity_from_a_varying_primvar_takes_its_mean(tmp_path):
    path = tmp_path / "cutout.usda"
    stage = _stage(path)
    UsdLux.DomeLight.Define(stage, "/Sky")
    surface = _surface(stage)
    surface.CreateInput("opacityThreshold", Sdf.ValueTypeNames.Float).Set(0.6)
    _read_through(stage, surface, "opacity", "UsdPrimvarReader_float", "alpha",
                  [0.0, 1.0, 1.0, 0.2], UsdGeom.Tokens.vertex, Sdf.ValueTypeNames.FloatArray)
    stage.GetRootLayer().Save()
    said = []
    animation = UsdScene(path, warn=said.append)
    assert said == [
        f"stage {str(path)!r}: /Quad: alpha of interpolation 'vertex' varies over the mesh "
        f"(a cutout (opacityThreshold) is not an interpolated opacity); its mean 0.55 is used"]
    bsdf = animation._meshes[0].bsdf
    assert bsdf["type"] == "mask" and bsdf["opacity"] == 0.0  # 0.55 < 0.6: cut out


def test_a_reader_of_the_wrong_kind_or_primvar_is_said_naming_what_is_dropped(tmp_path):
    path = tmp_path / "wrong.usda"
    stage = _stage(path)
    UsdLux.DomeLight.Define(stage, "/Sky")
    surface = _surface(stage)
    _read_through(stage, surface, "roughness", "UsdPrimvarReader_float3", "rough",
                  [(0.1, 0.1, 0.1)], UsdGeom.Tokens.constant, Sdf.ValueTypeNames.Color3fArray)
    _read_through(stage, surface, "metallic", "UsdPrimvarReader_float", "metal",
                  [(1, 1, 1)], UsdGeom.Tokens.constant, Sdf.ValueTypeNames.Color3fArray)
    stage.GetRootLayer().Save()
    said = []
    animation = UsdScene(path, warn=said.append)
    assert said == [
        f"stage {str(path)!r}: /Quad: has no primvar 'metal' of numbers that "
        f"/Looks/Look/metallic_reader reads; metallic is 0.0",
        f"stage {str(path)!r}: /Looks/Look: connected inputs roughness "
        f"(UsdPrimvarReader_float3) are not read; their authored values are used"]
    assert animation._meshes[0].bsdf["roughness"] == 0.5


# ---- Skinning -----------------------------------------------------------------------------


def _skinned(path, baked_points):
    """A stage in metres, time codes 0..2: a quad bound to a one-joint skeleton whose
    animation moves it +x by the time code; with ``baked_points`` the quad's points are
    time-sampled (the skinning baked into them by the export, binding kept)."""
    stage = _stage(path, 0, 2, quad="/Char/Body")
    UsdSkel.Root.Define(stage, "/Char")
    skeleton = UsdSkel.Skeleton.Define(stage, "/Char/Skel")
    skeleton.CreateJointsAttr(["root"])
    skeleton.CreateBindTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1)]))
    skeleton.CreateRestTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1)]))
    animation = UsdSkel.Animation.Define(stage, "/Char/Skel/Walk")
    animation.CreateJointsAttr(["root"])
    for t in range(3):
        animation.CreateTranslationsAttr().Set(Vt.Vec3fArray([Gf.Vec3f(t, 0, 0)]), t)
    animation.CreateRotationsAttr().Set(Vt.QuatfArray([Gf.Quatf(1)]))
    animation.CreateScalesAttr().Set(Vt.Vec3hArray([Gf.Vec3h(1, 1, 1)]))
    UsdSkel.BindingAPI.Apply(skeleton.GetPrim()).CreateAnimationSourceRel().SetTargets(
        [animation.GetPath()])
    body = UsdGeom.Mesh(stage.GetPrimAtPath("/Char/Body"))
    if baked_points:
        corners = [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)]
        for t in range(3):
            body.GetPointsAttr().Set([(x + t, y, z) for x, y, z in corners], t)
    binding = UsdSkel.BindingAPI.Apply(body.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skeleton.GetPath()])
    binding.CreateJointIndicesPrimvar(True, 1).Set([0])
    binding.CreateJointWeightsPrimvar(True, 1).Set([1.0])
    binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1))
    stage.GetRootLayer().Save()
    return path


@pytest.mark.parametrize("baked_points", [False, True])
def test_skinning_is_pxr_s_and_baked_points_are_not_warned(tmp_path, baked_points):
    path = _skinned(tmp_path / "char.usda", baked_points)
    before = path.read_bytes()
    said = []
    animation = UsdScene(path, warn=said.append)
    assert not any("skinning is not" in line or "rest" in line for line in said), said
    assert path.read_bytes() == before  # the file is never written
    (body,) = [i for i, p in animation.prim_paths().items() if p == "/Char/Body"]
    for t in range(3):
        corners = animation.world_triangles(t)[body].reshape(-1, 3)
        assert corners[:, 0].min() == pytest.approx(-1 + t) and \
            corners[:, 0].max() == pytest.approx(1 + t), (t, corners)


# ---- Time codes ---------------------------------------------------------------------------


def test_time_codes_are_pxr_s_with_start_or_end_authored_alone(tmp_path):
    stage = _stage(tmp_path / "end.usda", end=100)
    stage.GetRootLayer().Save()
    animation = UsdScene(tmp_path / "end.usda", warn=lambda line: None)
    assert animation.frame_count == 101 and animation.time_code(100) == 100
    stage = _stage(tmp_path / "start.usda", start=5)
    stage.GetRootLayer().Save()
    animation = UsdScene(tmp_path / "start.usda", warn=lambda line: None)
    assert animation.frame_count == 1 and animation.time_code(0) == 5


def test_compare_says_when_both_images_are_black(tmp_path, capsys):
    path = tmp_path / "dark.usda"
    stage = _stage(path)
    stage.GetRootLayer().Save()
    status, out, _ = run_cli(capsys, "compare", path, "--no-default-light", "--frames", "0:1",
                             "--out", tmp_path / "out", "--resolution", "8", "--spp", "1",
                             "--quiet")
    assert status == 0 and "Images: both accelerators' images are black on every frame " \
        "(nothing lights the scene), so their agreement says nothing about hlbvh." in out, out
    status, out, _ = run_cli(capsys, "compare", path, "--frames", "0:1",
                             "--out", tmp_path / "lit", "--resolution", "8", "--spp", "1",
                             "--quiet")
    assert status == 0 and "black" not in out and "within Monte Carlo noise of native's" in out, out


# ---- .usdz packages -----------------------------------------------------------------------


def test_a_usdz_package_s_textures_are_read_through_pxr_s_resolver(tmp_path):
    """A binary layer whose map sits under ``0/`` in the package (as glTF converters
    lay them out), packaged, then referenced from a layer that adds a light."""
    from pxr import UsdUtils
    source = tmp_path / "src"
    (source / "0").mkdir(parents=True)
    pixels = np.zeros((4, 4, 3), dtype=np.float32)
    pixels[..., 0] = 1.0  # red
    mi.Bitmap(pixels).write(str(source / "0" / "map.exr"))
    stage = _stage(source / "cube.usdc")
    UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/Quad")).CreatePrimvar(
        "st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex).Set(
        [(0, 0), (1, 0), (1, 1), (0, 1)])
    stage.SetDefaultPrim(stage.GetPrimAtPath("/Quad"))
    surface = _surface(stage)
    image = UsdShade.Shader.Define(stage, "/Looks/Look/Map")
    image.CreateIdAttr("UsdUVTexture")
    image.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(Sdf.AssetPath("./0/map.exr"))
    surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(
        image.ConnectableAPI(), "rgb")
    stage.GetRootLayer().Save()
    package = tmp_path / "cube.usdz"
    assert UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(str(source / "cube.usdc")), str(package))
    shot = Usd.Stage.CreateNew(str(tmp_path / "shot.usda"))
    shot.GetRootLayer().subLayerPaths.append("./cube.usdz")
    UsdLux.DomeLight.Define(shot, "/Sky")
    shot.GetRootLayer().Save()
    for path in (package, tmp_path / "shot.usda"):
        said = []
        animation = UsdScene(path, warn=said.append)
        assert not any("'s texture" in line or "not read" in line for line in said), said
        bitmap = animation._meshes[0].bsdf["base_color"]
        assert bitmap["type"] == "bitmap" and bitmap["filename"].endswith("map.exr")
        centre = _render(animation)[4, 4]
        assert centre[0] > 5 * max(centre[1], centre[2])  # the red map, under specular
        digest = animation.source_digest()
        assert UsdScene(path, warn=said.append).source_digest() == digest  # resumes agree
