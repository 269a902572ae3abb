"""UsdPreviewSurface as a DCC exports it: opacity read from a texture (cutouts with
opacityThreshold, partial opacity), UsdTransform2d on the texture coordinates, normal
maps (a UsdUVTexture on inputs:normal with its scale and bias) and single-sided
meshes seen from behind. Each stage is written with pxr and judged against an
equivalent stage: the cutout against geometry cut the same way, the transform against
st authored already transformed, the normal map against the flat surface."""

import math

import numpy as np
import pytest

pxr = pytest.importorskip("pxr")

import mitsuba as mi  # noqa: E402
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdShade  # noqa: E402

from hlbvh.scenes.usd import UsdScene  # noqa: E402

#: The unit quad's st at its corners (-1, -1), (1, -1), (1, 1), (-1, 1).
ST = [(0.0, 0.0), (1.0, 0.0), (1.0, 1.0), (0.0, 1.0)]


def _stage(path):
    """A new Y-up stage in metres seen by a camera 4 m away on +Z (it sees the
    square of side 1.66 m about the origin)."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdGeom.Camera.Define(stage, "/Cam").AddTranslateOp().Set(Gf.Vec3d(0, 0, 4))
    return stage


def _quad(stage, path, x0=-1.0, x1=1.0, z=0.0, st=ST, size=1.0):
    """A quad facing +Z from (x0, -size) to (x1, size) at depth ``z``, with
    per-point st ``st``."""
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr([Gf.Vec3f(x0, -size, z), Gf.Vec3f(x1, -size, z),
                           Gf.Vec3f(x1, size, z), Gf.Vec3f(x0, size, z)])
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    UsdGeom.PrimvarsAPI(mesh).CreatePrimvar(
        "st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex).Set(
        [Gf.Vec2f(*c) for c in st])
    return mesh


def _material(stage, mesh, path, constants, textures=None, transform=None):
    """A UsdPreviewSurface bound to ``mesh``: ``constants`` (colours as tuples),
    ``textures`` ``{input: (file, output, {texture input: value})}`` each read over
    st through a primvar reader, and through one UsdTransform2d with ``transform``
    (``{"scale": ..., "rotation": ..., "translation": ...}``) when given."""
    material = UsdShade.Material.Define(stage, path)
    surface = UsdShade.Shader.Define(stage, f"{path}/Surface")
    surface.CreateIdAttr("UsdPreviewSurface")
    for name, value in constants.items():
        kind = Sdf.ValueTypeNames.Color3f if isinstance(value, tuple) else Sdf.ValueTypeNames.Float
        surface.CreateInput(name, kind).Set(value)
    reader = UsdShade.Shader.Define(stage, f"{path}/Reader")
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    reader.CreateInput("varname", Sdf.ValueTypeNames.Token).Set("st")
    st_source, st_output = reader, "result"
    if transform is not None:
        moved = UsdShade.Shader.Define(stage, f"{path}/Transform")
        moved.CreateIdAttr("UsdTransform2d")
        moved.CreateInput("in", Sdf.ValueTypeNames.Float2).ConnectToSource(
            reader.ConnectableAPI(), "result")
        moved.CreateInput("scale", Sdf.ValueTypeNames.Float2).Set(Gf.Vec2f(*transform["scale"]))
        moved.CreateInput("rotation", Sdf.ValueTypeNames.Float).Set(transform["rotation"])
        moved.CreateInput("translation", Sdf.ValueTypeNames.Float2).Set(
            Gf.Vec2f(*transform["translation"]))
        st_source = moved
    for k, (name, (filename, output, inputs)) in enumerate((textures or {}).items()):
        image = UsdShade.Shader.Define(stage, f"{path}/Image{k}")
        image.CreateIdAttr("UsdUVTexture")
        image.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(Sdf.AssetPath(str(filename)))
        image.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(
            st_source.ConnectableAPI(), st_output)
        for key, value in inputs.items():
            kind = Sdf.ValueTypeNames.Token if isinstance(value, str) else Sdf.ValueTypeNames.Float4
            image.CreateInput(key, kind).Set(value if isinstance(value, str)
                                             else Gf.Vec4f(*value))
        kind = Sdf.ValueTypeNames.Float if len(output) == 1 else (
            Sdf.ValueTypeNames.Normal3f if name == "normal" else Sdf.ValueTypeNames.Color3f)
        surface.CreateInput(name, kind).ConnectToSource(image.ConnectableAPI(), output)
    material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)
    return material


def _render(path, size=16, spp=4):
    """The stage at ``path`` rendered (``size`` square, ``spp``; no default light:
    only what the stage holds lights it), as an (H, W, 3) array; nothing said but
    that."""
    said = []
    scene = mi.load_dict(UsdScene(path, warn=said.append, default_light=False).scene_dict(
        resolution=(size, size), spp=spp))
    assert all("no UsdLux light" in line for line in said), said
    return np.array(mi.render(scene, seed=0))


def _backdrop(stage):
    """A green emitter behind everything (1 m back), black itself."""
    back = _quad(stage, "/Back", -3.0, 3.0, z=-1.0, size=3.0)
    _material(stage, back, "/Looks/Back", {"diffuseColor": (0.0, 0.0, 0.0),
                                           "emissiveColor": (0.0, 1.0, 0.0)})


def test01_an_opacity_texture_cut_by_its_threshold_renders_as_geometry_cut_there(tmp_path):
    alpha = np.ones((8, 8, 4), dtype=np.float32)
    alpha[:, :4, 3] = 0.9  # the image's left half kept, its right half cut away
    alpha[:, 4:, 3] = 0.1
    mi.Bitmap(alpha).write(str(tmp_path / "leaf.exr"))
    stage = _stage(tmp_path / "cutout.usda")
    _backdrop(stage)
    _material(stage, _quad(stage, "/Leaf"), "/Looks/Leaf",
              {"diffuseColor": (0.0, 0.0, 0.0), "opacityThreshold": 0.5},
              {"opacity": (tmp_path / "leaf.exr", "a", {})})
    stage.GetRootLayer().Save()
    stage = _stage(tmp_path / "cut.usda")
    _backdrop(stage)
    _material(stage, _quad(stage, "/Leaf", -1.0, 0.0), "/Looks/Leaf",
              {"diffuseColor": (0.0, 0.0, 0.0)})
    stage.GetRootLayer().Save()
    cutout, cut = _render(tmp_path / "cutout.usda"), _render(tmp_path / "cut.usda")
    assert cut[:, :8, 1].max() == 0 and cut[:, 8:, 1].min() > 0.99  # the judge itself
    # The backdrop's specular sees the leaf's back (both sides render): a few
    # thousandths of interreflection, noise that differs where rays pass the cutout.
    np.testing.assert_allclose(cutout, cut, atol=5e-3)


def test02_partial_opacity_from_an_8_bit_alpha_lets_that_share_through(tmp_path):
    rgba = np.full((4, 4, 4), 255, dtype=np.uint8)
    rgba[..., 3] = 64  # alpha 0.251: three quarters of the backdrop shows through
    mi.Bitmap(rgba).write(str(tmp_path / "glass.png"))
    stage = _stage(tmp_path / "glass.usda")
    _backdrop(stage)
    _material(stage, _quad(stage, "/Pane"), "/Looks/Glass",
              {"diffuseColor": (0.0, 0.0, 0.0)},
              {"opacity": (tmp_path / "glass.png", "a", {})})
    stage.GetRootLayer().Save()
    image = _render(tmp_path / "glass.usda", spp=16)
    assert abs(image[..., 1].mean() - (1 - 64 / 255)) < 0.03, image[..., 1].mean()


def _st_moved(st, scale, rotation, translation):
    """UsdTransform2d's result (its specification: ``in * scale * rotate +
    translation``, rotation counter-clockwise in degrees) of each of ``st``."""
    c, s = math.cos(math.radians(rotation)), math.sin(math.radians(rotation))
    moved = []
    for u, v in st:
        u, v = u * scale[0], v * scale[1]
        moved.append((c * u - s * v + translation[0], s * u + c * v + translation[1]))
    return moved


def test03_a_usdtransform2d_maps_as_st_authored_already_transformed(tmp_path):
    rng = np.random.default_rng(3)
    mi.Bitmap(rng.random((4, 4, 3)).astype(np.float32)).write(str(tmp_path / "tiles.exr"))
    transform = {"scale": (1.5, 0.75), "rotation": 30.0, "translation": (0.2, -0.1)}
    glow = {"emissiveColor": (tmp_path / "tiles.exr", "rgb", {})}
    black = {"diffuseColor": (0.0, 0.0, 0.0)}
    stage = _stage(tmp_path / "moved.usda")
    _material(stage, _quad(stage, "/Tiles"), "/Looks/Tiles", black, glow, transform)
    stage.GetRootLayer().Save()
    stage = _stage(tmp_path / "authored.usda")
    _material(stage, _quad(stage, "/Tiles", st=_st_moved(ST, **transform)), "/Looks/Tiles",
              black, glow)
    stage.GetRootLayer().Save()
    moved, authored = _render(tmp_path / "moved.usda"), _render(tmp_path / "authored.usda")
    assert authored.std() > 0.1  # the texture shows
    np.testing.assert_allclose(moved, authored, atol=1e-4)


def _lit_quad(path, light_turn, normal_png=None):
    """A grey matte quad facing +Z under a distant light turned by ``light_turn``
    (``(axis, degrees)``), its normal read from ``normal_png`` as a DCC exports a
    normal map (8-bit, raw, scale 2 and bias -1)."""
    stage = _stage(path)
    textures = None if normal_png is None else {"normal": (normal_png, "rgb", {
        "scale": (2.0, 2.0, 2.0, 1.0), "bias": (-1.0, -1.0, -1.0, 0.0),
        "sourceColorSpace": "raw"})}
    _material(stage, _quad(stage, "/Wall"), "/Looks/Wall",
              {"diffuseColor": (0.8, 0.8, 0.8), "roughness": 1.0}, textures)
    sun = UsdLux.DistantLight.Define(stage, "/Sun")
    axis, degrees = light_turn
    (sun.AddRotateYOp() if axis == "y" else sun.AddRotateXOp()).Set(degrees)
    stage.GetRootLayer().Save()
    return path


@pytest.mark.parametrize("tilt, toward, away", [
    ((0.5, 0.0, math.sqrt(0.75)), ("y", 45.0), ("y", -45.0)),    # toward +s: from +X
    ((0.0, 0.5, math.sqrt(0.75)), ("x", -45.0), ("x", 45.0)),    # toward +t: from +Y
])
def test04_a_normal_map_tilts_the_surface_toward_s_and_t_as_usd_defines(
        tmp_path, tilt, toward, away):
    pixels = np.round((np.array(tilt) + 1) / 2 * 255).astype(np.uint8)
    mi.Bitmap(np.tile(pixels, (2, 2, 1))).write(str(tmp_path / "bumps.png"))
    mean = {}
    for name, light in (("toward", toward), ("away", away)):
        for mapped in (False, True):
            path = _lit_quad(tmp_path / f"{name}{mapped}.usda", light,
                             tmp_path / "bumps.png" if mapped else None)
            mean[name, mapped] = _render(path).mean()
    # The light 45 degrees off the quad's normal, the map's normal 30 degrees off it:
    # cos 15 / cos 45 = 1.37 toward the light, cos 75 / cos 45 = 0.37 away from it.
    assert mean["toward", True] > 1.2 * mean["toward", False] > 0, mean
    assert mean["away", True] < 0.6 * mean["away", False], mean


def test05_a_bad_texture_transform_is_one_line_naming_the_shader(tmp_path):
    mi.Bitmap(np.ones((2, 2, 3), dtype=np.float32)).write(str(tmp_path / "tiles.exr"))
    stage = _stage(tmp_path / "bad.usda")
    _material(stage, _quad(stage, "/Tiles"), "/Looks/Tiles", {},
              {"diffuseColor": (tmp_path / "tiles.exr", "rgb", {})},
              {"scale": (1.0, 1.0), "rotation": float("nan"), "translation": (0.0, 0.0)})
    stage.GetRootLayer().Save()
    with pytest.raises(ValueError, match=r"/Looks/Tiles/Transform: inputs:rotation is nan"):
        UsdScene(tmp_path / "bad.usda", warn=lambda line: None)


def _turned(path, degrees):
    """A quad with a red UsdPreviewSurface, single-sided (doubleSided's fallback),
    turned ``degrees`` about Y (180: its back toward the camera), under a white dome."""
    stage = _stage(path)
    quad = _quad(stage, "/Card")
    quad.AddRotateYOp().Set(degrees)
    _material(stage, quad, "/Looks/Card", {"diffuseColor": (0.8, 0.1, 0.1)})
    UsdLux.DomeLight.Define(stage, "/Sky")
    stage.GetRootLayer().Save()
    return path


def test06_a_single_sided_quad_seen_from_behind_shows_its_material_as_storm_draws_it(
        tmp_path):
    """Storm (usdview's defaults) neither culls a single-sided back face nor draws it
    black: its back, under a uniform dome, is its front's colour within noise (it
    rendered black)."""
    front = _render(_turned(tmp_path / "front.usda", 0.0), spp=64).mean(axis=(0, 1))
    back = _render(_turned(tmp_path / "back.usda", 180.0), spp=64).mean(axis=(0, 1))
    assert front[0] > 0.5 and front[1] < 0.2  # the red card fills the view
    np.testing.assert_allclose(back, front, rtol=0.02)


def _materialx_surface(stage, material, colour):
    """A MaterialX standard surface of base colour ``colour`` on ``material``'s
    ``outputs:mtlx:surface``, as MaterialX-aware DCCs export it."""
    shader = UsdShade.Shader.Define(stage, f"{material.GetPath()}/Standard")
    shader.CreateIdAttr("ND_standard_surface_surfaceshader")
    shader.CreateInput("base_color", Sdf.ValueTypeNames.Color3f).Set(colour)
    material.CreateSurfaceOutput("mtlx").ConnectToSource(
        shader.CreateOutput("out", Sdf.ValueTypeNames.Token))


def test07_materialx_falls_back_to_the_preview_surface_else_is_said(tmp_path):
    """A material with both surfaces renders its UsdPreviewSurface, unsaid; one with
    only MaterialX's is one line naming it; a reference to a .mtlx file, which usd-core
    cannot read, is one line naming the file and the material bound in it (not "does
    not resolve": the file is there)."""
    (tmp_path / "look.mtlx").write_text('<?xml version="1.0"?>\n<materialx version="1.38">'
                                        '<surfacematerial name="M_Wood"/></materialx>\n')
    path = tmp_path / "mtlx.usda"
    stage = _stage(path)
    UsdLux.DomeLight.Define(stage, "/Sky")
    both = _material(stage, _quad(stage, "/Both", -1.0, -0.4), "/Looks/Both",
                     {"diffuseColor": (0.9, 0.1, 0.1)})
    _materialx_surface(stage, both, (0.1, 0.9, 0.1))
    only = UsdShade.Material.Define(stage, "/Looks/Only")
    _materialx_surface(stage, only, (0.1, 0.1, 0.9))
    UsdShade.MaterialBindingAPI.Apply(_quad(stage, "/Only", -0.3, 0.3).GetPrim()).Bind(only)
    stage.DefinePrim("/Wood", "Scope").GetReferences().AddReference(
        "./look.mtlx", "/MaterialX/Materials")
    wood = UsdShade.MaterialBindingAPI.Apply(_quad(stage, "/Table", 0.4, 1.0).GetPrim())
    wood.GetPrim().CreateRelationship("material:binding").SetTargets(["/Wood/M_Wood"])
    stage.GetRootLayer().Save()
    said = []
    animation = UsdScene(path, warn=said.append)
    meshes = {mesh.id: mesh for mesh in animation._meshes}
    assert meshes["Both"].bsdf["base_color"]["value"] == pytest.approx([0.9, 0.1, 0.1])
    assert meshes["Only"].bsdf["reflectance"]["value"] == [0.5, 0.5, 0.5]
    where = f"stage {str(path)!r}"
    assert said == [
        f"{where}: /Looks/Only: its surface is MaterialX only (outputs:mtlx:surface, "
        f"ND_standard_surface_surfaceshader), whose definitions (.mtlx) usd-core does not "
        f"read, and it has no UsdPreviewSurface (outputs:surface) to fall back on; its "
        f"meshes render their displayColor, else grey",
        f"{where}: /Wood: MaterialX file 'look.mtlx' is not read: usd-core reads no .mtlx "
        f"(no MaterialX file format in pxr's wheels), so the materials bound there "
        f"(/Wood/M_Wood) do not exist on the stage and have no UsdPreviewSurface to fall "
        f"back on; their meshes render their displayColor, else grey"], said
