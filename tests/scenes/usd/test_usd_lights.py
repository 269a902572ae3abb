"""UsdLux lights render in UsdLux's units (:mod:`hlbvh.scenes.usd.lights`): for each
light type a white-ish diffuse floor seen through a narrow camera looking straight
down, lit from above, gives the pixel value ``albedo / pi * E`` of the irradiance ``E``
computed here by hand from the light's definition (radiance ``intensity *
2^exposure * color``, divided by its area with ``normalize``)."""

import math

import numpy as np
import pytest

pytest.importorskip("pxr")

import mitsuba as mi  # noqa: E402
from pxr import Gf, Usd, UsdGeom, UsdLux  # noqa: E402

from hlbvh.scenes.usd import UsdScene  # noqa: E402
from hlbvh.scenes.usd.lights import distant_size_factor  # noqa: E402

ALBEDO = 0.5
HEIGHT = 2.0  # of the light over the floor


def _floor_stage(path, light):
    """A stage in metres: a 20 m floor at y=0 of displayColor ALBEDO, a camera 1 m over
    it looking down with a 500 mm lens (it sees a 4 cm patch), and ``light(stage)``."""
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    floor = UsdGeom.Mesh.Define(stage, "/Floor")
    floor.CreatePointsAttr([(-10, 0, -10), (-10, 0, 10), (10, 0, 10), (10, 0, -10)])
    floor.CreateFaceVertexCountsAttr([4])
    floor.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    floor.CreateSubdivisionSchemeAttr("none")
    floor.CreateDisplayColorPrimvar().Set([(ALBEDO, ALBEDO, ALBEDO)])
    camera = UsdGeom.Camera.Define(stage, "/Cam")
    camera.AddTranslateOp().Set(Gf.Vec3d(0, 1, 0))
    camera.AddRotateXOp().Set(-90.0)
    camera.CreateFocalLengthAttr(500.0)
    camera.CreateClippingRangeAttr(Gf.Vec2f(0.01, 100))
    light(stage)
    stage.GetRootLayer().Save()
    return path


def _above(light):
    """``light`` 2 m over the floor, its -Z (where UsdLux lights emit) turned down."""
    light.AddTranslateOp().Set(Gf.Vec3d(0, HEIGHT, 0))
    light.AddRotateXOp().Set(-90.0)
    return light


def _rect_irradiance(radiance, width, height, distance):
    """Irradiance under the centre of a Lambertian rectangle of ``radiance`` facing the
    point from ``distance``: four corner-aligned quarters, each of form factor
    ``(a/A atan(b/A) + b/B atan(a/B)) / (2 pi)`` with ``A = sqrt(a^2 + d^2)``,
    ``B = sqrt(b^2 + d^2)``."""
    a, b, d = width / 2, height / 2, distance
    big_a, big_b = math.hypot(a, d), math.hypot(b, d)
    quarter = (a / big_a * math.atan(b / big_a) + b / big_b * math.atan(a / big_b)) / (2 * math.pi)
    return math.pi * radiance * 4 * quarter


def _distant(normalize):
    def light(stage):
        sun = _above(UsdLux.DistantLight.Define(stage, "/Sun"))
        sun.CreateIntensityAttr(100.0)
        sun.CreateAngleAttr(10.0)
        sun.CreateNormalizeAttr(normalize)
    return light


def _sphere(point, normalize):
    def light(stage):
        bulb = _above(UsdLux.SphereLight.Define(stage, "/Bulb"))
        bulb.CreateRadiusAttr(0.2)
        bulb.CreateIntensityAttr(50.0)
        bulb.CreateTreatAsPointAttr(point)
        bulb.CreateNormalizeAttr(normalize)
    return light


def _rect(normalize):
    def light(stage):
        panel = _above(UsdLux.RectLight.Define(stage, "/Panel"))
        panel.CreateWidthAttr(1.0)
        panel.CreateHeightAttr(0.5)
        panel.CreateIntensityAttr(10.0)
        panel.CreateExposureAttr(1.0)
        panel.CreateNormalizeAttr(normalize)
    return light


def _disk(stage):
    disk = _above(UsdLux.DiskLight.Define(stage, "/Disk"))
    disk.CreateRadiusAttr(0.5)
    disk.CreateIntensityAttr(10.0)
    disk.CreateColorAttr(Gf.Vec3f(1.0, 0.5, 0.25))


def _dome(stage):
    UsdLux.DomeLight.Define(stage, "/Sky").CreateIntensityAttr(0.8)


SIN2_5 = math.sin(math.radians(5)) ** 2
# (the light, the irradiance E on the floor under it, worked out by hand)
CASES = {
    # a disc of radiance 100 and angular radius 5 degrees: E = L pi sin^2(5)
    "distant": (_distant(False), 100 * math.pi * SIN2_5),
    # normalize: intensity is the irradiance
    "distant_normalized": (_distant(True), 100.0),
    # a sphere of radius r at distance d: E = L pi (r/d)^2
    "sphere": (_sphere(False, False), 50 * math.pi * (0.2 / HEIGHT) ** 2),
    # normalize: L / (4 pi r^2)
    "sphere_normalized": (_sphere(False, True),
                          50 / (4 * math.pi * 0.04) * math.pi * (0.2 / HEIGHT) ** 2),
    # treatAsPoint: intensity L pi r^2, E = I / d^2 (the sphere's own irradiance)
    "point": (_sphere(True, False), 50 * math.pi * 0.04 / HEIGHT ** 2),
    "point_normalized": (_sphere(True, True), 50 / 4 / HEIGHT ** 2),
    # exposure 1 doubles the radiance
    "rect": (_rect(False), _rect_irradiance(20.0, 1.0, 0.5, HEIGHT)),
    "rect_normalized": (_rect(True), _rect_irradiance(20.0 / 0.5, 1.0, 0.5, HEIGHT)),
    # a disc of radius R on the axis: E = L pi R^2 / (R^2 + d^2) (red channel)
    "disk": (_disk, 10 * math.pi * 0.25 / (0.25 + HEIGHT ** 2)),
    # a uniform sky over a floor: E = pi L
    "dome": (_dome, math.pi * 0.8),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_each_light_type_gives_the_irradiance_usdlux_defines(tmp_path, case):
    light, irradiance = CASES[case]
    animation = UsdScene(_floor_stage(tmp_path / f"{case}.usda", light),
                         warn=lambda line: None)
    spp = 4 if case.startswith(("distant", "point")) else 64
    image = np.array(mi.render(mi.load_dict(animation.scene_dict(resolution=(8, 8), spp=spp)),
                               seed=1))
    expected = ALBEDO / math.pi * irradiance
    assert float(image[..., 0].mean()) == pytest.approx(expected, rel=0.02), case


def test_the_distant_size_factor_follows_usdlux():
    assert distant_size_factor(0.0) == 1.0
    assert distant_size_factor(10.0) == pytest.approx(math.pi * SIN2_5)
    assert distant_size_factor(180.0) == pytest.approx(math.pi)
    # past a hemisphere: pi (2 - sin^2), up to 2 pi for the whole sphere
    assert distant_size_factor(270.0) == pytest.approx(math.pi * 1.5)
    assert distant_size_factor(360.0) == pytest.approx(2 * math.pi)
