"""Values nobody checks in a USD stage (:mod:`hlbvh.scenes.usd`): a NaN, infinite,
zero or negative number where a light, a material, a camera, the render settings, the
stage's units or a mesh needs a finite (positive) one is one line naming the prim and
the attribute, never a traceback, NaN pixels or a blank image; a texture that is a
folder or not an image is said and its input takes its fallback."""

import math

import numpy as np
import pytest

pytest.importorskip("pxr")

import mitsuba as mi  # noqa: E402
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux, UsdRender, UsdShade  # noqa: E402

from cli_helpers import run_cli  # noqa: E402
from hlbvh.scenes.usd import UsdScene  # noqa: E402

def write_lit(path, change=None):
    """A Y-up stage in metres: a quad at z=0 with a UsdPreviewSurface, a camera at
    z=4 looking at it, a sphere light; ``change(stage)`` edits it before it is
    saved. Returns the path."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    mesh = UsdGeom.Mesh.Define(stage, "/Quad")
    mesh.CreatePointsAttr([(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)])
    mesh.CreateFaceVertexCountsAttr([4])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    mesh.CreateSubdivisionSchemeAttr("none")
    material = UsdShade.Material.Define(stage, "/Looks/Paint")
    shader = UsdShade.Shader.Define(stage, "/Looks/Paint/Surface")
    shader.CreateIdAttr("UsdPreviewSurface")
    shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set((0.5, 0.5, 0.5))
    material.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)
    camera = UsdGeom.Camera.Define(stage, "/Cam")
    camera.AddTranslateOp().Set(Gf.Vec3d(0, 0, 4))
    bulb = UsdLux.SphereLight.Define(stage, "/Bulb")
    bulb.CreateRadiusAttr(0.1)
    bulb.AddTranslateOp().Set(Gf.Vec3d(0, 0, 2))
    if change is not None:
        change(stage)
    stage.GetRootLayer().Save()
    return path


def _set(path, attribute, value):
    """A change setting ``attribute`` of the prim at ``path`` (created as a float or a
    colour when the schema did not author it)."""
    def change(stage):
        prim = stage.GetPrimAtPath(path)
        found = prim.GetAttribute(attribute)
        if not found:
            kind = (Sdf.ValueTypeNames.Color3f if isinstance(value, tuple)
                    else Sdf.ValueTypeNames.Float)
            found = prim.CreateAttribute(attribute, kind)
        found.Set(value)
    return change


def _shader(name, value):
    return _set("/Looks/Paint/Surface", f"inputs:{name}", value)


def _zero_scale(stage):
    UsdGeom.Xformable(stage.GetPrimAtPath("/Cam")).AddScaleOp().Set(Gf.Vec3f(0, 0, 0))


def _settings(resolution):
    def change(stage):
        settings = UsdRender.Settings.Define(stage, "/Render/Settings")
        settings.CreateResolutionAttr(Gf.Vec2i(*resolution))
        stage.SetMetadata("renderSettingsPrimPath", "/Render/Settings")
    return change


def _negative_count(stage):
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Quad"))
    mesh.GetFaceVertexCountsAttr().Set([4, -1, 1])


def _units(value):
    def change(stage):
        stage.SetMetadata("metersPerUnit", value)
    return change


NAN, INF = float("nan"), float("inf")


@pytest.mark.parametrize("change, line", [
    (_set("/Bulb", "inputs:intensity", NAN), "/Bulb: inputs:intensity is nan: expected "
                                             "finite and >= 0 values"),
    (_set("/Bulb", "inputs:intensity", -2.0), "/Bulb: inputs:intensity is -2: expected "
                                              "finite and >= 0 values"),
    (_set("/Bulb", "inputs:exposure", 5000.0), "/Bulb: inputs:intensity 1 * "
                                               "2^inputs:exposure 5000 * inputs:color is "
                                               "past single precision"),
    (_set("/Bulb", "inputs:color", (NAN, 1.0, 1.0)), "/Bulb: inputs:color is (nan, 1, 1)"),
    (_set("/Bulb", "inputs:radius", NAN), "/Bulb: inputs:radius is nan"),
    (_shader("roughness", NAN), "/Looks/Paint/Surface: inputs:roughness is nan: expected "
                                "finite values"),
    (_shader("diffuseColor", (NAN, 0.5, 0.5)), "/Looks/Paint/Surface: inputs:diffuseColor "
                                               "is (nan, 0.5, 0.5)"),
    (_shader("emissiveColor", (INF, 1.0, 1.0)), "/Looks/Paint/Surface: inputs:emissiveColor "
                                                "is (inf, 1, 1)"),
    (_set("/Cam", "focalLength", NAN), "camera /Cam: focalLength is nan: expected finite "
                                       "and > 0 values"),
    (_set("/Cam", "focalLength", 0.0), "camera /Cam: focalLength is 0: expected finite "
                                       "and > 0 values"),
    (_set("/Cam", "focalLength", -35.0), "camera /Cam: focalLength is -35"),
    (_set("/Cam", "horizontalAperture", 0.0), "camera /Cam: horizontalAperture is 0"),
    (_set("/Cam", "verticalAperture", 0.0), "camera /Cam: verticalAperture is 0"),
    (_set("/Cam", "clippingRange", Gf.Vec2f(0, 0)), "camera /Cam: clippingRange is (0, 0): "
                                                    "expected near < far"),
    (_zero_scale, "camera /Cam: its transform (xformOps, its own or an ancestor's) is not "
                  "finite or scales it to nothing"),
    (_settings((0, 0)), "render settings /Render/Settings: resolution is (0, 0): expected "
                        "positive integers"),
    (_settings((-640, 480)), "render settings /Render/Settings: resolution is (-640, 480)"),
    (_units(0.0), "metersPerUnit is 0: expected finite and > 0 values"),
    (_units(-0.01), "metersPerUnit is -0.01: expected finite and > 0 values"),
    (_negative_count, "mesh /Quad: faceVertexCounts holds -1 (face 1): a face has 0 or "
                      "more vertices"),
])
def test_a_bad_value_is_one_line_naming_the_prim_and_attribute(tmp_path, capsys, change,
                                                               line):
    path = write_lit(tmp_path / "bad.usda", change)
    # The render settings' resolution is the one used without --resolution.
    size = [] if "render settings" in line else ["--resolution", "8"]
    status, _, err = run_cli(capsys, "render", path, "--frames", "0:1", "--out",
                             tmp_path / "out", "--spp", "1", "--quiet", *size)
    assert status == 2 and len(err) == 1, err
    assert err[0].startswith(f"hlbvh render: stage {str(path)!r}: ") and line in err[0], err
    assert not (tmp_path / "out" / "frame_0000.exr").exists()


def test_the_largest_finite_exposure_renders_finite_pixels(tmp_path):
    """An exposure within single precision is no error: the image is finite."""
    path = write_lit(tmp_path / "bright.usda", _set("/Bulb", "inputs:exposure", 100.0))
    animation = UsdScene(path, warn=lambda line: None)
    image = np.array(mi.render(mi.load_dict(animation.scene_dict(resolution=(8, 8), spp=1))))
    assert np.isfinite(image).all() and image.max() > 1e20


def _textured(texture):
    """A change connecting the quad's diffuseColor and emissiveColor to UsdUVTextures
    of ``texture``."""
    def change(stage):
        surface = UsdShade.Shader(stage.GetPrimAtPath("/Looks/Paint/Surface"))
        surface.CreateInput("emissiveColor", Sdf.ValueTypeNames.Color3f).Set((1, 1, 1))
        for name in ("diffuseColor", "emissiveColor"):
            image = UsdShade.Shader.Define(stage, f"/Looks/Paint/{name}Map")
            image.CreateIdAttr("UsdUVTexture")
            image.CreateInput("file", Sdf.ValueTypeNames.Asset).Set(Sdf.AssetPath(str(texture)))
            surface.GetInput(name).ConnectToSource(image.ConnectableAPI(), "rgb")
        st = UsdGeom.PrimvarsAPI(stage.GetPrimAtPath("/Quad")).CreatePrimvar(
            "st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex)
        st.Set([(0, 0), (1, 0), (1, 1), (0, 1)])
    return change


@pytest.mark.parametrize("kind", ["folder", "not_an_image"])
def test_a_texture_that_is_no_image_is_said_and_takes_the_fallback(tmp_path, kind):
    texture = tmp_path / "paint.png"
    if kind == "folder":
        texture.mkdir()
    else:
        texture.write_text("not a png\n")
    path = write_lit(tmp_path / "textured.usda", _textured(texture))
    said = []
    animation = UsdScene(path, warn=said.append)
    for name, value in (("diffuseColor", "(0.5, 0.5, 0.5)"), ("emissiveColor", "(0.0, 0.0, 0.0)")):
        found = [line for line in said if f"inputs:{name}'s texture" in line]
        assert len(found) == 1, said
        assert f"{name} is {value}" in found[0], found
        reason = "is not a file" if kind == "folder" else "is not an image Mitsuba reads"
        assert reason in found[0], found
    scene_dict = animation.scene_dict(resolution=(8, 8), spp=1)
    quad = scene_dict["Quad"]
    assert quad.emitter() is None  # no white emitter in place of the texture
    image = np.array(mi.render(mi.load_dict(scene_dict)))
    assert np.isfinite(image).all() and image.max() > 0


def test_a_dome_texture_that_is_a_folder_is_said_and_the_dome_is_constant(tmp_path):
    folder = tmp_path / "sky.exr"
    folder.mkdir()

    def change(stage):
        dome = UsdLux.DomeLight.Define(stage, "/Sky")
        dome.CreateTextureFileAttr(Sdf.AssetPath(str(folder)))
    said = []
    animation = UsdScene(write_lit(tmp_path / "dome.usda", change), warn=said.append)
    assert animation.scene_dict(resolution=(8, 8), spp=1)["Sky"]["type"] == "constant"
    assert sum("/Sky: texture" in line and "is not a file" in line for line in said) == 1


def test_exposure_and_intensity_scale_the_radiance_as_usdlux_says(tmp_path):
    """``intensity * 2^exposure * color``: exposure 3 is intensity times 8."""
    path = write_lit(tmp_path / "exposed.usda", lambda stage: (
        UsdLux.RectLight.Define(stage, "/Panel").CreateIntensityAttr(1.5),
        stage.GetPrimAtPath("/Panel").CreateAttribute(
            "inputs:exposure", Sdf.ValueTypeNames.Float).Set(3.0),
        stage.GetPrimAtPath("/Panel").CreateAttribute(
            "inputs:color", Sdf.ValueTypeNames.Color3f).Set((1.0, 0.5, 0.25))))
    panel = UsdScene(path, warn=lambda line: None).scene_dict(resolution=(8, 8), spp=1)["Panel"]
    np.testing.assert_allclose(panel["emitter"]["radiance"]["value"],
                               [12.0, 6.0, 3.0], rtol=1e-6)
    assert math.isfinite(sum(panel["emitter"]["radiance"]["value"]))
