"""``.usdz`` packages laid out as Blender's USD exporter and Apple's usdzconvert /
Reality Composer write them, authored here with pxr and packaged with pxr's own
``UsdUtils``: each renders its texture (a map red on its left half, green on its
right, on a quad that fills the camera's view)."""

import numpy as np
import pytest

pytest.importorskip("pxr")

import mitsuba as mi  # noqa: E402
from pxr import Gf, Kind, Sdf, Usd, UsdGeom, UsdLux, UsdShade, UsdUtils, Vt  # noqa: E402

from hlbvh.scenes.usd import UsdScene  # noqa: E402

CORNERS = [(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)]
UV = [(0, 0), (1, 0), (1, 1), (0, 1)]


def _red_green(path):
    """An 8-bit sRGB PNG, 8x8: red on its left half (s < 0.5), green on its right."""
    pixels = np.zeros((8, 8, 3), dtype=np.uint8)
    pixels[:, :4, 0] = 255
    pixels[:, 4:, 1] = 255
    path.parent.mkdir(parents=True, exist_ok=True)
    mi.Bitmap(pixels).write(str(path))


def _quad(stage, path, uv_name, interpolation):
    """A 2x2 quad in the stage's xy plane, its uv in primvar ``uv_name`` (faceVarying
    ones indexed, as Blender writes them)."""
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreatePointsAttr(CORNERS)
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    mesh.CreateSubdivisionSchemeAttr("none")
    uv = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar(uv_name, Sdf.ValueTypeNames.TexCoord2fArray,
                                                 interpolation)
    uv.Set(UV)
    if interpolation == UsdGeom.Tokens.faceVarying:
        uv.SetIndices(Vt.IntArray([0, 1, 2, 3]))
    return mesh


def _camera(stage, path):
    """A camera 4 units along the stage's z, looking down -z at the quad."""
    UsdGeom.Camera.Define(stage, path).AddTranslateOp().Set(Gf.Vec3d(0, 0, 4))


def _texture(material, name, file, reader):
    """A ``UsdUVTexture`` under ``material`` reading ``file`` over ``reader``'s result."""
    texture = UsdShade.Shader.Define(material.GetPrim().GetStage(),
                                     material.GetPath().AppendChild(name))
    texture.CreateIdAttr("UsdUVTexture")
    texture.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(Sdf.AssetPath(file))
    texture.CreateInput("st", Sdf.ValueTypeNames.Float2).ConnectToSource(
        reader.ConnectableAPI(), "result")
    texture.CreateOutput("rgb", Sdf.ValueTypeNames.Float3)
    return texture


def _blender(folder, varname):
    """What Blender's USD exporter writes, as a .usdz: Z-up in metres, everything under
    ``/root``, materials under ``/root/_materials``, the map at ``./textures/...``
    beside the layer, the uv in an indexed faceVarying ``UVMap`` read by a
    ``UsdPrimvarReader_float2`` whose ``varname`` is a token, a string, or (as pxr's
    tutorial and usdzconvert write it) connected from the material's
    ``inputs:frame:stPrimvarName``."""
    _red_green(folder / "textures" / "red_green.png")
    stage = Usd.Stage.CreateNew(str(folder / "scene.usdc"))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    stage.SetDefaultPrim(UsdGeom.Xform.Define(stage, "/root").GetPrim())
    UsdGeom.Xform.Define(stage, "/root/Plane")
    mesh = _quad(stage, "/root/Plane/Plane", "UVMap", UsdGeom.Tokens.faceVarying)
    _camera(stage, "/root/Camera")
    UsdLux.DomeLight.Define(stage, "/root/env_light")
    material = UsdShade.Material.Define(stage, "/root/_materials/Material")
    surface = UsdShade.Shader.Define(stage, "/root/_materials/Material/Principled_BSDF")
    surface.CreateIdAttr("UsdPreviewSurface")
    surface.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(0.5)
    material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
    reader = UsdShade.Shader.Define(stage, "/root/_materials/Material/uvmap")
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    reader.CreateOutput("result", Sdf.ValueTypeNames.Float2)
    if varname == "interface":
        frame = material.CreateInput("frame:stPrimvarName", Sdf.ValueTypeNames.Token)
        frame.Set("UVMap")
        reader.CreateInput("varname", Sdf.ValueTypeNames.Token).ConnectToSource(frame)
    else:
        reader.CreateInput("varname", Sdf.ValueTypeNames.Token if varname == "token"
                           else Sdf.ValueTypeNames.String).Set("UVMap")
    texture = _texture(material, "Image_Texture", "./textures/red_green.png", reader)
    texture.CreateInput("sourceColorSpace", Sdf.ValueTypeNames.Token).Set("sRGB")
    texture.CreateInput("wrapS", Sdf.ValueTypeNames.Token).Set("repeat")
    texture.CreateInput("wrapT", Sdf.ValueTypeNames.Token).Set("repeat")
    surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(
        texture.ConnectableAPI(), "rgb")
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)
    stage.GetRootLayer().Save()
    package = folder.parent / "blender.usdz"
    assert UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(str(folder / "scene.usdc")),
                                         str(package))
    return package


def _usdzconvert(folder, file):
    """What usdzconvert and Reality Composer write, as an ARKit .usdz: a default prim of
    kind ``component`` with no camera or light, the map at the package's root or under
    ``0/`` (``file``, no ``./``), a ``UsdUVTexture`` with ``scale``, ``bias``,
    ``fallback``, ``wrapS``/``wrapT``, its reader's ``varname`` the token ``st``."""
    _red_green(folder / file)
    stage = Usd.Stage.CreateNew(str(folder / "toy.usdc"))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    asset = UsdGeom.Xform.Define(stage, "/toy")
    Usd.ModelAPI(asset).SetKind(Kind.Tokens.component)
    stage.SetDefaultPrim(asset.GetPrim())
    mesh = _quad(stage, "/toy/Geom/quad", "st", UsdGeom.Tokens.vertex)
    material = UsdShade.Material.Define(stage, "/toy/Materials/Mat")
    surface = UsdShade.Shader.Define(stage, "/toy/Materials/Mat/surfaceShader")
    surface.CreateIdAttr("UsdPreviewSurface")
    material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
    reader = UsdShade.Shader.Define(stage, "/toy/Materials/Mat/uvReader_st")
    reader.CreateIdAttr("UsdPrimvarReader_float2")
    reader.CreateInput("varname", Sdf.ValueTypeNames.Token).Set("st")
    reader.CreateOutput("result", Sdf.ValueTypeNames.Float2)
    texture = _texture(material, "diffuseColor_texture", file, reader)
    texture.CreateInput("scale", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(1, 1, 1, 1))
    texture.CreateInput("bias", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(0, 0, 0, 0))
    texture.CreateInput("fallback", Sdf.ValueTypeNames.Float4).Set(Gf.Vec4f(0.2, 0.2, 0.2, 1))
    texture.CreateInput("wrapS", Sdf.ValueTypeNames.Token).Set("repeat")
    texture.CreateInput("wrapT", Sdf.ValueTypeNames.Token).Set("repeat")
    surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(
        texture.ConnectableAPI(), "rgb")
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)
    stage.GetRootLayer().Save()
    package = folder.parent / "toy.usdz"
    assert UsdUtils.CreateNewARKitUsdzPackage(Sdf.AssetPath(str(folder / "toy.usdc")),
                                              str(package))
    return package


def _referencing(path, package):
    """A Y-up layer in metres that references ``package`` (its default prim) under
    ``/World/Toy`` and adds a camera and a dome light."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdGeom.Xform.Define(stage, "/World")
    toy = stage.DefinePrim("/World/Toy")
    toy.GetReferences().AddReference(f"./{package.name}")
    _camera(stage, "/World/Cam")
    UsdLux.DomeLight.Define(stage, "/World/Sky")
    stage.GetRootLayer().Save()
    return path


def _renders_red_green(path):
    """``path`` loads with nothing said about textures and its image (16x16, lit by a
    dome) is red on its left quarter and green on its right quarter: the map read over
    the uv. Returns the loaded scene."""
    said = []
    animation = UsdScene(path, warn=said.append)
    assert not any("texture" in line or "not read" in line or "not mapped" in line
                   for line in said), said
    scene = mi.load_dict(animation.scene_dict(resolution=(16, 16), spp=4))
    image = np.array(mi.render(scene, seed=0))
    left, right = image[:, :4].mean(axis=(0, 1)), image[:, 12:].mean(axis=(0, 1))
    assert left[0] > 4 * left[1] and right[1] > 4 * right[0], (left, right)
    return animation


@pytest.mark.parametrize("varname", ["token", "string", "interface"])
def test_a_blender_usdz_renders_its_texture(tmp_path, varname):
    _renders_red_green(_blender(tmp_path / "export", varname))


@pytest.mark.parametrize("file", ["texture.png", "0/texture.png"])
def test_a_referenced_usdzconvert_package_renders_its_texture(tmp_path, file):
    package = _usdzconvert(tmp_path / "export", file)
    _renders_red_green(_referencing(tmp_path / "shot.usda", package))


def test_a_texture_changed_inside_a_package_changes_the_source_digest(tmp_path):
    package = _blender(tmp_path / "export", "token")
    shot = _referencing(tmp_path / "shot.usda", package)
    digest = UsdScene(shot, warn=lambda line: None).source_digest()
    pixels = np.zeros((8, 8, 3), dtype=np.uint8)
    pixels[..., 2] = 255  # the map turns blue; the layers stay as they are
    mi.Bitmap(pixels).write(str(tmp_path / "export" / "textures" / "red_green.png"))
    package.unlink()
    assert UsdUtils.CreateNewUsdzPackage(
        Sdf.AssetPath(str(tmp_path / "export" / "scene.usdc")), str(package))
    assert UsdScene(shot, warn=lambda line: None).source_digest() != digest


def test_an_input_fed_by_the_material_s_interface_takes_its_value(tmp_path):
    """Material interfaces (as Houdini's and Omniverse's exports write them): the
    surface's diffuseColor connected to the material's own input takes that value,
    with nothing said."""
    stage = Usd.Stage.CreateNew(str(tmp_path / "interface.usda"))
    mesh = _quad(stage, "/Quad", "st", UsdGeom.Tokens.vertex)
    material = UsdShade.Material.Define(stage, "/Looks/Look")
    surface = UsdShade.Shader.Define(stage, "/Looks/Look/Surface")
    surface.CreateIdAttr("UsdPreviewSurface")
    material.CreateSurfaceOutput().ConnectToSource(surface.ConnectableAPI(), "surface")
    colour = material.CreateInput("baseColor", Sdf.ValueTypeNames.Color3f)
    colour.Set((0.1, 0.2, 0.7))
    surface.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(colour)
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)
    stage.GetRootLayer().Save()
    said = []
    animation = UsdScene(tmp_path / "interface.usda", warn=said.append)
    assert not any("not read" in line for line in said), said
    assert animation._meshes[0].bsdf["base_color"] == {
        "type": "rgb", "value": pytest.approx([0.1, 0.2, 0.7])}
